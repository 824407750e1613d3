"""Markdown report of a workflow run (``<out>/report.md``).

The report is :data:`SECTIONS`, one function per heading, each ``f(workflow_result, base) ->
markdown`` ("" leaves the section out): title, run settings, timings, one subsection per
specimen (posterior mean, sd, 90 % interval, log-evidence ± SE, automatically detected
identified directions, manifold, Sobol), identifiable combinations across specimens, VOLF–T1
manifolds compared, population estimates (hierarchical layer), specimen variability, figures
across specimens; then any ``extra_sections`` (hooks ``f(workflow_result) -> markdown``, e.g.
organ predictions).  Numbers come from :mod:`hbm.identifiability.views` and :func:`hbm.fit.summarize`; the
report draws nothing.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .._version import __version__
from ..fit.specimen import at_bounds, fit_quality, format_at_bounds, summarize
from ..settings.fit import FitRecord
from ..identifiability.manifolds import compare_manifolds
from ..model.spec import spec_of
from ..samplers.hierarchical import group_differences, variance_split
from ..runtime.files import atomic_write_text
from ..identifiability.views import population_table, quantity_samples, specimen_variability

__all__ = ["render_report", "write_report", "fmt", "SECTIONS"]


def fmt(x: float, digits: int = 4) -> str:
    """Compact number formatting for tables."""
    if x is None or not np.isfinite(x):
        return "–"
    return f"{x:.{digits}g}"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines)


def _rel(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:  # pragma: no cover - other drive
        return str(path)


def _header(wres, base: Path) -> str:
    """Title line: date, version, specimens, reused ones; the failed specimens."""
    ids = sorted(wres.results)
    txt = (f"# hbm run report\n\nGenerated {_dt.datetime.now(_dt.timezone.utc):%Y-%m-%d %H:%M UTC} by hbm "
           f"{__version__}. {len(ids)} specimens from `{wres.config.data}`"
           + (f"; {len(wres.skipped)} reused from a previous run ({', '.join(wres.skipped)})" if wres.skipped else "")
           + ".")
    if wres.errors:
        txt += "\n\n**Failed specimens:**\n\n" + "\n".join(f"- `{k}`: {v}" for k, v in sorted(wres.errors.items()))
    return txt


def _settings(wres, base: Path) -> str:
    """## Run settings: the run's settings that shape the results (the TMCMC move keeps its stored label,
    "kernel", so that a report of unchanged results is unchanged)."""
    cfg = wres.config
    rows = [("samples (TMCMC N)", cfg.samples), ("kernel", cfg.move), ("noise model", cfg.noise),
            ("seed", cfg.seed), ("workers", cfg.workers if cfg.workers is not None else "all cores"),
            ("scheduler", cfg.scheduler or os.environ.get("DASK_SCHEDULER_ADDRESS") or "embedded LocalCluster"),
            ("CMA-ES restarts / budget per run", f"{cfg.restarts} / {cfg.maxfevals} evaluations"),
            ("bound sweep", cfg.sweep or "none"), ("Sobol N", cfg.sobol_n if cfg.sobol else "off"),
            ("fixed", cfg.fix or "none"), ("narrowed bounds", cfg.bounds or "none"),
            ("hierarchical samples", cfg.hier_samples if cfg.hierarchical else "off"),
            ("quick", "yes" if cfg.quick else "no")]
    return "## Run settings\n\n" + _table(["setting", "value"], rows)


def _timings(wres, base: Path) -> str:
    """## Timings: wall time of each phase, CPU sums over the specimen tasks."""
    t = wres.timings
    reused = list(getattr(wres, "skipped", []) or [])
    split = bool(t.get("specimens_extras_beside_layer"))
    # a split run's parallel phase is the posteriors only: the optima, sweep and Sobol ran beside the layer
    fit_label = ("specimen posteriors (parallel phase, wall; optima, sweep and Sobol beside the layer)" if split
                 else "specimen fits (parallel phase, wall)")
    if reused:  # a resumed/re-run workflow: the fits' own times come from their stored results
        fit_label += f"; {len(reused)} of {len(wres.results)} reused from an earlier run"
    trow = [(fit_label, t.get("specimens_wall"))]
    for ph, lab in (("cmaes", "CMA-ES"), ("tmcmc", "TMCMC"), ("predictive", "posterior predictive"),
                    ("sobol", "Sobol")):
        # beside the layer at a lower priority these tasks' times are stretched by the layer's use of the cores
        beside = "; beside the layer, stretched by it" if split and ph in ("cmaes", "sobol") else ""
        trow.append((f"{lab} (sum over specimens, in tasks{', as stored' if reused else ''}{beside})",
                     t.get(f"{ph}_cpu")))
    hier_label = "hierarchical layer" + ("; reused from an earlier run (unchanged specimens and settings)"
                                         if t.get("hierarchical_reused") else "")
    trow += [(hier_label, t.get("hierarchical"))]
    if split:
        trow.append(("specimens' optima, sweep and Sobol: waited for after the layer (wall)",
                     t.get("specimens_extras_wait")))
    if t.get("hierarchical_evaluations") is not None:
        trow.append(("hierarchical layer: model evaluations (count, not seconds)", t["hierarchical_evaluations"]))
    trow += [("identifiability + manifolds", t.get("identify")),
             ("figures", t.get("figures")), ("total before report", t.get("total_before_report"))]
    return "## Timings (seconds)\n\n" + _table(["phase", "s"], [(a, f"{b:,}" if isinstance(b, int) else fmt(b, 3))
                                                               for a, b in trow])


