"""``febio-optimize``: an FEBio optimisation input (febio_optimize version 2.0) started from the posterior.

The parameters are those of the card a user puts in their model: ``febio-energy`` for energy-form
results, ``febio-uniaxial`` for thesis-form ones.  Start: the summary's value; bounds: the 1–99 %
interval of the same card parameter over the posterior draws.  Only parameters with a closed-form
map from hbm's are listed (Mooney-Rivlin c1 = k_iso·G/2; the fibre's E = c·P1·(1 + EOPT), or the
load-curve scale smax); the collagen families' fitted ksi/alpha (six copies that must move
together) stay as written in the card.  The objective's data are hbm's summary curve (Cauchy
stress against stretch); the data source (``fnc``) must be pointed at the matching output of the
user's model before running ``febio4 -i model.feb -s this.feb``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from ._xml import provenance_lines, sub, to_text
from .registry import Written

DESCRIPTION = "FEBio optimisation input: posterior summary as start, 1-99 % posterior interval as bounds"
SUFFIX = ".feb"
VALID = "a starting point for refining the card's parameters inside the user's own FE model"
QUANTILES = (0.01, 0.99)
N_DATA = 21


def parameters(src) -> list[tuple[str, float, float, float, str]]:
    """(FEBio parameter path, start, lower, upper, meaning) of the card of ``src``."""
    d = src.draws
    every, cons = src.constituents(d), src.constituents()  # every draw's and the summary's
    c1 = src.k_iso * every.shear_modulus / 2.0
    c1_0 = src.k_iso * cons.shear_modulus / 2.0
    out = [("fem.material[0].solid[0].c1", c1_0, *np.quantile(c1, QUANTILES), "Mooney-Rivlin c1 (MPa)")]
    if src.form == "energy":
        e = every.fibre_amplitude * (1 + every.fibre_onset)
        e0 = cons.fibre_amplitude * (1 + cons.fibre_onset)
        out.append(("fem.material[0].solid[1].E", e0, *np.quantile(e, QUANTILES), "fibre modulus E (MPa)"))
    else:
        # smax scales the tabulated fibre + collagen stress: its spread is that of that stress at the
        # largest tested strain relative to the summary's
        hi = np.array([src.strain_range[1]])
        lam = 1.0 + hi[0]

        def fibre_collagen(t):
            t = np.atleast_2d(t)
            g = src.constituents(t).shear_modulus
            return src.model().stress(hi, t)[:, 0] - src.k_iso * g * (lam ** 2 - 1 / lam)

        s0 = float(fibre_collagen(src.theta)[0])
        ratio = fibre_collagen(d) / s0 if s0 > 0 else np.ones(1)
        out.append(("fem.material[0].solid[1].smax", 1.0, *np.quantile(ratio, QUANTILES),
                    "active fibre stress scale smax (MPa per load-curve unit)"))
    return [(n, float(x0), float(min(lo, x0)), float(max(hi_, x0)), m) for n, x0, lo, hi_, m in out]


def build(src, params) -> ET.Element:
    root = ET.Element("febio_optimize", version="2.0")
    opts = sub(root, "Options", type="levmar")
    sub(opts, "print_level", "PRINT_ITERATIONS")
    ps = sub(root, "Parameters")
    for name, x0, lo, hi, _ in params:
        sub(ps, "param", f"{x0:.10g},{lo:.10g},{hi:.10g}", name=name)
    obj = sub(root, "Objective", type="data-fit")
    fnc = sub(obj, "fnc", type="parameter")
    sub(fnc, "param", name="fem.rigidbody('grip').Fx")
    data = sub(obj, "data")
    idx = np.linspace(0, src.curve_strain.size - 1, N_DATA).round().astype(int)
    keep = [i for i in idx if src.tested_mask()[i]]
    for i in keep:
        sub(data, "pt", f"{1 + src.curve_strain[i]:.10g},{src.curve_stress[i]:.10g}")
    return root


def write(src) -> Written:
    params = parameters(src)
    lines = provenance_lines(src, DESCRIPTION, VALID, [])
    lines.append("parameters (path: start, lower, upper): " + "; ".join(
        f"{n} = {x0:.6g} in [{lo:.6g}, {hi:.6g}] ({m})" for n, x0, lo, hi, m in params))
    lines.append("paths assume the card of 'hbm export --to " + ("febio-energy" if src.form == "energy" else
                 "febio-uniaxial") + "' as material 1; the data are hbm's summary curve (stretch, Cauchy "
                 "stress MPa): point <fnc> at your model's matching output (the grip force here is a placeholder)")
    return Written(text=to_text(build(src, params), lines), checks=[],
                   card={"parameters": [{"name": n, "start": x0, "lower": lo, "upper": hi, "meaning": m}
                                        for n, x0, lo, hi, m in params]})
