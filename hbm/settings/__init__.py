"""The settings of hbm, one record per level: a specimen's fit, the population layer, a run.

* :mod:`.rules` -- ONE validation rule per kind of setting (API check and command-line parse);
* :mod:`.fields` -- the field machinery: a setting is declared once (default, help, rule, flag,
  whether it keys the result, its stored name) and the record gives the result key
  (:meth:`~.fields.Settings.record`), the stored form (``to_attrs``/``from_attrs``) and the
  command-line options (:func:`~.fields.add_arguments`, choices read from the registries);
* :mod:`.fit` -- :class:`FitSettings` (what :func:`hbm.fit.fit_specimen` takes) and
  :class:`FitRecord` (a result file's ``config``);
* :mod:`.population` -- :class:`PopulationSettings` (:func:`hbm.population.run_population`);
* :mod:`.run` -- :class:`RunSettings` (``hbm run``: the fit settings with the run's defaults, the
  population layer's as ``hier_*``, the run's own).

Adding a fit setting touches one file: declare it in :class:`FitSettings` (it is then checked,
keyed, stored, an option of ``hbm fit`` and ``hbm run``, and a field of both records) and read it
where it acts.

Renamed concepts keep their stored names (result files, ``run.json``, result keys)::

    record        field       stored as
    FitSettings   move        kernel
    FitSettings   tier        likelihood
    FitSettings   maxfevals   optimize_options.maxfevals (run.json: maxfevals)
"""

from .fields import Setting, Settings, add_arguments, canonical, record, setting
from .fit import FitRecord, FitSettings, Sweep
from .population import PopulationSettings
from .run import DEFAULT_OUT, RunSettings

__all__ = ["Setting", "Settings", "setting", "record", "add_arguments", "canonical", "FitSettings", "FitRecord",
           "Sweep", "PopulationSettings", "RunSettings", "DEFAULT_OUT"]
