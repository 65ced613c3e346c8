"""The tile state machine: events in, decisions out, no cluster and no files."""

from __future__ import annotations

from workers.tilestate import TILE_RETRIES, Decision, TileState


def _run_in_process(state: TileState, outcomes: dict[int, list[str | None]]) -> list[tuple[int, Decision]]:
    """Drive ``state`` as the in-process loop does: each tile's attempts fail with the
    given error, or succeed at None (then its result is ``"r<tile>"``)."""
    log = []
    while (tid := state.next_tile()) is not None:
        errors = outcomes.get(tid, [])
        error = errors.pop(0) if errors else None
        decision = state.tile_failed(tid, error) if error else state.tile_succeeded(tid, f"r{tid}")
        log.append((tid, decision))
        if decision is Decision.STOP:
            break
    return log


def test_a_tile_that_fails_twice_then_succeeds_is_kept_after_two_retries():
    state = TileState([0, 1, 2])
    log = _run_in_process(state, {1: ["boom", "boom again", None]})
    assert log == [
        (0, Decision.KEEP),
        (1, Decision.RETRY),
        (1, Decision.RETRY),  # retried before tile 2 starts
        (1, Decision.KEEP),
        (2, Decision.KEEP),
    ]
    assert state.attempts == {0: 1, 1: 3, 2: 1}
    assert state.finished and not state.partial and state.failed == {}
    assert state.ordered_results() == ["r0", "r1", "r2"]


def test_a_later_tile_failing_three_times_is_given_up_and_the_result_is_partial():
    state = TileState([4, 5, 6])
    log = _run_in_process(state, {5: ["e1", "e2", "e3"]})
    assert [d for _, d in log] == [Decision.KEEP, Decision.RETRY, Decision.RETRY, Decision.GIVE_UP, Decision.KEEP]
    assert state.finished and state.partial
    assert state.failed == {5: "e3"}  # the last error
    assert state.settled == 3 and state.ordered_results() == ["r4", "r6"]


def test_the_canary_failing_after_its_retries_stops_the_job():
    state = TileState([7, 8, 9])
    log = _run_in_process(state, {7: ["x", "y", "z"]})
    assert log == [(7, Decision.RETRY), (7, Decision.RETRY), (7, Decision.STOP)]
    assert state.stopped_by == 7 and state.errors[7] == "z"
    assert state.next_tile() is None and not state.finished
    assert state.results == {} and state.given_up == []  # 8 and 9 never ran
    assert state.tile_succeeded(8, "late") is Decision.IGNORE


def test_a_stage_that_needs_every_tile_stops_on_any_and_has_no_canary():
    state = TileState([0, 1], partial=False)
    assert state.canary is None and state.priority(0) == state.priority(1) == 0
    log = _run_in_process(state, {1: ["a", "b", "c"]})
    assert log[-1] == (1, Decision.STOP) and state.stopped_by == 1


def test_a_scheduler_that_retries_by_itself_reports_all_attempts_at_once():
    # dask ran the tile retries + 1 times: no retry is asked for
    state = TileState([0, 1, 2])
    assert state.priority(0) == 1 and state.priority(1) == 0  # the canary runs first
    assert state.tile_succeeded(2, "r2") is Decision.KEEP  # out of order
    assert state.tile_failed(1, "gone", attempts=TILE_RETRIES + 1) is Decision.GIVE_UP
    assert state.settled == 2 and not state.finished
    assert state.tile_succeeded(0, "r0") is Decision.KEEP
    assert state.finished and state.ordered_results() == ["r0", "r2"] and state.failed == {1: "gone"}
    assert state.tile_failed(0, "again", attempts=TILE_RETRIES + 1) is Decision.IGNORE  # settled already


def test_a_cancel_stops_everything_and_later_events_are_ignored():
    state = TileState([0, 1, 2])
    assert state.next_tile() == 0
    assert state.tile_succeeded(0, "r0") is Decision.KEEP
    assert state.cancel() is Decision.STOP
    assert state.cancelled and state.ended and not state.finished
    assert state.next_tile() is None
    assert state.tile_failed(1, "late") is Decision.IGNORE
    assert state.tile_succeeded(2, "late") is Decision.IGNORE
    assert state.ordered_results() == ["r0"] and state.settled == 1


def test_no_retries_gives_up_at_the_first_failure():
    state = TileState([0, 1], retries=0)
    assert state.tile_succeeded(0, "r0") is Decision.KEEP
    assert state.tile_failed(1, "once") is Decision.GIVE_UP
    assert state.attempts[1] == 1


def test_an_empty_plan_is_finished_at_once():
    state = TileState([])
    assert state.canary is None and state.next_tile() is None and state.finished
