"""Segmentation kernels on hand-built node sets."""

import numpy as np
import pytest
from scipy.sparse import csgraph

from pipeline.graph import build_graph
from pipeline.params import SegmentParams
from pipeline.segment import (
    curved_patches,
    faces,
    flat_patches,
    hard_surfaces,
    planar_patches,
    segment_nodes,
    trunk_feet,
    tree_reach,
)


def _grid(x0, y0, z, n, step=0.1):
    g = np.arange(n) * step
    xx, yy = np.meshgrid(x0 + g, y0 + g, indexing="ij")
    return np.column_stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)])


def _scene():
    """A trunk with a branch reaching over a 1 m x 1 m roof, a small flat leaf patch and grass."""
    trunk = np.column_stack([np.zeros(20), np.zeros(20), np.arange(20) * 0.1])  # 0-1.9 m
    branch = np.column_stack([np.arange(1, 15) * 0.1, np.zeros(14), np.full(14, 1.9)])  # to x=1.4
    roof = _grid(0.8, -0.5, 1.8, 11)  # 121 nodes, its top 1.8 m; touches the branch
    leaf = _grid(-0.3, 1.0, 1.5, 3)  # 9 planar nodes
    grass = _grid(3.0, 3.0, 0.1, 11)  # 121 planar nodes, low
    nodes = np.vstack([trunk, branch, roof, leaf, grass])
    parts = np.repeat(np.arange(5), [len(trunk), len(branch), len(roof), len(leaf), len(grass)])
    planar = np.isin(parts, [2, 3, 4])
    return nodes, parts, planar


def test_large_raised_surfaces_and_their_margin_are_found():
    nodes, parts, planar = _scene()
    graph = build_graph(nodes, radius=0.15)
    patch, size = planar_patches(graph, planar)
    s = hard_surfaces(nodes, patch, size, nodes[:, 2], min_nodes=40, margin=0.15, min_top=0.5)
    assert s[parts == 2].all()  # the roof
    assert not s[parts == 3].any()  # a small flat patch is foliage
    assert not s[parts == 4].any()  # grass is flat but low
    assert not s[parts == 0].any()  # the trunk stands 0.8 m away
    # the branch passes 0.1 m above the roof: inside the margin where it crosses it
    near = (parts == 1) & (nodes[:, 0] >= 0.8 - 1e-9)
    assert s[near].all() and not s[(parts == 1) & (nodes[:, 0] < 0.65)].any()
    assert not hard_surfaces(nodes, patch, size, nodes[:, 2], min_nodes=0, margin=0.15, min_top=0.5).any()
    none = planar_patches(graph, np.zeros(len(nodes), bool))
    assert not hard_surfaces(nodes, *none, nodes[:, 2], min_nodes=40, margin=0.15, min_top=0.5).any()


def test_faces_are_large_connected_planar_patches_only():
    nodes, parts, planar = _scene()
    graph = build_graph(nodes, radius=0.15)
    patch, size = planar_patches(graph, planar)
    f = faces(patch, size, 10)
    assert f[parts == 2].all() and f[parts == 4].all()  # roof and grass: 121 nodes each
    assert not f[parts == 3].any()  # 9 connected planar nodes are no face
    assert not f[~planar].any()
    assert faces(patch, size, 9)[parts == 3].all()
    assert not faces(*planar_patches(graph, np.zeros(len(nodes), bool)), 10).any()


def test_planar_patches_split_where_the_normals_disagree():
    # a roof and a wall meeting at its edge: one patch by connection alone, two when
    # neighbours' normals must agree (a face does not run on into what touches it)
    roof = _grid(0.0, 0.0, 1.0, 5)  # 25 nodes, normal z
    wall = np.column_stack([np.full(20, 0.5), np.tile(np.arange(5) * 0.1, 4), np.repeat(0.9 - np.arange(4) * 0.1, 5)])
    nodes = np.vstack([roof, wall])
    normal = np.vstack([np.tile([0.0, 0.0, 1.0], (25, 1)), np.tile([1.0, 0.0, 0.0], (20, 1))])
    graph = build_graph(nodes, radius=0.15)
    planar = np.ones(len(nodes), bool)
    patch, size = planar_patches(graph, planar)
    assert len(size) == 1 and size[0] == 45
    patch, size = planar_patches(graph, planar, normal, 0.9)
    assert sorted(size.tolist()) == [20, 25]
    assert len(set(patch[:25])) == 1 and len(set(patch[25:])) == 1 and patch[0] != patch[-1]
    # sign of a normal is arbitrary: a flipped one still agrees
    flipped = normal.copy()
    flipped[::2] *= -1
    assert sorted(planar_patches(graph, planar, flipped, 0.9)[1].tolist()) == [20, 25]


