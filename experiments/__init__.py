"""The studies: one module (or folder) per figure, table or research question, run from the
repository root by ``python -m experiments <name> [--quick] [--out DIR]`` (:mod:`experiments._cli`).

They are not part of the installed package: ``avsm_dr`` never imports them.  Each is thin on the
public harness :mod:`avsm_dr.evaluation`; shared study scaffolding (results folder, cache, CSV and
meta writers) lives in :mod:`experiments._common`.
"""
