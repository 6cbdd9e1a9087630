"""Mitsuba ``.vol`` grid files (binary, little-endian, format version 3).

Layout (Mitsuba 3 ``VolumeGrid``): bytes ``'V' 'O' 'L' 3``; int32 encoding (1 = float32);
int32 xres, yres, zres, channels; float32 bbox (xmin, ymin, zmin, xmax, ymax, zmax);
then ``xres*yres*zres*channels`` float32 values, x fastest:
``data[((z * yres + y) * xres + x) * channels + c]`` - i.e. a C-order (z, y, x[, c]) array.
"""
from __future__ import annotations

import os
import struct

import numpy as np

from . import validation as V
from .geometry import check_bbox

_MAGIC = b"VOL"
_VERSION = 3
_FLOAT32 = 1
_HEADER = 48


def write_vol(path, data, bbox=None) -> None:
    """Write a (z, y, x) or (z, y, x, c) array as float32 ``.vol``.

    bbox: (min_xyz, max_xyz) stored in the header (default the unit cube; Mitsuba places
    ``gridvolume`` by its ``to_world`` and does not use it).
    """
    a = V.array(data, "data", np.float32, finite=False)
    if a.ndim == 3:
        a = a[..., None]
    if a.ndim != 4 or min(a.shape) < 1:
        raise ValueError(f"data: expected a (z, y, x) or (z, y, x, c) array, got shape {np.shape(data)}")
    lo, hi = check_bbox(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)) if bbox is None else bbox, "bbox", flat=True)
    if max(np.abs(lo).max(), np.abs(hi).max()) > np.finfo(np.float32).max:
        raise ValueError(f"bbox: beyond the float32 range of the .vol header, got {bbox!r}")
    nz, ny, nx, nc = a.shape
    with open(path, "wb") as f:
        f.write(_MAGIC + bytes([_VERSION]))
        f.write(struct.pack("<5i", _FLOAT32, nx, ny, nz, nc))
        f.write(struct.pack("<6f", *lo, *hi))
        f.write(np.ascontiguousarray(a, dtype="<f4").tobytes())


def read_vol(path, with_bbox: bool = False):
    """Read a float32 ``.vol``: (z, y, x) array for one channel, (z, y, x, c) otherwise.

    with_bbox: also return the header's (min_xyz, max_xyz) as float64 arrays.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        head = f.read(_HEADER)
        if head[:3] != _MAGIC:
            raise ValueError(f"path: {path!r} is not a Mitsuba .vol file (bad magic)")
        if len(head) < _HEADER:
            raise ValueError(f"path: {path!r} has a truncated .vol header ({len(head)} of {_HEADER} bytes)")
        if head[3] != _VERSION:
            raise ValueError(f"path: {path!r} has .vol version {head[3]}, expected {_VERSION}")
        enc, nx, ny, nz, nc = struct.unpack("<5i", head[4:24])
        if enc != _FLOAT32:
            raise ValueError(f"path: {path!r} uses encoding {enc}; only float32 (1) is supported")
        if min(nx, ny, nz, nc) < 1:
            raise ValueError(f"path: {path!r} has an invalid size {(nx, ny, nz, nc)}")
        bb = np.array(struct.unpack("<6f", head[24:48]), dtype=np.float64)
        n = nx * ny * nz * nc
        have = (os.fstat(f.fileno()).st_size - _HEADER) // 4      # before allocating n values
        if have < n:
            raise ValueError(f"path: {path!r} is truncated ({have} of the {n} values its header "
                             f"{(nx, ny, nz, nc)} announces)")
        data = np.fromfile(f, dtype="<f4", count=n)
    data = data.reshape(nz, ny, nx, nc).astype(np.float32)
    if nc == 1:
        data = data[..., 0]
    return (data, (bb[:3], bb[3:])) if with_bbox else data
