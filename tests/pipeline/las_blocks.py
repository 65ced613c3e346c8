"""Small LAS/LAZ blocks for the IO tests: a random cloud at UTM-sized coordinates, written
in two parts, and a byte patcher for forging header fields."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from pipeline.laswriting import LasBlockWriter

EASTING, NORTHING = 512_345.0, 6_234_567.0


def cloud(n=5000, seed=0):
    """``n`` random points in a 40 m cube at (EASTING, NORTHING, 100) [m]."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 40, (n, 3)) + [EASTING, NORTHING, 100.0]


def write_block(path, xyz, **kw):
    """Write ``xyz`` with LasBlockWriter (``kw`` passed on) in two calls; returns ``path``."""
    kw.setdefault("offsets", (EASTING, NORTHING, 0.0))
    with LasBlockWriter(path, **kw) as w:
        half = len(xyz) // 2
        w.write(xyz[:half])
        w.write(xyz[half:])
    return path


def patch(path, offset, fmt, *values):
    """Overwrite bytes of a file at ``offset`` with ``struct.pack(fmt, *values)``."""
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, *values)
    path.write_bytes(bytes(data))


def one_line(err: pytest.ExceptionInfo) -> str:
    """The error's message, checked to be one short line."""
    msg = str(err.value)
    assert "\n" not in msg and len(msg) < 300
    return msg
