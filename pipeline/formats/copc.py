"""COPC blocks (``.copc.laz``): the octree's nodes as an index of the file's points.

A COPC file is a LAZ 1.4 file whose chunks are the nodes of an octree, listed with their
bounds and point counts in its hierarchy (https://copc.io). The hierarchy is all a job
needs to plan its tiles, and each tile reads the nodes its box meets, decoded by lazrs
(laspy's :class:`laspy.CopcReader` reads the hierarchy; this module keeps the points'
positions in the file, which laspy's query drops). No pass over the whole block.

A point's index is its position in the file, as :func:`pipeline.reading.iter_raw` numbers
it: the chunks lie in the file in the order of their offsets.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

import lazrs
import numpy as np

from pipeline.blockinfo import BlockInfo, input_error, one_line
from pipeline.budget import DensitySample
from pipeline.laspyload import laspy

#: decode only X, Y, Z (the other fields' layers are skipped)
_XYZ_ONLY = laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z


@dataclass(frozen=True)
class Nodes:
    """The octree nodes of a COPC file that hold points, in the order of their chunks in
    the file.

    Attributes
    ----------
    boxes : (k, 6) float64
        Each node's cube, ``xmin, ymin, zmin, xmax, ymax, zmax`` [m], input CRS.
    first : (k,) int64
        Index in the file of each node's first point.
    count : (k,) int64
        Points of each node.
    offset, size : (k,) int64
        Byte offset and size of each node's LAZ chunk.
    level : (k,) int64
        Depth in the octree (0: the root).
    """

    boxes: np.ndarray
    first: np.ndarray
    count: np.ndarray
    offset: np.ndarray
    size: np.ndarray
    level: np.ndarray

    @property
    def n_points(self) -> int:
        return int(self.count.sum())


def read_nodes(path) -> Nodes:
    """The hierarchy of the COPC file ``path`` (every page of it).

    Raises
    ------
    InputError
        The file is no COPC file, or its hierarchy cannot be read.
    """
    st = os.stat(path)
    return _read_nodes(os.path.abspath(os.fspath(path)), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=8)
def _read_nodes(path: str, _mtime: int, _size: int) -> Nodes:
    # cached per process by the file's identity: every tile of a job asks for it
    try:
        with laspy.copc.CopcReader.open(path) as reader:
            nodes = [n for n in laspy.copc.load_octree_for_query(reader.source, reader.copc_info, reader.root_page) if n.point_count > 0]
    except Exception as exc:  # noqa: BLE001 - laspy and lazrs raise their own types
        raise input_error(path, f"not a readable COPC file ({one_line(exc)})") from None
    nodes.sort(key=lambda n: n.offset)
    count = np.array([n.point_count for n in nodes], dtype=np.int64)
    return Nodes(
        boxes=np.array([[*n.bounds.mins, *n.bounds.maxs] for n in nodes], dtype=np.float64).reshape(-1, 6),
        first=np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64),
        count=count,
        offset=np.array([n.offset for n in nodes], dtype=np.int64),
        size=np.array([n.byte_size for n in nodes], dtype=np.int64),
        level=np.array([n.key.level for n in nodes], dtype=np.int64),
    )


def nodes_meeting(nodes: Nodes, box) -> np.ndarray:
    """Indices of the nodes whose cube's x-y footprint meets the closed box
    ``(xmin, ymin, xmax, ymax)`` [m]."""
    x0, y0, x1, y1 = box
    b = nodes.boxes
    return np.flatnonzero((b[:, 0] <= x1) & (b[:, 3] >= x0) & (b[:, 1] <= y1) & (b[:, 4] >= y0))


def read_box(info: BlockInfo, box) -> tuple[np.ndarray, np.ndarray]:
    """The points of every node of the COPC block ``info`` whose cube meets ``box``
    ``(xmin, ymin, xmax, ymax)`` [m]: a superset of the points in the box, for the caller
    to select from.

    Returns
    -------
    ints : (m, 3) int32
        The stored X, Y, Z.
    index : (m,) uint64
        Each point's position in the file.

    Raises
    ------
    InputError
        The nodes' data is corrupt or truncated.
    """
    parts = list(iter_box(info, box))
    if not parts:
        return np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.uint64)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def iter_box(info: BlockInfo, box, *, batch_points: int = 2_000_000):
    """:func:`read_box` in batches of whole nodes of at most ``batch_points`` points (a
    larger node alone), in file order: memory stays one batch however large the box.

    Yields
    ------
    (ints, index) as :func:`read_box` returns them.
    """
    nodes = read_nodes(info.path)
    pick = nodes_meeting(nodes, box)
    start, total = 0, 0
    for i, k in enumerate(pick):
        if total and total + int(nodes.count[k]) > batch_points:
            yield _decode(info, nodes, pick[start:i])
            start, total = i, 0
        total += int(nodes.count[k])
    if total:
        yield _decode(info, nodes, pick[start:])


def _decode(info: BlockInfo, nodes: Nodes, pick: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stored X, Y, Z and file positions of the points of the nodes ``pick`` (in file order)."""
    if pick.size == 0:
        return np.zeros((0, 3), dtype=np.int32), np.zeros(0, dtype=np.uint64)
    try:
        with laspy.copc.CopcReader.open(info.path, decompression_selection=_XYZ_ONLY) as reader:
            data = bytearray(int(nodes.size[pick].sum()))
            view, at = memoryview(data), 0
            for k in pick:  # in file order: one seek and read per node
                reader.source.seek(int(nodes.offset[k]))
                n = int(nodes.size[k])
                reader.source.readinto(view[at : at + n])
                at += n
            fmt = reader.header.point_format
            raw = np.zeros(int(nodes.count[pick].sum()) * fmt.size, dtype=np.uint8)
            table = [(int(nodes.count[k]), int(nodes.size[k])) for k in pick]
            lazrs.decompress_points_with_chunk_table(data, reader.laszip_vlr.record_data, raw, table,
                                                     reader.decompression_selection)
            arr = np.frombuffer(raw, dtype=fmt.dtype())
    except Exception as exc:  # noqa: BLE001 - lazrs raises its own types (and panics) on corrupt chunks
        raise input_error(info.path, f"corrupt or truncated COPC node data ({one_line(exc)})") from None
    ints = np.empty((len(arr), 3), dtype=np.int32)
    ints[:, 0], ints[:, 1], ints[:, 2] = arr["X"], arr["Y"], arr["Z"]
    index = np.concatenate([np.arange(nodes.first[k], nodes.first[k] + nodes.count[k], dtype=np.uint64) for k in pick])
    return ints, index


