"""The case-study pipeline (tnn_dsl.studies.thesis) on tiny data and budgets: M4 and M5, where M5's frozen
Peltier network must be M4's trained one; out-of-distribution evaluation; ratios and tables; plots.
The full study is ``examples/thesis_case_study.py`` (results in docs/results.md)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tnn_dsl.studies.thesis import StudyConfig, plot_study, ratios_table, results_table, run_study, thesis_ratios


@pytest.mark.parametrize("backend", ["jax"])
def test_study_tiny(tmp_path, backend):
    cfg = StudyConfig(backend=backend, epochs=2, time_limit=None, lbfgs_iters=0, n_ood=1, widen=(0.4,),
                      durations=(600.0, 300.0, 300.0), models=("M4", "M5"))
    msgs, runs = [], {}
    res = run_study(tmp_path / "out", data_dir=tmp_path / "data", config=cfg, progress=msgs.append,
                    validation_runs=runs)
    assert set(res["models"]) == {"M4", "M5"}
    for name, r in res["models"].items():
        assert math.isfinite(r["validation"]["mae"]) and r["validation"]["mae"] > 0
        assert r["validation"]["max_error"] >= r["validation"]["mae"]
        assert set(r["ood"]) == {"40"} and math.isfinite(r["ood"]["40"])
        assert 0 < r["compile_seconds"] <= r["train_seconds"]  # the first calls that compiled, within the training
    # M5's Peltier net is M4's, frozen: identical arrays, and not counted as trainable
    from safetensors.numpy import load_file

    p4 = load_file(str(tmp_path / "out/models/m4/params.safetensors"))
    p5 = load_file(str(tmp_path / "out/models/m5/params.safetensors"))
    import tnn_dsl

    frozen = [fn.name for fn in tnn_dsl.load_model(tmp_path / "out/models/m5").network.learned if fn.frozen]
    assert len(frozen) == 1
    pel = [k for k in p5 if k.startswith(frozen[0] + ".")]
    assert len(pel) >= 6
    for k in pel:
        np.testing.assert_array_equal(p4[k], p5[k])
    # ... while M5 trains: its loss falls; and its heat-pipe network moves below (with the rest, the CI check of
    # test_train.py::test_m5_loads_m4_frozen_and_trains)
    m5_meta = json.loads((tmp_path / "out/models/m5/meta.json").read_text())
    adam = [r["loss"] for r in m5_meta["curve"] if r["phase"] == "adam"]
    assert adam and adam[-1] < m5_meta["curve"][0]["loss"]
    # m5.thn as written (`init_from = "models/m4"`, which the study points at its own M4) reads the M4 beside it,
    # relative to its own file; without that model it is a clear error, not a silent fresh start
    import shutil

    from tnn_dsl.core import TnnError
    from tnn_dsl.studies import network_path

    shutil.copy(network_path("peltier_heatpipe/m5.thn"), tmp_path / "out" / "m5.thn")
    kw = dict(backend=backend, epochs=2, lbfgs_iters=0, seed=0)
    # no validation: the last epoch's values, not the best validated ones (the study's M5 kept its start)
    m5_as_written = tnn_dsl.train(tmp_path / "out" / "m5.thn", res["data"]["train"], **kw)
    for k in pel:
        np.testing.assert_array_equal(m5_as_written.params[k], p4[k], err_msg=k)
    assert np.any(m5_as_written.params["fn_R_hp1.W2"] != 0)  # the heat-pipe network moved
    shutil.copy(network_path("peltier_heatpipe/m5.thn"), tmp_path / "m5.thn")  # no models/m4 beside this one
    with pytest.raises(TnnError, match="m4"):
        tnn_dsl.train(tmp_path / "m5.thn", res["data"]["train"], **kw)
    # the thesis's parameter counts: M4 122 (Peltier MLP) + 3 (constants), M5 139 (heat-pipe MLP only)
    assert res["models"]["M4"]["n_trainable"] == 125 and res["models"]["M5"]["n_trainable"] == 139
    # ratios are computed from our numbers; the ones needing absent models are NaN
    r = res["ratios"]
    assert r["M5 improvement over M4 [%]"]["thesis"] == 26.0
    expect = (1 - res["models"]["M5"]["validation"]["mae"] / res["models"]["M4"]["validation"]["mae"]) * 100
    assert r["M5 improvement over M4 [%]"]["ours"] == pytest.approx(expect)
    assert math.isnan(r["M1/M2 validation MAE"]["ours"])
    assert json.dumps(thesis_ratios(res)) == json.dumps(r)  # (NaN != NaN, so compare the text)
    assert "| M4 |" in results_table(res) and "M5/M3" in ratios_table(res)
    saved = json.loads((tmp_path / "out/results.json").read_text())
    assert saved["models"]["M4"]["validation"]["mae"] == pytest.approx(res["models"]["M4"]["validation"]["mae"])
    # the validation runs handed to the plot are the runs the validation metrics score (made by the trained models
    # in memory); the out-of-distribution sets, read once for both models, score as the files read by a model
    # loaded from disk score them
    from tnn_dsl.fit import error_metrics

    assert set(runs) == {"M4", "M5"}
    for name, run in runs.items():
        assert error_metrics([run], ["T_out"])["mae"] == pytest.approx(res["models"][name]["validation"]["mae"],
                                                                       rel=1e-9)
    loaded = tnn_dsl.load_model(tmp_path / "out/models/m5")
    assert loaded.evaluate(res["data"]["val"])["mae"] == pytest.approx(res["models"]["M5"]["validation"]["mae"],
                                                                       rel=1e-9)
    (ood_file,) = sorted((tmp_path / "data").glob("ood_40_*.csv"))
    assert loaded.evaluate([str(ood_file)])["mae"] == pytest.approx(res["models"]["M5"]["ood"]["40"], rel=1e-9)
    res["models_dir"] = str(tmp_path / "out/models")
    for where, given in (("drawn", runs), ("loaded", None)):
        plots = plot_study(res, tmp_path / where, validation_runs=given)
        assert len(plots) == 2 and all((tmp_path / where / p.split("/")[-1]).stat().st_size > 1000 for p in plots)
    assert any("M5" in m for m in msgs)


def test_m5_needs_m4(tmp_path):
    with pytest.raises(ValueError, match="M5 needs M4"):
        run_study(tmp_path, config=StudyConfig(models=("M5",), n_ood=0, durations=(300.0, 300.0, 300.0)))


def test_demo_registered():
    from tnn_dsl.cli import build_parser

    args = build_parser().parse_args(["demo", "--quick", "--out", "x"])
    assert args.quick and args.out == "x"


def test_out_of_distribution_reports_a_diverged_set_and_goes_on():
    """One free run leaving the physical range on an out-of-distribution set (the quick demo's M2 at +40 %) makes
    that widening 'diverged' with the reason, not an error that stops the study (it used to end `tnnc demo`)."""
    import math

    from tnn_dsl.core import Diagnostic, TnnError
    from tnn_dsl.studies.thesis import _out_of_distribution, results_table

    class FakeModel:
        def evaluate_each(self, paths, backend=None):  # a widening's files in one call, an error in a file's place
            return [TnnError(Diagnostic("the simulation left the physical range: node `ph` became NaN"))
                    if p == "/d/ood_40_1.csv" else {"experiments": [{"mae": 0.01, "max_error": 0.02}]} for p in paths]

    files = {"10": ["/d/ood_10_0.csv", "/d/ood_10_1.csv"], "40": ["/d/ood_40_0.csv", "/d/ood_40_1.csv"]}
    r = _out_of_distribution(FakeModel(), files, "jax")
    assert r["ood"]["10"] == 0.01 and r["ood_max"]["10"] == 0.02
    assert math.isnan(r["ood"]["40"]) and math.isnan(r["ood_max"]["40"])
    assert r["ood_diverged"] == {"40": ["ood_40_1.csv: the simulation left the physical range: node `ph` became NaN"]}
    table = results_table({"data": {"widen": [0.1, 0.4]}, "models": {"M2": {
        "what": "w", "validation": {"mae": 0.002, "max_error": 0.005}, **r}}})
    assert "| 10 | diverged | – |" in table
