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
# # Error analysis: error against memory for every representation
#
# Draws error against bytes per texel for every registered representation on the built-in scenes,
# and what the measurements say about the papers' claims. It only reads: the output of
# `python -m experiments error_curves` (the README's main job) when `results/error_curves/` holds it,
# otherwise the measurements committed with the docs (`docs/data/`, made by the command named in
# `docs/data/README.md`).

# %%
import json
import os
from pathlib import Path

import avsm_dr as ad  # first: picks Dr.Jit's libLLVM
import matplotlib.pyplot as plt
from avsm_dr.evaluation import read_csv

results = Path(os.environ.get('AVSM_DR_RESULTS', 'results')) / 'error_curves'
docs_data = Path(ad.__file__).resolve().parents[1] / 'docs' / 'data'
if (results / 'data.csv').exists():
    csv_path, findings_path = results / 'data.csv', results / 'findings.json'
else:
    csv_path, findings_path = docs_data / 'error_sweep.csv', docs_data / 'error_claims.csv'
rows = [r for r in read_csv(csv_path) if r.get('curve') in (True, 'True')]
print(f'{len(rows)} sweep rows from {csv_path.relative_to(csv_path.parents[2])}')

# %% [markdown]
# ## Error against memory
# One panel per scene: every kind's size sweep in its base configuration, error against the exact
# curve of the same segments (what compression loses) at in-volume receivers.

# %%
scenes = sorted({r['scene'] for r in rows})
methods = [k for k in ad.kinds() if k != 'exact' and any(r['method'] == k for r in rows)]
fig, axes = plt.subplots(2, (len(scenes) + 1) // 2, figsize=(4.2 * ((len(scenes) + 1) // 2), 7.2),
                         squeeze=False, sharey=True)
for ax, s in zip(axes.flat, scenes):
    for i, m in enumerate(methods):
        rs = sorted((r for r in rows if r['scene'] == s and r['method'] == m),
                    key=lambda r: float(r['bytes_per_texel']))
        if rs:
            ax.loglog([float(r['bytes_per_texel']) for r in rs], [max(float(r['rmse']), 1e-6) for r in rs],
                      'o-' if i < 10 else 's--', ms=3, label=m)
    ax.set_title(s)
    ax.set_xlabel('bytes per texel')
for ax in axes[:, 0]:
    ax.set_ylabel('RMSE vs exact curve')
for ax in axes.flat[len(scenes):]:
    ax.axis('off')
axes.flat[0].legend(fontsize=7, ncol=2)
fig.tight_layout()
plt.show()

# %% [markdown]
# ## The papers' claims, as measured
# `findings.json`: each claim as a paired bootstrap ratio of RMSEs (95 % interval), per configuration
# and pooled, and whether it holds in all of them.

# %%
if findings_path.suffix == '.json':
    claims = [dict(name=k, **c) for k, c in json.loads(findings_path.read_text())['claims'].items()]
else:
    claims = read_csv(findings_path)
for c in claims:
    print(f"{c['statement']} ({c['scene']})\n    {float(c['estimate']):.3g} "
          f"[{float(c['low']):.3g}, {float(c['high']):.3g}]: {c['verdict']}")
