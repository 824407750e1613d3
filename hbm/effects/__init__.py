"""Library of candidate physical effects that extend the base muscle model.

One small :class:`hbm.Effect` subclass per effect id; each docstring gives the formula, the
literature range of its parameters and a reference, and each parameter has a ``null`` value at
which the effect vanishes (the class attribute ``strength`` names the parameter whose null
switches the effect off; other parameters' nulls are placeholders).

============================  ===========  ==========================================
id                            stage        parameters (null)
============================  ===========  ==========================================
``offset``                    output       S0 (0)
``prestress``                 elastic      S0 (0)            — placement of ``offset``
``slack``                     kinematics   SLACK (0)
``fiber_exponential``         elastic      FEXP_A (0), FEXP_B
``recruitment``               elastic      REC_W (0)
``dispersion``                elastic      DISP (0)
``series_compliance``         kinematics   C_S (0)
``viscoelastic``              history      G1 (0), LOGTAU1   — needs a time column
``viscoelastic_2``            history      G2 (0), LOGTAU2   — a second relaxation time (beside viscoelastic)
``viscoelastic_3``            history      G3 (0), LOGTAU3   — a third one (beside viscoelastic_2)
``damage``                    history      DMG (0)           — needs load-unload-reload
============================  ===========  ==========================================

In the loading modes of issue 35 (:mod:`hbm.model.modes_effects`) ``viscoelastic*`` relax every stress
observable along its own history and ``offset`` adds one zero per stress observable (``S0``, ``S0_2``); the
others know only the along-fibre path and are refused elsewhere (``Effect.in_mode`` gives the reason).

``make_effect(id, **kwargs)`` builds a library effect, ``load_effect("path.py:ClassName")`` a
user's effect from their own file, ``resolve_effect(spec)`` either.  ``placements(effect)``
lists the other placements of an effect (``prestress`` is ``offset`` carried by the tissue,
before the history stage).  An effect with ``requires`` (a further relaxation time) is a
candidate only beside the effects it names (:func:`applicable`).
``CONFUSABLE_GROUPS`` and ``SEPARATING_EXPERIMENT`` record which effects one monotonic curve cannot tell apart
(DESIGN.md §2) and what experiment would.
"""

from __future__ import annotations

import copyreg
import hashlib
import importlib.util
import sys
from pathlib import Path

from ..errors import HbmError
from ..model.core import Effect
from .damage import Damage
from .dispersion import Dispersion
from .fiber_exponential import FiberExponential
from .offset import Offset
from .prestress import Prestress
from .recruitment import Recruitment
from .relaxation import SecondRelaxation, ThirdRelaxation
from .series_compliance import SeriesCompliance, solve_series
from .slack import Slack
from .viscoelastic import Viscoelastic

#: effect id -> Effect subclass
REGISTRY: dict[str, type[Effect]] = {
    cls.name: cls
    for cls in (Offset, Prestress, Slack, FiberExponential, Recruitment, Dispersion, SeriesCompliance, Viscoelastic,
                Damage, SecondRelaxation, ThirdRelaxation)
}

#: groups of effects whose signatures on one monotonic ramp look alike (DESIGN.md §2)
CONFUSABLE_GROUPS: tuple[frozenset[str], ...] = (
    frozenset({"slack", "fiber_exponential"}),
    frozenset({"series_compliance", "damage", "dispersion", "recruitment", "viscoelastic"}),
)

#: group -> the experiment that separates its members
SEPARATING_EXPERIMENT: dict[frozenset[str], str] = {
    CONFUSABLE_GROUPS[0]: (
        "Pin the reference length independently (measure the stress-free length at a minimal preload, "
        "or the sarcomere length by laser diffraction to fix EOPT) and sample the toe region densely: "
        "slack gives a zero-stress stretch followed by a shifted curve, exponential fibers an immediate "
        "smooth stiffening beyond EOPT."),
    CONFUSABLE_GROUPS[1]: (
        "Test the same specimen with ramps at several strain rates (e.g. 0.01, 0.1, 1 %/s) plus a "
        "relaxation hold (viscoelastic: rate-dependent stress, decay at constant strain), a "
        "load-unload-reload cycle beyond the previous maximum (damage: softer unloading/reloading "
        "below the previous maximum only), and measure the tissue strain optically on the mid-belly "
        "(markers/DIC; series compliance: grip strain exceeds tissue strain in proportion to the "
        "force); collagen recruitment vs angle dispersion needs imaging of collagen crimp and "
        "orientation (SHG microscopy) or off-axis/biaxial tests."),
}


def group_of(effect_id: str) -> frozenset[str] | None:
    """The confusable group containing ``effect_id`` (``None`` if it has no look-alikes)."""
    for g in CONFUSABLE_GROUPS:
        if effect_id in g:
            return g
    return None


def applicable(effect: Effect, model) -> bool:
    """Can ``effect`` be added to ``model``?  Every effect its ``requires`` names is in the model
    (a second relaxation time needs the first), and none of its parameter names is taken."""
    names = set(model.effect_names)
    return (all(r in names for r in getattr(effect, "requires", ()))
            and not {q.name for q in effect.parameters} & set(model.parameter_names))


