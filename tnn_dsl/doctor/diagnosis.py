"""``tnn_dsl.diagnose``: the model doctor.

Given a network and measured data it answers, in one call: where the simulation is wrong, why (a cause
named in words and as ``.thn`` structure), what the extended model is, and how much better it is on data
it was not fitted on. The question answered is the *simulation* one ("is my free-run simulation right?",
output error from the initial steady state), not the one-step-predictor one of Kalman-filter methods.

Steps (see docs/architecture.md, "Diagnosis"):

1. **Fit** the nominal model's free parameters on the training rows by Levenberg–Marquardt (Gauss–Newton
   with Marquardt damping on forward-mode Jacobians; positive parameters in log space, bounds respected).
   Least squares is the statistic's own estimator; the Jacobians are reused by the score test. Free
   constants that are not identifiable as written (tclab.thn: heater gains, conductances and capacities
   scale together) leave a flat, curved valley where the damped step points the right way but is short:
   after an accepted step the fit goes on along it (2δ, 4δ, … up to 64δ, one simulation each, no
   Jacobian) while the training SSE keeps dropping. On the Kuntz–Rawlings TCLab file the nominal fit
   reaches the training least-squares optimum (the same SSE from the file's values and from the trainer's
   fitted values); its held-out MAE is that of the least-squares fit of the nominal structure, which is
   not the trainer's number (the trainer validates the tail from its measured state and keeps its
   best-*validation* iterate). Candidate fits (step 4) run until the SSE drops by less than 1e-4
   relatively, at most ``FIT_ITER`` iterations.
2. **Residuals** on the held-out rows (``val`` files, else the last 30 % of each training file, simulated
   as a free run from the file's start): per-sensor MAE/max/bias, binned residual against inputs, states
   and time, whiteness (Ljung–Box, cumulated periodogram), noise σ (``_residuals``).
3. **Candidates** from the IR (``_candidates``), all exactly null, in ONE extended network, plus structural
   ones (a sensor lag, a missing thermal mass on a link, a heat capacity behind a source) that are not. **Score test** at the fitted point: Jacobian ``J`` of the training
   outputs w.r.t. every candidate column and every free column. Candidates enter as extra heat flows per
   node (``C·∂rhs_big/∂θ`` at the current trajectory, pointwise) pushed through ONE batched forward-mode
   derivative of the current network's simulation w.r.t. forcing inputs (``_with_forcing``), plus direct
   output terms; a sensor lag's column is ``−dT_node/dt``. The free directions are projected out
   (``P = I − J_f J_f⁺``) and for candidate c
   ``S_c = N_eff · rᵀ Ĵ_c (Ĵ_cᵀĴ_c)⁻¹ Ĵ_cᵀ r / rᵀr`` (the LM statistic ``N·R²`` with the sample size corrected
   for residual autocorrelation), p-value from χ²(k_c); ranked on the noise's own scale (``_score_stats``).
   The Gauss–Newton step gives the initial value.
4. **Fit the best few** distinct candidates (``_shortlist``; free + candidate columns, LM from the GN step,
   successive halving) and measure on held-out rows. Accept the best only if it pays: a Diebold–Mariano
   test on the held-out squared errors (Newey–West variance for the autocorrelation, an AIC charge for the
   k extra parameters; p < 0.05) and MAE at least 10 % lower. Compensation guard (thesis §6.2.4): among
   fitted candidates whose held-out SSE is within noise of the best, the one with fewer parameters, then the
   more physical placement wins (a parameter of an element beats a heat load at a node, a parameter the
   user already declared uncertain beats one they did not; see ``_place``); runners-up are reported.
5. **Extend**: the input text plus the accepted ``learn``/link/radiation/offset clauses, re-loaded to check
   it is valid; the gain on held-out data. Repeat 3–5 (forward selection) until nothing pays.
"""

from __future__ import annotations

import math
import os
import re
import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy import stats
from scipy.signal import lfilter

from ..analysis import held_out_test as _held_out_test
from ..analysis import residuals as R
from ..compiler import backend_of
from ..core import THN, Diagnostic, TnnError, check_output, to_jsonable, write_text_atomic
from ..ir import POSITIVE_ROLES, Input, Network, Param
from .candidates import (
    STRUCTURAL_KINDS,
    Candidate,
    Extended,
    apply_structural,
    build_extended,
    structural_candidates,
    var_label,
)
from .selection import CLOSE_RATIO, MIN_GAIN, P_ACCEPT

__all__ = ["diagnose", "Diagnosis", "Finding"]

# placement preference for the compensation guard: lower is more physical/specific
_PLACEMENT = {
    "param_dependence": 0, "wrong_constant": 0, "missing_link": 1, "radiation": 1, "sensor_offset": 2,
    "heat_load": 3, "unused_column": 3, "sensor_lag": 2, "thermal_mass": 1, "source_mass": 1,
}


def _place(c: Candidate) -> float:
    """Placement preference of a candidate (lower is more physical/specific): its kind's, half a step better
    when it extends a function the user already declared uncertain (a ``learn`` clause of the input file:
    gray-box modelling puts what is not known there first)."""
    return _PLACEMENT.get(c.kind, 3) - (0.5 if c.element.get("learned") else 0.0)


FIT_ITER = 80  # Levenberg–Marquardt iterations (at most) of a candidate's proper fit (it stops when the SSE drops < tol)
FIT_ITER_FIRST = 4  # ... all shortlisted candidates get this many first; the FIT_CONTINUE best go on
FIT_CONTINUE = 3
MIN_R2 = 0.02  # a candidate whose linearised fit explains less of the training residual is not fitted


# ---------------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# The fitting engine: one compiled model, columns, Jacobians, Levenberg–Marquardt
# ---------------------------------------------------------------------------------------------


@dataclass
class _Col:
    key: str
    index: int
    log: bool  # value = base·exp(θ) (positive parameter) else base + θ
    lower: float | None = None
    upper: float | None = None


