"""Differentiable shadows end to end, and recovering a density grid from shadow images.

Pipeline (every step differentiable with respect to the voxel densities ``sigma``)::

    sigma (z, y, x) --capture--> segments (tau_i by Simpson's rule, gradients to the
    8 voxels of each sample) --build--> representation --eval--> T at receivers
    --> radiance L = albedo / pi * E * cos * T --> loss

* **Capture** with ``keep_zero=True``: every march step inside the box is a segment,
  empty ones included, so voxels that are still 0 receive gradients; the light camera is
  fitted to the whole box and, with a tiny ``epsilon``, the segment layout is geometry only.
* **Representations**: the configurations ``ad.describe`` marks differentiable (``avsm``
  with its node layout held fixed, ``dsm`` with ``placement='curve'``: node depths fixed).
* Reverse mode for many parameters (``dr.backward``), forward mode for a few;
  :func:`gradient_check` compares the two (a too-small loop bound corrupts reverse mode only).

Inverse problem (:func:`recover`): minimise over ``sigma >= 0`` ::

    E(sigma) = 1/|lights| sum_l mean_k (T_l,k(sigma) - T*_l,k)^2 + lambda sum_(v,w) (sigma_v - sigma_w)^2 / n_pairs

(``T*`` the target shadow images, the second term a smoothness prior over
face-adjacent voxel pairs) with Adam (Kingma and Ba 2015, "Adam: A Method for
Stochastic Optimization", ICLR; Dr.Jit's ``drjit.opt.Adam``) and projection onto
``sigma >= 0`` after each step (:class:`ProjectedAdam`).  A few directional lights
give a limited-angle tomography problem: shadows behind the volume only constrain
line integrals, so the recovered grid matches the targets long before it matches
the density.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import drjit as dr
import drjit.opt
import numpy as np

from . import _arrays as A
from . import backend
from . import validation as V
from .capture import capture as _capture
from .geometry import check_bbox, orthonormal_basis
from .representations import build, differentiable_configuration, kinds
from .scene import DirectionalLight, Scene
from .checks import check_gradients
from .shading import irradiance


def light_from_angles(azimuth: float, elevation: float, irradiance: float = 1.0) -> DirectionalLight:
    """Directional light coming from azimuth/elevation (degrees; azimuth about +y from
    +x towards +z, elevation above the horizon); ``direction`` is where it travels."""
    az, el = math.radians(azimuth), math.radians(elevation)
    toward = np.array([math.cos(el) * math.cos(az), math.sin(el), math.cos(el) * math.sin(az)])
    return DirectionalLight(direction=-toward, irradiance=irradiance)


def receiver_grid(bbox, light: DirectionalLight, n: int = 32, gap: float = 0.05) -> np.ndarray:
    """(n*n, 3) receivers on the plane orthogonal to ``light.direction`` just behind the box
    (``gap`` world units past its far corner), covering the box's shadow footprint.

    Behind the whole volume each receiver sees the full line integral along its light
    ray: the image is a radiograph of the grid along the light."""
    if not isinstance(light, DirectionalLight):
        raise ValueError(f"light: expected a DirectionalLight, got {type(light).__name__}")
    n = V.integer(n, "n", 1)
    lo, hi = check_bbox(bbox)
    u, v, w = orthonormal_basis(light.direction)
    c = 0.5 * (lo + hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]) - c
    hu, hv = np.abs(corners @ u).max(), np.abs(corners @ v).max()
    depth = (corners @ w).max() + float(gap)
    s = (np.arange(n) + 0.5) / n * 2 - 1
    a, b = np.meshgrid(s, s, indexing="ij")
    return c + depth * w + hu * a.reshape(-1, 1) * u + hv * b.reshape(-1, 1) * v


def with_light(scene: Scene, light, density=None) -> Scene:
    """A copy of ``scene`` lit by ``light`` (and holding ``density`` when given)."""
    return replace(scene, light=light, **({} if density is None else {"density": density}))


def density_tensor(density, dtype: str = "float32", grad: bool = True):
    """A Dr.Jit 3-D tensor (``TensorXf`` / ``TensorXf64``) of ``density`` (z, y, x), with
    gradients enabled when ``grad``."""
    t = backend.types()
    arr = V.density_grid(density, "density", np.float64 if dtype == "float64" else np.float32)
    x = (t.TensorXf64 if dtype == "float64" else t.TensorXf)(arr)
    if grad:
        dr.enable_grad(x)
    return x


@dataclass(eq=False)
class Shadow:
    """Result of :func:`shadow`: ``T`` (Dr.Jit Float (K,), AD graph kept), the capture
    and the representation it came from."""
    T: object
    capture: object
    rep: object


def shadow(scene: Scene, density, points=None, light=None, kind: str = "fom", params: dict | None = None,
           resolution: int = 64, step: float | None = None, epsilon: float = 1e-4,
           filter: str = "point", reverse: str = "auto") -> Shadow:
    """Transmittance from ``light`` (default ``scene.light``) to ``points`` (default
    ``scene.receivers``) through ``density`` (a Dr.Jit tensor, gradients kept, or NumPy),
    via capture -> ``kind`` (``params``, default: the kind's first differentiable
    configuration in the registry, ``representations.differentiable_configuration``) -> lookup.

    resolution, step, epsilon: of :func:`avsm_dr.capture` (always ``keep_zero=True`` and the
    Simpson march, ``method='march'``: module docstring).  filter: the lookup filter.
    reverse: 'auto' | 'trajectory' | 'checkpoint' (:func:`avsm_dr.build`).
    """
    V.one_of(kind, "kind", kinds())
    p = differentiable_configuration(kind) if params is None else dict(params)
    if p is None:
        raise ValueError(f"kind: {kind!r} has no differentiable configuration")
    sc = scene if light is None else with_light(scene, light)
    cap = _capture(sc, resolution=resolution, step=step, epsilon=epsilon, density=density, keep_zero=True,
                   method="march", order="depth")
    rep = build(kind, cap.segments, reverse=reverse, **p)
    if not rep.differentiable:
        raise ValueError(f"params: {kind} with {p} is not differentiable (see ad.describe({kind!r}))")
    pts = sc.receivers if points is None else points
    return Shadow(cap.transmittance(rep, pts, filter=filter), cap, rep)


def radiance_weights(light, points, normal=None, albedo: float = 1.0) -> np.ndarray:
    """(K,) factor ``albedo / pi * E * cos`` turning light transmittance into the outgoing
    radiance of diffuse receivers (the model of :func:`avsm_dr.shading.shade_receivers`);
    ``normal`` (3,) one-sided, ``cos = max(0, n . l)`` with ``l`` the unit direction to the
    light; default: receivers facing the light (cos = 1)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    cos = np.ones(p.shape[0])
    if normal is not None:
        n = np.asarray(normal, np.float64).reshape(3)
        l = light.directions_to(p)
        cos = np.maximum(l @ (n / np.linalg.norm(n)), 0.0)
    return albedo / math.pi * irradiance(light, p) * cos


