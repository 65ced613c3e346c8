"""The pipeline's Parquet outputs: GeoParquet trees, rows and gaps (WKB geometry, ``geo``
metadata), streamed per-point labels and truth, and reading them back."""

from __future__ import annotations

import functools
import json
import os
import struct
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.atomic import AtomicWriter, temp_name
from pipeline.blockinfo import one_line
from pipeline.errors import InputError

POINT_SCHEMA = pa.schema(
    [
        ("point_index", pa.uint64()),
        ("tree_id", pa.int64()),
        ("is_ground", pa.bool_()),
        ("is_wood", pa.bool_()),
        ("wood_score", pa.float32()),
    ]
)

_WKB_POINT = np.dtype([("order", "u1"), ("kind", "<u4"), ("x", "<f8"), ("y", "<f8")])  # packed: 21 bytes


def wkb_points(x: np.ndarray, y: np.ndarray) -> pa.Array:
    """WKB (little-endian, ISO) 2D points as an Arrow binary array.

    Parameters
    ----------
    x, y : (k,) float64 [m]
    """
    k = len(x)
    rec = np.empty(k, dtype=_WKB_POINT)
    rec["order"] = 1
    rec["kind"] = 1
    rec["x"] = x
    rec["y"] = y
    offsets = (np.arange(k + 1, dtype=np.int32) * _WKB_POINT.itemsize).astype(np.int32)
    return pa.BinaryArray.from_buffers(
        pa.binary(), k, [None, pa.py_buffer(offsets.tobytes()), pa.py_buffer(rec.tobytes())]
    )


def wkb_linestrings(lines: list[np.ndarray]) -> pa.Array:
    """WKB (little-endian, ISO) 2D line strings as an Arrow binary array.

    Parameters
    ----------
    lines : list of (m, 2) float64
        Each line's vertices [m]; a line of one vertex is stored with it twice (WKB
        line strings have at least two points).
    """
    blobs = []
    for line in lines:
        v = np.asarray(line, dtype="<f8").reshape(-1, 2)
        if len(v) == 1:
            v = np.r_[v, v]
        blobs.append(struct.pack("<BII", 1, 2, len(v)) + v.tobytes())
    return pa.array(blobs, type=pa.binary())


def geo_metadata(crs_wkt: str | None, bbox: list[float] | None, geometry_type: str = "Point") -> dict:
    """GeoParquet 1.1 ``geo`` metadata for a WKB column named ``geometry``."""
    column = {"encoding": "WKB", "geometry_types": [geometry_type], "crs": _projjson(crs_wkt) if crs_wkt else None}
    if bbox is not None:
        column["bbox"] = bbox
    return {"version": "1.1.0", "primary_column": "geometry", "columns": {"geometry": column}}


@functools.lru_cache(maxsize=8)
def _projjson(crs_wkt: str) -> dict:
    """The PROJJSON of a CRS's WKT, parsed once for the trees, rows and gaps of a job
    (a millisecond each). Read-only: callers serialise it, never change it."""
    import pyproj

    return pyproj.CRS.from_wkt(crs_wkt).to_json_dict()


def write_trees_parquet(path, columns: dict[str, np.ndarray], *, crs_wkt: str | None, metadata: dict | None = None) -> None:
    """Write the per-tree table as GeoParquet (atomic).

    Parameters
    ----------
    path : str or Path
    columns : dict name → (k,) array
        ``metrics.TREE_COLUMNS`` (coordinates in the input CRS); other columns are kept.
    crs_wkt : str or None
        The block's CRS, stored as PROJJSON in the ``geo`` metadata (``null`` = unknown).
    metadata : dict str → str, optional
        More key-value metadata (e.g. ``orchard:failed_tiles`` of a partial result).
    """
    x = np.asarray(columns["trunk_x"], dtype=np.float64)
    y = np.asarray(columns["trunk_y"], dtype=np.float64)
    bbox = [float(x.min()), float(y.min()), float(x.max()), float(y.max())] if len(x) else None
    _write_geoparquet(path, columns, wkb_points(x, y), "Point", bbox, crs_wkt=crs_wkt, metadata=metadata)


