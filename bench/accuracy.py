"""Accuracy over noise and tree spacing: ours (the product path) and the baselines.

Ours is scored the way a user would get it: ``run_job`` writes ``trees.parquet`` and
``points.parquet`` and ``simulator.scoring.result.evaluate_result`` scores them against the
truth. The baselines (``bench.baselines``: closest-trunk segmentation, the paper as
published) return labels in memory and are scored by the same
``simulator.scoring.scores.score_labels`` on the same points. Blocks are scored in parallel
processes (one per usable core).
"""

from __future__ import annotations

import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bench.blocks import accuracy_params, make_block

METHODS = ("ours", "closest_trunk", "paper_with_our_trunks", "paper_as_published")
METRICS = ("trunk_precision", "trunk_recall", "trunk_f1", "trunk_mean_distance", "v_measure", "wood_f1")


def score_block(work: str, noise: float, spacing: float, seed: int, baselines: bool = True) -> dict:
    """All methods on one generated block; returns {method: metrics} plus block facts."""
    import numpy as np

    from pipeline.errors import NoTreesError
    from simulator.scoring.result import evaluate_result
    from simulator.scoring.scores import score_labels
    from pipeline.jobparams import JobParams
    from pipeline.params import PipelineParams
    from pipeline.reading import read_points
    from simulator.truth import read_truth
    from workers.job import run_job
    from workers.jobspec import JobSpec

    work_dir = Path(work)
    block = make_block(work_dir, f"acc-n{noise:g}-s{spacing:g}", accuracy_params(noise, spacing, seed))
    params = PipelineParams()
    out = {"noise": noise, "spacing": spacing, "n_points": block.n_points, "n_trees": block.n_trees, "methods": {}, "seconds": {}}
    result_dir = work_dir / "acc-results" / Path(block.las).stem
    shutil.rmtree(result_dir, ignore_errors=True)
    t = time.perf_counter()
    try:
        run_job(JobSpec(input_path=block.las, out_dir=str(result_dir), job=JobParams(pipeline=params)))
        out["methods"]["ours"] = evaluate_result(block.truth, str(result_dir))
    except NoTreesError as exc:
        # "no trees found" is an answer, scored as such: no trunks, every point tree 0.
        truth, true_trunks = read_truth(block.truth)
        n = len(truth["tree_id"])
        out["methods"]["ours"] = score_labels(
            true_tree_id=truth["tree_id"], true_is_wood=truth["is_wood"], true_trunks=true_trunks,
            pred_tree_id=np.zeros(n, np.int64), pred_is_wood=np.zeros(n, bool), found_trunks=np.zeros((0, 2)),
        )
        out["methods"]["ours"]["note"] = f"no trees found ({exc})"
    except Exception as exc:  # noqa: BLE001 - a failure is a result to report
        out["methods"]["ours"] = {"error": f"{type(exc).__name__}: {exc}"}
    out["seconds"]["ours"] = time.perf_counter() - t
    shutil.rmtree(result_dir, ignore_errors=True)
    if not baselines:
        return out
    try:
        from bench import baselines as bl
    except ImportError as exc:
        out["baselines_missing"] = str(exc)
        return out
    truth, true_trunks = read_truth(block.truth)
    xyz, info = read_points(block.las)
    origin = np.asarray(info.origin, dtype=np.float64)
    for name in METHODS[1:]:
        fn = getattr(bl, name, None)
        if fn is None:
            out["methods"][name] = {"error": f"bench.baselines.{name} not found"}
            continue
        t = time.perf_counter()
        try:
            res = fn(xyz, params=params)
            found = np.asarray(res.trunks, dtype=np.float64).reshape(-1, 3) + origin
            out["methods"][name] = score_labels(
                true_tree_id=truth["tree_id"], true_is_wood=truth["is_wood"], true_trunks=true_trunks,
                pred_tree_id=res.tree_id, pred_is_wood=res.is_wood, found_trunks=found,
            )
        except Exception as exc:  # noqa: BLE001
            out["methods"][name] = {"error": f"{type(exc).__name__}: {exc}"}
        out["seconds"][name] = time.perf_counter() - t
    return out


def run_grid(
    work: Path, noises, spacings, *, seed: int = 3, processes: int | None = None, log=print, baselines: bool = True
) -> list[dict]:
    """Score every (noise, spacing) block; returns one dict per block."""
    processes = processes or max(1, len(os.sched_getaffinity(0)))
    cells = [(n, s) for n in noises for s in spacings]
    results = []
    with ProcessPoolExecutor(max_workers=processes) as pool:
        futures = {pool.submit(score_block, str(work), n, s, seed + i, baselines): (n, s) for i, (n, s) in enumerate(cells)}
        for fut in futures:
            n, s = futures[fut]
            r = fut.result()
            log(f"  accuracy noise {n:g} m, spacing {s:g} m: " + ", ".join(
                f"{m} F1 {v.get('trunk_f1', float('nan')):.2f} vm {v.get('v_measure', float('nan')):.2f} wood {v.get('wood_f1', float('nan')):.2f}"
                if "error" not in v else f"{m} error" for m, v in r["methods"].items()))
            results.append(r)
    return results


def summarise(results: list[dict]) -> dict:
    """Mean of each metric per method over all blocks (errors excluded, counted)."""
    import numpy as np

    out = {}
    for m in METHODS:
        rows = [r["methods"][m] for r in results if m in r["methods"]]
        ok = [row for row in rows if "error" not in row]
        out[m] = {k: float(np.nanmean([row[k] for row in ok])) if ok else float("nan") for k in METRICS}
        out[m]["n_blocks"] = len(ok)
        out[m]["n_errors"] = len(rows) - len(ok)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.accuracy``: the accuracy grid of ``python -m bench``, ours only
    unless ``--baselines``, and the mean of each metric."""
    import argparse

    ap = argparse.ArgumentParser(description="the accuracy grid of python -m bench (same blocks and seeds)")
    ap.add_argument("--work", default="bench-work", help="folder for the generated blocks")
    ap.add_argument("--baselines", action="store_true", help="score the baselines too")
    ap.add_argument("--processes", type=int, default=None, help="parallel blocks (default: usable cores)")
    args = ap.parse_args(argv)
    noises, spacings = [0.0, 0.02, 0.05, 0.1], [3.0, 4.0, 5.0, 6.0, 8.0]
    blocks = run_grid(Path(args.work), noises, spacings, processes=args.processes, baselines=args.baselines)
    for m, v in summarise(blocks).items():
        if v["n_blocks"]:
            print(f"{m}: " + ", ".join(f"{k} {v[k]:.3f}" for k in METRICS) + f" ({v['n_blocks']} blocks)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
