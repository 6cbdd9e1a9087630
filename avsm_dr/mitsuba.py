"""Mitsuba 3 integrator ``avsm_single_scatter``: single scattering with shadow-map transmittance.

Example::

    import avsm_dr.mitsuba                     # registers the plugin for the current variant
    scene = mi.load_dict({..., "integrator": {"type": "avsm_single_scatter",
                                              "representation": "avsm", "nodes": 8}})
    img = mi.render(scene, spp=64)

The image a game engine would show: the camera ray's attenuation and the in-scattering come
from Mitsuba's medium, only the light's transmittance to each shading point from an avsm_dr
representation of a light-view capture of the same grid (Salvi et al., "Adaptive Volumetric
Shadow Maps", EGSR 2010, sec. 3).  With ``representation='exact'`` this is ``volpath`` with
``max_depth = 2``.

Importing this module selects a variant only when none is set (``llvm_ad_rgb``, or
``cuda_ad_rgb`` on the CUDA backend) and re-registers the plugin on every variant change; the
rest of the package imports Mitsuba lazily.  Errors are ValueErrors naming the property or the
scene, also as raised by ``mi.load_dict`` and ``mi.render``.
"""
from __future__ import annotations

import functools
import inspect

import drjit as dr
import mitsuba as mi
import numpy as np

from . import backend
from . import validation as V
from .capture import RESOLUTION_RANGE, capture
from .capture.grid import METHODS as CAPTURE_METHODS
from .filtering import FILTERS
from .geometry import ray_box_dr
from .groundtruth.media import mitsuba as _mitsuba_with_variant, sample_grid
from .representations import REGISTRY, build, describe
from .representations.schema import BASE_PARAMETERS, Param
from .scene import Light, Scene

NAME = "avsm_single_scatter"
#: Null-BSDF interfaces (medium boundaries) a camera or shadow ray crosses before the first
#: opaque surface; past that many, a camera ray counts as hitting nothing and a shadow ray as
#: unblocked (a box medium needs 2).
MAX_NULL_INTERFACES = 2
#: Properties of the plugin itself; every other property is a parameter of the representation
#: (its schema's, or :data:`~avsm_dr.representations.schema.BASE_PARAMETERS`).
OWN_PROPERTIES = ("representation", "resolution", "filter", "max_depth", "march_steps", "capture_method",
                  "hide_emitters", "samples_per_pass", "timeout")


# ===================================================================== scene reading
def light_of(emitter):
    """The avsm_dr light of a Mitsuba emitter (:meth:`avsm_dr.scene.Light.of_mitsuba`)."""
    return Light.of_mitsuba(emitter, mi.traverse(emitter))


def scene_medium(scene):
    """(medium, sigma_t grid, bbox lo (3,), bbox hi (3,)) of the one shape with an interior
    medium; the grid (z, y, x) is a Dr.Jit TensorXf ``scale * data``, AD graph kept."""
    found = [(s, s.interior_medium()) for s in scene.shapes() if s.interior_medium() is not None]
    if len(found) != 1:
        raise ValueError(f"scene: {NAME} needs exactly one shape with an interior medium, found {len(found)}")
    shape, medium = found[0]
    params = mi.traverse(medium)
    if medium.class_name() != "HeterogeneousMedium" or "sigma_t.data" not in params.keys():
        raise ValueError(f"scene: the medium must be 'heterogeneous' with a 'gridvolume' sigma_t, "
                         f"got {medium.class_name()}")
    data = params["sigma_t.data"]
    if data.ndim != 4 or data.shape[3] != 1:
        raise ValueError(f"scene: the medium's sigma_t grid must have one channel, got shape {data.shape}")
    density = mi.TensorXf(data.array * float(params["scale"]), tuple(int(s) for s in data.shape[:3]))
    lo, hi = (np.array([float(v) for v in end], np.float64) for end in (shape.bbox().min, shape.bbox().max))
    return medium, density, lo, hi


