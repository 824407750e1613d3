"""The multi-specimen workflow behind ``hbm run`` (:mod:`.run`), its Markdown report (:mod:`.report`) and
the organ-scale prediction from fitted specimens (:mod:`.organ`, ``hbm predict organ``)."""

from .run import DEFAULT_OUT, RunConfig, WorkflowResult, fit_task, run_workflow

__all__ = ["DEFAULT_OUT", "RunConfig", "WorkflowResult", "run_workflow", "fit_task"]
