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
from tnn_dsl.analysis import residuals as R
from tnn_dsl.doctor.candidates import build_extended
from tnn_dsl.studies.planted import plant

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


def test_all_white_holds_its_level_across_sensors_and_tests():
    """``all_white`` decides "is anything left?" for all sensors and both tests at a family-wise 5 % (Bonferroni).
    On 600 pairs of white-noise residuals (two sensors, 900 samples: the hidden-effect suite's TCLab board) it
    rejects about 6 % of them (Ljung–Box at 40 lags is itself a little liberal: 6.4 % at a nominal 5 % on 2000 such
    series, 2.3 % at 1.25 %), while asking whether any sensor's own flag says "not white" rejects about 19 %
    (1 − 0.95⁴ and that liberality); an AR(1) residual of φ = 0.3 on one sensor is found in every pair."""
    rng = np.random.default_rng(7)
    family = flags = ar_found = 0
    n_pairs = 600
    for _ in range(n_pairs):
        pair = {s: R.whiteness(rng.normal(0, 0.01, 900)) for s in ("T1", "T2")}
        family += not R.all_white(pair)
        flags += not all(w["white"] for w in pair.values())
        e = np.zeros(900)
        noise = rng.normal(0, 0.01, 900)
        for k in range(1, 900):
            e[k] = 0.3 * e[k - 1] + noise[k]
        ar_found += not R.all_white({"T1": R.whiteness(e), "T2": pair["T2"]})
    assert family / n_pairs <= 0.08
    assert flags / n_pairs >= 0.15
    assert ar_found == n_pairs
    assert R.all_white({}) and R.all_white({"T": {"white": True, "ljung_box_p": 1.0, "note": "too few samples"}})


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
    from tnn_dsl.compiler.model import compile as _compile

    specs = _compile(ext.network, backend="numpy").param_specs
    for c in ext.candidates:
        for col in c.columns:
            assert col.key in specs and col.index < int(np.prod(specs[col.key].shape) or 1)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_extended_network_is_exactly_null(backend):
    from tnn_dsl.compiler.model import compile as _compile

    net = tnn_dsl.load(TCLAB)
    ext = build_extended(net, ["Q1", "Q2"])
    m0 = _compile(net, backend=backend)
    m1 = _compile(ext.network, backend=backend)
    rng = np.random.default_rng(0)
    from tnn_dsl.studies.planted import step_inputs

    u = step_inputs(rng, 300, BOUNDS, net.input_names, hold=(20, 80))
    p0, p1 = m0.init_params(), m1.init_params()
    y0 = m0.to_numpy({"y": m0.rollout(p0, m0.steady_state(p0, u[0]), u, 1.0)[1]})["y"]
    y1 = m1.to_numpy({"y": m1.rollout(p1, m1.steady_state(p1, u[0]), u, 1.0)[1]})["y"]
    assert np.max(np.abs(y0 - y1)) < 1e-10


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_forced_score_matches_the_big_network(backend, monkeypatch):
    """The score test's shortcut (each candidate as an extra heat flow through the current network's
    linearised dynamics, plus its direct output term) ranks like the exact Jacobian of the big extended
    network's simulation. Its pointwise derivatives taken in blocks of samples (the last one padded) are the ones
    taken in one block."""
    import tnn_dsl.doctor.engine as E
    import tnn_dsl.doctor.scoring as S

    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.0, seed=3, n_train=240, n_val=10,
               backend=backend, hold=(20, 60))
    exps, tm, vm = E._split_masks(pl.train, pl.val)
    kinds = ("wrong_constant", "radiation", "sensor_offset")  # a small "big" network: fast to compile
    ext = build_extended(net, ["Q1", "Q2"], kinds=kinds)
    state, ref = E._State(), {}
    cur = E._make_engine(build_extended(net, ["Q1", "Q2"], kinds=kinds, only=set()), net, exps, tm, vm, backend,
                         state, ref, [])[0]
    big, _, free, cols = E._make_engine(ext, net, exps, tm, vm, backend, state, ref,
                                        [c.key for c in ext.candidates], with_candidates=True)
    fast = S._score_forced(cur, big, ext.candidates, cols, [])
    exact = S._score(big, ext.candidates, list(free), cols, 0.0)
    r2_fast = {d["cand"].key: d["r2"] for d in fast}
    r2_exact = {d["cand"].key: d["r2"] for d in exact}
    assert set(r2_fast) == set(r2_exact)
    a = np.array([r2_exact[k] for k in r2_exact])
    b = np.array([r2_fast[k] for k in r2_exact])
    assert np.max(np.abs(a - b)) < 0.02, (a, b)
    # the best candidate of the exact test is (within the shortcut's accuracy) the best of the shortcut too
    assert r2_fast[exact[0]["cand"].key] >= fast[0]["r2"] - 0.02
    assert {d["cand"].kind for d in fast} == set(kinds)
    _, X = cur.simulate()
    X = X[:cur.n_score_rows]
    U = np.concatenate([e.inputs for e in cur.exps], 0)[:cur.n_score_rows, :len(big.model.input_names)]
    some = sorted(j for c in ext.candidates for j in cols[c.key])[:5]
    whole = big.point_derivs(some, X, U, chunk=4)
    assert X.shape[0] < min(E.POINT_BLOCK.values())  # one block here, and below three, the last padded
    monkeypatch.setattr(E, "POINT_BLOCK", dict.fromkeys(E.POINT_BLOCK, X.shape[0] // 3 + 7))
    for a, b in zip(whole, big.point_derivs(some, X, U, chunk=4)):
        assert np.abs(a).max() > 0 and np.max(np.abs(a - b)) <= 1e-12 * np.abs(a).max()


def test_indistinguishable_candidates_are_named():
    import tnn_dsl.doctor.scoring as S
    from tnn_dsl.doctor.base import Candidate

    rng = np.random.default_rng(0)
    base = rng.normal(size=500)
    mk = lambda name, v: {"cand": Candidate("param_dependence", name, ["u1"], []), "k": 1,  # noqa: E731
                          "dir": (v / np.linalg.norm(v)).astype(np.float32)}
    chosen = mk("R_hp1", base)
    twin = mk("R_hp2", base + 0.05 * rng.normal(size=500))
    other = mk("C_hp", rng.normal(size=500))
    out = S._indistinguishable(chosen, [chosen, twin, other])
    assert [d["key"] for d in out] == ["param_dependence:R_hp2:u1"] and out[0]["cos"] > 0.95


# ---------------------------------------------------------------------------------------------
# end to end
# ---------------------------------------------------------------------------------------------


# slow on both backends: CI checks the same answer to the same planted dependence (other seed, shorter data) in
# test_doctor_threads.py::test_one_thread_and_two_give_the_same_diagnosis, which diagnoses it anyway (22 s saved)
@pytest.mark.slow
@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_planted_dependence_is_found_named_and_pays(backend):
    # torch runs the rollout as a Python loop (about 30x slower per fit); the fast torch checks are the null data
    # set, the exactly-null extension and the score shortcut
    net = tnn_dsl.load(TCLAB)
    n_train, n_val = (1000, 500) if backend == "jax" else (500, 250)
    pl = plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.01, seed=0,
               n_train=n_train, n_val=n_val, backend=backend, hold=(30, 200))
    # one round: this test is about the first answer. (On tclab.thn, whose free constants are not
    # identifiable as written, the nominal fit converges slowly and a second round can accept a compensating
    # heat load on the short torch data; see the closing note of issue 6.)
    d = tnn_dsl.diagnose(net, pl.train, pl.val, backend=backend, top=2, max_rounds=1, mlp_check=False)
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


@pytest.mark.slow  # CI checks the same on its own planted lag: test_diagnose_hidden.py's tclab/sensor_lag (13 s saved)
def test_planted_sensor_lag_is_found_and_written():
    """A structural (not exactly null) candidate: the thermistor of h1 lags by 15 s; the score test ranks it
    by its first-order column −dT(h1)/dt, its own network fits τ, and the extension edits the sensor line."""
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "sensor_lag", "T1", None, 15.0, noise=0.01, seed=4, n_train=800, n_val=600,
               hold=(20, 150))
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=1)
    acc = d.accepted
    assert acc and acc[0].kind == "sensor_lag" and acc[0].target == "T1", d.summary()
    assert "lag" in d.verdict and "T1" in d.verdict
    ext = tnn_dsl.loads(d.extended_text, "extended.thn")
    s1 = next(s for s in ext.sensors if s.name == "T1")
    assert s1.lag is not None and ext.param(s1.lag).value == pytest.approx(15.0, rel=0.1)
    assert d.extended["val_mae"] < 0.25 * d.baseline["val_mae"]


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_null_data_set_gives_no_finding(backend):
    net = tnn_dsl.load(TCLAB)
    n_train, n_val = (1000, 500) if backend == "jax" else (400, 300)
    pl = plant(net, BOUNDS, None, noise=0.02, seed=5, n_train=n_train, n_val=n_val, hold=(30, 200), backend=backend)
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=1, backend=backend)
    assert not d.accepted, d.summary()
    assert d.verdict == "no significant deficiency found" and d.decided and d.budget is None
    assert "white noise" in d.left
    assert d.extended["val_mae"] == pytest.approx(d.baseline["val_mae"])
    # nothing accepted: the diagnosed model is the network itself at the doctor's baseline fit, and its free runs
    # (the trained model's, from the same initial-state rule) give the held-out error the doctor reports
    assert d.model is not None and d.model.network.learned == net.learned and d.model_dir is None
    assert d.model.meta["diagnosis"]["values"] == "the doctor's baseline fit"
    assert d.model.evaluate(pl.val)["mae"] == pytest.approx(d.extended["val_mae"], rel=1e-9)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_a_budget_spent_before_any_test_is_not_a_clean_bill(backend):
    """The torch demo's doctor (a 25 s budget, compiling eating it) printed "no significant deficiency found"
    having tested no candidate, and a baseline whose fit the budget had stopped. A verdict reached with less work
    than the method asks says so; with time, the same data gets a real verdict."""
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, None, noise=0.02, seed=5, n_train=400, n_val=300, hold=(30, 200), backend=backend)
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=1, backend=backend, budget_s=1e-3)
    assert not d.accepted and not d.scores
    assert d.verdict.startswith("not decided: the budget (0.001 s) ran out before any candidate was tested"), d.verdict
    assert any("stopped the nominal model's fit" in n for n in d.notes), d.notes
    doc = d.to_dict()  # what tnnc diagnose --json and a fleet's unit rows carry
    assert doc["decided"] is False and doc["budget"] == {"seconds": 1e-3, "ran_out": "before any candidate was tested",
                                                         "interrupted": False}


