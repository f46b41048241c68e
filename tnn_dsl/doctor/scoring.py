"""The score test: each candidate's linearised correction (forced heat-flow columns through the forced Jacobian,
lag and mass columns), projected off the free directions and ranked on the noise's scale; the shortlist."""

from __future__ import annotations

import itertools
import math
from typing import Callable, Iterator

import numpy as np
from scipy import stats
from scipy.signal import lfilter

from ..analysis import residuals as R
from ..core.memory import release_free_memory
from .base import STRUCTURAL_KINDS, Candidate
from .engine import _Engine
from .selection import _place

FORCED_CHUNK = 8
"""Candidate columns whose forcing series are built and pushed through the forced Jacobian together (the engine's
tangent batch): memory per chunk ``FORCED_CHUNK × N × nodes`` floats, several times over inside the compiled
derivative (issue 18; ``python benchmarks/trace_diagnose_memory.py [--chunk 32]`` prints each call's resident size:
on the 4 h case study a call of 16 takes about half the time of a call of 32). 16 → 8 (2026-11-28, ``--rounds 2
--chunk 8`` against the default, one run each on a busy host): the second score test's highest resident size 743 →
686 MB, the diagnosis' peak then; the forced Jacobians and pointwise derivatives took 15.0 → 18.4 s in round 1's
score test (its first calls compiling) and 13.8 → 15.5 s in round 2's."""
MIN_R2 = 0.02  # a candidate whose linearised fit explains less of the training residual is not fitted


