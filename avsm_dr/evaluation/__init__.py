"""The evaluation harness: how wrong is a representation, against the true transmittance,
where it matters, and at what cost.  For example::

    import avsm_dr as ad
    methods = {"avsm-8": ("avsm", {"nodes": 8}), "fom-4": ("fom", {"harmonics": 4})}
    table = ad.evaluation.evaluate(methods, ["plume"],
                                   ad.evaluation.configurations(seeds=4, lights=("dir_a", "spot")))
    print(ad.evaluation.compare(table, "avsm-8", "fom-4"))
"""
from .comparison import Comparison, compare
from .configuration import LIGHTS, Configuration, configurations, light_variants
from .curves import curve_values, depth_grid, depth_l2
from .harness import METRICS, RECEIVER_SETS, evaluate
from .probe import Built, Probe, SubsetBuilder, truth
from .table import Table, read_csv
from .timing import measure, sync, timed

__all__ = ["Built", "Comparison", "Configuration", "LIGHTS", "METRICS", "Probe", "RECEIVER_SETS",
           "SubsetBuilder", "Table", "compare", "configurations", "curve_values", "depth_grid", "depth_l2", "evaluate",
           "light_variants", "measure", "read_csv", "sync", "timed", "truth"]
