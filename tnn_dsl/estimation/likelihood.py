"""The continuous–discrete extended-Kalman-filter likelihood of a compiled network (maximum-likelihood
grey-box identification in the manner of CTSM-R / pySIP; Bacher & Madsen 2011, Kristensen et al. 2004).

Model (states ``T`` K, inputs ``u`` held over each sample interval)::

    dT = f(T, u; θ) dt + diag(σ_w) dω          σ_w,i  K/√s, one per state
    y_k = h(T_k, u_k) + e_k,   e_k ~ N(0, diag(σ_v²))   σ_v,j  K, one per sensor
    T(t_0) ~ N(x0, diag(p0_std²))

Filter (the convention of :mod:`tnn_dsl.estimation.kalman`: the prior ``x0, P0`` is at the first sample;
update with ``y_k``, then predict over ``[t_k, t_k + dt)`` with ``u_k``)::

    update   ε = y − h(x⁻)    S = H P⁻ Hᵀ + R    K = P⁻ Hᵀ S⁻¹    x = x⁻ + K ε
             P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ                                   (Joseph form)
    predict  x⁻ = Φ(x, u)     P⁻ = F P Fᵀ + Q_d,   F = ∂Φ/∂x (automatic differentiation)
    −log L = ½ Σ_k [ log det S_k + ε_kᵀ S_k⁻¹ ε_k + m_k log 2π ]

``Φ`` is the model's own integrator over one sample (``Model.rollout``: ``rk4``/``euler``/``expeuler`` with
the sub-steps chosen for stability), so the mean prediction is exactly the simulation the rest of the package
uses, and ``F`` its exact derivative. ``H = ∂h/∂x`` likewise. A missing reading (NaN) removes that sensor's
row for that sample (its row and column of ``S`` become the identity, its innovation zero): ``m_k`` counts
the readings present, and a sample without any only predicts.

**Process noise.** ``Q_d = ∫₀^Δt e^{As} Σ e^{Aᵀs} ds`` with ``Σ = diag(σ_w²)`` and ``A = ∂f/∂T`` at the filtered
state: the exact discretisation of the linearised system, the block that Van Loan's (1978) matrix exponential
of ``[[−A, Σ], [0, Aᵀ]]·Δt`` gives. That exponential is not formed as such: its ``e^{−AΔt}`` block overflows the
digits on a stiff network (``|λ|Δt = 30`` loses every digit of ``Q_d``), and ``torch.linalg.matrix_exp``
returns ``Q_d`` to only ~1e-11 relative. Instead, by scaling and squaring on the pair: on ``h = Δt/2ˢ``, with
``|λ|h ≤ 2⁻¹⁰`` at the nominal parameters (``s`` from the fastest time constant; Gershgorin ``|λ| ≤ 2/τ_min``),
the Taylor series (to order 12) ``G_h = e^{Ah} − I`` and ``Q_h = Σ_k h^{k+1}/(k+1)! L^k(Σ)``, ``L(X) = AX + XAᵀ``,
then ``s`` exact doublings ``Q_{2h} = Q_h + e^{Ah} Q_h e^{Aᵀh}``, ``G_{2h} = 2G_h + G_h²`` — only sums of
positive semi-definite terms and products of decaying factors, so ``Q_d`` is accurate to round-off on any
network (where the plain Van Loan exponential overflows), the same matrix products on both backends, and
differentiable. The margin of ``2⁻¹⁰`` keeps the
truncation below round-off while the parameters move up to ~100-fold from their nominal values. For a
linear network this is the exact discrete Kalman filter's ``Q_d`` (with ``expeuler`` on a one-node network,
whose step is exact, the whole filter is exact; with ``rk4`` the mean and ``F`` are the integrator's, and
``Q_d`` exact). The cost is ``3·12 + 3s`` products of ``n × n`` matrices per sample (``s = 4`` for Bacher &
Madsen's Ti at 5-min samples; a stiff two-node chain, ``|λ|Δt = 3300``, still gives ``Q_d`` to 1e-15);
``qd="euler"`` (``Q_d = Σ·Δt``, what :func:`~tnn_dsl.estimation.kalman.ekf` uses) is the cheap alternative
for large networks, consistent only to first order in ``Δt``. Checked (tests/test_likelihood.py) against Van
Loan's exponential in 80-digit arithmetic: ≤ 1e-12 relative with every conductance moved 100-fold either way
from the values the doublings were chosen for (``|λ|Δt`` up to 80).

**Constant linearisation.** The JAX trace of ``H``, ``F`` and ``A`` (for a torch model, that of its network
compiled for JAX) is read once per model (a dependency analysis of the program, followed into nested calls and
``scan`` carries; anything it does not follow counts as a dependence): when none depends on the state or the
input — a linear network with constant coefficients, e.g.
Bacher & Madsen's building models — they and ``Q_d`` are formed once per evaluation, outside the scan (``Q_d``'s
three loops then rolled, a small compiled body each), and each sample only runs the model's step and the
Riccati recursion. Same operations, same values (value and gradient within 1e-14 relative of the per-sample
form on TiTh/TiTeTh); on TiTeTh, one run each on a loaded 2-core machine (2026-11-24), compiling the gradient
took 4.7 → 2.5 s of CPU and an evaluation 70 → 12 ms. With one sensor, ``S`` is a number: divided by, not
factorised.

Everything is written once against the backend's namespace; the loop over samples is the adapter's
``scan`` (``jax.lax.scan``; a Python loop on torch), differentiable end to end on both backends (the
Jacobians inside the filter are forward-mode JVPs on JAX and one reverse pass kept differentiable on torch, whose
forward mode runs through Python reference implementations; reverse mode differentiates either again). Eager torch
prepares the model once per record (``Model.sample_steps``) and, with a constant linearisation, integrates every
sample's interval at once, the step then being affine in the state (:func:`_parts`), and runs the stretches where
the covariance has settled as one vectorised linear recursion (:func:`_stationary_runs`). A torch fit of a long
record (:class:`LikelihoodProblem`, :data:`SCAN_MIN_SAMPLES`) with a constant linearisation runs that filter as
compiled scans instead (:mod:`.torch_filter`), whether or not the covariance settles.

Entry points: :func:`nll` (a backend scalar, differentiable), :func:`loglik` (a float),
:func:`innovations` (one-step predictions and standardised residuals, numpy), and
:class:`LikelihoodProblem`, the likelihood as a pure function of one flat vector (log-parameters, log noise
levels, initial state) for an optimiser.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..compiler import INTEGRATORS, backend_of, check_step
from ..core import Diagnostic, TnnError

__all__ = ["nll", "loglik", "innovations", "Innovations", "LikelihoodProblem", "QD_METHODS"]

QD_METHODS = ("vanloan", "euler")
_LOG_2PI = math.log(2.0 * math.pi)
_TAYLOR = 12
"""Order of the Taylor series of ``e^{Ah}`` and ``Q_h`` on the base step of ``Q_d``."""
_ACCURATE_STEP = 0.5
"""Without explicit ``substeps``, explicit integrators take sub-steps of at most this fraction of the fastest time
constant (at the nominal parameters) — for accuracy, not only stability: the mean's discretisation error is read
by the likelihood as signal when the measurement noise is small. Bacher & Madsen's TiTeTh (5-min samples, heater
node τ = 360 s as written): one RK4 step per sample (stable) stops at log L = 5431.0; 2 sub-steps (this rule)
5437.12; 4 and 8 sub-steps 5437.42 and 5437.43 (CTSM-R, exact discretisation: 5437.0). Measured 2026-11-24."""
_MARGIN = 10
"""``log2`` of the margin between the base step ``|λ|h`` and 1 at the nominal parameters."""


# ---------------------------------------------------------------------------------------------
# Checks and static choices
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Static:
    """What is fixed per (model, record length, dt): the integrator's sub-steps and the doublings of Q_d."""

    dt: float
    integrator: str
    substeps: int
    qd: str
    doublings: int
    constant: bool = False
    """The linearisation (``H``, ``F``, ``A``, hence ``Q_d``) does not depend on the state or the input (JAX's
    trace of the network shows it; a linear network with constant coefficients): formed once per evaluation."""


