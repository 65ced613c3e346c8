"""Voxelisation: points → voxel nodes (centroids), with index maps both ways."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.passes import CACHE_POINTS


@dataclass(frozen=True)
class Voxels:
    """Occupied voxels of a point set.

    Attributes
    ----------
    point_voxel : (n,) int64
        Voxel of each input point (index into the arrays below).
    keys : (m, 3) int64
        Integer voxel coordinates, ``floor((xyz - grid_origin) / voxel_size)``.
    centroids : (m, 3) float64
        Mean position of the points in each voxel [m] (the graph nodes).
    counts : (m,) int64
        Points per voxel.
    """

    point_voxel: np.ndarray
    keys: np.ndarray
    centroids: np.ndarray
    counts: np.ndarray

    @property
    def n(self) -> int:
        return int(self.counts.shape[0])


def column_min(a: np.ndarray) -> np.ndarray:
    """``a.min(axis=0)`` of an (n, d) array, shape (d,) (numpy's reduction across the rows
    of a narrow array is many times slower, and so is one down a strided column that
    does not fit in the CPU's cache: CACHE_POINTS rows at a time)."""
    return _column_reduce(a, np.min)


def column_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=0)`` of an (n, d) array, like :func:`column_min`."""
    return _column_reduce(a, np.max)


def _column_reduce(a: np.ndarray, reduce) -> np.ndarray:
    parts = [[reduce(a[s : s + CACHE_POINTS, d]) for d in range(a.shape[1])]
             for s in range(0, max(a.shape[0], 1), CACHE_POINTS)]  # an empty array raises as numpy's does
    return reduce(np.array(parts, dtype=a.dtype), axis=0)


def cell_index(v: np.ndarray, origin: float, cell: float) -> np.ndarray:
    """``floor((v - origin) / cell)`` of one coordinate column ``v`` (n,) as int64, a
    cache-sized pass at a time: one float temporary in cache, not one of every point
    (whose fresh pages the kernel must zero), and no (n, 2) or (n, 3) arrays."""
    n = v.shape[0]
    out = np.empty(n, np.int64)
    t = np.empty(min(n, CACHE_POINTS), np.result_type(v, origin))  # the dtype np.subtract(v, origin) gives
    for a in range(0, n, CACHE_POINTS):
        tb = t[: min(n, a + CACHE_POINTS) - a]
        np.subtract(v[a : a + CACHE_POINTS], origin, out=tb)
        np.divide(tb, cell, out=tb)
        np.floor(tb, out=tb)
        out[a : a + tb.shape[0]] = tb
    return out


def keyed_cells(i: np.ndarray, j: np.ndarray, *, counts: bool = False):
    """The distinct cells of columns ``i`` and ``j`` (c,) int64 (c > 0), sorted by i then
    j (``np.unique(np.c_[i, j], axis=0)``), with how many times each occurs if ``counts``.

    One int64 key a cell, marked or counted where the keys are dense, else a sort of int64
    keys: several times faster than a sort of rows viewed as bytes.

    Returns
    -------
    (u, 2) int64, or ((u, 2) int64, (u,) int64) with ``counts``
    """
    lo = np.array([i.min(), j.min()])
    span = np.array([i.max(), j.max()]) - lo + 1
    if int(span[0]) * int(span[1]) >= 2**62:  # the key would overflow: far-apart cells
        return np.unique(np.column_stack([i, j]), axis=0, return_counts=counts)
    # x-major key: its order is the rows' lexicographic order
    key = (i - lo[0]) * span[1] + (j - lo[1])
    n_keys = int(span[0]) * int(span[1])
    tally = None
    if n_keys <= 8 * i.shape[0]:  # a dense grid: no sort
        if counts:
            tally = np.bincount(key, minlength=n_keys)
            key = np.flatnonzero(tally)
            tally = tally[key]
        else:
            occupied = np.zeros(n_keys, bool)
            occupied[key] = True
            key = np.flatnonzero(occupied)
    elif counts:
        key, tally = np.unique(key, return_counts=True)
    else:
        key = np.unique(key)
    cells = np.column_stack([key // span[1] + lo[0], key % span[1] + lo[1]])
    return (cells, tally) if counts else cells


def rows_by_column(xyz: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``xyz[rows]`` of an (n, 3) array, in column-major order: its readers take it a
    column at a time, and numpy's passes down contiguous columns are several times
    faster than down the strided ones of a row-major copy (the same values).
    ``rows``: indices in ``[0, n)``, not checked."""
    # whole rows gathered, then transposed: a gather down each strided column reads a
    # cache line for every value (twice the time on 0.9 M rows of a mobile block's crowns);
    # a cache-sized pass of rows at a time, not a row-major copy of them all first
    n = rows.shape[0]
    out = np.empty((n,) + xyz.shape[1:], xyz.dtype, order="F")
    buf = np.empty((min(n, CACHE_POINTS),) + xyz.shape[1:], xyz.dtype)
    for a in range(0, n, CACHE_POINTS):
        b = min(n, a + CACHE_POINTS)
        np.take(xyz, rows[a:b], axis=0, mode="clip", out=buf[: b - a])
        out[a:b] = buf[: b - a]
    return out


