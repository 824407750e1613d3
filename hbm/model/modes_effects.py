"""Effects beyond the base model in the loading modes (issue 35, item 2: "effects act per test where they
are defined in 3-D").

Every effect declares where it is defined (:meth:`hbm.Effect.in_mode`, from its ``modes`` attribute): the
default ``"along_fibre"`` knows only the 1-D along-fibre path -- uniaxial_f's ``stress`` -- and is refused in
every other (mode, observable) with its reason; ``"stress_observables"`` marks a history/output operator
defined on every stress observable (quasi-linear viscoelasticity, a load-cell offset).  Nothing here names
an effect class: :class:`ModeEffects` asks each effect.

Quasi-linear viscoelasticity in 3-D.  Applied to the elastic Kirchhoff stress tensor τ_e (J = 1) with one
scalar relaxation operator 𝒢 (the Prony hereditary integral of ``viscoelastic``; the 1-D effect applies it
to the Cauchy stress, which is the same thing at J = 1), the pressure stays a Lagrange multiplier:
σ = 𝒢⊛τ_e − p·I.  Two traction-free faces b, b' give 𝒢⊛(τ_e,bb − τ_e,b'b') = 0 at every time, and 𝒢 is
invertible (G(0) = 1), so τ_e,bb = τ_e,b'b': the free stretches satisfy the *elastic* condition at every
instant.  The kinematics -- lateral strains, uniaxial_c's free fibre stretch -- are those of the elastic
solve, and every stress observable is 𝒢 applied to its own elastic history (σ_aa = 𝒢⊛(τ_e,aa − τ_e,bb)
with b the free face; in simple shear σ_XY = 𝒢⊛τ_e,XY, no pressure).  (Fung's variant on the second
Piola-Kirchhoff stress would differ by the stretch history; hbm keeps the 1-D effect's convention.)  Along the fibres this is exactly what the
1-D effect does to the Cauchy stress.  A history must therefore stay in one mode (one tensor component per
observable): tests of different modes in one loading history (time continuing across them) are refused.

Offsets: one load-cell zero per stress observable (``S0`` on ``stress``, ``S0_2`` on ``stress_2``), the
effect's parameters repeated for each further stress observable the specimen measures (``per_observable``).
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Mapping

import numpy as np

from ..errors import HbmError, SettingError
from .core import Effect, Loading, Model, State
from .spec import spec_of

__all__ = ["ModeEffects", "added_effects", "observable_suffix"]

#: the mode in which along-fibre-only effects act (on its ``stress``)
ALONG_FIBRE_MODE = "uniaxial_f"
MAIN = "stress"


def added_effects(model: Model) -> tuple[Effect, ...]:
    """The model's effects beyond its base (:attr:`hbm.model.spec.ModelSpec.effects`), in model order."""
    spec = spec_of(model)
    base = set(spec.effects) if spec is not None else set()
    return tuple(e for e in model.effects if e.name not in base)


def observable_suffix(observable: str) -> str:
    """The suffix of a per-observable parameter copy: ``""`` for ``stress``, ``"_2"`` for ``stress_2``."""
    if observable == MAIN:
        return ""
    return observable[len(MAIN):] if observable.startswith(MAIN + "_") else "_" + observable


