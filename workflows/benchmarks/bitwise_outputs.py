"""Digests of every number hbm's commands write, to prove a refactor changed no result (issue 34).

Runs, with the checkout given by ``--tree`` (default: this repository), in fresh processes:

* ``hbm run --quick`` and (``--full``) the default ``hbm run`` on the shipped specimens;
* ``hbm fit`` at defaults on every shipped file (``data/specimens/*.csv``, ``data/measured/*.csv`` with
  ``--sl0 2.0``);
* ``hbm diagnose --json`` on every shipped file;
* ``hbm export`` of every fitted specimen to every card format hbm writes without a compiler;
* (``extra``) the energy form: ``hbm fit --form energy`` of one specimen and its ``febio-energy`` card, and
  ``fit`` and ``diagnose`` of the other curves the repository ships (``results/**/*.csv``).

and writes a manifest ``{output: digest}`` where a digest covers the *content*: every variable of every
netCDF group (dtype, shape and bytes) and its attributes, JSON after dropping wall/CPU times, text after
masking durations.  Two manifests are compared with ``--compare A.json B.json`` (exit 1 on any
difference, which is named).  Outputs go to one fixed folder (``--work``, default
``$TMPDIR/hbm-bitwise``); the folder's name is masked in every digest, so runs in different folders compare.

Usage (the baseline from a worktree of the old commit, then the new code)::

    git worktree add --detach /tmp/before 68827b1
    python workflows/benchmarks/bitwise_outputs.py --tree /tmp/before --full --manifest /tmp/before.json
    python workflows/benchmarks/bitwise_outputs.py --full --manifest /tmp/after.json
    python workflows/benchmarks/bitwise_outputs.py --compare /tmp/before.json /tmp/after.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
#: keys whose values are durations or machine facts, not results
VOLATILE = re.compile(r"(^|_)(time|times|timings|seconds|wall|cpu|elapsed|created|date|task_times|"
                      r"total_before_report|hostname|workers_used)($|_)", re.I)
DURATION = re.compile(r"\d+(\.\d+)?\s*(s|ms|min)\b")

#: diagnose's --max-time for the comparison: a diagnosis cut at its deadline depends on the machine's load
UNBOUNDED = "86400"

FORMATS = ("febio-uniaxial", "febio-energy", "febio-optimize", "abaqus-marlow", "csv", "json")


def _scrub(obj):
    if isinstance(obj, dict):
        return {k: _scrub(v) for k, v in obj.items() if not VOLATILE.search(str(k))}
    if isinstance(obj, list):
        return [_scrub(v) for v in obj]
    return obj


WORK = [""]  # the output folder of this run: written into files as paths, masked in digests


def _mask(text: str) -> str:
    return text.replace(WORK[0], "<work>") if WORK[0] else text


def _attr(value):
    text = _mask(str(value))
    if text[:1] in "{[":
        try:
            return json.dumps(_scrub(json.loads(text)), sort_keys=True)
        except ValueError:
            pass
    if hasattr(value, "tobytes"):
        return value.tobytes().hex()
    return text


def digest_netcdf(path: Path) -> dict:
    import netCDF4

    out = {}

    def walk(group, prefix):
        attrs = {k: _attr(group.getncattr(k)) for k in group.ncattrs() if not VOLATILE.search(k)}
        out[prefix + "@attrs"] = hashlib.sha256(json.dumps(attrs, sort_keys=True).encode()).hexdigest()[:16]
        for name, var in group.variables.items():
            var.set_auto_mask(False)
            data = var[...]
            h = hashlib.sha256(f"{data.dtype}{data.shape}".encode())
            h.update(data.tobytes() if data.dtype != object else repr(data.tolist()).encode())
            h.update(json.dumps({k: _attr(var.getncattr(k)) for k in var.ncattrs()}, sort_keys=True).encode())
            out[f"{prefix}{name}"] = h.hexdigest()[:16]
        for name, sub in group.groups.items():
            walk(sub, f"{prefix}{name}/")

    with netCDF4.Dataset(path) as ds:
        walk(ds, "")
    return out


def digest_file(path: Path, work: Path) -> dict | str:
    if path.suffix == ".nc":
        return digest_netcdf(path)
    if path.suffix in (".png", ".pdf", ".svg", ".lock") or path.name.endswith(".tmp"):
        return "skipped"
    text = _mask(path.read_text(errors="replace"))
    if path.suffix == ".json":
        try:
            return hashlib.sha256(json.dumps(_scrub(json.loads(text)), sort_keys=True).encode()).hexdigest()[:16]
        except ValueError:
            pass
    return hashlib.sha256("\n".join(_text_lines(text)).encode()).hexdigest()[:16]


def _text_lines(text: str) -> list[str]:
    """The lines of a text output that hold results: durations masked, dates and timing sections dropped."""
    out, skip = [], False
    for ln in text.splitlines():
        if ln.startswith("#"):
            skip = bool(re.search(r"timings?", ln, re.I))
        if skip or ln.startswith("Generated ") or re.search(r"\btime\b|timings?|wall", ln):
            continue
        out.append(DURATION.sub("<t>", ln))
    return out


def hbm(tree: Path, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "hbm", *args], capture_output=True, text=True, cwd=cwd, env=env)
    print(f"  {time.perf_counter() - t:6.1f} s  exit {out.returncode}  hbm {' '.join(args)}", file=sys.stderr)
    return out


def shipped(tree: Path) -> list[tuple[Path, list[str]]]:
    files = [(p, []) for p in sorted((tree / "data" / "specimens").glob("*.csv"))]
    files += [(p, ["--sl0", "2.0"]) for p in sorted((tree / "data" / "measured").glob("*.csv"))]
    return files


def run_all(tree: Path, work: Path, full: bool, which: set[str]) -> dict:
    WORK[0] = str(work)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    (work / "fits").mkdir()
    manifest: dict = {}
    data = work / "data"
    shutil.copytree(tree / "data", data)  # the same input paths for every checkout
    files = [(data / p.relative_to(tree / "data"), extra) for p, extra in shipped(tree)]

    def record(label, proc, outputs=()):
        manifest[label + " exit"] = proc.returncode
        stdout = _mask(proc.stdout)
        if "--json" in label:
            try:
                stdout = json.dumps(_scrub(json.loads(stdout)), sort_keys=True)
            except ValueError:
                pass
        stdout = "\n".join(DURATION.sub("<t>", ln) for ln in stdout.splitlines()
                           if not re.search(r"^time:|\btimings?\b|wall", ln))
        manifest[label + " stdout"] = hashlib.sha256(stdout.encode()).hexdigest()[:16]
        for p in outputs:
            for f in sorted(Path(p).rglob("*")) if Path(p).is_dir() else [Path(p)]:
                if f.is_file():
                    manifest[f"{label} :: {f.relative_to(work)}"] = digest_file(f, work)

    if "quick" in which:
        out = work / "run-quick"
        record("run --quick", hbm(tree, ["run", "--quick", "--out", str(out), "--no-progress",
                                         "--data", str(data / "specimens")], work), [out])
    if full and "full" in which:
        out = work / "run-full"
        record("run", hbm(tree, ["run", "--out", str(out), "--no-progress", "--data", str(data / "specimens")], work),
               [out])
    fits = work / "fits"
    for path, extra in files:
        if "fit" in which:
            nc = fits / f"{path.stem}.nc"
            record(f"fit {path.name}", hbm(tree, ["fit", str(path), *extra, "--out", str(nc), "--no-progress",
                                                  "--no-plot", "--json"], work), [nc])
            if nc.exists() and "export" in which:
                for fmt in FORMATS:
                    card = work / "export" / f"{path.stem}_{fmt}"
                    card.parent.mkdir(exist_ok=True)
                    suffix = {"febio-uniaxial": ".feb", "febio-energy": ".feb", "febio-optimize": ".feb",
                              "abaqus-marlow": ".inp", "csv": ".csv", "json": ".json"}[fmt]
                    card = card.with_suffix(suffix)
                    record(f"export {path.name} {fmt} --json",
                           hbm(tree, ["export", str(nc), "--to", fmt, "--out", str(card), "--json"], work), [card])
        if "diagnose" in which:
            record(f"diagnose {path.name} --json",
                   hbm(tree, ["diagnose", str(path), *extra, "--json", "--no-progress", "--workers", "1",
                              "--max-time", UNBOUNDED], work))
    if "extra" in which:
        spec = data / "specimens" / "calvo2010_rat1.csv"
        nc = fits / "calvo2010_rat1_energy.nc"
        record("fit calvo2010_rat1.csv --form energy", hbm(tree, ["fit", str(spec), "--form", "energy", "--out", str(nc),
                                                                  "--no-progress", "--no-plot", "--json"], work), [nc])
        card = work / "export" / "calvo2010_rat1_energy_febio-energy.feb"
        card.parent.mkdir(exist_ok=True)
        record("export calvo2010_rat1_energy febio-energy --json",
               hbm(tree, ["export", str(nc), "--to", "febio-energy", "--out", str(card), "--json"], work), [card])
        for src in sorted((tree / "results").rglob("*.csv")):
            path = work / "results-data" / src.name
            path.parent.mkdir(exist_ok=True)
            shutil.copy(src, path)
            out = fits / f"{path.stem}.nc"
            record(f"fit {path.name}", hbm(tree, ["fit", str(path), "--out", str(out), "--no-progress", "--no-plot",
                                                  "--json"], work), [out])
            record(f"diagnose {path.name} --json",
                   hbm(tree, ["diagnose", str(path), "--json", "--no-progress", "--workers", "1", "--max-time",
                              UNBOUNDED], work))
    return manifest


def compare(a: dict, b: dict) -> list[str]:
    diffs = []
    for k in sorted(set(a) | set(b)):
        if a.get(k) != b.get(k):
            if isinstance(a.get(k), dict) and isinstance(b.get(k), dict):
                inner = [f"{k} [{v}]" for v in sorted(set(a[k]) | set(b[k])) if a[k].get(v) != b[k].get(v)]
                diffs += inner
            else:
                diffs.append(f"{k}: {a.get(k)!r} != {b.get(k)!r}")
    return diffs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tree", default=str(REPO), help="checkout whose hbm runs (default: this repository)")
    p.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "hbm-bitwise"))
    p.add_argument("--full", action="store_true", help="also the default hbm run (minutes)")
    p.add_argument("--only", default="quick,full,fit,export,diagnose,extra", help="comma-separated subset")
    p.add_argument("--manifest", help="write the manifest here (default: stdout)")
    p.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two manifests")
    p.add_argument("--redigest", metavar="MANIFEST", help="recompute the file digests of MANIFEST from the outputs "
                   "still in --work (after a change of this script's masking; stdout digests are kept)")
    args = p.parse_args(argv)
    if args.redigest:
        WORK[0] = str(Path(args.work))
        manifest = json.loads(Path(args.redigest).read_text())
        for key in [k for k in manifest if " :: " in k]:
            f = Path(args.work) / key.split(" :: ", 1)[1]
            if f.is_file():
                manifest[key] = digest_file(f, Path(args.work))
        Path(args.redigest).write_text(json.dumps(manifest, indent=1, sort_keys=True))
        return 0
    if args.compare:
        a, b = (json.loads(Path(x).read_text()) for x in args.compare)
        diffs = compare(a, b)
        print("\n".join(diffs) if diffs else f"identical: {len(a)} outputs")
        return 1 if diffs else 0
    manifest = run_all(Path(args.tree).resolve(), Path(args.work), args.full, set(args.only.split(",")))
    text = json.dumps(manifest, indent=1, sort_keys=True)
    if args.manifest:
        Path(args.manifest).write_text(text)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
