"""The field machinery of the settings records: one declaration per setting.

A record is a frozen dataclass (:func:`record`) whose fields are declared with :func:`setting`:
the default, the help line, the validation rule (:mod:`hbm.settings.rules`), the command-line
flag, whether it keys the result, and the name under which files and keys store it when the
concept was renamed (``stored``).  Everything else follows from the declaration:

* construction checks every field by its rule (:class:`~hbm.errors.SettingError` naming it);
* :meth:`Settings.record` -- the settings that key a result and its checkpoints (canonical JSON
  form, stored names, unset fields left out, plus the package version);
* :meth:`Settings.to_attrs` / :meth:`Settings.from_attrs` -- the stored form (netCDF ``config``,
  ``run.json``) and back;
* :func:`add_arguments` / :meth:`Settings.from_args` -- the command-line options, choices read from
  the registries whenever argparse looks, older flags kept as hidden aliases that warn.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Iterable, Mapping

import numpy as np

from .._version import __version__
from ..errors import HbmWarning, SettingError
from .rules import ChoiceRule, Rule

__all__ = ["Setting", "setting", "record", "Settings", "add_arguments", "canonical"]


@dataclass(frozen=True)
class Setting:
    """What a field of a settings record declares (besides its name and default).

    Attributes
    ----------
    help : str
        One line for ``--help`` and the docs; ``{default}`` is replaced by the command's default.
    rule : Rule or None
        The validation rule (None: the value is checked where it is used, e.g. against the model).
    flag : str or None
        Command-line option; None: no option of its own.
    metavar : str or None
    stored : str or None
        The name in result files, ``run.json`` and result keys when it differs from the field's
        (a concept renamed after files were written keeps its stored name).
    keyed : bool
        Whether it changes the result (enters :meth:`Settings.record`).
    aliases : tuple of str
        Older flags, hidden from ``--help``; they still work and warn.
    old_names : tuple of str
        Older keyword names, accepted with a DeprecationWarning.
    omit_default : bool
        Stored (:meth:`Settings.to_attrs`) only when not at its default, so files of runs that do not
        use a setting added later stay byte for byte what they were.
    """

    help: str
    rule: Rule | None = None
    flag: str | None = None
    metavar: str | None = None
    stored: str | None = None
    keyed: bool = True
    aliases: tuple[str, ...] = ()
    old_names: tuple[str, ...] = ()
    omit_default: bool = False


def setting(default: Any = None, *, help: str, rule: Rule | None = None, flag: str | None = None,  # noqa: A002
            metavar: str | None = None, stored: str | None = None, keyed: bool = True,
            aliases: tuple[str, ...] = (), old_names: tuple[str, ...] = (), omit_default: bool = False):
    """A field of a settings record (a ``dataclasses.field`` carrying its :class:`Setting`)."""
    meta = {"setting": Setting(help, rule, flag, metavar, stored, keyed, tuple(aliases), tuple(old_names),
                               omit_default)}
    if isinstance(default, (dict, list)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def canonical(obj: Any) -> Any:
    """JSON-able, order-independent form of a setting's value (floats by ``repr``, arrays as
    lists, a seed sequence as entropy and spawn key, objects with ``to_dict`` by their content)."""
    if isinstance(obj, Mapping):
        return {str(k): canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return canonical(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return repr(float(obj))
    if isinstance(obj, (np.integer, int, bool, str)) or obj is None:
        return obj.item() if isinstance(obj, np.generic) else obj
    if isinstance(obj, np.random.SeedSequence):
        return {"entropy": canonical(obj.entropy), "spawn_key": list(map(int, obj.spawn_key))}
    if hasattr(obj, "to_dict"):  # a Prior: its content, not its id()
        return canonical(obj.to_dict())
    return repr(obj)


def record(cls):
    """Class decorator: a frozen dataclass whose constructor also takes the fields' older keyword
    names (:attr:`Setting.old_names`) with a DeprecationWarning."""
    cls = dataclass(frozen=True)(cls)
    old = {o: f.name for f in dataclasses.fields(cls) for o in _setting(f).old_names if _setting(f)}
    if old:
        init = cls.__init__

        def __init__(self, *args, **kwargs):
            for name, new in old.items():
                if name in kwargs:
                    if new in kwargs:
                        raise SettingError(f"{cls.__name__}: give {new}= (the newer name of {name}=), not both")
                    warnings.warn(f"{cls.__name__}({name}=...) is deprecated; use {new}=", DeprecationWarning,
                                  stacklevel=2)
                    kwargs[new] = kwargs.pop(name)
            init(self, *args, **kwargs)

        __init__.__doc__ = init.__doc__
        cls.__init__ = __init__
    return cls


def _setting(f: dataclasses.Field) -> Setting | None:
    return f.metadata.get("setting")


class Settings:
    """Base of the settings records (:class:`~hbm.settings.FitSettings`, ...); see the module docstring."""

    #: fields of older layouts that no longer exist, at the values every run of today has, folded into
    #: :meth:`record` so a stored result keeps its key (empty unless a subclass retired a setting)
    RETIRED: ClassVar[Mapping[str, Any]] = {}
    #: whether unset settings (None) key the result as None (else they are left out)
    KEY_UNSET: ClassVar[bool] = False
    #: whether the package version keys the result
    KEY_VERSION: ClassVar[bool] = True

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            s = _setting(f)
            value = getattr(self, f.name)
            if s is not None and s.rule is not None and value is not None:
                object.__setattr__(self, f.name, s.rule.check(value, f.name))

    # -- the declarations ------------------------------------------------------------------
    @classmethod
    def declared(cls) -> dict[str, tuple[dataclasses.Field, Setting]]:
        """``{field name: (dataclass field, Setting)}`` of every declared setting, in order."""
        return {f.name: (f, _setting(f)) for f in dataclasses.fields(cls) if _setting(f) is not None}

    @classmethod
    def stored_names(cls) -> dict[str, str]:
        """``{field name: stored name}`` where they differ (the table of renamed concepts)."""
        return {n: s.stored for n, (_, s) in cls.declared().items() if s.stored}

    @classmethod
    def default(cls, name: str) -> Any:
        f, _ = cls.declared()[name]
        return f.default_factory() if f.default is dataclasses.MISSING else f.default

    @classmethod
    def stored(cls, **values: Any):
        """A record of values read from a file, NOT checked by the rules (a file may hold a move or
        noise model not registered in this process, or a size below today's minimum); missing
        fields at their defaults."""
        obj = cls.__new__(cls)
        for f in dataclasses.fields(cls):
            value = values[f.name] if f.name in values else (
                f.default_factory() if f.default is dataclasses.MISSING else f.default)
            object.__setattr__(obj, f.name, value)
        return obj

    def replace(self, **changes: Any):
        """A copy with some settings changed (checked like a new record; older names warn as in the constructor)."""
        current = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
        for name, (_, s) in self.declared().items():
            if any(o in changes for o in s.old_names):
                current.pop(name, None)  # the older keyword replaces it (and warns)
        return type(self)(**{**current, **changes})

    # -- keys and files ----------------------------------------------------------------------
    def record(self, **extra: Any) -> dict:
        """The settings that key a result and its checkpoints: every keyed setting under its stored
        name, plus :attr:`RETIRED`, ``extra`` and (:attr:`KEY_VERSION`) the package version.

        An unset setting (None) is left out (unless :attr:`KEY_UNSET`; a setting declared
        ``omit_default`` always), so that adding an optional setting does not change the key of
        results that do not use it."""
        out = dict(self.RETIRED)
        for name, (_, s) in self.declared().items():
            value = getattr(self, name)
            if not s.keyed or (value is None and (not self.KEY_UNSET or s.omit_default)):
                continue
            out[s.stored or name] = value
        out.update({k: v for k, v in extra.items() if v is not None})
        if self.KEY_VERSION:
            out["version"] = __version__
        return out

    def to_attrs(self) -> dict:
        """The stored form: every setting under its stored name (those declared ``omit_default``
        only when changed), values as given."""
        out = {}
        for name, (_, s) in self.declared().items():
            value = getattr(self, name)
            if s.omit_default and value == self.default(name):
                continue
            out[s.stored or name] = value
        return out

    @classmethod
    def from_attrs(cls, attrs: Mapping[str, Any], **overrides: Any):
        """The record of a stored form (:meth:`to_attrs`, or an older file's): stored names mapped back,
        unknown keys ignored, missing ones at their defaults, ``overrides`` last."""
        kwargs = {}
        for name, (_, s) in cls.declared().items():
            key = s.stored or name
            if key in attrs:
                kwargs[name] = attrs[key]
        kwargs.update(overrides)
        return cls(**kwargs)

    # -- the command line ----------------------------------------------------------------------
    @classmethod
    def from_args(cls, args: argparse.Namespace, **overrides: Any):
        """The record of parsed options: every declared setting with a flag that the parser has."""
        decl = cls.declared()
        kwargs = {n: getattr(args, n) for n, (_, s) in decl.items() if s.flag and hasattr(args, n)}
        kwargs.update(overrides)
        try:
            return cls(**kwargs)
        except SettingError as exc:  # name the option as the user typed it
            msg = str(exc)
            for name, (_, s) in decl.items():
                if s.flag and msg.startswith(name) and msg[len(name):len(name) + 1] in (":", " "):
                    msg = s.flag + msg[len(name):]
                    break
            raise SettingError(msg) from None


class _DeprecatedFlag(argparse.Action):
    """A hidden older flag: sets the setting and says the newer flag (an ``hbm: warning:`` line, shown
    by default, unlike a DeprecationWarning on the command line)."""

    def __init__(self, option_strings, dest, new: str, **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        warnings.warn(f"{option_string} is deprecated; use {self.new}", HbmWarning, stacklevel=2)
        setattr(namespace, self.dest, values)


def add_arguments(parser: argparse.ArgumentParser, cls: type[Settings], names: Iterable[str], *,
                  defaults: Mapping[str, Any] | None = None, helps: Mapping[str, str] | None = None,
                  refuse: Mapping[str, Mapping[str, str]] | None = None) -> None:
    """Add the options of ``cls``'s settings ``names`` to ``parser``.

    Choices come from the registries whenever argparse looks (:class:`~hbm.settings.rules.RegistryChoices`);
    a flag's older spelling (:attr:`Setting.aliases`) is a hidden alias that warns.

    Parameters
    ----------
    defaults : mapping, optional
        The command's defaults where they differ from the record's.
    helps : mapping, optional
        The command's help line of a setting where its meaning differs (e.g. a default chosen later).
    refuse : mapping name -> {value: reason}, optional
        Values the command cannot honour: refused when parsed with one line saying why.
    """
    decl = cls.declared()
    for name in names:
        f, s = decl[name]
        default = (defaults or {}).get(name, cls.default(name))
        text = (helps or {}).get(name) or s.help.replace("{default}", str(default))
        kw: dict[str, Any] = {"dest": name, "default": default, "help": text}
        if isinstance(s.rule, ChoiceRule):
            kw["choices"] = s.rule.choices
            if refuse and name in refuse:
                kw["type"] = _refusing(s.flag, refuse[name])
        elif s.rule is not None:
            kw["type"] = s.rule   # a rule is argparse's type= (its parse)
        if s.metavar:
            kw["metavar"] = s.metavar
        parser.add_argument(s.flag, **kw)
        for alias in s.aliases:
            parser.add_argument(alias, dest=name, default=argparse.SUPPRESS, help=argparse.SUPPRESS,
                                action=_DeprecatedFlag, new=s.flag, **{k: v for k, v in kw.items()
                                                                        if k in ("choices", "type", "metavar")})


def _refusing(flag: str, reasons: Mapping[str, str]) -> Callable[[str], str]:
    def parse(text: str) -> str:
        if text in reasons:
            raise argparse.ArgumentTypeError(f"{flag} {text} is not offered here: {reasons[text]}")
        return text

    parse.__name__ = flag.lstrip("-")
    return parse