def _static(model, inputs, outputs, dt, integrator, substeps, qd) -> tuple[_Static, np.ndarray, np.ndarray]:
    if model.backend not in ("jax", "torch"):
        raise TnnError(Diagnostic(f"the likelihood needs automatic differentiation; backend {model.backend!r} has "
                                  "none", hint="compile with backend='jax' or backend='torch'"))
    if integrator not in INTEGRATORS:
        raise TnnError(Diagnostic(f"unknown integrator {integrator!r}", hint="use one of: " + ", ".join(INTEGRATORS)))
    if qd not in QD_METHODS:
        raise TnnError(Diagnostic(f"unknown process-noise discretisation {qd!r}",
                                  hint="use one of: " + ", ".join(QD_METHODS)))
    if not model.output_names:
        raise TnnError(Diagnostic(f"network {model.network.name!r} has no sensors; the likelihood needs one",
                                  hint="declare `sensor NAME = NODE column \"...\"`"))
    U = np.asarray(inputs, dtype=np.float64)
    Y = np.asarray(outputs, dtype=np.float64)
    n_in, n_out = len(model.input_names), len(model.output_names)
    if U.ndim != 2 or U.shape[1] != n_in:
        raise TnnError(f"inputs must have shape (N, {n_in}), got {U.shape}")
    if Y.shape != (U.shape[0], n_out):
        raise TnnError(f"outputs must have shape ({U.shape[0]}, {n_out}), got {Y.shape}")
    if U.shape[0] < 1:
        raise TnnError("the record is empty")
    if not np.all(np.isfinite(U)):
        raise TnnError(Diagnostic("the inputs hold NaN or infinite values; the filter needs every input",
                                  hint="fill or drop the missing input samples"))
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise TnnError(f"dt must be a positive number of seconds, got {dt!r}")
    dt = float(dt)
    tau, where = model.fastest_time_constant()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sub = check_step(integrator, dt, tau, substeps, where)
    if substeps is None and integrator in ("rk4", "euler") and math.isfinite(tau) and tau > 0:
        sub = max(sub, math.ceil(dt / (_ACCURATE_STEP * tau)))
    # Q_d's base step h = dt/2^s with |λ|h ≤ 2/τ_min·h ≤ 2^-10 at the nominal parameters
    s = 0
    if qd == "vanloan":
        s = max(0, math.ceil(math.log2(2.0 * dt / tau) + _MARGIN)) if math.isfinite(tau) and tau > 0 else _MARGIN
    st = _Static(dt, integrator, sub, qd, s)
    if _HOIST:
        st = _Static(dt, integrator, sub, qd, s, _constant_linearisation(model, st))
    return st, U, Y


def _as(B, x, n: int, what: str):
    """A backend vector of length ``n`` from numpy/lists/numbers; backend arrays (possibly traced or
    requiring a gradient) pass through unchanged."""
    if isinstance(x, (np.ndarray, list, tuple, float, int, np.floating)):
        a = np.asarray(x, dtype=np.float64).reshape(-1)
        if a.size == 1 and n > 1:
            a = np.full(n, float(a[0]))
        if a.shape != (n,):
            raise TnnError(f"{what} must have {n} entries, got {a.shape}")
        return B.asarray(a)
    shape = tuple(x.shape)
    if shape != (n,):
        raise TnnError(f"{what} must have shape ({n},), got {shape}")
    return x


# ---------------------------------------------------------------------------------------------
# The filter, written once against a namespace
# ---------------------------------------------------------------------------------------------