class _Engine:
    """A compiled model over a set of experiments with train/val row masks.

    ``cols`` is the fixed list of scalar parameters the engine may move (free + candidate columns);
    ``params`` the current numpy parameter dict. Jacobians are taken w.r.t. θ at 0 where the column's
    value is ``base·exp(θ)`` (log) or ``base + θ``."""

    def __init__(self, net: Network, experiments, train_mask, val_mask, backend: str, cols: list[_Col],
                 params: dict[str, np.ndarray] | None = None, model=None, n_force: int = 0):
        from ..compiler import compile as _compile

        self.net = net
        self.backend = backend
        self.model = model if model is not None else _compile(net, backend=backend, dtype="float64")
        self.exps = experiments
        self.n_force = n_force  # trailing forcing inputs (W, one per node; zero in every simulation)
        # the experiments holding training rows come first: the score test simulates only those
        has_train = [bool(m.any()) for m in np.split(train_mask, np.cumsum([e.n_steps for e in experiments])[:-1])]
        self.n_score_exps = max(i + 1 for i, h in enumerate(has_train) if h) if any(has_train) else len(experiments)
        self.cols = cols
        self.col_index = {(c.key, c.index): i for i, c in enumerate(cols)}
        self.params = params if params is not None else {
            k: np.array(v, dtype=float) for k, v in self.model.to_numpy(self.model.init_params(seed=0)).items()}
        self.y = np.concatenate([e.outputs for e in experiments], axis=0)  # (N, n_out)
        ok = np.isfinite(self.y)
        self.train_mask = train_mask & ok
        self.val_mask = val_mask & ok
        self.train_idx = np.flatnonzero(self.train_mask.ravel())
        self.val_idx = np.flatnonzero(self.val_mask.ravel())
        # scatter matrices: for each key, (size, n_cols) for log and lin columns
        self.keys = sorted({c.key for c in cols})
        self._build_scatter()
        self._setup_backend()

    # -- parameter plumbing ---------------------------------------------------------------------

    def _build_scatter(self):
        n = len(self.cols)
        self.m_lin, self.m_log = {}, {}
        for k in self.keys:
            size = int(np.asarray(self.params[k]).size)
            a, b = np.zeros((size, n)), np.zeros((size, n))
            for j, c in enumerate(self.cols):
                if c.key == k:
                    (b if c.log else a)[c.index, j] = 1.0
            self.m_lin[k], self.m_log[k] = a, b

    def _setup_backend(self):
        model = self.model
        keys = self.keys
        exps = self.exps
        # The pure pieces, written once against the model's array namespace; only the autodiff
        # transforms (jvp, vmap, jit) below are per backend.
        xp = model.xp
        nf = self.n_force
        u_list = [xp.asarray(_pad(e.inputs, nf)) for e in exps]
        dts = [float(e.dt) for e in exps]
        m_lin = {k: xp.asarray(v) for k, v in self.m_lin.items()}
        m_log = {k: xp.asarray(v) for k, v in self.m_log.items()}
        n_sc = self.n_score_exps
        lens = [e.n_steps for e in exps[:n_sc]]

        def with_theta(base, theta):
            p = dict(base)
            for k in keys:
                b = base[k]
                flat = b.reshape(-1) * xp.exp(m_log[k] @ theta) + m_lin[k] @ theta
                p[k] = flat.reshape(b.shape)
            return p

        def simulate(p):
            ys, xs = [], []
            for u, dt in zip(u_list, dts):
                st, y = model.rollout(p, model.steady_state(p, u[0]), u, dt)
                ys.append(y)
                xs.append(st)
            return xp.concat(ys, 0), xp.concat(xs, 0)

        def out_flat(base, theta, idx):
            """Outputs at ``idx`` (training rows: only the files holding them are simulated)."""
            p = with_theta(base, theta)
            ys = []
            for u, dt in zip(u_list[:n_sc], dts[:n_sc]):
                _, y = model.rollout(p, model.steady_state(p, u[0]), u, dt)
                ys.append(y)
            return xp.concat(ys, 0).reshape(-1)[idx]

        def out_forced(base, theta, F, idx):
            """Outputs with the forcing heat flows F (N_score, n_force) W added (training files only)."""
            p = with_theta(base, theta)
            ys, s0 = [], 0
            for u, dt, n in zip(u_list[:n_sc], dts[:n_sc], lens):
                uu = xp.concat([u[:, : u.shape[1] - nf], F[s0: s0 + n]], axis=1)
                s0 += n
                _, y = model.rollout(p, model.steady_state(p, uu[0]), uu, dt)
                ys.append(y)
            return xp.concat(ys, 0).reshape(-1)[idx]

        B = backend_of(model)
        zeros = lambda n: B.zeros(n)  # noqa: E731

        def jac_chunk(base, tangents, idx):
            """∂outputs[idx]/∂θ along each row of ``tangents`` (m, n_θ) → (m, len(idx))."""
            return B.batched_jvp(lambda th: out_flat(base, th, idx), (zeros(tangents.shape[1]),), (tangents,))

        def jac_forced(base, tan_theta, tan_F, idx):
            F0 = B.xp.zeros(tuple(tan_F.shape[1:]), dtype=B.dtype)
            return B.batched_jvp(lambda th, F: out_forced(base, th, F, idx), (zeros(tan_theta.shape[1]), F0),
                                 (tan_theta, tan_F))

        def point(base, tangents, X, U):
            """∂rhs/∂θ and ∂outputs/∂θ at given states/inputs (no time loop): (m, N, ns), (m, N, n_out)."""
            def f(th):
                p = with_theta(base, th)
                return model.rhs(p, X, U), model.outputs(p, X, U)

            return B.batched_jvp(f, (zeros(tangents.shape[1]),), (tangents,))

        def inv_cap(base, X, U):
            """∂rhs/∂(forcing) with every forcing input at 1 W: 1/C per node state (N, ns)."""
            dU = xp.concat([B.xp.zeros(tuple(U.shape[:-1]) + (U.shape[-1] - nf,), dtype=B.dtype),
                            B.xp.ones(tuple(U.shape[:-1]) + (nf,), dtype=B.dtype)], -1)
            return B.jvp(lambda uu: model.rhs(base, X, uu), (U,), (dU,))[1]

        jac_j, jac_forced_j = B.jit(jac_chunk), B.jit(jac_forced)
        self._sim = B.jit(B.no_grad(simulate))
        self._jac = lambda base, tangents, idx: jac_j(base, tangents, B.asarray(idx))  # noqa: E731
        self._jac_forced = lambda base, a, F, idx: jac_forced_j(base, a, F, B.asarray(idx))  # noqa: E731
        self._point = B.jit(point)
        self._inv_cap = B.jit(inv_cap)
        self._to = B.tree
        self._np = B.numpy

    # -- evaluation -----------------------------------------------------------------------------

    def simulate(self, params=None):
        """Outputs (N, n_out) K and states (N, n_states) K for ``params`` (default: current)."""
        y, x = self._sim(self._to(self.params if params is None else params))
        return np.asarray(self._np(y)), np.asarray(self._np(x))

    def residual(self, params=None):
        ym, _ = self.simulate(params)
        return self.y - ym  # (N, n_out), NaN where unmeasured

    def jacobian(self, active: list[int], chunk: int = 16) -> np.ndarray:
        """∂ y_model[train rows] / ∂θ_active, shape (n_train, len(active)). Directions go in batches of
        ``chunk`` forward-mode tangents (one compiled shape: 8 for small sets, else ``chunk``)."""
        base = self._to(self.params)
        n = len(self.cols)
        out = []
        size = 8 if len(active) <= 8 else chunk
        for s in range(0, len(active), size):
            part = active[s: s + size]
            tan = np.zeros((size, n))
            for r, j in enumerate(part):
                tan[r, j] = 1.0
            tan_b = self._to({"t": tan})["t"]
            jc = np.asarray(self._np(self._jac(base, tan_b, self.train_idx)))
            out.append(jc[: len(part)].T)
        return np.concatenate(out, axis=1) if out else np.zeros((self.train_idx.size, 0))

    @property
    def n_score_rows(self) -> int:
        """Rows of the experiments the score test simulates (those holding training rows)."""
        return int(sum(e.n_steps for e in self.exps[: self.n_score_exps]))

    def forced_jacobian(self, active: list[int], forcing: np.ndarray | None = None, chunk: int = 32) -> np.ndarray:
        """∂ y_model[train rows] w.r.t. the columns ``active`` (first block) and w.r.t. the forcing heat-flow
        time series ``forcing (m, N_score, n_force)`` W (second block): shape (n_train, len(active) + m).
        One compiled shape: ``chunk`` tangents per call."""
        base = self._to(self.params)
        n = len(self.cols)
        nsr, nf = self.n_score_rows, self.n_force
        m = 0 if forcing is None else forcing.shape[0]
        total = len(active) + m
        out = []
        for s0 in range(0, total, chunk):
            ta = np.zeros((chunk, n))
            tf_ = np.zeros((chunk, nsr, nf))
            for r in range(chunk):
                j = s0 + r
                if j >= total:
                    break
                if j < len(active):
                    ta[r, active[j]] = 1.0
                else:
                    tf_[r] = forcing[j - len(active)]
            t = self._to({"a": ta, "f": tf_})
            jc = np.asarray(self._np(self._jac_forced(base, t["a"], t["f"], self.train_idx)))
            out.append(jc[: min(chunk, total - s0)].T)
        return np.concatenate(out, axis=1) if out else np.zeros((self.train_idx.size, 0))

    def point_derivs(self, active: list[int], X: np.ndarray, U: np.ndarray, chunk: int = 32):
        """(∂rhs/∂θ (m, N, ns), ∂outputs/∂θ (m, N, n_out)) for the columns ``active`` at states ``X (N, ns)`` K
        and inputs ``U (N, n_in)`` SI (vectorised over time, no simulation)."""
        base = self._to(self.params)
        n = len(self.cols)
        t = self._to({"X": X, "U": _pad(U, self.n_force)})
        d_rhs, d_out = [], []
        for s0 in range(0, len(active), chunk):
            ta = np.zeros((chunk, n))
            part = active[s0: s0 + chunk]
            for r, j in enumerate(part):
                ta[r, j] = 1.0
            a, b = self._point(base, self._to({"a": ta})["a"], t["X"], t["U"])
            d_rhs.append(np.asarray(self._np(a))[: len(part)])
            d_out.append(np.asarray(self._np(b))[: len(part)])
        ns, no = X.shape[1], len(self.model.output_names)
        return (np.concatenate(d_rhs) if d_rhs else np.zeros((0, X.shape[0], ns)),
                np.concatenate(d_out) if d_out else np.zeros((0, X.shape[0], no)))

    def rates(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """``dT/dt (N, ns)`` K/s at states ``X`` and inputs ``U`` (current parameters, forcing 0)."""
        t = self._to({"X": X, "U": _pad(U, self.n_force)})
        return np.asarray(self._np(self.model.rhs(self._to(self.params), t["X"], t["U"])))

    def inv_capacity(self, X: np.ndarray, U: np.ndarray) -> np.ndarray:
        """``∂(dT/dt)/∂Q`` for a heat flow into each node's own forcing input: ``1/C`` (N, ns) 1/(J/K); 0 for
        lag states."""
        t = self._to({"X": X, "U": _pad(U, self.n_force)})
        return np.asarray(self._np(self._inv_cap(self._to(self.params), t["X"], t["U"])))

    def apply(self, params, active: list[int], delta: np.ndarray, trust: bool = True) -> dict[str, np.ndarray]:
        """New numpy params after the step ``delta`` on columns ``active`` (bounds clipped; with ``trust``,
        log-parameters move by at most e^±2 and learned weights by at most ±1 per step)."""
        p = {k: np.array(v, dtype=float, copy=True) for k, v in params.items()}
        for j, d in zip(active, delta):
            c = self.cols[j]
            flat = p[c.key].reshape(-1)
            if c.log:
                v = flat[c.index] * math.exp(float(np.clip(d, -2, 2) if trust else np.clip(d, -30, 30)))
            else:  # learned weights act on normalised inputs: at most ±1 per step (a trust region)
                v = flat[c.index] + (float(np.clip(d, -1, 1)) if trust and c.key.rsplit(".", 1)[-1][:1] in "Wbc"
                                     and "." in c.key else d)
            if c.lower is not None:
                v = max(v, c.lower)
            if c.upper is not None:
                v = min(v, c.upper)
            flat[c.index] = v
            p[c.key] = flat.reshape(p[c.key].shape)
        return p

    def sse(self, params=None, which="train") -> float:
        e = self.residual(params).ravel()
        idx = self.train_idx if which == "train" else self.val_idx
        v = e[idx]
        if not np.all(np.isfinite(v)):
            return math.inf
        with np.errstate(over="ignore"):  # a trial step far along a valley may blow a simulation up: inf
            return float(np.dot(v, v))

    def fit(self, active: list[int], max_iter: int = 25, init_delta: np.ndarray | None = None,
            deadline: float | None = None, tol: float = 1e-7, extrapolate: bool = True) -> dict:
        """Levenberg–Marquardt on the training rows over columns ``active`` (updates ``self.params``)."""
        params = self.params
        if init_delta is not None and np.any(init_delta):
            # the score test's Gauss–Newton step, whole (it is exact for a candidate linear in its
            # parameters), else inside the trust region; kept only if it helps
            best = self.sse(params)
            for trust in (False, True):
                trial = self.apply(params, active, init_delta, trust=trust)
                sse_t = self.sse(trial)
                if sse_t < best:
                    params, best = trial, sse_t
                    break
        cur = self.sse(params)
        lam = 1e-3
        it = 0
        if not active:
            self.params = params
            return {"sse": cur, "iterations": 0}
        for it in range(1, max_iter + 1):
            self.params = params
            r = self.residual(params).ravel()[self.train_idx]
            J = self.jacobian(active)
            A = J.T @ J
            g = J.T @ r
            d = np.sqrt(np.maximum(np.diag(A), 1e-300))
            improved = False
            for _ in range(12):
                M = A + lam * np.diag(np.diag(A)) + 1e-12 * np.trace(A) / max(len(active), 1) * np.eye(len(active))
                try:
                    delta = np.linalg.solve(M, g)
                except np.linalg.LinAlgError:
                    delta = np.linalg.lstsq(M, g, rcond=None)[0]
                trial = self.apply(params, active, delta)
                new = self.sse(trial)
                if new < cur:
                    rel = (cur - new) / max(cur, 1e-300)
                    # flat valleys (free constants that are not identifiable as written, a conductance
                    # drifting towards 0 in log space): the damped step is right in direction but short, so
                    # go on along it (2δ, 4δ, ...) while the SSE keeps dropping; one simulation per try
                    mult = 1.0
                    while extrapolate and mult < 64:
                        t2 = self.apply(params, active, 2 * mult * delta)
                        n2 = self.sse(t2)
                        if not n2 < new:
                            break
                        trial, new, mult = t2, n2, 2 * mult
                    rel = (cur - new) / max(cur, 1e-300)
                    params, cur = trial, new
                    lam = max(lam / 4, 1e-9)
                    improved = True
                    break
                lam *= 6
            del d
            if not improved or rel < tol or (deadline is not None and _time.monotonic() > deadline):
                break
        self.params = params
        return {"sse": cur, "iterations": it}


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def _pad(u: np.ndarray, n: int) -> np.ndarray:
    """Inputs ``(N, n_in)`` with ``n`` zero columns appended (the forcing inputs)."""
    u = np.asarray(u, dtype=float)
    return np.concatenate([u, np.zeros(u.shape[:-1] + (n,))], axis=-1) if n else u


FORCE_PREFIX = "dxF_"


def _with_forcing(net: Network) -> Network:
    """``net`` plus one heat source per node driven by a new input ``dxF_<node>`` (W). With those inputs at 0
    it is exactly ``net``; the score test differentiates the simulation w.r.t. them (the response to any
    candidate's extra heat flow through the same linearised dynamics)."""
    from ..ir import Ref, Source

    w = {"kg": 1.0, "m": 2.0, "s": -3.0}
    names = set(net.input_names) | set(net.param_names) | {s.name for s in net.sources}
    inputs, params, sources = list(net.inputs), list(net.params), list(net.sources)
    for n in net.node_names:
        base = FORCE_PREFIX + re.sub(r"[^A-Za-z0-9_]", "_", n)
        name = base
        while name in names:
            name += "_"
        names.add(name)
        inputs.append(Input(name=name, column=name, dim=w, unit="W"))
        params.append(Param(name=name + ".q", expr=Ref(name=name, kind="input"), dim=w, unit="W", role="heat_flow",
                            owner=f"source {name}"))
        sources.append(Source(name=name, node=n, value=name + ".q"))
    return net.model_copy(update={"inputs": inputs, "params": params, "sources": sources}, deep=True)


def _paths_of(data) -> list:
    """The file paths among data arguments (paths or :class:`Experiment` objects)."""
    items = data if isinstance(data, (list, tuple)) else [data]
    return [x if isinstance(x, (str, os.PathLike)) else getattr(x, "path", None) for x in items if x is not None]


def _load(net_or_path) -> tuple[Network, str | None, str]:
    """Network, its file path (or None) and its source text."""
    from ..lang import load

    if isinstance(net_or_path, Network):
        path = net_or_path.source_files[0] if net_or_path.source_files else None
        text = open(path, encoding="utf-8").read() if path and os.path.isfile(path) else ""
        return net_or_path, path, text
    path = os.fspath(net_or_path)
    net = load(path)
    return net, path, open(path, encoding="utf-8").read()


def _unused_columns(net: Network, experiments) -> list[tuple[str, str]]:
    """(input name, column) for numeric data columns present in every training file that the network does
    not read (not the time column, not an input, not a sensor)."""
    from ..data import read_table

    used = {i.column for i in net.inputs} | {s.column for s in net.sensors}
    # a column that reads a modelled node's temperature (``T_hx1``, ``hx1``) is a state, not a driver
    node_cols = {n.lower() for n in net.node_names} | {f"t_{n}".lower() for n in net.node_names}
    common: list[str] | None = None
    for e in experiments:
        try:
            tab = read_table(e.path)
        except Exception:  # noqa: BLE001 - the file was read before; a re-read problem just skips this
            return []
        cols = []
        for j, c in enumerate(tab.columns):
            if not c or c in used or c == e.time_column or c.lower() in node_cols:
                continue
            vals = tab.cells.get(j)
            try:
                arr = np.asarray(vals, dtype=float)
            except (TypeError, ValueError):
                continue
            if arr.size and np.all(np.isfinite(arr)) and np.ptp(arr) > 0:
                cols.append(c)
        common = cols if common is None else [c for c in common if c in cols]
    taken = set(net.input_names) | set(net.node_names) | set(net.param_names) | set(net.boundary_names)
    out = []
    for c in common or []:
        name = re.sub(r"[^A-Za-z0-9_]", "_", c)
        if not re.match(r"[A-Za-z_]", name):
            name = "c_" + name
        while name in taken:
            name += "_"
        taken.add(name)
        out.append((name, c))
    return out


def _split_masks(experiments, val_experiments, frac: float = 0.7):
    """Experiments to simulate and (train, val) row masks (N, n_out) over their concatenation."""
    exps = list(experiments) + list(val_experiments)
    n_out = exps[0].outputs.shape[1]
    tm, vm = [], []
    for i, e in enumerate(exps):
        n = e.n_steps
        t = np.zeros((n, n_out), bool)
        v = np.zeros((n, n_out), bool)
        if val_experiments:
            (t if i < len(experiments) else v)[:] = True
        else:
            cut = int(round(frac * n))
            t[:cut] = True
            v[cut:] = True
        tm.append(t)
        vm.append(v)
    return exps, np.concatenate(tm), np.concatenate(vm)


def normalisation_stats(model, params, fn_vars, net, inputs, states, rows, dt: float = 1.0, state_names=None):
    """Each learned function's input normalisation from the training rows of the nominal run, as the
    trainer sets it (``x_mean`` the mid-range, ``x_scale`` the half-range, floors 0.5 K for temperatures),
    and its output scale: ``|nominal|`` for a parameter, the node's typical heat throughput ``C·rms(dT/dt)``
    for a heat load (``dt`` the sample interval, s, so dT/dt is per second). Returns the updated numpy
    params."""
    p = dict(params)
    in_idx = {n: i for i, n in enumerate(net.input_names)}
    st_idx = {n: i for i, n in enumerate(state_names or model.state_names)}  # columns of ``states``
    caps = {n.name: n.capacitance for n in net.nodes}
    for fn in net.learned:
        if f"{fn.name}.x_mean" not in p:
            continue
        vars_ = [(li.kind, li.name) for li in fn.inputs]
        if vars_:
            xs = []
            for kind, name in vars_:
                if kind == "input" and name in in_idx:
                    xs.append(inputs[rows, in_idx[name]])
                elif name in st_idx:
                    xs.append(states[rows, st_idx[name]])
                else:
                    xs.append(np.zeros(1))
            mean = np.array([(x.max() + x.min()) / 2 for x in xs])
            half = np.array([(x.max() - x.min()) / 2 for x in xs])
            floor = np.maximum(1e-3 * np.abs(mean), 1e-9)
            for i, (kind, _) in enumerate(vars_):
                if kind == "node":
                    floor[i] = max(floor[i], 0.5)
            p[f"{fn.name}.x_mean"] = mean.reshape(np.shape(p[f"{fn.name}.x_mean"]))
            p[f"{fn.name}.x_scale"] = np.maximum(half, floor).reshape(np.shape(p[f"{fn.name}.x_scale"]))
        ysc = []
        for t in fn.targets:
            if t.kind == "param":
                try:
                    v = net.param(t.name).value
                except KeyError:
                    v = None
                ysc.append(abs(v) if v else 1.0)
            elif t.kind == "heat_load" and t.name in st_idx and t.name in caps:
                try:
                    C = net.param(caps[t.name]).value
                except KeyError:
                    C = None
                x = states[rows, st_idx[t.name]]
                spacing = float(np.median(np.diff(np.flatnonzero(rows)))) if rows.sum() > 1 else 1.0
                d = np.diff(x) / max(spacing * float(dt), 1e-12)
                ysc.append(max(float(C * np.sqrt(np.mean(d ** 2))), 1e-3) if C and d.size else 1.0)
            else:
                ysc.append(1.0)
        k = f"{fn.name}.y_scale"
        if k in p and np.size(p[k]) == len(ysc):
            p[k] = np.asarray(ysc, dtype=float).reshape(np.shape(p[k]))
    return p


def _fmt(x: float, digits: int = 3) -> str:
    if x == 0 or not math.isfinite(x):
        return "0" if x == 0 else str(x)
    return f"{x:.{digits}g}"


# ---------------------------------------------------------------------------------------------
# diagnose
# ---------------------------------------------------------------------------------------------


def diagnose(net_or_path, train, val=None, budget_s: float | None = None, backend: str = "jax",
             progress: Callable[[str], None] | None = None, *, top: int = 5, max_rounds: int = 4,
             output: str | None = None, kinds: tuple[str, ...] | None = None, mlp_check: bool = True,
             mlp_time: float = 60.0, force: bool = False) -> Diagnosis:
    """Diagnose ``net_or_path`` (a ``.thn`` path or a :class:`Network`) on measured data.

    Parameters
    ----------
    train : path(s) or list of :class:`Experiment`
        Training data; the fit and the score test use it.
    val : path(s) or list of Experiment, optional
        Held-out data; default the last 30 % of each training file (a free run over the whole file,
        measured on the tail).
    budget_s : float, optional
        Wall-clock budget in seconds; the forward selection stops early when it is spent.
    backend : "jax" | "torch"
    progress : callable(str), optional
        Called with one line per step (the CLI's progress display).
    top : int
        How many of the best-scoring distinct candidates are fitted properly each round.
    output : str, optional
        Where to write the extended ``.thn`` (default: not written; the text is in the result). Checked
        before any work: never an input, never an existing file other than a ``.thn`` unless ``force``.
    mlp_check : bool
        When the extended model's held-out residual is still not white, train the extension with its
        ``linear`` clauses and with them as MLPs and keep the MLP only if it pays on held-out data
        (:mod:`tnn_dsl.doctor.mlp_check`); ``mlp_time`` s of training for each (skipped when the budget is short).

    Returns
    -------
    Diagnosis
    """
    from ..data import Experiment, read_data

    t_start = _time.monotonic()
    deadline = None if budget_s is None else t_start + float(budget_s)
    say = progress or (lambda s: None)
    timings: dict[str, float] = {}

    def lap(name, t0):
        timings[name] = round(_time.monotonic() - t0, 3)

    net, path, text = _load(net_or_path)
    if output:
        check_output(output, THN, inputs=[path, *net.source_files, *_paths_of(train), *_paths_of(val)],
                     force=force)
    if backend not in ("jax", "torch"):
        raise TnnError(Diagnostic(f"unknown backend {backend!r}", hint="use --backend jax or --backend torch"))

    def read(x, n):
        if x is None:
            return []
        if isinstance(x, Experiment):
            return [x]
        if isinstance(x, (list, tuple)) and x and all(isinstance(e, Experiment) for e in x):
            return list(x)
        return read_data(n, x)

    train_exps = read(train, net)
    val_exps = read(val, net)
    if not train_exps:
        raise TnnError(Diagnostic("no training data given", hint="pass at least one CSV file"))
    train_paths = [e.path for e in train_exps]
    val_paths = [e.path for e in val_exps]

    # unused data columns become inputs of the extended network
    unused = _unused_columns(net, train_exps + val_exps) if (kinds is None or "unused_column" in kinds) else []
    net_x = net
    if unused:
        net_x = net.model_copy(update={"inputs": list(net.inputs) + [
            Input(name=n, column=c, dim={}, unit=None) for n, c in unused]}, deep=True)
        train_exps = read_data(net_x, train_paths) if train_paths and os.path.isfile(train_paths[0]) else train_exps
        val_exps = read_data(net_x, val_paths) if val_paths and os.path.isfile(val_paths[0]) else val_exps
        if train_exps[0].inputs.shape[1] != len(net_x.inputs):  # Experiments given directly: cannot add
            unused, net_x = [], net
    exps, train_mask, val_mask = _split_masks(train_exps, val_exps)
    all_u = np.concatenate([e.inputs for e in exps], 0)
    train_rows = train_mask.any(1)
    varying = [n for j, n in enumerate(net.input_names) if np.ptp(all_u[train_rows, j]) > 0]
    extra = [n for n, _ in unused]

    # ---- 1. the nominal model (the "small" network with no candidate) and its fit
    t0 = _time.monotonic()
    say("building candidates from the network ...")
    ext: Extended = build_extended(net_x, varying, extra, kinds=kinds)
    kinds_all = kinds
    state = _State()
    ref: dict = {}

    def small(keys: list[str]) -> tuple[_Engine, Extended, list[int], dict[str, list[int]]]:
        """An engine over the original network plus just the candidates ``keys`` (values from ``state``):
        (engine, its Extended, free column indices, candidate key → its column indices)."""
        ext_s = build_extended(net_x, varying, extra, kinds=kinds_all, only=set(keys))
        return _make_engine(ext_s, net_x, exps, train_mask, val_mask, backend, state, ref, keys)

    eng, ext0, free_idx, _ = small([])
    lap("compile", t0)
    t0 = _time.monotonic()
    say(f"fitting the nominal model ({len(free_idx)} free parameters) on {int(train_rows.sum())} samples ...")
    eng.fit(free_idx, max_iter=30, deadline=deadline, tol=1e-6)
    state.harvest(eng, ext0, [])
    lap("nominal_fit", t0)

    # ---- 2. residual analysis
    t0 = _time.monotonic()
    y_nom, x_nom = eng.simulate()
    e_nom = eng.y - y_nom
    model = eng.model
    out_names = list(model.output_names)
    vmask = eng.val_mask
    e_val = np.where(vmask, e_nom, np.nan)
    vrows = vmask.any(1)
    t_all = np.concatenate([e.t for e in exps])
    variables = {n: all_u[vrows, j] for j, n in enumerate(net_x.input_names) if np.ptp(all_u[vrows, j]) > 0}
    for j, n in enumerate(model.state_names):
        variables[f"T({n})" if n in net.node_names else n] = x_nom[vrows, j]
    variables["time"] = t_all[vrows]
    res = R.summarise(e_val[vrows], out_names, variables)
    e_tr = np.where(eng.train_mask, e_nom, np.nan)
    base = {
        "val_mae": res.mae, "val_max": res.max,
        "train_mae": float(np.nanmean(np.abs(e_tr))), "train_max": float(np.nanmax(np.abs(e_tr))),
        "per_sensor": res.errors,
        "free_params": {f"{k}" + (f"[{i}]" if i else ""): v for (k, i), v in state.free.items()},
    }
    sigma = float(np.mean(list(res.sigma.values()))) if res.sigma else 0.0
    lap("residuals", t0)
    say(f"baseline held-out MAE {res.mae:.4g} K, max {res.max:.4g} K; residual "
        + ("white" if all(w.get("white") for w in res.whiteness.values()) else "not white"))

    # ---- 3–5. forward selection: score test on the big extended network, proper fits on small ones
    findings: list[Finding] = []
    scores_out: list[dict] = []
    accepted: list[Candidate] = []
    current_val = (res.mae, res.max, eng.sse(which="val"))
    final_eng, final_ext = eng, ext0
    with_struct = kinds is None or any(k in STRUCTURAL_KINDS for k in kinds)
    dt_min = min(float(e.dt) for e in exps)

    def candidates_now() -> list[Candidate]:
        done = {a.key for a in accepted}
        struct = structural_candidates(net_x, kinds if kinds else None) if with_struct else []
        return [c for c in list(ext.candidates) + struct if c.key not in done]

    remaining = candidates_now()
    big = None
    for rnd in range(1, max_rounds + 1):
        if deadline is not None and _time.monotonic() > deadline:
            say("budget spent; stopping the forward selection")
            break
        t0 = _time.monotonic()
        acc_keys = [c.key for c in accepted if c.kind not in STRUCTURAL_KINDS]  # structural ones live in net_x
        if big is None:
            say(f"compiling the extended network ({len(ext.candidates)} candidates at their null value) ...")
            big = _make_engine(ext, net_x, exps, train_mask, val_mask, backend, state, ref, [c.key for c in ext.candidates],
                               with_candidates=True)
        else:
            big[0].params = _params_from_state(big[0], big[1], state, acc_keys)
        b_eng, b_ext, b_free, b_cols = big
        say(f"round {rnd}: score test over {len(remaining)} candidates ...")
        scored = _score_forced(final_eng, b_eng, remaining, b_cols, [_cand_in(b_ext, k) for k in acc_keys])
        if scored is None:
            remaining = [r for r in remaining if r.kind not in STRUCTURAL_KINDS]
        if scored is None:
            active_base = list(b_free) + [j for k in acc_keys for j in b_cols.get(k, [])]
            scored = _score(b_eng, remaining, active_base, b_cols, sigma)
        lap(f"score_round{rnd}", t0)
        if rnd == 1:
            scores_out = [dict(s["public"]) for s in scored]
        if not scored:
            break
        t0 = _time.monotonic()
        fits = []
        e_base_val = final_eng.residual().ravel()[final_eng.val_idx]
        short = []
        for s_ in _shortlist(scored, top):
            if s_["r2"] < MIN_R2 and short:
                continue  # the linearised fit explains too little of the residual to pay
            short.append(s_)
        # ONE small network for the round: the original, the accepted and every shortlisted candidate (each
        # exactly null at zero); each candidate is fitted with only its own columns moving, so the
        # compiled simulation and Jacobian are shared by all the round's fits
        sh_keys = [s_["cand"].key for s_ in short if s_["cand"].kind not in STRUCTURAL_KINDS]
        t_c = _time.monotonic()
        e_s, x_s, f_s, c_s = small(acc_keys + sh_keys)
        t_c = _time.monotonic() - t_c
        start_params = {k: np.array(v, copy=True) for k, v in e_s.params.items()}
        for s_ in short:
            c: Candidate = s_["cand"]
            if deadline is not None and _time.monotonic() > deadline and fits:
                break
            if s_["r2"] < MIN_R2:
                say(f"  {c.describe()}: the score test explains only {100 * s_['r2']:.2g} % of the residual;"
                    " not fitted")
                break
            say(f"  fitting {c.describe()} (k={c.k}) ...")
            if c.kind in STRUCTURAL_KINDS:
                f = _fit_structural(c, s_, net_x, varying, extra, kinds_all, acc_keys, exps, train_mask, val_mask,
                                    backend, state, ref, dt_min, deadline, e_base_val, say)
                if f is not None:
                    fits.append(f)
                continue
            e_s.params = {k: np.array(v, copy=True) for k, v in start_params.items()}
            act = list(f_s) + [j for k in acc_keys + [c.key] for j in c_s.get(k, [])]
            init = np.zeros(len(act))  # the Gauss–Newton step of the score test (kept only if it helps)
            own = c_s.get(c.key, [])
            for d, j in zip(s_["delta"], own):
                init[act.index(j)] = d
            t_f = _time.monotonic()
            info = e_s.fit(act, max_iter=FIT_ITER_FIRST, init_delta=init, deadline=deadline, tol=1e-4)
            say(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} iterations"
                + (f", network compiled in {t_c:.1f} s" if len(fits) == 0 else "") + ")")
            f = _fit_result(c, s_, e_s, x_s, e_base_val)
            f.update(act=act, train_sse=info["sse"], more=info["iterations"] >= FIT_ITER_FIRST)
            fits.append(f)
        # successive halving: the fits still moving after FIT_ITER_FIRST iterations, best training SSE first,
        # go on to convergence (the held-out rows never decide who continues)
        going = sorted([f for f in fits if f.get("more")], key=lambda f: f["train_sse"])[:FIT_CONTINUE]
        for f in going:
            if deadline is not None and _time.monotonic() > deadline:
                break
            c = f["cand"]
            say(f"  continuing {c.describe()} ...")
            e_s.params = {k: np.array(v, copy=True) for k, v in f["params"].items()}
            t_f = _time.monotonic()
            info = e_s.fit(f["act"], max_iter=FIT_ITER - FIT_ITER_FIRST, deadline=deadline, tol=1e-4)
            say(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} more iterations)")
            f.update(_fit_result(c, f["score"], e_s, x_s, e_base_val), train_sse=info["sse"])
        lap(f"fit_round{rnd}", t0)
        if not fits:
            break
        e_base_tr = final_eng.residual().ravel()[final_eng.train_idx]
        for f in fits:
            f["S_train"], f["p_train"] = _train_lr_test(e_base_tr, f["e_all"].ravel()[f["eng"].train_idx],
                                                        f["cand"].k, len(scored))
        chosen = _choose(fits, current_val, e_base_val)
        twins = _indistinguishable(chosen["score"], scored) if chosen is not None else []
        for rank, f in enumerate(sorted(fits, key=lambda f: f["val_sse"]), start=1):
            c = f["cand"]
            cf = _cand_in(f["ext"], c.key) or c
            prm = f["params"]
            findings.append(Finding(
                rank=rank, kind=c.kind, target=c.target, depends_on=list(c.depends_on),
                clause=_clause(cf, prm, f["ext"], f["eng"]),
                val_mae_after=f["val_mae"], val_max_after=f["val_max"], accepted=f is chosen,
                words=_words(cf, prm, f["ext"], f["eng"], f["eng"].model), round=rnd,
                evidence={"score": f["score"]["public"]["score"], "score_p": f["score"]["public"]["p"],
                          "r2_linearised": f["score"]["public"]["r2"], "k": c.k,
                          "val_mae_before": current_val[0], "val_sse_before": current_val[2],
                          "val_sse_after": f["val_sse"], "dm_stat": f["F"], "p_value": f["p"], "n_eff": f["n_eff"],
                          "lr_train": f.get("S_train"), "p_train": f.get("p_train"),
                          "test": ("likelihood ratio on the training rows (effective N, Bonferroni over the "
                                   "candidates scored) and Diebold–Mariano on held-out squared errors (HAC "
                                   "variance, AIC charge for k)"),
                          "mae_gain": 1 - f["val_mae"] / current_val[0] if current_val[0] else 0.0,
                          "reason": f.get("reason", ""),
                          "indistinguishable_from": twins if f is chosen else []}))
        if chosen is None:
            say(f"round {rnd}: no candidate pays on held-out data")
            break
        c = chosen["cand"]
        say(f"round {rnd}: accepted {c.describe()} (held-out MAE {current_val[0]:.4g} → {chosen['val_mae']:.4g} K)")
        accepted.append(c)
        chosen["eng"].params = chosen["params"]
        state.harvest(chosen["eng"], chosen["ext"], [k.key for k in accepted])
        final_eng, final_ext = chosen["eng"], chosen["ext"]
        current_val = (chosen["val_mae"], chosen["val_max"], chosen["val_sse"])
        if chosen["net"] is not None:  # a structural edit becomes part of the base network (its parameter free)
            net_x = chosen["net"]
            ext = build_extended(net_x, varying, extra, kinds=kinds)
            big = None
        remaining = candidates_now()

    # ---- the extension text, re-loaded to check it is valid
    t0 = _time.monotonic()
    acc_small = [_cand_in(final_ext, c.key) or c for c in accepted]
    fitted_params = final_eng.params
    clauses = _merged_clauses(acc_small, fitted_params, final_ext, final_eng)
    ext_text, diff = _extend_text(text, clauses, acc_small, net, fitted_params, final_ext, unused)
    ext_file = None
    lap("extend", t0)
    # ---- linear or MLP, as the evidence says (only where a structured residual is left)
    y_fin, _ = final_eng.simulate()
    e_fin = np.where(final_eng.val_mask, final_eng.y - y_fin, np.nan)
    res_fin = R.summarise(e_fin[vrows], out_names)
    form = None
    if (accepted and ext_text and mlp_check and any(" as linear(" in c for c in clauses)
            and not all(w.get("white") for w in res_fin.whiteness.values())
            and (deadline is None or _time.monotonic() + 2 * mlp_time < deadline)):
        from ..data import split_by_time
        from .mlp_check import compare

        t0 = _time.monotonic()
        say("the residual is not white: is an MLP better than the linear law? (training both)")
        tr_e, va_e = train_exps, val_exps
        if not va_e:
            parts = [split_by_time(e, 0.7) for e in train_exps]
            tr_e, va_e = [a for a, _ in parts], [b for _, b in parts]
        try:
            form = compare(ext_text, output or (path or "extended.thn"), tr_e, va_e, backend=backend,
                           time_limit=mlp_time, say=say)
        except TnnError as exc:  # e.g. data given as Experiments without the extension's extra columns
            form = {"choice": "linear", "reason": f"not compared: {exc.diagnostics[0].message}"}
        if form is not None and form.get("choice") == "mlp" and form["mlp"]["val_mae"] > (1 - MIN_GAIN) * res_fin.mae:
            form.update(choice="linear", text=ext_text,
                        reason=(f"the trained MLP ({form['mlp']['val_mae']:.4g} K held out) beats the trained linear "
                                f"law but not the doctor's own linear fit ({res_fin.mae:.4g} K) by {100 * MIN_GAIN:.0f} %"))
        if form is not None:
            say(f"  {form['reason']}")
            if form["choice"] == "mlp":
                import difflib

                ext_text = form["text"]
                diff = "".join(difflib.unified_diff(text.splitlines(True), ext_text.splitlines(True), "original",
                                                    "extended"))
                clauses = [ln for ln in ext_text.splitlines() if ln.startswith("learn ") and ln not in text]
            form = {k: v for k, v in form.items() if k != "text"}
        lap("mlp_check", t0)
    if accepted and ext_text:
        _check_text(ext_text, output or (path or "extended.thn"))
        if output:
            write_text_atomic(output, ext_text)
            ext_file = output
    extended = {"val_mae": res_fin.mae, "val_max": res_fin.max, "clauses": clauses,
                "per_sensor": res_fin.errors, "form": "linear"}
    if form is not None:
        extended["mlp_check"] = form
        if form.get("choice") == "mlp":  # the held-out numbers of the trained MLP extension
            extended.update(form="mlp", val_mae=form["mlp"]["val_mae"], val_max=form["mlp"]["val_max"])
    verdict = "; ".join(f.words for f in findings if f.accepted) if accepted else "no significant deficiency found"
    left = _what_is_left(res_fin)
    timings["total"] = round(_time.monotonic() - t_start, 3)
    plots = {"t": t_all, "y": eng.y, "y_nominal": y_nom, "y_extended": y_fin, "val_mask": eng.val_mask,
             "train_mask": eng.train_mask, "residual_nominal": e_nom, "variables": variables,
             "output_names": out_names, "dependence": res.dependence}
    return Diagnosis(network=net.name, baseline=base, residuals=res, scores=scores_out, findings=findings,
                     extended_text=ext_text if accepted else text, extended_file=ext_file, extended=extended,
                     diff=diff, verdict=verdict, left=left, timings=timings, plots=plots)


