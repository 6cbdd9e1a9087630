"""Shadowed receiver images per representation next to the Mitsuba reference, with 4x
enhanced difference images (seed 000 figures 4-5).

Each image shows the receiver plane (and the medium in front of it) from the same camera:
the reference is Mitsuba ``volpath`` on the density grid (or the deterministic ray-marched
ground truth for scenes Mitsuba cannot hold), ours use light transmittance from each
representation with bilinear shadow filtering, as in the paper.  The medium scatters
(single scattering, albedo 1) and the view is from the side, so the smoke's self-shadowing - where the
representations differ - is visible, not only the shadow on the wall behind it (which
every method here reproduces exactly: node methods keep the last node, FOM/OSM are exact
at far).
"""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from .. import build, kinds
from ._common import Results

METHODS = [("exact", {}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 12}), ("fom", {"harmonics": 16}),
           ("osm", {"slices": 32}), ("dsm", {"tolerance": 0.01})]


#: Side views: the light crosses the image, so the smoke's self-shadowing (where the
#: representations differ) is in view, with the receiver behind or below it.
CAMERAS = {
    "three_columns": dict(origin=[0.0, 0.5, 4.2], target=[0.2, 0.5, 0.0], up=[0, 1, 0], fov=52.0, aspect=2.2),
    "hair_and_smoke": dict(origin=[0.1, 0.0, 2.8], target=[0.15, 0.0, 0.0], up=[0, 1, 0], fov=40.0),
    "smoke_over_table": dict(origin=[0.0, 1.5, 2.4], target=[0.0, 0.35, 0.0], up=[0, 1, 0], fov=45.0),
    "plume": dict(origin=[0.0, 0.75, 3.4], target=[0.15, 0.75, 0.0], up=[0, 1, 0], fov=40.0),
}


def _label(kind, p):
    return kind if not p else f"{kind}-{next(iter(p.values()))}"


def run(quick: bool = False, out=None, force: bool = False) -> dict:
    """Run the experiment; write CSV, figures and meta.json into ``out``
    (default ``results/<name>/``); ``quick`` = small sizes, ``force`` = recompute."""
    from .. import capture, groundtruth, scenes as scene_lib, shading
    names = ["three_columns"] if quick else ["three_columns", "hair_and_smoke", "smoke_over_table"]
    params = dict(scenes=names, resolution=64 if quick else 256, image=48 if quick else 160,
                  spp=32 if quick else 256, filter="bilinear", albedo=1.0, reflectance=0.25)
    res = Results("images", out, quick, params)
    if res.exists() and not force:
        return {"csv": str(res.dir / "data.csv"), "out": str(res.dir), "cached": True}
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = []
    W = params["image"]
    for name in tqdm(names, desc="images", unit="scene"):
        scene = getattr(scene_lib, name)()
        cap = capture(scene, resolution=params["resolution"])
        cam = dict(CAMERAS.get(name, {}))
        Wx = int(round(W * cam.pop("aspect", 1.0)))
        look = dict(albedo=params["albedo"], reflectance=params["reflectance"], camera=cam or None)
        try:
            ref = groundtruth.render_reference(scene, width=Wx, height=W, spp=params["spp"], **look)
            ref_name = "Mitsuba volpath"
        except ValueError:
            ref = shading.groundtruth_plane(scene, width=Wx, height=W, **look)
            ref_name = "ray-marched ground truth"
        todo = [(k, p) for k, p in METHODS if k in kinds()]
        imgs = {}
        for kind, p in todo:
            rep = build(kind, cap.segments, **p)
            imgs[_label(kind, p)] = shading.shade_plane(scene, rep, cap, width=Wx, height=W,
                                                        filter=params["filter"], **look)
        exact_img = imgs.get("exact")
        vmax = float(np.percentile(ref, 99.5)) or 1.0
        # one row per representation: image, 4x |difference| to the reference, to exact
        aspect = Wx / W
        fig, axes = plt.subplots(len(imgs) + 1, 3, figsize=(3 * 2.4 * aspect, 2.3 * (len(imgs) + 1)), squeeze=False)
        for ax in axes.ravel():
            ax.axis("off")
        axes[0][0].imshow(ref, cmap="gray", vmin=0, vmax=vmax)
        axes[0][0].set_title(ref_name, fontsize=8)
        for row, (label, img) in enumerate(imgs.items(), start=1):
            vs_ref = shading.compare_images(ref, img)
            vs_exact = shading.compare_images(exact_img, img) if exact_img is not None else None
            axes[row][0].imshow(img, cmap="gray", vmin=0, vmax=vmax)
            axes[row][0].set_title(label, fontsize=9)
            axes[row][1].imshow(vs_ref["diff4x"], cmap="gray", vmin=0, vmax=vmax)
            axes[row][1].set_title(f"4x |{label} - reference|, rmse {vs_ref['rmse']:.3g}", fontsize=7)
            if vs_exact is not None:
                axes[row][2].imshow(vs_exact["diff4x"], cmap="gray", vmin=0, vmax=vmax)
                axes[row][2].set_title(f"4x |{label} - exact|, rmse {vs_exact['rmse']:.3g}", fontsize=7)
            kind = label.split("-")[0]
            rows.append(dict(scene=name, method=kind, param=label[len(kind) + 1:], reference=ref_name,
                             rmse_vs_reference=vs_ref["rmse"], max_abs_vs_reference=vs_ref["max_abs"],
                             rel_rmse_vs_reference=vs_ref["rel_rmse"],
                             rmse_vs_exact=vs_exact["rmse"] if vs_exact else "",
                             max_abs_vs_exact=vs_exact["max_abs"] if vs_exact else ""))
        fig.suptitle(f"{name}: {params['resolution']}^2 shadow map, {params['filter']} filtering")
        res.save_figure(fig, f"images_{name}.png")
        np.savez_compressed(res.dir / f"images_{name}.npz", reference=ref, **{k.replace("-", "_"): v for k, v in imgs.items()})
    csv = res.write_csv(rows)
    summary = {f"{r['scene']}_{r['method']}{r['param']}_rmse_vs_exact": r["rmse_vs_exact"] for r in rows}
    res.write_meta(summary)
    return {"csv": str(csv), "out": str(res.dir), "summary": summary, "figures": res.figures}
