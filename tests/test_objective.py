"""Estimates with their uncertainty under either objective (issue 16, items 1–2): ``TrainConfig.objective``,
``tnnc train --objective``, the coefficient table in ``tnnc train``, ``meta.json`` and ``tnnc inspect``.

* output error: the Gauss–Newton standard errors equal those of a finite-difference Jacobian of the free run
  (both backends), and cover the truth on data with white measurement noise;
* ``ml``: the likelihood fit continues from the output-error fit, its log-likelihood is at least the start's,
  and the model keeps its estimates; learned functions train under it;
* the command line: ``--objective ml --json`` carries ``loglik``, ``aic``, ``bic``, ``n_params`` at the top level,
  ``meta.json`` the table, ``tnnc inspect`` prints it; an unknown objective is a clear error.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.core import TnnError
from tnn_dsl.estimation import output_error_estimates

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_ml_coverage import RC  # noqa: E402 - one node, the likelihood tests' network

TRUE_C, TRUE_R, SIGMA_V = 130.0, 0.4, 0.08
TNNC = [sys.executable, "-c", "import sys; from tnn_dsl.cli import main; sys.exit(main())"]


def _white_noise_record(tmp_path: Path, n: int = 240, dt: float = 5.0, seed: int = 0) -> Path:
    """One node simulated exactly (no process noise), readings with white N(0, 0.08²) noise, as a CSV."""
    rng = np.random.default_rng(seed)
    tau = TRUE_R * TRUE_C
    a = math.exp(-dt / tau)
    Ta = 293.0 + 2.0 * np.sin(np.arange(n) / 40.0)
    P = np.repeat(rng.uniform(0.0, 20.0, n // 15 + 1), 15)[:n]
    x, y = 296.0, np.empty(n)
    for k in range(n):
        y[k] = x + SIGMA_V * rng.standard_normal()
        xinf = Ta[k] + TRUE_R * P[k]
        x = xinf + a * (x - xinf)
    path = tmp_path / f"rc_{seed}.csv"
    rows = ["time,Ta,P,y"] + [f"{k * dt},{float(Ta[k])!r},{float(P[k])!r},{float(y[k])!r}" for k in range(n)]
    path.write_text("\n".join(rows) + "\n")
    return path


def test_unknown_objective_is_a_clear_error():
    with pytest.raises(TnnError, match="objective must be one of output-error, ml"):
        tnn_dsl.TrainConfig(objective="least-squares")


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_output_error_errors_equal_a_finite_difference_jacobian(backend, tmp_path):
    """The forward-mode Jacobian of the free run against central differences of it (h = 1e-6 in z)."""
    net = tnn_dsl.loads(RC, "rc.thn")
    (exp,) = tnn_dsl.read_data(net, _white_noise_record(tmp_path, n=120))
    model = tnn_dsl.compile(net, backend)
    params = model.init_params()
    pn = model.to_numpy(params)
    T0 = np.array([296.0])
    rec = [("rc", exp.inputs, exp.outputs, exp.dt, T0)]
    est = output_error_estimates(model, params, rec, integrator="expeuler")

    def run(z):  # z = [log C, log R, x0 offset]
        p = dict(pn)
        p["C_n"], p["Rn"] = np.exp(z[0]), np.exp(z[1])
        _, y = model.rollout(model.from_numpy(p), model.from_numpy({"x": T0 + z[2]})["x"], exp.inputs, exp.dt,
                             integrator="expeuler")
        return model.to_numpy({"y": y})["y"][:, 0]

    z0 = np.array([math.log(pn["C_n"]), math.log(pn["Rn"]), 0.0])
    J = np.stack([(run(z0 + h) - run(z0 - h)) / 2e-6 for h in np.eye(3) * 1e-6], axis=1)
    r = exp.outputs[:, 0] - run(z0)
    n, k = len(r), 4
    s2 = float(r @ r) / (n - k)
    se_z = np.sqrt(np.diag(np.linalg.inv(J.T @ J / s2)))
    got = {row["name"]: row for row in est.rows}
    assert got["C_n"]["se_z"] == pytest.approx(se_z[0], rel=1e-4)
    assert got["Rn"]["se_z"] == pytest.approx(se_z[1], rel=1e-4)
    assert got["x0[n]"]["se"] == pytest.approx(se_z[2], rel=1e-4)
    ll = -0.5 * n * (math.log(2 * math.pi * float(r @ r) / n) + 1)
    assert est.loglik == pytest.approx(ll, rel=1e-9) and est.n_params == k and est.objective == "output-error"


def test_both_objectives_on_white_noise_cover_the_truth(tmp_path):
    """With white measurement noise only, the output-error fit is the maximum-likelihood fit: both tables hold the
    truth within 3 standard errors, the likelihood fit's log L is at least the output-error start's, and the two
    objectives' standard errors agree within 30 %."""
    path = _white_noise_record(tmp_path, n=240, seed=4)
    net = tnn_dsl.loads(RC, "rc.thn")
    opts = dict(epochs=150, integrator="expeuler")
    oe = tnn_dsl.train(net, path, objective="output-error", **opts)
    ml = tnn_dsl.train(net, path, objective="ml", **opts)
    e_oe, e_ml = oe.meta["estimation"], ml.meta["estimation"]
    assert e_oe["objective"] == "output-error" and e_ml["objective"] == "ml"
    truth = {"C_n": TRUE_C, "Rn": TRUE_R}
    for e in (e_oe, e_ml):
        rows = {r["name"]: r for r in e["rows"]}
        for name, v in truth.items():
            assert rows[name]["status"] == "ok"
            assert abs(rows[name]["estimate"] - v) < 3 * rows[name]["se"], (e["objective"], rows[name])
    oe_rows = {r["name"]: r for r in e_oe["rows"]}
    ml_rows = {r["name"]: r for r in e_ml["rows"]}
    for name in truth:
        assert ml_rows[name]["se"] == pytest.approx(oe_rows[name]["se"], rel=0.3)
    # the model keeps the likelihood's estimates
    assert float(ml.params["C_n"]) == pytest.approx(ml_rows["C_n"]["estimate"], rel=1e-12)
    assert e_ml["loglik"] >= e_oe["loglik"] - 1e-6  # same Gaussian readings; ml adds process noise