def _score_forced(cur: _Engine, big: _Engine, cands: list[Candidate], cols_of: dict[str, list[int]],
                  accepted: list[Candidate], stop: Callable[[], bool] | None = None, threads: int = 1
                  ) -> list[dict] | None:
    """The score test without simulating the big extended network: every candidate enters the dynamics as
    an extra heat flow per node, ``F_c(t) = C·∂rhs/∂θ_c`` at the current trajectory (the big network's
    right-hand side differentiated pointwise, vectorised over time), plus a direct output term
    ``∂h/∂θ_c`` (sensor offsets). The response of the outputs to ``F_c`` is one forward-mode derivative of
    the *current* network's simulation w.r.t. its forcing inputs (``_with_forcing``), batched over
    candidates: exact in continuous time, the discrete step holding ``F_c`` over each sample. Returns None
    when the two networks' states differ (then the caller uses :func:`_score` on the big network), and an empty
    list when ``stop()`` (the session's budget) said stop between two chunks of ``FORCED_CHUNK`` columns: a score
    test of only some candidates would rank them unfairly, so none is returned. On torch the case study's score test
    took 51 s and overran a 60 s budget by as much (issue 18); a chunk takes a second or two.

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
    inv_c = cur.inv_capacity(X, U)  # (N, ns)
    nn = cur.n_force
    # structural candidates, no simulation of the edit. A thermal mass C_m on a link a–b is an extra heat flow
    # per node (``_candidates.mass_forcing``: −C_m·(1−f)·dT_m/dt into a, −C_m·f·dT_m/dt into b, f = 1/2 here;
    # the proper fit frees f), pushed through the forced Jacobian with the other candidates' F; a sensor lag τ
    # is a direct output term ∂y_s/∂τ = −dT_node/dt.
    struct = [c for c in cands if c.kind in STRUCTURAL_KINDS]
    mass = [c for c in struct if c.kind == "thermal_mass"]
    smass = [c for c in struct if c.kind == "source_mass"]
    rates = cur.rates(X, U) if struct else None  # (N, ns) K/s
    mass_rows: list[tuple[Candidate, float | None, str | None]] = []  # (candidate, C or τ, source part)
    # columns [nominal free and accepted | candidates' (forced response + direct output term) | structural forcings],
    # computed FORCED_CHUNK columns at a time: the forcing series of all candidates at once, (m, N, nodes) floats,
    # held 1 GB on the 4 h case study (issue 18); a chunk holds a few MB. Between chunks the C heap's free pages go
    # back to the system (``release_free_memory``): each chunk's arrays are the size of the last's, but the heap
    # they were freed on is fragmented by what stays, and without it the resident size kept every chunk's peak.
    n0 = len(active_base)
    parts = [cand_idx[s0: s0 + FORCED_CHUNK] for s0 in range(0, len(cand_idx), FORCED_CHUNK)]

    def forcing_of(part: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """A chunk's forcing series ``F (k, N, nodes)`` W and direct output terms ``(k, N, n_out)``."""
        release_free_memory()  # each chunk's arrays are freed on a heap fragmented by the last: give them back
        d_rhs, d_out = big.point_derivs(part, X, U, chunk=FORCED_CHUNK)  # (k, N, ns), (k, N, n_out)
        with np.errstate(divide="ignore", invalid="ignore"):
            F = np.where(np.abs(inv_c[None, :, :nn]) > 0, d_rhs[:, :, :nn] / inv_c[None, :, :nn], 0.0)
        del d_rhs
        return F, d_out

    def response(F: np.ndarray, d_out: np.ndarray) -> np.ndarray:
        J = cur.forced_jacobian([], F, chunk=FORCED_CHUNK)
        J += d_out.reshape(d_out.shape[0], -1)[:, cur.train_idx].T  # the direct output term (sensor offsets)
        return J

    # With a second thread the big network's pointwise derivatives of the next chunk are taken while this thread
    # pushes the last chunk's forcing through the current network (two programs, two cores; one chunk ahead, so one
    # chunk's arrays more in memory); the first chunk's go beside the base columns' forced Jacobian, each compiling
    # its program. The same calls on the same arrays: the same numbers as one after the other (issue 18).
    ahead = _Ahead(forcing_of, parts, stop) if threads > 1 and parts else None
    try:
        blocks = [cur.forced_jacobian(active_base, chunk=FORCED_CHUNK)]
        for part in parts:
            if stop is not None and stop():
                return []
            got = ahead.next() if ahead is not None else forcing_of(part)
            if got is None:  # the budget ran out before the thread ahead started this chunk
                return []
            F, d_out = got
            release_free_memory()
            blocks.append(response(F, d_out))
            del F, d_out
    finally:
        if ahead is not None:
            ahead.close()
    # the structural forcings last, made a chunk at a time (each an (N, nodes) series: all of them at once held
    # ~40 MB through the whole score test on the 4 h case study, issue 18)
    forcings = _structural_forcing(cur, mass, smass, X, U, rates, nn)
    while part_f := list(itertools.islice(forcings, FORCED_CHUNK)):
        if stop is not None and stop():
            return []
        mass_rows += [row for _, row in part_f]
        blocks.append(cur.forced_jacobian([], np.stack([f for f, _ in part_f]), chunk=FORCED_CHUNK))
        del part_f
    cur.forget_linear_steps()
    J_all = np.concatenate(blocks, axis=1)
    del blocks
    if struct:
        J_all, cols_of, cand_idx = _structural_columns(cur, big, struct, mass_rows, J_all, n0, len(cand_idx), X,
                                                       rates, dict(cols_of), cand_idx)
    e = cur.residual()
    return _score_stats(J_all, len(active_base), e.ravel()[cur.train_idx], cands, cand_idx, cols_of,
                        _noise_var(e, cur.train_mask))


