"""A finished job's outputs as the service serves them: where each file is, and the report.

`job_output` finds an output of a tenant's job (ConflictError, a 409, while the job is
not done, or when it failed); `require_output` turns a missing file into a
NotFoundError (404); `ensure_report` draws the HTML report and its map on first use.
The API and the browser's pages use the same rules.
"""

from __future__ import annotations

from collections.abc import Callable
from datetime import datetime
from pathlib import Path

from service.db.errors import ConflictError, NotFoundError
from service.db.jobstore import Store
from service.jobfolders import job_dir
from service.reports import report as reports
from service.settings import Settings


def job_block_name(job: dict, block: dict | None) -> str | None:
    """How a job names its block to the farm: the inbox file its schedule took it from,
    else the block's file name (its first upload's); None if neither is known."""
    return job.get("capture") or (block or {}).get("filename")


def job_output(store: Store, settings: Settings, tenant: dict, job_id: str, name: str) -> tuple[dict, Path]:
    """The job record and the path of its output file ``name`` (which may be missing:
    see `require_output`); ConflictError (409) unless the job is done."""
    job = store.jobs.get(tenant["id"], job_id)
    if job["state"] in ("failed", "cancelled"):  # "once it is done" would never come
        raise ConflictError(f"job {job_id} is {job['state']} and has no results; submit its block again "
                            f"with POST /v1/jobs (GET /v1/jobs/{job_id} says why it ended)")
    if job["state"] != "done":
        raise ConflictError(f"job {job_id} is {job['state']}; results are available once it is done (GET /v1/jobs/{job_id})")
    path = job_dir(settings, job_id) / name
    outputs = (job.get("outcome") or {}).get("outputs") or {}
    if not path.exists():
        for value in outputs.values():
            if isinstance(value, str) and Path(value).name == name and Path(value).exists():
                path = Path(value)
                break
    return job, path


def require_output(path: Path, what: str) -> Path:
    """``path``, or NotFoundError (404) naming ``what`` when the file is missing."""
    if not path.exists():
        raise NotFoundError(f"the {what} of this job is missing on the server")
    return path


def ensure_report(store: Store, settings: Settings, job: dict, *, sample: dict | None = None,
                  draw: Callable[..., Path] | None = None) -> Path:
    """``report.html`` (and ``map.png``) of a finished job, both written again if either is
    missing (a lost ``map.png`` beside its report would fail every request for either).

    ``sample``: the map's points, if the job kept them (``workers.jobspec.JobOutcome.sample``);
    else they are read from the block and ``points.parquet``. ``draw(write_report, **its
    arguments)``: where the report is drawn (the runner's: a task on a dask worker, as it
    reads the block's points and loads matplotlib); by default in this process.
    """
    out = job_dir(settings, job["id"])
    html_path = out / "report.html"
    if html_path.exists() and (out / "map.png").exists():
        return html_path
    block = store.blocks.get(job["tenant_id"], job["block_id"])
    if not Path(block["path"]).is_file():  # not the farm's fault, and not its file name to show
        raise NotFoundError("the uploaded block of this job is missing on the server, so its report cannot be "
                            "drawn; the per-tree downloads (trees.csv, trees.parquet) still work")
    _, trees = job_output(store, settings, {"id": job["tenant_id"]}, job["id"], "trees.parquet")
    _, points = job_output(store, settings, {"id": job["tenant_id"]}, job["id"], "points.parquet")
    outcome = job.get("outcome") or {}
    rows_total = outcome.get("n_trees")
    finished = job.get("finished_at")
    summary = {
        "Block": job_block_name(job, block) or block["id"],
        "Job": job["id"],
        # the server's local time, as its schedules' cron times, with the zone said
        "Finished": datetime.fromtimestamp(finished).astimezone().strftime("%Y-%m-%d %H:%M %Z (UTC%z)") if finished else "",
        "Points": str((block.get("info") or {}).get("n_points", "")),
        "Trees": str(rows_total if rows_total is not None else ""),
    }
    capture = store.orchard_blocks.capture_of_job(job["tenant_id"], job["id"])
    if capture is not None:  # a capture of an orchard block: which, and when
        summary["Orchard block"] = f"{capture['orchard_block_name']} (capture {capture['seq']})"
        summary["Captured"] = capture.get("captured_at") or ""
    warning = None
    if outcome.get("partial"):
        failed = ", ".join(str(t) for t in outcome.get("failed_tiles") or []) or "some"
        warning = (f"Partial result: tile(s) {failed} of this block failed. Trees standing in them are missing "
                   "from this report and the downloads, and their points are in no tree.")
    return (draw or _here)(
        reports.write_report,
        block_path=block["path"],
        trees_parquet=require_output(trees, "trees.parquet"),
        points_parquet=require_output(points, "points.parquet"),
        out_dir=out,
        title=f"Orchard report — {job_block_name(job, block) or block['id']}",
        summary=summary,
        warning=warning,
        sample=sample,
    )


def _here(fn: Callable[..., Path], **kwargs) -> Path:
    return fn(**kwargs)
