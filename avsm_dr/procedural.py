"""Content unlike the smoke of :mod:`avsm_dr.builtin_scenes`: Perlin-Worley noise and four scenes,
:func:`cumulus`, :func:`fog_bank`, :func:`gaussian_blobs` and :func:`tall_column`.

Densities are extinction per world unit, deterministic for ``seed``.  Noise: value-noise fBm
(:func:`fbm`) remapped by Worley cellular noise (Worley 1996, "A cellular texture basis function";
Schneider, "The real-time volumetric cloudscapes of Horizon Zero Dawn", SIGGRAPH 2015 course).
Also the helpers every built-in scene shares: :func:`grid_box`, :func:`check_args`, :func:`square_points`.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

from . import validation as V
from .scene import DirectionalLight, Particles, Scene, check_light, voxel_coords

#: Largest ``size`` (voxels per unit: the plume's grid is then 256 x 384 x 256, its float64
#: noise work arrays ~1.5 GB) and most receivers or particles of a built-in scene.
MAX_SIZE, MAX_POINTS = 256, 1 << 22
#: Normalised outer radii (units of the blob width w) of the nested spheres of one Gaussian blob.
BLOB_SHELLS = (0.5, 1.0, 1.5, 2.25)


def _axes(shape, cells):
    """Per axis: (cell index, fraction in the cell, cell count) of the voxel centres."""
    nmax = max(shape)
    out = []
    for n in shape:
        c = max(1, int(np.ceil(cells * n / nmax)))
        u = (np.arange(n) + 0.5) / n * c
        i0 = np.minimum(np.floor(u).astype(np.int64), c - 1)
        out.append((i0, u - i0, c))
    return out


def value_noise(shape, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth value noise in [0, 1] on a (nz, ny, nx) grid: random values on a lattice of
    ``cells`` cells along the longest axis, interpolated with smoothstep weights."""
    shape = tuple(int(s) for s in shape)
    (iz, fz, cz), (iy, fy, cy), (ix, fx, cx) = _axes(shape, cells)
    wz, wy, wx = (f * f * (3 - 2 * f) for f in (fz, fy, fx))
    lat = rng.random((cz + 1, cy + 1, cx + 1))
    out = np.zeros(shape)
    for dz, dy, dx in itertools.product((0, 1), repeat=3):
        w = ((wz if dz else 1 - wz)[:, None, None] * (wy if dy else 1 - wy)[None, :, None]
             * (wx if dx else 1 - wx)[None, None, :])
        out += w * lat[np.ix_(iz + dz, iy + dy, ix + dx)]
    return out


def fbm(shape, rng: np.random.Generator, octaves: int = 4, cells: int = 3) -> np.ndarray:
    """Value-noise fBm in [0, 1] on a (nz, ny, nx) grid: octaves of :func:`value_noise` at
    doubling lattice frequency (``cells`` cells along the longest axis first) and halving
    amplitude."""
    out, total = np.zeros(tuple(int(s) for s in shape)), 0.0
    for o in range(octaves):
        out += 0.5 ** o * value_noise(shape, cells * 2 ** o, rng)
        total += 0.5 ** o
    return out / total


