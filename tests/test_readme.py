"""The README and the docs pages it leads to: short, runnable as written, no dead links."""

import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
#: pages whose links this test owns (the README's pages moved out of it)
PAGES = [README] + [ROOT / "docs" / f"{name}.md" for name in
                    ("method", "outputs", "api", "operations", "benchmarks", "limits", "architecture")]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.DOTALL)
    return {_slug(m) for m in re.findall(r"^#+ (.+)$", text, flags=re.MULTILINE)}


def _ci_test_command() -> str:
    lines = [ln for ln in (ROOT / ".ci" / "run").read_text().splitlines() if "pytest" in ln]
    assert len(lines) == 1, lines
    return lines[0].strip()


def test_readme_is_short():
    assert len(README.read_text().splitlines()) <= 300


def test_quickstart_commands_are_what_ci_runs():
    text = README.read_text()
    block = re.search(r"## Quickstart.*?```sh\n(.*?)```", text, flags=re.DOTALL).group(1).splitlines()
    assert block[0] == "pip install -e . && orchard demo"
    assert shlex.split(block[1]) == shlex.split(_ci_test_command().replace("pip install -q ", "pip install "))
    assert 'python -m pytest -q -m "not slow"' in text


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page):
    if not page.exists():
        pytest.fail(f"{page.relative_to(ROOT)} is missing")
    dead = []
    for target in LINK.findall(page.read_text()):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists() or (anchor and dest.suffix == ".md" and anchor not in _anchors(dest)):
            dead.append(target)
    assert dead == [], f"dead links in {page.name}: {dead}"