def write_rows_parquet(path, columns: dict[str, np.ndarray], lines: list[np.ndarray], *, crs_wkt: str | None) -> None:
    """Write the per-row table as GeoParquet (atomic): one row per orchard row, its
    line through its trees (WKB line string) as ``geometry``.

    Parameters
    ----------
    columns : dict name → (r,) array
        ``row``, ``n_trees``, ``n_gaps``, ``spacing_m``, ``length_m``, ``azimuth_deg``.
    lines : list of (m, 2) float64
        Each row's line [m], input CRS.
    """
    v = np.concatenate([np.asarray(line).reshape(-1, 2) for line in lines]) if lines else np.zeros((0, 2))
    bbox = [float(v[:, 0].min()), float(v[:, 1].min()), float(v[:, 0].max()), float(v[:, 1].max())] if len(v) else None
    _write_geoparquet(path, columns, wkb_linestrings(lines), "LineString", bbox, crs_wkt=crs_wkt)


def write_gaps_parquet(path, columns: dict[str, np.ndarray], *, crs_wkt: str | None) -> None:
    """Write the empty planting slots as GeoParquet (atomic): ``row``, ``position``,
    ``x``, ``y`` (input CRS) and the slot's point as ``geometry``."""
    x = np.asarray(columns["x"], dtype=np.float64)
    y = np.asarray(columns["y"], dtype=np.float64)
    bbox = [float(x.min()), float(y.min()), float(x.max()), float(y.max())] if len(x) else None
    _write_geoparquet(path, columns, wkb_points(x, y), "Point", bbox, crs_wkt=crs_wkt)


def _write_geoparquet(path, columns: dict, geometry: pa.Array, geometry_type: str, bbox, *, crs_wkt, metadata=None) -> None:
    dst = Path(str(path))
    arrays = {name: _arrow(values) for name, values in columns.items()}
    arrays["geometry"] = geometry
    table = pa.table(arrays)
    meta = dict(table.schema.metadata or {})
    meta[b"geo"] = json.dumps(geo_metadata(crs_wkt, bbox, geometry_type)).encode()
    meta.update({str(k).encode(): str(v).encode() for k, v in (metadata or {}).items()})
    table = table.replace_schema_metadata(meta)
    tmp = temp_name(dst)
    try:
        pq.write_table(table, str(tmp))
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _arrow(values) -> pa.Array:
    """A column as Arrow: a masked array's masked entries (and an object array's Nones) are nulls."""
    if isinstance(values, np.ma.MaskedArray):
        return pa.array(values.data, mask=np.ma.getmaskarray(values))
    return pa.array(np.asarray(values))


def write_table_parquet(path, columns: dict, *, metadata: dict | None = None) -> None:
    """Write a plain (non-geographic) table as Parquet (atomic); masked entries are nulls."""
    dst = Path(str(path))
    table = pa.table({name: _arrow(values) for name, values in columns.items()})
    if metadata:
        table = table.replace_schema_metadata({str(k).encode(): str(v).encode() for k, v in metadata.items()})
    tmp = temp_name(dst)
    try:
        pq.write_table(table, str(tmp))
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class PointsParquetWriter(AtomicWriter):
    """Streaming writer of ``points.parquet`` (atomic: temp name, renamed on close).

    Each :meth:`write` call appends one or more row groups.
    """

    def __init__(self, path, *, metadata: dict[str, str] | None = None, row_group_size: int = 1_000_000):
        self.path = Path(str(path))
        self._tmp = temp_name(self.path)
        schema = POINT_SCHEMA
        if metadata:
            schema = schema.with_metadata({k.encode(): v.encode() for k, v in metadata.items()})
        # point_index counts up: delta encoding stores it in a few bits per row, where a
        # dictionary of unique values is a wasted attempt
        self._writer = pq.ParquetWriter(
            str(self._tmp),
            schema,
            use_dictionary=["tree_id"],
            column_encoding={"point_index": "DELTA_BINARY_PACKED"},
        )
        self._row_group_size = int(row_group_size)
        self.n_rows = 0
        self._closed = False

    def write(self, point_index, tree_id, is_ground, is_wood, wood_score) -> None:
        """Append rows; all arrays (m,)."""
        table = pa.table(
            [
                pa.array(np.asarray(point_index, dtype=np.uint64)),
                pa.array(np.asarray(tree_id, dtype=np.int64)),
                pa.array(np.asarray(is_ground, dtype=np.bool_)),
                pa.array(np.asarray(is_wood, dtype=np.bool_)),
                pa.array(np.asarray(wood_score, dtype=np.float32)),
            ],
            schema=POINT_SCHEMA,
        )
        self._writer.write_table(table, row_group_size=self._row_group_size)
        self.n_rows += table.num_rows


