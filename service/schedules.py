"""Overnight processing: a farm's inbox folder scanned on a cron schedule.

A schedule is ``{inbox, cron, params, tiling}`` owned by a tenant. The
`ScheduleClock` thread sleeps until the earliest ``next_run_at`` (a local-time cron
expression, default ``0 1 * * *`` = 01:00 every night), then `run_schedule` submits one
job per new capture in the inbox: every ``*.las`` / ``*.laz`` file (and ``*.ply``, ``*.pcd``,
``*.e57``, ``*.xyz``, ``*.pts``, converted to LAZ when taken) whose sha256 this
schedule has not handled before. Handled files (accepted, or rejected as unusable) are
recorded in the store, so a capture is never processed twice. A capture still being
copied in (written to within ``capture_settle_s``) is left for a scan that follows
as soon as it has settled. A run the service missed while it was down happens once at
the next start.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import threading
import time
import unicodedata
import uuid
from datetime import datetime
from pathlib import Path
from typing import Any

from croniter import croniter
from croniter.croniter import CroniterBadDateError

from pipeline.errors import InputError, ParameterError
from service.background import Background
from service.db.block_files import accept_block
from service.db.errors import NotFoundError
from service.db.jobstore import Store
from service.quotas import QuotaExceeded
from service.settings import Settings
from service.tempfiles import process_dir
from service.webhooks import rejected_event

log = logging.getLogger("orchard.schedules")

DEFAULT_CRON = "0 1 * * *"
#: LAS/LAZ and the point formats converted to LAZ (pipeline.formats); not .txt or .csv,
#: which an inbox may hold for other reasons
CAPTURE_SUFFIXES = (".las", ".laz", ".ply", ".pcd", ".e57", ".xyz", ".pts")
_CHUNK = 1 << 20
LAS_MAGIC = b"LASF"  #: the first 4 bytes of every LAS and LAZ file (file signature)
_scan_locks: dict[str, threading.Lock] = {}
_scan_locks_guard = threading.Lock()


def scan_lock(tenant_id: str) -> threading.Lock:
    """The lock a tenant's inbox scans take in turn: one farm's scan waits for its own
    farm's other scans only, not behind another farm copying a large capture."""
    with _scan_locks_guard:
        return _scan_locks.setdefault(tenant_id, threading.Lock())


_CRON_FIELDS = (
    ("minute", "0-59"),
    ("hour", "0-23"),
    ("day-of-month", "1-31, or L for the last day"),
    ("month", "1-12 or JAN-DEC"),
    ("weekday", "0-7 or SUN-SAT, 0 and 7 being Sunday"),
)
_CRON_EXAMPLE = "e.g. '0 1 * * *' for 01:00 every night"
# croniter's R (a random value, drawn again each time the next run is worked out: the
# schedule wandered) and H (a hashed one)
_CRON_RANDOM = re.compile(r"(?:^|,)[RH](?:$|[(/,])", re.IGNORECASE)


def validate_cron(expr: str) -> str:
    """The expression, stripped, if it is a valid 5-field cron expression that ever
    matches; ParameterError naming the field at fault otherwise."""
    expr = " ".join(str(expr).split())
    fields = expr.split(" ") if expr else []
    if len(fields) != 5:
        raise ParameterError(
            f"invalid cron expression {expr!r}: it has {len(fields)} field(s); use 5, "
            f"'minute hour day-of-month month weekday', {_CRON_EXAMPLE}"
        )
    for i, (field, (name, values)) in enumerate(zip(fields, _CRON_FIELDS)):
        alone = " ".join(field if j == i else "*" for j in range(5))
        if _CRON_RANDOM.search(field) or not croniter.is_valid(alone):
            raise ParameterError(
                f"invalid cron expression {expr!r}: its {name} field {field!r} is not valid (values {values}; "
                f"'*', lists 'a,b', ranges 'a-b' and steps '*/n' or 'a-b/n' with n > 0); {_CRON_EXAMPLE}"
            )
    if not croniter.is_valid(expr):
        raise ParameterError(f"invalid cron expression {expr!r}; {_CRON_EXAMPLE}")
    try:  # valid fields can still name a day that never comes ('0 0 31 2 *')
        croniter(expr, datetime(2000, 1, 1).astimezone()).get_next(datetime)
    except (CroniterBadDateError, ValueError):
        raise ParameterError(f"cron expression {expr!r} never matches a date (e.g. 30 or 31 February)") from None
    return expr


