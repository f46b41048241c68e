"""State estimation on a compiled model: the extended Kalman filter (virtual sensing, innovation likelihood), the
continuous–discrete likelihood (``likelihood``) and the maximum-likelihood fit with standard errors (``ml_fit``).

May import: ``tnn_dsl.core``, ``tnn_dsl.ir``, ``tnn_dsl.compiler``, ``tnn_dsl.data`` (units of the file's values).
"""

from __future__ import annotations

from .kalman import EKFResult, ekf, open_loop, tune_process_noise
from .likelihood import Innovations, LikelihoodProblem, innovations, loglik, nll
from .ml_fit import MLResult, fit_ml

__all__ = [
    "EKFResult", "ekf", "open_loop", "tune_process_noise",
    "Innovations", "LikelihoodProblem", "innovations", "loglik", "nll", "MLResult", "fit_ml",
]
