"""Virtual sensing: an extended Kalman filter (EKF) on any compiled model (thesis §6.4.2, eq. 6.1–6.5).

The model is the discrete map of one sample interval ``x_{k+1} = F(x_k, u_k)``: the compiled model's own
integrator (``rk4``/``euler``/``expeuler`` with its sub-steps) over ``dt`` with the inputs held, exactly
what ``Model.rollout`` computes. Its Jacobian ``A_k = ∂F/∂x`` and the sensor Jacobian ``H_k = ∂h/∂x`` come
from automatic differentiation on the model's backend (``jax.jacfwd`` / ``torch.func.jacfwd``); nothing
is linearised by hand, so learned functions, radiation, Peltier elements and derived parameters are all
handled.

Filter (per sample ``k``, inputs ``u_k`` held over ``[t_k, t_k + dt)``)::

    update   ŷ = h(x̂_{k|k-1}, u_k)        S = H P Hᵀ + R        K = P Hᵀ S⁻¹
             x̂_{k|k} = x̂_{k|k-1} + K (y_k − ŷ)      P_{k|k} = (I − K H) P (I − K H)ᵀ + K R Kᵀ   (Joseph)
    predict  x̂_{k+1|k} = F(x̂_{k|k}, u_k)    P_{k+1|k} = A P_{k|k} Aᵀ + Q_d

Only the sensors named in ``use`` enter ``y``. A missing reading (NaN: a dropout) removes that sensor's
row for that sample, so the filter simply predicts through gaps. ``R = diag(σ_v²)`` (K²) per used
sensor; ``Q_d = diag(q²)·dt`` with ``q`` the process-noise intensity per state in K/√s (a random walk of
``q·√dt`` K per step on top of the model), so the same numbers work for any sample time.

Joint parameter estimation (``augment``): constant physical parameters named there become random-walk
states (thesis §6.4: "disturbance and parameter estimation to take unknown heat loads … into account").
A positive parameter (R, G, C, τ …) is carried as its logarithm, so its noise is relative (1/√s); any
other (an ambient temperature, a gain) in its SI unit per √s.

All temperatures are kelvin; inputs SI (temperature inputs in K), as ``Experiment`` holds them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from ..compiler import backend_of
from ..core import Diagnostic, TnnError

__all__ = ["ekf", "EKFResult", "open_loop", "tune_process_noise", "DEFAULT_PROCESS_NOISE", "DEFAULT_MEAS_NOISE",
           "DEFAULT_INIT_STD"]

DEFAULT_PROCESS_NOISE = 0.01
"""K/√s: process-noise intensity of every temperature state (a 1-s step adds 0.01 K of uncertainty)."""
DEFAULT_MEAS_NOISE = 0.1
"""K: standard deviation of every used sensor's reading."""
DEFAULT_INIT_STD = 1.0
"""K: standard deviation of the initial state estimate."""
DEFAULT_PARAM_NOISE_REL = 1e-3
"""1/√s: random-walk intensity of an augmented positive parameter (relative, in log space)."""
DEFAULT_PARAM_NOISE_TEMP = 0.01
"""K/√s: random-walk intensity of an augmented temperature parameter."""


@dataclass
class EKFResult:
    """What :func:`ekf` returns (all numpy, float64).

    ``t (N,)`` s; ``states (N, n_states)`` K: the filtered estimate ``x̂_{k|k}``; ``std (N, n_states)`` K:
    its standard deviation ``√diag P_{k|k}``; ``outputs (N, n_outputs)`` K: every sensor of the model
    evaluated at ``x̂_{k|k}`` (the estimate of an unused sensor is its virtual reading);
    ``innovations (N, n_used)`` K: ``y_k − h(x̂_{k|k-1})`` for the used sensors (NaN where missing);
    ``params (N, n_aug)``: the augmented parameters (SI) and ``param_std`` their standard deviation (for a
    positive parameter, relative); ``nis``: mean normalised innovation squared per used sensor (≈ 1 when
    the noise levels are consistent with the data); ``loglik``: the Gaussian log-likelihood of the
    innovations (what :func:`tune_process_noise` maximises)."""

    t: np.ndarray
    states: np.ndarray
    std: np.ndarray
    outputs: np.ndarray
    innovations: np.ndarray
    state_names: tuple[str, ...]
    output_names: tuple[str, ...]
    used: tuple[str, ...]
    params: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    param_std: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    param_names: tuple[str, ...] = ()
    nis: dict[str, float] = field(default_factory=dict)
    loglik: float = math.nan
    process_noise: dict[str, float] = field(default_factory=dict)
    meas_noise: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# Option handling (the one place where user values are checked)
