"""Inputs in the formats scanners write besides LAS/LAZ: PLY, PCD, E57 and text (x y z).

Each is turned into a LAZ file at the edge (:func:`pipeline.formats.convert.to_laz`), so
everything downstream reads LAS/LAZ only. A file's format comes from its first bytes
(:func:`sniff`); text, which has no signature, is what is left.
One module per format, each reading with a maintained library (``plyfile``, ``pypcd4``,
``pye57``, numpy for text) in chunks where the format allows.
"""

from __future__ import annotations

from pipeline.formats.source import PointSource, bad

#: the formats read here, with the suffixes their files usually carry
SUFFIXES = {
    "ply": (".ply",),
    "pcd": (".pcd",),
    "e57": (".e57",),
    "text": (".xyz", ".txt", ".csv", ".pts", ".asc"),
}
#: every suffix of a point file taken (LAS/LAZ and the formats above)
POINT_SUFFIXES = (".las", ".laz") + tuple(s for v in SUFFIXES.values() for s in v)


def sniff(path) -> str:
    """``"las"``, ``"ply"``, ``"pcd"``, ``"e57"`` or ``"text"``, from the file's first bytes.

    Raises
    ------
    InputError
        An empty file, or one that holds NUL bytes where a text file would begin (a
        binary file of another kind).
    """
    with open(path, "rb") as fh:
        head = fh.read(512)
    if not head:
        raise bad(path, "the file is empty (0 bytes)")
    if head.startswith(b"LASF"):
        return "las"
    if head.startswith(b"ASTM-E57"):
        return "e57"
    if head[:4] == b"ply\n" or head[:5] == b"ply\r\n":
        return "ply"
    lines = [ln.strip() for ln in head.split(b"\n")]
    first = next((ln for ln in lines if ln and not ln.startswith(b"#")), b"")
    if head.startswith(b"# .PCD") or first.startswith((b"VERSION", b"FIELDS")):
        return "pcd"
    if b"\0" in head:
        raise bad(path, "not a LAS, LAZ, PLY, PCD, E57 or text point file")
    return "text"


def open_points(path, fmt: str, *, columns: str | None = None) -> PointSource:
    """The :class:`PointSource` of a non-LAS point file of format ``fmt`` (:func:`sniff`)."""
    if columns is not None and fmt != "text":
        raise bad(path, f"--columns names the columns of a text file; this is a {fmt.upper()} file")
    if fmt == "ply":
        from pipeline.formats.ply import open_ply

        return open_ply(path)
    if fmt == "pcd":
        from pipeline.formats.pcd import open_pcd

        return open_pcd(path)
    if fmt == "e57":
        from pipeline.formats.e57 import open_e57

        return open_e57(path)
    if fmt == "text":
        from pipeline.formats.text import open_text

        return open_text(path, columns=columns)
    raise ValueError(f"no reader for {fmt!r}")


__all__ = ["POINT_SUFFIXES", "SUFFIXES", "PointSource", "open_points", "sniff"]
