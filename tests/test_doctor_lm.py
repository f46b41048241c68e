"""The doctor's Levenberg–Marquardt (``_Engine.fit``): a fresh Jacobian every ``jacobian_every`` iterations and
Broyden's secant update in between reach the optimum that a fresh Jacobian every iteration reaches, with fewer
Jacobians; the caps count Jacobians; the forward-difference Jacobian that steers the fits agrees with the exact
forward-mode one, and both reach the same optimum (issue 18)."""

from __future__ import annotations

import os

import numpy as np
import pytest

import tnn_dsl
import tnn_dsl.doctor.engine as E
from tnn_dsl.doctor.candidates import build_extended
from tnn_dsl.studies.planted import plant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}


def _nominal_engine(backend: str, init: str = "steady"):
    """The nominal TCLab network's engine on data with a planted heat load (the nominal model cannot fit it
    exactly: a least-squares problem with a non-zero residual), and its free columns; its free runs start by the
    rule ``init`` (``measured``: fixed starts, each file's steady state at its first readings)."""
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "heat_load", "Q[h2]", "Q1", 0.3, noise=0.0, seed=2, n_train=300, n_val=10,
               backend="jax", hold=(20, 60))  # the data; the engine below runs on ``backend``
    exps, tm, vm = E._split_masks(pl.train, pl.val)
    ext0 = build_extended(net, ["Q1", "Q2"], kinds=("sensor_offset",), only=set())
    eng, _, free, _ = E._make_engine(ext0, net, exps, tm, vm, backend, E._State(E._InitPlan(init)), {}, [])
    if init != "steady":
        eng.initial_states(range(len(exps)), init)
    return eng, [j for j in free if not eng.cols[j].key.startswith(E.X0_PREFIX)]


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])  # torch eager: 11 s
def test_secant_updates_reach_the_same_optimum_with_fewer_jacobians(backend, monkeypatch):
    monkeypatch.setattr(E, "LM_JACOBIAN", "forward")  # exact Jacobians: only the secant update differs
    eng, free = _nominal_engine(backend)
    assert free, "the TCLab network has free constants"
    start = eng.apply(eng.params, free, np.full(len(free), 0.4), trust=False)  # every log-constant × e^0.4
    out = {}
    for every in (1, 4):
        eng.params = start
        info = eng.fit(free, max_iter=200, tol=1e-12, jacobian_every=every)
        out[every] = (info, eng.sse())
    (exact, sse_exact), (secant, sse_secant) = out[1], out[4]
    assert not exact["capped"] and not secant["capped"], (exact, secant)
    assert exact["iterations"] == exact["jacobians"]
    assert sse_secant == pytest.approx(sse_exact, rel=1e-6, abs=1e-12)
    assert secant["jacobians"] < exact["jacobians"], (exact, secant)
    assert secant["iterations"] > secant["jacobians"]  # the secant update did carry some iterations


