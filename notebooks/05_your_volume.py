# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Compare representations on your own volume
#
# Point `VOLUME` at your density grid (a Mitsuba `.vol` file, or a NumPy `.npy` array indexed
# `(z, y, x)`; the environment variable `AVSM_DR_VOLUME` does the same), choose the representations
# in `KINDS`, and run every cell. Without a volume the notebook uses a built-in smoke plume simulated
# with stable fluids (`ad.scenes.simulated_plume`). It captures the volume from the light, builds
# every representation over its size sweep (read from the registry), and shows
#
# * error curves: RMSE against bytes per texel, against the exact curve of the same segments (what
#   compression loses) and against the true transmittance (a float64 ray march of the grid),
# * shadow images on the receiver plane, with signed error heat maps (> 0: the representation lets
#   too much light through).

# %%
import dataclasses
import os
from pathlib import Path

import avsm_dr as ad          # before drjit / mitsuba: picks a working libLLVM
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import TwoSlopeNorm
from matplotlib.ticker import NullFormatter
from avsm_dr import groundtruth, receivers, shading

# The test suite runs the notebooks with AVSM_DR_NOTEBOOK_SMALL=1 (small sizes, fast).
SMALL = os.environ.get('AVSM_DR_NOTEBOOK_SMALL') == '1'
VOLUME = os.environ.get('AVSM_DR_VOLUME')     # or a path: VOLUME = 'smoke.vol'
DENSITY_SCALE = 1.0                            # extinction = DENSITY_SCALE x grid value (nothing else rescales it)
BBOX = None                                    # world box ((x0, y0, z0), (x1, y1, z1)); None: the .vol header's,
                                               # else voxels of side 1 centred at the origin (never stretched)
BYTES = 32                                     # the budget: sparse bytes per texel
KINDS = ['avsm', 'fom', 'osm', 'moments', 'dsm']
RES = 64 if SMALL else 256                     # shadow map: RES x RES texels
N_RECEIVERS = 512 if SMALL else 4096           # in-volume receivers for the error curves
IMG = 40 if SMALL else 96                      # shadow images: IMG x IMG pixels
print('registered kinds:', ', '.join(ad.kinds()))
unknown = [k for k in KINDS if k not in ad.kinds()]
if unknown:
    raise ValueError(f'KINDS: unknown kinds {unknown}; choose from {ad.kinds()}')

# %% [markdown]
# ## Load the volume
# `ad.Scene.from_grid` reads your grid in its own box and units (`BBOX`, `DENSITY_SCALE`: see
# the docs page "Measuring a representation"), lit by a directional light from above. A wall
# behind the volume, facing the light, receives its shadow for the images below. The command-line
# answer to "which kind at `BYTES` bytes per texel" is `python -m experiments budget --volume
# my.vol --bytes 32` (docs: "Which kind fits my byte budget").

# %%
scene = ad.scenes.simulated_plume(size=16 if SMALL else 32)
if VOLUME:
    path = Path(VOLUME)
    scene = ad.Scene.from_grid(path, bbox=BBOX, density_scale=DENSITY_SCALE)
    lo, hi = (np.asarray(v, np.float64) for v in scene.bbox)
    d = np.asarray(scene.light.direction, np.float64)
    d /= np.linalg.norm(d)
    reach = 0.5 * float(np.linalg.norm(hi - lo))          # the box's half diagonal
    wall = (0.5 * (lo + hi) + 1.05 * reach * d, -d, reach)  # centre, normal (towards the light), half side
    scene = dataclasses.replace(scene, receiver_plane=wall)
lo, hi = (np.asarray(v, np.float64) for v in scene.bbox)
print(f'{scene.name}: grid {scene.density.shape} (z, y, x) in the box {lo.round(3).tolist()} .. '
      f'{hi.round(3).tolist()}, max extinction {scene.density.max():.1f} per world unit')
fig, axes = plt.subplots(1, 3, figsize=(10, 3.2))
for ax, axis, title in zip(axes, (0, 1, 2), ('summed along z', 'summed along y', 'summed along x')):
    ax.imshow(scene.density.sum(axis=axis), origin='lower', cmap='magma')
    ax.set_title(title)
    ax.axis('off')
plt.show()

# %% [markdown]
# ## Capture, receivers and the truth
# One light ray per texel gives the segments every representation is built from. Receivers are
# drawn inside the medium where it contributes to an image (`avsm_dr.receivers.in_volume`); the
# truth at them is a float64 ray march of the grid, independent of the capture.

# %%
cap = ad.capture(scene, resolution=RES, order="depth")
print(cap.segments)
points = receivers.in_volume(scene, N_RECEIVERS, seed=0)
truth = groundtruth.transmittance(scene, points, method='raymarch')[0]
exact_rep = ad.build('exact', cap.segments)
exact = np.asarray(cap.transmittance(exact_rep, points, filter='bilinear'), np.float64)
print(f'{len(points)} receivers; the exact map is {np.sqrt(np.mean((exact - truth) ** 2)):.4f} RMS from the truth '
      '(capture and texel size: no representation can do better)')

