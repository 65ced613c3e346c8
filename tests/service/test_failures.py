"""Failures sorted by their classes: exceptions in, outcomes out, no cluster and no store."""

from __future__ import annotations

import asyncio
import concurrent.futures
import errno
import json
import sqlite3

import pytest
from distributed.client import CancelledFuturesGroup, FutureCancelledError, FuturesCancelledError
from distributed.comm.core import CommClosedError
from hypothesis import given
from hypothesis import strategies as st

from pipeline.errors import InputError, NoOverlapError, NoTreesError, OrchardError, ParameterError
from service.failures import RETRIED, ClusterUnavailable, Outcome, classify
from service.wording import cli_name, failure_words
from workers.stops import ClusterLost, JobCancelled, TileFailed


def _futures_cancelled(reason="scheduler-connection-lost"):
    return FuturesCancelledError([CancelledFuturesGroup([FutureCancelledError("k", reason)], reason=reason)])


#: (exception, cancel set, kind, retried, client replaced, log)
CASES = [
    (JobCancelled("cancelled"), False, "cancelled", False, False, None),
    (concurrent.futures.CancelledError(), False, "cancelled", False, False, None),
    (asyncio.CancelledError(), False, "cancelled", False, False, None),
    (ZeroDivisionError("x"), True, "cancelled", False, False, None),  # the cancel's doing
    (KeyboardInterrupt(), False, "exit", False, False, None),
    (SystemExit(1), False, "exit", False, False, None),
    (KeyboardInterrupt(), True, "cancelled", False, False, None),  # asked to stop while cancelling
    (InputError("b.laz: truncated"), True, "input", False, False, None),  # the job's own error wins a cancel
    (ParameterError("bad", param="tiling.buffer", value=2.0, limit=6.15), False, "parameter", False, False, None),
    (NoOverlapError("no overlap", capture="b", previous="a"), False, "parameter", False, False, None),
    (NoTreesError("no trees found"), False, "no_trees", False, False, None),
    (TileFailed("tile 3 failed", 3, hint="; resume with --work w --resume"), False, "tile_failed", False, False, None),
    (ClusterLost("no worker for 120 s", hint="; resume"), False, "cluster_lost", True, False, None),
    (OrchardError("something the user did"), False, "error", False, False, None),
    (ClusterUnavailable("tcp://h:8786", "timed out"), False, "cluster_unavailable", True, False, None),
    (OSError(errno.ENOSPC, "No space left on device"), False, "disk_full", True, False, "line"),
    (OSError(errno.EDQUOT, "Disk quota exceeded"), False, "disk_full", True, False, "line"),
    (sqlite3.OperationalError("database or disk is full"), False, "disk_full", True, False, "line"),
    (CommClosedError("in <TCP (closed) ConnectionPool.gather>: Stream is closed"), False, "scheduler_lost", True, True, None),
    (_futures_cancelled(), False, "scheduler_lost", True, True, None),
    (FutureCancelledError("k", "scheduler-connection-lost"), False, "scheduler_lost", True, True, None),
    (OSError(errno.EACCES, "Permission denied"), False, "internal", False, False, "traceback"),
    (ValueError("scheduler-connection-lost"), False, "internal", False, False, "traceback"),  # words are no class
    (MemoryError(), False, "internal", False, False, "traceback"),
]


@pytest.mark.parametrize("exc, cancelled, kind, retry, reconnect, log", CASES,
                         ids=[f"{type(c[0]).__name__}-{c[2]}" for c in CASES])
def test_each_class_has_its_outcome(exc, cancelled, kind, retry, reconnect, log):
    outcome = classify(exc, cancelled=cancelled)
    assert (outcome.kind, outcome.retry, outcome.reconnect, outcome.log) == (kind, retry, reconnect, log)
    assert outcome.retry == (kind in RETRIED)


def test_a_domain_errors_fields_are_its_own_unworded():
    exc = ParameterError("tile buffer 2 m is smaller than the reach; ", hint="use {tiling.buffer} 6.15 or more",
                         param="tiling.buffer", value=2.0, limit=6.15)
    fields = classify(exc).fields
    assert fields == {"class": "ParameterError", "message": exc.message, "hint": exc.hint,
                      "param": "tiling.buffer", "value": 2.0, "limit": 6.15}
    # each edge words the same fields its own way
    assert failure_words("parameter", fields).endswith("use tiling.buffer 6.15 or more")
    assert failure_words("parameter", fields, name=cli_name).endswith("use --buffer 6.15 or more")


