"""A compact stable-fluids smoke solver on Dr.Jit, for volumes with sharp structure.

Stam, "Stable Fluids", SIGGRAPH 1999 (sec. 2-3), on a staggered (MAC) grid with the
smoke forces of Fedkiw, Stam and Jensen, "Visual Simulation of Smoke", SIGGRAPH 2001
(sec. 3: buoyancy, vorticity confinement).  Grid units: cell side h = 1, velocities in
cells per time unit; one lane per sample, every kernel a gather.  Cell (k, j, i) of the
(nz, ny, nx) grid is centred at (i + 1/2, j + 1/2, k + 1/2) and holds density ``d`` and
pressure ``p``; ``u`` lies on x-faces (nz, ny, nx + 1) at (i, j + 1/2, k + 1/2), ``v`` on
y-faces (nz, ny + 1, nx), ``w`` on z-faces (nz + 1, ny, nx).  The box is closed: boundary
faces carry zero normal velocity (solid walls).

One step of size ``dt`` (:meth:`StableFluids.step`)::

    sources      d = max(d, s * source),  v = v_s inside the source          (injection)
    advect       q(x) = q(x - dt * u(x - dt/2 * u(x)))   for q in u, v, w, d  (RK2 backtrace,
                                                        trilinear, clamped to the box)
    forces       v += dt * buoyancy * d              (on y-faces, d averaged)
                 u += dt * eps * (N x omega)         N = grad|omega| / |grad|omega||
    project      L p = div u,   u -= grad p          (7-point Laplacian, Neumann walls,
                                                        red-black SOR, warm-started)

``div u`` at a cell is the sum of its face fluxes, ``grad p`` on an interior face the
difference of its two cells, so ``div(grad p) = L p`` exactly (after the solve ``div u`` is
the Poisson residual).  Semi-Lagrangian advection keeps ``d >= 0`` and is unconditionally
stable, neither exactly conservative nor free of numerical diffusion.

:func:`simulate_plume` and :func:`simulate_plume_sequence` (cached on disk) run a buoyant plume
from a seeded, wobbling source.
"""
from __future__ import annotations

import hashlib
import inspect
import itertools
import json
import os
import warnings
from pathlib import Path

import drjit as dr
import numpy as np

from . import backend
from . import validation as V

#: Default cache folder of :func:`simulate_plume` (``$AVSM_DR_CACHE`` overrides it).
CACHE_DIR = Path(os.environ.get("AVSM_DR_CACHE", Path.home() / ".cache" / "avsm_dr"))


def _check_shape(shape) -> tuple[int, int, int]:
    if not (isinstance(shape, (tuple, list)) and len(shape) == 3):
        raise ValueError(f"shape: expected 3 integers (nz, ny, nx), got {shape!r}")
    return tuple(V.integer(v, "shape", 4, 1024) for v in shape)


