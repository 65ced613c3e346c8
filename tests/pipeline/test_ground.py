"""Ground removal: slopes, grass, isolated points below the ground, canopy holes."""

import numpy as np
import pytest

from pipeline import bilinear as bilinear_module
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


def _dense_scene(rng):
    """Flat ground 20 x 20 m at about 100 points per 0.25 m cell, with a dense trunk-like
    column (several thousand points in one cell, as under a scanned trunk)."""
    g = _terrain(rng, n=160_000, slope=0.05)
    col = np.column_stack([rng.uniform(10.0, 10.2, (6000, 2)), rng.uniform(0.5, 3.0, 6000)])
    col[:, 2] += 0.05 * col[:, 0]
    return np.concatenate([g, col])


@pytest.mark.parametrize("depths", ["scattered", "one cell"])
def test_many_returns_far_below_the_ground_leave_the_surface_where_it_is(depths):
    # multipath: returns metres under the ground. Scattered over the block (0.2 % of the
    # points: one cell in twenty has one, the trunk's column a dozen) or five in one
    # cell; before, the cell test dropped only the lowest point of a cell and judged
    # cells against neighbours that were as deep, and the surface fell 10-15 m
    rng = np.random.default_rng(3)
    xyz = _dense_scene(rng)
    p = GroundParams()
    clean = ground_model(xyz, params=p)
    noisy = xyz.copy()
    if depths == "scattered":
        pick = rng.choice(len(xyz), int(0.002 * len(xyz)), replace=False)
    else:
        pick = np.flatnonzero((np.abs(xyz[:, 0] - 10.1) < 0.1) & (np.abs(xyz[:, 1] - 10.1) < 0.1))[:5]
    noisy[pick, 2] -= rng.uniform(2.0, 20.0, len(pick))
    m = ground_model(noisy, params=p)
    assert np.abs(m.dtms[0] - clean.dtms[0]).max() < 0.05
    h, is_g = classify_ground(noisy, m, params=p)
    assert not is_g[pick].any()
    assert (h[pick] < -1.5).all()


def test_backed_minima_by_hand():
    # one row of five 1 m cells, band 0.3 m; a minimum is backed by three points of its
    # cell within the band (itself included) or by two neighbouring minima within it:
    # cell 0: 0.0, 0.1, 0.2 -> backed by its own points
    # cell 1: -5.0 alone, then 0.0, 0.1, 0.25 -> the -5 is passed over, 0.0 backed by its own
    # cell 2: -3.0 alone, nothing else -> no backed minimum
    # cell 3: 0.05 alone, backed by cell 4 only -> not backed: a cell more is needed
    # cell 4: 0.1 alone, backed by cell 3 only -> neither
    z = np.array([0.0, 0.1, 0.2, -5.0, 0.0, 0.1, 0.25, -3.0, 0.05, 0.1])
    flat = np.array([0, 0, 0, 1, 1, 1, 1, 2, 3, 4])
    zmin = np.array([[0.0, -5.0, -3.0, 0.05, 0.1]])
    got, own = ground._backed_minima(z, flat, zmin, 0.3)
    assert got.tolist() == [[0.0, 0.0, np.inf, np.inf, np.inf]]
    assert own.tolist() == [[True, True, False, False, False]]
    # lone points continued by the minima of two neighbouring cells are backed (sparse
    # ground: one return per cell), though their cells do not back them
    z = np.array([1.0, 1.1, 1.2])
    got, own = ground._backed_minima(z, np.arange(3), z.reshape(1, 3), 0.3)
    assert got.tolist() == [[np.inf, 1.1, np.inf]]
    got, own = ground._backed_minima(np.tile(z, 3), np.arange(9), np.tile(z, 3).reshape(3, 3), 0.3)
    assert np.isfinite(got).all() and not own.any()


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


def test_too_steep_by_hand():
    # 1 m cells (one cell per slope square), slope 1: the envelope at a cell is the lowest
    # z_j + d_ij; a cell is too steep above allowance + one square's diagonal (0.5 + 1.414)
    z = np.full((5, 5), np.inf)
    z[0, 0] = 0.0
    for height, steep in ((4.0, False), (4.9, False), (5.0, True)):
        z[3, 0] = height  # 3 m from the low cell: envelope 3, margin 1.914
        assert ground._too_steep(z, 1.0, 1.0, 0.5)[3, 0] == steep, height
    z[3, 0] = np.inf
    z[3, 3] = 3 * np.sqrt(2.0) + 1.9  # diagonal steps cost sqrt(2) each
    assert not ground._too_steep(z, 1.0, 1.0, 0.5)[3, 3]
    z[3, 3] += 0.1
    out = ground._too_steep(z, 1.0, 1.0, 0.5)
    assert out[3, 3] and out.sum() == 1  # the low cell and empty cells are never too steep


