"""The multi-specimen workflow behind ``hbm run`` (:mod:`.run`), its Markdown report (:mod:`.report`) and
the organ-scale prediction from fitted specimens (:mod:`.organ`, ``hbm predict organ``)."""

from ..runtime.lazy import attach

# hbm.workflow.organ (hbm predict) does not load the dask workflow (hbm.runtime.lazy)
__getattr__, __dir__ = attach(__name__, {".run": ["DEFAULT_OUT", "RunConfig", "WorkflowResult", "fit_task",
                                                  "run_workflow"]})

__all__ = ["DEFAULT_OUT", "RunConfig", "WorkflowResult", "run_workflow", "fit_task"]
