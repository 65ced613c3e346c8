"""Edge weightings of the segmentation graph that make contacts cost more than continuations.

    python -m bench.edges [--seeds 0,1] [--alphas 0.5,1,2,4] [--weightings axis,...]
                          [--settings "paper setting,...,leafless hedge,real young,real"] [--auc]

Issue 61. ``bench.contested`` found the wrong points in runs of twigs and leaves that
their own trunk reaches inside their own tree by a path only 1.05-1.16 times the
shortest: the shortest path crosses a contact between two trees' twigs. This bench
tries edge weightings that should make such contacts dearer than the edges continuing
a twig. Per block it runs the pipeline once, records the graph, sources and parameters
its last segmentation search was given (``pipeline.segment.segment_nodes``), and
segments again with every edge's length multiplied by a factor (:func:`edge_factors`),
the trunks unchanged. It prints the v-measure of the tree points in the vegetation
with the nodes' labels mapped to points (a little below ``bench.segmentation``'s, which
also labels trunk feet and post foliage), per setting and seed, for each weighting and
each ``alpha``. Tune on seeds 1000.., evaluate on 0, 1. ``--auc`` prints instead how
well each factor tells contacts (edges joining two true trees) from the edges inside
one tree beside them (ROC AUC, :func:`contact_auc`). Settings: names (or parts of
names) of ``bench.segmentation.SETTINGS`` and of ``LEAFLESS`` (``bench.young``'s grown
blocks scanned leafless: ``leafless vase``, ``leafless tall spindle``, ``leafless
hedge``), ``real`` for the row of AdTree trees and ``real young`` for the young block of
real trees (``bench.real_data.young_row``).
"""

from __future__ import annotations

import argparse
from unittest import mock

import numpy as np
from scipy import sparse
from scipy.stats import rankdata

import pipeline.process
from bench.segmentation import SETTINGS
from bench.young import DORMANT
from pipeline.enrichment import symmetric_eigen3
from pipeline.params import PipelineParams
from pipeline.process import analyse_nodes
from simulator.scoring.scores import v_measure
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

WEIGHTINGS = ("axis", "axis linear", "density", "scattering", "shared", "enriched", "turn", "oracle")
"""Edge factors of :func:`edge_factors` ("oracle": the truth's contacts, a bound, not a rule)."""
#: the ``turn`` factor reads a path's direction over this many of its last edges
TURN_HOPS = 2


def principal_axes(nodes: np.ndarray, adjacency: sparse.csr_matrix) -> np.ndarray:
    """(m, 3) unit principal axis of each node's neighbourhood (``adjacency``: 0/1 with the diagonal)."""
    c = nodes - nodes.mean(axis=0)
    x, y, z = c[:, 0], c[:, 1], c[:, 2]
    s = adjacency @ np.column_stack([np.ones(len(c)), x, y, z, x * x, y * y, z * z, x * y, x * z, y * z])
    n = s[:, 0]
    mu = s[:, 1:4] / n[:, None]
    cov = (s[:, 4] / n - mu[:, 0] ** 2, s[:, 5] / n - mu[:, 1] ** 2, s[:, 6] / n - mu[:, 2] ** 2,
           s[:, 7] / n - mu[:, 0] * mu[:, 1], s[:, 8] / n - mu[:, 0] * mu[:, 2], s[:, 9] / n - mu[:, 1] * mu[:, 2])
    return symmetric_eigen3(*cov)[2]


