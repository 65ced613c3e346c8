"""The files of a generated block: the points as LAS/LAZ, the truth as Parquet (contract in
``docs/simulator.md``)."""

from __future__ import annotations

import json
from typing import Iterable

import numpy as np

from simulator.orchard import KIND, Orchard
from simulator.simparams import SimulationParams
from simulator.simulate import iter_simulation

TRUTH_COLUMNS = ("point_index", "tree_id", "is_wood", "kind")


def write_simulation(source: Orchard | SimulationParams | Iterable[Orchard], las_path: str, truth_path: str, *,
                     creation_date=None) -> dict:
    """Write a block as LAS/LAZ (``.laz`` compresses) and its truth as Parquet.

    Parameters
    ----------
    source : Orchard, SimulationParams or iterable of Orchard chunks
        A block in memory, or parameters / chunks to stream (bounded memory).
    las_path, truth_path : str
        Outputs; written to temporary names and renamed, so nothing partial is left.
    creation_date : datetime.date, optional
        The LAS header's creation day (a capture's date; default today).

    Returns
    -------
    dict
        ``n_points``, ``n_trees``, ``crs_epsg``.

    Notes
    -----
    The truth file has one row per point in file order: ``point_index`` (uint64),
    ``tree_id`` (int64, 0 = not a tree), ``is_wood`` (bool), ``kind`` (uint8 code into
    :data:`simulator.orchard.KIND`). Its key-value metadata holds ``orchard:trunks`` (JSON list of absolute
    [x, y, z] trunk bases, tree ``k`` at position ``k-1``), ``orchard:trunk_radius``,
    ``orchard:kinds`` and ``orchard:crs_epsg``; for a generated block also the layout
    (:func:`read_truth_layout`): ``orchard:tree_rows``, ``orchard:tree_slots``,
    ``orchard:tree_young``, ``orchard:empty_slots``, ``orchard:spacing`` and
    ``orchard:row_spacing``.
    """
    from pipeline.laswriting import LasBlockWriter
    from pipeline.parquet import TruthParquetWriter

    if isinstance(source, Orchard):
        chunks: Iterable[Orchard] = [source]
    elif isinstance(source, SimulationParams):
        chunks = iter_simulation(source)
    else:
        chunks = source
    truth = None
    n = 0
    n_trees = 0
    epsg = None
    las = None
    try:
        for ch in chunks:
            if las is None:
                epsg = ch.crs_epsg
                n_trees = len(ch.trunks)
                offsets = tuple(float(np.floor(v)) for v in ch.trunks.min(axis=0)) if n_trees else (0.0, 0.0, 0.0)
                las = LasBlockWriter(las_path, crs_epsg=ch.crs_epsg, offsets=offsets, creation_date=creation_date)
                truth = TruthParquetWriter(
                    truth_path,
                    metadata={
                        "orchard:trunks": json.dumps(np.round(ch.trunks, 6).tolist()),
                        "orchard:trunk_radius": json.dumps(np.round(ch.trunk_radius, 6).tolist()),
                        "orchard:kinds": json.dumps(list(KIND)),
                        "orchard:crs_epsg": str(ch.crs_epsg),
                        **_layout_metadata(ch),
                    },
                )
            m = ch.n_points
            if m == 0:
                continue
            las.write(ch.xyz)
            truth.write(np.arange(n, n + m, dtype=np.uint64), ch.tree_id, ch.is_wood, ch.kind)
            n += m
        if las is None:
            raise ValueError("nothing to write: the simulation produced no chunks")
        if n == 0:  # a file no command reads (`orchard process` refuses it as empty)
            from pipeline.errors import ParameterError

            raise ParameterError("the simulation made no points: its point density is too low", param="simulation.density")
        truth.close()
        las.close()
    except BaseException:
        for w in (truth, las):
            if w is not None:
                w.abort()
        raise
    return {"n_points": n, "n_trees": n_trees, "crs_epsg": epsg}


