"""Shadowed images per representation against a converged, deterministic reference, ranked
by RMSE, PSNR and FLIP, with signed difference images, zoom-ins and a leak / dark split
(the AVSM paper's figures 4-5: Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010).

Each image shows the receiver plane and the smoke in front of it from one side camera,
single scattering (albedo 1) plus the diffuse plane (:func:`avsm_dr.shading.render_plane`).
All images share the view-ray quadrature; only the light's transmittance T differs:

* **reference**: T by float64 midpoint quadrature of the trilinear density along the
  light ray of every shading point (:func:`quadrature_light`, step voxel / 8; Dr.Jit,
  one lane per point; analytic factors for hair, particles, blockers) - not a shadow map;
* **methods**: T looked up in each representation built on a ``resolution``^2 capture,
  bilinear filtering.

The reference is validated against Mitsuba 3 ``volpath`` (max_depth 2) at high spp on a
crop around the zoom window (a camera aimed there with the image's pixel pitch): RMSE over
the pixels away from surface silhouettes against Mitsuba's standard error from independent
seeds (ratio ~1: the difference is Mitsuba's noise); its own quadrature error is measured
by re-rendering the crop with half the steps (``self_convergence_rmse``).

Metrics (image ``I``, reference ``R``, display white ``S`` = 99.5th percentile of R):
RMSE; PSNR = 10 log10(S^2 / MSE); FLIP (Andersson et al., "FLIP: A Difference Evaluator for
Alternating Images", HPG 2020; ``flip_evaluator``, LDR, on min(I / S, 1) sRGB-encoded, 67
pixels per degree); signed ``e = I - R`` (> 0: light leaking): mean, mean of max(e, 0)
(leak) and of max(-e, 0) (dark), share of pixels with e > 0.02 S (leak) or e < -0.02 S.

The claims (rankings) use these image metrics: the study is about the pictures, so the
receiver RMSE of the shadow-map harness does not apply (the pixels are the receivers here,
and their signed mean and leak share are ``mean_signed`` and ``leak_pixels``).  Beside them
every row carries the curve metrics of the map that made the image, cheap at the map's
resolution: ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2` against the exact
curve of the same capture), ``order`` ('depth' for the kinds whose build depends on the
insertion order: the capture is front to back; '-' otherwise), ``bytes`` (sparse layout) and
``bytes_dense``.  One configuration per scene: no interval.
"""

from __future__ import annotations

import dataclasses
import math

import drjit as dr
import numpy as np
from tqdm import tqdm

from avsm_dr import backend, build, kinds
from avsm_dr.receivers import voxel_step
from ._headline import listing, num
from ._study import Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi, Vidimce, Lauritzen and Lefohn, "Adaptive Volumetric Shadow Maps", EGSR 2010, '
    'figures 4-5: shadowed images per representation next to a reference, with difference '
    'images.'
)


METHODS = [("exact", {}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 12}), ("fom", {"harmonics": 16}),
           ("osm", {"slices": 32}), ("moments", {}), ("dsm", {"tolerance": 0.01})]

#: Side views: the light crosses the image, so the smoke's self-shadowing (where the
#: representations differ) is in view, with the receiver behind or below it.
CAMERAS = {
    "three_columns": dict(origin=[0.0, 0.5, 4.2], target=[0.2, 0.5, 0.0], up=[0, 1, 0], fov=52.0, aspect=2.2),
    "hair_and_smoke": dict(origin=[0.1, 0.0, 2.8], target=[0.15, 0.0, 0.0], up=[0, 1, 0], fov=40.0),
    "smoke_over_table": dict(origin=[0.0, 1.5, 2.4], target=[0.0, 0.35, 0.0], up=[0, 1, 0], fov=45.0),
    "plume": dict(origin=[0.0, 0.75, 3.4], target=[0.15, 0.75, 0.0], up=[0, 1, 0], fov=40.0),
    "simulated_plume": dict(origin=[0.0, 0.75, 3.4], target=[0.15, 0.75, 0.0], up=[0, 1, 0], fov=40.0),
}
#: Light-ray quadrature step of the reference, in smallest voxel sides.
LIGHT_STEP = 1 / 8
#: Single-scattering step along view rays (all images), in smallest voxel sides.
VIEW_STEP = 1 / 4
#: |e| above this share of the display white counts a pixel as leaking / over-dark.
PIXEL_THRESHOLD = 0.02


def _label(kind, p):
    return kind if not p else f"{kind}-{next(iter(p.values()))}"


