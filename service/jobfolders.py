"""Where a job's files live: its result folder under the data folder, and its work store
(its tiles while it runs)."""

from __future__ import annotations

from pathlib import Path

from service.settings import Settings


def job_dir(settings: Settings, job_id: str) -> Path:
    """Where a job's results live: ``data_dir/jobs/<job id>/``."""
    return settings.jobs_dir / job_id


def work_dir_of(settings: Settings, job_id: str) -> str:
    """A job's work store (its tiles): ``<work_dir>/<job id>``, or ``<job dir>/_work``."""
    if settings.work_dir:
        return f"{settings.work_dir.rstrip('/')}/{job_id}"
    return str(job_dir(settings, job_id) / "_work")
