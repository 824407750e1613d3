"""``hbm fit`` of a specimen tested in several loading modes: its options and its path (issue 35)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any, Mapping

from ..errors import SettingError
from ..fit.modes import fit_modes
from ..model.energy3d import COLLAGEN_READINGS, DEFAULT_COLLAGEN3D
from ..settings import FitSettings
from ._common import print_json

#: the fit settings the joint fit across modes does not use (it uses samples, seed, max_evaluations, fix,
#: bounds and prior), each with why
_NOT_HERE = {
    "noise": "it has its own noise model (one Gaussian sd per mode and observable)",
    "sigma_bounds": "its noise boxes are set per mode and observable",
    "tier": "it samples the full parameter space",
    "move": "it uses TMCMC's default move",
    "restarts": "it runs no CMA-ES optima",
    "maxfevals": "it runs no CMA-ES optima",
    "sweep": "it runs no CMA-ES optima",
    "sobol_n": "Sobol indices are computed along the fibres only",
    "reduce": "it fits the records as given",
    "artefacts": "it fits the records as given",
}


def add_modes_arguments(p: argparse.ArgumentParser) -> None:
    """--collagen3d and --test-scale: options of a fit across loading modes (ignored along the fibres)."""
    p.add_argument("--collagen3d", choices=sorted(COLLAGEN_READINGS), default=None,
                   help="3-D reading of the collagen for tests in other modes than uniaxial_f (energy form): "
                        f"default {DEFAULT_COLLAGEN3D}; recorded in the result")
    p.add_argument("--test-scale", action="store_true",
                   help="tests in several modes: a multiplicative factor per test on its predicted stresses "
                        "(cross-section and gauge errors), prior N(1, 0.05^2)")


def check_modes_settings(settings: FitSettings, defaults: Mapping[str, Any]) -> None:
    """Refuse a fit setting the joint fit across modes would ignore (given away from the command's default)."""
    base = FitSettings()
    for name, why in _NOT_HERE.items():
        # the record's default, or the command's (a command default may be stored as the record's: 0 -> None)
        if getattr(settings, name) not in (getattr(base, name), defaults.get(name, getattr(base, name))):
            flag = FitSettings.declared()[name][1].flag or name
            raise SettingError(f"{flag}: the tests are in several loading modes and their joint fit does not use "
                               f"this setting ({why}); expected it left at its default")


def modes_record(args: argparse.Namespace) -> dict[str, Any]:
    """The settings of the joint fit that FitSettings does not hold: they key its result and checkpoint."""
    return {"collagen3d": args.collagen3d or DEFAULT_COLLAGEN3D, "test_scale": bool(args.test_scale)}


def run_modes(args: argparse.Namespace, model, fix, bounds, prior, settings, data, out: Path,
              figure: Path | None, draw, checkpoint_dir: Path | None = None,
              config_extra: Mapping[str, Any] | None = None) -> int:
    """Fit the tests in their modes (:func:`hbm.fit.modes.fit_modes`), write the result and figure, print
    the report (tier and why, the reading, each test's mode and fit quality); ``draw(fit, figure)`` draws
    the figure (the caller imports matplotlib).  The caller holds the output locks and keys the result."""
    fit = fit_modes(data, model=model, collagen3d=args.collagen3d, samples=settings.samples,
                    seed=settings.seed, test_scale=args.test_scale, fix=fix or None, bounds=bounds or None,
                    prior=prior, max_evaluations=settings.max_evaluations, progress=not args.no_progress, out=out,
                    config_extra=config_extra, checkpoint_dir=checkpoint_dir)
    if figure is not None:
        draw(fit, figure)
    if args.json:
        print_json({"specimen": data.id, "tier": "full", "collagen3d": fit.likelihood.energy.collagen3d,
                    "log_evidence": fit.log_evidence, "log_evidence_se": fit.log_evidence_se,
                    "n_evaluations": fit.n_evaluations, "tests": fit.quality(),
                    "posterior_mean": dict(zip(fit.names, map(float, fit.samples.mean(axis=0)))),
                    "identifiability": None if fit.identifiability is None else fit.identifiability.to_dict()})
        return 0
    print(fit.report())
    print("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in fit.timings.items()))
    print(f"wrote {fit.path}" + (f" and {figure}" if figure is not None else ""))
    return 0
