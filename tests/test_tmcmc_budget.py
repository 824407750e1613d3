"""``--max-evaluations`` on ``hbm fit`` / ``hbm run``: the budget reaches TMCMC, bad budgets fail early."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import hbm.cli as cli
import hbm.cli.fit as cli_fit
import hbm.cli.run as cli_run
from hbm.samplers.tmcmc import tmcmc

ROOT = Path(__file__).resolve().parents[1]
SPECIMEN = str(ROOT / "data" / "specimens" / "calvo2010_rat1.csv")


class Captured(Exception):
    """Raised by the patched engine with the keyword arguments it was called with."""


def _capture(*args, **kwargs):
    raise Captured(kwargs)


def test_fit_passes_the_budget(monkeypatch, tmp_path):
    monkeypatch.setenv("HBM_DEBUG", "1")
    monkeypatch.setattr(cli_fit, "fit_specimen", _capture)
    with pytest.raises(Captured) as exc:
        cli.main(["fit", SPECIMEN, "--samples", "500", "--max-evaluations", "40000", "--no-plot",
                  "--out", str(tmp_path / "never-written.nc")])
    assert exc.value.args[0]["settings"].max_evaluations == 40000
    with pytest.raises(Captured) as exc:
        cli.main(["fit", SPECIMEN, "--no-plot", "--out", str(tmp_path / "never-written.nc")])
    assert exc.value.args[0]["settings"].max_evaluations is None


def test_run_passes_the_budget(monkeypatch, tmp_path):
    monkeypatch.setenv("HBM_DEBUG", "1")
    monkeypatch.setattr(cli_run, "run_workflow", lambda cfg, **kw: _capture(cfg=cfg))
    with pytest.raises(Captured) as exc:
        cli.main(["run", "--out", str(tmp_path / "r"), "--max-evaluations", "90000", "--no-progress"])
    assert exc.value.args[0]["cfg"].tmcmc_options == {"max_evaluations": 90000}
    with pytest.raises(Captured) as exc:
        cli.main(["run", "--out", str(tmp_path / "r"), "--no-progress"])
    assert exc.value.args[0]["cfg"].tmcmc_options is None


@pytest.mark.parametrize("argv", [["fit", SPECIMEN, "--samples", "500", "--max-evaluations", "499"],
                                  ["run", "--max-evaluations", "1999"],
                                  ["run", "--quick", "--max-evaluations", "499"],
                                  ["fit", SPECIMEN, "--max-evaluations", "0"]])
def test_budget_below_the_population_is_a_one_line_error(argv, capsys, monkeypatch, tmp_path):
    monkeypatch.setattr(cli_fit, "fit_specimen", _capture)
    monkeypatch.setattr(cli_run, "run_workflow", _capture)
    assert cli.main(argv + ["--out", str(tmp_path / "o.nc" if argv[0] == "fit" else tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hbm: error:") and "--max-evaluations" in err[0]


def test_budget_is_respected_by_the_sampler():
    # independent count: rows seen by the likelihood, against the cap and the reported number
    rows = [0]

    def ll(x):
        rows[0] += len(x)
        return -0.5 * np.sum(((x - 0.3) / 0.05) ** 2, axis=1)

    r = tmcmc(ll, np.array([[0.0, 1.0]] * 3), 200, seed=1, progress=False, max_evaluations=5000)
    assert rows[0] == r.n_evaluations <= 5000 and r.budget_exhausted


def test_diagnose_and_extend_pass_the_budget(monkeypatch):
    import hbm.cli.diagnose as cli_diag
    monkeypatch.setenv("HBM_DEBUG", "1")
    for cmd, fn, extra in (("diagnose", "diagnose", []), ("extend", "extend", ["--auto"])):
        monkeypatch.setattr(cli_diag, fn, _capture)
        with pytest.raises(Captured) as exc:
            cli.main([cmd, SPECIMEN, "--max-evaluations", "30000", *extra])
        assert exc.value.args[0]["max_evaluations"] == 30000


def test_detective_evidence_run_keeps_within_the_budget():
    """Each TMCMC evidence run of the detective spends at most its budget (counted by the sampler)."""
    from hbm.data import load_specimen
    from hbm.detective.fitting import sample
    from hbm.likelihood import make_likelihood
    from hbm.model import spyrou_model

    lik = make_likelihood(spyrou_model(), load_specimen(SPECIMEN))
    free = sample(lik, 800, seed=3)
    capped = sample(lik, 800, seed=3, max_evaluations=20000)
    assert capped.n_evaluations <= 20000 < free.n_evaluations
