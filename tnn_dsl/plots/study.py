"""The thesis case study: out-of-distribution error per model (thesis Fig. 5.6) and the validation run
per model (Fig. 5.4)."""

from __future__ import annotations

from typing import Any, Sequence

from .figure import new_figure

__all__ = ["ood_growth", "validation_runs"]


def ood_growth(results: dict, ax: Any | None = None) -> Any | None:
    """Validation MAE and MAE per input widening for every model of a study's ``results`` (``run_study``);
    ``None`` when the study has no out-of-distribution sets."""
    m = results["models"]
    widen = results["data"].get("widen", [])
    if not widen or not any("ood" in r for r in m.values()):
        return None
    fig, axs = new_figure(1, 1, figsize=(6.5, 4.2), axes=None if ax is None else [ax])
    a = axs[0, 0]
    xs = [0] + [round(float(w) * 100) for w in widen]
    for name, r in m.items():
        if "ood" in r:
            a.plot(xs, [r["validation"]["mae"] * 1e3] + [r["ood"][f"{x}"] * 1e3 for x in xs[1:]], "o-",
                   label=f"{name}: {r['what']}")
    a.set_yscale("log")
    a.set_xlabel("input bounds widened by [%] (0 = validation set)")
    a.set_ylabel("T_out MAE [mK] (mean over data sets)")
    a.set_title(f"out-of-distribution error (cf. thesis Fig. 5.6), {results['data'].get('n_ood')} sets per level",
                fontsize=9)
    a.grid(alpha=0.3, which="both")
    a.legend(fontsize=7)
    fig.tight_layout()
    return fig


def validation_runs(preds: dict[str, dict], axes: Sequence[Any] | None = None) -> Any:
    """``T_out`` through the validation run (top) and each model's error (bottom); ``preds``: model name →
    its ``TrainedModel.predict`` record on the validation file."""
    fig, ax = new_figure(2, 1, figsize=(10, 6), axes=axes, sharex=axes is None)
    top, bottom = ax[0, 0], ax[1, 0]
    first = next(iter(preds.values()))
    t = first["t"] / 3600
    top.plot(t, first["measured"][:, 0] - 273.15, color="k", lw=1.0, label="truth (validation)")
    for name, p in preds.items():
        top.plot(t, p["y"][:, 0] - 273.15, lw=0.9, label=name)
        bottom.plot(t, (p["y"][:, 0] - p["measured"][:, 0]) * 1e3, lw=0.9, label=name)
    top.set_ylabel("T_out [°C]")
    bottom.set_ylabel("error [mK]")
    bottom.set_xlabel("time [h]")
    for a in (top, bottom):
        a.grid(alpha=0.3)
        a.legend(fontsize=7, ncol=3)
    top.set_title("validation run: free-run prediction per model (cf. thesis Fig. 5.4)", fontsize=9)
    fig.tight_layout()
    return fig
