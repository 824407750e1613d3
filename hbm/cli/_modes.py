"""``hbm fit`` of a specimen tested in several loading modes: its options and its path (issue 35)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..fit.modes import fit_modes
from ..model.energy3d import COLLAGEN_READINGS
from ._common import print_json


def add_modes_arguments(p: argparse.ArgumentParser) -> None:
    """--collagen3d and --test-scale: options of a fit across loading modes (ignored along the fibres)."""
    p.add_argument("--collagen3d", choices=sorted(COLLAGEN_READINGS), default=None,
                   help="3-D reading of the collagen for tests in other modes than uniaxial_f (energy form): "
                        "default cone; recorded in the result")
    p.add_argument("--test-scale", action="store_true",
                   help="tests in several modes: a multiplicative factor per test on its predicted stresses "
                        "(cross-section and gauge errors), prior N(1, 0.05^2)")


def run_modes(args: argparse.Namespace, model, fix, bounds, prior, settings, data, out: Path,
              figure: Path | None, draw) -> int:
    """Fit the tests in their modes (:func:`hbm.fit.modes.fit_modes`), write the result and figure, print
    the report (tier and why, the reading, each test's mode and fit quality); ``draw(fit, figure)`` draws
    the figure (the caller imports matplotlib)."""
    fit = fit_modes(data, model=model, collagen3d=args.collagen3d, samples=settings.samples,
                    seed=settings.seed, test_scale=args.test_scale, fix=fix or None, bounds=bounds or None,
                    prior=prior, max_evaluations=settings.max_evaluations, progress=not args.no_progress, out=out)
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
