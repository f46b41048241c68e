"""State estimation on a compiled model: the extended Kalman filter (virtual sensing, innovation likelihood), the
continuous–discrete likelihood (``likelihood``), the maximum-likelihood fit with standard errors (``ml_fit``), the
standard errors of an output-error fit (``output_error``) and the result both give (``estimates``).

May import: ``tnn_dsl.core``, ``tnn_dsl.ir``, ``tnn_dsl.compiler``, ``tnn_dsl.data`` (units of the file's values).
"""

from __future__ import annotations

from .estimates import Estimates, estimation_summary
from .kalman import EKFResult, ekf, open_loop, tune_process_noise
from .likelihood import Innovations, LikelihoodProblem, innovations, loglik, nll
from .ml_fit import MLResult, fit_ml
from .output_error import output_error_estimates

__all__ = [
    "EKFResult", "ekf", "open_loop", "tune_process_noise",
    "Innovations", "LikelihoodProblem", "innovations", "loglik", "nll", "MLResult", "fit_ml",
    "Estimates", "estimation_summary", "output_error_estimates",
]
