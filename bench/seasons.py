"""The same trees over the seasons: series of captures of one generated block.

    python -m bench.seasons [--seeds 2] [--first-seed 100] [--captures 5] [--only NAME]

For each planting system and seed (evaluation seeds ``first-seed`` .. ``first-seed +
seeds - 1``; the tests and the tuning used seeds 11 and 21, series seeds 1 and 2) it
generates a series of captures of one block (:func:`simulator.series.capture_series`:
trees grown 5-10 % between captures, 5 % of the grown trees cut, half the slots cut
before replanted, each capture's frame drifted by 0.5-2 m and 0.5-2 degrees against the
previous one, a new scan each time), processes each as ``orchard process --previous``
does (``workers.job.run_job``, untiled, the previous capture's folder as ``previous``)
and scores every pair of consecutive captures against the truth:

- key retention: of the trees standing in both captures and found in both, the share
  that keep their key and their address (row, position);
- removed recall: of the trees cut between the two and found in the first, the share
  that the second's ``gaps.parquet`` reports with their key at their address; false
  removals: removed keys that were not cut;
- growth sign: the share of those trees whose ``height_change_m`` is positive (every
  tree grew); height change error: ``height_change_m`` against the difference of the two
  captures' measured heights, and against the true change of the trees' tops;
- registration: the residual recorded with the capture (RMS of the matched trunks the
  fit used), the RMS of all matched trunks, and the true error (RMS distance of the true
  trunks after the recorded transform);
- over the series, the share of the first capture's trees standing and found in the
  last that still carry their first key;
- time: the seconds the seasons step took (reading the previous folder, registration,
  matching, keys, history) plus the coverage cells the tiles compute, against the job.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from pipeline.coverage import occupied_cells, stem_cells
from pipeline.reading import read_points
from pipeline.registration import RigidTransform
from simulator.plan import make_plan
from simulator.series import capture_series
from simulator.simparams import SimulationParams, local_origin
from simulator.truth import write_simulation
from workers.job import run_job
from workers.jobspec import JobSpec
from workers.tasks import COVERAGE_STRIDE

SYSTEMS: dict[str, dict] = {
    "vase 5 m x 6 m": dict(form="vase", spacing=5.0, row_spacing=6.0, rows=3, trees_per_row=6),
    "tall spindle 1.0 m x 3.5 m": dict(form="spindle", spacing=1.0, row_spacing=3.5, rows=3, trees_per_row=14),
    "tall spindle 1.5 m x 3.5 m": dict(form="spindle", spacing=1.5, row_spacing=3.5, rows=3, trees_per_row=10),
    "hedge 1.35 m x 4 m": dict(form="hedge", spacing=1.35, row_spacing=4.0, rows=3, trees_per_row=12),
}
#: truth trunks match found trees within this fraction of the in-row spacing (at most 0.5 m)
MATCH_FRACTION = 0.4


def _truth(params: SimulationParams) -> dict:
    """Grid slot → (true trunk xy in the input CRS, true height)."""
    plan = make_plan(params)
    xy = plan.trunks[:, :2] + local_origin(params)[:2]
    return {int(s): (p, h) for s, p, h in zip(plan.layout.trees, xy, plan.heights)}


def _found(truth: dict, out: Path, radius: float) -> dict:
    """Grid slot → the found tree on it: key, row, position, height, height change, status."""
    t = pq.read_table(out / "trees.parquet").to_pydict()
    xy = np.c_[t["trunk_x"], t["trunk_y"]]
    found = {}
    for slot, (p, _) in truth.items():
        d = np.linalg.norm(xy - p, axis=1)
        i = int(d.argmin())
        if d[i] <= radius:
            found[slot] = {k: t[k][i] for k in ("tree_key", "row", "position", "height_m", "height_change_m", "status")}
    return found


def run_series(system: dict, seed: int, captures: int, work: Path) -> dict:
    base = SimulationParams(seed=seed, density=0.5, **system)
    series = capture_series(base, captures, seed=seed)
    radius = min(0.5, MATCH_FRACTION * base.spacing)
    truths, founds, outs, times = [], [], [], []
    pairs = []
    for k, cap in enumerate(series):
        las = work / f"s{seed}c{k}.laz"
        write_simulation(cap.params, str(las), str(work / f"s{seed}c{k}.truth.parquet"), creation_date=cap.captured_at)
        out = work / f"s{seed}out{k}"
        outcome = run_job(JobSpec(str(las), str(out), previous=str(outs[-1]) if outs else None))
        xyz = read_points(str(las))[0]
        height = xyz[:, 2] - xyz[:, 2].min()  # a stand-in: the time is the band test's, whatever the heights
        t = time.perf_counter()
        occupied_cells(xyz[::COVERAGE_STRIDE, :2], (0.0, 0.0))  # what every job's tiles add: coverage and stem cells
        stem_cells(xyz[:, :2], height, np.ones(len(xyz), bool), (0.0, 0.0))
        cells = time.perf_counter() - t
        total = outcome.timings["total"]
        times.append((outcome.timings.get("seasons", 0.0) + cells) / (total - outcome.timings.get("seasons", 0.0)))
        truths.append(_truth(cap.params))
        founds.append(_found(truths[-1], out, radius))
        outs.append(out)
        if k:
            pairs.append(_score_pair(series[k], truths[k - 1], truths[k], founds[k - 1], founds[k], out))
    first, last = founds[0], founds[-1]
    replaced = set().union(*(set(c.cut) for c in series[1:]))
    lasting = [s for s in first if s in last and s not in replaced]
    kept = sum(first[s]["tree_key"] == last[s]["tree_key"] for s in lasting)
    return {"pairs": pairs, "series_kept": kept, "series_total": len(lasting), "overhead": times[1:]}


def _score_pair(cap, truth_a, truth_b, found_a, found_b, out: Path) -> dict:
    both = [s for s in found_a if s in found_b and s not in cap.cut and s not in cap.replanted]
    kept = [s for s in both if (found_a[s]["tree_key"], found_a[s]["row"], found_a[s]["position"])
            == (found_b[s]["tree_key"], found_b[s]["row"], found_b[s]["position"])]
    gaps = pq.read_table(out / "gaps.parquet").to_pydict()
    removed = {k: (r, p) for k, r, p in zip(gaps["tree_key"], gaps["row"], gaps["position"]) if k is not None}
    cut = [s for s in cap.cut if s in found_a]
    reported = [s for s in cut if removed.get(found_a[s]["tree_key"]) == (found_a[s]["row"], found_a[s]["position"])]
    cut_keys = {found_a[s]["tree_key"] for s in cut}
    false_removed = [k for k in removed if k not in cut_keys]
    same = [s for s in kept if found_b[s]["height_change_m"] is not None]
    change = np.array([found_b[s]["height_change_m"] for s in same])
    measured = np.array([found_b[s]["height_m"] - found_a[s]["height_m"] for s in same])
    true = np.array([truth_b[s][1] - truth_a[s][1] for s in same])
    record = json.loads(pq.read_schema(out / "trees.parquet").metadata[b"orchard:capture"])
    reg = record["registration"]
    transform = RigidTransform(reg["dx"], reg["dy"], reg["rotation_deg"], reg["cx"], reg["cy"])
    common = [s for s in truth_b if s in truth_a and s not in cap.replanted]
    moved = transform.apply(np.array([truth_b[s][0] for s in common]))
    true_err = float(np.sqrt(np.mean(np.sum((moved - np.array([truth_a[s][0] for s in common])) ** 2, axis=1))))
    return {"both": len(both), "kept": len(kept), "cut": len(cut), "reported": len(reported),
            "false_removed": len(false_removed), "grew": int(np.sum(change > 0)), "same": len(same),
            "err_measured": np.abs(change - measured), "err_true": np.abs(change - true),
            "residual": reg["residual_m"], "residual_all": reg["residual_all_m"], "true_error": true_err}


HEADER = (
    "| planting system | series × captures | key + address kept (pairs) | removed reported at address (false removals) "
    "| growth sign right | height change within 5 cm of the measured / true difference (true: median, 95th pct) "
    "| registration residual, max: fitted, all matches (true error, max) | keys kept first → last | seasons time / job, max |\n"
    "|---|---|---|---|---|---|---|---|---|"
)


def table_row(name: str, results: list[dict], captures: int) -> str:
    pairs = [p for r in results for p in r["pairs"]]
    s = lambda k: sum(p[k] for p in pairs)  # noqa: E731
    err_m = np.concatenate([p["err_measured"] for p in pairs])
    err_t = np.concatenate([p["err_true"] for p in pairs])
    series_kept = sum(r["series_kept"] for r in results)
    series_total = sum(r["series_total"] for r in results)
    over = [o for r in results for o in r["overhead"]]
    return (f"| {name} | {len(results)} × {captures} | {s('kept')}/{s('both')} = {s('kept') / max(s('both'), 1):.3f} "
            f"| {s('reported')}/{s('cut')} ({s('false_removed')}) | {s('grew') / max(s('same'), 1):.3f} "
            f"| {np.mean(err_m <= 0.05):.3f} / {np.mean(err_t <= 0.05):.3f} ({np.median(err_t) * 100:.1f} cm, "
            f"{np.percentile(err_t, 95) * 100:.1f} cm) "
            f"| {max(p['residual'] for p in pairs) * 100:.1f} cm, {max(p['residual_all'] for p in pairs) * 100:.1f} cm "
            f"({max(p['true_error'] for p in pairs) * 100:.1f} cm) "
            f"| {series_kept}/{series_total} = {series_kept / max(series_total, 1):.3f} "
            f"| {np.mean(over) * 100:.1f} %, {np.max(over) * 100:.1f} % |")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m bench.seasons", description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="series per planting system (default 2)")
    ap.add_argument("--first-seed", type=int, default=100, help="first seed (default 100: the evaluation seeds)")
    ap.add_argument("--captures", type=int, default=5, help="captures per series (default 5)")
    ap.add_argument("--only", default=None, help="run only the systems whose name contains this text")
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.captures < 2:
        ap.error("--seeds must be at least 1 and --captures at least 2")
    print(HEADER, flush=True)
    with tempfile.TemporaryDirectory(prefix="bench-seasons-") as tmp:
        for n, (name, system) in enumerate(SYSTEMS.items()):
            if args.only and args.only not in name:
                continue
            work = Path(tmp) / f"system{n}"
            work.mkdir()
            results = [run_series(system, args.first_seed + i, args.captures, work) for i in range(args.seeds)]
            print(table_row(name, results, args.captures), flush=True)


if __name__ == "__main__":
    main()
