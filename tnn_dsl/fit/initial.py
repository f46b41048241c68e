"""Initial states: where every free run starts, by one documented rule.

A free run (training with single shooting, validation, ``evaluate``, ``simulate``) needs the state of every node at
the first sample. Measured data rarely start at rest: a building with a 15 h time constant, a board switched on
cold. So the state is estimated from the data, never assumed, unless the user asks otherwise:

``estimate`` (the default)
    The initial state is fitted to the measurements of a *burn-in* at the start of the file: a maximum a
    posteriori estimate with the parameters fixed (Gauss–Newton on the forward-mode Jacobian of the rollout with
    respect to the initial state, a step that raises the cost halved; residuals weighted by each sensor's noise
    from first differences; a prior
    around the ``measured`` state, tight for sensed states — their first reading — and weak for the others, so
    the burn-in decides what it sees and leaves what it cannot see where the network puts it). The burn-in is
    excluded from every score. In training with single shooting the initial state of each training file is a
    parameter fitted with the rest, and the trained model stores it, so a training file simulated again
    continues exactly (no burn-in).
``filter``
    An extended Kalman filter runs over the burn-in (:func:`tnn_dsl.estimation.ekf`, from the ``measured``
    state); the free run starts from the filtered state at the burn-in's last sample.
``steady``
    The steady state of the first inputs (thesis §4.5); a warning when a sensor starts more than 1 K away.
``measured``
    That steady state with every sensed node (and its lag state) moved so that its sensor reads the first
    measurement.

The burn-in is ``burn_in`` seconds if given, else :func:`default_burn_in` (a tenth of the file, at least 10
samples, at most half the file).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..compiler import backend_of
from ..core import Diagnostic, TnnError
from ..data import Experiment
from ..ir import Network
from .ranges import start_range

INIT_RULES = ("estimate", "filter", "steady", "measured")
"""The rules for the initial state of a free run (see the module docstring)."""

FAR_FROM_STEADY_K = 1.0
"""A sensor this far (K) from its steady-state reading at the first sample makes ``steady`` warn."""

SENSED_PRIOR_K = 0.1
"""Prior standard deviation (K) of a sensed state's initial value around its first reading (the reading is
nearly the state: the burn-in may refine it, not replace it)."""

UNSENSED_PRIOR_K = 10.0
"""Prior standard deviation (K) of an unsensed state's initial value around the ``measured`` state: weak, so the
burn-in decides what it can see, and what it cannot see stays where the rest of the network puts it."""

MIN_NOISE_K = 0.01
"""Smallest measurement noise (K) assumed when weighting the burn-in's residuals."""

MAX_GN_ITER = 20
"""Rollouts of the burn-in an estimate may take (a Gauss–Newton iteration, or a halved step tried again)."""

GN_MAX_HALVINGS = 6
"""A Gauss–Newton step that raises the weighted cost is halved and tried again, at most this many times in a row;
then the estimate is the last iterate that lowered it. Without the check the burn-in fits of the case study's M4 (an
MLP Peltier element) on ten out-of-distribution files ran six times to the 20-iteration cap, going uphill (the first
file's cost 4.36·10⁵ → 2.88·10⁶) and returning the last iterate; with it they take 2–6 steps (2026-12-02,
``python benchmarks/profile_burn_in_fits.py --model m4 --files 10``). Where no step goes uphill nothing changes."""

GN_DECREMENT_TOL = 1e-4
"""The burn-in fit stops when the next Gauss–Newton step would lower the weighted cost (chi-square units: residuals
over their noise, plus the prior's term) by less than this, or moves no state by more than 1e-7 K. That predicted
decrease is the step's squared length in the cost's curvature, ``‖W·J·dx‖² + ‖P·dx‖²``, i.e. in units of the
estimate's standard errors: 1e-4 stops when the step would move the estimate by less than 1 % of its standard
error. Measured that way, directions the burn-in cannot see (an unsensed state held by its prior alone) do not
keep it going. On a model far out of its range the fit converges only linearly, and a tighter tolerance paid for
Jacobians that changed nothing: the case study's M5 on ten +40 % files took 2–14 steps a file with 1e-8, the
cost moving by less than 0.03 chi-square a step over the last half of them (2026-12-02, ``python
benchmarks/profile_burn_in_fits.py --model m5 --files 10 --cache DIR --every-file``, DIR a ``tnnc demo --out DIR``)."""


@dataclass
class InitialState:
    """Where a free run starts.

    ``T`` (n_states,) K is the state at sample ``at`` (0 for every rule but ``filter``); samples before
    ``burn_in`` are not scored; ``rule`` is the rule applied (``stored`` for a training file's own fitted
    state); ``notes`` are lines for the user (warnings start with ``warning:``)."""

    T: np.ndarray
    at: int
    burn_in: int
    rule: str
    notes: list[str] = field(default_factory=list)
    prefix_outputs: np.ndarray | None = None
    """``filter``: the filtered outputs (at, n_outputs) K before the free run starts."""
    params: dict[str, float] = field(default_factory=dict)
    """The values (SI) of the network's per-experiment parameters for this file: estimated with the state
    (``estimate``), stored (a training file) or the training files' mean (the other rules)."""


def check_rule(init: str) -> str:
    """``init`` if it is a rule (``auto`` is read as ``estimate``), else a :class:`TnnError`."""
    if init == "auto":
        return "estimate"
    if init not in INIT_RULES:
        raise TnnError(Diagnostic(f"unknown initial-state rule {init!r}",
                                  hint=f"use one of: {', '.join(INIT_RULES)}"))
    return init


