"""Orchard simulator: branching trees in rows, scanned from the alleys, with ground truth.

Not a kernel of the product: generated blocks are the test bench for every accuracy
figure, so they are built to be hard in the ways real mobile captures are hard:

- rows of trees along x with jittered positions, on sloping, gently undulating ground
  with patchy grass and a few points below the ground (:mod:`~simulator.terrain`);
- trees with a real branching structure (:mod:`~simulator.forms`): open-centre
  vase trees whose crowns overlap their neighbours', tall-spindle apples (a thin leader
  with short laterals along the row) or a hedgerow wall of olive/almond trees; optionally
  drooping branches whose leaves hang down to 0.2-0.5 m above the ground (``low_foliage``);
- a planting layout (:mod:`~simulator.planting`): empty slots, young replants,
  rows of different length, rows bowed sideways and the whole block rotated;
- sampled as a mobile scanner driving every alley sees it (:mod:`~simulator.scanner`):
  point density falls with range (1/r^2) and with the cosine of incidence, only surfaces
  facing the sensor are seen, and leaves occlude what lies behind them (Beer-Lambert
  attenuation through a coarse leaf-area grid);
- Gaussian noise, ghosting (each alley pass is offset by a small rigid shift, so
  surfaces seen from two passes are doubled), random outliers in the block volume,
  fence posts with a wire, a parked vehicle and a bin as distractors; optionally a
  trellis in every row (``trellis``: posts among the trees, wires along the row) and
  irrigation risers (``risers``) (:mod:`~simulator.clutter`); optionally a winter scan
  of leafless trees (``leafless``).

Modules, in the order a block is made: :mod:`~simulator.simparams` (the
parameters), :mod:`~simulator.plan` (everything drawn before the points),
:mod:`~simulator.simulate` (the points, chunk by chunk, bounded memory),
:mod:`~simulator.orchard` (a block with its per-point truth) and
:mod:`~simulator.truth` (LAS/LAZ and truth Parquet files). Everything is
deterministic for a seed.

All lengths are metres. The local frame has the first slot of the first row at the
origin; absolute coordinates add ``(easting, northing, elevation)``. The truth file's
contract is in ``docs/simulator.md``.
"""
