"""The model doctor's acceptance thresholds (shared by the forward selection and the linear-or-MLP check)."""

from __future__ import annotations

__all__ = ["P_ACCEPT", "MIN_GAIN", "CLOSE_RATIO"]

P_ACCEPT = 0.05  # held-out confirmation: one-sided Diebold–Mariano p below this
MIN_GAIN = 0.10  # minimum relative MAE reduction on held-out data
CLOSE_RATIO = 2.0  # a rival more than this many times the best's held-out MAE is never "within noise" of it
