"""What a model and its data say: sensitivity, identifiability, excitation, residuals, significance tests.

Owns: the sensitivity pass (``sensitivities``: the α scan, the exact eq. 3.4 derivative, trajectory
sensitivity; results in ``report``), identifiability from the Fisher information (``identifiability``),
excitation from input Hankel singular values (``hankel``), residual analysis (``residuals``), the held-out
test on prediction errors (``significance``) and shared formatting (``common``).
May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``, ``fit``.
"""

from __future__ import annotations

from . import residuals
from .comparison import Comparison, Nesting, compare_models, nesting
from .hankel import excitation
from .identifiability import fisher_analysis
from .report import SensitivityReport
from .sensitivities import sensitivity
from .significance import held_out_loglik_test, held_out_test

__all__ = [
    "residuals", "SensitivityReport", "excitation", "fisher_analysis", "sensitivity", "held_out_test",
    "held_out_loglik_test",
    "Comparison", "Nesting", "compare_models", "nesting",
]