def test_learned_functions_train_under_the_likelihood(tmp_path):
    """A learned dependence (linear in the ambient) is estimated by the likelihood fit with the constants: its
    weights move from the output-error fit's, the table counts them in a note, and k includes them."""
    text = RC.replace("R n -- amb = 0.5 K/W  free in [0.01 K/W, 50 K/W] as Rn",
                      "R n -- amb = 0.5 K/W as Rn\nlearn Rn as linear(Ta)")
    net = tnn_dsl.loads(text, "rc_learn.thn")
    path = _white_noise_record(tmp_path, n=200, seed=2)
    oe = tnn_dsl.train(net, path, objective="output-error", epochs=80, integrator="expeuler")
    ml = tnn_dsl.train(net, path, objective="ml", epochs=80, integrator="expeuler")
    names = [k for k in ml.params if k.startswith(net.learned[0].name + ".") and "scale" not in k
             and "mean" not in k]
    assert names
    moved = max(float(np.max(np.abs(np.asarray(ml.params[k]) - np.asarray(oe.params[k])))) for k in names)
    assert moved > 0
    e = ml.meta["estimation"]
    assert any("weights of a learned function" in n for n in e["notes"])
    n_w = sum(int(np.asarray(ml.params[k]).size) for k in names)
    assert e["n_params"] == 1 + n_w + 1 + 1 + 1  # C_n, the weights, σ_w, σ_v, x0