def radiance(T, weights):
    """Differentiable receiver radiance ``weights * T`` (weights from :func:`radiance_weights`)."""
    return T * A.to_float(np.asarray(weights, np.float64), type(T))


def image_loss(predictions: Sequence, targets: Sequence):
    """Mean over images of the mean squared difference (Dr.Jit scalar, differentiable)."""
    if len(predictions) != len(targets) or not predictions:
        raise ValueError("targets: need one target image per prediction (and at least one)")
    total = 0
    for pred, tgt in zip(predictions, targets):
        tg = A.to_float(np.asarray(tgt, np.float64).reshape(-1), type(pred))
        if dr.width(tg) != dr.width(pred):
            raise ValueError(f"targets: image of {dr.width(tg)} pixels for a prediction of {dr.width(pred)}")
        total = total + dr.mean(dr.square(pred - tg))
    return total / len(predictions)


def neighbour_pairs(shape) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (a, b) of all face-adjacent voxel pairs of a (z, y, x) grid."""
    idx = np.arange(int(np.prod(shape))).reshape(shape)
    side = [[idx[(slice(None),) * ax + (s,)].ravel() for ax in range(3)] for s in (slice(0, -1), slice(1, None))]
    return np.concatenate(side[0]), np.concatenate(side[1])


def smoothness(x, pairs=None):
    """Mean squared difference of face-adjacent voxels of the tensor ``x`` (differentiable)."""
    a, b = neighbour_pairs(tuple(x.shape)) if pairs is None else pairs
    Float = type(x.array)
    if a.size == 0:
        return dr.zeros(Float, 1)
    return dr.mean(dr.square(dr.gather(Float, x.array, A.to_uint32(a)) - dr.gather(Float, x.array, A.to_uint32(b))))


class ProjectedAdam(drjit.opt.Adam):
    """Dr.Jit's Adam (``drjit.opt.Adam``: Kingma and Ba 2015) followed, after every step,
    by projection of each parameter onto ``[lower, inf)`` (the moments are kept)::

        m <- b1 m + (1 - b1) g;  v <- b2 v + (1 - b2) g^2
        x <- max(x - lr sqrt(1 - b2^t) / (1 - b1^t) * m / sqrt(v + eps^2), lower)

    (``sqrt(v + eps^2)``: Dr.Jit's form for eps <= 1e-6, ``sqrt(v) + eps`` above.)
    beta2 defaults to 0.99, the value the inverse experiment was tuned with (Adam's
    own default is 0.999)."""

    def __init__(self, lr: float = 0.1, params=None, *, beta1: float = 0.9, beta2: float = 0.99,
                 eps: float = 1e-8, lower: float | None = 0.0):
        lr, eps = (V.real(v, name, 0, open_min=True) for v, name in ((lr, "lr"), (eps, "eps")))
        beta1, beta2 = (V.real(v, name, 0, 1, open_max=True) for v, name in ((beta1, "beta1"), (beta2, "beta2")))
        self.lower = None if lower is None else V.real(lower, "lower")
        super().__init__(lr, params, beta_1=beta1, beta_2=beta2, epsilon=eps)

    def step(self, **kwargs) -> None:
        """One Adam step (keyword arguments of ``drjit.opt.Adam.step``), then the projection."""
        super().step(**kwargs)
        if self.lower is not None:
            for key in list(self.keys()):
                self[key] = dr.maximum(self[key], self.lower)


def gradient_check(loss_fn: Callable, x, rng=None, rtol: float = 1e-4, atol: float = 1e-9) -> dict:
    """Reverse mode vs forward mode on ``loss_fn(x)`` (a Dr.Jit scalar of tensor ``x``).

    :func:`avsm_dr.checks.check_gradients` without finite differences (``g . v`` against
    forward mode along a random direction ``v``); returns dict(reverse, forward, error, ok).
    """
    chk = check_gradients(loss_fn, x, fd=0, rtol=rtol, atol=atol, rng=rng)
    return {k: chk.summary()[k] for k in ("reverse", "forward", "error", "ok")}


def density_error(recovered, truth) -> dict:
    """Errors of a recovered grid against the known one: relative L2, RMSE, mean
    absolute, max absolute, and the relative error of the total mass."""
    r, t = (np.asarray(v, np.float64) for v in (recovered, truth))
    if r.shape != t.shape:
        raise ValueError(f"recovered: shape {r.shape} differs from the truth's {t.shape}")
    d = r - t
    nt = np.linalg.norm(t)
    return {"rel_l2": float(np.linalg.norm(d) / nt) if nt > 0 else float(np.linalg.norm(d)),
            "rmse": float(np.sqrt(np.mean(d * d))), "mae": float(np.mean(np.abs(d))),
            "max_abs": float(np.abs(d).max()),
            "mass_rel": float((r.sum() - t.sum()) / t.sum()) if t.sum() > 0 else float(r.sum())}


@dataclass
class Recovery:
    """Result of :func:`recover`: ``density`` (z, y, x) float NumPy, ``history``: one dict
    per iteration (loss, data term, smoothness, density errors, seconds)."""
    density: np.ndarray
    history: list = field(default_factory=list)
    gradient_check: dict | None = None


def recover(scene: Scene, lights: Sequence, targets: Sequence, receivers: Sequence, kind: str = "fom",
            params: dict | None = None, iterations: int = 100, lr: float = 0.5, init: str = "empty",
            init_value: float = 0.0, smooth: float = 0.0, resolution: int = 64, step: float | None = None,
            epsilon: float = 1e-4, filter: str = "point", reverse: str = "auto", truth=None,
            callback: Callable[[int, dict], None] | None = None) -> Recovery:
    """Recover ``scene``'s density grid (shape and box) from shadow images.

    lights: directional lights; targets: one (K_l,) transmittance image per light at
    ``receivers[l]`` (K_l, 3).  kind/params: the differentiable shadow model.
    init: 'empty' (all 0) or 'uniform' (``init_value`` everywhere).  smooth: weight
    lambda of the smoothness prior.  resolution, step, epsilon, filter, reverse: of
    :func:`shadow`.  truth: the known grid, for the error history.  callback(iteration,
    record) after every step.  :func:`gradient_check` (reverse vs forward mode) runs at the
    start: RuntimeError when they disagree.
    """
    if scene.density is None or scene.bbox is None:
        raise ValueError("scene: needs a density grid and its bbox (shape and box of the unknown)")
    if not (len(lights) == len(targets) == len(receivers)) or not lights:
        raise ValueError("targets: need one target image and one receiver set per light")
    V.one_of(init, "init", ("empty", "uniform"))
    V.integer(iterations, "iterations", 0)
    shape = tuple(np.asarray(scene.density).shape)
    start = np.zeros(shape) if init == "empty" else np.full(shape, float(init_value))
    x = density_tensor(start, grad=False)
    pairs = neighbour_pairs(shape)
    tgts = [np.asarray(t, np.float64).reshape(-1) for t in targets]

    def losses(xt):
        preds = [shadow(scene, xt, pts, light=l, kind=kind, params=params, resolution=resolution,
                        step=step, epsilon=epsilon, filter=filter, reverse=reverse).T
                 for l, pts in zip(lights, receivers)]
        data = image_loss(preds, tgts)
        reg = smoothness(xt, pairs) if smooth > 0 else 0
        return data, reg, data + smooth * reg if smooth > 0 else data

    # float32: the two modes sum in different orders (relative ~1e-6); a wrong loop bound
    # gives O(1) errors.  An empty start is checked at 0.5 everywhere (every segment absorbs).
    chk = gradient_check(lambda xt: losses(xt)[2], x + 0.5 if init == "empty" else x, rtol=1e-3)
    if not chk["ok"]:
        raise RuntimeError(f"gradient check failed (reverse vs forward mode): {chk}")
    out = Recovery(start.astype(np.float32), gradient_check=chk)
    opt = ProjectedAdam(lr=lr, params={"sigma": x})
    for it in range(int(iterations) + 1):
        t0 = time.perf_counter()
        xt = opt["sigma"]                                   # gradients enabled by the optimizer
        data, reg, total = losses(xt)
        if it < iterations:
            dr.backward(total)
            opt.step()
        rec = {"iteration": it, "loss": float(total[0]), "data": float(data[0]),
               "smoothness": float(reg[0]) if smooth > 0 else 0.0, "seconds": time.perf_counter() - t0}
        if truth is not None:
            cur = np.asarray(dr.detach(xt).numpy())
            rec.update({f"density_{k}": v for k, v in density_error(cur, truth).items()})
        out.history.append(rec)
        if callback is not None:
            callback(it, rec)
    out.density = np.asarray(dr.detach(opt["sigma"]).numpy(), np.float32)
    return out
