"""Issue 28: on compression data (ε ≤ 0) the fibre term c·P1·⟨ε − EOPT⟩₊ is identically zero,
so VOLF·P1 is the prior: the fit report labels it prior-dominated, not identified."""

from __future__ import annotations

import numpy as np

from hbm.fit.quality import _uninformed_combinations, quality_lines
from hbm.model.spyrou import spyrou_model


def test_fibre_term_is_zero_in_compression():
    m = spyrou_model()
    th = np.array([dict(VOLF=0.8, EOPT=0.1, P1=0.15, T1=0.8, T2=14.0, THETA=58.5, GF=0.015, GM=0.01)[k]
                   for k in m.parameter_names])
    eps = np.linspace(-0.3, 0.0, 31)
    th2 = th.copy()
    th2[m.index("P1")] = 0.45        # any fibre stiffness: the same compression curve
    np.testing.assert_allclose(m.stress(eps, th), m.stress(eps, th2), atol=1e-14)
    assert "VOLF*P1" in _uninformed_combinations(eps)
    assert _uninformed_combinations(np.linspace(-0.1, 0.2, 31)) == {}


def test_report_lists_it_as_prior_dominated():
    q = {"rmse": 1e-3, "rmse_rel": 1.0, "coverage90": 0.9, "n_points": 30, "log_evidence": 1.0,
         "log_evidence_se": 0.1, "noise": {}, "map_source": "sample", "map_log_likelihood": 0.0, "map": {},
         "combinations": {"G": {"median": 0.01, "lower": 0.009, "upper": 0.011},
                          "VOLF*P1": {"median": 0.24, "lower": 0.026, "upper": 0.46}},
         "at_bounds": [], "prior_dominated": _uninformed_combinations(np.array([-0.2, -0.1, 0.0]))}
    lines = quality_lines(q)
    ident = next(ln for ln in lines if ln.startswith("identified combinations"))
    assert "G 0.01" in ident and "VOLF*P1" not in ident
    assert any(ln.startswith("prior-dominated, not identified: VOLF*P1 0.24") for ln in lines)
