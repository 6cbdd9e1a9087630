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
# # Differentiable shadows and an inverse problem
#
# Gradients flow from a shadow image back to the voxels of a density grid:
# `density -> capture -> representation (exact, FOM, OSM, AVSM, DSM 'curve') -> T at receivers -> loss`.
# This notebook checks one gradient against finite differences, uses forward mode for a single direction,
# then recovers a smoke plume's density from its shadows under three lights with Adam, and compares the
# recovered grid's shadow for a held-out light with Mitsuba ratio tracking.

# %%
import avsm_dr as ad          # before drjit / mitsuba: picks a working libLLVM
import os
import numpy as np
import matplotlib.pyplot as plt
import drjit as dr
from avsm_dr import reconstruction as inv, groundtruth as gt
from avsm_dr.representations import _loops as ck
from avsm_dr.receivers import lattice
# The test suite runs these notebooks with AVSM_DR_NOTEBOOK_SMALL=1 (small sizes, fast).
SMALL = os.environ.get('AVSM_DR_NOTEBOOK_SMALL') == '1'
SIZE, ITERS, RES, IMG = (6, 15, 64, 14) if SMALL else (10, 120, 96, 32)

# %% [markdown]
# ## A shadow and its gradient with respect to every voxel (reverse mode)
# `inv.density_tensor` makes a Dr.Jit tensor with gradients enabled; `inv.shadow` captures it with
# `keep_zero=True` (empty voxels get gradients too), builds the representation and looks up the receivers.

# %%
scene = ad.scenes.plume(size=SIZE, density_scale=20.0)
light = inv.light_from_angles(180, 20)
pts = inv.receiver_grid(scene.bbox, light, IMG)           # a shadow image behind the plume
x = inv.density_tensor(scene.density)
sh = inv.shadow(scene, x, pts, light=light, kind='avsm', resolution=RES, filter='bilinear')
loss = dr.mean(sh.T)                                      # mean brightness of the shadow image
dr.backward(loss)
g = dr.grad(x).numpy()
print(sh.capture.segments, ' loss', loss[0])
fig, axes = plt.subplots(1, 3, figsize=(10, 3.2))
axes[0].imshow(np.asarray(sh.T).reshape(IMG, IMG), cmap='gray', vmin=0, vmax=1)
axes[0].set_title('shadow image (AVSM)')
axes[1].imshow(scene.density.sum(axis=0), origin='lower', cmap='magma')
axes[1].set_title('density, summed along z')
axes[2].imshow(g.sum(axis=0), origin='lower', cmap='Blues_r')
axes[2].set_title('d loss / d density, summed along z')
for a in axes:
    a.axis('off')
plt.show()

# %% [markdown]
# ## Forward mode for a few parameters, and a finite-difference check
# Forward mode propagates one direction at a time and needs no loop-bound hint; here the direction is
# "scale the whole grid". The same number from reverse mode is `sum(g * density)`.

# %%
x = inv.density_tensor(scene.density)
L = dr.mean(inv.shadow(scene, x, pts, light=light, kind='avsm', resolution=RES, filter='bilinear').T)
dr.set_grad(x, type(x)(scene.density))
dr.forward_to(L)
h = 1e-3


def f(s):
    return dr.mean(inv.shadow(scene, s * scene.density, pts, light=light, kind='avsm', resolution=RES,
                               filter='bilinear').T)[0]


print('forward mode   ', dr.grad(L)[0])
print('reverse mode   ', float(np.sum(g * scene.density)))
print('central diff.  ', (f(1 + h) - f(1 - h)) / (2 * h), '(float32 capture, h = 1e-3)')
print('reverse vs forward check:', inv.gradient_check(
    lambda xt: dr.mean(inv.shadow(scene, xt, pts, light=light, kind='fom', resolution=RES).T),
    inv.density_tensor(scene.density, grad=False)))