def edge_factors(kind: str, a: np.ndarray, b: np.ndarray, *, nodes: np.ndarray, alpha: float,
                 axis: np.ndarray | None = None, linearity: np.ndarray | None = None,
                 density: np.ndarray | None = None, scattering: np.ndarray | None = None,
                 shared: np.ndarray | None = None, features: np.ndarray | None = None,
                 pred: np.ndarray | None = None, truth: np.ndarray | None = None) -> np.ndarray:
    """(e,) factor >= 1 on the length of each edge (a[i], b[i]).

    ``axis``: 1 + alpha (1 - mean |cos|) of the edge's direction and its two nodes'
    principal axes; ``axis linear``: the same, each node's term times its linearity (a
    leaf's axis says nothing); ``density``: 1 + alpha |log(d_a / d_b)|, d the nodes'
    point density; ``scattering``: 1 + alpha |s_a - s_b|; ``shared``: 1 + alpha (1 - the
    share of the two nodes' neighbours they share); ``enriched``: 1 + alpha (1 - cosine
    similarity of the nodes' feature vectors) (alpha 1: the paper's weighting);
    ``turn``: 1 + alpha (1 - cos) / 2 of the turn from the direction of the shortest
    path to a node over its last TURN_HOPS edges (``pred``: the shortest-path forest of a
    first search, -1 at roots) into the edge, the smaller of its two ends (a path
    continuing a branch goes straight on; one that crosses to another tree's branch at
    a contact turns); ``oracle``: 1 + alpha on the edges joining nodes of two true trees (``truth``: each
    node's majority tree), the most an edge classification could give.
    """
    if kind in ("axis", "axis linear"):
        d = nodes[b] - nodes[a]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        off_a = 1.0 - np.abs((d * axis[a]).sum(1))
        off_b = 1.0 - np.abs((d * axis[b]).sum(1))
        if kind == "axis linear":
            off_a, off_b = off_a * linearity[a], off_b * linearity[b]
        return 1.0 + alpha * 0.5 * (off_a + off_b)
    if kind == "density":
        return 1.0 + alpha * np.abs(np.log(density[a] / density[b]))
    if kind == "scattering":
        return 1.0 + alpha * np.abs(scattering[a] - scattering[b])
    if kind == "shared":
        return 1.0 + alpha * (1.0 - shared)
    if kind == "enriched":
        f = features / (np.linalg.norm(features, axis=1, keepdims=True) + 1e-12)
        return 1.0 + alpha * (1.0 - np.clip((f[a] * f[b]).sum(1), -1.0, 1.0))
    if kind == "turn":
        top = np.arange(pred.size)
        for _ in range(TURN_HOPS):
            top = np.where(pred[top] >= 0, pred[top], top)
        u = nodes - nodes[top]
        norm = np.linalg.norm(u, axis=1)
        u /= np.maximum(norm, 1e-12)[:, None]
        d = nodes[b] - nodes[a]
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        # an end no path leads to (a root, an unreached node) gives no direction
        turn_a = np.where(norm[a] > 0, 1.0 - (u[a] * d).sum(1), np.inf)
        turn_b = np.where(norm[b] > 0, 1.0 + (u[b] * d).sum(1), np.inf)
        turn = np.minimum(turn_a, turn_b)
        return 1.0 + alpha * 0.5 * np.where(np.isfinite(turn), turn, 0.0)
    if kind == "oracle":
        return 1.0 + alpha * ((truth[a] != truth[b]) & (truth[a] > 0) & (truth[b] > 0))
    raise ValueError(f"unknown weighting {kind!r}; known: {', '.join(WEIGHTINGS)}")


