"""FEBio names hbm writes, pinned to FEBio's source (febiosoftware/FEBio at 65622b5, 2026-01-29).

Only names are taken: the material type strings of ``REGISTER_FECORE_CLASS`` in
FEBioMech/FEBioMechModule.cpp and FECore/FECore.cpp, the parameter/property strings of each
class's ``ADD_PARAMETER``/``ADD_PROPERTY`` (inherited ones included), and the element names that
FEBioOpt/FEOptimizeInput.cpp reads.  Every tag an FEBio writer of :mod:`hbm.export` emits is
checked against these tables (:func:`check_tree`), by the export itself and by the tests.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

#: material/property type string -> child element names allowed inside it
MATERIAL_PARAMETERS: dict[str, frozenset[str]] = {
    # FEUncoupledElasticMixture: property "solid", optional "mat_axis"; FEUncoupledMaterial: "k",
    # "pressure_model"; FESolidMaterial: "density"
    "uncoupled solid mixture": frozenset({"solid", "mat_axis", "k", "pressure_model", "density"}),
    # FEMooneyRivlin: c1, c2 (+ FEUncoupledMaterial k, pressure_model; FESolidMaterial density)
    "Mooney-Rivlin": frozenset({"c1", "c2", "k", "pressure_model", "density"}),
    # FEUncoupledFiberPowLinear: E, lam0, beta; FEElasticFiberMaterialUC: property "fiber"
    "fiber-pow-linear-uncoupled": frozenset({"E", "lam0", "beta", "fiber", "k", "pressure_model", "density"}),
    # FEUncoupledFiberExpLinear (FEBioMech/FEUncoupledFiberExpLinear.cpp): c3, c4, c5, lambda; property "fiber"
    "uncoupled fiber-exp-linear": frozenset({"c3", "c4", "c5", "lambda", "fiber", "k", "pressure_model",
                                             "density"}),
    # FEActiveFiberStressUC: smax, activation; properties stl, stv, mat_axis
    "uncoupled active fiber stress": frozenset({"smax", "activation", "stl", "stv", "mat_axis", "k",
                                                "pressure_model", "density"}),
    # FEPointFunction ("point"): interpolate, extend, points
    "point": frozenset({"interpolate", "extend", "points"}),
    # FEMat3dVectorMap ("vector" as a mat3d valuator): a, d
    "vector/mat_axis": frozenset({"a", "d"}),
    # FEConstValueVec3 ("vector" as a vec3 valuator): vector (or the value written inline)
    "vector/fiber": frozenset({"vector"}),
}

#: enumeration values accepted by FEPointFunction
POINT_INTERPOLATE = frozenset({"linear", "step", "smooth", "cubic spline", "control points", "approximation",
                               "smooth-step", "C2-smooth"})
POINT_EXTEND = frozenset({"constant", "extrapolate", "repeat", "repeat offset"})

#: elements of a febio_optimize (version "2.0") file, FEBioOpt/FEOptimizeInput.cpp
OPTIMIZE_ELEMENTS = frozenset({"febio_optimize", "Options", "Task", "Parameters", "param", "Constraints",
                               "constraint", "Objective", "fnc", "data", "ordinate", "pt", "log_level",
                               "print_level"})
#: optimisation methods registered in FEBioOpt/FEBioOpt.cpp
OPTIMIZE_METHODS = frozenset({"levmar", "constrained levmar", "powell", "scan"})
#: objective types parsed by FEOptimizeInput::ParseObjective, and data sources of "data-fit"
OBJECTIVE_TYPES = frozenset({"data-fit", "target", "element-data", "node-data"})
DATA_SOURCES = frozenset({"parameter", "filter_positive_only", "filter_sum"})

#: elements of the material section of an febio_spec file that are not typed materials
SPEC_ELEMENTS = frozenset({"febio_spec", "Material", "material", "pt"})


def _kind(el: ET.Element, parent: ET.Element | None) -> str | None:
    t = el.get("type")
    if t is None:
        return None
    if t == "vector":
        return f"vector/{el.tag}"
    return t


def check_tree(root: ET.Element) -> list[str]:
    """Names in an FEBio XML tree that are not in the pinned tables ([] when all are known).

    Checks the type of every typed element, every child of a typed element against its type's
    parameter table, the enumerations of load curves, and the elements of a febio_optimize file.
    """
    bad: list[str] = []
    if root.tag == "febio_optimize":
        for el in root.iter():
            if el.tag not in OPTIMIZE_ELEMENTS:
                bad.append(f"element <{el.tag}> not read by FEOptimizeInput")
        for el in root.iter("Options"):
            if el.get("type") not in OPTIMIZE_METHODS:
                bad.append(f"optimisation method {el.get('type')!r}")
        for el in root.iter("Objective"):
            if el.get("type") not in OBJECTIVE_TYPES:
                bad.append(f"objective type {el.get('type')!r}")
        for el in root.iter("fnc"):
            if el.get("type") not in DATA_SOURCES:
                bad.append(f"data source {el.get('type')!r}")
        return bad
    parents = {c: p for p in root.iter() for c in p}
    for el in root.iter():
        kind = _kind(el, parents.get(el))
        if kind is not None and kind not in MATERIAL_PARAMETERS:
            bad.append(f"type {el.get('type')!r} of <{el.tag}>")
            continue
        parent = parents.get(el)
        pkind = _kind(parent, None) if parent is not None else None
        if pkind is not None and pkind in MATERIAL_PARAMETERS:
            if el.tag not in MATERIAL_PARAMETERS[pkind]:
                bad.append(f"<{el.tag}> in {pkind!r}")
        elif kind is None and el.tag not in SPEC_ELEMENTS and pkind is None:
            bad.append(f"untyped element <{el.tag}>")
        if pkind == "point" and el.tag == "interpolate" and (el.text or "").strip() not in POINT_INTERPOLATE:
            bad.append(f"interpolate {el.text!r}")
        if pkind == "point" and el.tag == "extend" and (el.text or "").strip() not in POINT_EXTEND:
            bad.append(f"extend {el.text!r}")
    return bad
