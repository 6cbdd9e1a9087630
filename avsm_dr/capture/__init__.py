"""Light-view capture: scene content -> occluder segments along one light ray per texel.

Example::

    cap = ad.capture(scene, resolution=256)     # cap.segments: Segments of every texel
    texel, depth = cap.lookup(points)           # world points -> (texel, light-space depth)
    T = ad.build("exact", cap.segments).eval(texel, depth)

Every kind of content becomes segments ``[z0, z1]`` with optical depth ``tau``
(Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, sec. 3): density grids
by ray marching (:mod:`.grid`, :mod:`.dda`), particles as chords (:mod:`.particles`), hair
strands as crossings (:mod:`.hair`), opaque blockers as short segments with T = 0
(:mod:`.opaque_map`), seen by the light's camera (:mod:`.camera`).  Each texel's segments are
stored in an insertion order (:data:`ORDERS`), the order an order-dependent build inserts them.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ..geometry import check_bbox
from ..scene import Scene, check_light, validate_blockers
from ..segments import OPAQUE_OPTICAL_DEPTH, Segments
from . import hair as _hair
from . import opaque_map as _opaque_map
from . import particles as _particles
from .assembly import combine
from .camera import CubeCamera, LightCamera, OrthoCamera, PerspectiveCamera, make_camera
from ._grid_lanes import SUBMISSION_BRICK, brick_keys
from .dda import traverse
from .grid import GridVolume, check_method, march
from .hair import load_tfx, procedural_strands

RESOLUTION_RANGE = (64, 1024)
#: Insertion orders of :func:`capture` (``order=``), the default first:
#:
#: * ``"submission"``: the draw order of a renderer, primitive by primitive: opaque blockers
#:   first, in the scene's list order (an engine's opaque pass precedes its transparent
#:   ones); then the density grid brick by brick, bricks of 8^3 voxels
#:   (:data:`~.grid.SUBMISSION_BRICK`) in memory order (x fastest), each brick's segments
#:   along the ray front to back (:func:`~.grid.brick_keys`); then the particles, in
#:   list order (``submission="list"``) or sorted back to front as for alpha blending
#:   (``submission="back_to_front"``, :func:`~.particles.draw_ranks`); then the hair strands
#:   in list order, a strand's crossings in vertex order.
#: * ``"depth"``: front to back (z0 quantised to 32 bits over the depth range; equal values in
#:   content order: grid, particles, hair, blockers); ``"reverse_depth"`` and ``"random"``
#:   (seed ``order_seed``): as :meth:`~avsm_dr.segments.Segments.in_order`.
ORDERS = ("submission", "depth", "reverse_depth", "random")
#: Particle draw orders of ``order="submission"`` (``submission=``), the default first.
SUBMISSIONS = ("list", "back_to_front")
#: Depth that :meth:`Capture.lookup` gives points the map does not cover: the light's own
#: position (spot/point) or reference plane (directional), in front of every segment
#: (segments lie at ray parameters >= 0), so every representation returns T = 1 there.
OUTSIDE_DEPTH = 0.0
#: Finest grid march step, as a fraction of the smallest voxel side (the march's error falls
#: as step^2, its cost grows as 1 / step).
MIN_STEP_FRACTION = 1.0 / 1024


@dataclass(eq=False)
class Capture:
    """Result of :func:`capture`.

    Attributes
    ----------
    segments
        :class:`~avsm_dr.Segments` over ``width * height`` texels (row-major,
        texel ``y * width + x``; cube maps stack their six faces vertically).
    camera, light, resolution, epsilon
        the light camera, ``scene.light`` and the arguments of :func:`capture`.
    step
        the grid march step (None for the exact capture).
    stats
        counts and host/kernel timings of the capture.
    opaque_depth
        (texels,) float64 opaque depth map of ``opaque='separate'`` (+inf: no blocker),
        composed with every representation at lookup; None when inline."""
    segments: Segments
    camera: LightCamera
    light: Any
    resolution: int
    step: float | None
    epsilon: float
    stats: dict = field(default_factory=dict)
    opaque_depth: Any = None

    @property
    def order(self) -> str:
        """``segments.order`` (:data:`ORDERS`)."""
        return self.segments.order

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    def lookup(self, points, continuous: bool = False):
        """World points (K, 3) -> (texel, depth) through the light's camera.

        Returns (K,) int64 texel indices (nearest texel, clamped to the map) and (K,)
        float64 light-space depths; with ``continuous=True`` the (K, 2) float64 map
        coordinates (x, y) in texel units instead of indices, for the filters of
        :mod:`avsm_dr.filtering` (``rep.eval(coords, depth, filter, width=..., height=...)``).

        Points the map does not cover (:meth:`covers`: behind a spot light or outside its
        square frustum, beside a directional map's window; a cube map covers everything)
        are lit, the border convention of shadow mapping: they get the nearest texel
        (coordinates clamped onto the map) and depth :data:`OUTSIDE_DEPTH`, in front of
        every segment, so ``rep.eval`` returns 1 for them."""
        coords, depth, _ = self._lookup(points)
        return (coords if continuous else self.camera.texel_index(coords)), depth

    def _lookup(self, points):
        """(coords, depth, outside) with the border convention of :meth:`lookup` applied."""
        coords, depth = self.camera.project(V.points(points, "points", allow_empty=True))
        out = ~self.camera.covers(coords)
        depth = np.where(out, OUTSIDE_DEPTH, depth)
        coords[out] = np.clip(coords[out], 0.5, [self.width - 0.5, self.height - 0.5])
        return coords, depth, out

    def covers(self, points) -> np.ndarray:
        """(K,) bool: the points lie inside the light camera's map (see :meth:`lookup`)."""
        return ~self._lookup(points)[2]

    def transmittance(self, rep, points, filter: str = "point", radius: float = 1.0):
        """T at world points from representation ``rep`` (built on ``self.segments``);
        exactly 1 at points the map does not cover (:meth:`lookup`)."""
        coords, depth, out = self._lookup(points)
        rep = _opaque_map.compose(rep, self.opaque_depth)
        if filter == "point":
            T = rep.eval(self.camera.texel_index(coords), depth)
        else:
            T = rep.eval(coords, depth, filter=filter, width=self.width, height=self.height, radius=radius)
        if out.any():
            T = dr.select(backend.types().Bool(out), 1.0, T)
        return T

    def __repr__(self) -> str:
        return (f"Capture({type(self.light).__name__}, {self.width}x{self.height}, "
                f"{self.segments!r})")


def _check_order(order, submission, order_seed) -> tuple[str, str, int | None]:
    """(order, submission, seed) after checks; ValueError names the argument."""
    V.one_of(order, "order", ORDERS)
    if submission is not None and order != "submission":
        raise ValueError(f"submission: only order='submission' takes a particle draw order, got "
                         f"submission={submission!r} with order={order!r}")
    if order_seed is not None and order != "random":
        raise ValueError(f"order_seed: only order='random' takes a seed, got order_seed={order_seed!r} "
                         f"with order={order!r}")
    submission = V.one_of(SUBMISSIONS[0] if submission is None else submission, "submission", SUBMISSIONS)
    seed = None if order != "random" else V.integer(0 if order_seed is None else order_seed,
                                                    "order_seed", 0, 2**32 - 1)
    return order, submission, seed


def _check_params(scene, resolution, step, epsilon, opaque_bias, opaque_slope_bias):
    """The checks of :func:`capture`'s scene (type, light, receivers, some content) and
    numeric arguments; ValueError names the argument or the scene's field."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected avsm_dr.scene.Scene, got {type(scene).__name__}")
    check_light(scene.light)
    V.points(scene.receivers, "receivers", allow_empty=True)
    if scene.density is None and scene.particles is None and scene.hair is None and not scene.blockers:
        raise ValueError("scene: no content (density, particles, hair or blockers)")
    V.integer(resolution, "resolution", *RESOLUTION_RANGE)
    if step is not None:
        V.real(step, "step", 0.0, open_min=True)
    V.real(epsilon, "epsilon", 0.0, 1.0, open_min=True, open_max=True)
    if opaque_bias is not None:
        V.real(opaque_bias, "opaque_bias", 0.0, open_min=True)
    V.real(opaque_slope_bias, "opaque_slope_bias", 0.0)


def capture(scene: Scene, resolution: int = 256, step: float | None = None, epsilon: float = 1e-4, *,
            density=None, block: int = 8, keep_zero: bool = False, dtype: str | None = None,
            opaque_bias: float | None = None, opaque_slope_bias: float = 2.0, bounds=None,
            method: str | None = None, opaque: str = "inline", order: str = "submission",
            submission: str | None = None, order_seed: int | None = None) -> Capture:
    """Segments of every shadow-map texel for ``scene`` seen from ``scene.light``.

    Parameters
    ----------
    scene
        the content (density grid, particles, hair, blockers) and the light.
    resolution
        texels per side, 64..1024 (a point light's cube map is resolution x 6 resolution).
    step
        grid march step in world units (method 'march'; default half the smallest voxel side).
    epsilon
        a grid ray stops once its transmittance falls below ``epsilon``.
    density
        overrides ``scene.density``: a (z, y, x) NumPy array, a 3-D Dr.Jit tensor (gradients
        flow to ``segments.optical_depth``), a ``.vol`` path or a prepared :class:`GridVolume`.
    block, keep_zero
        empty-space-skipping block size in voxels; emit zero-density steps inside occupied
        blocks (:func:`.grid.march`).
    dtype
        'float32' (default) | 'float64' (default for float64 Dr.Jit densities).
    opaque_bias, opaque_slope_bias
        constant depth offset (and thickness) of opaque blocker segments (default 1e-4 x
        the content's diagonal), and the slope offset in texel widths (:mod:`.opaque_map`).
    bounds
        (min_xyz, max_xyz) to fit a directional light's map to instead of the content.
    method
        grid capture: 'march' (default, Simpson steps of ``step``) or 'exact' (:mod:`.dda`).
    opaque
        'inline' (blockers are segments of the one map) or 'separate' (a per-texel opaque
        depth map, ``Capture.opaque_depth``, composed at lookup; :mod:`.opaque_map`).
    order, submission, order_seed
        the insertion order of each texel's segments (:data:`ORDERS`, default 'submission',
        recorded as ``Segments.order``); the particles' draw order of 'submission'
        (:data:`SUBMISSIONS`); the seed of 'random', an integer in [0, 2^32) (default 0).

    Returns
    -------
    Capture
        the segments, the light camera and the capture's statistics."""
    _check_params(scene, resolution, step, epsilon, opaque_bias, opaque_slope_bias)
    order, submission, order_seed = _check_order(order, submission, order_seed)
    drawn = order == "submission"          # pieces carry a draw key per segment
    method = check_method(method, step)
    V.one_of(opaque, "opaque", _opaque_map.OPAQUE_MODES)
    stats: dict = {}
    t_start = time.perf_counter()

    # ---- content and its world bounds
    dens = scene.density if density is None else density
    grid = None if dens is None else GridVolume.prepare(dens, scene.bbox, block=block, dtype=dtype,
                                                        skip_empty=not keep_zero)
    if dtype is None:
        dtype = grid.dtype if grid is not None else "float32"
    Float = A.float_type(dtype)
    if grid is not None and grid.dtype != dtype:
        raise ValueError(f"dtype: {dtype!r} differs from the prepared grid's {grid.dtype!r}")
    blockers = validate_blockers(scene.blockers)
    boxes = [item.bounds() for item in (scene.particles, scene.hair, *blockers) if item is not None]
    if grid is not None and (grid.occupied is not None or not boxes):     # an all-zero grid alone: empty map
        boxes.insert(0, grid.occupied if grid.occupied is not None else (grid.bmin, grid.bmax))
    if bounds is not None:
        boxes = [check_bbox(bounds, "bounds", flat=True)]
    bmin, bmax = (np.array([b[k] for b in boxes]) for k in (0, 1))
    pos = getattr(scene.light, "position", None)           # a light at a point (spot, point)
    _check_range(bmin, bmax, pos, dtype)
    diag = float(np.linalg.norm(bmax.max(0) - bmin.min(0))) or 1.0

    # ---- the light
    if pos is not None:
        if grid is not None and np.all((pos >= grid.bmin) & (pos <= grid.bmax)):
            raise ValueError("light: a spot/point light inside the density grid's bbox is not supported "
                             "(move it outside the volume)")
        for i, b in enumerate(blockers):
            if b.contains(pos):
                raise ValueError(f"light: the light lies inside blockers[{i}]")
    camera = make_camera(scene.light, int(resolution), bmin, bmax)
    if grid is not None and method == "march":
        finest = MIN_STEP_FRACTION * float(grid.voxel.min())
        if step is None:
            step = 0.5 * float(grid.voxel.min())
        elif step < finest:
            raise ValueError(f"step: {step:g} is below 1/{round(1 / MIN_STEP_FRACTION)} of the smallest "
                             f"voxel side (finest useful step {finest:.3g}; the march costs one "
                             f"iteration per step per texel)")
    stats["setup_s"] = time.perf_counter() - t_start

    # ---- segments of every content kind: pieces (texel, z0, z1, tau[, draw key])
    pieces = []
    bases = _draw_bases(blockers, grid, scene) if drawn else None

    def add(kind, t0, piece, key, inline=True, **st):
        stats[kind] = {**st, "segments": int(piece[0].size), "seconds": time.perf_counter() - t0}
        if inline and piece[0].size:
            pieces.append(piece + ((key(),) if drawn else ()))
    if grid is not None:
        t0 = time.perf_counter()
        tex, z0, z1, tau, st = (traverse(grid, camera, epsilon, keep_zero=keep_zero, runs=True) if method == "exact"
                                else march(grid, camera, step, epsilon, keep_zero=keep_zero, runs=True))
        add("grid", t0, (tex, z0, z1, tau),
            lambda: dr.opaque(backend.types().UInt32, bases["grid"]) + brick_keys(grid, camera, tex, z0, z1), **st)
    if scene.particles is not None:
        t0 = time.perf_counter()
        *piece, pid = _particles.capture_particles(camera, scene.particles, Float)
        add("particles", t0, tuple(piece),
            lambda: bases["particles"] + _particles.draw_ranks(camera, scene.particles, submission)[pid])
    if scene.hair is not None:
        t0 = time.perf_counter()
        *piece, cid = _hair.capture_hair(camera, scene.hair)
        add("hair", t0, tuple(piece), lambda: bases["hair"] + cid)
    opaque_depth = None
    if blockers:
        t0 = time.perf_counter()
        bias = 1e-4 * diag if opaque_bias is None else float(opaque_bias)
        tex, z0, z1, bid = _opaque_map.capture_opaque(camera, blockers, bias, bias, opaque_slope_bias)
        if opaque == "separate":
            opaque_depth = _opaque_map.depth_map(tex, z0, camera.n_texels)
            pieces = _opaque_map.clip_pieces(pieces, opaque_depth, Float)
        add("opaque", t0, (tex, z0, z1, np.full(tex.size, OPAQUE_OPTICAL_DEPTH)), lambda: bid, opaque == "inline")

    t0 = time.perf_counter()
    seg = combine([p[:4] for p in pieces], camera.n_texels, Float, order,
                  keys=[p[4] for p in pieces] if drawn else None, seed=order_seed)
    stats["order"] = {"order": order, **({"submission": submission} if drawn else {}),
                      **({"order_seed": order_seed} if order == "random" else {})}
    stats["combine_s"] = time.perf_counter() - t0
    stats["total_s"] = time.perf_counter() - t_start
    return Capture(seg, camera, scene.light, int(resolution), step, float(epsilon), stats, opaque_depth)


def _draw_bases(blockers, grid, scene) -> dict:
    """First draw key of each content kind in the ``'submission'`` order (:data:`ORDERS`):
    blockers, then the grid's bricks, then particles, then hair capsules; ValueError naming
    ``order`` when the keys exceed 32 bits."""
    counts = {"opaque": len(blockers),
              "grid": 0 if grid is None else int(np.prod(-(-np.array(grid.shape) // SUBMISSION_BRICK))),
              "particles": 0 if scene.particles is None else int(np.asarray(scene.particles.radii).size),
              "hair": 0 if scene.hair is None else int(np.prod(np.subtract(np.shape(scene.hair.strands)[:2], (0, 1))))}
    total, bases = 0, {}
    for kind, n in counts.items():
        bases[kind], total = total, total + n
    if total > 2**32:
        raise ValueError(f"order: 'submission' numbers {total} primitives "
                         f"(blockers, bricks, particles, hair capsules), more than 2^32")
    return bases


def _check_range(bmin, bmax, position, dtype: str) -> None:
    """Content and light coordinates small enough that depths fit the storage dtype.

    Depths are differences of coordinates (at most 4x the largest magnitude along the
    map's rays), so the coordinates must stay below 1/16 of the dtype's largest value."""
    reach = float(max(np.abs(a).max() for a in (bmin, bmax, position) if a is not None))
    limit = float(np.finfo(dtype).max) / 16
    if not reach <= limit:
        raise ValueError(f"scene: content or light coordinates reach {reach:.3g}; {dtype} depths need "
                         f"coordinates below {limit:.3g}"
                         + (" (use dtype='float64')" if dtype == "float32" else ""))


__all__ = ["capture", "Capture", "GridVolume", "load_tfx", "procedural_strands",
           "LightCamera", "OrthoCamera", "PerspectiveCamera", "CubeCamera",
           "RESOLUTION_RANGE", "OUTSIDE_DEPTH", "MIN_STEP_FRACTION", "ORDERS", "SUBMISSIONS"]