# ---------------------------------------------------------------------------------------------


def _per_name(value, names: Sequence[str], default: float, what: str, unit: str) -> np.ndarray:
    """A float or ``{name: float}`` (``"*"`` for the rest) → one positive value per name."""
    out = np.full(len(names), float(default))
    if value is None:
        return out
    if isinstance(value, Mapping):
        rest = value.get("*")
        if rest is not None:
            out[:] = float(rest)
        unknown = [k for k in value if k != "*" and k not in names]
        if unknown:
            raise TnnError(Diagnostic(f"{what}: unknown name {unknown[0]!r}",
                                      hint=f"names here are: {', '.join(names)}"))
        for i, n in enumerate(names):
            if n in value:
                out[i] = float(value[n])
    else:
        out[:] = float(value)
    bad = [n for n, v in zip(names, out) if not (math.isfinite(v) and v >= 0)]
    if bad:
        raise TnnError(Diagnostic(f"{what} for {bad[0]!r} must be a finite number ≥ 0 {unit}"))
    return out


class _Setup:
    """Checked options: used sensors, augmented parameters, noise levels, initial state."""

    def __init__(self, model, params, inputs, measurements, dt, use, process_noise, meas_noise, init_std,
                 augment, param_noise, x0):
        self.model = model
        self._check_data(model, inputs, measurements, dt, use)
        self._augment(model, params, augment, param_noise)
        p0 = self._noise_levels(model, process_noise, meas_noise, init_std)
        self._initial_state(model, params, x0, p0)

    def _check_data(self, model, inputs, measurements, dt, use) -> None:
        """The sensors used, the inputs ``(N, n_inputs)`` SI, the readings ``(N, n_outputs)`` K and ``dt`` s,
        each checked (a :class:`TnnError` that says what was received and what is expected)."""
        self.ns = len(model.state_names)
        outs = list(model.output_names)
        if not outs:
            raise TnnError(Diagnostic(f"network {model.network.name!r} has no sensors; the filter needs at least one",
                                      hint="declare `sensor NAME = NODE column \"...\"`"))
        use = list(outs if use is None else ([use] if isinstance(use, str) else use))
        if not use:
            raise TnnError(Diagnostic("no sensor to use", hint=f"name one or more of: {', '.join(outs)}"))
        for s in use:
            if s not in outs:
                raise TnnError(Diagnostic(f"unknown sensor {s!r}",
                                          hint=f"the network's sensors are: {', '.join(outs)}"))
        self.use = tuple(dict.fromkeys(use))
        self.use_idx = [outs.index(s) for s in self.use]
        self.inputs = np.asarray(inputs, dtype=np.float64)
        self.y_all = np.asarray(measurements, dtype=np.float64)
        N = self.inputs.shape[0]
        if self.inputs.ndim != 2 or self.inputs.shape[1] != len(model.input_names):
            raise TnnError(f"inputs must have shape (N, {len(model.input_names)}), got {self.inputs.shape}")
        if self.y_all.shape != (N, len(outs)):
            raise TnnError(f"measurements must have shape ({N}, {len(outs)}), got {self.y_all.shape}")
        if not np.all(np.isfinite(self.inputs)):
            raise TnnError(Diagnostic("the inputs hold NaN or infinite values; the filter needs every input",
                                      hint="fill or drop the missing input samples"))
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise TnnError(f"dt must be a positive number of seconds, got {dt!r}")
        self.dt = float(dt)
        self.y = self.y_all[:, self.use_idx]
        if not np.isfinite(self.y).any():
            raise TnnError(Diagnostic(f"the sensor(s) {', '.join(self.use)} have no reading at all",
                                      hint="check the sensor columns named in the network"))

    def _augment(self, model, params, augment, param_noise) -> None:
        """The augmented (estimated) parameters: their names, positivity and role, their starting values
        ``theta0`` (log for positive ones) and their random-walk noise levels ``q_param``."""
        augment = list(augment or [])
        specs = model.param_specs
        self.aug = []
        for name in augment:
            spec = specs.get(name)
            if spec is None or spec.kind != "physical":
                consts = [k for k, s in specs.items() if s.kind == "physical"]
                raise TnnError(Diagnostic(f"cannot estimate {name!r}: not a constant parameter of the network",
                                          hint="constant parameters: " + ", ".join(consts[:20])))
            self.aug.append((name, bool(spec.positive), spec.role))
        self.na = len(self.aug)
        pn = model.to_numpy(params)
        self.params_np = pn
        self.theta0 = np.array([math.log(float(pn[n])) if pos else float(pn[n]) for n, pos, _ in self.aug])
        if self.na and not np.all(np.isfinite(self.theta0)):
            raise TnnError("an augmented positive parameter is not positive")
        aug_names = [n for n, _, _ in self.aug]
        pdef = []
        for n, pos, role in self.aug:
            if pos:
                pdef.append(DEFAULT_PARAM_NOISE_REL)
            elif role == "temperature":
                pdef.append(DEFAULT_PARAM_NOISE_TEMP)
            else:
                pdef.append(DEFAULT_PARAM_NOISE_REL * max(abs(float(pn[n])), 1e-12))
        self.q_param = _per_name(param_noise, aug_names, 0.0, "parameter noise", "per √s")
        if param_noise is None or (isinstance(param_noise, Mapping) and "*" not in param_noise):
            given = set(param_noise or {}) if isinstance(param_noise, Mapping) else set()
            for i, n in enumerate(aug_names):
                if n not in given:
                    self.q_param[i] = pdef[i]

    def _noise_levels(self, model, process_noise, meas_noise, init_std) -> np.ndarray:
        """Process noise ``q`` (K/√s per state) and measurement noise ``r`` (K per used sensor); returns the
        initial standard deviation per state (K)."""
        snames = list(model.state_names)
        self.q = _per_name(process_noise, snames, DEFAULT_PROCESS_NOISE, "process noise", "K/√s")
        self.r = _per_name(meas_noise, list(self.use), DEFAULT_MEAS_NOISE, "measurement noise", "K")
        if np.any(self.r <= 0):
            raise TnnError(Diagnostic("measurement noise must be > 0 K",
                                      hint="a perfect sensor: use a small σ, e.g. 0.01"))
        p0 = _per_name(init_std, snames, DEFAULT_INIT_STD, "initial std", "K")
        return p0

    def _initial_state(self, model, params, x0, p0) -> None:
        """The initial augmented state and covariance, and the discrete noise covariances ``Qd``, ``R``.
        Without ``x0``: the steady state of the first inputs, with the used sensors' nodes moved to the first
        reading."""
        xp = model.xp
        snames = list(model.state_names)
        if x0 is None:
            u0 = xp.asarray(self.inputs[0])
            x0 = np.asarray(model.to_numpy({"x": model.steady_state(params, u0)})["x"], dtype=np.float64)
            if not np.all(np.isfinite(x0)):
                raise TnnError(Diagnostic("the steady state of the first inputs is not finite",
                                          hint="pass x0 (the initial state) explicitly"))
            y0 = model.to_numpy({"y": model.outputs(params, xp.asarray(x0), u0)})["y"]
            net = model.network
            for j in self.use_idx:
                s = net.sensors[j]
                if np.isfinite(self.y_all[0, j]):
                    gap = self.y_all[0, j] - y0[j]
                    for nm in (s.node, f"{s.name}.lag"):
                        if nm in snames:
                            x0[snames.index(nm)] += gap
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        if x0.shape != (self.ns,):
            raise TnnError(f"x0 must have {self.ns} entries ({', '.join(snames)}), got {x0.shape}")
        self.x0 = np.concatenate([x0, self.theta0])
        self.P0 = np.diag(np.concatenate([p0 ** 2, np.zeros(self.na)]))
        if self.na:  # initial parameter uncertainty: 10 % (positive) or 1 K / 10 % of the value
            s0 = []
            for (n, pos, role), th in zip(self.aug, self.theta0):
                s0.append(0.1 if pos else (1.0 if role == "temperature" else 0.1 * max(abs(th), 1e-12)))
            self.P0[self.ns:, self.ns:] = np.diag(np.square(s0))
        self.Qd = np.diag(np.concatenate([self.q ** 2, self.q_param ** 2]) * self.dt)
        self.R = np.diag(self.r ** 2)


