"""Excitation metric (thesis §4.2, §5.6.1): block-Hankel singular values of the inputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tnn_dsl.analysis.hankel import excitation, hankel_matrix, hankel_metrics
from tnn_dsl.core.errors import DataError, TnnError


def test_hankel_matrix_layout():
    u = np.array([1.0, 2.0, 3.0, 4.0])
    H = hankel_matrix(u, 2)
    np.testing.assert_allclose(H * math.sqrt(3), [[1, 2, 3], [2, 3, 4]])
    # two channels: blocks of m rows per lag
    u2 = np.column_stack([u, 10 * u])
    H2 = hankel_matrix(u2, 2) * math.sqrt(3)
    np.testing.assert_allclose(H2, [[1, 2, 3], [10, 20, 30], [2, 3, 4], [20, 30, 40]])
    with pytest.raises(ValueError):
        hankel_matrix(u, 5)


def test_hankel_metrics_analytic():
    # a constant sequence: rank 1, condition inf, effective rank 1
    m = hankel_metrics(np.full(50, 3.0), 4)
    assert m["rank"] == 1 and not m["full_rank"] and math.isinf(m["condition"])
    assert m["effective_rank"] == pytest.approx(1.0)
    np.testing.assert_allclose(m["singular_values"][0], 3.0 * 2.0)  # ‖(3,3,3,3)‖ per RMS column
    # an alternating ±1 sequence with window 2: H Hᵀ/L = [[1, −1], [−1, 1]] → rank 1
    alt = np.tile([1.0, -1.0], 100)
    assert hankel_metrics(alt, 2)["rank"] == 1
    # white noise is well conditioned: κ → 1 for long sequences
    rng = np.random.default_rng(0)
    w = hankel_metrics(rng.standard_normal(200_00), 5)
    assert w["full_rank"] and w["condition"] < 1.1
    assert w["effective_rank"] > 4.9


def _signals(n: int = 4 * 3600 + 1):
    from tnn_dsl.studies.casestudy import case_study_inputs

    prbs = case_study_inputs(seed=1, duration_s=n - 1)
    t = np.arange(n, dtype=float)
    step = {k: v.copy() for k, v in prbs.items()}
    step["I"] = np.where(t < n // 2, 1.0, 2.5)
    step["u1"] = np.full(n, 0.5)
    steady = {k: v.copy() for k, v in prbs.items()}
    steady["I"] = np.full(n, 1.5)
    steady["u1"] = np.full(n, 0.5)
    return prbs, step, steady


def _write(path, sig: dict, with_output: bool = True):
    import pandas as pd

    n = len(sig["I"])
    df = pd.DataFrame({"time": np.arange(n, dtype=float), **sig})
    if with_output:
        df["T_out"] = 25.0
    df.to_csv(path, index=False)
    return str(path)


def test_prbs_above_step_above_steady_arrays():
    prbs, step, steady = _signals()
    rep = excitation([{k: prbs[k] for k in ("I", "u1", "Ta")}, {k: step[k] for k in ("I", "u1", "Ta")},
                      {k: steady[k] for k in ("I", "u1", "Ta")}], window=20)
    assert rep.ranking == ["set 1", "set 2", "set 3"]
    assert rep.excluded == ["Ta"]  # constant in every file: left out
    best, mid, worst = rep.results
    assert best.full_rank and math.isfinite(best.condition)
    assert mid.rank < best.rank and mid.rank > worst.rank == 0
    assert math.isinf(worst.condition)
    # on the channel that both vary (I alone), the single step is full rank but worse conditioned
    rep_i = excitation([prbs["I"], step["I"], steady["I"]], window=20)
    a, b, c = rep_i.results
    assert (a.name, b.name, c.name) == ("array 1", "array 2", "array 3")
    assert a.full_rank and b.full_rank and a.condition < b.condition / 2
    assert math.isinf(c.condition)


@pytest.mark.parametrize("window", [5, 20, 50])
def test_ranking_stable_over_windows(window):
    prbs, step, steady = _signals(3601)
    rep = excitation([prbs["I"], step["I"], steady["I"]], window=window)
    assert rep.ranking == ["array 1", "array 2", "array 3"]


def test_files_without_network(tmp_path):
    prbs, step, steady = _signals(2 * 3600 + 1)
    files = [_write(tmp_path / f"{n}.csv", s) for n, s in (("steady", steady), ("prbs", prbs), ("step", step))]
    rep = excitation(files, columns=["I", "u1", "Ta", "Tf1", "Tf2"])
    assert rep.ranking == ["prbs.csv", "step.csv", "steady.csv"]
    assert set(rep.excluded) == {"Ta", "Tf1", "Tf2"}
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["ranking"] == rep.ranking and d["results"][2]["condition"] == "inf"
    # without columns every numeric non-time column is taken (the note says so)
    rep2 = excitation(files[:1])
    assert "T_out" in rep2.excluded  # a constant column, read as an input without a network
    assert any("every numeric column" in n for n in rep2.results[0].notes)
    assert "time" not in rep2.channels
    text = rep.table()
    assert "prbs.csv" in text and "condition" in text


def test_file_errors(tmp_path):
    prbs, _, _ = _signals(100)
    f = _write(tmp_path / "a.csv", prbs)
    with pytest.raises(DataError) as err:
        excitation([f], columns=["nope"])
    assert "nope" in str(err.value) and "hint:" in str(err.value)
    with pytest.raises(DataError):
        excitation([str(tmp_path / "missing.csv")])
    with pytest.raises(TnnError):
        excitation([f], window=0)
    with pytest.raises(DataError):
        excitation([np.ones((10, 2)), np.ones((10, 3))])


def test_with_network_and_cli(tmp_path, capsys):
    load = pytest.importorskip("tnn_dsl.lang.parser").load
    from tnn_dsl.cli import main
    from tnn_dsl.studies.casestudy import network_path

    net_path = str(network_path("peltier_heatpipe/m1.thn"))
    net = load(net_path)
    prbs, step, steady = _signals(3601)
    files = [_write(tmp_path / f"{n}.csv", s) for n, s in (("step", step), ("steady", steady), ("prbs", prbs))]
    rep = excitation(files, net=net, window=20)
    assert [r.path for r in rep.results] == [files[2], files[0], files[1]]
    assert set(rep.excluded) == {"Ta", "Tf1", "Tf2"}
    assert main(["excitation", *files, "--net", net_path, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["path"] for r in out["results"]] == [files[2], files[0], files[1]]
    assert main(["excitation", *files, "--net", net_path, "--window", "10"]) == 0
    assert "condition" in capsys.readouterr().out
