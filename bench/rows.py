"""Rows and addresses end to end: trunks found, v-measure, addresses, empty slots, replants.

    python -m bench.rows [--seeds 3] [--first-seed 0]

For each planting system it generates blocks (evaluation seeds ``first-seed`` ..
``first-seed + seeds - 1``; tune on other seeds) with 10 % of the planting slots empty
and 5 % replanted, writes each as LAZ with its truth, runs the whole job as
``orchard process`` does (``workers.job.run_job``, untiled) and scores it with
``orchard evaluate`` (``simulator.scoring.result.evaluate_result``). Prints a Markdown table:
pooled trunk precision, recall and F1, mean v-measure, the share of found trees at their
true address (up to the numbering rule, docs/rows.md), empty-slot precision and recall,
replants found and flagged young, and the rows found (those from the canopy alone, with
no trunk found, in brackets).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from simulator.scoring.result import evaluate_result
from simulator.simparams import SimulationParams
from simulator.truth import write_simulation
from workers.job import run_job
from workers.jobspec import JobSpec

#: planting systems: in-row spacing and row spacing [m] of each, and the tree form
SYSTEMS: dict[str, dict] = {
    "tall spindle 1.0 m x 3.5 m": dict(form="spindle", spacing=1.0, row_spacing=3.5, rows=3, trees_per_row=16),
    "tall spindle 1.5 m x 3.5 m": dict(form="spindle", spacing=1.5, row_spacing=3.5, rows=3, trees_per_row=12),
    "hedge (SHD olive) 1.35 m x 4 m": dict(form="hedge", spacing=1.35, row_spacing=4.0, rows=3, trees_per_row=12),
    "high density 2.5 m x 4.5 m, low foliage": dict(spacing=2.5, row_spacing=4.5, low_foliage=True, rows=3, trees_per_row=8),
    "vase 5 m x 6 m": dict(spacing=5.0, row_spacing=6.0, rows=3, trees_per_row=6),
}
#: share of planting slots left empty, and replanted with a young tree
MISSING, REPLANTS = 0.1, 0.05
#: trunks match within this fraction of the in-row spacing (at most 1 m)
MATCH_FRACTION = 0.4


def score(system: dict, seed: int, work: Path) -> dict:
    """Generate, process and score one block."""
    sim = SimulationParams(seed=seed, missing=MISSING, replants=REPLANTS, density=0.5, **system)
    las, truth = work / f"b{seed}.laz", work / f"b{seed}.truth.parquet"
    write_simulation(sim, str(las), str(truth))
    out = work / f"out{seed}"
    run_job(JobSpec(str(las), str(out)))
    scores = evaluate_result(str(truth), str(out), match_distance=min(1.0, MATCH_FRACTION * sim.spacing))
    rows = pq.read_table(out / "rows.parquet", columns=["n_trees"]).column("n_trees").to_numpy()
    return dict(scores, rows_true=sim.rows, rows_found=int(len(rows)), rows_without_trees=int((rows == 0).sum()))


def table_row(name: str, scores: list[dict]) -> str:
    tp, fp, fn = (sum(s[k] for s in scores) for k in ("trunk_tp", "trunk_fp", "trunk_fn"))
    p = tp / max(tp + fp, 1)
    r = tp / max(tp + fn, 1)
    f1 = 2 * p * r / max(p + r, 1e-12)
    vm = np.mean([s["v_measure"] for s in scores])
    addr = sum(s.get("n_correct", 0) for s in scores) / max(sum(s.get("n_matched", 0) for s in scores), 1)
    gtp, gfp, gfn = (sum(s.get(k, 0) for s in scores) for k in ("gap_tp", "gap_fp", "gap_fn"))
    gp = gtp / max(gtp + gfp, 1)
    gr = gtp / max(gtp + gfn, 1)
    young = f"{sum(s.get('young_correct', 0) for s in scores)} / {sum(s.get('young_true', 0) for s in scores)}"
    flagged = sum(s.get("young_found", 0) for s in scores)
    rows = f"{sum(s['rows_found'] for s in scores)} / {sum(s['rows_true'] for s in scores)}"
    canopy = sum(s["rows_without_trees"] for s in scores)
    return (f"| {name} | {len(scores)} | {p:.3f} | {r:.3f} | {f1:.3f} | {vm:.3f} | {addr:.3f} | {gp:.2f} | {gr:.2f} "
            f"| {young} ({flagged} flagged) | {rows} ({canopy}) |")


HEADER = (
    "| planting system | blocks | trunk precision | trunk recall | trunk F1 | v-measure | address accuracy "
    "| empty-slot precision | empty-slot recall | replants flagged young / true | rows found / true (from the canopy only) |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.rows", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=3, help="blocks per planting system (default 3)")
    ap.add_argument("--first-seed", type=int, default=0, help="first seed (default 0: the evaluation seeds)")
    ap.add_argument("--only", default=None, help="run only the systems whose name contains this text")
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    print(HEADER, flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-rows-") as tmp:
        for name, system in SYSTEMS.items():
            if args.only and args.only not in name:
                continue
            work = Path(tmp) / str(abs(hash(name)))
            work.mkdir()
            scores = [score(system, args.first_seed + i, work) for i in range(args.seeds)]
            print(table_row(name, scores), flush=True)


if __name__ == "__main__":
    main()
