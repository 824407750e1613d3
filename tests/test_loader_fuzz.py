"""Property-based test of the CSV loader on mutated files (issue 14).

Valid files are mutated (cells replaced by random text, huge numbers or nothing, delimiters dropped or
doubled, extra columns, truncated / deleted / duplicated / swapped lines, random bytes).  For every
mutated file the loader must EITHER raise a clean DataError OR return a dataset whose values equal what
the file means.  "What the file means" is computed here by an independent reading of the documented
rules (README "Data format"): the csv module, float() and plain Python, no numpy, no hbm code.  Both
directions are checked: a file valid by the rules must load, an invalid one must be refused.
"""

from __future__ import annotations

import csv
import json
import math
import re
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from hbm.data import load_specimen
from hbm.errors import DataError

# ----------------------------------------------------------------------------- the documented rules
UNITS = {"mpa": 1.0, "kpa": 1000.0, "pa": 1e6}
DEFORMATION_NAMES = {"strain", "strain_percent", "stretch", "sarcomere_length_um"}
RECORDS = ("units_stress_original", "stress_measure_original", "deformation_input", "test_labels")
LABEL = re.compile(r"[A-Za-z][A-Za-z0-9_.+\-/()% ]{0,63}")
META = re.compile(r"#\s*([A-Za-z_][A-Za-z0-9_.\- ]*?)\s*:\s?(.*)")


def _float(text):
    try:
        return float(text)
    except ValueError:
        return None


def _stress_name(col):
    """(measure, unit) of a stress column name, or None if it is not one."""
    measure = None
    for m in ("nominal_", "cauchy_"):
        if col.startswith(m):
            measure, col = m[:-1], col[len(m):]
    if col == "stress":
        return measure, None
    if col.startswith("stress_") and col[7:] in UNITS:
        return measure, col[7:]
    return None


# headers as labs write them (README "Data format"): word, optional unit in () or []
LAB_STRAIN = {"strain", "engineering strain", "nominal strain"}
LAB_STRESS = {"stress": "", "cauchy stress": "cauchy_", "true stress": "cauchy_", "nominal stress": "nominal_",
              "engineering stress": "nominal_"}
LAB_STRESS_UNITS = {"mpa": "mpa", "n/mm2": "mpa", "n/mm^2": "mpa", "n/mm²": "mpa", "kpa": "kpa",
                    "mn/mm2": "kpa", "mn/mm^2": "kpa", "mn/mm²": "kpa", "pa": "pa", "n/m2": "pa", "n/m^2": "pa",
                    "n/m²": "pa"}
NO_UNIT = {"", "-", "1", "mm/mm", "m/m"}


def _lab_name(name):
    """Documented column name of a header cell (lower case, stripped); False: refused; None: not a lab form."""
    word, unit = name, None
    for op, cl in ("()", "[]"):
        if name.endswith(cl) and op in name:
            k = name.rindex(op)
            inner = name[k + 1:-1]
            if not any(c in inner for c in "()[]") and not any(c in name[:k] for c in "()[]"):
                word, unit = name[:k], inner.strip()
            break
    word = " ".join(word.replace("_", " ").split())
    if word in ("force", "load"):
        return False
    if word in LAB_STRAIN:
        return "strain_percent" if unit == "%" else "strain" if unit is None or unit in NO_UNIT else False
    if word in ("stretch", "stretch ratio"):
        return "stretch" if unit is None or unit in NO_UNIT else False
    if word == "sarcomere length":
        return "sarcomere_length_um" if unit in ("um", "µm", "μm", "micrometre", "micrometres", "micrometer",
                                                 "micrometers", "micron", "microns") else False
    if word in LAB_STRESS:
        if unit is None:
            return LAB_STRESS[word] + "stress"
        return LAB_STRESS[word] + "stress_" + LAB_STRESS_UNITS[unit] if unit in LAB_STRESS_UNITS else False
    if word == "time" and unit is not None:
        return "time" if unit in ("s", "sec", "second", "seconds") else False
    return None


def _documented(name):
    """The documented name a header cell stands for, or False if it is refused."""
    if name in DEFORMATION_NAMES or name in ("time", "test") or _stress_name(name):
        return name
    lab = _lab_name(name)
    return name if lab is None else lab