def check_box(medium, density, lo, hi, n: int = 64) -> None:
    """The gridvolume spans the medium shape's box (the convention of :mod:`avsm_dr.groundtruth`):
    sigma_t from Mitsuba equals the NumPy trilinear lookup over [lo, hi] at ``n`` points."""
    rng = np.random.default_rng(7)
    p = lo + (hi - lo) * rng.uniform(0.02, 0.98, (n, 3))
    mei = dr.zeros(mi.MediumInteraction3f, n)
    mei.p = mi.Point3f(*(mi.Float(p[:, i].astype(np.float32)) for i in range(3)))
    sig = np.asarray(dr.detach(medium.get_scattering_coefficients(mei)[2][0]).numpy(), np.float64)
    g = np.asarray(dr.detach(density.array).numpy(), np.float64).reshape(density.shape)
    ref = sample_grid(g, lo, hi, p)
    if not np.allclose(sig, ref, rtol=1e-3, atol=1e-4 * max(float(g.max()), 1e-30)):
        raise ValueError("scene: the medium's gridvolume must map the unit cube onto the box of the shape "
                         "that holds the medium (to_world of the grid = the shape's bounding box)")


# ======================================================================= integrator
#: The plugin's own options, checked as a representation's parameters are.
_OPTIONS = (Param("resolution", "int", 256, min=RESOLUTION_RANGE[0], max=RESOLUTION_RANGE[1]),
            Param("filter", "choice", "bilinear", choices=FILTERS),
            Param("max_depth", "int", 2, "paths of at most two segments: 1 emitters seen directly, 2 also "
                  "single scattering and direct surface light", min=1, max=2),
            Param("march_steps", "int", 64, min=1, max=4096),
            Param("hide_emitters", "bool", False),
            Param("capture_method", "choice", "march", choices=CAPTURE_METHODS))


def _check_properties(props) -> dict:
    """Plugin options and the representation's parameters (schema-validated); ValueError names one:
    the kind, then unknown names (a misspelt one, with its "did you mean", first), then values."""
    kind = props.get("representation", "exact")
    if not isinstance(kind, str) or kind not in REGISTRY:
        raise ValueError(f"representation: unknown kind {kind!r}; known: {sorted(REGISTRY)}"
                         f"{V.did_you_mean(kind, REGISTRY)}")
    given = {k: props[k] for k in props.keys() if k not in OWN_PROPERTIES}
    schema = REGISTRY[kind].schema
    unknown = sorted(set(given) - set(schema.names()) - set(BASE_PARAMETERS))
    if unknown:                                          # private (``_``) switches are accepted, not listed
        typos = [u for u in unknown if V.did_you_mean(u, schema.public_names() + list(OWN_PROPERTIES))]
        name = (typos or unknown)[0]
        msg = schema.unknown_message(kind, name)
        if not V.did_you_mean(name, schema.public_names()):     # then the plugin's own, too
            msg += f"; {NAME} properties: {list(OWN_PROPERTIES)}{V.did_you_mean(name, OWN_PROPERTIES)}"
        raise ValueError(msg)
    opts = {"kind": kind}
    for p in _OPTIONS:
        opts[p.name] = p.validate(props.get(p.name, p.default))
    extra = {k: given.pop(k) for k in BASE_PARAMETERS if k in given}
    precisions = describe(kind)["precisions"]
    if extra.get("precision") is not None and extra["precision"] not in precisions:
        raise ValueError(f"precision: kind {kind!r} accepts None or {precisions}, got {extra['precision']!r}"
                         if precisions else f"precision: kind {kind!r} accepts only None, "
                         f"got {extra['precision']!r}")
    schema.validate(kind, given)                         # bad value or constraint -> ValueError
    opts["params"] = {**given, **extra}
    return opts


def _variant_backend():
    """The Dr.Jit backend of the current Mitsuba variant, as a context (``backend.use_backend``)."""
    return backend.use_backend("cuda" if mi.variant().startswith("cuda") else "llvm")