#: Parameters of the full and the quick run.
FULL = dict(scenes=["three_columns", "hair_and_smoke", "smoke_over_table", "simulated_plume"], resolution=256,
            image=160, supersample=2, crop=32, crop_spp=32768, crop_seeds=8, filter="bilinear", albedo=1.0,
            reflectance=0.25, light_step=LIGHT_STEP, view_step=VIEW_STEP, methods=[_label(k, p) for k, p in METHODS])
QUICK = dict(FULL, scenes=["three_columns"], resolution=64, image=48, supersample=1, crop=16, crop_spp=4096,
             crop_seeds=4)


# ============================================================ reference light T
def _march_grid(g, lo, hi, o, d, L, step):
    """Optical depth (K,) float64 of the trilinear grid along o + t d, t in [0, L] clipped to
    the box: ``ceil(length / step)`` equal midpoint pieces per ray, one Dr.Jit lane per ray
    (the sampling convention of :func:`avsm_dr.groundtruth.sample_density`)."""
    from avsm_dr.geometry import ray_box
    m = backend.types()
    t0, t1, _ = ray_box(o, d, lo, hi)
    t0 = np.maximum(t0, 0.0)
    length = np.maximum(np.minimum(t1, L) - t0, 0.0)
    n = np.ceil(length / step)
    h = np.where(n > 0, length / np.maximum(n, 1), 0.0)
    tau = np.zeros(o.shape[0])
    rays = np.nonzero(n > 0)[0]
    if rays.size == 0:
        return tau
    nz, ny, nx = g.shape
    G = m.Float64(np.ascontiguousarray(g, np.float64).ravel())
    dims = (nx, ny, nz)
    F = lambda a: m.Float64(np.ascontiguousarray(a, np.float64))  # noqa: E731
    org = [F(o[rays, a] + t0[rays] * d[rays, a]) for a in range(3)]
    dirs = [F(d[rays, a]) for a in range(3)]
    hh, count = F(h[rays]), m.UInt32(n[rays].astype(np.uint32))
    scale = [dims[a] / (hi[a] - lo[a]) for a in range(3)]

    def body(j, acc):
        t = (m.Float64(j) + 0.5) * hh
        idx, frac = [], []
        for a in range(3):
            u = dr.clip((org[a] + t * dirs[a] - lo[a]) * scale[a] - 0.5, 0.0, dims[a] - 1.0)
            i0 = dr.minimum(m.UInt32(dr.floor(u)), max(dims[a] - 2, 0))
            idx.append(i0)
            frac.append(u - m.Float64(i0))
        sig = m.Float64(0.0)
        for cz in (0, 1):
            kz = dr.minimum(idx[2] + cz, nz - 1)
            wz = frac[2] if cz else 1.0 - frac[2]
            for cy in (0, 1):
                ky = dr.minimum(idx[1] + cy, ny - 1)
                wy = frac[1] if cy else 1.0 - frac[1]
                for cx in (0, 1):
                    kx = dr.minimum(idx[0] + cx, nx - 1)
                    wx = frac[0] if cx else 1.0 - frac[0]
                    sig += wz * wy * wx * dr.gather(m.Float64, G, (kz * ny + ky) * nx + kx)
        return j + 1, acc + sig * hh

    _, acc = dr.while_loop((m.UInt32(0), dr.zeros(m.Float64, rays.size)), lambda j, acc: j < count, body,
                           label="images_light_quadrature")
    tau[rays] = acc.numpy()
    return tau


def quadrature_light(scene, step_fraction: float = LIGHT_STEP):
    """Callable points (N, 3) -> (N,) float64 transmittance from ``scene.light``: the grid
    by float64 midpoint quadrature (step ``step_fraction`` x the smallest voxel side),
    times the analytic particle / hair / blocker factors of
    :func:`avsm_dr.groundtruth.transmittance` - the same numbers as its ``'raymarch'``
    method, computed with one Dr.Jit lane per point."""
    from avsm_dr import groundtruth as gt
    from avsm_dr.groundtruth.content import check_scene
    from avsm_dr.groundtruth.tracking import default_step
    content = check_scene(scene)
    others = dataclasses.replace(scene, density=None, bbox=None)
    has_others = content["particles"] is not None or content["hair"] is not None or bool(content["blockers"])

    def light_T(points):
        p = np.asarray(points, np.float64).reshape(-1, 3)
        T = np.ones(p.shape[0])
        if content["grid"] is not None:
            g, lo, hi = content["grid"]
            o, d, L = gt.light_paths(scene, p)
            T = np.exp(-_march_grid(g, lo, hi, o, d, L, default_step(g, lo, hi, step_fraction)))
        if has_others:
            T = T * gt.transmittance(others, p, method="raymarch")[0]
        return T
    return light_T


