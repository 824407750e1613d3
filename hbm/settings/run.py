"""The settings of ``hbm run`` (:class:`RunSettings`): every specimen's fit settings (inherited from
:class:`~hbm.settings.FitSettings`, with the run's defaults), the population layer's (``hier_*``) and
the run's own (folders, workers, figures ...).

:meth:`RunSettings.fit_settings` and :meth:`RunSettings.population_settings` compose the two other
levels; ``run.json`` stores :meth:`RunSettings.to_attrs` (today's flat layout: ``kernel``,
``likelihood``, ``maxfevals``; settings added to the fit later appear only when set).
"""

from __future__ import annotations

from typing import Any

from ..errors import SettingError
from .fields import record, setting
from .fit import RUN_SWEEP, FitSettings
from .population import PopulationSettings
from .rules import POSITIVE_INT, POWER_OF_TWO, SAMPLE_SIZE, WORKERS, NON_NEGATIVE_INT, ChoiceRule, RealRule

__all__ = ["RunSettings", "DEFAULT_OUT", "QUICK"]

#: default output folder of hbm run and hbm fit: untracked (.gitignore), so that a run never replaces
#: the shipped reference results in results/
DEFAULT_OUT = "hbm-results"
#: ``--quick``: every phase with small budgets (caps of the settings; the sweep's width)
QUICK = {"samples": 500, "restarts": 2, "maxfevals": 2000, "sweep_width": 0.1, "sobol_n": 128, "hier_samples": 500}