def _specimen(wres, sid: str, base: Path) -> str:
    """### <id>: evidence, posterior table, identified directions, manifold, Sobol, figures."""
    r = wres.results[sid]
    converted = FitRecord.from_attrs(r.config).input
    rows = [(k, fmt(v["mean"]), fmt(v["sd"], 3), f"[{fmt(v['lower'])}, {fmt(v['upper'])}]")
            for k, v in summarize(r).items()]
    txt = [f"### {sid}\n",
           f"log-evidence **{r.log_evidence:.3f} ± {r.log_evidence_se:.3f}** ({len(r.stages)} TMCMC stages, "
           f"{r.n_samples} samples" + (f", fixed {r.fixed}" if r.fixed else "") + ")\n",
           *([f"Input converted: {converted} (stresses here are Cauchy, MPa).\n"] if converted else []),
           _table(["quantity", "mean", "sd", "90% interval"], rows)]
    dirs = wres.directions.get(sid)
    if dirs is not None:
        lead = ("\nIdentified combinations, found from the samples (a sparse basis of the directions in log "
                "space whose posterior sd is below 10% of the prior's; products of powers): ")
        txt.append(lead + ("; ".join(f"`{d['expression']}`"
                                     + (f" = {fmt(d['median'])} [{fmt(d['lo'])}, {fmt(d['hi'])}]"
                                        if np.isfinite(d.get("median", np.nan)) else "")
                                     + f" (sd ratio {d['ratio']:.2g})" for d in dirs[:6])
                           or "none (no combination of up to three parameters is pinned that tightly)"))
    m = wres.manifolds.get(sid)
    man = spec_of(r).manifold
    if m is not None and man is not None:
        x, y, level = man.x, man.y, man.level_text
        txt.append(f"\n{x}–{y} manifold from {m['source']}: {x} ∈ [{fmt(min(m['points_x']), 3)}, "
                   f"{fmt(max(m['points_x']), 3)}], variation of {level} along it ((max−min)/median) "
                   f"{m['combination_rel_spread']:.1%}"
                   + (f"; level {level} = {fmt(m['level'][0])} [{fmt(m['level'][1])}, {fmt(m['level'][2])}]"
                      if "level" in m else "") + ".")
    if r.sobol:
        order = sorted(r.sobol["ST"], key=lambda k: -np.nan_to_num(r.sobol["ST"][k], nan=-1))
        txt.append("\nSobol (ST, " + str(r.sobol.get("qoi", "")) + "): "
                   + ", ".join(f"{k} {fmt(r.sobol['ST'][k], 2)} ({r.sobol['relevance'].get(k, '')})"
                               for k in order))
    figs = [f for f in wres.figures if Path(f).name.startswith(sid + "_")]
    if figs:
        txt.append("\nFigures: " + ", ".join(f"[{Path(f).stem.split('_')[-1]}]({_rel(Path(f), base)})"
                                             for f in figs))
    return "\n".join(txt)


