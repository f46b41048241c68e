"""The Kalman filter of a constant linearisation on torch as two compiled scans (issue 18).

With ``H = ∂h/∂x``, ``F = ∂Φ/∂x`` and ``Q_d`` constant (:func:`~tnn_dsl.estimation.likelihood._constant_linearisation`),
one sample of the filter (:func:`~tnn_dsl.estimation.likelihood._filter`'s ``body``) is a fixed function of the
prior ``(x⁻, P⁻)``, the sample's data and a few constant matrices, whatever the network::

    ŷ = H x⁻ + d_k                 (d_k = h(x_ref, u_k) − H x_ref: the sensors' affine part)
    S = H̃ P⁻ H̃ᵀ + diag(σ_v² where read, else 1)       H̃ = H with the rows of missing readings zeroed
    K = P⁻ H̃ᵀ S⁻¹    x = x⁻ + K (y − ŷ)    P = (I − K H̃) P⁻ (I − K H̃)ᵀ + K R Kᵀ     (Joseph form)
    x⁻' = Φ(x_ref, u_k) + F (x − x_ref)    P⁻' = F P Fᵀ + Q_d

Eager torch pays its per-operation dispatch some forty times a sample, forward and reverse: one value and gradient
of Bacher & Madsen's Ti with a second node (1691 samples) took 1.9 s wherever the covariance does not settle and
:func:`~tnn_dsl.estimation.likelihood._stationary_runs` cannot vectorise, 130 ms where it settles, and 48 ms here
(JAX 38 ms; ``python benchmarks/bench_likelihood.py``, 2026-12-06, the AMD host).

Here the recursion of ``(x⁻, P⁻)`` runs as the compiled forward and adjoint scans of
:class:`~tnn_dsl.compiler.torch_adjoint.AdjointRollout`, the state being ``[x⁻, vec P⁻]`` and the constants its
prepared values; every per-sample output (the likelihood's terms, ``ŷ⁻``, ``ε``, the standard deviations) is then
one vectorised expression of the stored priors, differentiated by autograd as usual. The step is the same for
every network of ``n`` states and ``m`` sensors: the compiled programs are kept per ``(n, m, dtype)`` for the
process, not per model, so a model doctor's candidates share them.

The matrix products are written as multiplications and sums: inductor fuses them (as library calls the forward
and reverse scans took 28 and 62 ms of that evaluation, against 12 and 21 ms). ``S⁻¹`` is a Cholesky factorisation
written out (:func:`_solve_spd`) and a one-state filter is scanned as two states (:func:`_padded`): both work around
failures of torch 2.13.

Same operations as the sample loop, in another order: values and gradients agree to round-off
(``tests/test_likelihood_torch_scan.py``). Second derivatives through the scans are not available (the likelihood's
Hessian is taken by differences of the gradient)."""

from __future__ import annotations

import math
import warnings
from typing import Any

__all__ = ["filter_scan"]

_LOG_2PI = math.log(2.0 * math.pi)
_ROLLOUT: list = []


def _stepper(prep: dict, traced: bool):
    """``step(T, c)``: one sample of the filter on ``T = [x⁻, vec P⁻] (n + n²,)`` with the constants ``prep``
    (``H (m, n)``, ``F (n, n)``, ``Q (n, n)``, ``sv2 (m,)`` K², ``xr (n,)`` K) and the sample's data ``c["s"]``
    (``y (m,)`` K, 0 where missing; ``ok (m,)`` 1.0 where read; ``d (m,)`` K) and ``c["u"] = Φ(x_ref, u_k) (n,)``."""
    import torch

    H, F, Q, sv2, xr = prep["H"], prep["F"], prep["Q"], prep["sv2"], prep["xr"]
    n, m = int(F.shape[0]), int(H.shape[0])
    eye = torch.eye(n, dtype=F.dtype)
    Ft = F.T.clone()  # not a view of an input: torch's scan refuses inputs of its body that alias one another

    def mm(A, B):  # A @ B as a multiply-and-sum: inductor fuses it with its neighbours (no library call a sample)
        return (A[:, :, None] * B[None, :, :]).sum(1)

    def mv(A, v):
        return (A * v[None, :]).sum(1)

    def step(T, c):
        x, P = T[:n], T[n:].reshape(n, n)
        y, ok, d, phi = c["s"]["y"], c["s"]["ok"], c["s"]["d"], c["u"]
        Hm = H * ok[:, None]
        HP = mm(Hm, P)
        S = mm(HP, Hm.T) + torch.diag(torch.where(ok > 0.5, sv2, torch.ones_like(sv2)))
        eps = (y - (mv(H, x) + d)) * ok
        K = (HP / S[0, 0]).T if m == 1 else _solve_spd(S, HP).T
        x_f = x + mv(K, eps)
        IKH = eye - mm(K, Hm)
        P_f = mm(mm(IKH, P), IKH.T) + mm(K * (ok * sv2)[None, :], K.T)
        P_f = 0.5 * (P_f + P_f.T)
        x_n = phi + mv(F, x_f - xr)
        P_n = mm(mm(F, P_f), Ft) + Q
        P_n = 0.5 * (P_n + P_n.T)
        return torch.cat([x_n, P_n.reshape(-1)])
    return step