@pytest.mark.parametrize("backend", ["jax", "torch"])  # torch's fast check of the secant path (2 s)
def test_the_cap_counts_jacobians(backend):
    eng, free = _nominal_engine(backend)
    eng.params = eng.apply(eng.params, free, np.full(len(free), 0.8), trust=False)
    info = eng.fit(free, max_iter=2, tol=1e-12, jacobian_every=3)
    assert info["jacobians"] == 2 and 2 < info["iterations"] <= 6  # iterations carried by the secant update
    assert info["capped"] is True
    first = info["sse"]
    info = eng.fit(free, max_iter=200, tol=1e-12, jacobian_every=3)  # it was still moving: going on helps
    assert info["sse"] <= first and info["capped"] is False


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_difference_jacobian_matches_forward_mode_and_fits_reach_the_same_optimum(backend, monkeypatch):
    """Every column (log constants, initial states in K) within 1e-4 of the exact one relative to its largest
    entry; a fit steered by either reaches the same training SSE (to 1e-9)."""
    eng, free = _nominal_engine(backend)
    every = free + [j for j, c in enumerate(eng.cols) if c.key.startswith(E.X0_PREFIX)]
    exact = eng.jacobian(every, method="forward")
    diff = eng.jacobian(every, method="difference")
    assert diff.shape == exact.shape == (eng.train_idx.size, len(every))
    scale = np.abs(exact).max(0)
    assert np.all(scale > 0)
    assert np.all(np.abs(diff - exact).max(0) <= 1e-4 * scale), np.abs(diff - exact).max(0) / scale
    with pytest.raises(ValueError, match="method must be"):
        eng.jacobian(every, method="central")
    # a column on its upper bound steps backwards, and its column still agrees
    import dataclasses

    j = free[0]
    c = eng.cols[j]
    eng.cols[j] = dataclasses.replace(c, upper=float(eng.params[c.key].reshape(-1)[c.index]))
    assert eng._diff_step(j) < 0
    back = eng.jacobian([j], method="difference")[:, 0]
    assert np.abs(back - exact[:, 0]).max() <= 1e-4 * scale[0]
    eng.cols[j] = c
    start = eng.apply(eng.params, free, np.full(len(free), 0.4), trust=False)
    sse = {}
    for method in ("forward", "difference"):
        monkeypatch.setattr(E, "LM_JACOBIAN", method)
        eng.params = start
        info = eng.fit(free, max_iter=200, tol=1e-12)
        assert not info["capped"], (method, info)
        sse[method] = info["sse"]
    assert sse["difference"] == pytest.approx(sse["forward"], rel=1e-9)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_a_crawling_candidate_fit_stops_when_its_last_jacobians_gained_little(backend, monkeypatch):
    """``stall=True`` (the candidates' fits) stops a fit whose training SSE fell by less than ``STALL_REL`` over its
    last ``STALL_JACOBIANS`` fresh Jacobians: not capped, fewer Jacobians than the fit run until a step fails, and an
    SSE whose distance to that fit's is of the order of ``STALL_REL``. A zero ``STALL_REL`` never stops a fit."""
    eng, free = _nominal_engine(backend)
    start = eng.apply(eng.params, free, np.full(len(free), 0.4), trust=False)
    runs = {}
    for stall in (False, True):
        eng.params = start
        runs[stall] = eng.fit(free, max_iter=200, tol=1e-12, stall=stall)
    full, stopped = runs[False], runs[True]
    assert not full["capped"] and not stopped["capped"], runs
    assert stopped["jacobians"] < full["jacobians"], runs
    assert full["sse"] <= stopped["sse"] <= full["sse"] * (1 + 4 * E.STALL_REL) + 1e-12, runs
    monkeypatch.setattr(E, "STALL_REL", 0.0)
    eng.params = start
    never = eng.fit(free, max_iter=200, tol=1e-12, stall=True)
    assert never["jacobians"] == full["jacobians"] and never["sse"] == pytest.approx(full["sse"], rel=1e-12)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_released_programs_are_built_again_and_give_the_same_numbers(backend):
    """``_Engine.release_programs`` (issue 18: a finished phase's networks free their compiled programs) lets the
    engine's programs and its model's compiled cache go; the next simulation, Jacobian and fit compile them again and
    give the numbers they gave before, to round-off."""
    eng, free = _nominal_engine(backend)
    y0, x0 = eng.simulate()
    J0 = eng.jacobian(free, method="difference")
    sse0 = eng._train_sse(eng.params)[0]
    eng.release_programs()
    assert not any(name in eng.__dict__ for name in E._PROGRAMS)
    assert not any(isinstance(k, tuple) for k in eng.model._jit_cache)
    eng._sim_memo = None  # the last simulation is kept (``simulate``): this one must run the rebuilt program
    y1, x1 = eng.simulate()
    np.testing.assert_allclose(y1, y0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x1, x0, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(eng.jacobian(free, method="difference"), J0, rtol=1e-9, atol=1e-12)
    assert eng._train_sse(eng.params)[0] == pytest.approx(sse0, rel=1e-12)
    assert all(name in eng.__dict__ for name in ("_sim", "_sim_train", "_jac_diff"))
    clone = eng.clone()  # a clone of a released engine shares nothing it lacks
    clone._sim_memo = None
    eng.release_programs()
    np.testing.assert_allclose(clone.simulate()[0], y0, rtol=1e-12, atol=1e-12)
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        eng.nothing_here  # noqa: B018


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_a_simulation_and_the_held_out_starts_are_made_once_for_the_same_parameters(backend, monkeypatch):
    """``_Engine.simulate`` gives its last simulation again (copies) for bitwise the same parameters, and the held-out
    files' starts (the ``estimate`` rule's burn-in fits) are put back, not fitted again, when the other parameters
    are bitwise those of the last fit — a table set anew with the same values included; a moved parameter runs both
    again, and going back gives the first numbers to the bit (issue 18: half of a diagnosis' simulations were
    repeats)."""
    eng, free = _nominal_engine(backend, init="estimate")
    assert eng.val_only, "the planted data's held-out file is the one whose start is estimated"
    sims, fits = [], []
    run = eng._sim
    monkeypatch.setattr(eng, "_sim", lambda p: (sims.append(1), run(p))[1], raising=False)
    estimate = E._Engine.initial_states
    monkeypatch.setattr(E._Engine, "initial_states", lambda self, *a, **k: (fits.append(a), estimate(self, *a, **k))[1])
    start = {k: np.array(v, copy=True) for k, v in eng.params.items()}
    y0, x0 = eng.simulate()
    assert (len(sims), len(fits)) == (1, 1)
    y1, x1 = eng.simulate()
    assert (len(sims), len(fits)) == (1, 1)
    np.testing.assert_array_equal(y1, y0)
    np.testing.assert_array_equal(x1, x0)
    y1[:] = 0.0  # a copy: the kept simulation is not the caller's to change
    np.testing.assert_array_equal(eng.simulate()[0], y0)
    eng.params = {k: np.array(v, copy=True) for k, v in eng.params.items()}  # marks the starts stale
    assert eng.x0_stale
    np.testing.assert_array_equal(eng.residual(), eng.y - y0)
    assert (len(sims), len(fits)) == (1, 1)
    assert eng.sse(which="val") == eng._sse_of((eng.y - y0).ravel()[eng.val_idx])
    moved = eng.apply(eng.params, free[:1], np.array([0.3]), trust=False)
    eng.params = moved
    y2, _ = eng.simulate()
    assert (len(sims), len(fits)) == (2, 2)
    assert not np.array_equal(y2, y0)
    eng.params = {k: np.array(v, copy=True) for k, v in start.items()}
    y3, x3 = eng.simulate()
    assert (len(sims), len(fits)) == (3, 3)
    np.testing.assert_array_equal(y3, y0)
    np.testing.assert_array_equal(x3, x0)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_a_fit_on_a_network_holding_more_null_candidates_gives_its_own_networks_numbers(backend):
    """The round's shared small network (``_Session.foreseen``, issue 18): a heat load at h2 growing with Q1 (the
    planted effect) fitted on a network that also holds, at their null values, its square, its constant sub-model
    and a load depending on T(h1) simulates what the network of that one candidate simulates (to round-off) and its
    fit reaches the same training SSE and values."""
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "heat_load", "Q[h2]", "Q1", 0.3, noise=0.0, seed=2, n_train=300, n_val=10,
               backend="jax", hold=(20, 60))
    exps, tm, vm = E._split_masks(pl.train, pl.val)
    own_key = "heat_load:Q[h2]:Q1"
    more = [own_key, "heat_load:Q[h2]:Q1²", "heat_load:Q[h2]:", "heat_load:Q[h2]:T(h1)"]
    state, ref = E._State(E._InitPlan("estimate")), {}
    fits = []
    for keys in ([own_key], more):
        ext = build_extended(net, ["Q1", "Q2"], only=set(keys))
        assert {c.key for c in ext.candidates} >= set(keys)
        eng, _, free, cols = E._make_engine(ext, net, exps, tm, vm, backend, state, ref, keys)
        eng.initial_states(range(len(exps)), "measured")  # the files' starts (the doctor's: its nominal fit's)
        y0, _ = eng.simulate()
        act = list(free) + cols[own_key]
        info = eng.fit(act, max_iter=30, tol=1e-10)
        fits.append((y0, info["sse"], [float(np.asarray(eng.params[eng.cols[j].key]).reshape(-1)[eng.cols[j].index])
                                       for j in cols[own_key]]))
    (y_own, sse_own, v_own), (y_more, sse_more, v_more) = fits
    np.testing.assert_allclose(y_more, y_own, rtol=0, atol=1e-10)
    assert sse_more == pytest.approx(sse_own, rel=1e-8)
    top = max(abs(v) for v in v_own)
    np.testing.assert_allclose(v_more, v_own, rtol=1e-6, atol=1e-9 * top)
    assert top == pytest.approx(0.3, rel=0.05)  # the planted load's slope, 0.3 W per unit of Q1 (no noise)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_warm_compiles_what_a_fit_calls_first_and_changes_nothing(backend):
    """``_Engine.warm`` (the doctor calls it before a round's fits start side by side): the parameters stay as they
    were, a fit on a clone afterwards compiles nothing more on JAX, and it reaches the SSE that the same fit reaches
    on an engine never warmed, to the bit."""
    eng, free = _nominal_engine(backend)
    eng.params = eng.apply(eng.params, free, np.full(len(free), 0.4), trust=False)
    cold = eng.clone()  # shares no compiled program with the warmed engine's later calls: released below
    before = {k: np.array(v, copy=True) for k, v in eng.params.items()}
    eng.warm(free)
    assert set(eng.params) == set(before)
    for k, v in before.items():
        np.testing.assert_array_equal(eng.params[k], v)
    warm = eng.clone()
    compiled: list[str] = []
    if backend == "jax":
        import jax.monitoring

        def listen(event: str, duration: float, **kwargs) -> None:
            if event == "/jax/core/compile/backend_compile_duration":
                compiled.append(event)

        jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        got = warm.fit(free, max_iter=3, init_delta=np.full(len(free), -0.2), tol=1e-12)
    finally:
        if backend == "jax":
            jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == [], f"the fit compiled {len(compiled)} program(s) after warm"
    cold.release_programs()
    want = cold.fit(free, max_iter=3, init_delta=np.full(len(free), -0.2), tol=1e-12)
    assert got["sse"] == want["sse"] and got["jacobians"] == want["jacobians"] == 3