# ====================================================================== metrics
def _srgb(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1 / 2.4) - 0.055)


def _ldr(img, white):
    """(H, W, 3) float32 sRGB-encoded min(img / white, 1), the input FLIP's LDR mode expects."""
    x = _srgb(np.clip(np.asarray(img, np.float64) / white, 0.0, 1.0))
    return np.ascontiguousarray(np.repeat(x[..., None], 3, axis=2), np.float32)


def image_metrics(reference, image, white: float) -> tuple[dict, np.ndarray]:
    """(metrics, FLIP error map (H, W)) of ``image`` against ``reference`` (module docstring);
    ``white``: the display white S (> 0)."""
    import flip_evaluator
    R = np.asarray(reference, np.float64)
    e = np.asarray(image, np.float64) - R
    mse = float(np.mean(e ** 2))
    fmap, fmean, _ = flip_evaluator.evaluate(_ldr(R, white), _ldr(image, white), "LDR", applyMagma=False)
    fmap = np.asarray(fmap, np.float64)
    fmap = fmap[..., 0] if fmap.ndim == 3 else fmap
    thr = PIXEL_THRESHOLD * white
    return dict(rmse=math.sqrt(mse), psnr=10 * math.log10(white ** 2 / mse) if mse > 0 else float("inf"),
                flip=float(fmean), mean_signed=float(e.mean()), leak_mean=float(np.maximum(e, 0).mean()),
                dark_mean=float(np.maximum(-e, 0).mean()), leak_pixels=float(np.mean(e > thr)),
                dark_pixels=float(np.mean(e < -thr)), max_abs=float(np.abs(e).max())), fmap


# =================================================================== validation
def _crop_camera(scene, cam: dict, width: int, height: int, row: int, col: int, crop: int) -> dict:
    """A camera aimed through pixel (row, col) of the ``width`` x ``height`` image with the
    field of view of ``crop`` of its pixels (Mitsuba's fov is horizontal): the same pixel
    pitch, so the crop shows the image's pixels around (row, col) (exactly at the centre)."""
    from avsm_dr.groundtruth import camera_rays
    o, d = camera_rays(scene, width, height, cam, 1)
    k = row * width + col
    fov = 2 * math.degrees(math.atan(math.tan(math.radians(cam["fov"]) / 2) * crop / width))
    return dict(cam, target=(o[k] + d[k]).tolist(), fov=fov)


def _check_reference(scene, ccam, crop, spp, seeds, look):
    """The reference on a crop: against itself with half the quadrature steps (its
    discretisation error, ``self_convergence_rmse``) and with 8 x 8 instead of 4 x 4 rays per
    pixel (``pixel_integration_rmse``, interior pixels), and, for grid / blocker scenes,
    against Mitsuba ``volpath`` (``seeds`` independent renders of spp / seeds samples: mean
    and standard error), compared at 8 x 8 rays per pixel."""
    from avsm_dr import groundtruth, shading
    step = voxel_step(scene, VIEW_STEP)
    light = quadrature_light(scene)
    ref = shading.render_plane(scene, light, crop, crop, ccam, supersample=4, step=step, **look)
    fine = shading.render_plane(scene, quadrature_light(scene, LIGHT_STEP / 2), crop, crop, ccam, supersample=4,
                                step=step / 2, **look)
    ref8 = shading.render_plane(scene, light, crop, crop, ccam, supersample=8, step=step, **look)
    inner = _interior_pixels(scene, ccam, crop)
    out = dict(crop=crop, crop_mean=float(ref.mean()),
               self_convergence_rmse=float(np.sqrt(np.mean((ref - fine) ** 2))),
               pixel_integration_rmse=float(np.sqrt(np.mean((ref - ref8)[inner] ** 2))))
    if scene.hair is not None or scene.particles is not None:      # Mitsuba renders grids and blockers only
        return out, (ref8, None, None)
    runs = np.stack([groundtruth.render_reference(scene, width=crop, height=crop, spp=spp // seeds, camera=ccam,
                                                  seed=s, **look) for s in range(seeds)])
    mits, se = runs.mean(0), runs.std(0, ddof=1) / math.sqrt(seeds)
    diff = ref8 - mits
    rmse, se_rms = float(np.sqrt(np.mean(diff[inner] ** 2))), float(np.sqrt(np.mean(se[inner] ** 2)))
    out.update(crop_spp=spp, crop_seeds=seeds, interior_pixels=int(inner.sum()), vs_mitsuba_rmse=rmse,
               vs_mitsuba_mean=float(diff[inner].mean()), mitsuba_stderr_rms=se_rms,
               rmse_over_stderr=rmse / se_rms if se_rms > 0 else float("nan"),
               bias_bound=float(math.sqrt(max(rmse ** 2 - se_rms ** 2, 0.0))),
               vs_mitsuba_rmse_all_pixels=float(np.sqrt(np.mean(diff ** 2))))
    return out, (ref8, mits, np.where(inner, se, np.nan))