class _State:
    """Fitted values carried between the engines of different (small, big) networks: free scalars by
    ``(key, index)`` and each candidate's column values by candidate key."""

    def __init__(self):
        self.free: dict[tuple[str, int], float] = {}
        self.cand: dict[str, list[float]] = {}

    def harvest(self, eng: "_Engine", ext: Extended, keys: list[str]) -> None:
        for c in eng.cols[: eng.n_free]:
            self.free[(c.key, c.index)] = float(np.asarray(eng.params[c.key]).reshape(-1)[c.index])
        for cand in ext.candidates:
            if cand.key in keys:
                self.cand[cand.key] = [float(np.asarray(eng.params[col.key]).reshape(-1)[col.index])
                                       for col in cand.columns]


def _cand_in(ext: Extended, key: str) -> Candidate | None:
    return next((c for c in ext.candidates if c.key == key), None)


def _fit_structural(c: Candidate, s_: dict, net_x: Network, varying, extra, kinds, acc_keys, exps, train_mask, val_mask,
                    backend, state, ref, dt_min, deadline, e_base_val, say) -> dict | None:
    """Fit a structural (not exactly null) candidate on its own network: the base network with the edit
    built in (:func:`apply_structural`), started from the score test's Gauss–Newton value.

    A thermal mass starts at the Gauss–Newton ``C_m`` (J/K) clipped to ``[max(4·dt/R, 10⁻³·C_min), 100·C_max]``
    (``R`` the split link's total resistance, so that the new node's time constant ``C_m·f(1−f)·R`` is at least
    one sample at f = 1/2; ``C_min``/``C_max`` the capacities of the link's nodes) and is bounded below by
    ``0.4·dt/R`` (a tenth of a sample); ``f`` starts at 1/2.

    A heat capacity behind a source starts at the score test's lag ``τ`` (the grid value whose two columns
    explained most, times the Gauss–Newton amplitude of the lag column, clipped to [0.2, 5]) and at the
    Gauss–Newton ``C_h`` of the capacity column (clipped to [10⁻³, 10] × the heated node's capacity; a tenth of
    it if not positive), ``R_h = τ/C_h``; ``C_h`` is bounded below by 10⁻⁴ of that capacity, ``R_h`` by
    ``0.05·dt/C_h``."""
    t0 = float(s_["delta"][0]) if len(s_["delta"]) else 0.0
    frac = 0.5
    if c.kind == "sensor_lag":
        if not t0 > 0:
            say("    the linearised fit wants a negative lag: not fitted")
            return None
        t0 = float(np.clip(t0, 0.5 * dt_min, 1e4 * dt_min))
        lower = 0.2 * dt_min
    elif c.kind == "thermal_mass":
        if not t0 > 0:
            say("    the linearised fit wants a negative thermal mass: not fitted")
            return None
        el = c.element
        v = float(net_x.param(el["value"]).value)
        r_tot = v if el["form"] == "R" else 1.0 / v
        caps = []
        for n in net_x.nodes:
            if n.name in (el["a"], el["b"]):
                pc = net_x.param(n.capacitance)
                if pc.is_constant and pc.value and pc.value > 0:
                    caps.append(float(pc.value))
        lo = 4.0 * dt_min / r_tot
        hi = 100.0 * max(caps) if caps else 1e6 * lo
        if caps:
            lo = max(lo, 1e-3 * min(caps))
        t0 = float(np.clip(t0, lo, max(hi, lo)))
        lower = 0.4 * dt_min / r_tot
    elif c.kind == "source_mass":
        if not t0 > 0:
            say("    the linearised fit wants a negative lag behind the source: not fitted")
            return None
        el = c.element
        tau = float(el.get("score_tau") or dt_min) * float(np.clip(t0, 0.2, 5.0))
        node = next(n for n in net_x.nodes if n.name == el["at"])
        pc = net_x.param(node.capacitance)
        c_node = float(pc.value) if pc.is_constant and pc.value and pc.value > 0 else None
        c_gn = float(s_["delta"][1]) if len(s_["delta"]) > 1 else 0.0  # the capacity column's Gauss–Newton C_h
        if c_node:
            cap0 = float(np.clip(c_gn, 1e-3 * c_node, 10.0 * c_node)) if c_gn > 0 else 0.1 * c_node
        else:
            cap0 = c_gn if c_gn > 0 else max(tau, dt_min)  # J/K; without a known capacity: R_h = 1 K/W
        t0 = cap0
        lower = 1e-4 * c_node if c_node else None
        extra_kw = {"resistance": tau / cap0, "resistance_lower": 0.05 * dt_min / cap0}
    else:
        raise ValueError(f"not a structural candidate kind: {c.kind}")
    kw = {"frac": frac} if c.kind == "thermal_mass" else (extra_kw if c.kind == "source_mass" else {})
    net_s = apply_structural(net_x, c, t0, lower=lower, **kw)
    ext_s = build_extended(net_s, varying, extra, kinds=kinds, only=set(acc_keys))
    eng, x_s, f_s, c_s = _make_engine(ext_s, net_s, exps, train_mask, val_mask, backend, state, ref, acc_keys)
    act = list(f_s) + [j for k in acc_keys for j in c_s.get(k, [])]
    t_f = _time.monotonic()
    info = eng.fit(act, max_iter=15, deadline=deadline, tol=1e-4)
    say(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} iterations, own network)")
    e_after = eng.residual()
    ev = np.where(eng.val_mask, e_after, np.nan)
    e1 = e_after.ravel()[eng.val_idx]
    F, pval, n_eff = _held_out_test(e_base_val, e1, c.k)
    val_sse = eng.sse(which="val")
    if c.kind in ("thermal_mass", "source_mass") and "states" in ref:
        # the reference run's states (learned-function normalisation, read by position) get the new node's
        # trajectory where it will sit if accepted: after the original nodes (lag states, never learn inputs,
        # shift). Of several masses fitted on one layout, the best-fitting one's column is kept.
        n0 = len(net_x.nodes)
        _, xs = eng.simulate()
        col = xs[:, list(eng.model.state_names).index(c.element["node"])]
        prev = ref.get("mass_col")
        st, names = np.asarray(ref["states"]), list(ref["names"])
        if prev is not None and prev["n0"] == n0 and st.shape[1] > n0:
            if val_sse < prev["sse"]:
                st = st.copy()
                st[:, n0] = col
                names[n0] = c.element["node"]
                ref["mass_col"] = {"n0": n0, "sse": val_sse}
        elif st.shape[1] >= n0:
            st = np.concatenate([st[:, :n0], col[:, None], st[:, n0:]], axis=1)
            names = names[:n0] + [c.element["node"]] + names[n0:]
            ref["mass_col"] = {"n0": n0, "sse": val_sse}
        ref["states"], ref["names"] = st, names
    return {"cand": c, "score": s_, "eng": eng, "ext": x_s, "val_mae": float(np.nanmean(np.abs(ev))),
            "val_max": float(np.nanmax(np.abs(ev))), "e_val": e1, "val_sse": val_sse, "F": F, "p": pval,
            "n_eff": n_eff, "params": eng.params, "e_all": e_after, "net": net_s}


