"""Which tiles of a job are done, which failed, and what a failure means (lidR's policy).

Events in, decisions out: :class:`TileState` is told what happened to each tile and
answers what to do next; it runs nothing, waits for nothing and touches no file, so the
dispatch loop (:mod:`workers.dispatch`) acts on its answers on dask and in-process alike.

- A tile that fails is run again, up to ``retries`` times.
- The first tile of the plan is the canary (it runs first): if it still fails, the job
  stops, since a failure there is probably a bug rather than the tile.
- A later tile that still fails is given up: the job finishes without it and its result
  is partial.
- With ``partial=False`` (a stage that needs every tile, such as the block's ground
  statistics) any tile that still fails stops the job.
- Once the job is cancelled or stopped, nothing more is run and late events are ignored.
"""

from __future__ import annotations

import enum
from collections import deque
from collections.abc import Iterable
from typing import Any

#: Attempts after the first for a failing tile.
TILE_RETRIES = 2


class Decision(enum.Enum):
    """What the dispatch loop does after an event."""

    KEEP = "keep"  # the tile's result is kept
    RETRY = "retry"  # run the tile again
    GIVE_UP = "give up"  # go on without the tile: the result is partial
    STOP = "stop"  # stop the job
    IGNORE = "ignore"  # the tile was settled already, or the job has ended


class TileState:
    """The state of the tiles of one stage of a job.

    Parameters
    ----------
    tiles : iterable of int
        Tile ids in the plan's order; the first is the canary.
    retries : int
        Attempts after the first for a failing tile.
    partial : bool
        Whether the job may go on without a later tile that keeps failing (False: any
        such tile stops the job, and there is no canary).
    """

    def __init__(self, tiles: Iterable[int], *, retries: int = TILE_RETRIES, partial: bool = True):
        self.tiles = tuple(int(t) for t in tiles)
        self.retries = int(retries)
        self.partial_allowed = bool(partial)
        self.canary = self.tiles[0] if partial and self.tiles else None
        self.attempts = dict.fromkeys(self.tiles, 0)
        self.results: dict[int, Any] = {}
        self.errors: dict[int, str] = {}  # the last error of each tile that failed
        self.given_up: list[int] = []
        self.stopped_by: int | None = None
        self.cancelled = False
        self._todo = deque(self.tiles)

    @property
    def total(self) -> int:
        return len(self.tiles)

    @property
    def settled(self) -> int:
        """Tiles done or given up."""
        return len(self.results) + len(self.given_up)

    @property
    def ended(self) -> bool:
        """Cancelled or stopped: nothing more runs."""
        return self.cancelled or self.stopped_by is not None

    @property
    def finished(self) -> bool:
        """Every tile settled and the job neither stopped nor cancelled."""
        return not self.ended and self.settled == self.total

    @property
    def partial(self) -> bool:
        return bool(self.given_up)

    @property
    def failed(self) -> dict[int, str]:
        """Given-up tile → its last error."""
        return {t: self.errors[t] for t in self.given_up}

    def ordered_results(self) -> list:
        """The kept results in tile-id order (whatever order they arrived in)."""
        return [self.results[t] for t in sorted(self.results)]

    def priority(self, tile: int) -> int:
        """Scheduling priority of a tile: the canary runs first."""
        return 1 if tile == self.canary else 0

    def next_tile(self) -> int | None:
        """The tile to run next in this process: a tile to retry before a new one, new
        ones in the plan's order. None when none is left or the job has ended."""
        if self.ended or not self._todo:
            return None
        return self._todo.popleft()

    def _settled(self, tile: int) -> bool:
        return tile in self.results or tile in self.given_up

    def tile_succeeded(self, tile: int, result: Any) -> Decision:
        """``tile`` ran and gave ``result``."""
        if self.ended or self._settled(tile):
            return Decision.IGNORE
        self.attempts[tile] += 1
        self.results[tile] = result
        return Decision.KEEP

    def tile_failed(self, tile: int, error: str, *, attempts: int = 1) -> Decision:
        """``attempts`` runs of ``tile`` failed, the last with ``error`` (one line).

        A scheduler that retries by itself (dask's ``retries``) reports all the tile's
        attempts at once, ``retries + 1``, and is never asked to retry.
        """
        if self.ended or self._settled(tile):
            return Decision.IGNORE
        self.attempts[tile] += attempts
        self.errors[tile] = error
        if self.attempts[tile] <= self.retries:
            self._todo.appendleft(tile)
            return Decision.RETRY
        if not self.partial_allowed or tile == self.canary:
            self.stopped_by = tile
            return Decision.STOP
        self.given_up.append(tile)
        return Decision.GIVE_UP

    def cancel(self) -> Decision:
        """The job was cancelled: nothing more runs."""
        self.cancelled = True
        return Decision.STOP
