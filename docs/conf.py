"""Sphinx configuration of the avsm_dr docs.

    python -m sphinx -W -b html docs docs/_build/html

Markdown pages and notebooks through myst-nb; the API reference through autodoc + napoleon;
pages generated from the registry, the committed measurements (``docs/data/``), the recipes and
the notebooks by the local extension ``_ext/avsm_docs.py`` into ``_generated/`` at build time.
Notebooks are executed during the build (``AVSM_DR_NOTEBOOK_SMALL=1`` runs them at the test
suite's small sizes).
"""
import os
import sys
from pathlib import Path

import avsm_dr  # noqa: F401  (first: points Dr.Jit at a working libLLVM before anything imports drjit)

sys.path.insert(0, str(Path(__file__).resolve().parent / "_ext"))

project = "avsm_dr"
author = "avsm_dr contributors"
copyright = "avsm_dr contributors"
release = version = avsm_dr.__version__

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "avsm_docs",
]

exclude_patterns = ["_build", "data/README.md", "data/gpu_h200/*", "representations/notes/*", "research/*/**",
                    "_generated/fragments/*", "**.ipynb_checkpoints"]
# Ambiguous Python cross-references (``max``, ``type``: attributes of several classes, named in
# plain-text docstrings) resolve to the first target; every other warning is an error.
suppress_warnings = ["ref.python"]


# ------------------------------------------------------------------ MyST / myst-nb
myst_enable_extensions = ["dollarmath", "colon_fence"]
myst_heading_anchors = 3
nb_execution_mode = "force"                     # generated notebooks carry no outputs
nb_execution_timeout = 900                      # seconds per cell
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True
os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"   # figures as outputs in the kernels

# ------------------------------------------------------------------ autodoc
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"undoc-members": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = True
napoleon_use_ivar = True                        # Attributes sections as fields (dataclass fields are no duplicates)

# ------------------------------------------------------------------ HTML
html_theme = "furo"
html_title = f"avsm_dr {release}"
