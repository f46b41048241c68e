"""The pre-fit of a ``replace``-mode learned flow to the nominal physics law it replaces.

Before training, the trainer fits such a function's weights to the nominal flow along the nominal run, so that
training starts from the known physics (thesis M4: the Peltier element's heat flows by an MLP of its side
temperatures and the current). The fit is a small nonlinear least-squares problem: ``PREFIT_POINTS`` samples of
the run, one residual per sample and flow, ``(q(x; w) − q_nominal(x)) / rms(q_nominal)``.

It is solved by Levenberg–Marquardt (MINPACK's ``lmder`` through :func:`scipy.optimize.least_squares`) with the
backend's forward-mode Jacobian of the residuals. An MLP fitted to a smooth law sits in a flat valley of equally
good weights; a quasi-Newton method (L-BFGS, used here until 2026-12-02) wanders along it, and where it stops
depends on the last digits of the gradient, so JAX and torch started training the same network from weights
10–30 % apart (BENCHMARKS.md, "The demos after the reverse scan's change"). The damped Gauss–Newton steps do not
amplify round-off along the valley: the two backends' fits agree to about 1e-12 (``tests/test_train_prefit.py``),
and they fit closer. ``python benchmarks/profile_prefit.py`` (the case study's M4 on the demo's data, 2026-12-02,
the Intel host): relative RMS error over the whole run 3.0e-4 (Q_hot) and 2.0e-4 (Q_cold) on both backends, the
weights 7.7e-13 apart, in 2.1 s on JAX and 3.6–4.2 s on torch; the L-BFGS pre-fit before (the same script in a
worktree of 556c60a) 1.8e-3 and 1.1e-3 on JAX, 1.5e-3 and 1.3e-3 on torch, weights 0.16 apart, 0.9 and 1.8 s.
Functions with more than ``PREFIT_LM_MAX_WEIGHTS`` weights, whose Jacobian would not fit in memory comfortably, are
fitted by L-BFGS-B on the same residuals instead.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

PREFIT_POINTS = 1000
"""Samples of the nominal run the pre-fit uses (evenly spaced over all training files): every 14 s of the case
study's 4 h run, and ``PREFIT_POINTS × n_flows`` residuals against the 122 weights of its 3→8→8→2 MLP."""

PREFIT_MAX_EVALUATIONS = 60
"""Residual evaluations of the Levenberg–Marquardt fit (about 45 Jacobians). ``python benchmarks/profile_prefit.py
--backends jax --evaluations 20 40 100`` (M4, 2026-12-02): relative RMS error (Q_hot) 1.6e-3 after 20, 5.5e-4 after
40, 3.0e-4 after 60, 1.7e-4 after 100, in 1.1, 1.4, 2.1 and 2.3 s. A fixed budget, not a tolerance, ends it: the
start of training needs the nominal law closely, not exactly."""

PREFIT_RIDGE = 1e-7
"""Weight decay of the pre-fit: ``ridge · ‖w‖²`` is added to the sum over flows of the mean squared relative error
(both dimensionless: the weights act on normalised inputs and outputs), so a weight of 1 costs as much as a relative
error of 3e-4 at every sample. Without it Levenberg–Marquardt follows the valley to large weights that cancel, a fit
that Adam's first steps of training throw far off. ``python benchmarks/profile_prefit.py --backends jax --ridge 0
1e-8 1e-6`` (M4, 2026-12-02): largest weight 3.78 without it, 2.14 at 1e-8, 1.53 at 1e-7, 0.85 at 1e-6 (relative RMS
error 3.5e-4, 1.8e-4, 3.0e-4, 5.7e-4); ``--first-epochs --ridge 0 1e-7`` (M4 on the 40-minute case study of
``tests/test_train.py``): validation MAE 91 → 1142 mK after the first epoch without it, 91 → 196 mK with it. It also
makes the least-squares problem better posed, so the fit depends less on the path to it."""

PREFIT_LM_MAX_WEIGHTS = 2000
"""Above this many weights the pre-fit uses L-BFGS-B (its Jacobian would hold ``PREFIT_POINTS × n_flows ×
n_weights`` floats)."""


def fit_weights(residuals: Callable[[Any], Any], z0: np.ndarray, ops: Any, ridge: float = PREFIT_RIDGE
                ) -> tuple[np.ndarray, float, str]:
    """Least squares ``min ‖r(z)‖² + ridge·‖z‖²`` from ``z0`` for a backend function ``residuals: z (n,) → r (m,)``
    → ``(z, ‖r(z)‖, method)``; ``method`` is ``"levenberg-marquardt"`` or ``"l-bfgs-b"``. Never worse than
    ``z0``: a fit that ends higher, or not finite, returns ``z0``."""
    from scipy.optimize import least_squares, minimize

    z0 = np.asarray(z0, dtype=float)
    fit_residuals = residuals
    if ridge > 0:
        def residuals(z):
            return ops.xp.concat([fit_residuals(z), math.sqrt(ridge) * z])

    r_prog, fit_prog = ops.jit(residuals), ops.jit(fit_residuals)

    def r(z):
        out = np.asarray(ops.numpy(r_prog(ops.asarray(z))), dtype=float)
        return np.where(np.isfinite(out), out, 1e6)  # a blown-up trial step: a large finite residual, so LM backs off

    m = int(r(z0).shape[0])
    if z0.size <= PREFIT_LM_MAX_WEIGHTS and m >= z0.size:
        jac = ops.jacobian_program(residuals)

        def J(z):
            out = jac(z)
            return np.where(np.isfinite(out), out, 0.0)

        res = least_squares(r, z0, jac=J, method="lm", max_nfev=PREFIT_MAX_EVALUATIONS,
                            ftol=1e-12, xtol=1e-12, gtol=1e-12)
        z, method = res.x, "levenberg-marquardt"
    else:
        vg = ops.value_and_grad(lambda zz: ops.xp.sum(residuals(zz) ** 2))
        scale = 1.0 / max(float(np.sum(r(z0) ** 2)), 1e-300)  # scipy's stopping test is relative to max(|f|, 1)

        def fun(z):
            v, g = vg(z)
            return (v * scale, g * scale) if math.isfinite(v) and np.all(np.isfinite(g)) else (1e12, np.zeros_like(z))

        z, method = minimize(fun, z0, jac=True, method="L-BFGS-B", options={"maxiter": 500}).x, "l-bfgs-b"
    if not (np.all(np.isfinite(z)) and np.linalg.norm(r(z)) <= np.linalg.norm(r(z0))):
        z = z0
    return z, float(np.linalg.norm(ops.numpy(fit_prog(ops.asarray(z))))), method


__all__ = ["PREFIT_POINTS", "PREFIT_MAX_EVALUATIONS", "PREFIT_RIDGE", "PREFIT_LM_MAX_WEIGHTS", "fit_weights"]