def test_a_jacobian_compiled_without_running_is_not_compiled_again():
    """``_Engine.jacobian(run=False)`` (the doctor compiles the standard errors' forward-mode Jacobian beside the
    extended model's polish, issue 18): nothing is returned, and the Jacobian taken afterwards on a clone compiles no
    program and is the Jacobian of an engine that never compiled ahead, to the bit."""
    import jax.monitoring

    eng, free = _nominal_engine("jax")
    cold = eng.clone()
    assert eng.clone().jacobian(free, run=False) is None
    compiled: list[str] = []

    def listen(event: str, duration: float, **kwargs) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(event)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        got = eng.jacobian(free)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == [], f"the Jacobian compiled {len(compiled)} program(s) after run=False"
    cold.release_programs()
    np.testing.assert_array_equal(got, cold.jacobian(free))


def test_fitted_initial_states_stay_in_the_datas_start_range(tmp_path):
    """A training file's fitted initial state is a Levenberg–Marquardt column bounded by
    :func:`tnn_dsl.fit.ranges.start_range` (the trainer's penalty and the burn-in estimate keep theirs there too).
    Unbounded, the case study's nominal fit from M1 (the heat pipe's u1 law missing) started ``ph`` at −301 K, ``hx1``
    at −80 K and ``hs`` at 815 K, the transients standing in for the missing law (4 h data, 2026-12-03)."""
    from tnn_dsl.doctor.session import _Session
    from tnn_dsl.fit.ranges import start_range
    from tnn_dsl.studies.casestudy import generate_case_study

    generate_case_study(tmp_path / "cs", widen=(), n_ood=0, durations=(80 * 60.0, 40 * 60.0, 60.0))
    m1 = os.path.join(ROOT, "networks", "peltier_heatpipe", "m1.thn")
    s = _Session(m1, [str(tmp_path / "cs" / "train.csv")], [str(tmp_path / "cs" / "val.csv")], None, "jax",
                 None, top=5, max_rounds=1, output=None, kinds=None, mlp_check=False, mlp_time=60.0, force=False)
    s.read_data()
    s.fit_baseline()
    eng = s.eng
    lo, hi = start_range(eng.model, eng.exps[0])
    x0 = [j for j, c in enumerate(eng.cols) if c.key.startswith(E.X0_PREFIX + "0:")]
    assert len(x0) == len(eng.model.state_names)
    assert all((eng.cols[j].lower, eng.cols[j].upper) == (lo, hi) for j in x0)
    fitted = {eng.cols[j].key: float(eng.params[eng.cols[j].key]) for j in x0}
    assert all(lo <= v <= hi for v in fitted.values()), (lo, hi, fitted)
    # a step far below the range lands on its edge
    p = eng.apply(eng.params, x0, np.full(len(x0), -1e4), trust=False)
    assert all(float(p[eng.cols[j].key]) == lo for j in x0)


