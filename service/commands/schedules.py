"""``orchard schedules``: list, create, change, pause, run and delete overnight inbox schedules."""

from __future__ import annotations

import argparse
import json
from datetime import datetime
from pathlib import Path

from pipeline.errors import ParameterError
from service.commands.options import add_pipeline_options, add_tiling_options, pipeline_params_from_args

NAME = "schedules"
HELP = "List, create, change, pause, resume, run or delete overnight schedules (an inbox folder scanned on a cron schedule)."


def _data_dir(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", default=argparse.SUPPRESS, help="the service's data folder (env ORCHARD_DATA_DIR)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", default=None, help="the service's data folder (env ORCHARD_DATA_DIR)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = sub.add_parser("list", help="list schedules (all tenants, or one)")
    ls.add_argument("--tenant", default=None, help="only this tenant's schedules")
    ls.add_argument("--json", action="store_true", help="print JSON")
    _data_dir(ls)
    c = sub.add_parser("create", help="register an inbox folder and a schedule for a tenant")
    c.add_argument("--tenant", required=True, help="tenant (farm) name; created if new")
    c.add_argument("--inbox", required=True, help="folder where the mobile captures (LAS/LAZ) land")
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.schedules import DEFAULT_CRON

    c.add_argument("--orchard-block", default=None, metavar="NAME",
                   help="the inbox of this orchard block of the tenant ('orchard blocks create'): each file landing in it "
                   "is one more capture of the block")
    c.add_argument("--cron", default=DEFAULT_CRON, help=f"cron expression in local time (default '{DEFAULT_CRON}' = 01:00 nightly)")
    add_tiling_options(c, ("tile_size", "buffer"), {"tile_size": "default: each capture in one piece",
                                                    "buffer": "at least the reach"})
    _data_dir(c)
    add_pipeline_options(c)
    u = sub.add_parser("update", help="change a schedule's cron or tiling (what is not given stays)")
    u.add_argument("schedule_id")
    u.add_argument("--cron", default=None, help="new cron expression in local time")
    add_tiling_options(u, ("tile_size", "buffer"), {"tile_size": "the buffer stays as it is unless --buffer is given",
                                                    "buffer": "alone, it changes a tiled schedule's buffer"})
    u.add_argument("--untiled", action="store_true", help="process each capture as one tile")
    _data_dir(u)
    add_pipeline_options(u)  # each given option changes that parameter; the others stay
    for action, what in (("pause", "the clock skips it until it is resumed (a scan by hand still runs)"),
                         ("resume", "run it again from its next cron time (runs missed while paused are not made up)")):
        a = sub.add_parser(action, help=f"{action} a schedule: {what}")
        a.add_argument("schedule_id")
        _data_dir(a)
    r = sub.add_parser("run", help="scan a schedule's inbox now and queue jobs for new captures")
    r.add_argument("schedule_id")
    _data_dir(r)
    d = sub.add_parser("delete", help="delete a schedule")
    d.add_argument("schedule_id")
    _data_dir(d)


def _when(ts: float | None) -> str:
    return datetime.fromtimestamp(ts).astimezone().isoformat(timespec="minutes") if ts else "-"


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.db.jobstore import Store
    from service.jobrequests import request_job, schedule_changes, stored
    from service.schedules import check_inbox_use, next_run_time, run_schedule, validate_cron, validate_inbox
    from service.settings import build_settings

    settings = build_settings(data_dir=args.data_dir)
    store = Store(settings.store_path)
    try:
        if args.action == "list":
            tenants = {t["id"]: t["name"] for t in store.accounts.list_tenants()}
            if args.tenant:
                rows = store.schedules.list(store.accounts.tenant_by_name(args.tenant)["id"])
            else:
                rows = store.schedules.list_any_tenant()
            _print_list(rows, tenants, store, settings, as_json=args.json)
        elif args.action == "create":
            cron = validate_cron(args.cron)
            inbox = validate_inbox(args.inbox, root=settings.inbox_root, base=Path.cwd())
            params = pipeline_params_from_args(args)
            if args.tile_size is None and args.buffer is not None:
                raise ParameterError("--buffer needs --tile-size")
            tiling = None if args.tile_size is None else {"tile_size": args.tile_size, "buffer": args.buffer}
            job = request_job(params, tiling)  # as a job would: refused now, not every night
            tenant = store.accounts.ensure_tenant(args.tenant)
            check_inbox_use(inbox, settings=settings, store=store, tenant_id=tenant["id"])
            block_id = store.orchard_blocks.by_name(tenant["id"], args.orchard_block)["id"] if args.orchard_block else None
            rec = store.schedules.create(
                tenant_id=tenant["id"],
                inbox=str(inbox),
                cron=cron,
                job=stored(job),
                next_run_at=next_run_time(cron, datetime.now().astimezone()).timestamp(),
                orchard_block_id=block_id,
            )
            print(rec["id"])
        elif args.action in ("update", "pause", "resume"):
            sched = store.schedules.get_any_tenant(args.schedule_id)
            given = _update_body(args, sched) if args.action == "update" else {"paused": args.action == "pause"}
            rec = store.schedules.update_any_tenant(sched["id"], lambda current: schedule_changes(current, given))
            state = "paused" if rec["paused"] else f"next run {_when(rec['next_run_at'])}"
            print(f"{rec['id']}\t{rec['cron']}\t{state}")
        elif args.action == "run":
            sched = store.schedules.get_any_tenant(args.schedule_id)
            res = run_schedule(store, settings, sched)
            print(json.dumps(res, indent=2))
        elif args.action == "delete":
            sched = store.schedules.get_any_tenant(args.schedule_id)
            store.schedules.delete(sched["tenant_id"], sched["id"])
            print("deleted")
    finally:
        store.close()
    return 0


def _print_list(rows: list[dict], tenants: dict, store, settings, *, as_json: bool) -> None:
    """The schedules, each followed by its captures' fates (one line each)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.capturefates import capture_fates, fate_line
    from service.wording import cli_name

    fates = [capture_fates(store, settings, s, name=cli_name) for s in rows]
    if as_json:
        print(json.dumps([{**s, "paused": bool(s["paused"]), "tenant": tenants.get(s["tenant_id"]), **f}
                          for s, f in zip(rows, fates)], indent=2))
        return
    print("id\ttenant\tcron\tnext run\tinbox")
    for s, f in zip(rows, fates):
        print(f"{s['id']}\t{tenants.get(s['tenant_id'])}\t{s['cron']}\t{'paused' if s['paused'] else _when(s['next_run_at'])}\t{s['inbox']}")
        counts = ", ".join(f"{n} {fate}" for fate, n in f["counts"].items() if n)
        print(f"  captures: {counts or 'none yet'}")
        for c in f["captures"]:
            print("    " + fate_line(c))


def _update_body(args: argparse.Namespace, sched: dict) -> dict:
    """The changes ``orchard schedules update``'s options ask for (``--buffer`` alone
    changes a tiled schedule's buffer; a pipeline option changes that parameter and
    leaves the schedule's others as they are)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.params import PipelineParams
    from service.jobrequests import request_tiling

    body: dict = {}
    if args.cron is not None:
        body["cron"] = args.cron
    current = PipelineParams.model_validate(sched["job"]["pipeline"])
    tiling = request_tiling(sched["job"])
    params = pipeline_params_from_args(args, base=current)
    if params != current:
        body["params"] = params.model_dump()
    if args.untiled and (args.tile_size is not None or args.buffer is not None):
        raise ParameterError("--untiled takes no --tile-size or --buffer")
    if args.untiled:
        body["tiling"] = None
    elif args.tile_size is not None:  # a buffer set before stays (widened for wide crowns, say)
        buffer = args.buffer if args.buffer is not None else (tiling or {}).get("buffer")
        body["tiling"] = {"tile_size": args.tile_size, "buffer": buffer}
    elif args.buffer is not None:
        if not tiling:
            raise ParameterError("--buffer needs --tile-size: the schedule processes each capture as one tile")
        body["tiling"] = {"tile_size": tiling["tile_size"], "buffer": args.buffer}
    if not body:
        raise ParameterError("nothing to change: give --cron, --tile-size (with --buffer), --untiled or pipeline options")
    return body