# ---------------------------------------------------------------------------------------------
# The filter, written once against a namespace (jax.numpy or torch)
# ---------------------------------------------------------------------------------------------


def _filter_fns(model, params, setup: _Setup, integrator: str, substeps: int):
    """``step(x, u) -> x⁺`` and ``meas(x, u) -> y`` (all sensors) on augmented states."""
    ns, aug, dt = setup.ns, setup.aug, setup.dt
    xp = model.xp

    def with_params(x):
        if not aug:
            return params
        p = dict(params)
        for j, (name, pos, _) in enumerate(aug):
            th = x[ns + j]
            p[name] = xp.exp(th) if pos else th
        return p

    def step(x, u):
        """``x (..., n)`` → ``(..., n)``; a leading batch axis only without augmented parameters."""
        p = with_params(x)
        U = xp.stack([u, u], axis=0)
        states, _ = model.rollout(p, x[..., :ns], U, dt, integrator=integrator, substeps=substeps)
        Tn = states[..., 1, :]
        return xp.concat([Tn, x[ns:]], axis=0) if aug else Tn

    def meas(x, u):
        return model.outputs(with_params(x), x[..., :ns], u)

    return step, meas


def _update_predict(m, solve, step, meas, jac_step, jac_meas, use_idx, R, Qd, I, x, P, u, y):
    """One EKF cycle with namespace ``m`` (``jax.numpy`` or ``torch``) → (x_pred, P_pred, x_f, P_f, y_f, innov)."""
    yhat_all = meas(x, u)
    H = jac_meas(x, u)[use_idx, :]
    yhat = yhat_all[use_idx]
    ok = m.isfinite(y)
    okf = ok * 1.0
    y0 = m.where(ok, y, yhat)                # a missing reading contributes no innovation (not NaN)
    innov = (y0 - yhat) * okf
    Hm = H * okf[:, None]
    S = Hm @ P @ Hm.T + R
    K = solve(S, Hm @ P).T                   # P Hᵀ S⁻¹ (S, P symmetric)
    xf = x + K @ innov
    IKH = I - K @ Hm
    Pf = IKH @ P @ IKH.T + K @ R @ K.T
    Pf = 0.5 * (Pf + Pf.T)
    nis_terms = innov * innov / m.diagonal(S)
    # log-likelihood of the innovation over the sensors read at this sample (missing rows have S_ii = R_ii)
    _, logdet = m.linalg.slogdet(S)
    ll = -0.5 * (logdet - m.sum((1.0 - okf) * m.log(m.diagonal(R))) + innov @ solve(S, innov)
                 + m.sum(okf) * math.log(2.0 * math.pi))
    yf = meas(xf, u)
    A = jac_step(xf, u)
    xp_ = step(xf, u)
    Pp = A @ Pf @ A.T + Qd
    Pp = 0.5 * (Pp + Pp.T)
    return xp_, Pp, xf, Pf, yf, m.where(ok, innov, float("nan") + 0.0 * yhat), nis_terms, ll