def _alias(key: str, params) -> str | None:
    """A learned constant ``f.c`` is the linear ``f.b`` of its replacement (and back)."""
    if key in params:
        return key
    for a, b in ((".c", ".b"), (".b", ".c")):
        if key.endswith(a) and key[: -len(a)] + b in params:
            return key[: -len(a)] + b
    return None


def _params_from_state(eng: "_Engine", ext: Extended, state: _State, keys: list[str]) -> dict:
    p = {k: np.array(v, dtype=float, copy=True) for k, v in eng.params0.items()}
    for (k, i), v in state.free.items():
        kk = _alias(k, p)
        if kk is not None and i < p[kk].size:
            flat = p[kk].reshape(-1)
            flat[i] = v
            p[kk] = flat.reshape(p[kk].shape)
    for cand in ext.candidates:
        vals = state.cand.get(cand.key)
        if vals is None or cand.key not in keys:
            continue
        for col, v in zip(cand.columns, vals):
            flat = p[col.key].reshape(-1)
            flat[col.index] = v
            p[col.key] = flat.reshape(p[col.key].shape)
    return p


def _make_engine(ext_s: Extended, net_x: Network, exps, train_mask, val_mask, backend, state: _State, ref: dict,
                 keys: list[str], with_candidates: bool = False):
    """Compile ``ext_s`` and set up an engine whose columns are the nominal free scalars followed by the
    candidate columns of ``keys``; parameters from ``state``; learned-function statistics from the reference
    nominal run (the same for every network, so values carry over)."""
    from ..compiler import compile as _compile

    n_force = 0 if with_candidates else len(ext_s.network.nodes)
    model = _compile(ext_s.network if with_candidates else _with_forcing(ext_s.network), backend=backend,
                     dtype="float64")
    specs = model.param_specs
    params0 = {k: np.array(v, dtype=float) for k, v in model.to_numpy(model.init_params(seed=0)).items()}
    free_cols = _free_columns(net_x, ext_s, specs, params0)
    cand_cols: list[_Col] = []
    seen: dict[tuple[str, int], int] = {(c.key, c.index): i for i, c in enumerate(free_cols)}
    cols_of: dict[str, list[int]] = {}
    for cand in ext_s.candidates:
        if cand.key not in keys:
            continue
        idx = []
        for col in cand.columns:
            if (col.key, col.index) not in seen:
                lower = 0.0 if cand.kind in ("missing_link", "radiation") else None
                seen[(col.key, col.index)] = len(free_cols) + len(cand_cols)
                cand_cols.append(_Col(col.key, col.index, False, lower, None))
            idx.append(seen[(col.key, col.index)])
        cols_of[cand.key] = idx
    eng = _Engine(model.network, exps, train_mask, val_mask, backend, free_cols + cand_cols, params0, model=model,
                  n_force=n_force)
    eng.n_free = len(free_cols)
    all_u = np.concatenate([e.inputs for e in exps], 0)
    if "states" not in ref:
        _, st = eng.simulate()
        ref["states"] = st
        ref["names"] = list(model.state_names)
    rows = train_mask.any(1)
    eng.params0 = normalisation_stats(model, params0, ext_s.fn_vars, ext_s.network, all_u, ref["states"], rows,
                             dt=float(exps[0].dt), state_names=ref.get("names"))
    eng.params = _params_from_state(eng, ext_s, state, keys)
    return eng, ext_s, list(range(len(free_cols))), cols_of


