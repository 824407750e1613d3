"""``hbm predict organ RESULTS --geometry FILE.toml``: organ-scale force–elongation predictions."""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

from ..errors import HbmError, OutputError, OutputLockedError
from ..organ import load_geometry
from ..workflow.organ import format_summary, predict_organ
from ..runtime.files import file_lock, output_lock, prepare_output_dir, remove_stale_temps
from ..runtime.memory import require_memory
from ._common import add_seed, integer, positive_float, real, sample_size

DESCRIPTION = """\
Predictions from fitted specimens.  Targets:
  organ   force-elongation curve of a fusiform muscle (slender-body model, hbm.organ)
"""

ORGAN_DESCRIPTION = """\
Force-elongation curves of a fusiform muscle (belly + tendons, geometry from a TOML file, see
data/geometry/fusiform.toml) from the results of 'hbm run' (thesis sec. 3.3.2, Figs. 3.64-3.66).

For every specimen in RESULTS/specimens/*.nc, on one force grid per specimen (0 up to
--extrapolate x the force at which its organ leaves the tested strain range):
  * 90% bands from its TMCMC posterior (--samples draws, seeded subsample);
  * 90% bands from its updated individual posterior (RESULTS/hierarchical.nc, if present);
  * the curves of its near-optimal CMA-ES sets (-log L within --near of the best), which lie on
    the VOLF-T1 manifold and should coincide (Fig. 3.65);
and, from hierarchical.nc, the curves of a new, unseen specimen (population predictive).
Where the organ's largest fiber strain exceeds the largest strain tested on the specimen the
prediction is an extrapolation: flagged per draw, dashed/hatched in the figures (Fig. 3.64).

Outputs in --out (default RESULTS/organ):
  organ.nc              bands (5/50/95%), extrapolated share per force, optima curves
  figures/organ_<id>.png, organ_overlay.png, organ_optima_<id>.png
Prints a table: elongation at a reference force F_ref (median [90%]), the share of draws
extrapolated there, and the force at which the organ leaves the tested range.

examples:
  hbm predict organ hbm-results --geometry data/geometry/fusiform.toml
  hbm predict organ /tmp/run --geometry my_muscle.toml --samples 1000 --ref-force 0.5 --no-figures
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("predict", help="predictions from fitted specimens (organ-scale curves)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.set_defaults(func=_no_target)
    sub = p.add_subparsers(dest="target", metavar="TARGET")
    o = sub.add_parser("organ", help="fusiform muscle force-elongation curves with posterior bands",
                       description=ORGAN_DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    o.add_argument("results", metavar="RESULTS", help="output folder of 'hbm run' (holds specimens/<id>.nc)")
    o.add_argument("--geometry", required=True, metavar="FILE.toml",
                   help="muscle geometry (lengths mm, areas mm^2, moduli MPa), e.g. data/geometry/fusiform.toml")
    o.add_argument("--out", metavar="DIR", help="output folder (default RESULTS/organ)")
    o.add_argument("--samples", type=sample_size, default=2000, metavar="N",
                   help="posterior draws per specimen and source (default 2000; all if fewer)")
    o.add_argument("--forces", type=integer(2), default=200, metavar="K",
                   help="force levels per specimen (default 200)")
    o.add_argument("--extrapolate", type=real(1.0), default=2.0, metavar="X",
                   help="force grid up to X times the force where the organ leaves the tested range (default 2)")
    o.add_argument("--ref-force", type=positive_float, default=None, metavar="F",
                   help="reference force (N) of the table (default: a round number inside every tested range)")
    o.add_argument("--near", type=real(0.0), default=3.0, metavar="D",
                   help="CMA-ES optima within D of the best -log-likelihood are shown (default 3)")
    o.add_argument("--optima-specimen", metavar="ID", help="specimen of the CMA-ES optima figure")
    add_seed(o, "seed of the draw subsampling (default 0)")
    o.add_argument("--no-figures", action="store_true", help="skip figures")
    o.set_defaults(func=run_organ)


def _no_target(args: argparse.Namespace) -> int:
    raise HbmError("predict: expected a target, e.g. 'hbm predict organ RESULTS --geometry FILE.toml'")


def run_organ(args: argparse.Namespace) -> int:
    """Check the geometry, sizes and output folder, then predict and print the table."""
    t0 = time.perf_counter()
    # the draws' elongations at every force level, per source, at least
    require_memory(8.0 * args.samples * args.forces, f"--samples {args.samples} with --forces {args.forces}",
                   f"{args.samples} draws x {args.forces} forces x 8 bytes")
    geometry = load_geometry(args.geometry)  # before reading results: a bad file fails fast
    with contextlib.ExitStack() as held:
        if Path(args.results).is_dir():  # (a missing RESULTS is predict_organ's own one-line error)
            out = prepare_output_dir(args.out or Path(args.results) / "organ", "--out", files=("organ.nc",),
                                     subdirs=("figures",))
            # the one writer rule: the run folder's lock (refused while 'hbm run' writes there), then organ.nc's
            try:
                held.enter_context(output_lock(Path(args.results)))
            except OutputLockedError:
                raise
            except OutputError:  # a read-only RESULTS folder: nobody writes there, --out is elsewhere
                if Path(args.results).absolute() in out.parents:
                    raise
            held.enter_context(file_lock(out / "organ.nc", "--out"))
            remove_stale_temps(out, recursive=False, target="organ.nc")  # leftovers of a killed prediction
            remove_stale_temps(out / "figures", recursive=False)
        pred = predict_organ(args.results, geometry, out=args.out, samples=args.samples, forces=args.forces,
                             extrapolate=args.extrapolate, ref_force=args.ref_force, near=args.near,
                             seed=args.seed, figures=not args.no_figures, optima_specimen=args.optima_specimen)
    print(geometry.describe())
    print(format_summary(pred.rows))
    for note in pred.notes:
        print(f"note: {note}")
    t = pred.timings
    print(f"time: organ solver {t.get('solver', 0.0):.2f} s, figures {t.get('figures', 0.0):.2f} s, "
          f"total {time.perf_counter() - t0:.2f} s")
    figs = f" and {len(pred.figures)} figures in {pred.figures[0].parent}" if pred.figures else ""
    print(f"wrote {pred.path}{figs}")
    return 0
