"""Samplers: Transitional MCMC (pure init/step core + driver)."""

from .tmcmc import (DEFAULT_N_SAMPLES, StageInfo, TMCMCConfig, TMCMCResult, TMCMCState, checkpoint_progress, init,
                    step, tmcmc)

__all__ = ["DEFAULT_N_SAMPLES", "StageInfo", "TMCMCConfig", "TMCMCResult", "TMCMCState", "checkpoint_progress",
           "init", "step", "tmcmc"]