def _process_noise(B, A, sw2, st: _Static, rolled: bool = False):
    """``Q_d (n, n)`` for the linearised drift ``A`` and the intensity ``diag(sw2)`` (module docstring).
    ``rolled``: the three loops as the backend's ``scan`` (one small compiled body each; for the single
    ``Q_d`` of a constant linearisation) instead of written out (inside the filter's own scan)."""
    m = B.xp
    if st.qd == "euler":
        return m.diag(sw2) * st.dt
    h = st.dt / 2.0 ** st.doublings
    Ah = A * h
    I = 0.0 * A + B.asarray(np.eye(A.shape[0]))

    def loop(body, carry, coefficients):
        if rolled:
            return B.scan(lambda c, k: (body(c, k[0]), k[0]), carry, (B.asarray(np.asarray(coefficients, float)),))[0]
        for k in coefficients:
            carry = body(carry, k)
        return carry

    def horner(G, k):  # G = e^{Ah} − I = Ah (I + Ah/2 (I + Ah/3 (…)))
        return Ah @ (I + G) / k

    def series(TQ, c):  # Q_h = Σ_k h^{k+1}/(k+1)! L^k(Σ),  L(X) = A X + X Aᵀ = A X + (A X)ᵀ for a symmetric X
        T, Q = TQ
        AT = A @ T
        T = (AT + AT.T) * c
        return T, Q + T

    def double(QG, _):  # Q_2h = Q_h + e^{Ah} Q_h e^{Aᵀh},   e^{2Ah} − I = 2G + G²
        Q, G = QG
        E = I + G
        return Q + E @ Q @ E.T, 2.0 * G + G @ G

    G = loop(horner, Ah / _TAYLOR, [float(k) for k in range(_TAYLOR - 1, 0, -1)])
    T = m.diag(sw2) * h
    _, Q = loop(series, (T, T), [h / (k + 1) for k in range(1, _TAYLOR + 1)])
    Q, _ = loop(double, (Q, G), [0.0] * st.doublings)
    return 0.5 * (Q + Q.T)


def _parts(B, model, st: _Static, params, U):
    """``(outputs(x, u), step(x, u, k), rhs(x, u), jac, affine)``: the sensors, the integrator over sample ``k``'s
    interval (``u = U[k]``) and the drift, each on a leading batch axis of ``x``; ``jac(f, x, rows) = (f(x),
    ∂f/∂x)`` (:func:`_jac`);
    ``affine(x_ref, F)``, where not ``None``, the step of a constant linearisation ``F = ∂Φ/∂x``.

    Eager torch steps the model prepared once for the record (:meth:`~tnn_dsl.compiler.model.Model.sample_steps`:
    the parameters' preparation and the inputs' part of the drift once, not once per sample and per Jacobian), and
    with a constant linearisation (the step is then affine in the state: ``Φ(x, u_k) = Φ(x_ref, u_k) + F (x −
    x_ref)`` exactly) integrates every sample's interval at once from ``x_ref``, leaving each sample one product
    with ``F``: the filter's Python loop and its reverse pass then run a few operations per sample, not the
    integrator's stages. JAX traces :meth:`~tnn_dsl.compiler.model.Model.rollout` of one interval, compiled once with
    the filter (its program as before)."""
    m = B.xp
    I_s = B.asarray(np.eye(len(model.state_names)))
    if B.name == "torch":
        prepared = model.sample_steps(params, U, st.dt, integrator=st.integrator, substeps=st.substeps)

        def affine(x_ref, F):
            phi = prepared.step_all(x_ref[None, :] + 0.0 * U[:, :1])  # Φ(x_ref, u_k), one row per k
            rows = phi.unbind(0)

            def step_affine(x, u, k):
                return rows[int(k)] + (x - x_ref) @ F.T
            step_affine.phi = phi  # type: ignore[attr-defined]  # every row at once (_stationary_runs)
            return step_affine

        return prepared.outputs, (lambda x, u, k: prepared.step(x, k, eager=True)), prepared.rhs, _jac(B, I_s), affine

    def step(x, u, k):
        states, _ = model.rollout(params, x, m.stack([u, u], axis=0), st.dt, integrator=st.integrator,
                                  substeps=st.substeps)
        return states[..., 1, :]

    return ((lambda x, u: model.outputs(params, x, u)), step, (lambda x, u: model.rhs(params, x, u)), _jac(B, I_s),
            None)


def _jac(B, I_s):
    """``jac(f, x, rows) = (f(x), ∂f/∂x (rows, ns))`` for ``f`` with ``rows`` outputs on a leading batch axis."""
    if B.name == "torch":
        torch = B.torch

        def jac_reverse(f, x, rows):
            """One reverse pass over ``rows`` copies of ``x``: the gradient of ``Σ_i f(X)[i, i]`` is row ``i`` of the
            Jacobian in row ``i`` of ``X``; kept differentiable (``create_graph``) where the caller differentiates.
            Not forward mode: torch 2.13 runs forward-mode derivatives (``torch.func.jvp``, dual tensors) of even an
            addition through its Python reference implementations, ~0.1 ms an operation — 10 ms a sample of the
            filter on one node (2026-12-05)."""
            outer = torch.is_grad_enabled()
            with torch.enable_grad():
                X = x.unsqueeze(0).expand(rows, x.shape[-1])
                if not X.requires_grad:
                    X = X.detach().requires_grad_(True)
                Y = f(X)
                (G,) = torch.autograd.grad(torch.diagonal(Y).sum(), X, create_graph=outer, allow_unused=True)
            if G is None:
                G = torch.zeros_like(X)
            return (Y[0], G) if outer else (Y[0].detach(), G.detach())
        return jac_reverse

    def jac(f, x, rows):
        """``(f(x), ∂f/∂x (n_f, ns))`` by one forward-mode pass over ``ns`` copies of ``x``, copy ``i`` along
        ``e_i`` (``f`` takes a leading batch axis; differentiable again in reverse mode; no ``vmap``, and the
        primal ``f(x)`` comes with it)."""
        X = x[None, :] + 0.0 * I_s
        y, dy = B.jvp(f, (X,), (I_s,))
        return y[0], dy.T

    return jac


_HOIST = True
"""Form a state- and input-independent linearisation once per evaluation instead of per sample (both backends; the
tests switch it off to compare the two)."""
_CONSTANT: dict = {}