class _Layout:
    """Sample positions of one field: dims (Z, Y, X), offset (ox, oy, oz) in cell units;
    sample (k, j, i) sits at (i + ox, j + oy, k + oz)."""

    def __init__(self, m, dims, offset):
        self.m = m
        self.dims = dims
        self.offset = offset
        Z, Y, X = dims
        self.n = Z * Y * X
        idx = dr.arange(m.UInt32, self.n)
        self.i = idx % X
        self.j = (idx // X) % Y
        self.k = idx // (X * Y)
        dr.eval(self.i, self.j, self.k)
        self.pos = [m.Float(c) + o for c, o in zip((self.i, self.j, self.k), offset)]
        dr.eval(self.pos)

    def index(self, i, j, k):
        Z, Y, X = self.dims
        return (k * Y + j) * X + i

    def neighbour(self, field, di=0, dj=0, dk=0):
        """``field`` at (i + di, j + dj, k + dk), indices clamped to the grid."""
        m = self.m
        ijk = (dr.clip(m.Int32(c) + dc, 0, n - 1) for c, dc, n in zip((self.i, self.j, self.k), (di, dj, dk),
                                                                       self.dims[::-1]))
        return dr.gather(m.Float, field, m.UInt32(self.index(*ijk)))

    def sample(self, field, x, y, z, bounds: bool = False):
        """Trilinear interpolation of ``field`` at positions (x, y, z) (cell units), clamped
        to the samples' hull (constant extension past the outermost samples); with
        ``bounds``: (value, min, max) of the 8 samples used."""
        m = self.m
        Z, Y, X = self.dims
        idx, frac = [], []
        for p, o, n in ((x, self.offset[0], X), (y, self.offset[1], Y), (z, self.offset[2], Z)):
            c = dr.clip(p - o, 0.0, n - 1.0)
            i0 = dr.minimum(m.UInt32(dr.floor(c)), n - 2)
            idx.append(i0)
            frac.append(c - m.Float(i0))
        (i0, j0, k0), (fx, fy, fz) = idx, frac
        out = m.Float(0.0)
        lo = hi = None
        for dk, dj, di in itertools.product((0, 1), repeat=3):
            wz, wy, wx = (f if c else 1.0 - f for f, c in ((fz, dk), (fy, dj), (fx, di)))
            v = dr.gather(m.Float, field, self.index(i0 + di, j0 + dj, k0 + dk))
            out += wz * wy * wx * v
            lo = v if lo is None else dr.minimum(lo, v)
            hi = v if hi is None else dr.maximum(hi, v)
        return (out, lo, hi) if bounds else out


class StableFluids:
    """Smoke on a closed (nz, ny, nx) MAC grid (module docstring); fields are Dr.Jit
    ``Float`` arrays in z-major order: ``u``, ``v``, ``w`` (face velocities), ``d``
    (density, cell centres), ``p`` (last pressure, the warm start of the next solve).

    buoyancy: upward acceleration per unit density.  vorticity: confinement strength
    eps (0 = off).  iterations: red-black SOR sweeps per projection; omega: the SOR
    relaxation factor in (0, 2).  maccormack: MacCormack density advection (:meth:`advect`)."""

    def __init__(self, shape, buoyancy: float = 0.25, vorticity: float = 0.3, iterations: int = 40,
                 omega: float = 1.8, maccormack: bool = True):
        self.shape = _check_shape(shape)
        self.buoyancy = V.real(buoyancy, "buoyancy")
        self.vorticity = V.real(vorticity, "vorticity", 0.0)
        self.iterations = V.integer(iterations, "iterations", 0)
        self.omega = V.real(omega, "omega", 0.0, 2.0, open_min=True, open_max=True)
        self.maccormack = bool(maccormack)
        m = self.m = backend.types()
        nz, ny, nx = self.shape
        self.C = _Layout(m, (nz, ny, nx), (0.5, 0.5, 0.5))
        self.U = _Layout(m, (nz, ny, nx + 1), (0.0, 0.5, 0.5))
        self.V = _Layout(m, (nz, ny + 1, nx), (0.5, 0.0, 0.5))
        self.W = _Layout(m, (nz + 1, ny, nx), (0.5, 0.5, 0.0))
        self._faces = (self.U, self.V, self.W)
        self.u, self.v, self.w = (dr.zeros(m.Float, L.n) for L in self._faces)
        self.d = dr.zeros(m.Float, self.C.n)
        self.p = dr.zeros(m.Float, self.C.n)
        C = self.C
        # Neumann walls: a cell's stencil counts only neighbours inside the box
        self._has = [(C.i > 0, -1, 0, 0), (C.i < nx - 1, 1, 0, 0), (C.j > 0, 0, -1, 0),
                     (C.j < ny - 1, 0, 1, 0), (C.k > 0, 0, 0, -1), (C.k < nz - 1, 0, 0, 1)]
        self._count = sum((dr.select(has, 1.0, 0.0) for has, *_ in self._has), m.Float(0.0))
        self._red = ((C.i + C.j + C.k) & 1) == 0
        self._interior = [(c > 0) & (c < n) for c, n in ((self.U.i, nx), (self.V.j, ny), (self.W.k, nz))]
        dr.eval(self._count, self._red, self._interior)

    # ================================================================ state
    def set_density(self, density) -> None:
        """Replace ``d`` by a (nz, ny, nx) array."""
        a = V.density_grid(density, "density", np.float32)
        if a.shape != self.shape:
            raise ValueError(f"density: expected shape {self.shape}, got {a.shape}")
        self.d = self.m.Float(np.ascontiguousarray(a).ravel())

    def set_velocity(self, u, v, w) -> None:
        """Replace the face velocities (shapes (nz, ny, nx+1), (nz, ny+1, nx), (nz+1, ny, nx));
        boundary faces are set to 0 (closed box)."""
        out = []
        for name, a, L, inner in zip("uvw", (u, v, w), self._faces, self._interior):
            a = V.array(a, name, np.float32)
            if a.shape != L.dims:
                raise ValueError(f"{name}: expected shape {L.dims}, got {a.shape}")
            out.append(dr.select(inner, self.m.Float(np.ascontiguousarray(a).ravel()), 0.0))
        self.u, self.v, self.w = out
        dr.eval(self.u, self.v, self.w)

    def density(self) -> np.ndarray:
        """(nz, ny, nx) float32 copy of the density."""
        return np.asarray(self.d.numpy(), np.float32).reshape(self.shape)

    def divergence(self):
        """Net outflow of each cell, sum of face fluxes (Float, one lane per cell)."""
        C, U, V, W = self.C, self.U, self.V, self.W
        m = self.m
        g = lambda f, L, i, j, k: dr.gather(m.Float, f, L.index(i, j, k))  # noqa: E731
        return (g(self.u, U, C.i + 1, C.j, C.k) - g(self.u, U, C.i, C.j, C.k)
                + g(self.v, V, C.i, C.j + 1, C.k) - g(self.v, V, C.i, C.j, C.k)
                + g(self.w, W, C.i, C.j, C.k + 1) - g(self.w, W, C.i, C.j, C.k))

    # =============================================================== phases
    def add_source(self, mask, amount: float, velocity) -> None:
        """Injection: ``d = max(d, amount * mask)``; faces next to a cell with mask > 0 get
        ``velocity`` (vx, vy, vz) blended by the mask.  mask: (nz, ny, nx) in [0, 1]."""
        mask = V.array(mask, "mask", np.float32)
        if mask.shape != self.shape or mask.size and not (mask.min() >= 0 and mask.max() <= 1):
            raise ValueError(f"mask: expected values in [0, 1] of shape {self.shape}, got shape {mask.shape}")
        amount = V.real(amount, "amount", 0.0)
        velocity = V.vec3(velocity, "velocity")
        mk = self.m.Float(np.ascontiguousarray(np.asarray(mask, np.float32)).ravel())
        self.d = dr.maximum(self.d, amount * mk)
        self._update_faces(lambda a, L, f: f + self._to_faces(mk, L, a) * (float(velocity[a]) - f), self.d)

    def add_forces(self, dt: float) -> None:
        """Buoyancy on y-faces and vorticity confinement (Fedkiw et al. 2001, sec. 3.2)."""
        db = self._to_faces(self.d, self.V, 1)         # density averaged over the two cells beside a y-face
        self.v = dr.select(self._interior[1], self.v + dt * self.buoyancy * db, 0.0)
        if self.vorticity > 0:
            f = self._confinement()
            self._update_faces(lambda a, L, q: q + dt * self._to_faces(f[a], L, a))
        dr.eval(self.u, self.v, self.w)

    def _update_faces(self, fn, *also) -> None:
        """``u, v, w = fn(axis, layout, field)`` on interior faces, 0 on the walls (a closed box);
        evaluated together with ``also``.  ``fn`` of a cell-centred field uses :meth:`_to_faces`."""
        self.u, self.v, self.w = (dr.select(inner, fn(a, L, f), 0.0) for a, (L, f, inner) in
                                  enumerate(zip(self._faces, (self.u, self.v, self.w), self._interior)))
        dr.eval(*also, self.u, self.v, self.w)

    def _confinement(self):
        """eps * (N x omega) at cell centres; omega = curl u by central differences."""
        C = self.C
        uc = [L.sample(q, *C.pos) for L, q in zip(self._faces, (self.u, self.v, self.w))]
        dr.eval(uc)

        def dd(f, axis):       # central difference along axis (one-sided-ish at walls via clamping)
            s = [int(a == axis) for a in range(3)]
            return 0.5 * (C.neighbour(f, *s) - C.neighbour(f, *[-x for x in s]))
        b, c = (1, 2, 0), (2, 0, 1)            # (a, b[a], c[a]) cyclic: omega_a = d_b u_c - d_c u_b
        om = [dd(uc[c[a]], b[a]) - dd(uc[b[a]], c[a]) for a in range(3)]
        dr.eval(om)
        mag = dr.sqrt(om[0] ** 2 + om[1] ** 2 + om[2] ** 2)
        dr.eval(mag)
        g = [dd(mag, a) for a in range(3)]
        inv = dr.rcp(dr.sqrt(g[0] ** 2 + g[1] ** 2 + g[2] ** 2) + 1e-6)
        n = [x * inv for x in g]
        f = [self.vorticity * (n[b[a]] * om[c[a]] - n[c[a]] * om[b[a]]) for a in range(3)]
        dr.eval(f)
        return f

    def _beside(self, fc, L, axis):
        """Cell-centred ``fc`` in the two cells beside each face of layout ``L`` (normal
        ``axis``: 0 = x): (lower, upper), indices clamped at the walls."""
        m, C = self.m, self.C
        ijk = [L.i, L.j, L.k]
        lo, hi = list(ijk), list(ijk)
        lo[axis] = m.UInt32(dr.maximum(m.Int32(ijk[axis]) - 1, 0))
        hi[axis] = dr.minimum(ijk[axis], C.dims[2 - axis] - 1)
        return dr.gather(m.Float, fc, C.index(*lo)), dr.gather(m.Float, fc, C.index(*hi))

    def _to_faces(self, fc, L, axis):
        """Cell-centred ``fc`` averaged onto the faces of layout ``L``."""
        lo, hi = self._beside(fc, L, axis)
        return 0.5 * (lo + hi)

    def advect(self, dt: float) -> None:
        """Semi-Lagrangian advection of u, v, w and d by the current velocity (RK2
        backtrace, trilinear lookups; Stam 1999 sec. 2.2).  With ``maccormack`` the density
        gets the MacCormack correction ``d1 + (d - A^-1 d1) / 2`` (``d1 = A d``, ``A^-1``:
        advection backwards in time), clamped to the 8 samples of the forward lookup
        (Selle et al., "An Unconditionally Stable MacCormack Method", 2008, sec. 3-4):
        sharper fronts, still >= 0 and within the old extrema."""
        U, V, W, C = self.U, self.V, self.W, self.C
        u, v, w = self.u, self.v, self.w

        def trace(L, h):
            x, y, z = L.pos
            vx, vy, vz = U.sample(u, x, y, z), V.sample(v, x, y, z), W.sample(w, x, y, z)
            xm, ym, zm = x - 0.5 * h * vx, y - 0.5 * h * vy, z - 0.5 * h * vz
            vx, vy, vz = U.sample(u, xm, ym, zm), V.sample(v, xm, ym, zm), W.sample(w, xm, ym, zm)
            return x - h * vx, y - h * vy, z - h * vz

        new_u, new_v, new_w = (dr.select(inner, L.sample(q, *trace(L, dt)), 0.0)
                               for L, q, inner in zip((U, V, W), (u, v, w), self._interior))
        d1, lo, hi = C.sample(self.d, *trace(C, dt), bounds=True)
        if self.maccormack:
            dr.eval(d1, lo, hi)
            back = C.sample(d1, *trace(C, -dt))
            d1 = dr.clip(d1 + 0.5 * (self.d - back), lo, hi)
        dr.eval(new_u, new_v, new_w, d1)
        self.u, self.v, self.w, self.d = new_u, new_v, new_w, d1

    def project(self, iterations: int | None = None) -> None:
        """Pressure projection: red-black SOR sweeps on ``L p = div u`` (warm start: the
        last ``p``), then ``u -= grad p`` on interior faces (Stam 1999 sec. 2.3)."""
        m, C = self.m, self.C
        iters = self.iterations if iterations is None else int(iterations)
        div = self.divergence()
        dr.eval(div)
        p = self.p
        w = self.omega
        for _ in range(iters):
            for colour in (True, False):
                s = sum((dr.select(has, C.neighbour(p, *ijk), 0.0) for has, *ijk in self._has), m.Float(0.0))
                gs = (s - div) / self._count
                p = dr.select(self._red == colour, p + w * (gs - p), p)
                dr.eval(p)
        self.p = p

        def minus_grad(a, L, f):            # grad p on a face: the difference of its two cells
            lo, hi = self._beside(p, L, a)
            return f - (hi - lo)
        self._update_faces(minus_grad)

    def step(self, dt: float) -> None:
        """advect, forces, project (Bridson, "Fluid Simulation for Computer Graphics", 2015,
        sec. 2.4); sources are the caller's, before the step."""
        dt = V.real(dt, "dt", 0.0, open_min=True)
        self.advect(dt)
        self.add_forces(dt)
        self.project()


# ==================================================================== the plume
#: Bump when the solver's numbers change in a way the source hash would not show.
_VERSION = 1


def _source_mask(shape, centre, radius: float, height: float) -> np.ndarray:
    """(nz, ny, nx) in [0, 1]: a disc of ``radius`` cells around ``centre`` (x, z) in the
    bottom ``height`` cells, with a one-cell linear edge."""
    nz, ny, nx = shape
    z, y, x = np.meshgrid(np.arange(nz) + 0.5, np.arange(ny) + 0.5, np.arange(nx) + 0.5, indexing="ij")
    r = np.hypot(x - centre[0], z - centre[1])
    return (np.clip(radius - r + 0.5, 0.0, 1.0) * (y < height)).astype(np.float32)


def _cached(cache, prefix: str, params: dict, shape: tuple, compute) -> np.ndarray:
    """``compute()``, cached (``cache``: True = :data:`CACHE_DIR`, a folder, or False = off) as
    ``<prefix>_<key>.npy``, key = hash of ``params`` and this module's source, written atomically
    (a temporary file, then a rename).  A file that is not a finite, non-negative float32 array of
    ``shape`` (unreadable, pickled, wrong) is warned about by name, recomputed and overwritten."""
    path = None
    if cache is not False:
        h = hashlib.sha256(json.dumps(params, sort_keys=True).encode())
        h.update(Path(__file__).read_bytes())
        path = (CACHE_DIR if cache is True else Path(cache)) / f"{prefix}_{h.hexdigest()[:20]}.npy"
    if path is not None and path.exists():
        try:
            out = np.load(path, allow_pickle=False)
            if not isinstance(out, np.ndarray) or out.dtype != np.float32 or out.shape != tuple(shape):
                raise ValueError(f"holds {getattr(out, 'dtype', type(out).__name__)} "
                                 f"{getattr(out, 'shape', '')}, expected float32 {tuple(shape)}")
            if not np.all(np.isfinite(out)) or (out.size and out.min() < 0):
                raise ValueError("holds NaN, inf or negative densities")
            return out
        except Exception as exc:
            warnings.warn(f"fluid: ignoring the cached plume {str(path)!r} ({exc}); recomputing",
                          RuntimeWarning, stacklevel=3)
    out = compute()
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
        np.save(tmp, out)
        os.replace(tmp, path)
    return out


def simulate_plume(shape=(32, 48, 32), steps: int = 40, seed: int = 0, dt: float = 1.0,
                   buoyancy: float = 0.25, vorticity: float = 0.3, source_speed: float = 1.5,
                   source_radius: float | None = None, wobble: float = 0.35, iterations: int = 40,
                   cache: bool | str | Path = True) -> np.ndarray:
    """Density (nz, ny, nx) float32 >= 0 of a buoyant smoke plume after ``steps`` steps of
    :class:`StableFluids` (Stam 1999; Fedkiw et al. 2001), deterministic for ``seed``.

    Each step injects density 1 (times a seeded per-voxel factor in [0.5, 1]) and upward
    velocity ``source_speed`` (cells per time unit) in a disc of ``source_radius`` cells
    (default nx / 8) on the floor, whose centre and horizontal velocity wander by
    ``wobble`` (seeded random walk), then :meth:`StableFluids.step` with ``dt``: advection
    (MacCormack for the density), forces (``buoyancy`` per unit density, vorticity
    confinement ``vorticity``), projection (``iterations`` SOR sweeps).
    cache: as in :func:`simulate_plume_sequence`, of which this is the one frame ``start = steps``."""
    solver = dict(dt=dt, buoyancy=buoyancy, vorticity=vorticity, source_speed=source_speed,
                  source_radius=source_radius, wobble=wobble, iterations=iterations)
    if V.integer(steps, "steps", 0) == 0:
        return np.zeros(_plume_params(shape, seed, **solver)["shape"], np.float32)
    return simulate_plume_sequence(shape, 1, steps, 1, seed, cache, **solver)[0]


# ============================================================ an animation
def _plume_params(shape, seed, dt, buoyancy, vorticity, source_speed, source_radius, wobble, iterations):
    """Checked parameters of the plume, source radius resolved."""
    shape = _check_shape(shape)
    radius = shape[2] / 8 if source_radius is None else V.real(source_radius, "source_radius", 0.0, open_min=True)
    return dict(shape=list(shape), seed=V.integer(seed, "seed", 0), dt=V.real(dt, "dt", 0.0, open_min=True),
                buoyancy=V.real(buoyancy, "buoyancy"), vorticity=V.real(vorticity, "vorticity", 0.0),
                source_speed=V.real(source_speed, "source_speed", 0.0, open_min=True), source_radius=radius,
                wobble=V.real(wobble, "wobble", 0.0), iterations=V.integer(iterations, "iterations", 0))


def _plume_frames(p):
    """Endless generator of the plume's (nz, ny, nx) float32 density after each step (the k-th
    is ``simulate_plume(steps=k)``); ``p``: the parameters of :func:`_plume_params`."""
    shape, radius = tuple(p["shape"]), p["source_radius"]
    nz, ny, nx = shape
    sim = StableFluids(shape, buoyancy=p["buoyancy"], vorticity=p["vorticity"], iterations=p["iterations"])
    rng = np.random.default_rng(p["seed"])
    centre = np.array([nx / 2, nz / 2], np.float64)
    kick = np.zeros(2)
    height = max(2.0, ny / 16)
    while True:
        centre = np.clip(centre + p["wobble"] * rng.standard_normal(2), nx / 2 - 2 * radius, nx / 2 + 2 * radius)
        kick = 0.7 * kick + p["wobble"] * rng.standard_normal(2)
        mask = _source_mask(shape, centre, radius, height) * rng.uniform(0.5, 1.0, shape).astype(np.float32)
        sim.add_source(mask, 1.0, (kick[0], p["source_speed"], kick[1]))
        sim.step(p["dt"])
        yield np.maximum(sim.density(), 0.0)


def simulate_plume_sequence(shape=(32, 48, 32), frames: int = 48, start: int = 40, stride: int = 1,
                            seed: int = 0, cache: bool | str | Path = True, progress: bool = False,
                            **kwargs) -> np.ndarray:
    """Animation of the plume of :func:`simulate_plume`: (frames, nz, ny, nx) float32, frame f
    the density after ``start + f * stride`` steps (frame 0 = ``simulate_plume(steps=start)``),
    one solver run for all frames.  kwargs: the solver parameters of :func:`simulate_plume`.
    cache: True (the folder :data:`CACHE_DIR`), a folder, or False: stored as ``plume_seq_<key>.npy``,
    key = hash of the parameters, the backend and this module's source.  progress: a tqdm bar."""
    frames = V.integer(frames, "frames", 1, 100000)
    start = V.integer(start, "start", 1)
    stride = V.integer(stride, "stride", 1)
    defaults = {k: v.default for k, v in inspect.signature(simulate_plume).parameters.items()
                if k not in ("shape", "steps", "seed", "cache")}
    if set(kwargs) - set(defaults):
        raise ValueError(f"kwargs: unknown solver parameters {sorted(set(kwargs) - set(defaults))}")
    params = dict(_plume_params(shape, seed, **dict(defaults, **kwargs)), frames=int(frames), start=int(start),
                  stride=int(stride), backend=backend.get_backend(), version=_VERSION)
    shape = (frames, *params["shape"])

    def run():
        out = np.empty(shape, np.float32)
        steps = range(1, start + (frames - 1) * stride + 1)
        if progress:
            from tqdm import tqdm
            steps = tqdm(steps, desc="plume", unit="step", leave=False)
        for k, d in zip(steps, _plume_frames(params)):
            if k >= start and (k - start) % stride == 0:
                out[(k - start) // stride] = d
        return out
    return _cached(cache, "plume_seq", params, shape, run)
