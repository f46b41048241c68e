"""`tnnc simulate` and `tnnc generate` (tnn_dsl/cli/_simulate.py, _generate.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tnn_dsl.cli import main

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
if not DATA.is_dir():
    DATA = ROOT / "data"

RC = """\
network rc "one node, one conductance to ambient, a heat source"
units temperature = degC
input P : [W]  column "P_W"
param Ta = 20 degC
boundary amb = Ta
node n  C = 100 J/K
G n -- amb = 2 W/K
source n = P
sensor Tn = n  column "T_n"
"""
# analytic: T = Ta + P/G at rest; a step of P from 0 to 10 W at t0 gives T = 20 + 5·(1 − exp(−(t − t0)/50)) °C


def rc_data(tmp_path: Path, n: int = 400, t_step: int = 10, t_measured=None) -> str:
    t = np.arange(n, dtype=float)
    P = np.where(t >= t_step, 10.0, 0.0)
    T = 20 + 5 * (1 - np.exp(-np.clip(t - t_step, 0, None) / 50.0)) if t_measured is None else t_measured
    p = tmp_path / "rc.csv"
    pd.DataFrame({"time_s": t, "P_W": P, "T_n": T}).to_csv(p, index=False)
    return str(p)


def rc_net(tmp_path: Path) -> str:
    p = tmp_path / "rc.thn"
    p.write_text(RC)
    return str(p)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_simulate_rc_step_matches_the_analytic_response(tmp_path, backend, capsys):
    net, data, out = rc_net(tmp_path), rc_data(tmp_path), tmp_path / "out.csv"
    rc = main(["simulate", net, "--data", data, "-o", str(out), "--backend", backend, "--states"])
    assert rc == 0, capsys.readouterr().err
    df = pd.read_csv(out)
    assert list(df.columns) == ["time_s", "Tn", "T_n"]
    t = df["time_s"].to_numpy()
    want = 20 + 5 * (1 - np.exp(-np.clip(t - 10, 0, None) / 50.0))
    np.testing.assert_allclose(df["Tn"], want, atol=1e-6)  # RK4 at 1 s on τ = 50 s
    np.testing.assert_allclose(df["T_n"], df["Tn"], atol=1e-12)
    printed = capsys.readouterr().out
    assert "Tn: MAE" in printed and "wrote" in printed


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_simulate_init_measured(tmp_path, backend, capsys):
    # the measurement starts at 30 °C with no heating: a cool-down from 30 to 20 °C
    t = np.arange(200.0)
    net, out = rc_net(tmp_path), tmp_path / "o.csv"
    data = rc_data(tmp_path, n=200, t_step=10_000, t_measured=20 + 10 * np.exp(-t / 50.0))
    assert main(["simulate", net, "--data", data, "-o", str(out), "--backend", backend, "--init", "steady"]) == 0
    err = capsys.readouterr().err
    assert "warning: the data do not start at rest" in err and "--init estimate" in err  # 10 K off: say so
    np.testing.assert_allclose(pd.read_csv(out)["Tn"], 20.0, atol=1e-9)
    assert main(["simulate", net, "--data", data, "-o", str(out), "--backend", backend, "--init", "measured"]) == 0
    np.testing.assert_allclose(pd.read_csv(out)["Tn"], 20 + 10 * np.exp(-t / 50.0), atol=1e-6)
    # the default estimates the initial state from a burn-in (a tenth of the file), says so, and finds the start
    assert main(["simulate", net, "--data", data, "-o", str(out), "--backend", backend]) == 0
    err = capsys.readouterr().err
    assert "initial state estimated from the first 20 samples (20 s), not scored" in err
    np.testing.assert_allclose(pd.read_csv(out)["Tn"], 20 + 10 * np.exp(-t / 50.0), atol=1e-6)


def test_simulate_needs_only_the_inputs_and_writes_a_plot(tmp_path, capsys):
    net = rc_net(tmp_path)
    p = tmp_path / "in.csv"
    pd.DataFrame({"t": np.arange(0, 100, 5.0), "P_W": 3.0}).to_csv(p, index=False)
    out, png = tmp_path / "o.csv", tmp_path / "o.png"
    assert main(["simulate", net, "--data", str(p), "-o", str(out), "--plot", str(png)]) == 0
    df = pd.read_csv(out)
    np.testing.assert_allclose(df["Tn"], 21.5, atol=1e-9)  # at rest: 20 + 3/2
    assert df["time_s"].iloc[1] == 5.0
    assert png.stat().st_size > 5000


@pytest.mark.parametrize("case,expect", [
    ("missing", "column 'P_W' (input P) not found"),
    ("nan", "input P (column 'P_W') has no value"),
    ("backwards", "time goes backwards"),
])
def test_simulate_bad_data_is_a_clear_error(tmp_path, capsys, case, expect):
    net = rc_net(tmp_path)
    t = np.arange(20.0)
    df = pd.DataFrame({"time_s": t, "P_W": 1.0, "T_n": 20.0})
    if case == "missing":
        df = df.rename(columns={"P_W": "power"})
    elif case == "nan":
        df.loc[5, "P_W"] = np.nan
    else:
        df.loc[7, "time_s"] = 3.0
    p = tmp_path / "bad.csv"
    df.to_csv(p, index=False)
    rc = main(["simulate", net, "--data", str(p), "-o", str(tmp_path / "o.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and expect in err and "hint:" in err and "Traceback" not in err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_simulate_tclab_on_real_data(tmp_path, backend, capsys):
    src = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
    if not src.is_file():
        pytest.skip("shared data not present")
    p = tmp_path / "prbs.csv"
    pd.read_csv(src).iloc[:600].to_csv(p, index=False)
    out = tmp_path / "sim.csv"
    rc = main(["simulate", str(ROOT / "networks" / "tclab" / "tclab.thn"), "--data", str(p), "-o", str(out),
               "--backend", backend, "--init", "measured"])
    assert rc == 0, capsys.readouterr().err
    df = pd.read_csv(out)
    assert list(df.columns) == ["time_s", "T1", "T2"] and len(df) == 600
    assert df["T1"].iloc[0] == pytest.approx(43.457, abs=1e-6)  # started from the measurement (°C)
    assert np.all(np.isfinite(df.to_numpy())) and 15 < df["T1"].min() and df["T1"].max() < 100


def test_generate_cli_writes_and_caches(tmp_path, capsys, monkeypatch):
    import tnn_dsl.studies.casestudy as cs

    # a short horizon keeps the test fast; the CLI passes everything else through
    monkeypatch.setattr(cs, "TRAIN_S", 300)
    monkeypatch.setattr(cs, "VAL_S", 300)
    monkeypatch.setattr(cs, "OOD_S", 300)
    out = tmp_path / "cs"
    assert main(["generate", "case-study", "-o", str(out), "--widen", "20", "--n-ood", "1", "--noise", "0.01"]) == 0
    assert "written" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "ood_20_0.csv", "train.csv", "val.csv"]
    assert len(pd.read_csv(out / "train.csv")) == 301
    assert main(["generate", "case-study", "-o", str(out), "--widen", "20", "--n-ood", "1", "--noise", "0.01"]) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(["generate", "case-study", "-o", str(out), "--widen", "-5"]) == 1
    assert "--widen" in capsys.readouterr().err


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_simulate_a_model_directory_uses_its_parameters(tmp_path, backend, capsys):
    import tnn_dsl
    from tnn_dsl.compiler.model import compile as compile_network
    from tnn_dsl.fit.model_files import save_model

    net = tnn_dsl.load(rc_net(tmp_path))
    model = compile_network(net, backend="jax")
    params = model.to_numpy(model.init_params(seed=0))
    gname = net.links[0].value
    params[gname] = np.asarray(4.0)  # fitted: G = 4 W/K instead of 2 → τ = 25 s, rise 2.5 K
    save_model(tmp_path / "model", net, params, {"backend": "jax"})
    out = tmp_path / "o.csv"
    rc = main(["simulate", str(tmp_path / "model"), "--data", rc_data(tmp_path), "-o", str(out), "--backend", backend,
               "--init", "steady"])
    assert rc == 0, capsys.readouterr().err
    t = pd.read_csv(out)["time_s"].to_numpy()
    want = 20 + 2.5 * (1 - np.exp(-np.clip(t - 10, 0, None) / 25.0))
    np.testing.assert_allclose(pd.read_csv(out)["Tn"], want, atol=1e-6)