def test_a_stopped_runs_advice_to_resume_is_no_service_jobs():
    fields = classify(TileFailed("tile 3 failed after 3 attempts: MemoryError: ", 3,
                                 hint="; its data is kept in /w (run again with --work /w --resume)")).fields
    assert fields["tile_id"] == 3 and fields["stopped"] is True
    assert failure_words("tile_failed", fields) == "tile 3 failed after 3 attempts: MemoryError: "


def test_the_blocks_stored_file_is_named_as_it_arrived():
    fields = {**classify(InputError("/srv/blocks/ab12.laz: truncated")).fields,
              "block_path": "/srv/blocks/ab12.laz", "block_name": "north.laz"}
    assert failure_words("input", fields) == "north.laz: truncated"


def test_a_retried_failure_says_its_attempt():
    fields = classify(ClusterUnavailable("tcp://h:8786", "timed out")).fields
    assert failure_words("cluster_unavailable", fields) == "cannot start or reach the dask cluster (tcp://h:8786): timed out"
    waiting = failure_words("cluster_unavailable", {**fields, "attempt": 1, "attempts": 3, "retry_at": 0.0})
    assert waiting == ("attempt 1 of 3 failed: cannot start or reach the dask cluster (tcp://h:8786): timed out; "
                       "trying again from 1970-01-01 00:00:00 UTC")
    lost = classify(ClusterLost("no dask worker for 120 s", hint="; resume with --work w")).fields
    assert failure_words("cluster_lost", {**lost, "attempt": 2}) == (
        "no dask worker for 120 s (attempt 2, the last); start dask workers and submit the job again")
    assert failure_words("disk_full", {"attempt": 1}) == (
        "the server ran out of disk space during the job; free disk space on the server and submit it again")


exceptions = st.one_of(
    st.builds(lambda cls, msg, hint: cls(msg, hint=hint),
              st.sampled_from([OrchardError, InputError, ParameterError, NoTreesError]), st.text(), st.text()),
    st.builds(lambda msg, tile: TileFailed(msg, tile), st.text(), st.integers(0, 10**6)),
    st.builds(ClusterLost, st.text()),
    st.builds(ClusterUnavailable, st.text(), st.text()),
    st.builds(lambda cls, msg: cls(msg), st.sampled_from([ValueError, RuntimeError, KeyError, MemoryError]), st.text()),
    st.builds(lambda code, msg: OSError(code, msg), st.sampled_from([errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.ENOENT]), st.text()),
    st.builds(lambda msg: CommClosedError(msg), st.text()),
    st.just(JobCancelled("cancelled")),
)


@given(exc=exceptions, cancelled=st.booleans())
def test_every_exception_has_one_outcome_the_store_can_keep(exc, cancelled):
    outcome = classify(exc, cancelled=cancelled)
    assert isinstance(outcome, Outcome) and outcome == classify(exc, cancelled=cancelled)  # pure
    assert json.loads(json.dumps(outcome.fields)) == outcome.fields  # kept by the store as it is
    assert outcome.retry == (outcome.kind in RETRIED)
    assert not outcome.reconnect or outcome.retry
    if outcome.kind not in ("cancelled", "exit"):
        words = failure_words(outcome.kind, outcome.fields)
        assert isinstance(words, str) and "Traceback" not in words
        assert words == failure_words(outcome.kind, json.loads(json.dumps(outcome.fields)))


@given(exc=exceptions)
def test_a_set_cancel_cancels_all_but_the_jobs_own_errors(exc):
    outcome = classify(exc, cancelled=True)
    if isinstance(exc, OrchardError) and not isinstance(exc, JobCancelled):
        assert outcome == classify(exc, cancelled=False) and outcome.kind != "cancelled"
    else:
        assert outcome.kind == "cancelled"


@given(message=st.text(), hint=st.text(), value=st.floats(allow_nan=True, allow_infinity=True))
def test_a_domain_errors_fields_survive_any_value(message, hint, value):
    fields = classify(ParameterError(message, hint=hint, param="tiling.buffer", value=value, limit=1.0)).fields
    assert fields["message"] == message and fields["hint"] == hint
    assert ("value" in fields) == (value == value and abs(value) != float("inf"))
