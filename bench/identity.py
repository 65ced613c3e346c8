"""Byte identity of every output across a refactoring.

    python -m bench.identity --write manifest.json      # before
    python -m bench.identity --compare manifest.json    # after: exit 1 on any difference

Generates a few blocks with the command line (a vase block in the paper's setting, a
tall-spindle hedgerow with missing trees and replants, a hedge with a trellis), runs
``orchard process`` on each untiled and tiled (in-process and on the embedded dask
cluster), and records the SHA-256 of every file each run writes. The blocks live in one
shared folder (``BLOCKS``, made once under a lock) whatever ``--work`` is: outputs record
their input's path, so both sides must read the same file.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

SCENES: dict[str, list[str]] = {
    "vase": ["--rows", "2", "--trees-per-row", "4", "--spacing", "5", "--row-spacing", "6", "--noise", "0.02", "--seed", "11"],
    "spindle": ["--form", "spindle", "--rows", "3", "--trees-per-row", "10", "--spacing", "1.0", "--row-spacing", "3.5",
                "--missing", "0.1", "--replants", "0.05", "--seed", "5"],
    "hedge": ["--form", "hedge", "--rows", "2", "--trees-per-row", "10", "--spacing", "1.35", "--row-spacing", "4",
              "--trellis", "3", "--seed", "7"],
}
"""``orchard simulate`` options of each block."""

RUNS: dict[str, list[str]] = {
    "whole": [],
    "tiled": ["--tile-size", "8", "--workers", "2", "--no-dashboard"],
    "labelled": ["--labelled-laz", "--trunks-max-post-radius", "0.08"],
}
"""``orchard process`` options of each run."""

BLOCKS = Path("/tmp/orchard-identity")
"""Where the generated blocks are (outputs store their input's path)."""


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def measure(work: Path) -> dict[str, dict[str, str]]:
    """Run every scene under every run; the hash of each output file by ``scene/run``."""
    work.mkdir(parents=True, exist_ok=True)
    BLOCKS.mkdir(parents=True, exist_ok=True)
    manifest: dict[str, dict[str, str]] = {}
    for scene, options in SCENES.items():
        block = BLOCKS / f"{scene}.laz"
        with open(BLOCKS / ".lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not block.exists():
                tmp = BLOCKS / f".{scene}.tmp.laz"
                subprocess.run(["orchard", "simulate", "--out", str(tmp), "--truth", str(BLOCKS / f"{scene}.truth.parquet"),
                                *options], check=True, stdout=subprocess.DEVNULL)
                tmp.rename(block)
        for run, extra in RUNS.items():
            out = work / f"{scene}-{run}"
            shutil.rmtree(out, ignore_errors=True)
            subprocess.run(["orchard", "process", str(block), "--out", str(out), *extra], check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            manifest[f"{scene}/{run}"] = {f.name: _sha256(f) for f in sorted(out.iterdir()) if f.is_file()}
            print(f"{scene}/{run}: {len(manifest[f'{scene}/{run}'])} files", file=sys.stderr)
    return manifest


def differences(before: dict, after: dict) -> list[str]:
    """Every file that is missing, new or different, as ``run/file: what``."""
    out = []
    for key in sorted(set(before) | set(after)):
        b, a = before.get(key, {}), after.get(key, {})
        for name in sorted(set(b) | set(a)):
            if name not in a:
                out.append(f"{key}/{name}: missing")
            elif name not in b:
                out.append(f"{key}/{name}: new")
            elif a[name] != b[name]:
                out.append(f"{key}/{name}: differs")
    return out


def manifest_arguments(argv: list[str] | None, *, prog: str, description: str, work: str) -> argparse.Namespace:
    """The options of a manifest bench: ``--write`` or ``--compare`` MANIFEST, and ``--work``
    (default ``work``) for the outputs."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", type=Path, metavar="MANIFEST", help="write the hashes to this JSON file")
    g.add_argument("--compare", type=Path, metavar="MANIFEST", help="compare with the hashes in this JSON file")
    p.add_argument("--work", type=Path, default=Path(work), help="folder for the outputs")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = manifest_arguments(argv, prog="python -m bench.identity", description=__doc__.splitlines()[0],
                              work="/tmp/orchard-identity-out")
    return write_or_compare(args, measure(args.work), "files")


def write_or_compare(args: argparse.Namespace, manifest: dict, unit: str) -> int:
    """Write ``manifest`` to ``args.write``, or compare it with ``args.compare`` and print
    each difference: the exit code (1 on any difference). ``unit``: what an entry is."""
    if args.write:
        args.write.write_text(json.dumps(manifest, indent=1, sort_keys=True))
        print(f"{sum(map(len, manifest.values()))} {unit} in {len(manifest)} runs -> {args.write}")
        return 0
    diff = differences(json.loads(args.compare.read_text()), manifest)
    for line in diff:
        print(line)
    n = sum(map(len, manifest.values()))
    print(f"{n - len(diff)} of {n} {unit} identical" if diff else f"all {n} {unit} in {len(manifest)} runs identical")
    return 1 if diff else 0


if __name__ == "__main__":
    raise SystemExit(main())