def _constant_linearisation(model, st: _Static) -> bool:
    """Whether ``H = ∂h/∂x``, ``F = ∂Φ/∂x`` and ``A = ∂f/∂x`` are independent of the state and the input — read
    off the JAX trace of the three Jacobians (a dependency analysis of the program, not a numerical test; a
    construct it does not follow counts as a dependence). A torch model's answer is read off the JAX compilation
    of its network: both backends run the same equations (one physics module), so the dependences are the same.
    On torch the per-sample form costs three Jacobians and ``Q_d``'s series at every sample in eager torch: formed
    once, an evaluation of a one-node RC model's likelihood and gradient on 20 samples took 65 instead of 330 ms,
    and its fit 7.6–8.9 instead of 40.6 s (JAX 2.8–3.9 s; tests/test_ml_fit.py's
    ``test_jax_and_torch_reach_the_same_optimum``, 2026-12-04; both forms are faster since, see
    ``benchmarks/bench_likelihood.py``). Cached per model and static choices."""
    key = (id(model), st)
    hit = _CONSTANT.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    try:
        traced = model
        if model.backend != "jax":
            from ..compiler import compile as compile_network

            traced = compile_network(model.network, "jax", sparse=getattr(model, "sparse", None))
        B = backend_of(traced)
        out, step, rhs, jac, _ = _parts(B, traced, st, traced.init_params(), None)
        ns, no = len(model.state_names), len(model.output_names)

        def jacobians(x, u):
            return (jac(lambda z: out(z, u), x, no)[1], jac(lambda z: step(z, u, 0), x, ns)[1],
                    jac(lambda z: rhs(z, u), x, ns)[1])

        x = B.xp.asarray(np.full(len(model.state_names), 293.15))
        u = B.xp.asarray(np.ones(len(model.input_names)))
        closed = B.jax.make_jaxpr(jacobians)(x, u)
        const = not any(_depends(closed.jaxpr, [True, True]))
    except Exception:  # noqa: BLE001 - anything unexpected: the general path
        const = False
    if len(_CONSTANT) > 64:
        _CONSTANT.clear()
    _CONSTANT[key] = (model, const)
    return const


_CALLS = ("jit", "pjit", "closed_call", "core_call", "custom_jvp_call", "remat", "remat2", "checkpoint")


def _depends(jaxpr, flags: list[bool]) -> list[bool]:
    """For each output of a jaxpr, whether it depends on the inputs flagged ``True`` (followed into nested calls
    and through ``scan`` carries; any other construct with a flagged input makes all its outputs depend)."""
    from jax.extend.core import Literal

    dep = {v for v, f in zip(jaxpr.invars, flags) if f}
    for eqn in jaxpr.eqns:
        ins = [not isinstance(v, Literal) and v in dep for v in eqn.invars]
        if not any(ins):
            continue
        name = eqn.primitive.name
        sub = eqn.params.get("jaxpr", eqn.params.get("call_jaxpr")) if name in _CALLS + ("scan",) else None
        sub = getattr(sub, "jaxpr", sub)
        if name == "scan" and sub is not None:
            nc, nk = eqn.params["num_consts"], eqn.params["num_carry"]
            cur = list(ins)
            while True:  # a carry depends once its initial value or any iteration's update does
                od = _depends(sub, cur)
                nxt = cur[:nc] + [a or b for a, b in zip(ins[nc:nc + nk], od[:nk])] + ins[nc + nk:]
                if nxt == cur:
                    break
                cur = nxt
        elif sub is not None and len(sub.invars) == len(ins) and len(sub.outvars) == len(eqn.outvars):
            od = _depends(sub, ins)
        else:
            od = [True] * len(eqn.outvars)
        dep.update(v for v, d in zip(eqn.outvars, od) if d)
    return [not isinstance(v, Literal) and v in dep for v in jaxpr.outvars]


def _filter(B, model, st: _Static, params, U, Y, lsw, lsv, x0, lp0, scan: bool = False):
    """``(−log L, (ŷ⁻ (N, n_out), ε (N, n_out), √diag(H P⁻ Hᵀ + R) (N, n_out), x⁻ (N, n), √diag P⁻ (N, n)))``
    with ε zero where a reading is missing (backend arrays). ``scan``: on torch, a constant linearisation runs as
    the compiled scans of :mod:`.torch_filter` (:func:`_scan_pays`)."""
    m = B.xp
    ns, no = len(model.state_names), len(model.output_names)
    I_s = B.asarray(np.eye(ns))
    sw2 = m.exp(2.0 * lsw)
    sv2 = m.exp(2.0 * lsv)
    out, step, rhs, jac, affine = _parts(B, model, st, params, U)
    if st.constant:  # H, F, A and Q_d once, at any point (they depend on neither)
        H0 = jac(lambda z: out(z, U[0]), x0, no)[1]
        F0 = jac(lambda z: step(z, U[0], 0), x0, ns)[1]
        A0 = jac(lambda z: rhs(z, U[0]), x0, ns)[1]
        Qd0 = _process_noise(B, A0, sw2, st, rolled=True)
        if affine is not None:
            step = affine(x0, F0)

    def body(carry, uym):
        x, P = carry
        u, y, okf, k = uym  # y: 0 where missing, okf: 1.0 where read (float: torch's bool * 1.0 is float32); k: index
        ok = okf > 0.5
        # update with the readings present
        if st.constant:
            yhat, H = out(x[None, :], u)[0], H0
        else:
            yhat, H = jac(lambda z: out(z, u), x, no)
        Hm = H * okf[:, None]
        HP = Hm @ P
        S = HP @ Hm.T + m.diag(m.where(ok, sv2, 1.0))
        eps = (y - yhat) * okf
        if no == 1:  # one sensor: S is a number (no factorisation to compile and differentiate)
            K = (HP / S[0, 0]).T
            logdet, quad = m.log(m.abs(S[0, 0])), eps[0] * eps[0] / S[0, 0]  # log|S| as slogdet
        else:
            K = B.solve(S, HP).T
            logdet, quad = m.linalg.slogdet(S)[1], eps @ B.solve(S, eps)
        x_f = x + K @ eps
        IKH = I_s - K @ Hm
        P_f = IKH @ P @ IKH.T + (K * (okf * sv2)[None, :]) @ K.T
        P_f = 0.5 * (P_f + P_f.T)
        term = logdet + quad + m.sum(okf) * _LOG_2PI
        # predict over the sample interval
        if st.constant:
            x_n, F, Qd = step(x_f[None, :], u, k)[0], F0, Qd0
        else:
            x_n, F = jac(lambda z: step(z, u, k), x_f, ns)
            Qd = _process_noise(B, jac(lambda z: rhs(z, u), x_f, ns)[1], sw2, st)
        P_n = F @ P_f @ F.T + Qd
        P_n = 0.5 * (P_n + P_n.T)
        sd_y = m.sqrt(B.clip_min(m.diagonal(H @ P @ H.T) + sv2, 0.0))
        sd_x = m.sqrt(B.clip_min(m.diagonal(P), 0.0))
        return (x_n, P_n), (term, yhat, eps, sd_y, x, sd_x)

    if lp0 is None:  # CTSM's default: the process noise accumulated over one sample interval
        P0 = Qd0 if st.constant else _process_noise(B, jac(lambda z: rhs(z, U[0]), x0, ns)[1], sw2, st)
    else:
        P0 = m.diag(m.exp(2.0 * lp0))
    mask = m.isfinite(Y)
    zero = 0.0 * U[:, :1]  # (N, 1) zeros of the floating type (U is finite)
    Y0, okf = m.where(mask, Y, zero), m.where(mask, 1.0 + zero, zero)
    index = B.asarray(np.arange(U.shape[0]))  # the sample's index (the torch step's prepared inputs; JAX ignores it)
    scanned = None
    if st.constant and affine is not None and scan and _SCAN_USABLE:
        scanned = _filter_scan(x0, P0, H0, F0, Qd0, sv2, step.phi, Y0, okf, out(x0[None, :] + zero, U) - x0 @ H0.T)
    if scanned is not None:
        terms, yhat, eps, sd_y, xs, sd_x = scanned
    elif st.constant and affine is not None and _STATIONARY:
        terms, yhat, eps, sd_y, xs, sd_x = _stationary_runs(
            B, body, (x0, P0), (U, Y0, okf, index), H0=H0, F0=F0, sv2=sv2, x_ref=x0, phi=step.phi, outputs_at=out)
    else:
        _, (terms, yhat, eps, sd_y, xs, sd_x) = B.scan(body, (x0, P0), (U, Y0, okf, index))
    return 0.5 * m.sum(terms), (yhat, eps, sd_y, xs, sd_x)


