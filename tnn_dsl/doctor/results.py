"""What the model doctor returns: every properly fitted candidate (:class:`Finding`) and the diagnosis
(:class:`Diagnosis`: baseline, residual analysis, score table, findings, the extension and its gain), with
its JSON document and terminal summary."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..analysis import residuals as R
from ..core import to_jsonable

__all__ = ["Finding", "Diagnosis"]


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
            "question": "free-run simulation (output error from the initial steady state)",
            "baseline": self.baseline,
            "residuals": {k: v for k, v in self.residuals.to_dict().items() if k != "dependence"},
            "scores": self.scores[:30],
            "findings": [f.to_dict() for f in self.findings],
            "extended": {**self.extended, "file": self.extended_file},
            "gain": self.gain,
            "verdict": self.verdict,
            "left": self.left,
            "diff": self.diff,
            "timings": self.timings,
        })

    def summary(self) -> str:
        """The terminal summary."""
        b = self.baseline
        lines = [f"model doctor: {self.network}",
                 f"  baseline (held-out): MAE {b['val_mae']:.4g} K, max {b['val_max']:.4g} K"
                 f"  (train MAE {b['train_mae']:.4g} K)"]
        for s, st in self.residuals.whiteness.items():
            lines.append(f"  residual {s}: {'white' if st.get('white') else 'NOT white'}"
                         f" (Ljung–Box p = {st.get('ljung_box_p', 1):.2g}), noise σ ≈ {self.residuals.sigma[s]:.3g} K")
        if self.scores:
            lines.append("  score test, best candidates:")
            for s in self.scores[:5]:
                lines.append(f"    {s['rank']:>2}. {s['words']:<60} k={s['k']}  R²={s['r2']:.3f}  p={s['p']:.2g}")
        for f in self.findings:
            mark = "ACCEPTED" if f.accepted else "rejected"
            lines.append(f"  [{mark}] round {f.round}: {f.words}")
            lines.append(f"      clause: {f.clause}")
            ev = f.evidence
            lines.append(f"      held-out MAE {ev.get('val_mae_before', float('nan')):.4g} → {f.val_mae_after:.4g} K"
                         f", held-out test p = {ev.get('p_value', float('nan')):.2g} (N_eff = {ev.get('n_eff', 0):.0f})"
                         + (f"; {ev['reason']}" if ev.get("reason") else ""))
            if f.accepted and ev.get("indistinguishable_from"):
                tw = ev["indistinguishable_from"]
                lines.append("      caution: to first order the data cannot tell this apart from "
                             + "; ".join(f"{t['candidate']} (|cos| = {t['cos']:.3f})" for t in tw[:3])
                             + " — the named element is the best-scoring, most physical choice; the others"
                             " could compensate for it (not separately identifiable from these sensors)")
        lines.append("  verdict: " + self.verdict)
        mc = self.extended.get("mlp_check")
        if mc and "linear" in mc:
            lines.append(f"  linear or MLP: trained both (held-out MAE linear {mc['linear']['val_mae']:.4g} K, "
                         f"MLP {mc['mlp']['val_mae']:.4g} K): {mc['choice']} — {mc['reason']}")
        elif mc:
            lines.append(f"  linear or MLP: {mc['reason']}")
        if self.accepted:
            g = self.gain
            lines.append(f"  gain: held-out MAE {g['val_mae_before']:.4g} → {g['val_mae_after']:.4g} K "
                         f"(÷{g['val_mae_ratio']:.2f}), max {g['val_max_before']:.4g} → {g['val_max_after']:.4g} K")
        lines.append("  what is left: " + self.left)
        if self.extended_file:
            lines.append(f"  extended network written to {self.extended_file}")
        return "\n".join(lines)