def test_a_tall_crown_over_a_patch_of_ground_is_not_ground():
    # a tree cut out of a scan with only a patch of ground under its trunk: the lowest
    # points of its crown have no ground within R_g, so the local minimum alone takes
    # them for ground; they stand 8 m above ground less than 5 m away (slope > 1)
    rng = np.random.default_rng(5)
    patch = np.column_stack([rng.uniform(9.5, 10.5, (800, 2)), rng.normal(0.0, 0.01, 800)])
    stem = np.column_stack([rng.normal(10.0, 0.1, (2000, 2)), rng.uniform(0.0, 8.0, 2000)])
    r, a = 5.0 * np.sqrt(rng.uniform(0, 1, 20000)), rng.uniform(0, 2 * np.pi, 20000)
    crown = np.column_stack([10 + r * np.cos(a), 10 + r * np.sin(a), rng.uniform(8.0, 12.0, 20000)])
    xyz = np.concatenate([patch, stem, crown])
    in_crown = np.arange(len(xyz)) >= len(patch) + len(stem)
    for slope, crown_ground in ((0.0, True), (1.0, False)):
        p = GroundParams(max_slope=slope)
        m = ground_model(xyz, params=p)
        h, is_g = classify_ground(xyz, m, params=p)
        assert is_g[: len(patch)].mean() > 0.99
        assert is_g[in_crown].any() == crown_ground, slope
    assert np.abs(h[in_crown] - xyz[in_crown, 2]).max() < 0.1  # heights from the patch's level


def test_a_steep_hillside_stays_ground():
    # 40 % over 60 m: within the local test's slope allowance and under max_slope, so the
    # slope test rejects none of it (its envelope reaches 40 squares of 1 m)
    rng = np.random.default_rng(6)
    g = _terrain(rng, n=60000, slope=0.0)
    g[:, 0] *= 3.0
    g[:, 2] += 0.4 * g[:, 0]
    p = GroundParams()
    m = ground_model(g, params=p)
    _, is_g = classify_ground(g, m, params=p)
    assert is_g.mean() > 0.99


def test_too_steep_squares_follow_the_block_grid():
    # a tile's raster starts at another cell of the block's grid; with the squares aligned
    # to that grid it judges every cell as the whole block's raster does
    rng = np.random.default_rng(7)
    z = np.full((60, 60), np.inf)
    cells = rng.integers(5, 55, (300, 2))
    z[cells[:, 0], cells[:, 1]] = rng.uniform(0.0, 6.0, 300)
    whole = ground._too_steep(z, 0.25, 1.0, 0.42)
    assert 0 < whole.sum() < 300
    for corner in ((1, 3), (2, 2), (5, 0)):
        tile = ground._too_steep(z[corner[0] :, corner[1] :], 0.25, 1.0, 0.42, corner)
        assert np.array_equal(tile, whole[corner[0] :, corner[1] :]), corner


def test_block_statistics_make_a_part_of_the_block_lift_like_the_block():
    # a tile of a tiled job fits its own raw surface but takes the block's (shift, noise):
    # where the tile and the block see the same ground, their models then agree exactly
    rng = np.random.default_rng(5)
    g = _terrain(rng, n=60000, slope=0.05)
    g[:, 2] += rng.normal(0.0, 0.03, len(g))
    p = GroundParams()
    block = ground_model(g, params=p)
    raw = ground.raw_ground_model(g, params=p)
    stats = ground.ground_stats(ground.ground_residuals(raw, g[:: ground.stats_stride(len(g))]))
    assert stats[1] == block.noise > 0.02
    assert all(np.array_equal(a, b) for a, b in zip(ground.lifted(raw, stats).dtms, block.dtms))
    # a 10 m square of it: its own estimate differs, the block's statistics do not
    part = g[(g[:, 0] < 10) & (g[:, 1] < 10)]
    inner = np.array([[4.0, 4.0], [5.0, 6.0], [6.5, 3.5]])
    own = ground_model(part, params=p)
    shared = ground_model(part, params=p, stats=stats)
    assert shared.noise == block.noise and own.noise != block.noise
    assert np.array_equal(shared.height_at(inner), block.height_at(inner))
    assert not np.array_equal(own.height_at(inner), block.height_at(inner))
    assert ground.stats_stride(199_999) == 1 and ground.stats_stride(1_000_000) == 5


@pytest.mark.parametrize("slope", [0.5, 0.6, 0.8])
def test_steep_hillsides_beyond_the_fixed_allowance_stay_ground(slope):
    # the fixed allowance (0.12 m + 0.3 x R_g) followed slopes up to about 0.42 m/m: at 0.6
    # only 3 % of a clean plane was ground. The allowance now grows with the terrain's
    # own slope (measured on the surface of local minima)
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [40, 20], (100_000, 2))
    xyz = np.c_[xy, slope * xy[:, 0] + rng.normal(0, 0.01, len(xy))]
    p = GroundParams()
    m = ground_model(xyz, params=p)
    h, is_g = classify_ground(xyz, m, params=p)
    inner = (xy[:, 0] > 5) & (xy[:, 0] < 35) & (xy[:, 1] > 5) & (xy[:, 1] < 15)
    assert is_g[inner].mean() > 0.99
    assert np.percentile(np.abs(h[inner]), 99) < 0.15


