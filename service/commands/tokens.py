"""``orchard tokens``: create, list and revoke the bearer tokens of tenants (farms)."""

from __future__ import annotations

import argparse
import re
import sys
import time

from pipeline.errors import ParameterError
from service.db.errors import NotFoundError

NAME = "tokens"
HELP = "Create, list or revoke API tokens; a token belongs to a tenant (farm)."

_DURATION = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([smhdw])\s*$")
_UNIT_S = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}
_MAX_LIFETIME_S = 10 * 366 * 86400


def duration_s(text: str) -> float:
    """Seconds of a lifetime such as ``90d``, ``12h``, ``30m``, ``2w`` or ``3600s``."""
    m = _DURATION.match(text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not a lifetime; give a number and a unit: 90d, 12h, 30m, 2w, 3600s")
    seconds = float(m.group(1)) * _UNIT_S[m.group(2)]
    if not 0 < seconds <= _MAX_LIFETIME_S:
        raise argparse.ArgumentTypeError(f"{text!r}: a lifetime is more than 0 s and at most 10 years")
    return seconds


def add_arguments(parser: argparse.ArgumentParser) -> None:
    data_help = "the service's data folder: the one `orchard serve` uses (env ORCHARD_DATA_DIR)"
    parser.add_argument("--data-dir", default=None, help=data_help)
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = sub.add_parser("create", help="create a token for a tenant (created if new); prints only the token on stdout")
    c.add_argument("--tenant", required=True, help="tenant (farm) name")
    c.add_argument("--expires-in", type=duration_s, default=None, metavar="LIFETIME",
                   help="refuse the token after this long: 90d, 12h, 30m, 2w (default: never)")
    c.add_argument("--data-dir", default=argparse.SUPPRESS, help=data_help)
    ls = sub.add_parser("list", help="list tokens (id, visible prefix, created, last used, expiry) by tenant")
    ls.add_argument("--tenant", default=None, help="only this tenant's tokens")
    ls.add_argument("--data-dir", default=argparse.SUPPRESS, help=data_help)
    r = sub.add_parser("revoke", help="revoke a token by its id (from `orchard tokens list`) or by the token itself")
    r.add_argument("token", metavar="ID", help="the token's id (or the whole token)")
    r.add_argument("--data-dir", default=argparse.SUPPRESS, help=data_help)


def _when(ts: float | None, never: str) -> str:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.auth import iso_time

    return iso_time(ts) or never


def run(args: argparse.Namespace) -> int:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from service.auth import hash_token, issue_token
    from service.db.jobstore import Store
    from service.settings import build_settings

    settings = build_settings(data_dir=args.data_dir)
    store = Store(settings.store_path)
    try:
        if args.action == "create":
            try:
                token, rec = issue_token(store, args.tenant, expires_in_s=args.expires_in)
            except ValueError as exc:
                raise ParameterError(str(exc)) from None
            print(token)  # alone on stdout: TOKEN=$(orchard tokens create ...)
            print(
                f"token {rec['id']} ({rec['prefix']}…) for tenant {rec['tenant']!r}, expires: "
                f"{_when(rec['expires_at'], 'never')}; valid on a server using the data folder {settings.data_dir}",
                file=sys.stderr,
            )
        elif args.action == "list":
            if args.tenant:
                tokens = store.accounts.list_tokens(store.accounts.tenant_by_name(args.tenant)["id"])
            else:
                tokens = store.accounts.list_tokens_any_tenant()
            now = time.time()
            print("tenant\tid\tprefix\tcreated\tlast used\texpires")
            for t in tokens:
                print("\t".join((
                    t["tenant"], t["id"], t["prefix"] or "(made before prefixes)", _when(t["created_at"], "-"),
                    _when(t["last_used_at"], "never"),
                    _when(t["expires_at"], "never") + (" (expired)" if t["expires_at"] and t["expires_at"] <= now else ""),
                )))
        elif args.action == "revoke":
            if not (store.accounts.revoke_token_id(args.token) or store.accounts.revoke_token(hash_token(args.token))):
                raise NotFoundError(f"no token {args.token!r} in the data folder {settings.data_dir}; "
                                    "`orchard tokens list` shows the ids")
            print("revoked")
    finally:
        store.close()
    return 0
