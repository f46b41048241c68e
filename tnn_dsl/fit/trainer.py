"""The trainer: one implementation for both backends (thesis §4.5, eq. 4.6–4.8).

How it works
------------
* The trainable quantities (free constants, weights of non-frozen learned functions and, with
  ``rollout="estimated"``, the initial state of every window) live in ONE flat float64 numpy vector
  ``z``. Each slot maps to its array by a transform: ``log`` for positive parameters, a scaled sigmoid
  for bounded ones, identity (scaled) otherwise — so every positive quantity stays positive.
* The loss is written once against a tiny array namespace (:class:`~tnn_dsl.compiler.backends.adapter.Backend`)
  and the compiled model contract (``rollout``, ``steady_state``); the backend gives its value and gradient
  (``jax.value_and_grad`` under ``jit``, or torch autograd). The optimisers run on numpy: Adam (with gradient
  clipping, a divergence guard and early stopping on validation), then an L-BFGS polish (``scipy.optimize``).
* Loss (thesis eq. 4.8): mean squared error over the non-missing sensor samples (K²)
  + ``lam`` · mean over windows of the window's max absolute error (K)
  + Σ ``gamma_i`` · ((θ_i − θ_ref,i)/|θ_ref,i|)² over regularised physical parameters
  + ``continuity`` · mean squared gap between a window's end state and its successor's estimated
  initial state (multiple shooting only) + ``weight_decay`` · Σ w² over learned weights.
* Validation is always a free run over each whole validation experiment (thesis §4.6).

Initial states of a rollout (``rollout``):
``free`` (each experiment whole, from the steady state of its first inputs), ``steady`` / ``measured``
(windows starting from the steady state of their first inputs, ``measured``: sensor nodes set to the
measurement) or ``estimated`` (windows with trainable initial states and a continuity penalty: multiple
shooting). ``auto`` picks ``free`` for short experiments and ``estimated`` for long ones.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..compiler import Backend
from ..core import Diagnostic, TnnError
from ..core.interrupt import is_interrupt
from ..ir import Network
from .config import TrainConfig
from .initial import check_rule
from .model_files import load_model
from .prefit import PREFIT_POINTS, fit_weights
from .rollouts import _Rollouts, _safe
from .simulation import START_PENALTY, free_run, simulate
from .transforms import _from_z, _make_slot, _NumpyOps, _sigmoid_to_tanh, _Slot, _tanh_to_sigmoid, _to_z


class _Stop(Exception):
    pass


def _net_of(network) -> Network:
    if isinstance(network, Network):
        return network
    from ..lang import load

    return load(network)


def _nominal_network(net: Network) -> Network:
    return net.model_copy(update={"learned": []})


class _Adam:
    """Adam's moments for one flat vector, with gradient-norm clipping (``clip``, default 10× the running
    mean norm), the step scale the divergence guard lowers and its restart count."""

    b1, b2, eps = 0.9, 0.999, 1e-8

    def __init__(self, z: np.ndarray):
        self.m = np.zeros_like(z)
        self.v = np.zeros_like(z)
        self.step = 0
        self.gnorm_ema: float | None = None
        self.lr_scale = 1.0
        self.restarts = 0

    def update(self, z: np.ndarray, g: np.ndarray, lr: float, clip: float | None) -> np.ndarray:
        gn = float(np.linalg.norm(g))
        limit = clip if clip is not None else (10.0 * self.gnorm_ema if self.gnorm_ema else None)
        if limit is not None and gn > limit > 0:
            g = g * (limit / gn)
            gn = limit
        self.gnorm_ema = gn if self.gnorm_ema is None else 0.9 * self.gnorm_ema + 0.1 * gn
        self.step += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1 ** self.step)
        vh = self.v / (1 - self.b2 ** self.step)
        return z - lr * mh / (np.sqrt(vh) + self.eps)

    def reset(self) -> None:
        self.m[:] = 0.0
        self.v[:] = 0.0
        self.step = 0


@dataclass
class _AdamRun:
    """The state of the Adam phase: the current and the best ``z`` with its loss, validation MAE and epoch."""

    z: np.ndarray
    t0: float
    has_val: bool
    adam: _Adam
    best_z: np.ndarray | None = None
    best_loss: float = math.inf
    best_val: float = math.inf
    best_epoch: int = 0
    val: float = math.inf
    t_val: float = 0.0
    t_epoch: float | None = None


class _Trainer(_Rollouts):
    """One training run: parameters and learned functions as one flat vector ``z``, the loss, Adam, the L-BFGS
    polish and validation (the rollouts it fits, single or multiple shooting: :class:`~.rollouts._Rollouts`)."""

    def __init__(self, net: Network, exps: list, vals: list, cfg: TrainConfig, model, callback=None,
                 log: Callable[[str], None] | None = None, start: Mapping[str, Any] | None = None):
        self.net, self.exps, self.vals, self.cfg, self.model = net, exps, vals, cfg, model
        self.start = dict(start or {})
        """The caller's starting values by parameter name (``train(start=...)``), applied after ``init_from``."""
        self.callback = callback
        self.log = log or (lambda msg: None)
        self.ops = Backend(cfg.backend, cfg.dtype)
        self.warnings: list[str] = []
        self.curve: list[dict[str, Any]] = []
        self.stopped = "completed"
        self._warmups: list[tuple[float, float]] = []
        """``(start, seconds)`` of the first call of each program the training compiles (its loss and gradient,
        the mini-batch one, the first validation: tracing and compiling, and one evaluation). ``time_limit``
        does not count them (:meth:`elapsed`); ``meta.json`` reports their sum as ``compile_seconds``."""
        self._validated = False
        self.normalisation: dict[str, Any] = {}
        self.loaded: set[str] = set()
        self._lbfgs_end = cfg.epochs + cfg.lbfgs_iters

    # -- parameters ----------------------------------------------------------------------
    def initial_params(self) -> dict[str, np.ndarray]:
        cfg, model = self.cfg, self.model
        params = {k: np.asarray(v, dtype=np.float64)
                  for k, v in model.to_numpy(model.init_params(seed=cfg.seed)).items()}
        sources: list[tuple[str, set[str] | None]] = []
        if cfg.init_from:
            sources.append((cfg.init_from, None))
        for fn in self.net.learned:
            if fn.init_from:
                src = fn.init_from
                if not os.path.isabs(src) and fn.span is not None and fn.span.file:
                    cand = Path(fn.span.file).parent / src
                    src = str(cand) if cand.exists() else src
                sources.append((src, {fn.name}))
        for src, only in sources:

            if only is not None and all(any(k.startswith(f + ".") for k in self.loaded) for f in only):
                continue  # already initialised by --init-from

            other = load_model(src)
            copied = []
            for k, v in other.params.items():
                fn_name = k.split(".", 1)[0] if "." in k else None
                if only is not None:
                    # the function's arrays; matched by name, else by identical targets
                    fn = next(f for f in self.net.learned if f.name in only)
                    src_fn = next((f for f in other.network.learned if f.name == fn.name
                                   and [t.name for t in f.targets] == [t.name for t in fn.targets]), None)
                    if src_fn is None:
                        src_fn = next((f for f in other.network.learned
                                       if [t.name for t in f.targets] == [t.name for t in fn.targets]), None)
                    if src_fn is None:
                        raise TnnError(Diagnostic(
                            f"learned function {fn.name} is initialised from {src}, but that model has no function "
                            f"with targets {', '.join(t.name for t in fn.targets)}", span=fn.span,
                            hint="init_from must name a model trained with the same learn targets"))
                    if fn_name != src_fn.name:
                        continue
                    k = fn.name + k[len(src_fn.name):]
                if k in params and np.shape(params[k]) == np.shape(v):
                    params[k] = np.asarray(v, dtype=np.float64).copy()
                    copied.append(k)
            if not copied:
                raise TnnError(Diagnostic(f"init_from {src}: no array of that model matches this network",
                                          hint="initialise from a model of the same network (same names and shapes)"))
            self.loaded.update(copied)
            self.log(f"initialised {len(copied)} arrays from {src}")
        given = [k for k, v in self.start.items() if k in params and np.shape(params[k]) == np.shape(v)]
        for k in given:
            params[k] = np.asarray(self.start[k], dtype=np.float64).copy()
        if given:
            self.loaded.update(given)
            self.log(f"started from {len(given)} given values")
        return params

    def nominal_runs(self, params: dict[str, np.ndarray]):
        """Simulate the nominal (no learned functions) network on the training data; with starting values for a
        learned function (``train(start=...)``: a fitted model to go on from) the network itself at those values,
        so the windows' first guesses are the starting model's own trajectory. Returns ``(nominal model, its
        parameters, the runs)``: the nominal model serves the flows' and heat loads' scales either way."""
        from ..compiler import compile as compile_network

        nom_net = _nominal_network(self.net)
        nom = compile_network(nom_net, backend=self.cfg.backend, dtype=self.cfg.dtype,
                              torch_compile=self.cfg.torch_compile)
        npar = nom.to_numpy(nom.init_params(seed=0))
        for k in npar:
            if k in params and np.shape(params[k]) == np.shape(npar[k]):
                npar[k] = params[k]
        bp = nom.from_numpy(npar)
        # the nominal run sets normalisations and the windows' first guesses: started as measured (an estimate
        # of the unsensed states with the nominal model would fit its errors into them), except for single
        # shooting, whose one initial state per file starts at the burn-in estimate
        init = check_rule(self.cfg.init)
        if init in ("estimate", "filter") and not self.plan_rollout()[2]:
            init = "measured"
        sim, sim_params = nom, bp
        started = {k.split(".", 1)[0] for k in self.start if k in params} & {fn.name for fn in self.net.learned}
        if started:
            sim, sim_params = self.model, self.model.from_numpy(params)
        elif self.cfg.backend == "torch" and init not in ("estimate", "filter"):
            # one simulation per file, without gradients: the numpy reference backend takes about half eager
            # torch's time per step (BENCHMARKS.md "Rollout cost": 114 against 247 µs on M3) and compiles no
            # torch graph for one use (M2: 5 → 4 graphs, BENCHMARKS.md "Training time")
            sim = compile_network(nom_net, backend="numpy", dtype=self.cfg.dtype)
            sim_params = sim.from_numpy(npar)
        runs = []
        for e in self.exps:
            states, y = simulate(sim, sim_params, e, init=init, integrator=self.cfg.integrator,
                                 substeps=self.cfg.substeps, burn_in_s=self.cfg.burn_in, check=False)
            if not np.all(np.isfinite(states)):
                raise TnnError(Diagnostic(
                    f"the nominal model does not simulate on {e.name}: its temperatures become non-finite",
                    hint="check the nominal values (capacities, resistances) and the integrator step; "
                         "try --integrator expeuler or --substeps"))
            runs.append(states)
        return nom, bp, runs

    def set_stats(self, params, nom, nom_params, runs) -> None:
        """Input normalisation (and output scales) of learned functions from the nominal simulation."""
        names = list(nom.state_names)
        U = np.concatenate([np.asarray(e.inputs, dtype=float) for e in self.exps])
        T = np.concatenate(runs)
        inputs = list(self.model.input_names)
        flows = None
        for fn in self.net.learned:
            if any(k.startswith(fn.name + ".") for k in self.loaded):
                continue  # keeps the statistics of the model it came from
            xs = []
            for a in fn.inputs:
                if a.kind == "node" and a.name in names:
                    xs.append(T[:, names.index(a.name)])
                elif a.kind == "input" and a.name in inputs:
                    xs.append(U[:, inputs.index(a.name)])
                elif a.name in params and np.size(params[a.name]) == 1:
                    xs.append(np.full(1, float(np.asarray(params[a.name]).reshape(()))))
                else:
                    xs.append(np.zeros(1))
            mean = np.array([(np.max(x) + np.min(x)) / 2 for x in xs]) if xs else np.zeros(0)
            half = np.array([(np.max(x) - np.min(x)) / 2 for x in xs]) if xs else np.zeros(0)
            floor = np.maximum(1e-3 * np.abs(mean), 1e-9)
            for i, a in enumerate(fn.inputs):
                if a.kind == "node":
                    floor[i] = max(floor[i], 0.5)  # K: a node that barely moves is not scaled up to noise
            scale = np.maximum(half, floor)
            ysc = []
            for t in fn.targets:
                if t.kind == "param":
                    p = next((q for q in self.net.params if q.name == t.name), None)
                    v = abs(p.value) if p is not None and p.value is not None else 0.0
                    ysc.append(v if v > 0 else 1.0)
                elif t.kind == "flow":
                    if flows is None:
                        flows = self._nominal_flows(nom, nom_params, T, U)
                    f = flows.get(t.name)
                    ysc.append(max(float(np.sqrt(np.mean(f ** 2))), 1e-3) if f is not None else 1.0)
                else:  # heat load: the node's typical heat throughput
                    ysc.append(self._node_heat_scale(nom, nom_params, T, U, t.name, flows))
            for arr, val in (("x_mean", mean), ("x_scale", scale), ("y_scale", np.array(ysc, dtype=float))):
                k = f"{fn.name}.{arr}"
                if k in params and np.shape(params[k]) == np.shape(val):
                    params[k] = val
            self.normalisation[fn.name] = {
                "inputs": [a.name for a in fn.inputs], "x_mean": mean.tolist(), "x_scale": scale.tolist(),
                "x_min": [float(np.min(x)) for x in xs], "x_max": [float(np.max(x)) for x in xs],
                "targets": [t.name for t in fn.targets], "y_scale": [float(v) for v in ysc],
            }
        for fn in self.net.learned:
            if fn.name not in self.normalisation:
                k = f"{fn.name}.x_mean"
                if k in params:
                    xm, xs_ = params[k], params.get(f"{fn.name}.x_scale", np.ones_like(params[k]))
                    self.normalisation[fn.name] = {
                        "inputs": [a.name for a in fn.inputs], "x_mean": xm.tolist(), "x_scale": xs_.tolist(),
                        "x_min": (xm - xs_).tolist(), "x_max": (xm + xs_).tolist(),
                        "targets": [t.name for t in fn.targets], "from": "init_from"}

    def _nominal_flows(self, nom, nom_params, T, U, max_points: int = 20000) -> dict[str, np.ndarray]:
        idx = np.linspace(0, len(T) - 1, min(len(T), max_points)).astype(int)
        hf = nom.heat_flows(nom_params, self.ops.asarray(T[idx]), self.ops.asarray(U[idx]))
        return {k: self.ops.numpy(v) for k, v in hf.items()}

    def _node_heat_scale(self, nom, nom_params, T, U, node, flows) -> float:
        names = list(nom.state_names)
        try:
            i = names.index(node)
            idx = np.linspace(0, len(T) - 1, min(len(T), 20000)).astype(int)
            d = self.ops.numpy(nom.rhs(nom_params, self.ops.asarray(T[idx]), self.ops.asarray(U[idx])))[:, i]
            C = next((p.value for p in self.net.params
                      if p.name == next(n.capacitance for n in self.net.nodes if n.name == node)), None)
            if C is not None:
                v = float(np.sqrt(np.mean((C * d) ** 2)))
                if v > 0:
                    return max(v, 1e-3)
        except (ValueError, StopIteration):
            pass
        return 1.0

    def prefit_replace(self, params, nom, nom_params, runs) -> None:
        """``replace``-mode flow functions: least squares on the nominal physics flow along the nominal run
        (:mod:`.prefit`: Levenberg–Marquardt, the same weights on both backends to round-off)."""
        fns = [fn for fn in self.net.learned if fn.replace and not fn.frozen
               and not any(k.startswith(fn.name + ".") for k in self.loaded) and fn.name not in self.cfg.freeze]
        if not fns or not self.cfg.prefit:
            return
        U = np.concatenate([np.asarray(e.inputs, dtype=float) for e in self.exps])
        T = np.concatenate(runs)
        idx = np.linspace(0, len(T) - 1, min(len(T), PREFIT_POINTS)).astype(int)
        target = self._nominal_flows(nom, nom_params, T[idx], U[idx], max_points=len(idx))
        Tb, Ub = self.ops.asarray(T[idx]), self.ops.asarray(U[idx])
        specs = self.model.param_specs
        for fn in fns:
            names = [k for k, s in specs.items() if k.startswith(fn.name + ".") and s.kind == "weights"]
            slots, start = [], 0
            for k in names:
                sl = _make_slot(k, specs[k], params[k], start, None)
                slots.append(sl)
                start += sl.size
            z0 = np.concatenate([_to_z(s, params[k]) for s, k in zip(slots, names)])
            fixed = self.model.from_numpy(params)
            tnames = [t.name for t in fn.targets]
            ysc = {t: max(float(np.sqrt(np.mean(target[t] ** 2))), 1e-6) for t in tnames if t in target}
            if not ysc:
                continue
            # residual (q − q_nominal) / (rms(q_nominal) · √points): ‖r‖² is the sum over flows of the mean
            # squared relative error
            tgt = {t: self.ops.asarray(target[t] / (ysc[t] * math.sqrt(len(idx)))) for t in ysc}
            div = {t: 1.0 / (ysc[t] * math.sqrt(len(idx))) for t in ysc}
            ops, model = self.ops, self.model

            def residuals(z, slots=slots, fixed=fixed, tgt=tgt, div=div):
                p = dict(fixed)
                for s in slots:
                    p[s.name] = _from_z(s, z[s.start:s.start + s.size], ops)
                hf = model.heat_flows(p, Tb, Ub)
                return ops.xp.concat([hf[t] * div[t] - y for t, y in tgt.items()])

            z, norm, method = fit_weights(residuals, z0, ops)
            for s, k in zip(slots, names):
                params[k] = _from_z(s, z[s.start:s.start + s.size], _NumpyOps)
            self.log(f"pre-fitted {fn.name} to the nominal {', '.join(tnames)} by {method} (relative RMS error "
                     f"{norm / math.sqrt(len(tgt)):.3g})")

    # -- layout and loss -----------------------------------------------------------------
    def layout(self, params: dict[str, np.ndarray]) -> None:
        cfg, specs = self.cfg, self.model.param_specs
        frozen_fns = {fn.name for fn in self.net.learned if fn.frozen}
        freeze = set(cfg.freeze)
        known = set(specs) | {fn.name for fn in self.net.learned}
        unknown = sorted(freeze - known)
        if unknown:
            import difflib

            close = difflib.get_close_matches(unknown[0], sorted(known), n=1)
            raise TnnError(Diagnostic(f"freeze: no parameter or learned function named {unknown[0]!r}",
                                      hint=f"did you mean {close[0]!r}?" if close else
                                      f"trainable names: {', '.join(k for k, s in specs.items() if s.trainable)}"))
        roles = {p.name: p.role for p in self.net.params}
        per_exp = {p.name for p in self.net.params if getattr(p, "per_experiment", False)}
        n_exp = len(self.exps)
        self.slots: list[_Slot] = []
        self.pe_names: list[str] = []
        start = 0
        for k, s in specs.items():
            if not s.trainable or k in freeze:
                continue
            owner = k.split(".", 1)[0]
            if s.kind != "physical" and (owner in freeze or owner in frozen_fns):
                continue
            sl = _make_slot(k, s, params[k], start, roles.get(k))
            self.slots.append(sl)
            start += sl.size
            if k in per_exp and n_exp > 1:  # one value per training file: experiment 0 in the slot named k
                self.pe_names.append(k)
                for i in range(1, n_exp):
                    self.slots.append(dataclasses.replace(sl, name=f"{k}@{i}", start=start))
                    params[f"{k}@{i}"] = np.asarray(params[k], dtype=np.float64).copy()
                    start += sl.size
        self.n_param_z = start
        if start == 0:
            raise TnnError(Diagnostic(
                f"network {self.net.name} has nothing to train: no free parameter and no learn clause"
                + (" (all frozen)" if freeze or frozen_fns else ""),
                hint="mark parameters `free` or add a `learn` line"))
        self.params0 = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
        self.fixed = self.model.from_numpy(self.params0)
        # regularisation towards the reference values (eq. 4.8)
        g = cfg.gamma
        self.reg = []
        for sl in self.slots:
            if specs[sl.name.split("@")[0]].kind != "physical":
                continue
            w = g.get(sl.name, 0.0) if isinstance(g, dict) else float(g)
            if w > 0:
                ref = self.params0[sl.name]
                self.reg.append((sl, float(w), ref, np.maximum(np.abs(ref), 1e-12)))
        self.weight_slots = [sl for sl in self.slots if specs[sl.name.split("@")[0]].kind == "weights"]
        # sigmoid MLPs whose every weight is trained move in tanh coordinates (cfg.centre_sigmoid)
        trained = {sl.name for sl in self.slots}
        self.tanh_coords: list[tuple[str, int]] = []
        if cfg.centre_sigmoid:
            for fn in self.net.learned:
                K = len(fn.hidden)
                if fn.kind == "mlp" and fn.activation == "sigmoid" and K > 0 and all(
                        f"{fn.name}.{a}{k}" in trained for k in range(K + 1) for a in "Wb"):
                    self.tanh_coords.append((fn.name, K))

    def params_from_z(self, z, ops=None) -> dict:
        ops = ops or self.ops
        p = dict(self.fixed) if ops is self.ops else dict(self.params0)
        for sl in self.slots:
            p[sl.name] = _from_z(sl, z[sl.start:sl.start + sl.size], ops)
        for fn, K in self.tanh_coords:
            _tanh_to_sigmoid(p, fn, K)
        return p

    def z_from_params(self, params: dict[str, np.ndarray]) -> np.ndarray:
        """The parameter part of ``z`` for numpy ``params`` (the inverse of :meth:`params_from_z`)."""
        p = dict(params)
        for fn, K in self.tanh_coords:
            _sigmoid_to_tanh(p, fn, K)
        return np.concatenate([_to_z(sl, p[sl.name]) for sl in self.slots])

    def numpy_params(self, z: np.ndarray) -> dict[str, np.ndarray]:
        """The model's parameters (numpy) at ``z``; a per-experiment parameter holds the mean of its training files'
        values (the starting value for a new file; :meth:`experiment_values` has each file's)."""
        p = self.params_from_z(np.asarray(z, dtype=float), _NumpyOps)
        out = {k: np.asarray(v, dtype=np.float64) for k, v in p.items() if "@" not in k}
        for k in self.pe_names:
            out[k] = np.mean([np.asarray(p[k])] + [np.asarray(p[f"{k}@{i}"]) for i in range(1, len(self.exps))],
                             axis=0)
        return out

    def selection_score(self, z: np.ndarray) -> float:
        """What decides between two fits of the same data: the validation MAE (K) with validation files, else the
        training loss of the current layout (a single-shooting layout: the free runs' mean squared error, K²)."""
        if self.vals:
            return self.validate(z)
        data, full_vg = self.full_loss()
        value = _safe(full_vg(z, data))[0]
        return value if math.isfinite(value) else math.inf

    def full_loss(self) -> tuple[Any, Any]:
        """``(data, vg)``: the current layout's whole training batch and ``vg(z, data) -> (loss, gradient)``, built
        (for JAX: traced and compiled) once per layout (:meth:`build_batches` forgets it): the Adam epochs, the
        L-BFGS polish and :meth:`selection_score` share one program. (A fresh one per score cost a real-data fit
        without validation files two more compilations of its loss and gradient, issue 18.)"""
        data, statics = self.batch_arrays(None)
        if self._full_vg is None:
            self._full_vg = self.first_call_timed(self.ops.value_and_grad(self.make_loss(statics)))
        return data, self._full_vg

    def first_call_timed(self, fn: Callable) -> Callable:
        """``fn`` whose first call's time is added to :attr:`warmup_s` (the call that compiles it)."""
        done = [False]

        def call(*args):
            if done[0]:
                return fn(*args)
            t = time.perf_counter()
            try:
                return fn(*args)
            finally:
                done[0] = True
                self._warmups.append((t, time.perf_counter() - t))

        return call

    @property
    def warmup_s(self) -> float:
        """Seconds in the first calls of the programs this training compiled (s)."""
        return float(sum(d for _, d in self._warmups))

    def elapsed(self, t0: float) -> float:
        """Seconds of training since ``t0`` that ``time_limit`` counts: wall time less the first calls of the
        programs compiled since ``t0``, so a backend that compiles longer (torch) trains as long as one that
        compiles fast, and a slow host's compiler does not eat the budget."""
        return time.perf_counter() - t0 - sum(d for s, d in self._warmups if s >= t0)

    def over_time_limit(self, t0: float) -> bool:
        return self.cfg.time_limit is not None and self.elapsed(t0) > self.cfg.time_limit

    def make_loss(self, statics):
        cfg, model, ops = self.cfg, self.model, self.ops
        n_states = len(model.state_names)
        n_x0, n_param_z = self.n_x0, self.n_param_z
        x0_guess = ops.asarray(self.x0_guess) if n_x0 else None
        x0_low = ops.asarray(self.x0_low) if n_x0 else None
        x0_high = ops.asarray(self.x0_high) if n_x0 else None
        n_windows = sum(st["B"] for st in statics)
        n_valid = max(sum(st["n_valid"] for st in statics), 1)

        def loss(z, data):
            params = self.params_from_z(z)
            X0 = None
            if n_x0:
                X0 = x0_guess + z[n_param_z:].reshape((n_x0, n_states))
            sse, mx, cont = 0.0, 0.0, 0.0
            for st, d in zip(statics, data):
                if st["exp"] is None and self.pe_names:  # windows of several files (fitted starts only)
                    states, yh = self._rollout_per_file(params, d["exps"], X0[d["idx"]], d["U"], st["dt"])
                else:
                    gp = self._experiment_params(params, st["exp"] or 0)
                    if st["init"] == "estimated":
                        T0 = X0[d["idx"]]
                    else:
                        T0 = ops.where(d["mask0"], d["vals0"], model.steady_state(gp, d["U"][:, 0, :]))
                    states, yh = model.rollout(gp, T0, d["U"], st["dt"], integrator=cfg.integrator,
                                               substeps=cfg.substeps)
                err = ops.where(d["M"], yh - d["Y"], 0.0 * yh)
                sse = sse + ops.sum(err * err) / n_valid
                if cfg.lam > 0:
                    mx = mx + ops.sum(ops.amax(ops.abs(err), (1, 2)))
                if st["init"] == "estimated" and cfg.continuity > 0:
                    gap = states[d["cb"], d["ck"]] - X0[d["cj"]]
                    cont = cont + ops.sum((gap * gap).sum(-1) * d["cw"]) / (st["n_pairs"] * n_states)
            total = sse
            if cfg.lam > 0:
                total = total + cfg.lam * mx / n_windows
            if n_x0 and cfg.continuity > 0:
                total = total + cfg.continuity * cont
            if n_x0:  # a fitted start outside the data's range is no start (simulation.start_range)
                below = ops.where(X0 < x0_low, x0_low - X0, 0.0 * X0)
                above = ops.where(X0 > x0_high, X0 - x0_high, 0.0 * X0)
                total = total + START_PENALTY * ops.sum(below * below + above * above)
            for sl, w, ref, den in self.reg:
                dv = (params[sl.name] - ops.asarray(ref)) / ops.asarray(den)
                total = total + w * ops.sum(dv * dv)
            if cfg.weight_decay > 0:
                for sl in self.weight_slots:
                    total = total + cfg.weight_decay * ops.sum(params[sl.name] ** 2)
            return total

        return loss

    # -- validation ----------------------------------------------------------------------
    def validate(self, z: np.ndarray, exps=None) -> float:
        """The mean absolute error (K) of free runs over ``exps`` (default: the validation files); the first
        validation's time counts as compilation (:attr:`warmup_s`)."""
        if not self._validated and exps is None:
            self._validated = True
            t = time.perf_counter()
            try:
                return self.validate(z, self.vals)
            finally:
                self._warmups.append((t, time.perf_counter() - t))
        exps = self.vals if exps is None else exps
        pn = self.numpy_params(z)
        bp = self.model.from_numpy(pn)
        abs_sum, n = 0.0, 0
        for e in exps:
            try:
                run = free_run(self.model, bp, e, self.cfg.init, integrator=self.cfg.integrator,
                               substeps=self.cfg.substeps, burn_in_s=self.cfg.burn_in,
                               per_experiment={k: float(np.asarray(pn[k]).reshape(-1)[0]) for k in self.pe_names})
            except TnnError:  # no steady state or no initial state at these parameters
                return math.inf
            y = run.y[run.burn_in:]
            err = y - np.asarray(e.outputs, dtype=float)[run.burn_in:]
            m = np.isfinite(np.asarray(e.outputs, dtype=float)[run.burn_in:])
            if not np.all(np.isfinite(y[m])):
                return math.inf
            abs_sum += float(np.abs(err[m]).sum())
            n += int(m.sum())
        return abs_sum / max(n, 1)

    # -- optimisation --------------------------------------------------------------------
    def run(self) -> np.ndarray:
        """Adam epochs (cosine step decay, gradient clipping, divergence guard, early stopping on validation),
        then the L-BFGS polish; returns the chosen ``z``."""
        cfg = self.cfg
        rng = np.random.default_rng(cfg.seed)
        z = np.concatenate([self.z_from_params(self.params0)]
                           + ([np.zeros(self.n_x0 * len(self.model.state_names))] if self.n_x0 else []))
        minibatch = bool(cfg.batch_size) and any(len(g["windows"]) > cfg.batch_size for g in self.groups)
        data, full_vg = self.full_loss()
        batch_vg = None
        if minibatch:
            _, bstatics = self.batch_arrays(rng)
            batch_vg = self.first_call_timed(self.ops.value_and_grad(self.make_loss(bstatics)))
        r = _AdamRun(z=z, t0=time.perf_counter(), has_val=bool(self.vals), adam=_Adam(z))
        loss0, g0 = full_vg(z, data)
        if not math.isfinite(loss0) or not np.all(np.isfinite(g0)):
            raise TnnError(Diagnostic(
                "the initial model gives a non-finite loss: the simulation blows up with the starting values",
                hint="check the nominal values and the integrator (try --integrator expeuler or --substeps 4)"))
        r.best_z, r.best_loss = z.copy(), loss0
        r.best_val = r.val = self.validate(z) if r.has_val else math.inf
        r.t_val = time.perf_counter() - r.t0
        val_every = cfg.val_every or self.auto_val_every()
        try:
            self.record(0, loss0, r.best_val, r.t0, "start")  # a callback may stop the training from here on
            for epoch in range(1, cfg.epochs + 1):
                if not self._adam_epoch(r, epoch, rng, minibatch, full_vg, batch_vg, data, val_every):
                    break
        except _Stop:
            return r.best_z
        except (KeyboardInterrupt, SystemError) as e:
            if not is_interrupt(e):  # a SystemError that no Ctrl-C caused is a bug: not hidden
                raise
            self.note_interrupt(f"at epoch {len(self.curve)}; kept the best model (epoch {r.best_epoch})")
            return r.best_z
        # L-BFGS polish on the full training loss, from Adam's last state (lower training loss than an
        # early best-validation state; that one stays the fallback)
        if cfg.lbfgs_iters > 0:
            start = r.z if np.all(np.isfinite(r.z)) else r.best_z
            return self.polish(start, full_vg, data, r.best_val if r.has_val else r.best_loss, r.has_val, r.t0,
                               fallback=r.best_z)
        return r.best_z.copy()

    def _adam_epoch(self, r: "_AdamRun", epoch: int, rng, minibatch: bool, full_vg, batch_vg, data,
                    val_every: int) -> bool:
        """One epoch: the Adam steps, validation, the divergence guard, progress, the stopping rules.
        ``False``: stop."""
        cfg = self.cfg
        te = time.perf_counter()
        lr = cfg.lr * r.adam.lr_scale * (cfg.lr_final + (1 - cfg.lr_final) * 0.5
                                        * (1 + math.cos(math.pi * (epoch - 1) / max(cfg.epochs, 1))))
        n_batches = 1 if not minibatch else max(1, math.ceil(max(len(g["windows"]) for g in self.groups)
                                                              / cfg.batch_size))
        ep_loss, z_prev, diverged = self._adam_steps(r, lr, n_batches, minibatch, rng, full_vg, batch_vg, data)
        if not diverged and not r.has_val and ep_loss < r.best_loss:
            r.best_loss, r.best_z, r.best_epoch = ep_loss, (z_prev if n_batches == 1 else r.z).copy(), epoch
        dt_ep = time.perf_counter() - te
        if epoch > 1:  # the first epoch includes compilation
            r.t_epoch = dt_ep if r.t_epoch is None else 0.8 * r.t_epoch + 0.2 * dt_ep
        if r.has_val and not diverged:
            diverged = self._validate_epoch(r, epoch, ep_loss, val_every)
        if diverged:
            self._restart(r, epoch)
            return True
        since_best = epoch - r.best_epoch
        self.record(epoch, ep_loss, r.val, r.t0, "adam",
                    eta=(cfg.epochs - epoch) * r.t_epoch * (1 + 0.4 * r.has_val) if r.t_epoch else math.nan)
        if cfg.patience and since_best >= cfg.patience and epoch >= cfg.epochs // 2:
            self.stopped = "early_stopping"
            self.log(f"early stopping at epoch {epoch}: no better validation MAE for {since_best} epochs")
            return False
        if self.over_time_limit(r.t0):
            self.stopped = "time_limit"
            return False
        return True

    def _adam_steps(self, r: "_AdamRun", lr: float, n_batches: int, minibatch: bool, rng, full_vg, batch_vg, data):
        """The epoch's Adam steps → ``(mean loss, z before the last step, diverged)``."""
        ep_loss, z_prev = 0.0, r.z
        for _ in range(n_batches):
            z_prev = r.z
            if minibatch:
                bdata, _ = self.batch_arrays(rng)
                loss, g = batch_vg(r.z, bdata)
            else:
                loss, g = full_vg(r.z, data)
            if not math.isfinite(loss) or not np.all(np.isfinite(g)) or loss > 1e4 * max(r.best_loss, 1e-12) + 1e3:
                return ep_loss, z_prev, True
            ep_loss += loss / n_batches
            r.z = r.adam.update(r.z, g, lr, self.cfg.clip)
        return ep_loss, z_prev, False

    def _validate_epoch(self, r: "_AdamRun", epoch: int, ep_loss: float, val_every: int) -> bool:
        """Validate on the epochs due (the first two, every ``val_every``, the last) and keep the best state.
        ``True``: the validation run diverged."""
        if not (epoch <= 2 or epoch % max(val_every, 1) == 0 or epoch == self.cfg.epochs):
            return False
        tv = time.perf_counter()
        r.val = self.validate(r.z)
        r.t_val = (time.perf_counter() - tv) if epoch == 1 else 0.5 * r.t_val + 0.5 * (time.perf_counter() - tv)
        if not math.isfinite(r.val):
            return True
        if r.val < r.best_val:
            r.best_val, r.best_z, r.best_epoch = r.val, r.z.copy(), epoch
            r.best_loss = min(r.best_loss, ep_loss)
        return False

    def _restart(self, r: "_AdamRun", epoch: int) -> None:
        """The divergence guard: back to the best state with a smaller step, or stop (``_Stop``)."""
        cfg = self.cfg
        r.adam.restarts += 1
        msg = (f"epoch {epoch}: the loss diverged (non-finite or exploding); restored the best state "
               f"(epoch {r.best_epoch}) and lowered the step to {cfg.lr * r.adam.lr_scale * 0.3:.3g}")
        self.warnings.append(msg)
        self.log("warning: " + msg)
        if r.adam.restarts > cfg.max_restarts:
            self.stopped = "diverged"
            self.warnings.append(
                f"training diverged {r.adam.restarts} times; stopped at epoch {epoch} and kept the best model "
                f"(epoch {r.best_epoch}); lower --lr or use --integrator expeuler")
            raise _Stop
        r.z = r.best_z.copy()
        r.adam.reset()
        r.adam.lr_scale *= 0.3

    def auto_val_every(self) -> int:
        """Validation period when ``val_every = 0``: validation costs at most ~40 % of the time and runs at
        least ~25 times. Estimated from step counts, not timings, so a run is the same on every machine
        and backend: a free validation run of N steps against one epoch ≈ 3 × the rollout length of each
        group of windows (forward + backward; the windows of a group run as one batch)."""
        n_val = sum(int(e.n_steps) for e in self.vals)
        n_epoch = 3 * sum(int(g["U"].shape[1]) for g in self.groups)
        return int(min(max(1, math.ceil(n_val / max(0.4 * n_epoch, 1))), max(1, self.cfg.epochs // 25)))

    def polish(self, z, full_vg, data, best, has_val, t0, val_every: int = 10, patience: int = 10,
               fallback: np.ndarray | None = None):
        """L-BFGS-B on the full training loss from ``z``; returns the iterate with the best validation MAE
        (checked every ``val_every`` iterations; the polish stops after ``patience`` checks without a
        better one), or ``fallback`` (default ``z``) when none beats ``best`` (``fallback``'s score).

        The loss is divided by its value at ``z`` first: scipy's stopping test compares the decrease
        with ``max(|f|, 1)``, so an unscaled loss of 1e-4 K² would stop after one iteration."""
        from scipy.optimize import minimize

        it = [0]
        epoch0 = self.curve[-1]["epoch"] if self.curve else 0
        self._lbfgs_end = epoch0 + self.cfg.lbfgs_iters
        f0 = _safe(full_vg(z, data))[0]
        scale = 1.0 / f0 if math.isfinite(f0) and f0 > 0 else 1.0
        state = {"best": best, "z": None, "last_loss": math.nan, "since": 0}

        def fun(x):
            v, g = _safe(full_vg(x, data))
            state["last_loss"] = v
            return v * scale, g * scale

        def check(xk, final=False):
            if has_val:
                val = self.validate(xk)
                if math.isfinite(val) and val < state["best"]:
                    state["best"], state["z"], state["since"] = val, np.array(xk, copy=True), 0
                else:
                    state["since"] += 1
                self.record(epoch0 + it[0], state["last_loss"], val, t0, "lbfgs")
            elif final:
                loss = _safe(full_vg(xk, data))[0]
                if math.isfinite(loss) and loss <= state["best"]:
                    state["best"], state["z"] = loss, np.array(xk, copy=True)
                self.record(epoch0 + it[0], loss, math.nan, t0, "lbfgs")

        def cb(xk):
            it[0] += 1
            if self.over_time_limit(t0):
                raise _Stop
            if it[0] % val_every == 0:
                check(xk)
                if has_val and state["since"] >= patience:
                    raise _Stop  # the validation MAE stopped improving: keep its best iterate

        cand = None
        try:
            res = minimize(fun, z, jac=True, method="L-BFGS-B", callback=cb,
                           options={"maxiter": self.cfg.lbfgs_iters, "ftol": 1e-12, "gtol": 1e-12})
            cand = res.x
        except _Stop:
            if self.over_time_limit(t0):
                self.stopped = "time_limit"
        except (KeyboardInterrupt, SystemError) as e:
            if not is_interrupt(e):
                raise
            self.note_interrupt("during the L-BFGS polish; kept the best model")
        try:  # the last iterate's check: a free run over the validation data (seconds), which Ctrl-C may cut
            if cand is not None and np.all(np.isfinite(cand)) and it[0] % val_every != 0:
                check(cand, final=True)
            elif cand is not None and not has_val:
                check(cand, final=True)
        except (KeyboardInterrupt, SystemError) as e:
            if not is_interrupt(e):
                raise
            self.note_interrupt("while checking the L-BFGS polish's last iterate; kept the best model checked before")
        if state["z"] is not None:
            return state["z"]
        self.log("the L-BFGS polish did not improve the " + ("validation MAE" if has_val else "training loss")
                 + "; kept the Adam result")
        return np.array(z if fallback is None else fallback, copy=True)

    def note_interrupt(self, what: str) -> None:
        """Ctrl-C stopped the fit: ``stopped = "interrupted"`` and a warning ``interrupted <what>``. The caller keeps
        the best state it has; what follows the fit (standard errors) is skipped, the model is still saved."""
        self.stopped = "interrupted"
        self.warnings.append(f"interrupted {what}")
        self.log(f"warning: interrupted {what}")

    def record(self, epoch, loss, val, t0, phase, eta=math.nan):
        best = min([r["val_mae"] for r in self.curve if math.isfinite(r["val_mae"])]
                   + [val if math.isfinite(val) else math.inf])
        rec = {"epoch": int(epoch), "phase": phase, "loss": float(loss), "val_mae": float(val),
               "time": time.perf_counter() - t0}
        self.curve.append(rec)
        if self.callback is not None:
            total = self.cfg.epochs if phase != "lbfgs" else self._lbfgs_end
            self.callback({**rec, "epochs": total, "best_val_mae": best, "elapsed": rec["time"],
                           "eta": eta})