@record
class RunSettings(FitSettings):
    """Settings of ``hbm run`` (see ``hbm run -h`` for their meaning).

    The fit settings are :class:`~hbm.settings.FitSettings`' with the run's defaults (3 CMA-ES
    restarts of 3000 evaluations, the manifold sweep at width 0.07, Sobol N = 1024); ``sobol``
    switches Sobol off; ``hier_*`` are the population layer's (:class:`PopulationSettings`)."""

    data: str = setting("data/specimens", flag="--data", metavar="DIR", keyed=False,
                        help="folder of specimen CSV files (default {default})")
    out: str = setting(DEFAULT_OUT, flag="--out", metavar="DIR", keyed=False,
                       help="output folder (default {default}, untracked; the shipped reference report stays in "
                            "results/); one hbm run at a time (locked)")
    # the fit settings with the run's defaults
    restarts: int = setting(3, rule=NON_NEGATIVE_INT, flag="--restarts", metavar="K",
                            help="CMA-ES restarts per specimen (0 = skip; default {default})")
    sweep: Any = setting("auto", rule=RUN_SWEEP, flag="--sweep", metavar="NAME:WIDTH",
                         help="CMA-ES bound sweep tracing the model's manifold (default: its fraction at width 0.07, "
                              "7 windows; 'none' to skip)")
    sobol_n: int | None = setting(1024, rule=POWER_OF_TWO, flag="--sobol-n", metavar="N",
                                  help="Sobol base sample size, a power of 2 (default {default})")
    maxfevals: int = setting(3000, rule=POSITIVE_INT, flag="--maxfevals", metavar="M",
                             help="evaluation budget per CMA-ES run (default {default})")
    optimize_options: dict | None = setting(None, omit_default=True, help="further CMA-ES keyword arguments")
    sigma_bounds: Any = setting(None, omit_default=True,
                                help="box of the noise sd (default: one box for all specimens, from the largest "
                                     "stress)")
    max_evaluations: int | None = setting(None, rule=POSITIVE_INT, flag="--max-evaluations", metavar="M",
                                          omit_default=True,
                                          help="cap on TMCMC likelihood evaluations of every specimen's fit including "
                                               "the initial N (default: no cap); stored in tmcmc_options")
    # the run's own
    workers: int | None = setting(None, rule=WORKERS, keyed=False, help="dask worker processes (None: all cores)")
    scheduler: str | None = setting(None, keyed=False, help="existing dask scheduler address")
    sobol: bool = setting(True, help="compute Sobol indices (False: skip)")
    hierarchical: bool = setting(True, help="fit the population layer")
    hier_samples: int = setting(1000, rule=SAMPLE_SIZE, help="hyper-posterior draws (at least)")
    hier_max_steps: int = setting(25, rule=POSITIVE_INT, help="MH steps per stage of the layer")
    hier_extend: float = setting(3.0, rule=RealRule(1.0), flag="--hier-extend", metavar="X",
                                 help="the joint sampler's chains go on until converged (R-hat <= 1.01, bulk ESS >= "
                                      "400) up to X times their planned draws (default 3; 1: never; --quick: 1)")
    hier_pooled: Any = setting("auto", help="what gets a population distribution")
    hier_estimator: str = setting("raw", rule=ChoiceRule(lambda: ("raw", "kernel"), "importance estimator"),
                                  help="estimator of p(d_i|psi)")
    hier_transforms: dict | None = setting(None, help="population transforms over the model's")
    hier_sd_range: tuple | None = setting(None, help="population sd range as a fraction of mu's range (None: the "
                                                     "layer's own)")
    #: the population layer: the joint sampler ("gibbs") or None (reuse + TMCMC refinement)
    hier_exact: str | None = setting("gibbs", help="the joint sampler of the population and every specimen "
                                                   "(gibbs or None)")
    figures: bool = setting(True, keyed=False, help="draw the figures")
    progress: bool = setting(True, keyed=False, help="progress lines and bars")
    retries: int = setting(1, rule=NON_NEGATIVE_INT, keyed=False, help="dask retries per specimen task")
    quick: bool = setting(False, help="smoke run: every phase with small budgets")
    #: reference sarcomere length (µm) for files with a sarcomere_length_um column (``--sl0``)
    sl0: float | None = setting(None, help="reference sarcomere length (um)")
    #: metadata key whose values group the specimens (``--group-by``); None: ``# group:`` lines, if any
    group_by: str | None = setting(None, help="metadata key grouping the specimens")

    def _normalise(self) -> None:
        if self.quick:  # a smoke run: every phase, small budgets
            for name in ("samples", "restarts", "maxfevals", "sobol_n", "hier_samples"):
                if getattr(self, name) is not None:
                    object.__setattr__(self, name, min(getattr(self, name), QUICK[name]))
        if self.max_evaluations is not None:  # stored and keyed inside tmcmc_options, as always
            self._check_budget()
            object.__setattr__(self, "tmcmc_options", {**dict(self.tmcmc_options or {}),
                                                       "max_evaluations": int(self.max_evaluations)})
            object.__setattr__(self, "max_evaluations", None)

    def with_sweep(self, parameter: str | None, width: float = 0.07) -> "RunSettings":
        """The settings with ``sweep="auto"`` resolved: a sweep over ``parameter`` (the fraction of the
        model's manifold) at ``width`` (its :attr:`~hbm.model.spec.Manifold.sweep_width`; 0.1 with
        ``quick``), or none when the model has none."""
        if self.sweep != "auto":
            return self
        if parameter is None:
            return self.replace(sweep=None)
        return self.replace(sweep=f"{parameter}:{QUICK['sweep_width'] if self.quick else width}")

    def fit_settings(self, sigma_bounds: tuple[float, float] | None = None, seed: Any = None) -> FitSettings:
        """Every specimen's :class:`FitSettings` (the same record runs the fits and keys their results
        and checkpoints): the run's fit settings, Sobol off when ``sobol`` is, the common noise box
        ``sigma_bounds`` and the specimen's ``seed``."""
        if self.sweep == "auto":
            raise SettingError("sweep='auto' is resolved against the model first (RunSettings.with_sweep)")
        names = [n for n in FitSettings.declared()]
        values = {n: getattr(self, n) for n in names}
        values.update(sobol_n=self.sobol_n if self.sobol else None,
                      sigma_bounds=None if sigma_bounds is None else tuple(sigma_bounds),
                      seed=self.seed if seed is None else seed)
        if self.prior:  # a user prior replaces the boxes (it holds them)
            values["bounds"] = None
        return FitSettings(**values)

    def population_settings(self) -> PopulationSettings:
        """The settings of the population layer (:func:`hbm.population.run_population`)."""
        return PopulationSettings(seed=self.seed, pooled=self.hier_pooled, samples=self.hier_samples,
                                  max_steps=self.hier_max_steps, estimator=self.hier_estimator,
                                  transforms=self.hier_transforms, sd_range=self.hier_sd_range,
                                  stage1_samples=self.samples, noise=self.noise, fix=self.fix, bounds=self.bounds,
                                  retries=self.retries, progress=self.progress, exact=self.hier_exact,
                                  # a smoke run: the joint sampler's chains shorter too, never extended
                                  **({"layer_burn": 100, "layer_keep": 50, "layer_extend": 1.0} if self.quick
                                     else {"layer_extend": float(self.hier_extend)}))