@pytest.mark.slow  # compiling: ~40-60 s; the fast variant is the next test
def test_torchs_compiled_rollouts_give_the_doctor_the_same_simulations_and_jacobians(monkeypatch):
    """On torch the doctor compiles its models' rollouts once its files are long enough (``doctor_model``): a
    simulation is one compiled scan instead of a Python call per sample, and the forward-difference Jacobian runs its
    simulations as one compiled scan vmapped over the parameter sets (``Model.rollouts_of``).
    The compiled engine gives the eager engine's simulation to 1e-9 K and its Jacobian to 1e-6 of each column's
    largest entry (issue 18: the case study's nominal fit spent 117 s of the demo's 120 s doctor budget eager)."""
    monkeypatch.delenv("TNN_TORCH_COMPILE", raising=False)
    monkeypatch.setattr(E, "DOCTOR_COMPILE_MIN_SAMPLES", 10**9)
    eager, free = _nominal_engine("torch", "measured")
    assert not eager.model.torch_compile
    monkeypatch.setattr(E, "DOCTOR_COMPILE_MIN_SAMPLES", 1)
    compiled, free_c = _nominal_engine("torch", "measured")
    assert compiled.model.torch_compile and free_c == free
    compiled.params = {k: np.array(v, copy=True) for k, v in eager.params.items()}
    y_e, x_e = eager.simulate()
    y_c, x_c = compiled.simulate()
    assert np.abs(y_c - y_e).max() <= 1e-9 and np.abs(x_c - x_e).max() <= 1e-9
    cols = free + [j for j, c in enumerate(eager.cols) if c.key.startswith(E.X0_PREFIX)]
    j_e = eager.jacobian(cols, method="difference")
    j_c = compiled.jacobian(cols, method="difference")
    assert np.all(np.abs(j_c - j_e).max(0) <= 1e-6 * np.abs(j_e).max(0)), np.abs(j_c - j_e).max(0)
    # the exact derivatives: torch.func's forward mode (eager) against central differences of compiled simulations
    assert compiled.by_differences and not eager.by_differences
    _same_derivatives(eager, compiled, free)


