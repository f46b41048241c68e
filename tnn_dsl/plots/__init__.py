"""Plots: every function returns a :class:`matplotlib.figure.Figure` and never switches matplotlib's backend.

Figures are built on :class:`matplotlib.figure.Figure` directly (no pyplot state), so they display inline in a
notebook when returned, and :func:`tnn_dsl.core.save_figure` writes them atomically. Functions that draw one
panel take ``ax=`` (draw into a given axes); those that draw a column of panels take ``axes=`` (a sequence of
at least as many axes). Temperatures are shown in the network's unit, time in s, min or h by duration.

Modules: ``figure`` (the shared helpers), ``series`` (time series: simulation, predictions, filter),
``functions`` (learned functions over their inputs), ``study`` (the thesis case study), ``sensitivity`` (the
ranked sensitivity bars), ``doctor`` (the model doctor's report), ``drawing``
(a picture of a network: Graphviz, else matplotlib).
May import: ``tnn_dsl.core``, ``tnn_dsl.ir``, ``tnn_dsl.data`` (unit conversions); results arrive as arrays or
duck-typed objects.
"""

from __future__ import annotations

from .doctor import before_after, residual_dependence, whiteness
from .drawing import network, render_png
from .figure import new_figure, time_axis
from .functions import learned_function
from .sensitivity import sensitivity_bars
from .series import filter_estimate, predictions, simulation
from .study import ood_growth, validation_runs

__all__ = ["new_figure", "time_axis", "learned_function", "filter_estimate", "predictions", "simulation",
           "ood_growth", "validation_runs", "sensitivity_bars",
           "before_after", "whiteness", "residual_dependence",
           "network", "render_png"]