def worley(shape, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Cellular noise F1 on a (nz, ny, nx) grid: distance (in cell units, clipped to [0, 1]) from
    each voxel centre to the nearest of one random feature point per cell of a lattice of
    ``cells`` cells along the longest axis (the 27 neighbouring cells are searched)."""
    shape = tuple(int(s) for s in shape)
    (iz, fz, cz), (iy, fy, cy), (ix, fx, cx) = _axes(shape, cells)
    pts = rng.random((cz + 2, cy + 2, cx + 2, 3))          # feature point per cell, padded by one cell
    best = np.full(shape, np.inf)
    for dz, dy, dx in itertools.product((-1, 0, 1), repeat=3):
        p = pts[np.ix_(iz + dz + 1, iy + dy + 1, ix + dx + 1)]
        d2 = ((dz + p[..., 0] - fz[:, None, None]) ** 2 + (dy + p[..., 1] - fy[None, :, None]) ** 2
              + (dx + p[..., 2] - fx[None, None, :]) ** 2)
        np.minimum(best, d2, out=best)
    return np.minimum(np.sqrt(best), 1.0)


def perlin_worley(shape, seed: int, cells: int = 3) -> np.ndarray:
    """Perlin-Worley noise in [0, 1]: fBm ``b`` remapped by ``w = 1 - F1`` fBm (3 octaves,
    weights 0.625, 0.25, 0.125): ``(b + w - 1) / w`` clipped, billowy cells with wispy edges."""
    rng = np.random.default_rng(seed)
    b = fbm(shape, rng, octaves=4, cells=cells)
    w = sum(a * (1.0 - worley(shape, cells * 2 ** o, rng)) for o, a in enumerate((0.625, 0.25, 0.125)))
    return np.clip((b + w - 1.0) / np.maximum(w, 1e-6), 0.0, 1.0)


def grid_box(bmin, bmax, size):
    """(shape (nz, ny, nx), X, Y, Z voxel centres) of the box at ``size`` voxels per unit."""
    size = V.integer(size, "size", 4, MAX_SIZE)
    bmin, bmax = np.asarray(bmin, np.float64), np.asarray(bmax, np.float64)
    n = np.maximum(np.round((bmax - bmin) * size).astype(int), 2)
    ax = [bmin[i] + (np.arange(n[i]) + 0.5) * (bmax[i] - bmin[i]) / n[i] for i in range(3)]
    Z, Y, X = np.meshgrid(ax[2], ax[1], ax[0], indexing="ij")
    return (int(n[2]), int(n[1]), int(n[0])), X, Y, Z


def check_args(seed, light, n_receivers, density_scale=1.0):
    """The arguments every scene shares, checked (ValueError names the argument)."""
    V.integer(seed, "seed", 0)
    V.integer(n_receivers, "n_receivers", 1, MAX_POINTS)
    V.real(density_scale, "density_scale", 0.0)
    if light is not None:
        check_light(light)


def square_points(center, u, v, half, k):
    """k points of a regular grid on the square ``center`` +- ``half`` along ``u`` and ``v``."""
    m = int(np.ceil(np.sqrt(k)))
    g = (np.arange(m) + 0.5) / m * 2 - 1
    a, b = (x.reshape(-1, 1)[:k] for x in np.meshgrid(g, g, indexing="ij"))
    return np.asarray(center, float) + half * (a * np.asarray(u, float) + b * np.asarray(v, float))


def _grid_scene(name, dens, bmin, bmax, light, direction, seed, n_receivers, plane, meta):
    """A grid scene: ``light`` (default directional along ``direction``), half the receivers in
    voxels with density > 0 (jittered), half on the square ``plane`` (centre, normal, half size;
    the receiver plane)."""
    light = DirectionalLight(direction=direction) if light is None else light
    bmin, bmax = np.asarray(bmin, float), np.asarray(bmax, float)
    vol = voxel_coords(dens, n_receivers // 2, np.random.default_rng(seed + 1))
    vol = bmin + vol * (bmax - bmin) / np.array(dens.shape[::-1])
    c, nrm, half = (np.asarray(plane[0], float), np.asarray(plane[1], float), plane[2])
    u = np.cross(nrm, (0.0, 0.0, 1.0) if abs(nrm[2]) < 0.9 else (1.0, 0.0, 0.0))
    u /= np.linalg.norm(u)
    rec = np.concatenate([vol, square_points(c, u, np.cross(nrm, u), half, n_receivers - len(vol))])
    return Scene(name, light, rec, density=dens, bbox=(bmin, bmax), receiver_plane=(c, nrm, half),
                 meta=dict(meta, seed=seed))


def cumulus(size: int = 16, seed: int = 0, density_scale: float = 4.0, light=None, n_receivers: int = 1024) -> Scene:
    """A cumulus cloud in the box [-2, 2] x [0, 1.6] x [-1, 1]: a deck with a flat base at
    y = 0.3 and 16 seeded spherical puffs on it (tallest and largest near x = 0), eroded by
    :func:`perlin_worley` noise.  Extinction per unit up to ``density_scale`` (dense cores,
    wispy edges).  Light: a low sun along +x (directional, (1, -0.35, 0.15)), so light-space
    depth spans the cloud's 4-unit length.
    Receivers: half in the cloud, half on the ground y = 0 (the receiver plane).
    """
    check_args(seed, light, n_receivers, density_scale)
    bmin, bmax = (-2.0, 0.0, -1.0), (2.0, 1.6, 1.0)
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    rng = np.random.default_rng(seed)
    k = 16                                                        # puffs, tallest near x = 0
    cx = rng.uniform(-1.6, 1.6, k)
    dome = 1.0 - (cx / 2.0) ** 2
    rad = (0.15 + 0.3 * dome) * rng.uniform(0.7, 1.1, k)
    cy = 0.4 + 0.5 * rad + dome * rng.uniform(0.0, 0.3, k)
    cz = rng.uniform(-0.35, 0.35, k)
    body = 1.0 - (X / 1.7) ** 2 - ((Y - 0.4) / 0.4) ** 2 - (Z / 0.6) ** 2     # the flat-bottomed deck
    for x0, y0, z0, r in zip(cx, cy, cz, rad):
        np.maximum(body, 1.0 - ((X - x0) ** 2 + (Y - y0) ** 2 + (Z - z0) ** 2) / r ** 2, out=body)
    body *= np.clip((Y - 0.3) / 0.06, 0.0, 1.0)                   # flat base
    pw = perlin_worley(shape, seed, cells=6)
    dens = np.clip(2.0 * body - 1.2 * (1.0 - pw), 0.0, 1.0) * density_scale
    return _grid_scene("cumulus", dens.astype(np.float32), bmin, bmax, light, (1.0, -0.35, 0.15), seed, n_receivers,
                       ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 2.0), {"size": size, "density_scale": density_scale})


def fog_bank(size: int = 24, seed: int = 0, density_scale: float = 5.0, light=None, n_receivers: int = 1024) -> Scene:
    """Ground fog in the box [-1.5, 1.5] x [0, 0.8] x [-1.5, 1.5]: extinction per unit
    ``density_scale`` x (0.75 + 0.5 fBm) below a gently rolling top surface y = h(x, z)
    (0.3 .. 0.55), exactly 0 above it: a sharp boundary, one voxel thick.  Light from above
    (directional, (0.35, -1, 0.2)).  Receivers: half in the fog, half on the ground y = 0
    (the receiver plane).
    """
    check_args(seed, light, n_receivers, density_scale)
    bmin, bmax = (-1.5, 0.0, -1.5), (1.5, 0.8, 1.5)
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    rng = np.random.default_rng(seed)
    top = 0.3 + 0.25 * fbm((shape[0], 1, shape[2]), rng, octaves=3, cells=3)
    dens = np.where(Y < top, (0.75 + 0.5 * fbm(shape, rng, cells=5)) * density_scale, 0.0)
    return _grid_scene("fog_bank", dens.astype(np.float32), bmin, bmax, light, (0.35, -1.0, 0.2), seed, n_receivers,
                       ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 1.5), {"size": size, "density_scale": density_scale})


def gaussian_blobs(n: int = 60, seed: int = 0, density_scale: float = 4.0, light=None,
                   n_receivers: int = 1024) -> Scene:
    """``n`` soft particles along a rising, spiralling trail (y = 0.05 .. 1; every sphere
    within the box [-0.75, 0.75] x [-0.1, 1.35] x [-0.75, 0.75]), in emission order: blob i is
    emitted at time i / n, so the list (draw) order runs bottom to top, roughly the light's
    back-to-front order but not sorted (overlapping turns and jitter interleave).

    Blob i has extinction per unit ``s_i exp(-|x - c_i|^2 / (2 w_i^2))``, width w_i growing
    (0.04 .. 0.1), peak s_i = ``density_scale`` x 0.04 / w_i falling with age, stored as 4
    nested uniform spheres (radii :data:`BLOB_SHELLS` x w_i, consecutive in the list).  Each
    shell's level is the profile's mean over its radial interval, so a chord through the centre
    keeps the Gaussian's optical depth but for the 2.4 % beyond +-2.25 w.  ``meta['blob']``:
    the blob of each sphere.  Light from above (directional, (0.3, -1, 0.2)).  Receivers: half
    in the blobs, half on the ground y = -0.1 (the receiver plane).
    """
    V.integer(n, "n", 1, (1 << 20))
    check_args(seed, light, n_receivers, density_scale)
    rng = np.random.default_rng(seed)
    t = np.arange(n) / n
    ang = 4.0 * np.pi * t + rng.uniform(0, 2 * np.pi)
    rad = 0.1 + 0.3 * t
    trail = np.stack([rad * np.cos(ang), 0.05 + 0.95 * t, rad * np.sin(ang)], 1)
    w = 0.04 + 0.06 * t
    centers = trail + 0.4 * w[:, None] * np.clip(rng.standard_normal((n, 3)), -2.0, 2.0)
    peak = density_scale * 0.04 / w
    edges = np.concatenate([[0.0], BLOB_SHELLS])
    cdf = np.array([math.erf(e / math.sqrt(2.0)) for e in edges])
    level = math.sqrt(math.pi / 2.0) * np.diff(cdf) / np.diff(edges)          # mean of exp(-r^2/2) per shell
    step = level - np.append(level[1:], 0.0)                                   # nested spheres add up
    m = len(BLOB_SHELLS)
    blob = np.repeat(np.arange(n), m)
    radii = (w[:, None] * np.asarray(BLOB_SHELLS)[None, :]).ravel()
    dens = (peak[:, None] * step[None, :]).ravel()
    light = DirectionalLight(direction=(0.3, -1.0, 0.2)) if light is None else light
    k_vol = n_receivers // 2
    pick = rng.integers(0, n, k_vol)
    inside = centers[pick] + w[pick, None] * np.clip(rng.standard_normal((k_vol, 3)), -2.0, 2.0)
    ground = square_points((0.0, -0.1, 0.0), (1, 0, 0), (0, 0, 1), 0.6, n_receivers - k_vol)
    return Scene("gaussian_blobs", light, np.concatenate([inside, ground]),
                 particles=Particles(centers=np.repeat(centers, m, axis=0), radii=radii, density=dens),
                 receiver_plane=(np.array([0.0, -0.1, 0.0]), np.array([0.0, 1.0, 0.0]), 0.6),
                 meta={"seed": seed, "n": n, "density_scale": density_scale, "blob": blob})


def tall_column(size: int = 40, seed: int = 0, steps: int | None = None, density_scale: float = 10.0,
                light=None, n_receivers: int = 1024) -> Scene:
    """A smoke column simulated by :func:`avsm_dr.fluid.simulate_plume` in the box [-0.5, 0.5] x
    [0, 3] x [-0.5, 0.5] (twice the simulated plume's height; 40 x 120 x 40 voxels by default),
    ``steps`` (default 3 x size) so that it reaches near the top; extinction per unit = density
    (peak ~1) x ``density_scale``.  Light: directional, (1, -0.3, 0.25).  Receivers: half in the
    smoke, half on the wall x = 0.8 behind it (the receiver plane).
    """
    from .fluid import simulate_plume
    check_args(seed, light, n_receivers, density_scale)
    steps = 3 * V.integer(size, "size", 4) if steps is None else V.integer(steps, "steps", 1)
    bmin, bmax = (-0.5, 0.0, -0.5), (0.5, 3.0, 0.5)
    shape = grid_box(bmin, bmax, size)[0]
    dens = (simulate_plume(shape, steps=steps, seed=seed) * density_scale).astype(np.float32)
    return _grid_scene("tall_column", dens, bmin, bmax, light, (1.0, -0.3, 0.25), seed, n_receivers,
                       ((0.8, 1.5, 0.0), (-1.0, 0.0, 0.0), 1.5),
                       {"size": size, "steps": steps, "density_scale": density_scale})
