"""Young, dormant blocks with default settings: the size floors follow the block's trees.

Generated blocks use evaluation seeds (< 100; the floors and the branch test were set on
seeds 100-101); the real row is made of real trees scaled to a young tree's size
(``bench.real_data.young_row``).
"""

import numpy as np
import pytest

from bench.real_data import REAL, young_row
from simulator.scoring.scores import diameter_errors, score_labels
from pipeline.params import MATURE_FLOORS, PipelineParams, TrunkParams
from pipeline.process import process_points
from simulator.orchard import KIND
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard
from pipeline.floors import block_floors, branches

YOUNG = dict(form="young", rows=2, trees_per_row=8, spacing=1.0, row_spacing=3.5)


def _run(o):
    origin = np.floor(o.xyz.min(axis=0))
    return origin, process_points(o.xyz - origin, params=PipelineParams())


def _scored(o):
    """:func:`_run` with the block's true trunks in the run's frame and its scores."""
    origin, r = _run(o)
    truth = o.trunks[:, :2] - origin[:2]
    s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=truth,
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
    return origin, r, truth, s


def test_young_dormant_block_with_defaults():
    o = simulate_orchard(SimulationParams(seed=3, **YOUNG))
    assert not (o.kind == KIND.index("leaf")).any()  # dormant
    assert (o.kind == KIND.index("post")).sum() > 0  # the stakes (and the fence)
    origin, r = _run(o)
    s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks[:, :2] - origin[:2],
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
    assert s["trunk_f1"] >= 0.97, s
    assert s["v_measure"] >= 0.95, s
    # a stake as thick as the stem 6-12 cm beside each: the diameter is one section's
    # (not a circle through both, 0.07 m too wide)
    d = diameter_errors(o.trunks[:, :2] - origin[:2], 2.0 * o.trunk_radius, r.trunks[:, :2], r.trunk_diameter)
    assert d["trunk_diameter_n"] >= 14 and d["trunk_diameter_mae"] < 0.05, d


@pytest.mark.parametrize("options", [YOUNG, pytest.param(dict(form="young", rows=2, trees_per_row=10, spacing=2.0,
                                                               row_spacing=4.0), marks=pytest.mark.slow)])
def test_irrigation_risers_among_young_trees_are_no_trees(options):
    # a 0.3-1.0 m pipe by 30 % of the trees (0.15-0.4 m from the trunk) and in 30 % of the
    # gaps: every tree found where it stands, no riser taken for one
    p = SimulationParams(seed=0, risers=0.3, **options)
    o = simulate_orchard(p)
    origin, r, truth, s = _scored(o)
    assert s["trunk_f1"] == 1.0, s
    assert s["v_measure"] >= 0.95, s
    # one trunk by each tree (F1 matches within 1 m, more than a slot here): no riser
    # stands for a tree. A trunk may sit up to a third of a metre off its stem, toward a
    # riser (1 m spacing: one of 16, the stem circle at 0.3 m fitted across stem and riser)
    d = np.hypot(*(r.trunks[:, None, :2] - truth[None]).transpose(2, 0, 1))
    assert len(r.trunks) == len(truth) and len(set(d.argmin(axis=1).tolist())) == len(truth)
    assert d.min(axis=1).max() < 0.35
    assert np.median(d.min(axis=1)) < 0.1
    # and the risers alone, with the stakes and the fence, are no trees
    keep = o.tree_id == 0
    assert process_points(o.xyz[keep] - origin, params=PipelineParams()).n_trees == 0


@pytest.mark.slow
def test_irrigation_risers_among_grown_trees_are_no_trees():
    p = SimulationParams(form="vase", rows=2, trees_per_row=6, seed=1, risers=0.3)
    o = simulate_orchard(p)
    origin, r, truth, s = _scored(o)
    assert s["trunk_f1"] == 1.0, s
    assert s["v_measure"] >= 0.95, s


@pytest.mark.slow
def test_a_leafless_grown_block_with_defaults():
    # a vase block scanned in winter: the same trees, bare (no leaf to occlude or to join crowns)
    o = simulate_orchard(SimulationParams(form="vase", rows=2, trees_per_row=6, seed=2, leafless=True))
    assert not (o.kind == KIND.index("leaf")).any()
    origin, r = _run(o)
    s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks[:, :2] - origin[:2],
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
    assert s["trunk_f1"] == 1.0, s
    assert s["v_measure"] >= 0.95, s


