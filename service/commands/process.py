"""``orchard process``: a LAS/LAZ block in; trees.parquet, points.parquet, trees.csv and report.html out."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import tempfile
import time
from datetime import datetime, timezone
from functools import partial
from pathlib import Path

from pipeline.errors import ParameterError
from service.commands.convert import add_input_options
from service.commands.options import add_pipeline_options, add_tiling_options, pipeline_params_from_args, tiling_default

NAME = "process"
HELP = (
    "Process a LAS/LAZ block into trees.parquet (one row per tree, GeoParquet) and points.parquet "
    "(one row per input point), with trees.csv and report.html (a page that opens from disk) beside them. A block that fits the memory budget of a worker "
    "(--worker-memory) is processed in one piece in this process; a larger one, or any with --tile-size, is "
    "split into buffered tiles processed by dask workers and merged. "
    "Exit codes: 0 done, 1 a tile failed or internal error, 2 bad input or parameters, "
    "3 no trees, 4 finished without some tiles (partial result; re-run them with --rerun-tile)."
)


def _settings_default(name: str):
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.settings import Settings

    return Settings.model_fields[name].default


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="INPUT", help="LAS or LAZ block (LAS 1.2-1.4, point formats 0-10), or a PLY, PCD, "
                        "E57 or text (x y z) point file, converted to LAZ first (docs/inputs.md)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder for trees.parquet, points.parquet, trees.csv and report.html")
    g = parser.add_argument_group("tiling and workers")
    add_tiling_options(g, ("tile_size", "buffer", "grid_origin", "engine", "workers", "worker_memory"), {
        "tile_size": "default: one tile if the block fits --worker-memory, else tiles chosen from its points and "
                     "voxels to fit it; 0: one tile whatever the block's size",
        "buffer": "max crown radius + 1 m + edge radius; also the minimum",
        "grid_origin": "negative: --grid-origin=-1000,-2000",
        "workers": f"default {tiling_default('workers')}, at most 4 per CPU",
        "worker_memory": f"default: ORCHARD_WORKER_MEMORY_GB, or {_settings_default('worker_memory_gb'):g}",
    })
    g.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT", help="use a running dask cluster instead of an embedded one")
    g.add_argument("--dask-host", default=None, metavar="HOST", help="address the embedded dask cluster and its dashboard listen on (default 127.0.0.1: this machine only)")
    g.add_argument("--no-dashboard", dest="dashboard", action="store_false", help="start the embedded dask cluster without its dashboard")
    g.add_argument("--work", default=None, metavar="DIR_OR_URL", help="work store for tiles (folder or fsspec URL); default OUT/_work")
    g.add_argument("--rerun-tile", type=int, action="append", default=None, metavar="ID", help="re-run this failed tile of the job in --work alone, then merge again (repeatable)")
    g.add_argument("--resume", action="store_true", help="process the tiles of the job in --work that have no result yet, then merge")
    parser.add_argument("--trees", action="store_true", help="print the per-tree table (address first) instead of the block summary and its rows")
    g.add_argument("--labelled-laz", action="store_true", help="also write labelled.laz: the input with extra dimensions tree_id, is_wood, wood_score")
    g.add_argument("--inject-failure", type=int, action="append", default=None, help=argparse.SUPPRESS)
    c = parser.add_argument_group("captures of one block over the seasons (docs/seasons.md)")
    c.add_argument("--previous", default=None, metavar="DIR_A",
                   help="output folder of the block's previous capture: register onto its trees, keep their tree_key "
                        "and addresses, and write the change columns and history.parquet against it")
    c.add_argument("--captured-on", dest="captured_at", default=None, metavar="YYYY-MM-DD",
                   help="the capture's date when the file's header has none (default: the file's modification day)")
    c.add_argument("--capture-id", default=None, metavar="ID", help="the capture's id in history.parquet (default: INPUT's file stem)")

    add_input_options(parser.add_argument_group("inputs other than LAS/LAZ"))
    add_pipeline_options(parser)


class _Bar:
    """A plain-text progress bar on stderr: over tiles, or what ``what`` names."""

    def __init__(self, stream=None, what: str = "tiles"):
        self.stream, self.what = stream, what
        self.start = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        width = 30
        fill = int(width * done / total) if total else width
        elapsed = time.perf_counter() - self.start
        stream = self.stream or sys.stderr
        stream.write(f"{self.what} [{'#' * fill}{'.' * (width - fill)}] {done}/{total}  {elapsed:6.1f} s\n")
        stream.flush()


def _check_cluster_options(args: argparse.Namespace) -> None:
    """ParameterError for tiling and cluster options that contradict each other or would
    go unused without a word (a job resumed from --work keeps the grid it was planned
    with and runs here or on --scheduler). Those a block processed in one piece leaves
    unused are refused once the budget has decided: :func:`_check_tiled_options`."""
    if args.rerun_tile or args.resume:
        given = [flag for flag, value in (("--tile-size", args.tile_size), ("--buffer", args.buffer),
                                          ("--grid-origin", args.grid_origin), ("--engine", args.engine),
                                          ("--workers", args.workers), ("--dask-host", args.dask_host),
                                          ("--worker-memory", args.worker_memory),
                                          ("--previous", args.previous), ("--captured-on", args.captured_at),
                                          ("--capture-id", args.capture_id),
                                          ("--no-dashboard", None if args.dashboard else True)) if value is not None]
        if given:
            raise ParameterError(
                f"{', '.join(given)}: --resume and --rerun-tile go on with the job in --work as it was planned "
                "(its tiles, on --scheduler or in this process); start a new job to change them"
            )
        return
    if args.worker_memory is not None and args.tile_size is not None:
        raise ParameterError("--worker-memory chooses the tile size: give it or --tile-size, not both")
    if args.tile_size == 0 and args.scheduler is not None:
        raise ParameterError("--tile-size 0 processes the block in this process; a cluster (--scheduler) needs tiles")
    if args.workers is not None:
        most = 4 * (os.cpu_count() or 1)
        if not 1 <= args.workers <= most:
            raise ParameterError(f"--workers must be from 1 to {most} (4 per CPU of this machine), not {args.workers}")
        if args.scheduler is not None:
            raise ParameterError("--workers is for the embedded cluster; a running one (--scheduler) brings its own workers")
    for flag, given in (("--dask-host", args.dask_host is not None), ("--no-dashboard", not args.dashboard)):
        if given and args.scheduler is not None:
            raise ParameterError(f"{flag} is for the embedded cluster; a running one (--scheduler) was started with its own")


def _check_tiled_options(args: argparse.Namespace, *, tiled: bool) -> None:
    """ParameterError for options of a tiled run given to one processed in one piece."""
    if tiled:
        return
    why = ("the block fits the memory budget (--worker-memory) and is processed in one piece in this process"
           if args.tile_size is None else "--tile-size 0 processes the block in one piece in this process")
    for flag, given in (("--workers", args.workers is not None), ("--dask-host", args.dask_host is not None),
                        ("--no-dashboard", not args.dashboard), ("--grid-origin", args.grid_origin is not None),
                        ("--engine", args.engine is not None), ("--work", args.work is not None)):
        if given:
            raise ParameterError(f"{flag} needs tiles: {why}; give --tile-size to tile it")


def _tiling(args: argparse.Namespace):
    """The tiling options as the job's `TilingParams`: ``--tile-size 0`` is one piece
    whatever the block's size."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.jobparams import TilingParams

    given = {k: getattr(args, k) for k in ("buffer", "grid_origin") if getattr(args, k) is not None}
    if args.tile_size is not None:
        given["tile_size"] = args.tile_size or None
    return TilingParams(**given)