def _solve_spd(S, B):
    """``S⁻¹ B`` for a small symmetric positive definite ``S (m, m)`` by Cholesky's factorisation written out (``m``
    is fixed when traced): plain arithmetic that inductor compiles into the scan's loop. torch 2.13 does not compile
    ``torch.linalg.solve`` inside a ``scan`` body ("Expected positional argument for parameter …", 2026-12-06)."""
    import torch

    m = int(S.shape[0])
    L = [[None] * m for _ in range(m)]
    for j in range(m):
        s = S[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        L[j][j] = torch.sqrt(s)
        for i in range(j + 1, m):
            t = S[i, j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / L[j][j]
    z = []
    for i in range(m):  # L z = B
        t = B[i]
        for k in range(i):
            t = t - L[i][k] * z[k]
        z.append(t / L[i][i])
    x: list = [None] * m
    for i in range(m - 1, -1, -1):  # Lᵀ x = z
        t = z[i]
        for k in range(i + 1, m):
            t = t - L[k][i] * x[k]
        x[i] = t / L[i][i]
    return torch.stack(x, 0)


def _padded(a, how: int):
    """``a`` with a zero appended along its last axis (``how`` 0: a vector, 1: a matrix's columns) or along both
    axes of a square matrix (``how`` 2). A one-state filter is scanned as a two-state one whose second state has no
    prior variance, no process noise, no transition and no sensor: it stays at zero, and every sum it enters gains an
    exact zero, so the first state's values and derivatives are those of the one-state filter. torch 2.13's C++
    wrapper crashes the process on the one-state scan (a segmentation fault, 2026-12-06), which no fallback could
    catch."""
    import torch

    if how == 2:
        a = torch.cat([a, torch.zeros_like(a[:, :1])], 1)
        return torch.cat([a, torch.zeros_like(a[:1])], 0)
    return torch.cat([a, torch.zeros_like(a[..., :1])], -1)


def _rollout():
    if not _ROLLOUT:
        from ..compiler.model import TorchCompileWarning, inductor_options
        from ..compiler.torch_adjoint import AdjointRollout

        def failed(e: Exception) -> None:
            warnings.warn(f"torch.compile failed in the likelihood filter's backward pass ({type(e).__name__}: "
                          f"{str(e)[:200]}); its gradients are computed uncompiled", TorchCompileWarning, stacklevel=2)

        _ROLLOUT.append(AdjointRollout(_stepper, "tnn_kalman", failed, options=inductor_options()))
    return _ROLLOUT[0]


def filter_scan(x0, P0, *, H, F, Q, sv2, x_ref, phi, Y0, okf, d) -> tuple[Any, ...]:
    """The filter over ``N`` samples from the prior ``x0 (n,)`` K, ``P0 (n, n)`` K²: ``(terms, ŷ⁻, ε, sd_y, x⁻,
    sd_x)``, each with a leading axis ``N`` (the stacked outputs of the sample loop, see the module docstring):
    ``terms (N,)`` = log det S + εᵀS⁻¹ε + m_k log 2π, ``ŷ⁻, ε, sd_y (N, m)`` K, ``x⁻, sd_x (N, n)`` K.
    ``phi (N, n)`` = ``Φ(x_ref, u_k)``, ``Y0 (N, m)`` the readings (0 where missing), ``okf (N, m)`` 1.0 where read,
    ``d (N, m)`` the sensors' affine part; differentiable in every floating argument but ``Y0`` and ``okf``."""
    import torch

    n = int(x0.shape[0])
    T0 = torch.cat([x0, P0.reshape(-1)])
    if n == 1:  # one state: scanned as two, the second held at zero (see _padded)
        prep = {"H": _padded(H, 1), "F": _padded(F, 2), "Q": _padded(Q, 2), "sv2": sv2, "xr": _padded(x_ref, 0)}
        ctx = {"s": {"y": Y0.detach(), "ok": okf.detach(), "d": d}, "v": {}, "u": _padded(phi, 1)}
        states = _rollout()(prep, torch.cat([_padded(x0, 0), _padded(P0, 2).reshape(-1)]), ctx)
        states = states[:, [0, 2]]  # x and P of the one state
    else:
        prep = {"H": H, "F": F, "Q": Q, "sv2": sv2, "xr": x_ref}
        ctx = {"s": {"y": Y0.detach(), "ok": okf.detach(), "d": d}, "v": {}, "u": phi}
        states = _rollout()(prep, T0, ctx)  # (N, n + n²): the prior of the next sample, after each sample
    priors = torch.cat([T0[None], states[:-1]], 0)
    xs, Ps = priors[:, :n], priors[:, n:].reshape(-1, n, n)
    ok = okf > 0.5
    yhat = xs @ H.T + d
    eps = (Y0 - yhat) * okf
    Hm = H[None] * okf[:, :, None]  # (N, m, n)
    HPH = Hm @ Ps @ Hm.transpose(1, 2)
    S = HPH + torch.diag_embed(torch.where(ok, sv2.expand_as(okf), torch.ones_like(okf)))
    if int(H.shape[0]) == 1:
        s = S[:, 0, 0]
        logdet, quad = torch.log(torch.abs(s)), eps[:, 0] * eps[:, 0] / s
    else:
        logdet = torch.linalg.slogdet(S)[1]
        quad = (eps * torch.linalg.solve(S, eps[..., None])[..., 0]).sum(-1)
    terms = logdet + quad + okf.sum(-1) * _LOG_2PI
    HP_H = torch.diagonal(H[None] @ Ps @ H.T[None], dim1=1, dim2=2)
    sd_y = torch.sqrt(torch.clamp(HP_H + sv2, min=0.0))
    sd_x = torch.sqrt(torch.clamp(torch.diagonal(Ps, dim1=1, dim2=2), min=0.0))
    return terms, yhat, eps, sd_y, xs, sd_x
