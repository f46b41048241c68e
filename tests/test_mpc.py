"""Gradient-based MPC (tnn_dsl.control.mpc) on a one-node RC network, where the answers are known:

* the cost gradient (autodiff through the rollout) matches finite differences;
* offset-free tracking: a plant whose conductance the controller gets wrong by 30 % still settles on the
  set-point (to a few mK) at the analytic steady input P* = G_plant (r − Ta);
* an unreachable set-point drives the input to its bound and never past it.
"""

from __future__ import annotations

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.control.mpc import MPC, closed_loop

RC = """
network rc "one node"
units temperature = K
input Ta : temperature
input P  : [W]
boundary amb = Ta
node n C = 100 J/K
G n -- amb = {g} W/K
source n = P
sensor y = n
"""


def _model(g, backend):
    return tnn_dsl.compile(tnn_dsl.loads(RC.format(g=g), "rc.thn"), backend)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_gradient_matches_finite_differences(backend):
    m = _model(2.0, backend)
    mpc = MPC(m, m.init_params(), "y", {"P": (0.0, 40.0)}, horizon=6, dt=5.0, move_penalty=0.3)
    rng = np.random.default_rng(0)
    useq = rng.uniform(0, 40, (6, 1))
    args = (np.array([295.0]), np.array([290.0, 0.0]), np.full(6, 300.0), np.array([10.0]), 0.2)
    v, g = mpc._vg(useq, *args)
    h = 1e-5
    fd = np.zeros_like(useq)
    for i in range(6):
        e = np.zeros_like(useq)
        e[i, 0] = h
        fd[i, 0] = (mpc._vg(useq + e, *args)[0] - mpc._vg(useq - e, *args)[0]) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert v > 0


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_offset_free_tracking_and_bounds(backend):
    plant = _model(2.6, "jax")          # the truth conducts 30 % more than the controller believes
    ctrl = _model(2.0, backend)
    mpc = MPC(ctrl, ctrl.init_params(), "y", {"P": (0.0, 40.0)}, horizon=8, dt=5.0, move_penalty=0.01)
    N = 600
    U = np.tile([290.0, 0.0], (N, 1))
    r = np.full(N, 300.0)
    r[300:] = 320.0                      # unreachable: needs P = 2.6·30 = 78 W > 40 W
    res = closed_loop(plant, plant.init_params(), mpc, U, r, plant_dt=1.0)
    P = res.u[:, 1]
    assert np.all(P >= 0.0) and np.all(P <= 40.0)
    # (the controller sees the set-point step 40 s ahead: its preview; check before that)
    assert abs(res.y[255] - 300.0) < 5e-3, res.y[255]
    assert abs(P[255] - 2.6 * 10.0) < 0.03, P[255]  # the analytic steady input of the true plant
    assert P[-1] == pytest.approx(40.0, abs=1e-9)   # saturated at the bound, not beyond
    assert res.y[-1] == pytest.approx(290.0 + 40.0 / 2.6, abs=0.05)


def test_errors():
    m = _model(2.0, "jax")
    p = m.init_params()
    with pytest.raises(tnn_dsl.TnnError, match="unknown sensor"):
        MPC(m, p, "z", {"P": (0, 1)})
    with pytest.raises(tnn_dsl.TnnError, match="unknown input"):
        MPC(m, p, "y", {"Q": (0, 1)})
    with pytest.raises(tnn_dsl.TnnError, match="lo < hi"):
        MPC(m, p, "y", {"P": (1, 0)})