def _run_options(args: argparse.Namespace):
    """How to run the job, `RunOptions`: with ``--tile-size`` no memory budget (the
    tiles are given); without, tiles are chosen to fit ``--worker-memory``, else the
    ORCHARD_WORKER_MEMORY_GB setting."""
    from workers.runoptions import RunOptions

    given = {k: getattr(args, k) for k in ("engine", "workers") if getattr(args, k) is not None}
    if args.tile_size is not None:
        given["worker_memory"] = None
    elif args.worker_memory is not None:
        given["worker_memory"] = args.worker_memory
    else:
        from service.settings import Settings

        given["worker_memory"] = Settings().worker_memory_gb
    return RunOptions(**given)


def _check_same_job(args: argparse.Namespace) -> None:
    """ParameterError if INPUT, the pipeline options or --labelled-laz are not those the
    job in ``work`` was started with (--rerun-tile and --resume go on with that job: they
    were ignored without a word)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from workers.jobspec import stored_job
    from workers.workstore import JOB_KEY, WorkStore

    work, input_path = args.work, args.input
    store = WorkStore(work)
    if not store.exists(JOB_KEY):
        return  # said by resume_job / finish_job / run_tile
    record = store.get_json(JOB_KEY)
    started_with = stored_job(record).pipeline
    if pipeline_params_from_args(args, base=started_with) != started_with:  # an option given to change one
        raise ParameterError(
            f"the pipeline options differ from those the job in --work {work} was started with; "
            "--resume and --rerun-tile go on with that job: leave them out, or start a new job"
        )
    if args.labelled_laz and not record.get("labelled_laz", False):
        raise ParameterError(f"the job in --work {work} was started without --labelled-laz; start a new job to write it")
    started_on = record["input_path"]
    try:
        same = os.path.samefile(started_on, input_path)
    except OSError:  # one of them is gone: the paths must agree
        same = os.path.abspath(started_on) == os.path.abspath(input_path)
    if not same:
        raise ParameterError(
            f"INPUT {input_path} is not the block the job in --work {work} was started on ({started_on}); "
            "give that block, or start a new job without --resume / --rerun-tile"
        )


def run(args: argparse.Namespace) -> int:
    fmt = _input_format(args)
    if fmt == "las":
        return _run(args)
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.formats.convert import parse_crs_option, to_laz

    crs = parse_crs_option(args.crs)
    pipeline_params_from_args(args)  # bad options fail before a long conversion
    _check_cluster_options(args)
    # beside the output folder, where a cluster's workers see it too; gone when the run ends
    try:
        folder = tempfile.TemporaryDirectory(prefix=".orchard-input-", dir=_existing_parent(Path(args.out).parent))
    except OSError:  # a folder this user cannot write to: the system's temporary folder
        folder = tempfile.TemporaryDirectory(prefix="orchard-input-")
    with folder as tmp:
        laz = Path(tmp) / (Path(args.input).name + ".laz")  # its messages name tree.ply.laz: the input, converted
        done = to_laz(args.input, laz, fmt=fmt, crs_epsg=crs, columns=args.columns)
        left = f", {done.n_dropped} with a non-finite coordinate left out" if done.n_dropped else ""
        print(f"orchard process: {Path(args.input).name}: {fmt.upper()}, {done.n_points} points{left}, converted to LAZ",
              file=sys.stderr)
        # the capture is the original file: its name and (without a --captured-on) its day
        args.capture_id = args.capture_id or Path(args.input).stem
        args.captured_at_fallback = _file_day(args.input)
        args.input_name, args.input = Path(args.input).name, str(laz)
        return _run(args)


def _file_day(path: str) -> str:
    """The day a file was last written (UTC, ISO): a capture's day when nothing better says it."""
    return datetime.fromtimestamp(os.path.getmtime(path), tz=timezone.utc).date().isoformat()


