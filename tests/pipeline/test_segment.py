"""Segmentation kernels on hand-built node sets."""

import numpy as np

from pipeline.graph import build_graph
from pipeline.params import SegmentParams
from pipeline.segment import hard_surfaces, segment_nodes


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
    s = hard_surfaces(nodes, graph, planar, nodes[:, 2], min_nodes=40, margin=0.15, min_top=0.5)
    assert s[parts == 2].all()  # the roof
    assert not s[parts == 3].any()  # a small flat patch is foliage
    assert not s[parts == 4].any()  # grass is flat but low
    assert not s[parts == 0].any()  # the trunk stands 0.8 m away
    # the branch passes 0.1 m above the roof: inside the margin where it crosses it
    near = (parts == 1) & (nodes[:, 0] >= 0.8 - 1e-9)
    assert s[near].all() and not s[(parts == 1) & (nodes[:, 0] < 0.65)].any()
    assert not hard_surfaces(nodes, graph, planar, nodes[:, 2], min_nodes=0, margin=0.15, min_top=0.5).any()


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
