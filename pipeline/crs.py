"""Coordinate reference systems of blocks: read from a LAS header, checked to be in
metres, and stored into the header of a written file (pyproj objects throughout)."""

from __future__ import annotations

from pipeline.laspyload import laspy

_LINEAR_UNITS_KEY, _VERTICAL_CS_KEY, _VERTICAL_UNITS_KEY = 3076, 4096, 4099
_METRE = 9001
_UNIT_NAMES = {9002: "foot", 9003: "US survey foot", 9005: "Clarke's foot", 9014: "fathom", 9030: "nautical mile",
               9036: "kilometre", 9070: "British foot", 9093: "statute mile", 9096: "yard", 32767: "user-defined unit"}


def parse_crs(header: "laspy.LasHeader"):
    """The block's CRS from its WKT or GeoTIFF-key records, EVLRs included (LAS 1.4 may
    keep it there), and why the GeoTIFF keys' units are not metres.

    laspy reads only the CRS codes of GeoTIFF keys, so the linear and vertical unit keys
    (a user-defined CRS in feet, heights in feet) and the vertical CRS
    (VerticalCSTypeGeoKey) are read here.

    Parameters
    ----------
    header : laspy.LasHeader
        With its VLRs and whichever EVLRs were read.

    Returns
    -------
    crs : pyproj.CRS or None
        None when absent or not understood (outputs then say "unknown CRS").
    problem : str or None
        Why the GeoTIFF keys' units are not metres, or None.
    """
    try:
        crs = header.parse_crs()
        keys = _geo_keys(header)
    except Exception:  # an unreadable CRS is not fatal
        return None, None
    vertical = keys.get(_VERTICAL_CS_KEY)
    if crs is not None and vertical is not None and 1024 <= vertical <= 32766 and not crs.is_compound:
        try:
            import pyproj

            vcrs = pyproj.CRS.from_epsg(vertical)
            if vcrs.is_vertical:
                crs = pyproj.CRS(pyproj.crs.CompoundCRS(name=f"{crs.name} + {vcrs.name}", components=[crs, vcrs]))
        except pyproj.exceptions.CRSError:  # a code pyproj does not know: the horizontal CRS alone
            pass
    return crs, _geo_key_units_problem(keys)


def _geo_keys(header) -> dict[int, int]:
    """The short-valued GeoTIFF keys of a header's GeoKeyDirectory record (VLRs and any EVLRs
    read); empty when a WKT record is present, which readers take instead."""
    records = list(header.vlrs.get_by_id("LASF_Projection"))
    if getattr(header, "evlrs", None) is not None:
        records += list(header.evlrs.get_by_id("LASF_Projection"))
    if any(isinstance(r, laspy.vlrs.known.WktCoordinateSystemVlr) for r in records):
        return {}
    keys: dict[int, int] = {}
    for rec in records:
        if isinstance(rec, laspy.vlrs.known.GeoKeyDirectoryVlr):
            for key in rec.geo_keys:
                if int(key.tiff_tag_location) == 0:  # the value itself, not an index into a params record
                    keys[int(key.id)] = int(key.value_offset)
    return keys


def _geo_key_units_problem(keys: dict[int, int]) -> str | None:
    for key, what in ((_LINEAR_UNITS_KEY, "coordinate"), (_VERTICAL_UNITS_KEY, "height")):
        unit = keys.get(key)
        if unit not in (None, 0, _METRE):
            name = _UNIT_NAMES.get(unit, f"EPSG unit {unit}")
            return (f"its GeoTIFF keys give the {what} unit as {name} (EPSG unit code {unit}), but every length "
                    "here is in metres; reproject the block to a projected CRS in metres (e.g. its UTM zone) first")
    return None


def crs_units_problem(crs) -> str | None:
    """Why coordinates in ``crs`` (a pyproj CRS or None) cannot be used as metres, or
    None when they can (every axis in metres, or no CRS given).

    Every length the pipeline measures or is given is in metres, so coordinates in
    feet or degrees would give wrong sizes under ``_m`` names, or no trees at all.
    """
    if crs is None:
        return None
    try:
        units = {(a.unit_name, float(a.unit_conversion_factor)) for a in crs.axis_info}
        geographic = bool(crs.is_geographic)
        geocentric = bool(crs.is_geocentric)
        name = crs.name
    except Exception:  # a CRS pyproj cannot describe: take the coordinates as given
        return None
    if geographic:
        return (f"its coordinates are longitude/latitude in degrees ({name}); "
                "reproject the block to a projected CRS in metres (e.g. its UTM zone) first")
    if geocentric:
        return (f"its coordinates are Earth-centred X/Y/Z ({name}), where Z is not up; "
                "reproject the block to a projected CRS in metres (e.g. its UTM zone) first")
    other = sorted(unit for unit, factor in units if unit != "metre" and factor != 1.0)
    if other:
        return (f"its coordinate unit is {' and '.join(other)} ({name}), but every length here is in metres; "
                "reproject the block to a projected CRS in metres (e.g. its UTM zone) first")
    return None


def crs_from(crs_wkt: str | None, crs_epsg: int | None):
    """A pyproj CRS from WKT (preferred) or an EPSG code; None when neither is given."""
    import pyproj

    if crs_wkt:
        return pyproj.CRS.from_wkt(crs_wkt)
    if crs_epsg:
        return pyproj.CRS.from_epsg(int(crs_epsg))
    return None


def add_crs(header: "laspy.LasHeader", crs) -> None:
    """Store a CRS: a WKT VLR for LAS 1.4 or point formats >= 6, GeoTIFF keys otherwise
    (falling back to a WKT VLR when the CRS has no GeoTIFF encoding)."""
    modern = header.version.minor >= 4 or header.point_format.id >= 6
    try:
        header.add_crs(crs, keep_compatibility=not modern)
    except Exception:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(crs.to_wkt()))
        if modern:
            header.global_encoding.wkt = True

