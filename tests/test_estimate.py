"""The extended Kalman filter (tnn_dsl.estimation.kalman) and ``tnnc estimate``.

* analytic: on a one-node linear RC network with the exact (exponential) discretisation the EKF is the
  linear Kalman filter, written out here in numpy;
* virtual sensing on synthetic TCLab-like data with an unmodelled ambient: the estimate of the sensor the
  filter does not read beats the open-loop model, also through a dropout; joint estimation of the ambient;
* the CLI writes the CSV and reports user errors as diagnostics.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.estimation.kalman import ekf, open_loop, tune_process_noise

BACKENDS = ["jax", "torch"]

RC = """
network rc "one node"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node n C = 100 J/K
G n -- amb = 2 W/K
source n = P
sensor y = n column "y"
"""

TWO = """
network two "TCLab-like two heaters"
units temperature = degC
input Q1 : [%] column "Q1"
input Q2 : [%] column "Q2"
param Ta = {ta} degC
boundary amb = Ta
node h1 C = 6 J/K
node h2 C = 6 J/K
G h1 -- amb = 0.03 W/K
G h2 -- amb = 0.03 W/K
G h1 -- h2 = 0.01 W/K
source h1 = 0.016 W/% * Q1
source h2 = 0.011 W/% * Q2
sensor T1 = h1 column "T1"
sensor T2 = h2 column "T2"
"""


def _np(x):
    return np.asarray(x.detach() if hasattr(x, "detach") else x, dtype=np.float64)


def _steps(rng, n, lo, hi, hold=60):
    out = np.empty(n)
    k = 0
    while k < n:
        out[k:k + hold] = rng.uniform(lo, hi)
        k += hold
    return out


@pytest.mark.parametrize("backend", BACKENDS)
def test_ekf_equals_linear_kalman_filter_on_rc(backend):
    net = tnn_dsl.loads(RC, "rc.thn")
    model = tnn_dsl.compile(net, backend)
    params = model.init_params()
    rng = np.random.default_rng(0)
    N, dt = 200, 5.0
    U = np.stack([np.full(N, 290.0), _steps(rng, N, 0.0, 40.0, 20)], axis=1)
    y = 290.0 + 10 * np.sin(np.arange(N) / 15.0) + rng.normal(0, 0.2, N)
    y[80:110] = np.nan  # dropout
    q, r, p0, x0 = 0.05, 0.2, 2.0, 300.0
    res = ekf(model, params, U, y[:, None], dt, ["y"], process_noise=q, meas_noise=r, init_std=p0, x0=[x0],
              integrator="expeuler")
    # the linear Kalman filter: x+ = a x + (1 - a) (Ta + P/G), exact for an RC node
    C, G = 100.0, 2.0
    a = math.exp(-dt * G / C)
    x, P = x0, p0 ** 2
    xs, ss = [], []
    for k in range(N):
        if np.isfinite(y[k]):
            K = P / (P + r ** 2)
            x, P = x + K * (y[k] - x), (1 - K) * P
        xs.append(x)
        ss.append(math.sqrt(P))
        x = a * x + (1 - a) * (U[k, 0] + U[k, 1] / G)
        P = a * a * P + q * q * dt
    np.testing.assert_allclose(res.states[:, 0], xs, rtol=0, atol=1e-8)
    np.testing.assert_allclose(res.std[:, 0], ss, rtol=1e-7)
    assert np.all(np.isnan(res.innovations[80:110, 0])) and np.all(np.isfinite(res.innovations[:80, 0]))
    # during the dropout the uncertainty grows (prediction only), and shrinks again after it
    assert np.all(np.diff(res.std[80:110, 0]) > 0) and res.std[115, 0] < res.std[109, 0]


def _two_data(ta_true=26.0, N=900, seed=3, noise=0.05):
    """Synthetic TCLab-like run from a 'truth' whose ambient is not the model's 23 °C."""
    truth = tnn_dsl.loads(TWO.format(ta=ta_true), "truth.thn")
    m = tnn_dsl.compile(truth, "jax")
    p = m.init_params()
    rng = np.random.default_rng(seed)
    U = np.stack([_steps(rng, N, 0, 80), _steps(rng, N, 0, 80)], axis=1)
    x0 = _np(m.steady_state(p, U[0]))
    _, y = m.rollout(p, x0, U, 1.0)
    y = _np(y) + rng.normal(0, noise, (N, 2))
    return U, y