def _make_class():
    """The integrator class for the current variant (Mitsuba's base classes are per variant)."""

    class AVSMSingleScatterIntegrator(mi.SamplingIntegrator):
        r"""Single scattering in a heterogeneous medium, light transmittance from a shadow map.

        Properties (described in the Mitsuba page of the docs): ``representation``, a kind of
        :func:`avsm_dr.kinds` (default ``exact``: equals ``volpath``); the kind's parameters,
        passed to :func:`avsm_dr.build` and checked by its schema; and the plugin's options
        (defaults and checks: :data:`_OPTIONS`).

        Per camera sample, with ``[a, b]`` the ray's stretch inside the medium's box (cut at
        the first surface), ``t* ~ U[a, b]`` and ``x* = o + t* d``::

            L = (b - a) T_v(t*) sigma_s(x*) f_p(-d, l) L_e T_light(x*) V(x*)          medium
              + T_v(b) f_r(x_s) |cos| L_e T_light(x_s) V(x_s)                         surface

        ``T_v(t) = exp(-int_a^t sigma_t)`` by the midpoint rule with ``march_steps`` pieces of
        ``[a, b]`` (one random ``t*`` per sample: unbiased for the in-scattering integral
        given ``T_v``; ``T_v`` itself has the midpoint rule's O(h^2) error), ``L_e`` the
        emitter sample (Mitsuba's ``sample_emitter_direction``), ``V`` the visibility of
        the light through opaque surfaces (Mitsuba ray tests, null interfaces skipped) and
        ``T_light`` the representation's transmittance through the medium at the point
        (:meth:`avsm_dr.capture.Capture.transmittance`).  The medium is the interior of a
        shape (its box bounds the march) holding a ``heterogeneous`` medium with a
        one-channel ``gridvolume`` ``sigma_t`` spanning that box; its ``albedo`` and phase
        function are Mitsuba's.  Reverse-mode AD (``dr.backward`` after ``mi.render``)
        reaches the grid both through ``sigma_t`` along camera rays and through the
        capture's optical depths (naive AD of the whole render).
        """

        def __init__(self, props):
            super().__init__(props)
            opts = _check_properties(props)
            for name in ("kind", "params", "resolution", "filter", "max_depth", "march_steps", "capture_method"):
                setattr(self, name, opts[name])
            self.hide_emitters_ = bool(opts["hide_emitters"])
            self.shadow = None

        # ------------------------------------------------------------- shadow map
        def prepare_shadow(self, scene):
            """Capture the scene's medium from its light and build the representation:
            ``self.shadow = (capture, representation, medium, box)``, the AD graph kept when
            the grid has gradients enabled."""
            emitters = scene.emitters()
            if len(emitters) != 1:
                raise ValueError(f"scene: {NAME} needs exactly one emitter, found {len(emitters)}")
            light = light_of(emitters[0])
            medium, density, lo, hi = scene_medium(scene)
            # the grid rule of every entry point (NaN, inf, negative: named here, not as a to_world mismatch)
            V.density_grid(density, "scene: the medium's sigma_t grid (scale * data)")
            with dr.suspend_grad():
                check_box(medium, density, lo, hi)
            with _variant_backend():
                av = Scene(NAME, light, np.zeros((0, 3)), density=density, bbox=(lo, hi))
                cap = capture(av, resolution=self.resolution, density=density, method=self.capture_method,
                              order="depth")
                rep = build(self.kind, cap.segments, **self.params)
            self.shadow = (cap, rep, medium, mi.ScalarBoundingBox3f(lo.tolist(), hi.tolist()))
            return self.shadow

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            """Capture the shadow map, then render as every SamplingIntegrator does."""
            self.prepare_shadow(scene)
            try:
                return super().render(scene, sensor, seed, spp, develop, evaluate)
            finally:
                self.shadow = None           # the image's graph keeps what it needs

        def light_transmittance(self, p):
            """T_light at world points ``p`` (Point3f): the representation's lookup."""
            cap, rep = self.shadow[:2]
            pts = np.stack([np.asarray(dr.detach(p[i]).numpy(), np.float64) for i in range(3)], axis=1)
            with _variant_backend():
                T = cap.transmittance(rep, pts, filter=self.filter)
            return mi.Float(T)

        # ---------------------------------------------------------------- tracing
        @staticmethod
        def _is_null(si):
            return si.is_valid() & mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Null)

        def first_surface(self, scene, ray, active):
            """First intersection with a non-null BSDF (medium boundaries crossed)."""
            o, act = mi.Point3f(ray.o), mi.Bool(active)
            for _ in range(MAX_NULL_INTERFACES):
                si = scene.ray_intersect(mi.Ray3f(o, ray.d), act)
                null = act & self._is_null(si)
                o = dr.select(null, si.spawn_ray(ray.d).o, o)
                act = null
            si = scene.ray_intersect(mi.Ray3f(o, ray.d), active)
            return si, active & si.is_valid() & ~self._is_null(si)

        def visible(self, scene, it, ds, active):
            """Light not blocked by an opaque surface between ``it`` and the emitter sample
            (``it``: a SurfaceInteraction3f, whose ray origin is offset off the surface, or an
            Interaction3f inside the medium)."""
            o = it.spawn_ray(ds.d).o if isinstance(it, mi.SurfaceInteraction3f) else mi.Point3f(it.p)
            left, act = mi.Float(ds.dist), mi.Bool(active)
            blocked = dr.zeros(mi.Bool, dr.width(act))
            for _ in range(MAX_NULL_INTERFACES):
                r = mi.Ray3f(o, ds.d)
                r.maxt = left * (1 - mi.math.ShadowEpsilon)
                si = scene.ray_intersect(r, act)
                hit = act & si.is_valid()
                null = hit & self._is_null(si)
                blocked |= hit & ~null
                left = dr.select(null, left - si.t, left)
                o = dr.select(null, si.spawn_ray(ds.d).o, o)
                act = null
            return active & ~blocked

        def sample(self, scene, sampler, ray, medium=None, active=True):
            """One sample of the estimator in the class docstring: (radiance, valid, aovs)."""
            if self.shadow is None:
                self.prepare_shadow(scene)
            _, _, med, box = self.shadow
            active = mi.Bool(active)
            n = dr.width(active) if dr.width(ray.o) == 1 else dr.width(ray.o)
            d = mi.Vector3f(ray.d)
            L = dr.zeros(mi.Spectrum, n)

            # ---- camera ray: first surface and the stretch [a, b] inside the medium's box
            si, on_surface = self.first_surface(scene, ray, active)
            t_surf = dr.select(on_surface, dr.dot(si.p - ray.o, d), dr.inf)
            mint, maxt, _ = ray_box_dr(ray.o, d, box.min, box.max)
            hit = maxt >= mint
            a = dr.maximum(mint, 0.0)
            b = dr.minimum(maxt, t_surf)
            in_medium = active & hit & (b > a)
            length = dr.select(in_medium, b - a, 0.0)
            t_star = a + sampler.next_1d(active) * length             # scattering distance, pdf 1/length

            # ---- midpoint march of T_v: one lane per (sample, piece); block sums per sample
            N = self.march_steps
            lane = dr.arange(mi.UInt32, n * N)
            path = lane // N
            j = mi.Float(lane - path * N)
            o_l = dr.gather(mi.Point3f, ray.o, path)
            d_l = dr.gather(mi.Vector3f, d, path)
            h = dr.gather(mi.Float, length, path) / N                # piece length
            s0 = dr.gather(mi.Float, a, path) + j * h                # piece start
            ts = dr.gather(mi.Float, t_star, path)
            live = dr.gather(mi.Bool, in_medium, path)
            sig_mid = self._sigma_t(med, o_l + d_l * (s0 + 0.5 * h), live)
            cut = dr.minimum(s0 + h, ts)                              # piece end, cut at t*
            partial = live & (s0 < ts) & (s0 + h > ts)
            sig_cut = self._sigma_t(med, o_l + d_l * (0.5 * (s0 + cut)), partial)
            part = dr.select(s0 + h <= ts, sig_mid * h, dr.select(partial, sig_cut * (cut - s0), 0.0))
            tau_b = dr.block_sum(sig_mid * h, N)                      # optical depth a -> b
            tau_star = dr.block_sum(part, N)                          # optical depth a -> t*

            # ---- emitters seen directly (max_depth >= 1)
            if not self.hide_emitters_:
                emitter = si.emitter(scene, on_surface)
                L += dr.select(on_surface, emitter.eval(si, on_surface), 0.0) * dr.exp(-tau_b)
            if self.max_depth < 2:
                return L, active, []

            # ---- emitter samples at the scattering point and at the surface
            x_star = ray.o + d * t_star
            it_m = dr.zeros(mi.Interaction3f, n)
            it_m.p, it_m.t = x_star, t_star
            ds_m, Le_m = scene.sample_emitter_direction(it_m, sampler.next_2d(in_medium), False, in_medium)
            ds_s, Le_s = scene.sample_emitter_direction(si, sampler.next_2d(on_surface), False, on_surface)
            vis_m = self.visible(scene, it_m, ds_m, in_medium & (ds_m.pdf > 0))
            vis_s = self.visible(scene, si, ds_s, on_surface & (ds_s.pdf > 0))
            T = self.light_transmittance(mi.Point3f(dr.concat([x_star.x, si.p.x]), dr.concat([x_star.y, si.p.y]),
                                                    dr.concat([x_star.z, si.p.z])))
            idx = dr.arange(mi.UInt32, n)
            T_m, T_s = dr.gather(mi.Float, T, idx), dr.gather(mi.Float, T, idx + n)

            # ---- single scattering: (b - a) T_v(t*) sigma_s f_p L_e T_light
            mei = dr.zeros(mi.MediumInteraction3f, n)
            mei.p, mei.t, mei.wi = x_star, t_star, -d
            mei.sh_frame = mi.Frame3f(mei.wi)
            sigma_s, _, _ = med.get_scattering_coefficients(mei, in_medium)
            phase_val, _ = med.phase_function().eval_pdf(mi.PhaseFunctionContext(sampler), mei, ds_m.d, in_medium)
            L += dr.select(vis_m, length * dr.exp(-tau_star) * sigma_s * phase_val * Le_m * T_m, 0.0)

            # ---- surface: T_v(b) f_r L_e T_light
            bsdf = si.bsdf(ray)
            f = bsdf.eval(mi.BSDFContext(), si, si.to_local(ds_s.d), vis_s)
            L += dr.select(vis_s, dr.exp(-tau_b) * f * Le_s * T_s, 0.0)
            return L, active, []

        @staticmethod
        def _sigma_t(medium, p, active):
            mei = dr.zeros(mi.MediumInteraction3f, dr.width(p))
            mei.p = p
            return dr.select(active, medium.get_scattering_coefficients(mei, active)[2][0], 0.0)

        def to_string(self):
            return f"AVSMSingleScatterIntegrator[representation={self.kind!r}, params={self.params}]"

    return AVSMSingleScatterIntegrator


