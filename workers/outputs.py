"""A job's outputs: the merged trees, their rows, and the files written as one set.

The per-tile summaries are reconciled into one set of trunks, the trees table and the
row layout are computed on the whole block (so tiled and untiled runs agree), and the
per-point labels are streamed window by window from the tiles' core results.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.blockinfo import BlockInfo
from pipeline.canopy import cell_centres, unique_cells
from pipeline.coverage import stems_of
from pipeline.errors import NoTreesError, ParameterError
from pipeline.laswriting import write_labelled_las
from pipeline.merge import GlobalTrunks, TileTrunks, reconcile_trunks
from pipeline.metrics import combine_partials, finalize_metrics
from pipeline.params import PipelineParams, RowParams
from pipeline.parquet import (
    PointsParquetWriter,
    write_gaps_parquet,
    write_rows_parquet,
    write_table_parquet,
    write_trees_parquet,
)
from pipeline.rows import RowLayout, find_rows
from workers.jobspec import OUTPUT_NAMES
from workers.captures import Capture
from workers.seasons import SeasonOutputs, nullable, season

#: Points per output window when streaming labels (bounded memory).
WINDOW_POINTS = 2_000_000


class Labels:
    """Per-point labels of the block assembled from per-tile core results (bounded memory).

    A part's arrays are in memory (a block processed whole) or
    :class:`workers.workstore.StoredArray` (a tile's stored results): each window reads
    only the rows of each part that fall in it, found from every :data:`FENCE`-th index
    value kept per part, so the process never holds more than a window of any part.
    """

    FIELDS = ("tree_id", "is_ground", "is_wood", "wood_score")

    def __init__(self, parts: list[dict], n_points: int):
        self.parts = parts  # each: index (sorted), tree_id (local or global), is_ground, is_wood, wood_score, map
        self.n_points = n_points
        self._fences = [_fence(p["index"]) for p in parts]

    @classmethod
    def single(cls, result, id_map: np.ndarray) -> Labels:
        """The labels of a block processed in one piece (``result`` of every point)."""
        n = len(result.tree_id)
        part = {
            "index": np.arange(n, dtype=np.uint64),
            "tree_id": id_map[result.tree_id],
            "is_ground": result.is_ground,
            "is_wood": result.is_wood,
            "wood_score": result.wood_score,
            "map": None,
        }
        return cls([part], n)

    def window(self, a: int, b: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Labels of points a..b-1: (filled mask, dict of arrays; read-only: they may be
        views of a part's arrays)."""
        whole = self._whole(a, b)
        if whole is not None:
            return np.ones(b - a, bool), whole
        m = b - a
        out = {
            "tree_id": np.zeros(m, np.int64),
            "is_ground": np.zeros(m, bool),
            "is_wood": np.zeros(m, bool),
            "wood_score": np.zeros(m, np.float32),
        }
        filled = np.zeros(m, bool)
        for p, fence in zip(self.parts, self._fences):
            # rows before fence[s - 1]'s hold indices below a; rows from fence[t]'s on, b or more
            s, t = np.searchsorted(fence, np.array([a, b], dtype=np.uint64))
            r0, r1 = max(int(s) - 1, 0) * FENCE, min(int(t) * FENCE, len(p["index"]))
            if r1 <= r0:
                continue
            idx = _rows(p["index"], r0, r1)
            lo, hi = np.searchsorted(idx, np.array([a, b], dtype=np.uint64))
            if hi <= lo:
                continue
            if int(idx[hi - 1]) - int(idx[lo]) == hi - lo - 1:  # consecutive points (a whole block): copies, no scatter
                pos = slice(int(idx[lo]) - a, int(idx[hi - 1]) - a + 1)
            else:
                pos = (idx[lo:hi] - np.uint64(a)).astype(np.int64)
            lo, hi = r0 + int(lo), r0 + int(hi)
            tree = _rows(p["tree_id"], lo, hi)
            out["tree_id"][pos] = tree if p.get("map") is None else p["map"][tree]
            for f in ("is_ground", "is_wood", "wood_score"):
                out[f][pos] = _rows(p[f], lo, hi)
            filled[pos] = True
        not_tree = out["tree_id"] == 0  # e.g. of a tree a failed tile owned, in a partial result
        out["is_wood"][not_tree] = False
        out["wood_score"][not_tree] = 0.0
        return filled, out

    def _whole(self, a: int, b: int) -> dict[str, np.ndarray] | None:
        """The window a..b-1 of a block processed in one piece (one part in memory whose
        rows a..b-1 are points a..b-1): its arrays' rows as they are, copied only where a
        point of no tree has wood to clear; None for any other window."""
        if len(self.parts) != 1:
            return None
        p = self.parts[0]
        index = p["index"]
        if not (isinstance(index, np.ndarray) and len(index) >= b > a and int(index[a]) == a and int(index[b - 1]) == b - 1):
            return None  # the indices are sorted and distinct: a..b-1 at rows a..b-1 means all of them
        types = {"tree_id": np.int64, "is_ground": np.bool_, "is_wood": np.bool_, "wood_score": np.float32}
        if not all(isinstance(p[f], np.ndarray) and p[f].dtype == t for f, t in types.items()):
            return None
        tree = p["tree_id"][a:b] if p.get("map") is None else p["map"][p["tree_id"][a:b]]
        if tree.dtype != np.int64:
            return None
        not_tree = tree == 0  # e.g. of a tree a failed tile owned, in a partial result
        is_wood, score = p["is_wood"][a:b], p["wood_score"][a:b]
        if np.any(is_wood & not_tree):
            is_wood = is_wood & ~not_tree
        if np.any(score.view(np.int32)[not_tree]):  # any bits set, -0.0 included: window() writes 0.0
            score = np.where(not_tree, np.float32(0.0), score)
        return {"tree_id": tree, "is_ground": p["is_ground"][a:b], "is_wood": is_wood, "wood_score": score}


#: Rows of a part between two index values :class:`Labels` keeps to find a window's rows.
FENCE = 4096
#: Rows read at a time while taking a stored part's fence.
_FENCE_READ = 256 * FENCE


def _rows(values, lo: int, hi: int) -> np.ndarray:
    """Rows lo..hi-1 of an array in memory or a :class:`workers.workstore.StoredArray`."""
    return values[lo:hi] if isinstance(values, np.ndarray) else values.rows(lo, hi)


def _fence(index) -> np.ndarray:
    """Every :data:`FENCE`-th value of a sorted index (streamed from a stored one)."""
    if isinstance(index, np.ndarray):
        return np.ascontiguousarray(index[::FENCE], dtype=np.uint64)
    parts = [index.rows(lo, lo + _FENCE_READ)[::FENCE] for lo in range(0, len(index), _FENCE_READ)]
    return np.concatenate(parts).astype(np.uint64) if parts else np.zeros(0, np.uint64)


def trees_table(summaries: list[dict], merged: GlobalTrunks, origin) -> dict:
    """The per-tree table (column → array) of the merged trees, in the input CRS."""
    parts = [s["partials"] for s in summaries]
    maps = [merged.id_maps[s["tile_id"]] for s in summaries]
    partials = combine_partials(parts, maps)
    cols = finalize_metrics(partials, merged.trunks, merged.diameter)
    org = np.asarray(origin, dtype=np.float64)
    cols["trunk_x"] = cols["trunk_x"] + org[0]
    cols["trunk_y"] = cols["trunk_y"] + org[1]
    cols["trunk_z"] = cols["trunk_z"] + org[2]
    return cols


def block_canopy(summaries: list[dict]) -> np.ndarray:
    """(c, 2) float64 centres of the canopy cells of every tile's core, in the input CRS [m]."""
    cells = [s["canopy"] for s in summaries if s.get("canopy") is not None]
    if not cells:
        return np.zeros((0, 2))
    return cell_centres(unique_cells(np.concatenate(cells)))


def without_trunks_between_rows(merged: GlobalTrunks, params: PipelineParams, canopy: np.ndarray | None = None,
                                own_stem: np.ndarray | None = None) -> GlobalTrunks:
    """The merged trunks less those that stand between two rows (the row model as a
    prior: off both row lines is foliage or a weed touching down, not a tree); the
    material of each goes to the nearest remaining tree within the crown radius.
    Decided on the whole block's trunks (and ``canopy``, cell centres in the trunks'
    frame), so tiled and untiled runs agree. ``own_stem`` (K,) bool: trunks with a stem
    of their own (:func:`own_stems`), never dropped: foliage or a weed has no bole, and
    in a closed stand the rows found are loose."""
    if not (params.rows.enabled and params.rows.drop_between_rows) or merged.n_trees < 3:
        return merged
    xy = merged.trunks[:, :2]
    drop = find_rows(xy, params=params.rows, canopy=canopy).between_rows
    if own_stem is not None:
        drop = drop & ~np.asarray(own_stem, bool)
    if not drop.any() or drop.all():
        return merged
    keep = ~drop
    new_id = np.zeros(merged.n_trees + 1, dtype=np.int64)
    new_id[1:][keep] = np.arange(1, int(keep.sum()) + 1)
    dist, nearest = cKDTree(xy[keep]).query(xy[drop])
    new_id[1:][drop] = np.where(dist <= params.segment.max_crown_radius, nearest + 1, 0)
    return GlobalTrunks(
        merged.trunks[keep], merged.diameter[keep], merged.support[keep], merged.owner[keep],
        {t: new_id[m] for t, m in merged.id_maps.items()},
    )


def _owned_flags(summaries: list[dict], merged: GlobalTrunks, key: str) -> np.ndarray:
    """(K,) bool: the per-trunk flag ``key`` of each tile's summary, as the tile owning
    each merged trunk set it (a summary without it: False)."""
    out = np.zeros(merged.n_trees, dtype=bool)
    for s in summaries:
        flags = s.get(key)
        if flags is None or not np.any(flags):
            continue
        glob = merged.id_maps[s["tile_id"]][1:]
        local = np.flatnonzero(np.asarray(flags, bool) & (glob > 0))
        g = glob[local] - 1
        out[g[merged.owner[g] == s["tile_id"]]] = True
    return out


def replanted(summaries: list[dict], merged: GlobalTrunks) -> np.ndarray:
    """(K,) bool: trees that the tile owning their trunk let in as replants."""
    return _owned_flags(summaries, merged, "young")


def own_stems(summaries: list[dict], merged: GlobalTrunks) -> np.ndarray:
    """(K,) bool: trunks that the tile owning them found with a stem of their own
    (:class:`pipeline.trunks.TrunkDetection`; a work store of an earlier release: none)."""
    return _owned_flags(summaries, merged, "own_stem")


def with_rows(trees: dict, params: RowParams, replants: np.ndarray | None = None,
              canopy: np.ndarray | None = None) -> tuple[dict, RowLayout | None]:
    """The trees table with each tree's address (``row``, ``position``, ``young``), and
    the block's rows (with those only the ``canopy`` shows: cell centres, input CRS);
    computed on the merged trees, so tiled and untiled runs agree. A tree is young when
    it is much lower than its row neighbours or was let in as a replant."""
    if not params.enabled:
        return trees, None
    layout = find_rows(np.c_[trees["trunk_x"], trees["trunk_y"]], trees["height_m"], params=params, canopy=canopy)
    young = layout.young if replants is None else layout.young | replants
    return dict(trees, row=layout.row, position=layout.position, young=young), layout


def in_address_order(merged: GlobalTrunks, trees: dict) -> tuple[GlobalTrunks, dict]:
    """The merged trunks and the trees table renumbered so that ``tree_id`` runs in
    address order (row, then position; the trees off the rows are rows numbered after
    the rows, so they come last): growers name trees by address, and neighbouring ids
    then stand side by side in a row. Without rows the (x, y) order stays."""
    if "row" not in trees or merged.n_trees == 0:
        return merged, trees
    order = np.lexsort((np.asarray(trees["position"]), np.asarray(trees["row"])))
    if np.array_equal(order, np.arange(len(order))):
        return merged, trees
    new_id = np.zeros(merged.n_trees + 1, dtype=np.int64)
    new_id[1:][order] = np.arange(1, merged.n_trees + 1)
    renumbered = {k: (np.asarray(v)[order] if k != "tree_id" else np.asarray(v)) for k, v in trees.items()}
    return GlobalTrunks(
        merged.trunks[order], merged.diameter[order], merged.support[order], merged.owner[order],
        {t: new_id[m] for t, m in merged.id_maps.items()},
    ), renumbered


def no_trees(info: BlockInfo) -> NoTreesError:
    return NoTreesError(
        f"{Path(info.path).name}: no trees found in {info.n_points} points (only ground or clutter: posts, stakes, boxes?); ",
        hint="check the block, or lower {trunks.min_tree_height} / {trunks.min_canopy_voxels}",
    )


def _tile_trunks(summary: dict) -> TileTrunks:
    return TileTrunks(summary["tile_id"], summary["trunks"], summary["support"], summary["diameter"], summary["owned"])


def merge_and_write(
    summaries: list[dict],
    info: BlockInfo,
    params: PipelineParams,
    out_dir: Path,
    *,
    labels: Callable[[GlobalTrunks], Labels],
    labelled_laz: bool,
    failed: list[int],
    dead_zones: np.ndarray | None = None,
    capture: Capture | None = None,
    timings: dict | None = None,
) -> tuple[int, dict, dict]:
    """Merge the tiles' summaries into trees and write the job's outputs.

    Parameters
    ----------
    summaries : list of dict
        Per-tile summaries (:func:`workers.tasks.summarise`) in tile-id order.
    info : BlockInfo
    params : PipelineParams
    out_dir : Path
    labels : callable
        The per-point labels given the merged trunks (their id maps).
    labelled_laz : bool
    failed : list of int
        Tiles without a result (recorded in the outputs' metadata).
    dead_zones : (f, 4) float64, optional
        Cores of the failed tiles in the block's local frame [m].
    capture : Capture, optional
        The capture the block is (:mod:`workers.seasons`); None: the input's file stem,
        its header's date, no previous capture.
    timings : dict, optional
        Gets ``seasons``: the seconds registration, matching and keys took.

    Returns
    -------
    (number of trees, trees table, output name → path)

    Raises
    ------
    NoTreesError, ParameterError (the outputs cannot be written), NoOverlapError (the
    capture does not overlap its previous capture: nothing is written)
    """
    default_radius = params.trunks.at_spacing(None).cluster_radius
    merged = reconcile_trunks(
        [_tile_trunks(s) for s in summaries],
        # the tiles' own clustering radii (they follow the trees' spacing): the smallest
        cluster_radius=min((s.get("cluster_radius", default_radius) for s in summaries), default=default_radius),
        fallback_radius=params.segment.max_crown_radius,
        dead_zones=dead_zones,
    )
    canopy = block_canopy(summaries) if params.rows.enabled else None
    local_canopy = None if canopy is None else canopy - np.asarray(info.origin[:2], dtype=np.float64)
    merged = without_trunks_between_rows(merged, params, local_canopy, own_stems(summaries, merged))
    if merged.n_trees == 0:
        raise no_trees(info)
    trees, layout = with_rows(trees_table(summaries, merged, info.origin), params.rows, replanted(summaries, merged), canopy)
    merged, trees = in_address_order(merged, trees)  # a first capture's keys follow its addresses
    seasonal = season(trees, layout, block_coverage(summaries), capture or Capture.of(info.path),
                      stems=block_stems(summaries))
    if timings is not None:
        timings["seasons"] = seasonal.seconds
    # ids follow the block's addresses, which a capture may carry over from the previous one
    merged, trees = in_address_order(merged, seasonal.trees)
    outputs = write_outputs(out_dir, info, labels(merged), trees, labelled_laz=labelled_laz, failed=failed,
                            layout=seasonal.layout, seasonal=seasonal)
    return merged.n_trees, trees, outputs


def block_stems(summaries: list[dict]) -> np.ndarray | None:
    """(c, 2) float64 centres of the cells holding stems (:func:`pipeline.coverage.stem_cells`) of every tile's core."""
    cells = [s.get("stems") for s in summaries]
    if not cells or any(c is None for c in cells):
        return None
    return stems_of(cells)


def block_coverage(summaries: list[dict]) -> np.ndarray | None:
    """(c, 2) int64: the 1 m cells the tiles' cores saw (input CRS); None when a tile's
    summary has none (a work store of an earlier release)."""
    cells = [s.get("coverage") for s in summaries]
    if not cells or any(c is None for c in cells):
        return None
    return np.unique(np.concatenate(cells), axis=0)


def write_outputs(out_dir: Path, info: BlockInfo, labels: Labels, trees: dict, *, labelled_laz: bool, failed: list[int],
                  layout: RowLayout | None = None, seasonal: SeasonOutputs | None = None) -> dict:
    """Write the outputs of a job into ``out_dir`` as one set.

    Every file is written into a hidden staging folder first; only when all are complete
    do they replace the folder's outputs, and an output of an earlier run that this run
    does not write (``labelled.laz``) is removed, so ``out_dir`` never mixes two runs.
    A failure leaves ``out_dir`` as it was. ``seasonal``: the capture's history
    (``history.parquet``) and records (trees.parquet's metadata).
    """
    stage = out_dir / f".staging-{uuid.uuid4().hex[:12]}"
    try:
        stage.mkdir(parents=True)
    except OSError as exc:
        raise ParameterError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}") from None
    written: dict[str, Path] = {}
    meta = {"orchard:input": info.path}
    if failed:
        meta["orchard:failed_tiles"] = json.dumps(failed)
    try:
        path = stage / "points.parquet"
        with PointsParquetWriter(path, metadata=meta) as w:
            for a in range(0, labels.n_points, WINDOW_POINTS):
                b = min(labels.n_points, a + WINDOW_POINTS)
                filled, lab = labels.window(a, b)
                idx = np.arange(a, b, dtype=np.uint64)
                if not filled.all():
                    idx = idx[filled]
                    lab = {k: v[filled] for k, v in lab.items()}
                w.write(idx, lab["tree_id"], lab["is_ground"], lab["is_wood"], lab["wood_score"])
        written["points"] = path
        if labelled_laz:
            path = stage / "labelled.laz"
            write_labelled_las(
                info.path,
                path,
                labels=lambda a, b: {k: v for k, v in labels.window(a, b)[1].items() if k != "is_ground"},
            )
            written["labelled"] = path
        path = stage / "trees.parquet"
        write_trees_parquet(path, nullable(trees), crs_wkt=info.crs_wkt,
                            metadata=meta if seasonal is None else {**meta, **seasonal.metadata})
        written["trees"] = path
        if seasonal is not None:
            path = stage / "history.parquet"
            write_table_parquet(path, {k: np.ma.masked_invalid(v) if v.dtype.kind == "f" else v
                                       for k, v in seasonal.history.items()})
            written["history"] = path
        if layout is not None:
            path = stage / "rows.parquet"
            write_rows_parquet(path, layout.rows, layout.lines, crs_wkt=info.crs_wkt)
            written["rows"] = path
            path = stage / "gaps.parquet"
            write_gaps_parquet(path, layout.gaps, crs_wkt=info.crs_wkt)
            written["gaps"] = path
        outputs = {}
        for key, staged in written.items():  # complete: publish (each rename is atomic)
            final = out_dir / staged.name
            os.replace(staged, final)
            outputs[key] = str(final)
        for name in OUTPUT_NAMES:
            if name not in {p.name for p in written.values()}:
                (out_dir / name).unlink(missing_ok=True)  # an earlier run's, not this run's
        return outputs
    except OSError as exc:  # a full disk, a folder that turned read-only: one line, nothing half-written
        raise ParameterError(f"cannot write the outputs to {out_dir}: {exc.strerror or exc}") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