def test_a_stem_is_as_wide_as_its_main_column_beside_a_riser():
    from pipeline.trunks import _main_column

    # group 0: a stem of four band nodes each carrying 100, a riser 0.3 m off carrying 150
    # of the tree's flow over two nodes; group 1: a lone stem
    xy = np.array([[0.0, 0.0], [0.05, 0.0], [0.0, 0.05], [0.05, 0.05], [0.3, 0.0], [0.3, 0.05], [5.0, 0.0]])
    group = np.array([0, 0, 0, 0, 0, 0, 1])
    flow = np.array([100.0, 100.0, 100.0, 100.0, 75.0, 75.0, 50.0])
    centre, width = _main_column(xy, group, flow, 3, 0.1)
    assert np.allclose(centre, [[0.0, 0.0], [5.0, 0.0], [0.0, 0.0]])
    assert width[0] == pytest.approx(2 * 0.05 + 0.1)  # half the flow within 5 cm of the heaviest node
    assert width[1] == pytest.approx(0.1) and width[2] == pytest.approx(0.1)  # one node; no band node
    # the flow's RMS spans both columns
    c = np.average(xy[:6], axis=0, weights=flow[:6])
    rms = np.sqrt(np.average(np.sum((xy[:6] - c) ** 2, axis=1), weights=flow[:6]))
    assert 2 * rms + 0.1 > 0.3


def test_posts_stakes_and_boxes_without_trees_are_no_trees():
    # a young block with its trees taken out: stakes, the fence with its wire, the vehicle and the bin
    o = simulate_orchard(SimulationParams(seed=4, **YOUNG))
    keep = o.tree_id == 0
    origin = np.floor(o.xyz.min(axis=0))
    r = process_points(o.xyz[keep] - origin, params=PipelineParams())
    assert r.n_trees == 0


