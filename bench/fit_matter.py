"""Fit the "combined" wood/leaf model on generated orchards (training seeds only).

    python -m bench.fit_matter [--seeds 4] [--models wide,narrow,spindle,noisy]

Generates orchards with seeds 1000, 1001, ... (never used for evaluation, which uses
seeds below 1000), runs the pipeline to the node level, and fits a logistic model of
node wood fraction on :data:`pipeline.woodleaf.FEATURES` (L2-regularised, points as
weights). Prints the weights and the threshold that maximises point-level wood F1 on
the training blocks, to paste into ``pipeline/woodleaf.py`` / ``pipeline/params.py``.
The narrow trees' model (``NARROW_WEIGHTS``) is fitted the same way on the narrow forms
(``NARROW_TRAINING``) over :func:`pipeline.woodleaf.narrow_features`, its bias shifted
so that its best threshold falls on the wide model's; the tall spindles' own model
(``SPINDLE_WEIGHTS``) likewise on ``SPINDLE_TRAINING``. The wide model's correction for
range noise (``NOISE_WEIGHTS``) is fitted on vase blocks over the noise x spacing grid
(``NOISY_TRAINING``) with the wide model's weights held, on the node features times
:func:`pipeline.woodleaf.noise_term` of each block's estimated ground noise and
:func:`pipeline.woodleaf.noise_gate` of each node's tree, with the columns of
:func:`pipeline.woodleaf.noise_features` beside them.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import minimize

from pipeline import woodleaf
from pipeline.params import PipelineParams
from pipeline.process import analyse_nodes
from bench.blocks import accuracy_params
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

TRAINING = [
    dict(rows=2, trees_per_row=4),
    dict(rows=2, trees_per_row=4, noise=0.05),
    dict(rows=2, trees_per_row=4, spacing=3.5, row_spacing=5.0),
    dict(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, low_foliage=True),
]
"""Blocks of wide (vase) trees: the wide trees' model."""

NARROW_TRAINING = [
    dict(form="spindle", rows=2, trees_per_row=14, spacing=1.0, row_spacing=3.5),
    dict(form="hedge", rows=2, trees_per_row=12, spacing=1.2, row_spacing=4.0),
]
"""Blocks of narrow trees (tall spindles, hedges): the narrow trees' model, each block
weighted alike (a spindle block holds a tenth of a vase block's wood)."""

SPINDLE_TRAINING = NARROW_TRAINING[:1]
"""Blocks of the narrowest trees (tall spindles): their own model (``SPINDLE_WEIGHTS``)."""

NOISY_TRAINING = [(noise, spacing) for noise in (0.0, 0.02, 0.05, 0.1) for spacing in (3.0, 4.0, 5.0, 6.0, 8.0)]
"""(noise sigma, spacing) [m] of the vase blocks (``bench.blocks.accuracy_params``, the
accuracy grid's layout) of the noise correction; seeds 1000 + 20 k + cell."""


def node_table(seed: int, sim: dict, params: PipelineParams, *, with_noise: bool = False):
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    xyz = o.xyz - np.floor(o.xyz.min(axis=0))
    a = analyse_nodes(xyz, params=params)
    pv = a.vox.point_voxel
    wood = o.is_wood[a.veg_idx].astype(float)
    tree = (o.tree_id[a.veg_idx] > 0).astype(float)
    n_wood = np.bincount(pv, weights=wood, minlength=a.vox.n)
    n_tree = np.bincount(pv, weights=tree, minlength=a.vox.n)
    p = woodleaf.path_counts(a.segmentation.paths.pred)
    x = woodleaf.wood_features(
        p, a.segmentation.node_tree, a.trunks.xy, a.vox.centroids, a.node_height, a.vox.counts, a.features, a.adjacency
    )
    keep = (a.segmentation.node_tree > 0) & (n_tree > 0)
    if with_noise:
        sp = a.segmentation.paths
        extra = woodleaf.noise_features(p, a.segmentation.node_tree, sp.pred, sp.dist, a.vox.counts, a.adjacency)
        return np.column_stack([x, extra])[keep], n_wood[keep], n_tree[keep], a.ground.noise
    return x[keep], n_wood[keep], n_tree[keep]


def fit(
    x: np.ndarray, n_wood: np.ndarray, n_all: np.ndarray, l2: float = 1e-3, offset: np.ndarray | None = None
) -> np.ndarray:
    """Logistic weights; with ``offset`` (held part of the linear predictor) every weight,
    the first too, is a correction and regularised."""
    y = n_wood / n_all
    w = n_all / n_all.sum()
    off = 0.0 if offset is None else offset
    mask = np.ones(x.shape[1])
    if offset is None:
        mask[0] = 0.0  # the bias is not regularised

    def loss(beta):
        z = off + x @ beta
        p = 1 / (1 + np.exp(-np.clip(z, -50, 50)))
        eps = 1e-9
        ll = -(w * (y * np.log(p + eps) + (1 - y) * np.log(1 - p + eps))).sum()
        grad = x.T @ (w * (p - y)) + l2 * mask * beta
        return ll + 0.5 * l2 * (mask * beta**2).sum(), grad

    res = minimize(loss, np.zeros(x.shape[1]), jac=True, method="L-BFGS-B")
    return res.x


def best_threshold(score: np.ndarray, n_wood: np.ndarray, n_all: np.ndarray) -> tuple[float, float]:
    best = (0.5, 0.0)
    for t in np.linspace(0.05, 0.95, 91):
        pred = score >= t
        tp = n_wood[pred].sum()
        fp = (n_all - n_wood)[pred].sum()
        fn = n_wood[~pred].sum()
        f1 = 2 * tp / max(2 * tp + fp + fn, 1e-9)
        if f1 > best[1]:
            best = (float(t), float(f1))
    return best


