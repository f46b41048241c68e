"""The pre-fit of `replace`-mode learned flows (tnn_dsl.fit.prefit): the nominal law closely, and the same weights
on both backends (an L-BFGS pre-fit ended 10–30 % apart on JAX and torch, so M4 and the M5 built on it trained
differently on the two)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tnn_dsl.compiler import Backend

NETS = Path(__file__).resolve().parents[1] / "networks" / "peltier_heatpipe"
BACKENDS = ["jax", "torch"]


@pytest.fixture(scope="module")
def case_short(tmp_path_factory):
    from tnn_dsl.studies.casestudy import generate_case_study

    return generate_case_study(tmp_path_factory.mktemp("cs"), n_ood=0, widen=(), durations=(2400.0, 1200.0, 60.0))


def _prefitted_m4(case_short, backend, log):
    """M4's parameters after the trainer's statistics and pre-fit, with the nominal model and run."""
    from tnn_dsl.compiler import compile as compile_network
    from tnn_dsl.data import as_experiments
    from tnn_dsl.fit.trainer import _Trainer
    from tnn_dsl.fit.training import make_config
    from tnn_dsl.lang import load

    net = load(str(NETS / "m4.thn"))
    cfg = make_config(None, dict(backend=backend, epochs=1, seed=0))
    exps, vals = as_experiments(net, case_short["train"]), as_experiments(net, case_short["val"])
    model = compile_network(net, backend=backend, dtype=cfg.dtype, torch_compile=False)
    tr = _Trainer(net, exps, vals, cfg, model, log=log)
    params = tr.initial_params()
    nom, nom_bp, runs = tr.nominal_runs(params)
    tr.set_stats(params, nom, nom_bp, runs)
    before = {k: np.array(v, copy=True) for k, v in params.items()}
    tr.prefit_replace(params, nom, nom_bp, runs)
    return tr, model, params, before, (nom, nom_bp, runs)


def _relative_rms(tr, model, params, nominal):
    """RMS over the run of (MLP flow − nominal flow) / rms(nominal flow), per Peltier flow."""
    nom, nom_bp, runs = nominal
    T = np.concatenate(runs)
    U = np.concatenate([np.asarray(e.inputs, dtype=float) for e in tr.exps])
    want = tr._nominal_flows(nom, nom_bp, T, U)
    ops = tr.ops
    got = model.heat_flows(model.from_numpy(params), ops.asarray(T), ops.asarray(U))
    return {t: float(np.sqrt(np.mean((ops.numpy(got[t]) - want[t]) ** 2) / np.mean(want[t] ** 2)))
            for t in ("pe.Q_hot", "pe.Q_cold")}


def test_the_prefit_gives_the_same_weights_on_both_backends_and_the_nominal_law(case_short):
    fitted, errors, logs = {}, {}, {}
    for backend in BACKENDS:
        logs[backend] = []
        tr, model, params, before, nominal = _prefitted_m4(case_short, backend, logs[backend].append)
        keys = sorted(k for k in params if k.startswith("fn_pe_Q_hot.") and k[len("fn_pe_Q_hot."):][0] in "Wb")
        assert keys and any(np.any(params[k] != before[k]) for k in keys)  # the pre-fit moved the weights
        fitted[backend] = {k: np.asarray(params[k]) for k in keys}
        errors[backend] = _relative_rms(tr, model, params, nominal)
    for k, w in fitted["jax"].items():  # the same weights to round-off (L-BFGS: 10–30 % apart)
        np.testing.assert_allclose(fitted["torch"][k], w, rtol=0, atol=1e-9 * max(1.0, float(np.abs(w).max())),
                                   err_msg=k)
    for backend in BACKENDS:
        # the nominal law closely over the whole run, not only at the fitted samples (the L-BFGS pre-fit: ~1e-3)
        assert max(errors[backend].values()) < 1e-3, (backend, errors[backend])
        assert any("by levenberg-marquardt" in m for m in logs[backend]), logs[backend]


def test_a_large_function_is_prefitted_by_lbfgs(case_short, monkeypatch):
    from tnn_dsl.fit import prefit

    monkeypatch.setattr(prefit, "PREFIT_LM_MAX_WEIGHTS", 10)  # M4's MLP has 122 weights
    log: list[str] = []
    tr, model, params, before, nominal = _prefitted_m4(case_short, "jax", log.append)
    assert any("by l-bfgs-b" in m for m in log), log
    errors = _relative_rms(tr, model, params, nominal)
    assert max(errors.values()) < 2e-2, errors  # a fit of the law, if a looser one


@pytest.mark.parametrize("backend", BACKENDS)
def test_fit_weights_recovers_an_analytic_least_squares_solution(backend):
    """``y = a·exp(−b·x) + c`` sampled without noise: the exact parameters, and never worse than the start."""
    from tnn_dsl.fit.prefit import fit_weights

    ops = Backend(backend)
    x = np.linspace(0.0, 4.0, 50)
    truth = np.array([2.0, 0.7, -0.3])
    y = truth[0] * np.exp(-truth[1] * x) + truth[2]
    xb, yb = ops.asarray(x), ops.asarray(y)

    def residuals(z):
        return z[0] * ops.xp.exp(-z[1] * xb) + z[2] - yb

    z, norm, method = fit_weights(residuals, np.array([1.0, 0.2, 0.0]), ops, ridge=0.0)
    assert method == "levenberg-marquardt"
    np.testing.assert_allclose(z, truth, rtol=1e-8)
    assert norm < 1e-8
    z_same, norm_same, _ = fit_weights(residuals, truth, ops, ridge=0.0)  # at the solution: stays there
    np.testing.assert_allclose(z_same, truth, rtol=1e-10)
    assert math.isfinite(norm_same) and norm_same < 1e-10
    # the weight decay pulls towards zero: the ridge solution has a smaller norm and a small misfit
    z_r, norm_r, _ = fit_weights(residuals, np.array([1.0, 0.2, 0.0]), ops, ridge=1e-2)
    assert np.linalg.norm(z_r) < np.linalg.norm(truth) and 0 < norm_r < 0.1
