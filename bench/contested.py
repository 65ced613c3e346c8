"""Where the segmentation's wrong points lie, and whether a learned model of contested nodes fixes them.

    python -m bench.contested [--seeds 2] [--train-seeds 2] [--margin 1.0]

Issue 61, deliverable 2. On generated blocks of the settings of ``bench.segmentation``
(evaluation seeds 0..N-1) and on the row of real AdTree trees, it runs the pipeline with
the shortest-path labels (the refinement's inputs are recorded and left unchanged) and
prints two Markdown tables.

The first says what the wrong points are. Each found tree stands for the true tree most
of its points belong to; a tree point is *wrong* when its found tree stands for another
one. Per block: the share of tree points that are wrong, and the share of those lying in
*wrong nodes* (graph nodes given to a tree that does not stand for their points'
majority; the rest are minority points of a node). Of the majority points of the wrong
nodes: the share that are wood, twig and leaf (the simulator's kinds); the share in
*runs* of at least ``RUN_NODES`` nodes (a run: wrong nodes joined by graph edges, given
to the same tree and truly of the same tree) and in runs holding wood; where they lie
between the two trunks (their horizontal distance to the trunk of their true tree over
that plus the distance to the trunk of the tree they were given: 0.5 is the midpoint;
10th, 50th and 90th percentile); the share
contested at the refinement's margin (0.2 m) and at ``--margin`` (with the share of all
tree points contested there); the share *entered* from the shortest-path forest at a
subtree of at least ``RUN_NODES`` wrong nodes (an entry: a wrong node whose forest
parent is not wrong), and the entries per run; and the share that a search over only the
edges joining nodes of one true tree reaches from a trunk, with the median ratio of that
search's path to the shortest path. Last, the v-measure of the tree points with the
shortest paths' node labels, and with every wrong node given to the found tree that
stands for its majority: the most any relabelling of these nodes can reach.

The second is a learned model of the contested nodes (at ``--margin``): logistic
regression and gradient-boosted depth-2 trees (numpy only), over per-node features
(``FEATURES``), fitted on seeds 1000.. of ``TRAIN`` (each block weighted alike) to tell
whether the rival tree is the right one, then applied to the evaluation blocks. Beside
them a branch-level rule, the *subtree vote*: each subtree of contested nodes in the
shortest-path forest moves to the rival as a whole when the random walk over the
contested nodes moves most of its points. The table gives the share of the contested
points each rule gets right (shortest paths, the walk, the vote, the two models), and
the v-measure of the tree points with the graph nodes' labels mapped to points (trunk
feet and post foliage left out, so these are a little below ``bench.segmentation``'s)
for shortest paths, the shipped refinement (the walk at 0.2 m), the vote and the two
models. The real row has no wood, twig or leaf labels; its models are the ones
fitted on generated blocks.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from unittest import mock

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

import pipeline.segment
from bench.segmentation import SETTINGS
from pipeline.params import PipelineParams
from pipeline.process import analyse_nodes
from pipeline.refine import contested_nodes, random_walk, refine_contested, rival_distance
from simulator.orchard import LEAF, TWIG, WOOD
from simulator.scoring.scores import v_measure
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

#: a run or a forest entry this many graph nodes or more is a whole branch, fewer is fringe
RUN_NODES = 20
#: the refinement's default margin [m]
SHIPPED_MARGIN = 0.2
#: settings the models are fitted on (seeds 1000..), names in bench.segmentation.SETTINGS
TRAIN = ("paper setting", "high density", "spindle 1.0 m", "hedge 1.2 m")
#: settings evaluated (seeds 0..N-1)
EVALUATE = ("paper setting", "high density", "hedge 1.2 m", "hedge 1.5 m", "spindle 1.0 m")
FEATURES = (
    "rival path gap / trunk spacing", "rival path gap / own path", "horizontal distance to own trunk / to both",
    "own path / straight distance", "rival path / straight distance", "their difference", "walk chooses the rival",
    "neighbours of own tree", "neighbours of the rival", "height / trunk spacing", "linearity", "scattering",
    "own path / trunk spacing",
)
"""Per-node features of a contested node (the trunk spacing: the two trunks' distance)."""


@dataclass(frozen=True)
class Block:
    """One block at the node level, with the truth.

    ``node_tree`` and ``dist`` are the shortest-path labels and lengths the refinement
    was given, ``final`` the labels after the unreached nodes were labelled (what
    ``method = "paths"`` returns); ``node_true`` (m, K) the true tree's points per node.
    """

    nodes: np.ndarray
    graph: sparse.csr_matrix
    node_tree: np.ndarray
    dist: np.ndarray
    final: np.ndarray
    pred: np.ndarray
    source_nodes: np.ndarray
    trunk_xy: np.ndarray
    node_height: np.ndarray
    linearity: np.ndarray
    scattering: np.ndarray
    point_node: np.ndarray
    point_true: np.ndarray
    point_kind: np.ndarray | None
    node_true: np.ndarray
    tree_points: int


def recorded_block(xyz: np.ndarray, tree_id: np.ndarray, kind: np.ndarray | None) -> Block:
    """Analyse ``xyz`` with the refinement replaced by a recorder of its inputs."""
    rec: dict = {}

    def record(graph, node_tree, dist, *, margin):
        rec.update(graph=graph.tocsr(), node_tree=node_tree.copy(), dist=dist.copy())
        return node_tree

    with mock.patch.object(pipeline.segment, "refine_contested", record):
        a = analyse_nodes(xyz, params=PipelineParams())
    pv, veg = a.vox.point_voxel, a.veg_idx
    t = tree_id[veg]
    node_true = sparse.csr_matrix((np.ones(pv.size), (pv, t)), shape=(a.vox.n, int(tree_id.max()) + 1)).toarray()
    return Block(a.vox.centroids, rec["graph"], rec["node_tree"], rec["dist"], a.segmentation.node_tree,
                 a.segmentation.paths.pred, a.trunks.source_nodes, a.trunks.xy, a.node_height,
                 a.features.linearity, a.features.scattering, pv, t, None if kind is None else kind[veg], node_true,
                 int((tree_id > 0).sum()))


def generated_block(setting: str, seed: int) -> Block:
    """A block of ``bench.segmentation.SETTINGS[setting]`` (the first setting whose name holds it)."""
    sim = next(v for k, v in SETTINGS.items() if setting in k)
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    return recorded_block(o.xyz - np.floor(o.xyz.min(axis=0)), o.tree_id, o.kind)


def stands_for(b: Block) -> np.ndarray:
    """True tree each found tree stands for (by its points' majority), (k+1,); -1 for 0."""
    k = int(b.final.max()) + 1
    counts = np.zeros((k, b.node_true.shape[1]))
    np.add.at(counts, (b.final[b.point_node], b.point_true), 1)
    out = counts.argmax(axis=1)
    out[0] = -1
    return out


def node_v_measure(b: Block, node_tree: np.ndarray) -> float:
    """V-measure of the tree points with these node labels (the recorded nodes only changed)."""
    lab = np.where(b.node_tree > 0, node_tree, b.final)
    tree = b.point_true > 0
    return v_measure(b.point_true[tree], lab[b.point_node][tree])


def diagnose(b: Block, margin: float) -> dict[str, float]:
    """The first table's figures for one block (see the module docstring)."""
    stands = stands_for(b)
    major = b.node_true.argmax(axis=1)
    m = major.size
    wrong = (b.final > 0) & (major > 0) & (stands[b.final] != major)
    wrong_pts = b.node_true[np.arange(m), major] * wrong
    total = wrong_pts.sum()
    pt_tree = b.final[b.point_node]
    pt_wrong_any = (b.point_true > 0) & (pt_tree > 0) & (stands[pt_tree] != b.point_true)
    out = {"wrong": pt_wrong_any.sum() / b.tree_points, "in wrong nodes": total / max(pt_wrong_any.sum(), 1)}
    if b.point_kind is not None:
        pt_wrong = wrong[b.point_node] & (b.point_true == major[b.point_node])
        for name, k in (("wood", WOOD), ("twig", TWIG), ("leaf", LEAF)):
            out[name] = float((pt_wrong & (b.point_kind == k)).sum() / max(pt_wrong.sum(), 1))
        wood_node = np.bincount(b.point_node, weights=pt_wrong & (b.point_kind == WOOD), minlength=m) > 0
    else:
        wood_node = np.zeros(m, bool)
    g = b.graph.tocoo()
    i, j = g.row, g.col
    same = wrong[i] & wrong[j] & (b.final[i] == b.final[j]) & (major[i] == major[j])
    _, run = csgraph.connected_components(sparse.csr_matrix((np.ones(same.sum()), (i[same], j[same])), shape=(m, m)),
                                          directed=False)
    run_nodes = np.bincount(run[wrong], minlength=m)
    run_wood = np.bincount(run[wood_node & wrong], minlength=m) > 0
    out["in runs"] = wrong_pts[run_nodes[run] >= RUN_NODES].sum() / max(total, 1)
    out["in runs with wood"] = wrong_pts[run_wood[run]].sum() / max(total, 1)
    # where they lie between the two trunks: the found tree standing for their true tree, and theirs
    own_tree = np.zeros(b.node_true.shape[1], np.int64)
    own_tree[stands[1:]] = np.arange(1, stands.size)
    at = np.flatnonzero(wrong & (own_tree[major] > 0))
    d_own = np.hypot(*(b.nodes[at, :2] - b.trunk_xy[own_tree[major[at]] - 1]).T)
    d_given = np.hypot(*(b.nodes[at, :2] - b.trunk_xy[b.final[at] - 1]).T)
    ratio = d_own / np.maximum(d_own + d_given, 1e-9)
    out["between trunks"] = _weighted_quantiles(ratio, wrong_pts[at], (0.1, 0.5, 0.9))
    fixed = b.final.copy()
    fixed[at] = own_tree[major[at]]
    tree = b.point_true > 0
    out["v paths"] = v_measure(b.point_true[tree], b.final[b.point_node][tree])
    out["v fixed"] = v_measure(b.point_true[tree], fixed[b.point_node][tree])
    rd, _ = rival_distance(b.graph, b.node_tree, b.dist)
    for name, mg in (("shipped", SHIPPED_MARGIN), ("margin", margin)):
        c = contested_nodes(b.node_tree, b.dist, rd, margin=mg)
        out[f"contested {name}"] = wrong_pts[c].sum() / max(total, 1)
        out[f"contested {name} share"] = b.node_true[c, 1:].sum() / b.tree_points
    # entries into wrong subtrees of the shortest-path forest, and their sizes
    parent = np.where(b.pred >= 0, b.pred, np.arange(m))
    entry = np.where(wrong & wrong[parent] & (parent != np.arange(m)), parent, np.arange(m))
    for _ in range(int(np.ceil(np.log2(max(m, 2)))) + 1):  # pointer doubling to each wrong node's entry
        entry = entry[entry]
    entry_nodes = np.bincount(entry[wrong], minlength=m)
    out["entered in subtrees"] = wrong_pts[wrong & (entry_nodes[entry] >= RUN_NODES)].sum() / max(total, 1)
    out["entries per run"] = (wrong & (entry == np.arange(m))).sum() / max(np.unique(run[wrong]).size, 1)
    # reach over edges inside one true tree: does the right tree connect to them at all?
    inside = (major[i] == major[j]) & (major[i] > 0)
    own = csgraph.dijkstra(sparse.csr_matrix((g.data[inside], (i[inside], j[inside])), shape=(m, m)),
                           indices=b.source_nodes, min_only=True)
    reach = wrong & np.isfinite(own) & np.isfinite(b.dist) & (b.dist > 0)
    out["reached inside own tree"] = wrong_pts[reach].sum() / max(total, 1)
    out["detour"] = float(np.median(own[reach] / b.dist[reach])) if reach.any() else float("nan")
    return out


def _weighted_quantiles(x: np.ndarray, w: np.ndarray, q: tuple[float, ...]) -> np.ndarray:
    if x.size == 0:
        return np.full(len(q), np.nan)
    order = np.argsort(x)
    cum = np.cumsum(w[order]) / w.sum()
    return x[order][np.minimum(np.searchsorted(cum, q), x.size - 1)]


def contested_features(b: Block, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Contested nodes at ``margin`` [m], their rival tree, features (c, len(FEATURES)) and the walk's labels."""
    rd, rival = rival_distance(b.graph, b.node_tree, b.dist)
    c = contested_nodes(b.node_tree, b.dist, rd, margin=margin)
    idx = np.flatnonzero(c)
    own_xy, riv_xy = b.trunk_xy[b.node_tree[idx] - 1], b.trunk_xy[rival[idx] - 1]
    spacing = np.maximum(np.hypot(*(own_xy - riv_xy).T), 0.3)
    d_own = np.hypot(*(b.nodes[idx, :2] - own_xy).T)
    d_riv = np.hypot(*(b.nodes[idx, :2] - riv_xy).T)
    h = b.node_height[idx]
    dist, gap = b.dist[idx], rd[idx] - b.dist[idx]
    tort_own = dist / np.maximum(np.hypot(d_own, h), 0.1)
    tort_riv = rd[idx] / np.maximum(np.hypot(d_riv, h), 0.1)
    walk = random_walk(b.graph, b.node_tree, c)
    nb = b.graph[idx].tocoo()
    deg = np.maximum(np.bincount(nb.row, minlength=idx.size), 1)
    nb_tree = b.node_tree[nb.col]
    nb_own = np.bincount(nb.row, weights=nb_tree == b.node_tree[idx][nb.row], minlength=idx.size) / deg
    nb_riv = np.bincount(nb.row, weights=nb_tree == rival[idx][nb.row], minlength=idx.size) / deg
    x = np.column_stack([gap / spacing, gap / np.maximum(dist, 0.1), d_own / np.maximum(d_own + d_riv, 1e-9), tort_own,
                         tort_riv, tort_own - tort_riv, walk[idx] == rival[idx], nb_own, nb_riv, h / spacing,
                         b.linearity[idx], b.scattering[idx], dist / spacing])
    return idx, rival[idx], x.astype(np.float64), walk


def fit_logistic(x: np.ndarray, y: np.ndarray, w: np.ndarray, *, l2: float = 1e-3, steps: int = 25) -> tuple:
    """Weighted logistic regression by Newton steps on standardised features: (beta, mean, sd)."""
    mean, sd = x.mean(axis=0), x.std(axis=0) + 1e-9
    z = np.column_stack([(x - mean) / sd, np.ones(len(x))])
    w = w / w.sum()
    beta = np.zeros(z.shape[1])
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-z @ beta))
        grad = z.T @ (w * (p - y)) + l2 * beta
        hess = (z * (w * p * (1 - p))[:, None]).T @ z + l2 * np.eye(beta.size)
        beta = beta - np.linalg.solve(hess, grad)
    return beta, mean, sd


