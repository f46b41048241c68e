"""tnn_dsl.plots: every plot returns a Figure, draws into the caller's axes when given, and leaves matplotlib's
backend and pyplot's figure list alone (so notebooks keep inline plots)."""

from __future__ import annotations

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl import plots
from tnn_dsl.data import Experiment

TCLAB = """\
network t "two heaters"
units temperature = degC
input Q1 : [%]  column "Q1"
input Ta : [degC] column "Ta"
boundary amb = Ta
node h1 C = 4 J/K
G h1 -- amb = 0.05 W/K
source h1 = 0.01 W/% * Q1
sensor T1 = h1 column "T1"
sensor T2 = h1 column "T2"
"""


@pytest.fixture
def case():
    net = tnn_dsl.loads(TCLAB, "t.thn")
    n = 50
    t = np.arange(n, dtype=float) * 60
    u = np.column_stack([np.where(t > 600, 50.0, 0.0), np.full(n, 296.15)])
    y = 296.15 + np.column_stack([np.linspace(0, 5, n), np.linspace(0, 4, n)])
    exp = Experiment(name="run", path="run.csv", t=t, dt=60.0, inputs=u, outputs=y + 0.1,
                     input_names=("Q1", "Ta"), output_names=("T1", "T2"), output_columns=("T1", "T2"))
    return net, exp, y


def _untouched(before_backend):
    import matplotlib
    import matplotlib.pyplot as plt

    assert matplotlib.get_backend() == before_backend
    assert plt.get_fignums() == []


def test_series_plots_return_figures_and_use_given_axes(case):
    import matplotlib
    from matplotlib.figure import Figure

    backend = matplotlib.get_backend()
    net, exp, y = case
    fig = plots.simulation(net, exp, y, "t.thn")
    assert isinstance(fig, Figure) and len(fig.axes) == 3
    mine = Figure()
    axes = mine.subplots(3, 1)
    assert plots.simulation(net, exp, y, "t.thn", axes=axes) is mine
    preds = [{"name": "run", "t": exp.t, "y": y, "measured": exp.outputs, "sensors": ["T1", "T2"]}]
    assert len(plots.predictions(net, preds).axes) == 4
    with pytest.raises(ValueError, match="needs 4 axes"):
        plots.predictions(net, preds, axes=[mine.axes[0]])
    _untouched(backend)


def test_learned_function_and_study_plots():
    import matplotlib

    backend = matplotlib.get_backend()
    summary = {"name": "fn_R", "kind": "linear", "targets": ["R"], "inputs": ["h1", "u"],
               "input_kinds": ["node", "input"], "x_min": [290.0, 0.0], "x_max": [310.0, 1.0]}
    fig = plots.learned_function(summary, lambda X: X[:, :1] * 0.01 + X[:, 1:])
    assert len(fig.axes) == 2 and fig.axes[0].get_xlabel() == "T(h1) °C"
    res = {"models": {"M1": {"what": "a", "validation": {"mae": 0.1}, "ood": {"10": 0.2}}},
           "data": {"widen": [0.1], "n_ood": 1}}
    assert plots.ood_growth(res) is not None
    assert plots.ood_growth({"models": {}, "data": {}}) is None
    t = np.arange(10.0) * 3600
    pred = {"t": t, "y": np.ones((10, 1)) * 300, "measured": np.ones((10, 1)) * 300.1}
    assert len(plots.validation_runs({"M1": pred}).axes) == 2
    _untouched(backend)


def test_time_axis_units():
    assert plots.time_axis(np.arange(0, 100.0))[1] == "s"
    assert plots.time_axis(np.arange(0, 3000.0))[1] == "min"
    assert plots.time_axis(np.arange(0, 20000.0, 10))[1] == "h"


def test_no_library_module_switches_the_backend():
    from pathlib import Path

    root = Path(tnn_dsl.__file__).parent
    offenders = [str(p.relative_to(root)) for p in root.rglob("*.py") if "matplotlib.use(" in p.read_text()]
    assert offenders == []
