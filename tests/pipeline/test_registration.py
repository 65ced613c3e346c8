"""Registration of a capture's trunks onto the previous capture's."""

import numpy as np
import pytest

from pipeline.errors import NoOverlapError
from pipeline.registration import RigidTransform, kabsch_2d, register, size_descriptors


def _block(rng, rows=4, per_row=12, spacing=1.2, row_spacing=3.5):
    r, c = np.divmod(np.arange(rows * per_row), per_row)
    xy = np.c_[c * spacing, r * row_spacing] + rng.normal(0, 0.03, (rows * per_row, 2)) + [500000.0, 6950000.0]
    h = rng.uniform(2.8, 3.5, len(xy))
    v = rng.uniform(2.0, 4.0, len(xy))
    t = rng.uniform(0.03, 0.05, len(xy))
    return xy, h, v, t


def _capture(rng, xy, h, v, t, truth: RigidTransform, keep):
    """The trees of ``keep`` seen again: grown 5-10 %, measured with noise, in a frame
    that ``truth`` maps back onto the first capture's."""
    g = rng.uniform(1.05, 1.10, len(xy))
    cur = truth.inverse(xy) + rng.normal(0, 0.02, xy.shape)
    return cur[keep], (h * g)[keep], (v * g**3)[keep], (t * g)[keep]


@pytest.mark.parametrize("dx, dy, deg", [(0.7, -0.4, 0.8), (1.9, 0.3, -1.7), (-1.6, 1.1, 2.0)])
def test_recovers_a_known_transform_even_beyond_half_the_spacing(dx, dy, deg):
    rng = np.random.default_rng(3)
    xy, h, v, t = _block(rng)
    truth = RigidTransform(dx, dy, deg, *xy.mean(axis=0))
    keep = np.ones(len(xy), bool)
    keep[[5, 17, 30]] = False  # cut since
    cur, ch, cv, ct = _capture(rng, xy, h, v, t, truth, keep)
    reg = register(cur, xy, cur_size=size_descriptors(ch, cv, ct), prev_size=size_descriptors(h, v, t))
    err = np.linalg.norm(reg.transform.apply(cur) - xy[keep], axis=1)
    assert err.max() < 0.1
    assert reg.residual_m < 0.05
    assert reg.n_matched == keep.sum()


def test_nearest_trunk_alone_locks_onto_the_wrong_tree():
    """A shift of 0.8 spacings: each trunk's nearest previous trunk is its neighbour."""
    rng = np.random.default_rng(4)
    xy, h, v, t = _block(rng, spacing=1.0)
    truth = RigidTransform(0.8, 0.0, 0.6, *xy.mean(axis=0))
    keep = np.ones(len(xy), bool)
    cur, ch, cv, ct = _capture(rng, xy, h, v, t, truth, keep)
    nearest = np.argmin(np.linalg.norm(cur[:, None] - xy[None], axis=2), axis=1)
    assert (nearest != np.arange(len(xy))).mean() > 0.5  # the naive match is wrong
    reg = register(cur, xy, cur_size=size_descriptors(ch, cv, ct), prev_size=size_descriptors(h, v, t))
    assert np.abs(reg.transform.apply(cur) - xy).max() < 0.1


def test_uncovered_row_ends_break_the_tie_without_sizes():
    rng = np.random.default_rng(5)
    xy, h, v, t = _block(rng, spacing=1.0)
    truth = RigidTransform(1.8, 0.2, -1.0, *xy.mean(axis=0))
    cur, *_ = _capture(rng, xy, h, v, t, truth, np.ones(len(xy), bool))
    lo, hi = cur.min(axis=0) - 0.5, cur.max(axis=0) + 0.5

    def covered(p):
        return np.all((p >= lo) & (p <= hi), axis=1)

    reg = register(cur, xy, covered=covered)
    assert np.abs(reg.transform.apply(cur) - xy).max() < 0.1


def test_kabsch_recovers_an_exact_transform():
    rng = np.random.default_rng(6)
    src = rng.uniform(0, 50, (20, 2))
    truth = RigidTransform(0.5, -1.2, 1.3, 25.0, 25.0)
    fit = kabsch_2d(src, truth.apply(src), np.array([25.0, 25.0]))
    assert np.allclose([fit.dx, fit.dy, fit.rotation_deg], [0.5, -1.2, 1.3])


def test_captures_that_do_not_overlap_name_both():
    rng = np.random.default_rng(7)
    xy, h, v, t = _block(rng)
    with pytest.raises(NoOverlapError) as err:
        register(xy + [300.0, 0.0], xy, names=("b_2026", "a_2025"))
    assert err.value.capture == "b_2026" and err.value.previous == "a_2025"
    assert "b_2026" in str(err.value) and "a_2025" in str(err.value)