_STATIONARY = True
"""Eager torch, constant linearisation: run the stretches where the filter's covariance has settled as one
vectorised recursion (:func:`_stationary_runs`; the tests switch it off to compare)."""
SCAN_MIN_SAMPLES = 1000
"""Records of at least this many samples: a torch fit (:class:`LikelihoodProblem`) of a constant linearisation runs
the filter as compiled scans (:mod:`.torch_filter`), unless the environment variable ``TNN_TORCH_COMPILE`` decides
(``1`` always, ``0`` never). Bacher & Madsen's Ti with a second node (1691 samples, ``python
benchmarks/bench_likelihood.py``, 2026-12-06, the AMD host): one value and gradient 48 ms compiled (JAX 38 ms)
against 130 ms eager where the covariance settles and 1.9 s where it does not, for 13 s of compiling on an empty
inductor cache, once per process and per ``(states, sensors)`` shape — every candidate of a model doctor of that
shape shares it; a fit takes 100–300 evaluations."""
_SCAN_USABLE = True
"""False once torch failed to compile the scans in this process (warned once; the eager filter runs)."""


def _scan_pays(B, n_samples: int) -> bool:
    """Whether a torch fit of ``n_samples`` runs its filter as compiled scans (:data:`SCAN_MIN_SAMPLES`)."""
    import os

    if B.name != "torch" or not _SCAN_USABLE:
        return False
    env = os.environ.get("TNN_TORCH_COMPILE", "").strip()
    if env in ("0", "1"):
        return env == "1"
    return int(n_samples) >= SCAN_MIN_SAMPLES


def _filter_scan(x0, P0, H0, F0, Qd0, sv2, phi, Y0, okf, d):
    """:func:`.torch_filter.filter_scan` (``x_ref = x0``), or ``None`` when torch cannot compile it here (inside a
    ``torch.func`` transform, or its compiler failed: warned once, and the eager filter serves the process)."""
    global _SCAN_USABLE
    import torch

    if torch._C._are_functorch_transforms_active():
        return None
    from .torch_filter import filter_scan

    try:
        return filter_scan(x0, P0, H=H0, F=F0, Q=Qd0, sv2=sv2, x_ref=x0, phi=phi, Y0=Y0, okf=okf, d=d)
    except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
        from ..compiler.model import TorchCompileWarning

        _SCAN_USABLE = False
        warnings.warn(f"torch.compile failed on the likelihood's filter ({type(e).__name__}: {str(e)[:200]}); it "
                      "runs eager", TorchCompileWarning, stacklevel=2)
        return None


_SETTLED_RTOL = 1e-15
"""The covariance has settled when one sample moves no entry of ``P⁻`` by more than this times its largest entry,
two samples in a row."""
_MIN_RUN = 8
"""Fewer fully read samples than this after the covariance settles: stepped one by one as before."""


def _stationary_runs(B, body, carry, xs, *, H0, F0, sv2, x_ref, phi, outputs_at):
    """The filter of a constant linearisation on eager torch, with its stationary stretches vectorised.

    ``H``, ``F`` and ``Q_d`` being constant, the covariance recursion does not depend on the data: once ``P⁻``
    settles (:data:`_SETTLED_RTOL`, in floating point the fixed point of the Riccati recursion) and while every
    sensor is read, ``S``, ``K`` and ``P⁻`` stay as they are, and the mean follows the linear recursion
    ``x⁻_{k+1} = M x⁻_k + c_k`` with ``M = F (I − K H)`` and ``c_k = Φ(x_ref, u_k) − F x_ref + F K (y_k − d_k)``,
    ``d_k = h(x_ref, u_k) − H x_ref`` (the step and the sensors are affine in the state). Such a stretch of ``L``
    samples is summed by doubling (``⌈log₂ L⌉`` rounds of one batched product) instead of ``L`` trips through the
    sample loop, forward and reverse; the rest (the start, until ``P⁻`` settles, and every sample with a reading
    missing) runs ``body`` sample by sample, as :meth:`Backend.scan` does. The values agree with the sample loop to
    round-off (the tests, with the stretches off: −log L 1e-12, gradient 1e-9 relative). ``phi (N, n)``:
    ``Φ(x_ref, u_k)`` for every sample. Returns the scan's stacked outputs ``(terms, ŷ⁻,
    ε, sd_y, x⁻, sd_x)``."""
    torch = B.torch
    U, Y0, okf, index = xs
    N = int(U.shape[0])
    full = (okf > 0.5).all(dim=-1).tolist()
    run_end = [N] * (N + 1)  # run_end[k]: one past the last sample of the fully read run starting at k (k: none)
    for k in range(N - 1, -1, -1):
        run_end[k] = run_end[k + 1] if full[k] else k
    pieces: list[tuple] = []
    settled, k = 0, 0
    x, P = carry
    while k < N:
        end = run_end[k]
        if settled >= 2 and end - k >= _MIN_RUN:
            x, block = _stationary_block(torch, x, P, Y0[k:end], U[k:end], phi[k:end], outputs_at, H0, F0, sv2, x_ref)
            pieces.append(block)
            k = end
            continue
        (x, P_n), outs = body((x, P), (U[k], Y0[k], okf[k], index[k]))
        with torch.no_grad():
            moved = float((P_n - P).abs().max()) <= _SETTLED_RTOL * float(P.abs().max())
        settled = settled + 1 if moved and full[k] else 0
        P = P_n
        pieces.append(tuple(o[None] for o in outs))
        k += 1
    return tuple(torch.cat([pc[i] for pc in pieces], 0) for i in range(6))


