"""Maximum-likelihood fit with standard errors (tnn_dsl.estimation.ml_fit).

* one linear node, data simulated exactly (numpy, fixed seed) from known parameters and noise: the estimates lie
  within 3 standard errors of the truth, and the exact (``jax.hessian``) standard errors equal those of central
  differences of the gradient to 1e-3;
* two records share parameters and noise, each its own x0; the table, summary, JSON and HTML views;
* JAX and torch reach the same log-likelihood at the optimum (a short record);
* Bacher & Madsen's Ti reaches CTSM-R's 2479.2 with a standard error for every physical parameter;
* a small Monte-Carlo coverage check of the 95 % intervals (the full 50-refit run: benchmarks/bench_ml_coverage.py).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.estimation.ml_fit import MLResult, _covariance, display_factor, fit_ml

ROOT = Path(__file__).resolve().parents[1]
BUILDING = Path(os.environ.get("TNN_SHARED", ROOT.parent / "shared")) / "data" / "bacher_madsen_inputPRBS1.csv"

sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_ml_coverage import RC, TRUTH, coverage, simulate  # noqa: E402 - the benchmark's record is the fixture

N_RC = 300


@pytest.fixture(scope="module")
def rc_model():
    """One compiled model for the JAX tests: same-shaped records reuse its compiled likelihood."""
    return tnn_dsl.compile(tnn_dsl.loads(RC, "rc.thn"), "jax")


@pytest.fixture(scope="module")
def rc_fit(rc_model):
    U, Y = simulate(N_RC, seed=3)
    return fit_ml(rc_model, (U, Y, 5.0), integrator="expeuler", hessian="exact")


def test_estimates_cover_the_truth_and_hessians_agree(rc_model, rc_fit):
    """One node simulated exactly (expeuler is then the exact discretisation of the mean): every estimate (C, R,
    σ_w, σ_v, x0) within 3 standard errors of the truth; the exact Hessian's standard errors equal those of the
    finite-difference Hessian of the gradient to 1e-3 relative."""
    r = rc_fit
    assert r.converged and r.n_params == 5 and r.n_obs == N_RC
    for row in r.rows:
        assert row["status"] == "ok", row
        assert abs(row["estimate"] - TRUTH[row["name"]]) < 3 * row["se"], row
        assert abs(row["dF"]) < 1e-3
    U, Y = simulate(N_RC, seed=3)
    fd = fit_ml(rc_model, (U, Y, 5.0), integrator="expeuler", hessian="fd")
    assert r.hessian_method == "exact" and fd.hessian_method == "fd"
    assert fd.loglik == pytest.approx(r.loglik, abs=1e-6)
    se, se_fd = np.array([x["se"] for x in r.rows]), np.array([x["se"] for x in fd.rows])
    np.testing.assert_allclose(se_fd, se, rtol=1e-3)
    np.testing.assert_allclose(fd.hessian, r.hessian, rtol=1e-3, atol=1e-6 * np.abs(r.hessian).max())
    auto = fit_ml(rc_model, (U, Y, 5.0), integrator="expeuler")  # Richardson: much closer to the exact one
    assert auto.hessian_method == "fd"
    np.testing.assert_allclose(auto.hessian, r.hessian, rtol=1e-6, atol=1e-8 * np.abs(r.hessian).max())


def test_table_views_and_criteria(rc_fit):
    """AIC/BIC, t = estimate/se, normal p-values, the delta method (log → value·se), the correlation matrix,
    the file's unit, summary text, JSON and HTML."""
    r = rc_fit
    k, n = r.n_params, r.n_obs
    assert r.aic == pytest.approx(2 * k - 2 * r.loglik) and r.bic == pytest.approx(k * math.log(n) - 2 * r.loglik)
    c = r.row("C_n")
    assert c["coordinate"] == "log" and c["se"] == pytest.approx(c["estimate"] * c["se_z"])
    assert c["t"] == pytest.approx(c["estimate"] / c["se"]) and 0 <= c["p"] < 1e-6
    assert c["unit"] == "J/K" and c["estimate_unit"] == pytest.approx(c["estimate"])
    x0 = r.row("x0[n]")
    assert x0["coordinate"] == "linear" and x0["se"] == pytest.approx(x0["se_z"])
    assert np.allclose(np.diag(r.corr), 1.0) and np.all(np.abs(r.corr) <= 1 + 1e-9)
    text = r.summary()
    for word in ("Estimate", "Std. Error", "t value", "Pr(>|t|)", "dF/dPar", "C_n", "sigma_v[y]", "AIC"):
        assert word in text
    d = json.loads(json.dumps(r.to_dict()))
    assert d["loglik"] == pytest.approx(r.loglik) and len(d["rows"]) == 5
    html = r._repr_html_()
    assert "<table" in html and "C_n" in html
    assert display_factor("kWh/K") == 3.6e6 and display_factor("K/kW") == pytest.approx(1e-3)
    assert display_factor("W/(m^2 K)") == 1.0 and display_factor("degC") is None


