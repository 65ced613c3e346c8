"""E57 files (ASTM E2807: terrestrial and mobile scanners), read with ``pye57``
(libE57Format).

Every scan of the file is read, a chunk of points at a time into buffers of
libE57Format (``CompressedVectorReader``), its invalid points dropped, spherical
coordinates turned Cartesian, and moved by the scan's pose into the file's common
frame, as ``pye57.E57.read_scan`` does for a whole scan. The file's
``coordinateMetadata``, when it names a CRS pyproj understands, is its CRS.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pipeline.blockinfo import one_line
from pipeline.formats.source import PointSource, bad

_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")


def _e57_errors():
    import pye57

    return (pye57.libe57.E57Exception, RuntimeError, ValueError, KeyError, IndexError, TypeError, MemoryError)


def _open(path):
    import pye57

    try:
        return pye57.E57(str(path))
    except _e57_errors() as exc:
        raise bad(path, f"not a readable E57 file ({one_line(exc)})") from None


def _crs_wkt(e57) -> str | None:
    import pyproj

    try:
        text = e57.root["coordinateMetadata"].value().strip()
    except Exception:  # noqa: BLE001 - an optional field; absent or of another kind
        return None
    if not text:
        return None
    try:
        return pyproj.CRS.from_user_input(text).to_wkt()
    except pyproj.exceptions.CRSError:
        return None


def open_e57(path) -> PointSource:
    """An E57 file's points (every scan, in the file's frame) as a :class:`PointSource`.

    Raises
    ------
    InputError
        Not an E57 file libE57Format can open, a scan without Cartesian or spherical
        coordinates, a corrupt point section.
    """
    e57 = _open(path)
    try:
        crs = _crs_wkt(e57)
        for i in range(e57.scan_count):
            fields = e57.get_header(i).point_fields
            if not (set(_CARTESIAN) <= set(fields) or set(_SPHERICAL) <= set(fields)):
                raise bad(path, f"scan {i} of the E57 file has neither cartesianX/Y/Z nor spherical coordinates")
    except _e57_errors() as exc:
        raise bad(path, f"the E57 file's scans could not be read ({one_line(exc)})") from None
    finally:
        e57.close()
    return PointSource("e57", lambda chunk_points: _points(path, chunk_points), crs_wkt=crs)


def _points(path, chunk_points: int) -> Iterator[np.ndarray]:
    from pye57.utils import convert_spherical_to_cartesian

    e57 = _open(path)
    try:
        for i in range(e57.scan_count):
            header = e57.get_header(i)
            fields = header.point_fields
            coords = _CARTESIAN if set(_CARTESIAN) <= set(fields) else _SPHERICAL
            state = "cartesianInvalidState" if coords is _CARTESIAN else "sphericalInvalidState"
            names = [*coords, *([state] if state in fields else [])]
            try:
                data, buffers = e57.make_buffers(names, chunk_points)
                reader = header.points.reader(buffers)
                rotation, translation = header.rotation, header.translation
                posed = header.has_pose()
                try:
                    while (got := reader.read()) > 0:
                        xyz = np.column_stack([data[c][:got] for c in coords]).astype(np.float64)
                        if state in data:
                            xyz = xyz[data[state][:got] == 0]
                        if coords is _SPHERICAL:
                            xyz = convert_spherical_to_cartesian(xyz)
                        if posed:
                            xyz = e57.to_global(xyz, rotation, translation)
                        yield np.ascontiguousarray(xyz, dtype=np.float64)
                finally:
                    reader.close()
            except _e57_errors() as exc:
                raise bad(path, f"scan {i} of the E57 file could not be read ({one_line(exc)})") from None
    finally:
        e57.close()