def next_run_time(cron: str, after: datetime | float) -> datetime:
    """First time strictly after ``after`` that ``cron`` matches, in local time (timezone-aware).

    ``after`` is a datetime (naive = local time) or a POSIX timestamp. The expression is
    matched against the server's local wall clock (``TZ``), daylight-saving changes
    included: ``0 1 * * *`` is 01:00 on the nights either side of a change too. A time
    the clock skips (02:30 when it jumps from 02:00 to 03:00) runs when the clock has
    passed it (03:30), a time it shows twice runs once.
    """
    if isinstance(after, datetime):
        after_ts = after.timestamp()  # naive: local time
    else:
        after_ts = float(after)
    # croniter steps through naive wall-clock times; time.mktime turns each into an
    # instant by the local zone's rules for that date (a fixed UTC offset, as an aware
    # start would give, is off by an hour across a change)
    wall = datetime.fromtimestamp(after_ts).replace(microsecond=0)
    try:
        it = croniter(validate_cron(cron), wall)
        for _ in range(10_000):
            candidate = it.get_next(datetime)
            ts = time.mktime(candidate.timetuple()[:8] + (-1,))
            if ts > after_ts:
                return datetime.fromtimestamp(ts).astimezone()
    except CroniterBadDateError:
        pass
    raise ParameterError(
        f"cron expression {cron!r} matches no date after {datetime.fromtimestamp(after_ts).astimezone().isoformat()}"
    ) from None


def validate_inbox(inbox: str, *, root: Path | None = None, base: Path | None = None, root_label: str = "the allowed inbox root") -> Path:
    """The resolved inbox folder; ParameterError if it lies outside ``root``, does not
    exist or is not a folder.

    Relative paths are resolved against ``base`` (the command line's working folder);
    without ``base`` they are refused (the server's working folder means nothing to a client).
    A path outside ``root`` is refused before anything about it is looked up, so the
    message says nothing about folders a client may not use.
    """
    raw = str(inbox)
    if not raw or "\x00" in raw:
        raise ParameterError("inbox must be a folder path")
    path = Path(raw)
    if base is not None and raw.startswith("~"):  # the command line expands ~ like a shell; the API does not
        try:
            path = path.expanduser()
        except RuntimeError:
            raise ParameterError(f"inbox {raw!r}: cannot expand '~'") from None
    if not path.is_absolute():
        if base is None:
            raise ParameterError(f"inbox {raw!r} must be an absolute path to a folder on the server")
        path = base / path
    try:
        path = path.resolve()
    except (OSError, RuntimeError, ValueError):
        raise ParameterError(f"inbox {raw!r} cannot be resolved to a folder") from None
    if root is not None:
        root = Path(root).resolve()
        if path != root and root not in path.parents:
            raise ParameterError(f"inbox {raw!r} is outside {root_label} {str(root)!r}")  # as given: resolved, it could show where a link leads
    try:
        exists, is_dir = path.exists(), path.is_dir()
    except (OSError, ValueError):
        raise ParameterError(f"inbox {raw!r} cannot be resolved to a folder") from None
    if not exists:
        raise ParameterError(f"inbox {str(path)!r} does not exist; create the folder where the captures land first")
    if not is_dir:
        raise ParameterError(f"inbox {str(path)!r} is not a folder")
    if not os.access(path, os.R_OK | os.X_OK):
        raise ParameterError(f"inbox {str(path)!r} is not readable by the service")
    return path