def test_cli_objective_ml_json_meta_and_inspect(tmp_path):
    """``tnnc train --objective ml --json -``: top-level loglik/aic/bic/n_params consistent with each other; the
    model's meta.json holds the table; ``tnnc inspect`` prints it with the file's temperature unit."""
    path = _white_noise_record(tmp_path, n=200, seed=7)
    net_path = tmp_path / "rc.thn"
    net_path.write_text(RC)
    out = tmp_path / "model"
    cmd = [*TNNC, "train", str(net_path), str(path), "-o", str(out), "--objective",
           "ml", "--epochs", "60", "--integrator", "expeuler", "--json", "-", "-q"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    doc = json.loads(p.stdout)
    for key in ("loglik", "aic", "bic", "n_params"):
        assert isinstance(doc[key], (int, float)), key
    assert doc["objective"] == "ml" and doc["n_params"] == 5
    assert doc["aic"] == pytest.approx(2 * doc["n_params"] - 2 * doc["loglik"])
    assert doc["bic"] == pytest.approx(doc["n_params"] * math.log(200) - 2 * doc["loglik"])
    meta = json.loads((out / "meta.json").read_text())
    assert meta["objective"] == "ml" and {r["name"] for r in meta["estimation"]["rows"]} >= {"C_n", "Rn"}
    q = subprocess.run([*TNNC, "inspect", str(out)], capture_output=True, text=True,
                       timeout=120)
    assert q.returncode == 0, q.stderr
    assert "Std. Error" in q.stdout and "maximum-likelihood fit of rc" in q.stdout and "log L =" in q.stdout
    bad_cmd = [*TNNC, "train", str(net_path), str(path), "-o", str(tmp_path / "m2"), "--objective", "oe", "-q"]
    bad = subprocess.run(bad_cmd, capture_output=True, text=True, timeout=120)
    assert bad.returncode != 0 and "objective must be one of" in bad.stderr and "Traceback" not in bad.stderr


HEATER = """
network rc_heater "a sensed room and its unsensed heater"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node n C = 100 J/K  free in [1 J/K, 10000 J/K]
node h C = 10 J/K   free in [0.5 J/K, 1000 J/K]
R h -- n = 0.1 K/W  free in [0.001 K/W, 10 K/W] as Rh
R n -- amb = 0.5 K/W  free in [0.01 K/W, 50 K/W] as Rn
source h = P
sensor y = n column "y"
"""


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_ml_fit_stores_a_free_run_start_for_its_training_file(backend, tmp_path):
    """After ``--objective ml`` each training file keeps, as its free-run start, the state the free run with the
    likelihood's parameters fits best (``free_run_start``), not the filter's prior mean ``x0`` (loose for the
    unsensed heater: Bacher & Madsen's TiTh put it at −605.7 K): the model re-simulates its training file within
    the physical range and about as well as the output-error fit does."""
    from tnn_dsl.fit.initial import free_run_start

    path = _white_noise_record(tmp_path, n=200, seed=5)
    net = tnn_dsl.loads(HEATER, "rc_heater.thn")
    opts = dict(epochs=60, integrator="expeuler", backend=backend, val_fraction=0.0)
    oe = tnn_dsl.train(net, path, objective="output-error", **opts)
    ml = tnn_dsl.train(net, path, objective="ml", **opts)
    (exp,) = tnn_dsl.read_data(net, path)
    (rec,) = ml.meta["initial_states"]
    stored = np.array([rec["T0"][n] for n in ("n", "h")])
    model = ml.compiled(backend)
    want, _ = free_run_start(net, model, ml.backend_params(backend), exp.inputs, exp.outputs, exp.dt,
                             integrator="expeuler")
    np.testing.assert_allclose(stored, want, atol=1e-9)
    assert 280.0 < stored[1] < 320.0, stored  # the heater near the room (296 K), not wherever x0 went
    from tnn_dsl.fit.simulation import start_range

    lo, hi = start_range(oe.compiled(backend), exp)  # the output-error fit's own fitted start, fenced in training
    assert all(lo <= v <= hi for v in oe.meta["initial_states"][0]["T0"].values())
    (pred,) = ml.predict(path, backend=backend)
    assert pred["init"] == "stored"
    mae_ml, mae_oe = ml.evaluate(path, backend=backend)["mae"], oe.evaluate(path, backend=backend)["mae"]
    assert mae_ml < 1.5 * mae_oe + 0.02, (mae_ml, mae_oe)