def ekf(model: Any, params: Mapping[str, Any], inputs: Any, measurements: Any, dt: float,
        use: Sequence[str] | str | None = None, *,
        process_noise: float | Mapping[str, float] | None = None,
        meas_noise: float | Mapping[str, float] | None = None,
        init_std: float | Mapping[str, float] | None = None,
        augment: Sequence[str] = (), param_noise: float | Mapping[str, float] | None = None,
        x0: Any = None, integrator: str = "rk4", substeps: int | None = None, t: Any = None) -> EKFResult:
    """Run an extended Kalman filter over a record.

    Parameters
    ----------
    model : compiled :class:`~tnn_dsl.Model` (JAX or PyTorch backend)
    params : the model's parameter table (backend arrays, e.g. ``TrainedModel.backend_params()``)
    inputs : (N, n_inputs) SI, zero-order hold; ``measurements``: (N, n_outputs) K with NaN where missing
    dt : s, the sample time
    use : sensor names that enter the filter (default: all); the others are estimated only
    process_noise : K/√s per state (one number or ``{state: q, "*": default}``), default 0.01
    meas_noise : K per used sensor, default 0.1
    init_std : K per state, the initial uncertainty (default 1 K)
    augment : constant parameter names estimated jointly as random walks (see the module docstring)
    param_noise : their random-walk intensity (per √s; relative for positive parameters)
    x0 : (n_states,) K initial estimate; default the steady state of the first inputs with the used
        sensors' nodes moved to their first readings
    integrator, substeps : the discretisation (as ``Model.rollout``; sub-steps chosen for stability)

    Returns an :class:`EKFResult`.
    """
    from ..compiler import INTEGRATORS, check_step

    if model.backend not in ("jax", "torch"):
        raise TnnError(Diagnostic(f"the filter needs automatic differentiation; backend {model.backend!r} has none",
                                  hint="compile with backend='jax' or backend='torch'"))
    if integrator not in INTEGRATORS:
        raise TnnError(Diagnostic(f"unknown integrator {integrator!r}", hint="use one of: " + ", ".join(INTEGRATORS)))
    setup = _Setup(model, params, inputs, measurements, dt, use, process_noise, meas_noise, init_std, augment,
                   param_noise, x0)
    tau, where = model.fastest_time_constant()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sub = check_step(integrator, setup.dt, tau, substeps, where)
    step, meas = _filter_fns(model, params, setup, integrator, sub)
    N = setup.inputs.shape[0]
    n = setup.ns + setup.na
    use_idx = list(setup.use_idx)

    B = backend_of(model)
    m = B.xp
    batched = setup.na == 0  # reverse-mode rows in one pass need a step that takes a batch of states
    jac_step = B.jacobian_fn(step, n, batched=batched)
    jac_meas = B.jacobian_fn(meas, len(model.output_names), batched=batched)
    R, Qd, I = (B.asarray(a) for a in (setup.R, setup.Qd, np.eye(n)))
    idx = B.asarray(np.asarray(use_idx, dtype=np.int64))

    def body(carry, uy):
        x, P = carry
        u, y = uy
        xp_, Pp, xf, Pf, yf, inn, nis, ll = _update_predict(m, B.solve, step, meas, jac_step, jac_meas, idx, R, Qd,
                                                            I, x, P, u, y)
        return (xp_, Pp), (xf, m.sqrt(B.clip_min(m.diagonal(Pf), 0.0)), yf, inn, nis, ll)

    run = B.jit(B.no_grad(lambda x0, P0, U, Y: B.scan(body, (x0, P0), (U, Y))[1]))
    xs, sd, ys, inn, nis, ll = (B.numpy(a) for a in run(
        B.asarray(setup.x0), B.asarray(setup.P0), B.asarray(setup.inputs), B.asarray(setup.y)))

    ns = setup.ns
    th = xs[:, ns:]
    pvals = np.stack([np.exp(th[:, j]) if pos else th[:, j] for j, (_, pos, _) in enumerate(setup.aug)], axis=1) \
        if setup.na else np.zeros((N, 0))
    mask = np.isfinite(setup.y)
    nis_mean = {s: float(np.mean(nis[mask[:, i], i])) if mask[:, i].any() else math.nan
                for i, s in enumerate(setup.use)}
    return EKFResult(
        t=np.arange(N) * setup.dt if t is None else np.asarray(t, dtype=np.float64),
        states=xs[:, :ns], std=sd[:, :ns], outputs=ys, innovations=inn,
        state_names=tuple(model.state_names), output_names=tuple(model.output_names), used=setup.use,
        params=pvals, param_std=sd[:, ns:], param_names=tuple(n for n, _, _ in setup.aug), nis=nis_mean,
        loglik=float(np.sum(ll)),
        process_noise=dict(zip(model.state_names, map(float, setup.q))),
        meas_noise=dict(zip(setup.use, map(float, setup.r))),
    )