def _value(cell):
    """A finite number written with '.', else None."""
    t = cell.strip()
    v = _float(t)
    if v is None or not math.isfinite(v):
        return None
    digits = t.lstrip("+-")
    if len(digits) > 1 and digits[0] == "0" and digits.isascii() and digits.isdigit():
        return None  # "01": the tail of a decimal comma
    return v


def _test_ids(cells):
    """Integer ids, or labels numbered by first appearance; None if the column is invalid."""
    texts = [c.strip() for c in cells]
    if _float(texts[0]) is not None:
        ids = []
        for t in texts:
            f = _float(t)
            if f is None:
                return None
            try:
                v = int(t)
            except ValueError:
                if not math.isfinite(f) or f != int(f):
                    return None
                v = int(f)
            if not -2 ** 63 <= v < 2 ** 63:
                return None
            ids.append(v)
        return ids, None
    order = {}
    for t in texts:
        if _float(t) is not None or not LABEL.fullmatch(t):
            return None
        order.setdefault(t, len(order))
    return [order[t] for t in texts], list(order)


def meaning(raw: bytes, sl0=None):
    """What a file means by the documented rules: columns as lists, or None if it is invalid."""
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    meta, header, header_raw, body, sep = {}, None, None, [], ","
    for line in text.split("\n"):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = META.fullmatch(s)
            key = "_".join(m.group(1).split()) if m else None
            if header is not None or m is None or key in meta:
                return None
            meta[key] = m.group(2).strip()
            continue
        if header is None:
            sep = "," if "," in line else "\t" if "\t" in line else ";" if ";" in line else ","
        try:
            cells = next(csv.reader([line], delimiter=sep))
        except csv.Error:
            return None
        if sep != ",":  # decimal commas: digits, one ',', digits (and an exponent)
            cells = [re.sub(r"^(\s*[+-]?[0-9]+),([0-9]+([eE][+-]?[0-9]+)?\s*)$", r"\1.\2", c) for c in cells]
        names = [c.strip().lower() for c in cells]
        if header is None:
            if all(_float(c) is not None for c in cells):
                return None
            if any(_documented(n) is False for n in names):
                return None
            header_raw, header = names, [_documented(n) for n in names]
            continue
        elif names == header_raw:
            return None
        elif len(cells) != len(header):
            return None
        else:
            body.append(cells)
    if header is None or len(set(header)) != len(header):
        return None
    defo = [j for j, c in enumerate(header) if c in DEFORMATION_NAMES]
    stress_cols = [j for j, c in enumerate(header) if _stress_name(c)]
    others = [c for c in header if c not in DEFORMATION_NAMES and not _stress_name(c)]
    if len(defo) != 1 or len(stress_cols) != 1 or any(c not in ("time", "test") for c in others):
        return None
    d, s = defo[0], stress_cols[0]
    measure, unit = _stress_name(header[s])
    if "units_stress" in meta:
        u = meta["units_stress"].strip().lower()
        if u not in UNITS or unit not in (None, u):
            return None
        unit = u
    if "stress_measure" in meta:
        m = meta["stress_measure"].strip().lower()
        if m not in ("cauchy", "nominal") or measure not in (None, m):
            return None
        measure = m
    ref = sl0
    if "reference_sarcomere_length_um" in meta:
        r = _float(meta["reference_sarcomere_length_um"])
        if r is None or not math.isfinite(r) or r <= 0 or (sl0 is not None and sl0 != r):
            return None
        ref = r
    if header[d] == "sarcomere_length_um" and ref is None:
        return None
    if len(body) < 5:
        return None

    cols, labels = {}, None
    for j, name in enumerate(header):
        if name == "test":
            parsed = _test_ids([row[j] for row in body])
            if parsed is None:
                return None
            cols["test"], labels = parsed
            continue
        values = [_value(row[j]) for row in body]
        if None in values:
            return None
        cols["strain" if j == d else "stress" if j == s else "time"] = values
    raw_def = cols["strain"]
    if header[d] == "stretch":
        strain = [x - 1.0 for x in raw_def]
    elif header[d] == "sarcomere_length_um":
        strain = [x / ref - 1.0 for x in raw_def]
    elif header[d] == "strain_percent":
        strain = [x / 100.0 for x in raw_def]
    else:
        strain = raw_def
    if not all(-0.5 <= e <= 2.0 for e in strain):
        return None
    if header[d] != "strain_percent" and all(x.is_integer() for x in raw_def):
        return None
    stress = cols["stress"]
    if unit not in (None, "mpa"):
        stress = [x / UNITS[unit] for x in stress]
    if measure == "nominal":
        stress = [(1.0 + e) * x for e, x in zip(strain, stress)]
    peak = max(abs(x) for x in stress)
    at = next(i for i, x in enumerate(stress) if abs(x) == peak)  # the first largest, as np.argmax
    if unit is None and _too_stiff(strain, stress, at):  # an undeclared unit stiffer than muscle: refused
        return None
    if strain[at] * stress[at] < 0:  # tension positive
        return None
    test, time = cols.get("test"), cols.get("time")
    if test is not None:
        done = set()
        for i in range(1, len(test)):
            if test[i] != test[i - 1]:
                done.add(test[i - 1])
                if test[i] in done:
                    return None
    if time is not None:
        for i in range(1, len(time)):
            new_test = test is not None and test[i] != test[i - 1]
            if time[i] < time[i - 1] and not (new_test and time[i] == 0.0):
                return None
    written = {"units_stress_original": None if unit in (None, "mpa") else unit,
               "stress_measure_original": "nominal" if measure == "nominal" else None,
               "deformation_input": None if header[d] == "strain" else header[d]}
    for key, value in written.items():
        if value is not None and key in meta and meta[key].strip().lower() != value:
            return None
    if labels is not None and "test_labels" in meta:
        try:
            if json.loads(meta["test_labels"]) != labels:
                return None
        except ValueError:
            return None
    return {"strain": strain, "stress": stress, "time": time, "test": test, "labels": labels}