def _specimens(wres, base: Path) -> str:
    """## Specimens: one subsection per specimen (:func:`_specimen`)."""
    return "\n\n".join(["## Specimens"] + [_specimen(wres, sid, base) for sid in sorted(wres.results)])


def _fit_quality(wres, base: Path) -> str:
    """## Fit quality and box edges: RMSE, predictive coverage and parameters on a prior edge."""
    results = wres.results
    if not results:
        return ""
    rows, edges = [], []
    for sid in sorted(results):
        r = results[sid]
        try:
            q = fit_quality(r)
        except Exception as exc:  # a quality table is a bonus; never lose the report over it
            rows.append([sid, f"(failed: {exc})", "", "", ""])
            continue
        rows.append([sid, fmt(q["rmse"]), f"{100 * q['rmse_rel']:.2f}", f"{100 * q['coverage90']:.0f}%",
                     _tier(r)])
        edges += [f"- {sid}: " + line.removeprefix("warning: ") for line in format_at_bounds(at_bounds(r))]
    text = ("## Fit quality and box edges\n\nRMSE of the best fit (MAP) and the fraction of points inside "
            "the 90% posterior-predictive band; the likelihood tier that produced each posterior (collapsed: the "
            "linear amplitudes integrated exactly, only the nonlinear and noise parameters sampled).\n\n"
            + _table(["specimen", "RMSE (MPa)", "RMSE (% of peak)", "90% coverage", "likelihood"], rows))
    if edges:
        text += ("\n\nParameters whose best fit, or more than 20% of whose posterior, lies within 2% of a box "
                 "edge: the result there rests on the prior box, not on the data.\n\n" + "\n".join(edges))
    else:
        text += "\n\nNo parameter sits on a box edge."
    return text


def _tier(r) -> str:
    """The likelihood tier of a stored result, with the evidence's source when it is not TMCMC's."""
    stored = FitRecord.from_attrs(r.config if isinstance(r.config, dict) else {})
    tier = str(stored.tier_used)
    source = stored.collapsed.get("evidence_source") if isinstance(stored.collapsed, dict) else None
    return tier if not source or source == "tmcmc" else f"{tier} (evidence: {source})"


def _combinations(wres, base: Path) -> str:
    """## Identifiable combinations: posterior mean and 90 % interval of each, per specimen."""
    results = wres.results
    ids = sorted(results)
    spec = _spec(wres)
    combos = [c for c in spec.combination_names if all(c in summarize(results[s]) for s in ids)] if ids else []
    if not combos:
        return ""
    rows = []
    for sid in ids:
        s = summarize(results[sid])
        rows.append([sid] + [f"{fmt(s[c]['mean'])} [{fmt(s[c]['lower'])}, {fmt(s[c]['upper'])}]" for c in combos])
    units = sorted({c.unit for c in spec.combinations if c.name in combos})
    note = spec.texts.get("combinations", "")
    return (f"## Identifiable combinations (posterior mean [90% interval], {', '.join(units)})\n\n"
            + (note + "\n\n" if note else "") + _table(["specimen"] + combos, rows))


def _spec(wres):
    """The spec of the run's base model (its results'; the default base's without results)."""
    return spec_of(next(iter(wres.results.values()), None))


def _manifolds(wres, base: Path) -> str:
    """## x–y manifolds across specimens (the spec's manifold: VOLF–T1 for the Spyrou base): level and
    flatness of (1 − x)·y per specimen."""
    objs = {k: m["object"] for k, m in wres.manifolds.items() if "object" in m}
    man = _spec(wres).manifold
    if len(objs) < 2 or man is None:
        return ""
    title, level = f"## {man.x}–{man.y} manifolds across specimens", man.level_text
    try:
        cmp = compare_manifolds(objs)
        return (f"{title}\n\nLevel of {level} along each "
                "specimen's manifold (flatness: (max−min)/median along the spline; ≈ 0 means the "
                f"manifold is the hyperbola {level} = const).\n\n" + cmp.table()
                + f"\n\nSpread of the levels (max/min): {cmp.spread:.3g}.")
    except Exception as exc:  # comparison is a bonus; never lose the report over it
        return f"{title}\n\n(comparison failed: {exc})"


