"""Writing LAS/LAZ files: a streaming block writer and a labelled copy of a block."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.atomic import AtomicWriter, temp_name
from pipeline.blockinfo import read_info
from pipeline.crs import add_crs, crs_from
from pipeline.laspyload import laspy
from pipeline.reading import CHUNK_POINTS


def _extra_type(dtype) -> np.dtype:
    dt = np.dtype(dtype)
    return np.dtype(np.uint8) if dt == np.bool_ else dt


class LasBlockWriter(AtomicWriter):
    """Streaming LAS/LAZ writer (LAZ when the path ends in ``.laz``).

    Points are appended with :meth:`write`; the file appears under its name only when
    :meth:`close` succeeds (it is written to a temporary name in the same folder). Used
    as a context manager, an exception deletes the temporary file.

    Parameters
    ----------
    path : str or Path
    crs_wkt, crs_epsg : optional
        CRS stored as a WKT VLR (LAS 1.4, or point formats >= 6) or as GeoTIFF keys
        (LAS 1.2/1.3 with formats 0–5).
    scales, offsets : (3,) float
        Stored integer = round((coordinate - offset) / scale). ``offsets=None`` takes
        the first written point's coordinates rounded down to 1 km.
    point_format : int
        0–10.
    version : str
        ``"1.2"``, ``"1.3"`` or ``"1.4"`` (formats >= 6 need 1.4).
    extra_dims : dict name → numpy dtype, optional
        Extra-bytes dimensions (bool is stored as uint8).
    creation_date : datetime.date or "unset", optional
        The header's file creation day (default: today, laspy's); ``"unset"`` writes
        day and year 0, the LAS way of saying the day is unknown (a file converted from
        a format without dates: the conversion day is no capture day).
    """

    def __init__(
        self,
        path,
        *,
        crs_wkt: str | None = None,
        crs_epsg: int | None = None,
        scales=(0.001, 0.001, 0.001),
        offsets=None,
        point_format: int = 6,
        version: str | None = None,
        extra_dims: dict | None = None,
        creation_date=None,
    ):
        self.path = Path(str(path))
        if version is None:
            version = "1.4" if point_format >= 6 else "1.2"
        header = laspy.LasHeader(version=version, point_format=int(point_format))
        header.scales = np.asarray(scales, dtype=np.float64)
        self._unset_date = creation_date == "unset"
        if creation_date is not None and not self._unset_date:
            header.creation_date = creation_date
        if offsets is not None:
            header.offsets = np.asarray(offsets, dtype=np.float64)
        self._extra = {k: _extra_type(v) for k, v in (extra_dims or {}).items()}
        if self._extra:
            header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=v) for k, v in self._extra.items()])
        crs = crs_from(crs_wkt, crs_epsg)
        if crs is not None:
            add_crs(header, crs)
        self.header = header
        self._auto_offsets = offsets is None
        self._tmp = temp_name(self.path)
        self._writer = None if self._auto_offsets else self._open()
        self.n_points = 0
        self._closed = False

    def close(self) -> None:
        if self._unset_date and not self._closed:
            if self._writer is None:
                self._writer = self._open()
            self._writer.close()
            # laspy always stamps a day: the header's day and year (bytes 90-93 of every
            # LAS version's public header, uncompressed in a LAZ too) are zeroed here
            with open(self._tmp, "r+b") as f:
                f.seek(90)
                f.write(b"\0\0\0\0")
            self._writer = _Closed()
        super().close()

    def _open(self):
        return laspy.open(str(self._tmp), mode="w", header=self.header, do_compress=self.path.suffix.lower() == ".laz")

    def write(self, xyz_abs: np.ndarray, **extra: np.ndarray) -> None:
        """Append points.

        Parameters
        ----------
        xyz_abs : (m, 3) float64
            Absolute coordinates [m], input CRS.
        **extra : (m,) arrays
            Values of the extra dimensions named at construction (missing ones are 0).
        """
        xyz_abs = np.asarray(xyz_abs, dtype=np.float64)
        m = len(xyz_abs)
        if m == 0:
            return
        if self._writer is None:
            self.header.offsets = np.floor(xyz_abs[0] / 1000.0) * 1000.0
            self._writer = self._open()
        rec = laspy.ScaleAwarePointRecord.zeros(m, header=self.header)
        ints = np.round((xyz_abs - self.header.offsets) / self.header.scales)
        if not np.isfinite(ints).all() or np.abs(ints).max() > np.iinfo(np.int32).max:
            raise ValueError("coordinates do not fit the LAS integer range with these scales/offsets")
        rec.array["X"] = ints[:, 0].astype(np.int32)
        rec.array["Y"] = ints[:, 1].astype(np.int32)
        rec.array["Z"] = ints[:, 2].astype(np.int32)
        for name, values in extra.items():
            if name not in self._extra:
                raise ValueError(f"unknown extra dimension {name!r}")
            rec[name] = np.asarray(values).astype(self._extra[name])
        self._writer.write_points(rec)
        self.n_points += m


class _Closed:
    """A writer already closed (closing it again does nothing)."""

    def close(self) -> None:
        pass


def write_labelled_las(
    src_path,
    dst_path,
    *,
    labels: Callable[[int, int], dict[str, np.ndarray]] | dict[str, np.ndarray],
    chunk_points: int = CHUNK_POINTS,
) -> None:
    """Copy a block with extra dimensions ``tree_id``, ``is_wood``, ``wood_score``.

    Parameters
    ----------
    src_path : input LAS/LAZ
    dst_path : output; LAZ when it ends in ``.laz``
    labels : dict of (n,) arrays (may be memory-mapped) or callable ``(start, stop) -> dict``
        Per-point values for the points ``start:stop`` of the input; keys among
        ``tree_id`` (int64 → stored int32), ``is_wood`` (bool → uint8), ``wood_score`` (float32).
    chunk_points : int
        Points per chunk (bounded memory).
    """
    info = read_info(src_path)
    dst = Path(str(dst_path))
    types = {"tree_id": np.dtype(np.int32), "is_wood": np.dtype(np.uint8), "wood_score": np.dtype(np.float32)}
    get = labels if callable(labels) else (lambda a, b: {k: v[a:b] for k, v in labels.items()})
    tmp = temp_name(dst)
    try:
        with laspy.open(info.path, read_evlrs=True) as reader:
            src_header = reader.header
            # laspy writes LAS 1.2-1.4; a LAS 1.0/1.1 block (same point formats 0-1) is copied as 1.2
            version = src_header.version if src_header.version.minor >= 2 else laspy.header.Version(1, 2)
            header = laspy.LasHeader(version=version, point_format=src_header.point_format.id)
            header.scales = src_header.scales
            header.offsets = src_header.offsets
            header.vlrs = [v for v in src_header.vlrs if not isinstance(v, laspy.vlrs.known.ExtraBytesVlr)]
            header.global_encoding = src_header.global_encoding
            # the file's identity: the output is a copy of it
            header.file_source_id = src_header.file_source_id
            header.uuid = src_header.uuid
            header.system_identifier = src_header.system_identifier
            src_extra = set(src_header.point_format.extra_dimension_names)
            # an input's own dimension named like one of ours is kept as input_NAME
            renamed = {n: _free_name(f"input_{n}", src_extra) for n in src_extra if n in types}
            params = []
            split: dict[str, int] = {}  # undocumented extra bytes -> one uint8 dimension per byte
            for d in src_header.point_format.extra_dimensions:
                if d.num_elements > 3:
                    # bytes no ExtraBytes record describes: laspy can write them only as an
                    # "undocumented" record that it cannot read back, so each byte becomes a
                    # documented uint8 dimension NAME_0, NAME_1, ... holding the same values
                    split[d.name] = int(d.num_elements)
                    params += [laspy.ExtraBytesParams(name=f"{d.name}_{i}", type=np.uint8) for i in range(d.num_elements)]
                else:  # with its scales and offsets: the stored integers keep their meaning
                    params.append(laspy.ExtraBytesParams(
                        name=renamed.get(d.name, d.name), type=d.dtype, description=d.description,
                        offsets=d.offsets if d.is_scaled else None, scales=d.scales if d.is_scaled else None,
                        no_data=d.no_data,
                    ))
            params += [laspy.ExtraBytesParams(name=k, type=v) for k, v in types.items()]
            header.add_extra_dims(params)
            with laspy.open(str(tmp), mode="w", header=header, do_compress=dst.suffix.lower() == ".laz") as writer:
                start = 0
                for chunk in reader.chunk_iterator(int(chunk_points)):
                    m = len(chunk)
                    rec = laspy.ScaleAwarePointRecord.zeros(m, header=header)
                    for name in chunk.array.dtype.names:  # the stored values, bit for bit
                        if name in split:
                            for i in range(split[name]):
                                rec.array[f"{name}_{i}"] = chunk.array[name][:, i]
                            continue
                        rec.array[renamed.get(name, name)] = chunk.array[name]
                    for k, v in get(start, start + m).items():
                        rec[k] = np.asarray(v).astype(types[k])
                    writer.write_points(rec)
                    start += m
                if src_header.evlrs and header.version.minor >= 4:
                    writer.write_evlrs(src_header.evlrs)
        os.replace(tmp, dst)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _free_name(name: str, taken: set[str]) -> str:
    """``name``, or ``name_2``, ``name_3``, ... if it is taken."""
    candidate, i = name, 1
    while candidate in taken:
        i += 1
        candidate = f"{name}_{i}"
    return candidate

