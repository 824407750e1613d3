"""Integrate the linear amplitudes of a model exactly and sample only its nonlinear parameters.

Modules: :mod:`~hbm.collapse.induced` (the prior a column amplitude inherits from its original
parameters), :mod:`~hbm.collapse.quadrature` (the box-truncated Gaussian integral and draws).
"""

from .induced import CollapseError, ColumnPrior, Term
from .quadrature import BoxGaussianIntegral, box_qp, truncated_normal_log_mass

__all__ = ["CollapseError", "ColumnPrior", "Term", "BoxGaussianIntegral", "box_qp", "truncated_normal_log_mass"]