_CLASSES: dict[str, type] = {}


def supported_variant(variant) -> bool:
    """True for the variants the integrator runs in: JIT with AD, ``llvm_ad_*`` / ``cuda_ad_*``."""
    return isinstance(variant, str) and variant.startswith(("llvm_ad", "cuda_ad"))


def integrator_class():
    """The ``avsm_single_scatter`` class of the current Mitsuba variant; ValueError, naming the
    variant to set, under a variant it cannot run in (not :func:`supported_variant`)."""
    variant = mi.variant()
    if not supported_variant(variant):
        raise ValueError(f"{NAME} needs a JIT variant of Mitsuba with autodiff (llvm_ad_rgb, or cuda_ad_rgb on an "
                         f"NVIDIA GPU; any llvm_ad_* / cuda_ad_*), the current variant is {variant!r}: call "
                         f"mi.set_variant('llvm_ad_rgb') before building the scene dict and loading it (importing "
                         f"avsm_dr.mitsuba selects it only when no variant is set)")
    if variant not in _CLASSES:
        _CLASSES[variant] = _make_class()
    return _CLASSES[variant]


def register() -> None:
    """Register ``avsm_single_scatter`` for the current variant (at import and after every variant
    change): the integrator under a JIT AD variant, else a constructor raising ValueError that
    names the variant to set (not Mitsuba's ``Plugin "avsm_single_scatter" not found!``).  Its
    ValueErrors lose their traceback, which Mitsuba's parser would quote whole, the message last."""
    if mi.variant() is None:
        return
    make = integrator_class() if supported_variant(mi.variant()) else lambda props: integrator_class()

    def factory(props):
        try:
            return make(props)
        except ValueError as err:
            err.__traceback__ = None
            raise
    mi.register_integrator(NAME, factory)


