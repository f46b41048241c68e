"""What the model doctor returns: every properly fitted candidate (:class:`Finding`) and the diagnosis
(:class:`Diagnosis`: baseline, residual analysis, score table, findings, the extension and its gain), with
its JSON document and terminal summary."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field
from typing import Any

from ..analysis import residuals as R
from ..core import to_jsonable
from ..core.htmlview import html_list, html_table, pre, safe_repr_html, view

__all__ = ["Finding", "Diagnosis"]


def _caution(twins: str) -> str:
    """The summary's caution for an accepted finding the data cannot tell apart from ``twins``."""
    return ("caution: to first order the data cannot tell this apart from " + twins
            + " — the named element is the best-scoring, most physical choice; the others"
            " could compensate for it (not separately identifiable from these sensors)")


@dataclass
class Finding:
    """One candidate that was fitted properly. ``evidence`` holds the numbers behind the decision."""

    rank: int
    kind: str
    target: str
    depends_on: list[str]
    clause: str
    val_mae_after: float
    val_max_after: float
    evidence: dict
    accepted: bool
    words: str = ""
    round: int = 1

    def to_dict(self) -> dict:
        return to_jsonable({
            "rank": self.rank, "round": self.round, "kind": self.kind, "target": self.target,
            "depends_on": self.depends_on, "clause": self.clause, "words": self.words,
            "val_mae_after": self.val_mae_after, "val_max_after": self.val_max_after,
            "evidence": self.evidence, "accepted": self.accepted,
        })


def uncertainty_text(u: dict | None, mlp_from_fit: bool = False) -> list[str]:
    """Lines of the extended model's values with standard errors and what the sensors cannot tell apart (``u``:
    ``Diagnosis.extended["uncertainty"]``, :mod:`tnn_dsl.doctor.uncertainty`; SI units); ``mlp_from_fit``: the MLP
    check chose an MLP started as the law these values are of (its weights have none). Nothing without estimates.
    The summary shows them, and ``tnnc inspect`` of a diagnosed model (``meta["diagnosis"]["uncertainty"]``)."""
    if not u or not u.get("estimates"):
        return []
    lines = ["values of the extended model (± one standard error, SI; " + u["method"] + "):"]
    for e in u["estimates"]:
        se = f" ± {e['se']:.2g}" if e.get("se") is not None and math.isfinite(e["se"]) else ""
        flag = f"  ({e['status']})" if e["status"] != "ok" else ""
        lines.append(f"  {e['name']} = {e['value']:.4g}{se} {e['unit']}".rstrip() + flag)
    lines += [f"identifiability: {s}" for s in u.get("statements", [])]
    if mlp_from_fit:
        lines.append("the MLP chosen instead of the linear law started as this law, every other value held at "
                     "the above, and trained its own weights only (they have no standard errors)")
    return lines


