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
# # Quickstart: every representation on a built-in scene
#
# Build the exact curve, AVSM, DSM, OSM and FOM from a captured smoke plume, look at the transmittance
# along one texel, and at the shadow each casts on the receiver plane.

# %%
import avsm_dr as ad          # before drjit / mitsuba: picks a working libLLVM
import numpy as np
import matplotlib.pyplot as plt
import os
from avsm_dr import shading
# The test suite runs these notebooks with AVSM_DR_NOTEBOOK_SMALL=1 (small sizes, fast).
SMALL = os.environ.get("AVSM_DR_NOTEBOOK_SMALL") == "1"
RES = 64 if SMALL else 256

# %% [markdown]
# ## Segments by hand
# Two texels; the second has an opaque blocker (transmittance 0).

# %%
seg = ad.Segments.from_arrays([0, 2, 3], z0=[0.1, 0.4, 0.2], z1=[0.3, 0.5, 0.2], transmittance=[0.5, 0.7, 0.0])
for kind in ['exact', 'avsm']:
    rep = ad.build(kind, seg)
    print(kind, np.asarray(rep.eval([0, 0, 1, 1], [0.2, 0.9, 0.1, 0.3])))

# %% [markdown]
# ## A captured scene

# %%
scene = ad.scenes.plume()
cap = ad.capture(scene, resolution=RES, order="depth")
print(cap.segments)
reps = {
    'exact': ad.build('exact', cap.segments),
    'avsm-8': ad.build('avsm', cap.segments, nodes=8),
    'dsm-0.01': ad.build('dsm', cap.segments, tolerance=0.01),
    'osm-32': ad.build('osm', cap.segments, slices=32),
    'fom-8': ad.build('fom', cap.segments, harmonics=8),
}
for name, rep in reps.items():
    print(f'{name:9s} {rep.nbytes_per_texel:8.1f} bytes/texel')

# %% [markdown]
# ## Transmittance along the busiest texel

# %%
texel = int(np.argmax(cap.segments.counts))
near, far = cap.segments.bounds()
z = np.linspace(near, far, 400)
fig, ax = plt.subplots(figsize=(7, 4))
for name, rep in reps.items():
    ax.plot(z, np.asarray(rep.eval(np.full(z.size, texel), z)), lw=2.5 if name == 'exact' else 1.2, label=name)
ax.set(xlabel='light-space depth', ylabel='transmittance')
ax.legend()
plt.show()

# %% [markdown]
# ## Errors at the scene's receivers

# %%
texels, depths = cap.lookup(scene.receivers)
exact = np.asarray(reps['exact'].eval(texels, depths))
for name, rep in reps.items():
    err = np.asarray(rep.eval(texels, depths)) - exact
    print(f'{name:9s} rmse {np.sqrt(np.mean(err**2)):.5f}  max {np.abs(err).max():.5f}')

# %% [markdown]
# ## Shadows on the receiver plane
# The same view, shaded with light transmittance from each representation.

# %%
W = 48 if SMALL else 160
imgs = {name: shading.shade_plane(scene, rep, cap, width=W, height=W) for name, rep in reps.items()}
fig, axes = plt.subplots(1, len(imgs), figsize=(3 * len(imgs), 3))
for ax, (name, img) in zip(axes, imgs.items()):
    ax.imshow(img, cmap='gray')
    ax.set_title(name)
    ax.axis('off')
plt.show()
