"""The energy cards in every loading mode (issue 35, item 8): how far N families and the FE laws are from hbm's cone.

For the six shipped specimens' generating parameters (``data/specimens/*.csv``, energy form, k_iso = 1, the
tested range 0..the file's largest strain), as a one-draw export source:

1. **N families** -- hbm's own segment law on N equally spaced azimuths (what a card with N fibre families
   computes) against the exact azimuthal average: the max deviation over the ten modes and their observables
   (:func:`hbm.export.modes.family_deviations`), N = 6 .. 96, on the tested range and on 1.5x it.
2. **febio-energy** as exported today (exp-linear families, N chosen by :mod:`hbm.export.modes`): along-fibre
   error, the family law's error, the max deviation per mode on the tested range, CPU seconds of the export.
3. **abaqus-uanisohyper** as exported today (hbm's segment law, N <= 24), the same (needs gfortran).
4. **The subroutine's cost** per call against N (``Subroutine`` with its arrays allocated once; CPU time,
   ``time.process_time``, including the ctypes call): Abaqus passes every pseudo-invariant pair, so the
   arrays grow as N² and N⁴.
5. With ``--old-laws FILE`` (``git show fede887:hbm/export/laws.py > FILE``): the febio-energy card of that
   commit (6 ``fiber-exp-pow-uncoupled`` families fitted on the along-fibre curve) solved in every mode the same
   way -- the measurement behind replacing it.

Usage::

    OMP_NUM_THREADS=1 python workflows/benchmarks/export_modes.py [--out results/benchmarks] [--old-laws FILE]

Writes ``export_modes.md`` / ``export_modes.json`` to ``--out`` and prints the tables.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from hbm.export import abaqus_uanisohyper, febio_energy, modes, source  # noqa: E402
from hbm.export.laws import BULK_FACTOR  # noqa: E402
from hbm.model.energy3d import Energy3D  # noqa: E402
from hbm.model.loadcases import LOAD_CASES, predict_observables  # noqa: E402
from hbm.model.spyrou import spyrou_model  # noqa: E402
from hbm.runtime.files import atomic_write_text  # noqa: E402

NS = (6, 12, 24, 48, 96)


def shipped() -> dict[str, tuple[dict, float]]:
    """specimen -> (generating parameters, largest strain of its file)."""
    out = {}
    for f in sorted((ROOT / "data" / "specimens").glob("*.csv")):
        text = f.read_text()
        line = next(x for x in text.splitlines() if x.startswith("# parameters:"))
        prm = {k: float(v) for k, v in re.findall(r'"(\w+)": ([-\d.e]+)', line)}
        strain = [float(x.split(",")[0]) for x in text.splitlines()[1:] if x and not x.startswith("#")
                  and x[0] in "-0123456789."]
        out[f.stem] = (prm, max(strain))
    return out


def export_source(name: str, prm: dict, hi: float) -> source.ExportSource:
    """A one-draw export source of ``prm`` (energy form, k_iso = 1) tested on strains 0..``hi``."""
    theta = np.array([prm[n] for n in source.NAMES])
    grid = np.linspace(0.0, 1.5 * hi, source.GRID)
    model = spyrou_model(form="energy")
    return source.ExportSource(path=Path(name), specimen=name, form="energy", k_iso=1.0, strain_range=(0.0, hi),
                               draws=theta[None], summary="median", theta=theta, curve_strain=grid,
                               curve_stress=model.stress(grid, theta), n_draws=1)


def families_table(sets) -> list[dict]:
    rows = []
    for name, (prm, hi) in sets.items():
        src = export_source(name, prm, hi)
        row = dict(parameters=name, T2=prm["T2"], tested=f"0..{hi:g}")
        for n in NS:
            t, x = modes.family_deviations(src, n)
            row[f"N={n}"] = f"{t:.2g} ({x:.2g})"
        rows.append(row)
    return rows


def card_row(name: str, prm: dict, written, seconds: float, extra: dict) -> dict:
    row = dict(parameters=name, T2=prm["T2"], N=written.modes[0].families, **extra,
               along=f"{written.checks[0].error_tested:.2g}", cpu_s=round(seconds, 1))
    row.update({c.mode: f"{c.error_tested:.2g} ({c.family_tested:.2g})" for c in written.modes})
    row["all passed"] = all(c.passed for c in written.modes)
    return row


def febio_table(sets) -> list[dict]:
    rows = []
    for name, (prm, hi) in sets.items():
        src = export_source(name, prm, hi)
        t = time.process_time()
        w = febio_energy.write(src)
        rows.append(card_row(name, prm, w, time.process_time() - t,
                             dict(law=f"{w.card['law_error']:.2g} ({w.card['law_error_15']:.2g})")))
    return rows


def abaqus_table(sets) -> list[dict]:
    rows = []
    for name, (prm, hi) in sets.items():
        src = export_source(name, prm, hi)
        t = time.process_time()
        w = abaqus_uanisohyper.write(src)
        rows.append(card_row(name, prm, w, time.process_time() - t, {}))
    return rows


def subroutine_cost(ns=(6, 12, 24, 48), seconds: float = 1.0) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as d:
        lib = abaqus_uanisohyper.compile_subroutine(Path(d))
        pr = dict(C10=0.01, D1=2.0 / (BULK_FACTOR * 0.02), Af=0.1, EOPT=0.1, Ac=0.01, T2=10.0)
        for n in ns:
            dirs = np.vstack([[1.0, 0, 0], np.tile([0.5, 0.8, 0.0], (n, 1))])
            sub = abaqus_uanisohyper.Subroutine(lib, pr, dirs)
            ainv = np.zeros(sub.ninv)
            ainv[0], ainv[2] = 3.1, 1.0
            ainv[sub.i4] = 1.05
            count, t0 = 0, time.process_time()
            while time.process_time() - t0 < seconds:
                sub._run(ainv)
                count += 1
            rows.append(dict(N=n, invariants=sub.ninv, second_derivatives=sub.ninv * (sub.ninv + 1) // 2,
                             us_per_call=round(1e6 * (time.process_time() - t0) / count, 1)))
    return rows


def old_card_table(sets, path: Path) -> list[dict]:
    """The febio-energy card of the commit whose laws.py is ``path``, solved in every mode here."""
    spec = importlib.util.spec_from_file_location("hbm.export._old_laws", path)
    old = importlib.util.module_from_spec(spec)
    old.__package__ = "hbm.export"
    sys.modules[spec.name] = old              # its dataclass looks itself up there
    spec.loader.exec_module(old)
    rows = []
    for name, (prm, hi) in sets.items():
        src = export_source(name, prm, hi)
        card = old.energy_card(src.params(), 1.0, src.strain_range, src.stress, src.curve_strain)
        dirs = np.vstack([[1.0, 0, 0], old.family_directions(card.theta, card.n_families)])

        def T(F, card=card, dirs=dirs):
            Fa = np.einsum("mij,kj->mki", F, dirs)
            In = np.einsum("mki,mki->mk", Fa, Fa)
            s = np.empty_like(In)
            s[:, 0] = old.pow_linear_cauchy(In[:, 0], card.fibre_E, card.fibre_lam0, card.fibre_beta)
            s[:, 1:] = old.exp_pow_cauchy(In[:, 1:], card.ksi, card.alpha, card.beta)
            return 2 * card.c1 * np.einsum("mij,mkj->mik", F, F) + np.einsum("mk,mki,mkj->mij", s / In, Fa, Fa)

        strain, tested = modes.control_grid(src.strain_range)
        cone = Energy3D(1.0, "energy", "cone")
        row = dict(parameters=name, T2=prm["T2"], N=card.n_families, along=f"{card.fit_error:.2g}")
        for mode, case in LOAD_CASES.items():
            try:
                got, _ = modes.solve_card(T, case, strain)
                dev = modes.deviations(case, predict_observables(cone, case, src.params(), strain), got, strain,
                                       tested)
                row[mode] = f"{max(v[0] for v in dev.values()):.2g}"
            except Exception as exc:   # noqa: BLE001 -- the old law may overflow or lose its root: say so
                row[mode] = f"no solution ({type(exc).__name__})"
        rows.append(row)
    return rows


def markdown(title: str, rows: list[dict], note: str = "") -> str:
    keys = list(rows[0])
    out = [f"### {title}", ""] + ([note, ""] if note else [])
    out += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "results" / "benchmarks"))
    ap.add_argument("--old-laws", type=Path, help="laws.py of the commit to compare (git show REV:hbm/export/laws.py)")
    a = ap.parse_args(argv)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    head = (f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, commit {commit}, Python "
            f"{platform.python_version()}, numpy {np.__version__}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, "
            f"load {load:.2f}; CPU times from time.process_time")
    sets = shipped()
    tables = {"families": families_table(sets), "febio_energy": febio_table(sets)}
    if shutil.which("gfortran"):
        tables["abaqus_uanisohyper"] = abaqus_table(sets)
        tables["subroutine_cost"] = subroutine_cost()
    if a.old_laws:
        tables["old_febio_energy"] = old_card_table(sets, a.old_laws)
    dev = ("max deviation from hbm's cone on the tested range over the mode's observables (|Δ| relative to the mode's "
           "largest stress; lateral strains to the applied strain); in brackets the N-family share")
    parts = ["# The energy cards in every loading mode (issue 35)", "", head, "",
             markdown("N equally spaced families vs the exact cone", tables["families"],
                      "hbm's segment law on N azimuths: max deviation over the ten modes and their observables, tested "
                      "range (1.5x in brackets)"),
             markdown("febio-energy today", tables["febio_energy"],
                      f"{dev}; law: the exp-linear family law's max relative error on the segment stretches of the "
                      "tested range (up to 1.5x in brackets); along: the along-fibre check")]
    if "abaqus_uanisohyper" in tables:
        parts += [markdown("abaqus-uanisohyper today", tables["abaqus_uanisohyper"], dev),
                  markdown("UANISOHYPER_INV cost per call", tables["subroutine_cost"],
                           "the subroutine with N + 1 local directions, its arrays allocated once; CPU time per call "
                           "including ctypes")]
    if "old_febio_energy" in tables:
        parts.append(markdown(f"febio-energy of {a.old_laws.name} (6 exp-pow families fitted along the fibres)",
                              tables["old_febio_energy"], dev.split(";")[0]))
    text = "\n".join(parts)
    print(text)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "export_modes.md", text)
    atomic_write_text(out / "export_modes.json", json.dumps(dict(header=head, **tables), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