def test_two_records_share_parameters():
    """Two records: one C, R, σ_w, σ_v; an x0 each; the log-likelihood is the sum of the records' (checked
    against fitting each with the joint estimates held: the sum equals the joint value)."""
    net = tnn_dsl.loads(RC, "rc.thn")
    recs = [simulate(120, seed=11), simulate(120, seed=12)]
    r = fit_ml(net, [(U, Y, 5.0) for U, Y in recs], integrator="expeuler", hessian="fd")  # fd: no 2nd compile
    names = [row["name"] for row in r.rows]
    assert names == ["C_n", "Rn", "sigma_w[n]", "sigma_v[y]", "x0[n] @record 0", "x0[n] @record 1"]
    assert r.n_obs == 240 and all(row["status"] == "ok" for row in r.rows)
    from tnn_dsl.estimation import loglik
    model = tnn_dsl.compile(net, "jax")
    p = model.init_params()
    p = {**p, "C_n": model.xp.asarray(r.row("C_n")["estimate"]), "Rn": model.xp.asarray(r.row("Rn")["estimate"])}
    total = sum(loglik(model, p, U, Y, 5.0, log_sigma_w=[math.log(r.row("sigma_w[n]")["estimate"])],
                       log_sigma_v=[math.log(r.row("sigma_v[y]")["estimate"])],
                       x0=[r.row(f"x0[n] @record {i}")["estimate"]], integrator="expeuler")
                for i, (U, Y) in enumerate(recs))
    assert total == pytest.approx(r.loglik, abs=1e-8)


def test_jax_and_torch_reach_the_same_optimum():
    """A short record (torch's filter is a Python loop): the torch fit (finite-difference Hessian) reaches the
    JAX fit's log-likelihood, and the standard errors agree."""
    U, Y = simulate(20, seed=5)
    net = tnn_dsl.loads(RC, "rc.thn")
    kw = dict(integrator="expeuler", free=["Rn"])
    rj = fit_ml(net, (U, Y, 5.0), **kw)
    rt = fit_ml(net, (U, Y, 5.0), backend="torch", restart=False, **kw)
    assert isinstance(rt, MLResult) and rt.backend == "torch" and rt.hessian_method == "fd"
    assert rt.loglik == pytest.approx(rj.loglik, abs=1e-6)
    for a, b in zip(rj.rows, rt.rows):
        assert a["name"] == b["name"] and b["estimate"] == pytest.approx(a["estimate"], rel=1e-4)
        if a["status"] == "ok":
            assert b["se"] == pytest.approx(a["se"], rel=1e-3)


@pytest.mark.skipif(not BUILDING.exists(), reason="shared building data not present")
def test_bacher_madsen_ti():
    """Bacher & Madsen's Ti on their PRBS data: log L ≥ 2479.2 − 2 (CTSM-R 2479.2; measured 2479.226 in ~6.5 s),
    a standard error for every physical parameter and σ_w, C ≈ 2.07 kWh/K and R ≈ 5.28 K/kW as CTSM-R; σ_v goes
    to ~0 (as in CTSM-R) and is reported not identifiable."""
    from tnn_dsl.data import read_data

    net = tnn_dsl.load(ROOT / "networks" / "building" / "ti.thn")
    (exp,) = read_data(net, BUILDING, time_unit="h")
    t0 = time.perf_counter()
    r = fit_ml(net, exp)
    print(f"Ti: log L = {r.loglik:.3f} in {time.perf_counter() - t0:.1f} s\n{r.summary()}")
    assert r.loglik > 2479.2 - 2
    for name in ("Aw", "C_ti", "Ria", "sigma_w[ti]", "x0[ti]"):
        row = r.row(name)
        assert row["status"] == "ok" and math.isfinite(row["se"]) and row["se"] > 0, row
    assert r.row("C_ti")["unit"] == "kWh/K" and r.row("C_ti")["estimate_unit"] == pytest.approx(2.07, rel=0.02)
    assert r.row("Ria")["estimate_unit"] == pytest.approx(5.28, rel=0.02)
    sv = r.row("sigma_v[Ti]")
    assert sv["status"] == "not identifiable" or sv["status"] == "ok"


