"""What the job page's map draws, as one JSON-able dict.

Coordinates are local metres (the input CRS minus ``origin``, a whole-metre corner below
every trunk) so that a browser's float arithmetic keeps centimetres. Every tree has its
trunk and, when the block and ``points.parquet`` are at hand, its footprint: the convex
hull of a subsample of its points seen from above (else the page draws a circle of its
crown diameter). Row lines (``rows.parquet``) and empty slots (``gaps.parquet``) are
added when the job has them; for a capture of an orchard block, each tree's status, the
block's history (``history.parquet`` beside ``trees.parquet``) and the capture's record
too (null for any other job: the pages then show no changes).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from pipeline.parquet import read_table
from service.reports.sampling import sample_points

#: points sampled from the block for the footprints (enough for a smooth hull per tree)
FOOTPRINT_POINTS = 400_000


def _clean(values: np.ndarray) -> list:
    """A column as a JSON list: floats rounded to mm, NaN as null, bools as 0/1."""
    arr = np.asarray(values)
    if arr.dtype.kind == "b":
        return arr.astype(int).tolist()
    if arr.dtype.kind == "f":
        out = np.round(arr.astype(np.float64), 3).astype(object)
        out[~np.isfinite(arr)] = None
        return out.tolist()
    if arr.dtype.kind in "iu":
        return arr.astype(np.int64).tolist()
    return [None if v is None else str(v) for v in arr.tolist()]


def parse_wkb(data: bytes) -> list[list[float]]:
    """The coordinate rings of a 2D/3D WKB Point, LineString or Polygon (or their Multi- forms),
    each as a flat ``[x0, y0, x1, y1, ...]`` list; [] for anything else."""
    rings: list[list[float]] = []

    def geom(off: int) -> int:
        order = "<" if data[off] == 1 else ">"
        (kind,) = struct.unpack_from(order + "I", data, off + 1)
        off += 5
        dims = 3 if (kind // 1000 in (1, 2) or kind & 0x80000000) else 2
        base = (kind & 0xFFFF) % 1000
        step = 8 * dims

        def coords(n: int, at: int) -> tuple[list[float], int]:
            flat = []
            for i in range(n):
                x, y = struct.unpack_from(order + "dd", data, at + i * step)
                flat += [x, y]
            return flat, at + n * step

        if base == 1:
            flat, off = coords(1, off)
            rings.append(flat)
        elif base == 2:
            (n,) = struct.unpack_from(order + "I", data, off)
            flat, off = coords(n, off + 4)
            rings.append(flat)
        elif base == 3:
            (nr,) = struct.unpack_from(order + "I", data, off)
            off += 4
            for _ in range(nr):
                (n,) = struct.unpack_from(order + "I", data, off)
                flat, off = coords(n, off + 4)
                rings.append(flat)
        elif base in (4, 5, 6):
            (n,) = struct.unpack_from(order + "I", data, off)
            off += 4
            for _ in range(n):
                off = geom(off)
        return off

    try:
        geom(0)
    except (struct.error, IndexError):
        return []
    return rings


def _local(flat: list[float], origin: np.ndarray) -> list[float]:
    arr = np.asarray(flat, dtype=np.float64).reshape(-1, 2) - origin
    return np.round(arr, 2).ravel().tolist()


def footprints(xy: np.ndarray, tree_id: np.ndarray, ids: np.ndarray) -> list[list[float] | None]:
    """Plan-view convex hull of each tree's sampled points, flat ``[x0, y0, ...]`` in the
    frame of ``xy`` [m], in the order of ``ids``; None for a tree with under 3 points."""
    keep = tree_id > 0
    xy, tree_id = xy[keep], tree_id[keep]
    order = np.argsort(tree_id, kind="stable")
    xy, tree_id = xy[order], tree_id[order]
    uniq, starts = np.unique(tree_id, return_index=True)
    ends = np.append(starts[1:], len(tree_id))
    where = {int(t): (s, e) for t, s, e in zip(uniq, starts, ends)}
    out: list[list[float] | None] = []
    for t in ids:
        span = where.get(int(t))
        if span is None or span[1] - span[0] < 3:
            out.append(None)
            continue
        pts = xy[span[0] : span[1]]
        try:
            hull = pts[ConvexHull(pts).vertices]
        except QhullError:  # collinear: no area to draw
            out.append(None)
            continue
        out.append(np.round(hull, 2).ravel().tolist())
    return out


def _features(path: Path, origin: np.ndarray) -> list[dict[str, Any]] | None:
    """The rows of ``rows.parquet`` / ``gaps.parquet``: their non-geometry columns and their
    geometry as local coordinates (``line`` for a row, ``x``/``y`` for a slot)."""
    if not path.is_file():
        return None
    table = read_table(path)
    names = [n for n in table.column_names if n != "geometry"]
    cols = {n: _clean(table.column(n).to_numpy(zero_copy_only=False)) for n in names}
    geoms = table.column("geometry").to_pylist() if "geometry" in table.column_names else [None] * table.num_rows
    out = []
    for i in range(table.num_rows):
        rec = {n: cols[n][i] for n in names}
        rings = parse_wkb(geoms[i]) if geoms[i] else []
        if rings:
            rec["line"] = _local(rings[0], origin)
        else:
            pairs = [("x0", "y0", "x1", "y1"), ("start_x", "start_y", "end_x", "end_y")]
            for a, b, c, d in pairs:
                if all(rec.get(k) is not None for k in (a, b, c, d)):
                    rec["line"] = _local([rec[a], rec[b], rec[c], rec[d]], origin)
                    break
        if len(rec.get("line") or []) == 2:  # a point: an empty slot
            rec["x"], rec["y"] = rec.pop("line")
        elif rec.get("x") is not None and rec.get("y") is not None and "line" not in rec:
            rec["x"], rec["y"] = _local([rec["x"], rec["y"]], origin)
        out.append(rec)
    return out


#: the per-tree columns of a capture that are text (shown in lists and details, not as metrics)
TEXT_COLUMNS = ("status",)
#: what the pages show of a tree's history (``history.parquet``), besides its key and capture
HISTORY_COLUMNS = ("row", "position", "height_m", "crown_volume_m3", "trunk_diameter_m")


def history_data(path: Path) -> dict[str, Any] | None:
    """A block's ``history.parquet`` as the pages draw it (None without one): the
    captures in the file's order (``captures``: ids, ``dates``: ISO days), and one entry
    per row: ``tree_key``, ``capture`` (an index into ``captures``), `HISTORY_COLUMNS`
    and ``status``."""
    if not path.is_file():
        return None
    table = read_table(path)
    names = set(table.column_names)
    if not {"tree_key", "capture"} <= names:
        return None
    capture = [str(c) for c in table.column("capture").to_pylist()]
    dates = table.column("captured_at").to_pylist() if "captured_at" in names else [None] * len(capture)
    order: dict[str, int] = {}
    for c in capture:
        order.setdefault(c, len(order))
    first_date: dict[str, Any] = {}
    for c, d in zip(capture, dates):
        first_date.setdefault(c, d)
    out: dict[str, Any] = {
        "captures": list(order),
        "dates": [None if first_date[c] is None else str(first_date[c]) for c in order],
        "tree_key": _clean(table.column("tree_key").to_numpy(zero_copy_only=False)),
        "capture": [order[c] for c in capture],
        "status": [None if v is None else str(v) for v in table.column("status").to_pylist()] if "status" in names else None,
    }
    for name in HISTORY_COLUMNS:
        if name in names:
            out[name] = _clean(table.column(name).to_numpy(zero_copy_only=False))
    return out


def capture_record(table_metadata: dict | None) -> dict[str, Any] | None:
    """The ``orchard:capture`` record in ``trees.parquet``'s schema metadata (None without one)."""
    raw = (table_metadata or {}).get(b"orchard:capture")
    if not raw:
        return None
    try:
        return json.loads(raw)
    except ValueError:
        return None


