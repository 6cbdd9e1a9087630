"""Built-in scenes and their registry :data:`SCENES`: each function returns a
:class:`~avsm_dr.scene.Scene` (content, light, receivers in and behind the volume, a receiver
plane for images): :func:`plume`, :func:`three_columns`, :func:`hair_and_smoke`,
:func:`particles`, :func:`smoke_over_table`, :func:`simulated_plume`, and those of
:mod:`avsm_dr.procedural`.

``size`` sets the grid resolution (voxels per world unit; small by default so tests stay fast);
densities are deterministic for a given ``seed``; ``light=`` replaces the default directional
light.  The AVSM paper: Salvi, Vidimce, Lauritzen and Lefohn, "Adaptive Volumetric Shadow Maps",
EGSR 2010.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from . import procedural, validation as V
from .procedural import MAX_POINTS, MAX_SIZE, grid_box, square_points  # noqa: F401  (MAX_*: re-exported)
from .scene import DirectionalLight, Hair, OpaqueBox, Particles, Scene, voxel_coords


def _fbm(shape, seed: int, cells: int = 3) -> np.ndarray:
    return procedural.fbm(shape, np.random.default_rng(seed), 4, cells)


def half_volume_half_surface(dens, bmin, bmax, n_receivers, rng, center, u, v, half) -> np.ndarray:
    """Receivers: n // 2 uniform in voxels with density > 0 (:func:`~avsm_dr.scene.voxel_coords`),
    the rest on the square ``center`` +- ``half`` along ``u``, ``v`` (:func:`~avsm_dr.procedural.square_points`)."""
    k_vol = n_receivers // 2
    h = (np.asarray(bmax) - np.asarray(bmin)) / np.array(dens.shape[::-1])
    vol = np.asarray(bmin) + voxel_coords(dens, k_vol, rng) * h
    return np.concatenate([vol, square_points(center, u, v, half, n_receivers - k_vol)])


def _smoke(name, dens, bmin, bmax, light, direction, seed, n_receivers, plane, wall, meta, **content):
    """A grid scene: ``light`` (default directional along ``direction``), receivers half in the
    smoke and half on the square ``wall`` (u, v, half size) around the centre of ``plane``
    (centre, normal, half size: the receiver plane)."""
    light = DirectionalLight(direction=direction) if light is None else light
    c = np.array(plane[0], np.float64)
    rec = half_volume_half_surface(dens, bmin, bmax, n_receivers, np.random.default_rng(seed + 1), plane[0], *wall)
    return Scene(name, light, rec, density=dens, bbox=(bmin, bmax), **content,
                 receiver_plane=(c, np.array(plane[1], np.float64), plane[2]), meta=meta)


# --------------------------------------------------------------------- registry
@dataclass(frozen=True)
class SceneEntry:
    """One registered scene: ``factory(**kwargs) -> Scene``, a one-line ``description``,
    the ``content`` it holds (tags of :data:`CONTENT`) and free ``tags``."""
    name: str
    factory: Callable[..., Scene]
    description: str = ""
    content: tuple = ()
    tags: tuple = ()


#: Content tags of :attr:`SceneEntry.content`.
CONTENT = ("grid", "particles", "hair", "blockers")


class SceneRegistry(Mapping):
    """The built-in scenes by name: a mapping ``name -> factory`` (registration order) that
    also keeps each scene's :class:`SceneEntry`; :meth:`register` (also a decorator,
    :func:`register_scene`) adds one."""

    def __init__(self):
        self._entries: dict[str, SceneEntry] = {}

    def register(self, factory=None, *, name: str | None = None, description: str | None = None, content=(), tags=()):
        """Register ``factory`` (default name: its ``__name__``; description: the first line
        of its docstring); used bare or with keywords as a decorator.  Returns the factory."""
        def add(fn):
            if not callable(fn):
                raise ValueError(f"factory: expected a callable returning a Scene, got {fn!r}")
            key = fn.__name__ if name is None else name
            if not (isinstance(key, str) and key):
                raise ValueError(f"name: expected a non-empty string, got {key!r}")
            bad = [c for c in content if c not in CONTENT]
            if bad:
                raise ValueError(f"content: unknown content tags {bad}; known: {list(CONTENT)}")
            doc = (description if description is not None
                   else (fn.__doc__ or "").strip().split("\n")[0])
            self._entries[key] = SceneEntry(key, fn, doc, tuple(content), tuple(tags))
            return fn
        return add if factory is None else add(factory)

    def __getitem__(self, name):
        return self._entries[name].factory

    def __iter__(self):
        return iter(self._entries)

    def __len__(self):
        return len(self._entries)

    def entry(self, name: str) -> SceneEntry:
        """The :class:`SceneEntry` of ``name``; ValueError for an unknown name."""
        if not (isinstance(name, str) and name in self._entries):
            raise ValueError(f"name: unknown scene {name!r}; known: {sorted(self)}{V.did_you_mean(name, self)}")
        return self._entries[name]

    def names(self, tag: str | None = None, content: str | None = None) -> tuple:
        """Names in registration order, those with ``tag`` in their tags and ``content`` in
        their content when given."""
        return tuple(n for n, e in self._entries.items()
                     if (tag is None or tag in e.tags) and (content is None or content in e.content))

    def __repr__(self) -> str:
        return f"SceneRegistry({list(self)})"


#: Every built-in scene (:class:`SceneRegistry`); tag ``'core'``: the six scenes the
#: studies sweep (``error_curves``, ``memory_budget``).
SCENES = SceneRegistry()
register_scene = SCENES.register


# --------------------------------------------------------------------- scenes
#: The plumes' receiver plane: the wall x = 0.8 behind them.
_PLUME_WALL = ((0.8, 0.75, 0.0), (-1.0, 0.0, 0.0), 0.75)


@register_scene(content=("grid",), tags=("core",))
def plume(size: int = 24, seed: int = 0, density_scale: float = 60.0, light=None, n_receivers: int = 1024) -> Scene:
    """A smoke plume rising from y = 0 and widening with height, in the box
    [-0.5, 0.5] x [0, 1.5] x [-0.5, 0.5], swaying with height; fBm noise (``seed``)
    breaks it into puffs.  Light: directional, mostly along +x, slightly down.
    Receivers: half in the smoke, half on the wall x = 0.8 behind it (the receiver plane)."""
    procedural.check_args(seed, light, n_receivers, density_scale)
    bmin, bmax = np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.5, 0.5])
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    h = Y / 1.5
    cx = 0.07 * np.sin(5.0 * Y + 0.3)
    cz = 0.05 * np.cos(4.0 * Y)
    R = 0.08 + 0.24 * h
    r2 = ((X - cx) ** 2 + (Z - cz) ** 2) / R ** 2
    body = np.exp(-2.0 * r2) * np.clip(6 * h, 0, 1) * np.clip(6 * (1 - h), 0, 1)
    dens = np.maximum(body * (0.35 + 0.9 * _fbm(shape, seed)) - 0.18, 0.0) * density_scale
    return _smoke("plume", dens.astype(np.float32), bmin, bmax, light, (1.0, -0.3, 0.25), seed, n_receivers,
                  _PLUME_WALL, ((0, 1, 0), (0, 0, 1), 0.75),
                  {"seed": seed, "size": size, "density_scale": density_scale})


@register_scene(content=("grid",), tags=("core",))
def three_columns(size: int = 16, seed: int = 0, density_scale: float = 14.0, light=None,
                  n_receivers: int = 1024) -> Scene:
    """Three vertical smoke columns at x = -1, 0, 1 in the box [-1.5, 1.5] x [0, 1] x [-0.5, 0.5],
    one behind the other along the (nearly horizontal, +x) light so each casts on the next:
    a translucent one nearest the light, a dense one, then a medium one (the AVSM paper's figures 4 and 7).
    Receivers: half in the columns, half on the wall x = 1.8 behind them."""
    procedural.check_args(seed, light, n_receivers, density_scale)
    bmin, bmax = np.array([-1.5, 0.0, -0.5]), np.array([1.5, 1.0, 0.5])
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    n = _fbm(shape, seed, cells=4)
    dens = np.zeros(shape)
    for x0, z0, radius, weight in ((-1.0, -0.12, 0.22, 0.35), (0.0, 0.0, 0.25, 1.6), (1.0, 0.12, 0.22, 1.0)):
        wob = 0.04 * np.sin(7 * Y + 3 * x0)
        r2 = ((X - x0 - wob) ** 2 + (Z - z0) ** 2) / radius ** 2
        top = np.clip(8 * (0.92 - Y), 0, 1) * np.clip(8 * Y, 0, 1)
        dens += weight * np.maximum(np.exp(-1.5 * r2) * top * (0.4 + 0.8 * n) - 0.2, 0.0)
    return _smoke("three_columns", (dens * density_scale).astype(np.float32), bmin, bmax, light, (1.0, -0.12, 0.08),
                  seed, n_receivers, ((1.8, 0.5, 0.0), (-1.0, 0.0, 0.0), 0.5), ((0, 1, 0), (0, 0, 1), 0.5),
                  {"seed": seed, "size": size, "density_scale": density_scale})


@register_scene(content=("grid", "hair",), tags=("core",))
def hair_and_smoke(size: int = 24, seed: int = 0, tfx_path=None, n_strands: int = 300,
                   hair_radius: float = 0.002, hair_opacity: float = 0.3,
                   density_scale: float = 8.0, light=None, n_receivers: int = 1024) -> Scene:
    """Hair strands inside a smoke puff in the box [-0.5, 0.5]^3 (the AVSM paper's figures 5-6).

    Hair: ``n_strands`` procedural strands (:func:`~avsm_dr.capture.hair.procedural_strands`),
    or the strands of the TressFX file ``tfx_path`` scaled into the box.  Each crossing of a
    light ray with a strand absorbs ``hair_opacity``.  Light: directional, nearly horizontal
    (+x).  Receivers: half in the smoke/hair, half on the wall x = 0.8 behind it."""
    from .capture.hair import fit_strands, load_tfx, procedural_strands
    procedural.check_args(seed, light, n_receivers, density_scale)
    hair_radius = V.real(hair_radius, "hair_radius", 0.0, open_min=True)
    hair_opacity = V.real(hair_opacity, "hair_opacity", 0.0, 1.0)
    bmin, bmax = np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.5])
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    r2 = (X ** 2 + (Y + 0.05) ** 2 / 1.3 + Z ** 2) / 0.33 ** 2
    dens = np.maximum(np.exp(-1.5 * r2) * (0.4 + 0.8 * _fbm(shape, seed)) - 0.15, 0.0) * density_scale
    if tfx_path is not None:
        strands = fit_strands(load_tfx(tfx_path), bmin, bmax, fill=0.8)
    else:
        V.integer(n_strands, "n_strands", 1)
        strands = procedural_strands(n_strands, 16, root_center=(0.0, -0.35, 0.0), root_radius=0.22,
                                     length=0.7, seed=seed)
    return _smoke("hair_and_smoke", dens.astype(np.float32), bmin, bmax, light, (1.0, -0.2, 0.1), seed, n_receivers,
                  ((0.8, 0.0, 0.0), (-1.0, 0.0, 0.0), 0.5), ((0, 1, 0), (0, 0, 1), 0.5),
                  {"seed": seed, "size": size, "tfx_path": None if tfx_path is None else str(tfx_path)},
                  hair=Hair(strands=strands, radius=hair_radius, opacity=hair_opacity))


@register_scene(content=("particles",), tags=("core",))
def particles(n: int = 200, seed: int = 0, light=None, n_receivers: int = 1024) -> Scene:
    """A cloud of ``n`` spherical particles (radius 0.03..0.1, extinction 5..20 per unit)
    around (0, 0.3, 0); light from above (directional, mostly -y).  Receivers: half inside
    the cloud, half on the ground y = -0.5 (the receiver plane)."""
    V.integer(n, "n", 1, MAX_POINTS)
    procedural.check_args(seed, light, n_receivers)
    rng = np.random.default_rng(seed)
    centers = np.array([0.0, 0.3, 0.0]) + 0.2 * rng.standard_normal((n, 3))
    radii = rng.uniform(0.03, 0.1, n)
    dens = rng.uniform(5.0, 20.0, n)
    light = DirectionalLight(direction=(0.25, -1.0, 0.15)) if light is None else light
    k_vol = n_receivers // 2
    pick = rng.integers(0, n, k_vol)
    u = rng.standard_normal((k_vol, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    inside = centers[pick] + u * (radii[pick] * rng.random(k_vol) ** (1 / 3))[:, None]
    ground = square_points((0.0, -0.5, 0.0), (1, 0, 0), (0, 0, 1), 0.8, n_receivers - k_vol)
    return Scene("particles", light, np.concatenate([inside, ground]),
                 particles=Particles(centers=centers, radii=radii, density=dens),
                 receiver_plane=(np.array([0.0, -0.5, 0.0]), np.array([0.0, 1.0, 0.0]), 0.8),
                 meta={"seed": seed, "n": n})


@register_scene(content=("grid", "blockers",), tags=("core",))
def smoke_over_table(size: int = 24, seed: int = 0, density_scale: float = 25.0, light=None,
                     n_receivers: int = 1024) -> Scene:
    """A smoke puff in [-0.4, 0.4] x [0.1, 0.9] x [-0.4, 0.4] above an opaque table top
    (the box [-1, 1] x [-0.05, 0] x [-1, 1], an :class:`OpaqueBox` blocker); light from
    above.  Receivers: half in the smoke, half on the table's top face y = 0 (the receiver
    plane; lit except where the smoke shadows it)."""
    procedural.check_args(seed, light, n_receivers, density_scale)
    bmin, bmax = np.array([-0.4, 0.1, -0.4]), np.array([0.4, 0.9, 0.4])
    shape, X, Y, Z = grid_box(bmin, bmax, size)
    r2 = (X ** 2 + (Y - 0.5) ** 2 + Z ** 2) / 0.3 ** 2
    dens = np.maximum(np.exp(-1.5 * r2) * (0.4 + 0.8 * _fbm(shape, seed)) - 0.15, 0.0) * density_scale
    table = OpaqueBox(min=np.array([-1.0, -0.05, -1.0]), max=np.array([1.0, 0.0, 1.0]))
    return _smoke("smoke_over_table", dens.astype(np.float32), bmin, bmax, light, (0.3, -1.0, 0.2), seed, n_receivers,
                  ((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 1.0), ((1, 0, 0), (0, 0, 1), 0.9),
                  {"seed": seed, "size": size, "density_scale": density_scale}, blockers=[table])


def get(name: str, **kwargs) -> Scene:
    """The scene ``name`` of :data:`SCENES` built with ``kwargs``; ValueError for an unknown name."""
    return SCENES.entry(name).factory(**kwargs)


@register_scene(content=("grid",), tags=("core",))
def simulated_plume(size: int = 32, seed: int = 0, steps: int | None = None, density_scale: float = 40.0,
                    light=None, n_receivers: int = 1024) -> Scene:
    """A buoyant smoke plume simulated by :func:`avsm_dr.fluid.simulate_plume` (``steps``,
    default 1.25 x size; cached on disk) in the box of :func:`plume`: sharp fronts, curled sheets
    and holes that fBm noise lacks.  Density (peak ~1) times ``density_scale``; light, receivers
    and receiver plane as in :func:`plume`."""
    from .fluid import simulate_plume
    procedural.check_args(seed, light, n_receivers, density_scale)
    steps = int(round(1.25 * size)) if steps is None else V.integer(steps, "steps", 1)
    bmin, bmax = np.array([-0.5, 0.0, -0.5]), np.array([0.5, 1.5, 0.5])
    dens = simulate_plume(grid_box(bmin, bmax, size)[0], steps=steps, seed=seed) * density_scale
    return _smoke("simulated_plume", dens.astype(np.float32), bmin, bmax, light, (1.0, -0.3, 0.25), seed, n_receivers,
                  _PLUME_WALL, ((0, 1, 0), (0, 0, 1), 0.75),
                  {"seed": seed, "size": size, "steps": steps, "density_scale": density_scale})


for _factory, _content in ((procedural.cumulus, "grid"), (procedural.fog_bank, "grid"),
                          (procedural.gaussian_blobs, "particles"), (procedural.tall_column, "grid")):
    SCENES.register(_factory, content=(_content,))      # Gaussian blobs are particles (nested spheres)