def _arc(radius, degrees, centre=(0.0, 0.0), heights=np.arange(0.2, 0.8, 0.1), step=0.1):
    """Nodes on an upright cylinder's arc (about one per ``step`` of bark) and their normals."""
    t = np.linspace(-np.radians(degrees) / 2, np.radians(degrees) / 2, max(3, int(np.radians(degrees) * radius / step)))
    tt, zz = np.meshgrid(t, heights, indexing="ij")
    n = np.column_stack([np.cos(tt.ravel()), np.sin(tt.ravel()), np.zeros(tt.size)])
    return np.column_stack([centre[0] + radius * n[:, 0], centre[1] + radius * n[:, 1], zz.ravel()]), n


def _plate(corner, u, v, nu, nv, step=0.1):
    """Nodes on a flat rectangle from ``corner`` along unit vectors u, v, and its normals."""
    a, b = np.meshgrid(np.arange(nu) * step, np.arange(nv) * step, indexing="ij")
    p = np.asarray(corner) + a.ravel()[:, None] * np.asarray(u) + b.ravel()[:, None] * np.asarray(v)
    return p, np.tile(np.cross(u, v), (len(p), 1)).astype(float)


def test_curved_patches_are_bark_not_faces():
    rng = np.random.default_rng(0)
    kw = dict(min_nodes=10, min_spread=0.05, max_radius=0.75, max_residual=0.25)
    parts = {
        "thick trunk, r 0.4 m, half seen": _arc(0.4, 180),
        "thick trunk, r 0.3 m, a third seen": _arc(0.3, 120, centre=(3.0, 0.0)),
        "leaning trunk": None,
        "box face": _plate((6.0, 0.0, 0.2), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 12, 8),
        "box corner": None,
        "tank, r 2 m": _arc(2.0, 90, centre=(20.0, 0.0)),
        "small arc": _arc(0.4, 40, centre=(30.0, 0.0), heights=np.array([0.3, 0.4])),
    }
    # a trunk leaning 20 degrees: the arc rotated about the x axis
    p, n = _arc(0.4, 180, centre=(0.0, 0.0))
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    parts["leaning trunk"] = (p @ rot.T + [10.0, 0.0, 0.0], n @ rot.T)
    # two faces of a 1.2 m bin meeting at an edge
    a = _plate((14.0, 0.0, 0.2), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 12, 8)
    b = _plate((14.0, 0.1, 0.2), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), 12, 8)
    parts["box corner"] = (np.vstack([a[0], b[0]]), np.vstack([a[1], b[1]]))
    names = list(parts)
    nodes = np.vstack([parts[k][0] for k in names])
    normals = np.vstack([parts[k][1] for k in names])
    normals *= rng.choice([-1.0, 1.0], size=(len(normals), 1))  # a normal's sign is arbitrary
    nodes += rng.normal(0, 0.01, nodes.shape)
    patch = np.repeat(np.arange(len(names)), [len(parts[k][0]) for k in names])
    size = np.bincount(patch)
    curved = dict(zip(names, curved_patches(nodes, normals, patch, size, **kw)))
    assert curved == {
        "thick trunk, r 0.4 m, half seen": True,
        "thick trunk, r 0.3 m, a third seen": True,
        "leaning trunk": True,
        "box face": False,  # one normal direction
        "box corner": False,  # two directions, but the normal lines meet in no centre
        "tank, r 2 m": False,  # wider than max_radius
        "small arc": False,  # below min_nodes, not tested
    }, curved
    small = names.index("small arc")
    assert size[small] < 10 and (np.delete(size, small) >= 10).all()
    assert not curved_patches(nodes, normals, np.full(len(nodes), -1), np.zeros(0, np.int64), **kw).any()


