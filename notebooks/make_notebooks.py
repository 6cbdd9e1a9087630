"""Regenerate notebooks 01-03 from this source: python notebooks/make_notebooks.py (run from the repo root)."""
import nbformat as nbf

def nb(cells, path):
    n = nbf.v4.new_notebook()
    n.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    n.cells = [nbf.v4.new_markdown_cell(c[1]) if c[0] == "md" else nbf.v4.new_code_cell(c[1]) for c in cells]
    nbf.write(n, path)

SIZE = '''import os
# The test suite runs these notebooks with AVSM_DR_NOTEBOOK_SMALL=1 (small sizes, fast).
SMALL = os.environ.get("AVSM_DR_NOTEBOOK_SMALL") == "1"
RES = 64 if SMALL else 256'''

nb([
("md", "# Quickstart: every representation on a built-in scene\n\nBuild the exact curve, AVSM, DSM, OSM and FOM from a captured smoke plume, look at the transmittance along one texel, and at the shadow each casts on the receiver plane."),
("code", "import avsm_dr as ad          # before drjit / mitsuba: picks a working libLLVM\nimport numpy as np\nimport matplotlib.pyplot as plt\n" + SIZE),
("md", "## Segments by hand\nTwo texels; the second has an opaque blocker (transmittance 0)."),
("code", "seg = ad.Segments.from_arrays([0, 2, 3], z0=[0.1, 0.4, 0.2], z1=[0.3, 0.5, 0.2], transmittance=[0.5, 0.7, 0.0])\nfor kind in ['exact', 'avsm']:\n    rep = ad.build(kind, seg)\n    print(kind, np.asarray(rep.eval([0, 0, 1, 1], [0.2, 0.9, 0.1, 0.3])))"),
("md", "## A captured scene"),
("code", "scene = ad.scenes.plume()\ncap = ad.capture(scene, resolution=RES)\nprint(cap.segments)\nreps = {\n    'exact': ad.build('exact', cap.segments),\n    'avsm-8': ad.build('avsm', cap.segments, nodes=8),\n    'dsm-0.01': ad.build('dsm', cap.segments, tolerance=0.01),\n    'osm-32': ad.build('osm', cap.segments, slices=32),\n    'fom-8': ad.build('fom', cap.segments, harmonics=8),\n}\nfor name, rep in reps.items():\n    print(f'{name:9s} {rep.nbytes_per_texel:8.1f} bytes/texel')"),
("md", "## Transmittance along the busiest texel"),
("code", "texel = int(np.argmax(cap.segments.counts))\nnear, far = cap.segments.bounds()\nz = np.linspace(near, far, 400)\nfig, ax = plt.subplots(figsize=(7, 4))\nfor name, rep in reps.items():\n    ax.plot(z, np.asarray(rep.eval(np.full(z.size, texel), z)), lw=2.5 if name == 'exact' else 1.2, label=name)\nax.set_xlabel('light-space depth'); ax.set_ylabel('transmittance'); ax.legend();"),
("md", "## Errors at the scene's receivers"),
("code", "texels, depths = cap.lookup(scene.receivers)\nexact = np.asarray(reps['exact'].eval(texels, depths))\nfor name, rep in reps.items():\n    err = np.asarray(rep.eval(texels, depths)) - exact\n    print(f'{name:9s} rmse {np.sqrt(np.mean(err**2)):.5f}  max {np.abs(err).max():.5f}')"),
("md", "## Shadows on the receiver plane\nThe same view, shaded with light transmittance from each representation."),
("code", "from avsm_dr import shading\nW = 48 if SMALL else 160\nimgs = {name: shading.shade_plane(scene, rep, cap, width=W, height=W) for name, rep in reps.items()}\nfig, axes = plt.subplots(1, len(imgs), figsize=(3 * len(imgs), 3))\nfor ax, (name, img) in zip(axes, imgs.items()):\n    ax.imshow(img, cmap='gray'); ax.set_title(name); ax.axis('off')"),
], "notebooks/01_quickstart.ipynb")

