"""``hbm run``: the whole multi-specimen workflow (dask-parallel fits, hierarchical layer, report)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
import sys

from ..data import load_specimens, specimen_groups
from ..data.modes import check_along_fibre
from ..errors import SettingError
from ..workflow.organ import organ_report_hook
from ..runtime.files import output_lock, prepare_output_dir, remove_stale_temps
from ..workflow.run import run_workflow
from ..model import BASE_EFFECTS
from ..population import POOL_MODES
from ..settings import RunSettings, add_arguments
from ._common import n_noise_parameters
from ._common import (
    add_model_arguments, build_prior, check_domain, build_model, check_population_memory, check_sobol_memory,
    free_parameters, name_list, non_negative_int, sample_size, workers)

#: the RunSettings that are options of ``hbm run`` with their declared flags
RUN_OPTIONS = ("data", "out", "samples", "move", "noise", "tier", "seed", "restarts", "sweep", "maxfevals",
               "max_evaluations", "sobol_n", "hier_extend")
#: why ``hbm run`` does not offer ``--tier collapsed``
COLLAPSED_REFUSED = ("a specimen where the amplitudes cannot be integrated would fail after the others ran; "
                     "use auto, which integrates them wherever the model and noise allow")

#: what hbm run writes inside --out (checked before the first fit)
OUT_FILES = ("report.md", "run.json", "hierarchical.nc", "manifolds.nc")
OUT_DIRS = ("specimens", "checkpoints", "figures", "organ")

DESCRIPTION = """\
For every specimen CSV in --data: CMA-ES optima with a VOLF bound sweep (the VOLF-T1
manifold), the TMCMC posterior with log-evidence, and Sobol indices, in parallel on dask
(one task per specimen).  Then the hierarchical Bayesian layer (a Gaussian population over the identifiable
combinations, hyper-evidence, updated individuals, a new specimen's predictive), identifiable
combinations, manifold splines, figures and a Markdown report.

Outputs in --out:
  specimens/<id>.nc   per-specimen ArviZ-compatible netCDF (arviz.from_netcdf)
  hierarchical.nc     hyper-posterior (mu_<P>, sd_<P>), updated individuals, new-specimen predictive
  manifolds.nc        VOLF-T1 manifold splines
  figures/*.png       corner, predictive, Sobol per specimen; manifolds, forest, hyper-posterior
  report.md           tables, population estimates, specimen variability, timings
  run.json            settings and timings
  organ/              with --geometry: organ-scale predictions (see 'hbm predict organ -h')

Re-running skips specimens whose result file is complete (same settings) and resumes
interrupted ones from <out>/checkpoints/.  Results do not depend on --workers.
Parallelism: an embedded dask LocalCluster with --workers processes (default: all cores), or an
existing cluster with --scheduler ADDRESS (or DASK_SCHEDULER_ADDRESS); for SLURM/PBS see
workflows/hpc_slurm.py (dask-jobqueue, pip install 'hbm[hpc]').  --workers 0 runs serially
without dask.

examples:
  hbm run
  hbm run --quick --workers 2 --out /tmp/smoke
  hbm run --samples 5000 --move manifold --scheduler tcp://10.0.0.5:8786
  hbm run --geometry data/geometry/fusiform.toml
  hbm run --data my_bundles --group-by species
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="all specimens in parallel + hierarchical layer + report",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    # the run's and every specimen's fit settings, declared once in hbm.settings (RunSettings inherits FitSettings)
    add_arguments(p, RunSettings, RUN_OPTIONS, refuse={"tier": {"collapsed": COLLAPSED_REFUSED}})
    add_model_arguments(p)
    p.add_argument("--workers", type=workers, default=None, metavar="K",
                   help="dask worker processes of the embedded cluster (default: all cores; 0 = no dask)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="existing dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--scheduler-file", metavar="FILE",
                   help="dask scheduler file (JSON with 'address', as written by dask-mpi or "
                        "'dask scheduler --scheduler-file') of a cluster started by an MPI/HPC script")
    p.add_argument("--no-sobol", action="store_true", help="skip Sobol indices")
    p.add_argument("--hier-samples", type=sample_size, default=1000, metavar="N",
                   help="hyper-posterior draws (default 1000): the joint sampler keeps all its chains x kept "
                        "draws, at least N (--hier-exact none: the TMCMC population over the hyperparameters)")
    p.add_argument("--pool", type=name_list, metavar="|".join(POOL_MODES) + "|P1,P2,...", default=["auto"],
                   help="what gets a population distribution: 'combinations' = the identifiable combinations "
                        "log G, log VOLF*P1, log (1-VOLF)*T1 with T2, THETA (and EOPT when informed); "
                        "'informed' = the model parameters whose posterior sd (transformed space) is below 2/3 "
                        "of the prior's in at least half of the specimens (the joint sampler: in ten at most); 'all' = every "
                        "model parameter; or a list of parameters. 'auto' (default): combinations for the base model with VOLF, P1, "
                        "T1, GF, GM, T2, THETA free, informed otherwise")
    p.add_argument("--hier-estimator", choices=("raw", "kernel"), default="raw",
                   help="estimator of p(d_i|psi): raw importance ratios (default, unbiased) or kernel-smoothed "
                        "ratios (O(h^2) bias, robust when the population is narrower than a posterior)")
    p.add_argument("--hier-exact", choices=("gibbs", "none"), default="gibbs",
                   help="the population layer: joint sampling of the population and every specimen with its "
                        "real likelihood (gibbs, default), or TMCMC over the population reusing the stage-1 "
                        "samples with a fresh TMCMC run of each specimen they cannot represent (none; it gives "
                        "the hyper-evidence, but lower tails too short: README)")
    p.add_argument("--group-by", metavar="KEY",
                   help="group the specimens by a metadata key of their files (e.g. species, muscle, protocol): "
                        "a population -> group -> specimen layer whose report says whether the groups differ; "
                        "every specimen needs '# KEY: NAME' and there must be two groups at least (default: the "
                        "'# group:' lines, if any)")
    p.add_argument("--no-hierarchical", action="store_true", help="skip the hierarchical layer")
    p.add_argument("--no-figures", action="store_true", help="skip figures")
    p.add_argument("--retries", type=non_negative_int, default=1, metavar="R",
                   help="dask retries per specimen task (default 1)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: N<=500, 2 restarts, the manifold sweep at width 0.1, Sobol N 128, 500 hyper samples")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--geometry", metavar="FILE.toml",
                   help="also predict a fusiform muscle's force-elongation curves (hbm predict organ) into "
                        "<out>/organ and add them to the report")
    p.set_defaults(func=run)


def _pool(names: list[str], free: list[str]) -> str | list[str]:
    """--pool: one keyword, or free model parameters (checked before any fit)."""
    if len(names) == 1 and names[0] in POOL_MODES:
        return names[0]
    bad = [n for n in names if n not in free]
    if bad:
        raise SettingError(f"--pool {','.join(names)}: {', '.join(bad)} not among the free model parameters "
                           f"{', '.join(free)}; expected one of {', '.join(POOL_MODES)} or a list of those")
    return names


def _check_sizes(cfg: RunSettings, datasets, model, fix: dict) -> None:
    """Refuse population/Sobol sizes whose memory cannot exist (one specimen task at least)."""
    points = max(ds.n_points for ds in datasets.values())
    check_population_memory(f"--samples {cfg.samples}", cfg.samples, points,
                            model.n_params + n_noise_parameters(cfg.noise))
    if cfg.sobol:
        free = len(free_parameters(model, fix))
        check_sobol_memory(f"--sobol-n {cfg.sobol_n}", cfg.sobol_n, free, model.n_params, points)
    if cfg.hierarchical:
        # the hyper-population's log-ratio blocks are (n_psi, >= 256 stage-1 samples)
        check_population_memory(f"--hier-samples {cfg.hier_samples}", cfg.hier_samples, 256, 2 * model.n_params)


def scheduler_address(address: str | None, scheduler_file: str | None, wait: float = 30.0) -> str | None:
    """The scheduler address: --scheduler, or the ``address`` of --scheduler-file (waited for up to
    ``wait`` s, as ``distributed.Client(scheduler_file=...)`` does, since an MPI launcher may start the
    scheduler and hbm together)."""
    if scheduler_file is None:
        return address
    if address is not None:
        raise SettingError("--scheduler and --scheduler-file: give one of them")
    path = Path(scheduler_file)
    deadline = time.monotonic() + wait
    while not path.is_file() and time.monotonic() < deadline:
        time.sleep(0.5)
    try:
        addr = json.loads(path.read_text(encoding="utf-8"))["address"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SettingError(f"--scheduler-file {path}: expected a dask scheduler file (JSON with 'address'); "
                           f"{type(exc).__name__}: {exc}") from None
    if not isinstance(addr, str) or "://" not in addr:
        raise SettingError(f"--scheduler-file {path}: 'address' is {addr!r}, expected e.g. tcp://host:8786")
    return addr


def run(args: argparse.Namespace) -> int:
    """Check every setting, path and size, lock --out, then run the workflow."""
    model, fix, bounds = build_model(args)
    prior = build_prior(model, args)
    pool = _pool(args.pool, free_parameters(model, fix))
    datasets = load_specimens(args.data, sl0=args.sl0)  # a bad or missing data folder fails before any fit
    for ds in datasets.values():
        check_domain(model, ds)
    check_along_fibre(datasets, args.data)
    if not args.no_hierarchical:  # groups matter to the hierarchical layer only
        specimen_groups(datasets, args.group_by)  # every specimen has its group, two groups at least
    cfg = RunSettings.from_args(
        args, workers=args.workers, scheduler=scheduler_address(args.scheduler, args.scheduler_file),
        sobol=not args.no_sobol, fix=fix or None, bounds=bounds or None, hierarchical=not args.no_hierarchical,
        hier_samples=args.hier_samples, figures=not args.no_figures, progress=not args.no_progress,
        retries=args.retries, quick=args.quick, hier_estimator=args.hier_estimator, hier_pooled=pool,
        hier_exact=None if args.hier_exact == "none" else args.hier_exact,
        prior=prior.to_dict() if prior is not None else None, sl0=args.sl0, group_by=args.group_by)
    _check_sizes(cfg, datasets, model, fix)
    hooks = []
    if getattr(args, "geometry", None):
        # the geometry is read now, so a bad file fails before hours of fitting
        hooks.append(organ_report_hook(args.geometry, model=model, seed=args.seed, figures=not args.no_figures))
    out = prepare_output_dir(args.out, "--out", files=OUT_FILES, subdirs=OUT_DIRS)
    is_base = model.effect_names == BASE_EFFECTS and model.name == "spyrou"
    with output_lock(out):
        # under the lock no other run writes here: temp files now are leftovers of a killed run
        stale = remove_stale_temps(out)
        if stale and not args.no_progress:
            print(f"[hbm run] removed {len(stale)} temporary file(s) left by an interrupted run", file=sys.stderr)
        res = run_workflow(cfg, model=None if is_base else model, extra_sections=hooks)
    print(f"{len(res.results)} specimens fitted ({len(res.skipped)} reused), "
          f"{len(res.errors)} failed; report: {res.report_path}")
    t = res.timings
    # a split run's specimens_wall is its posteriors; the rest of the fits ran beside the layer, then their tail
    print("time: " + ", ".join(f"{k} {t[k]:.1f} s" for k in ("specimens_wall", "hierarchical", "specimens_extras_wait",
                                                              "figures", "organ", "total") if k in t)
          + ("; the fits' optima, sweep and Sobol ran beside the layer" if t.get("specimens_extras_beside_layer")
             else ""))
    for hook in hooks:
        pred = getattr(hook, "prediction", None)
        if pred is None:
            print("organ prediction FAILED (see the report's organ section)")
            return 1
        print(f"organ prediction: {pred.path}")
    if res.errors:  # one line naming every failed specimen and why; the others' results are written
        failed = "; ".join(f"{sid}: {msg}" for sid, msg in sorted(res.errors.items()))
        print(f"hbm: error: {len(res.errors)} specimen(s) failed -- {failed}", file=sys.stderr)
        return 1
    return 0
