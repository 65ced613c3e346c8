"""Helpers of the worker tests that are not fixtures (a module of its own name: tests/
folders each have a conftest.py, and ``from conftest import`` took whichever came first)."""

from __future__ import annotations

from pathlib import Path


def write_variable_chunk_laz(src: Path, dst: Path, sizes: list[int]) -> Path:
    """The points of ``src`` as a LAZ of variable-size chunks (``sizes`` points each), as
    COPC files and some writers store them. laspy writes fixed chunks only, so its lazrs
    backend is handed a LAZ VLR asking for variable ones for this write."""
    import laspy
    import laspy._compression.lazrsbackend as backend

    las = laspy.read(src)
    assert sum(sizes) == len(las.points)
    real = backend.lazrs.LazVlr  # the lazrs module's own class

    class VariableVlr:
        @staticmethod
        def new_for_compression(fmt, extra, *_):
            return real.new_for_compression(fmt, extra, True)

    backend.lazrs.LazVlr = VariableVlr
    try:
        with laspy.open(dst, mode="w", header=las.header, do_compress=True, laz_backend=laspy.LazBackend.Lazrs) as w:
            start = 0
            for n in sizes:
                w.write_points(las.points[start : start + n])
                w.point_writer.compressor.finish_current_chunk()
                start += n
    finally:
        backend.lazrs.LazVlr = real
    return dst


def lying_copy(src: Path, dst: Path, *, count: int | None = None, max_x: float | None = None) -> Path:
    """``src`` copied to ``dst`` with its header's point count (LAS 1.4: uint64 at byte
    247) or maximum x (double at byte 179) replaced."""
    import shutil
    import struct

    shutil.copy(src, dst)
    with open(dst, "r+b") as f:
        if count is not None:
            f.seek(247)
            f.write(struct.pack("<Q", count))
        if max_x is not None:
            f.seek(179)
            f.write(struct.pack("<d", max_x))
    return dst