def _write(exp, net, path):
    from tnn_dsl.data import write_csv

    cols = {}
    for j, i in enumerate(net.inputs):
        from tnn_dsl.data import unit_factor

        cols[i.column] = exp.inputs[:, j] / (1.0 if i.is_temperature else unit_factor(i.unit))
    kel = [s.column for s in net.sensors]
    for j, s in enumerate(net.sensors):
        cols[s.column] = exp.outputs[:, j]
    write_csv(path, exp.t, cols, net.temperature_unit, kelvin=kel)


def test_cli_writes_json_report_and_extension(tmp_path, capsys):
    from tnn_dsl.cli import main

    net = tnn_dsl.load(TCLAB)
    # cross-talk: heater 1's command heats node h2 (a heat load at h2 driven by Q1); a source value at h2
    # that depends on Q1 is the same structure, so either name is right
    pl = plant(net, BOUNDS, "heat_load", "Q[h2]", "Q1", 0.5, noise=0.01, seed=1, n_train=1000, n_val=800,
               hold=(30, 200))
    tr, va = tmp_path / "train.csv", tmp_path / "val.csv"
    _write(pl.train[0], net, tr)
    _write(pl.val[0], net, va)
    out, model = tmp_path / "ext.thn", tmp_path / "model"
    rc = main(["diagnose", TCLAB, str(tr), "--val", str(va), "-o", str(out), "--json", str(tmp_path / "d.json"),
               "--report", str(tmp_path / "rep"), "--top", "2", "--max-rounds", "1", "--model", str(model), "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0, text
    doc = json.loads((tmp_path / "d.json").read_text())
    # the diagnosed model: the extension at the doctor's fitted values (the .thn holds them rounded, and no learned
    # weights), written as `tnnc train` writes a model; `tnnc evaluate` gives the held-out error the report gives
    assert doc["extended"]["model"] == str(model) and (model / "network.thn").read_text() == out.read_text()
    assert f"extended model written to {model} (`tnnc evaluate {model} {va}` gives the held-out numbers" in text
    rc = main(["evaluate", str(model), str(va), "--json", str(tmp_path / "e.json")])
    assert rc == 0 and json.loads((tmp_path / "e.json").read_text())["mae"] == pytest.approx(
        doc["extended"]["val_mae"], rel=1e-9)
    stored = tnn_dsl.load_model(model)
    assert stored.meta["diagnosis"]["held_out"]["data"] == [str(va)] and len(stored.meta["initial_states"]) == 1
    # `tnnc inspect` of it shows the doctor's values with their standard errors, as the summary does
    capsys.readouterr()
    assert main(["inspect", str(model)]) == 0
    shown = capsys.readouterr().out
    assert "the model doctor's verdict: " + doc["verdict"] in shown and "values of the extended model (±" in shown
    assert all(f"{e['name']} = " in shown for e in doc["extended"]["uncertainty"]["estimates"])
    # a second run refuses to write the model over an input, and over a directory that is not a model
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "mine.txt").write_text("keep")
    for bad in (str(tr), str(tmp_path / "notes")):
        rc = main(["diagnose", TCLAB, str(tr), "--val", str(va), "--model", bad, "--quiet"])
        assert rc == 1 and "--model" in capsys.readouterr().err
    assert (tmp_path / "notes" / "mine.txt").read_text() == "keep"
    assert doc["findings"] and any(f["accepted"] for f in doc["findings"]), text
    best = next(f for f in doc["findings"] if f["accepted"])
    assert best["target"] in ("Q[h2]", "Q_src_h2") and best["depends_on"] == ["Q1"], text
    assert out.exists() and f"learn {best['target']} as linear(Q1)" in out.read_text()
    tnn_dsl.load(str(out))
    html = (tmp_path / "rep" / "index.html").read_text()
    assert "data:image/png;base64," in html and best["target"] in html
    assert "model doctor" in text and "gain:" in text


def test_cli_bad_input_is_a_friendly_error(tmp_path, capsys):
    from tnn_dsl.cli import main

    rc = main(["diagnose", TCLAB, str(tmp_path / "missing.csv")])
    err = capsys.readouterr().err
    assert rc == 1
    assert "missing.csv" in err and "Traceback" not in err
