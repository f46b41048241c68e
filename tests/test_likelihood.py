"""The continuous–discrete EKF likelihood (tnn_dsl.estimation.likelihood), on both backends.

* a one-node linear network: the likelihood is the exact discrete Kalman filter written out here in numpy;
* JAX and torch agree to round-off (value and gradient), also on a two-node network with missing readings;
* the gradient (a physical parameter, log σ_w, log σ_v, x0, log p0) matches central finite differences;
* on data simulated exactly from a stochastic two-node network, the true σ_w beats 10× too small / too large;
* Bacher & Madsen's model Ti on their PRBS data reaches CTSM-R's maximum log-likelihood (2479.2).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

import tnn_dsl
from tnn_dsl.compiler import backend_of
from tnn_dsl.estimation.likelihood import LikelihoodProblem, innovations, loglik, nll

BACKENDS = ["jax", "torch"]
ROOT = Path(__file__).resolve().parents[1]
BUILDING = Path(os.environ.get("TNN_SHARED", ROOT.parent / "shared")) / "data" / "bacher_madsen_inputPRBS1.csv"

RC = """
network rc "one node"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node n C = 100 J/K  free
R n -- amb = 0.5 K/W  free as Rn
source n = P
sensor y = n column "y"
"""

RADIATING = """
network radiating "a heater losing heat by conduction and radiation"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node n C = 20 J/K  free
G n -- amb = 0.02 W/K  free as U
radiation n -- amb  area = 1e-3 m^2  emissivity = 0.9
source n = P
sensor y = n column "y"
"""

TWO = """
network two "two heaters, one sensor"
units temperature = K
input Ta : temperature column "Ta"
input Q1 : [W] column "Q1"
boundary amb = Ta
node h1 C = 60 J/K  free
node h2 C = 40 J/K  free
G h1 -- amb = 0.3 W/K  free as G1
G h2 -- amb = 0.2 W/K  free as G2
G h1 -- h2 = 0.5 W/K  free as G12
source h1 = Q1
sensor T1 = h1 column "T1"
sensor T2 = h2 column "T2"
"""

C_RC, R_RC = 100.0, 0.5
TAU = C_RC * R_RC


def _rc_record(N=60, dt=5.0, seed=0):
    rng = np.random.default_rng(seed)
    U = np.stack([290.0 + rng.normal(0.0, 1.0, N), rng.uniform(0.0, 40.0, N)], axis=1)
    y = 295.0 + np.cumsum(rng.normal(0.0, 0.3, N))
    y[0] = np.nan           # missing at the first sample (the prior predicts through)
    y[10:14] = np.nan       # a dropout
    y[30] = np.nan
    return U, y[:, None], dt


def _hand_filter(U, y, dt, a, sw, sv, x0, p0):
    """The exact discrete Kalman filter of ``C dT/dt = (Ta − T)/R + P`` (scalar, numpy): transition ``a``,
    ``b = (1 − a)``, towards ``T∞ = Ta + R P``, ``Q_d = σ_w² (1 − e^{−2Δt/τ}) τ/2``. Returns ``(log L, ŷ⁻, ε, std)``."""
    ae = math.exp(-dt / TAU)
    q = sw ** 2 * (1.0 - ae * ae) * TAU / 2.0
    x, P = x0, (q if p0 is None else p0 ** 2)
    ll, pred, inn, sd = 0.0, [], [], []
    for k in range(len(U)):
        S = P + sv ** 2
        pred.append(x)
        sd.append(math.sqrt(S))
        if np.isfinite(y[k, 0]):
            e = y[k, 0] - x
            inn.append(e)
            ll -= 0.5 * (math.log(S) + e * e / S + math.log(2.0 * math.pi))
            K = P / S
            x, P = x + K * e, (1.0 - K) ** 2 * P + K * K * sv ** 2
        else:
            inn.append(np.nan)
        x_inf = U[k, 0] + R_RC * U[k, 1]
        x, P = x_inf + a * (x - x_inf), a * a * P + q
    return ll, np.array(pred), np.array(inn), np.array(sd)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("integrator", ["expeuler", "rk4"])
@pytest.mark.parametrize("p0", [0.7, None])
def test_one_node_equals_the_exact_discrete_kalman_filter(backend, integrator, p0):
    """One linear node, one sensor, NaN readings (also the first): the likelihood equals the exact discrete
    Kalman filter in numpy to 1e-9 relative. ``expeuler`` is exact for a single RC node with constant inputs
    (``T⁺ = T + Δt·φ₁(−Δt/τ)·f = T∞ + e^{−Δt/τ}(T − T∞)``), so the hand filter uses ``a = e^{−Δt/τ}``. ``rk4``'s
    transition factor is its degree-4 Taylor polynomial of ``e^{−Δt/τ}`` (here ``Δt/τ = 0.1``: 8e-8 from the
    exponential, which would show at 1e-9), so for ``rk4`` the hand filter takes that factor for the mean and
    ``F`` and the exact ``Q_d`` (the module's documented choice). ``p0=None``: CTSM's ``P0 = Q_d``."""
    U, y, dt = _rc_record()
    model = tnn_dsl.compile(tnn_dsl.loads(RC, "rc.thn"), backend)
    params = model.init_params()
    sw, sv, x0 = 0.05, 0.2, 293.0
    z = -dt / TAU
    a = math.exp(z) if integrator == "expeuler" else 1 + z + z * z / 2 + z ** 3 / 6 + z ** 4 / 24
    ll, pred, inn, sd = _hand_filter(U, y, dt, a, sw, sv, x0, p0)
    kw = dict(log_sigma_w=[math.log(sw)], log_sigma_v=[math.log(sv)], x0=[x0],
              log_p0_std=None if p0 is None else [math.log(p0)], integrator=integrator)
    got = loglik(model, params, U, y, dt, **kw)
    assert got == pytest.approx(ll, rel=1e-9)
    v = nll(model, params, U, y, dt, **kw)
    assert float(backend_of(model).numpy(v)) == pytest.approx(-ll, rel=1e-9)
    res = innovations(model, params, U, y, dt, **kw)
    np.testing.assert_allclose(res.predicted[:, 0], pred, rtol=1e-12)
    np.testing.assert_allclose(res.std[:, 0], sd, rtol=1e-9)
    np.testing.assert_array_equal(np.isnan(res.innovations[:, 0]), np.isnan(y[:, 0]))
    np.testing.assert_allclose(res.innovations[:, 0], inn, rtol=1e-9, atol=1e-9)
    assert res.loglik == pytest.approx(ll, rel=1e-9)


def _two_record(N=50, dt=2.0, seed=1):
    rng = np.random.default_rng(seed)
    U = np.stack([295.0 + 0.5 * np.sin(np.arange(N) / 9.0), np.repeat(rng.uniform(0, 10, N // 10 + 1), 10)[:N]],
                 axis=1)
    Y = 297.0 + np.cumsum(rng.normal(0, 0.1, (N, 2)), axis=0)
    Y[5:9, 0] = np.nan   # sensor 1 missing
    Y[20:30, 1] = np.nan  # sensor 2 missing
    Y[40, :] = np.nan     # both missing
    return U, Y, dt


def _problem(backend, **kw):
    model = tnn_dsl.compile(tnn_dsl.loads(TWO, "two.thn"), backend)
    U, Y, dt = _two_record()
    return LikelihoodProblem(model, model.init_params(), U, Y, dt, log_sigma_w=[math.log(0.02), math.log(0.05)],
                             log_sigma_v=[math.log(0.1), math.log(0.2)], x0=[297.0, 296.5], **kw)


def test_backends_agree_on_value_and_gradient():
    """Two nodes, two sensors with dropouts (one, the other, both): JAX and torch give the same −log L and
    gradient to round-off, for the default ``P0`` and a fitted one."""
    for kw in ({}, {"fit_p0": True, "log_p0_std": [0.1, -0.3]}):
        out = {}
        for backend in BACKENDS:
            pr = _problem(backend, integrator="rk4", **kw)
            z = pr.z0 + 0.03 * np.random.default_rng(0).standard_normal(pr.z0.shape)
            out[backend] = pr.value_and_grad(z)
        (vj, gj), (vt, gt) = out["jax"], out["torch"]
        assert np.isfinite(vj) and vj == pytest.approx(vt, rel=1e-9)
        np.testing.assert_allclose(gj, gt, rtol=1e-9, atol=1e-9 * np.abs(gj).max())


def test_backends_agree_where_the_linearisation_moves_with_the_state():
    """A heater radiating to its surroundings (``H``, ``F``, ``A`` and ``Q_d`` at every sample; torch's Jacobians by
    reverse mode, JAX's by forward mode): the same −log L and gradient to round-off; and torch's model prepared
    once for the record (``Model.sample_steps``) steps as ``Model.rollout`` does."""
    net = tnn_dsl.loads(RADIATING, "radiating.thn")
    rng = np.random.default_rng(4)
    U = np.column_stack([np.full(24, 296.0), np.repeat(rng.uniform(0.0, 3.0, size=3), 8)])
    mn = tnn_dsl.compile(net, "numpy")
    p = mn.init_params()
    _, Y = mn.rollout(p, np.asarray(mn.steady_state(p, U[0])), U, 5.0)
    Y = np.asarray(Y) + 0.05 * rng.standard_normal(np.shape(Y))
    Y[5, 0] = np.nan  # a dropout
    out = {}
    for backend in BACKENDS:
        m = tnn_dsl.compile(net, backend)
        pr = LikelihoodProblem(m, m.init_params(), U, Y, 5.0)
        assert not pr.static.constant
        z = pr.z0 + 0.02 * np.random.default_rng(1).standard_normal(pr.z0.shape)
        out[backend] = pr.value_and_grad(z)
    (vj, gj), (vt, gt) = out["jax"], out["torch"]
    assert np.isfinite(vj) and vj == pytest.approx(vt, rel=1e-10)
    np.testing.assert_allclose(gt, gj, rtol=1e-8, atol=1e-9 * np.abs(gj).max())
    mt = tnn_dsl.compile(net, "torch")
    pt = mt.init_params()
    T = mt.xp.asarray(np.full((3, len(mt.state_names)), 300.0) + rng.standard_normal((3, len(mt.state_names))))
    prepared = mt.sample_steps(pt, mt.xp.asarray(U), 5.0)
    for k in (0, 9, len(U) - 1):
        ref = mt.rollout(pt, T, mt.xp.asarray(U[[k, k]]), 5.0)[0][..., 1, :]
        assert float((prepared.step(T, k) - ref).abs().max()) <= 1e-12
    every = prepared.step_all(T[:1].expand(len(U), -1))
    assert float((every[9] - prepared.step(T[0], 9)).abs().max()) <= 1e-12


def test_torch_settled_stretches_equal_the_sample_loop(monkeypatch):
    """torch, constant linearisation: the stretches where the covariance has settled and every sensor is read, run as
    one vectorised recursion, give the sample loop's −log L, gradient and innovations to round-off — with dropouts
    of one sensor, the other and both between the stretches, the default ``P0`` and a fitted one."""
    from tnn_dsl.estimation import likelihood as lk

    U, Y, dt = _two_record(N=400)
    Y[150:153, 0] = np.nan
    Y[200, :] = np.nan
    blocks: list[int] = []
    real_block = lk._stationary_block

    def counted(torch, x, P, Yb, *a, **k):
        blocks.append(int(Yb.shape[0]))
        return real_block(torch, x, P, Yb, *a, **k)

    monkeypatch.setattr(lk, "_stationary_block", counted)
    model = tnn_dsl.compile(tnn_dsl.loads(TWO, "two.thn"), "torch")
    for kw in ({}, {"fit_p0": True, "log_p0_std": [0.1, -0.3]}):
        out = []
        for on in (True, False):
            monkeypatch.setattr(lk, "_STATIONARY", on)
            pr = LikelihoodProblem(model, model.init_params(), U, Y, dt, log_sigma_w=[math.log(0.02), math.log(0.05)],
                                   log_sigma_v=[math.log(0.1), math.log(0.2)], x0=[297.0, 296.5], **kw)
            assert pr.static.constant
            z = pr.z0 + 0.05 * np.random.default_rng(2).standard_normal(pr.z0.shape)
            v, g = pr.value_and_grad(z)
            a = {k: (v_.detach().numpy() if hasattr(v_, "detach") else v_)
                 for k, v_ in pr.unpack(pr.B.asarray(z)).items() if k not in ("params", "log_p0_std")}
            res = innovations(model, pr.unpack(pr.B.asarray(z))["params"], U, Y, dt,
                              log_p0_std=None if not kw else np.asarray(kw["log_p0_std"]), **a)
            out.append((v, g, res))
        (v1, g1, r1), (v2, g2, r2) = out
        assert v1 == pytest.approx(v2, rel=1e-12)
        np.testing.assert_allclose(g1, g2, rtol=1e-9, atol=1e-10 * np.abs(g2).max())
        np.testing.assert_allclose(r1.predicted, r2.predicted, rtol=1e-12)
        np.testing.assert_allclose(r1.std, r2.std, rtol=1e-9)
        np.testing.assert_array_equal(np.isnan(r1.innovations), np.isnan(Y))
        np.testing.assert_allclose(r1.innovations, r2.innovations, rtol=1e-8, atol=1e-10)
    # four filters (value and gradient, innovations; two P0): each vectorised a stretch before the dropouts and one
    # after them, together at least 40 % of its samples
    assert len(blocks) >= 8 and sum(blocks) >= 4 * 0.4 * len(Y), blocks


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradient_matches_finite_differences(backend):
    """∂(−log L)/∂z against central differences (step 1e-5): a capacitance and a conductance (log), both
    log σ_w, both log σ_v, both initial states and log p0 — on the two-node network with dropouts."""
    pr = _problem(backend, free=["C_h2", "G12"], fit_p0=True, log_p0_std=[0.0, -0.5], integrator="rk4")
    z = pr.z0 + 0.05 * np.random.default_rng(2).standard_normal(pr.z0.shape)
    v, g = pr.value_and_grad(z)
    B = backend_of(pr.model)
    nll_z = B.no_grad(B.jit(pr.nll))
    f = lambda zz: float(B.numpy(nll_z(zz)))  # noqa: E731
    h = 1e-5
    fd = np.empty_like(z)
    for i in range(len(z)):
        e = np.zeros_like(z)
        e[i] = h
        fd[i] = (f(z + e) - f(z - e)) / (2 * h)
    assert pr.labels == ("log C_h2", "log G12", "log sigma_w[h1]", "log sigma_w[h2]", "log sigma_v[T1]",
                         "log sigma_v[T2]", "x0[h1] - x0_ref", "x0[h2] - x0_ref", "log p0_std[h1]",
                         "log p0_std[h2]")
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7 * np.abs(g).max())


def _simulate_two(N, dt, sw, sv, seed):
    """Exact simulation of the linear two-node SDE (numpy/scipy): ``x⁺ = Φ x + Γ u + w``, ``w ~ N(0, Q_d)`` with
    ``Φ``, ``Γ`` and ``Q_d`` from matrix exponentials (Van Loan), sensor 1 only read."""
    C = np.array([60.0, 40.0])
    G1, G2, G12 = 0.3, 0.2, 0.5
    A = np.array([[-(G1 + G12), G12], [G12, -(G2 + G12)]]) / C[:, None]
    Bm = np.array([[G1, 1.0], [G2, 0.0]]) / C[:, None]
    n = 2
    E = sla.expm(np.block([[A, Bm], [np.zeros((2, 4))]]) * dt)
    Phi, Gam = E[:n, :n], E[:n, n:]
    V = sla.expm(np.block([[-A, np.diag(sw ** 2)], [np.zeros((n, n)), A.T]]) * dt)
    Qd = V[n:, n:].T @ V[:n, n:]
    Lq = np.linalg.cholesky(0.5 * (Qd + Qd.T))
    rng = np.random.default_rng(seed)
    U = np.stack([293.0 + 2.0 * np.sin(np.arange(N) / 50.0), np.repeat(rng.uniform(0, 20, N // 25 + 1), 25)[:N]],
                 axis=1)
    x = np.array([295.0, 294.0])
    Y = np.empty((N, 2))
    for k in range(N):
        Y[k] = x + sv * rng.standard_normal(2)
        x = Phi @ x + Gam @ U[k] + Lq @ rng.standard_normal(n)
    Y[:, 1] = np.nan  # h2 is not measured
    return U, Y


@pytest.mark.parametrize("backend", BACKENDS)
def test_true_noise_level_has_the_higher_likelihood(backend):
    """Data simulated exactly from the stochastic two-node network (fixed seed; only T1 read): the likelihood at
    the true σ_w is higher than at σ_w 10× too small or 10× too large, and the standardised innovations at the
    truth are ≈ N(0, 1)."""
    N, dt = 400 if backend == "jax" else 150, 5.0
    sw, sv = np.array([0.02, 0.01]), np.array([0.05, 0.05])
    U, Y = _simulate_two(N, dt, sw, sv, seed=7)
    model = tnn_dsl.compile(tnn_dsl.loads(TWO, "two.thn"), backend)
    params = model.init_params()
    kw = dict(log_sigma_v=np.log(sv), x0=[295.0, 294.0], log_p0_std=[math.log(0.01)] * 2, integrator="rk4")
    ll = {f: loglik(model, params, U, Y, dt, log_sigma_w=np.log(sw * f), **kw) for f in (0.1, 1.0, 10.0)}
    assert ll[1.0] > ll[0.1] + 5 and ll[1.0] > ll[10.0] + 5, ll
    res = innovations(model, params, U, Y, dt, log_sigma_w=np.log(sw), **kw)
    r = res.standardized[:, 0]
    assert abs(np.mean(r)) < 4 / math.sqrt(N) and 0.85 < np.std(r) < 1.15  # 4 standard errors of the mean
    assert np.all(np.isnan(res.innovations[:, 1])) and np.all(np.isfinite(res.std))


@pytest.mark.skipif(not BUILDING.exists(), reason="shared building data not present")
def test_bacher_madsen_ti_reaches_the_ctsm_likelihood():
    """Bacher & Madsen's Ti (one state) on their PRBS data, 1691 samples of 5 min: L-BFGS-B over log Aw, log C,
    log R, log σ_w, log σ_v and x0 (P0 = the process noise of one sample, CTSM-R's default) reaches the
    maximum log-likelihood CTSM-R reports, 2479.2 (Bacher & Madsen 2011, CTSM-R's Ti example), to within 0.3
    (the reference is given to 0.1; the optimum found here is 2479.23, measured 2026-11-24, in ~4 s on JAX;
    σ_v goes to ~0, as in CTSM's estimate). The log-likelihood is invariant to the time unit (σ_w in K/√s
    here, °C/√h there) and to the °C → K shift. torch gives the same value at the optimum."""
    from scipy.optimize import minimize

    from tnn_dsl.data import read_data

    net = tnn_dsl.load(ROOT / "networks" / "building" / "ti.thn")
    (exp,) = read_data(net, BUILDING, time_unit="h")
    model = tnn_dsl.compile(net, "jax")
    pr = LikelihoodProblem(model, model.init_params(), exp.inputs, exp.outputs, exp.dt,
                           log_sigma_w=math.log(1e-3), log_sigma_v=math.log(0.1))
    t0 = time.perf_counter()
    r = minimize(pr.value_and_grad, pr.z0, jac=True, method="L-BFGS-B", options={"maxiter": 300})
    took = time.perf_counter() - t0
    best = -r.fun
    vals = pr.values(r.x)
    print(f"Ti: log L = {best:.3f} (CTSM-R 2479.2) in {took:.1f} s, {r.nit} iterations; "
          + ", ".join(f"{k} = {v:.4g}" for k, v in vals.items()))
    assert abs(best - 2479.2) < 0.3
    assert vals["C_ti"] / 3.6e6 == pytest.approx(2.07, rel=0.02)   # kWh/K
    assert vals["Ria"] * 1e3 == pytest.approx(5.28, rel=0.02)      # K/kW
    tm = tnn_dsl.compile(net, "torch")
    a = pr.unpack(pr.B.asarray(r.x))
    kw = {k: np.asarray(v, dtype=np.float64) for k, v in a.items() if k not in ("params", "log_p0_std")}
    n = 300  # a prefix on torch (its Python loop is ~4 ms a sample)
    vj = loglik(model, a["params"], exp.inputs[:n], exp.outputs[:n], exp.dt, **kw)
    vt = loglik(tm, tm.from_numpy(model.to_numpy(a["params"])), exp.inputs[:n], exp.outputs[:n], exp.dt, **kw)
    assert vt == pytest.approx(vj, rel=1e-9)


def _qd_reference(A, sw2, dt):
    """``Q_d = ∫₀^Δt e^{As} Σ e^{Aᵀs} ds`` by Van Loan's exponential in 80-digit arithmetic (mpmath)."""
    import mpmath

    mpmath.mp.dps = 80  # e^{−AΔt} reaches e^{80} below: 35 digits cancel in the product
    n = A.shape[0]
    M = mpmath.zeros(2 * n, 2 * n)
    for i in range(n):
        for j in range(n):
            M[i, j] = -mpmath.mpf(A[i, j]) * dt
            M[n + i, n + j] = mpmath.mpf(A[j, i]) * dt
        M[i, n + i] = mpmath.mpf(sw2[i]) * dt
    E = mpmath.expm(M)  # Q_d = F22ᵀ F12
    return np.array([[float(mpmath.fsum(E[n + k, n + i] * E[k, n + j] for k in range(n))) for j in range(n)]
                     for i in range(n)])


@pytest.mark.parametrize("factor", [0.01, 1.0, 100.0])
def test_process_noise_is_accurate_over_parameter_moves(factor):
    """``Q_d`` (scaling and squaring of the Taylor series, doublings fixed at the nominal parameters) against
    Van Loan's exponential in 80 digits: ≤ 1e-12 relative (Frobenius) for the two-node network with every
    conductance moved 100-fold either way from the values the doublings were chosen for (its fastest mode
    ``|λ|Δt`` from 0.0002 to 2 at the nominal Δt = 2 s; also at Δt = 60 s); written out and rolled agree."""
    pytest.importorskip("mpmath")
    from tnn_dsl.estimation import likelihood as lk

    model = tnn_dsl.compile(tnn_dsl.loads(TWO, "two.thn"), "jax")
    B = backend_of(model)
    C = np.array([60.0, 40.0])
    G1, G2, G12 = 0.3 * factor, 0.2 * factor, 0.5 * factor
    A = np.array([[-(G1 + G12), G12], [G12, -(G2 + G12)]]) / C[:, None]
    sw2 = np.array([0.02, 0.05]) ** 2
    for dt in (2.0, 60.0):
        st = lk._static(model, np.zeros((1, 2)), np.zeros((1, 2)), dt, "rk4", None, "vanloan")[0]
        ref = _qd_reference(A, sw2, dt)
        for rolled in (False, True):
            Q = np.asarray(lk._process_noise(B, B.asarray(A), B.asarray(sw2), st, rolled=rolled))
            assert np.linalg.norm(Q - ref) <= 1e-12 * np.linalg.norm(ref), (dt, rolled, Q, ref)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_constant_linearisation_is_formed_once_with_the_same_value(monkeypatch, backend):
    """A linear network's ``H``, ``F``, ``A`` (hence ``Q_d``) depend on neither state nor input: the trace
    analysis says so (JAX's trace; a torch model's network compiled for JAX) and not for a network with radiation,
    and the likelihood and its gradient with the linearisation formed once equal those with it formed per sample
    to 1e-12 relative."""
    from tnn_dsl.estimation import likelihood as lk

    pr = _problem(backend, integrator="rk4")
    assert pr.static.constant
    z = pr.z0 + 0.1 * np.random.default_rng(3).standard_normal(pr.z0.shape)
    v1, g1 = pr.value_and_grad(z)
    monkeypatch.setattr(lk, "_HOIST", False)
    pr2 = _problem(backend, integrator="rk4")
    assert not pr2.static.constant
    v2, g2 = pr2.value_and_grad(z)
    assert v1 == pytest.approx(v2, rel=1e-12)
    np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-12 * np.abs(g2).max())
    monkeypatch.setattr(lk, "_HOIST", True)
    rad = tnn_dsl.compile(tnn_dsl.load(ROOT / "networks" / "tclab" / "tclab_lag.thn"), backend)
    assert not lk._constant_linearisation(rad, lk._Static(1.0, "rk4", 1, "vanloan", 4))
