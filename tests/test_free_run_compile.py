"""When a trained model's free runs on torch compile their rollouts (issue 18): a loaded model evaluated over many
samples compiles (eager, a 2 h file of the case study's M4 took 19 s against 1.5 s compiled,
``benchmarks/bench_free_runs.py``), over few it stays eager (compiling costs 20–55 s); ``TNN_TORCH_COMPILE`` decides
where it is set; the model a training leaves in memory keeps the training's choice; a model whose compilation
failed is not asked again. The decision is observed, not paid: ``Model.compile_torch_rollouts`` is recorded."""

from __future__ import annotations

import numpy as np
import pytest

from tnn_dsl.compiler.model import Model
from tnn_dsl.data.experiment import Experiment
from tnn_dsl.fit import config
from tnn_dsl.fit.model_files import TrainedModel, load_model, save_model
from tnn_dsl.lang import loads

NET = ('network tiny\nunits temperature = K\nnode a C = 400 J/K free\nboundary amb = 296.15 K\n'
       'G a -- amb = 0.5 W/K free\nsensor T1 = a column "T1"\n')
PARAMS = {"C_a": np.array(400.0), "G_a_amb": np.array(0.5), "T_amb": np.array(296.15)}


def _exp(n: int, name: str = "x") -> Experiment:
    t = np.arange(n, dtype=float)
    y = (296.15 + 5.0 * np.exp(-t * 0.5 / 400.0))[:, None]  # the node cooling towards the ambient
    return Experiment(name=name, path="", t=t, dt=1.0, inputs=np.zeros((n, 0)), outputs=y, input_names=(),
                      output_names=("T1",))


@pytest.fixture
def calls(monkeypatch):
    """The models asked to compile (the call recorded, nothing compiled); a low threshold keeps the data short."""
    asked: list[Model] = []
    monkeypatch.setattr(Model, "compile_torch_rollouts", lambda self: asked.append(self) is None)
    monkeypatch.setattr(config, "FREE_RUN_COMPILE_MIN_SAMPLES", 300)
    monkeypatch.delenv("TNN_TORCH_COMPILE", raising=False)
    return asked


@pytest.fixture
def loaded(tmp_path):
    return load_model(save_model(tmp_path / "m", loads(NET), PARAMS, {"backend": "torch"}))


def test_rule_reads_the_threshold_and_the_environment(monkeypatch):
    monkeypatch.delenv("TNN_TORCH_COMPILE", raising=False)
    n = config.FREE_RUN_COMPILE_MIN_SAMPLES
    assert config.free_runs_compile_pay(n) is True and config.free_runs_compile_pay(n - 1) is False
    for v in ("0", "1"):
        monkeypatch.setenv("TNN_TORCH_COMPILE", v)
        assert config.free_runs_compile_pay(10 * n) is None  # compile() follows the variable


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_many_samples_compile_a_loaded_torch_model(calls, loaded, backend):
    said: list[str] = []
    few = loaded.evaluate([_exp(120), _exp(120, "y")], backend=backend, log=said.append)  # 240 samples: under
    assert calls == [] and said == []
    many = loaded.evaluate([_exp(200), _exp(200, "y")], backend=backend, log=said.append)  # 400, one call
    assert calls == ([loaded.compiled("torch")] if backend == "torch" else [])
    assert said == (["torch: compiling the model's rollouts for 400 samples (once; TNN_TORCH_COMPILE=0 runs eager)"]
                    if backend == "torch" else [])
    assert np.isfinite(few["mae"]) and many["mae"] < 1e-6  # the nominal model is the truth here


def test_environment_variable_decides(calls, loaded, monkeypatch):
    monkeypatch.setenv("TNN_TORCH_COMPILE", "0")
    loaded.evaluate([_exp(400)], backend="torch")
    assert calls == [] and loaded.compiled("torch").torch_compile is False


def test_trainers_model_keeps_the_trainers_choice(calls):
    import tnn_dsl

    net = loads(NET)
    tm = TrainedModel(net, PARAMS, {"backend": "torch"})
    tm._models[("torch", "float64")] = tnn_dsl.compile(net, backend="torch", torch_compile=False)  # as train() does
    tm.evaluate([_exp(400)], backend="torch")
    assert calls == []


def test_a_model_that_failed_to_compile_is_not_asked_again():
    import tnn_dsl

    model = tnn_dsl.compile(loads(NET), backend="torch")
    assert model.torch_compile is False
    with pytest.warns(Warning, match="eager from here on"):
        model._compiling_failed(RuntimeError("no C++ compiler"))
    assert model.compile_torch_rollouts() is False and model.torch_compile is False
    jax_model = tnn_dsl.compile(loads(NET), backend="jax")
    assert jax_model.compile_torch_rollouts() is False
    fresh = tnn_dsl.compile(loads(NET), backend="torch")
    assert fresh.compile_torch_rollouts() is True and fresh.torch_compile is True
