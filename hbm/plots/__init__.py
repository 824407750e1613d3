"""Figures (matplotlib, Agg backend).  The only hbm package that imports matplotlib.

Modules: :mod:`hbm.plots.specimen` (corner plot, posterior predictive and extrapolation,
Sobol bars), :mod:`hbm.plots.population` (VOLF–T1 manifolds, forest plot, hyper-posterior
densities); other helpers add their own modules (diagnose, organ).
"""

from __future__ import annotations

from ..runtime.lazy import attach

__all__ = ["plt", "save", "supported_formats", "RELEVANCE_COLORS"]

# matplotlib loads when a figure module or one of these names is first used, not with the package:
# the code that may draw (hbm fit, hbm run, the detective's report) holds `from .. import plots` and
# reaches `plots.fit`, `plots.population`, ... only when it draws (hbm.runtime.lazy)
__getattr__, __dir__ = attach(__name__, {"._mpl": __all__},
                              submodules=["diagnose", "fit", "organ", "population", "specimen", "tests_view"])