def _free_columns(net: Network, ext: Extended, specs, params0) -> list[_Col]:
    """The nominal model's trainable scalars: its ``free`` constants (from the IR: in the extended network
    they may be targets of a candidate function, which keeps their value as the nominal) and the weights of
    its own non-frozen learned functions. Positive ones move in log space."""
    cols: list[_Col] = []
    learned = net.learned_targets()
    for p in net.params:
        if p.free and p.is_constant and p.name not in learned and p.name in specs:
            v = float(np.asarray(params0[p.name]))
            cols.append(_Col(p.name, 0, p.role in POSITIVE_ROLES and v > 0, p.lower, p.upper))
    own = {fn.name for fn in net.learned}
    for name, sp in specs.items():
        fn = name.split(".", 1)[0]
        if sp.kind != "weights" or not sp.trainable or fn not in own or name in ext.candidate_keys:
            continue
        for i in range(int(np.asarray(params0[name]).size)):
            cols.append(_Col(name, i, False))
    return cols


def _free_values(eng: _Engine, free_cols: list[_Col], net: Network) -> dict:
    out = {}
    for c in free_cols:
        if "." in c.key and c.key.split(".")[0] in {f.name for f in net.learned}:
            continue
        out[c.key] = float(np.asarray(eng.params[c.key]).reshape(-1)[c.index])
    return out


def _same_columns(a: Candidate, b: Candidate) -> bool:
    return {(c.key, c.index) for c in a.columns} <= {(c.key, c.index) for c in b.columns}