def _input_format(args: argparse.Namespace) -> str:
    """The input's format ("las" for LAS/LAZ, and for a path that is no file: the
    LAS checks say what is wrong with it); ParameterError for options that go unused."""
    p = Path(args.input)
    if args.rerun_tile or args.resume or not p.is_file() or p.suffix.lower() in (".las", ".laz"):
        fmt = "las"  # (a .las/.laz that is not LAS/LAZ: the LAS checks say why)
    else:  # (here, not at the top: `orchard --help` imports every command module, see service.commands)
        from pipeline.formats import sniff

        fmt = sniff(p)
    if fmt == "las" and args.crs is not None:
        raise ParameterError("--crs is for PLY, PCD, E57 and text inputs; a LAS/LAZ file states its own CRS")
    if fmt != "text" and args.columns is not None:
        raise ParameterError("--columns names the columns of a text input" + ("" if fmt == "las" else f"; this is a {fmt.upper()} file"))
    if fmt != "las" and (args.rerun_tile or args.resume):
        raise ParameterError("--resume and --rerun-tile need the LAS/LAZ block the job ran on")
    return fmt


def _existing_parent(path: Path) -> Path:
    path = path.resolve()
    while not path.is_dir():
        path = path.parent
    return path


def _run(args: argparse.Namespace) -> int:
    # the pipeline (numpy, laspy, scipy, pyarrow) is imported once the input's header and
    # the options are checked: a bad input fails in a fraction of the time
    params = pipeline_params_from_args(args)
    if not (args.rerun_tile or args.resume):
        from pipeline.lasheader import check_file

        n_points = check_file(args.input).point_count
    _check_cluster_options(args)
    if args.rerun_tile or args.resume:
        return _go_on(args)
    import numpy  # noqa: F401 - every run needs it: imported before the fork, the map's process shares it

    from service.reports.mapprocess import MapProcess

    maps = MapProcess.start()  # matplotlib loads there while this process reads and processes the block
    try:
        spec = _spec(args, params)
        spec, tiled, count_on_cluster, points = _tiled(spec, args, n_points)
        _check_tiled_options(args, tiled=tiled)  # they went unused, without a word (the budget decided, or --tile-size 0)
        if args.work:
            from workers.workstore import check_work_url

            try:
                check_work_url(args.work, shared=tiled)
            except ParameterError as exc:
                raise ParameterError("{job.work_dir}: " + exc.message, hint=exc.hint, param="job.work_dir",
                                     value=args.work) from None
        outcome = _run_job(spec, args, tiled=tiled, count_on_cluster=count_on_cluster, points=points)
        points = None  # not held through the report
        return _report(outcome, args, draw_map=maps.draw)
    finally:
        maps.close()