def open_loop(model: Any, params: Mapping[str, Any], inputs: Any, dt: float, x0: Any, integrator: str = "rk4",
              substeps: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The model's free run from ``x0 (n_states,)`` K → ``(states (N, n_states), outputs (N, n_out))`` K (numpy):
    what the filter is compared against."""
    import warnings

    xp = model.xp
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s, y = model.rollout(params, xp.asarray(np.asarray(x0, dtype=np.float64)),
                             xp.asarray(np.asarray(inputs, dtype=np.float64)), float(dt), integrator=integrator,
                             substeps=substeps)
    out = model.to_numpy({"s": s, "y": y})
    return out["s"], out["y"]


def tune_process_noise(model: Any, params: Mapping[str, Any], inputs: Any, measurements: Any, dt: float,
                       use: Sequence[str] | str | None = None,
                       grid: Sequence[float] = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2),
                       **options: Any) -> tuple[float, dict[float, float]]:
    """Choose one process-noise intensity ``q`` (K/√s, all temperature states) by maximising the innovation
    log-likelihood over ``grid`` (the prediction-error method of CTSM-style grey-box identification,
    restricted to one scalar). Tune on training data only. Returns ``(best q, {q: loglik})``."""
    scores: dict[float, float] = {}
    for q in grid:
        r = ekf(model, params, inputs, measurements, dt, use, process_noise=float(q), **options)
        scores[float(q)] = r.loglik if math.isfinite(r.loglik) else -math.inf
    best = max(scores, key=scores.get)
    return best, scores
