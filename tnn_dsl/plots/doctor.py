"""The model doctor's figures: measured, nominal and extended simulations with their residuals, whether the
held-out residual is white (autocorrelation, cumulated periodogram), and the residual against each variable."""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .figure import new_figure

__all__ = ["before_after", "whiteness", "residual_dependence"]


def before_after(plots: dict, j: int, extended: bool = True, axes: Sequence[Any] | None = None) -> Any:
    """Sensor ``j`` over every sample of a diagnosis (``Diagnosis.plots``): measured, the fitted nominal model
    and (``extended``) the extension on top; their residuals below; held-out rows shaded."""
    s = plots["output_names"][j]
    y, yn, ye = np.asarray(plots["y"]), np.asarray(plots["y_nominal"]), np.asarray(plots["y_extended"])
    vm = np.asarray(plots["val_mask"])
    x = np.arange(len(np.asarray(plots["t"])))
    fig, ax = new_figure(2, 1, figsize=(10, 5.5), axes=axes, sharex=axes is None)
    top, bottom = ax[0, 0], ax[1, 0]
    top.plot(x, y[:, j] - 273.15, "k.", ms=1, label="measured")
    top.plot(x, yn[:, j] - 273.15, lw=1, label="nominal (fitted)")
    if extended:
        top.plot(x, ye[:, j] - 273.15, lw=1, label="extended")
    top.set_ylabel(f"{s} (°C)")
    top.legend(loc="best", fontsize=8)
    bottom.plot(x, y[:, j] - yn[:, j], lw=0.8, label="residual, nominal")
    if extended:
        bottom.plot(x, y[:, j] - ye[:, j], lw=0.8, label="residual, extended")
    bottom.axhline(0, color="k", lw=0.5)
    bottom.set_ylabel("residual (K)")
    bottom.set_xlabel("sample (all experiments, in order)")
    bottom.legend(loc="best", fontsize=8)
    for a in (top, bottom):
        lo, hi = a.get_ylim()
        a.fill_between(x, lo, hi, where=vm[:, j], color="0.9", zorder=-1, step="mid")
        a.set_ylim(lo, hi)
    fig.suptitle(f"{s}: measured and simulated (grey: held-out rows)")
    return fig


def whiteness(sensor: str, w: dict, axes: Sequence[Any] | None = None) -> Any:
    """The residual's autocorrelation with its band (Ljung–Box) and its cumulated periodogram with the
    Kolmogorov–Smirnov band, from :func:`tnn_dsl.analysis.residuals.whiteness`'s result ``w``."""
    fig, ax = new_figure(1, 2, figsize=(10, 3.2), axes=axes)
    acf, cp = ax[0, 0], ax[0, 1]
    acf.bar(w["lags"], w["acf"], width=0.6)
    acf.axhline(w["acf_band"], ls="--", color="r", lw=0.8)
    acf.axhline(-w["acf_band"], ls="--", color="r", lw=0.8)
    acf.set_title(f"autocorrelation (Ljung–Box p = {w['ljung_box_p']:.2g})", fontsize=9)
    acf.set_xlabel("lag (samples)")
    f = np.asarray(w["cpgram_freq"])
    c = np.asarray(w["cpgram"])
    cp.plot(f, c, lw=1)
    ideal = np.linspace(0, 1, len(f)) if len(f) else f
    cp.plot(f, ideal, "k", lw=0.5)
    cp.plot(f, ideal + w["ks_band"], "r--", lw=0.8)
    cp.plot(f, ideal - w["ks_band"], "r--", lw=0.8)
    cp.set_ylim(0, 1)
    cp.set_title(f"cumulated periodogram (KS p = {w['ks_p']:.2g})", fontsize=9)
    cp.set_xlabel("frequency (1/sample)")
    fig.suptitle(f"is the held-out residual of {sensor} white?")
    return fig


def residual_dependence(sensor: str, deps: dict) -> Any | None:
    """The mean held-out residual (K) in bins of each variable (``None`` when there is none to show)."""
    items = [(v, dd) for v, dd in deps.items() if dd.get("centers")]
    if not items:
        return None
    n = len(items)
    cols = min(4, n)
    rows = int(math.ceil(n / cols))
    fig, axs = new_figure(rows, cols, figsize=(3.0 * cols, 2.4 * rows))
    for a in axs.ravel()[n:]:
        a.axis("off")
    for a, (v, dd) in zip(axs.ravel(), items):
        a.plot(dd["centers"], dd["means"], "o-", ms=3)
        a.axhline(0, color="k", lw=0.5)
        a.set_title(f"{v} (r = {dd['corr']:.2f})", fontsize=8)
        a.tick_params(labelsize=7)
    fig.suptitle(f"{sensor}: mean held-out residual (K) in bins of each variable")
    fig.tight_layout()
    return fig
