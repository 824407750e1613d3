"""Samplers: Transitional MCMC (pure init/step core + driver)."""

from .tmcmc import DEFAULT_N_SAMPLES, TMCMCConfig, TMCMCResult, TMCMCState, init, step, tmcmc

__all__ = ["DEFAULT_N_SAMPLES", "TMCMCConfig", "TMCMCResult", "TMCMCState", "init", "step", "tmcmc"]