class TruthParquetWriter(AtomicWriter):
    """Streamed per-point truth of a generated block (the simulator's ``truth.parquet``).

    Columns ``point_index`` (uint64), ``tree_id`` (int64), ``is_wood`` (bool), ``kind``
    (uint8); ``metadata`` goes into the file's key-value metadata. Atomic like the other
    writers.
    """

    def __init__(self, path, *, metadata: dict[str, str]):
        self.path = Path(path)
        self._tmp = temp_name(self.path)
        self._schema = pa.schema(
            [("point_index", pa.uint64()), ("tree_id", pa.int64()), ("is_wood", pa.bool_()), ("kind", pa.uint8())],
            metadata=metadata,
        )
        self._writer = pq.ParquetWriter(
            str(self._tmp),
            self._schema,
            compression="zstd",
            use_dictionary=["tree_id", "is_wood", "kind"],
            column_encoding={"point_index": "DELTA_BINARY_PACKED"},
        )
        self._closed = False

    def write(self, point_index, tree_id, is_wood, kind) -> None:
        self._writer.write_table(
            pa.table(
                {
                    "point_index": np.asarray(point_index, dtype=np.uint64),
                    "tree_id": np.asarray(tree_id, dtype=np.int64),
                    "is_wood": np.asarray(is_wood, dtype=bool),
                    "kind": np.asarray(kind, dtype=np.uint8),
                },
                schema=self._schema,
            )
        )


def read_table(path, columns: list[str] | None = None) -> pa.Table:
    """One Parquet file as a table (``columns``: those only), as ``pq.read_table`` reads it.

    ``pq.read_table`` goes through ``pyarrow.dataset``, whose import (with
    ``pyarrow.compute``) costs a small run 0.06-0.1 s of CPU; one file needs neither.
    """
    with pq.ParquetFile(str(path)) as f:
        return f.read(columns=columns)


def read_parquet_columns(path, columns: list[str] | None = None, *, what: str = "Parquet file") -> tuple[dict[str, np.ndarray], dict]:
    """Columns of a Parquet file as numpy arrays, and its key-value metadata (bytes keys).

    Raises
    ------
    InputError
        The file does not exist or is not readable as Parquet (``what`` names it).
    """
    if os.path.exists(path) and not os.path.isfile(path):
        raise InputError(f"{what} {path} is not a regular file (a folder, device or pipe)")
    try:
        table = read_table(path, columns)
    except FileNotFoundError:
        raise InputError(f"{what} {path} does not exist") from None
    except Exception as exc:  # noqa: BLE001 - any unreadable file is bad input
        raise InputError(f"{what} {path} is not readable as Parquet ({one_line(exc)})") from None
    return {c: table.column(c).to_numpy() for c in table.column_names}, dict(table.schema.metadata or {})


def read_trees_parquet(path) -> tuple[dict[str, np.ndarray], dict]:
    """Read ``trees.parquet``: columns (without geometry) and the parsed ``geo`` metadata."""
    table = read_table(path)
    meta = json.loads((table.schema.metadata or {}).get(b"geo", b"null"))
    cols = {n: table.column(n).to_numpy() for n in table.column_names if n != "geometry"}
    return cols, meta


def sampled_tree_ids(points_parquet, index: np.ndarray, stride: int) -> np.ndarray:
    """The ``tree_id`` of ``points.parquet`` at the point indices ``index`` (multiples of
    ``stride``), 0 where the file has no such row (a tile left out of a partial result).

    Parameters
    ----------
    points_parquet : path of a ``points.parquet``
    index : (m,) int64, sorted — point indices in the block's file
    stride : int — every index in ``index`` is a multiple of it (rows between are skipped)

    Returns
    -------
    (m,) int64
    """
    pidx_parts, tid_parts = [], []
    pf = pq.ParquetFile(str(points_parquet))
    for batch in pf.iter_batches(columns=["point_index", "tree_id"], batch_size=1_000_000):
        p = batch.column(0).to_numpy().astype(np.int64)
        keep = p % stride == 0
        pidx_parts.append(p[keep])
        tid_parts.append(batch.column(1).to_numpy()[keep].astype(np.int64))
    pidx = np.concatenate(pidx_parts) if pidx_parts else np.zeros(0, np.int64)
    tids = np.concatenate(tid_parts) if tid_parts else np.zeros(0, np.int64)
    order = np.argsort(pidx, kind="stable")
    pidx, tids = pidx[order], tids[order]
    pos = np.clip(np.searchsorted(pidx, index), 0, max(len(pidx) - 1, 0))
    tree_id = np.zeros(len(index), np.int64)
    if len(pidx):
        hit = pidx[pos] == index
        tree_id[hit] = tids[pos[hit]]
    return tree_id
