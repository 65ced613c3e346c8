"""The per-tree report a grower reads: one HTML page with a map of the block and a table.

The page is interactive (`service.pages.report_page`: pan, zoom, colour by a
metric, search, a sortable table; for a capture of an orchard block, growth colours, the
changes since the previous capture and each tree's history, read from ``history.parquet``
beside ``trees.parquet``) and self-contained; the static map and table below
are what it shows where scripts do not run.

The map (PNG, :mod:`service.reports.mapimage`: matplotlib's axes over the points composed into one
image; embedded in the page as base64 and also saved as ``map.png``) shows a subsample
of the block's points seen from above, tree points
coloured by tree id, other points grey, and each trunk as a marker with its number. The
table has one row per tree from ``trees.parquet``. Memory stays bounded: the block and
``points.parquet`` are read in chunks and only every ``stride``-th point is kept
(:mod:`service.reports.sampling`).
"""

from __future__ import annotations

import base64
import html
import io
import os
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv

from pipeline.mapsample import REPORT_POINTS
from pipeline.parquet import read_table
from service.reports import mapdata
from service.reports.mapimage import render_map_png
from service.reports.sampling import sample_points
from service import pages

#: the outputs the report links to, beside it (relative links)
DOWNLOADS = ("trees.csv", "trees.parquet", "points.parquet", "rows.parquet", "gaps.parquet", "history.parquet", "map.png")

TABLE_COLUMNS = [
    ("tree_id", "Tree", "{:d}"),
    ("trunk_x", "Trunk x", "{:.2f}"),
    ("trunk_y", "Trunk y", "{:.2f}"),
    ("height_m", "Height [m]", "{:.2f}"),
    ("crown_diameter_m", "Crown diameter [m]", "{:.2f}"),
    ("crown_area_m2", "Crown area [m²]", "{:.2f}"),
    ("crown_volume_m3", "Crown volume [m³]", "{:.2f}"),
    ("trunk_diameter_m", "Trunk diameter [m]", "{:.3f}"),
    ("n_points", "Points", "{:d}"),
    ("wood_fraction", "Wood fraction", "{:.2f}"),
]
#: the columns of a capture of an orchard block, shown when the trees have them
CHANGE_COLUMNS = [
    ("tree_key", "Tree key", "{:d}"),
    ("status", "Status", "{}"),
    ("height_change_m", "Height change [m]", "{:+.2f}"),
    ("crown_volume_change_m3", "Crown volume change [m³]", "{:+.2f}"),
    ("trunk_diameter_change_m", "Trunk diameter change [m]", "{:+.3f}"),
]


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all (a reader never sees half a file)."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def trees_table(trees_parquet: str | os.PathLike) -> dict[str, np.ndarray]:
    """Columns of ``trees.parquet`` without the geometry."""
    table = read_table(trees_parquet)
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in table.column_names if n != "geometry"}


def trees_records(trees_parquet: str | os.PathLike) -> list[dict]:
    """One JSON-able dict per tree (NaN → None)."""
    cols = trees_table(trees_parquet)
    names = list(cols)
    n = len(cols[names[0]]) if names else 0
    out = []
    for i in range(n):
        rec = {}
        for name in names:
            v = cols[name][i]
            v = v.item() if hasattr(v, "item") else v
            if isinstance(v, float) and not np.isfinite(v):
                v = None
            rec[name] = v
        out.append(rec)
    return out


def write_trees_csv(trees_parquet: str | os.PathLike, csv_path: str | os.PathLike) -> Path:
    """``trees.csv``: the columns of ``trees.parquet`` without the geometry (atomic); a
    value that could not be measured (NaN) is an empty cell, as spreadsheets expect."""
    table = read_table(trees_parquet)
    if "geometry" in table.column_names:
        table = table.drop(["geometry"])
    for i, field in enumerate(table.schema):
        if pa.types.is_floating(field.type):  # (a null read as NaN stays null)
            # a mask from numpy: pyarrow.compute's import alone (0.1 s) was most of this file's cost
            col = table.column(i).to_numpy()
            table = table.set_column(i, field, pa.array(col, type=field.type, mask=np.isnan(col)))
    buf = io.BytesIO()
    pacsv.write_csv(table, buf)
    path = Path(csv_path)
    atomic_write(path, buf.getvalue())
    return path


def render_map(xy: np.ndarray, tree_id: np.ndarray, trunks_xy: np.ndarray, trunk_ids: np.ndarray, *, title: str) -> bytes:
    """PNG of the block from above: tree points coloured by id, trunk markers with numbers
    (:func:`service.reports.mapimage.render_map_png`).

    ``xy`` and ``trunks_xy`` are in the same local frame [m].
    """
    return render_map_png(xy, tree_id, trunks_xy, trunk_ids, title=title)


def _drawn_here(*args, **kwargs) -> Callable[[], bytes]:
    """:func:`render_map` now, as a ``draw_map`` of :func:`write_report`."""
    png = render_map(*args, **kwargs)
    return lambda: png