def voxelize(
    xyz: np.ndarray,
    *,
    voxel_size: float,
    grid_origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Voxels:
    """Group points into cubic voxels of side ``voxel_size`` [m].

    Parameters
    ----------
    xyz : (n, 3) float64 [m]
    voxel_size : float [m]
    grid_origin : (3,) float
        Voxel (0, 0, 0) has its corner here; tiles of one block share it.

    Returns
    -------
    Voxels, whose voxels are ordered by key (x, then y, then z).
    """
    # Strategy: pack the three integer keys into one int64 and let np.unique group them.
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[0] == 0:
        return Voxels(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3)), np.zeros(0, np.int64))
    packed, lo, span = packed_keys(xyz, voxel_size, grid_origin)
    uniq, inverse, counts = _group_keys(packed, int(span[0]) * int(span[1]) * int(span[2]))
    m = uniq.shape[0]
    cent = np.empty((m, 3))
    for d in range(3):
        cent[:, d] = np.bincount(inverse, weights=xyz[:, d], minlength=m) / counts
    uk = np.empty((m, 3), np.int64)
    uk[:, 2] = uniq % span[2]
    rest = uniq // span[2]
    uk[:, 1] = rest % span[1]
    uk[:, 0] = rest // span[1]
    return Voxels(inverse.astype(np.int64, copy=False), uk + lo, cent, counts.astype(np.int64, copy=False))


def packed_keys(xyz: np.ndarray, voxel_size: float, grid_origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point's voxel as one int64, ``(x * ny + y) * nz + z`` of its integer key
    relative to the lowest key ``lo`` (3,), in a grid of ``span`` (3,) voxels: (packed
    (n,), lo, span). ValueError when the grid has 2**62 voxels or more."""
    # every step from a coordinate to its key is monotonic, so the lowest and highest
    # keys are those of the lowest and highest coordinates; the keys themselves are then
    # packed CACHE_POINTS points at a time, whose temporaries stay in the CPU's cache
    # (0.6 of the time of whole columns, and no temporary of every point)
    origin = np.array([float(grid_origin[d]) for d in range(3)])
    ends = np.floor((np.stack([column_min(xyz), column_max(xyz)]) - origin) / voxel_size).astype(np.int64)
    lo = ends[0]
    span = ends[1] - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) >= 2**62:
        raise ValueError("block extent too large for the voxel size; tile it")
    n = xyz.shape[0]
    packed = np.empty(n, np.int64)
    buf = np.empty(min(n, CACHE_POINTS))
    key = np.empty(buf.shape[0], np.int64)
    for a in range(0, n, CACHE_POINTS):
        b = min(n, a + CACHE_POINTS)
        out, f, k = packed[a:b], buf[: b - a], key[: b - a]
        for d in range(3):
            np.subtract(xyz[a:b, d], origin[d], out=f)
            np.divide(f, voxel_size, out=f)
            np.floor(f, out=f)
            np.copyto(k, f, casting="unsafe")  # as astype(np.int64)
            k -= lo[d]
            if d == 0:
                out[...] = k
            else:
                out *= span[d]
                out += k
    return packed, lo, span


#: voxelize counts keys in a dense array (no sort) when the grid has at most this many
#: cells per point: its transient memory (12 bytes a cell) stays near the sort's
DENSE_CELLS_PER_POINT = 4


def _group_keys(packed: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(packed, return_inverse=True, return_counts=True)`` of keys in
    ``[0, n_keys)``: sorted distinct keys, index of each key among them (int64), counts."""
    if n_keys > DENSE_CELLS_PER_POINT * packed.shape[0] or packed.shape[0] >= 2**31:
        uniq, inverse, counts = np.unique(packed, return_inverse=True, return_counts=True)
        return uniq, inverse.reshape(-1), counts
    # a dense grid: count each cell and rank the occupied ones, where a sort costs ten times more
    counts = np.bincount(packed, minlength=n_keys)
    uniq = np.flatnonzero(counts > 0)  # numpy finds the set elements of a bool array twice as fast
    rank = np.empty(n_keys, np.int32)
    rank[uniq] = np.arange(uniq.shape[0], dtype=np.int32)
    n = packed.shape[0]
    inverse = np.empty(n, np.int64)
    for a in range(0, n, CACHE_POINTS):  # gathered straight into int64, with no int32 copy of every point
        inverse[a : a + CACHE_POINTS] = rank[packed[a : a + CACHE_POINTS]]
    return uniq, inverse, counts[uniq]
