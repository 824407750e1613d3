"""Shared test helpers."""

import os

import pytest


@pytest.fixture(autouse=True, scope="session")
def _isolated_cache(tmp_path_factory):
    """The tests' caches (the detective's calibration) in a temporary folder, never the user's
    ~/.cache/hbm: a test must compute what it checks, not read a cache of an earlier run."""
    old = os.environ.get("HBM_CACHE_DIR")
    os.environ["HBM_CACHE_DIR"] = str(tmp_path_factory.mktemp("hbm-cache"))
    yield
    if old is None:
        os.environ.pop("HBM_CACHE_DIR", None)
    else:
        os.environ["HBM_CACHE_DIR"] = old


@pytest.fixture
def run_cli(capsys):
    """Run ``hbm ARGV`` in-process; return (exit code, stdout, stderr)."""
    from hbm.cli import main

    def run(argv):
        capsys.readouterr()  # drop anything printed before
        rc = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return rc, out, err

    return run


def cli_error(run_cli, argv) -> str:
    """The one-line error of a failing ``hbm ARGV`` (asserts exit code 2 and a single line)."""
    rc, _, err = run_cli(argv)
    assert rc == 2, (rc, err)
    assert err.startswith("hbm: error: ") and err.count("\n") == 1, err
    return err
