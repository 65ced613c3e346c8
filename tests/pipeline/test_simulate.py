"""The orchard simulator: determinism, truth consistency, realism knobs, file round trip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError
from scipy.spatial import cKDTree

from pipeline.simulate import (
    KIND,
    LEAF,
    OUTLIER,
    POST,
    TWIG,
    VEHICLE,
    GROUND,
    WOOD,
    SimulationParams,
    ground_height,
    iter_simulation,
    read_truth,
    simulate_orchard,
    write_simulation,
)

SMALL = SimulationParams(rows=2, trees_per_row=3, density=0.15, seed=11)


@pytest.fixture(scope="module")
def small():
    return simulate_orchard(SMALL)


def test_same_seed_same_block_other_seed_other_block(small):
    again = simulate_orchard(SMALL)
    assert np.array_equal(small.xyz, again.xyz)
    assert np.array_equal(small.tree_id, again.tree_id)
    assert np.array_equal(small.is_wood, again.is_wood)
    assert np.array_equal(small.kind, again.kind)
    assert np.array_equal(small.trunks, again.trunks)
    other = simulate_orchard(SMALL.model_copy(update={"seed": 12}))
    assert other.n_points != small.n_points or not np.array_equal(other.xyz, small.xyz)


def test_chunks_concatenate_to_the_block(small):
    chunks = list(iter_simulation(SMALL))
    assert len(chunks) > SMALL.n_trees  # one chunk per tree, then ground and objects
    assert sum(c.n_points for c in chunks) == small.n_points
    assert np.array_equal(np.concatenate([c.xyz for c in chunks]), small.xyz)


def test_arrays_have_the_documented_shapes_and_types(small):
    n = small.n_points
    assert small.xyz.shape == (n, 3) and small.xyz.dtype == np.float64
    assert small.tree_id.shape == (n,) and small.tree_id.dtype == np.int64
    assert small.is_wood.dtype == bool and small.kind.dtype == np.uint8
    assert small.kind.max() < len(KIND)
    assert small.trunks.shape == (SMALL.n_trees, 3)
    assert small.trunk_radius.shape == (SMALL.n_trees,)
    assert np.all((small.trunk_radius > 0.04) & (small.trunk_radius < 0.2))
    assert small.crs_epsg == 28356


def test_coordinates_are_absolute_around_the_offsets(small):
    assert np.all(np.abs(small.trunks[:, 0] - 500000.0) < 20)
    assert np.all(np.abs(small.trunks[:, 1] - 6950000.0) < 20)
    assert np.all(np.abs(small.trunks[:, 2] - 100.0) < 3)


def test_one_trunk_per_tree_on_the_row_grid(small):
    assert len(small.trunks) == SMALL.rows * SMALL.trees_per_row
    local = small.trunks[:, :2] - small.trunks[0, :2]
    r, t = np.divmod(np.arange(SMALL.n_trees), SMALL.trees_per_row)
    grid = np.c_[t * SMALL.spacing, r * SMALL.row_spacing]
    assert np.all(np.abs(local - grid) < 1.0)  # jitter ~0.15 m
    assert set(np.unique(small.tree_id)) == set(range(SMALL.n_trees + 1))


def test_points_at_each_trunk_base_belong_to_that_tree(small):
    xy = small.xyz[:, :2]
    for k, (base, r) in enumerate(zip(small.trunks, small.trunk_radius), start=1):
        h = small.xyz[:, 2] - base[2]
        near = (np.hypot(*(xy - base[:2]).T) < r + 0.04) & (h > 0.28) & (h < 0.5)
        assert near.sum() >= 5, f"tree {k}: trunk hardly visible"
        assert np.mean(small.tree_id[near] == k) > 0.9
        assert np.mean(small.is_wood[near]) > 0.9


def test_kinds_and_labels_agree(small):
    tree = small.tree_id > 0
    assert np.all(np.isin(small.kind[tree], [WOOD, LEAF, TWIG]))
    assert np.all(~np.isin(small.kind[~tree], [WOOD, LEAF, TWIG]))
    assert (small.kind == TWIG).any() and (small.kind == LEAF).any()
    assert np.array_equal(small.is_wood, small.kind == WOOD)
    assert not small.is_wood[~tree].any()


def test_distractors_are_not_trees(small):
    for kind in (POST, VEHICLE, OUTLIER):
        sel = small.kind == kind
        assert sel.any(), KIND[kind]
        assert np.all(small.tree_id[sel] == 0)
    bare = simulate_orchard(SMALL.model_copy(update={"posts": False, "vehicle": False, "bin": False}))
    assert not np.isin(bare.kind, [POST, VEHICLE]).any()


def test_wood_fraction_is_orchard_like(small):
    frac = small.is_wood[small.tree_id > 0].mean()
    assert 0.08 < frac < 0.35


def test_neighbouring_crowns_overlap(small):
    """Leaves of one tree reach past the midpoint to its in-row neighbour."""
    trunks = small.trunks

    def intruders(a, b):  # leaf points of tree a closer to trunk b than to trunk a
        leaves = small.xyz[(small.tree_id == a) & (small.kind == LEAF), :2]
        return np.count_nonzero(np.hypot(*(leaves - trunks[b - 1, :2]).T) < np.hypot(*(leaves - trunks[a - 1, :2]).T))

    counts = []
    for k in range(1, SMALL.n_trees):
        if k % SMALL.trees_per_row == 0:
            continue  # k is the last tree of its row
        counts.append(intruders(k, k + 1) + intruders(k + 1, k))
        assert counts[-1] > 20, f"crowns of trees {k} and {k + 1} do not overlap"
    assert np.median(counts) > 100


def test_tree_heights_and_branching_height(small):
    for k, base in enumerate(small.trunks, start=1):
        z = small.xyz[small.tree_id == k, 2] - base[2]
        assert 3.0 < np.percentile(z, 99.9) < 5.2
    # branches, not lollipops: wood reaches well into the crown
    wood_z = small.xyz[small.is_wood, 2] - small.trunks[small.tree_id[small.is_wood] - 1, 2]
    assert np.percentile(wood_z, 90) > 1.5


def test_low_foliage_hangs_near_the_ground():
    def low_leaves(o):
        leaf = o.kind == LEAF
        base = o.trunks[o.tree_id[leaf] - 1]
        h = o.xyz[leaf, 2] - base[:, 2]
        d = np.hypot(*(o.xyz[leaf, :2] - base[:, :2]).T)
        return np.count_nonzero((h < 0.6) & (d > 0.5))

    p = SimulationParams(rows=1, trees_per_row=3, spacing=2.5, row_spacing=4.5, density=0.15, seed=4)
    plain = simulate_orchard(p)
    low = simulate_orchard(p.model_copy(update={"low_foliage": True}))
    assert low_leaves(low) > 50
    assert low_leaves(low) > 5 * max(low_leaves(plain), 1)


def test_a_trellis_stands_in_every_row():
    p = SimulationParams(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, density=0.15, seed=4, trellis=2)
    o = simulate_orchard(p)
    plain = simulate_orchard(p.model_copy(update={"trellis": 0}))
    post = o.kind == POST
    assert (o.tree_id[post] == 0).all()
    height = o.xyz[:, 2] - ground_height(p, o.xyz[:, 0], o.xyz[:, 1])
    for row in range(p.rows):
        trunks = o.trunks[row * p.trees_per_row : (row + 1) * p.trees_per_row]
        in_row = post & (np.abs(o.xyz[:, 1] - trunks[:, 1].mean()) < 0.3)
        assert not (plain.kind[np.abs(plain.xyz[:, 1] - trunks[:, 1].mean()) < 0.3] == POST).any()
        # a post at both row ends and in gaps 0 and 2 (every second gap), 2.8-3.2 m tall
        xs = [trunks[0, 0] - p.spacing / 2, *(0.5 * (trunks[i, 0] + trunks[i + 1, 0]) for i in (0, 2)),
              trunks[-1, 0] + p.spacing / 2]
        for x in xs:
            on = in_row & (np.abs(o.xyz[:, 0] - x) < 0.15)
            assert np.count_nonzero(on) > 50, x
            assert 2.6 < np.percentile(height[on], 99.5) < 3.3, x
        # three wires along the row between the posts: a few points at their heights
        for h in (0.8, 1.6, 2.4):
            wire = in_row & (np.abs(height - h) < 0.1) & (np.min(np.abs(o.xyz[:, [0]] - np.array(xs)), axis=1) > 0.3)
            assert np.count_nonzero(wire) > 5, h
    # the rest of the block is drawn as without a trellis
    assert np.array_equal(o.xyz[o.kind != POST][: 10_000], plain.xyz[plain.kind != POST][: 10_000])


def _ground_roughness(o):
    """Median std of ground points about a plane fitted in 1 m cells."""
    g = o.xyz[o.kind == 0]
    cell = np.floor(g[:, :2]).astype(np.int64)
    _, inv, cnt = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    stds = []
    for c in np.flatnonzero(cnt > 30)[:200]:
        q = g[inv.ravel() == c]
        A = np.c_[q[:, :2] - q[:, :2].mean(0), np.ones(len(q))]
        res = q[:, 2] - A @ np.linalg.lstsq(A, q[:, 2], rcond=None)[0]
        stds.append(res.std())
    return float(np.median(stds))


def test_noise_parameter_sets_the_spread():
    p = SimulationParams(rows=1, trees_per_row=1, density=0.1, grass=0.0, ghosting=0.0, outliers=0.0, seed=5)
    quiet = _ground_roughness(simulate_orchard(p.model_copy(update={"noise": 0.0})))
    noisy = _ground_roughness(simulate_orchard(p.model_copy(update={"noise": 0.05})))
    assert quiet < 0.01
    assert 0.035 < noisy < 0.065


def test_ground_height_is_the_surface_the_ground_points_lie_on():
    p = SimulationParams(rows=2, trees_per_row=2, density=0.05, grass=0.0, noise=0.0, ghosting=0.0, outliers=0.0,
                         slope=0.1, seed=7)
    o = simulate_orchard(p)
    g = o.xyz[o.kind == GROUND]
    assert len(g) > 1000
    np.testing.assert_allclose(ground_height(p, g[:, 0], g[:, 1]), g[:, 2], atol=1e-6)
    # another seed draws another surface
    other = ground_height(p.model_copy(update={"seed": 8}), g[:, 0], g[:, 1])
    assert np.abs(other - g[:, 2]).max() > 0.05


def test_ghosting_shifts_each_pass_rigidly():
    # the random streams do not depend on `ghosting`, so the two blocks differ exactly by
    # one rigid shift per alley pass: surfaces seen from both passes are doubled
    p = SimulationParams(rows=1, trees_per_row=2, density=0.05, noise=0.0, outliers=0.0, seed=5)
    sharp = simulate_orchard(p.model_copy(update={"ghosting": 0.0}))
    ghost = simulate_orchard(p.model_copy(update={"ghosting": 0.05}))
    assert ghost.n_points == sharp.n_points
    scanned = ghost.kind != OUTLIER  # outliers are not scanned from a pass
    shifts = np.unique(np.round(ghost.xyz - sharp.xyz, 5)[scanned], axis=0)
    assert len(shifts) == p.rows + 1  # one per pass
    norms = np.linalg.norm(shifts, axis=1)
    assert np.all((norms >= 0.025 - 1e-4) & (norms <= 0.05 + 1e-4))
    tree1 = np.unique(np.round(ghost.xyz - sharp.xyz, 5)[ghost.tree_id == 1], axis=0)
    assert len(tree1) == 2  # a tree is seen from the alleys on both sides


def test_occlusion_hides_the_crown_interior():
    p = SimulationParams(rows=1, trees_per_row=3, density=0.15, seed=1, posts=False, vehicle=False, bin=False)

    def inner_share(o):  # share of high leaf points within 1.2 m of their trunk axis
        leaf = o.kind == LEAF
        base = o.trunks[o.tree_id[leaf] - 1]
        d = np.hypot(*(o.xyz[leaf, :2] - base[:, :2]).T)
        high = o.xyz[leaf, 2] - base[:, 2] > 1.5
        return np.mean(d[high] < 1.2)

    clear = simulate_orchard(p.model_copy(update={"occlusion": 0.0}))
    dense = simulate_orchard(p.model_copy(update={"occlusion": 2.0}))
    assert inner_share(dense) < 0.8 * inner_share(clear)
    assert dense.n_points < 0.95 * clear.n_points


def test_density_scales_the_point_count():
    p = SimulationParams(rows=1, trees_per_row=2, density=0.1, seed=2)
    n1 = simulate_orchard(p).n_points
    n3 = simulate_orchard(p.model_copy(update={"density": 0.3})).n_points
    assert 2.5 < n3 / n1 < 3.5


def test_nonsense_parameters_are_rejected():
    for bad in ({"noise": 0.5}, {"rows": 0}, {"spacing": -1.0}, {"density": 0.0}, {"unknown": 1}):
        with pytest.raises(ValidationError):
            SimulationParams(**bad)


def test_las_and_truth_round_trip(tmp_path, small):
    from pipeline.io import read_info, read_points

    las, truth = tmp_path / "block.laz", tmp_path / "truth.parquet"
    summary = write_simulation(small, str(las), str(truth))
    assert summary == {"n_points": small.n_points, "n_trees": SMALL.n_trees, "crs_epsg": 28356}
    xyz, info = read_points(str(las))
    assert info.n_points == small.n_points
    assert info.crs_wkt and "28356" in info.crs_wkt
    assert np.abs(xyz + np.asarray(info.origin) - small.xyz).max() <= 0.0006  # 1 mm scale
    cols, trunks = read_truth(str(truth))
    assert np.array_equal(cols["point_index"], np.arange(small.n_points, dtype=np.uint64))
    assert np.array_equal(cols["tree_id"], small.tree_id)
    assert np.array_equal(cols["is_wood"], small.is_wood)
    assert np.array_equal(cols["kind"], small.kind)
    assert np.allclose(trunks, small.trunks, atol=1e-6)
    assert np.allclose(cols["trunk_radius"], small.trunk_radius, atol=1e-6)
    assert read_info(str(las)).n_points == small.n_points
    assert sorted(p.name for p in tmp_path.iterdir()) == ["block.laz", "truth.parquet"]


def test_streamed_write_equals_in_memory_write(tmp_path, small):
    from pipeline.io import read_points

    write_simulation(SMALL, str(tmp_path / "s.laz"), str(tmp_path / "s.parquet"))
    write_simulation(small, str(tmp_path / "m.laz"), str(tmp_path / "m.parquet"))
    a, _ = read_points(str(tmp_path / "s.laz"))
    b, _ = read_points(str(tmp_path / "m.laz"))
    assert np.array_equal(a, b)
    ta, _ = read_truth(str(tmp_path / "s.parquet"))
    assert np.array_equal(ta["tree_id"], small.tree_id)


def test_failed_write_leaves_nothing(tmp_path, small):
    def chunks():
        yield small
        raise RuntimeError("generator broke")

    with pytest.raises(RuntimeError):
        write_simulation(chunks(), str(tmp_path / "x.laz"), str(tmp_path / "x.parquet"))
    assert list(tmp_path.iterdir()) == []


def test_a_simulation_without_points_writes_nothing(tmp_path):
    # --density 1e-300 used to write a 0-point block ("wrote 0 points", exit 0)
    from pipeline.errors import ParameterError

    with pytest.raises(ParameterError, match="made no points"):
        write_simulation(SimulationParams(rows=1, trees_per_row=2, density=1e-300), str(tmp_path / "x.laz"),
                         str(tmp_path / "x.parquet"))
    assert list(tmp_path.iterdir()) == []


def test_read_truth_rejects_other_files(tmp_path):
    from pipeline.errors import InputError

    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"not parquet")
    with pytest.raises(InputError):
        read_truth(str(bad))
    with pytest.raises(InputError):
        read_truth(str(tmp_path / "missing.parquet"))
    from pipeline.simulate import read_truth_layout

    for path in (bad, tmp_path / "missing.parquet"):
        with pytest.raises(InputError):
            read_truth_layout(str(path))
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.table({"x": [1.0]}), tmp_path / "other.parquet")
    with pytest.raises(InputError, match="not an orchard truth file"):
        read_truth_layout(str(tmp_path / "other.parquet"))


def test_trunks_are_visible_points_close_to_the_truth(small):
    # the nearest tree point to each true base lies on that tree's trunk surface
    tree = cKDTree(small.xyz[small.tree_id > 0])
    d, _ = tree.query(small.trunks + [0, 0, 0.3])
    assert np.all(d < small.trunk_radius + 0.1)


# --------------------------------------------------------------------------- forms and layout

# SHA-1 of xyz, tree_id, kind and trunks of vase blocks generated before the forms and the
# layout options existed: with every new option at its default a vase block is the same
# block to the bit (float arithmetic of this platform's numpy; a port may need new pins).
VASE_PINS = [
    (dict(rows=2, trees_per_row=3, density=0.1, seed=0), 69831, "b68ff3f92ae89372606b4356fd2aa39346ae1ddb"),
    (dict(rows=2, trees_per_row=3, density=0.1, seed=1), 70347, "238e576df1ca9562d2d4f56f512ab3c9da827ad2"),
    (dict(rows=2, trees_per_row=3, density=0.1, seed=2), 70559, "406048e3136f97d41005f61e54b33c09334418c1"),
    (dict(rows=2, trees_per_row=4, density=0.1, seed=5, spacing=2.5, row_spacing=4.5, low_foliage=True, trellis=2),
     95477, "52cffa90755473ee6d877c0d89af20ea5751e77d"),
]


def _block_sha1(o) -> str:
    import hashlib

    h = hashlib.sha1()
    for a in (o.xyz, o.tree_id, o.kind, o.trunks):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@pytest.mark.parametrize("kw, n_points, sha1", VASE_PINS)
def test_vase_blocks_are_unchanged_to_the_bit(kw, n_points, sha1):
    o = simulate_orchard(SimulationParams(**kw))
    assert o.n_points == n_points
    assert _block_sha1(o) == sha1


SPINDLE = SimulationParams(form="spindle", rows=2, trees_per_row=5, spacing=1.0, row_spacing=3.5, density=0.25, seed=3)
HEDGE = SimulationParams(form="hedge", rows=2, trees_per_row=5, spacing=1.3, row_spacing=4.0, density=0.25, seed=3)


@pytest.fixture(scope="module")
def spindle():
    return simulate_orchard(SPINDLE)


@pytest.fixture(scope="module")
def hedge():
    return simulate_orchard(HEDGE)


def _tree_points(o, k):
    m = o.tree_id == k
    return o.xyz[m] - o.trunks[k - 1], m


def test_spindle_leaders_are_thin_and_tall(spindle):
    assert len(spindle.trunks) == SPINDLE.n_trees
    # 3-5 cm at the ground, a little thinner 0.3 m up (where the truth radius is taken)
    assert np.all((2 * spindle.trunk_radius > 0.026) & (2 * spindle.trunk_radius < 0.05))
    for k in range(1, len(spindle.trunks) + 1):
        d, _ = _tree_points(spindle, k)
        assert 2.7 < d[:, 2].max() < 3.65, k
        # the stem near the ground is one thin pole: its points hug the trunk axis
        low = (d[:, 2] > 0.1) & (d[:, 2] < 0.4)
        r = np.hypot(d[low, 0], d[low, 1])
        assert np.count_nonzero(r < 0.1) > 5, k
        assert np.mean(r < 0.07) > 0.8, k  # radius 1.5-2.5 cm, noise and ghosting around it


def test_spindle_laterals_are_short_and_trained_along_the_row(spindle):
    counts = []
    for k in range(1, len(spindle.trunks) + 1):
        d, _ = _tree_points(spindle, k)
        crown = d[d[:, 2] > 0.7]
        ax, ay = np.abs(crown[:, 0]), np.abs(crown[:, 1])
        assert 0.3 < np.percentile(ax, 98) < 0.95, k  # laterals 0.3-0.7 m (+ spurs and leaves)
        assert np.percentile(ax, 90) > 1.3 * np.percentile(ay, 90), k  # along the row more than across
        counts.append(len(d))
    # a small tree: ~10-30 k points at density 1
    assert 8_000 < np.median(counts) / SPINDLE.density < 35_000


def test_spindle_crowns_touch_along_the_row(spindle):
    p = SPINDLE
    for r in range(p.rows):
        for c in range(p.trees_per_row - 1):
            a, b = r * p.trees_per_row + c + 1, r * p.trees_per_row + c + 2
            da, _ = _tree_points(spindle, a)
            db, _ = _tree_points(spindle, b)
            gap = spindle.trunks[b - 1, 0] - spindle.trunks[a - 1, 0]
            # tree a reaches at least to the midpoint, and so does b from the other side
            assert da[:, 0].max() > 0.45 * gap and db[:, 0].min() < -0.45 * gap, (a, b)


def test_hedge_trunk_branches_low_into_a_wall(hedge):
    from pipeline.simforms import grow_tree

    class Flat:
        def z(self, x, y):
            return np.zeros(np.shape(x))

    for i in range(8):
        tree = grow_tree(np.random.default_rng([9, i]), HEDGE, np.zeros(2), Flat())
        # the first cylinder is the trunk: from below the ground to the branching point
        assert 0.5 <= tree.cyl_b[0, 2] <= 0.8
        assert 0.04 <= tree.cyl_ra[0] / 1.08 <= 0.06  # 8-12 cm diameter
    assert np.all((2 * hedge.trunk_radius > 0.07) & (2 * hedge.trunk_radius < 0.13))
    for k in range(1, len(hedge.trunks) + 1):
        d, m = _tree_points(hedge, k)
        assert 2.4 < d[:, 2].max() < 3.15, k
        # below the branching point only the trunk; the crown is 1-1.5 m wide across the row
        low = d[:, 2] < 0.45
        assert np.percentile(np.hypot(d[low, 0], d[low, 1]), 95) < 0.12, k
        crown = d[:, 2] > 0.9
        width = np.percentile(d[crown, 1], 98) - np.percentile(d[crown, 1], 2)
        assert 0.8 < width < 1.7, (k, width)


def test_hedge_crowns_form_a_continuous_wall(hedge):
    p = HEDGE
    tree = hedge.tree_id > 0
    for r in range(p.rows):
        row = hedge.trunks[r * p.trees_per_row : (r + 1) * p.trees_per_row]
        for a, b in zip(row[:-1], row[1:]):
            mid = 0.5 * (a + b)
            h = hedge.xyz[:, 2] - mid[2]
            at = tree & (np.abs(hedge.xyz[:, 0] - mid[0]) < 0.1) & (np.abs(hedge.xyz[:, 1] - mid[1]) < 0.6)
            for lo in (1.0, 1.5, 2.0):  # no hole between neighbours up the wall
                assert np.count_nonzero(at & (h > lo) & (h < lo + 0.5)) > 10, (r, lo)


def test_spacing_down_to_0_8_m():
    p = SimulationParams(form="spindle", rows=1, trees_per_row=3, spacing=0.8, row_spacing=3.0, density=0.05, seed=1)
    o = simulate_orchard(p)
    gaps = np.diff(o.trunks[:, 0])
    assert np.all(np.abs(gaps - 0.8) < 0.6)
    assert set(np.unique(o.tree_id)) == {0, 1, 2, 3}
    with pytest.raises(ValidationError):
        SimulationParams(spacing=0.79)


LAYOUT = SimulationParams(form="spindle", rows=3, trees_per_row=10, spacing=1.0, row_spacing=3.5, density=0.05,
                          seed=7, missing=0.1, replants=0.1, posts=False, vehicle=False, bin=False)


@pytest.fixture(scope="module")
def gappy():
    return simulate_orchard(LAYOUT)


def test_missing_trees_and_replants_are_counted_exactly(gappy):
    n = len(gappy.trunks)
    assert n == 30 - 3  # round(0.1 x 30) empty slots
    assert set(np.unique(gappy.tree_id)) == set(range(n + 1))  # ids stay 1..n
    assert gappy.tree_young.sum() == 3 and len(gappy.empty_slots) == 3
    for arr in (gappy.tree_row, gappy.tree_slot, gappy.tree_young, gappy.trunk_radius):
        assert len(arr) == n
    # every slot of every row holds one tree or is empty, never both; empty slots lie between trees
    taken = {(int(r), int(s)) for r, s in zip(gappy.tree_row, gappy.tree_slot)}
    empty = {(int(r), int(s)) for r, s, _, _ in gappy.empty_slots}
    assert len(taken) == n and not taken & empty
    assert taken | empty == {(r, s) for r in (1, 2, 3) for s in range(1, 11)}
    for r, s in empty:
        row = gappy.tree_slot[gappy.tree_row == r]
        assert row.min() < s < row.max()
    # trees in row-major order: rows, then slots, ascending
    assert np.all(np.diff(gappy.tree_row * 100 + gappy.tree_slot) > 0)


def test_empty_slots_sit_on_the_grid_between_their_neighbours(gappy):
    for r, s, x, y in gappy.empty_slots:
        assert x == pytest.approx(LAYOUT.easting + (s - 1) * LAYOUT.spacing)  # no ragged rows: slot 1 at x = 0
        assert y == pytest.approx(LAYOUT.northing + (r - 1) * LAYOUT.row_spacing)
        row = gappy.tree_row == r
        for step in (-1, 1):  # a neighbour one slot away, when that slot holds a tree (jitter 0.04 m)
            nb = gappy.trunks[row & (gappy.tree_slot == s + step)]
            if len(nb):
                assert np.hypot(nb[0, 0] - x - step * LAYOUT.spacing, nb[0, 1] - y) < 0.2


def test_replants_are_much_smaller_than_their_neighbours(gappy):
    heights = np.array([_tree_points(gappy, k)[0][:, 2].max() for k in range(1, len(gappy.trunks) + 1)])
    young, old = gappy.tree_young, ~gappy.tree_young
    assert np.all(heights[young] < 0.6 * np.median(heights[old]))
    assert np.all(gappy.trunk_radius[young] < 0.6 * np.median(gappy.trunk_radius[old]))
    assert np.all(heights[young] > 0.25 * np.median(heights[old]))


def test_other_trees_stay_when_a_slot_is_emptied(gappy):
    """A tree's random stream is its slot's: the full block holds the same trees."""
    full = simulate_orchard(LAYOUT.model_copy(update={"missing": 0.0, "replants": 0.0}))
    slot = (gappy.tree_row - 1) * LAYOUT.trees_per_row + gappy.tree_slot - 1
    same = ~gappy.tree_young
    assert np.allclose(full.trunks[slot[same]], gappy.trunks[same])
    assert np.allclose(full.trunk_radius[slot[same]], gappy.trunk_radius[same])


def test_ragged_rows_lose_up_to_three_slots_at_either_end():
    from pipeline.simlayout import make_layout

    p = SimulationParams(rows=4, trees_per_row=8, spacing=1.2, form="hedge", ragged_rows=True, seed=3,
                         density=0.02, posts=False, vehicle=False, bin=False)
    o = simulate_orchard(p)
    lengths = set()
    for r in range(1, 5):
        slots = o.tree_slot[o.tree_row == r]
        assert slots[0] == 1 and np.array_equal(slots, np.arange(1, len(slots) + 1))
        assert 2 <= len(slots) <= 8
        lengths.add(len(slots))
        # the first tree stands 0-3 slots from the grid's first slot
        x0 = o.trunks[o.tree_row == r][0, 0] - p.easting
        assert -0.5 < x0 < 3 * 1.2 + 0.5
    assert len(lengths) > 1
    cuts = set()
    for seed in range(30):
        lay = make_layout(p.model_copy(update={"seed": seed}))
        for r in range(4):
            planted = lay.col[(lay.row == r) & lay.planted]
            assert np.array_equal(planted, np.arange(planted[0], planted[-1] + 1))
            cuts |= {int(planted[0]), int(p.trees_per_row - 1 - planted[-1])}
    assert cuts == {0, 1, 2, 3}


def _rot(xy, deg):
    a = np.deg2rad(deg)
    return np.c_[np.cos(a) * xy[:, 0] - np.sin(a) * xy[:, 1], np.sin(a) * xy[:, 0] + np.cos(a) * xy[:, 1]]


def test_rotation_turns_the_whole_block_about_the_first_slot():
    p = SimulationParams(form="spindle", rows=2, trees_per_row=6, spacing=1.0, row_spacing=3.5, density=0.03, seed=2,
                         position_jitter=0.0)
    straight = simulate_orchard(p)
    turned = simulate_orchard(p.model_copy(update={"rotation": 35.0}))
    origin = np.array([p.easting, p.northing])
    assert np.allclose(_rot(straight.trunks[:, :2] - origin, 35.0) + origin, turned.trunks[:, :2], atol=1e-6)
    assert np.allclose(straight.trunks[:, 2], turned.trunks[:, 2])
    assert np.allclose(_rot(straight.xyz[:, :2] - origin, 35.0) + origin, turned.xyz[:, :2], atol=1e-6)
    assert np.array_equal(straight.tree_id, turned.tree_id)
    # each row's direction is the rotation
    for r in (1, 2):
        t = turned.trunks[turned.tree_row == r, :2]
        t = t - t.mean(axis=0)
        direction = np.linalg.svd(t, full_matrices=False)[2][0]
        azimuth = np.rad2deg(np.arctan2(direction[1], direction[0])) % 180.0
        assert abs(azimuth - 35.0) < 0.5
    # the ground turns with the block
    g = turned.kind == GROUND
    assert np.percentile(np.abs(turned.xyz[g, 2] - ground_height(turned_p := p.model_copy(update={"rotation": 35.0}),
                                                                   turned.xyz[g, 0], turned.xyz[g, 1])), 95) < 0.06
    assert turned_p.rotation == 35.0


def test_curved_rows_bow_sideways_and_keep_their_trees_whole():
    p = SimulationParams(form="spindle", rows=2, trees_per_row=9, spacing=1.0, row_spacing=3.5, density=0.03, seed=2,
                         trellis=2)
    straight = simulate_orchard(p)
    bowed = simulate_orchard(p.model_copy(update={"row_curvature": 1.0}))
    u = (straight.trunks[:, 0] - p.easting) / 8.0
    assert np.allclose(bowed.trunks[:, 1] - straight.trunks[:, 1], 4.0 * u * (1 - u), atol=1e-6)
    assert np.allclose(bowed.trunks[:, [0, 2]], straight.trunks[:, [0, 2]])
    mid = bowed.tree_slot == 5
    assert np.all(np.abs(bowed.trunks[mid, 1] - straight.trunks[mid, 1] - 1.0) < 0.05)
    # a tree moves as one rigid body: distances between its points are kept
    for k in (1, 5, 9):
        a = straight.xyz[straight.tree_id == k][:200]
        b = bowed.xyz[bowed.tree_id == k][:200]
        da = np.linalg.norm(a[:, None] - a[None], axis=2)
        db = np.linalg.norm(b[:, None] - b[None], axis=2)
        assert np.allclose(da, db, atol=1e-6)
    # the trellis follows the rows: post points near the middle of row 1 bowed by ~1 m
    post = (bowed.kind == POST) & (np.abs(bowed.xyz[:, 0] - p.easting - 4.0) < 1.2)
    row1 = np.abs(bowed.xyz[:, 1] - p.northing - 1.0) < 0.4
    assert np.count_nonzero(post & row1) > 20
    assert ground_height(p.model_copy(update={"row_curvature": 1.0}), np.array([p.easting + 4.0]),
                         np.array([p.northing + 1.0]))[0] == pytest.approx(
        ground_height(p, np.array([p.easting + 4.0]), np.array([p.northing]))[0])


def test_curvature_must_stay_gentle():
    with pytest.raises(ValidationError):
        SimulationParams(trees_per_row=5, spacing=1.0, row_curvature=1.5)
    SimulationParams(trees_per_row=5, spacing=1.0, row_curvature=-1.0)


def test_truth_layout_round_trip(tmp_path, gappy):
    from pipeline.simulate import Orchard, read_truth_layout

    las, truth = str(tmp_path / "b.las"), str(tmp_path / "t.parquet")
    write_simulation(gappy, las, truth)
    lay = read_truth_layout(truth)
    assert np.array_equal(lay["tree_row"], gappy.tree_row) and lay["tree_row"].dtype == np.int64
    assert np.array_equal(lay["tree_slot"], gappy.tree_slot)
    assert np.array_equal(lay["tree_young"], gappy.tree_young) and lay["tree_young"].dtype == bool
    assert np.allclose(lay["empty_slots"], gappy.empty_slots, atol=1e-6) and lay["empty_slots"].shape == (3, 4)
    assert lay["spacing"] == 1.0 and lay["row_spacing"] == 3.5
    cols, trunks = read_truth(truth)  # the point truth reads as before
    assert len(trunks) == len(gappy.trunks)
    # a truth file without a layout (an Orchard made by hand) answers None and no empty slots
    bare = Orchard(gappy.xyz[:100], gappy.tree_id[:100], gappy.is_wood[:100], gappy.kind[:100], gappy.trunks,
                   gappy.trunk_radius)
    write_simulation(bare, str(tmp_path / "c.las"), str(tmp_path / "u.parquet"))
    old = read_truth_layout(str(tmp_path / "u.parquet"))
    assert old["tree_row"] is None and old["tree_slot"] is None and old["tree_young"] is None
    assert old["spacing"] is None and old["empty_slots"].shape == (0, 4)


def test_a_block_without_options_has_a_full_layout(small):
    assert np.array_equal(small.tree_row, np.repeat([1, 2], 3))
    assert np.array_equal(small.tree_slot, np.tile([1, 2, 3], 2))
    assert not small.tree_young.any() and small.empty_slots.shape == (0, 4)
    assert small.spacing == SMALL.spacing and small.row_spacing == SMALL.row_spacing


def test_the_cli_takes_the_new_options():
    import argparse

    from service.commands import simulate as cmd

    parser = argparse.ArgumentParser()
    cmd.add_arguments(parser)
    args = parser.parse_args(["--out", "b.laz", "--truth", "t.parquet", "--form", "hedge", "--spacing", "0.8",
                              "--missing", "0.1", "--replants", "0.05", "--rotation", "-20", "--row-curvature",
                              "0.5", "--ragged-rows"])
    p = cmd.params_from_args(args)
    assert (p.form, p.spacing, p.missing, p.replants, p.rotation, p.row_curvature, p.ragged_rows) == (
        "hedge", 0.8, 0.1, 0.05, -20.0, 0.5, True)
    with pytest.raises(SystemExit):
        parser.parse_args(["--out", "b.laz", "--truth", "t.parquet", "--form", "pyramid"])


_layouts = dict(
    rows=st.integers(1, 6), trees_per_row=st.integers(1, 15), missing=st.floats(0.0, 0.5),
    replants=st.floats(0.0, 0.5), ragged_rows=st.booleans(), seed=st.integers(0, 2**32 - 1),
)


@settings(max_examples=150, deadline=None)
@given(**_layouts)
def test_every_slot_is_a_tree_an_empty_slot_or_off_the_row(**kw):
    from pipeline.simlayout import make_layout

    p = SimulationParams(**kw)
    lay = make_layout(p)
    n = p.rows * p.trees_per_row
    assert not (lay.present & ~lay.planted).any() and not (lay.young & ~lay.present).any()
    for r in range(p.rows):
        planted = np.flatnonzero(lay.planted & (lay.row == r))
        assert len(planted) >= min(2, p.trees_per_row)
        assert np.array_equal(np.diff(planted), np.ones(len(planted) - 1))  # one unbroken run
        assert lay.present[planted[0]] and lay.present[planted[-1]]  # rows end in trees
        assert np.array_equal(lay.position[planted], np.arange(1, len(planted) + 1))
        if not p.ragged_rows:
            assert len(planted) == p.trees_per_row
    inner = sum(max(np.count_nonzero(lay.planted & (lay.row == r)) - 2, 0) for r in range(p.rows))
    assert len(lay.empty) == min(round(p.missing * n), inner)
    assert np.count_nonzero(lay.young) == min(round(p.replants * n), len(lay.trees))


@settings(max_examples=100, deadline=None)
@given(rotation=st.floats(-360, 360), bow=st.floats(-1.0, 1.0), tpr=st.integers(2, 30),
       xyz=st.lists(st.tuples(st.floats(-20, 60), st.floats(-10, 40), st.floats(-2, 5)), min_size=1, max_size=20))
def test_the_block_frame_maps_back_to_the_straight_frame(rotation, bow, tpr, xyz):
    from pipeline.simlayout import place, unplace_xy

    p = SimulationParams(trees_per_row=tpr, spacing=1.0, rotation=rotation, row_curvature=bow * 0.25 * (tpr - 1))
    pts = np.array(xyz, dtype=np.float64)
    out = place(p, pts)
    assert np.array_equal(out[:, 2], pts[:, 2])
    x, y = unplace_xy(p, out[:, 0], out[:, 1])
    assert np.allclose(np.c_[x, y], pts[:, :2], atol=1e-7)
    # a tree moves rigidly: distances between its points are kept
    tree = place(p, pts, pts[0, :2])
    d0 = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    assert np.allclose(np.linalg.norm(tree[:, None] - tree[None], axis=2), d0, atol=1e-7)
    assert np.allclose(tree[0], out[0], atol=1e-9)  # the trunk base lands where the ground under it does


@pytest.mark.parametrize("form, spacing", [("vase", 2.5), ("hedge", 1.3)])
def test_replants_of_every_form_are_30_to_50_percent_of_a_tree(form, spacing):
    p = SimulationParams(form=form, rows=1, trees_per_row=6, spacing=spacing, row_spacing=4.0, density=0.03,
                         replants=0.34, seed=5, posts=False, vehicle=False, bin=False, tree_height=3.0,
                         trunk_radius=0.05)
    o = simulate_orchard(p)
    assert o.tree_young.sum() == 2
    ratio = o.trunk_radius[o.tree_young] / np.median(o.trunk_radius[~o.tree_young])
    assert np.all((ratio > 0.25) & (ratio < 0.56))
    heights = np.array([_tree_points(o, k)[0][:, 2].max() for k in range(1, 7)])
    ratio = heights[o.tree_young] / np.median(heights[~o.tree_young])
    assert np.all((ratio > 0.22) & (ratio < 0.6))