def _cell(value, fmt: str) -> str:
    if value is None:
        return "–"
    if isinstance(value, str):
        return html.escape(value)
    try:
        if isinstance(value, float) and not np.isfinite(value):
            return "–"
        if fmt == "{:d}":
            return str(int(value))
        return fmt.format(float(value))
    except (TypeError, ValueError):
        return html.escape(str(value))


def render_html(
    *, title: str, png: bytes, rows: list[dict], origin: np.ndarray, summary: dict[str, str], warning: str | None = None
) -> str:
    columns = TABLE_COLUMNS + [c for c in CHANGE_COLUMNS if rows and c[0] in rows[0]]
    head = "".join(f"<th>{html.escape(label)}</th>" for _, label, _ in columns)
    body = "\n".join(
        "<tr>" + "".join(f"<td>{_cell(r.get(key), fmt)}</td>" for key, _, fmt in columns) + "</tr>" for r in rows
    )
    facts = "".join(f"<li>{html.escape(k)}: {html.escape(v)}</li>" for k, v in summary.items())
    notice = f'<p class="warning"><strong>{html.escape(warning)}</strong></p>' if warning else ""
    img = base64.b64encode(png).decode("ascii")
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; }} th, td {{ padding: 4px 10px; border-bottom: 1px solid #ddd; text-align: right; }}
th {{ background: #f3f3f3; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
.warning {{ background: #fff3cd; border: 1px solid #e0b000; padding: 0.6em 1em; }}
</style></head>
<body>
<h1>{html.escape(title)}</h1>
{notice}
<ul>{facts}</ul>
<p>Map: the block from above; tree points coloured by tree, trunks numbered. Local frame: x − {origin[0]:.0f}, y − {origin[1]:.0f} (input CRS).</p>
<img alt="map of the block with numbered trees" src="data:image/png;base64,{img}">
<h2>Trees ({len(rows)})</h2>
<p>Trunk x/y in the input CRS.</p>
<table><thead><tr>{head}</tr></thead><tbody>
{body}
</tbody></table>
</body></html>
"""


def _body_of(page: str) -> str:
    """The inside of a page's ``<body>`` (the static report, shown where scripts do not run)."""
    return page.split("<body>", 1)[1].rsplit("</body>", 1)[0]


def write_report(
    *,
    block_path: str,
    trees_parquet: str | os.PathLike,
    points_parquet: str | os.PathLike,
    out_dir: str | os.PathLike,
    title: str,
    summary: dict[str, str] | None = None,
    warning: str | None = None,
    max_points: int = REPORT_POINTS,
    sample: dict | None = None,
    draw_map: Callable[..., Callable[[], bytes]] | None = None,
) -> Path:
    """Write ``report.html`` and ``map.png`` into ``out_dir``; returns the HTML path.

    The report is the job page of the service (`service.pages.report_page`) with its
    scripts, styles and data inlined: it opens from disk, offline. Where scripts do not
    run it shows the static map (``map.png``, embedded) and table. ``warning`` is shown
    above everything else (a partial result). ``sample``: the points :func:`sample_points`
    would read, already in memory (``workers.job.report_sample``), used when taken for
    the same ``max_points``. ``draw_map``: takes :func:`render_map`'s arguments and returns
    a function that returns the PNG (:meth:`service.reports.mapprocess.MapProcess.draw`,
    which draws it in another process while this one builds the page's data); default:
    drawn here.
    """
    out = Path(out_dir)
    if sample is not None and sample["max_points"] == max_points:
        xy, tree_id, origin = sample["xy"], sample["tree_id"], sample["origin"]
    else:
        xy, tree_id, origin = sample_points(block_path, points_parquet, max_points=max_points)
    rows = trees_records(trees_parquet)
    if rows:
        trunks_xy = np.array([[r["trunk_x"], r["trunk_y"]] for r in rows], dtype=np.float64) - origin[:2]
        ids = np.array([r["tree_id"] for r in rows])
    else:
        trunks_xy, ids = np.zeros((0, 2)), np.zeros(0, np.int64)
    drawn = (draw_map or _drawn_here)(xy, tree_id, trunks_xy, ids, title=title)
    data = mapdata.build_map_data(trees_parquet, sample=(xy + origin[:2], tree_id))
    png = drawn()
    atomic_write(out / "map.png", png)
    static = render_html(title=title, png=png, rows=rows, origin=origin, summary=summary or {}, warning=warning)
    # the files beside the report: relative links work from disk and under /v1/jobs/<id>/
    # (trees.csv is written beside it by `orchard process`, and on its first download by the service)
    downloads = {name: name for name in DOWNLOADS if name == "trees.csv" or (out / name).is_file()}
    page = pages.report_page(title=title, data_json=mapdata.to_json(data), facts=summary or {}, downloads=downloads,
                              warning=warning, fallback=_body_of(static))
    path = out / "report.html"
    atomic_write(path, page.encode("utf-8"))
    return path