def _stationary_block(torch, x, P, Y, U, phi, outputs_at, H0, F0, sv2, x_ref):
    """``L`` fully read samples from the prior ``x`` (n,) with the settled ``P⁻`` (n, n): ``(x⁻ after the last,
    (terms, ŷ⁻, ε, sd_y, x⁻, sd_x) each with a leading axis L)`` (see :func:`_stationary_runs`)."""
    L, n = int(Y.shape[0]), int(x.shape[0])
    HP = H0 @ P
    S = HP @ H0.T + torch.diag(sv2)
    K = torch.linalg.solve(S, HP).T  # (n, n_out)
    logdet = torch.linalg.slogdet(S)[1]
    Sinv = torch.linalg.inv(S)
    M = F0 @ (torch.eye(n, dtype=x.dtype) - K @ H0)
    d = outputs_at(x_ref[None, :] + 0.0 * U[:, :1], U) - x_ref @ H0.T  # (L, n_out): the sensors' affine part
    c = phi - x_ref @ F0.T + (Y - d) @ (F0 @ K).T  # (L, n)
    v = torch.cat([x[None, :], c[:-1]], 0)  # v_0 = x⁻ at the first sample, v_j = c_{j-1}; doubling sums them
    Md, step = M, 1
    while step < L:
        v = torch.cat([v[:step], v[step:] + v[:-step] @ Md.T], 0)
        Md, step = Md @ Md, 2 * step
    x_next = v[-1] @ M.T + c[-1]
    yhat = v @ H0.T + d
    eps = Y - yhat
    quad = ((eps @ Sinv) * eps).sum(-1)
    n_out = int(Y.shape[1])
    terms = logdet + quad + n_out * _LOG_2PI
    sd_y = torch.sqrt(torch.clamp(torch.diagonal(H0 @ P @ H0.T) + sv2, min=0.0)).expand(L, n_out)
    sd_x = torch.sqrt(torch.clamp(torch.diagonal(P), min=0.0)).expand(L, n)
    return x_next, (terms, yhat, eps, sd_y, v, sd_x)


_CACHE: dict = {}


def _runner(B, model, st: _Static):
    """The filter as one function of the backend arrays, jitted on JAX (kept per model and static choices)."""
    key = (id(model), st)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]
    if len(_CACHE) > 32:
        _CACHE.clear()
    fn = B.jit(lambda params, U, Y, lsw, lsv, x0, lp0: _filter(B, model, st, params, U, Y, lsw, lsv, x0, lp0))
    _CACHE[key] = (model, fn)
    return fn


def _run(model, params, inputs, outputs, dt, log_sigma_w, log_sigma_v, x0, log_p0_std, integrator, substeps, qd):
    B = backend_of(model)
    st, U, Y = _static(model, inputs, outputs, dt, integrator, substeps, qd)
    ns, no = len(model.state_names), len(model.output_names)
    args = (_as(B, log_sigma_w, ns, "log_sigma_w"), _as(B, log_sigma_v, no, "log_sigma_v"), _as(B, x0, ns, "x0"),
            None if log_p0_std is None else _as(B, log_p0_std, ns, "log_p0_std"))
    return B, _runner(B, model, st)(params, B.asarray(U), B.asarray(Y), *args)


# ---------------------------------------------------------------------------------------------
# Public functions
# ---------------------------------------------------------------------------------------------


def nll(model: Any, params: Mapping[str, Any], inputs: Any, outputs: Any, dt: float, *, log_sigma_w: Any,
        log_sigma_v: Any, x0: Any, log_p0_std: Any = None, integrator: str = "rk4", substeps: int | None = None,
        qd: str = "vanloan") -> Any:
    """The negative log-likelihood ``−log L`` of a record under the stochastic network (module docstring), a
    backend scalar, differentiable in ``params`` and in every backend-array argument.

    Parameters
    ----------
    model : compiled :class:`~tnn_dsl.Model`, JAX or torch backend
    params : the model's parameter table (backend arrays)
    inputs : (N, n_inputs) SI, zero-order hold; ``outputs``: (N, n_outputs) K, NaN where missing
    dt : s, the sample time
    log_sigma_w : (n_states,) log of the process-noise intensity, σ_w in K/√s
    log_sigma_v : (n_outputs,) log of the measurement-noise standard deviation, σ_v in K
    x0 : (n_states,) K, the initial state's mean at the first sample
    log_p0_std : (n_states,) the log of its standard deviation (K); default (``None``) CTSM's convention, the
        covariance ``Q_d`` that the process noise accumulates over the first sample interval (CTSM-R's
        ``initialVarianceScaling = 1``). Estimating ``P0`` together with ``x0`` is degenerate when ``σ_v → 0``
        (the first reading then pins ``x0`` exactly and the likelihood grows without bound).
    integrator, substeps : the mean's discretisation (as ``Model.rollout``); ``qd``: ``"vanloan"`` (exact for
        the linearised system) or ``"euler"`` (``Σ·Δt``)

    Numpy arguments become backend constants; pass backend arrays to differentiate in them.
    """
    return _run(model, params, inputs, outputs, dt, log_sigma_w, log_sigma_v, x0, log_p0_std, integrator, substeps,
                qd)[1][0]


def loglik(model: Any, params: Mapping[str, Any], inputs: Any, outputs: Any, dt: float, *, log_sigma_w: Any,
           log_sigma_v: Any, x0: Any, log_p0_std: Any = None, integrator: str = "rk4", substeps: int | None = None,
           qd: str = "vanloan") -> float:
    """``log L`` as a float (:func:`nll` without a gradient)."""
    B = backend_of(model)
    run = B.no_grad(lambda: _run(model, params, inputs, outputs, dt, log_sigma_w, log_sigma_v, x0, log_p0_std,
                                 integrator, substeps, qd)[1][0])
    return -float(B.numpy(run()))


