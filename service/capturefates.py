"""What became of every file in a schedule's inbox, as a person asks after it.

A capture a scan handled is *processed* (its job) or *rejected* (why), as the store
recorded it; a file in the inbox now that no scan has handled is *arriving* (still
being written to), *new* (settled; the next scan takes it) or *ignored* (a file of
another type, a folder or a link: why). Nothing here reads a capture's contents: a file
is matched to a record by the checksum a scan remembered for its path and state, so a
look is a directory listing and a few lookups, whatever the captures weigh.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from service.db.jobstore import Store
from service.schedules import captures, display_name, ignored_files, still_arriving
from service.settings import Settings
from service.wording import api_name, job_error

#: the fates, in the order a list shows them
FATES = ("arriving", "new", "rejected", "processed", "ignored")
#: most captures listed per schedule (counts cover all of them)
MAX_LISTED = 200


def capture_fates(store: Store, settings: Settings, schedule: dict[str, Any], *, now: float | None = None,
                  limit: int = MAX_LISTED, name: Callable[[str], str | None] = api_name) -> dict[str, Any]:
    """Every capture's fate for one schedule: ``{"captures": [...], "counts": {fate: n}}``.

    Each capture is ``{"file", "fate", "job_id", "job_state", "reason", "seen_at"}``:
    ``job_id``/``job_state`` for a processed one, ``reason`` for a rejected or ignored
    one (and for a processed one whose job failed: the job's error), ``seen_at`` when a
    scan handled it (POSIX seconds). Files now in the inbox come first, then the handled
    ones, newest first; at most ``limit`` are listed. ``name`` words a parameter a job's
    error names (the API's `api_name`, the command line's `cli_name`).
    """
    now = time.time() if now is None else now
    handled, counts = store.schedules.captures(schedule["id"], limit=limit)
    recorded = {r["sha256"] for r in handled}
    current: list[dict[str, Any]] = []
    inbox = Path(schedule["inbox"])
    ignored: list[dict[str, str]] = []
    if inbox.is_dir():
        try:
            found = captures(inbox)
        except Exception:  # noqa: BLE001 - an unreadable inbox: the records still tell what was handled
            found = []
        for path in found:
            entry = _unhandled(store, schedule, path, now, settings.capture_settle_s, recorded)
            if entry is not None:
                current.append(entry)
        ignored = ignored_files(inbox)
    out = current + [_handled(r, name) for r in handled] + [_capture(f["file"], "ignored", reason=f["reason"]) for f in ignored]
    counts = {"arriving": 0, "new": 0, **counts, "ignored": len(ignored)}
    for c in current:
        counts[c["fate"]] += 1
    return {"captures": out[:limit], "counts": {f: counts.get(f, 0) for f in FATES}}


def _capture(file: str, fate: str, *, job_id: str | None = None, job_state: str | None = None,
             reason: str | None = None, seen_at: float | None = None) -> dict[str, Any]:
    return {"file": file, "fate": fate, "job_id": job_id, "job_state": job_state, "reason": reason, "seen_at": seen_at}


def _handled(rec: dict[str, Any], name: Callable[[str], str | None]) -> dict[str, Any]:
    name = display_name(Path(rec["path"]))
    if rec["job_id"] is None:
        return _capture(name, "rejected", reason=rec["error"], seen_at=rec["seen_at"])
    reason = job_error(rec, name=name, prefix="job_") if rec["job_state"] == "failed" else None
    return _capture(name, "processed", job_id=rec["job_id"], job_state=rec["job_state"] or "deleted",
                    reason=reason, seen_at=rec["seen_at"])


def _unhandled(store: Store, schedule: dict[str, Any], path: Path, now: float, settle_s: float,
               recorded: set[str]) -> dict[str, Any] | None:
    """A capture in the inbox that no listed record covers (None if one does)."""
    name = display_name(path)
    try:
        path.name.encode("utf-8", "strict")
    except UnicodeEncodeError:
        return _capture(name, "rejected", reason="the file name is not valid UTF-8; rename the file to have it taken")
    try:
        stat = path.stat()
    except OSError:
        return None  # gone since the listing
    sha = store.schedules.known_hash(str(path), (stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino))
    if sha is not None and (sha in recorded or store.schedules.file_seen(schedule["id"], sha)):
        return None  # handled: listed from its record (or older than the records listed)
    if sha is not None and store.schedules.capture_scheduled(schedule["tenant_id"], sha):
        return None  # the same bytes were processed by an earlier schedule of this farm
    if still_arriving(stat, now, settle_s):
        return _capture(name, "arriving", reason="still being written to; taken once it has settled")
    return _capture(name, "new", reason="taken at the next scan")


def fate_line(capture: dict[str, Any]) -> str:
    """One capture as a line of text (the command line's list): fate, file, job or why."""
    detail = ""
    if capture["job_id"]:
        detail = f"job {capture['job_id']} ({capture['job_state']})"
        if capture["reason"]:
            detail += f": {capture['reason']}"
    elif capture["reason"]:
        detail = capture["reason"]
    return f"{capture['fate']:<9} {capture['file']}" + (f"  {detail}" if detail else "")