def tenant_inbox_root(settings: Settings, tenant_name: str) -> Path:
    """The folder a tenant's inboxes must lie in when it creates schedules over HTTP:
    ``<inbox root>/<tenant name>``, the inbox root being ``ORCHARD_INBOX_ROOT`` or
    ``<data dir>/inboxes``. Created if missing (where the service may)."""
    name = str(tenant_name)
    if name in (".", "..") or any(c in name for c in "/\\\x00"):
        raise ParameterError(
            f"tenant {name!r} has no inbox folder (its name is not a folder name); "
            "an operator can create its schedules with `orchard schedules create`"
        )
    folder = Path(settings.http_inbox_root) / name
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        pass  # validate_inbox says it does not exist
    return folder


def check_inbox_use(inbox: Path, *, settings: Settings, store: Store, tenant_id: str) -> None:
    """ParameterError if ``inbox`` (resolved) is one of the service's own folders or
    another tenant's inbox (a schedule would hand their files to this tenant), or
    already has a schedule (each capture would be processed once per schedule)."""
    data = Path(settings.data_dir).resolve()
    own = [data / "blocks", data / "jobs", data / "tmp"]
    if inbox == data or any(inbox == d or d in inbox.parents for d in own):
        raise ParameterError(f"inbox {str(inbox)!r} is a folder of the service's own data; captures must land elsewhere")
    for sched in store.schedules.list_any_tenant():
        if Path(sched["inbox"]) != inbox:
            continue
        if sched["tenant_id"] != tenant_id:
            raise ParameterError(f"inbox {str(inbox)!r} is already another tenant's inbox")
        # two schedules on one inbox would each take every capture
        raise ParameterError(
            f"inbox {str(inbox)!r} already has schedule {sched['id']} (cron {sched['cron']!r}); "
            "change that one's cron, parameters or tiling instead (PATCH /v1/schedules/ID, 'orchard schedules update')"
        )


def accepted_suffixes() -> tuple[str, ...]:
    """The file types an inbox takes (lower case, with the dot); a file of any other type
    is ignored, and `ignored_files` says so."""
    return CAPTURE_SUFFIXES


def captures(inbox: Path) -> list[Path]:
    """Point files (:data:`CAPTURE_SUFFIXES`) directly in ``inbox`` (not in sub-folders), sorted by name.

    Symbolic links are not captures: a link could hand a farm a file outside its inbox
    (another farm's capture), so only files that are really in the folder are taken.
    """
    out = []
    try:
        entries = sorted(inbox.iterdir())
    except OSError as exc:
        raise InputError(f"cannot read inbox {str(inbox)!r}: {exc.strerror}") from None
    for p in entries:
        if p.suffix.lower() in accepted_suffixes() and not p.name.startswith(".") and not p.is_symlink() and p.is_file():
            out.append(p)
    return out


def ignored_why(path: Path) -> str | None:
    """Why a scan passes over an entry of an inbox, or None if it is a capture it takes
    (or a hidden file, not shown: copies in progress, ``.DS_Store``)."""
    if path.name.startswith("."):
        return None
    if path.is_symlink():
        return "a link: only files really in the inbox are taken"
    if path.is_dir():
        return "a folder: only files directly in the inbox are taken"
    suffix = path.suffix.lower()
    if suffix in accepted_suffixes():
        return None if path.is_file() else "not a regular file"
    kind = f"a {suffix} file" if suffix else "a file without a type suffix"
    return f"{kind}: the inbox takes {', '.join(accepted_suffixes())} files only"


def ignored_files(inbox: Path) -> list[dict[str, str]]:
    """The entries of ``inbox`` a scan passes over, ``[{"file", "reason"}]`` by name
    (hidden files left out); a grower who drops a ``.xyz`` file learns why nothing came of it."""
    try:
        entries = sorted(inbox.iterdir())
    except OSError:
        return []
    out = []
    for p in entries:
        try:
            why = ignored_why(p)
        except OSError:
            continue
        if why is not None:
            out.append({"file": display_name(p), "reason": why})
    return out


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _copy_hashed(src: Path, dst: Path) -> tuple[str, int]:
    h = hashlib.sha256()
    n = 0
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        while chunk := fin.read(_CHUNK):
            h.update(chunk)
            fout.write(chunk)
            n += len(chunk)
    return h.hexdigest(), n