@dataclass
class Innovations:
    """One-step-ahead predictions of the filter (numpy, float64; what residual checks need).

    ``predicted (N, n_outputs)`` K: ``ŷ_{k|k−1}`` for every sensor; ``innovations (N, n_outputs)`` K:
    ``y_k − ŷ_{k|k−1}``, NaN where the reading is missing; ``std (N, n_outputs)`` K: the innovation's standard
    deviation ``√(H P⁻ Hᵀ + R)_jj`` (for a missing reading: the prediction's); ``states``/``state_std``
    ``(N, n_states)`` K: ``x_{k|k−1}`` and ``√diag P_{k|k−1}``; ``loglik``: ``log L``; :attr:`loglik_rows` its
    per-sample terms (sensor by sensor)."""

    predicted: np.ndarray
    innovations: np.ndarray
    std: np.ndarray
    states: np.ndarray
    state_std: np.ndarray
    output_names: tuple[str, ...]
    state_names: tuple[str, ...]
    loglik: float

    @property
    def standardized(self) -> np.ndarray:
        """``ε / std`` (N, n_outputs): ≈ white N(0, 1) for a model and noise levels consistent with the data."""
        return self.innovations / self.std

    @property
    def loglik_rows(self) -> np.ndarray:
        """``(N,)`` each sample's Gaussian log-likelihood ``Σ_j −½(log 2π s_j² + ε_j²/s_j²)`` over its sensors
        read (NaN where none was): the terms of ``log L`` (with one innovation covariance per sensor, its
        diagonal), for comparing two predictors sample by sample."""
        eps, sd = self.innovations, self.std
        ok = np.isfinite(eps) & np.isfinite(sd) & (sd > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            terms = np.where(ok, -0.5 * (np.log(2.0 * np.pi * sd**2) + (eps / sd) ** 2), 0.0)
        return np.where(ok.any(axis=1), terms.sum(axis=1), np.nan)


def innovations(model: Any, params: Mapping[str, Any], inputs: Any, outputs: Any, dt: float, *, log_sigma_w: Any,
                log_sigma_v: Any, x0: Any, log_p0_std: Any = None, integrator: str = "rk4", substeps: int | None = None,
                qd: str = "vanloan") -> Innovations:
    """The filter's one-step predictions, innovations and their standard deviations (:class:`Innovations`)."""
    B = backend_of(model)
    run = B.no_grad(lambda: _run(model, params, inputs, outputs, dt, log_sigma_w, log_sigma_v, x0, log_p0_std,
                                 integrator, substeps, qd)[1])
    v, (yhat, eps, sd_y, xs, sd_x) = run()
    Y = np.asarray(outputs, dtype=np.float64)
    eps = np.where(np.isfinite(Y), B.numpy(eps), np.nan)
    return Innovations(B.numpy(yhat), eps, B.numpy(sd_y), B.numpy(xs), B.numpy(sd_x), tuple(model.output_names),
                       tuple(model.state_names), -float(B.numpy(v)))


# ---------------------------------------------------------------------------------------------
# The likelihood as a function of one flat vector
# ---------------------------------------------------------------------------------------------


class LikelihoodProblem:
    """``−log L`` as a pure function of one flat numpy/backend vector ``z``, for an optimiser.

    Layout of ``z`` (:attr:`labels` names every entry): the free constant parameters (``free``; default every
    trainable physical parameter), each as ``log`` of its SI value when it is positive (a positive role, or a
    lower bound ≥ 0 and a positive value) else the SI value; then the learned functions' arrays named in ``free``
    (flattened, as stored: ``NAME[i]``); then ``log σ_w`` (n_states), ``log σ_v``
    (n_outputs), the initial state as an offset in K from :attr:`x0_ref` (``fit_x0``), and ``log p0_std``
    (``fit_p0``). What is not in ``z`` is held at the values given.

    ``problem.nll(z)`` → backend scalar (differentiable; ``z`` a backend vector); ``problem.value_and_grad(z)``
    → ``(float, ndarray)`` (numpy in, jitted on JAX); ``problem.unpack(z)`` → the ``nll`` keyword arguments;
    ``problem.values(z)`` → ``{label: value}`` in natural units (SI, σ's not logged, x0 in K);
    ``problem.bounds()``: L-BFGS-B bounds from the parameters' declared ranges.
    """

    def __init__(self, model: Any, params: Mapping[str, Any], inputs: Any, outputs: Any, dt: float, *,
                 free: Sequence[str] | None = None, log_sigma_w: Any = math.log(1e-3), log_sigma_v: Any = math.log(0.1),
                 x0: Any = None, log_p0_std: Any = None, fit_x0: bool = True, fit_p0: bool = False,
                 integrator: str = "rk4", substeps: int | None = None, qd: str = "vanloan") -> None:
        self.model = model
        self.B = B = backend_of(model)
        self.static, U, Y = _static(model, inputs, outputs, dt, integrator, substeps, qd)
        self.U, self.Y = B.asarray(U), B.asarray(Y)
        self.params = dict(params)
        ns, no = len(model.state_names), len(model.output_names)
        specs = model.param_specs
        pn = model.to_numpy(params)
        if free is None:
            free = [k for k, s in specs.items() if s.kind == "physical" and s.trainable]
        self.free, self.logged = [], []
        z, labels = [], []
        learned = [name for name in free if specs.get(name) is not None and specs[name].kind == "weights"]
        free = [name for name in free if name not in learned]
        for name in free:
            s = specs.get(name)
            if s is None or s.kind != "physical":
                raise TnnError(Diagnostic(f"cannot estimate {name!r}: not a constant parameter or learned array of "
                                          "the network"))
            v = float(pn[name])
            log = bool(s.positive or (s.lower is not None and s.lower >= 0 and v > 0))
            if log and not v > 0:
                raise TnnError(f"parameter {name!r} must be positive to be estimated in log space, got {v}")
            self.free.append(name)
            self.logged.append(log)
            z.append(math.log(v) if log else v)
            labels.append(f"log {name}" if log else name)
        # learned functions' arrays, flattened, in their own (linear) coordinates, after the constants
        self.learned = [(name, tuple(np.shape(pn[name]))) for name in learned]
        for name, shape in self.learned:
            flat = np.asarray(pn[name], dtype=np.float64).reshape(-1)
            z += list(flat)
            labels += [f"{name}[{i}]" for i in range(flat.size)]
        self.n_learned = sum(int(np.prod(shape)) for _, shape in self.learned)
        if x0 is None:  # the steady state of the first inputs, the sensors' nodes moved to their first readings
            x0 = _default_x0(model, params, U, Y)
        self.x0_ref = np.asarray(x0, dtype=np.float64).reshape(-1)
        if fit_p0 and log_p0_std is None:
            log_p0_std = 0.0
        self.fixed = {"log_sigma_w": np.broadcast_to(np.asarray(log_sigma_w, float), (ns,)).copy(),
                      "log_sigma_v": np.broadcast_to(np.asarray(log_sigma_v, float), (no,)).copy(),
                      "log_p0_std": None if log_p0_std is None
                      else np.broadcast_to(np.asarray(log_p0_std, float), (ns,)).copy()}
        if self.x0_ref.shape != (ns,):
            raise TnnError(f"x0 must have {ns} entries, got {self.x0_ref.shape}")
        z += list(self.fixed["log_sigma_w"]) + list(self.fixed["log_sigma_v"])
        labels += [f"log sigma_w[{s}]" for s in model.state_names] + [f"log sigma_v[{s}]" for s in model.output_names]
        self.fit_x0, self.fit_p0 = bool(fit_x0), bool(fit_p0)
        if fit_x0:
            z += [0.0] * ns
            labels += [f"x0[{s}] - x0_ref" for s in model.state_names]
        if fit_p0:
            z += list(self.fixed["log_p0_std"])
            labels += [f"log p0_std[{s}]" for s in model.state_names]
        self.z0 = np.asarray(z, dtype=np.float64)
        self.labels = tuple(labels)
        self._x0_ref_b = B.asarray(self.x0_ref)
        self._fixed_b = {k: None if v is None else B.asarray(v) for k, v in self.fixed.items()}
        self._vg = None
        self._scan = _scan_pays(B, U.shape[0])

    def unpack(self, z: Any) -> dict[str, Any]:
        """``{"params", "log_sigma_w", "log_sigma_v", "x0", "log_p0_std"}`` as backend arrays from ``z``."""
        m, ns, no = self.B.xp, len(self.model.state_names), len(self.model.output_names)
        p = dict(self.params)
        for i, (name, log) in enumerate(zip(self.free, self.logged)):
            p[name] = m.exp(z[i]) if log else z[i]
        i = len(self.free)
        for name, shape in self.learned:
            size = int(np.prod(shape))
            p[name] = m.reshape(z[i:i + size], shape)
            i += size
        out = {"params": p, "log_sigma_w": z[i:i + ns], "log_sigma_v": z[i + ns:i + ns + no]}
        i += ns + no
        if self.fit_x0:
            out["x0"] = self._x0_ref_b + z[i:i + ns]
            i += ns
        else:
            out["x0"] = self._x0_ref_b
        out["log_p0_std"] = z[i:i + ns] if self.fit_p0 else self._fixed_b["log_p0_std"]
        return out

    def nll(self, z: Any) -> Any:
        """``−log L`` at ``z`` (a backend vector; numpy is converted): a backend scalar."""
        if isinstance(z, (np.ndarray, list, tuple)):
            z = self.B.asarray(np.asarray(z, dtype=np.float64))
        a = self.unpack(z)
        return _filter(self.B, self.model, self.static, a["params"], self.U, self.Y, a["log_sigma_w"],
                       a["log_sigma_v"], a["x0"], a["log_p0_std"], scan=self._scan)[0]

    def value_and_grad(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """``(−log L, ∂(−log L)/∂z)`` at a numpy ``z`` (JAX: compiled once)."""
        if self._vg is None:
            self._vg = self.B.value_and_grad(self.nll)
        return self._vg(np.asarray(z, dtype=np.float64))

    def values(self, z: np.ndarray) -> dict[str, float]:
        """``{name: value}`` in natural units: parameters SI, ``sigma_w[...]`` K/√s, ``sigma_v[...]`` K,
        ``x0[...]`` K, ``p0_std[...]`` K."""
        z = np.asarray(z, dtype=np.float64)
        out = {}
        for i, (name, log) in enumerate(zip(self.free, self.logged)):
            out[name] = float(np.exp(z[i]) if log else z[i])
        skip = len(self.free) + self.n_learned
        for lab, v in zip(self.labels[len(self.free):skip], z[len(self.free):skip]):
            out[lab] = float(v)
        for lab, v in zip(self.labels[skip:], z[skip:]):
            if lab.startswith("log "):
                out[lab[4:]] = float(np.exp(v))
            else:
                k = self.model.state_names.index(lab[3:lab.index("]")])
                out[lab.split(" - ")[0]] = float(self.x0_ref[k] + v)
        return out

    def bounds(self) -> list[tuple[float | None, float | None]]:
        """L-BFGS-B bounds per entry of ``z``: the free parameters' declared ranges (in log space where logged),
        ``None`` elsewhere."""
        specs = self.model.param_specs
        out: list[tuple[float | None, float | None]] = []
        for name, log in zip(self.free, self.logged):
            lo, hi = specs[name].lower, specs[name].upper
            if log:
                lo = math.log(lo) if lo is not None and lo > 0 else None
                hi = math.log(hi) if hi is not None and hi > 0 else None
            out.append((lo, hi))
        return out + [(None, None)] * (len(self.z0) - len(self.free))


def _default_x0(model, params, U, Y) -> np.ndarray:
    """The steady state of the first inputs with each sensor's node moved to its first reading (as the EKF)."""
    xp = model.xp
    u0 = xp.asarray(U[0])
    x0 = np.asarray(model.to_numpy({"x": model.steady_state(params, u0)})["x"], dtype=np.float64).copy()
    y0 = model.to_numpy({"y": model.outputs(params, xp.asarray(x0), u0)})["y"]
    snames = list(model.state_names)
    for j, s in enumerate(model.network.sensors):
        if np.isfinite(Y[0, j]) and np.isfinite(y0[j]):
            for nm in (s.node, f"{s.name}.lag"):
                if nm in snames:
                    x0[snames.index(nm)] += Y[0, j] - y0[j]
    return x0
