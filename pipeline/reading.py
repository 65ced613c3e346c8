"""Reading the points of a LAS/LAZ block in bounded-memory chunks.

Points are returned in float64 relative to a local origin (``floor`` of the header
minimum), so UTM-sized coordinates lose nothing: ``local = X * scale + (offset - origin)``
where ``X`` is the stored integer, rounded to whole micrometres
(:data:`LOCAL_STEPS_PER_M`), so that a point gets the same float whatever scale and
offset its file stores it with.
"""

from __future__ import annotations

import math
import os
from typing import Iterator

import numpy as np

from pipeline import lasheader
from pipeline.blockinfo import BlockInfo, input_error, one_line, read_info
from pipeline.budget import DensitySample, count_cells
from pipeline.chunks import CHUNK_POINTS
from pipeline.errors import InputError
from pipeline.laspyload import laspy
from pipeline.mapsample import first_sampled
from pipeline.voxels import DENSE_CELLS_PER_POINT, packed_keys

#: decode only X, Y, Z of LAZ points (the other fields' layers are skipped)
_XYZ_ONLY = laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z
#: decode only X and Y (with the returns and channel, stored in the same layer)
_XY_ONLY = laspy.DecompressionSelection.XY_RETURNS_CHANNEL


def iter_raw(path, *, chunk_points: int = CHUNK_POINTS, info: BlockInfo | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Stream the stored integer coordinates of a block in chunks.

    Yields
    ------
    start : int
        Index of the chunk's first point in the file.
    ints : (m, 3) int32
        The stored X, Y, Z; coordinates are ``ints * scales + offsets``.

    Raises
    ------
    InputError
        The point data is truncated or corrupt.
    """
    info = info or read_info(path)
    for start, arr in _records(info, int(chunk_points), _XYZ_ONLY):
        yield start, _stored_xyz(arr)


def _records(info: BlockInfo, chunk_points: int, selection) -> Iterator[tuple[int, np.ndarray]]:
    """Every point record of a block in order, ``chunk_points`` at a time, decoding the
    layers of ``selection``: (index of the chunk's first point, records). Raises
    InputError on corrupt data or fewer points than the header announces."""
    start = 0
    try:
        with laspy.open(info.path, read_evlrs=False, decompression_selection=selection) as reader:
            for chunk in reader.chunk_iterator(chunk_points):
                arr = chunk.array
                m = len(arr)
                if m == 0:
                    break
                yield start, arr
                start += m
    except (InputError, KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # lazrs panics (pyo3's PanicException is no Exception) on corrupt chunks
        raise input_error(info.path, f"corrupt or truncated point data after point {start} ({one_line(exc)})") from None
    if start < info.n_points:
        raise input_error(info.path, f"truncated: the header announces {info.n_points} points but only {start} could be read")


def _stored_xyz(arr) -> np.ndarray:
    ints = np.empty((len(arr), 3), dtype=np.int32)
    ints[:, 0] = arr["X"]
    ints[:, 1] = arr["Y"]
    ints[:, 2] = arr["Z"]
    return ints


def read_raw_range(path, start: int, count: int, *, info: BlockInfo | None = None) -> np.ndarray:
    """The stored integer X, Y, Z of points ``[start, start + count)``, shape (m, 3) int32.

    Seeks in the file (LAZ chunk table), so workers can each read their own range of one
    block in parallel; a file that is not ``info.seekable`` is decoded from its start.

    Raises
    ------
    InputError
        The range lies beyond the points the file holds, or its data is corrupt.
    """
    info = info or read_info(path)
    count = max(0, min(int(count), info.n_points - int(start)))
    try:
        with laspy.open(info.path, read_evlrs=False, decompression_selection=_XYZ_ONLY) as reader:
            if info.seekable:
                reader.seek(int(start))
            else:  # decode and drop the points before the range
                skip = int(start)
                while skip > 0:
                    got = len(reader.read_points(min(skip, 1_000_000)))
                    if got == 0:
                        break
                    skip -= got
            arr = reader.read_points(count).array
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # lazrs panics (pyo3's PanicException is no Exception) on corrupt chunks
        raise input_error(info.path, f"corrupt or truncated point data after point {start} ({one_line(exc)})") from None
    if len(arr) < count:
        raise input_error(info.path, f"truncated: the header announces {info.n_points} points but only {start + len(arr)} could be read")
    return _stored_xyz(arr)


LOCAL_STEPS_PER_M = 1e6
"""Local coordinates are whole multiples of ``1 / LOCAL_STEPS_PER_M`` [m] (1 µm).
``X * scale + (offset - origin)`` alone depends in its last bit on how a file stores a
point, so the same point re-saved with another offset or scale could fall on the other
side of a voxel or ground-cell boundary. Rounding to 1 µm gives one float per point;
no scale in use comes near it."""


#: rows :func:`to_local` converts at a time (a 256 KiB buffer)
TO_LOCAL_BLOCK = 32_768


def to_local(ints, info: BlockInfo, origin=None, *, out: np.ndarray | None = None) -> np.ndarray:
    """Local float64 coordinates (m, 3) [m] of stored integers: ``X * scale + (offset - origin)``
    rounded to whole micrometres (:data:`LOCAL_STEPS_PER_M`; written into ``out``, an (m, 3)
    float64 array, when given). ``ints``: an (m, 3) array, or its three columns (the
    X, Y and Z fields of point records, converted where they lie)."""
    org = np.asarray(info.origin if origin is None else origin, dtype=np.float64)
    scale = np.asarray(info.scales, dtype=np.float64)
    shift = np.asarray(info.offsets, dtype=np.float64) - org
    cols = tuple(ints) if isinstance(ints, (tuple, list)) else (ints[:, 0], ints[:, 1], ints[:, 2])
    n = cols[0].shape[0]
    xyz = np.empty((n, 3), dtype=np.float64) if out is None else out
    # a block of rows at a time in a cache-sized buffer: five passes over a strided column
    # of the whole array cost more memory traffic than the arithmetic
    tmp = np.empty(min(n, TO_LOCAL_BLOCK))
    for s in range(0, n, TO_LOCAL_BLOCK):
        e = min(n, s + TO_LOCAL_BLOCK)
        col = tmp[: e - s]
        for j in range(3):
            np.multiply(cols[j][s:e], scale[j], out=col, casting="unsafe")
            col += shift[j]
            col *= LOCAL_STEPS_PER_M
            np.rint(col, out=col)
            col /= LOCAL_STEPS_PER_M
            xyz[s:e, j] = col
    return xyz


def check_bounds(xyz: np.ndarray, info: BlockInfo, *, start: int = 0, origin=None) -> None:
    """Raise InputError if local points (m, 3) lie more than 1 m outside the header's bounds."""
    org = np.asarray(info.origin if origin is None else origin, dtype=np.float64)
    lo = np.asarray(info.mins) - org - 1.0
    hi = np.asarray(info.maxs) - org + 1.0
    if xyz.shape[0] == 0 or all(xyz[:, d].min() >= lo[d] and xyz[:, d].max() <= hi[d] for d in range(3)):
        return  # the common case, in two passes per column instead of a full mask
    bad = (xyz < lo) | (xyz > hi)
    if bad.any():
        i = int(np.flatnonzero(bad.any(axis=1))[0])
        raise input_error(
            info.path,
            f"point {start + i} lies outside the header's bounds ({(xyz[i] + org).tolist()}); the file is corrupt",
        )


def iter_points(path, *, chunk_points: int = CHUNK_POINTS, origin=None, info: BlockInfo | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """Stream the points of a block in chunks.

    Parameters
    ----------
    path : str or Path
    chunk_points : int
        Points per chunk; memory is bounded by this, not by the file size.
    origin : (3,) float, optional
        Local origin [m]; default ``read_info(path).origin``.
    info : BlockInfo, optional
        Already-read header information (skips a second header check).

    Yields
    ------
    start : int
        Index of the chunk's first point in the file.
    xyz : (m, 3) float64
        Local coordinates [m]: ``X * scale + (offset - origin)``.

    Raises
    ------
    InputError
        The file is broken, the point data is truncated or corrupt, or points lie at
        absurd coordinates (outside the header's bounds).
    """
    info = info or read_info(path)
    for start, ints in iter_raw(path, chunk_points=chunk_points, info=info):
        yield start, _checked_local(ints, info, start, origin)


def _checked_local(ints: np.ndarray, info: BlockInfo, start: int, origin, out: np.ndarray | None = None) -> np.ndarray:
    xyz = to_local(ints, info, origin, out=out)
    check_bounds(xyz, info, start=start, origin=origin)
    return xyz


def sample_xy(path, stride: int, *, info: BlockInfo | None = None,
              chunk_points: int = CHUNK_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th point of a block (those whose index in the file is a multiple
    of ``stride``): their local x, y as :func:`read_points` gives them, and their indices.

    Only X and Y are decoded (LAZ point formats 6-10 store them apart from the other
    fields) and only the sampled points are converted.

    Returns
    -------
    xy : (m, 2) float64 [m], local frame (minus ``info.origin``)
    index : (m,) int64

    Raises
    ------
    InputError
        The point data is truncated or corrupt.
    """
    info = info or read_info(path)
    stride = max(1, int(stride))
    xy_parts, idx_parts = [], []
    for start, arr in _records(info, int(chunk_points), _XY_ONLY):
        first = first_sampled(start, stride)
        picked = arr[first::stride]
        ints = np.zeros((len(picked), 3), dtype=np.int32)  # Z left 0: its column is dropped
        ints[:, 0] = picked["X"]
        ints[:, 1] = picked["Y"]
        xy_parts.append(to_local(ints, info)[:, :2])
        idx_parts.append(np.arange(start + first, start + len(arr), stride, dtype=np.int64))
    if not xy_parts:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    return np.concatenate(xy_parts), np.concatenate(idx_parts)


#: points the LAZ decoder fills per call and core when a whole block is read: a few of
#: LAZ's 50,000-point chunks for each core, their records (30 bytes a point in format 6)
#: still in cache when they are converted
DECODE_POINTS_PER_CORE = 131_072


def decode_points(chunk_points: int) -> int:
    """Points decoded per call when a whole block is read ``chunk_points`` at most at a
    time: :data:`DECODE_POINTS_PER_CORE` per core the process may run on."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, min(int(chunk_points), DECODE_POINTS_PER_CORE * cores))


def read_points(path, *, origin=None, chunk_points: int = CHUNK_POINTS) -> tuple[np.ndarray, BlockInfo]:
    """Read a whole block (decoding at most ``chunk_points``, fewer per core, at a time).

    Returns
    -------
    xyz : (n, 3) float64
        Local coordinates [m] (``xyz + info.origin`` when ``origin`` is None).
    info : BlockInfo
    """
    info = read_info(path)
    out = np.empty((info.n_points, 3), dtype=np.float64)
    for start, arr in _records(info, decode_points(chunk_points), _XYZ_ONLY):
        _checked_local((arr["X"], arr["Y"], arr["Z"]), info, start, origin, out=out[start : start + len(arr)])
    return out, info


#: runs of points :func:`sample_density` reads when it samples, at least: each run is one
#: LAZ chunk (decoded from its start, so nothing is decoded twice), or ``las_run`` points
#: of a LAS file; a file of no more runs is counted whole
SAMPLE_RUNS = 256

#: share of a file's runs :func:`sample_density` reads by default: all of them. A sample
#: needs a margin for its error (:data:`pipeline.budget.SAMPLE_MARGIN`), and on blocks at
#: mobile density the smaller tiles it then chooses cost more work than the full count
#: saves (docs/performance.md)
SAMPLE_FRACTION = 1.0

#: points per run of a LAS file (as LAZ's default chunk)
LAS_RUN_POINTS = 50_000

#: side of a density sample's cells [m]: a buffered tile's count takes every cell its box
#: touches, so a cell this small overcounts a 25 m box by 2 %
SAMPLE_CELL = 0.25

#: most cells along either axis of a density sample: cells of :data:`SAMPLE_CELL` up to
#: 512 m, coarser ones beyond (at most 2048^2 counts, 32 MB)
MAX_SAMPLE_CELLS = 2048


def sample_density(path, *, info: BlockInfo | None = None, voxel_size: float | None = None, runs: int = SAMPLE_RUNS,
                   fraction: float = SAMPLE_FRACTION, las_run: int = LAS_RUN_POINTS,
                   chunk_points: int = CHUNK_POINTS) -> DensitySample:
    """Count the points of a block per square cell: all of them, read in order, or with
    ``fraction`` below 1, from evenly spread runs of its points (``runs`` or the
    ``fraction`` of them, whichever is more). A run is one LAZ chunk, or ``las_run``
    points of a LAS file. Every point is counted when the file holds no more runs than
    ``runs``, when half of them or more would be read, and in a LAZ file that is not
    ``info.seekable`` (a chunk there is reached only by decoding every one before it).

    With a ``voxel_size`` [m] the voxels of that size (a grid from the block origin) the
    points occupy are counted too, per cell of their centre: each run (``chunk_points``
    when every point is counted) counts its own distinct voxels, so a voxel that several
    runs reach counts in each (:attr:`DensitySample.nodes`).

    Cells are :data:`SAMPLE_CELL` wide (whole multiples of it, for a block wider than
    :data:`MAX_SAMPLE_CELLS` cells), their corner at the block origin (``floor`` of the
    header minimum), so whole-metre tile edges from that origin fall on cell edges. Only
    X and Y (and Z, for the voxels) are decoded where the point format stores them apart;
    memory is one run (``chunk_points`` when every point is counted) and the counts.

    A COPC block is counted from its hierarchy, reading no point
    (:func:`pipeline.formats.copc.density_from_nodes`).

    Raises
    ------
    InputError
        The point data is truncated or corrupt.
    """
    info = info or read_info(path)
    if info.copc:  # its hierarchy counts every point by node: nothing is decoded
        from pipeline.formats.copc import density_from_nodes, read_nodes

        cell, shape = _density_grid(info)
        return density_from_nodes(info, read_nodes(info.path), cell=cell, shape=shape, voxel_size=voxel_size)
    cell, counts, nodes = _empty_counts(info, voxel_size)
    selection = _XY_ONLY if voxel_size is None else _XYZ_ONLY
    run, picked = int(chunk_points), None  # None: every point, in order
    if fraction < 1.0 and info.seekable:
        run = int(lasheader.check_header(info.path).chunk_size) if info.compressed else int(las_run)
        n_runs = -(-info.n_points // run)
        n_read = min(max(int(runs), math.ceil(n_runs * fraction)), n_runs)
        if 2 * n_read < n_runs:  # else count it all, exactly, for little more
            picked = np.unique(np.linspace(0, n_runs - 1, n_read).round().astype(np.int64))
    sampled = 0
    records = (arr for _, arr in _records(info, run, selection)) if picked is None else _picked_runs(info, run, picked,
                                                                                                      selection)
    for arr in records:
        _count_run(info, arr["X"], arr["Y"], arr["Z"] if nodes is not None else None, voxel_size, cell, counts, nodes)
        sampled += len(arr)
    return _sample(info, cell, counts, nodes, sampled)


def read_counted(path, *, info: BlockInfo | None = None, voxel_size: float | None = None,
                 chunk_points: int = CHUNK_POINTS) -> tuple[np.ndarray, DensitySample]:
    """:func:`read_points` and :func:`sample_density` counting every point, in one pass
    over the file: the block's local coordinates (``xyz + info.origin``) and the same
    count, cell for cell, as ``sample_density(path, voxel_size=voxel_size,
    chunk_points=chunk_points)``. What a job that counts a block to choose its tiles and
    then keeps it in one piece reads (the file is decoded once, not twice).

    Raises
    ------
    InputError
        The point data is truncated or corrupt, or a point lies outside the header's bounds.
    """
    info = info or read_info(path)
    cell, counts, nodes = _empty_counts(info, voxel_size)
    out = np.empty((info.n_points, 3), dtype=np.float64)
    for start, ints in iter_raw(info.path, chunk_points=chunk_points, info=info):
        _count_run(info, ints[:, 0], ints[:, 1], ints[:, 2] if nodes is not None else None, voxel_size, cell, counts,
                   nodes)
        _checked_local(ints, info, start, None, out=out[start : start + len(ints)])
    return out, _sample(info, cell, counts, nodes, info.n_points)


def _sample(info: BlockInfo, cell: float, counts: np.ndarray, nodes: np.ndarray | None, sampled: int) -> DensitySample:
    return DensitySample(counts=counts, origin=(float(info.origin[0]), float(info.origin[1])),
                         cell=cell, sampled=sampled, n_points=info.n_points, nodes=nodes)


def _density_grid(info: BlockInfo) -> tuple[float, tuple[int, int]]:
    """Cell side [m] and shape (ny, nx) of a block's density sample."""
    extent = max(info.maxs[0] - info.origin[0], info.maxs[1] - info.origin[1])
    cell = SAMPLE_CELL * max(1, math.ceil(extent / MAX_SAMPLE_CELLS / SAMPLE_CELL))
    nx = int(math.floor((info.maxs[0] - info.origin[0]) / cell)) + 1
    ny = int(math.floor((info.maxs[1] - info.origin[1]) / cell)) + 1
    return cell, (ny, nx)


def _empty_counts(info: BlockInfo, voxel_size: float | None) -> tuple[float, np.ndarray, np.ndarray | None]:
    """The density grid's cell side [m] and its zeroed point counts, and voxel counts
    (None without a ``voxel_size``)."""
    cell, shape = _density_grid(info)
    return cell, np.zeros(shape, dtype=np.int64), None if voxel_size is None else np.zeros(shape, dtype=np.int64)


def _count_run(info: BlockInfo, X, Y, Z, voxel_size, cell, counts, nodes) -> None:
    """Add one run's points (stored integers ``X``, ``Y``, ``Z``; ``Z`` None: points only)
    to ``counts`` and its distinct voxels to ``nodes``, in place."""
    # local coordinates (the origin's cell corner at 0): no UTM-sized sums
    scale, shift = info.scales, np.asarray(info.offsets) - np.asarray(info.origin)
    x, y = X * scale[0] + shift[0], Y * scale[1] + shift[1]
    counts += count_cells(x, y, origin=(0.0, 0.0), cell=cell, shape=counts.shape)
    if Z is not None:
        nodes += _voxel_cells(np.column_stack([x, y, Z * scale[2] + shift[2]]), voxel_size, cell, counts.shape)


def count_range(path, start: int, count: int, *, info: BlockInfo | None = None,
                voxel_size: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Points ``[start, start + count)`` counted per cell of :func:`sample_density`'s grid
    as one run (a task: workers count their own ranges of a file in parallel).

    Ranges of ``CHUNK_POINTS`` from the first point give, summed with
    :func:`sample_from_ranges`, the same sample as :func:`sample_density` counting every
    point. Returns the cells holding points (flat indices into the grid), their points
    and (with a ``voxel_size``) their voxels, or None.

    Raises
    ------
    InputError
        The range lies beyond the points the file holds, or its data is corrupt.
    """
    info = info or read_info(path)
    return count_ints(info, read_raw_range(info.path, start, count, info=info), voxel_size=voxel_size)


def count_ints(info: BlockInfo, ints: np.ndarray, *, voxel_size: float | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`count_range` of a range already decoded: its stored integers ``ints`` (m, 3)
    int32 counted as one run."""
    cell, counts, nodes = _empty_counts(info, voxel_size)
    _count_run(info, ints[:, 0], ints[:, 1], ints[:, 2] if nodes is not None else None, voxel_size, cell, counts, nodes)
    # a run covers a strip of the block: only its cells are returned (a voxel's centre can
    # lie in a cell that holds none of its points)
    held = np.flatnonzero(counts if nodes is None else (counts != 0) | (nodes != 0))
    return held, counts.ravel()[held], None if nodes is None else nodes.ravel()[held]


def sample_from_ranges(info: BlockInfo, parts) -> DensitySample:
    """The :class:`DensitySample` of a block whose every point was counted by
    :func:`count_range` tasks, from their results ``parts``."""
    cell, shape = _density_grid(info)
    counts = np.zeros(shape, dtype=np.int64)
    nodes = None
    for held, points, voxels in parts:  # a part's cells are distinct
        counts.ravel()[held] += points
        if voxels is not None:
            nodes = np.zeros(shape, dtype=np.int64) if nodes is None else nodes
            nodes.ravel()[held] += voxels
    return _sample(info, cell, counts, nodes, int(counts.sum()))


def _voxel_cells(xyz: np.ndarray, voxel_size: float, cell: float, shape: tuple[int, int]) -> np.ndarray:
    """Distinct voxels of ``voxel_size`` that the points ``xyz`` (local frame, grid at 0)
    occupy, counted per square cell of ``cell`` by their centres, shape ``shape``."""
    packed, lo, span = packed_keys(xyz, voxel_size, (0.0, 0.0, 0.0))
    n_keys = int(span[0]) * int(span[1]) * int(span[2])
    if n_keys <= DENSE_CELLS_PER_POINT * len(packed):
        # a grid of at most a few cells per point: mark the occupied ones, where a sort
        # of the keys costs ten times more (the same keys, in the same order)
        seen = np.zeros(n_keys, dtype=bool)
        seen[packed] = True
        del packed
        uniq = np.flatnonzero(seen)
        del seen
    else:
        # sorted in place and kept where the key changes: a quarter of np.unique's time on a
        # run of 2 M points, and half the memory of a hash of its keys (docs/performance.md)
        packed.sort()
        changes = np.empty(len(packed), dtype=bool)
        changes[:1] = True
        np.not_equal(packed[1:], packed[:-1], out=changes[1:])
        uniq = packed[changes]
        del packed, changes
    yz = span[1] * span[2]
    centre_x = (uniq // yz + lo[0] + 0.5) * voxel_size
    centre_y = ((uniq // span[2]) % span[1] + lo[1] + 0.5) * voxel_size
    return count_cells(centre_x, centre_y, origin=(0.0, 0.0), cell=cell, shape=shape)


def _picked_runs(info: BlockInfo, run: int, picked: np.ndarray, selection=_XY_ONLY) -> Iterator[np.ndarray]:
    """The runs of ``run`` points numbered ``picked`` (decoding the layers of
    ``selection``), each read from its first point through the file's chunk table."""
    start = 0
    try:
        with laspy.open(info.path, read_evlrs=False, decompression_selection=selection) as reader:
            for k in picked:
                start = int(k) * run
                reader.seek(start)
                yield reader.read_points(min(run, info.n_points - start)).array
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # lazrs panics (pyo3's PanicException is no Exception) on corrupt chunks
        raise input_error(info.path, f"corrupt or truncated point data after point {start} ({one_line(exc)})") from None
