"""The dual grid of a voxel grid (the cells between voxel centres, inside which trilinear
density is a cubic along a ray): its edge-padded window, per-block occupancy for block
skipping, and the table of every dual cell's 8 corner voxels (one packet load per crossing).
Shared by the exact traversal (:mod:`.dda`) and the half-voxel march (:mod:`.grid`)."""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ._grid_volume import window_max

#: Most dual cells of the table of 8 corners per cell (:func:`corner_table`, 256 MB in float32);
#: larger windows read the 8 corners with 8 gathers from the padded window.
CORNER_TABLE_CELLS = 1 << 23


def dual_block_max(padded: np.ndarray, block: int) -> np.ndarray:
    """(nbz, nby, nbx) max of the edge-padded window ``padded`` over each dual block.

    ``padded`` is the (wz + 2, wy + 2, wx + 2) window with one layer of repeated edge
    voxels on every side; dual cell ``c`` (window voxel units, -1 <= c <= w - 1) has
    corners ``padded[c + 1]`` and ``padded[c + 2]`` along each axis; block ``B`` holds
    the cells with ``(c + 1) // block == B``, i.e. padded voxels ``[B block, (B + 1) block]``
    (inclusive).  0 means sigma = 0 on the whole closed block.
    """
    return window_max(padded, block, 0, lambda n: (n - 2) // block + 1)


def dual_grid(grid):
    """(padded data (Dr.Jit Float, detached), dual block occupancy (host uint32, flat),
    occupancy shape (nbz, nby, nbx)) of ``grid``, computed once and cached on it."""
    cache = grid.__dict__.setdefault("_dual_cache", {})
    if "pad" not in cache:
        host = np.asarray(dr.detach(grid.data).numpy()).reshape(grid.window_shape)
        pad = np.pad(host, 1, mode="edge")
        occ = dual_block_max(pad, grid.block) > 0
        cache["pad"] = A.to_float(pad, grid.Float)
        cache["occ"] = A.to_uint32(occ.ravel().astype(np.uint32))
        cache["occ_shape"] = occ.shape
    return cache["pad"], cache["occ"], cache["occ_shape"]


def corner_table(grid):
    """The 8 corner voxels of every dual cell, contiguous: cell ``((cz + 1) (wy + 1) + cy + 1)
    (wx + 1) + cx + 1``, corner ``4 k + 2 j + i``, so a crossing reads them with one packet
    load instead of 8 gathers (bit-identical values).  Gathered on the device from the padded
    window of :func:`dual_grid` and cached on the grid; None when it would exceed
    :data:`CORNER_TABLE_CELLS` cells (8 x the window's memory)."""
    cache = grid.__dict__.setdefault("_dual_cache", {})
    if "table" not in cache:
        pad, _, _ = dual_grid(grid)
        wz, wy, wx = grid.window_shape
        n = (wx + 1) * (wy + 1) * (wz + 1)
        table = None
        if n <= CORNER_TABLE_CELLS:
            UInt32 = backend.types().UInt32
            i = dr.arange(UInt32, 8 * n)
            cell, c = i // 8, i % 8
            cz = cell // dr.opaque(UInt32, (wx + 1) * (wy + 1))
            rest = cell - cz * dr.opaque(UInt32, (wx + 1) * (wy + 1))
            cy = rest // dr.opaque(UInt32, wx + 1)
            cx = rest - cy * dr.opaque(UInt32, wx + 1)
            src = (((cz + (c >> 2)) * dr.opaque(UInt32, wy + 2) + cy + ((c >> 1) & 1)) * dr.opaque(UInt32, wx + 2)
                   + cx + (c & 1))
            table = dr.gather(grid.Float, pad, src)
            dr.eval(table)
        cache["table"] = table
    return cache["table"]
