"""Shared test helpers."""

import pytest


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
