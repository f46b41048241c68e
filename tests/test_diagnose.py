"""The model doctor (`tnn_dsl.diagnose`, `tnnc diagnose`): fast tests that run in CI.

Residual statistics are checked against known series; the extended network is checked to be exactly
null on both backends; the end-to-end diagnosis runs on a planted effect and on a null data set (nominal
model + noise), and through the CLI with --json, --report and -o."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl import _residuals as R
from tnn_dsl._candidates import build_extended
from tnn_dsl._planted import plant

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}  # heater fraction (SI of [%])


# ---------------------------------------------------------------------------------------------
# residual statistics (pure numpy)
# ---------------------------------------------------------------------------------------------


def test_white_noise_is_white_and_ar1_is_not():
    rng = np.random.default_rng(0)
    e = rng.normal(0, 0.05, 3000)
    w = R.whiteness(e)
    assert w["white"] and w["ljung_box_p"] > 0.01
    ar = np.zeros(3000)
    for k in range(1, 3000):
        ar[k] = 0.9 * ar[k - 1] + rng.normal(0, 0.05)
    w2 = R.whiteness(ar)
    assert not w2["white"] and w2["ljung_box_p"] < 1e-6 and w2["ks_p"] < 1e-6


def test_noise_sigma_ignores_slow_structure():
    rng = np.random.default_rng(1)
    t = np.arange(5000)
    e = 0.5 * np.sin(2 * np.pi * t / 2000) + rng.normal(0, 0.02, t.size)
    assert R.noise_sigma(e) == pytest.approx(0.02, rel=0.1)


def test_effective_n_shrinks_with_autocorrelation():
    rng = np.random.default_rng(2)
    white = rng.normal(size=4000)
    assert R.effective_n(white) == pytest.approx(4000, rel=0.1)
    ar = np.zeros(4000)
    for k in range(1, 4000):
        ar[k] = 0.8 * ar[k - 1] + rng.normal()
    assert R.effective_n(ar) == pytest.approx(4000 * 0.2 / 1.8, rel=0.2)


def test_binned_dependence_sees_a_nonlinear_effect():
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, 4000)
    e = x**2 - 1 / 3 + rng.normal(0, 0.05, x.size)
    d = R.binned_dependence(e, x, bins=10)
    assert abs(d["corr"]) < 0.1  # a linear correlation misses it
    assert d["r2_binned"] > 0.8  # the bin means do not
    assert d["means"][0] > 0.3 and d["means"][len(d["means"]) // 2] < 0


def test_sensor_errors_ignore_nan():
    e = np.array([[0.1, np.nan], [-0.3, 0.2], [0.2, np.nan]])
    s = R.sensor_errors(e, ["a", "b"])
    assert s["a"]["mae"] == pytest.approx(0.2) and s["a"]["max"] == pytest.approx(0.3)
    assert s["b"]["n"] == 1 and s["b"]["bias"] == pytest.approx(0.2)


# ---------------------------------------------------------------------------------------------
# candidates: from the IR, exactly null
# ---------------------------------------------------------------------------------------------


def test_candidates_come_from_the_ir():
    net = tnn_dsl.load(TCLAB)
    ext = build_extended(net, ["Q1", "Q2"])
    kinds = {c.kind for c in ext.candidates}
    assert {"param_dependence", "heat_load", "radiation", "sensor_offset"} <= kinds
    assert "missing_link" not in kinds  # h1, h2 and amb are all joined already
    keys = {c.key for c in ext.candidates}
    assert "param_dependence:U1:T(h1)" in keys and "param_dependence:U12:T(h2)" in keys
    assert "param_dependence:U1:T(h2)" not in keys  # only the element's own temperatures
    assert "radiation:h1--amb:" in keys and "heat_load:Q[h2]:Q1" in keys
    # every column of every candidate exists in the compiled model
    from tnn_dsl._compile import compile as _compile

    specs = _compile(ext.network, backend="numpy").param_specs
    for c in ext.candidates:
        for col in c.columns:
            assert col.key in specs and col.index < int(np.prod(specs[col.key].shape) or 1)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_extended_network_is_exactly_null(backend):
    from tnn_dsl._compile import compile as _compile

    net = tnn_dsl.load(TCLAB)
    ext = build_extended(net, ["Q1", "Q2"])
    m0 = _compile(net, backend=backend)
    m1 = _compile(ext.network, backend=backend)
    rng = np.random.default_rng(0)
    from tnn_dsl._planted import step_inputs

    u = step_inputs(rng, 300, BOUNDS, net.input_names, hold=(20, 80))
    p0, p1 = m0.init_params(), m1.init_params()
    y0 = m0.to_numpy({"y": m0.rollout(p0, m0.steady_state(p0, u[0]), u, 1.0)[1]})["y"]
    y1 = m1.to_numpy({"y": m1.rollout(p1, m1.steady_state(p1, u[0]), u, 1.0)[1]})["y"]
    assert np.max(np.abs(y0 - y1)) < 1e-10


# ---------------------------------------------------------------------------------------------
# end to end
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_planted_dependence_is_found_named_and_pays(backend):
    net = tnn_dsl.load(TCLAB)
    n_train, n_val = (1500, 700) if backend == "jax" else (500, 250)
    pl = plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.01, seed=0,
               n_train=n_train, n_val=n_val, backend=backend, hold=(30, 200))
    d = tnn_dsl.diagnose(net, pl.train, pl.val, backend=backend, top=2, max_rounds=2)
    acc = d.accepted
    assert acc, d.summary()
    first = acc[0]
    assert first.target == "U1" and first.depends_on == ["T(h1)"], d.summary()
    assert first.kind == "param_dependence"
    assert "U1" in d.verdict and "T(h1)" in d.verdict
    assert d.extended["val_mae"] < 0.5 * d.baseline["val_mae"]
    assert "learn U1 as linear(h1)" in d.extended_text
    tnn_dsl.loads(d.extended_text, "extended.thn")  # the extension is a valid network
    doc = d.to_dict()
    for k in ("baseline", "findings", "extended", "gain"):
        assert k in doc
    assert {"val_mae", "val_max"} <= set(doc["baseline"])
    for f in doc["findings"]:
        assert {"rank", "kind", "target", "depends_on", "clause", "val_mae_after", "evidence", "accepted"} <= set(f)
    json.dumps(doc)  # JSON-able


def test_null_data_set_gives_no_finding():
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, None, noise=0.02, seed=5, n_train=1500, n_val=700, hold=(30, 200))
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=1)
    assert not d.accepted, d.summary()
    assert d.verdict == "no significant deficiency found"
    assert "white noise" in d.left
    assert d.extended["val_mae"] == pytest.approx(d.baseline["val_mae"])


def _write(exp, net, path):
    from tnn_dsl._data import write_csv

    cols = {}
    for j, i in enumerate(net.inputs):
        from tnn_dsl._data import unit_factor

        cols[i.column] = exp.inputs[:, j] / (1.0 if i.is_temperature else unit_factor(i.unit))
    kel = [s.column for s in net.sensors]
    for j, s in enumerate(net.sensors):
        cols[s.column] = exp.outputs[:, j]
    write_csv(path, exp.t, cols, net.temperature_unit, kelvin=kel)


def test_cli_writes_json_report_and_extension(tmp_path, capsys):
    from tnn_dsl.cli import main

    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "heat_load", "Q[h2]", None, 0.5, noise=0.01, seed=1, n_train=1200, n_val=600,
               hold=(30, 200))
    tr, va = tmp_path / "train.csv", tmp_path / "val.csv"
    _write(pl.train[0], net, tr)
    _write(pl.val[0], net, va)
    out = tmp_path / "ext.thn"
    rc = main(["diagnose", TCLAB, str(tr), "--val", str(va), "-o", str(out), "--json", str(tmp_path / "d.json"),
               "--report", str(tmp_path / "rep"), "--top", "2", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0, text
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["findings"] and any(f["accepted"] for f in doc["findings"]), text
    best = next(f for f in doc["findings"] if f["accepted"])
    assert best["target"] == "Q[h2]", text
    assert out.exists() and "learn Q[h2] as" in out.read_text()
    tnn_dsl.load(str(out))
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "data:image/png;base64," in html and "Q[h2]" in html
    assert "model doctor" in text and "gain:" in text


def test_cli_bad_input_is_a_friendly_error(tmp_path, capsys):
    from tnn_dsl.cli import main

    rc = main(["diagnose", TCLAB, str(tmp_path / "missing.csv")])
    err = capsys.readouterr().err
    assert rc == 1
    assert "missing.csv" in err and "Traceback" not in err