@dataclass
class Diagnosis:
    """What ``diagnose`` found. ``to_dict()`` is the ``--json`` document."""

    network: str
    baseline: dict
    residuals: R.ResidualSummary
    scores: list[dict]
    findings: list[Finding]
    extended_text: str
    extended_file: str | None
    extended: dict
    diff: str
    verdict: str
    left: str
    timings: dict = field(default_factory=dict)
    plots: dict = field(default_factory=dict)  # series for the report (numpy arrays)
    notes: list[str] = field(default_factory=list)
    """Lines for the user before the findings: the initial-state rule and its burn-in, warnings (``warning:``
    first) such as data that do not start at rest, parameters the baseline fit moved far."""
    initial: dict = field(default_factory=dict)
    """How the free runs start: ``rule``, ``burn_in`` (held-out file → samples not scored)."""
    objective: str = "output-error"
    """What the selection maximises: ``output-error`` (free-run error, held-out Diebold–Mariano on squared errors)
    or ``ml`` (the Kalman-filter likelihood, likelihood-ratio tests; evidence ``likelihood`` per finding)."""
    model: Any = None
    """The diagnosed model (a :class:`~tnn_dsl.fit.TrainedModel`; :mod:`.saved_model`): the extension (or, with
    nothing accepted, the network itself) at the values the doctor measured it with, the MLP check's trained MLP where
    it chose one; ``None`` where the doctor's values could not be put under the extension's names (said in
    :attr:`notes`). ``model.evaluate(val)`` gives the held-out numbers of :attr:`extended`."""
    model_dir: str | None = None
    """Where :attr:`model` was written (``diagnose(model_dir=...)``, ``tnnc diagnose --model DIR``), else ``None``."""
    budget: dict | None = None
    """``{"seconds": s, "ran_out": where, "interrupted": bool}`` when the budget (``budget_s``) or Ctrl-C
    (``interrupted``; :mod:`.stopping`) cut the work (``where``: ``"before any candidate was tested"``, ``"in round
    2"``, ...), else ``None``. With nothing accepted the diagnosis is then not decided (:attr:`decided`)."""

    @property
    def decided(self) -> bool:
        """``False`` where the budget ran out with nothing accepted: no deficiency found, but the search did not
        finish (a fleet lists such units apart from clean ones)."""
        return bool(self.accepted) or self.budget is None

    @property
    def accepted(self) -> list[Finding]:
        return [f for f in self.findings if f.accepted]

    @property
    def gain(self) -> dict:
        b, e = self.baseline["val_mae"], self.extended["val_mae"]
        return {"val_mae_ratio": (b / e) if e else None,
                "val_mae_before": b, "val_mae_after": e,
                "val_max_before": self.baseline["val_max"], "val_max_after": self.extended["val_max"]}

    def to_dict(self) -> dict:
        return to_jsonable({
            "network": self.network,
            "question": ("one-step prediction (Kalman-filter likelihood) for the selection; " if self.objective == "ml"
                         else "") + "free-run simulation (output error from each file's initial state, rule "
                        + str(self.initial.get("rule", "steady")) + ")",
            "objective": self.objective,
            "initial_state": self.initial,
            "notes": self.notes,
            "baseline": self.baseline,
            "residuals": {k: v for k, v in self.residuals.to_dict().items() if k != "dependence"},
            "scores": self.scores[:30],
            "findings": [f.to_dict() for f in self.findings],
            "extended": {**self.extended, "file": self.extended_file, "model": self.model_dir},
            "gain": self.gain,
            "verdict": self.verdict,
            "decided": self.decided,
            "budget": self.budget,
            "left": self.left,
            "diff": self.diff,
            "timings": self.timings,
        })

    def residual_rows(self) -> list[dict[str, Any]]:
        """Per sensor, the nominal model's residual: ``sensor``, ``white``, ``ljung_box_p``, ``sigma`` (K)."""
        return [{"sensor": s, "white": bool(st.get("white")), "ljung_box_p": st.get("ljung_box_p", 1),
                 "sigma": self.residuals.sigma[s]} for s, st in self.residuals.whiteness.items()]

    def finding_rows(self) -> list[dict[str, Any]]:
        """One row per finding (what :meth:`summary` and the notebook view show): ``round``, ``accepted``,
        ``cause`` (in words), ``dependence`` (the variables), ``clause``, ``mae_before``/``mae_after`` (held
        out, K), ``p_value`` and ``n_eff`` of the held-out test, ``reason``, ``caution`` (the candidates an
        accepted finding cannot be told apart from; empty if none) and ``separated`` (first-order twins the held-out
        run tells apart: at least twice its held-out error, or diverged)."""
        rows = []
        for f in self.findings:
            ev = f.evidence
            twins = ev.get("indistinguishable_from") if f.accepted else None
            rows.append({
                "round": f.round, "accepted": f.accepted, "cause": f.words, "dependence": list(f.depends_on),
                "clause": f.clause, "mae_before": ev.get("val_mae_before", math.nan), "mae_after": f.val_mae_after,
                "p_value": ev.get("p_value", math.nan), "n_eff": ev.get("n_eff", 0), "reason": ev.get("reason") or "",
                "caution": "; ".join(f"{t['candidate']} (|cos| = {t['cos']:.3f})"
                                     for t in [t for t in twins or [] if not t.get("separated")][:3]),
                "separated": "; ".join(
                    f"{t['candidate']} (held-out MAE {t['val_mae']:.4g} K against {f.val_mae_after:.4g} K)"
                    if math.isfinite(t["val_mae"]) else f"{t['candidate']} (its fit diverged)"
                    for t in twins or [] if t.get("separated")),
                "likelihood": ev.get("likelihood"),
            })
        return rows

    def mlp_text(self) -> str | None:
        """The summary's "linear or MLP" answer (None when the MLP check did not run)."""
        mc = self.extended.get("mlp_check")
        if mc and "linear" in mc and mc["linear"].get("stopped") == "the doctor's fit":
            return (f"an MLP trained from the doctor's linear law (held-out MAE linear "
                    f"{mc['linear']['val_mae']:.4g} K, MLP {mc['mlp']['val_mae']:.4g} K): {mc['choice']} — "
                    f"{mc['reason']}")
        if mc and "linear" in mc:
            return (f"trained both (held-out MAE linear {mc['linear']['val_mae']:.4g} K, "
                    f"MLP {mc['mlp']['val_mae']:.4g} K): {mc['choice']} — {mc['reason']}")
        if mc and "mlp" in mc:
            return f"trained the MLP (held-out MAE {mc['mlp']['val_mae']:.4g} K): {mc['choice']} — {mc['reason']}"
        return mc["reason"] if mc else None

    def summary(self) -> str:
        """The terminal summary."""
        b = self.baseline
        lines = [f"model doctor: {self.network}",
                 f"  baseline (held-out): MAE {b['val_mae']:.4g} K, max {b['val_max']:.4g} K"
                 f"  (train MAE {b['train_mae']:.4g} K)"]
        lk = b.get("likelihood")
        if lk:
            rms = lk.get("one_step_rms_val")
            lines.append(f"  objective ml: nominal model log L {lk['loglik']:.2f} (k = {lk['k']}, "
                         f"{lk['n_obs']} readings)"
                         + (f", held-out one-step RMS {rms:.4g} K" if rms is not None else ""))
        lines += [f"  {n}" for n in self.notes]
        for r in self.residual_rows():
            lines.append(f"  residual {r['sensor']}: {'white' if r['white'] else 'NOT white'}"
                         f" (Ljung–Box p = {r['ljung_box_p']:.2g}), noise σ ≈ {r['sigma']:.3g} K")
        if self.scores:
            lines.append("  score test, best candidates:")
            for s in self.scores[:5]:
                lines.append(f"    {s['rank']:>2}. {s['words']:<60} k={s['k']}  R²={s['r2']:.3f}  p={s['p']:.2g}")
        for r in self.finding_rows():
            mark = "ACCEPTED" if r["accepted"] else "rejected"
            lines.append(f"  [{mark}] round {r['round']}: {r['cause']}")
            lines.append(f"      clause: {r['clause']}")
            after = f"{r['mae_after']:.4g} K" if math.isfinite(r["mae_after"]) else "diverged"
            lines.append(f"      held-out MAE {r['mae_before']:.4g} → {after}"
                         + (f", held-out test p = {r['p_value']:.2g} (N_eff = {r['n_eff']:.0f})"
                            if math.isfinite(r["mae_after"]) else "")
                         + (f"; {r['reason']}" if r["reason"] else ""))
            lk = r["likelihood"]
            if lk:
                lines.append(f"      likelihood: log L {lk['loglik_before']:.2f} → {lk['loglik']:.2f}, "
                             f"LR = {lk['lr']:.4g} on {lk['df']} df (p = {lk['p_lr']:.2g} after ×{lk['m']}); "
                             "held-out one-step log L "
                             f"{lk['val_loglik_gain']:+.4g} (p = {lk['p_val_loglik']:.2g})"
                             + (", NOT converged" if lk.get("converged") is False else ""))
                est = [f"{e['name']} = {e['estimate']:.4g}" + (f" ± {e['se']:.2g}" if e.get("status") == "ok"
                                                               else f" ({e.get('status')})") + " (SI)"
                       for e in lk.get("estimates") or []]
                if est:
                    lines.append("      estimates: " + ", ".join(est))
            if r["caution"]:
                lines.append("      " + _caution(r["caution"]))
            if r.get("separated"):
                lines.append("      to first order the same as " + r["separated"]
                             + ", but the held-out run separates them")
        lines += ["  " + ln for ln in self.verdict_lines()]
        lines += ["  " + ln for ln in self.uncertainty_lines()]
        if self.extended_file:
            lines.append(f"  extended network written to {self.extended_file}")
        if self.model_dir:
            what = "extended model" if self.accepted else "model (the network at the baseline fit)"
            held = (((self.model.meta if self.model is not None else {}).get("diagnosis") or {}).get("held_out")
                    or {}).get("data")
            how = (f"`tnnc evaluate {self.model_dir} {' '.join(held)}` gives the held-out numbers above"
                   if isinstance(held, list) and held else
                   "the held-out numbers above are its free run over each training file, scored on the last 30 %")
            lines.append(f"  {what} written to {self.model_dir} ({how})")
        return "\n".join(lines)

    def uncertainty_lines(self) -> list[str]:
        """The extended model's values with standard errors and what the sensors cannot tell apart
        (:mod:`tnn_dsl.doctor.uncertainty`), SI units; nothing when no finding was accepted."""
        mc = self.extended.get("mlp_check") or {}
        return uncertainty_text(self.extended.get("uncertainty"), self.extended.get("form") == "mlp" and (
            mc.get("linear") or {}).get("stopped") == "the doctor's fit")

    def verdict_lines(self) -> list[str]:
        """The verdict, the linear-or-MLP choice, the gain and what is left, one line each (summary and notebook
        view)."""
        lines = [f"verdict: {self.verdict}"]
        mlp = self.mlp_text()
        if mlp:
            lines.append(f"linear or MLP: {mlp}")
        if self.accepted:
            g = self.gain
            lines.append(f"gain: held-out MAE {g['val_mae_before']:.4g} → {g['val_mae_after']:.4g} K "
                         f"(÷{g['val_mae_ratio']:.2f}), max {g['val_max_before']:.4g} → {g['val_max_after']:.4g} K")
        lk0, lk1 = self.baseline.get("likelihood"), self.extended.get("likelihood")
        if lk0 and lk1 and self.accepted:
            r0, r1 = lk0.get("one_step_rms_val"), lk1.get("one_step_rms_val")
            lines.append(f"likelihood: log L {lk0['loglik']:.2f} → {lk1['loglik']:.2f} (k {lk0['k']} → {lk1['k']})"
                         + (f", held-out one-step RMS {r0:.4g} → {r1:.4g} K" if r0 is not None and r1 is not None
                            else ""))
        lines.append(f"what is left: {self.left}")
        return lines

    def _repr_html_(self) -> str:
        """The notebook view: :meth:`summary` as tables (``<pre>`` of the summary should that fail)."""
        return safe_repr_html(self._html, self.summary, f"Diagnosis({self.network!r})")

    def _html(self) -> str:
        b = self.baseline
        parts = [html_table(["held-out MAE K", "held-out max K", "train MAE K"],
                            [[b["val_mae"], b["val_max"], b["train_mae"]]], numeric=[True] * 3),
                 html_table(["sensor", "residual", "Ljung–Box p", "noise σ K"],
                            [[r["sensor"], "white" if r["white"] else "NOT white", r["ljung_box_p"], r["sigma"]]
                             for r in self.residual_rows()], numeric=[False, False, True, True], digits=3)]
        if self.scores:
            parts.append(html_table(["#", "score test: best candidates", "k", "R²", "p"],
                                    [[s["rank"], s["words"], s["k"], s["r2"], s["p"]] for s in self.scores[:5]],
                                    numeric=[True, False, True, True, True], digits=3))
        rows = self.finding_rows()
        if rows:
            parts.append(html_table(
                ["round", "cause", "depends on", "held-out MAE before K", "after K", "p-value", "N_eff",
                 "accepted", "clause", "reason"],
                [[r["round"], r["cause"], ", ".join(r["dependence"]), r["mae_before"], r["mae_after"], r["p_value"],
                  round(float(r["n_eff"])), "ACCEPTED" if r["accepted"] else "rejected", r["clause"], r["reason"]]
                 for r in rows],
                numeric=[True, False, False, True, True, True, True, False, False, False]))
        lines = self.verdict_lines()
        parts.append(html_list(lines))
        warnings = [f"{r['cause']}: {_caution(r['caution'])}" for r in rows if r["caution"]]
        if warnings:
            parts.append("<b>warnings</b>" + html_list(warnings))
        clauses = list(self.extended.get("clauses") or [])
        if clauses:
            where = f" (written to {self.extended_file})" if self.extended_file else ""
            parts.append(f"<b>{html.escape('extension' + where)}</b>"
                         + pre("\n".join(clauses)))
        return view(f"model doctor: {self.network}", *parts)