#: how many footprints of nodes are decoded to measure a COPC block's voxel-graph nodes
#: per point (:func:`voxels_per_point`)
PROBES = 6
#: a sampled share of voxels per point is raised by this for the sampling error (as
#: :data:`pipeline.budget.SAMPLE_MARGIN` raises a sampled count)
PROBE_MARGIN = 1.25


def voxels_per_point(info: BlockInfo, nodes: Nodes, voxel_size: float, *, probes: int = PROBES) -> float:
    """The largest share of occupied voxels of ``voxel_size`` [m] per point among
    ``probes`` footprints of nodes two levels above the deepest, evenly picked in file
    order, from the points of their own and deeper levels (the upper levels' few points
    are left out: decoding them would take a large share of the block; on a 14.8 M-point
    block at mobile density the shares with and without them differed by under 10 %)."""
    level = max(0, int(nodes.level.max()) - 2)
    cand = np.flatnonzero(nodes.level == level)
    picked = cand[np.unique(np.linspace(0, len(cand) - 1, min(probes, len(cand))).round().astype(np.int64))]
    deep = nodes.level >= level
    worst = 0.0
    for k in picked:
        x0, y0, _, x1, y1, _ = nodes.boxes[k]
        pad = 1e-3 * (x1 - x0)  # inside the footprint: its neighbours' cubes only touch it
        meet = nodes_meeting(nodes, (x0 + pad, y0 + pad, x1 - pad, y1 - pad))
        ints, _ = _decode(info, nodes, meet[deep[meet]])
        xyz = ints * np.asarray(info.scales) + (np.asarray(info.offsets) - np.asarray(info.origin))
        o = info.origin
        xyz = xyz[(xyz[:, 0] >= x0 - o[0]) & (xyz[:, 0] < x1 - o[0]) & (xyz[:, 1] >= y0 - o[1]) & (xyz[:, 1] < y1 - o[1])]
        if len(xyz):
            keys = np.floor(xyz / voxel_size).astype(np.int64)
            worst = max(worst, len(np.unique(keys, axis=0)) / len(xyz))
    return worst


