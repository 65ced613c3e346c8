"""The orchard simulator: determinism, truth consistency, realism knobs."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial import cKDTree

from simulator.orchard import GROUND, KIND, LEAF, OUTLIER, POST, TWIG, VEHICLE, WOOD
from simulator.simparams import SimulationParams
from simulator.simulate import iter_simulation, simulate_orchard
from simulator.terrain import ground_height
from synthetic_blocks import SMALL


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


def test_trunks_are_visible_points_close_to_the_truth(small):
    # the nearest tree point to each true base lies on that tree's trunk surface
    tree = cKDTree(small.xyz[small.tree_id > 0])
    d, _ = tree.query(small.trunks + [0, 0, 0.3])
    assert np.all(d < small.trunk_radius + 0.1)


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


def test_spacing_down_to_0_8_m():
    p = SimulationParams(form="spindle", rows=1, trees_per_row=3, spacing=0.8, row_spacing=3.0, density=0.05, seed=1)
    o = simulate_orchard(p)
    gaps = np.diff(o.trunks[:, 0])
    assert np.all(np.abs(gaps - 0.8) < 0.6)
    assert set(np.unique(o.tree_id)) == {0, 1, 2, 3}
    with pytest.raises(ValidationError):
        SimulationParams(spacing=0.79)


def test_irrigation_risers_stand_on_the_drip_line_in_no_tree():
    from simulator.clutter import risers
    from simulator.plan import make_plan

    p = SimulationParams(rows=2, trees_per_row=4, spacing=2.0, row_spacing=4.0, density=0.15, seed=4, risers=0.5,
                         vehicle=False, bin=False, posts=False)
    plain = simulate_orchard(p.model_copy(update={"risers": 0.0}))
    o = simulate_orchard(p)
    a, b, r = risers(make_plan(p))
    assert len(a) == 4 + 3  # half of the 8 trees, half of the 6 gaps (rounded)
    assert np.all((r >= 0.01) & (r <= 0.025))
    height = b[:, 2] - a[:, 2] - 0.05
    assert np.all((height >= 0.29) & (height <= 1.01))
    riser = o.kind == POST
    assert riser.sum() > 100 and (o.tree_id[riser] == 0).all()
    # on the rows' lines (y 0 or 4 in the straight frame), by a trunk or mid-gap
    local = o.xyz[riser, :2] - o.trunks[0, :2]
    assert np.all(np.min(np.abs(local[:, [1]] - np.array([0.0, 4.0])), axis=1) < 0.5)
    h = o.xyz[riser, 2] - ground_height(p, o.xyz[riser, 0], o.xyz[riser, 1])
    assert h.max() < 1.1
    # the rest of the block is drawn as without them
    assert np.array_equal(o.xyz[~riser], plain.xyz)


def test_a_leafless_block_has_the_same_trees_without_leaves():
    p = SimulationParams(rows=1, trees_per_row=3, density=0.1, seed=6)
    leafy = simulate_orchard(p)
    bare = simulate_orchard(p.model_copy(update={"leafless": True}))
    assert (leafy.kind == LEAF).sum() > 1000 and not (bare.kind == LEAF).any()
    assert np.array_equal(leafy.trunks, bare.trunks)
    assert np.array_equal(leafy.trunk_radius, bare.trunk_radius)
    # the wood is the same, and seen better without the leaves in front of it
    assert (bare.is_wood.sum()) > leafy.is_wood.sum()
    with pytest.raises(ValidationError, match="conifer"):
        SimulationParams(form="conifer", leafless=True)