def test_excluded_nodes_carry_no_paths_and_stay_unlabelled():
    nodes, parts, planar = _scene()
    graph = build_graph(nodes, radius=0.15)
    exclude = parts == 2
    kw = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=np.zeros((1, 2)),
              node_height=nodes[:, 2], params=SegmentParams(unreached_radius=0.0))
    free = segment_nodes(nodes, graph, **kw)
    assert (free.node_tree[parts == 2] == 1).all()  # without the exclusion the roof is "crown"
    cut = segment_nodes(nodes, graph, exclude=exclude, **kw)
    assert (cut.node_tree[exclude] == 0).all()
    assert not cut.reached[exclude].any()
    assert (cut.node_tree[parts == 0] == 1).all() and (cut.node_tree[parts == 1] == 1).all()
    # the trunk's seed is never excluded
    also_seed = exclude.copy()
    also_seed[0] = True
    assert segment_nodes(nodes, graph, exclude=also_seed, **kw).node_tree[0] == 1


def test_lone_fragments_join_a_tree_only_when_they_float_right_beside_it():
    trunk = np.column_stack([np.zeros(20), np.zeros(20), np.arange(20) * 0.1])  # 0-1.9 m
    rim = [0.25, 0.0, 1.9]  # a lone leaf 0.25 m from the crown (no edge: radius 0.15)
    far = [1.5, 0.0, 1.9]  # an outlier in the air
    low = [0.25, 0.0, 0.2]  # a lone grass tuft beside the trunk
    pair = [[0.0, 0.6, 1.0], [0.0, 0.7, 1.0]]  # a two-node floating fragment 0.6 m away
    nodes = np.vstack([trunk, rim, far, low, pair])
    graph = build_graph(nodes, radius=0.15)
    kw = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=np.zeros((1, 2)), node_height=nodes[:, 2])
    tree = segment_nodes(nodes, graph, params=SegmentParams(fragment_reach=0.3), **kw).node_tree
    assert (tree[:20] == 1).all()
    assert tree[20] == 1  # the rim leaf joins
    assert tree[21] == 0 and tree[22] == 0  # the outlier and the low tuft stay unlabelled
    assert (tree[23:] == 0).all()  # small fragments beyond fragment_reach are outliers
    tree = segment_nodes(nodes, graph, params=SegmentParams(fragment_reach=0.0), **kw).node_tree
    assert tree[20] == 0  # 0 switches the rule off
    tree = segment_nodes(nodes, graph, params=SegmentParams(min_fragment=2, fragment_reach=0.0), **kw).node_tree
    assert (tree[23:] == 1).all()  # a fragment of min_fragment nodes is canopy, labelled by distance



def test_a_chain_of_lone_leaves_joins_link_by_link_but_not_across_a_gap():
    trunk = np.column_stack([np.zeros(20), np.zeros(20), np.arange(20) * 0.1])  # 0-1.9 m
    chain = np.column_stack([0.25 * np.arange(1, 7), np.zeros(6), np.full(6, 1.9)])  # 0.25 m apart, to x = 1.5
    beyond = [[1.5 + 0.45, 0.0, 1.9]]  # 0.45 m past the chain's end
    grass = np.column_stack([0.25 * np.arange(1, 5), np.zeros(4), np.full(4, 0.2)])  # lone tufts on the ground
    nodes = np.vstack([trunk, chain, beyond, grass])
    graph = build_graph(nodes, radius=0.15)
    assert graph[20:].nnz == 0  # every leaf and tuft is its own fragment
    kw = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=np.zeros((1, 2)), node_height=nodes[:, 2])
    tree = segment_nodes(nodes, graph, params=SegmentParams(fragment_reach=0.3), **kw).node_tree
    assert (tree[20:26] == 1).all()  # 1.5 m of sparse rim, one fragment_reach at a time
    assert tree[26] == 0  # an outlier past the rim's end
    assert (tree[27:] == 0).all()  # tufts on the ground do not chain (only the first is within reach: too low)
    tree = segment_nodes(nodes, graph, params=SegmentParams(fragment_reach=0.3, max_crown_radius=1.1), **kw).node_tree
    assert (tree[20:24] == 1).all() and (tree[24:26] == 0).all()  # never past the crown radius


