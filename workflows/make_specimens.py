"""Generate the six labelled synthetic stand-in specimens in ``data/specimens/``.

The thesis analysed one rat curve of Hawkins & Bey (1994) and five of Calvo et al. (2010).
Those measurements are not redistributable here, so each is replaced by a *synthetic
stand-in*: the Spyrou–Agoras–Danas model (k_iso = 1) evaluated at the per-specimen estimates
reported in the thesis (DESIGN.md §1) plus Gaussian noise.  Where the thesis leaves a value
open (VOLF and T1 are not separately identifiable, only (1−c)·T1 is) the choice is recorded in
each file's metadata together with the seed, so this script reproduces the files byte for byte::

    PYTHONPATH=. python workflows/make_specimens.py            # writes data/specimens/
    PYTHONPATH=. python workflows/make_specimens.py --out DIR  # anywhere else

Seeds: ``numpy.random.SeedSequence(ENTROPY).spawn(6)``, one child per specimen in the order
of ``SPECIMENS``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

import hbm
from hbm.data import save_specimen, synthetic_specimen
from hbm.model.core import Loading

ENTROPY = 20100201  # fixed root entropy of the seed sequence
ISO_FACTOR = 1.0
CALVO_RATE = 2.2e-4  # 0.022 %/s (Calvo et al. 2010), in 1/s

HAWKINS = "Hawkins D, Bey M (1994) A comprehensive approach for studying muscle-tendon mechanics. J Biomech 27:1223-1235"
CALVO = ("Calvo B, Ramirez A, Alonso A, Grasa J, Soteras F, Osta R, Munoz MJ (2010) Passive nonlinear "
         "elastic behaviour of skeletal muscle: experimental results and model formulation. "
         "J Biomech 43:318-325")

# id, citation, eps_max, n points, relative noise sd, strain rate (None: no time column), parameters, notes
SPECIMENS = [
    ("hawkins1994_rat", HAWKINS, 0.42, 42, 0.02, None,
     dict(VOLF=0.97, EOPT=0.192, P1=0.005, T1=0.127, T2=162.0, THETA=59.8, GF=0.006, GM=0.006),
     "thesis 3.1: EOPT 0.192 fixed (Hawkins' value), T2~162, THETA 59.8, GF=GM~0.006, P1 in [1e-4,0.01]; "
     "chosen VOLF 0.97 and T1 0.127 so (1-c)*T1=3.81e-3 MPa (Appendix B manifold); P1 0.005 chosen"),
    ("calvo2010_rat1", CALVO, 0.44, 45, 0.015, CALVO_RATE,
     dict(VOLF=0.9, EOPT=0.184, P1=0.13, T1=1.5, T2=9.3, THETA=60.0, GF=0.012, GM=0.009),
     "thesis 3.2.1 Table 3.9: EOPT~0.184, P1~0.13, T1~1.5 at VOLF~0.9, T2 9.3, THETA 60, GF~0.012, GM~0.009"),
    ("calvo2010_rat2", CALVO, 0.42, 40, 0.03, CALVO_RATE,
     dict(VOLF=0.9, EOPT=0.0, P1=1e-4, T1=1.2, T2=16.0, THETA=60.0, GF=0.035, GM=0.03),
     "thesis 3.2.2: EOPT<0.1 (CMA 0), P1~1e-4, T2~16, THETA 60, GF~0.035, GM~0.03, larger misfit -> 3% noise; "
     "chosen VOLF 0.9, T1 1.2"),
    ("calvo2010_rat3", CALVO, 0.40, 36, 0.02, CALVO_RATE,
     dict(VOLF=0.8, EOPT=0.16, P1=0.05, T1=20.0, T2=2.5, THETA=60.0, GF=0.04, GM=0.04),
     "thesis 3.2.3: EOPT>~0.16, T1 large (30-80 explored at high VOLF), THETA 60, GF~GM~0.04; chosen "
     "VOLF 0.8 with T1 20 (box edge; (1-c)*T1=4 MPa, i.e. T1=40 at VOLF 0.9), T2 2.5, P1 0.05"),
    ("calvo2010_rat4", CALVO, 0.43, 50, 0.025, CALVO_RATE,
     dict(VOLF=0.9, EOPT=0.15, P1=0.06, T1=1.0, T2=14.0, THETA=60.0, GF=0.03, GM=0.02),
     "thesis 3.2.4: GF~0.03, GM~0.02; chosen VOLF 0.9, EOPT 0.15, P1 0.06, T1 1.0, T2 14, THETA 60"),
    ("calvo2010_rat5", CALVO, 0.45, 38, 0.02, CALVO_RATE,
     dict(VOLF=0.9, EOPT=0.21, P1=0.08, T1=0.8, T2=24.0, THETA=60.0, GF=0.04, GM=0.04),
     "thesis 3.2.5: EOPT~0.21, T2~24, GF~GM~0.04, THETA 60 (one of two modes); chosen VOLF 0.9, "
     "P1 0.08, T1 0.8"),
]


def make(out: Path) -> list[Path]:
    """Write the six specimen files into ``out``; return their paths."""
    model = hbm.spyrou_model(ISO_FACTOR)
    seeds = np.random.SeedSequence(ENTROPY).spawn(len(SPECIMENS))
    paths = []
    for (sid, cite, eps_max, n, rel_sd, rate, params, notes), seed in zip(SPECIMENS, seeds):
        # strain grid rounded to 1e-6 like a recorded extensometer signal
        strain = np.round(np.linspace(0.0, eps_max, n), 6)
        time = None if rate is None else np.round(strain / rate, 3)
        attrs = {
            "id": sid,
            "provenance": "synthetic",
            "source": "synthetic stand-in (not measured data) for a rat passive-muscle curve of the paper cited below",
            "citation": cite,
            "generator": "workflows/make_specimens.py (hbm.data.synthetic_specimen)",
            "model": f"spyrou_model(iso_factor={ISO_FACTOR})",
            "iso_factor": repr(ISO_FACTOR),
            "parameters": json.dumps(params),
            "parameter_notes": notes,
            "A_m": f"{(1 - params['VOLF']) * params['T1']:.6g} MPa ((1-VOLF)*T1, the identifiable collagen scale)",
            "units": "strain: engineering (-); stress: Cauchy along fibers (MPa)"
                     + ("; time: s" if rate is not None else ""),
            "strain_rate": (f"{rate!r} 1/s ({rate * 100:.3g} %/s, quasi-static)" if rate is not None
                            else "not given (quasi-static); no time column"),
        }
        ds = synthetic_specimen(model, params, Loading(strain, time), rel_sd, seed, noise="iid",
                                relative=True, attrs=attrs)
        ds = ds.with_series("stress", np.round(ds.stress, 7)).with_attrs(
            noise_description=(f"iid Gaussian, sd {rel_sd:g} x max stress = "
                               f"{float(ds.attrs['noise_sd']):.4g} MPa; stress rounded to 1e-7 MPa"))
        paths.append(save_specimen(ds, out / f"{sid}.csv"))
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "data" / "specimens",
                        help="output folder (default: data/specimens of this repository)")
    args = parser.parse_args(argv)
    for p in make(args.out):
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