def printable(text: str) -> str:
    """``text`` without control and format characters (newlines, escape sequences,
    right-to-left overrides), as file names are shown in the API and the reports."""
    return "".join(c for c in text if unicodedata.category(c)[0] != "C")


def display_name(path: Path) -> str:
    """A file name as text, whatever its bytes (undecodable ones as ``\\xNN``), without
    control characters (a capture's name reached the API and the report's title raw)."""
    return printable(os.fsencode(path.name).decode("utf-8", "backslashreplace")).strip() or "(unnamed)"


def run_schedule(
    store: Store, settings: Settings, schedule: dict[str, Any], *, now: float | None = None, by_clock: bool = False
) -> dict[str, Any]:
    """Submit a job for every new capture in the schedule's inbox; returns what was done.

    Returns ``{"schedule_id", "jobs": [job ids], "skipped": n already handled,
    "rejected": [{"file", "error"}], "waiting": [file names], "ignored": [{"file",
    "reason"}]}`` (files of other types, see `ignored_files`). Unusable files are
    recorded as handled (with their error) so they are not retried every night. A
    capture written to within ``settings.capture_settle_s`` of ``now`` (or changed while
    it was read) is still arriving: it is left as *waiting*, not recorded, for a later
    scan, and the schedule's next run is brought forward to when it will have settled (a
    scan asked for by hand said "waiting" and then left it to the next cron time, a month
    away for a monthly schedule). A file whose name is not valid UTF-8 is rejected
    without being recorded (taken once renamed), and a capture that fails in any other
    unexpected way is rejected and logged without stopping the scan of the others.

    The schedule is read again before each capture's job is queued: a change made during
    a long scan applies to the jobs queued after it, and a pause (``by_clock``: the
    clock's scan; a scan by hand runs on) or a deletion ends the scan there.
    """
    result: dict[str, Any] = {"schedule_id": schedule["id"], "jobs": [], "skipped": 0, "rejected": [], "waiting": [], "ignored": []}
    inbox = Path(schedule["inbox"])
    if not inbox.is_dir():
        raise InputError(f"inbox {str(inbox)!r} of schedule {schedule['id']} no longer exists")
    if inbox.resolve() != inbox:  # checked when the schedule was made: it must still be that folder
        raise InputError(f"inbox {str(inbox)!r} of schedule {schedule['id']} is now a link to another folder; not scanned")
    now = time.time() if now is None else now
    tenant_id = schedule["tenant_id"]
    with scan_lock(tenant_id):
        for path in captures(inbox):
            schedule = _current(store, schedule["id"], by_clock=by_clock)
            if schedule is None:
                break
            name = display_name(path)
            try:
                outcome = _take_capture(store, settings, schedule, path, name, now, by_clock=by_clock)
            except Exception as exc:  # one capture must not stop the scan of the others (logged)
                log.warning("schedule %s: capture %s could not be taken", schedule["id"], name, exc_info=True)
                # the farm sees the kind of failure, not the server's paths; the log has the rest
                why = exc.strerror if isinstance(exc, OSError) and exc.strerror else type(exc).__name__
                outcome = ("rejected", f"could not be taken ({why}); it is tried again at the next scan")
            kind, detail = outcome
            if kind == "stopped":
                break
            if kind == "job":
                result["jobs"].append(detail)
            elif kind == "skipped":
                result["skipped"] += 1
            elif kind == "waiting":
                result["waiting"].append(name)
            else:
                result["rejected"].append({"file": name, "error": detail})
    result["ignored"] = ignored_files(inbox)
    if result["rejected"]:  # told to the farm's webhooks (a scan by hand's rejections too)
        rejected_event(store, tenant_id=tenant_id, schedule_id=result["schedule_id"], rejected=result["rejected"])
    if result["waiting"]:
        store.schedules.bring_forward(schedule["id"], settled_at(settings, now))
    return result


def settled_at(settings: Settings, now: float) -> float:
    """When a capture seen arriving at ``now`` is looked at again."""
    return now + max(settings.capture_settle_s, 1.0)