def default_burn_in(n_samples: int) -> int:
    """Samples of burn-in at the start of an ``n_samples`` file: a tenth, at least 10, at most half."""
    return int(min(max(10, round(0.1 * n_samples)), n_samples // 2))


def burn_in_samples(exp: Experiment, burn_in_s: float | None) -> int:
    """The burn-in of ``exp`` in samples: ``burn_in_s`` seconds (rounded, at most half the file), else the
    default."""
    n = int(np.asarray(exp.inputs).shape[0])
    if burn_in_s is None:
        return default_burn_in(n)
    if not (math.isfinite(burn_in_s) and burn_in_s >= 0):
        raise TnnError(Diagnostic(f"burn-in must be a non-negative number of seconds, got {burn_in_s!r}",
                                  hint="e.g. --burn-in 600"))
    return int(min(round(burn_in_s / float(exp.dt)), n // 2))


def fingerprint(exp: Experiment) -> str:
    """A hash of an experiment's sample step, inputs and outputs: the key under which a trained model stores the
    fitted initial state of a training file (found again whatever the file is called)."""
    h = hashlib.sha256()
    h.update(np.float64(exp.dt).tobytes())
    h.update(np.ascontiguousarray(np.asarray(exp.inputs, dtype=np.float64)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(exp.outputs, dtype=np.float64)).tobytes())
    return h.hexdigest()


def measured_state(net: Network, model: Any, params: Mapping[str, Any], u0: np.ndarray,
                   y0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The steady state of ``u0`` (n_inputs,) SI and the ``measured`` state (each sensed node and its lag state
    moved by the mean gap between the first reading ``y0`` (n_outputs,) K and the steady reading), both
    (n_states,) K; returns ``(steady, measured)``."""
    B = backend_of(model)
    ub = B.asarray(np.asarray(u0, dtype=np.float64))
    T0 = B.numpy(model.steady_state(params, ub))
    if not np.all(np.isfinite(T0)):
        raise TnnError(Diagnostic("the steady state of the first inputs could not be computed (not finite)",
                                  hint="check the network's parameters; a node with no path to a boundary has no "
                                       "steady state"))
    if y0 is None or not np.isfinite(y0).any():
        return T0, T0.copy()
    gap = np.asarray(y0, dtype=float) - B.numpy(model.outputs(params, B.asarray(T0), ub))
    idx = {n: i for i, n in enumerate(model.state_names)}
    shifts: dict[int, list[float]] = {}
    for k, s in enumerate(net.sensors):
        if np.isfinite(gap[k]):
            for name in (s.node, f"{s.name}.lag"):
                if name in idx:
                    shifts.setdefault(idx[name], []).append(float(gap[k]))
    T = T0.copy()
    for i, g in shifts.items():
        T[i] += float(np.mean(g))
    return T0, T


def sensed_states(model: Any, net: Network, params_np: Mapping[str, np.ndarray] | None) -> list[tuple[int, int, float]]:
    """``[(state index, output index, offset K)]``: the states a first measurement sets directly (a sensor's node
    and its lag state, less the sensor's offset), for batched windows (:func:`measured_arrays`)."""
    names = list(model.state_names)
    out = []
    seen = set()
    for j, s in enumerate(net.sensors):
        off = 0.0
        if s.offset and params_np is not None and s.offset in params_np:
            off = float(np.asarray(params_np[s.offset]).reshape(()))
        for t in [s.node] + ([f"{s.name}.lag"] if s.lag else []):
            if t in names and t not in seen:
                seen.add(t)
                out.append((names.index(t), j, off))
    return out


def measured_arrays(mapping: list[tuple[int, int, float]], n_states: int,
                    y0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mask (..., n_states) bool`` and ``values (..., n_states)`` K from first readings ``y0 (..., n_out)``: the
    states :func:`sensed_states` sets (NaN readings leave them to the steady state)."""
    y0 = np.asarray(y0, dtype=float)
    mask = np.zeros(y0.shape[:-1] + (n_states,), dtype=bool)
    vals = np.zeros(y0.shape[:-1] + (n_states,), dtype=float)
    for i, j, off in mapping:
        ok = np.isfinite(y0[..., j])
        mask[..., i] = ok
        vals[..., i] = np.where(ok, y0[..., j] - off, 0.0)
    return mask, vals


def _steady_warning(model: Any, params: Mapping[str, Any], T0: np.ndarray, u0: np.ndarray,
                    y0: np.ndarray | None) -> list[str]:
    if y0 is None:
        return []
    B = backend_of(model)
    gap = np.asarray(y0, dtype=float) - B.numpy(model.outputs(params, B.asarray(T0), B.asarray(u0)))
    if not np.isfinite(gap).any() or np.nanmax(np.abs(gap)) <= FAR_FROM_STEADY_K:
        return []
    k = int(np.nanargmax(np.abs(gap)))
    return [f"warning: the data do not start at rest: at the steady state of the first inputs "
            f"{model.output_names[k]} would read {abs(gap[k]):.2f} K {'below' if gap[k] > 0 else 'above'} its first "
            f"measurement; use --init estimate (the default) or --init measured"]


class _BurnInFit:
    """Least squares of the outputs over a burn-in with respect to the initial state (params fixed); the
    rollout and its Jacobian are compiled once per model, integrator, step and burn-in length, and kept in the
    model's own cache (``model._jit_cache``), so they go with the model. A class-level cache kept up to 64
    models and their compiled programs alive: the model doctor, which compiles a network per shortlist and per
    continued fit, held 300 MB more at its peak on the case study (issue 18)."""

    fJ: Any = None
    """``J(p, U, x)`` (n_t, n_out, n_unknowns), beside ``fy(p, U, x)`` (n_t, n_out); ``None`` where ``fyJ`` gives
    both."""
    fyJ: Any = None
    """``(y, J)`` from one call (JAX's forward mode, torch's central differences), or ``None``."""

    def __init__(self, model: Any, dt: float, n: int, integrator: str, substeps: int | None,
                 pe_names: tuple[str, ...] = ()):
        key = ("burn_in_fit", repr(float(dt)), int(n), integrator, substeps, pe_names)
        self.packable = not pe_names  # per-experiment values are set by name, beside the packed constants
        cache = getattr(model, "_jit_cache", None)
        if not isinstance(cache, dict):
            cache = {}  # a model without a cache of its own: compiled for this fit only
        hit = cache.get(key)
        if hit is not None:
            self.fy, self.fJ, self.fyJ = hit
            return
        B = backend_of(model)

        ns = len(model.state_names)
        n_unknowns = ns + len(pe_names)
        n_readings = int(n) * len(model.output_names)

        def outputs(params, U, x):  # x = [T0 (n_states) K, the per-experiment parameters (SI)]
            p = dict(params)
            for i, k in enumerate(pe_names):
                p[k] = x[ns + i] + 0.0 * params[k]
            return model.rollout(p, x[:ns], U, float(dt), integrator=integrator, substeps=substeps)[1]

        # the burn-in's programs run a few Gauss–Newton iterations per estimate: XLA's lean options (``Backend.jit``)
        if n_unknowns > n_readings:  # a large network: one reverse pass per reading, not a tangent per state
            self.fy = B.jit(B.no_grad(outputs), lean=True) if B.name == "jax" else B.no_grad(outputs)
            self.fJ = _reverse_jacobian(B, outputs, n_readings)
        elif B.name == "jax":
            # the readings and their Jacobian from one program (``jacfwd`` runs the rollout from ``x`` as its primal
            # anyway): one compilation a network and burn-in length instead of two, and one call a Gauss–Newton
            # iteration instead of two (a halved trial step calls the same program and keeps the readings). The model
            # doctor compiles these for every network it fits (issue 18: 84 → 75 programs in the case study's
            # diagnosis, the same estimates to the bit)
            jax = B.jax
            yJ = B.jit(lambda p, U, x: jax.jacfwd(lambda T: (outputs(p, U, T),) * 2, has_aux=True)(x)[::-1],
                       lean=True)
            self.fyJ = yJ
            self.fy = lambda p, U, x: yJ(p, U, x)[0]
        elif not pe_names:
            # torch: forward mode (torch.func) cannot call a compiled rollout, and eager it carries a tangent
            # through every operation of every step (about 300 µs a step compiled or not; 16 s an estimate of
            # the case study's M2). Central differences run all perturbed initial states as one batched
            # rollout: about 1 µs a sequence-step compiled, and eager the same per-step dispatch as one
            # sequence (FD_REL_STEP says why the difference quotient is as good as the tangent here)
            self.fy = B.no_grad(outputs)
            self.fyJ = _central_difference_jacobian(B, model, float(dt), integrator, substeps)
        else:
            self.fy = B.no_grad(outputs)
            self.fJ = lambda p, U, T0: B.asarray(B.jacobian(lambda T: outputs(p, U, T), B.numpy(T0)))
        cache[key] = (self.fy, self.fJ, self.fyJ)

    held: list[int]
    """The states the last :meth:`solve` left on an edge of its ``bounds`` (indices)."""

    def solve(self, model: Any, params: Mapping[str, Any], U: np.ndarray, Y: np.ndarray, prior: np.ndarray,
              prior_std: np.ndarray, bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, float]:
        """The unknowns ``x`` (the initial state (n_states,) K, then the per-experiment parameters, SI) minimising
        ``Σ ((ŷ − y)/σ_y)² + Σ ((x − prior)/prior_std)²`` over the burn-in (``U`` (n, n_in), ``Y`` (n, n_out) K
        with NaN where missing; ``σ_y`` per sensor from the readings' first differences); returns ``x`` and the
        burn-in's RMS error (K). ``bounds`` ``(low, high)`` K: every state is kept inside (a projected step); a
        model that cannot explain the start otherwise pushes an unsensed state there, and :attr:`held` says
        which. A step that raises the cost is halved (:data:`GN_MAX_HALVINGS`), so the estimate never ends worse
        than an iterate it has seen. (:func:`_gauss_newton` is the iteration; :func:`solve_batched` runs several
        files' together.)"""
        B = backend_of(model)
        Ub = B.asarray(np.asarray(U, dtype=np.float64))
        if self.packable and hasattr(model, "pack_params"):  # one jit argument, not one per constant
            params = model.pack_params(params)
        steps = _gauss_newton(len(model.state_names), Y, prior, prior_std, bounds, self.fyJ is not None)
        request = next(steps)
        try:
            while True:
                kind, x = request
                if kind == "yJ":  # the readings and their Jacobian from one call
                    answer = tuple(B.numpy(a) for a in self.fyJ(params, Ub, B.asarray(x)))
                elif kind == "y":
                    answer = B.numpy(self.fy(params, Ub, B.asarray(x)))
                else:  # "J"
                    answer = B.numpy(self.fJ(params, Ub, B.asarray(x)))  # (n_t, n_out, n_states)
                request = steps.send(answer)
        except StopIteration as done:
            x, rms, self.held = done.value
        return x, rms


def _gauss_newton(ns: int, Y: np.ndarray, prior: np.ndarray, prior_std: np.ndarray,
                  bounds: tuple[float, float] | None, joint: bool):
    """The burn-in fit's Gauss–Newton iteration (:meth:`_BurnInFit.solve`) as a generator: it yields what it needs
    computed — ``("yJ", x)`` the readings and their Jacobian from one call (``joint``: torch's central differences),
    ``("y", x)`` the readings alone (a trial step), ``("J", x)`` the Jacobian alone — and is sent the answer; it
    returns ``(x, rms K, the states held on a bound)``. Written once, so that one file's fit and several files' fits
    run in lockstep (:func:`solve_batched`: their requests of one kind as one batched call) take the same steps."""
    mask = np.isfinite(Y)
    sig = _noise_std(Y)  # (n_out,)
    W = np.broadcast_to(1.0 / sig, Y.shape)[mask]
    x = np.asarray(prior, dtype=np.float64).copy()
    P = 1.0 / np.asarray(prior_std, dtype=np.float64)
    if bounds is not None:
        x[:ns] = np.clip(x[:ns], bounds[0], bounds[1])
    rms = math.inf
    best: tuple[float, np.ndarray, float] | None = None  # (cost, x, rms) of the last iterate that went downhill
    halvings = 0
    for _ in range(MAX_GN_ITER):
        if joint and not halvings:  # the readings and their Jacobian from one call
            y, J = yield ("yJ", x)
        else:  # a halved step is a trial: its readings alone (torch: one run, not the 2·n + 1 of the batch)
            y = yield ("y", x)
            J = None
        r = (y - Y)[mask]
        with np.errstate(over="ignore", invalid="ignore"):
            cost = float(np.sum((W * r) ** 2) + np.sum((P * (x - prior)) ** 2))
        if best is not None and not cost <= best[0] * (1.0 + 1e-12):
            # the last step went uphill (a nonlinear network far from the linearisation, a state projected
            # onto its bound) or out of the finite: take half of it, at most GN_MAX_HALVINGS times in a row
            halvings += 1
            if halvings > GN_MAX_HALVINGS:
                x, rms = best[1], best[2]
                break
            x = best[1] + 0.5 * (x - best[1])
            continue
        if not math.isfinite(cost):
            break  # the start itself: nothing better to go back to (the run is checked later)
        with np.errstate(over="ignore"):
            rms = float(np.sqrt(np.mean(r * r))) if r.size else 0.0
        best, halvings = (cost, x, rms), 0
        if J is None and joint:  # a trial taken: its Jacobian (the readings as they were)
            J = (yield ("yJ", x))[1]
        elif J is None:
            J = yield ("J", x)  # (n_t, n_out, n_states)
        Jm = J[mask]
        if not (np.all(np.isfinite(Jm)) and np.all(np.isfinite(r))):
            break  # the model's sensitivities overflow here: keep the last state (the run is checked later)
        try:
            dx = gauss_newton_step(Jm, r, W, P, x - prior)
        except np.linalg.LinAlgError:
            break
        step = float(np.max(np.abs(dx))) if dx.size else 0.0
        if step > 50.0:  # a trust region for strongly nonlinear networks (K)
            dx *= 50.0 / step
        x_new = x + dx
        if bounds is not None:
            x_new[:ns] = np.clip(x_new[:ns], bounds[0], bounds[1])
        moved = x_new - x  # the step taken (a state held on a bound does not move)
        x = x_new
        with np.errstate(over="ignore", invalid="ignore"):  # huge sensitivities: inf, the loop goes on
            decrement = float(np.sum((W * (Jm @ moved)) ** 2) + np.sum((P * moved) ** 2))
        if float(np.max(np.abs(moved), initial=0.0)) < 1e-7 or decrement < GN_DECREMENT_TOL:
            break
    else:
        if best is not None:  # out of iterations: the best iterate seen, not an untried last step
            x, rms = best[1], best[2]
    held = [] if bounds is None else [i for i in range(ns) if x[i] <= bounds[0] + 1e-9 or x[i] >= bounds[1] - 1e-9]
    return x, rms, held


def gauss_newton_step(J: np.ndarray, r: np.ndarray, W: np.ndarray, P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The step ``dx`` minimising ``‖W·(r + J·dx)‖² + ‖P·(d + dx)‖²`` (readings ``J (m, n)``, residuals
    ``r (m,)``, weights ``W (m,)``, prior weights ``P (n,) > 0``, distance from the prior ``d (n,)``).

    With no more unknowns than readings, the stacked least-squares problem (``lstsq``). With more (a large
    network seen by a few sensors), the same minimiser in the readings' space (Woodbury:
    ``dx = D⁻¹g − D⁻¹Jᵀ S⁻¹ J D⁻¹g`` with ``D = P²``, ``g = −JᵀW²r − D·d``, ``S = W⁻² + J D⁻¹ Jᵀ``), which
    costs O(m² n) instead of an (m + n) × n least squares: the prior makes the problem full rank, so both
    give the same step."""
    m, n = J.shape
    if n <= m:
        A = np.vstack([J * W[:, None], np.diag(P)])
        b = np.concatenate([-r * W, -P * d])
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise np.linalg.LinAlgError("non-finite least-squares problem")
        return np.linalg.lstsq(A, b, rcond=None)[0]
    Dinv = 1.0 / (P * P)
    g = -(J.T @ (W * W * r)) - d / Dinv
    Dg = Dinv * g
    S = np.diag(1.0 / (W * W)) + (J * Dinv) @ J.T
    return Dg - Dinv * (J.T @ np.linalg.solve(S, J @ Dg))


FD_REL_STEP = 1e-4
"""Central differences (torch, compiled or eager): the initial state is perturbed by ``FD_REL_STEP · max(1, |T0|)``
(0.03 K at room temperature). For a network linear in the temperatures the difference quotient is exact up to round-off
(about 1e-16 · 300 K / 0.03 K ≈ 1e-12 relative); a nonlinearity (radiation, a learned law of T) adds
``O(step²)``: ``(0.03 K / 300 K)² ≈ 1e-8`` relative for radiation. Either is far below what a Gauss–Newton step on
the burn-in can notice: the estimate it converges to moves by that fraction of a step."""


def _central_difference_jacobian(B: Any, model: Any, dt: float, integrator: str, substeps: int | None) -> Any:
    """``yJ(p, U, x) -> (y (n_t, n_out), J (n_t, n_out, n_states))``: the burn-in readings from the initial state
    ``x`` (n_states,) K and their derivatives with respect to it by central differences, the run from ``x`` and all
    ``2·n_states`` perturbed runs as one batched rollout (torch's compiled scan, or eager torch, whose cost per step
    hardly grows with the batch; ``U`` (n_t, n_in) is shared). (The run from ``x`` as a rollout of its own cost a
    compiled call per Gauss–Newton iteration: 24 ms beside the batch's 62 ms on the case study's M4, issue 18.)
    The case study's M2 on its 2 h validation file, eager (``python benchmarks/bench_burn_in.py --backends
    jax,torch``): 1.42 s an estimate (median of 3, 2026-11-29) against 16.3 s by forward mode (2026-11-26); the
    estimate within 4.3e-5 K of JAX's (``jacfwd``), the Gauss–Newton iterations stopping a little apart in the
    burn-in's poorly seen directions (issue 18)."""
    torch = B.torch

    def yJ(p, U, x):
        n = x.shape[0]
        with torch.no_grad():
            h = FD_REL_STEP * torch.clamp(x.abs(), min=1.0)
            E = torch.diag(h)
            X = torch.cat([x[None], x + E, x - E], 0)  # (2n + 1, n)
            step = torch.diagonal(X[1:n + 1] - X[n + 1:])  # the differences as represented (2h, up to round-off)
            Ub = U.unsqueeze(0).expand(2 * n + 1, *U.shape).contiguous()
            Y = model.rollout(p, X, Ub, dt, integrator=integrator, substeps=substeps)[1]  # (2n + 1, n_t, n_out)
            return Y[0], torch.movedim((Y[1:n + 1] - Y[n + 1:]) / step[:, None, None], 0, -1)

    return yJ


REVERSE_CHUNK = 32
"""Readings whose sensitivities to the initial state are computed together by reverse mode (large networks)."""


def _reverse_jacobian(B: Any, outputs: Any, n_readings: int) -> Any:
    """``J(p, U, x) (n_t, n_out, n_unknowns)``: the Jacobian of the burn-in readings by reverse mode, in chunks
    of :data:`REVERSE_CHUNK` cotangents (memory: chunk × burn-in × states), for networks with more unknowns
    than readings (forward mode would carry one tangent per state)."""
    if B.name == "jax":
        jax, jnp = B.jax, B.xp

        def chunk_rows(p, U, x, E):
            _, vjp = jax.vjp(lambda T: outputs(p, U, T), x)
            return jax.vmap(lambda e: vjp(e)[0])(E)

        chunk_rows = B.jit(chunk_rows, lean=True)

        def J(p, U, x):
            y_shape = jax.eval_shape(lambda T: outputs(p, U, T), x).shape
            rows = []
            for s0 in range(0, n_readings, REVERSE_CHUNK):
                E = np.zeros((REVERSE_CHUNK, n_readings))
                k = np.arange(s0, min(s0 + REVERSE_CHUNK, n_readings))
                E[k - s0, k] = 1.0
                rows.append(np.asarray(chunk_rows(p, U, x, jnp.asarray(E.reshape(REVERSE_CHUNK, *y_shape),
                                                                      dtype=B.dtype)))[: k.size])
            return np.concatenate(rows, 0).reshape(*y_shape, -1)

        return J
    torch = B.torch

    def J_torch(p, U, x):
        xr = x.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            y = outputs(p, U, xr)
            flat = y.reshape(-1)
            m = flat.numel()
            rows = []
            for s0 in range(0, m, REVERSE_CHUNK):
                k = min(REVERSE_CHUNK, m - s0)
                E = torch.zeros((k, m), dtype=flat.dtype)
                E[torch.arange(k), torch.arange(s0, s0 + k)] = 1.0
                last = s0 + k >= m
                try:
                    rows.append(torch.autograd.grad(flat, xr, E, retain_graph=not last, is_grads_batched=True)[0])
                except RuntimeError:  # an operation without a batching rule: one reading at a time
                    rows += [torch.autograd.grad(flat, xr, E[i], retain_graph=not (last and i == k - 1))[0][None]
                             for i in range(k)]
        return torch.cat(rows).reshape(*y.shape, -1).detach()

    return J_torch


def _noise_std(Y: np.ndarray) -> np.ndarray:
    """Measurement noise (K) per sensor from first differences of its readings (``std(Δy)/√2``; at least
    :data:`MIN_NOISE_K`)."""
    out = np.full(Y.shape[1], MIN_NOISE_K)
    for j in range(Y.shape[1]):
        d = np.diff(Y[:, j])
        d = d[np.isfinite(d)]
        if d.size >= 2:
            out[j] = max(float(np.std(d)) / math.sqrt(2.0), MIN_NOISE_K)
    return out


def initial_state(net: Network, model: Any, params: Mapping[str, Any], exp: Experiment, rule: str = "estimate",
                  *, burn_in_s: float | None = None, integrator: str = "rk4", substeps: int | None = None,
                  stored: Mapping[str, Sequence[float]] | None = None,
                  per_experiment: Mapping[str, float] | None = None,
                  stored_params: Mapping[str, Mapping[str, float]] | None = None) -> InitialState:
    """The initial state of a free run of ``model`` (backend ``params``) over ``exp`` by ``rule`` (see the
    module docstring). ``stored``: ``{fingerprint: T0 (n_states,) K}`` of a trained model's training files;
    with ``estimate`` a match is used as it is (no burn-in). ``per_experiment``: ``{name: value SI}`` of the network's
    per-experiment parameters (the training files' mean): ``estimate`` fits them with the state, the other
    rules use these values; ``stored_params``: ``{fingerprint: {name: value}}`` of the training files."""
    rule = check_rule(rule)
    U = np.asarray(exp.inputs, dtype=np.float64)
    Y = np.asarray(exp.outputs, dtype=np.float64)
    y0 = Y[0] if np.isfinite(Y[0]).any() else None
    pe = {k: float(v) for k, v in (per_experiment or {}).items()}
    b = burn_in_samples(exp, burn_in_s)  # checked whatever the rule
    if stored and rule == "estimate":  # an explicit other rule is applied as asked, also to a training file
        fp = fingerprint(exp)
        hit = stored.get(fp)
        if hit is not None and len(hit) == len(model.state_names):
            return InitialState(np.asarray(hit, dtype=np.float64), 0, 0, "stored",
                                ["note: initial state: as fitted when this file was trained on"],
                                params={**pe, **dict((stored_params or {}).get(fp, {}))})
    if pe:
        params = with_values(model, params, pe)
    steady, measured = measured_state(net, model, params, U[0], y0)
    if rule == "steady":
        return InitialState(steady, 0, 0, rule, _steady_warning(model, params, steady, U[0], y0), params=pe)
    if rule == "measured":
        return InitialState(measured, 0, 0, rule, params=pe)
    if b < 2 or not np.isfinite(Y[:b]).any():
        if y0 is None:
            return InitialState(steady, 0, 0, "steady",
                                ["note: no sensor reading at the start; initial state: the steady state of the first "
                                 "inputs"], params=pe)
        return InitialState(measured, 0, 0, "measured",
                            ["note: the file is too short for a burn-in; initial state: the steady state with the "
                             "sensed nodes at their first readings"], params=pe)
    span = f"{b} samples ({b * float(exp.dt):g} s)"
    if rule == "filter":
        ini = _filtered(model, params, exp, b, measured, integrator, span)
        ini.params = pe
        return ini
    names = tuple(pe)
    bounds = start_range(model, exp)
    x, rms, held = _map_start(net, model, params, U[:b], Y[:b], float(exp.dt), measured, pe, integrator, substeps,
                              bounds)
    return _estimated(model, x, rms, held, b, span, names, bounds)


def _estimated(model: Any, x: np.ndarray, rms: float, held: list[int], b: int, span: str, names: tuple[str, ...],
               bounds: tuple[float, float]) -> InitialState:
    """The ``estimate`` rule's :class:`InitialState` from its burn-in fit (``x``: the state, then the per-experiment
    values ``names``; ``rms`` K; the states ``held`` on a bound) over ``b`` samples (``span`` in words)."""
    if not np.all(np.isfinite(x)):
        raise TnnError(Diagnostic("the initial state could not be estimated from the burn-in (not finite)",
                                  hint="try --init measured, or a longer --burn-in"))
    ns = len(model.state_names)
    values = {k: float(x[ns + i]) for i, k in enumerate(names)}
    also = f" with {', '.join(names)}" if names else ""
    notes = [f"note: initial state{also} estimated from the first {span}, not scored (RMS there {rms:.3g} K)"]
    if held:
        which = ", ".join(f"{model.state_names[i]} = {x[i]:.4g} K" for i in held)
        notes.append(f"warning: the burn-in fit pushed {which} to the edge of the plausible start range "
                     f"({bounds[0]:.4g} … {bounds[1]:.4g} K) and holds it there: the model does not explain how "
                     f"this file starts (a missing element, or parameters far off)")
    return InitialState(x[:ns], 0, b, "estimate", notes, params=values)


def initial_states(net: Network, model: Any, params: Mapping[str, Any], exps: Sequence[Experiment],
                   rule: str = "estimate", *, burn_in_s: float | None = None, integrator: str = "rk4",
                   substeps: int | None = None, stored: Mapping[str, Sequence[float]] | None = None,
                   per_experiment: Mapping[str, float] | None = None,
                   stored_params: Mapping[str, Mapping[str, float]] | None = None) -> list[InitialState | TnnError]:
    """:func:`initial_state` of each experiment of ``exps`` (a file's :class:`~tnn_dsl.core.TnnError` in its place).
    On torch, the ``estimate`` rule's burn-in fits of files alike in step and burn-in length (no stored start, no
    per-experiment values) run in lockstep (:func:`solve_batched`): each Gauss–Newton iteration is one batched
    rollout for all of them instead of one per file — torch pays its per-step overhead once a call, and ten 2 h
    files' starts cost ten compiled calls an iteration before (1.5 s of the 1.8 s a widening of the demo's
    out-of-distribution sets took on M4, issue 18). The steps each file takes are its own fit's: the rows of a
    batch are each file's arithmetic (the same starts to round-off, ``tests/test_initial_states.py``)."""
    out: list[InitialState | TnnError | None] = [None] * len(exps)
    groups: dict[tuple[str, int], list[tuple[int, tuple]]] = {}
    batched = backend_of(model).name == "torch" and check_rule(rule) == "estimate" and not per_experiment
    for i, exp in enumerate(exps):
        try:
            plan = _burn_in_plan(net, model, params, exp, burn_in_s, stored) if batched else None
            if plan is None:
                out[i] = initial_state(net, model, params, exp, rule, burn_in_s=burn_in_s, integrator=integrator,
                                       substeps=substeps, stored=stored, per_experiment=per_experiment,
                                       stored_params=stored_params)
            else:
                groups.setdefault((repr(float(exp.dt)), plan[0]), []).append((i, plan))
        except TnnError as err:
            out[i] = err
    for (dt, b), members in groups.items():
        fit = _BurnInFit(model, float(dt), b, integrator, substeps)
        if len(members) == 1 or fit.fyJ is None:  # one file, or not central differences: each file its own fit
            for i, _ in members:
                try:
                    out[i] = initial_state(net, model, params, exps[i], rule, burn_in_s=burn_in_s,
                                           integrator=integrator, substeps=substeps)
                except TnnError as err:
                    out[i] = err
            continue
        problems = [(np.asarray(exps[i].inputs, dtype=np.float64)[:b], np.asarray(exps[i].outputs,
                                                                                  dtype=np.float64)[:b],
                     prior, prior_std, bounds) for i, (_, prior, prior_std, bounds) in members]
        solved = solve_batched(model, params, problems, float(dt), integrator, substeps)
        for (i, (_, _, _, bounds)), (x, rms, held) in zip(members, solved):
            try:
                out[i] = _estimated(model, x, rms, held, b, f"{b} samples ({b * float(dt):g} s)", (), bounds)
            except TnnError as err:
                out[i] = err
    return out  # type: ignore[return-value]


def _burn_in_plan(net: Network, model: Any, params: Mapping[str, Any], exp: Experiment, burn_in_s: float | None,
                  stored: Mapping[str, Sequence[float]] | None) -> tuple | None:
    """``(burn-in samples, prior, prior_std, bounds)`` of ``exp``'s ``estimate`` fit (no per-experiment values), or
    ``None`` where :func:`initial_state` does something else for it (a stored start, a file too short or without a
    reading in its burn-in): the same preparation as :func:`initial_state` and :func:`_map_start`."""
    Y = np.asarray(exp.outputs, dtype=np.float64)
    b = burn_in_samples(exp, burn_in_s)
    if stored:
        hit = stored.get(fingerprint(exp))
        if hit is not None and len(hit) == len(model.state_names):
            return None
    if b < 2 or not np.isfinite(Y[:b]).any() or not np.isfinite(Y[0]).any():
        return None
    U = np.asarray(exp.inputs, dtype=np.float64)
    _, measured = measured_state(net, model, params, U[0], Y[0])
    sensed = np.zeros(len(model.state_names), dtype=bool)
    for i, j, _ in sensed_states(model, net, None):
        sensed[i] = bool(np.isfinite(Y[0, j]))
    prior_std = np.where(sensed, SENSED_PRIOR_K, UNSENSED_PRIOR_K)
    return b, np.asarray(measured, dtype=np.float64), prior_std, start_range(model, exp)


def solve_batched(model: Any, params: Mapping[str, Any], problems: Sequence[tuple], dt: float, integrator: str,
                  substeps: int | None) -> list[tuple[np.ndarray, float, list[int]]]:
    """Several burn-in fits (torch's central differences; ``problems``: ``(U (n, n_in), Y (n, n_out) K, prior,
    prior_std, bounds)`` each, one ``n`` for all) in lockstep: each file's :func:`_gauss_newton`, their requests
    of one kind answered by one batched rollout (the readings and Jacobians: every file's ``2·n_states + 1`` runs
    together, as :func:`_central_difference_jacobian` runs one file's). Returns ``(x, rms K, held)`` per problem."""
    B = backend_of(model)
    torch = B.torch
    ns = len(model.state_names)
    if hasattr(model, "pack_params"):  # one argument for the compiled call, not one per constant
        params = model.pack_params(params)
    U = [B.asarray(np.asarray(u, dtype=np.float64)) for u, *_ in problems]
    steps = [_gauss_newton(ns, Y, prior, prior_std, bounds, True) for _, Y, prior, prior_std, bounds in problems]
    requests = {k: next(g) for k, g in enumerate(steps)}
    out: list = [None] * len(problems)

    def rollout(X, Ub):
        with torch.no_grad():
            return model.rollout(params, X, Ub, dt, integrator=integrator, substeps=substeps)[1]

    while requests:
        answers: dict[int, Any] = {}
        joint = [k for k, (kind, _) in requests.items() if kind == "yJ"]
        alone = [k for k, (kind, _) in requests.items() if kind == "y"]
        if joint:
            with torch.no_grad():
                Xs, diffs = [], []
                for k in joint:
                    x = B.asarray(requests[k][1])
                    h = FD_REL_STEP * torch.clamp(x.abs(), min=1.0)
                    E = torch.diag(h)
                    X = torch.cat([x[None], x + E, x - E], 0)  # (2n + 1, n), as one file's fit builds it
                    Xs.append(X)
                    diffs.append(torch.diagonal(X[1:ns + 1] - X[ns + 1:]))
                Ub = torch.cat([U[k].unsqueeze(0).expand(2 * ns + 1, *U[k].shape) for k in joint], 0).contiguous()
                Y = rollout(torch.cat(Xs, 0), Ub).reshape(len(joint), 2 * ns + 1, *U[joint[0]].shape[:1], -1)
                for k, Yk, step in zip(joint, Y, diffs):
                    J = torch.movedim((Yk[1:ns + 1] - Yk[ns + 1:]) / step[:, None, None], 0, -1)
                    answers[k] = (B.numpy(Yk[0]), B.numpy(J))
        if len(alone) == 1:  # one sequence as one file's fit runs it (a batch of one is a shape torch compiles anew)
            k = alone[0]
            answers[k] = B.numpy(rollout(B.asarray(requests[k][1]), U[k]))
        elif alone:
            X = B.asarray(np.stack([requests[k][1] for k in alone]))
            Y = rollout(X, torch.stack([U[k] for k in alone], 0))
            answers.update({k: B.numpy(Yk) for k, Yk in zip(alone, Y)})
        for k, answer in answers.items():
            try:
                requests[k] = steps[k].send(answer)
            except StopIteration as done:
                out[k] = done.value
                del requests[k]
    return out


def _map_start(net: Network, model: Any, params: Mapping[str, Any], U: np.ndarray, Y: np.ndarray, dt: float,
               measured: np.ndarray, pe: Mapping[str, float], integrator: str,
               substeps: int | None, bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, float, list[int]]:
    """The ``estimate`` rule's fit over ``U (n, n_in)``, ``Y (n, n_out)``: the initial state (then the
    per-experiment values ``pe``) around the ``measured`` state, tight for sensed states, weak for the others,
    every state within ``bounds`` K; returns ``(x, rms K, the states held on a bound)``."""
    names = tuple(pe)
    fit = _BurnInFit(model, dt, len(U), integrator, substeps, names)
    sensed = np.zeros(len(model.state_names), dtype=bool)
    for i, j, _ in sensed_states(model, net, None):
        sensed[i] = bool(np.isfinite(Y[0, j]))
    prior = np.concatenate([measured, [pe[k] for k in names]])
    prior_std = np.concatenate([np.where(sensed, SENSED_PRIOR_K, UNSENSED_PRIOR_K),
                                [_param_prior_std(net, k, pe[k]) for k in names]])
    x, rms = fit.solve(model, params, U, Y, prior, prior_std, bounds)
    return x, rms, fit.held


def free_run_start(net: Network, model: Any, params: Mapping[str, Any], inputs: np.ndarray, outputs: np.ndarray,
                   dt: float, *, integrator: str = "rk4", substeps: int | None = None) -> tuple[np.ndarray, float]:
    """The initial state ``(n_states,)`` K from which a free run with ``params`` fixed best fits a whole record
    (``inputs (n, n_in)`` SI, ``outputs (n, n_out)`` K, NaN where missing): the ``estimate`` rule's fit with the
    whole record as its burn-in. Returns ``(T0, rms K)``.

    What a training file stores when its parameters were not fitted by free runs (``--objective ml``): the
    likelihood's own initial state is the filter's prior mean, which an unsensed node barely constrains (the first
    updates move the state wherever the data says), so it is no start for a free run."""
    U = np.asarray(inputs, dtype=np.float64)
    Y = np.asarray(outputs, dtype=np.float64)
    y0 = Y[0] if np.isfinite(Y[0]).any() else None
    _, measured = measured_state(net, model, params, U[0], y0)
    if len(U) < 2 or not np.isfinite(Y).any():
        return measured, math.nan
    x, rms, _ = _map_start(net, model, params, U, Y, float(dt), measured, {}, integrator, substeps)
    if not np.all(np.isfinite(x)):
        raise TnnError(Diagnostic("the initial state for a free run could not be estimated (not finite)",
                                  hint="check the fitted parameters"))
    return x, rms


def _param_prior_std(net: Network, name: str, value: float) -> float:
    """Prior standard deviation (SI) of a per-experiment parameter around the training files' mean: a quarter of
    its bounds where it has both, :data:`UNSENSED_PRIOR_K` for a temperature or an offset, else its magnitude."""
    p = net.param(name)
    if p.lower is not None and p.upper is not None and p.upper > p.lower:
        return 0.25 * (p.upper - p.lower)
    if p.role in ("temperature", "offset"):
        return UNSENSED_PRIOR_K
    return max(abs(value), 1e-12)


def with_values(model: Any, params: Mapping[str, Any], values: Mapping[str, float]) -> dict[str, Any]:
    """``params`` (backend arrays) with the scalar ``values`` (SI) put in, each in its parameter's shape."""
    B = backend_of(model)
    out = dict(params)
    for k, v in values.items():
        out[k] = B.asarray(np.full(np.shape(B.numpy(params[k])), float(v)))
    return out


def _filtered(model: Any, params: Mapping[str, Any], exp: Experiment, b: int, x0: np.ndarray, integrator: str,
              span: str) -> InitialState:
    from ..estimation import ekf

    res = ekf(model, params, np.asarray(exp.inputs)[:b], np.asarray(exp.outputs)[:b], float(exp.dt), x0=x0,
              integrator=integrator)
    T = np.asarray(res.states[b - 1], dtype=np.float64)
    return InitialState(T, b - 1, b, "filter",
                        [f"note: initial state filtered (EKF) over the first {span}, not scored"],
                        prefix_outputs=np.asarray(res.outputs[: b - 1], dtype=np.float64))


__all__ = ["INIT_RULES", "InitialState", "initial_state", "check_rule", "default_burn_in", "burn_in_samples",
           "fingerprint", "measured_state", "sensed_states", "measured_arrays", "with_values"]