def build_map_data(
    trees_parquet: str | os.PathLike,
    *,
    block_path: str | None = None,
    points_parquet: str | os.PathLike | None = None,
    sample: tuple[np.ndarray, np.ndarray] | None = None,
    max_points: int = FOOTPRINT_POINTS,
) -> dict[str, Any]:
    """The map's data for a job's outputs folder (see the module docstring).

    The footprints come from ``sample`` ((m, 2) points in the input CRS [m] and their
    (m,) tree ids) or else from sampling ``block_path`` with ``points_parquet``; without
    either the page draws circles.
    """
    trees_parquet = Path(trees_parquet)
    table = read_table(trees_parquet)
    names = [n for n in table.column_names if n != "geometry"]
    cols = {n: table.column(n).to_numpy(zero_copy_only=False) for n in names}
    n = table.num_rows
    tx = np.asarray(cols.get("trunk_x", np.zeros(n)), dtype=np.float64)
    ty = np.asarray(cols.get("trunk_y", np.zeros(n)), dtype=np.float64)
    finite = np.isfinite(tx) & np.isfinite(ty)
    origin = np.floor([tx[finite].min(), ty[finite].min()]) if finite.any() else np.zeros(2)
    outlines: list | None = None
    if sample is None and block_path and points_parquet and Path(block_path).is_file() and Path(points_parquet).is_file():
        xy, tree_id, block_origin = sample_points(block_path, points_parquet, max_points=max_points)
        sample = (xy + block_origin[:2], tree_id)
    if sample is not None and n:
        outlines = footprints(sample[0] - origin, sample[1], np.asarray(cols["tree_id"]))
    folder = trees_parquet.parent
    return {
        "origin": origin.tolist(),
        "n_trees": n,
        "x": _clean(np.round(tx - origin[0], 2)),
        "y": _clean(np.round(ty - origin[1], 2)),
        "columns": {k: _clean(v) for k, v in cols.items() if np.asarray(v).dtype.kind in "biuf"},
        "outlines": outlines,
        "rows": _features(folder / "rows.parquet", origin),
        "gaps": _features(folder / "gaps.parquet", origin),
        "partial": (table.schema.metadata or {}).get(b"orchard:failed_tiles") is not None,
        # a capture of an orchard block: each tree's status, the block's history, the capture's record
        "text": {k: [None if v is None else str(v) for v in table.column(k).to_pylist()] for k in TEXT_COLUMNS if k in names},
        "history": history_data(folder / "history.parquet"),
        "capture": capture_record(table.schema.metadata),
    }


def to_json(data: dict[str, Any]) -> str:
    """Compact JSON safe to put inside an HTML ``<script>`` element."""
    # no "<" at all: "</script" would end the element, "<!--" would change how it is parsed
    return json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