def still_arriving(stat: os.stat_result, now: float, settle_s: float) -> bool:
    """Whether a file was written to (or its times set) less than ``settle_s`` before ``now``.

    A copy that keeps the source's times (``cp -p``, ``rsync -a``, unzip) from a device
    whose clock runs ahead gives a modification time in the future: read as "written just
    now", such a capture waited until that date came round, and its inbox was re-read at
    every settle interval meanwhile. A time further ahead than ``settle_s`` says nothing;
    the change time (ctime, the server's own clock, set again by every write and by
    setting the times) does.
    """
    return any(abs(now - t) < settle_s for t in (stat.st_mtime, stat.st_ctime))


def _current(store: Store, schedule_id: str, *, by_clock: bool) -> dict[str, Any] | None:
    """The schedule as stored now; None if it was deleted, or paused during a clock's scan."""
    try:
        schedule = store.schedules.get_any_tenant(schedule_id)
    except NotFoundError:
        return None
    return None if by_clock and schedule["paused"] else schedule


def _take_capture(
    store: Store, settings: Settings, schedule: dict[str, Any], path: Path, name: str, now: float, *, by_clock: bool = False
) -> tuple[str, str | None]:
    """One capture of a scan: ("job", job id), ("skipped", None), ("waiting", None),
    ("rejected", error), or ("stopped", None) when the schedule was paused or deleted
    while the capture was read (nothing queued; a later scan takes it)."""
    try:
        path.name.encode("utf-8", "strict")  # undecodable bytes are surrogates here
    except UnicodeEncodeError:
        return "rejected", "the file name is not valid UTF-8 (as names from some USB sticks or shares are); rename the file to have it taken"
    try:
        stat = path.stat()
        if still_arriving(stat, now, settings.capture_settle_s):  # still being copied in
            return "waiting", None
        state = _file_state(stat)
        sha = store.schedules.known_hash(str(path), state)
        if sha is None:
            sha = file_sha256(path)
            if _file_state(path.stat()) == state:  # not written to while it was read
                store.schedules.remember_hash(str(path), state, sha)
    except OSError as exc:
        return "rejected", f"cannot read: {exc.strerror}"
    # taken before by this schedule, or by an earlier one of this farm (deleted to change its cron)
    if store.schedules.file_seen(schedule["id"], sha) or store.schedules.capture_scheduled(schedule["tenant_id"], sha):
        return "skipped", None
    error = _header_problem(path, name)  # before the copy: a 2 GB file refused after it held the scan for seconds
    if error is not None:
        store.schedules.record_file(schedule_id=schedule["id"], sha256=sha, path=str(path), job_id=None, error=error)
        return "rejected", error
    tmp = process_dir(settings.tmp_dir) / f"inbox-{uuid.uuid4().hex}.part"
    try:
        if store.blocks.by_sha(schedule["tenant_id"], sha) is None:  # the same bytes uploaded before take no more room
            store.quotas.check_storage(schedule["tenant_id"], stat.st_size)
        copied_sha, size = _copy_hashed(path, tmp)
        if copied_sha != sha or path.stat().st_mtime != stat.st_mtime:  # written to meanwhile
            return "waiting", None
        block, _ = accept_block(
            store,
            blocks_dir=settings.blocks_dir,
            tenant_id=schedule["tenant_id"],
            tmp_path=tmp,
            sha256=sha,
            size_bytes=size,
            filename=name,
        )
    except QuotaExceeded as exc:  # not recorded: taken at a scan after the quota allows it
        return "rejected", f"{exc}; the capture is tried again at the next scan"
    except InputError as exc:
        store.schedules.record_file(schedule_id=schedule["id"], sha256=sha, path=str(path), job_id=None, error=str(exc))
        return "rejected", str(exc)
    finally:
        tmp.unlink(missing_ok=True)
    schedule = _current(store, schedule["id"], by_clock=by_clock)  # reading may have taken minutes
    if schedule is None:
        return "stopped", None
    try:
        job = store.schedules.create_job(schedule=schedule, block_id=block["id"], sha256=sha, path=str(path), capture=name)
    except QuotaExceeded as exc:
        return "rejected", f"{exc}; the capture is tried again at the next scan"
    if job is None:  # another scan of this inbox (another process) took it first
        return "skipped", None
    return "job", job["id"]


