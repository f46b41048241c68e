"""Per-experiment parameters in training and evaluation (issue 15): one value per training file, fitted with the
rest and stored in the model; on a new file estimated with the initial state from its burn-in.

The network: one node of C = 100 J/K heated by P and cooled through G = 2 W/K to an ambient ``Ta`` that was not
logged and differs per file (20, 26 and, for the held-out file, 17 °C). The data start at rest (steady state)."""

from __future__ import annotations

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler.model import compile as compile_network
from tnn_dsl.data import Experiment
from tnn_dsl.fit.simulation import free_run

K0 = 273.15
NET = """\
network room "one node, ambient per file"
units temperature = degC
input P : [W]  column "P_W"
param Ta = {Ta} degC {free}
boundary amb = Ta
node n  C = 100 J/K
G n -- amb = 2 W/K {gfree} as G
source n = P
sensor T = n  column "T_degC"
"""


def _data(ta_c: float, seed: int, n: int = 400) -> Experiment:
    """A file simulated from the truth at ambient ``ta_c`` °C: PRBS heating 0/10 W, 1 s samples, from rest."""
    truth = tnn_dsl.loads(NET.format(Ta=ta_c, free="", gfree=""), "truth.thn")
    model = compile_network(truth, backend="jax")
    rng = np.random.default_rng(seed)
    P = np.repeat(rng.choice([0.0, 10.0], size=n // 40 + 1), 40)[:n, None]
    tmp = Experiment(name=f"run{seed}", path="", t=np.arange(n, dtype=float), dt=1.0, inputs=P,
                     outputs=np.zeros((n, 1)), input_names=("P",), output_names=("T",))
    y = free_run(model, model.init_params(), tmp, "steady").y
    return Experiment(name=f"run{seed}", path="", t=np.arange(n, dtype=float), dt=1.0, inputs=P, outputs=y,
                      input_names=("P",), output_names=("T",))


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_ambient_per_experiment_is_fitted_per_file_and_estimated_on_a_new_one(backend):
    net = tnn_dsl.loads(NET.format(Ta=23, free="free in [10 degC, 35 degC] per experiment", gfree="free"), "m.thn")
    assert net.param("Ta").per_experiment
    a, b, new = _data(20.0, 1), _data(26.0, 2), _data(17.0, 3)
    tm = tnn_dsl.train(net, [a, b], backend=backend, epochs=150, lbfgs_iters=200, seed=0)
    # one value per training file, each the file's own ambient; the shared conductance is the truth's
    per = {r["name"]: r["values"]["Ta"] - K0 for r in tm.meta["per_experiment"]}
    assert per["run1"] == pytest.approx(20.0, abs=0.05) and per["run2"] == pytest.approx(26.0, abs=0.05), per
    assert float(tm.params["G"]) == pytest.approx(2.0, rel=0.02)
    # the model's own value is the mean (the start for a new file); a training file continues with its own value
    assert float(tm.params["Ta"]) - K0 == pytest.approx(23.0, abs=0.1)
    pa = tm.predict([a], backend=backend)[0]
    assert pa["init"] == "stored" and pa["experiment_params"]["Ta"] - K0 == pytest.approx(20.0, abs=0.05)
    assert tm.evaluate([a], backend=backend)["mae"] < 0.02
    # a new file: the ambient is estimated with the initial state from the burn-in, and the free run follows it
    pn = tm.predict([new], backend=backend)[0]
    assert pn["init"] == "estimate" and pn["burn_in"] == 40
    assert "with Ta estimated" in pn["notes"][0]
    assert pn["experiment_params"]["Ta"] - K0 == pytest.approx(17.0, abs=0.1)
    assert tm.evaluate([new], backend=backend)["mae"] < 0.05
    # the rules that do not estimate use the training files' mean: 6 K too warm here
    assert tm.evaluate([new], backend=backend, init="measured")["mae"] > 3.0


def test_one_value_per_file_survives_saving(tmp_path):
    net = tnn_dsl.loads(NET.format(Ta=23, free="free per experiment", gfree=""), "m.thn")
    a, b = _data(20.0, 1, n=200), _data(26.0, 2, n=200)
    tm = tnn_dsl.train(net, [a, b], backend="jax", epochs=60, lbfgs_iters=100, seed=0, out=tmp_path / "model")
    back = tnn_dsl.load_model(tmp_path / "model")
    assert back.meta["per_experiment"] == tm.meta["per_experiment"]
    assert back.free_run_context()["stored_params"] == tm.free_run_context()["stored_params"]
    assert back.evaluate([b])["mae"] == pytest.approx(tm.evaluate([b])["mae"], rel=1e-9)
    assert back.predict([b])[0]["experiment_params"]["Ta"] - K0 == pytest.approx(26.0, abs=0.05)
