"""Writers of small PLY, PCD, E57 and text files for the format tests, each with the
libraries' own writers (plyfile, pypcd4, pye57; numpy for text)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the E57 scan's pose: its points are stored relative to this, in single precision
E57_TRANSLATION = (100.0, 200.0, 0.0)


def write_ply(path: Path, xyz: np.ndarray, *, text: bool = False, dtype="f8") -> Path:
    from plyfile import PlyData, PlyElement

    v = np.empty(len(xyz), dtype=[("x", dtype), ("y", dtype), ("z", dtype), ("intensity", "u2")])
    v["x"], v["y"], v["z"] = xyz.T
    v["intensity"] = np.arange(len(xyz)) % 1000
    PlyData([PlyElement.describe(v, "vertex")], text=text, byte_order="<").write(str(path))
    return path


def write_pcd(path: Path, xyz: np.ndarray, encoding: str, *, dtype=np.float32) -> Path:
    """``encoding``: "ascii", "binary" or "binary_compressed" (checked: pypcd4 writes
    binary when LZF cannot shrink the data)."""
    from pypcd4 import Encoding, PointCloud

    size = np.dtype(dtype).itemsize
    pc = PointCloud.from_points(np.column_stack([xyz.astype(dtype), np.zeros(len(xyz), np.float32)]),
                                ("x", "y", "z", "intensity"), (dtype, dtype, dtype, np.float32))
    pc.save(str(path), encoding=Encoding(encoding))
    head = path.read_bytes()[:400]
    assert f"DATA {encoding}\n".encode() in head and f"SIZE {size} {size} {size} 4".encode() in head
    return path


def write_e57(path: Path, xyz: np.ndarray) -> Path:
    """One scan posed at :data:`E57_TRANSLATION` (pye57 stores single precision)."""
    import pye57

    local = xyz - np.asarray(E57_TRANSLATION)
    e57 = pye57.E57(str(path), mode="w")
    try:
        e57.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]},
                           rotation=np.array([1.0, 0.0, 0.0, 0.0]), translation=np.asarray(E57_TRANSLATION))
    finally:
        e57.close()
    return path


def write_text(path: Path, xyz: np.ndarray, *, header: str | None = "x y z intensity", delimiter: str = " ") -> Path:
    cols = np.column_stack([xyz, np.arange(len(xyz)) % 1000])
    with open(path, "w") as fh:
        if header is not None:
            fh.write(header + "\n")
        np.savetxt(fh, cols, fmt=["%.3f", "%.3f", "%.3f", "%d"], delimiter=delimiter)
    return path


def every_format(folder: Path, xyz: np.ndarray) -> dict[str, Path]:
    """One file of each format and variant holding ``xyz`` (local metres, mm-exact)."""
    folder.mkdir(parents=True, exist_ok=True)
    return {
        "ply-binary": write_ply(folder / "b.ply", xyz),
        "ply-binary-float": write_ply(folder / "f.ply", xyz, dtype="f4"),
        "ply-ascii": write_ply(folder / "a.ply", xyz, text=True),
        "pcd-ascii": write_pcd(folder / "a.pcd", xyz, "ascii"),
        "pcd-binary": write_pcd(folder / "b.pcd", xyz, "binary"),
        "pcd-binary_compressed": write_pcd(folder / "c.pcd", xyz, "binary_compressed"),
        "e57": write_e57(folder / "s.e57", xyz),
        "text-header": write_text(folder / "h.xyz", xyz),
        "text-bare": write_text(folder / "n.xyz", xyz, header=None),
        "text-csv": write_text(folder / "c.csv", xyz, header="//X,Y,Z,Intensity", delimiter=","),
    }
