"""Receiver sets for error measurements: points where a shadow carries information.

* :func:`in_volume`  points in the medium drawn with probability ~ their *contribution* to
  an image, ``sigma_t(x) * T_light(x) * T_view(x)`` (single scattering seen by
  :func:`avsm_dr.groundtruth.default_camera`), by sampling-importance-resampling:
  ``4 n`` candidates drawn ~ density (a voxel ~ its density, a point uniform inside it; or
  a particle ~ extinction x volume, a point uniform inside the sphere), ``n`` of them kept
  without replacement ~ ``T_light * T_view``: float64 ray marches with one-voxel steps (a
  sampling weight, not a measurement) through grid, particles and blockers (hair left out).
* :func:`surface`    a jittered, stratified grid on the scene's receiver plane (the wall or
  ground behind the volume, or the table top).
* ``uniform``        the scene's own ``scene.receivers`` (half in occupied voxels, half on
  a wall: every voxel weighs alike).

Every set is deterministic for a given seed.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from . import groundtruth
from . import validation as V
from .geometry import check_bbox, orthonormal_basis
from .groundtruth.images import receiver_plane
from .groundtruth.tracking import default_step
from .scene import PointLight, Scene

#: Candidates drawn per kept in-volume receiver (sampling-importance-resampling).
CANDIDATES_PER_POINT = 4
#: Estimated host bytes per drawn point of :func:`in_volume` (its candidates and their ray
#: march), checked against :func:`avsm_dr.validation.memory_budget` before drawing.
BYTES_PER_POINT = 2600
#: The receiver sets of :func:`receiver_sets`.
NAMES = ("in_volume", "surface", "uniform")


def _check(scene, n, seed):
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected avsm_dr.scene.Scene, got {type(scene).__name__}")
    V.integer(n, "n", 0)
    V.integer(seed, "seed", 0)
    V.check_memory("n", int(n), lambda m: float(m) * BYTES_PER_POINT, lo=0, what="points")


def _density_candidates(scene: Scene, m: int, rng) -> np.ndarray:
    """(m, 3) points drawn proportionally to the extinction of the grid or the particles."""
    if scene.density is not None and float(np.max(scene.density)) > 0:
        d = np.asarray(scene.density, np.float64)
        lo, hi = (np.asarray(b, np.float64) for b in scene.bbox)
        p = d.ravel() / d.sum()
        kz, ky, kx = np.unravel_index(rng.choice(p.size, size=m, p=p), d.shape)
        h = (hi - lo) / np.array(d.shape[::-1])
        return lo + (np.stack([kx, ky, kz], 1) + rng.random((m, 3))) * h
    if scene.particles is not None:
        c, r, s = (np.asarray(getattr(scene.particles, k), np.float64) for k in ("centers", "radii", "density"))
        w = s * r ** 3
        pick = rng.choice(w.size, size=m, p=w / w.sum())
        u = rng.standard_normal((m, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        return c[pick] + u * (r[pick] * rng.random(m) ** (1 / 3))[:, None]
    return np.zeros((0, 3))


def visibility(scene: Scene, points, origin=None) -> np.ndarray:
    """(K,) float64 transmittance from ``scene.light`` (``origin=None``) or from the point
    ``origin`` to each point, through grid, particles and blockers (hair left out), by a
    float64 ray march with one-voxel steps."""
    p = V.points(points, "points", allow_empty=True)
    sc = dataclasses.replace(scene, hair=None)
    if origin is not None:
        sc = dataclasses.replace(sc, light=PointLight(position=V.vec3(origin, "origin")))
    if p.shape[0] and sc.density is None and sc.particles is None and not sc.blockers:
        return np.ones(p.shape[0])
    return marched(sc, p, 1.0)


def voxel_step(scene: Scene, fraction: float) -> float | None:
    """``fraction`` of the smallest voxel side of ``scene``'s grid (None without a grid)."""
    if scene.density is None:
        return None
    return default_step(scene.density, *(np.asarray(b, np.float64) for b in scene.bbox), fraction)


def marched(scene: Scene, points, step_fraction: float) -> np.ndarray:
    """(K,) float64 transmittance from ``scene.light`` to the (K, 3) ``points``: the ground
    truth's float64 ray march (``method='raymarch'``), step ``step_fraction`` voxels."""
    p = np.asarray(points, np.float64)
    if p.shape[0] == 0:
        return np.zeros(0)
    return groundtruth.transmittance(scene, p, method="raymarch", step=voxel_step(scene, step_fraction))[0]


def lattice(bbox, counts) -> np.ndarray:
    """(nx*ny*nz, 3) float64 cell-centred lattice of points inside ``bbox = (min_xyz, max_xyz)``,
    ``counts = (nx, ny, nz)`` cells per axis (x slowest)."""
    lo, hi = check_bbox(bbox)
    n = [int(V.integer(c, "counts", 1)) for c in counts]
    if len(n) != 3:
        raise ValueError(f"counts: expected 3 cell counts, got {len(n)}")
    axes = [lo[i] + (np.arange(n[i]) + 0.5) / n[i] * (hi[i] - lo[i]) for i in range(3)]
    return np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], axis=1)


def in_volume(scene: Scene, n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) points in the medium, drawn ~ density x T_light x T_view (module docstring; no
    view term for a scene without a receiver plane).  Returns (0, 3) for a scene with
    neither grid nor particles.
    """
    _check(scene, n, seed)
    rng = np.random.default_rng(seed)
    cand = _density_candidates(scene, CANDIDATES_PER_POINT * n, rng)
    if cand.shape[0] == 0 or n == 0:
        return np.zeros((0, 3))
    w = visibility(scene, cand)
    if scene.receiver_plane is not None:
        w = w * visibility(scene, cand, origin=groundtruth.default_camera(scene).origin)
    if not np.any(w > 0):
        w = np.ones_like(w)
    # keep n of the candidates, without replacement, with probability ~ w
    k = min(n, int(np.count_nonzero(w > 0)))
    keep = rng.choice(w.size, size=k, replace=False, p=w / w.sum())
    return cand[np.sort(keep)]


def surface(scene: Scene, n: int, seed: int = 0) -> np.ndarray:
    """(m*m, 3) points, m = ceil(sqrt(n)), one jittered point per cell of an m x m grid
    over the receiver plane's square (centre, normal, half size); (0, 3) without a plane."""
    _check(scene, n, seed)
    if scene.receiver_plane is None or n == 0:
        return np.zeros((0, 3))
    c, normal, half = receiver_plane(scene)
    u, v, _ = orthonormal_basis(normal)
    m = int(np.ceil(np.sqrt(n)))
    rng = np.random.default_rng(seed)
    a, b = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    s = (a.reshape(-1) + rng.random(m * m)) / m * 2 - 1
    t = (b.reshape(-1) + rng.random(m * m)) / m * 2 - 1
    return c + half * (s[:, None] * u + t[:, None] * v)


def receiver_sets(scene: Scene, n_volume: int = 4096, n_surface: int = 1024, seed: int = 0,
                  names=NAMES) -> dict[str, np.ndarray]:
    """{'in_volume': :func:`in_volume`, 'surface': :func:`surface`, 'uniform':
    ``scene.receivers``} of the sets ``names`` (in their order); empty sets are left out."""
    make = {"in_volume": lambda: in_volume(scene, n_volume, seed),
            "surface": lambda: surface(scene, n_surface, seed),
            "uniform": lambda: V.points(scene.receivers, "receivers", allow_empty=True)}
    out = {k: make[V.one_of(k, "names", NAMES)]() for k in names}
    return {k: v for k, v in out.items() if v.shape[0] > 0}