def logistic_p(model: tuple, x: np.ndarray) -> np.ndarray:
    beta, mean, sd = model
    return 1.0 / (1.0 + np.exp(-(np.column_stack([(x - mean) / sd, np.ones(len(x))]) @ beta)))


def fit_trees(x: np.ndarray, y: np.ndarray, w: np.ndarray, *, rounds: int = 150, rate: float = 0.2,
              bins: int = 16) -> tuple:
    """Gradient-boosted depth-2 trees (logistic loss) over quantile bins of each feature."""
    w = w / w.sum()
    cuts = [np.unique(np.quantile(x[:, f], np.linspace(0, 1, bins + 1)[1:-1])) for f in range(x.shape[1])]
    xb = _binned(cuts, x)
    base = float(np.log((w * y).sum() / max((w * (1 - y)).sum(), 1e-12)))
    score = np.full(len(y), base)
    trees = []
    for _ in range(rounds):
        p = 1.0 / (1.0 + np.exp(-score))
        g, h = w * (y - p), w * p * (1 - p)
        top = _split(xb, g, h, np.ones(len(y), bool), bins)
        if top is None:
            break
        tree = [top]
        for side in (xb[:, top[0]] <= top[1], xb[:, top[0]] > top[1]):
            sub = _split(xb, g, h, side, bins)
            leaves = [side] if sub is None else [side & (xb[:, sub[0]] <= sub[1]), side & (xb[:, sub[0]] > sub[1])]
            values = [g[s].sum() / (h[s].sum() + 1e-9) for s in leaves]
            for s, v in zip(leaves, values):
                score[s] += rate * v
            tree.append((sub, values))
        trees.append(tree)
    return cuts, base, rate, trees


