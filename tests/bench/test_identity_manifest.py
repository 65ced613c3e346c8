"""bench.identity's manifest options and comparison (the benches that guard byte identity)."""

from __future__ import annotations

import json

import pytest

from bench.identity import manifest_arguments, write_or_compare


def _args(argv):
    return manifest_arguments(argv, prog="t", description="t", work="/tmp/w")


def test_write_or_compare_is_required_and_exclusive(capsys):
    for argv in ([], ["--write", "a.json", "--compare", "b.json"]):
        with pytest.raises(SystemExit) as exc:
            _args(argv)
        assert exc.value.code == 2
    assert str(_args(["--write", "a.json"]).work) == "/tmp/w"


def test_a_changed_file_fails_the_comparison(tmp_path, capsys):
    manifest = {"vase/whole": {"trees.parquet": "aa", "points.laz": "bb"}}
    path = tmp_path / "m.json"
    assert write_or_compare(_args(["--write", str(path)]), manifest, "files") == 0
    assert json.loads(path.read_text()) == manifest
    assert write_or_compare(_args(["--compare", str(path)]), manifest, "files") == 0
    assert "all 2 files in 1 runs identical" in capsys.readouterr().out
    changed = {"vase/whole": {"trees.parquet": "aa", "points.laz": "cc"}}
    assert write_or_compare(_args(["--compare", str(path)]), changed, "files") == 1
    out = capsys.readouterr().out
    assert "points.laz" in out and "1 of 2 files identical" in out
