"""Specimen stress–strain curves: CSV (+ metadata) <-> :class:`Specimen`, validation, synthetic data.

A :class:`Specimen` (:mod:`hbm.data.specimen`) is the one type every layer reads: the control path
(strain, time, test), its tests and its measured series with their units; ``Specimen.to_dataset()``
is the xarray view and :func:`as_specimen` converts a Dataset once.

CSV format
----------
::

    # id: calvo2010_rat1                  <- optional metadata, ``# key: value``, only at the top
    # source: synthetic stand-in for ...
    strain,stress,time,test               <- header: a deformation and a stress column, any order
    0.0,0.0012,0.0,1
    0.01,0.0031,45.45,1
    ...

Columns (header names are case-insensitive; exactly one deformation and one stress column;
headers as labs write them, ``Strain (%)``, ``Nominal stress [kPa]``, ``Time (s)``, are read as the
names below, see :func:`_canonical_header`; a header without ',' makes tab or ';' the separator and
then decimal commas are read):

* deformation — ``strain``: engineering strain ε = ΔL/L0 (dimensionless); or
  ``strain_percent``: 100·ε; or ``stretch`` λ = L/L0 (ε = λ − 1); or ``sarcomere_length_um``, the sarcomere length SL in µm
  (ε = SL/SL0 − 1 with the reference SL0 from ``# reference_sarcomere_length_um: 2.0`` or the
  ``sl0=`` argument).  The resulting strain must lie within [−0.5, 2] and must not consist of
  whole numbers only (that is what decimal commas or percent leave behind).
* stress — ``stress`` in MPa unless declared otherwise: ``# units_stress: MPa|kPa|Pa`` or a unit
  suffix on the column (``stress_kPa``, ``stress_Pa``, ``stress_MPa``); Cauchy (true) stress
  unless ``# stress_measure: nominal`` or the column is ``nominal_stress*`` (``cauchy_stress*``
  declares Cauchy).  Nominal stress P (force / undeformed area) becomes Cauchy stress
  σ = λ·P = (1 + ε)·P (incompressible uniaxial tension).  The loaded specimen always holds
  Cauchy stress in MPa.  The unit is judged from the physics (:mod:`hbm.data.plausibility`): a curve
  whose stress per unit strain (toe or peak) is stiffer than passive muscle with NO declared unit
  is refused with the declaration that fixes it; with a declared unit (or outside the range on
  the soft side) it loads with a warning.  A cell like ``01`` (leading zero) is refused: it is the
  tail of a decimal comma.
* ``time`` (optional) — seconds.
* ``test`` (optional) — a protocol segment (a ramp, a hold, an unloading ...): integer ids, or
  labels as labs write them (``load``, ``unload``, ``hold``, ``ramp_0.01``: a letter, then
  letters, digits, spaces or ``_ . + - / ( ) %``, at most 64 characters), not both.  Labels are
  numbered 0, 1, 2 ... in order of first appearance and kept in the ``test_labels`` attribute
  (JSON list).  The rows of one test must be contiguous.

Rules for ``time`` (DESIGN.md §2).  Inside a test, time is non-decreasing.  At the first row
of a new test, time either *continues* (≥ the previous row's time): the new test is the next
segment of the same loading history (load → unload → reload, ramp → relaxation hold), and
history-dependent effects see what came before; or it *restarts at exactly 0*: the new test
starts from rest, a new loading history.  Any other drop in time is an error.  Without a
``test`` column, time must be non-decreasing over the whole file (one history).  Without a
``time`` column, every test is its own history (see :class:`hbm.Loading`).

Metadata lines must come before the header and look like ``# key: value`` (key: letters,
digits, ``_ . -`` and spaces, which become ``_``; each key once).  Blank lines are ignored.
``id`` names the specimen (default: the file stem); ``provenance`` is ``synthetic`` or
``measured``; ``group`` (optional, non-empty) names the specimen's group (species, muscle,
protocol ...): specimens with groups get a population → group → specimen layer
(:func:`specimen_groups`, ``hbm run --group-by KEY`` groups by any other key).  Every row has as many cells as the header; only regular files are read.

Conversions are recorded in the attributes, so that :func:`save_specimen` writes a file that
loads back to the same numbers: ``units_stress`` (then ``MPa``) and ``units_stress_original``,
``stress_measure`` (then ``cauchy``) and ``stress_measure_original``, ``deformation_input``,
``reference_sarcomere_length_um``, ``test_labels``.  A file that carries one of these records
itself keeps it when no conversion happens, and must agree with it when one does.

Every problem raises :class:`hbm.errors.DataError` with a one-line message naming the file,
the line (and column) and what was expected.
"""

from .specimen import DEFAULT_LOAD_CASE, OBSERVABLES, Series, Specimen, Test, as_specimen
from .columns import DEFORMATIONS, GROUP_KEY, MIN_POINTS, STRAIN_RANGE, STRESS_UNITS
from .loader import load_specimen, load_specimens
from .writer import save_specimen
from .summary import input_line, input_summary, provenance, specimen_groups, specimen_loading
from .synthetic import Segment, cycle, hold, protocol, ramp, synthetic_specimen

__all__ = [
    "Specimen", "Series", "Test", "as_specimen", "OBSERVABLES", "DEFAULT_LOAD_CASE", "STRAIN_RANGE", "MIN_POINTS", "STRESS_UNITS", "DEFORMATIONS",
    "load_specimen", "load_specimens", "save_specimen", "specimen_loading", "provenance",
    "input_summary", "input_line", "synthetic_specimen", "GROUP_KEY", "specimen_groups", "Segment", "ramp", "hold",
    "cycle", "protocol",
]
