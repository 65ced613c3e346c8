"""Service settings: one typed object, built by an entry point and passed down.

Every field can be set with an environment variable ``ORCHARD_<FIELD>`` (for example
``ORCHARD_DATA_DIR=/srv/orchard``) or, for the command line, with an option that
overrides it. Nothing reads the environment at import time: `Settings()` is called
by `orchard serve`, `orchard tokens`, `orchard schedules` and `orchard demo`.
"""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, field_validator
from pydantic.fields import FieldInfo
from pydantic.types import AllowInfNan
from pydantic_settings import BaseSettings, SettingsConfigDict

from workers.runoptions import RunOptions


def _run_field(name: str, description: str, **default):
    """A setting that stands for a run option (`RunOptions`): its bounds, and its default
    unless ``default`` gives the deployment's."""
    field = FieldInfo.merge_field_infos(RunOptions.model_fields[name], description=description, **default)
    field.metadata.append(AllowInfNan(False))  # the model's config says it for all its fields
    return field


class Settings(BaseSettings):
    """Settings of the orchard service (environment prefix ``ORCHARD_``)."""

    model_config = SettingsConfigDict(env_prefix="ORCHARD_", extra="ignore")

    data_dir: Path = Field(
        Path("orchard-data"), validate_default=True,
        description="folder of the job store (SQLite), uploaded blocks and job results (a relative path is taken from the current folder)",
    )
    host: str = Field("127.0.0.1", description="address the HTTP server binds")
    port: int = Field(8000, ge=0, le=65535, description="port the HTTP server binds (0 = any free port)")
    scheduler: str | None = Field(None, description="dask scheduler address (tcp://HOST:PORT); unset = embedded LocalCluster")
    scheduler_timeout_s: float = Field(
        20.0, gt=0, le=600, description="how long a job waits to reach the dask scheduler before that attempt fails [s]"
    )
    n_workers: int = _run_field("workers", "workers of the embedded LocalCluster")
    threads_per_worker: int = Field(1, ge=1, le=64, description="threads per worker of the embedded LocalCluster")
    worker_memory_gb: float = _run_field(
        "worker_memory", "memory budget of one worker [GB]: a block without a tile size that would need more in one "
        "piece is tiled, with tiles chosen to fit it", default=2.0,
    )
    dashboard: bool = Field(False, description="start the dask dashboard of the embedded LocalCluster")
    dask_host: str = Field(
        "127.0.0.1", min_length=1,
        description="address the embedded LocalCluster's scheduler, workers and dashboard listen on "
        "(none asks for a login; 0.0.0.0 exposes them on every interface)",
    )
    work_dir: str | None = Field(
        None, description="work store for tiles (folder or fsspec URL such as s3://bucket/orchard); a job uses <work_dir>/<job id>; unset = data_dir/jobs/<id>/_work"
    )
    max_upload_mb: float = Field(4096.0, gt=0, description="largest accepted block upload [MB]")
    min_free_mb: float = Field(
        512.0, ge=0, description="/healthz answers 'not ok' (503) while the data folder's disk has less free space [MB]"
    )
    max_request_kb: int = Field(256, ge=1, description="largest accepted request body other than an upload [kB]; a job's JSON is a few kB, and a body past this is refused from its length before it is read")
    upload_idle_s: float = Field(
        300.0, gt=0, le=86400,
        description="an upload whose body sends nothing for this long is dropped (408) and its partial file deleted [s]",
    )
    upload_deadline_s: float = Field(
        3600.0, gt=0, le=7 * 86400,
        description="an upload still arriving this long after it began is dropped (408) and its partial file deleted [s]",
    )
    upload_min_kbps: float = Field(
        8.0, ge=0, description="an upload that has averaged less than this since it began is dropped (408), judged "
        "from upload_idle_s on (0 = no minimum) [kB/s]",
    )
    header_timeout_s: float = Field(
        10.0, gt=0, le=600, description="a request whose line and headers have not all arrived this long after the "
        "connection opened (or its first byte on a kept-alive one) is answered 408 and closed [s]",
    )
    body_timeout_s: float = Field(
        120.0, gt=0, le=86400, description="a request body other than an upload that has not all arrived this long "
        "after its headers is cut off [s]",
    )
    max_connections: int = Field(
        1000, ge=1, description="open HTTP connections in all; past it (or past the process's file-handle limit less "
        "a reserve) a new one is answered 503 and closed",
    )
    max_connections_per_client: int = Field(
        64, ge=1, description="open HTTP connections from one address (behind a reverse proxy: the proxy's); past it "
        "a new one is answered 503 and closed",
    )
    log_file: Path | None = Field(
        None, description="write the log to this file, rotated (unset: stderr); repeated warnings are rate-limited either way",
    )
    log_max_mb: float = Field(10.0, gt=0, description="size at which the log file is rotated [MB]")
    log_backups: int = Field(5, ge=0, le=100, description="rotated log files kept beside the log file")
    runner: bool = Field(True, description="run queued jobs in this process (background runner thread)")
    scheduling: bool = Field(True, description="run overnight schedules in this process (schedule clock thread)")
    inbox_root: Path | None = Field(
        None,
        description="if set, schedule inbox folders must lie inside this folder; a tenant creating a schedule over HTTP "
        "may only use folders in <inbox root>/<tenant name> (unset: <data_dir>/inboxes/<tenant name>)",
    )
    schedule_poll_s: float = Field(30.0, gt=0, le=3600, description="longest sleep of the schedule clock between checks [s]")
    capture_settle_s: float = Field(
        60.0, ge=0, le=86400,
        description="a capture written to within this many seconds is still arriving: a scan leaves it and looks again this much later [s]",
    )
    runner_poll_s: float = Field(1.0, gt=0, le=60, description="longest sleep of the runner between looks at the queue [s]")
    job_retries: int = Field(
        2, ge=0, le=20,
        description="times a job is queued again after the dask cluster could not be reached or was lost during it "
        "(an overnight job outlives a cluster restart); other failures are final",
    )
    retry_delay_s: float = Field(300.0, ge=0, le=86400, description="wait before such a job runs again [s]")
    max_crashes: int = Field(
        2, ge=1, le=100,
        description="a job during which the service process died (killed, out of memory, power cut) this many times "
        "is failed at the next start instead of run again: it may be what kills the service",
    )
    webhook_hosts: str = Field(
        "*", max_length=4000,
        description="host names a farm's webhook may call, comma-separated ('*': any); allow only hosts you trust "
        "(a webhook is a request made from the server)",
    )
    webhook_attempts: int = Field(6, ge=1, le=20, description="attempts to deliver a webhook call before it is given up")
    webhook_backoff_s: float = Field(
        30.0, ge=0, le=3600, description="wait after a webhook call's first failed attempt, doubled after each next one [s]")
    webhook_timeout_s: float = Field(10.0, gt=0, le=120, description="longest wait for a webhook receiver's answer [s]")
    webhook_poll_s: float = Field(5.0, gt=0, le=3600, description="longest sleep of the webhook sender between looks [s]")

    @field_validator("data_dir", "inbox_root", "log_file")
    @classmethod
    def _absolute_path(cls, v: Path | None) -> Path | None:
        # the store records block paths, and dask workers resolve relative ones against
        # their own folders: every path is absolute from here on
        return None if v is None else Path(os.path.abspath(os.path.expanduser(v)))

    @field_validator("work_dir")
    @classmethod
    def _absolute_work_dir(cls, v: str | None) -> str | None:
        if not v:
            return None
        from workers.workstore import absolute_url  # here: numpy (~0.35 s) is no cost of `orchard tokens`

        return absolute_url(v)

    @property
    def store_path(self) -> Path:
        return self.data_dir / "orchard.sqlite"

    @property
    def blocks_dir(self) -> Path:
        return self.data_dir / "blocks"

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    @property
    def http_inbox_root(self) -> Path:
        """Root of the tenants' inbox folders for schedules created over HTTP."""
        return self.inbox_root if self.inbox_root is not None else self.data_dir / "inboxes"

    @property
    def tmp_dir(self) -> Path:
        return self.data_dir / "tmp"

    @property
    def worker_memory_bytes(self) -> float:
        return self.worker_memory_gb * 1e9

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)


def build_settings(**fields) -> Settings:
    """Settings from the environment, overridden by the command-line values given.

    ``fields`` maps Settings field names to values; ``None`` values are ignored, so an
    option the user did not give keeps the environment's (or the default) value.
    """
    return Settings(**{k: v for k, v in fields.items() if v is not None})