def _too_stiff(strain, stress, at) -> bool:
    """Stress per unit strain above 3 MPa at the peak (largest |stress| over the largest |strain| on
    its side), or in the toe (the point nearest 30 % of that strain, the first of equals), written
    out independently of hbm.data.plausibility."""
    ep = strain[at]
    if ep == 0:
        return False
    reach = max(abs(e) for e in strain if e != 0 and (e > 0) == (ep > 0))
    if abs(stress[at]) / reach > 3.0:
        return True
    side = [i for i, e in enumerate(strain) if e != 0 and (e > 0) == (ep > 0) and abs(e) < reach]
    if not side:
        return False
    j = min(side, key=lambda i: (abs(abs(strain[i]) - 0.3 * reach), i))
    return abs(stress[j] / strain[j]) > 3.0


# ----------------------------------------------------------------------------- valid base files
def _base_int_tests():
    """Ten short tests: time restarts at 0 (from rest) or continues (same history) in turn."""
    lines = ["# id: fuzz_a", "# source: fuzz base", "strain,stress,time,test"]
    t = 0.0
    for k in range(10):
        t = 0.0 if k % 2 == 0 else t
        for i in range(2):
            e = 0.05 * i + 0.1 * (k % 2) + 0.01
            lines.append(f"{e!r},{0.01 * e + e ** 2!r},{t!r},{k + 1}")
            t += 1.5
    return "\n".join(lines) + "\n"


def _base_tests_no_time():
    rows = [f"{0.02 * i + 0.01:.2f},{0.003 * i:.3f},{i // 3}" for i in range(15)]
    return "strain,stress,test\n" + "\n".join(rows) + "\n"


def _base_sl_labels():
    lines = ["# id: fuzz_b", "# units_stress: kPa", "# reference_sarcomere_length_um: 2.0",
             "sarcomere_length_um,nominal_stress,time,test"]
    for i in range(10):
        label = "load" if i < 5 else "unload" if i < 8 else "hold 60 s"
        sl = 2.0 + 0.1 * (i if i < 5 else 9 - i if i < 8 else 2)
        lines.append(f"{round(sl, 3)!r},{round(0.3 * i * i + 0.1, 4)!r},{2.0 * i!r},{label}")
    return "\n".join(lines) + "\n"


def _base_stretch_pa():
    rows = [f"{1 + 0.04 * i:.2f},{150.0 * i * i + 10:.1f}" for i in range(9)]
    return "# stress_measure: cauchy\nstretch,stress_Pa\n" + "\n".join(rows) + "\n"


