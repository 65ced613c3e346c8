"""The ``orchard`` console script.

Every domain error becomes a one-line message on stderr and exit code 2 (bad input
or parameters) or 3 (no trees / not found); a failed run (a tile that kept failing, a
lost cluster, a cancel) and an unexpected error become a one-line message and exit code 1. No traceback reaches the user unless ORCHARD_DEBUG=1 is set
by the caller for a debugging session.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import os
import sys

from pipeline.errors import NoTreesError, OrchardError
from service.commands import COMMANDS
from service.db.errors import NotFoundError
from service.interrupts import ctrl_c
from service.wording import cli_words, disk_full, validation_words


def _validation_error(exc: BaseException) -> bool:
    """True for pydantic's ValidationError (pydantic is imported only by the commands
    that validate something: `orchard --help` starts without it)."""
    core = sys.modules.get("pydantic_core")
    return core is not None and isinstance(exc, core.ValidationError)


def _validation_message(err) -> str:
    return "invalid parameters: " + "; ".join(validation_words(err.errors()))


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line naming the problem and the help option (exit 2), not
    the whole usage text."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _run_failed(exc: BaseException) -> bool:
    """True for a run that failed rather than its input (a tile that kept failing, a lost
    cluster, a cancel). Only a job run raises these, and it has imported workers.jobspec:
    the command line need not import it (and dask) to tell."""
    job = sys.modules.get("workers.jobspec")
    return job is not None and isinstance(exc, (job.TileFailed, job.ClusterLost, job.JobCancelled))


def _command_in(argv: list[str]) -> str | None:
    """The sub-command named in ``argv``: its first word that is not an option."""
    return next((a for a in argv if not a.startswith("-")), None)


def build_parser(argv: list[str] | None = None) -> tuple[argparse.ArgumentParser, dict]:
    """The parser of ``orchard``; only the sub-command named in ``argv`` (default
    ``sys.argv[1:]``) gets its options, so ``orchard --help`` and each command import
    no more than they need (the pipeline's options load pydantic models)."""
    chosen = _command_in(sys.argv[1:] if argv is None else argv)
    parser = _Parser(
        prog="orchard",
        description="Turn LiDAR captures of orchards into per-tree data.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {}
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"service.commands.{name}")
        except ModuleNotFoundError as exc:  # a command whose module is not written yet
            if exc.name == f"service.commands.{name}":
                continue
            raise
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        if mod.NAME == chosen:
            mod.add_arguments(p)
        modules[mod.NAME] = mod
    return parser, modules


def main(argv: list[str] | None = None) -> int:
    """Run the command in ``argv`` (default: the command line's); returns the exit code."""
    try:
        return _main(argv)
    finally:
        if argv is None:  # the command line's own process, which ends with the command
            # the interpreter's shutdown collects cycles among the objects of every module
            # loaded, again and again (0.26-0.36 s of CPU after a run of `orchard process`);
            # frozen, they are left to the process's end: its files are closed already
            gc.freeze()


def _main(argv: list[str] | None) -> int:
    parser, modules = build_parser(argv)
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    with ctrl_c() as interrupted:
        args.interrupted = interrupted  # a job run watches it as its cancel flag
        try:
            return int(modules[args.command].run(args) or 0)
        except KeyboardInterrupt:
            print("orchard: interrupted", file=sys.stderr)
            return 130
        except (NoTreesError, NotFoundError) as exc:
            print(f"orchard {args.command}: {cli_words(exc)}", file=sys.stderr)
            return 3
        except OrchardError as exc:
            if interrupted.is_set():  # the job stopped on it (a KeyboardInterrupt lost in a callback)
                print("orchard: interrupted", file=sys.stderr)
                return 130
            print(f"orchard {args.command}: {cli_words(exc)}", file=sys.stderr)
            return 1 if _run_failed(exc) else 2
        except Exception as exc:  # noqa: BLE001 - last line of defence: no tracebacks
            if _validation_error(exc):
                print(f"orchard {args.command}: {_validation_message(exc)}", file=sys.stderr)
                return 2
            if os.environ.get("ORCHARD_DEBUG") == "1":
                raise
            if disk_full(exc):  # the machine's trouble, said as such
                print(f"orchard {args.command}: the disk is full ({exc}); free some space and run it again", file=sys.stderr)
                return 1
            print(f"orchard {args.command}: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 1


if __name__ == "__main__":
    sys.exit(main())
