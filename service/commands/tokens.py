"""``orchard tokens``: create, list and revoke the bearer tokens of tenants (farms)."""

from __future__ import annotations

import argparse

NAME = "tokens"
HELP = "Create, list or revoke API tokens; a token belongs to a tenant (farm)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", default=None, help="the service's data folder (env ORCHARD_DATA_DIR)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = sub.add_parser("create", help="create a token for a tenant (created if new); prints only the token")
    c.add_argument("--tenant", required=True, help="tenant (farm) name")
    c.add_argument("--data-dir", default=argparse.SUPPRESS, help="the service's data folder (env ORCHARD_DATA_DIR)")
    ls = sub.add_parser("list", help="list tenants and how many tokens each has")
    ls.add_argument("--data-dir", default=argparse.SUPPRESS, help="the service's data folder (env ORCHARD_DATA_DIR)")
    r = sub.add_parser("revoke", help="revoke a token")
    r.add_argument("token", help="the token to revoke")
    r.add_argument("--data-dir", default=argparse.SUPPRESS, help="the service's data folder (env ORCHARD_DATA_DIR)")


def run(args: argparse.Namespace) -> int:
    from pipeline.errors import NotFoundError, ParameterError
    from service.auth import create_token, hash_token
    from service.settings import build_settings
    from service.store import Store

    settings = build_settings(data_dir=args.data_dir)
    store = Store(settings.store_path)
    try:
        if args.action == "create":
            try:
                token = create_token(store, args.tenant)
            except ValueError as exc:
                raise ParameterError(str(exc)) from None
            print(token)
        elif args.action == "list":
            for t in store.list_tenants():
                print(f"{t['name']}\t{t['n_tokens']} token(s)")
        elif args.action == "revoke":
            if not store.revoke_token(hash_token(args.token)):
                raise NotFoundError("no such token")
            print("revoked")
    finally:
        store.close()
    return 0