def _population(wres, base: Path) -> str:
    """## Population estimates: hyperparameters, pooling, a new specimen, importance ESS, warnings."""
    h = wres.hierarchical
    if h is None:
        return ""
    spec = _spec(wres)
    pt = population_table(h)
    rows = [(k, v["transform"], f"{fmt(v['median'])} [{fmt(v['median_lower'])}, {fmt(v['median_upper'])}]",
             f"[{fmt(v.get('new_lower'))}, {fmt(v.get('new_upper'))}]", fmt(v["sd_transformed"], 3))
            for k, v in pt.items()]
    txt = ["## Population estimates (hierarchical layer)\n",
           f"Each parameter θ_k ~ Normal(mu_k, sd_k) in a transformed space (column 'transform': "
           f"{spec.texts.get('transforms', 'log, logit or identity, by the model')}); uniform hyperprior on mu, "
           f"{h.attrs.get('hyperprior', {}).get('sd', 'log-uniform sd')}; " + _how_sampled(h) + "\n",
           _table(["quantity", "transform", "population median [90%]", "new specimen 90%",
                   "population sd (transformed units)"], rows)]
    reasons = dict(h.attrs.get("pool_reasons") or {})
    if h.attrs.get("mode") == "combinations" and spec.mixture is not None:
        reasons.pop("combinations", None)
        pooled = list(h.attrs.get("pooled", []))
        labels = [c.text for c in spec.combinations]
        mixed = ", ".join(spec.mixture.params)
        txt.append(
            f"\nPooled (`--pool combinations`, the default for the base model): {', '.join(pooled)}. A uniaxial "
            f"curve identifies {', '.join(labels[:-1])} and {labels[-1]}, not {mixed} "
            "one by one, so the population is put on the logs of the combinations (a log-normal population "
            f"of each) together with {' and '.join(spec.pooled_shape)}; the exact density that the uniform "
            "stage-1 prior induces on the combinations is divided out of the importance ratios. Given its "
            f"combinations, a specimen's {mixed} keep their stage-1 prior"
            + "".join(f", and so does {p} (not pooled)" for p in spec.pooled_when_informed if p not in pooled)
            + ". Fraction of new-specimen draws outside the support of the combinations (rejected): "
            f"{fmt(h.attrs.get('outside_support_fraction'), 2)}.")
        for p in spec.pooled_when_informed:
            if p in reasons:
                txt.append(f"\n{p} is pooled only when the posteriors inform it: {reasons[p]}")
    elif reasons:
        # why each parameter is (not) pooled: a population over parameters the curves do not
        # inform makes the reused-sample importance weights degenerate
        txt.append("\nPooled parameters (`--pool informed`: posterior sd in the transformed space below 2/3 "
                   "of the prior's in at least half of the specimens, in ten at most with the joint sampler; the others "
                   "keep their own prior):\n")
        txt.extend(f"- {v}" if str(v).startswith(f"{k}:") else f"- {k}: {v}" for k, v in reasons.items())
    pop = quantity_samples(h.pooled_names, h.new_specimen, spec) if h.new_specimen is not None else {}
    if pop:
        med = {}
        if h.updated is not None:
            med = {c: np.median(quantity_samples(h.param_names, h.updated.reshape(-1, h.updated.shape[-1]), spec)[c])
                   for c in pop}
        rows = [(c, f"[{fmt(np.quantile(v, 0.05))}, {fmt(np.quantile(v, 0.95))}]", fmt(np.median(v)),
                 fmt(med.get(c)))
                for c, v in pop.items()]
        txt.append("\nIdentifiable quantities of a new specimen (population predictive):\n\n"
                   + _table(["quantity", "90% interval", "median", "median over updated individuals"], rows))
    ess = h.attrs.get("ess_summary", {})
    exact = h.attrs.get("exact") or {}
    if ess:
        low = {k: v for k, v in ess.items() if v.get("q10", np.inf) < 50}
        real = set(exact.get("exact") or [])
        if low and low.keys() <= real:
            # the fallback replaced the reuse estimates of exactly these specimens by their real likelihoods
            consequence = (f". ESS collapsed for {', '.join(sorted(low))} in the reuse pass; the exact fallback "
                           "sampled the population and these specimens with their real likelihoods, so the "
                           "population estimates above do not rest on those importance estimates (see \"Reuse "
                           "of the stage-1 samples\" for its convergence).")
        elif low:
            consequence = (f". **ESS collapsed for {', '.join(sorted(low))}**: their updated posteriors come from "
                           f"a fresh TMCMC run (done for: {', '.join(h.attrs.get('refined') or []) or 'none'}), but "
                           f"the hyper-posterior itself rests on importance estimates with few effective samples "
                           f"for them: read the population estimates with care, increase --samples, or pool "
                           f"fewer quantities (`--pool informed` or a list).")
        else:
            consequence = "."
        txt.append("\nImportance ESS per specimen (min / 10% quantile over hyper-posterior draws"
                   + (" of the reuse pass" if exact else "") + "): "
                   + ", ".join(f"{k} {fmt(v.get('min'), 3)}/{fmt(v.get('q10'), 3)}" for k, v in ess.items())
                   + consequence)
    if h.attrs.get("warnings"):
        txt.append("\nWarnings: " + "; ".join(map(str, h.attrs["warnings"][:5])))
    return "\n".join(txt)