def _score_forced(cur: _Engine, big: _Engine, cands: list[Candidate], cols_of: dict[str, list[int]],
                  accepted: list[Candidate]) -> list[dict] | None:
    """The score test without simulating the big extended network: every candidate enters the dynamics as
    an extra heat flow per node, ``F_c(t) = C·∂rhs/∂θ_c`` at the current trajectory (the big network's
    right-hand side differentiated pointwise, vectorised over time), plus a direct output term
    ``∂h/∂θ_c`` (sensor offsets). The response of the outputs to ``F_c`` is one forward-mode derivative of
    the *current* network's simulation w.r.t. its forcing inputs (``_with_forcing``), batched over
    candidates: exact in continuous time, the discrete step holding ``F_c`` over each sample. Returns None
    when the two networks' states differ (then the caller uses :func:`_score` on the big network).

    Structural candidates (not exactly null) get their first-order column without simulating the edit:

    * sensor lag τ: the reading is ``T_n − τ·dT_n/dt + O(τ²)``, a direct output column ``−dT_n/dt``;
    * heat capacity ``C_h`` behind a source at a resistance ``R_h`` (``_candidates.source_lag_forcing``): the
      heat reaching the node is ``Q_h = lag_τ(Q) − C_h·lag_τ(dT_n/dt)``, τ = C_h·R_h: two columns per τ of a grid
      (``source_tau_grid``), the lag part and the capacity part; the pair explaining most of the residual is
      the candidate's (k = 2), the lag's Gauss–Newton amplitude scales τ and the capacity's is ``C_h``;
    * thermal mass ``C_m`` on a link a–b (resistance R) split at m into ``f·R`` (a side) and ``(1−f)·R``: m's
      balance ``C_m·dT_m/dt = (T_a − T_m)/(f·R) + (T_b − T_m)/((1−f)·R)``. At ``C_m → 0`` m is quasi-static,
      ``T_m0 = (1−f)·T_a + f·T_b``, and the heat into a is the unsplit link's. To first order,
      ``T_m = T_m0 + δ``, ``δ = −C_m·f(1−f)·R·dT_m0/dt``, so the heat into a changes by
      ``δ/(f·R) = −C_m·(1−f)·dT_m0/dt`` and into b (a node) by ``−C_m·f·dT_m0/dt``: per unit ``C_m`` a heat-flow
      column (W per J/K) that goes through the forced Jacobian like ``F_c`` (``_candidates.mass_forcing``;
      node rates as interval means of the simulated states, boundary rates from the input samples, f = 1/2;
      the proper fit frees f). The column's Gauss–Newton step is the starting ``C_m`` of the proper fit."""
    if tuple(big.model.state_names) != tuple(cur.model.state_names) or cur.n_force == 0:
        return None
    nsr = cur.n_score_rows
    _, X = cur.simulate()
    X = X[:nsr]
    n_in = len(big.model.input_names)
    U = np.concatenate([e.inputs for e in cur.exps], 0)[:nsr, :n_in]
    acc_cols = {(col.key, col.index) for a in accepted for col in a.columns}
    # the base directions: the nominal free columns and the accepted candidates' (the current engine may also
    # hold last round's rejected candidates, at zero: left out)
    active_base = [i for i, c in enumerate(cur.cols) if i < cur.n_free or (c.key, c.index) in acc_cols]
    taken = {(cur.cols[i].key, cur.cols[i].index) for i in active_base}
    cand_idx = sorted({j for cand in cands for j in cols_of.get(cand.key, [])
                       if (big.cols[j].key, big.cols[j].index) not in acc_cols | taken})
    d_rhs, d_out = big.point_derivs(cand_idx, X, U)
    inv_c = cur.inv_capacity(X, U)  # (N, ns)
    nn = cur.n_force
    with np.errstate(divide="ignore", invalid="ignore"):
        F = np.where(np.abs(inv_c[None, :, :nn]) > 0, d_rhs[:, :, :nn] / inv_c[None, :, :nn], 0.0)
    # structural candidates, no simulation of the edit. A thermal mass C_m on a link a–b is an extra heat flow
    # per node (``_candidates.mass_forcing``: −C_m·(1−f)·dT_m/dt into a, −C_m·f·dT_m/dt into b, f = 1/2 here;
    # the proper fit frees f), pushed through the forced Jacobian with the other candidates' F; a sensor lag τ
    # is a direct output term ∂y_s/∂τ = −dT_node/dt.
    struct = [c for c in cands if c.kind in STRUCTURAL_KINDS]
    mass = [c for c in struct if c.kind == "thermal_mass"]
    smass = [c for c in struct if c.kind == "source_mass"]
    rates = cur.rates(X, U) if struct else None  # (N, ns) K/s
    mass_rows: list[tuple[Candidate, float | None, str | None]] = []  # (candidate, C or τ, source part)
    if mass or smass:
        # At first order (T_m = (1−f)·T_a + f·T_b) a mass on a link to a constant boundary is exactly a larger
        # capacity of a (−C_m(1−f)²·dT_a/dt): only its lag tells them apart. So each mass is also tried with its
        # lag at a grid of capacities (``mass_grid``: T_m lagged behind its quasi-static value on the current
        # trajectory, the flows divided by C); the column explaining most of the residual is the candidate's.
        from .candidates import mass_forcing, mass_grid, source_lag_forcing, source_tau_grid

        lens = [e.n_steps for e in cur.exps[: cur.n_score_exps]]
        dts = [float(e.dt) for e in cur.exps[: cur.n_score_exps]]
        duration = max(n * d for n, d in zip(lens, dts))
        Fm = []
        for c in mass:
            for cg in [None] + mass_grid(cur.net, c, cur.params, min(dts), duration):
                Fm.append(mass_forcing(cur.net, c, X, U, cur.params, lens, dts, frac=0.5, rates=rates,
                                       mass=cg)[:, :nn])
                mass_rows.append((c, cg, None))
        for c in smass:  # two columns per τ: the lag part and the capacity part (per J/K of C_h)
            for tau in source_tau_grid(min(dts), duration):
                Fm.append(source_lag_forcing(cur.net, c, X, U, cur.params, lens, dts, tau)[:, :nn])
                mass_rows.append((c, tau, "lag"))
                Fm.append(source_lag_forcing(cur.net, c, X, U, cur.params, lens, dts, tau, rates=rates)[:, :nn])
                mass_rows.append((c, tau, "capacity"))
        if Fm:
            F = np.concatenate([F, np.stack(Fm)], axis=0)
    J_all = cur.forced_jacobian(active_base, F)
    direct = d_out.reshape(d_out.shape[0], -1)[:, cur.train_idx].T  # (n_train, m)
    n0 = len(active_base)
    J_all[:, n0: n0 + direct.shape[1]] += direct
    if struct:
        names = list(cur.model.state_names)
        outs = list(cur.model.output_names)
        cols_of = dict(cols_of)
        n_new = 0
        extra_cols = []
        if mass_rows:  # the forced Jacobian's last columns: keep each mass's best one (free directions projected out)
            n_c = n0 + direct.shape[1]
            Jm, J_all = J_all[:, n_c:], J_all[:, :n_c]
            r_tr = cur.residual().ravel()[cur.train_idx]
            Ub = _free_basis(J_all[:, :n0])
            rp = r_tr - Ub @ (Ub.T @ r_tr)
            Jp = Jm - Ub @ (Ub.T @ Jm)
            with np.errstate(divide="ignore", invalid="ignore"):
                share = (Jp.T @ rp) ** 2 / (np.sum(Jp * Jp, axis=0) * max(float(rp @ rp), 1e-300))
            share = np.where(np.isfinite(share), share, -1.0)
            best: dict[str, tuple[float, int, int]] = {}  # key -> (share of the residual, first column, width)
            i = 0
            while i < len(mass_rows):
                c, _, part = mass_rows[i]
                width = 2 if part == "lag" else 1
                if width == 2:  # a source's lag and capacity columns together
                    A = Jp[:, i:i + 2]
                    coef = np.linalg.lstsq(A, rp, rcond=None)[0]
                    fit = A @ coef
                    sc = float(fit @ fit) / max(float(rp @ rp), 1e-300)
                    sc = sc if np.isfinite(sc) else -1.0
                else:
                    sc = float(share[i])
                if c.key not in best or sc > best[c.key][0]:
                    best[c.key] = (sc, i, width)
                i += width
            for c in mass + smass:
                _, i, width = best[c.key]
                c.element["score_mass" if c.kind == "thermal_mass" else "score_tau"] = mass_rows[i][1]  # None: 1st order
                idx = []
                for w in range(width):
                    extra_cols.append(Jm[:, i + w])
                    idx.append(len(big.cols) + n_new)
                    n_new += 1
                cols_of[c.key] = idx
                cand_idx = cand_idx + idx
        for c in struct:
            if c.kind in ("thermal_mass", "source_mass"):
                continue
            col = np.zeros((nsr, len(outs)))
            if c.kind == "sensor_lag":
                col[:, outs.index(c.target)] = -rates[:, names.index(c.element["node"])]
                col = _best_lag_column(cur, c, col, X[:, names.index(c.element["node"])], outs.index(c.target),
                                       J_all[:, :n0])
            j = len(big.cols) + n_new
            n_new += 1
            cols_of[c.key] = [j]
            cand_idx = cand_idx + [j]
            extra_cols.append(col.reshape(-1)[cur.train_idx])
        if extra_cols:
            J_all = np.concatenate([J_all, np.stack(extra_cols, axis=1)], axis=1)
    e = cur.residual()
    return _score_stats(J_all, len(active_base), e.ravel()[cur.train_idx], cands, cand_idx, cols_of,
                        _noise_var(e, cur.train_mask))


def _free_basis(Jf: np.ndarray) -> np.ndarray:
    """An orthonormal basis ``(n, r)`` of the span of the free columns ``Jf (n, m)`` (columns scaled to unit
    norm first; directions below 1e-10 of the largest singular value dropped): what a candidate's column
    and the residual are projected off, since the free parameters move in every fit."""
    if not Jf.shape[1]:
        return np.zeros((Jf.shape[0], 0))
    sc = np.linalg.norm(Jf, axis=0)
    sc[sc == 0] = 1.0
    U, s, _ = np.linalg.svd(Jf / sc, full_matrices=False)
    return U[:, s > s.max() * 1e-10] if s.size and s.max() > 0 else U[:, :0]


def _best_lag_column(cur: "_Engine", c: Candidate, first: np.ndarray, x_node: np.ndarray, out: int,
                     Jf: np.ndarray) -> np.ndarray:
    """The score column of a sensor lag: the first-order one (``−dT_node/dt``, exact as τ → 0) or, when it
    explains more of the residual (free directions projected out), the reading lagged at a finite τ on the
    current trajectory, per unit τ: ``(s_τ − T_node)/τ`` with ``s`` the node's samples through
    ``τ ds/dt = T − s`` (exact for a held sample, started at the first sample of each file). τ runs from
    half a sample to a third of the data in factors of 3, so a slow sensor (τ of the order of the plant's
    own time constants, where the first-order term fails) scores as what it is; ``c.element["score_tau"]``
    keeps the τ that won (None: first order). Shapes: ``first (N_score, n_out)``, ``x_node (N_score,)`` K."""
    lens = [e.n_steps for e in cur.exps[: cur.n_score_exps]]
    dts = [float(e.dt) for e in cur.exps[: cur.n_score_exps]]
    r = cur.residual().ravel()[cur.train_idx]
    Ub = _free_basis(Jf)
    rp = r - Ub @ (Ub.T @ r)
    rr = max(float(rp @ rp), 1e-300)

    def share(col2d):
        v = col2d.reshape(-1)[cur.train_idx]
        v = v - Ub @ (Ub.T @ v)
        nv = float(v @ v)
        return (float(v @ rp) ** 2 / (nv * rr)) if nv > 0 else -1.0

    best, best_share, best_tau = first, share(first), None
    dt = min(dts)
    duration = max(n * d for n, d in zip(lens, dts))
    tau = dt / 2
    while tau < duration / 3:
        s = np.empty_like(x_node)
        i0 = 0
        for n, d in zip(lens, dts):
            a = math.exp(-d / tau)
            seg = x_node[i0: i0 + n]
            s[i0: i0 + n] = lfilter([1 - a], [1.0, -a], seg, zi=[a * seg[0]])[0]
            i0 += n
        col = np.zeros_like(first)
        col[:, out] = (s - x_node) / tau
        sh = share(col)
        if sh > best_share:
            best, best_share, best_tau = col, sh, tau
        tau *= 3
    c.element["score_tau"] = best_tau
    return best


def _score(eng: _Engine, cands: list[Candidate], active_base: list[int], cols_of: dict[str, list[int]],
           sigma: float) -> list[dict]:
    """The score (LM) test of every candidate at the current point, on the big network's simulation (used
    where :func:`_score_forced` cannot be); sorted best first."""
    e = eng.residual()
    cand_idx = sorted({j for cand in cands for j in cols_of.get(cand.key, [])} - set(active_base))
    J_all = eng.jacobian(active_base + cand_idx)
    return _score_stats(J_all, len(active_base), e.ravel()[eng.train_idx], cands, cand_idx, cols_of,
                        _noise_var(e, eng.train_mask))


def _noise_var(e: np.ndarray, mask: np.ndarray) -> float:
    """The measurement-noise variance K² seen in the residual ``e (N, n_out)`` on the rows of ``mask``: half
    the mean squared first difference along time (white noise of variance σ² gives 2σ²; a smooth model
    error contributes almost nothing), so a large structured residual does not inflate it."""
    m = mask[1:] & mask[:-1]
    d = np.diff(e, axis=0)[m]
    d = d[np.isfinite(d)]
    return float(np.mean(d * d) / 2.0) if d.size else 0.0


def _score_stats(J_all: np.ndarray, n_base: int, r: np.ndarray, cands: list[Candidate], cand_idx: list[int],
                 cols_of: dict[str, list[int]], noise_var: float = 0.0) -> list[dict]:
    """Score statistics from the Jacobian ``J_all = [J_base | J_candidate columns cand_idx]`` (n_train, ·)
    and the training residual ``r``; sorted best first.

    Two scales: ``S = N_eff·R²`` (``N_eff`` the autocorrelation-corrected sample size of the residual; its
    χ²(k) tail is the reported, conservative ``p``), and for the *ranking* the score on the noise's own
    scale, ``S_w = R²·‖r‖²/σ²`` with σ² from the residual's first differences (:func:`_noise_var`): a
    structured residual leaves ``N_eff`` at a handful of samples, where a charge of 2 per parameter would
    outweigh any difference in explained residual; against the noise it is the usual AIC-type charge."""
    Jf = J_all[:, :n_base]
    Jc_all = J_all[:, n_base:]
    pos = {j: i for i, j in enumerate(cand_idx)}
    if Jf.shape[1]:  # project out the free directions: orthonormal basis of span(Jf)
        U = _free_basis(Jf)
        Jc_all = Jc_all - U @ (U.T @ Jc_all)
        r = r - U @ (U.T @ r)
    rr = float(r @ r)
    n_eff = R.effective_n(r)
    out = []
    for cand in cands:
        idx = [pos[j] for j in cols_of.get(cand.key, []) if j in pos]
        if not idx or rr <= 0:
            continue
        Jc = Jc_all[:, idx]
        norms = np.linalg.norm(Jc, axis=0)
        if not np.any(norms > 1e-12 * max(1.0, math.sqrt(rr))):
            continue
        sc = np.where(norms > 0, norms, 1.0)
        Q, s, Vt = np.linalg.svd(Jc / sc, full_matrices=False)
        keep = s > (s.max() * 1e-8)
        Q, s, Vt = Q[:, keep], s[keep], Vt[keep]
        proj = Q.T @ r
        r2 = float(proj @ proj) / rr
        k = int(keep.sum())
        delta = (Vt.T @ (proj / s)) / sc
        S = n_eff * r2
        p = float(stats.chi2.sf(S, k))
        S_w = r2 * rr / noise_var if noise_var > 0 else S
        fit_dir = Q @ proj  # the training-output change the candidate's linearised fit makes
        nrm = float(np.linalg.norm(fit_dir))
        out.append({"cand": cand, "r2": r2, "S": S, "p": p, "k": k, "delta": delta,
                    "adj": max(S, S_w) - 2 * k, "place": _place(cand),
                    "dir": (fit_dir / nrm).astype(np.float32) if nrm > 0 else None})
    out.sort(key=lambda d: (-d["adj"], d["k"], d["place"]))
    for i, d in enumerate(out, start=1):
        c = d["cand"]
        d["public"] = {"rank": i, "kind": c.kind, "target": c.target, "depends_on": c.depends_on, "k": d["k"],
                       "score": d["S"], "r2": d["r2"], "p": d["p"], "words": c.describe()}
    return out


