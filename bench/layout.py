"""``python -m bench.layout``: the project's packages, modules and their imports, as Markdown.

Walks the source of the project's packages with :mod:`ast` (nothing is imported or run)
and prints:

- a mermaid graph of package → package imports (each edge labelled with the number of
  module-to-module imports behind it);
- a mermaid graph of module imports, one box per package;
- imports against the dependency direction (service → workers → pipeline) and import
  cycles between modules, if any;
- the line counts of the largest modules.

Imports inside functions are dependencies too, only deferred: they are drawn dotted, and
cycles are reported both with and without them (a loop of module-level imports can fail
at import time; one closed by a deferred import cannot).
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
START, END = "<!-- layout:start -->", "<!-- layout:end -->"
PACKAGES = ("pipeline", "workers", "service", "bench")
#: lower layers first: a package may import those before it, not those after
LAYERS = ("pipeline", "workers", "service")


@dataclass
class Layout:
    """Modules (dotted names) with their line counts and the project modules they import."""

    lines: dict[str, int] = field(default_factory=dict)
    imports: dict[str, set[str]] = field(default_factory=dict)
    #: the subset of ``imports`` made inside a function (deferred)
    deferred: dict[str, set[str]] = field(default_factory=dict)
    packages: set[str] = field(default_factory=set)

    def top_level(self) -> dict[str, set[str]]:
        """Imports made when the module is imported (not deferred into a function)."""
        return {m: t - self.deferred.get(m, set()) for m, t in self.imports.items()}

    def package_of(self, module: str) -> str:
        """The package a module belongs to (a package's ``__init__`` belongs to itself)."""
        return module if module in self.packages else module.rpartition(".")[0]


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(name: str, known: set[str]) -> str | None:
    """The longest known module that ``name`` (``a.b.c``, maybe an attribute) lies in."""
    while name:
        if name in known:
            return name
        name = name.rpartition(".")[0]
    return None


def _imported_names(tree: ast.AST, module: str, is_package: bool) -> list[tuple[str, bool]]:
    """(dotted name, deferred) of every import of a module, relative imports made absolute;
    deferred = made inside a function."""
    names = []
    todo = [(node, False) for node in ast.iter_child_nodes(tree)]
    while todo:
        node, deferred = todo.pop()
        inner = deferred or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
        todo += [(child, inner) for child in ast.iter_child_nodes(node)]
        if isinstance(node, ast.Import):
            names += [(alias.name, deferred) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                # ``from . import x`` in a package's __init__ is the package itself
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            # ``from pkg import mod`` imports a module; ``from mod import func`` its attribute
            found = [f"{prefix}.{alias.name}" for alias in node.names if alias.name != "*"] or [prefix]
            names += [(n, deferred) for n in found]
    return names


def scan(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> Layout:
    """Parse every module of ``packages`` under ``root``."""
    layout = Layout()
    sources: dict[str, tuple[ast.AST, bool]] = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            if not (path.parent / "__init__.py").exists():
                continue  # scripts and data folders that are not part of a package
            name = _module_name(path, root)
            text = path.read_text(encoding="utf-8")
            layout.lines[name] = len(text.splitlines())
            is_package = path.name == "__init__.py"
            if is_package:
                layout.packages.add(name)
            sources[name] = (ast.parse(text, filename=str(path)), is_package)
    known = set(layout.lines)
    for name, (tree, is_package) in sources.items():
        now: set[str] = set()
        later: set[str] = set()
        for dotted, deferred in _imported_names(tree, name, is_package):
            target = _resolve(dotted, known)
            if target and target != name:
                (later if deferred else now).add(target)
        layout.imports[name] = now | later
        layout.deferred[name] = later - now
    return layout


def package_edges(layout: Layout) -> Counter:
    """(package, package) → number of module imports from the first into the second."""
    edges: Counter = Counter()
    for src, targets in layout.imports.items():
        for dst in targets:
            a, b = layout.package_of(src), layout.package_of(dst)
            if a != b:
                edges[a, b] += 1
    return edges


def against_direction(layout: Layout, layers: tuple[str, ...] = LAYERS) -> list[tuple[str, str]]:
    """Module imports from a lower layer into a higher one (pipeline → workers, ...)."""
    rank = {name: i for i, name in enumerate(layers)}
    bad = []
    for src, targets in sorted(layout.imports.items()):
        a = rank.get(src.split(".")[0])
        for dst in sorted(targets):
            b = rank.get(dst.split(".")[0])
            if a is not None and b is not None and b > a:
                bad.append((src, dst))
    return bad


def cycles(layout: Layout, *, deferred: bool = True) -> list[list[str]]:
    """Groups of modules that import each other in a loop (Tarjan's strongly connected
    components of more than one module), each sorted; ``deferred=False`` follows only
    module-level imports."""
    graph = layout.imports if deferred else layout.top_level()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0

    def visit(v: str) -> None:
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(layout.lines) + 100))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(found)


def largest(layout: Layout, n: int = 5) -> list[tuple[str, int]]:
    """The ``n`` modules with the most lines, largest first."""
    return sorted(layout.lines.items(), key=lambda kv: (-kv[1], kv[0]))[:n]


def _node(name: str) -> str:
    return name.replace(".", "_")


def _module_graph(layout: Layout, pkgs: list[str]) -> list[str]:
    """The mermaid graph of module imports, one box per package."""
    out = ["## Modules", "",
           ("Every module of a package in one box; an arrow is an import of one module by another, "
            "dotted where it is made inside a function."), "",
           "```mermaid", "flowchart LR"]
    for p in pkgs:
        out.append(f'    subgraph {_node(p)}_box["{p}"]')
        for m in sorted(m for m in layout.lines if layout.package_of(m) == p):
            label = m.rpartition(".")[2] if m != p else "__init__"
            out.append(f'        {_node(m)}["{label}"]')
        out.append("    end")
    for src in sorted(layout.imports):
        for dst in sorted(layout.imports[src]):
            arrow = "-.->" if dst in layout.deferred.get(src, ()) else "-->"
            out.append(f"    {_node(src)} {arrow} {_node(dst)}")
    out += ["```", ""]
    return out


def render(layout: Layout, *, top: int = 5, modules: bool = True) -> str:
    """The Markdown report: package graph, module graph (unless ``modules`` is False),
    checks, largest modules."""
    out = []
    pkgs = sorted(layout.packages)
    out += ["## Packages", "",
            (f"{len(layout.lines)} modules, {sum(layout.lines.values()):,} lines in {len(pkgs)} packages. "
             "An arrow is an import; its label, how many module-to-module imports it stands for."), "",
            "```mermaid", "flowchart LR"]
    for p in pkgs:
        sizes = [n for m, n in layout.lines.items() if layout.package_of(m) == p]
        out.append(f'    {_node(p)}["{p}<br/>{len(sizes)} modules, {sum(sizes):,} lines"]')
    for (a, b), k in sorted(package_edges(layout).items()):
        out.append(f"    {_node(a)} -->|{k}| {_node(b)}")
    out += ["```", ""]

    if modules:
        out += _module_graph(layout, pkgs)
    out += ["## Checks", ""]
    bad = against_direction(layout)
    out.append("- Imports against the direction " + " ← ".join(reversed(LAYERS)) + ": "
               + (", ".join(f"`{a}` → `{b}`" for a, b in bad) if bad else "none."))
    for label, loops in (("module-level imports", cycles(layout, deferred=False)),
                         ("with the deferred ones", cycles(layout))):
        out.append(f"- Import cycles between modules, {label}: "
                   + ("; ".join(" ↔ ".join(f"`{m}`" for m in group) for group in loops) if loops else "none."))
    out += ["", f"## The {top} largest modules", "", "| module | lines |", "| --- | ---: |"]
    out += [f"| `{m}` | {n:,} |" for m, n in largest(layout, top)]
    out.append("")
    return "\n".join(out)


def stamp(root: Path) -> str:
    """Which command made the report, when, and on which commit."""
    from datetime import datetime

    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    at = f" on the working tree of commit {commit}" if commit else ""
    return f"Generated by `python -m bench.layout` on {when}{at}.\n\n"


def splice(page: Path, text: str) -> bool:
    """Replace what lies between the layout markers of ``page``; False if it has none."""
    old = page.read_text(encoding="utf-8") if page.exists() else ""
    if START not in old or END not in old or old.index(START) > old.index(END):
        return False
    a, b = old.index(START) + len(START), old.index(END)
    page.write_text(old[:a] + "\n" + text.strip() + "\n" + old[b:], encoding="utf-8")
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.layout", description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="project folder (default: this checkout)")
    parser.add_argument("--packages", default=",".join(PACKAGES),
                        help=f"comma-separated top-level packages (default {','.join(PACKAGES)})")
    parser.add_argument("--top", type=int, default=5, help="how many of the largest modules to list (default 5)")
    parser.add_argument("--no-modules", action="store_true", help="leave out the module graph (packages only)")
    parser.add_argument("--write", type=Path, metavar="PAGE",
                        help=f"write the report into PAGE between {START} and {END} instead of printing it "
                             "(docs/architecture.md)")
    args = parser.parse_args(argv)
    packages = tuple(p.strip() for p in args.packages.split(",") if p.strip())
    missing = [p for p in packages if not (args.root / p / "__init__.py").exists()]
    if missing:
        print(f"python -m bench.layout: no package {', '.join(missing)} under {args.root}", file=sys.stderr)
        return 2
    try:
        layout = scan(args.root, packages)
    except SyntaxError as exc:
        print(f"python -m bench.layout: cannot parse {exc.filename}: {exc.msg} (line {exc.lineno})", file=sys.stderr)
        return 2
    text = stamp(args.root) + render(layout, top=args.top, modules=not args.no_modules)
    if args.write is None:
        sys.stdout.write(text)
        return 0
    if not splice(args.write, text):
        print(f"python -m bench.layout: {args.write} has no {START} / {END} markers; left it alone", file=sys.stderr)
        return 2
    print(f"wrote the layout into {args.write}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