def _how_sampled(h) -> str:
    """Where the hyper-posterior and the hyper-evidence come from (the joint sampler, or for files made
    before issue 37 the exact fallback, replaces the first but does not estimate the second)."""
    layer = h.attrs.get("layer") or {}
    if layer:
        rhat_s = layer.get("rhat_specimen_max")
        return (f"hyper-posterior and updated individuals by joint sampling of the population and every specimen "
                f"with its real likelihood (batched Metropolis-within-Gibbs, {layer.get('chains')} chains × "
                f"{layer.get('n_keep')} kept draws after {layer.get('n_burn')} burn-in rounds; "
                f"{layer.get('evaluations'):,} model evaluations, {fmt(layer.get('wall_s'), 3)} s). Convergence: "
                f"max R-hat {fmt(layer.get('rhat_hyper_max'), 4)} and min bulk ESS {fmt(layer.get('ess_hyper_min'), 4)} "
                f"over the hyper-parameters, max R-hat {fmt(rhat_s, 4)} over the specimens' columns"
                + (" (**not converged**: see the warnings)" if h.attrs.get("warnings") else "")
                + ". No hyper-evidence: this sampler does not estimate it (`--hier-exact none`, TMCMC over the "
                "population reusing the stage-1 samples, does).")
    ev = f"**{h.log_evidence:.3f} ± {h.log_evidence_se:.3f}**"
    if not (h.attrs.get("exact") or {}):
        return f"hyper-posterior by TMCMC reusing the stage-1 samples. Hyper-evidence {ev}."
    return ("hyper-posterior by the exact fallback (joint Metropolis-within-Gibbs with the specimens' real "
            "likelihoods; see \"Reuse of the stage-1 samples\"). Hyper-evidence " + ev + ", the importance "
            "estimate of the reuse pass (the fallback does not estimate evidence): it rests on the reused samples "
            "of the flagged specimens, so compare it across models with their caveats in mind.")