def trees_p(model: tuple, x: np.ndarray) -> np.ndarray:
    cuts, base, rate, trees = model
    xb = _binned(cuts, x)
    score = np.full(len(x), base)
    for (f, k), *sides in trees:
        for side, (sub, values) in zip((xb[:, f] <= k, xb[:, f] > k), sides):
            if sub is None:
                score[side] += rate * values[0]
            else:
                low = xb[:, sub[0]] <= sub[1]
                score[side & low] += rate * values[0]
                score[side & ~low] += rate * values[1]
    return 1.0 / (1.0 + np.exp(-score))


def _binned(cuts: list[np.ndarray], x: np.ndarray) -> np.ndarray:
    return np.column_stack([np.searchsorted(c, x[:, f]) for f, c in enumerate(cuts)])


def _split(xb: np.ndarray, g: np.ndarray, h: np.ndarray, rows: np.ndarray, bins: int) -> tuple[int, int] | None:
    """Best (feature, bin) to split ``rows`` at (Newton gain), None when no split gains."""
    best, at = 0.0, None
    for f in range(xb.shape[1]):
        sg = np.cumsum(np.bincount(xb[rows, f], weights=g[rows], minlength=bins + 1))
        sh = np.cumsum(np.bincount(xb[rows, f], weights=h[rows], minlength=bins + 1))
        left, right = sg[:-1] ** 2 / (sh[:-1] + 1e-9), (sg[-1] - sg[:-1]) ** 2 / (sh[-1] - sh[:-1] + 1e-9)
        gain = left + right - sg[-1] ** 2 / (sh[-1] + 1e-9)
        k = int(np.argmax(gain))
        if gain[k] > best + 1e-12:
            best, at = gain[k], (f, k)
    return at