def test_a_floating_fragment_goes_whole_to_the_tree_most_of_its_nodes_are_nearest():
    def tree_at(x0, sign):
        trunk = np.column_stack([np.full(21, x0), np.zeros(21), np.linspace(0.0, 2.0, 21)])
        limb = np.column_stack([x0 + sign * np.arange(1, 10) * 0.1, np.zeros(9), np.full(9, 2.0)])  # tip 0.9 m out
        return np.vstack([trunk, limb])

    # a floating piece of limb between the tips (0.9 and 2.1): four nodes nearer tree 1, three nearer tree 2
    piece = np.column_stack([1.15 + np.arange(7) * 0.1, np.zeros(7), np.full(7, 2.0)])
    # and an isolated cluster of three nodes 4 m off the row, floating as high
    far = np.column_stack([1.4 + np.arange(3) * 0.1, np.full(3, 4.0), np.full(3, 2.0)])
    nodes = np.vstack([tree_at(0.0, 1), tree_at(3.0, -1), piece, far])
    graph = build_graph(nodes, radius=0.15)
    assert csgraph.connected_components(graph, directed=False)[0] == 4  # the piece is reached by no search
    kw = dict(source_nodes=np.array([0, 30]), source_trunk=np.array([0, 1]), trunk_xy=np.array([[0.0, 0.0], [3.0, 0.0]]),
              node_height=nodes[:, 2], params=SegmentParams())
    seg = segment_nodes(nodes, graph, **kw)
    assert (seg.node_tree[:30] == 1).all() and (seg.node_tree[30:60] == 2).all()
    assert not seg.reached[60:].any()
    assert (seg.node_tree[60:67] == 1).all()  # not split at the midpoint between the tips
    assert (seg.node_tree[67:] == 0).all()  # the far cluster joins no tree


def _hedge_tree_and_wire(arm: float):
    """A trunk (0-1.9 m) with four limbs ``arm`` m long at 1.5 m; a fence wire (1.0 m high,
    1.5 m long, 15 nodes, touching nothing) 3 m to one side, along the row; and a tuft of
    the crown (5 nodes at 1.8 m) floating 1.4 m from the trunk on the other side."""
    trunk = np.column_stack([np.zeros(20), np.zeros(20), np.arange(20) * 0.1])
    r = np.arange(1, int(round(arm * 10)) + 1) * 0.1
    limbs = np.vstack([np.column_stack([sx * r if ax == 0 else 0 * r, sx * r if ax == 1 else 0 * r, np.full(r.size, 1.5)])
                       for ax in (0, 1) for sx in (-1, 1)])
    wire = np.column_stack([np.arange(15) * 0.1 - 1.0, np.full(15, -3.0), np.full(15, 1.0)])
    tuft = np.column_stack([np.full(5, 0.1), 1.4 + np.arange(5) * 0.1, np.full(5, 1.8)])
    nodes = np.vstack([trunk, limbs, wire, tuft])
    part = np.repeat(np.arange(4), [len(trunk), len(limbs), len(wire), len(tuft)])
    return nodes, part


def test_a_wire_beside_a_row_end_does_not_join_the_tree_its_crown_fragments_do():
    kw = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=np.zeros((1, 2)))
    nodes, part = _hedge_tree_and_wire(arm=1.0)
    graph = build_graph(nodes, radius=0.15)
    assert csgraph.connected_components(graph)[0] == 3  # the tree, the wire, the tuft
    tree = segment_nodes(nodes, graph, node_height=nodes[:, 2], params=SegmentParams(), **kw).node_tree
    assert (tree[part <= 1] == 1).all()
    assert (tree[part == 2] == 0).all()  # 3 m off: three times as far as the crown reaches
    assert (tree[part == 3] == 1).all()  # the crown's own tuft joins, beyond the reached crown
    # a crown that reaches 1.6 m takes floating material out to 3.2 m: the rule is relative
    nodes, part = _hedge_tree_and_wire(arm=1.6)
    tree = segment_nodes(nodes, build_graph(nodes, radius=0.15), node_height=nodes[:, 2], params=SegmentParams(), **kw).node_tree
    assert (tree[part == 2] == 1).all()