def _indistinguishable(chosen: dict, scored: list[dict], cos_min: float = 0.95, most: int = 5) -> list[dict]:
    """Candidates whose linearised correction of the training outputs is (nearly) the same as the chosen
    one's (|cos| ≥ ``cos_min`` between the fitted output changes, free directions projected out): the data
    cannot tell them apart, e.g. two series resistances seen through one sensor (thesis §6.2.4). This is
    the identifiability test of ``tnn_dsl.sensitivity`` (|corr| > 0.95 between sensitivity columns) applied
    to the candidates' columns."""
    d0 = chosen.get("dir")
    if d0 is None:
        return []
    out = []
    for s in scored:
        if s is chosen or s.get("dir") is None:
            continue
        cos = abs(float(np.dot(d0.astype(float), s["dir"].astype(float))))
        if cos >= cos_min:
            out.append({"candidate": s["cand"].describe(), "key": s["cand"].key, "cos": cos, "k": s["k"]})
    out.sort(key=lambda d: -d["cos"])
    return out[:most]


def _fit_result(c: Candidate, s_: dict, eng: "_Engine", ext: Extended, e_base_val: np.ndarray) -> dict:
    """The held-out numbers of a candidate fitted on ``eng`` (its current parameters)."""
    e_after = eng.residual()
    ev = np.where(eng.val_mask, e_after, np.nan)
    e1 = e_after.ravel()[eng.val_idx]
    F, pval, n_eff = _held_out_test(e_base_val, e1, c.k)
    return {"cand": c, "score": s_, "eng": eng, "ext": ext, "val_mae": float(np.nanmean(np.abs(ev))),
            "val_max": float(np.nanmax(np.abs(ev))), "e_val": e1, "val_sse": eng.sse(which="val"), "F": F,
            "p": pval, "n_eff": n_eff, "params": eng.params, "e_all": e_after, "net": None}


def _train_lr_test(e0: np.ndarray, e1: np.ndarray, k: int, m: int) -> tuple[float, float]:
    """Likelihood-ratio test of the fitted candidate on the training rows: ``S = N_eff·ln(SSE0/SSE1)``
    against χ²(k), ``N_eff`` the extended model's residual sample size corrected for autocorrelation
    (:func:`tnn_dsl.analysis.residuals.effective_n`: under the alternative that residual is the noise). The
    candidate was picked among ``m`` scored ones, so its p is Bonferroni-corrected (×m). Returns
    ``(S, corrected p)``."""
    ok = np.isfinite(e0) & np.isfinite(e1)
    if ok.sum() < 8 or not np.all(np.isfinite(e1)):
        return 0.0, 1.0
    sse0, sse1 = float(e0[ok] @ e0[ok]), float(e1[ok] @ e1[ok])
    if not (sse1 > 0 and sse0 > sse1):
        return 0.0, 1.0
    S = R.effective_n(e1[ok]) * math.log(sse0 / sse1)
    return float(S), float(min(1.0, max(m, 1) * stats.chi2.sf(S, max(k, 1))))


def _shortlist(scored: list[dict], top: int, same_cos: float = 0.99999) -> list[dict]:
    """The ``top`` best by score among *distinct* candidates, plus (compensation guard) the best-scoring
    physical-placement candidate when only heat loads made the list, so a heat load never wins without a
    physical rival being fitted.

    Distinct: two candidates with the same number of parameters whose linearised corrections of the
    training outputs coincide (|cos| ≥ ``same_cos``, e.g. a heat load at a node and the error of the source
    there) would be fitted twice for one answer; only the more physical (then the better-scoring) one is
    fitted, the other is listed under ``"same"`` of the one kept (reported as indistinguishable)."""
    short: list[dict] = []
    for s in scored:
        twin = None
        if s.get("dir") is not None:
            for t in short:
                if (t.get("dir") is not None and t["k"] == s["k"]
                        and abs(float(np.dot(t["dir"].astype(float), s["dir"].astype(float)))) >= same_cos):
                    twin = t
                    break
        if twin is not None:
            if s["place"] < twin["place"]:  # keep the more physical one in the twin's slot
                s["same"] = twin.get("same", []) + [twin]
                twin.pop("same", None)
                short[short.index(twin)] = s
            else:
                twin.setdefault("same", []).append(s)
            continue
        if len(short) >= top:
            break
        short.append(s)
    if short and all(s["place"] >= 3 for s in short):
        phys = next((s for s in scored if s not in short and s["place"] < 3 and s["r2"] > 0.5 * short[0]["r2"]),
                    None)
        if phys is not None:
            short.append(phys)
    # the user's own uncertain parts: the best candidates extending a `learn` clause of the input file
    if short:
        r2_best = max(s["r2"] for s in short)
        for s in [s for s in scored if s["cand"].element.get("learned") and s not in short
                  and s["r2"] > 0.5 * r2_best][:2]:
            if not any(s in t.get("same", []) for t in short):
                short.append(s)
    # parsimony: the best one-parameter candidates are fitted too when larger ones filled the list (a
    # dependence with its offset contains the wrong constant, and the score on the noise's scale favours
    # a tiny gain in explained residual over the parameter it costs)
    if short:
        r2_best = max(s["r2"] for s in short)
        for s in [s for s in scored if s["k"] == 1 and s not in short and s["r2"] > 0.9 * r2_best][:2]:
            if not any(s in t.get("same", []) for t in short):
                short.append(s)
    return short


def _choose(fits: list[dict], current_val, e_base_val) -> dict | None:
    """Pick the candidate that pays on held-out data: a Diebold–Mariano test with a charge for its k
    parameters (p < ``P_ACCEPT``) and a held-out MAE gain of at least ``MIN_GAIN``. Among those within noise
    of the best (not significantly worse, and not ``CLOSE_RATIO`` times its held-out MAE), fewer parameters win,
    then the more physical placement (an exact sub-model explains the data as well as the larger candidate
    containing it: the larger one only adds a parameter to compensate).

    The training likelihood-ratio test (:func:`_train_lr_test`) is reported as evidence but does not gate:
    on noise-free or nearly noise-free data its autocorrelation-corrected sample size collapses to a few
    samples, while the held-out test still sees whether the gain is real. The gain threshold is what keeps
    null runs clean: fitting noise cannot cut the held-out MAE by ``MIN_GAIN``."""
    mae0 = current_val[0]
    paying = []
    for f in fits:
        gain = 1 - f["val_mae"] / mae0 if mae0 else 0.0
        if not (math.isfinite(f["val_mae"]) and f["val_mae"] < 1e3):
            f["reason"] = "its held-out simulation diverges (the fitted law leaves the physical range there)"
        elif f["p"] >= P_ACCEPT:
            f["reason"] = f"not confirmed on held-out data (Diebold–Mariano p = {f['p']:.2g} ≥ {P_ACCEPT})"
        elif gain < MIN_GAIN:
            f["reason"] = f"gain too small ({100 * gain:.1f} % < {100 * MIN_GAIN:.0f} %)"
        else:
            paying.append(f)
    if not paying:
        return None
    best = min(paying, key=lambda f: f["val_sse"])
    # within noise of the best: the best is not significantly better (same held-out test, k = 0) and not
    # CLOSE_RATIO times better in held-out MAE (on very smooth residuals N_eff is a handful of samples and the
    # test cannot separate even a 20-fold difference: building/radiation at full length, 0.0077 against 0.17 K)
    close = [f for f in paying if f is best or (_held_out_test(f["e_val"], best["e_val"], 0)[1] > 0.05
                                                and f["val_mae"] <= CLOSE_RATIO * best["val_mae"])]
    pick = min(close, key=lambda f: (f["cand"].k, _place(f["cand"]), f["val_sse"]))
    for f in paying:
        if f is not pick:
            f["reason"] = ("within noise of the chosen one, which is more physical or smaller"
                           if f in close else "explains less than the chosen one")
    return pick


# ---------------------------------------------------------------------------------------------
# Naming the cause: coefficients read back in physical units
# ---------------------------------------------------------------------------------------------


def _linear_coeffs(c: Candidate, params, ext: Extended):
    """For a linear learned-function candidate: (offset z0, [(var label, slope per unit, mean, scale)])
    with the raw output ``z = z0 + Σ slope·(x − mean)`` for the candidate's target (output ``j``)."""
    fn = c.fn
    vars_ = ext.fn_vars.get(fn, [])
    j = int(c.element.get("output", 0))
    n = max(len(vars_), 1)
    W = np.asarray(params.get(f"{fn}.W", np.zeros((n, j + 1))))
    W = W.reshape(n, -1) if W.size else np.zeros((n, j + 1))
    b = np.asarray(params.get(f"{fn}.b", params.get(f"{fn}.c", np.zeros(j + 1)))).reshape(-1)
    mean = np.asarray(params.get(f"{fn}.x_mean", np.zeros(len(vars_)))).reshape(-1)
    scale = np.asarray(params.get(f"{fn}.x_scale", np.ones(len(vars_)))).reshape(-1)
    terms = []
    for i, (k, v) in enumerate(vars_):
        w = float(W[i, j])
        if w != 0.0:
            terms.append((var_label(k, v), w / scale[i], float(mean[i]), float(scale[i])))
    return (float(b[j]) if b.size > j else 0.0), terms


def _out_scale(params, c: Candidate) -> float:
    """The output scale of the candidate's own output ``j`` of its learned function (W, or the parameter's
    unit)."""
    ys = np.asarray(params.get(f"{c.fn}.y_scale", np.ones(1))).reshape(-1)
    j = int(c.element.get("output", 0))
    return float(ys[j] if j < ys.size else ys[0])


def _pos1_slope() -> float:
    sp4 = math.log1p(math.exp(4.0))
    return 4.0 / (1.0 + math.exp(-4.0)) / sp4


def _unit_of(net: Network, pname: str) -> str:
    try:
        p = net.param(pname)
    except KeyError:
        return ""
    # values are shown in SI: the SI unit of the role (a file's own unit, e.g. K/kW, would mislabel them)
    si = {"resistance": "K/W", "conductance": "W/K", "capacitance": "J/K", "heat_flow": "W", "time_constant": "s",
          "temperature": "K", "offset": "K"}
    if p.role in si:
        return si[p.role]
    from ..lang import format_dim

    try:
        return format_dim(p.dim) if p.dim else ""
    except Exception:  # noqa: BLE001 - display only
        return ""


def _var_unit(net: Network, label: str) -> tuple[str, float, float]:
    """(unit text, display offset, display scale) for a variable's value: temperatures shown in the
    file's unit (a centred value is the same in K and degC)."""
    if label.startswith("T("):
        return ("K", 0.0, 1.0)
    for i in net.inputs:
        if i.name == label:
            if i.is_temperature:
                return ("K", 0.0, 1.0)
            return (i.unit or "", 0.0, 1.0)
    return ("", 0.0, 1.0)