def _reuse(wres, base: Path) -> str:
    """## Reuse of the stage-1 samples: per-specimen diagnostics of what the reused samples cannot represent."""
    h = wres.hierarchical
    reuse = getattr(h, "reuse", None) or {}
    if not reuse:
        return ""
    refined = set(h.attrs.get("refined") or [])
    exact = h.attrs.get("exact") or {}
    rows = []
    for sid, r in reuse.items():
        verdict = ("**unreliable**: " + "; ".join(r.get("reasons") or []) if r.get("unreliable") else "fine")
        rows.append((sid, fmt(r.get("ess_q10"), 3), fmt(r.get("khat_median"), 2), fmt(r.get("khat_q90"), 2),
                     fmt(r.get("population_beyond"), 2), fmt(r.get("uncovered"), 2),
                     fmt(r.get("population_outside"), 2), verdict,
                     _updated_from(sid, refined, exact)))
    return ("## Reuse of the stage-1 samples\n\nThe population layer reweights each specimen's stage-1 "
            "samples. The importance ESS only measures how unevenly the existing samples are weighted; "
            "the other columns measure what they cannot represent: PSIS k̂ of the importance ratios "
            "(median and 90 % quantile over hyper-posterior draws; > 0.7 unreliable), the population mass "
            "beyond the samples' 0.5–99.5 % range with the likelihood extrapolated by its slope at the edge "
            "of the samples (> 0.35 unreliable: where the data bound a quantity from one side only, as c·P1 "
            "when the fibre term is buried in the noise, the samples drawn under the uniform prior thin out "
            "exactly where a population may put its mass), the specimen's posterior share beyond the "
            "samples' range (same extrapolation) and the population-predictive probability outside the "
            "samples' 99 % range (likelihood ignored: information only). " + _reuse_consequence(reuse, exact) + "\n\n"
            + _table(["specimen", "ESS 10%", "k̂ median", "k̂ 90%", "population beyond samples",
                      "posterior beyond samples", "population outside 99%", "verdict", "updated posterior from"],
                     rows))


def _updated_from(sid: str, refined: set, exact: dict) -> str:
    """Where a specimen's updated posterior comes from (the reuse table's last column)."""
    if exact:
        return ("joint Gibbs, real likelihood" if sid in (exact.get("exact") or [])
                else "joint Gibbs, reweighted samples")
    return "fresh TMCMC" if sid in refined else "reweighted samples"


def _reuse_consequence(reuse: dict, exact: dict | None = None) -> str:
    """What the run did about flagged specimens, and what that leaves uncertain."""
    second = any(any(str(x).startswith("first pass:") for x in (r.get("reasons") or [])) for r in reuse.values())
    flagged = [sid for sid, r in reuse.items() if r.get("unreliable")]
    if exact:
        ev = sum((exact.get("evaluations") or {}).values())
        others = exact.get("reuse") or []
        text = (f"The exact fallback ran (`--hier-exact gibbs`, the default): the joint posterior of the population "
                f"and the specimens was sampled by Metropolis-within-Gibbs, {', '.join(exact.get('exact') or [])} "
                f"with their real likelihoods"
                + (f", {', '.join(others)} by their reweighted stage-1 samples" if others else "")
                + f" ({exact.get('n_chains')} chains × {exact.get('n_keep')} kept draws after {exact.get('n_burn')} "
                f"burn-in sweeps, {ev} likelihood evaluations, {fmt(exact.get('wall_s'), 3)} s); the population "
                f"estimates and updated individuals above are its draws. Convergence: max R-hat "
                f"{fmt(exact.get('rhat_max'), 3)}, min bulk ESS {fmt(exact.get('ess_min'), 3)}")
        text += (" (above 1.05: the chains have not mixed in every direction; `--hier-samples` doubling the kept "
                 "sweeps is the remedy; on the gold benchmark the default reached max R-hat 1.03–1.05 with every "
                 "hyper-parameter median within 0.05 and every 5 %/95 % quantile within 0.21 NUTS sd of a joint NUTS "
                 "model)." if (exact.get("rhat_max") or 0) > 1.05 else ".")
        return text
    text = ("Flagged specimens got draws of their posterior under a reference population flat in the pooled "
            "coordinates and the layer was refitted (second pass); a specimen still flagged gets its updated "
            "posterior from a fresh TMCMC run under the population." if second else
            "A flagged specimen's updated posterior comes from a fresh TMCMC run under the population; the "
            "exact fallback (joint Metropolis-within-Gibbs, on by default) did not run (switched off, a grouped "
            "layer, or reference draws chosen).")
    if flagged:
        text += (f" **{len(flagged)} of {len(reuse)} specimens are flagged, so the population estimates above "
                 "rest partly on samples that do not cover where the population puts mass**: on the gold "
                 "benchmark (`results/benchmarks/hierarchical_gold.md`, joint NUTS) such reuse left the medians "
                 "within 0.41 posterior sd but put the 5 % quantile of mu of log VOLF·P1 1.0–1.2 sd too high and "
                 "the 95 % quantile of its sd 0.5–0.65 sd too low; read the lower tails of the population of "
                 "one-sided quantities as too short.")
    return text


