"""``orchard blocks``: create and list a farm's orchard blocks, and list a block's captures
(in the service's data folder; the HTTP API's ``/v1/orchard-blocks`` does the same)."""

from __future__ import annotations

import argparse
import json

from pipeline.errors import ParameterError
from service.db.errors import NotFoundError

NAME = "blocks"
HELP = ("Create or list orchard blocks (the same piece of orchard scanned again and again) and list a block's captures, "
        "in the service's data folder.")


def _data_dir(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-dir", default=argparse.SUPPRESS, help="the service's data folder (env ORCHARD_DATA_DIR)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", default=None, help="the service's data folder (env ORCHARD_DATA_DIR)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = sub.add_parser("create", help="create a named orchard block for a tenant")
    c.add_argument("name", help="the block's name, unique within the farm")
    c.add_argument("--tenant", required=True, help="tenant (farm) name; created if new")
    _data_dir(c)
    ls = sub.add_parser("list", help="list orchard blocks (all tenants, or one)")
    ls.add_argument("--tenant", default=None, help="only this tenant's blocks")
    ls.add_argument("--json", action="store_true", help="print JSON")
    _data_dir(ls)
    cp = sub.add_parser("captures", help="list an orchard block's captures in arrival order (the order they are processed in)")
    cp.add_argument("name", help="the block's name (or id)")
    cp.add_argument("--tenant", required=True, help="tenant (farm) name")
    cp.add_argument("--json", action="store_true", help="print JSON")
    _data_dir(cp)


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.db.jobstore import Store
    from service.settings import build_settings

    settings = build_settings(data_dir=args.data_dir)
    store = Store(settings.store_path)
    try:
        if args.action == "create":
            name = " ".join(args.name.split())
            if not name or len(name) > 200:
                raise ParameterError(f"a block's name is 1 to 200 characters, not {args.name!r}")
            tenant = store.accounts.ensure_tenant(args.tenant)
            print(store.orchard_blocks.create(tenant["id"], name)["id"])
        elif args.action == "list":
            tenants = {t["id"]: t["name"] for t in store.accounts.list_tenants()}
            if args.tenant:
                rows = store.orchard_blocks.list(store.accounts.tenant_by_name(args.tenant)["id"])
            else:
                rows = store.orchard_blocks.list_any_tenant()
            if args.json:
                print(json.dumps([{**r, "tenant": tenants.get(r["tenant_id"])} for r in rows], indent=2))
            else:
                print("id\ttenant\tname\tcaptures\tprocessed\tlast capture")
                for r in rows:
                    print(f"{r['id']}\t{tenants.get(r['tenant_id'])}\t{r['name']}\t{r['n_captures']}\t{r['n_done']}\t"
                          f"{r['last_captured_at'] or '-'}")
        elif args.action == "captures":
            tenant = store.accounts.tenant_by_name(args.tenant)
            try:
                block = store.orchard_blocks.by_name(tenant["id"], args.name)
            except NotFoundError:
                block = store.orchard_blocks.get(tenant["id"], args.name)  # an id: else its own "no orchard block"
            rows = store.orchard_blocks.list_captures(tenant["id"], block["id"])
            if args.json:
                print(json.dumps(rows, indent=2))
            else:
                print("seq\tcapture\tcaptured on\t(from)\tstate\tjob\tregistration")
                for c in rows:
                    reg = (c.get("record") or {}).get("registration")
                    shift = (f"shift {reg['dx']:.2f},{reg['dy']:.2f} m, {reg['rotation_deg']:.2f} deg, residual "
                             f"{reg['residual_m'] * 100:.1f} cm" if reg else "-")
                    print(f"{c['seq']}\t{c['id']}\t{c['captured_at'] or '-'}\t{c['captured_at_source'] or '-'}\t"
                          f"{c['state']}\t{c['job_id']}\t{shift}")
    finally:
        store.close()
    return 0
