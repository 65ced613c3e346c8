"""``orchard tenants``: list tenants (farms) with their use, and set their quotas."""

from __future__ import annotations

import argparse

from service.quotas import GB, gigabytes

NAME = "tenants"
HELP = "List tenants (farms) with what they store and queue, or set a tenant's quotas."


def _limit(kind: type, what: str):
    """An argparse type: a number >= 0, or 'none' (no limit)."""

    def parse(text: str):
        if text.strip().lower() in ("none", "unlimited"):
            return None
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number or 'none', not {text!r}") from None
        if not value >= 0 or value == float("inf"):
            raise argparse.ArgumentTypeError(f"{what} must be 0 or more (or 'none'), not {text!r}")
        return value

    parse.__name__ = what  # argparse names the type in its messages
    return parse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    data_dir = {"default": argparse.SUPPRESS, "help": "the service's data folder (env ORCHARD_DATA_DIR)"}
    parser.add_argument("--data-dir", default=None, help=data_dir["help"])
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = sub.add_parser("list", help="tenants with their stored GB, queued jobs and quotas")
    ls.add_argument("--data-dir", **data_dir)
    q = sub.add_parser(
        "quota",
        help="set a tenant's quotas (the options given; 'none' lifts one); without options, show them",
        description="Set a tenant's quotas. Over its storage quota an upload or capture is refused "
        "(HTTP 507, nothing kept); at its queued-jobs quota a new job is refused (HTTP 429). What the tenant "
        "holds already is kept. Quotas apply at once, also to a running service.",
    )
    q.add_argument("name", help="tenant (farm) name")
    q.add_argument("--storage-gb", type=_limit(float, "storage GB"), default=argparse.SUPPRESS, metavar="GB",
                   help="most bytes of blocks (uploads and captures) the tenant may store [GB, 10^9 bytes], or 'none'")
    q.add_argument("--max-queued", type=_limit(int, "queued jobs"), default=argparse.SUPPRESS, metavar="N",
                   help="most jobs the tenant may have queued at once, or 'none'")
    q.add_argument("--data-dir", **data_dir)


def _row(name: str, quota: dict) -> str:
    storage = gigabytes(quota["used_storage_bytes"]) + " of " + (
        "unlimited" if quota["storage_bytes"] is None else gigabytes(quota["storage_bytes"]))
    queued = f"{quota['used_queued_jobs']} of " + ("unlimited" if quota["queued_jobs"] is None else str(quota["queued_jobs"]))
    return f"{name}\tstorage {storage}\tqueued jobs {queued}"


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.db.jobstore import Store
    from service.settings import build_settings

    settings = build_settings(data_dir=args.data_dir)
    store = Store(settings.store_path)
    try:
        if args.action == "list":
            for t in store.accounts.list_tenants():
                print(_row(t["name"], store.quotas.get(t["id"])))
        else:
            tenant = store.accounts.tenant_by_name(args.name)
            limits = {}
            if "storage_gb" in args:
                limits["storage_bytes"] = None if args.storage_gb is None else round(args.storage_gb * GB)
            if "max_queued" in args:
                limits["queued_jobs"] = args.max_queued
            print(_row(tenant["name"], store.quotas.set_limits(tenant["id"], **limits) if limits else store.quotas.get(tenant["id"])))
    finally:
        store.close()
    return 0