def _go_on(args: argparse.Namespace) -> int:
    """--rerun-tile and --resume: go on with the tiled job in --work."""
    from workers.replay import finish_job, resume_job, run_tile

    if not args.work:
        raise ParameterError("--rerun-tile and --resume need --work: the work folder of the tiled run that failed")
    _check_same_job(args)
    for tid in args.rerun_tile or ():
        print(f"re-running tile {tid} from {args.work}", file=sys.stderr)
        run_tile(args.work, tid)
    if not args.resume:
        return _report(finish_job(args.work, out_dir=args.out), args)
    client = None
    try:
        if args.scheduler:
            from workers.cluster import close_client, make_client

            client = make_client(args.scheduler)
        outcome = resume_job(args.work, out_dir=args.out, client=client, progress=_Bar(),
                             cancel=getattr(args, "interrupted", None))
    finally:
        if client is not None:
            close_client(client)
    return _report(outcome, args)


def _spec(args: argparse.Namespace, params):
    """The job the options describe: its parameters (a `JobParams`, checked once, here)
    and how to run it."""
    from pipeline.jobparams import JobParams
    from workers.jobspec import JobSpec

    return JobSpec(
        input_path=args.input,
        out_dir=args.out,
        job=JobParams(pipeline=params, tiling=_tiling(args)),
        run=_run_options(args),
        work_dir=args.work,
        labelled_laz=args.labelled_laz,
        inject_failure=tuple(args.inject_failure or ()),
        previous=args.previous,
        capture_id=args.capture_id,
        captured_at=args.captured_at,
        captured_at_fallback=getattr(args, "captured_at_fallback", None),
    )


