"""The trainer: unit tests of its parts (transforms, windows, config, metrics) and end-to-end fits on
both backends (parameter recovery, case study M1 vs M2, real TCLab data, divergence)."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tnn_dsl.core.errors import TnnError
from tnn_dsl.fit.config import TrainConfig, load_config
from tnn_dsl.fit.simulation import error_metrics
from tnn_dsl.fit.transforms import _from_z, _make_slot, _NumpyOps, _to_z
from tnn_dsl.fit.windows import MIN_WINDOW_SAMPLES, _windows, auto_window

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TNN_SHARED", ROOT.parent / "shared")) / "data"


# ---------------------------------------------------------------------------------------------
# parameter transforms
# ---------------------------------------------------------------------------------------------


@dataclass
class _Spec:
    kind: str = "physical"
    positive: bool = False
    lower: float | None = None
    upper: float | None = None


CASES = [
    (_Spec(positive=True), "capacitance", "log"),
    (_Spec(positive=True, lower=1.0), "capacitance", "lower"),
    (_Spec(lower=0.0, upper=0.05), "component", "sigmoid"),
    (_Spec(positive=True, upper=10.0), "resistance", "sigmoid"),
    (_Spec(upper=5.0), "generic", "upper"),
    (_Spec(), "temperature", "ident"),
    (_Spec(), "component", "ident"),
    (_Spec(kind="weights"), None, "ident"),
]


@pytest.mark.parametrize("spec,role,transform", CASES)
def test_transform_kind(spec, role, transform):
    assert _make_slot("p", spec, np.array(2.0), 0, role).transform == transform


@settings(max_examples=60, deadline=None)
@given(i=st.integers(0, len(CASES) - 1), frac=st.floats(0.01, 0.99), z=st.floats(-30, 30))
def test_transform_round_trip_and_bounds(i, frac, z):
    spec, role, _ = CASES[i]
    lo = spec.lower if spec.lower is not None else (0.0 if spec.positive else -50.0)
    hi = spec.upper if spec.upper is not None else lo + 100.0
    v = np.array([lo + frac * (hi - lo)])
    slot = _make_slot("p", spec, v, 0, role)
    back = _from_z(slot, _to_z(slot, v), _NumpyOps)
    np.testing.assert_allclose(back, v, rtol=1e-6, atol=1e-9 * (hi - lo))
    # any z maps into the feasible set
    w = float(np.asarray(_from_z(slot, np.array([z]), _NumpyOps)).reshape(()))
    if spec.positive:
        assert w >= 0.0
    if spec.lower is not None:
        assert w >= spec.lower
    if spec.upper is not None:
        assert w <= spec.upper


def test_ident_scale_is_relative():
    slot = _make_slot("pe.seebeck", _Spec(), np.array(0.05), 0, "component")
    assert slot.scale == pytest.approx(0.05)
    slot = _make_slot("Ta", _Spec(), np.array(296.0), 0, "temperature")
    assert slot.scale == 1.0  # a temperature moves in kelvin, not in fractions of 296 K


# ---------------------------------------------------------------------------------------------
# windows
# ---------------------------------------------------------------------------------------------


@dataclass
class _E:
    n_steps: int
    dt: float = 1.0


@pytest.mark.parametrize("dts,expected", [((1.0,), 600.0), ((1.0, 10.0), 600.0), ((1.0, 300.0), 15000.0),
                                          ((60.0,), 3000.0)])
def test_auto_window_is_600_s_and_at_least_50_samples(dts, expected):
    assert MIN_WINDOW_SAMPLES == 50
    assert auto_window([_E(100, dt) for dt in dts]) == expected


@pytest.mark.parametrize("n,window", [(1000, 100.0), (1001, 100.0), (50, 100.0), (1234, 77.0)])
def test_windows_cover_and_chain(n, window):
    wins = _windows([_E(n), _E(n // 2 + 3)], window)
    for e_i, e in enumerate([_E(n), _E(n // 2 + 3)]):
        mine = [w for w in wins if w.exp == e_i]
        covered = np.zeros(e.n_steps, bool)
        for w in mine:
            assert 0 <= w.start and w.start + w.length <= e.n_steps
            covered[w.start:w.start + w.length] = True
        assert covered.all()
        assert len({w.length for w in mine}) == 1
        # successors: the next window starts inside this one, same experiment
        for w in mine[:-1]:
            j, k = w.succ
            assert wins[j].exp == e_i and wins[j].start == w.start + k and 0 < k < w.length
        assert mine[-1].succ is None


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------


def test_config_yaml_and_overrides(tmp_path):
    f = tmp_path / "train.yaml"
    f.write_text("epochs: 12\nlr-final: 0.5\nfreeze: [U12]\ngamma: {U1: 0.1}\n")
    cfg = load_config(f, epochs=7, lr=None)
    assert cfg.epochs == 7 and cfg.lr_final == 0.5 and cfg.freeze == ["U12"] and cfg.gamma == {"U1": 0.1}


def test_config_unknown_key_suggests(tmp_path):
    f = tmp_path / "train.yaml"
    f.write_text("epoch: 12\n")
    with pytest.raises(TnnError, match="did you mean `epochs`"):
        load_config(f)


def test_config_bad_yaml_points_at_line(tmp_path):
    f = tmp_path / "train.yaml"
    f.write_text("epochs: 12\nlr: [0.1\n")
    with pytest.raises(TnnError) as e:
        load_config(f)
    assert str(f) in str(e.value) and "YAML" in str(e.value)


@pytest.mark.parametrize("bad", [{"backend": "tf"}, {"rollout": "sideways"}, {"lr": -1.0}, {"epochs": -3},
                                 {"val_fraction": 1.5}])
def test_config_rejects(bad):
    with pytest.raises(TnnError, match="training option"):
        TrainConfig(**bad)


# ---------------------------------------------------------------------------------------------
# metrics (eq. 4.9)
# ---------------------------------------------------------------------------------------------


def test_error_metrics_known_values():
    meas = np.array([[1.0, 2.0], [2.0, np.nan], [3.0, 4.0]])
    pred = np.array([[1.5, 2.0], [1.0, 7.0], [3.0, 3.0]])
    m = error_metrics([{"name": "a", "y": pred, "measured": meas}], ["s1", "s2"])
    assert m["sensors"]["s1"]["mae"] == pytest.approx(0.5)
    assert m["sensors"]["s1"]["max_error"] == pytest.approx(1.0)
    assert m["sensors"]["s1"]["bias"] == pytest.approx((0.5 - 1.0 + 0.0) / 3)
    assert m["sensors"]["s2"]["n"] == 2 and m["sensors"]["s2"]["mae"] == pytest.approx(0.5)
    assert m["mae"] == pytest.approx((0.5 + 1.0 + 0 + 0 + 1.0) / 5)
    assert m["n"] == 5


# ---------------------------------------------------------------------------------------------
# end to end (need the parser, the compiler and the data loader)
# ---------------------------------------------------------------------------------------------

BACKENDS = ["jax", "torch"]

REC_NET = """
network recovery "two heaters, nominal structure, no hidden effect"
units temperature = degC
input Q1 : [%]  column "Q1"
input Q2 : [%]  column "Q2"
param Ta = 23 degC
param a1 = 0.01 W/%
param a2 = 0.0075 W/%
boundary amb = Ta
node h1 C = {C1} J/K free
node h2 C = {C2} J/K free
G h1 -- amb = {U1} W/K free as U1
G h2 -- amb = {U2} W/K free as U2
G h1 -- h2  = {U12} W/K free as U12
source h1 = a1 * Q1
source h2 = a2 * Q2
sensor T1 = h1 column "T1"
sensor T2 = h2 column "T2"
"""
TRUE = {"C1": 4.0, "C2": 6.0, "U1": 0.05, "U2": 0.04, "U12": 0.02}
START = {"C1": 4.0 * 1.3, "C2": 6.0 * 0.7, "U1": 0.05 * 0.7, "U2": 0.04 * 1.3, "U12": 0.02 * 1.3}
NAMES = {"C1": "C_h1", "C2": "C_h2", "U1": "U1", "U2": "U2", "U12": "U12"}


def _prbs(rng, n, lo, hi, hold=(30, 150)):
    out = np.empty(n)
    k = 0
    while k < n:
        h = int(rng.integers(hold[0], hold[1]))
        out[k:k + h] = rng.uniform(lo, hi)
        k += h
    return out


def _simulated(net, seed, n, dt=2.0, backend="jax"):
    """An Experiment simulated from ``net`` (its written values) with PRBS heater inputs."""
    from tnn_dsl.data import Experiment
    from tnn_dsl.fit.simulation import simulate

    rng = np.random.default_rng(seed)
    U = np.stack([_prbs(rng, n, 0.0, 1.0), _prbs(rng, n, 0.0, 1.0)], axis=1)  # [%] in SI: 0..100 % = 0..1
    from tnn_dsl.compiler.model import compile as compile_network

    model = compile_network(net, backend=backend, dtype="float64")
    p = model.init_params(seed=0)
    t = np.arange(n) * dt
    tmp = Experiment(name=f"sim{seed}", path="", t=t, dt=dt, inputs=U, outputs=np.zeros((n, 2)),
                     input_names=("Q1", "Q2"), output_names=("T1", "T2"))
    _, y = simulate(model, p, tmp, init="steady")
    return Experiment(name=f"sim{seed}", path="", t=t, dt=dt, inputs=U, outputs=y,
                      input_names=("Q1", "Q2"), output_names=("T1", "T2"))


@pytest.mark.parametrize("backend", BACKENDS)
def test_parameter_recovery(backend):
    """Nominal-network data; all C and G start 30 % off; all five are identifiable (both nodes
    measured, independent heaters) and come back within 2 %."""
    import tnn_dsl

    truth = tnn_dsl.loads(REC_NET.format(**TRUE), "truth.thn")
    start = tnn_dsl.loads(REC_NET.format(**START), "start.thn")
    tr = _simulated(truth, 1, 800)
    va = _simulated(truth, 2, 300)
    tm = tnn_dsl.train(start, [tr], [va], backend=backend, rollout="measured", window=200.0, epochs=100,
                       lr=0.05, lbfgs_iters=200, seed=0)
    for k, name in NAMES.items():
        got = float(tm.params[name])
        assert abs(got / TRUE[k] - 1) < 0.02, (name, got, TRUE[k])
    assert tm.meta["metrics"]["validation"]["mae"] < 0.01
    assert tm.meta["backend"] == backend


@pytest.mark.parametrize("backend", BACKENDS)
def test_lbfgs_polish_converges_on_a_tiny_loss(backend):
    """The polish must not stop after one iteration when the loss is already small (scipy's stopping
    test is relative to max(|f|, 1)): start 2 % off, one Adam epoch, then L-BFGS alone recovers the
    values to 0.1 % and keeps its best-validation iterate."""
    import tnn_dsl

    near = {k: v * (1.02 if i % 2 else 0.98) for i, (k, v) in enumerate(TRUE.items())}
    truth = tnn_dsl.loads(REC_NET.format(**TRUE), "truth.thn")
    start = tnn_dsl.loads(REC_NET.format(**near), "start.thn")
    tr = _simulated(truth, 1, 600)
    va = _simulated(truth, 2, 200)
    tm = tnn_dsl.train(start, [tr], [va], backend=backend, rollout="measured", window=200.0, epochs=1, lr=1e-4,
                       lbfgs_iters=150, seed=0)
    assert tm.meta["curve"][1]["loss"] < 0.1  # K²: the polish starts from a small loss
    for k, name in NAMES.items():
        assert abs(float(tm.params[name]) / TRUE[k] - 1) < 1e-3, (name, float(tm.params[name]), TRUE[k])
    lb = [r for r in tm.meta["curve"] if r["phase"] == "lbfgs"]
    assert len(lb) >= 2 and min(r["val_mae"] for r in lb) == pytest.approx(tm.meta["metrics"]["validation"]["mae"])


# ---------------------------------------------------------------------------------------------
# case study (spec/case-study.md): M2 (linear heat pipe) clearly beats M1 (constant)
# ---------------------------------------------------------------------------------------------

NETS = ROOT / "networks" / "peltier_heatpipe"


@pytest.fixture(scope="module")
def case_short(tmp_path_factory):
    from tnn_dsl.studies.casestudy import generate_case_study

    return generate_case_study(tmp_path_factory.mktemp("cs"), n_ood=0, widen=(), durations=(2400.0, 1200.0, 60.0))


SLOW_TORCH = ["jax", pytest.param("torch", marks=pytest.mark.slow)]  # torch rollouts are ~20x slower on CPU


@pytest.mark.parametrize("backend", SLOW_TORCH)
def test_case_study_m2_beats_m1_fast(case_short, backend):
    import tnn_dsl

    kw = dict(backend=backend, rollout="estimated", window=400.0, epochs=60, lbfgs_iters=30, seed=0)
    m1 = tnn_dsl.train(NETS / "m1.thn", case_short["train"], case_short["val"], **kw)
    m2 = tnn_dsl.train(NETS / "m2.thn", case_short["train"], case_short["val"], **kw)
    v1 = m1.meta["metrics"]["validation"]["mae"]
    v2 = m2.meta["metrics"]["validation"]["mae"]
    assert v2 < v1 / 3, (v1, v2)
    # validation is a free run of the whole file: evaluating the returned model reproduces it
    assert m2.evaluate(case_short["val"], backend=backend)["mae"] == pytest.approx(v2, rel=1e-9)


@pytest.mark.slow
def test_case_study_acceptance(tmp_path):
    """Issue 4 acceptance with the default options: 4 h train, 2 h validation, no noise.

    M2 ≤ M1/3; M3 in M2's class: within 60 % of M2 (M1 is 50× M2). M3's final MAE is round-off's: a 1e-12
    perturbation of the L-BFGS polish's start moves it by up to 22 % (BENCHMARKS.md, "M3's final MAE is
    round-off's"); JAX's M3 over eight such runs 2.75–3.35 mK, 1.23–1.50× M2's 2.24 mK, and 2.95 mK (1.32×) in
    the slow suite of 2026-12-07 (the AMD host), where the earlier 25 % bound failed; 2.46 and 2.70 mK on other
    days and hosts.
    M4 (MLP Peltier) and M5 (M4's net frozen + M3's heat-pipe net) are trained and reported (M5 must beat M4).
    Backends: the default torch run takes ~45 min on a 2-core CPU (torch rollouts are ~60x slower than JAX there),
    so torch and JAX train M2 on one fixed schedule (60 Adam epochs, validation every 10, no polish) and must end
    within 5 % of each other (they agree to ~1e-12)."""
    import shutil

    import tnn_dsl
    from tnn_dsl.studies.casestudy import generate_case_study

    cs = generate_case_study(tmp_path / "cs", n_ood=0, widen=())
    res = {}
    (tmp_path / "models").mkdir()
    shutil.copy(NETS / "m5.thn", tmp_path / "m5.thn")
    for name, backend in [("m1", "jax"), ("m2", "jax"), ("m3", "jax"), ("m4", "jax"), ("m5", "jax")]:
        src = tmp_path / "m5.thn" if name == "m5" else NETS / f"{name}.thn"
        out = tmp_path / "models" / "m4" if name == "m4" else None
        tm = tnn_dsl.train(src, cs["train"], cs["val"], backend=backend, seed=0, out=out)
        res[name, backend] = tm.meta["metrics"]["validation"]["mae"]
        print(f"{name} {backend}: validation MAE {res[name, backend]:.5f} K ({tm.meta['train_seconds']:.0f} s)")
    assert res["m2", "jax"] <= res["m1", "jax"] / 3
    assert res["m3", "jax"] <= 1.6 * res["m2", "jax"]
    assert res["m5", "jax"] < res["m4", "jax"]
    fixed = dict(epochs=60, val_every=10, lbfgs_iters=0, patience=0, seed=0)
    same = {b: tnn_dsl.train(NETS / "m2.thn", cs["train"], cs["val"], backend=b, **fixed)
            .meta["metrics"]["validation"]["mae"] for b in BACKENDS}
    print("M2, fixed schedule:", same)
    assert abs(same["torch"] / same["jax"] - 1) <= 0.05


# ---------------------------------------------------------------------------------------------
# real data: TCLab (Kuntz & Rawlings PRBS run), fit on the first 70 %
# ---------------------------------------------------------------------------------------------

PRBS = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
STEPS = DATA / "tclab_apmonitor_energy_balance_steps.csv"


@pytest.mark.skipif(not PRBS.exists(), reason="shared TCLab data not present")
@pytest.mark.parametrize("backend", SLOW_TORCH)
def test_tclab_real_fit(backend):
    import tnn_dsl
    from tnn_dsl.data import read_data, split_by_time

    net = tnn_dsl.load(ROOT / "networks" / "tclab" / "tclab.thn")
    (exp,) = read_data(net, PRBS)
    head, tail = split_by_time(exp, 0.7)
    nominal = tnn_dsl.TrainedModel(net, {p.name: np.asarray(p.value) for p in net.params if p.is_constant},
                                   {"backend": backend})
    before = nominal.evaluate(tail, backend=backend)["mae"]
    tm = tnn_dsl.train(net, [head], [tail], backend=backend, rollout="measured", window=600.0, epochs=150, seed=0)
    tail_mae = tm.evaluate(tail, backend=backend)["mae"]
    steps_mae = tm.evaluate(STEPS, backend=backend, init="measured")["mae"]
    print(f"TCLab {backend}: last-30 % MAE {tail_mae:.3f} K (nominal {before:.3f} K); "
          f"APMonitor steps {steps_mae:.3f} K")
    assert tail_mae < 0.6 and tail_mae < before / 2
    assert np.isfinite(steps_mae)


BUILDING = DATA / "bacher_madsen_inputPRBS1.csv"


@pytest.mark.skipif(not BUILDING.exists(), reason="shared building data not present")
@pytest.mark.parametrize("backend", SLOW_TORCH)
def test_building_titeth_default_fits_the_free_run(backend):
    """Bacher & Madsen's TiTeTh on their real PRBS data (5-min samples; DTU CTSM-R example), default options: the
    training part (1184 samples) is fitted in windows of at least the slowest time constant, then as one free run
    from a fitted initial state (single shooting; 600 s windows were 3 samples, whose loss fell while the free run
    got worse: training MAE 6.4 K, measured 2026-11-23). The fitted model must follow the training part as a free
    run, and the model stores the fitted initial state, so simulating the training part again continues exactly."""
    import tnn_dsl
    from tnn_dsl.data import read_data, split_by_time

    net = tnn_dsl.load(ROOT / "networks" / "building" / "titeth.thn")
    (exp,) = read_data(net, BUILDING, time_unit="h")
    head, tail = split_by_time(exp, 0.7)
    tm = tnn_dsl.train(net, [head], [tail], backend=backend, epochs=150, lbfgs_iters=100, seed=0)
    assert tm.meta["config"]["window"] is None
    assert tm.meta["single_shooting"]  # after multiple shooting in windows of at least the slowest time constant
    assert [r["name"] for r in tm.meta["initial_states"]] == [head.name]
    train_mae = tm.evaluate(head, backend=backend)["mae"]
    assert train_mae == pytest.approx(tm.meta["metrics"]["train"]["mae"], rel=1e-9)
    assert tm.predict(head, backend=backend)[0]["init"] == "stored"
    print(f"TiTeTh {backend}: training free-run MAE {train_mae:.3f} K, "
          f"held out {tm.meta['metrics']['validation']['mae']:.3f} K")
    assert train_mae < 2.0


def test_loss_and_gradient_agree_across_backends(case_short):
    """The one trainer on both backends: same loss and gradient for M2 (multiple shooting, all terms on)."""
    import tnn_dsl
    from tnn_dsl.compiler.model import compile as compile_network
    from tnn_dsl.data import read_data
    from tnn_dsl.fit.trainer import _Trainer

    net = tnn_dsl.load(NETS / "m2.thn")
    (exp,) = read_data(net, case_short["train"])
    out = {}
    for backend in BACKENDS:
        cfg = TrainConfig(backend=backend, rollout="estimated", window=300.0, lam=0.1, gamma=0.01,
                          weight_decay=1e-3)
        tr = _Trainer(net, [exp], [], cfg, compile_network(net, backend=backend))
        p = tr.initial_params()
        nom, bp, runs = tr.nominal_runs(p)
        tr.set_stats(p, nom, bp, runs)
        tr.layout(p)
        tr.build_batches(runs)
        data, statics = tr.batch_arrays(None)
        rng = np.random.default_rng(3)
        z = np.concatenate([_to_z(sl, tr.params0[sl.name]) for sl in tr.slots] + [np.zeros(tr.n_x0 * 7)])
        z = z + 0.05 * rng.standard_normal(z.shape)
        out[backend] = tr.ops.value_and_grad(tr.make_loss(statics))(z, data)
    (vj, gj), (vt, gt) = out["jax"], out["torch"]
    assert vj > 0 and vj == pytest.approx(vt, rel=1e-9)
    np.testing.assert_allclose(gj, gt, rtol=1e-7, atol=1e-10 * np.abs(gj).max())


# ---------------------------------------------------------------------------------------------
# M4 -> M5: M5 loads M4's Peltier net (init_from, frozen) and trains only its heat-pipe net
# ---------------------------------------------------------------------------------------------


def test_nominal_run_on_torch_is_a_numpy_simulation_equal_to_jax(case_short, monkeypatch):
    """torch's nominal run (one simulation per file, no gradients) runs on the numpy reference backend, not as a
    torch rollout, and gives JAX's states to round-off; its model (normalisations, pre-fits) stays torch's."""
    import tnn_dsl
    from tnn_dsl.compiler import model as compiled_model
    from tnn_dsl.compiler.model import compile as compile_network
    from tnn_dsl.data import read_data
    from tnn_dsl.fit.trainer import _Trainer

    net = tnn_dsl.load(NETS / "m2.thn")
    (exp,) = read_data(net, case_short["train"])
    rollout = compiled_model.Model.rollout
    used: list = []

    def recorded(self, *a, **k):
        used.append(self.backend)
        return rollout(self, *a, **k)

    monkeypatch.setattr(compiled_model.Model, "rollout", recorded)
    runs, seen = {}, {}
    for backend in BACKENDS:
        used.clear()
        tr = _Trainer(net, [exp], [], TrainConfig(backend=backend), compile_network(net, backend=backend))
        nom, _bp, (runs[backend],) = tr.nominal_runs(tr.initial_params())
        seen[backend] = set(used)
        assert nom.backend == backend
    assert seen == {"jax": {"jax"}, "torch": {"numpy"}}
    assert runs["jax"].shape == (exp.n_steps, 7)
    np.testing.assert_allclose(runs["torch"], runs["jax"], rtol=0, atol=1e-9)


# slow (20 s in CI, 2026-12-04): CI checks the same on the models tests/test_study.py::test_study_tiny trains anyway
# (M5's Peltier network M4's, its heat-pipe network trained, m5.thn's relative init_from and its missing model)
@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_m5_loads_m4_frozen_and_trains(case_short, tmp_path, backend):
    import shutil

    import tnn_dsl

    kw = dict(backend=backend, rollout="estimated", window=400.0, epochs=8, lbfgs_iters=0, seed=0)
    m4 = tnn_dsl.train(NETS / "m4.thn", case_short["train"], case_short["val"], out=tmp_path / "models" / "m4", **kw)
    pe_keys = sorted(k for k in m4.params if k.startswith("fn_pe_Q_hot."))
    assert pe_keys and any(k.endswith(".W0") for k in pe_keys)
    # M5's `init_from = "models/m4"` is relative to its own file
    shutil.copy(NETS / "m5.thn", tmp_path / "m5.thn")
    m5 = tnn_dsl.train(tmp_path / "m5.thn", case_short["train"], case_short["val"], **kw)
    for k in pe_keys:  # weights and normalisation statistics: exactly M4's, untouched by training
        np.testing.assert_array_equal(m5.params[k], m4.params[k], err_msg=k)
    hp = [k for k in m5.params if k.startswith("fn_R_hp1.W")]
    assert hp and any(np.any(m5.params[k] != 0) for k in hp if k.endswith("W2"))  # the heat-pipe net trained
    curve = [r["loss"] for r in m5.meta["curve"] if r["phase"] == "adam"]
    assert curve[-1] < m5.meta["curve"][0]["loss"]
    assert math.isfinite(m5.meta["metrics"]["validation"]["mae"])
    # a frozen function without its model directory is a clear error, not a silent fresh start
    shutil.rmtree(tmp_path / "models")
    with pytest.raises(TnnError, match="m4"):
        tnn_dsl.train(tmp_path / "m5.thn", case_short["train"], case_short["val"], **kw)


# ---------------------------------------------------------------------------------------------
# sigmoid MLPs train in tanh coordinates (TrainConfig.centre_sigmoid); the polish starts from Adam's end
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_tanh_coordinates_give_the_same_sigmoid_mlp(backend):
    """``_tanh_to_sigmoid`` maps the weights of a tanh MLP to those of the sigmoid MLP computing the same
    function (exactly, on backend arrays), and ``_sigmoid_to_tanh`` inverts it."""
    from tnn_dsl.compiler.backends.adapter import Backend as _Ops
    from tnn_dsl.fit.transforms import _sigmoid_to_tanh, _tanh_to_sigmoid

    ops = _Ops(backend)
    rng = np.random.default_rng(4)
    sizes = [3, 5, 4, 2, 2]  # three hidden layers: first, middle and last-layer rules all used
    K = len(sizes) - 2
    primed = {}
    for k in range(K + 1):
        primed[f"f.W{k}"] = rng.normal(size=(sizes[k], sizes[k + 1]))
        primed[f"f.b{k}"] = rng.normal(size=sizes[k + 1])
    p = {k: ops.asarray(v) for k, v in primed.items()}
    _tanh_to_sigmoid(p, "f", K)
    stored = {k: ops.numpy(v) for k, v in p.items()}
    x = rng.normal(size=(7, 3))

    def net(w, act):
        h = x
        for k in range(K + 1):
            h = h @ w[f"f.W{k}"] + w[f"f.b{k}"]
            h = act(h) if k < K else h
        return h

    np.testing.assert_allclose(net(stored, lambda a: 1.0 / (1.0 + np.exp(-a))), net(primed, np.tanh),
                               rtol=1e-12, atol=1e-12)
    back = dict(stored)
    _sigmoid_to_tanh(back, "f", K)
    for k, v in primed.items():
        np.testing.assert_allclose(back[k], v, rtol=1e-12, atol=1e-12, err_msg=k)


HIDDEN_NET = """
network hidden_loss "two heaters; h1's loss to ambient depends on Q2"
units temperature = degC
input Q1 : [%]  column "Q1"
input Q2 : [%]  column "Q2"
param Ta = 23 degC
boundary amb = Ta
node h1 C = 4 J/K
node h2 C = 6 J/K
G h1 -- amb = {G1} as U1
G h2 -- amb = 0.04 W/K as U2
G h1 -- h2  = 0.02 W/K as U12
source h1 = 0.01 W/% * Q1
source h2 = 0.0075 W/% * Q2
sensor T1 = h1 column "T1"
sensor T2 = h2 column "T2"
"""


# torch (27 s / 21 s in CI) is slow; the JAX variant runs in CI and torch trains in test_parameter_recovery
@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_centre_sigmoid_trains_a_sigmoid_mlp_faster(backend):
    """A sigmoid MLP (the thesis's M3 kind) learns a hidden dependence in 30 Adam epochs in tanh
    coordinates; in its own coordinates it has barely left the nominal model (0.10 vs 0.80 K, from 1.1 K)."""
    import tnn_dsl

    truth = tnn_dsl.loads(HIDDEN_NET.format(G1="0.05 W/K * (1 + 0.8 * (Q2 - 0.5))"), "truth.thn")
    model = tnn_dsl.loads(HIDDEN_NET.format(G1="0.05 W/K") +
                          "learn U1 as mlp(h1, Q2; hidden = [6, 6], activation = sigmoid)\n", "m.thn")
    tr, va = _simulated(truth, 1, 800), _simulated(truth, 2, 300)
    # the data were simulated from rest: validation free runs start there too (init steady), so the comparison is
    # about the optimiser's coordinates alone
    kw = dict(backend=backend, rollout="measured", window=200.0, epochs=30, lbfgs_iters=0, seed=0, init="steady")
    on = tnn_dsl.train(model, [tr], [va], **kw)
    off = tnn_dsl.train(model, [tr], [va], centre_sigmoid=False, **kw)
    start = on.meta["curve"][0]["val_mae"]
    v_on, v_off = on.meta["metrics"]["validation"]["mae"], off.meta["metrics"]["validation"]["mae"]
    assert v_on < 0.2 * start and v_on < 0.3 * v_off, (start, v_on, v_off)
    # the stored weights are ordinary sigmoid-MLP weights: the saved model reproduces the validation MAE
    assert on.evaluate([va], backend=backend, init="steady")["mae"] == pytest.approx(v_on, rel=1e-9)


def test_polish_starts_from_adams_last_state(monkeypatch):
    """The L-BFGS polish starts from Adam's last iterate, not from an earlier best-validation state, and
    falls back to that state when it cannot beat its validation MAE."""
    import tnn_dsl
    import tnn_dsl.fit.trainer as _train

    calls = {"n": 0}

    def fake_validate(self, z, exps=None):  # the start is the best validation state; nothing later beats it
        calls["n"] += 1
        return 1.0 if calls["n"] == 1 else 2.0

    seen = {}
    orig = _train._Trainer.polish

    def spy(self, z, full_vg, data, best, has_val, t0, **kw):
        seen["start"], seen["fallback"], seen["best"] = np.array(z), np.array(kw["fallback"]), best
        out = orig(self, z, full_vg, data, best, has_val, t0, **kw)
        seen["out"] = np.array(out)
        return out

    monkeypatch.setattr(_train._Trainer, "validate", fake_validate)
    monkeypatch.setattr(_train._Trainer, "polish", spy)
    truth = tnn_dsl.loads(REC_NET.format(**TRUE), "truth.thn")
    start = tnn_dsl.loads(REC_NET.format(**START), "start.thn")
    tm = tnn_dsl.train(start, [_simulated(truth, 1, 300)], [_simulated(truth, 2, 100)], rollout="measured",
                       window=100.0, epochs=5, lbfgs_iters=20, seed=0)
    assert seen["best"] == 1.0
    assert np.abs(seen["start"] - seen["fallback"]).max() > 1e-3  # Adam moved; the polish starts there
    np.testing.assert_array_equal(seen["out"], seen["fallback"])  # and nothing beat the best: fallback kept
    for k, name in NAMES.items():  # the fallback is the starting point here: the model keeps its values
        assert float(tm.params[name]) == pytest.approx(START[k], rel=1e-12), name