nb([
("md", "# Ground truth: our exact curve against Mitsuba 3\n\nThe same density grid is loaded as a Mitsuba heterogeneous medium; ratio tracking gives unbiased transmittance with standard errors. We compare it with the `exact` representation of the captured segments, for receivers on the shadow map's texel rays (so that only the capture's march error remains) and for arbitrary receivers (which adds the shadow map's spatial resolution)."),
("code", "import avsm_dr as ad\nimport numpy as np\nimport matplotlib.pyplot as plt\nfrom avsm_dr import groundtruth\n" + SIZE + "\nSPP = 64 if SMALL else 512"),
("code", "scene = ad.scenes.plume()\ncap = ad.capture(scene, resolution=RES)\nexact = ad.build('exact', cap.segments)\npoints = np.asarray(scene.receivers)\nmean, stderr = groundtruth.transmittance(scene, points, spp=SPP)\ntexels, depths = cap.lookup(points)\nours = np.asarray(exact.eval(texels, depths))\nz = (ours - mean) / np.maximum(stderr, 1e-9)\nprint(f'receivers {len(points)}, |ours - mitsuba| <= 3 stderr for {np.mean(np.abs(z) <= 3):.1%}')\nprint(f'rmse {np.sqrt(np.mean((ours - mean)**2)):.4f}, mean stderr {stderr.mean():.4f}')"),
("code", "fig, ax = plt.subplots(1, 2, figsize=(10, 4))\nax[0].errorbar(mean, ours, xerr=3 * stderr, fmt='.', ms=2, alpha=0.4)\nax[0].plot([0, 1], [0, 1], 'k:'); ax[0].set_xlabel('Mitsuba ratio tracking'); ax[0].set_ylabel('exact (captured)')\nax[1].hist(np.clip(z, -10, 10), bins=60); ax[1].set_xlabel('(ours - mitsuba) / stderr');"),
("md", "## Resolution: the gap shrinks as the shadow map gets finer"),
("code", "for res in ([64, 96] if SMALL else [64, 128, 256, 512]):\n    c = ad.capture(scene, resolution=res)\n    t, d = c.lookup(points)\n    o = np.asarray(ad.build('exact', c.segments).eval(t, d))\n    print(f'{res:4d}^2: rmse vs Mitsuba {np.sqrt(np.mean((o - mean)**2)):.4f}')"),
], "notebooks/02_ground_truth.ipynb")

nb([
("md", "# Error analysis: error against memory for every representation\n\nReads the CSV written by `python -m avsm_dr error_curves` (runs the quick version if it is missing) and draws error against bytes per texel, plus what the measurements say about the papers' claims."),
("code", "import json\nimport os\nfrom pathlib import Path\nimport avsm_dr  # noqa: F401  (first: picks Dr.Jit's libLLVM)\nimport matplotlib.pyplot as plt\nfrom avsm_dr.experiments import error_curves\nfrom avsm_dr.experiments._common import read_csv\nSMALL = os.environ.get('AVSM_DR_NOTEBOOK_SMALL') == '1'\nout = Path(os.environ.get('AVSM_DR_RESULTS', 'results')) / ('error_curves_quick' if SMALL else 'error_curves')\nresult = error_curves.run(quick=SMALL, out=out)\nrows = read_csv(result['csv'])\nprint(len(rows), 'rows')"),
("code", "scenes = sorted({r['scene'] for r in rows if '_range_' not in r['scene']})\nfig, axes = plt.subplots(1, len(scenes), figsize=(4.5 * len(scenes), 3.6), squeeze=False)\nfor ax, s in zip(axes[0], scenes):\n    for m in ['avsm', 'fom', 'osm', 'dsm']:\n        rs = [r for r in rows if r['scene'] == s and r['method'] == m]\n        if rs:\n            ax.loglog([float(r['bytes_per_texel']) for r in rs], [max(float(r['rmse']), 1e-6) for r in rs], 'o-', label=m)\n    ax.set_title(s); ax.set_xlabel('bytes per texel')\naxes[0][0].set_ylabel('RMSE vs exact'); axes[0][0].legend();"),
("md", "## The papers' claims, as measured"),
("code", "print(json.dumps(json.loads((out / 'findings.json').read_text()), indent=1))"),
], "notebooks/03_error_analysis.ipynb")