def _header_problem(path: Path, name: str) -> str | None:
    """Why an inbox file is no usable point file, read from its signature and header
    where it lies (the header and VLRs only); None if it looks usable. The copy taken
    afterwards is checked again, as any upload."""
    # here: laspy and pyproj (~0.6 s) are no cost of `orchard schedules --help`, which imports service.schedules
    from pipeline.blockinfo import read_info
    from pipeline.formats import open_points, sniff

    try:
        if path.suffix.lower() in (".las", ".laz"):
            with open(path, "rb") as fh:
                if fh.read(len(LAS_MAGIC)) != LAS_MAGIC:
                    return f"{name}: not a LAS or LAZ file (it does not begin with the LAS signature 'LASF')"
            read_info(str(path))
        elif (fmt := sniff(path)) == "las":
            read_info(str(path))
        else:
            open_points(path, fmt)  # its header: the points are read when the copy is converted
    except InputError as exc:
        return str(exc).replace(str(path), name).replace(path.name, name)
    except OSError:
        return None  # unreadable now: the copy says why
    return None


def _file_state(stat: os.stat_result) -> tuple[int, int, int, int]:
    """What changes when a file is written to or replaced: size, mtime_ns, ctime_ns, inode."""
    return stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino


class ScheduleClock(Background):
    """Background thread that runs every schedule at its cron times (``wake()``: a
    schedule was created or changed).

    ``on_jobs`` is called after a run that queued jobs (the runner's wake-up).
    """

    def __init__(self, store: Store, settings: Settings, *, on_jobs=None) -> None:
        super().__init__("orchard-schedules")
        self.store = store
        self.settings = settings
        self.on_jobs = on_jobs

    def tick(self, now: float | None = None) -> float:
        """Run the schedules that are due; return the earliest next run time (POSIX seconds)."""
        now = time.time() if now is None else now
        earliest = now + self.settings.schedule_poll_s
        for sched in self.store.schedules.list_any_tenant():
            if sched["paused"]:
                continue
            nxt = sched["next_run_at"]
            try:
                if nxt is None:
                    nxt = next_run_time(sched["cron"], now).timestamp()
                    self.store.schedules.set_times(sched["id"], cron=sched["cron"], last_run_at=None, next_run_at=nxt)
                elif nxt <= now:
                    again = None
                    try:
                        res = run_schedule(self.store, self.settings, sched, now=now, by_clock=True)
                        log.info("schedule %s: %d new jobs, %d already handled, %d rejected, %d ignored, %d still arriving",
                                 sched["id"], len(res["jobs"]), res["skipped"], len(res["rejected"]),
                                 len(res["ignored"]), len(res["waiting"]))
                        if res["jobs"] and self.on_jobs:
                            self.on_jobs()
                        if res["waiting"]:  # look again once they have settled, not a day later
                            again = settled_at(self.settings, now)
                    except Exception as exc:  # noqa: BLE001 - one farm's broken inbox must not stop the others
                        log.warning("schedule %s failed: %s", sched["id"], exc)
                    nxt = next_run_time(sched["cron"], now).timestamp()
                    if again is not None:
                        nxt = min(nxt, again)
                    self.store.schedules.set_times(sched["id"], cron=sched["cron"], last_run_at=now, next_run_at=nxt)
            except ParameterError as exc:
                log.warning("schedule %s has an invalid cron expression: %s", sched["id"], exc)
                continue
            earliest = min(earliest, nxt)
        return earliest

    def run(self) -> None:
        while not self._stopping.is_set():
            try:
                earliest = self.tick()
            except Exception as exc:  # noqa: BLE001 - keep the clock alive (e.g. store briefly locked)
                log.warning("schedule clock: %s", exc)
                earliest = time.time() + self.settings.schedule_poll_s
            self._wake.wait(max(0.0, min(earliest - time.time(), self.settings.schedule_poll_s)))
            self._wake.clear()