class _Ahead:
    """``make(part)`` for each of ``parts`` in order on a thread of its own, at most one result ahead of the consumer
    (:meth:`next`, which raises what ``make`` raised, and returns None once ``stop()`` said stop before a part: the
    budget's rule, no chunk starts once it is spent); :meth:`close` ends the thread, what it holds dropped."""

    def __init__(self, make: Callable[[list[int]], tuple], parts: list[list[int]],
                 stop: Callable[[], bool] | None = None) -> None:
        import queue
        import threading

        self._q: queue.Queue = queue.Queue(maxsize=1)
        self._closed = threading.Event()

        def run() -> None:
            for part in parts:
                if self._closed.is_set():
                    return
                if stop is not None and stop():
                    item: tuple = ("stopped", None)
                else:
                    try:
                        item = ("ok", make(part))
                    except BaseException as exc:  # handed to the consumer, raised there
                        item = ("error", exc)
                while not self._closed.is_set():
                    try:
                        self._q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if item[0] != "ok":
                    return

        self._thread = threading.Thread(target=run, name="tnn-score-ahead", daemon=True)
        self._thread.start()

    def next(self) -> tuple | None:
        kind, value = self._q.get()
        if kind == "error":
            raise value
        return value

    def close(self) -> None:
        import queue

        self._closed.set()
        while True:  # a result waiting to be put is let go
            try:
                self._q.get_nowait()
            except queue.Empty:
                break
        self._thread.join()


def _structural_forcing(cur: _Engine, mass: list[Candidate], smass: list[Candidate], X, U, rates, nn: int
                        ) -> Iterator[tuple[np.ndarray, tuple[Candidate, float | None, str | None]]]:
    """Forcing heat flows of the thermal-mass and source-mass candidates, one at a time: ``(F (N, nn) W, what it
    is: (candidate, capacity or τ, source part))``.

    At first order (T_m = (1−f)·T_a + f·T_b) a mass on a link to a constant boundary is exactly a larger
    capacity of a (−C_m(1−f)²·dT_a/dt): only its lag tells them apart. So each mass is also tried with its lag
    at a grid of capacities (``mass_grid``: T_m lagged behind its quasi-static value on the current trajectory,
    the flows divided by C); a source mass gets two columns per τ of a grid, the lag part and the capacity part
    (per J/K of C_h). The column explaining most of the residual is the candidate's
    (:func:`_best_structural_columns`)."""
    from .forcing import mass_forcing, mass_grid, source_lag_forcing, source_tau_grid

    lens = [e.n_steps for e in cur.exps[: cur.n_score_exps]]
    dts = [float(e.dt) for e in cur.exps[: cur.n_score_exps]]
    duration = max(n * d for n, d in zip(lens, dts))
    for c in mass:
        for cg in [None] + mass_grid(cur.net, c, cur.params, min(dts), duration):
            yield mass_forcing(cur.net, c, X, U, cur.params, lens, dts, frac=0.5, rates=rates, mass=cg)[:, :nn], (
                c, cg, None)
    for c in smass:
        for tau in source_tau_grid(min(dts), duration):
            yield source_lag_forcing(cur.net, c, X, U, cur.params, lens, dts, tau)[:, :nn], (c, tau, "lag")
            yield source_lag_forcing(cur.net, c, X, U, cur.params, lens, dts, tau, rates=rates)[:, :nn], (
                c, tau, "capacity")


def _structural_columns(cur: _Engine, big: _Engine, struct: list[Candidate], mass_rows, J_all: np.ndarray, n0: int,
                        n_direct: int, X, rates, cols_of: dict[str, list[int]], cand_idx: list[int]):
    """The score-test columns of the structural candidates appended to ``J_all``: each mass's best forced
    column (the forced Jacobian's last columns), a sensor lag's direct output column ``−dT_n/dt`` at its best
    lag. Returns ``(J_all, cols_of, cand_idx)`` with their column indices after the big engine's."""
    names = list(cur.model.state_names)
    outs = list(cur.model.output_names)
    nsr = cur.n_score_rows
    n_new = 0
    extra_cols = []
    if mass_rows:
        n_c = n0 + n_direct
        Jm, J_all = J_all[:, n_c:], J_all[:, :n_c]
        best = _best_structural_columns(cur, Jm, J_all[:, :n0], mass_rows)
        mass = [c for c in struct if c.kind == "thermal_mass"]
        for c in mass + [c for c in struct if c.kind == "source_mass"]:
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
    return J_all, cols_of, cand_idx


