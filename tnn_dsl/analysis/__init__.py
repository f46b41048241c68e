"""What a model and its data say: sensitivity, identifiability, excitation, residuals, significance tests.

May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``, ``fit``.
"""

from __future__ import annotations

from . import residuals
from .hankel import excitation
from .identifiability import fisher_analysis
from .report import SensitivityReport
from .sensitivities import sensitivity
from .significance import held_out_test

__all__ = [
    "residuals", "SensitivityReport", "excitation", "fisher_analysis", "sensitivity", "held_out_test"
]