# %% [markdown]
# ## Error curves
# Every size of each kind's sweep (`ad.configurations(kind)`: the headline configuration with the size
# parameter varied).

# %%
curves = {}
for kind in KINDS:
    for params in ad.configurations(kind, quick=SMALL):
        rep = ad.build(kind, cap.segments, **params)
        T = np.asarray(cap.transmittance(rep, points, filter='bilinear'), np.float64)
        curves.setdefault(kind, []).append((rep.nbytes_per_texel, np.sqrt(np.mean((T - exact) ** 2)),
                                            np.sqrt(np.mean((T - truth) ** 2)), np.mean(T - exact), params,
                                            rep.nbytes_sparse_per_texel))
fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharex=True)
for kind, pts in curves.items():
    pts = sorted(pts, key=lambda p: p[0])
    x = [p[0] for p in pts]
    axes[0].loglog(x, [max(p[1], 1e-6) for p in pts], 'o-', ms=3, label=kind)
    axes[1].loglog(x, [p[2] for p in pts], 'o-', ms=3, label=kind)
axes[1].axhline(np.sqrt(np.mean((exact - truth) ** 2)), color='k', ls=':', label='exact map')
axes[0].set(xlabel='bytes per texel', ylabel='RMSE', title='against the exact curve (compression)')
axes[1].set(xlabel='bytes per texel', title='against the true transmittance')
for ax in axes:
    ax.grid(alpha=0.3, which='both')
    ax.xaxis.set_minor_formatter(NullFormatter())
axes[1].legend(fontsize=8)
plt.show()
print(f'the most accurate setting of each kind within {BYTES} sparse bytes per texel (against the truth):')
for kind, pts in curves.items():
    fits = [p for p in pts if p[5] <= BYTES]
    if not fits:
        print(f'{kind:9s} no setting of the sweep fits (smallest: {min(p[5] for p in pts):.1f} B)')
        continue
    best = min(fits, key=lambda p: p[2])
    print(f'{kind:9s} {best[4]}: {best[5]:.1f} B/texel sparse ({best[0]:.0f} dense), RMSE {best[2]:.4f} vs truth, '
          f'{best[1]:.4f} vs exact, mean signed {best[3]:+.4f}')

# %% [markdown]
# ## Shadow images and signed errors
# The view of the volume in front of its wall, lit through each representation at its headline
# configuration, with single scattering in the medium (albedo `ALBEDO`): the wall behind the volume
# only sees each texel's total optical depth, which every kind stores exactly, while the light
# scattered inside the medium depends on the whole curve. Next to them the exact curve's image and
# the ray-marched truth. Error maps: the representation's image minus the exact curve's (compression
# only) on one diverging colour scale centred on zero, and the exact curve's own error against the
# truth on its own scale.

# %%
ALBEDO = 0.8
view = dict(width=IMG, height=IMG, albedo=ALBEDO)
images = {'truth': shading.groundtruth_plane(scene, **view),
          'exact': shading.shade_plane(scene, exact_rep, cap, filter='bilinear', **view)}
for kind in KINDS:
    rep = ad.build(kind, cap.segments, **ad.describe(kind)['headline'])
    images[kind] = shading.shade_plane(scene, rep, cap, filter='bilinear', **view)
errors = {k: img - images['exact'] for k, img in images.items() if k not in ('truth', 'exact')}
scale = max(max(float(np.abs(e).max()) for e in errors.values()), 1e-6)
norm = TwoSlopeNorm(vcenter=0.0, vmin=-scale, vmax=scale)
n = len(images)
fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 5.8))
vmax = max(float(np.percentile(img, 99.5)) for img in images.values())
for ax, (name, img) in zip(axes[0], images.items()):
    ax.imshow(img, cmap='gray', vmin=0, vmax=vmax)
    ax.set_title(name, fontsize=9)
for ax, (name, err) in zip(axes[1][2:], errors.items()):
    im = ax.imshow(err, cmap='RdBu_r', norm=norm)
    ax.set_title(f'{name} - exact\nRMS {np.sqrt(np.mean(err ** 2)):.2g}', fontsize=8)
own = images['exact'] - images['truth']
s0 = max(float(np.abs(own).max()), 1e-6)
im0 = axes[1][1].imshow(own, cmap='RdBu_r', norm=TwoSlopeNorm(vcenter=0.0, vmin=-s0, vmax=s0))
axes[1][1].set_title(f'exact - truth\nRMS {np.sqrt(np.mean(own ** 2)):.2g}', fontsize=8)
for ax in axes.flat:
    ax.axis('off')
fig.colorbar(im0, ax=axes[1][:2].tolist(), shrink=0.8, location='left', label='exact - truth')
fig.colorbar(im, ax=axes[1][2:].tolist(), shrink=0.8, label='signed radiance error (> 0: too bright)')
plt.show()
