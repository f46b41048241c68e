"""The rollouts the trainer fits: which (single shooting from fitted initial states, multiple shooting in windows of
at least the slowest time constant, windows from the measured or steady state), their batched arrays, the fitted
initial states and per-experiment values they leave, and the switch from a windowed fit to single shooting.

:class:`_Rollouts` is a base of :class:`~tnn_dsl.fit.trainer._Trainer` and works on its attributes (``cfg``,
``exps``, ``model``, ``net``, ``params0``, ``n_param_z``, ``pe_names``, ``ops``) and methods (``polish``,
``validate``, ``make_loss``, ``params_from_z``, ``numpy_params``, ``log``)."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .config import finishes_as_single_shooting
from .initial import check_rule, fingerprint, initial_state, measured_arrays, sensed_states
from .simulation import start_range
from .transforms import _NumpyOps
from .windows import _Window, _windows, auto_window


def _safe(res: tuple[float, np.ndarray]) -> tuple[float, np.ndarray]:
    """``(value, gradient)`` with a non-finite value or gradient replaced by a large value and a zero gradient
    (so that L-BFGS-B backs off instead of stopping)."""
    v, g = res
    if not math.isfinite(v) or not np.all(np.isfinite(g)):
        return 1e30, np.zeros_like(g)
    return v, g


class _Rollouts:
    """The rollout part of the trainer (see the module docstring)."""

    def experiment_values(self, z: np.ndarray) -> list[dict[str, Any]]:
        """Each training file's per-experiment parameter values (SI): ``[{"name", "fingerprint", "values"}]``."""
        if not self.pe_names:
            return []
        p = self.params_from_z(np.asarray(z, dtype=float), _NumpyOps)
        out = []
        for i, e in enumerate(self.exps):
            vals = {k: float(np.asarray(p[k if i == 0 else f"{k}@{i}"]).reshape(-1)[0]) for k in self.pe_names}
            out.append({"name": e.name, "fingerprint": fingerprint(e), "values": vals})
        return out

    def _experiment_params(self, params: dict, e_i: int) -> dict:
        """``params`` with experiment ``e_i``'s values of the per-experiment parameters."""
        if not self.pe_names or e_i == 0:
            return params
        out = dict(params)
        for k in self.pe_names:
            out[k] = params[f"{k}@{e_i}"]
        return out

    def _rollout_per_file(self, params: dict, exps: Any, T0: Any, U: Any, dt: float) -> tuple[Any, Any]:
        """Rollouts of windows of several files, each with its file's per-experiment values: ``exps (B,)`` the
        file of each window, ``T0 (B, n_states)``, ``U (B, L, n_inputs)``. One vectorised rollout (``jax.vmap``
        over the windows, the values gathered per window) instead of one per file: one program, whatever the number
        of files (JAX only; :meth:`build_batches` keeps the files apart elsewhere)."""
        import jax

        xp = self.ops.xp
        n = len(self.exps)
        per = {k: xp.stack([params[k]] + [params[f"{k}@{i}"] for i in range(1, n)])[exps] for k in self.pe_names}
        common = {k: v for k, v in params.items() if "@" not in k and k not in per}
        cfg, model = self.cfg, self.model

        def one(pw, T0w, Uw):
            return model.rollout({**common, **pw}, T0w, Uw, dt, integrator=cfg.integrator, substeps=cfg.substeps)

        return jax.vmap(one)(per, T0, U)

    def fitted_initial_states(self, z: np.ndarray) -> list[dict[str, Any]]:
        """The fitted initial state of each training file whose first window starts at its first sample (single
        shooting, multiple shooting): ``[{"name", "fingerprint", "T0": {state: K}}]``, stored with the model."""
        if not self.n_x0:
            return []
        names = list(self.model.state_names)
        X0 = self.x0_guess + np.asarray(z[self.n_param_z:], dtype=float).reshape((self.n_x0, len(names)))
        out = []
        for w_i, w in enumerate(self.wins):
            if w.start == 0 and np.all(np.isfinite(X0[w_i])):
                e = self.exps[w.exp]
                out.append({"name": e.name, "fingerprint": fingerprint(e),
                            "T0": {n: float(v) for n, v in zip(names, X0[w_i])}})
        return out

    _force_single = False
    _full_vg: Any = None
    """The current layout's compiled loss and gradient over the whole batch (``full_loss``); ``None`` until built."""
    vectorise_files = True
    """Windows of several files with per-experiment values in one vectorised rollout (JAX; :meth:`_rollout_per_file`)
    rather than one rollout per file (the same loss to round-off; the tests compare both)."""
    windowed: tuple[str, float] | None = None
    """(mode, window s) of the windowed phase when :meth:`finish_single_shooting` followed it."""

    def wants_single_shooting_finish(self) -> bool:
        """Whether a windowed fit goes on as single shooting (:data:`~.config.SINGLE_SHOOTING_MAX_STEPS`)."""
        return not self.single_shooting and self.mode != "free" and finishes_as_single_shooting(self.cfg, self.exps)

    def finish_single_shooting(self, z: np.ndarray) -> np.ndarray:
        """The windowed solution ``z`` polished as single shooting: each file one free run from a fitted initial
        state (the first window's fitted state, else the burn-in estimate), L-BFGS on the free-run loss; the
        result is kept where it beats ``z`` (validation MAE, else the free-run training loss). Returns the new
        ``z`` in the single-shooting layout."""
        names = list(self.model.state_names)
        starts = [None] * len(self.exps)
        if self.n_x0:
            X0 = self.x0_guess + np.asarray(z[self.n_param_z:], dtype=float).reshape((self.n_x0, len(names)))
            for w_i, w in enumerate(self.wins):
                if w.start == 0:
                    starts[w.exp] = X0[w_i]
        zp = np.asarray(z[:self.n_param_z], dtype=float)
        bp = self.model.from_numpy(self.params_from_z(zp, _NumpyOps))
        for i, e in enumerate(self.exps):
            if starts[i] is None:
                starts[i] = initial_state(self.net, self.model, self._experiment_params(bp, i), e, "estimate",
                                          integrator=self.cfg.integrator, substeps=self.cfg.substeps).T
        windowed = (self.mode, self.window)
        self._force_single = True
        self.build_batches([np.asarray(T0)[None] for T0 in starts])
        z_ss = np.concatenate([zp, np.zeros(self.n_x0 * len(names))])
        data, full_vg = self.full_loss()
        has_val = bool(self.vals)
        best = self.validate(z_ss) if has_val else _safe(full_vg(z_ss, data))[0]
        self.log("single shooting: one free run per file from its fitted initial state, from the windowed fit")
        out = self.polish(z_ss, full_vg, data, best, has_val, time.perf_counter())
        self.windowed = windowed
        return out

    def slowest_tau(self) -> float:
        """The slowest node time constant (s) of the network at its nominal values (``C/ΣG`` per node): the
        shortest automatic window of multiple shooting (a window shorter than it fits the slow states' starts
        instead of their dynamics)."""
        try:
            taus = [float(t) for t in self.model.time_constants().values()]
        except Exception:  # noqa: BLE001 - a network whose nominal point has no time constants: no lower bound
            return 0.0
        taus = [t for t in taus if math.isfinite(t) and t > 0]
        return max(taus) if taus else 0.0

    def plan_rollout(self) -> tuple[str, float, bool]:
        """``(mode, window s, single shooting)``: ``rollout=auto`` is one free run per file for files of at most
        three windows, else multiple shooting in windows of ``max(auto_window, slowest node time constant)``
        unless ``window`` is given; a free run with the ``estimate`` or ``filter`` rule fits each file's initial
        state with the parameters (single shooting: one window per file with its initial state free, mode
        ``estimated``). :meth:`finish_single_shooting` switches a windowed fit to single shooting."""
        cfg = self.cfg
        mode = cfg.rollout
        window = float(cfg.window) if cfg.window is not None else max(auto_window(self.exps), self.slowest_tau())
        if mode == "auto":
            longest = max(e.n_steps for e in self.exps)
            dt = min(float(e.dt) for e in self.exps)
            mode = "free" if longest <= 3 * (window / dt + 1) else "estimated"
        if (mode == "free" or self._force_single) and check_rule(cfg.init) in ("estimate", "filter"):
            return "estimated", 2.0 * max(e.n_steps * float(e.dt) for e in self.exps), True
        return mode, window, False

    def build_batches(self, runs) -> None:
        """Groups of equal-length rollouts (arrays) and their static description."""
        cfg = self.cfg
        self._full_vg = None  # the whole batch's loss program is this layout's (``full_loss``)
        mode, window, self.single_shooting = self.plan_rollout()
        self.window = window
        init = check_rule(cfg.init)
        self.mode = mode
        n_states = len(self.model.state_names)
        mapping = sensed_states(self.model, self.net, self.params0)
        self.groups: list[dict[str, Any]] = []
        self.n_x0 = 0
        if mode == "free":
            for e_i, e in enumerate(self.exps):
                Y = np.asarray(e.outputs, dtype=float)[None]
                mask0, vals0 = measured_arrays(mapping, n_states, Y[:, 0])
                if init != "measured":
                    mask0[:] = False
                self.groups.append({"dt": float(e.dt), "init": "measured", "windows": [_Window(e_i, 0, e.n_steps)],
                                    "U": np.asarray(e.inputs, dtype=float)[None], "Y": Y,
                                    "mask0": mask0, "vals0": vals0, "exp": e_i})
            return
        wins = _windows(self.exps, window)
        # windows of one file apart where the files have per-experiment values, unless each window can carry its
        # file's values through a vectorised rollout (JAX, fitted starts: one rollout for the windows of every file)
        self.pe_vmap = (bool(self.pe_names) and mode == "estimated" and self.model.backend == "jax"
                        and self.vectorise_files)
        by_len: dict[tuple[float, int, int], list[int]] = {}
        for w_i, w in enumerate(wins):
            apart = w.exp if self.pe_names and not self.pe_vmap else 0
            by_len.setdefault((float(self.exps[w.exp].dt), w.length, apart), []).append(w_i)
        if mode == "estimated":
            guess = np.zeros((len(wins), n_states))
            for w_i, w in enumerate(wins):
                guess[w_i] = runs[w.exp][w.start]
                if self.single_shooting:  # the nominal run started at the burn-in estimate: keep it
                    continue
                y0 = np.asarray(self.exps[w.exp].outputs, dtype=float)[w.start]
                m, v = measured_arrays(mapping, n_states, y0)
                guess[w_i] = np.where(m, v, guess[w_i])
            self.x0_guess = guess
            self.n_x0 = len(wins)
            # where a fitted initial state may lie (a penalty outside: start_range), per window's file
            bounds = [start_range(self.model, self.exps[w.exp]) for w in wins]
            self.x0_low = np.array([b[0] for b in bounds])[:, None] * np.ones((1, n_states))
            self.x0_high = np.array([b[1] for b in bounds])[:, None] * np.ones((1, n_states))
        self.wins = wins
        for (dt, L, e_i), ids in by_len.items():
            U = np.stack([np.asarray(self.exps[wins[i].exp].inputs, dtype=float)[wins[i].start:wins[i].start + L]
                          for i in ids])
            Y = np.stack([np.asarray(self.exps[wins[i].exp].outputs, dtype=float)[wins[i].start:wins[i].start + L]
                          for i in ids])
            mask0, vals0 = measured_arrays(mapping, n_states, Y[:, 0])
            if mode == "steady":
                mask0[:] = False
            self.groups.append({"dt": dt, "init": "estimated" if mode == "estimated" else "measured",
                                "windows": [wins[i] for i in ids], "ids": np.array(ids), "U": U, "Y": Y,
                                "mask0": mask0, "vals0": vals0, "exp": None if self.pe_vmap else e_i,
                                "exps": np.array([wins[i].exp for i in ids], dtype=np.int64)})

    def batch_arrays(self, rng: np.random.Generator | None):
        """The per-step data: list (one per group) of dicts of backend arrays, and the statics."""
        out, statics = [], []
        for g in self.groups:
            B = len(g["windows"])
            sel = np.arange(B)
            if rng is not None and self.cfg.batch_size and self.cfg.batch_size < B:
                sel = np.sort(rng.choice(B, size=self.cfg.batch_size, replace=False))
            Y = g["Y"][sel]
            M = np.isfinite(Y)
            d = {"U": g["U"][sel], "Y": np.where(M, Y, 0.0), "M": M}
            st = {"dt": g["dt"], "init": g["init"], "n_valid": max(int(M.sum()), 1), "B": len(sel), "exp": g["exp"]}
            if g["exp"] is None:  # windows of several files, each rolled out with its file's values
                d["exps"] = g["exps"][sel]
            if g["init"] == "estimated":
                ids = g["ids"][sel]
                cb, ck, cj, cw = [], [], [], []
                for b, i in enumerate(ids):
                    w = self.wins[i]
                    if w.succ is not None:
                        cb.append(b)
                        ck.append(w.succ[1])
                        cj.append(w.succ[0])
                        cw.append(1.0)
                if not cb:
                    cb, ck, cj, cw = [0], [0], [int(ids[0])], [0.0]
                d.update({"idx": ids.astype(np.int64), "cb": np.array(cb, dtype=np.int64),
                          "ck": np.array(ck, dtype=np.int64), "cj": np.array(cj, dtype=np.int64),
                          "cw": np.array(cw, dtype=float)})
                st["n_pairs"] = max(float(sum(cw)), 1.0)
            else:
                d.update({"mask0": g["mask0"][sel], "vals0": g["vals0"][sel]})
            out.append(d)
            statics.append(st)
        return self.ops.tree(out), statics