@pytest.mark.parametrize("backend", BACKENDS)
def test_virtual_sensor_beats_open_loop(backend):
    U, Y = _two_data()
    net = tnn_dsl.loads(TWO.format(ta=23.0), "model.thn")  # the model believes Ta = 23 °C
    model = tnn_dsl.compile(net, backend)
    params = model.init_params()
    res = ekf(model, params, U, Y, 1.0, ["T1"], process_noise=0.02, meas_noise=0.05)
    _, y_open = open_loop(model, params, U, 1.0, res.states[0])
    err_ekf = np.mean(np.abs(res.outputs[:, 1] - Y[:, 1]))
    err_open = np.mean(np.abs(y_open[:, 1] - Y[:, 1]))
    assert err_ekf < 0.8 * err_open, (err_ekf, err_open)
    assert np.mean(np.abs(res.outputs[:, 0] - Y[:, 0])) < 0.1  # the used sensor is tracked

    # a dropout of T1 in the middle: the estimate coasts on the model, then recovers
    Yd = Y.copy()
    Yd[300:500, 0] = np.nan
    rd = ekf(model, params, U, Yd, 1.0, ["T1"], process_noise=0.02, meas_noise=0.05)
    assert np.all(np.isfinite(rd.states))
    assert np.mean(np.abs(rd.outputs[:, 1] - Y[:, 1])) < err_open
    assert rd.std[499, 0] > 2 * rd.std[299, 0]  # uncertainty grows without the sensor
    np.testing.assert_allclose(rd.states[:300], res.states[:300], atol=1e-9)  # identical before the gap

    # joint estimation of the unmodelled ambient recovers it and makes T2 nearly exact
    ra = ekf(model, params, U, Y, 1.0, ["T1"], process_noise=0.002, meas_noise=0.05, augment=["Ta"],
             param_noise=0.01)
    assert abs(ra.params[-1, 0] - (273.15 + 26.0)) < 0.4, ra.params[-1, 0]
    assert np.mean(np.abs(ra.outputs[-300:, 1] - Y[-300:, 1])) < 0.5 * err_open


def test_backends_agree_and_tuning():
    U, Y = _two_data(N=300)
    net = tnn_dsl.loads(TWO.format(ta=23.0), "model.thn")
    out = {}
    for be in BACKENDS:
        m = tnn_dsl.compile(net, be)
        out[be] = ekf(m, m.init_params(), U, Y, 1.0, ["T1"], process_noise={"h1": 0.03, "*": 0.01})
    np.testing.assert_allclose(out["jax"].states, out["torch"].states, atol=1e-8)
    assert math.isclose(out["jax"].loglik, out["torch"].loglik, abs_tol=1e-3)
    m = tnn_dsl.compile(net, "jax")
    best, scores = tune_process_noise(m, m.init_params(), U, Y, 1.0, ["T1"], grid=(1e-4, 0.01, 10.0))
    assert best == 0.01 and scores[0.01] > scores[1e-4] and scores[0.01] > scores[10.0]


def test_option_errors():
    net = tnn_dsl.loads(TWO.format(ta=23.0), "model.thn")
    m = tnn_dsl.compile(net, "jax")
    p = m.init_params()
    U, Y = np.zeros((5, 2)), np.full((5, 2), 300.0)
    with pytest.raises(tnn_dsl.TnnError, match="unknown sensor 'T9'"):
        ekf(m, p, U, Y, 1.0, ["T9"])
    with pytest.raises(tnn_dsl.TnnError, match="unknown name 'h7'"):
        ekf(m, p, U, Y, 1.0, ["T1"], process_noise={"h7": 1.0})
    with pytest.raises(tnn_dsl.TnnError, match="not a constant parameter"):
        ekf(m, p, U, Y, 1.0, ["T1"], augment=["nope"])
    with pytest.raises(tnn_dsl.TnnError, match="no reading at all"):
        ekf(m, p, U, np.full((5, 2), np.nan), 1.0, ["T1"])
    with pytest.raises(tnn_dsl.TnnError, match="must be > 0 K"):
        ekf(m, p, U, Y, 1.0, ["T1"], meas_noise=0.0)


def test_cli_estimate(tmp_path, capsys):
    from tnn_dsl.cli import main
    from tnn_dsl.data import write_csv

    U, Y = _two_data(N=300)
    t = np.arange(300.0)
    data = tmp_path / "run.csv"
    write_csv(data, t, {"Q1": U[:, 0], "Q2": U[:, 1], "T1": Y[:, 0], "T2": Y[:, 1]}, "degC", kelvin=["T1", "T2"])
    netp = tmp_path / "two.thn"
    netp.write_text(TWO.format(ta=23.0))
    out = tmp_path / "states.csv"
    rc = main(["estimate", str(netp), str(data), "--use", "T1", "-o", str(out), "--drop", "100:150",
               "--process-noise", "0.02", "--plot", str(tmp_path / "p.png")])
    assert rc == 0
    text = capsys.readouterr().out
    assert "T2           estimated" in text and "dropout: 50 samples" in text
    import csv

    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 300
    assert {"T_h1", "T_h2", "T1", "T2", "T2_open", "T_h2_std_K"} <= set(rows[0])
    assert abs(float(rows[0]["T1"]) - Y[0, 0] + 273.15) < 0.05  # °C in the file, starts at the reading
    assert (tmp_path / "p.png").stat().st_size > 1000
    rc = main(["estimate", str(netp), str(data), "--use", "T5", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 1 and "unknown sensor 'T5'" in err and "hint:" in err
    rc = main(["estimate", str(netp), str(data), "--use", "T1", "-o", str(out), "--drop", "9:1"])
    assert rc == 1 and "START < END" in capsys.readouterr().err