def _trunk_on_ground(radius=0.1, noise=0.0, seed=0):
    """A vertical trunk (circle of ``radius`` at the origin, 0-0.6 m) standing on a flat ground grid."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, 3000)
    z = rng.uniform(0.0, 0.6, 3000)
    trunk = np.column_stack([radius * np.cos(a), radius * np.sin(a), z])
    g = np.arange(-1.0, 1.0001, 0.02)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    ground = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    xyz = np.vstack([trunk, ground])
    xyz += rng.normal(0.0, noise, xyz.shape)
    is_trunk = np.r_[np.ones(len(trunk), bool), np.zeros(len(ground), bool)]
    height = xyz[:, 2]
    is_ground = height < 0.12
    tree_id = np.where(is_trunk & ~is_ground, 1, 0)
    return xyz, is_trunk, is_ground, height, tree_id


def test_trunk_feet_are_the_ground_points_inside_the_trunk_circle():
    xyz, is_trunk, is_ground, height, tree_id = _trunk_on_ground()
    idx, src = trunk_feet(xyz, tree_id, is_ground, height, np.array([[0.02, -0.01]]), ground_top=0.12, margin=0.03,
                          max_radius=0.5)
    got = np.zeros(len(xyz), bool)
    got[idx] = True
    assert got[is_trunk & is_ground].all()  # the whole bottom of the trunk comes back
    r = np.hypot(xyz[:, 0], xyz[:, 1])
    assert (r[got] <= 0.13 + 1e-6).all()  # nothing beyond circle + margin
    assert got[~is_trunk & (r < 0.1)].all()  # ground points inside the trunk are the trunk
    assert not got[~is_trunk & (r > 0.131)].any()
    assert (tree_id[src] == 1).all() and (height[src] >= 0.12).all()
    # the source is the nearest slice point: on the bark, right above a foot point of the bark
    bark = is_trunk[idx]
    assert np.percentile(np.hypot(*(xyz[idx[bark], :2] - xyz[src[bark], :2]).T), 90) < 0.03


def test_trunk_feet_need_a_plausible_trunk():
    xyz, _, is_ground, height, tree_id = _trunk_on_ground()
    empty = np.zeros(0, np.int64)
    kw = dict(ground_top=0.12, margin=0.03)
    at = dict(kw, max_radius=0.5)
    assert trunk_feet(xyz, tree_id, is_ground, height, np.zeros((0, 2)), **at)[0].size == 0  # no trunks
    assert trunk_feet(xyz, np.zeros_like(tree_id), is_ground, height, np.zeros((1, 2)), **at)[0].size == 0
    # the trunk is 2 m from where its tree's trunk was detected: not its foot
    assert trunk_feet(xyz, tree_id, is_ground, height, np.array([[2.0, 0.0]]), **at)[0].size == 0
    # a wide ring (a 1.5 m hedge skirt) is no trunk: radius above max_radius
    wide = xyz.copy()
    wide[tree_id == 1, :2] *= 15.0
    far_ok = trunk_feet(wide, tree_id, is_ground, height, np.zeros((1, 2)), max_radius=2.0, **kw)[0]
    assert far_ok.size > 0  # allowed when max_radius allows it
    assert np.array_equal(trunk_feet(wide, tree_id, is_ground, height, np.zeros((1, 2)), **at)[0], empty)


def _tree_with_limb(height, limb=7.0):
    """A stem ``height`` m tall at the origin with a limb along x at 2 m, ``limb`` m long (0.1 m nodes)."""
    stem = np.column_stack([np.zeros(int(height * 10)), np.zeros(int(height * 10)), np.arange(int(height * 10)) * 0.1])
    arm = np.column_stack([np.arange(1, int(limb * 10) + 1) * 0.1, np.zeros(int(limb * 10)), np.full(int(limb * 10), 2.0)])
    return np.vstack([stem, arm])


def test_a_tall_tree_reaches_as_far_as_it_is_tall_a_short_one_its_crown_radius():
    kw = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=np.zeros((1, 2)))
    wide = SegmentParams(max_crown_radius=9.0)
    for height, reach in ((3.0, 5.0), (8.0, 8.0), (12.0, 9.0)):  # crown_radius 5, x height, up to max_crown_radius 9
        nodes = _tree_with_limb(height, limb=10.0)
        graph = build_graph(nodes, radius=0.15)
        tree = segment_nodes(nodes, graph, node_height=nodes[:, 2], params=wide, **kw).node_tree
        x = nodes[:, 0]
        assert (tree[x <= reach - 0.05] == 1).all() and (tree[x > reach + 0.05] == 0).all(), height
    nodes = _tree_with_limb(8.0)
    graph = build_graph(nodes, radius=0.15)
    # max_crown_radius is a cap whatever the height (it sets the tile buffer) ...
    tree = segment_nodes(nodes, graph, node_height=nodes[:, 2], params=SegmentParams(max_crown_radius=3.0), **kw).node_tree
    assert (tree[nodes[:, 0] > 3.05] == 0).all() and (tree[nodes[:, 0] <= 2.95] == 1).all()
    # ... by default 5 m, as crown_radius ...
    tree = segment_nodes(nodes, graph, node_height=nodes[:, 2], params=SegmentParams(), **kw).node_tree
    assert (tree[nodes[:, 0] > 5.05] == 0).all() and (tree[nodes[:, 0] <= 4.95] == 1).all()
    # ... and crown_per_height 0 keeps every tree at crown_radius
    wide0 = SegmentParams(max_crown_radius=9.0, crown_per_height=0.0)
    tree = segment_nodes(nodes, graph, node_height=nodes[:, 2], params=wide0, **kw).node_tree
    assert (tree[nodes[:, 0] > 5.05] == 0).all() and (tree[nodes[:, 0] <= 4.95] == 1).all()


def test_tree_reach_reads_the_height_beside_the_trunk_only():
    nodes = np.vstack([_tree_with_limb(3.0, limb=3.0), [[2.0, 0.0, 12.0]]])  # a tall node 2 m away: not this tree's height
    got = tree_reach(nodes, nodes[:, 2], np.array([[0.0, 0.0], [2.0, 0.0]]), params=SegmentParams(crown_radius=1.0, max_crown_radius=9.0))
    assert got == pytest.approx([2.9, 9.0])  # 2.9 m stem; the other trunk's 12 m column, capped at 9 m
def test_flat_patches_point_one_way():
    # a face (normals parallel, signs mixed), a thick trunk's bark (normals turning around
    # its axis) and a ball's envelope (every way): only the face is flat
    face = np.tile([0.0, 1.0, 0.0], (30, 1))
    face[::3] *= -1
    _, bark = _arc(0.4, 360)
    u = np.random.default_rng(0).normal(size=(50, 3))
    ball = u / np.linalg.norm(u, axis=1)[:, None]
    normals = np.vstack([face, bark, ball])
    patch = np.repeat([0, 1, 2], [len(face), len(bark), len(ball)])
    size = np.bincount(patch)
    assert flat_patches(normals, patch, size, min_align=0.9).tolist() == [True, False, False]
    # a patch in two faces at right angles turns one way half the time
    corner = np.vstack([np.tile([1.0, 0, 0], (10, 1)), np.tile([0, 0, 1.0], (10, 1))])
    assert not flat_patches(corner, np.zeros(20, np.int64), np.array([20]), min_align=0.9)[0]
    assert flat_patches(corner, np.zeros(20, np.int64), np.array([20]), min_align=0.5)[0]
    none = flat_patches(normals, np.full(len(normals), -1), np.zeros(0, np.int64), min_align=0.9)
    assert none.shape == (0,)


def test_trunk_feet_of_a_thin_and_a_thick_trunk_each_within_its_own_circle():
    # the ground points are looked up at the thick trunk's reach: the thin one's feet
    # stay within its own circle
    thin, thin_trunk, _, _, thin_id = _trunk_on_ground(radius=0.05, seed=1)
    thick, thick_trunk, _, _, thick_id = _trunk_on_ground(radius=0.2, seed=2)
    thick = thick + np.array([3.0, 0.0, 0.0])
    xyz = np.vstack([thin, thick])
    height = xyz[:, 2]
    is_ground = height < 0.12
    tree_id = np.r_[thin_id, 2 * thick_id]
    idx, src = trunk_feet(xyz, tree_id, is_ground, height, np.array([[0.0, 0.0], [3.0, 0.0]]), ground_top=0.12,
                          margin=0.03, max_radius=0.5)
    for t, centre, r in ((1, (0.0, 0.0), 0.05), (2, (3.0, 0.0), 0.2)):
        mine = idx[tree_id[src] == t]
        d = np.hypot(xyz[mine, 0] - centre[0], xyz[mine, 1] - centre[1])
        assert mine.size and (d <= r + 0.03 + 0.01).all()
        on_ground = np.flatnonzero(is_ground & (np.hypot(xyz[:, 0] - centre[0], xyz[:, 1] - centre[1]) < r - 0.02))
        assert np.isin(on_ground, mine).all()