def _variability(wres, base: Path) -> str:
    """## Specimen variability: Cochran's Q and separated pairs per identifiable quantity."""
    results = wres.results
    ids = sorted(results)
    if len(ids) < 2:
        return ""
    rows = []
    spec = _spec(wres)
    qs = {sid: quantity_samples(list(results[sid].as_dict()),
                                np.column_stack(list(results[sid].as_dict().values())), spec) for sid in ids}
    for k in spec.combination_names + spec.shape_parameters:
        if not all(k in qs[s] for s in ids):
            continue
        v = specimen_variability({s: qs[s][k] for s in ids})
        verdict = "differ" if v["p_value"] < 0.01 else "compatible with one common value"
        pairs = ", ".join(f"{a}≠{b}" for a, b in v["separated_pairs"][:6])
        more = f" (+{len(v['separated_pairs']) - 6} more)" if len(v["separated_pairs"]) > 6 else ""
        rows.append((k, f"{v['Q']:.1f}", v["df"], f"{v['p_value']:.2g}", verdict,
                     f"{len(v['separated_pairs'])}/{v['n_pairs']}: {pairs}{more}"))
    return ("## Specimen variability\n\nDo specimens differ beyond their posterior uncertainty? Cochran's Q "
            "of the posterior means (log scale for positive quantities) against χ²(S−1), and the "
            "pairs whose posterior difference excludes 0 with 95% probability.\n\n"
            + _table(["quantity", "Q", "df", "p", "verdict", "separated pairs"], rows))


def _short(name: str, n: int = 40) -> str:
    """A group name for a table cell: as the data wrote it, cut at ``n`` characters."""
    name = str(name).replace("|", "/")  # a '|' would split the Markdown cell
    return name if len(name) <= n else name[: n - 1] + "…"


def _groups(wres, base: Path) -> str:
    """## Groups: between- vs within-group spread and the posterior of the group-mean differences."""
    h = wres.hierarchical
    g = getattr(h, "groups", None) if h is not None else None
    if not g:
        return ""
    key, names, pooled = g["key"], list(g["names"]), list(g["pooled"])
    transforms = dict(h.attrs.get("transforms", {}))
    label, log_scale = {}, {}
    for p in pooled:  # the coordinate the group level lives in, named as the population table does
        t = transforms.get(p, "identity")
        log_scale[p] = t == "log" or (t == "identity" and p.startswith("log_"))
        label[p] = f"log {p[4:]}" if p.startswith("log_") and t == "identity" else (p if t == "identity" else f"{t} {p}")
    members = {n: [s for s, v in g["specimen_group"].items() if v == n] for n in names}
    txt = ["## Groups\n",
           f"Specimens grouped by `{key}` (their `# {key}:` metadata): "
           + "; ".join(f"**{_short(n)}** ({len(m)}: {', '.join(m)})" for n, m in members.items()) + ". "
           f"Three levels, Gaussian in the transformed coordinates of the population table: each {key} has a mean "
           f"m_g ~ Normal(mu, sd_between²) and its specimens scatter around it with sd_within; the hyper-posterior "
           f"is sampled jointly with the group means, reusing the stage-1 samples. In the population table above, "
           f"sd is the total √(sd_between² + sd_within²) and a new specimen is one of a new {key}.\n"]
    bounds = dict(h.attrs.get("bounds", {}))
    means = np.asarray(g["means"])
    rows = []
    for k, p in enumerate(pooled):  # group centres g⁻¹(m_g) in natural units, as the population median
        t, m = transforms.get(p, "identity"), means[:, :, k]
        if log_scale[p]:
            m = np.exp(m)
        elif t == "logit":
            lo, hi = bounds.get(p, (0.0, 1.0))
            m = lo + (hi - lo) / (1.0 + np.exp(-m))
        q = np.quantile(m, [0.05, 0.5, 0.95], axis=0)
        rows.append([p[4:] if p.startswith("log_") and t == "identity" else p]
                    + [f"{fmt(q[1, j])} [{fmt(q[0, j])}, {fmt(q[2, j])}]" for j in range(len(names))])
    txt.append("Group centres in natural units (median of the group's population, median [90%]):\n\n"
               + _table(["quantity"] + [_short(n, 24) for n in names], rows) + "\n")
    vs = variance_split(h.hyper_samples, h.hyper_names, pooled)
    rows = [(label[p], f"{fmt(v['sd_between'], 3)} [{fmt(v['sd_between_lo'], 3)}, {fmt(v['sd_between_hi'], 3)}]",
             f"{fmt(v['sd_within'], 3)} [{fmt(v['sd_within_lo'], 3)}, {fmt(v['sd_within_hi'], 3)}]",
             f"{v['between_fraction']:.0%} [{v['between_fraction_lo']:.0%}, {v['between_fraction_hi']:.0%}]")
            for p, v in vs.items()]
    txt.append(f"Variability between and within groups (transformed units, median [90%]):\n\n"
               + _table(["quantity", f"sd between {key} groups", "sd within a group (between specimens)",
                         "share of the variance between groups"], rows))
    rows = []
    for d in group_differences(np.asarray(g["means"]), names, pooled, 0.9):
        a, b, p = _short(d["a"], 24), _short(d["b"], 24), d["parameter"]
        pp = d["p_positive"]
        verdict = (f"{b} higher" if pp >= 0.95 else f"{a} higher" if pp <= 0.05
                   else "no clear difference (90% interval includes 0)")
        ratio = (f"×{fmt(np.exp(d['median']), 3)} [{fmt(np.exp(d['lo']), 3)}, {fmt(np.exp(d['hi']), 3)}]"
                 if log_scale[p] else "–")
        rows.append((label[p], f"{b} − {a}", f"{fmt(d['median'], 3)} [{fmt(d['lo'], 3)}, {fmt(d['hi'], 3)}]", ratio,
                     f"{pp:.3f}", verdict))
    txt.append(f"\nDo the groups differ? Posterior of the difference of the group means, per pair and quantity "
               f"(median [90%]; the ratio for log-scale quantities), the posterior probability that the second "
               f"group's mean is the higher one, and the verdict at 95% (either sign):\n\n"
               + _table(["quantity", "difference", "median [90%]", "ratio", "P(> 0)", "verdict"], rows))
    return "\n".join(txt)