def labelled_contested(b: Block, margin: float) -> tuple[np.ndarray, ...]:
    """Contested nodes, rival, features, and for each: rival right, own right, points; the walk's labels."""
    idx, rival, x, walk = contested_features(b, margin)
    stands, major = stands_for(b), b.node_true.argmax(axis=1)
    return idx, rival, x, stands[rival] == major[idx], stands[b.node_tree[idx]] == major[idx], b.node_true[idx].sum(axis=1), walk


def evaluate(b: Block, models: dict, margin: float) -> dict[str, float]:
    """The second table's figures for one block."""
    idx, rival, x, riv_ok, own_ok, pts, walk = labelled_contested(b, margin)
    out = {"contested": pts.sum() / b.tree_points}
    vote = subtree_vote(b, idx, pts, walk[idx] == rival)
    right = {"paths": own_ok, "walk": np.where(walk[idx] == rival, riv_ok, own_ok),
             "subtree vote": np.where(vote, riv_ok, own_ok)}
    by_vote = b.node_tree.copy()
    by_vote[idx[vote]] = rival[vote]
    labels = {"paths": b.node_tree, "refined": refine_contested(b.graph, b.node_tree, b.dist, margin=SHIPPED_MARGIN),
              "subtree vote": by_vote}
    for name, (_, p) in models.items():
        flip = p(x) > 0.5 if idx.size else np.zeros(0, bool)
        right[name] = np.where(flip, riv_ok, own_ok)
        lab = b.node_tree.copy()
        lab[idx[flip]] = rival[flip]
        labels[name] = lab
    for name, ok in right.items():
        out[f"right {name}"] = (pts * ok).sum() / max(pts.sum(), 1)
    for name, lab in labels.items():
        out[f"v {name}"] = node_v_measure(b, lab)
    return out


