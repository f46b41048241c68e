"""Model predictive control over a compiled, differentiable model (thesis §6.4.3).

At every control instant the controller solves, over a horizon of ``H`` intervals of ``dt`` seconds,

    min_u  (1/H) Σ_k w_y (ŷ_k − r_k)²  +  ρ Σ_k Σ_j ((u_{k,j} − u_{k−1,j}) / (hi_j − lo_j))²
    s.t.   lo_j ≤ u_{k,j} ≤ hi_j,      ŷ_k = h(x_k) + d,      x_{k+1} = F(x_k, u_k)

where ``F`` is the model's own integrator over one interval (``Model.rollout``), ``u_{−1}`` the input
applied last, and ``d`` the output disturbance (offset-free tracking, see :func:`closed_loop`). The
gradient of the cost with respect to the whole input sequence comes from automatic differentiation
through the rollout (``jax.value_and_grad`` or torch autograd); the bounds are enforced by projection
in a projected quasi-Newton method (``scipy.optimize.minimize(method="L-BFGS-B")``), so no iterate and
no applied input ever leaves ``[lo, hi]``. The previous solution, shifted by one interval, warm-starts
the next problem (receding horizon). Only the first input of the plan is applied.

Inputs the controller does not manipulate (a disturbance such as ``u1``, ambient, inlet temperatures)
are taken as known over the horizon at their current values.

Units: temperatures K, inputs SI, times s.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from ..compiler import Backend, backend_of
from ..core import Diagnostic, TnnError

__all__ = ["MPC", "closed_loop", "ClosedLoopResult"]


class MPC:
    """A receding-horizon controller for one sensor of ``model`` (see the module docstring).

    Parameters
    ----------
    model, params : the controller's compiled model (JAX or PyTorch) and its parameter table
    output : the sensor to track (a name in ``model.output_names``)
    controls : ``{input name: (lo, hi)}`` manipulated inputs with their bounds (SI)
    horizon : H, intervals predicted; ``dt`` the control interval (s)
    move_penalty : ρ, weight of the squared input moves (normalised by the input range)
    track_weight : w_y (1/K²)
    max_iter : L-BFGS-B iterations per solve
    integrator, substeps : the model's discretisation of one interval
    """

    def __init__(self, model: Any, params: Mapping[str, Any], output: str,
                 controls: Mapping[str, tuple[float, float]], *,
                 horizon: int = 30, dt: float = 10.0, move_penalty: float = 0.05, track_weight: float = 1.0,
                 max_iter: int = 60, integrator: str = "rk4", substeps: int | None = None) -> None:
        if model.backend not in ("jax", "torch"):
            raise TnnError(Diagnostic(f"MPC needs gradients; backend {model.backend!r} has none",
                                      hint="compile with backend='jax' or backend='torch'"))
        if output not in model.output_names:
            raise TnnError(Diagnostic(f"unknown sensor {output!r}", hint=f"sensors: {', '.join(model.output_names)}"))
        if not controls:
            raise TnnError(Diagnostic("no manipulated input given", hint=f"inputs: {', '.join(model.input_names)}"))
        for name, (lo, hi) in controls.items():
            if name not in model.input_names:
                raise TnnError(Diagnostic(f"unknown input {name!r}", hint=f"inputs: {', '.join(model.input_names)}"))
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise TnnError(Diagnostic(f"bounds of {name!r} must be finite with lo < hi, got ({lo}, {hi})"))
        if int(horizon) < 1 or not (dt > 0):
            raise TnnError(Diagnostic(f"horizon must be ≥ 1 and dt > 0 s, got {horizon}, {dt}"))
        self.model, self.params = model, params
        self.out_idx = list(model.output_names).index(output)
        self.output = output
        self.ctrl_names = list(controls)
        self.ctrl_idx = [list(model.input_names).index(n) for n in self.ctrl_names]
        self.lo = np.array([float(controls[n][0]) for n in self.ctrl_names])
        self.hi = np.array([float(controls[n][1]) for n in self.ctrl_names])
        self.H, self.dt = int(horizon), float(dt)
        self.rho, self.wy = float(move_penalty), float(track_weight)
        self.max_iter = int(max_iter)
        self.integrator = integrator
        from ..compiler import check_step

        tau, where = model.fastest_time_constant()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.substeps = check_step(integrator, self.dt, tau, substeps, where)
        self._vg = self._build()
        self._warm: np.ndarray | None = None

    # -- the cost and its gradient on the backend ------------------------------------------------

    def _build(self):
        m, nc = self.model, len(self.ctrl_idx)
        ni = len(m.input_names)
        sel = np.zeros((nc, ni))
        for j, i in enumerate(self.ctrl_idx):
            sel[j, i] = 1.0
        keep = 1.0 - sel.sum(axis=0)
        span = self.hi - self.lo
        oi = self.out_idx

        B = backend_of(m)
        xp = m.xp
        sel_b, keep_b, span_b = (B.asarray(a) for a in (sel, keep, span))

        def cost(useq, x0, ubase, r, uprev, d):
            U = ubase[None, :] * keep_b[None, :] + useq @ sel_b
            U = xp.concat([U, U[-1:]], axis=0)
            _, y = m.rollout(self.params, x0, U, self.dt, integrator=self.integrator, substeps=self.substeps)
            e = y[1:, oi] + d - r
            moves = (useq - xp.concat([uprev[None, :], useq[:-1]], axis=0)) / span_b
            return self.wy * B.xp.mean(e * e) + self.rho * B.xp.sum(moves * moves)

        vg = B.value_and_grad(cost)

        def f(useq, x0, ubase, r, uprev, d):
            return vg(useq, *(B.asarray(np.asarray(a, dtype=np.float64)) for a in (x0, ubase, r, uprev, d)))
        return f

    # -- one solve ---------------------------------------------------------------------------------

    def plan(self, x0: Any, u_now: Any, setpoint: float, u_prev: Any = None,
             d: float = 0.0) -> tuple[np.ndarray, dict]:
        """Solve the horizon problem from the controller-model state ``x0 (n_states,)`` K.

        ``u_now (n_inputs,)`` SI: current inputs (the non-manipulated ones are held over the horizon);
        ``setpoint``: K, a number or ``(H,)`` profile; ``u_prev (n_controls,)``: the input applied last
        (default: from ``u_now``); ``d``: output disturbance added to the prediction (K).
        Returns ``(plan (H, n_controls) SI, info)`` with ``info = {cost, iterations, success}``."""
        from scipy.optimize import minimize

        u_now = np.asarray(u_now, dtype=np.float64)
        u_prev = u_now[self.ctrl_idx] if u_prev is None else np.asarray(u_prev, dtype=np.float64)
        r = np.broadcast_to(np.asarray(setpoint, dtype=np.float64), (self.H,)).copy()
        nc = len(self.ctrl_idx)
        if self._warm is None:
            u0 = np.tile(np.clip(u_prev, self.lo, self.hi), (self.H, 1))
        else:
            u0 = np.concatenate([self._warm[1:], self._warm[-1:]], axis=0)
        x0 = np.asarray(x0, dtype=np.float64)

        def fun(z):
            v, g = self._vg(z.reshape(self.H, nc), x0, u_now, r, u_prev, float(d))
            return v, g.reshape(-1)

        bounds = [(lo, hi) for _ in range(self.H) for lo, hi in zip(self.lo, self.hi)]
        res = minimize(fun, u0.reshape(-1), jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": self.max_iter, "ftol": 1e-12, "gtol": 1e-9})
        sol = np.clip(res.x.reshape(self.H, nc), self.lo, self.hi)
        self._warm = sol
        return sol, {"cost": float(res.fun), "iterations": int(res.nit), "success": bool(res.success)}

    def reset(self) -> None:
        """Forget the warm start."""
        self._warm = None


@dataclass
class ClosedLoopResult:
    """A closed-loop run on the plant's sample grid (numpy): ``t (N,)`` s, ``y (N,)`` K plant output,
    ``r (N,)`` K set-point, ``u (N, n_inputs)`` SI applied inputs, ``states (N, n_plant_states)`` K,
    ``d (N,)`` K the output-disturbance estimate, ``solve_s`` seconds per solve, ``iterations`` per solve."""

    t: np.ndarray
    y: np.ndarray
    r: np.ndarray
    u: np.ndarray
    states: np.ndarray
    d: np.ndarray
    input_names: tuple[str, ...]
    controls: tuple[str, ...]
    solve_s: list[float] = field(default_factory=list)
    iterations: list[int] = field(default_factory=list)


def closed_loop(plant: Any, plant_params: Mapping[str, Any], mpc: MPC, inputs: Any, setpoint: Any,
                plant_dt: float = 1.0, plant_substeps: int | None = None,
                progress: Callable[[int, int, np.ndarray, np.ndarray], None] | None = None) -> ClosedLoopResult:
    """Simulate ``mpc`` controlling ``plant`` (a compiled model: the true system).

    ``inputs (N, n_inputs)`` SI on the plant grid: the non-manipulated inputs (their manipulated columns
    are ignored); ``setpoint (N,)`` K on the same grid. Every ``mpc.dt`` seconds the controller reads the
    plant's output, updates its internal model (run in parallel with the applied inputs, as in internal
    model control) and the output disturbance ``d = y_plant − y_model``, then plans and applies its first
    input (zero-order hold). The plant starts at the steady state of the first inputs with the
    manipulated inputs at their lower bounds; so does the controller's model. Offset-free: with a
    constant disturbance and a reachable set-point the plant output converges to the set-point even
    when the controller's model is wrong."""
    m = mpc.model
    if tuple(plant.input_names) != tuple(m.input_names):
        raise TnnError(Diagnostic("the plant and the controller's model must have the same inputs, got "
                                  f"{plant.input_names} and {m.input_names}"))
    inputs = np.array(inputs, dtype=np.float64)
    N = inputs.shape[0]
    setpoint = np.broadcast_to(np.asarray(setpoint, dtype=np.float64), (N,))
    ratio = mpc.dt / plant_dt
    every = int(round(ratio))
    if every < 1 or abs(ratio - every) > 1e-9:
        raise TnnError(Diagnostic(f"the control interval ({mpc.dt:g} s) must be a multiple of the plant step "
                                  f"({plant_dt:g} s)"))
    pxp, mxp = plant.xp, m.xp
    out_p = list(plant.output_names).index(mpc.output)
    u = inputs[0].copy()
    u[mpc.ctrl_idx] = mpc.lo
    xp_state = Backend.numpy(plant.steady_state(plant_params, pxp.asarray(u)))
    xm = Backend.numpy(m.steady_state(mpc.params, mxp.asarray(u)))
    ys, us, ss, ds = [], [], [], []
    solve_s, iters = [], []
    import time

    u_prev = u[mpc.ctrl_idx].copy()
    mpc.reset()
    d = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k0 in range(0, N, every):
            k1 = min(N, k0 + every)
            u = inputs[k0].copy()
            u[mpc.ctrl_idx] = u_prev
            y_plant = float(Backend.numpy(plant.outputs(plant_params, pxp.asarray(xp_state), pxp.asarray(u)))[out_p])
            y_model = float(Backend.numpy(m.outputs(mpc.params, mxp.asarray(xm), mxp.asarray(u)))[mpc.out_idx])
            d = y_plant - y_model
            H = mpc.H
            r = setpoint[np.minimum(k0 + every * np.arange(1, H + 1), N - 1)]
            t0 = time.perf_counter()
            plan, info = mpc.plan(xm, u, r, u_prev, d)
            solve_s.append(time.perf_counter() - t0)
            iters.append(info["iterations"])
            u_prev = plan[0].copy()
            U = inputs[k0:k1].copy()
            U[:, mpc.ctrl_idx] = u_prev
            Up = np.concatenate([U, U[-1:]], axis=0)
            st, yp = plant.rollout(plant_params, pxp.asarray(xp_state), pxp.asarray(Up), plant_dt,
                                   substeps=plant_substeps)
            st, yp = Backend.numpy(st), Backend.numpy(yp)
            ss.append(st[:-1])
            ys.append(yp[:-1, out_p])
            us.append(U)
            ds.append(np.full(k1 - k0, d))
            xp_state = st[-1]
            # the controller's internal model, advanced with the same input over the interval
            Um = np.stack([U[0], U[0]])
            sm, _ = m.rollout(mpc.params, mxp.asarray(xm), mxp.asarray(Um), mpc.dt, integrator=mpc.integrator,
                              substeps=mpc.substeps)
            xm = Backend.numpy(sm)[-1]
            if progress is not None:
                progress(k1, N, y_plant, u_prev)
    return ClosedLoopResult(
        t=np.arange(N) * plant_dt, y=np.concatenate(ys), r=np.array(setpoint), u=np.concatenate(us),
        states=np.concatenate(ss), d=np.concatenate(ds), input_names=tuple(plant.input_names),
        controls=tuple(mpc.ctrl_names), solve_s=solve_s, iterations=iters)
