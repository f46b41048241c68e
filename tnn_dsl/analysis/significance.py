"""Significance tests on prediction errors.

* :func:`held_out_test`: does a model predict held-out rows better than another one, charged for its extra
  parameters and with autocorrelated errors (Diebold–Mariano with a Newey–West variance)?
* :func:`held_out_loglik_test`: the same question for one-step-ahead predictors, on the per-sample log-likelihood
  of the held-out rows (the likelihood objective's held-out check).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from . import residuals as R

__all__ = ["held_out_test", "held_out_loglik_test"]


def held_out_test(e0: np.ndarray, e1: np.ndarray, k: int) -> tuple[float, float, float]:
    """Does the candidate predict the held-out rows better, accounting for its ``k`` extra parameters and
    for autocorrelated errors? Diebold–Mariano test on the squared-error differential
    ``d_t = e0_t² − e1_t² − 2k·mean(e1²)/N`` (an AIC-type charge for the extra parameters, spread over the
    samples) with a Newey–West (Bartlett) long-run variance whose bandwidth is where the differential's
    autocorrelation has died out. Returns ``(DM statistic, one-sided p, effective sample size N/(1+2Σρ))``."""
    ok = np.isfinite(e0) & np.isfinite(e1)
    if not np.all(np.isfinite(e1)) or ok.sum() < 8:
        return 0.0, 1.0, 0.0
    e0, e1 = e0[ok], e1[ok]
    n = e0.size
    if np.allclose(e0, e1, rtol=1e-9, atol=1e-12):  # the same predictions: no evidence either way
        return 0.0, 0.5, float(n)
    d = e0**2 - e1**2 - 2.0 * k * float(np.mean(e1**2)) / n
    return _diebold_mariano(d)


def held_out_loglik_test(l0: np.ndarray, l1: np.ndarray, k: int) -> tuple[float, float, float]:
    """Does model 1 predict the held-out rows better one step ahead, charged ``k`` for its extra estimated
    quantities (AIC's charge, spread over the samples)? Diebold–Mariano on ``d_t = l1_t − l0_t − k/N``, ``l_t`` the
    Gaussian log-likelihood of sample ``t``'s innovations under each model. Returns ``(DM statistic, one-sided p,
    effective sample size)``; ``(0, 1, 0)`` with fewer than 8 rows finite in both."""
    ok = np.isfinite(l0) & np.isfinite(l1)
    if ok.sum() < 8:
        return 0.0, 1.0, 0.0
    d = l1[ok] - l0[ok] - float(k) / int(ok.sum())
    return _diebold_mariano(d)


def _diebold_mariano(d: np.ndarray) -> tuple[float, float, float]:
    """Is the mean of the loss differential ``d`` (N,) positive? ``(statistic, one-sided p, N/(1+2Σρ))``, the
    long-run variance Newey–West (Bartlett) with the bandwidth where ``d``'s autocorrelation has died out."""
    n = d.size
    dm = d - d.mean()
    var0 = float(dm @ dm) / n
    if var0 <= 0:
        return (math.inf, 0.0, float(n)) if d.mean() > 0 else (0.0, 1.0, float(n))
    rho = R.acf(d, min(n // 4, 2000))
    band = 1.96 / math.sqrt(n)
    below = np.flatnonzero(np.abs(rho[1:]) < band)
    L = int(below[0]) + 1 if below.size else rho.size - 1
    w = 1.0 - np.arange(1, L + 1) / (L + 1)
    lrv = var0 * (1.0 + 2.0 * float(np.sum(w * rho[1: L + 1])))
    lrv = max(lrv, var0 / n)
    stat = float(d.mean() / math.sqrt(lrv / n))
    p = float(stats.norm.sf(stat))
    return stat, p, float(n * var0 / lrv)
