"""Segmentation methods side by side: v-measure, wood F1, crowns at a row's end, clutter.

    python -m bench.segmentation [--seeds 2] [--only TEXT] [--methods paths,refined]

For every setting of ``SETTINGS`` (the issue's four target settings, and forms and
spacings the refinement was not tuned on) and evaluation seeds 0..N-1 (the refinement's
margin and the narrow trees' wood model were chosen on seeds 1000+), runs
:func:`pipeline.process.process_points` once per segmentation method and prints one
Markdown row per setting and method: trunk F1, v-measure and wood F1 (mean [min, max]
over the blocks), the median crown diameter of each row's two end trees over that of
its inner trees (crown diameter as in ``trees.parquet``), the share of the vehicle's and
bin's points and of the grass points put in a tree, and the seconds per block. Then the
same for the row of real AdTree trees (:func:`bench.real_data.adtree_row`, seeds 0..N-1),
which has exact ids but no wood labels or clutter.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pipeline.metrics import finalize_metrics, tree_partials
from pipeline.params import PipelineParams
from pipeline.process import process_points
from simulator.orchard import GRASS, VEHICLE
from simulator.scoring.scores import score_labels
from simulator.simparams import SimulationParams
from simulator.simulate import simulate_orchard

SETTINGS: dict[str, dict] = {
    "paper setting vase 5 m × 6 m": dict(rows=2, trees_per_row=4, spacing=5.0, row_spacing=6.0, noise=0.02),
    "high density vase 2.5 m × 4.5 m, low foliage": dict(rows=2, trees_per_row=5, spacing=2.5, row_spacing=4.5, low_foliage=True),
    "spindle 1.0 m × 3.5 m": dict(form="spindle", rows=2, trees_per_row=14, spacing=1.0, row_spacing=3.5),
    "hedge 1.2 m × 4 m": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.2, row_spacing=4.0),
    "spindle 1.5 m × 3.5 m (not tuned on)": dict(form="spindle", rows=2, trees_per_row=12, spacing=1.5, row_spacing=3.5),
    "hedge 1.5 m × 4 m (not tuned on)": dict(form="hedge", rows=2, trees_per_row=12, spacing=1.5, row_spacing=4.0),
    "vase 3.5 m × 5 m, noise 0.05 m (not tuned on)": dict(rows=2, trees_per_row=5, spacing=3.5, row_spacing=5.0, noise=0.05),
}
"""Simulator parameters of each setting (``simulator.simparams.SimulationParams``)."""

METHODS: dict[str, dict] = {
    "paths": {"segment": {"method": "paths"}},
    "refined": {"segment": {"method": "refined"}},
}
"""Pipeline parameters of each segmentation method."""


def crown_diameters(xyz: np.ndarray, tree_id: np.ndarray, trunks: np.ndarray) -> np.ndarray:
    """Crown diameter of each found tree [m], as ``trees.parquet`` gives it, (k,)."""
    params = PipelineParams().metrics
    parts = tree_partials(xyz, tree_id, np.zeros(len(tree_id), bool), trunks[:, 2], params=params)
    return finalize_metrics(parts, trunks, np.full(len(trunks), np.nan))["crown_diameter_m"]


def end_ratio(found: np.ndarray, diam: np.ndarray, true_trunks: np.ndarray, row_spacing: float, match: float) -> float:
    """Median crown diameter of the rows' end trees over that of their inner trees.

    Rows run along x (the simulator's layout); each true trunk's row is its y over the
    row spacing, its end trees the first and last by x; a found tree counts for the true
    trunk within ``match`` [m] of it.
    """
    row = np.round((true_trunks[:, 1] - true_trunks[:, 1].min()) / row_spacing).astype(int)
    end = np.zeros(len(true_trunks), bool)
    for r in np.unique(row):
        idx = np.flatnonzero(row == r)
        end[idx[np.argmin(true_trunks[idx, 0])]] = end[idx[np.argmax(true_trunks[idx, 0])]] = True
    d = np.hypot(*(found[:, None, :2] - true_trunks[None, :, :2]).transpose(2, 0, 1))
    j = d.argmin(axis=1)
    ok = d[np.arange(len(found)), j] <= match
    ends, inner = diam[ok & end[j]], diam[ok & ~end[j]]
    if not len(ends) or not len(inner):
        return float("nan")
    return float(np.median(ends) / np.median(inner))


def score_block(sim: dict, seed: int) -> dict[str, dict]:
    """One generated block under every method: its scores."""
    o = simulate_orchard(SimulationParams(seed=seed, **sim))
    origin = np.floor(o.xyz.min(axis=0))
    xyz = o.xyz - origin
    true_trunks = o.trunks - origin
    match = min(1.0, 0.5 * sim["spacing"])
    out = {}
    for name, over in METHODS.items():
        t0 = time.perf_counter()
        r = process_points(xyz, params=PipelineParams.model_validate(over))
        dt = time.perf_counter() - t0
        s = score_labels(true_tree_id=o.tree_id, true_is_wood=o.is_wood, true_trunks=true_trunks,
                         pred_tree_id=r.tree_id, pred_is_wood=r.is_wood, found_trunks=r.trunks, match_distance=match)
        diam = crown_diameters(xyz, r.tree_id, r.trunks)
        in_tree = r.tree_id > 0
        vehicle, grass = o.kind == VEHICLE, o.kind == GRASS
        out[name] = {
            "trunk_f1": s["trunk_f1"], "v_measure": s["v_measure"], "wood_f1": s["wood_f1"],
            "end_ratio": end_ratio(r.trunks, diam, true_trunks, sim["row_spacing"], match),
            "vehicle_in_trees": float(in_tree[vehicle].mean()) if vehicle.any() else float("nan"),
            "grass_in_trees": float(in_tree[grass].mean()) if grass.any() else float("nan"),
            "seconds": dt,
        }
    return out


def _mean_range(v: list[float], fmt: str = ".3f") -> str:
    a = np.asarray(v, float)
    return f"{np.nanmean(a):{fmt}} [{np.nanmin(a):{fmt}}, {np.nanmax(a):{fmt}}]"


HEADER = (
    "| setting | method | blocks | trunk F1 | v-measure | wood F1 | end ÷ inner crown diameter | vehicle and bin in trees | grass in trees | s / block |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def table_row(setting: str, method: str, rows: list[dict]) -> str:
    col = {k: [r[k] for r in rows] for k in rows[0]}
    return (f"| {setting} | {method} | {len(rows)} | {_mean_range(col['trunk_f1'], '.2f')} | {_mean_range(col['v_measure'])} | "
            f"{_mean_range(col['wood_f1'])} | {_mean_range(col['end_ratio'], '.2f')} | {100 * np.nanmean(col['vehicle_in_trees']):.1f} % | "
            f"{100 * np.nanmean(col['grass_in_trees']):.1f} % | {np.mean(col['seconds']):.1f} |")


def real_rows(seeds: int) -> list[str]:
    """The row of four real AdTree trees under every method."""
    from bench.real_data import _scored_row, adtree_row

    out = []
    scores: dict[str, list[dict]] = {m: [] for m in METHODS}
    for seed in range(seeds):
        xyz, tid, bases = adtree_row(seed=seed)
        for name, over in METHODS.items():
            s, dt = _scored_row(xyz, tid, bases, PipelineParams.model_validate(over))
            scores[name].append({"trunk_f1": s["trunk_f1"], "v_measure": s["v_measure"], "seconds": dt})
    for name, rows in scores.items():
        col = {k: [r[k] for r in rows] for k in rows[0]}
        out.append(f"| real AdTree row (4 trees, crowns overlapping) | {name} | {len(rows)} | {_mean_range(col['trunk_f1'], '.2f')} | "
                   f"{_mean_range(col['v_measure'])} | – | – | – | – | {np.mean(col['seconds']):.1f} |")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.segmentation", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="evaluation seeds 0..N-1 per setting (default 2)")
    ap.add_argument("--only", default="", help="run only the settings whose name contains this text ('real': the real row)")
    ap.add_argument("--methods", default=",".join(METHODS), help="segmentation methods, comma-separated")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    unknown = set(args.methods.split(",")) - set(METHODS)
    if unknown:
        ap.error(f"unknown --methods {', '.join(sorted(unknown))}; known: {', '.join(METHODS)}")
    for name in list(METHODS):
        if name not in args.methods.split(","):
            del METHODS[name]
    print(HEADER, flush=True)
    for setting, sim in SETTINGS.items():
        if args.only and args.only not in setting:
            continue
        blocks = [score_block(sim, seed) for seed in range(args.seeds)]
        for name in METHODS:
            print(table_row(setting, name, [b[name] for b in blocks]), flush=True)
    if not args.only or args.only in "real":
        for line in real_rows(args.seeds):
            print(line, flush=True)


if __name__ == "__main__":
    main()
