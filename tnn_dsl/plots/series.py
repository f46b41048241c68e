"""Time series: a simulation against measurements, trained-model predictions with their errors, and an
extended Kalman filter's estimate against the open loop."""

from __future__ import annotations

import math
import os
from typing import Any, Sequence

import numpy as np

from ..data import from_kelvin, unit_scale_offset
from ..ir import Network
from .figure import UNIT_LABEL, new_figure, time_axis

__all__ = ["simulation", "predictions", "filter_estimate"]


def _inputs_panel(ax, net, t: np.ndarray, inputs: np.ndarray) -> None:
    """Every input in the unit the network declares (temperatures in its temperature unit)."""
    unit = net.temperature_unit
    for k, inp in enumerate(net.inputs):
        if inp.is_temperature:
            v, u = from_kelvin(inputs[:, k], unit), UNIT_LABEL[unit]
        else:  # back to the unit the network declares (% stays %)
            scale, offset = unit_scale_offset(inp.unit)
            v, u = (inputs[:, k] - offset) / scale, (inp.unit or "1")
        ax.step(t, v, where="post", lw=0.9, label=f"{inp.name} [{u}]")
    ax.set_ylabel("inputs")
    ax.legend(fontsize=8, loc="best", ncol=min(5, max(1, len(net.inputs))))
    ax.grid(alpha=0.3)


def simulation(net: Network, exp: Any, y: np.ndarray, label: str, axes: Sequence[Any] | None = None) -> Any:
    """One panel per sensor (measured, where the file has it, and simulated ``y (N, n_sensors)`` K) and one of
    the inputs, over ``exp.t``. ``axes``: ``n_sensors + 1`` axes to draw into."""
    unit = net.temperature_unit
    n_s = len(net.sensors)
    fig, ax = new_figure(n_s + 1, 1, figsize=(10, 2.6 * (n_s + 1)), axes=axes, sharex=axes is None)
    ax = ax[:, 0]
    tt, tl = time_axis(exp.t)
    for k, s in enumerate(net.sensors):
        meas = exp.outputs[:, k]
        if np.isfinite(meas).any():
            ax[k].plot(tt, from_kelvin(meas, unit), color="0.3", lw=1.0, label=f"measured ({exp.output_columns[k]})")
            ax[k].set_title(f"{s.name}: MAE {np.nanmean(np.abs(y[:, k] - meas)):.3f} K", fontsize=9, loc="left")
        ax[k].plot(tt, from_kelvin(y[:, k], unit), color="C0", lw=1.2, label="simulated")
        ax[k].set_ylabel(f"{s.name} [{UNIT_LABEL[unit]}]")
        ax[k].legend(fontsize=8, loc="best")
        ax[k].grid(alpha=0.3)
    _inputs_panel(ax[-1], net, tt, exp.inputs)
    ax[-1].set_xlabel(f"time [{tl}]")
    fig.suptitle(f"{label} on {os.path.basename(exp.path)}", fontsize=10)
    fig.tight_layout()
    return fig


def predictions(net: Network, preds: Sequence[dict], axes: Sequence[Any] | None = None,
                max_panels: int = 12) -> Any:
    """For each (experiment, sensor) of ``preds`` (``TrainedModel.predict`` output; at most ``max_panels``):
    measured and predicted in the network's unit, and the error (K) below. ``axes``: two per pair."""
    unit = net.temperature_unit
    pairs = [(p, j) for p in preds for j in range(len(p["sensors"]))][:max_panels]
    fig, ax = new_figure(2 * len(pairs), 1, figsize=(10, 3.2 * len(pairs)), axes=axes,
                         **({} if axes is not None else {"gridspec_kw": {"height_ratios": [2, 1] * len(pairs)}}))
    for i, (p, j) in enumerate(pairs):
        tt, tu = time_axis(p["t"])
        meas, pred = np.asarray(p["measured"])[:, j], np.asarray(p["y"])[:, j]
        a, a_e = ax[2 * i, 0], ax[2 * i + 1, 0]
        a.plot(tt, from_kelvin(meas, unit), color="0.3", lw=1.0, label="measured")
        a.plot(tt, from_kelvin(pred, unit), color="C0", lw=1.2, label="predicted")
        err = pred - meas
        ok = np.isfinite(err)
        mae = float(np.mean(np.abs(err[ok]))) if ok.any() else math.nan
        a.set_title(f"{p['name']}: {p['sensors'][j]}  (MAE {mae:.3g} K)")
        a.set_ylabel(UNIT_LABEL[unit])
        a.legend(loc="best", fontsize=8)
        a_e.plot(tt, err, color="C3", lw=0.8)
        a_e.axhline(0.0, color="0.5", lw=0.6)
        a_e.set_ylabel("error K")
        a_e.set_xlabel(f"time ({tu})")
    fig.tight_layout()
    return fig


def filter_estimate(net: Network, exp: Any, res: Any, y_open: np.ndarray, dropped: np.ndarray, label: str,
                    axes: Sequence[Any] | None = None) -> Any:
    """Per sensor: measured, the filter's estimate with ±2σ of the sensed node, and the open loop; whether the
    filter used the sensor; dropouts shaded. ``res`` is an ``EKFResult``; ``axes``: one per sensor."""
    unit = net.temperature_unit
    sensors = [s.name for s in net.sensors]
    fig, ax = new_figure(len(sensors), 1, figsize=(10, 2.8 * len(sensors) + 0.4), axes=axes, sharex=axes is None)
    tt, tl = time_axis(exp.t)
    for k, s in enumerate(sensors):
        a = ax[k, 0]
        meas = exp.outputs[:, k]
        ok = np.isfinite(meas)
        if ok.any():
            a.plot(tt, from_kelvin(meas, unit), color="0.25", lw=0.9, label="measured")
        a.plot(tt, from_kelvin(y_open[:, k], unit), color="C1", lw=1.0, ls="--", label="open loop")
        a.plot(tt, from_kelvin(res.outputs[:, k], unit), color="C0", lw=1.1, label="EKF estimate")
        node = net.sensors[k].node
        if node in res.state_names:
            i = res.state_names.index(node)
            f = 1.8 if unit == "degF" else 1.0
            mid = from_kelvin(res.outputs[:, k], unit)
            a.fill_between(tt, mid - 2 * f * res.std[:, i], mid + 2 * f * res.std[:, i], color="C0", alpha=0.15,
                           lw=0, label="±2σ")
        if dropped.any() and s in res.used:
            a.fill_between(tt, 0, 1, where=dropped, transform=a.get_xaxis_transform(), color="red", alpha=0.08,
                           lw=0, label="dropout")
        role = "used by the filter" if s in res.used else "not used: virtual sensor"
        if ok.any():
            e1 = np.mean(np.abs(res.outputs[ok, k] - meas[ok]))
            e0 = np.mean(np.abs(y_open[ok, k] - meas[ok]))
            role += f"   MAE: EKF {e1:.3f} K, open loop {e0:.3f} K"
        a.set_title(f"{s} ({role})", fontsize=9, loc="left")
        a.set_ylabel(f"{s} [{UNIT_LABEL[unit]}]")
        a.grid(alpha=0.3)
        a.legend(fontsize=8, loc="best", ncol=3)
    ax[-1, 0].set_xlabel(f"time [{tl}]")
    fig.suptitle(f"extended Kalman filter: {label} on {os.path.basename(exp.path)}", fontsize=10)
    fig.tight_layout()
    return fig
