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
# # Ground truth: our exact curve against Mitsuba 3
#
# The same density grid is loaded as a Mitsuba heterogeneous medium; ratio tracking gives unbiased
# transmittance with standard errors. We compare it with the `exact` representation of the captured
# segments, for receivers on the shadow map's texel rays (so that only the capture's march error
# remains) and for arbitrary receivers (which adds the shadow map's spatial resolution).

# %%
import avsm_dr as ad
import numpy as np
import matplotlib.pyplot as plt
from avsm_dr import groundtruth
import os
# The test suite runs these notebooks with AVSM_DR_NOTEBOOK_SMALL=1 (small sizes, fast).
SMALL = os.environ.get("AVSM_DR_NOTEBOOK_SMALL") == "1"
RES = 64 if SMALL else 256
SPP = 64 if SMALL else 512

# %%
scene = ad.scenes.plume()
cap = ad.capture(scene, resolution=RES, order="depth")
exact = ad.build('exact', cap.segments)
points = np.asarray(scene.receivers)
mean, stderr = groundtruth.transmittance(scene, points, spp=SPP)
texels, depths = cap.lookup(points)
ours = np.asarray(exact.eval(texels, depths))
z = (ours - mean) / np.maximum(stderr, 1e-9)
print(f'receivers {len(points)}, |ours - mitsuba| <= 3 stderr for {np.mean(np.abs(z) <= 3):.1%}')
print(f'rmse {np.sqrt(np.mean((ours - mean)**2)):.4f}, mean stderr {stderr.mean():.4f}')

# %%
fig, ax = plt.subplots(1, 2, figsize=(10, 4))
ax[0].errorbar(mean, ours, xerr=3 * stderr, fmt='.', ms=2, alpha=0.4)
ax[0].plot([0, 1], [0, 1], 'k:')
ax[0].set(xlabel='Mitsuba ratio tracking', ylabel='exact (captured)')
ax[1].hist(np.clip(z, -10, 10), bins=60)
ax[1].set_xlabel('(ours - mitsuba) / stderr')
plt.show()

# %% [markdown]
# ## Resolution: the gap shrinks as the shadow map gets finer

# %%
for res in ([64, 96] if SMALL else [64, 128, 256, 512]):
    c = ad.capture(scene, resolution=res, order="depth")
    t, d = c.lookup(points)
    o = np.asarray(ad.build('exact', c.segments).eval(t, d))
    print(f'{res:4d}^2: rmse vs Mitsuba {np.sqrt(np.mean((o - mean)**2)):.4f}')