def contact_auc(factor: np.ndarray, a: np.ndarray, b: np.ndarray, truth: np.ndarray) -> float:
    """ROC AUC of ``factor`` (e,) telling contacts (edges joining two true trees, ``truth``
    (m,) each node's majority tree, 0 none) from the edges inside one tree that touch a
    contact's node; nan without both."""
    tree = (truth[a] > 0) & (truth[b] > 0)
    contact = tree & (truth[a] != truth[b])
    border = np.zeros(truth.shape[0], bool)
    border[a[contact]] = border[b[contact]] = True
    inside = tree & ~contact & (border[a] | border[b])
    if not contact.any() or not inside.any():
        return float("nan")
    rank = rankdata(np.r_[factor[contact], factor[inside]])
    n1, n0 = int(contact.sum()), int(inside.sum())
    return float((rank[:n1].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def shared_neighbours(graph: sparse.csr_matrix, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(e,) share of the union of the neighbourhoods (each node included) of a[i] and b[i] that both hold."""
    adj = (graph != 0).astype(np.float64) + sparse.identity(graph.shape[0], format="csr")
    adj = adj.tocsr()
    deg = np.asarray(adj.sum(1)).ravel()
    common = np.asarray(adj[a].multiply(adj[b]).sum(1)).ravel()
    return common / (deg[a] + deg[b] - common)


class Recorded:
    """One analysed block, the last segmentation search's inputs and the truth."""

    def __init__(self, xyz: np.ndarray, tree_id: np.ndarray):
        calls: list = []
        real = pipeline.process.segment_nodes

        def record(nodes, graph, **kw):
            calls.append((graph, kw))
            return real(nodes, graph, **kw)

        with mock.patch.object(pipeline.process, "segment_nodes", record):
            an = analyse_nodes(xyz, params=PipelineParams())
        self.graph, self.kw = calls[-1]
        self.nodes = an.vox.centroids
        self.point_node = an.vox.point_voxel
        self.point_true = tree_id[an.veg_idx]
        self.base = an.segmentation.node_tree
        g = sparse.triu(self.graph, k=1).tocoo()
        self.a, self.b = g.row.astype(np.int64), g.col.astype(np.int64)
        self.length = g.data
        f = an.features
        vs = PipelineParams().graph.voxel_size
        self.inputs = dict(
            nodes=self.nodes, axis=principal_axes(self.nodes, an.adjacency), linearity=f.linearity,
            density=np.maximum(an.vox.counts, 1) / vs**3, scattering=f.scattering,
            shared=shared_neighbours(self.graph, self.a, self.b), features=f.matrix(),
            pred=pipeline.process.segment_nodes(self.nodes, self.graph, **self.kw).paths.pred,
            truth=sparse.csr_matrix((np.ones(self.point_node.size), (self.point_node, self.point_true)),
                                    shape=(len(self.nodes), int(tree_id.max()) + 1)).toarray().argmax(1),
        )

    def v(self, node_tree: np.ndarray) -> float:
        """V-measure of the tree points in the vegetation under these node labels."""
        tree = self.point_true > 0
        return v_measure(self.point_true[tree], node_tree[self.point_node][tree])

    def segmented(self, kind: str, alpha: float) -> np.ndarray:
        """Node labels with the edges reweighted."""
        w = self.length * edge_factors(kind, self.a, self.b, alpha=alpha, **self.inputs)
        m = self.nodes.shape[0]
        g = sparse.coo_matrix((np.r_[w, w], (np.r_[self.a, self.b], np.r_[self.b, self.a])), shape=(m, m)).tocsr()
        return pipeline.process.segment_nodes(self.nodes, g, **self.kw).node_tree


#: grown blocks scanned leafless, as ``bench.young`` has them (every point wood or twig)
LEAFLESS = {f"leafless {k.split(',')[0]}": v for k, v in ((name, o) for name, o in DORMANT if o.get("leafless"))}


def generated(setting: str, seed: int) -> Recorded:
    sim = next(v for k, v in {**SETTINGS, **LEAFLESS}.items() if setting in k)
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    return Recorded(o.xyz - np.floor(o.xyz.min(axis=0)), o.tree_id)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.edges", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1", help="seeds, comma-separated (tune on 1000.., evaluate on 0, 1)")
    ap.add_argument("--alphas", default="0.5,1,2,4", help="factors' alpha, comma-separated")
    ap.add_argument("--weightings", default=",".join(WEIGHTINGS))
    ap.add_argument("--settings", default="paper setting,high density,hedge 1.2 m,spindle 1.0 m,real")
    ap.add_argument("--auc", action="store_true",
                    help="print instead each weighting's ROC AUC for contacts against the edges beside them")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    alphas = [float(s) for s in args.alphas.split(",")]
    kinds = args.weightings.split(",")
    if args.auc:
        print("| setting | seed | " + " | ".join(kinds) + " |")
        print("|---" * (2 + len(kinds)) + "|", flush=True)
    else:
        print("| setting | seed | baseline | " + " | ".join(f"{k} {a:g}" for k in kinds for a in alphas) + " |")
        print("|---" * (3 + len(kinds) * len(alphas)) + "|", flush=True)
    for setting in args.settings.split(","):
        for seed in seeds:
            if setting in ("real", "real young"):
                from bench.real_data import adtree_row, young_row

                xyz, tid, _ = (adtree_row if setting == "real" else young_row)(seed=seed)
                r = Recorded(xyz - np.floor(xyz.min(axis=0)), tid)
            else:
                r = generated(setting, seed)
            if args.auc:
                aucs = [contact_auc(edge_factors(k, r.a, r.b, alpha=1.0, **r.inputs), r.a, r.b, r.inputs["truth"])
                        for k in kinds]
                print(f"| {setting} | {seed} | " + " | ".join(f"{v:.2f}" for v in aucs) + " |", flush=True)
                continue
            vs = [r.v(r.segmented(k, a)) for k in kinds for a in alphas]
            print(f"| {setting} | {seed} | {r.v(r.base):.3f} | " + " | ".join(f"{v:.3f}" for v in vs) + " |", flush=True)


if __name__ == "__main__":
    main()
