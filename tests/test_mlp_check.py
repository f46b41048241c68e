"""Linear or MLP (``tnn_dsl.doctor.mlp_check``): the doctor trains its extension both ways and keeps the MLP only
when it pays on held-out data."""

from __future__ import annotations

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.data import Experiment
from tnn_dsl.doctor.mlp_check import compare, mlp_text

BASE = """network board "one heater"
units temperature = degC
input Q : [%]  column "Q_pct"
param Ta = 23 degC
boundary amb = Ta
node h "heater"  C = 4 J/K
G h -- amb = 0.02 W/K  as U
source h = 0.01 W/% * Q  as Qh
sensor T = h  column "T_degC"
"""

EXTENDED = BASE + """
# ---- added by `tnnc diagnose` -------------------------------------------------
# U depends on Q
learn U as linear(Q)
"""


def test_mlp_text_changes_only_the_doctors_linear_clauses():
    user = BASE + "learn Qh as linear(Q)\n"
    text = user + EXTENDED[len(BASE):]
    new, n = mlp_text(text)
    assert n == 1
    assert "learn Qh as linear(Q)" in new  # the user's own clause, above the marker, is left alone
    assert "learn U as mlp(Q; hidden = [8], activation = tanh)" in new
    tnn_dsl.loads(new, "x.thn")  # a valid network
    assert mlp_text(BASE) == (BASE, 0)


def _data(conductance, n, seed):
    """A free run of the one-heater board whose conductance is ``conductance(Q)`` (W/K), noise 0.01 K."""
    rng = np.random.default_rng(seed)
    holds = rng.integers(20, 80, size=n)
    q = np.repeat(rng.uniform(0.0, 1.0, size=n), holds)[:n]
    T, Ta, C = np.empty(n), 23.0, 4.0
    g0 = conductance(q[0])
    T[0] = Ta + 0.01 * 100 * q[0] / g0  # steady state of the first input
    for k in range(1, n):  # RK4 at dt = 1 s with the input held
        g, p = conductance(q[k - 1]), 0.01 * 100 * q[k - 1]

        def f(x):
            return (p - g * (x - Ta)) / C

        x = T[k - 1]
        k1 = f(x)
        k2 = f(x + k1 / 2)
        k3 = f(x + k2 / 2)
        k4 = f(x + k3)
        T[k] = x + (k1 + 2 * k2 + 2 * k3 + k4) / 6
    y = T + 273.15 + rng.normal(0, 0.01, n)
    return Experiment(name=f"s{seed}", path="<test>", t=np.arange(n, dtype=float), dt=1.0,
                      inputs=(100 * q)[:, None] * 0.01, outputs=y[:, None], input_names=("Q",), output_names=("T",))


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_a_curved_law_makes_the_mlp_pay_and_a_straight_one_does_not(backend):
    curved = lambda q: 0.02 * (1 + 12 * (q - 0.5) ** 2)  # noqa: E731 - convection that rises at both ends
    r = compare(EXTENDED, "x.thn", [_data(curved, 900, 1)], [_data(curved, 500, 2)], backend=backend,
                time_limit=20.0)
    assert r["choice"] == "mlp", r
    assert r["mlp"]["val_mae"] < 0.5 * r["linear"]["val_mae"]
    assert "mlp(Q; hidden = [8], activation = tanh)" in r["text"]
    # the linear clause's own law: a conductance is ``nominal·pos1(1 + z)``, positive by construction, with
    # ``pos1(v) = softplus(4v)/softplus(4)`` (tnn_dsl.compiler.learned)
    def pos1(v):
        return np.logaddexp(0.0, 4.0 * v) / np.logaddexp(0.0, 4.0)

    straight = lambda q: 0.02 * float(pos1(1.0 + 0.5 * (q - 0.5) / 0.5))  # noqa: E731
    r = compare(EXTENDED, "x.thn", [_data(straight, 900, 1)], [_data(straight, 500, 2)], backend=backend,
                time_limit=20.0)
    assert r["choice"] == "linear", r
    assert "learn U as linear(Q)" in r["text"]