def _base_percent():
    rows = [f"{2 * i},{0.0004 * i * i - 0.0001:.4f}" for i in range(12)]
    return "strain_percent,stress\n" + "\n".join(rows) + "\n"


def _base_sl_argument():
    rows = [f"{2.5 + 0.05 * i:.3f},{0.5 * i:.2f},ramp_0.01" for i in range(8)]
    return "sarcomere_length_um,nominal_stress_kPa,test\n" + "\n".join(rows) + "\n"


def _base_lab_semicolon():
    """A spreadsheet export: ';' separated, decimal commas, units in the header."""
    rows = [f"{2 * i};{0.4 * i * i + 0.1:.2f};{1.5 * i:.1f}".replace(".", ",") for i in range(10)]
    return "# id: lab\nStrain (%);Nominal stress (kPa);Time (s)\n" + "\n".join(rows) + "\n"


def _base_lab_tab():
    rows = [f"{0.03 * i + 0.01:.2f}\t{0.002 * i * i:.4f}\t{'load' if i < 6 else 'unload'}" for i in range(9)]
    return "Engineering strain\tTrue stress [N/mm2]\ttest\n" + "\n".join(rows) + "\n"


BASES = [(_base_int_tests(), None), (_base_sl_labels(), None), (_base_stretch_pa(), None),
         (_base_sl_argument(), 2.5), (_base_tests_no_time(), None), (_base_percent(), None),
         (_base_lab_semicolon(), None), (_base_lab_tab(), None)]

CELLS = st.one_of(
    st.text(max_size=12),
    st.sampled_from(["9" * 25, "1e30", "-1e30", "1e400", "-1e308", "1e-320", "9" * 5000,
                     "x" * 140_000, "99999999999999999999"]),
    st.just(""),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-0.6, 3.0).map(repr),  # values that keep many files valid
    st.integers(-10 ** 20, 10 ** 20).map(str),
    st.sampled_from(["load", "unload", "reload", "hold", "ramp_0.01", "0,5", "1;2", "kPa", "Pa",
                     "nominal", '"0.1"', "0", "1", "2", "3", "1.0", "0.0", "1e30", "99999999999999999999"]),
    st.sampled_from(["01", "007", "-05", "00", "+012"]),  # decimal-comma tails
)
TEST_CELLS = st.one_of(  # for the test column
    st.sampled_from(["99999999999999999999", "1e30", "-9223372036854775809", "9223372036854775807", "2.5",
                     "1e400", "nan"]),
    st.sampled_from(["load", "unload", "reload", "hold", "ramp_0.01", "@", "", " 3 ", "1.0"]),
    st.integers(-3, 12).map(str),
    st.text(max_size=8),
)


def _decimal_commas(lines, first_data):
    """A spreadsheet with decimal commas: the first two columns, '.' -> ','."""
    return lines[:first_data] + [b",".join(ln.split(b",")[:2]).replace(b".", b",") for ln in lines[first_data:]]


def _variant(k, edit):
    """Base file k edited by ``edit(lines, first_data) -> lines`` (explicit examples)."""
    text, sl0 = BASES[k]
    lines = text.encode().split(b"\n")
    first_data = next(j for j, ln in enumerate(lines) if not ln.startswith(b"#")) + 1
    return b"\n".join(edit(lines, first_data)), sl0


# rules the random mutations reach only rarely, through the same oracle
EXAMPLES = [
    # issue 14: two columns with decimal commas (0,1;0,1 ...) under a four-column header; the cells
    # split into strain 0 everywhere and only the whole-number rule refuses the file
    (b"strain,stress,time,test\n0,1,0,1\n0,2,0,4\n0,3,0,9\n0,4,1,6\n0,5,2,5\n", None),
    _variant(1, _decimal_commas),
    _variant(0, lambda ln, f: ln[:f + 8] + ln[f + 9:]),  # test 5 starts at 1.5 after 4.5: a time drop
    _variant(0, lambda ln, f: ln[:f + 4]),  # 4 rows
    _variant(4, lambda ln, f: ln[:f] + [ln[f][:-1] + b"1e30"] + ln[f + 1:]),  # test id out of int64
]