# %% [markdown]
# ## Recover the density from three shadow images
# Targets: the ground truth's float64 ray march of the true grid (independent of the capture code).
# Receivers per light: the shadow image behind the volume plus a lattice of probes inside it (where FOM and
# AVSM differ from the exact curve). Start: an empty grid; Adam with projection onto density >= 0.

# %%
lights = [inv.light_from_angles(a, 20) for a in (180, 300, 60)]
probes = lattice(scene.bbox, (4, 6, 4))
receivers = [np.concatenate([inv.receiver_grid(scene.bbox, l, IMG), probes]) for l in lights]
targets = [gt.transmittance(inv.with_light(scene, l), r, method='raymarch')[0]
           for l, r in zip(lights, receivers)]
runs = {}
for kind in ['fom', 'avsm']:
    runs[kind] = inv.recover(scene, lights, targets, receivers, kind=kind, iterations=ITERS, lr=0.5,
                             resolution=RES, filter='bilinear', truth=scene.density)
    h = runs[kind].history
    print(f"{kind}: loss {h[0]['data']:.4f} -> {h[-1]['data']:.5f}, density error {h[-1]['density_rel_l2']:.3f}, "
          f"{sum(r['seconds'] for r in h):.1f} s")
fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
for kind, r in runs.items():
    axes[0].semilogy([e['data'] for e in r.history], label=kind)
    axes[1].plot([e['density_rel_l2'] for e in r.history], label=kind)
axes[0].set(xlabel='iteration', title='shadow loss')
axes[1].set(xlabel='iteration', title='relative density error')
for a in axes:
    a.legend()
    a.grid(alpha=0.3)
plt.show()

# %% [markdown]
# ## Held-out light: Mitsuba ratio tracking on the recovered grid
# The recovered grid becomes a Mitsuba heterogeneous medium (`groundtruth.transmittance` on a scene
# holding it); its shadow under a light that was not used for fitting is compared with ratio tracking on the true grid.

# %%
held = inv.light_from_angles(120, 35)
hp = inv.receiver_grid(scene.bbox, held, IMG)
spp = 32 if SMALL else 256
T_true, _ = gt.transmittance(inv.with_light(scene, held), hp, spp=spp, seed=1)
imgs = {'truth (Mitsuba)': T_true}
for kind, r in runs.items():
    T_rec, _ = gt.transmittance(inv.with_light(scene, held, density=r.density), hp, spp=spp, seed=2)
    imgs[f'{kind} recovered (Mitsuba)'] = T_rec
    print(f'{kind}: held-out RMSE {np.sqrt(np.mean((T_rec - T_true) ** 2)):.4f}  (empty grid: '
          f'{np.sqrt(np.mean((1 - T_true) ** 2)):.4f})')
fig, axes = plt.subplots(1, len(imgs), figsize=(3.2 * len(imgs), 3.2))
for a, (name, img) in zip(axes, imgs.items()):
    a.imshow(img.reshape(IMG, IMG), cmap='gray', vmin=0, vmax=1)
    a.set_title(name, fontsize=9)
    a.axis('off')
plt.show()

# %% [markdown]
# ## What reverse mode costs
# Reverse mode through a per-texel loop keeps a trajectory of *segments per texel x loop state* per lane
# (AVSM: 2N + 5 words per iteration). The exact curve's loop is a sum loop that reverse mode
# recomputes (no trajectory), and
# `ad.build(kind, seg, reverse='auto')` checkpoints AVSM's loop in chunks when the trajectory would be
# large; forward mode needs no trajectory at all. `python -m experiments backward_cost` measures time and memory.

# %%
seg = sh.capture.segments
for kind, p in [('exact', {}), ('avsm', {'nodes': 8}), ('avsm', {'nodes': 32})]:
    words = ad.build(kind, seg, **p).loop_state_words * seg.max_count
    print(f"{kind:5s} {p}: {seg.max_count} segments per texel -> {words} trajectory words per lane "
          f"({'checkpointed' if words > ck.TRAJECTORY_BUDGET_WORDS else 'fits the budget'})")