def test_a_block_of_posts_without_trees_stops_with_a_clear_message(tmp_path):
    from dataclasses import replace

    from pipeline.errors import NoTreesError
    from simulator.truth import write_simulation
    from workers.job import run_job
    from workers.jobspec import JobSpec

    o = simulate_orchard(SimulationParams(seed=5, **YOUNG))
    keep = o.tree_id == 0
    posts = replace(o, xyz=o.xyz[keep], tree_id=o.tree_id[keep], is_wood=o.is_wood[keep], kind=o.kind[keep])
    las = tmp_path / "posts.laz"
    write_simulation(posts, str(las), str(tmp_path / "truth.parquet"))
    with pytest.raises(NoTreesError, match="no trees found .* posts, stakes"):
        run_job(JobSpec(str(las), str(tmp_path / "out")))
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.skipif(not (REAL / "AdTree").is_dir() or not (REAL / "aRchi").is_dir(), reason="../shared/data/real absent")
def test_real_trees_at_a_young_size_with_defaults():
    xyz, tid, bases = young_row(0)
    origin = np.floor(xyz.min(axis=0))
    r = process_points(xyz - origin, params=PipelineParams())
    s = score_labels(true_tree_id=tid, true_is_wood=np.zeros(len(tid), bool), true_trunks=bases[:, :2] - origin[:2],
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
    assert s["trunk_f1"] >= 0.95, s  # measured 1.00 (seeds 0, 1)
    assert s["v_measure"] >= 0.90, s  # measured 0.93


def test_floors_given_are_used_as_given_and_unset_ones_follow_the_block():
    p = TrunkParams(min_tree_height=1.2)
    assert p.needs_floors() and p.at_floors(0.8, 30).min_tree_height == 1.2
    assert p.at_floors(0.8, 30).min_canopy_voxels == 30
    assert TrunkParams().at_floors().min_tree_height == MATURE_FLOORS["min_tree_height"]
    # half the median height, a quarter of the median catchment, within [least, mature]
    top, support = np.array([1.6, 1.8, 2.0, 9.0]), np.array([100.0, 120.0, 140.0, 10.0])
    ok = np.array([True, True, True, False])
    assert block_floors(top, support, ok) == (0.9, 30)
    # a block of grown trees (median 2 m or more) keeps the mature floors
    assert block_floors(np.array([1.9, 2.1, 5.0]), np.array([4000.0] * 3), np.ones(3, bool)) == (None, None)
    # young trees a little over 2 m that drain little are young all the same
    assert block_floors(np.array([1.96, 2.17, 2.19]), np.array([112.0, 120.0, 124.0]), np.ones(3, bool)) == (1.085, 30)
    assert block_floors(np.array([0.5]), np.array([20.0]), np.array([True])) == (0.7, 20)
    assert block_floors(top, support, np.zeros(4, bool)) == (None, None)


def _column(x, y, z0, z1, step=0.1):
    z = np.arange(z0, z1, step)
    return np.c_[np.full_like(z, x), np.full_like(z, y), z]


def test_branch_test_by_hand():
    # group 0: a post with a wire at one height; group 1: a stem with two side shoots at
    # different heights; group 2: a stem with a stake 8 cm beside it
    post = np.r_[_column(0, 0, 0.1, 1.6), np.c_[np.arange(0.1, 1.5, 0.1), np.zeros(14), np.full(14, 1.0)]]
    s = np.linspace(0.1, 0.5, 5)
    tree = np.r_[_column(5, 0, 0.1, 1.8), np.c_[5 + s, np.zeros(5), 0.8 + s], np.c_[5 - s, np.zeros(5), 1.2 + 0.5 * s]]
    staked = np.r_[_column(10, 0, 0.1, 1.8), _column(10.08, 0, 0.1, 1.5)]
    nodes = np.r_[post, tree, staked]
    group = np.r_[np.zeros(len(post)), np.ones(len(tree)), np.full(len(staked), 2)].astype(np.int64)
    centre = np.array([[0.0, 0.0], [5.0, 0.0], [10.04, 0.0]])
    assert branches(nodes, nodes[:, 2], group, centre, 0.1).tolist() == [False, True, False]
    # group 3: a stake and a riser 0.3 m from it, each on its own ground contact; the
    # tree's side shoots drain down its stem
    pair = np.r_[_column(15, 0, 0.1, 1.8), _column(15.3, 0, 0.1, 1.0)]
    nodes = np.r_[nodes, pair]
    group = np.r_[group, np.full(len(pair), 3)]
    centre = np.r_[centre, [[15.0, 0.0]]]
    foot = np.where(group[:, None] == 3, nodes[:, :2], centre[group])  # each column drains to its own foot
    assert branches(nodes, nodes[:, 2], group, centre, 0.1).tolist() == [False, True, False, True]
    assert branches(nodes, nodes[:, 2], group, centre, 0.1, node_foot=foot).tolist() == [False, True, False, False]


def test_grass_carries_no_paths_beyond_a_trunks_foot():
    # a stem with a crown, standing in a strip of grass running 3 m out along x: without
    # the rule the grass joins the tree all along; with it, only at the stem's foot
    from pipeline.graph import build_graph
    from pipeline.params import SegmentParams
    from pipeline.process import _without_edges_within, grass_nodes
    from pipeline.segment import segment_nodes

    stem = _column(0, 0, 0.15, 2.0)
    crown = np.c_[np.linspace(-0.5, 0.5, 11), np.zeros(11), np.full(11, 2.0)]
    x = np.arange(0.1, 3.0, 0.1)
    grass = np.r_[np.c_[x, np.zeros_like(x), np.full_like(x, 0.15)], np.c_[x, np.full_like(x, 0.1), np.full_like(x, 0.18)]]
    nodes = np.r_[stem, crown, grass]
    height = nodes[:, 2]
    graph = build_graph(nodes, radius=0.15)
    params = SegmentParams()
    trunk = np.zeros((1, 2))
    on = dict(source_nodes=np.array([0]), source_trunk=np.array([0]), trunk_xy=trunk, node_height=height,
              params=params.at_spacing(None))
    is_grass = np.r_[np.zeros(len(stem) + len(crown), bool), np.ones(len(grass), bool)]
    plain = segment_nodes(nodes, graph, **on).node_tree
    assert (plain[is_grass] == 1).all()
    low = grass_nodes(nodes, height, trunk, params=params)
    assert not low[: len(stem)].any() and low[is_grass & (np.abs(nodes[:, 0]) > 0.55)].all()
    ruled = segment_nodes(nodes, _without_edges_within(graph, low), **on).node_tree
    assert (ruled[~is_grass] == 1).all()
    far = is_grass & (nodes[:, 0] > 1.0)
    assert (ruled[far] == 0).all() and (ruled[is_grass & (nodes[:, 0] < 0.45)] == 1).all()


def test_a_stem_of_its_own_is_never_a_neighbours_satellite():
    # two groups 1.5 m apart, one draining a quarter of the other: a satellite by
    # catchment, unless it stands on a stem of its own
    from pipeline.neighbours import accept as _accept, own_stems as _own_stems

    xy = np.array([[0.0, 0.0], [1.5, 0.0]])
    support = np.array([4000.0, 1000.0])
    stem = np.array([100.0, 50.0])
    ok = np.ones(2, bool)
    params = TrunkParams().at_floors().at_spacing(None)
    assert _accept(xy, support, stem, ok, np.zeros(2, bool), params)[0].tolist() == [True, False]
    own = np.array([True, True])
    assert _accept(xy, support, stem, ok, np.zeros(2, bool), params, own)[0].tolist() == [True, True]
    # the column: nodes within 0.25 m in every 0.25 m slice from 0.3 to 2.5 m
    bole = _column(1.5, 0.0, 0.05, 6.0)
    broken = np.r_[_column(0.0, 0.0, 0.05, 1.0), _column(0.0, 0.0, 1.6, 6.0)]
    nodes = np.r_[bole, broken]
    assert _own_stems(xy[::-1], nodes, nodes[:, 2]).tolist() == [True, False]


def test_a_cloud_of_random_points_is_no_block_of_young_trees():
    # the service tests' upload fixture: 20,000 points in a 10 m x 10 m x 3 m box. Its
    # contact groups branch everywhere, but their flow passes the contact band as a
    # curtain (0.75-0.82 m), not through stems
    xyz = np.random.default_rng(7).uniform([0, 0, 0], [10, 10, 3], (20_000, 3))
    assert process_points(xyz, params=PipelineParams()).n_trees == 0
    support = np.array([100.0, 110.0, 120.0])
    top = np.array([1.5, 1.6, 1.7])
    assert block_floors(top, support, np.ones(3, bool), np.array([0.2, 0.3, 0.6])) == (0.8, 28)
    assert block_floors(top, support, np.ones(3, bool), np.array([0.6, 0.8, 0.3])) == (None, None)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 2])