def _population_figures(wres, base: Path) -> str:
    """## Figures across specimens: every figure not named after a specimen."""
    ids = sorted(wres.results)
    pop_figs = [f for f in wres.figures if not any(Path(f).name.startswith(s + "_") for s in ids)]
    if not pop_figs:
        return ""
    return "## Figures across specimens\n\n" + "\n".join(f"![{Path(f).stem}]({_rel(Path(f), base)})"
                                                        for f in pop_figs)


#: the report's sections in order: ``f(workflow_result, base) -> markdown`` ("" leaves it out)
SECTIONS: tuple[Callable[[Any, Path], str], ...] = (_header, _settings, _timings, _specimens, _fit_quality,
                                                    _combinations,
                                                    _manifolds, _population, _groups, _reuse, _variability,
                                                    _population_figures)


def render_report(wres, *, base: Path | None = None,
                  extra_sections: Sequence[Callable] | None = None) -> str:
    """The Markdown text for a :class:`hbm.workflow.WorkflowResult`.

    Parameters
    ----------
    wres : WorkflowResult
    base : Path, optional
        Folder the figure links are relative to (default ``wres.out``).
    extra_sections : sequence of callables, optional
        Hooks ``f(wres) -> markdown`` appended after :data:`SECTIONS`; a failing hook becomes a
        short "(failed: ...)" section.
    """
    base = Path(base or wres.out)
    parts = [txt for txt in (section(wres, base) for section in SECTIONS) if txt]
    for hook in extra_sections or ():
        try:
            txt = hook(wres)
        except Exception as exc:  # a broken hook must not lose the report
            txt = f"## {getattr(hook, '__name__', 'extra section')}\n\n(failed: {type(exc).__name__}: {exc})"
        if txt:
            parts.append(str(txt).strip())
    return "\n\n".join(parts) + "\n"


def write_report(wres, path: str | os.PathLike, *, extra_sections: Sequence[Callable] | None = None) -> Path:
    """Render and write the report atomically; returns its path."""
    path = Path(path)
    atomic_write_text(path, render_report(wres, base=path.parent, extra_sections=extra_sections))
    return path