def read_truth(path: str) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a truth file written by :func:`write_simulation`.

    Returns
    -------
    columns : dict of str to ndarray
        ``point_index`` (n,) uint64, ``tree_id`` (n,) int64, ``is_wood`` (n,) bool,
        ``kind`` (n,) uint8, sorted by point_index; plus ``trunk_radius`` (k,) float64.
    trunks : (k, 3) float64
        Absolute trunk base centres [m]; tree ``k`` is ``trunks[k-1]``.
    """
    from pipeline.errors import InputError
    from pipeline.parquet import read_parquet_columns

    table, meta = read_parquet_columns(path, what="truth file")
    if b"orchard:trunks" not in meta or any(c not in table for c in TRUTH_COLUMNS):
        raise InputError(f"{path} is not an orchard truth file (the per-point truth written beside a simulated block)")
    cols = {c: table[c] for c in TRUTH_COLUMNS}
    if len(cols["point_index"]) and np.any(np.diff(cols["point_index"].astype(np.int64)) < 0):
        order = np.argsort(cols["point_index"], kind="stable")
        cols = {c: v[order] for c, v in cols.items()}
    trunks = np.asarray(json.loads(meta[b"orchard:trunks"]), dtype=np.float64).reshape(-1, 3)
    cols["trunk_radius"] = np.asarray(json.loads(meta.get(b"orchard:trunk_radius", b"[]")), dtype=np.float64)
    return cols, trunks


def _layout_metadata(o: Orchard) -> dict[str, str]:
    """The truth file's layout keys (none for a block without a layout)."""
    out = {}
    if o.tree_row is not None:
        out["orchard:tree_rows"] = json.dumps(np.asarray(o.tree_row, dtype=np.int64).tolist())
    if o.tree_slot is not None:
        out["orchard:tree_slots"] = json.dumps(np.asarray(o.tree_slot, dtype=np.int64).tolist())
    if o.tree_young is not None:
        out["orchard:tree_young"] = json.dumps(np.asarray(o.tree_young, dtype=bool).tolist())
    if o.empty_slots is not None:
        e = np.asarray(o.empty_slots, dtype=np.float64).reshape(-1, 4)
        out["orchard:empty_slots"] = json.dumps([[int(r), int(s), round(float(x), 6), round(float(y), 6)] for r, s, x, y in e])
    if o.spacing is not None:
        out["orchard:spacing"] = json.dumps(float(o.spacing))
    if o.row_spacing is not None:
        out["orchard:row_spacing"] = json.dumps(float(o.row_spacing))
    return out


def read_truth_layout(path: str) -> dict:
    """The planting layout stored in a truth file by :func:`write_simulation`.

    Returns
    -------
    dict
        ``tree_row`` (k,) int64 and ``tree_slot`` (k,) int64 (1-based; tree ``k`` at
        position ``k-1``), ``tree_young`` (k,) bool, ``empty_slots`` (e, 4) float64 rows of
        ``[row, slot, x, y]`` (absolute slot centre [m]), ``spacing`` and ``row_spacing``
        [m]. Keys a file lacks (written before layouts were recorded) are ``None``, and
        ``empty_slots`` is then an empty (0, 4) array.

    Raises
    ------
    InputError
        The file is missing, not Parquet, or not a truth file.
    """
    from pipeline.errors import InputError
    from pipeline.parquet import read_parquet_columns

    _, meta = read_parquet_columns(path, [], what="truth file")
    if b"orchard:trunks" not in meta:
        raise InputError(f"{path} is not an orchard truth file (the per-point truth written beside a simulated block)")

    def get(key, dtype):
        raw = meta.get(key.encode())
        return None if raw is None else np.asarray(json.loads(raw), dtype=dtype)

    empty = get("orchard:empty_slots", np.float64)
    spacing = get("orchard:spacing", np.float64)
    row_spacing = get("orchard:row_spacing", np.float64)
    return {
        "tree_row": get("orchard:tree_rows", np.int64),
        "tree_slot": get("orchard:tree_slots", np.int64),
        "tree_young": get("orchard:tree_young", bool),
        "empty_slots": np.empty((0, 4)) if empty is None else empty.reshape(-1, 4),
        "spacing": None if spacing is None else float(spacing),
        "row_spacing": None if row_spacing is None else float(row_spacing),
    }
