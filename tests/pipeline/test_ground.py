"""Ground removal: slopes, grass, isolated points below the ground, canopy holes."""

import numpy as np
import pytest

from pipeline import ground
from pipeline.errors import InputError
from pipeline.ground import MAX_PART_CELLS, PART_GAP, classify_ground, ground_model
from pipeline.params import GroundParams


def _terrain(rng, n=40000, slope=0.12):
    xy = rng.uniform(0, 20, (n, 2))
    z = slope * xy[:, 0] + 0.1 * np.sin(xy[:, 1] / 3) + rng.normal(0, 0.01, n)
    return np.column_stack([xy, z])


def test_sloping_ground_is_ground_and_height_is_relative():
    rng = np.random.default_rng(0)
    g = _terrain(rng)
    # a 2 m tall block of canopy, and no ground returns under its central 1.6 m
    # (gaps narrower than 2 R_g: the paper's coverage assumption)
    c = rng.uniform([7, 7, 1.0], [13, 13, 3.0], (8000, 3))
    c[:, 2] += 0.12 * c[:, 0]
    keep = ~((g[:, 0] > 9.2) & (g[:, 0] < 10.8) & (g[:, 1] > 9.2) & (g[:, 1] < 10.8))
    xyz = np.concatenate([g[keep], c])
    p = GroundParams()
    m = ground_model(xyz, params=p)
    h, is_g = classify_ground(xyz, m, params=p)
    n_g = keep.sum()
    assert is_g[:n_g].mean() > 0.99
    assert not is_g[n_g:].any()
    # heights of the canopy are measured from the sloping surface, not from z = 0
    true_h = c[:, 2] - (0.12 * c[:, 0] + 0.1 * np.sin(c[:, 1] / 3))
    assert np.abs(h[n_g:] - true_h).max() < 0.15


def test_isolated_points_below_ground_do_not_pull_the_surface_down():
    rng = np.random.default_rng(1)
    g = _terrain(rng, slope=0.0)
    holes = np.column_stack([rng.uniform(2, 18, (20, 2)), np.full(20, -2.0)])
    gxy = rng.uniform(0, 20, (3000, 2))
    grass = np.column_stack([gxy, 0.1 * np.sin(gxy[:, 1] / 3) + rng.uniform(0.0, 0.08, 3000)])
    xyz = np.concatenate([g, grass, holes])
    p = GroundParams()
    m = ground_model(xyz, params=p)
    h, is_g = classify_ground(xyz, m, params=p)
    assert is_g[: len(g) + len(grass)].mean() > 0.99
    assert not is_g[-20:].any()  # below-ground noise is neither ground ...
    assert (h[-20:] < -1.5).all()  # ... nor anything above it


def test_noise_estimate_widens_tolerance_on_noisy_scans():
    rng = np.random.default_rng(2)
    g = _terrain(rng, slope=0.05)
    g[:, 2] += rng.normal(0, 0.08, len(g))
    p = GroundParams()
    m = ground_model(g, params=p)
    assert 0.04 < m.noise < 0.15
    _, is_g = classify_ground(g, m, params=p)
    assert is_g.mean() > 0.97


def test_separate_parts_get_their_own_surface():
    # two patches of sloping ground 5 km apart, one 30 m lower: each is modelled by its
    # own raster, and heights under each come from its own surface
    rng = np.random.default_rng(3)
    a = _terrain(rng, n=20000)
    b = _terrain(rng, n=20000) + [5000.0, 5000.0, -30.0]
    p = GroundParams()
    m = ground_model(np.concatenate([a, b]), params=p)
    assert len(m.dtms) == 2 and sum(d.size for d in m.dtms) < 2 * (20 / p.cell_size + 2) ** 2
    for pts, surface in ((a, 0.0), (b, -30.0)):
        q = pts[:500] + [0.0, 0.0, 1.0]
        h, is_g = classify_ground(q, m, params=p)
        assert np.allclose(h, 1.0, atol=0.1) and not is_g.any(), surface
    # a part alone gives the same surface as it does beside the other
    alone = ground_model(a, params=p)
    assert np.allclose(alone.height_at(a), m.height_at(a), atol=0.02)


def test_parts_are_split_where_the_gap_is_wider_than_part_gap(monkeypatch):
    monkeypatch.setattr(ground, "ONE_PART_CELLS", 0)  # look for parts in a small block too
    rng = np.random.default_rng(4)
    a = _terrain(rng, n=5000)
    near = _terrain(rng, n=5000) + [20.0 + 0.5 * PART_GAP, 0.0, 0.0]
    far = _terrain(rng, n=5000) + [20.0 + 2.5 * PART_GAP, 0.0, 0.0]
    assert len(ground_model(np.concatenate([a, near]), params=GroundParams()).dtms) == 1
    assert len(ground_model(np.concatenate([a, far]), params=GroundParams()).dtms) == 2


def test_a_part_too_wide_for_one_raster_is_refused_with_a_message():
    p = GroundParams()
    side = 1.2 * np.sqrt(MAX_PART_CELLS) * p.cell_size  # a connected line of points this long
    t = np.arange(0.0, side, 5.0)
    with pytest.raises(InputError, match="process the block in tiles"):
        ground_model(np.column_stack([t, t, np.zeros_like(t)]), params=p)
