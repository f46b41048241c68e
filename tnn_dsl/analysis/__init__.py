"""What a model and its data say: sensitivity, identifiability, excitation, residuals, significance tests.

May import: ``core``, ``ir``, ``lang``, ``compiler``, ``data``, ``estimation``, ``fit``.
"""

from __future__ import annotations

from . import residuals
from .sensitivities import excitation, fisher_analysis, sensitivity
from .significance import held_out_test

__all__ = [
    "residuals", "excitation", "fisher_analysis", "sensitivity", "held_out_test"
]