@st.composite
def mutated(draw):
    """(file bytes, sl0): a valid base file with 1-3 mutations."""
    text, sl0 = draw(st.sampled_from(BASES))
    lines = text.encode().split(b"\n")
    first_data = next(k for k, ln in enumerate(lines) if not ln.startswith(b"#")) + 1
    for _ in range(draw(st.sampled_from([1, 1, 1, 2, 3]))):
        op = draw(st.sampled_from(["cell"] * 4 + ["del_line"] * 2 + ["drop_delim", "dup_delim", "extra_col",
                                                                     "truncate", "bytes", "dup_line", "swap",
                                                                     "decimal_commas"]))
        # mostly data rows, sometimes any line (metadata, header)
        i = draw(st.one_of(st.integers(min(first_data, len(lines) - 1), len(lines) - 1),
                           st.integers(0, len(lines) - 1)))
        line = lines[i]
        if op == "cell":
            cells = line.split(b",")
            j = draw(st.integers(0, len(cells) - 1))
            test_column = j == len(cells) - 1 and lines[first_data - 1].endswith(b",test")
            cells[j] = draw(TEST_CELLS if test_column else CELLS).encode("utf-8", "surrogatepass")
            lines[i] = b",".join(cells)
        elif op in ("drop_delim", "dup_delim") and b"," in line:
            k = draw(st.sampled_from([m.start() for m in re.finditer(b",", line)]))
            lines[i] = line[:k] + (b"" if op == "drop_delim" else b",,") + line[k + 1:]
        elif op == "extra_col":
            lines[i] = line + b"," + draw(CELLS).encode("utf-8", "surrogatepass")
        elif op == "truncate":
            lines[i] = line[:draw(st.integers(0, max(len(line) - 1, 0)))]
        elif op == "bytes":
            k = draw(st.integers(0, len(line)))
            lines[i] = line[:k] + draw(st.binary(min_size=1, max_size=6)) + line[k:]
        elif op == "del_line" and len(lines) > 1:
            del lines[i]
        elif op == "dup_line":
            lines.insert(i, line)
        elif op == "swap":
            k = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[k] = lines[k], lines[i]
        elif op == "decimal_commas":
            lines = _decimal_commas(lines, first_data)
    return b"\n".join(lines), sl0


def _assert_means(ds, expected):
    np.testing.assert_array_equal(ds.strain, expected["strain"])
    np.testing.assert_array_equal(ds.stress, expected["stress"])
    for key in ("time", "test"):
        assert (getattr(ds, key) is not None) == (expected[key] is not None)
        if expected[key] is not None:
            np.testing.assert_array_equal(getattr(ds, key), expected[key])
    if expected["labels"] is not None:
        assert json.loads(ds.attrs["test_labels"]) == expected["labels"]


def test_base_files_load_and_mean_what_they_say(tmp_path):
    for k, (text, sl0) in enumerate(BASES):
        path = tmp_path / f"base{k}.csv"
        path.write_text(text)
        expected = meaning(text.encode(), sl0)
        assert expected is not None, text
        _assert_means(load_specimen(path, sl0=sl0), expected)


def _examples(fn):
    for case in EXAMPLES:
        fn = example(case)(fn)
    return fn


def test_mutated_files_error_cleanly_or_mean_what_they_say():
    outcomes: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "case.csv"

        @settings(max_examples=200, derandomize=True, deadline=None, database=None,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
        @given(mutated())
        @_examples
        def check(case):
            data, sl0 = case
            path.write_bytes(data)
            expected = meaning(data, sl0)
            try:
                ds = load_specimen(path, sl0=sl0)
            except DataError as exc:  # anything else (OverflowError, csv.Error ...) fails the test
                msg = str(exc)
                assert expected is None, f"valid file refused: {msg}\n{data[:400]!r}"
                assert msg.startswith(str(path)) and "\n" not in msg and len(msg) < 1000, msg
                outcomes.append("refused")
                return
            assert expected is not None, f"invalid file accepted:\n{data[:400]!r}"
            _assert_means(ds, expected)
            outcomes.append("loaded")

        check()
    # the mutations reach both outcomes often enough for the test to mean something
    assert outcomes.count("loaded") >= 20 and outcomes.count("refused") >= 60, \
        (outcomes.count("loaded"), outcomes.count("refused"))
