"""Where the time of a tiled ``orchard process`` run goes, phase by phase.

    python -m bench.tiled_phases BLOCK.laz --out DIR [more orchard process options]

Runs the command line (its defaults: auto-tiled to the memory budget, 2 embedded dask
workers) in this process and prints, as one JSON line on stderr after the command's
own output: the job's phase timings [s] (``tile``: header, tiling; ``ground``: the
block's ground statistics; ``process``: the tiles, the slot-tree settlement included;
``merge_write``; ``total``), ``views`` [s] (trees.csv and report.html, after the job),
the tiles with points and how many points they hold with their buffers, and the tiles
:func:`workers.dispatch.settle_slot_trees` ran a second time. Wrap it in
``/usr/bin/time -v`` for the CPU time of every process (the workers are children).
"""

from __future__ import annotations

import json
import sys
import time

from workers import dispatch

STATS: dict = {}


def _spy_run_again(run_again):
    def wrapper(tiles, summaries, trees, origin):
        again = run_again(tiles, summaries, trees, origin)
        STATS.update(tiles=len(tiles), n_buffered=sum(t["n_buffered"] for t in tiles),
                     run_again=[t["id"] for t in again], n_buffered_run_again=sum(t["n_buffered"] for t in again))
        return again
    return wrapper


def _spy_report(report):
    def wrapper(outcome, args, **kwargs):
        t = time.perf_counter()
        rc = report(outcome, args, **kwargs)
        STATS["timings"] = {k: round(v, 2) for k, v in outcome.timings.items()}
        STATS["views"] = round(time.perf_counter() - t, 2)
        return rc
    return wrapper


def main(argv: list[str] | None = None) -> int:
    import service.commands.process as command
    from service.cli import main as cli

    STATS.clear()
    run_again, report = dispatch.tiles_to_run_again, command._report
    dispatch.tiles_to_run_again, command._report = _spy_run_again(run_again), _spy_report(report)
    try:
        return cli(["process", *(sys.argv[1:] if argv is None else argv)])
    finally:
        dispatch.tiles_to_run_again, command._report = run_again, report
        print(json.dumps(STATS), file=sys.stderr)


if __name__ == "__main__":  # the workers' processes import this module again: run only here
    sys.exit(main())
