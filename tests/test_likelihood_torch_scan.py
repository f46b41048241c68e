"""The Kalman-filter likelihood of a constant linearisation as compiled torch scans (tnn_dsl.estimation.torch_filter):
the same −log L and gradient as torch's eager filter and as JAX, to round-off, with missing readings; the compiled
programs shared by every network of one shape; when a fit takes that path; and the eager filter when torch cannot
compile it."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from test_likelihood import RC, TWO  # one node and sensor; two nodes and sensors

import tnn_dsl
from tnn_dsl.compiler.model import TorchCompileWarning
from tnn_dsl.estimation import likelihood as lk
from tnn_dsl.estimation import torch_filter
from tnn_dsl.estimation.likelihood import LikelihoodProblem

RC_OTHER = """
network rc_other "one node, written otherwise: the same shape"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node wall C = 800 J/K  free
G wall -- amb = 4 W/K  free as Gw
source wall = 0.5 * P
sensor T_wall = wall column "y"
"""


def _record(n_out: int, N: int = 80, seed: int = 3):
    rng = np.random.default_rng(seed)
    U = np.stack([295.0 + 0.5 * np.sin(np.arange(N) / 9.0), np.repeat(rng.uniform(0, 10, N // 10 + 1), 10)[:N]],
                 axis=1)
    Y = 297.0 + np.cumsum(rng.normal(0, 0.1, (N, n_out)), axis=0)
    Y[0, 0] = np.nan       # missing at the first sample
    Y[5:9, 0] = np.nan     # a dropout of the first sensor
    Y[40, :] = np.nan      # every sensor missing
    if n_out > 1:
        Y[20:30, 1] = np.nan  # the second sensor alone missing
    return U, Y, 2.0


def _value_and_grad(net: str, backend: str, monkeypatch, compile_env: str, **kw):
    monkeypatch.setenv("TNN_TORCH_COMPILE", compile_env)
    model = tnn_dsl.compile(tnn_dsl.loads(net, "net.thn"), backend)
    ns, no = len(model.state_names), len(model.output_names)
    U, Y, dt = _record(no)
    pr = LikelihoodProblem(model, model.init_params(), U, Y, dt, log_sigma_w=[math.log(0.02)] * ns,
                           log_sigma_v=[math.log(0.1)] * no, x0=[297.0] * ns, **kw)
    assert pr.static.constant
    z = pr.z0 + 0.05 * np.random.default_rng(2).standard_normal(pr.z0.shape)
    return pr, pr.value_and_grad(z)


@pytest.mark.parametrize("net", ["one sensor", "two sensors"])
def test_compiled_scan_gives_the_eager_filters_and_jaxs_value_and_gradient(net, monkeypatch):
    """One node and one sensor (``S`` a number), two nodes and two sensors (``S`` solved): −log L to 1e-12 and its
    gradient (parameters, noise levels, initial state, a fitted ``P0``) to 1e-9 relative against eager torch and
    JAX, with readings missing at the start, from one sensor, from the other, and from both."""
    text = RC if net == "one sensor" else TWO
    calls: list[int] = []
    real = torch_filter.filter_scan

    def counted(x0, P0, **kw):
        calls.append(int(kw["Y0"].shape[0]))
        return real(x0, P0, **kw)

    monkeypatch.setattr(torch_filter, "filter_scan", counted)
    for kw in ({}, {"fit_p0": True}):
        pr, (v_scan, g_scan) = _value_and_grad(text, "torch", monkeypatch, "1", **kw)
        assert pr._scan
        _, (v_eager, g_eager) = _value_and_grad(text, "torch", monkeypatch, "0", **kw)
        _, (v_jax, g_jax) = _value_and_grad(text, "jax", monkeypatch, "", **kw)
        assert np.isfinite(v_scan) and v_scan == pytest.approx(v_eager, rel=1e-12) == pytest.approx(v_jax, rel=1e-12)
        for g in (g_eager, g_jax):
            np.testing.assert_allclose(g_scan, g, rtol=1e-9, atol=1e-10 * np.abs(g).max())
    assert calls == [80, 80]  # the compiled path ran for the two torch evaluations with TNN_TORCH_COMPILE=1 only


def test_networks_of_one_shape_share_the_compiled_programs(monkeypatch):
    """Two different one-node networks (other names, parameters, a scaled source) run through the same compiled
    forward and reverse scans: the programs are kept per (states, sensors) shape, not per model."""
    _value_and_grad(RC, "torch", monkeypatch, "1")
    rollout = torch_filter._rollout()
    programs = (len(rollout._fwd), len(rollout._bwd))
    pr, (v, g) = _value_and_grad(RC_OTHER, "torch", monkeypatch, "1")
    assert (len(rollout._fwd), len(rollout._bwd)) == programs
    _, (v_eager, g_eager) = _value_and_grad(RC_OTHER, "torch", monkeypatch, "0")
    assert v == pytest.approx(v_eager, rel=1e-12)
    np.testing.assert_allclose(g, g_eager, rtol=1e-9, atol=1e-10 * np.abs(g_eager).max())


def test_which_fits_take_the_compiled_scans(monkeypatch):
    """torch only; ``TNN_TORCH_COMPILE`` decides when set (1 always, 0 never), else the record's length."""
    from tnn_dsl.compiler import backend_of

    jax_b = backend_of(tnn_dsl.compile(tnn_dsl.loads(RC, "rc.thn"), "jax"))
    torch_b = backend_of(tnn_dsl.compile(tnn_dsl.loads(RC, "rc.thn"), "torch"))
    long, short = lk.SCAN_MIN_SAMPLES, lk.SCAN_MIN_SAMPLES - 1
    monkeypatch.delenv("TNN_TORCH_COMPILE", raising=False)
    assert lk._scan_pays(torch_b, long) and not lk._scan_pays(torch_b, short)
    assert not lk._scan_pays(jax_b, long)
    monkeypatch.setenv("TNN_TORCH_COMPILE", "1")
    assert lk._scan_pays(torch_b, 3)
    monkeypatch.setenv("TNN_TORCH_COMPILE", "0")
    assert not lk._scan_pays(torch_b, 10 * long)


def test_a_scan_torch_cannot_compile_leaves_the_eager_filter_with_a_warning(monkeypatch):
    """torch's compiler failing (here made to fail) costs the fit nothing but time: one warning, the eager
    filter's value and gradient, and no further attempt in the process."""
    attempts: list[int] = []

    def failing(x0, P0, **kw):
        attempts.append(1)
        raise RuntimeError("InductorError: C++ compile error (made up by the test)")

    monkeypatch.setattr(torch_filter, "filter_scan", failing)
    monkeypatch.setattr(lk, "_SCAN_USABLE", True)
    with pytest.warns(TorchCompileWarning, match="likelihood's filter.*runs eager"):
        pr, (v, g) = _value_and_grad(RC, "torch", monkeypatch, "1")
    with warnings.catch_warnings():
        warnings.simplefilter("error", TorchCompileWarning)
        pr.value_and_grad(pr.z0)
    assert attempts == [1] and not lk._SCAN_USABLE and not lk._scan_pays(pr.B, 10**6)
    _, (v_eager, g_eager) = _value_and_grad(RC, "torch", monkeypatch, "0")
    assert v == v_eager
    np.testing.assert_array_equal(g, g_eager)