def family(effect: Effect | type[Effect]) -> str:
    """The id an effect is a placement of (its own name for an effect without placements)."""
    return effect.placement_of or effect.name


def placements(effect: Effect) -> list[Effect]:
    """The library's *other* placements of ``effect`` (same parameters at another stage), new
    instances; empty for most effects.  ``placements(Offset())`` is ``[Prestress()]``."""
    fam = family(effect)
    return [cls() for cls in REGISTRY.values() if family(cls) == fam and cls is not type(effect)]


def make_effect(effect_id: str, **kwargs) -> Effect:
    """Instantiate the library effect ``effect_id`` (see :data:`REGISTRY`)."""
    try:
        cls = REGISTRY[effect_id]
    except KeyError:
        raise HbmError(f"unknown effect {effect_id!r}; expected one of {', '.join(REGISTRY)} "
                       "or a user effect 'path.py:ClassName'") from None
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise HbmError(f"effect {effect_id!r}: bad options {kwargs}: {exc}") from None


def load_effect(spec: str, **kwargs) -> Effect:
    """Load a user-written effect from ``"path/to/file.py:ClassName"`` and instantiate it.

    The file is imported with :mod:`importlib` (it may ``import hbm``); no edit of hbm is
    needed.  Raises :class:`HbmError` if the file or class is missing or the class is not an
    :class:`hbm.Effect` subclass.  Instances cross to worker processes (dask, spawned pools) as
    "import the class from its file, restore the attributes": the file must be readable there
    (always on one machine; on a cluster, from a shared file system).
    """
    if not isinstance(spec, str) or ":" not in spec:
        raise HbmError(f"effect spec {spec!r}: expected 'path/to/file.py:ClassName'")
    file, cls_name = spec.rsplit(":", 1)
    cls = _user_effect_class(Path(file).expanduser(), cls_name, spec)
    try:
        effect = cls(**kwargs)
    except Exception as exc:
        raise HbmError(f"{spec!r}: cannot instantiate {cls_name}: {type(exc).__name__}: {exc}") from None
    return effect


def _user_effect_class(path: Path, cls_name: str, spec: str) -> type:
    """The class ``cls_name`` of the user file ``path``, its module imported once per process."""
    if not cls_name.isidentifier():
        raise HbmError(f"effect spec {spec!r}: {cls_name!r} is not a class name (expected 'file.py:ClassName')")
    if not path.is_file():
        raise HbmError(f"effect file {str(path)!r} not found (from {spec!r})")
    digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:12]
    mod_name = f"hbm_user_effect_{path.stem}_{digest}"
    module = sys.modules.get(mod_name)
    if module is None:
        try:
            module_spec = importlib.util.spec_from_file_location(mod_name, path)
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[mod_name] = module  # dataclasses/pickling look the module up by name
            module_spec.loader.exec_module(module)
        except Exception as exc:  # any error in user code becomes one clear line
            sys.modules.pop(mod_name, None)
            msg = str(exc).splitlines()[0] if str(exc) else ""
            raise HbmError(f"effect file {str(path)!r}: import failed: {type(exc).__name__}: {msg}") from None
    cls = getattr(module, cls_name, None)
    if cls is None:
        raise HbmError(f"effect file {str(path)!r} has no class {cls_name!r}")
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise HbmError(f"{spec!r}: {cls_name} is not a subclass of hbm.Effect")
    # worker processes cannot import the module by its made-up name: pickle instances by file and class
    copyreg.pickle(cls, _reduce_user_effect)
    return cls


def _reduce_user_effect(effect: Effect):
    cls = type(effect)
    return _new_user_effect, (sys.modules[cls.__module__].__file__, cls.__qualname__), dict(vars(effect))


def _new_user_effect(file: str, cls_name: str) -> Effect:
    """An uninitialised instance of the user effect class ``cls_name`` of ``file`` (the unpickler then
    restores its attributes)."""
    cls = _user_effect_class(Path(file), cls_name, f"{file}:{cls_name}")
    return cls.__new__(cls)


def resolve_effect(spec: str, **kwargs) -> Effect:
    """A library id (``"damage"``) or a user spec (``"my.py:MyEffect"``) -> Effect instance."""
    if spec in REGISTRY:
        return make_effect(spec, **kwargs)
    if ":" in spec:
        return load_effect(spec, **kwargs)
    return make_effect(spec, **kwargs)  # raises the 'unknown effect' error


__all__ = ["REGISTRY", "CONFUSABLE_GROUPS", "SEPARATING_EXPERIMENT", "group_of", "applicable", "family", "placements",
           "make_effect", "load_effect", "resolve_effect", "solve_series", "Offset", "Prestress", "Slack",
           "FiberExponential", "Recruitment", "Dispersion", "SeriesCompliance", "Viscoelastic", "Damage",
           "SecondRelaxation", "ThirdRelaxation"]
