"""Byte identity of budgeted jobs on a cluster across a change.

    python -m bench.budget_identity --write manifest.json      # before
    python -m bench.budget_identity --compare manifest.json    # after: exit 1 on any difference

:mod:`bench.identity`'s tiled runs give their tile size, and ``orchard process`` counts
a block that may fit its budget in its own process, so neither runs a job that counts
its block on the cluster to choose its tiles (:func:`workers.job.splits_while_counting`).
This runs that job: :func:`workers.job.run_job` with a memory budget that tiles each of
:mod:`bench.identity`'s blocks (made there if missing) on an in-process cluster of two
workers, and records the SHA-256 of every file it writes.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

from bench.identity import BLOCKS, manifest_arguments, measure, write_or_compare

#: a budget [GB] per block that tiles it (the smallest tile still fits)
BUDGETS = {"vase": 0.48, "spindle": 0.45, "hedge": 0.45}


def run(work: Path) -> dict[str, dict[str, str]]:
    """The hash of each output file of each block's budgeted job, by ``scene/budgeted``."""
    from distributed import Client, LocalCluster

    from workers.job import run_job
    from workers.jobspec import JobSpec
    from workers.runoptions import RunOptions

    manifest = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None,
                      memory_limit=0) as cluster, Client(cluster) as client:
        for scene, gb in BUDGETS.items():
            out = work / scene
            shutil.rmtree(out, ignore_errors=True)
            outcome = run_job(JobSpec(str(BLOCKS / f"{scene}.laz"), str(out), run=RunOptions(worker_memory=gb)),
                              client=client)
            files = {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(out.iterdir()) if f.is_file()}
            manifest[f"{scene}/budgeted"] = {"tiles": str(outcome.n_tiles), **files}
    return manifest


def main(argv: list[str] | None = None) -> int:
    args = manifest_arguments(argv, prog="python -m bench.budget_identity", description=__doc__.splitlines()[0],
                              work="/tmp/orchard-budget-identity-out")
    if not all((BLOCKS / f"{scene}.laz").exists() for scene in BUDGETS):
        measure(args.work / "identity")  # makes the blocks (and runs bench.identity's runs once)
    return write_or_compare(args, run(args.work), "entries")


if __name__ == "__main__":
    raise SystemExit(main())