class ModeEffects:
    """The added effects of a model, checked and applied per test across loading modes.

    Parameters
    ----------
    model : Model
        The base model plus effects.
    loading : Loading
        The specimen's control path (its time column gives the histories).
    tests : sequence of (Test, LoadCase)
        The specimen's tests with their load cases.
    pairs : iterable of (Test, observable name)
        What the caller predicts: the measured series of a likelihood, every observable in a simulation.
        Each added effect is asked about each pair's (mode, observable) before anything is computed.

    Attributes
    ----------
    model : Model
        ``model`` with the per-observable parameter copies appended (``S0_2`` ...); the caller's theta
        rows follow its parameter table.
    effects : tuple of Effect
        The added effects.

    Raises
    ------
    SettingError
        An effect not defined in a (mode, observable) it would have to predict (one line naming the effect,
        the mode and why), a kinematic/elastic effect declaring a 3-D scope (hbm applies those only at the
        history and output stages), a history effect over a loading history that spans tests of different
        modes, or an effect that cannot evaluate on this control path (e.g. no time column).
    """

    def __init__(self, model: Model, loading: Loading, tests, pairs: Iterable) -> None:
        self.loading = loading
        self.tests = tuple(tests)
        self.effects = added_effects(model)
        pairs = list(pairs)
        case_of = {t.id: c for t, c in self.tests}
        self._acts: dict[tuple[str, str], dict[str, bool]] = {}
        for t, obs in pairs:
            case = case_of[t.id]
            for e in self.effects:
                self._acts.setdefault((e.name, case.name), {})[obs] = self._ask(e, case, obs)
        self._stress = tuple(dict.fromkeys(o.name for _, c in self.tests for o in c.observables if o.is_stress))
        self.model = self._with_copies(model)
        self._check_histories()
        # the 1-D path of kinematic/elastic along-fibre effects (uniaxial_f's stress only, the pairs say so)
        pre = [e for e in model.effects if e.stage in ("kinematics", "elastic")]
        self._pre1d = (Model(pre, parameters=self.model.parameters, name=model.name, spec=model.spec)
                       if any(e.stage in ("kinematics", "elastic") for e in self.effects) else None)
        if self.effects:
            self._probe()

    # -- declarations -----------------------------------------------------------------------------
    @staticmethod
    def _ask(effect: Effect, case, obs: str) -> bool:
        answer = effect.in_mode(case.name, obs, case.observable(obs).is_stress)
        if answer not in ("acts", "passes"):
            raise SettingError(f"effect {effect.name!r} is not defined in mode {case.name} ({obs}): {answer}")
        if answer == "acts" and case.name != ALONG_FIBRE_MODE and effect.stage in ("kinematics", "elastic"):
            raise SettingError(f"effect {effect.name!r} ({effect.stage} stage) declares a 3-D scope, but hbm "
                               f"applies effects in mode {case.name} only at the history and output stages")
        return answer == "acts"

    def _with_copies(self, model: Model) -> Model:
        extra = [dataclasses.replace(q, name=q.name + observable_suffix(o), meaning=f"{q.meaning} ({o})")
                 for e in self.effects if e.per_observable for o in self._stress if observable_suffix(o)
                 for q in e.parameters]
        taken = [q.name for q in extra if q.name in model.parameter_names]
        if taken:
            raise SettingError(f"per-observable parameter(s) {', '.join(taken)} clash with the model's own")
        if not extra:
            return model
        return Model(model.effects, parameters=model.parameters + tuple(extra), name=model.name, spec=model.spec)

    def _check_histories(self) -> None:
        if not any(e.stage == "history" for e in self.effects):
            return
        hist = self.loading.history
        modes: dict[int, tuple[str, object]] = {}
        for t, case in self.tests:
            for h in np.unique(hist[t.rows]).tolist():
                seen = modes.setdefault(h, (case.name, t))
                if seen[0] != case.name:
                    other = seen[1]
                    raise SettingError(
                        f"tests {other.label or other.id} ({seen[0]}) and {t.label or t.id} ({case.name}) are one "
                        "loading history (their time continues), but a history effect acts on each stress "
                        "observable's own history in one mode; restart the time at the new mode's first row")

    def _probe(self) -> None:
        """Run every added effect once on a zero stress at the middle of the box (one particle): an effect that
        cannot evaluate on this control path (no time column ...) fails here, not inside the sampler."""
        mid = self.model.bounds.mean(axis=1)[None, :]
        preds = {t.id: {o.name: np.zeros((1, t.n_points)) for o in c.observables} for t, c in self.tests}
        try:
            with np.errstate(all="ignore"):
                self.apply(mid, preds, elastic_1d=False)
        except HbmError as exc:
            raise SettingError(str(exc)) from None

    # -- application --------------------------------------------------------------------------------
    def acts(self, effect: Effect, mode: str, observable: str) -> bool:
        """Whether ``effect`` transforms ``observable`` in ``mode`` (False where nobody asked for it)."""
        return self._acts.get((effect.name, mode), {}).get(observable, False)

    def _params(self, p: Mapping[str, np.ndarray], effect: Effect, observable: str) -> Mapping[str, np.ndarray]:
        sfx = observable_suffix(observable)
        if not (effect.per_observable and sfx):
            return p
        q = dict(p)
        q.update({x.name: p[x.name + sfx] for x in effect.parameters})
        return q

    def solve(self, energy, rows: np.ndarray, strain_2: np.ndarray | None = None) -> dict[int, dict[str, np.ndarray]]:
        """Every test solved in its mode with the 3-D ``energy`` at the parameter rows (n, ``model.n_params``),
        then the added effects (:meth:`apply`): test id -> observable -> (n, n_test_points).  ``strain_2``: the
        specimen's second control column (biaxial tests), None without one."""
        rows = np.asarray(rows, dtype=float)
        p = self.model._params(rows)
        out = {}
        for t, case in self.tests:
            s2 = None if strain_2 is None or "strain_2" not in case.inputs else strain_2[t.rows]
            out[t.id] = case.solve(energy, p, self.loading.strain[t.rows], s2)
        self.apply(rows, out)
        return out

    def apply(self, rows: np.ndarray, preds: dict[int, dict[str, np.ndarray]], *, elastic_1d: bool = True) -> None:
        """Transform the elastic predictions ``preds`` (test id -> observable -> (n, n_test_points)) in place.

        ``rows``: the parameter rows (n, ``model.n_params``).  With kinematic/elastic along-fibre effects,
        uniaxial_f's ``stress`` is first replaced by the model's 1-D stress before the history stage.  Then
        the history-stage effects, then the output-stage ones, in model order (as :meth:`hbm.Model.stress`),
        each on every stress observable's full-length array over the specimen (its own histories), kept where
        the effect acts."""
        if not self.effects:
            return
        rows = np.asarray(rows, dtype=float)
        n, npts = rows.shape[0], self.loading.n_points
        if elastic_1d and self._pre1d is not None:
            for t, case in self.tests:
                if MAIN in preds[t.id] and any(self.acts(e, case.name, MAIN) for e in self.effects
                                               if e.stage in ("kinematics", "elastic")):
                    lt = self.loading
                    sub = Loading(lt.strain[t.rows], None if lt.time is None else lt.time[t.rows])
                    preds[t.id][MAIN] = self._pre1d.stress(sub, rows)
        p = self.model._params(rows)
        state = State(self.loading.strain, self.loading)
        ordered = [e for stage in ("history", "output") for e in self.effects if e.stage == stage]
        for obs in self._stress:
            have = [(t, c) for t, c in self.tests if obs in preds[t.id]]
            if not have:
                continue
            full = np.zeros((n, npts))
            for t, _ in have:
                full[:, t.rows] = preds[t.id][obs]
            for e in ordered:
                where = [t for t, c in have if self.acts(e, c.name, obs)]
                if not where:
                    continue
                out = np.broadcast_to(e.modify(state, self._params(p, e, obs), full), full.shape)
                for t in where:
                    full[:, t.rows] = out[:, t.rows]
            for t, _ in have:
                preds[t.id][obs] = full[:, t.rows]
