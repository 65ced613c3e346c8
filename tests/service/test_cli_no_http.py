"""Only ``orchard serve`` and ``orchard demo`` load an HTTP framework: every other command,
run for real against a data folder (or asked for its help), imports no FastAPI,
Starlette or uvicorn. Each runs in a fresh interpreter, so earlier tests' imports do not
hide a regression."""

from __future__ import annotations

import subprocess
import sys

import pytest

HTTP = ("fastapi", "starlette", "uvicorn")

_PROBE = """
import sys
{pre}
from service.cli import main
for argv in {runs!r}:
    try:
        code = main(argv)
    except SystemExit as exc:  # --help
        code = exc.code
    print("exit:", code, argv, file=sys.stderr)
print("imported:", *sorted({{name.split(".")[0] for name in sys.modules}} & set({names!r})))
"""


def _http_imported_by(runs: list[list[str]], *, pre: str = "") -> set[str]:
    p = subprocess.run([sys.executable, "-c", _PROBE.format(runs=runs, names=HTTP, pre=pre)], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr, p.stderr
    for line in p.stderr.splitlines():
        if line.startswith("exit:"):
            assert line.split()[1] in ("0", "None"), p.stderr
    last = p.stdout.rstrip("\n").splitlines()[-1]
    assert last.startswith("imported:")
    return set(last.split()[1:])


def test_the_store_commands_run_without_an_http_framework(tmp_path):
    d = ["--data-dir", str(tmp_path / "data")]
    runs = [
        ["tokens", "create", "--tenant", "farm", *d],
        ["tokens", "list", *d],
        ["tokens", "list", "--tenant", "farm", *d],
        ["tenants", "list", *d],
        ["tenants", "quota", "farm", "--max-queued", "5", *d],
        ["blocks", "create", "north", "--tenant", "farm", *d],
        ["blocks", "list", *d],
        ["blocks", "captures", "north", "--tenant", "farm", *d],
        ["schedules", "list", *d],
    ]
    assert _http_imported_by(runs) == set()


@pytest.mark.parametrize("command", ["process", "convert", "simulate", "evaluate", "schedules", "blocks", "tokens",
                                     "tenants"])
def test_no_command_but_serve_and_demo_imports_an_http_framework_for_its_help(command):
    assert _http_imported_by([[command, "--help"]]) == set()


def test_the_probe_sees_an_http_framework_where_there_is_one():
    # what `orchard tokens` imported when its error class lived beside the HTTP status mapping
    assert _http_imported_by([["tokens", "--help"]], pre="import service.errors") == {"fastapi", "starlette"}