def _f1(score: np.ndarray, n_wood: np.ndarray, n_all: np.ndarray, thr: float) -> float:
    pred = score >= thr
    tp, fp, fn = n_wood[pred].sum(), (n_all - n_wood)[pred].sum(), n_wood[~pred].sum()
    return float(2 * tp / max(2 * tp + fp + fn, 1e-9))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=2, help="training blocks per configuration")
    ap.add_argument("--models", default="wide,narrow,spindle", help="which models to fit: wide, narrow, spindle, noisy (comma-separated)")
    args = ap.parse_args(argv)
    params = PipelineParams()
    print("features :", ", ".join(woodleaf.FEATURES))
    if "wide" in args.models:
        rows = [node_table(1000 + s, sim, params) for s in range(args.seeds) for sim in TRAINING]
        x = np.concatenate([r[0] for r in rows])[:, : woodleaf.NODE_FEATURES]
        nw = np.concatenate([r[1] for r in rows])
        na = np.concatenate([r[2] for r in rows])
        beta = fit(x, nw, na)
        thr, f1 = best_threshold(1 / (1 + np.exp(-np.clip(x @ beta, -50, 50))), nw, na)
        beta = np.r_[beta, 0.0, 0.0]  # the tree's width and height play no part in the wide model
        print("COMBINED_WEIGHTS:", np.array2string(beta, precision=3, separator=", "))
        print(f"threshold: {thr:.2f}  (training point-level wood F1 {f1:.3f}, {len(x)} nodes)")
    for name, training in (("narrow", NARROW_TRAINING), ("spindle", SPINDLE_TRAINING)):
        if name in args.models:
            _fit_narrow(name, training, args.seeds, params)
    if "noisy" in args.models:
        nf = woodleaf.NODE_FEATURES
        rows = []
        for k in range(args.seeds):
            for i, (noise, spacing) in enumerate(NOISY_TRAINING):
                sim = accuracy_params(noise, spacing, 1000 + 20 * k + i).model_dump(exclude={"seed"})
                rows.append(node_table(1000 + 20 * k + i, sim, params, with_noise=True))
        nx = len(woodleaf.FEATURES)
        base = np.concatenate([r[0][:, :nf] for r in rows])
        cols = [np.column_stack([r[0][:, :nf], r[0][:, nx:]]) for r in rows]
        share = [woodleaf.noise_term(r[3]) * woodleaf.noise_gate(r[0]) for r in rows]
        x = np.concatenate([c * g[:, None] for c, g in zip(cols, share)])
        nw = np.concatenate([r[1] for r in rows])
        na = np.concatenate([r[2] for r in rows])
        # lightly regularised: at 1e-3 the path columns stay near zero (docs/accuracy.md,
        # "the paths' topology, cheaply")
        beta = fit(x, nw, na, l2=1e-6, offset=base @ woodleaf.COMBINED_WEIGHTS[:nf])
        print("NOISE_WEIGHTS:", np.array2string(beta, precision=3, separator=", ", max_line_width=110))
        target = PipelineParams().matter.effective_threshold()
        for (noise, spacing), (xi, nwi, nai, est) in zip(NOISY_TRAINING * args.seeds, rows):
            xi, extra = xi[:, :nx], xi[:, nx:]
            before = woodleaf.combined_score(xi, narrow_weights=np.zeros(2 * nf))
            after = woodleaf.combined_score(
                xi, narrow_weights=np.zeros(2 * nf), noise=est, noise_weights=beta, noise_columns=extra
            )
            print(f"  sigma {noise:g} spacing {spacing:g} (estimated noise {est:.3f}): training wood F1 "
                  f"{_f1(before, nwi, nai, target):.3f} -> {_f1(after, nwi, nai, target):.3f}")
    return 0


def _fit_narrow(name: str, training: list[dict], seeds: int, params: PipelineParams) -> None:
    """Fit and print one of the narrow trees' models (``NARROW_WEIGHTS``, ``SPINDLE_WEIGHTS``)."""
    cells = [(s, sim) for s in range(seeds) for sim in training]
    rows = [node_table(1000 + s, sim, params) for s, sim in cells]
    x = np.concatenate([woodleaf.narrow_features(r[0]) for r in rows])
    nw = np.concatenate([r[1] / r[2].sum() for r in rows])  # each block weighs alike
    na = np.concatenate([r[2] / r[2].sum() for r in rows])
    beta = fit(x, nw, na, l2=1e-4)
    thr, f1 = best_threshold(1 / (1 + np.exp(-np.clip(x @ beta, -50, 50))), nw, na)
    target = PipelineParams().matter.effective_threshold()
    beta[0] += np.log(target / (1 - target)) - np.log(thr / (1 - thr))
    print(f"{name.upper()}_WEIGHTS:", np.array2string(beta, precision=3, separator=", ", max_line_width=110))
    print(f"best threshold {thr:.2f} moved to {target:.2f} (training wood F1 {f1:.3f}, blocks weighted alike)")
    for (s, sim), (xi, nwi, nai) in zip(cells, rows):
        score = 1 / (1 + np.exp(-np.clip(woodleaf.narrow_features(xi) @ beta, -50, 50)))
        print(f"  seed {1000 + s} {sim}: training wood F1 {_f1(score, nwi, nai, target):.3f}")


if __name__ == "__main__":
    raise SystemExit(main())