def _same_derivatives(exact, central, cols, tol=1e-7):
    """``central``'s ``jacobian(method="forward")`` and ``forced_jacobian`` (columns and two forcing series) agree with
    ``exact``'s within ``tol`` of each column's largest entry."""
    want = exact.jacobian(cols, method="forward")
    got = central.jacobian(cols, method="forward")
    assert np.all(np.abs(got - want).max(0) <= tol * np.abs(want).max(0)), np.abs(got - want).max(0)
    rng = np.random.default_rng(0)
    F = rng.normal(size=(2, exact.n_score_rows, exact.n_force)) * np.array([1.0, 50.0])[:, None, None]
    want = exact.forced_jacobian(cols[:3], F, chunk=4)
    got = central.forced_jacobian(cols[:3], F, chunk=4)
    assert got.shape == want.shape == (exact.train_idx.size, 5)
    assert np.all(np.abs(got - want).max(0) <= tol * np.abs(want).max(0)), np.abs(got - want).max(0)


def test_central_differences_give_the_exact_derivatives(monkeypatch):
    """The fast variant of the derivative check above, on JAX: the same engine's central differences (what a torch
    engine with compiled rollouts takes, :attr:`_Engine.by_differences`) against its exact forward mode."""
    exact, free = _nominal_engine("jax", "measured")
    central, _ = _nominal_engine("jax", "measured")
    monkeypatch.setattr(E._Engine, "by_differences", property(lambda self: self is central))
    monkeypatch.setattr(E, "LINEAR_STEPS_MAX", 0)  # the forcing block by differences, not by the linearised steps
    assert central.by_differences and not exact.by_differences and exact.n_force > 0
    calls = []
    monkeypatch.setattr(central, "_forced_central", lambda *a, f=central._forced_central: calls.append(1) or f(*a))
    _same_derivatives(exact, central, free)
    assert calls, "the forcing columns were taken by central differences"


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_the_forcing_block_through_the_linearised_steps_is_the_forward_mode_one(backend, monkeypatch):
    """The score test's forcing columns (``forced_jacobian``'s second block) through the tangent-linear model of the
    simulation — each sample's step and outputs differentiated at its state, then ``x_k+1 = Φ_k·x_k + Γ_k·F_k`` —
    equal JAX's forward mode through the whole rollout to round-off, on both backends (torch's engine took them by
    central differences before, 1e-8). A steady start moves with the forcing's first sample: no linearised steps
    there; nor beyond ``LINEAR_STEPS_MAX`` numbers, nor on JAX below ``LINEAR_STEPS_MIN_ROWS`` samples."""
    exact, _ = _nominal_engine("jax", "measured")
    eng, _ = _nominal_engine(backend, "measured")
    eng.params = {k: np.array(v, copy=True) for k, v in exact.params.items()}
    assert eng._by_steps() == (backend == "torch")  # 300 samples: JAX keeps forward mode below LINEAR_STEPS_MIN_ROWS
    monkeypatch.setattr(E, "LINEAR_STEPS_MIN_ROWS", 0)
    rng = np.random.default_rng(0)
    F = rng.normal(size=(5, exact.n_score_rows, exact.n_force)) * np.array([1.0, 50.0, 0.1, 3.0, 7.0])[:, None, None]
    with monkeypatch.context() as m:
        m.setattr(E, "LINEAR_STEPS_MAX", 0)
        assert not exact._by_steps()
        want = exact.forced_jacobian([0], F, chunk=4)  # forward mode through the rollout
    assert eng._by_steps()
    got = eng.forced_jacobian([0], F, chunk=4)
    assert got.shape == want.shape == (exact.train_idx.size, 6)
    assert np.all(np.abs(got - want).max(0) <= 1e-11 * np.abs(want).max(0)), np.abs(got - want).max(0)
    assert "_lin_memo" in eng.__dict__
    eng.forget_linear_steps()
    assert "_lin_memo" not in eng.__dict__
    steady, _ = _nominal_engine(backend, "steady")
    assert not steady._by_steps()


def test_the_doctor_compiles_torch_rollouts_for_long_files_unless_told_otherwise(monkeypatch):
    """The fast variant of the test above: which torch models compile (the files' samples against
    ``DOCTOR_COMPILE_MIN_SAMPLES``; ``TNN_TORCH_COMPILE`` decides where set; JAX untouched). The compiled rollouts
    of many parameter sets (the difference Jacobians') are checked in ``tests/test_torch_compile.py``."""
    net = tnn_dsl.load(TCLAB)
    monkeypatch.delenv("TNN_TORCH_COMPILE", raising=False)
    assert E.doctor_model(net, "torch", E.DOCTOR_COMPILE_MIN_SAMPLES).torch_compile
    assert not E.doctor_model(net, "torch", E.DOCTOR_COMPILE_MIN_SAMPLES - 1).torch_compile
    assert not getattr(E.doctor_model(net, "jax", 10**9), "torch_compile", False)
    monkeypatch.setenv("TNN_TORCH_COMPILE", "0")
    assert not E.doctor_model(net, "torch", 10**9).torch_compile
    monkeypatch.setenv("TNN_TORCH_COMPILE", "1")
    assert E.doctor_model(net, "torch", 1).torch_compile
