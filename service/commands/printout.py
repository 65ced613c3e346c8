"""What `orchard process` prints on the terminal: a block summary and one line per row
by default (a block of a thousand trees is a screenful, not a thousand lines), the
per-tree table with each tree's address only on request (``--trees``)."""

from __future__ import annotations

import sys

import numpy as np

TREE_COLUMNS = [
    ("row", "row", "{:d}"),
    ("position", "pos", "{:d}"),
    ("tree_id", "tree", "{:d}"),
    ("young", "young", "{}"),
    ("trunk_x", "trunk_x", "{:.2f}"),
    ("trunk_y", "trunk_y", "{:.2f}"),
    ("height_m", "height_m", "{:.2f}"),
    ("crown_diameter_m", "crown_d_m", "{:.2f}"),
    ("crown_area_m2", "crown_m2", "{:.1f}"),
    ("trunk_diameter_m", "trunk_d_m", "{:.3f}"),
    ("n_points", "points", "{:d}"),
    ("wood_fraction", "wood", "{:.2f}"),
]


def _cell(v, fmt: str) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, float) and v != v:
        return "nan"
    return fmt.format(v.item() if hasattr(v, "item") else v)


def _table(header: list[str], rows: list[list[str]], stream) -> None:
    rows = [header, *rows]
    widths = [max(len(r[j]) for r in rows) for j in range(len(header))]
    for r in rows:
        stream.write("  ".join(c.rjust(w) for c, w in zip(r, widths)) + "\n")


def print_trees(trees: dict, stream=None) -> None:
    """The per-tree table, address first (the columns a block without rows lacks are left out)."""
    stream = stream or sys.stdout
    cols = [c for c in TREE_COLUMNS if c[0] in trees]
    body = [[_cell(trees[name][i], fmt) for name, _, fmt in cols] for i in range(len(trees["tree_id"]))]
    _table([h for _, h, _ in cols], body, stream)


def print_summary(trees: dict, rows: dict | None, stream=None) -> None:
    """The block in a few lines: trees, rows, empty slots, young trees, mean height; then
    one line per row (trees, empty slots, young, mean height). ``rows`` is the content of
    rows.parquet (None: the block was processed without rows)."""
    stream = stream or sys.stdout
    n = len(trees["tree_id"])
    height = np.asarray(trees["height_m"], dtype=np.float64)
    young = np.asarray(trees.get("young", np.zeros(n, bool)), dtype=bool)
    parts = [f"{n} trees"]
    if rows is not None:
        parts += [f"{len(rows['row'])} rows", f"{int(np.sum(rows['n_gaps']))} empty slots"]
    parts += [f"{int(young.sum())} young", f"mean height {height.mean():.2f} m" if n else "mean height -"]
    stream.write(", ".join(parts) + "\n")
    if rows is None or not len(rows["row"]):
        return
    row_of = np.asarray(trees["row"])
    body = []
    for r, gaps in zip(rows["row"], rows["n_gaps"]):
        mine = row_of == r
        h = f"{height[mine].mean():.2f}" if mine.any() else "-"
        body.append([str(r), str(int(mine.sum())), str(int(gaps)), str(int(young[mine].sum())), h])
    off = ~np.isin(row_of, np.asarray(rows["row"]))
    if off.any():
        body.append(["off rows", str(int(off.sum())), "-", str(int(young[off].sum())), f"{height[off].mean():.2f}"])
    _table(["row", "trees", "empty", "young", "height_m"], body, stream)