def test_terrain_slope_sees_a_hillside_and_not_the_step_to_a_crown():
    c, foot = 0.25, ground._disk(4.0)
    x = np.arange(120)[:, None] * c + np.zeros((1, 80))
    plane = ground.ndimage.minimum_filter(0.7 * x, footprint=foot, mode="nearest")
    s = ground._terrain_slope(plane, c, foot, cap=1.0)
    assert np.allclose(s[20:100, 20:60], 0.7, atol=0.01)
    assert np.allclose(ground._terrain_slope(plane * 3, c, foot, cap=1.0)[20:100, 20:60], 1.0)  # capped
    # flat ground with a 4 m patch where the lowest returns are a crown's bottom, 1.5 m up
    flat = np.zeros((120, 80))
    flat[50:66, 30:46] = 1.5
    s = ground._terrain_slope(ground.ndimage.minimum_filter(flat, footprint=foot, mode="nearest"), c, foot, cap=1.0)
    assert s.max() <= ground.SLOPE_ALLOWANCE  # the fixed allowance, exactly as before


def test_a_raw_model_fitted_beforehand_is_taken_as_it_is():
    # a tiled job fits each tile's raw model in its ground pass and hands it to the
    # tile's processing: the result must be the model fitted there, and it must be used
    rng = np.random.default_rng(6)
    g = _terrain(rng, n=30000, slope=0.05)
    g[:, 2] += rng.normal(0.0, 0.02, len(g))
    p = GroundParams()
    raw = ground.raw_ground_model(g, params=p)
    for stats in (None, (0.01, 0.02)):
        fitted, given = ground_model(g, params=p, stats=stats), ground_model(g, params=p, stats=stats, raw=raw)
        assert given.noise == fitted.noise
        assert all(np.array_equal(a, b) for a, b in zip(given.dtms, fitted.dtms))
    higher = ground.GroundModel(tuple(d + 1.0 for d in raw.dtms), raw.origins, raw.cell_size, 0.0)
    lifted_by_one = ground_model(g, params=p, stats=(0.0, 0.0), raw=higher)
    assert all(np.array_equal(a, b + 1.0) for a, b in zip(lifted_by_one.dtms, raw.dtms))


@pytest.mark.parametrize("table", [True, False])  # corners from the padded table, or gathered one by one
@pytest.mark.parametrize("shape", [(1, 1), (1, 5), (2, 3), (7, 9), (106, 66)])
def test_bilinear_is_map_coordinates_bit_for_bit(shape, table, monkeypatch):
    from scipy import ndimage

    monkeypatch.setattr(bilinear_module, "BILINEAR_TABLE_POINTS", 0.0 if table else np.inf)

    rng = np.random.default_rng(sum(shape))
    grid = rng.normal(0, 3, shape)
    origin, cell = np.array([-2.5, 10.0]), 0.25
    g = rng.uniform(-3, max(shape) + 3, (2, 3 * bilinear_module.BILINEAR_CHUNK + 17))  # grid coordinates, past the edges
    g[:, :2000] = np.round(g[:, :2000])  # on cell centres and edges
    special = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0, shape[0] - 1.0, 1e300, -1e300, 1e-300])
    g = np.concatenate([g, np.array(np.meshgrid(special, special)).reshape(2, -1)], axis=1)
    xy = (g.T + 0.5) * cell + origin
    want = ndimage.map_coordinates(grid, (xy.T - origin[:, None]) / cell - 0.5, order=1, mode="nearest")
    got = bilinear_module.bilinear(grid, xy, origin, cell)
    assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("n", [0, 1, 5, 3 * ground.CACHE_POINTS + 17])
def test_classify_ground_is_the_whole_array_formula(n):
    # reference: the whole-array expression classify_ground computed before its masks ran
    # a cache-sized pass at a time
    rng = np.random.default_rng(n)
    g = _terrain(rng, n=max(n, 2000), slope=0.1)
    g[:, 2] += rng.normal(0.0, 0.05, len(g))
    model = ground_model(g, params=GroundParams())
    pts = np.c_[rng.uniform(-5, 45, (n, 2)), rng.uniform(-1, 3, n)]
    pts[: n // 50, 2] = model.height_at(pts[: n // 50]) + GroundParams().tolerance  # on the edge of the band
    p = GroundParams()
    height, is_ground = classify_ground(pts, model, params=p)
    want = pts[:, 2] - model.height_at(pts)
    tol = model.tolerance(p)
    want_ground = (want <= tol) & (want >= -max(p.outlier_depth, ground.NOISE_WIDTHS * model.noise))
    assert height.tobytes() == want.tobytes()
    assert np.array_equal(is_ground, want_ground)
