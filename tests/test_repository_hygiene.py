"""The repository names no folder of the machine it was written on (issue 34): tests, scripts, results and
docs use paths relative to the repository, or an environment variable with a documented default."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MACHINE = re.compile(r"(?<![\w.])/(work|root|home|Users)/[\w.-]")


def _tracked() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / p for p in out.decode().split("\0") if p]


def test_no_absolute_machine_paths_in_tracked_text():
    bad = []
    for path in _tracked():
        if path.suffix not in (".py", ".md", ".toml", ".txt", ".json", ".csv", ".cfg") and path.name != "run":
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        bad += [f"{path.relative_to(ROOT)}:{i}" for i, line in enumerate(text.splitlines(), 1) if MACHINE.search(line)]
    assert not bad, "absolute paths of a machine: " + ", ".join(bad[:20])
