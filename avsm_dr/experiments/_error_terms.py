"""Re-export of the error decomposition the studies share, now public in
:mod:`avsm_dr.evaluation` (the formulas: :mod:`avsm_dr.evaluation.probe`); kept until the
studies import :mod:`avsm_dr.evaluation` themselves."""
from __future__ import annotations

from ..evaluation.lights import light_variants
from ..evaluation.perturb import with_faint_segments
from ..evaluation.probe import Built, Probe, SubsetBuilder, truth

__all__ = ["Built", "Probe", "SubsetBuilder", "light_variants", "truth", "with_faint_segments"]