def _best_structural_columns(cur: _Engine, Jm: np.ndarray, J_free: np.ndarray, mass_rows) -> dict:
    """For each mass candidate, the column (a source's lag and capacity columns: the pair) whose projection
    off the free directions explains most of the training residual: ``key -> (share, first column, width)``."""
    r_tr = cur.residual().ravel()[cur.train_idx]
    Ub = _free_basis(J_free)
    rp = r_tr - Ub @ (Ub.T @ r_tr)
    Jp = Jm - Ub @ (Ub.T @ Jm)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = (Jp.T @ rp) ** 2 / (np.sum(Jp * Jp, axis=0) * max(float(rp @ rp), 1e-300))
    share = np.where(np.isfinite(share), share, -1.0)
    best: dict[str, tuple[float, int, int]] = {}
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
    return best


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


EXACT_TWIN_COS = 0.999
"""|cos| at and above which two candidates' linearised corrections are the same equations to the data: every such
twin is listed (a board's offset on T1 and a constant heat at its other heater, with a fitted ambient: ten
candidates at |cos| = 1.000); nearer-than-``cos_min`` ones only up to ``most``."""


def _indistinguishable(chosen: dict, scored: list[dict], cos_min: float = 0.95, most: int = 5) -> list[dict]:
    """Candidates whose linearised correction of the training outputs is (nearly) the same as the chosen
    one's (|cos| ≥ ``cos_min`` between the fitted output changes, free directions projected out): the data
    cannot tell them apart, e.g. two series resistances seen through one sensor (thesis §6.2.4). This is
    the identifiability test of ``tnn_dsl.sensitivity`` (|corr| > 0.95 between sensitivity columns) applied
    to the candidates' columns. Every twin at |cos| ≥ :data:`EXACT_TWIN_COS` is listed, then up to ``most`` of the
    others."""
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
    exact = [d for d in out if d["cos"] >= EXACT_TWIN_COS]
    return exact + [d for d in out if d["cos"] < EXACT_TWIN_COS][:most]


SAME_COS = 0.99999
"""Two candidates with the same number of parameters whose linearised corrections of the training outputs have
|cos| at least this are exact twins: one answer, fitted once (:func:`_shortlist`)."""


def same_correction(a: dict, b: dict, same_cos: float = SAME_COS) -> bool:
    """Score-test entries ``a`` and ``b`` make the same linearised correction (exact twins, same k)."""
    return (a.get("dir") is not None and b.get("dir") is not None and a["k"] == b["k"]
            and abs(float(np.dot(a["dir"].astype(float), b["dir"].astype(float)))) >= same_cos)


SHORTLIST_TOP = 3
"""Distinct candidates fitted properly per round by default (``diagnose(top=)``, ``tnnc diagnose --top``): the best by
score, to which :func:`_shortlist` adds a physical rival of heat loads and the best extensions of the user's own
``learn`` clauses, and the round adds candidates tied with the list. Five until 2026-12-05; three is what the
hidden-effect suite has always been run and judged with (``benchmarks/diagnose_suite.py``), and on the case study and
the real-data examples the answers were the same with three as with five — every finding, gain and value — in less
time (the case study's diagnosis 98.6 → 83.1 s with two threads, 122.4 → 96.3 s with one, run one after the other;
TCLab's four rounds 55.2 → 44.7 s; BENCHMARKS.md "Diagnosis: time and memory", 2026-12-05). A wider search:
``top=5``."""


def _shortlist(scored: list[dict], top: int, same_cos: float = SAME_COS) -> list[dict]:
    """The ``top`` best by score among *distinct* candidates, plus (compensation guard) the best-scoring
    physical-placement candidate when only heat loads made the list, so a heat load never wins without a
    physical rival being fitted.

    Distinct: two candidates with the same number of parameters whose linearised corrections of the
    training outputs coincide (|cos| ≥ ``same_cos``, e.g. a heat load at a node and the error of the source
    there) would be fitted twice for one answer; only the more physical (then the better-scoring) one is
    fitted, the other is listed under ``"same"`` of the one kept (reported as indistinguishable)."""
    short: list[dict] = []
    for s in scored:
        twin = next((t for t in short if same_correction(t, s, same_cos)), None)
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