def test_a_block_of_mixed_ages_with_defaults(seed):
    # grown vase trees with a third of the slots replanted (0.3-0.5 times a grown tree):
    # the grown trees set the mature floors, the rows let the replants in (two rows of
    # six keep three grown trees each; replants at a row's end). On seed 2 the grown trees
    # stand 5 or 10 m apart in their rows and 6 m across: the rows must still be read
    # along the planting for their slots to open (before: 8 of 12 found)
    o = simulate_orchard(SimulationParams(form="vase", rows=2, trees_per_row=6, replants=0.3, seed=seed))
    origin, r = _run(o)
    s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=o.trunks[:, :2] - origin[:2],
                     pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks[:, :2])
    assert s["trunk_f1"] >= 0.95, s
    assert s["v_measure"] >= 0.95, s


def test_a_grown_block_with_replants_keeps_the_mature_floors():
    # most groups short (replants, crown fragments), most material in grown crowns
    top, support = np.array([1.2, 1.3, 1.4, 3.5, 3.6]), np.array([100.0, 120.0, 90.0, 5000.0, 6000.0])
    assert block_floors(top, support, np.ones(5, bool)) == (None, None)
    # trellis posts with their wires drain more than young trees, but far less than a crown
    top, support = np.array([1.5, 1.6, 1.7, 2.9, 2.9]), np.array([100.0, 110.0, 120.0, 300.0, 320.0])
    assert block_floors(top, support, np.ones(5, bool)) == (0.85, 30)


def test_young_trees_as_tall_as_the_height_floor_with_risers_keep_the_young_floors():
    """Each floor passed alone at the median, but by different groups (the tall ones drain
    little, the ones with a riser's column drain more): the mature floors would drop two
    thirds of them (young, 1 m x 3.5 m, a riser by every tree: tuning seed 107, 1 of 16)."""
    top = np.array([1.5, 1.6, 2.05, 2.1, 2.2, 2.3])
    support = np.array([300.0, 250.0, 100.0, 120.0, 130.0, 200.0])
    assert np.median(top) >= MATURE_FLOORS["min_tree_height"]
    assert np.median(support) >= MATURE_FLOORS["min_canopy_voxels"]
    assert block_floors(top, support, np.ones(6, bool)) == (1.0375, 41)
    # half of them passing both floors is a grown block
    support[2:4] = 400.0
    assert block_floors(top, support, np.ones(6, bool)) == (None, None)


def test_young_trees_among_trellis_posts_with_end_posts():
    """Posts every two gaps and one past each row's end (a gap from the last gap's post):
    a trellis among young trees, not tall spindles' leaders; the posts are cut out."""
    o = simulate_orchard(SimulationParams(seed=0, trellis=2, **YOUNG))
    _, r, _, s = _scored(o)
    assert s["trunk_f1"] >= 0.9, s  # 8 of 16 trees while the end posts kept every post in