def test_coverage_of_the_95_percent_intervals(rc_model):
    """Ten refits of the one-node network on records simulated from ten seeds: the 95 % Wald intervals (in the
    fitted coordinates) of the 5 estimates cover the truth in ≥ 70 % of the 50 intervals. The bound: at the
    nominal 95 % the misses are ~Binomial(50, 0.05) (mean 2.5), so more than 15 misses (< 70 %) has probability
    < 1e-7 even allowing for the correlation within a fit — a failure means the standard errors are too small,
    not bad luck. (The issue's 85–100 % over 50 refits: benchmarks/bench_ml_coverage.py, measured 2026-11-24.)"""
    res = coverage(10, N=N_RC, seed0=100, model=rc_model)  # the benchmark's own count, 10 refits instead of 50
    hits, n = res["hits"], res["intervals"]
    assert n == 50 and hits / n >= 0.70, hits


def test_at_bound_and_not_identifiable_get_no_standard_error():
    """A resistance whose declared range stops below the truth ends at its bound: ``status = "at bound"``, no
    standard error, a note; the others keep theirs. A singular Hessian (two coordinates that enter only as a
    sum) marks both ``not identifiable`` and leaves the third's variance exact."""
    U, Y = simulate(80, seed=4)
    text = RC.replace("0.5 K/W  free in [0.01 K/W, 50 K/W]", "0.25 K/W  free in [0.01 K/W, 0.3 K/W]")
    net = tnn_dsl.loads(text, "rc.thn")
    r = fit_ml(net, (U, Y, 5.0), integrator="expeuler", hessian="fd")
    row = r.row("Rn")
    assert row["status"] == "at bound" and math.isnan(row["se"]) and row["estimate"] == pytest.approx(0.3)
    assert any(n.startswith("Rn: no standard error") for n in r.notes) and "at bound" in r.summary()
    assert r.row("C_n")["status"] == "ok" and math.isfinite(r.row("C_n")["se"])
    assert r.to_dict()["rows"][1]["se"] is None
    H = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 4.0]])
    cov, singular = _covariance(H, np.zeros(3, dtype=bool))
    assert singular.tolist() == [True, True, False] and cov[2, 2] == pytest.approx(0.25)
    assert np.isnan(cov[0, 0])


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_a_run_that_ends_on_a_diverged_filter_stops_at_its_best_finite_point(backend, monkeypatch):
    """The likelihood turning non-finite in a run's last line search (the filter diverged; here from the 6th
    evaluation of the first run on) ends the fit at the best finite point it evaluated, reported not converged, with
    no restart from there (a doctor's candidate crawled 1000 iterations from such a restart). Without it, the same
    fit restarts once and converges."""
    import scipy.optimize

    from tnn_dsl.estimation import ml_fit

    U, Y = simulate(30, seed=5)
    net = tnn_dsl.loads(RC, "rc.thn")
    real_minimize, real_vg = scipy.optimize.minimize, ml_fit._Joint.value_and_grad
    runs: list[list[float]] = []  # the values each L-BFGS-B run evaluated
    state = {"diverge": True, "inside": False}

    def minimize(fun, x0, **kw):
        runs.append([])
        state["inside"] = True
        try:
            return real_minimize(fun, x0, **kw)
        finally:
            state["inside"] = False

    def value_and_grad(self, z):
        f, g = real_vg(self, z)
        if state["inside"]:
            if state["diverge"] and len(runs) == 1 and len(runs[0]) >= 5:
                f, g = math.nan, np.full_like(g, math.nan)
            runs[-1].append(f)
        return f, g

    monkeypatch.setattr(scipy.optimize, "minimize", minimize)
    monkeypatch.setattr(ml_fit._Joint, "value_and_grad", value_and_grad)
    kw = dict(backend=backend, integrator="expeuler", hessian="fd")
    r = fit_ml(net, (U, Y, 5.0), **kw)
    assert len(runs) == 1 and any(math.isnan(f) for f in runs[0])
    best = min(f for f in runs[0] if np.isfinite(f))
    assert not r.converged and "non-finite" in r.message and r.loglik == pytest.approx(-best, abs=1e-9)
    assert np.all(np.isfinite(r.z)) and any("non-finite" in n for n in r.notes)
    runs.clear()
    state["diverge"] = False
    ok = fit_ml(net, (U, Y, 5.0), **kw)
    assert len(runs) == 2 and ok.converged and ok.loglik > r.loglik