def subtree_vote(b: Block, idx: np.ndarray, pts: np.ndarray, flip: np.ndarray) -> np.ndarray:
    """Branch-level assignment: each subtree of contested nodes ``idx`` in the shortest-path
    forest (its root: a contested node whose parent is not) moves to the rival as a whole
    when the walk moves most of its points, (c,) bool."""
    m = b.node_tree.size
    contested = np.zeros(m, bool)
    contested[idx] = True
    parent = np.where(b.pred >= 0, b.pred, np.arange(m))
    root = np.where(contested & contested[parent] & (parent != np.arange(m)), parent, np.arange(m))
    for _ in range(int(np.ceil(np.log2(max(m, 2)))) + 1):
        root = root[root]
    moved = np.bincount(root[idx], weights=pts * flip, minlength=m)
    held = np.bincount(root[idx], weights=pts, minlength=m)
    return moved[root[idx]] > 0.5 * held[root[idx]]


def fitted_models(seeds: int, margin: float) -> dict:
    """Both models, fitted on seeds 1000.. of TRAIN, each block weighted alike."""
    xs, ys, ws = [], [], []
    for setting in TRAIN:
        for seed in range(1000, 1000 + seeds):
            _, _, x, riv_ok, own_ok, pts, _ = labelled_contested(generated_block(setting, seed), margin)
            keep = riv_ok | own_ok
            xs.append(x[keep])
            ys.append(riv_ok[keep].astype(np.float64))
            ws.append(pts[keep] / max(pts[keep].sum(), 1))
    x, y, w = np.vstack(xs), np.concatenate(ys), np.concatenate(ws)
    lr, gb = fit_logistic(x, y, w), fit_trees(x, y, w)
    return {"logistic": (lr, lambda q: logistic_p(lr, q)), "trees": (gb, lambda q: trees_p(gb, q))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.contested", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="evaluation seeds 0..N-1 per setting (default 2)")
    ap.add_argument("--train-seeds", type=int, default=2, help="fitting seeds 1000..1000+N-1 per setting (default 2)")
    ap.add_argument("--margin", type=float, default=1.0, help="contested margin of the learned models [m] (default 1.0)")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.train_seeds < 1 or args.margin <= 0:
        ap.error("--seeds and --train-seeds must be at least 1, --margin above 0")
    from bench.real_data import adtree_row

    blocks = [(s, seed, generated_block(s, seed)) for s in EVALUATE for seed in range(args.seeds)]
    for seed in range(args.seeds):
        xyz, tid, _ = adtree_row(seed=seed)
        blocks.append(("real AdTree row", seed, recorded_block(xyz - np.floor(xyz.min(axis=0)), tid, None)))
    m = f"{args.margin:g} m"
    print("| setting | seed | wrong (of tree points) | in wrong nodes | wood / twig / leaf (of wrong) | "
          f"in runs ≥ {RUN_NODES} nodes | in runs with wood | between the trunks (10 / 50 / 90 %) | "
          f"contested at {SHIPPED_MARGIN:g} m (share of tree points) | contested at {m} | "
          f"entered by subtrees ≥ {RUN_NODES} nodes | entries per run | reached inside own tree | "
          "its path ÷ shortest path (median) | v-measure: paths | wrong nodes put right |")
    print("|---" * 16 + "|")
    for s, seed, b in blocks:
        d = diagnose(b, args.margin)
        kinds = f"{d['wood']:.0%} / {d['twig']:.0%} / {d['leaf']:.0%}" if "wood" in d else "–"
        print(f"| {s} | {seed} | {d['wrong']:.1%} | {d['in wrong nodes']:.0%} | {kinds} | {d['in runs']:.0%} | "
              f"{d['in runs with wood']:.0%} | "
              f"{' / '.join(f'{v:.2f}' for v in d['between trunks'])} | "
              f"{d['contested shipped']:.0%} ({d['contested shipped share']:.1%}) | {d['contested margin']:.0%} "
              f"({d['contested margin share']:.1%}) | {d['entered in subtrees']:.0%} | {d['entries per run']:.1f} | "
              f"{d['reached inside own tree']:.0%} | {d['detour']:.2f} | {d['v paths']:.3f} | {d['v fixed']:.3f} |", flush=True)
    models = fitted_models(args.train_seeds, args.margin)
    print()
    print(f"| setting | seed | contested at {m} (of tree points) | right: paths | walk | subtree vote | logistic | trees | "
          "v-measure: paths | refined | subtree vote | logistic | trees |")
    print("|---" * 13 + "|")
    for s, seed, b in blocks:
        e = evaluate(b, models, args.margin)
        print(f"| {s} | {seed} | {e['contested']:.1%} | {e['right paths']:.3f} | {e['right walk']:.3f} | "
              f"{e['right subtree vote']:.3f} | "
              f"{e['right logistic']:.3f} | {e['right trees']:.3f} | {e['v paths']:.3f} | {e['v refined']:.3f} | "
              f"{e['v subtree vote']:.3f} | {e['v logistic']:.3f} | {e['v trees']:.3f} |",
              flush=True)


if __name__ == "__main__":
    main()