def _words(c: Candidate, params, ext: Extended, eng: _Engine, model) -> str:
    net = ext.network
    if c.kind in ("param_dependence", "wrong_constant"):
        p = net.param(c.target)
        nominal = p.value
        z0, terms = _linear_coeffs(c, params, ext)
        positive = p.role in ("resistance", "conductance", "capacitance", "time_constant")
        where = f" ({p.owner.split(' ', 1)[1] if p.owner and ' ' in p.owner else p.owner})" if p.owner else ""
        where = _element_where(net, c.target) or where
        unit = _unit_of(net, c.target)
        if positive and nominal is not None:
            k = _pos1_slope()
            rel = [(lab, k * s, m) for lab, s, m, _ in terms]
            base_v = nominal * (math.log1p(math.exp(4 * (1 + z0))) / math.log1p(math.exp(4.0)))
            if not rel:
                return f"{c.target}{where} is wrong: ≈ {_fmt(base_v)} {unit} (was {_fmt(nominal)})"
            strengths = _strengths(terms, eng, c)
            dep = " and ".join(f"{lab} ({st})" for (lab, _, _), st in zip(rel, strengths))
            inner = " ".join(f"{'+' if r >= 0 else '−'} {_fmt(abs(r) / (1 + k * z0) if 1 + k * z0 else abs(r))}·({lab} − {_fmt(m if not lab.startswith('T(') else m - 273.15, 3)}{' °C' if lab.startswith('T(') else ''})"
                             for lab, r, m in rel)
            return (f"{c.target}{where} depends on {dep}: {c.target} ≈ {_fmt(base_v)}·(1 {inner}) {unit}")
        y_scale = _out_scale(params, c)
        off = y_scale * z0
        if not terms:
            return f"{c.target}{where} is wrong by {_fmt(off)} {unit}"
        inner = " ".join(f"{'+' if s >= 0 else '−'} {_fmt(abs(y_scale * s))}·({lab} − {_fmt(m, 3)})" for lab, s, m, _ in terms)
        return f"{c.target}{where} depends on {', '.join(t[0] for t in terms)}: Δ{c.target} ≈ {_fmt(off)} {inner} {unit}"
    if c.kind in ("heat_load", "unused_column"):
        z0, terms = _linear_coeffs(c, params, ext)
        y_scale = _out_scale(params, c)
        node = c.target[2:-1]
        if not terms:
            return f"unmodelled constant heat load at {node}: Q ≈ {_fmt(y_scale * z0)} W"
        inner = " ".join(f"{'+' if s >= 0 else '−'} {_fmt(abs(y_scale * s))}·({lab} − {_fmt(m, 3)})" for lab, s, m, _ in terms)
        what = "data column" if c.kind == "unused_column" else ""
        return (f"unmodelled heat load at {node} depending on {what + ' ' if what else ''}{', '.join(t[0] for t in terms)}:"
                f" Q[{node}] ≈ {_fmt(y_scale * z0)} {inner} W")
    if c.kind == "missing_link":
        g = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"missing conduction path {c.element['a']}–{c.element['b']}: G ≈ {_fmt(g)} W/K (R ≈ {_fmt(1 / g) if g > 0 else '∞'} K/W)"
    if c.kind == "radiation":
        a = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"missing radiation {c.element['a']}–{c.element['b']}: ε·A ≈ {_fmt(a)} m²"
    if c.kind == "sensor_offset":
        o = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"sensor {c.target} reads {_fmt(o)} K {'high' if o > 0 else 'low'} (offset)"
    if c.kind == "sensor_lag":
        tau = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"sensor {c.target} lags its node {c.element['node']}: first-order lag τ ≈ {_fmt(tau)} s"
    if c.kind == "thermal_mass":
        from .candidates import mass_values

        el = c.element
        v = mass_values(net, c, params)
        return (f"missing thermal mass between {el['a']} and {el['b']}: a node {el['node']} of C ≈ {_fmt(v['C'])} J/K"
                f" splitting link {el['link']} ({el['a']}–{el['b']}, R ≈ {_fmt(v['R'])} K/W in total),"
                f" {100 * v['f']:.0f} % of it on the {el['a']} side; its own time constant C·f(1−f)·R ≈ {_fmt(v['tau'])} s")
    if c.kind == "source_mass":
        from .candidates import source_mass_values

        el = c.element
        v = source_mass_values(net, c, params)
        return (f"missing heat capacity behind source {el['source']}: it heats a node {el['node']} of C ≈ {_fmt(v['C'])}"
                f" J/K joined to {el['at']} by R ≈ {_fmt(v['R'])} K/W (time constant C·R ≈ {_fmt(v['tau'])} s), not"
                f" {el['at']} directly")
    return c.describe()


def _element_where(net: Network, pname: str) -> str:
    for l in net.links:
        if l.value == pname:
            return f" ({l.a}–{l.b})"
    for n in net.nodes:
        if n.capacitance == pname:
            return f" (capacity of {n.name})"
    return ""


def _strengths(terms, eng: _Engine, c: Candidate) -> list[str]:
    """'strongly' / 'weakly' by each term's share of the variation it causes (slope × spread)."""
    eff = [abs(s) * sc for _, s, _, sc in terms]
    top = max(eff) if eff else 0.0
    return ["strongly" if e >= 0.5 * top else "weakly" for e in eff]


# ---------------------------------------------------------------------------------------------
# The extension as .thn text
# ---------------------------------------------------------------------------------------------


def _var_text(net: Network, kind: str, name: str) -> str:
    if kind == "node":
        return f"T{name}" if name.isdigit() else name
    return name


def _clause(c: Candidate, params, ext: Extended, eng: _Engine) -> str:
    net = ext.network
    if c.kind in ("param_dependence", "wrong_constant"):
        if not c.vars:
            return f"learn {c.target} as const"
        return f"learn {c.target} as linear({', '.join(_var_text(net, k, v) for k, v in c.vars)})"
    if c.kind in ("heat_load", "unused_column"):
        if not c.vars:
            return f"learn {c.target} as const"
        return f"learn {c.target} as linear({', '.join(_var_text(net, k, v) for k, v in c.vars)})"
    if c.kind == "missing_link":
        g = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        a, b = (_var_text(net, "node", c.element["a"]), c.element["b"])
        b = _var_text(net, "node", b) if b in net.node_names else b
        return f"G {c.element['a']} -- {c.element['b']} = {max(g, 1e-9):.4g} W/K  free"
    if c.kind == "radiation":
        a = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return (f"radiation {c.element['a']} -- {c.element['b']}  area = {max(a, 1e-9):.4g} m^2 free"
                f"  emissivity = 1")
    if c.kind == "sensor_offset":
        o = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"offset {o:.4g} K free"
    if c.kind == "sensor_lag":
        tau = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        return f"lag {tau:.4g} s free"
    if c.kind == "thermal_mass":  # the new node and the two links (the .thn extension has the parameters too)
        from .candidates import mass_lines

        return "; ".join(mass_lines(net, c, params)[2:])
    if c.kind == "source_mass":  # the new node and its link (the source's line moves to the new node)
        from .candidates import source_mass_lines

        return "; ".join(source_mass_lines(net, c, params))
    return ""


def _merged_clauses(accepted: list[Candidate], params, ext: Extended, eng: _Engine) -> list[str]:
    """One clause per target: dependence candidates on the same target merge into one function with
    several inputs (``learn R as linear(u1, T(hx1))``); targets with the same inputs share one clause."""
    by_target: dict[str, list[Candidate]] = {}
    order: list[str] = []
    out: list[str] = []
    for c in accepted:
        if c.kind in ("param_dependence", "wrong_constant", "heat_load", "unused_column"):
            if c.target not in by_target:
                order.append(c.target)
            by_target.setdefault(c.target, []).append(c)
    groups: dict[tuple, list[str]] = {}
    gorder: list[tuple] = []
    net = ext.network
    for tgt in order:
        vars_: list[tuple[str, str]] = []
        for c in by_target[tgt]:
            for v in c.vars:
                if v not in vars_:
                    vars_.append(v)
        key = tuple(vars_)
        if key not in groups:
            gorder.append(key)
        groups.setdefault(key, []).append(tgt)
    for key in gorder:
        tg = ", ".join(groups[key])
        if key:
            out.append(f"learn {tg} as linear({', '.join(_var_text(net, k, v) for k, v in key)})")
        else:
            out.append(f"learn {tg} as const")
    for c in accepted:
        if c.kind in ("missing_link", "radiation"):
            out.append(_clause(c, params, ext, eng))
    for c in accepted:
        if c.kind == "thermal_mass":  # the split link's value, the share f, the new node, the two new links
            from .candidates import mass_lines

            out += mass_lines(net, c, params)
    for c in accepted:
        if c.kind == "source_mass":  # the new node and its link; the source's own line is moved in the text
            from .candidates import source_mass_lines

            out += source_mass_lines(net, c, params)
    return out


def _extend_text(text: str, clauses: list[str], accepted: list[Candidate], net: Network, params, ext, unused):
    """The input text plus the chosen clauses (and sensor offsets edited in place); a unified diff."""
    import difflib

    if not accepted:
        return text, ""
    lines = text.splitlines()
    for c in accepted:
        if c.kind not in ("sensor_offset", "sensor_lag"):
            continue
        s = next(s for s in net.sensors if s.name == c.target)
        o = float(np.asarray(params[c.element["param"]]).reshape(-1)[0])
        if s.span is not None and 1 <= s.span.line <= len(lines):
            ln = lines[s.span.line - 1]
            m = re.search(r"\bcolumn\b", ln)
            ins = f"offset {o:.4g} K free  " if c.kind == "sensor_offset" else f"lag {o:.4g} s free  "
            lines[s.span.line - 1] = (ln[: m.start()] + ins + ln[m.start():]) if m else ln.rstrip() + "  " + ins.strip()
    # a thermal mass replaces its link: the original line is commented out (its value is a `param` line now)
    for c in accepted:
        if c.kind != "thermal_mass":
            continue
        link = next((l for l in net.links if l.name == c.element["link"]), None)
        if link is None or link.span is None:
            continue
        for ln in range(link.span.line, link.span.end_line + 1):
            if 1 <= ln <= len(lines):
                lines[ln - 1] = (f"# (split by `tnnc diagnose` at the new thermal mass {c.element['node']}, see below) "
                                 + lines[ln - 1])
    # a capacity behind a source: the source's line now heats the new node (or, if the line has another form,
    # it is commented out and written again below)
    moved_src: list[str] = []
    for c in accepted:
        if c.kind != "source_mass":
            continue
        from .candidates import source_line_moved

        src = next((sr for sr in net.sources if sr.name == c.element["source"]), None)
        if src is None or src.span is None or not 1 <= src.span.line <= len(lines):
            continue
        new_line = source_line_moved(lines[src.span.line - 1], c) if src.span.line == src.span.end_line else None
        if new_line is not None:
            lines[src.span.line - 1] = new_line
        else:
            for ln in range(src.span.line, src.span.end_line + 1):
                lines[ln - 1] = f"# (moved by `tnnc diagnose` to the new node {c.element['node']}, see below) " + lines[ln - 1]
            moved_src.append(f"source {c.element['node']} = {c.element['value']}")
    # a learned constant of the original network that now depends on something: its clause is replaced
    # (the dependent targets get their own clause; the others stay constant)
    for fname in dict.fromkeys(c.element.get("learned") for c in accepted if c.element.get("learned")):
        fn = next((f for f in net.learned if f.name == fname), None)
        if fn is None or fn.span is None:
            continue
        moved = {c.target for c in accepted if c.element.get("learned") == fname}
        for ln in range(fn.span.line, fn.span.end_line + 1):
            if 1 <= ln <= len(lines):
                lines[ln - 1] = "# (replaced by `tnnc diagnose`, see below) " + lines[ln - 1]
        rest = [t.name for t in fn.targets if t.name not in moved]
        if rest:
            clauses = [f"learn {', '.join(rest)} as {fn.kind}"] + list(clauses)
    used_inputs = {v for c in accepted for k, v in c.vars if k == "input"}
    add = ["", "# ---- added by `tnnc diagnose` -------------------------------------------------"]
    for name, col in unused:
        if name in used_inputs:
            add.append(f'input {name} : [1]  column "{col}"')
    for c in accepted:
        add.append(f"# {c.describe()}")
    add += clauses + moved_src
    new = "\n".join(lines).rstrip("\n") + "\n" + "\n".join(add) + "\n"
    diff = "".join(difflib.unified_diff(text.splitlines(True), new.splitlines(True), "original", "extended"))
    return new, diff


def _check_text(text: str, filename: str) -> None:
    """Re-load the extension to make sure it is a valid ``.thn`` (a failure here is a bug: say so)."""
    from ..lang import loads

    loads(text, filename=filename)


def _what_is_left(res: R.ResidualSummary) -> str:
    parts = []
    for s, w in res.whiteness.items():
        sig = res.sigma[s]
        if w.get("white"):
            parts.append(f"{s}: white noise of σ ≈ {sig:.3g} K")
        else:
            dep = res.dependence.get(s, {})
            worst = max(dep.items(), key=lambda kv: abs(kv[1].get("corr", 0)), default=None)
            extra = (f"; largest correlation with {worst[0]} (r = {worst[1]['corr']:.2f})"
                     if worst and abs(worst[1].get("corr", 0)) > 0.2 else "")
            parts.append(f"{s}: structure it cannot explain (residual not white, Ljung–Box p = "
                         f"{w.get('ljung_box_p', 0):.2g}, MAE {res.errors[s]['mae']:.3g} K, noise σ ≈ {sig:.3g} K{extra})")
    return "; ".join(parts)
