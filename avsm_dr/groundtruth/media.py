"""Mitsuba media of a density grid, and the NumPy statement of their lookup convention.

The grid becomes a ``heterogeneous`` medium whose ``sigma_t`` is a ``gridvolume`` (the (z, y, x)
float32 array, ``to_world`` mapping the unit cube onto ``bbox``, trilinear, ``scale = 1``): the
convention of :mod:`avsm_dr.scene`, which :func:`sample_density` states in NumPy (the tests check
it against Mitsuba).  Mitsuba is imported, and the variant chosen (:func:`mitsuba`), per call.
"""
from __future__ import annotations

import itertools

import numpy as np

from .. import backend
from .. import validation as V
from ..geometry import check_bbox


def mitsuba():
    """The ``mitsuba`` module with this package's variant set.

    ``cuda_ad_rgb`` when the Dr.Jit backend is CUDA, else ``llvm_ad_rgb``; the
    variant is changed only when it differs (Mitsuba and Dr.Jit share the process).
    """
    import mitsuba as mi
    want = "cuda_ad_rgb" if backend.get_backend() == "cuda" else "llvm_ad_rgb"
    if mi.variant() != want:
        mi.set_variant(want)
    return mi


def check_grid(density, bbox):
    """(grid float32 (nz, ny, nx), lo (3,), hi (3,)) after checks; ValueError names the field."""
    if density is None:
        raise ValueError("density: the scene has no density grid")
    g32 = V.density_grid(density, "density", np.float32)      # Mitsuba's grid is float32
    if bbox is None:
        raise ValueError("bbox: a density grid needs bbox = (min_xyz, max_xyz)")
    lo, hi = check_bbox(bbox)
    return g32, lo, hi


def grid_to_world(mi, lo, hi):
    """ScalarTransform4f mapping the unit cube onto the box [lo, hi]."""
    return (mi.ScalarTransform4f().translate([float(v) for v in lo])
            @ mi.ScalarTransform4f().scale([float(v) for v in hi - lo]))


def _volume_dict(mi, grid, lo, hi) -> dict:
    return {"type": "gridvolume", "grid": mi.VolumeGrid(np.ascontiguousarray(grid[..., None], dtype=np.float32)),
            "to_world": grid_to_world(mi, lo, hi), "filter_type": "trilinear"}


def medium_dict(mi, grid, lo, hi, albedo: float) -> dict:
    """``load_dict`` description of the heterogeneous medium (sigma_t = grid, scale 1)."""
    return {"type": "heterogeneous", "sigma_t": _volume_dict(mi, grid, lo, hi), "albedo": float(albedo), "scale": 1.0}


def mitsuba_volume(density, bbox):
    """The ``gridvolume`` for ``density`` (nz, ny, nx) over ``bbox`` (trilinear; Mitsuba clamps
    lookups to the edge even outside the box, where its media are never evaluated)."""
    mi = mitsuba()
    grid, lo, hi = check_grid(density, bbox)
    return mi.load_dict(_volume_dict(mi, grid, lo, hi))


def sample_density(density, bbox, points) -> np.ndarray:
    """sigma_t at world ``points`` (K, 3): (K,) float64, voxel (k, j, i) at ``lo + ((i, j, k) +
    0.5) * (hi - lo) / (nx, ny, nz)``, trilinear between, clamped to the edge inside the box, 0
    outside (:mod:`avsm_dr.scene`)."""
    g, lo, hi = check_grid(density, bbox)
    return sample_grid(g.astype(np.float64), lo, hi, V.points(points))


def sample_grid(g, lo, hi, p) -> np.ndarray:
    """:func:`sample_density` on checked input: float64 grid ``g``, box ``lo``/``hi``, points (K, 3)."""
    nz, ny, nx = g.shape
    n = np.array([nx, ny, nz], np.float64)
    u = (p - lo) / (hi - lo) * n - 0.5
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    u = np.clip(u, 0.0, n - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), np.maximum(n.astype(np.int64) - 2, 0))
    f = u - i0
    i1 = np.minimum(i0 + 1, n.astype(np.int64) - 1)
    out = np.zeros(p.shape[0])
    for cz, cy, cx in itertools.product((0, 1), repeat=3):
        kz, ky, kx = (i1[:, a] if c else i0[:, a] for a, c in ((2, cz), (1, cy), (0, cx)))
        wz, wy, wx = (f[:, a] if c else 1 - f[:, a] for a, c in ((2, cz), (1, cy), (0, cx)))
        out += wz * wy * wx * g[kz, ky, kx]
    return np.where(inside, out, 0.0)
