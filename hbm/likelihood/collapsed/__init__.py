"""Integrate the linear amplitudes of a model exactly and sample only its nonlinear parameters.

Modules: :mod:`~hbm.likelihood.collapsed.induced` (the prior a column amplitude inherits from its original
parameters), :mod:`~hbm.likelihood.collapsed.quadrature` (the box-truncated Gaussian integral and draws),
:mod:`~hbm.likelihood.collapsed.likelihood` (the collapsed likelihood of a specimen and the tier choice),
:mod:`~hbm.likelihood.collapsed.sampling` (TMCMC over φ, the importance finish, the completed posterior).
"""

from .induced import CollapseError, ColumnPrior, Term
from .likelihood import TIERS, CollapsedLikelihood, choose_tier, collapse_reason
from .quadrature import BoxGaussianIntegral, box_qp
from .sampling import FIT_ROUTE, CollapsedFit, CollapsedRoute, fit_collapsed, sample_collapsed

__all__ = ["CollapseError", "ColumnPrior", "Term", "BoxGaussianIntegral", "box_qp",
           "TIERS", "CollapsedLikelihood", "choose_tier", "collapse_reason", "CollapsedFit", "CollapsedRoute", "FIT_ROUTE", "fit_collapsed", "sample_collapsed"]