def _interior_pixels(scene, cam, crop, s: int = 4):
    """(crop, crop) True where a pixel and its 8 neighbours are all fully on, or all fully
    off, the receiver plane (s x s sub-rays, blockers in front counted): away from the
    silhouettes, where Mitsuba's random in-pixel positions and our stratified ones
    integrate a step edge differently (measured up to 50 % of a pixel's value)."""
    from avsm_dr import groundtruth
    from avsm_dr.scene import OpaquePlane
    o, d = groundtruth.camera_rays(scene, crop, crop, cam, s)
    c, n, half = groundtruth.receiver_plane_for(scene, groundtruth.check_camera(scene, cam))
    tp = OpaquePlane(c, n, half).surface_hit(o, d)
    tb = np.full(tp.shape, np.inf)
    for b in scene.blockers or []:
        tb = np.minimum(tb, b.surface_hit(o, d))
    seen = np.isfinite(tp) & (tp < tb)
    cov = seen.reshape(crop, crop, s * s).mean(axis=2)
    out = np.zeros((crop, crop), bool)
    for full in (cov == 1, cov == 0):
        p = np.pad(full, 1)
        e = full.copy()
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                e &= p[1 + dy:1 + dy + crop, 1 + dx:1 + dx + crop]
        out |= e
    return out


