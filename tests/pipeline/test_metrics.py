"""Per-tree metrics: hulls, and merging partials equals computing at once."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.metrics import (
    TREE_COLUMNS,
    combine_partials,
    finalize_metrics,
    group_runs,
    tree_partials,
    trunk_circles,
)
from pipeline.params import MetricsParams


def _cone_tree(rng, x0, y0, n=3000, h=4.0, r=2.0):
    z = rng.uniform(0, h, n)
    rad = r * (1 - z / h) * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([x0 + rad * np.cos(a), y0 + rad * np.sin(a), z])


def test_metrics_of_a_known_shape():
    # a cylinder trunk of diameter 0.3 m and a square crown 2 x 2 m from 1 to 3 m high
    rng = np.random.default_rng(1)
    th = rng.uniform(0, 2 * np.pi, 2000)
    trunk = np.column_stack([0.15 * np.cos(th), 0.15 * np.sin(th), rng.uniform(0, 1, 2000)])
    crown = rng.uniform([-1, -1, 1], [1, 1, 3], (20000, 3))
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (1, 3)], float)
    xyz = np.concatenate([trunk, crown, corners])
    tid = np.ones(len(xyz), np.int64)
    wood = np.zeros(len(xyz), bool)
    wood[:2000] = True
    trunks = np.array([[0.0, 0.0, 0.0]])
    p = MetricsParams(trunk_height=0.3, crown_base=1.0)
    parts = tree_partials(xyz, tid, wood, trunks[:, 2], params=p)
    cols = finalize_metrics(parts, trunks, trunk_circles(xyz, tid, trunks, params=p)[1])
    assert list(cols) == list(TREE_COLUMNS)
    assert cols["height_m"][0] == pytest.approx(3.0)
    assert cols["crown_area_m2"][0] == pytest.approx(4.0, rel=1e-6)
    assert cols["crown_diameter_m"][0] == pytest.approx(2 * np.sqrt(2), rel=1e-6)
    # crown points are those above 1 m: exactly the box
    assert cols["crown_volume_m3"][0] == pytest.approx(8.0, rel=0.02)
    assert cols["trunk_diameter_m"][0] == pytest.approx(0.3, abs=0.01)
    assert cols["n_points"][0] == len(xyz)
    assert cols["wood_fraction"][0] == pytest.approx(2000 / len(xyz))


@settings(max_examples=15, deadline=None)
@given(st.integers(1, 6), st.integers(0, 2**16))
def test_partials_merged_across_a_split_equal_partials_at_once(n_split, seed):
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([_cone_tree(rng, 0, 0), _cone_tree(rng, 3, 0.5)])
    tid = np.repeat([1, 2], 3000)
    wood = rng.uniform(size=len(xyz)) < 0.2
    trunk_z = np.zeros(2)
    p = MetricsParams()
    whole = tree_partials(xyz, tid, wood, trunk_z, params=p)
    # split the points into arbitrary "tiles"; each tile numbers the trees its own way
    part = rng.integers(0, n_split, len(xyz))
    parts, maps = [], []
    for t in range(n_split):
        sel = part == t
        local = np.where(tid[sel] == 1, 2, 1)  # swap the numbering
        parts.append(tree_partials(xyz[sel], local, wood[sel], trunk_z, params=p))
        maps.append(np.array([0, 2, 1]))
    merged = combine_partials(parts, maps)
    trunks = np.array([[0, 0, 0], [3, 0.5, 0]], float)
    a = finalize_metrics(whole, trunks, np.full(2, np.nan))
    b = finalize_metrics(merged, trunks, np.full(2, np.nan))
    for col in TREE_COLUMNS:
        assert np.allclose(a[col], b[col], equal_nan=True), col


@pytest.mark.parametrize("shape", ["cone", "flat", "line", "tiny"])
def test_crown_hulls_match_hulls_of_all_points(shape):
    # the plan-view hull is taken over the 3D hull's vertices only; it must be the
    # hull of all the crown's points, also when the crown is flat or a line
    from scipy.spatial import ConvexHull

    from pipeline.metrics import _crown_hulls

    rng = np.random.default_rng(3)
    pts = _cone_tree(rng, 5.0, -3.0, n=5000)
    if shape == "flat":
        pts[:, 2] = 2.0
    elif shape == "line":
        pts = np.column_stack([np.linspace(0, 3, 50), np.linspace(1, 2, 50), np.full(50, 2.0)])
    elif shape == "tiny":
        pts = pts[:4]
    xy, xyz = _crown_hulls(pts)
    if shape in ("line", "tiny"):
        assert {tuple(p) for p in xy} >= {tuple(p) for p in pts[[0, -1], :2]}
        return
    assert ConvexHull(xy).volume == pytest.approx(ConvexHull(pts[:, :2]).volume, rel=1e-12)
    assert {tuple(p) for p in xy} == {tuple(p) for p in pts[ConvexHull(pts[:, :2]).vertices, :2]}
    if shape == "cone":
        assert ConvexHull(xyz).volume == pytest.approx(ConvexHull(pts).volume, rel=1e-12)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(-3, 70_000), max_size=60), st.booleans())
def test_group_runs_groups_labels_like_a_stable_sort_and_unique(labels, small):
    labels = np.asarray([v % 50 for v in labels] if small else labels, dtype=np.int64)
    order, uniq, start, counts = group_runs(labels)
    np.testing.assert_array_equal(order, np.argsort(labels, kind="stable"))
    want_u, want_s, want_c = np.unique(labels[order], return_index=True, return_counts=True)
    np.testing.assert_array_equal(uniq, want_u)
    np.testing.assert_array_equal(start, want_s)
    np.testing.assert_array_equal(counts, want_c)
    assert uniq.dtype == np.int64


@pytest.mark.parametrize("flat", ["plane", "line"])
def test_a_flat_part_of_a_crown_in_another_tile_keeps_its_hull(flat):
    # a tile holding only a flat (or collinear) part of a crown kept just its per-axis
    # extremes, so the merged crown volume came out short (9.18 instead of 9.48 m3)
    rng = np.random.default_rng(0)
    a = rng.uniform([0, 0, 1], [2, 2, 3], (2000, 3))
    if flat == "plane":
        b = np.c_[rng.uniform(2.0, 3.0, 40), rng.uniform(0, 2, 40), np.full(40, 3.0)]
    else:
        t = rng.uniform(0, 1, 40)
        b = np.c_[2.0 + t, 0.5 + t, 1.5 + t]
    both = np.r_[a, b]
    p = MetricsParams()
    whole = tree_partials(both, np.ones(len(both), np.int64), np.zeros(len(both), bool), np.zeros(1), params=p)
    parts = [tree_partials(x, np.ones(len(x), np.int64), np.zeros(len(x), bool), np.zeros(1), params=p) for x in (a, b)]
    merged = combine_partials(parts, [np.array([0, 1]), np.array([0, 1])])
    trunks, diam = np.zeros((1, 3)), np.array([np.nan])
    one, two = finalize_metrics(whole, trunks, diam), finalize_metrics(merged, trunks, diam)
    for key in ("crown_area_m2", "crown_volume_m3", "crown_diameter_m"):
        assert two[key][0] == pytest.approx(one[key][0], rel=1e-9), key


def _crown_diameter(xy: np.ndarray) -> float:
    xyz = np.c_[xy, np.full(len(xy), 2.0)]
    parts = tree_partials(xyz, np.ones(len(xy), np.int64), np.zeros(len(xy), bool), np.zeros(1), params=MetricsParams())
    return finalize_metrics(parts, np.zeros((1, 3)), np.array([np.nan]))["crown_diameter_m"][0]


def test_crown_diameter_is_the_average_of_the_longest_spread_and_the_one_across_it():
    a = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    turn = np.deg2rad(30)
    x, y = 2 * np.cos(a), np.sin(a)  # an ellipse 4 m x 2 m, turned by 30 degrees
    ellipse = np.c_[x * np.cos(turn) - y * np.sin(turn), x * np.sin(turn) + y * np.cos(turn)]
    assert _crown_diameter(ellipse) == pytest.approx(3.0, abs=1e-3)
    # a round crown 2 m across with one twig reaching 0.6 m past its rim: the twig adds
    # half its reach (the largest extent would read 2.6 m)
    disc = np.c_[np.cos(a), np.sin(a)]
    assert _crown_diameter(disc) == pytest.approx(2.0, abs=1e-3)
    assert _crown_diameter(np.r_[disc, [[1.6, 0.0]]]) == pytest.approx(2.3, abs=1e-3)


def _cloud(seed: int, shape: str, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if shape == "ball":
        p = rng.normal(size=(n, 3))
        p /= np.maximum(np.linalg.norm(p, axis=1), 1e-9)[:, None]
        p *= rng.random(n)[:, None] ** (1 / 3)
    elif shape == "shell":  # most points on the surface: many are vertices
        p = rng.normal(size=(n, 3))
        p /= np.maximum(np.linalg.norm(p, axis=1), 1e-9)[:, None]
        p[: n // 4] *= rng.random(n // 4)[:, None]
    elif shape == "box":
        p = rng.random((n, 3)) * [3.0, 1.2, 2.0]
    else:  # "lattice": coordinates on a 5 cm grid, many points sharing bins and faces
        p = np.round(rng.random((n, 3)) * [1.0, 0.6, 0.8] / 0.05) * 0.05
    return p * [1.5, 0.8, 1.0] + [500.0, 20.0, 3.0]


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), shape=st.sampled_from(["ball", "shell", "box", "lattice"]),
       n=st.integers(2_000, 6_000))
def test_hull_candidates_keep_every_vertex_and_the_hull(seed, shape, n):
    from scipy.spatial import ConvexHull

    from pipeline.metrics import _crown_hulls, _hull_candidates, _hull_vertices

    pts = _cloud(seed, shape, n)
    kept = _hull_candidates(pts)
    rows = pts.view([("", pts.dtype)] * 3).ravel()
    # a subset of the points, in their order, holding every vertex of the whole hull
    picked = np.isin(rows, kept.view([("", kept.dtype)] * 3).ravel())
    assert np.array_equal(kept, pts[picked]) if np.unique(rows).size == n else len(kept) <= picked.sum()
    vertices = pts[ConvexHull(pts).vertices]
    assert picked[ConvexHull(pts).vertices].all()
    whole = (_hull_vertices(vertices[:, :2]), vertices)
    got = _crown_hulls(pts)
    if np.unique(rows).size == n:  # the same vertices in the same order
        assert all(np.array_equal(a, b) for a, b in zip(got, whole))
    else:  # qhull keeps any one of a vertex's duplicates: the same vertices, in some order
        for a, b in zip(got, whole):
            assert sorted(map(tuple, a.tolist())) == sorted(map(tuple, b.tolist()))
    if shape in ("ball", "box"):
        assert len(kept) < 0.8 * n  # the filter does drop the inside


def test_hull_candidates_by_hand():
    from pipeline.metrics import _hull_candidates

    # a 16 x 16 x 16 lattice: its inner points are dropped, its 8 corners kept
    g = np.arange(16, dtype=float) * 0.1
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    kept = _hull_candidates(pts)
    corners = {(x, y, z) for x in (0.0, 1.5) for y in (0.0, 1.5) for z in (0.0, 1.5)}
    assert corners <= {tuple(np.round(r, 9)) for r in kept.tolist()}
    assert len(kept) < len(pts) // 2
    # an apex in the same height bin as the tops of the columns around it is a vertex:
    # only a point in a lower bin than theirs is surely below them
    rng = np.random.default_rng(2)
    box = np.column_stack([rng.random(20_000), rng.random(20_000), 1.0 - 0.5 * rng.random(20_000) ** 3])
    apex, tall = [0.5, 0.5, 1.0001], [0.0, 0.0, 2.0]  # the tall point widens the bins to 1/63.5 m
    kept = _hull_candidates(np.vstack([box, apex, tall]))
    assert any(np.array_equal(r, apex) for r in kept) and len(kept) < 10_000
    # flat (one height) or a single column: nothing is inside, everything is kept
    flat = pts.copy()
    flat[:, 2] = 1.0
    assert np.array_equal(_hull_candidates(flat), flat)
    assert len(_hull_candidates(pts[:1_999])) == 1_999  # too few points to filter
    # a long, thin crown would need a grid of many cells a point: it goes to qhull whole
    thin = np.column_stack([rng.random(5_000) * 50.0, rng.random(5_000) * 0.05, rng.random(5_000)])
    assert _hull_candidates(thin) is thin


@pytest.mark.parametrize("seed", [0, 1])
def test_partials_among_some_points_equal_partials_of_their_copies(seed):
    # a tile's core is picked by a mask (workers.tasks.summarise): the same partials, to
    # the bit, as of the core's points copied out
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([_cone_tree(rng, 0, 0), _cone_tree(rng, 3, 0.5), rng.uniform(-2, 5, (500, 3))])
    tid = np.r_[np.repeat([1, 2], 3000), np.zeros(500, np.int64)]
    wood = rng.uniform(size=len(xyz)) < 0.2
    among = xyz[:, 0] < 2.5  # cuts the second tree
    p, trunk_z = MetricsParams(), np.array([0.0, 0.1])
    a = tree_partials(xyz[among], tid[among], wood[among], trunk_z, params=p)
    b = tree_partials(xyz, tid, wood, trunk_z, params=p, among=among)
    for name in ("tree_id", "n_points", "n_wood", "z_max"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    for name in ("crown_xy", "crown_xyz"):
        assert len(getattr(a, name)) == len(getattr(b, name)) == 2
        for u, v in zip(getattr(a, name), getattr(b, name)):
            assert np.array_equal(u, v), name
