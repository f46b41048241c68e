"""Fixed-step integrators for ``dT/dt = f(T)`` over one sample interval (inputs held constant).

* ``euler``: explicit Euler, thesis eq. 4.7 ``T_{k+1} = T_k + Δt·f(T_k)``.
* ``rk4``: classical fourth-order Runge–Kutta.
* ``expeuler``: exponential Euler with the diagonal ``d`` of the network's linear part,
  ``T_{k+1} = T_k + Δt·φ₁(Δt·d)·f(T_k)``, ``φ₁(z) = (eᶻ − 1)/z``. It is exact for a single RC node at
  any step, first order in general, and stable for any step on a diagonally dominant conductance network
  (as Δt → ∞ the update becomes a Jacobi sweep towards the steady state), so it does not blow up on
  stiff networks. ``d`` (1/s) comes from the compiler: ``−Σ G/C`` per node, the linearised radiation,
  fluid and Peltier terms, and ``−1/τ`` for sensor lags; the dependence of learned parameters on the
  state is not included. Steady states are exact; energy of an adiabatic network is conserved only
  to O(Δt) in transients (each node is scaled by its own φ₁ factor) — use ``euler``/``rk4`` where
  conservation to round-off matters.

:func:`check_step` compares Δt with the network's fastest time constant ``τ_min = min C/ΣG`` and
chooses sub-steps for the explicit methods (with a warning) instead of letting the rollout diverge.
"""

from __future__ import annotations

import math
import warnings

INTEGRATORS = ("euler", "rk4", "expeuler")

# Largest stable Δt·|λ| on the negative real axis: Euler 2, RK4 ≈ 2.785. The network's eigenvalues
# satisfy |λ| ≤ 2/τ_min (Gershgorin), so Δt ≤ limit·τ_min/2 is safe; a 0.9 margin on top.
_STABLE_RATIO = {"euler": 2.0 / 2.0 * 0.9, "rk4": 2.785 / 2.0 * 0.9}


class StepSizeWarning(UserWarning):
    """The sample interval is too long for an explicit integrator; the rollout sub-steps."""


def euler(f, T, dt):
    """One explicit Euler step (thesis eq. 4.7)."""
    return T + dt * f(T)


def rk4(f, T, dt):
    """One classical RK4 step."""
    k1 = f(T)
    k2 = f(T + (0.5 * dt) * k1)
    k3 = f(T + (0.5 * dt) * k2)
    k4 = f(T + dt * k3)
    return T + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def phi1(xp, z):
    """``(eᶻ − 1)/z`` with the limit 1 at z = 0 (series for |z| < 1e-5)."""
    small = xp.abs(z) < 1e-5
    z_safe = xp.where(small, 1.0, z)
    return xp.where(small, 1.0 + 0.5 * z + z * z / 6.0, xp.expm1(z_safe) / z_safe)


def expeuler(f_and_diag, T, dt, xp):
    """One exponential-Euler step; ``f_and_diag(T) -> (f, d)`` with ``d`` the Jacobian diagonal (1/s)."""
    f, d = f_and_diag(T)
    return T + dt * phi1(xp, dt * d) * f


def stable_substeps(integrator: str, dt: float, tau_min: float) -> int:
    """Sub-steps per sample so that an explicit method is stable: ``ceil(Δt / (ratio·τ_min))``;
    1 for ``expeuler`` or a network without capacities."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    if integrator == "expeuler" or not math.isfinite(tau_min) or tau_min <= 0:
        return 1
    limit = _STABLE_RATIO[integrator] * tau_min
    return max(1, math.ceil(dt / limit - 1e-12))


MAX_AUTO_SUBSTEPS = 1000
"""The most sub-steps per sample chosen automatically; a network that needs more is an error (a value far
too small), not a run of hours."""


def check_step(integrator: str, dt: float, tau_min: float, substeps: int | None, where: str = "") -> int:
    """The number of sub-steps to use. With ``substeps=None`` choose it from :func:`stable_substeps`
    and warn (``StepSizeWarning``) if more than one is needed; an explicit ``substeps`` that is too few
    also warns but is respected."""
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    need = stable_substeps(integrator, float(dt), tau_min)
    node = f" (node {where})" if where else ""
    if substeps is None:
        if need > MAX_AUTO_SUBSTEPS:
            from ..core import Diagnostic, TnnError

            raise TnnError(Diagnostic(
                f"the fastest time constant of the network is {tau_min:.4g} s{node}: a stable {integrator} step "
                f"over the sample period of {dt:g} s would need {need:,} sub-steps (more than "
                f"{MAX_AUTO_SUBSTEPS:,})",
                hint="check the values that set it (a capacity or resistance many orders of magnitude too small), "
                     "or use --integrator expeuler (integrator='expeuler'), which is stable at any step"))
        if need > 1:
            warnings.warn(
                f"dt = {dt:g} s is too long for {integrator} on this network: the fastest time constant is "
                f"{tau_min:.4g} s{node}; using {need} sub-steps of {dt / need:.4g} s. Pass substeps=... to "
                f"choose, or integrator='expeuler' for a stiff-stable step.",
                StepSizeWarning,
                stacklevel=3,
            )
        return need
    substeps = int(substeps)
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    if substeps < need:
        warnings.warn(
            f"{substeps} sub-step(s) of {dt / substeps:g} s may be unstable for {integrator}: the fastest time "
            f"constant is {tau_min:.4g} s{node}; at least {need} are needed.",
            StepSizeWarning,
            stacklevel=3,
        )
    return substeps


__all__ = ["INTEGRATORS", "euler", "rk4", "expeuler", "phi1", "stable_substeps", "check_step", "StepSizeWarning"]