def _tiled(spec, args: argparse.Namespace, n_points: int):
    """Whether the job is tiled: given tiles, a scheduler, or a block that does not fit
    the memory budget. Returns the spec (with the budget's tiles), whether it is tiled,
    whether its workers are to count the block (it surely needs tiles), and the block's
    points when they were read here and it stays whole."""
    tiled = bool(args.tile_size) or args.scheduler is not None
    count_on_cluster = False  # a block that surely needs tiles is counted by the workers
    points = None  # the block's points, read here when it stays whole
    if spec.tiling.tile_size is None and not tiled:
        from pipeline.budget import surely_tiled

        if surely_tiled(n_points, spec.run.memory_budget):
            tiled = count_on_cluster = True
        else:
            spec, points = _budget_tiles(spec)  # bad input fails here, before anything else
            tiled = spec.tiling.tile_size is not None
    return spec, tiled, count_on_cluster, points


def _run_job(spec, args: argparse.Namespace, *, tiled: bool, count_on_cluster: bool, points):
    """Check the job, start the cluster a tiled job needs (its workers count the block
    when ``count_on_cluster``) and run it."""
    from workers.job import splits_while_counting
    from workers.jobspec import check_job

    client, fused, tiles_chosen = None, False, None
    try:
        info, _ = check_job(spec, tiled=tiled)  # bad input or parameters fail before a cluster starts
        if tiled:
            from workers.cluster import LOOPBACK, close_client, dashboard_address, make_client

            client = make_client(args.scheduler, n_workers=spec.run.workers, quiet=True, dashboard=args.dashboard,
                                 host=args.dask_host or LOOPBACK)
            # the job's workers count the block as they split it (workers.cellranges), else here
            fused = count_on_cluster and splits_while_counting(spec, info)
            if count_on_cluster and not fused:
                from workers.counting import count_block
                from workers.dispatch import cluster_threads

                spec, _ = _budget_tiles(spec, count=partial(count_block, client=client,
                                                            cancel=getattr(args, "interrupted", None),
                                                            progress=_Bar(what="counting")),
                                        n_workers=cluster_threads(client))
            dashboard_line = f"dask dashboard: {dashboard_address(client) or 'none'}"

            def tiles_chosen(spec):
                # after the count: a budget that cannot work ends the count's lines
                _say_tiles(spec)
                print(dashboard_line, file=sys.stderr)

            if not fused:
                print(dashboard_line, file=sys.stderr)
        from workers.job import run_job

        # TileFailed: exit 1 (service.cli)
        with _budget_worded(spec):
            return run_job(spec, client=client, progress=_Bar() if tiled else None,
                           cancel=getattr(args, "interrupted", None), points=points,
                           on_tiles=tiles_chosen if fused else None, counting=_Bar(what="counting") if fused else None)
    finally:
        if client is not None:
            close_client(client)


def _budget_tiles(spec, count=None, n_workers=None):
    """``spec`` with the tiles its memory budget needs (:func:`workers.jobspec.auto_tiled`,
    for ``n_workers``: default the embedded cluster's ``spec.run.workers``), said on stderr
    when there are any, and the block's points when it stays whole and they were read
    here (:func:`workers.jobspec.budgeted`; ``count`` None)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from workers.jobspec import auto_tiled, budgeted

    points = None
    with _budget_worded(spec):
        if count is None:
            spec, points = budgeted(spec)
        else:
            spec = auto_tiled(spec, count=count, n_workers=n_workers)
    _say_tiles(spec)
    return spec, points


@contextlib.contextmanager
def _budget_worded(spec):
    """A :class:`pipeline.budget.BudgetError` raised inside, worded for the command line."""
    from pipeline.budget import BudgetError

    try:
        yield
    except BudgetError as exc:
        need = math.ceil(exc.need / 1e8) / 10  # GB, rounded up
        raise ParameterError(exc.message, hint=f"{exc.hint} ({{tiling.worker_memory}} {need:g} or more)",
                             param="tiling.worker_memory", value=spec.run.worker_memory, limit=need) from None


def _say_tiles(spec) -> None:
    """The budget's tile size, said on stderr when it chose tiles."""
    run = spec.run
    if spec.tiling.tile_size is not None:
        print(
            f"orchard process: the block would need more than {run.worker_memory:g} GB in one piece: "
            f"tiles of {spec.tiling.tile_size:g} m (--tile-size 0: one piece)",
            file=sys.stderr,
        )


