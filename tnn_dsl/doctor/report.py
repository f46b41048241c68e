"""The model doctor's HTML report: one self-contained page (PNG plots embedded as base64, no scripts,
no external files) a person reads top to bottom — verdict, data and baseline, residual plots (time,
autocorrelation, cumulated periodogram, residual against each variable), the candidate table, the
findings with their clauses and evidence, before/after plots and the extension's diff."""

from __future__ import annotations

import base64
import html
import io
import math
import os
from pathlib import Path

import numpy as np

from ..core import OutputKind, check_output, write_text_atomic
from .results import Diagnosis

__all__ = ["write_report"]


def _png(fig) -> str:
    """A figure as a ``data:`` URI (the report embeds its plots)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _img(uri: str, alt: str) -> str:
    return f'<img src="{uri}" alt="{html.escape(alt)}" style="max-width:100%">'


def _num(x, d=4) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{d}g}" if isinstance(x, (float, np.floating)) else html.escape(str(x))


def _plots(d) -> list[tuple[str, str]]:
    """``[(title, data URI)]``: before/after per sensor, whiteness per sensor, residual against variables."""
    from .. import plots

    out = [(f"{s}: before and after", _png(plots.before_after(d.plots, j, extended=bool(d.accepted))))
           for j, s in enumerate(d.plots["output_names"])]
    out += [(f"{s}: whiteness", _png(plots.whiteness(s, w))) for s, w in d.residuals.whiteness.items() if "acf" in w]
    for s, deps in d.plots.get("dependence", {}).items():
        fig = plots.residual_dependence(s, deps)
        if fig is not None:
            out.append((f"{s}: residual against each variable", _png(fig)))
    return out


def _is_report_dir(p: Path) -> bool:
    """A directory holding only a report page that this module wrote."""
    names = {c.name for c in p.iterdir()}
    if names != {"index.html"}:
        return False
    try:
        with open(p / "index.html", encoding="utf-8") as fh:
            return _MARK in fh.read(4096)
    except (OSError, UnicodeDecodeError):
        return False


_MARK = "<meta name='generator' content='tnnc diagnose'>"
REPORT_DIR = OutputKind("report directory", is_dir=True, ours=_is_report_dir, example="report/")
"""What ``tnnc diagnose --report DIR`` writes: ``DIR/index.html`` alone."""


def write_report(d: Diagnosis, directory: str | os.PathLike, *, force: bool = False) -> str:
    """Write ``directory/index.html`` for a :class:`~tnn_dsl.doctor.diagnosis.Diagnosis`; returns its path.

    ``directory`` must be absent, empty or an earlier report, unless ``force`` (then only its
    ``index.html`` is replaced)."""
    check_output(directory, REPORT_DIR, force=force, option="--report")
    e = html.escape
    b = d.baseline
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'>{_MARK}",
        f"<title>tnnc diagnose: {e(d.network)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse;font-size:90%}td,th{border:1px solid #ccc;padding:3px 6px}"
        "pre{background:#f6f6f6;padding:8px;overflow-x:auto}.ok{color:#070}.no{color:#a00}</style></head><body>",
        f"<h1>Model doctor: {e(d.network)}</h1>",
        "<p>Question answered: is the <b>free-run simulation</b> right (output error from the initial steady "
        "state), not the one-step predictor.</p>",
        f"<h2>Verdict</h2><p><b>{e(d.verdict)}</b></p><p>What is left: {e(d.left)}</p>",
        "<h2>Baseline (nominal model, free parameters fitted)</h2><table><tr><th></th><th>MAE (K)</th>"
        "<th>max (K)</th></tr>",
        f"<tr><td>training rows</td><td>{_num(b['train_mae'])}</td><td>{_num(b['train_max'])}</td></tr>",
        f"<tr><td>held-out rows</td><td>{_num(b['val_mae'])}</td><td>{_num(b['val_max'])}</td></tr>",
        f"<tr><td>extended, held-out</td><td>{_num(d.extended['val_mae'])}</td>"
        f"<td>{_num(d.extended['val_max'])}</td></tr>",
        "</table>",
        "<h3>Per sensor (held-out)</h3><table><tr><th>sensor</th><th>MAE</th><th>max</th><th>bias</th>"
        "<th>noise σ</th><th>white?</th></tr>",
    ]
    for s, st in d.residuals.errors.items():
        w = d.residuals.whiteness.get(s, {})
        parts.append(f"<tr><td>{e(s)}</td><td>{_num(st['mae'])}</td><td>{_num(st['max'])}</td>"
                     f"<td>{_num(st['bias'])}</td><td>{_num(d.residuals.sigma.get(s))}</td>"
                     f"<td>{'yes' if w.get('white') else 'no'} "
                     f"(Ljung–Box p = {_num(w.get('ljung_box_p'), 2)})</td></tr>")
    parts.append("</table>")
    if b.get("free_params"):
        parts.append("<h3>Fitted free parameters (SI)</h3><table>")
        for k, v in b["free_params"].items():
            parts.append(f"<tr><td>{e(k)}</td><td>{_num(v)}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Findings</h2>")
    if not d.findings:
        parts.append("<p>No candidate was fitted.</p>")
    else:
        parts.append("<table><tr><th>round</th><th>rank</th><th>cause</th><th>clause</th><th>held-out MAE after</th>"
                     "<th>held-out test p</th><th>N_eff</th><th>decision</th></tr>")
        for f in d.findings:
            cls = "ok" if f.accepted else "no"
            ev = f.evidence
            parts.append(
                f"<tr><td>{f.round}</td><td>{f.rank}</td><td>{e(f.words)}</td><td><code>{e(f.clause)}</code></td>"
                f"<td>{_num(f.val_mae_after)}</td><td>{_num(ev.get('p_value'), 2)}</td>"
                f"<td>{_num(ev.get('n_eff'), 4)}</td>"
                f"<td class='{cls}'>{'accepted' if f.accepted else 'rejected: ' + e(ev.get('reason', ''))}</td></tr>")
        parts.append("</table>")
    parts.append("<h2>Score test (first round, best 20)</h2><table><tr><th>rank</th><th>candidate</th><th>k</th>"
                 "<th>R² (linearised)</th><th>score</th><th>p (χ²)</th></tr>")
    for s in d.scores[:20]:
        parts.append(f"<tr><td>{s['rank']}</td><td>{e(s['words'])}</td><td>{s['k']}</td><td>{_num(s['r2'], 3)}</td>"
                     f"<td>{_num(s['score'], 4)}</td><td>{_num(s['p'], 2)}</td></tr>")
    parts.append("</table>")
    if d.diff:
        parts.append(f"<h2>The extension</h2><pre>{e(d.diff)}</pre>")
        if d.extended_file:
            parts.append(f"<p>Written to <code>{e(d.extended_file)}</code>.</p>")
    parts.append("<h2>Plots</h2>")
    try:
        for title, uri in _plots(d):
            parts.append(f"<h3>{e(title)}</h3>{_img(uri, title)}")
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        parts.append("<p>(matplotlib not available: no plots)</p>")
    parts.append(f"<h2>Timings (s)</h2><pre>{e(str(d.timings))}</pre></body></html>")
    path = os.path.join(directory, "index.html")
    write_text_atomic(path, "\n".join(parts))
    return path
