"""Where a simulated or fitted temperature may lie on an experiment: the data's range widened by its span.

Shared by the free-run check (:func:`tnn_dsl.fit.simulation.check_rollout`), the trainer's penalty on fitted initial
states and the burn-in estimate of :mod:`tnn_dsl.fit.initial` (which :mod:`.simulation` imports, so the ranges
live here)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..data import Experiment

IMPLAUSIBLE_SPANS = 100.0
"""A simulated temperature more than this many times the data's temperature span (at least 10 K) beyond the
data's range is implausible: the model, not the plant, is doing that."""
IMPLAUSIBLE_SPANS_BELOW = 10.0
"""Below the data's range the limit is tighter: nothing passive cools below its coldest boundary, and a Peltier
element's cold side stays within tens of kelvin of it."""


def plausible_range(model: Any, exp: Experiment) -> tuple[float, float]:
    """``(low, high)`` K a simulated temperature may reach on ``exp``: above absolute zero, and within
    ``IMPLAUSIBLE_SPANS`` times the span of every temperature the data holds (sensors, temperature inputs;
    at least 10 K) above that data's range and ``IMPLAUSIBLE_SPANS_BELOW`` times below it. Without temperatures in
    the data, 200 … 400 K."""
    parts = [np.asarray(exp.outputs, dtype=float).ravel()]
    net = model.network
    temp_inputs = [k for k, inp in enumerate(net.inputs) if inp.is_temperature]
    if temp_inputs and np.size(exp.inputs):
        parts.append(np.asarray(exp.inputs, dtype=float)[:, temp_inputs].ravel())
    vals = np.concatenate(parts) if parts else np.zeros(0)
    vals = vals[np.isfinite(vals)]
    lo, hi = (float(vals.min()), float(vals.max())) if vals.size else (200.0, 400.0)
    span = max(hi - lo, 10.0)
    return max(lo - span * IMPLAUSIBLE_SPANS_BELOW, 0.0), hi + span * IMPLAUSIBLE_SPANS


START_SPANS_BELOW = 1.0
"""A fitted initial state may lie this many data spans below the data's coldest temperature (a node does not start
far colder than everything measured unless something cools it; the high side is :func:`plausible_range`'s)."""

START_PENALTY = 1.0
"""Weight (per K², beside the mean squared error in K²) of a fitted initial state's distance outside
:func:`start_range` in the training loss: zero inside, so it changes no fit that starts within the range."""


def start_range(model: Any, exp: Experiment) -> tuple[float, float]:
    """``(low, high)`` K where the fitted initial state of a training file on ``exp`` may lie:
    :func:`plausible_range` with the low side ``START_SPANS_BELOW`` data spans below the coldest temperature.
    Without it an unsensed fast node's start is a free kick: Bacher & Madsen's TiTeTh fitted its heater node to
    start at −605.7 K, which the free-run check then refuses."""
    lo, hi = plausible_range(model, exp)
    parts = [np.asarray(exp.outputs, dtype=float).ravel()]
    temp_inputs = [k for k, inp in enumerate(model.network.inputs) if inp.is_temperature]
    if temp_inputs and np.size(exp.inputs):
        parts.append(np.asarray(exp.inputs, dtype=float)[:, temp_inputs].ravel())
    vals = np.concatenate(parts)
    vals = vals[np.isfinite(vals)]
    if vals.size:
        span = max(float(vals.max() - vals.min()), 10.0)
        lo = max(lo, float(vals.min()) - START_SPANS_BELOW * span)
    return lo, hi