def _zoom_window(diffs, size):
    """(row, col) top-left of the size x size window with the largest mean |difference|
    summed over ``diffs`` (box filter by cumulative sums)."""
    a = sum(np.abs(d) for d in diffs)
    H, W = a.shape
    s = min(size, H, W)
    c = np.pad(a.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    box = c[s:, s:] - c[:-s, s:] - c[s:, :-s] + c[:-s, :-s]
    r, q = np.unravel_index(int(np.argmax(box)), box.shape)
    return int(r), int(q), s


# ========================================================================== run
def _resolved(order, imgs, scored, eps):
    """For each method in ``order`` (by RMSE), is its lead over the next one larger than the
    reference's own error can account for?  With R = R_true + e, the squared-error gap
    mean(e_b^2) - mean(e_a^2) moves by at most 2 |e| |I_a - I_b| (RMS norms, Cauchy-Schwarz);
    ``eps`` (the crop's self-convergence RMSE) stands in for |e|."""
    out = {}
    for a, b in zip(order, order[1:]):
        gap = scored[b][0]["rmse"] ** 2 - scored[a][0]["rmse"] ** 2
        out[a] = bool(gap > 2 * eps * float(np.sqrt(np.mean((imgs[a] - imgs[b]) ** 2))))
    return out


def _compute(res, params: dict) -> dict:
    """Each scene's images per representation against the reference, the crops and the ranking."""
    from avsm_dr import capture, scenes as scene_lib, shading
    from avsm_dr.evaluation import curve_values, depth_l2
    from .error_curves.labels import order_dependent
    names = params["scenes"]
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows, summary = [], {}
    H = params["image"]
    for name in tqdm(names, desc="images", unit="scene"):
        scene = getattr(scene_lib, name)()
        cap = capture(scene, resolution=params["resolution"], order="depth")
        cam = dict(CAMERAS.get(name, {}))
        Wx = int(round(H * cam.pop("aspect", 1.0)))
        look = dict(albedo=params["albedo"], reflectance=params["reflectance"])
        common = dict(camera=cam, supersample=params["supersample"], step=voxel_step(scene, VIEW_STEP), **look)
        ref = shading.render_plane(scene, quadrature_light(scene), Wx, H, **common)
        imgs, maps = {}, {}
        ex_curve = curve_values(build("exact", cap.segments), cap.segments)
        for kind, p in METHODS:
            if kind in kinds():
                rep = build(kind, cap.segments, **p)
                imgs[_label(kind, p)] = shading.shade_plane(scene, rep, cap, Wx, H, filter=params["filter"],
                                                            **common)
                # the curve metrics of the map that made the image (module docstring)
                maps[_label(kind, p)] = dict(order="depth" if order_dependent(kind) else "-",
                                             depth_l2=depth_l2(rep, cap.segments, exact=ex_curve),
                                             bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel)
        zoom = _zoom_window([v - ref for k, v in imgs.items() if k != "exact"] or [ref], max(8, H // 4))
        r0, c0, zs = zoom
        ccam = _crop_camera(scene, cam, Wx, H, r0 + zs // 2, c0 + zs // 2, params["crop"])
        check, crops = _check_reference(scene, ccam, params["crop"], params["crop_spp"], params["crop_seeds"], look)
        summary[f"{name}_reference_check"] = check
        white = float(np.percentile(ref, 99.5)) or float(ref.max()) or 1.0
        scored = {label: image_metrics(ref, img, white) for label, img in imgs.items()}
        order_rmse = sorted(scored, key=lambda k: scored[k][0]["rmse"])
        order_flip = sorted(scored, key=lambda k: scored[k][0]["flip"])
        resolved = _resolved(order_rmse, imgs, scored, check["self_convergence_rmse"])
        for label, (met, _) in scored.items():
            kind = label.split("-")[0]
            row = dict(scene=name, method=kind, param=label[len(kind) + 1:], reference="float64 quadrature",
                       resolution=params["resolution"], **met, rank_rmse=order_rmse.index(label) + 1,
                       rank_flip=order_flip.index(label) + 1, ahead_of_next_resolved=resolved.get(label, ""),
                       white=white, reference_self_convergence_rmse=check["self_convergence_rmse"], **maps[label])
            if "vs_mitsuba_rmse" in check:
                row.update(reference_vs_mitsuba_rmse=check["vs_mitsuba_rmse"],
                           mitsuba_stderr_rms=check["mitsuba_stderr_rms"])
            rows.append(row)
        summary[f"{name}_ranking_rmse"] = order_rmse
        summary[f"{name}_ranking_flip"] = order_flip
        _figure(plt, res, name, params, ref, imgs, scored, white, zoom, crops, check)
        res.write_npz(f"images_{name}.npz", reference=ref,
                      **{k.replace("-", "_").replace(".", "p"): v for k, v in imgs.items()})
    _ranking_figure(plt, res, rows, names)
    return dict(rows=rows, summary=summary)


# ====================================================================== figures
def _figure(plt, res, name, params, ref, imgs, scored, white, zoom, crops, check):
    """Rows: the reference (zoom window yellow; crop checks: quadrature, Mitsuba, their
    difference in standard errors), then each method: image, signed difference, FLIP map,
    zoomed image, zoomed difference."""
    from matplotlib.patches import Rectangle
    H, W = ref.shape
    r0, c0, s = zoom
    diffs = {k: v - ref for k, v in imgs.items()}
    dmax = max(float(np.percentile(np.abs(np.stack(list(diffs.values()))), 99.9)), 1e-12)
    aspect = W / H
    n = len(imgs) + 1
    fig, axes = plt.subplots(n, 5, figsize=(2.3 * (3 * aspect + 2), 2.2 * n), squeeze=False,
                             gridspec_kw=dict(width_ratios=[aspect, aspect, aspect, 1, 1]))
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    gray = dict(cmap="gray", vmin=0, vmax=white, interpolation="nearest")
    signed = dict(cmap="RdBu_r", vmin=-dmax, vmax=dmax, interpolation="nearest")
    win = (slice(r0, r0 + s), slice(c0, c0 + s))
    axes[0][0].imshow(ref, **gray)
    axes[0][0].add_patch(Rectangle((c0 - 0.5, r0 - 0.5), s, s, fill=False, ec="yellow", lw=1))
    axes[0][0].set_title("reference: float64 quadrature (yellow: zoom, crop)", fontsize=7)
    qref, mits, se = crops
    axes[0][1].imshow(qref, **gray)
    axes[0][1].set_title(f"crop: quadrature; half steps differ by {check['self_convergence_rmse']:.1g} rms",
                         fontsize=7)
    if mits is not None:
        axes[0][2].imshow(mits, **gray)
        axes[0][2].set_title(f"crop: Mitsuba {check['crop_spp']} spp; interior rmse {check['vs_mitsuba_rmse']:.2g}"
                             f" = {check['rmse_over_stderr']:.2f} stderr", fontsize=7)
        z = np.where(se > 1e-6 * np.abs(mits), (qref - mits) / np.where(se > 0, se, 1.0), 0.0)
        axes[0][4].imshow(np.where(np.isnan(se), np.nan, z), cmap="RdBu_r", vmin=-4, vmax=4,
                          interpolation="nearest")
        axes[0][4].set_title("(quad. - Mitsuba) / stderr, interior", fontsize=7)
    axes[0][3].imshow(ref[win], **gray)
    axes[0][3].set_title("zoom", fontsize=8)
    for row, (label, img) in enumerate(imgs.items(), start=1):
        met, fmap = scored[label]
        axes[row][0].imshow(img, **gray)
        axes[row][0].set_title(f"{label}: rmse {met['rmse']:.2g}, PSNR {met['psnr']:.1f} dB", fontsize=7)
        axes[row][1].imshow(diffs[label], **signed)
        axes[row][1].set_title(f"signed (red: leak {met['leak_mean']:.1g}, blue: dark {met['dark_mean']:.1g})",
                               fontsize=7)
        axes[row][2].imshow(fmap, cmap="magma", vmin=0, vmax=1, interpolation="nearest")
        axes[row][2].set_title(f"FLIP {met['flip']:.3g}", fontsize=7)
        axes[row][3].imshow(img[win], **gray)
        axes[row][4].imshow(diffs[label][win], **signed)
    fig.suptitle(f"{name}: {params['resolution']}^2 shadow map, {params['filter']} filtering; "
                 f"signed differences +-{dmax:.2g}", y=1.0)
    fig.tight_layout()
    res.save_figure(fig, f"images_{name}.png")


def _ranking_figure(plt, res, rows, names):
    """Per scene: leak (up) and dark (down) mean differences, and FLIP, per method."""
    fig, axes = plt.subplots(2, len(names), figsize=(4.5 * len(names), 6), squeeze=False)
    for j, name in enumerate(names):
        rs = sorted([r for r in rows if r["scene"] == name], key=lambda r: r["rank_rmse"])
        labels = [r["method"] + (f"-{r['param']}" if r["param"] else "") for r in rs]
        x = np.arange(len(rs))
        axes[0][j].bar(x, [r["leak_mean"] for r in rs], color="C3", label="leak (mean max(e, 0))")
        axes[0][j].bar(x, [-r["dark_mean"] for r in rs], color="C0", label="dark (mean max(-e, 0))")
        axes[0][j].axhline(0, color="k", lw=0.5)
        for sgn in (1, -1):
            axes[0][j].axhline(sgn * rs[0]["reference_self_convergence_rmse"], color="k", ls=":", lw=0.8,
                               label="reference error (rms)" if sgn > 0 else None)
        axes[0][j].set_title(f"{name} (sorted by RMSE)", fontsize=9)
        axes[1][j].bar(x, [r["flip"] for r in rs], color="C2")
        axes[1][j].set_ylabel("mean FLIP")
        for ax in axes[:, j]:
            ax.set_xticks(x)
            ax.set_xticklabels(labels, rotation=45, ha="right", fontsize=7)
    axes[0][0].legend(fontsize=7)
    axes[0][0].set_ylabel("signed image error (radiance)")
    fig.tight_layout()
    res.save_figure(fig, "ranking.png")

def _headline(s: dict) -> list[str]:
    """Per scene: the ranking by image RMSE and by FLIP, and the reference's check against Mitsuba."""
    out = []
    for key, v in s.items():
        if key.endswith("_ranking_rmse"):
            scene = key[:-len("_ranking_rmse")]
            out.append(f"{scene}, best to worst by RMSE: {listing(v, 10)}")
            out.append(f"{scene}, best to worst by FLIP: {listing(s.get(scene + '_ranking_flip', []), 10)}")
        elif key.endswith("_reference_check"):
            out.append(f"{key[:-len('_reference_check')]} reference vs Mitsuba: RMSE {num(v['vs_mitsuba_rmse'])} "
                       f"= {num(v['rmse_over_stderr'])}x its standard error, bias bound {num(v['bias_bound'])}")
    return out


STUDY = Study("images", "Shadowed images per representation against a converged, deterministic reference",
              REPRODUCES, FULL, QUICK, _compute, writes=("data.csv", "images_<scene>.npz"), headline=_headline)
run = STUDY.run
