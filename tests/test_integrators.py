"""Integrators: convergence order, stiff stability, and the step-size check."""

from __future__ import annotations

import warnings

import nets
import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler.backends import get_xp
from tnn_dsl.compiler.integrators import StepSizeWarning, check_step, phi1, stable_substeps

BACKENDS = ["jax", "torch"]


def _err(model, dt, integrator, t_end=40.0):
    R, C, Ta = 2.0, 10.0, 300.0  # τ = 20 s
    N = int(round(t_end / dt)) + 1
    s, _ = model.rollout(model.init_params(), np.array([Ta]), np.tile([Ta, 4.0], (N, 1)), dt,
                         integrator=integrator, substeps=1)
    exact = Ta + 4.0 * R * (1 - np.exp(-t_end / (R * C)))
    return abs(float(np.asarray(model.xp.to_numpy(s))[-1, 0]) - exact)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("integrator,order", [("euler", 1), ("rk4", 4)])
def test_convergence_order(backend, integrator, order):
    m = tnn_dsl.compile(nets.one_node_rc(2.0, 10.0, Q=True), backend)
    e1, e2 = _err(m, 2.0, integrator), _err(m, 1.0, integrator)
    assert np.log2(e1 / e2) == pytest.approx(order, abs=0.15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_expeuler_is_stable_on_a_stiff_network(backend):
    # a 1 J/K node strongly coupled (τ = 0.01 s) inside a slow network; dt = 10 s
    b = nets.B("stiff")
    b.input("Ta", is_temperature=True)
    b.boundary("amb", nets.ref("Ta"))
    b.node("tiny", 1.0)
    b.node("big", 1000.0)
    b.G("tiny", "big", 100.0)
    b.R("big", "amb", 1.0)
    b.sensor("T", "big")
    m = tnn_dsl.compile(b.build(), backend)
    assert m.fastest_time_constant() == (pytest.approx(0.01), "tiny")
    p = m.init_params()
    u = np.full((3000, 1), 290.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s, _ = m.rollout(p, np.array([350.0, 320.0]), u, 10.0, integrator="expeuler")
    s = np.asarray(m.xp.to_numpy(s))
    assert np.all(np.isfinite(s)) and np.all(s <= 350.0) and np.all(s >= 290.0 - 1e-9)
    np.testing.assert_allclose(s[-1], 290.0, atol=1e-3)
    # explicit methods warn and sub-step instead of diverging (four samples: a step this far over its limit diverges
    # in one; each sample is some 800 sub-steps, eager on torch: 5.2 → 1.1 s against 20 samples)
    with pytest.warns(StepSizeWarning, match="sub-steps"):
        s, _ = m.rollout(p, np.array([350.0, 320.0]), u[:4], 10.0, integrator="rk4")
    assert np.all(np.isfinite(np.asarray(m.xp.to_numpy(s))))
    ref, _ = m.rollout(p, np.array([350.0, 320.0]), u[:4], 10.0, integrator="rk4", substeps=2000)
    np.testing.assert_allclose(np.asarray(m.xp.to_numpy(s)), np.asarray(m.xp.to_numpy(ref)), atol=1e-6)


def test_check_step():
    assert stable_substeps("euler", 1.0, 1.94) == 1
    assert stable_substeps("euler", 10.0, 1.0) == 12  # 10 / (0.9·1)
    assert stable_substeps("rk4", 10.0, 1.0) == 8
    assert stable_substeps("expeuler", 1e6, 1e-3) == 1
    with pytest.warns(StepSizeWarning):
        assert check_step("euler", 10.0, 1.0, None, "pc") == 12
    with pytest.warns(StepSizeWarning, match="at least 12"):
        assert check_step("euler", 10.0, 1.0, 3) == 3
    with pytest.raises(ValueError):
        check_step("euler", -1.0, 1.0, None)


@pytest.mark.parametrize("backend", BACKENDS)
def test_phi1(backend):
    xp = get_xp(backend)
    z = np.array([-50.0, -1.0, -1e-7, 0.0, 1e-7, 0.3])
    got = np.asarray(xp.to_numpy(phi1(xp, xp.asarray(z))))
    ref = np.where(z == 0, 1.0, np.expm1(z) / np.where(z == 0, 1.0, z))
    np.testing.assert_allclose(got, ref, rtol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_case_study_needs_no_substeps_at_1s(backend):
    m = tnn_dsl.compile(nets.case_study("linear"), backend)
    tau, node = m.fastest_time_constant()
    assert node == "pc" and tau == pytest.approx(40.0 / (1 / 0.05 + 1 / 1.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error", StepSizeWarning)
        m.rollout(m.init_params(), np.full(7, 298.15), nets.case_inputs(5), 1.0, integrator="euler")