def _integrator_of(signature, args, kwargs):
    """The integrator an ``mi.render(*args, **kwargs)`` call used (None if it cannot tell)."""
    try:
        bound = signature.bind(*args, **kwargs).arguments
        integrator = bound.get("integrator")
        return bound["scene"].integrator() if integrator is None else integrator
    except Exception:
        return None


def _checked_render(render):
    """``mi.render`` raising this integrator's own ValueError instead of Dr.Jit's ``RuntimeError
    ... (see above)`` whose ``__cause__`` it is; anything else passes through unchanged."""
    signature = inspect.signature(render)

    @functools.wraps(render)
    def wrapper(*args, **kwargs):
        try:
            return render(*args, **kwargs)
        except RuntimeError as err:
            cause = err.__cause__
            ours = isinstance(_integrator_of(signature, args, kwargs), tuple(_CLASSES.values()))
            if not (isinstance(cause, ValueError) and ours):
                raise
            cause.__suppress_context__ = True             # Dr.Jit's wrapper is no news
            raise cause
    wrapper._avsm_dr_checked = True
    return wrapper


if mi.variant() is None:
    _mitsuba_with_variant()
register()
mi.detail.add_variant_callback(lambda *_args: register())
if not getattr(mi.render, "_avsm_dr_checked", False):
    mi.render = _checked_render(mi.render)

__all__ = ["NAME", "register", "integrator_class", "supported_variant", "light_of", "scene_medium"]
