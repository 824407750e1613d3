"""CLI choice lists come from the registries: a noise model registered once is a --noise choice of
every command (fit, run, optimize), with its own number of parameters, and goes away with it."""

from __future__ import annotations

import numpy as np
import pytest

from hbm import cli
from hbm.cli._common import n_noise_parameters
from hbm.errors import SettingError
from hbm.likelihood.noise import NOISE_REGISTRY, NoiseModel, register_noise

COMMANDS = ("fit", "run", "optimize")


class ToyNoise(NoiseModel):
    """A three-parameter toy model (more than the two the CLI once assumed): sd = s0 + s1 + s2."""

    name = "toy3"
    names = ("s0", "s1", "s2")

    def default_box(self):
        return {k: (1e-4, 1.0) for k in self.names}

    def sd(self, q, model_stress=None):
        return np.broadcast_to(q.sum(axis=1, keepdims=True), (q.shape[0], self.n_points)).copy()


@pytest.fixture
def toy():
    parser = cli.build_parser()  # built before the registration: the choices must still see it
    register_noise(ToyNoise)
    try:
        yield parser
    finally:
        NOISE_REGISTRY.pop(ToyNoise.name, None)


def _help(parser, command, capsys) -> str:
    capsys.readouterr()
    with pytest.raises(SystemExit):
        parser.parse_args([command, "--help"])
    return capsys.readouterr().out


@pytest.mark.parametrize("command", COMMANDS)
def test_registered_noise_model_is_a_choice_of_every_command(toy, command, capsys):
    assert "toy3" in _help(toy, command, capsys)
    assert "toy3" in _help(cli.build_parser(), command, capsys)
    args = ["x"] if command in ("fit", "optimize") else []
    assert toy.parse_args([command, *args, "--noise", "toy3"]).noise == "toy3"
    assert n_noise_parameters("toy3") == 3 and n_noise_parameters("ar1") == 2 and n_noise_parameters("iid") == 1


@pytest.mark.parametrize("command", COMMANDS)
def test_unregistered_noise_model_is_refused_and_the_toy_is_gone(command, capsys):
    assert "toy3" not in NOISE_REGISTRY
    parser = cli.build_parser()
    assert "toy3" not in _help(parser, command, capsys)
    args = ["x"] if command in ("fit", "optimize") else []
    with pytest.raises(SettingError, match="--noise: invalid choice: 'toy3'.*'iid'"):
        parser.parse_args([command, *args, "--noise", "toy3"])