def _write_views(outcome, args, draw_map=None) -> None:
    """``trees.csv`` and ``report.html`` beside the Parquet files: a spreadsheet and a page
    that open from disk (``draw_map``: see :func:`service.reports.report.write_report`)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.reports.report import write_report, write_trees_csv

    trees, points = outcome.outputs.get("trees"), outcome.outputs.get("points")
    if not trees:
        return
    out = Path(trees).parent
    write_trees_csv(trees, out / "trees.csv")
    if not points:
        return
    name = getattr(args, "input_name", None) or Path(args.input).name
    summary = {"Block": name, "Points": str(outcome.n_points), "Trees": str(outcome.n_trees)}
    warning = None
    if outcome.partial:
        warning = (f"Partial result: tile(s) {', '.join(map(str, outcome.failed_tiles))} of this block failed. Trees "
                   "standing in them are missing from this report, and their points are in no tree.")
    write_report(block_path=args.input, trees_parquet=trees, points_parquet=points, out_dir=out,
                 title=f"Orchard report — {name}", summary=summary, warning=warning, sample=outcome.sample,
                 draw_map=draw_map)


def _report_capture(outcome) -> None:
    """One line on stderr for a capture registered onto its previous capture."""
    if not outcome.outputs.get("trees"):
        return
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from workers.seasons import capture_record

    record = capture_record(Path(outcome.outputs["trees"]).parent)
    reg, counts = record.get("registration"), record["counts"]
    if reg is None:
        return
    print(f"capture {record['capture_id']} ({record['captured_at']}) onto {record['previous_capture_id']}: "
          f"shifted {math.hypot(reg['dx'], reg['dy']):.2f} m, turned {reg['rotation_deg']:.2f} deg, "
          f"residual {reg['residual_m'] * 100:.1f} cm; {counts['same']} same, {counts['new']} new, "
          f"{counts['replanted']} replanted, {counts['removed']} removed", file=sys.stderr)


def _report(outcome, args, draw_map=None) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    import pyarrow.parquet as pq

    from pipeline.parquet import read_table
    from service.commands.printout import print_summary, print_trees

    if outcome.trees is not None:
        rows_path = outcome.outputs.get("rows")
        rows = read_table(rows_path, ["row", "n_gaps"]).to_pydict() if rows_path else None
        if args.trees:
            print_trees(outcome.trees)
        else:
            print_summary(outcome.trees, rows)
    _write_views(outcome, args, draw_map)
    out = Path(args.out)
    points = f"{outcome.n_points} points"
    if outcome.partial and outcome.outputs.get("points"):
        stored = pq.ParquetFile(outcome.outputs["points"]).metadata.num_rows
        points = f"{outcome.n_points} points ({stored} of them in points.parquet)"
    print(
        f"{outcome.n_trees} trees, {points}, {outcome.n_tiles} tile(s) "
        f"in {outcome.timings.get('total', 0.0):.1f} s -> {out}",
        file=sys.stderr,
    )
    _report_capture(outcome)
    if outcome.partial:
        tiles = " ".join(f"--rerun-tile {t}" for t in outcome.failed_tiles)
        if getattr(args, "input_name", None):  # the converted block is gone with the run
            print(f"orchard process: partial result: tiles {outcome.failed_tiles} failed and are missing; to re-run "
                  f"them, convert {args.input_name} with 'orchard convert' and process the LAZ", file=sys.stderr)
            return 4
        print(
            f"orchard process: partial result: tiles {outcome.failed_tiles} failed and are missing; "
            f"re-run them with: orchard process {args.input} --out {args.out} --work {args.work or out / '_work'} {tiles}",
            file=sys.stderr,
        )
        return 4
    return 0