def density_from_nodes(info: BlockInfo, nodes: Nodes, *, cell: float, shape: tuple[int, int],
                       voxel_size: float | None) -> DensitySample:
    """A :class:`pipeline.budget.DensitySample` of a COPC block from its hierarchy and
    a few of its nodes' points.

    Each node's points are spread evenly over the cells its footprint (clipped to the
    header's bounds) covers, rounded up. With a ``voxel_size`` [m] a cell's voxel-graph
    nodes are its points times the largest share of voxels per point found in
    :data:`PROBES` footprints (:func:`voxels_per_point`) times :data:`PROBE_MARGIN`, and at
    most the voxels the cubes of its nodes hold (at most its points).
    """
    ny, nx = shape
    ox, oy = info.origin[0], info.origin[1]
    b = nodes.boxes
    x0 = np.maximum(b[:, 0], info.mins[0]) - ox
    x1 = np.minimum(b[:, 3], info.maxs[0]) - ox
    y0 = np.maximum(b[:, 1], info.mins[1]) - oy
    y1 = np.minimum(b[:, 4], info.maxs[1]) - oy
    i0 = np.clip(np.floor(x0 / cell), 0, nx - 1).astype(np.int64)
    i1 = np.clip(np.floor(x1 / cell), i0, nx - 1).astype(np.int64)
    j0 = np.clip(np.floor(y0 / cell), 0, ny - 1).astype(np.int64)
    j1 = np.clip(np.floor(y1 / cell), j0, ny - 1).astype(np.int64)
    n_cells = (i1 - i0 + 1) * (j1 - j0 + 1)

    def spread(values: np.ndarray) -> np.ndarray:
        # Strategy: each node adds a constant over a rectangle of cells; a difference
        # array with four corners per node and two cumulative sums draws them all
        diff = np.zeros((ny + 1, nx + 1), dtype=np.float64)
        per = values / n_cells
        np.add.at(diff, (j0, i0), per)
        np.add.at(diff, (j0, i1 + 1), -per)
        np.add.at(diff, (j1 + 1, i0), -per)
        np.add.at(diff, (j1 + 1, i1 + 1), per)
        dense = np.cumsum(np.cumsum(diff, axis=0), axis=1)[:ny, :nx]
        return np.ceil(np.maximum(dense, 0.0) - 1e-9).astype(np.int64)

    counts = spread(nodes.count.astype(np.float64))
    voxels = None
    if voxel_size is not None:
        side = b[:, 3:] - b[:, :3]
        held = spread(np.minimum(nodes.count.astype(np.float64), np.prod(np.ceil(side / voxel_size) + 1, axis=1)))
        share = min(1.0, PROBE_MARGIN * voxels_per_point(info, nodes, voxel_size))
        voxels = np.minimum(np.ceil(counts * share).astype(np.int64), held)
    return DensitySample(counts=counts, origin=(float(ox), float(oy)), cell=cell, sampled=info.n_points,
                         n_points=info.n_points, nodes=voxels)


def check_nodes_count(info: BlockInfo, nodes: Nodes) -> None:
    """InputError when the hierarchy's points are not the header's count."""
    if nodes.n_points != info.n_points:
        raise input_error(info.path, f"its header announces {info.n_points} points but its COPC hierarchy holds "
                                     f"{nodes.n_points}")

