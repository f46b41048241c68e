"""Linear or MLP (``tnn_dsl.doctor.mlp_check``): the doctor trains its extension both ways and keeps the MLP only
when it pays on held-out data."""

from __future__ import annotations

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.data import Experiment
from tnn_dsl.doctor.mlp_check import compare, mlp_variant
from tnn_dsl.lang import print_thn

BASE = """network board "one heater"
units temperature = degC
input Q : [%]  column "Q_pct"
param Ta = 23 degC
boundary amb = Ta
node h "heater"  C = 4 J/K
G h -- amb = 0.02 W/K  as U
source h = 0.01 W/% * Q  as Qh
sensor T = h  column "T_degC"
"""

EXTENDED = tnn_dsl.loads(BASE + "learn U as linear(Q)\n", "x.thn")  # the doctor's finding: U depends on Q


def test_mlp_variant_changes_only_the_doctors_linear_functions():
    net = tnn_dsl.loads(BASE + "learn Qh as linear(Q)\nlearn U as linear(Q)\n", "x.thn")
    new, n = mlp_variant(net, {"U"})
    assert n == 1
    text = print_thn(new)
    assert "learn Qh as linear(Q)" in text  # the user's own function is left alone
    assert "learn U as mlp(Q; hidden = [8])" in text  # tanh: the default activation
    assert [fn.kind for fn in tnn_dsl.loads(text, "x.thn").learned] == ["linear", "mlp"]  # a valid network
    assert mlp_variant(net, set()) == (net, 0)


def _data(conductance, n, seed):
    """A free run of the one-heater board whose conductance is ``conductance(Q)`` (W/K), noise 0.01 K."""
    rng = np.random.default_rng(seed)
    holds = rng.integers(20, 80, size=n)
    q = np.repeat(rng.uniform(0.0, 1.0, size=n), holds)[:n]
    T, Ta, C = np.empty(n), 23.0, 4.0
    g0 = conductance(q[0])
    T[0] = Ta + 0.01 * 100 * q[0] / g0  # steady state of the first input
    for k in range(1, n):  # RK4 at dt = 1 s with the input held
        g, p = conductance(q[k - 1]), 0.01 * 100 * q[k - 1]

        def f(x):
            return (p - g * (x - Ta)) / C

        x = T[k - 1]
        k1 = f(x)
        k2 = f(x + k1 / 2)
        k3 = f(x + k2 / 2)
        k4 = f(x + k3)
        T[k] = x + (k1 + 2 * k2 + 2 * k3 + k4) / 6
    y = T + 273.15 + rng.normal(0, 0.01, n)
    return Experiment(name=f"s{seed}", path="<test>", t=np.arange(n, dtype=float), dt=1.0,
                      inputs=(100 * q)[:, None] * 0.01, outputs=y[:, None], input_names=("Q",), output_names=("T",))


TORCH_POLISH_WANDERS = (
    "the MLP's training from nominal values agrees with JAX's through Adam (losses within 1e-14 relative) and parts "
    "from it in the L-BFGS polish's first ten iterations (4.935 against 4.828), which round-off steers (BENCHMARKS.md, "
    "\"M3's final MAE is round-off's\"): torch's MLP ends at 1.457 K held out against JAX's 0.382 K, behind the "
    "linear law's 1.208 K (the same on both), so the check keeps the linear law; the same numbers in two runs "
    "(2026-12-07, the AMD host)")


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=[
    pytest.mark.slow, pytest.mark.xfail(strict=True, reason=TORCH_POLISH_WANDERS)])])
def test_a_curved_law_makes_the_mlp_pay_and_a_straight_one_does_not(backend):
    """From nominal values (``compare`` without ``start``). Each training is given 60 s: torch's, cut at 20 s, ended
    with the linear law at 1.08 K and the MLP at 1.29 K held out (2026-12-06, before and after the nested check)."""
    curved = lambda q: 0.02 * (1 + 12 * (q - 0.5) ** 2)  # noqa: E731 - convection that rises at both ends
    r = compare(EXTENDED, {"U"}, [_data(curved, 900, 1)], [_data(curved, 500, 2)], backend=backend,
                time_limit=60.0)
    assert r["choice"] == "mlp", r
    assert r["mlp"]["val_mae"] < 0.5 * r["linear"]["val_mae"]
    assert "learn U as mlp(Q; hidden = [8])" in print_thn(r["network"])
    # the linear clause's own law: a conductance is ``nominal·pos1(1 + z)``, positive by construction, with
    # ``pos1(v) = softplus(4v)/softplus(4)`` (tnn_dsl.compiler.learned)
    def pos1(v):
        return np.logaddexp(0.0, 4.0 * v) / np.logaddexp(0.0, 4.0)

    straight = lambda q: 0.02 * float(pos1(1.0 + 0.5 * (q - 0.5) / 0.5))  # noqa: E731
    r = compare(EXTENDED, {"U"}, [_data(straight, 900, 1)], [_data(straight, 500, 2)], backend=backend,
                time_limit=60.0)
    assert r["choice"] == "linear", r
    assert "learn U as linear(Q)" in print_thn(r["network"])


class _Trained:
    """What ``compare`` reads of a trained model: held-out predictions, how the training stopped, the parameters."""

    def __init__(self, err: np.ndarray, stopped: str, k: int, burn_in: int = 0):
        self.err, self.meta, self.k, self.burn_in = err, {"stopped": stopped}, k, burn_in

    def predict(self, vals, check=False):
        return [{"measured": self.err, "y": np.zeros_like(self.err), "burn_in": self.burn_in}]

    def compiled(self):
        spec = type("Spec", (), {"shape": (self.k,), "trainable": True})
        return type("M", (), {"param_specs": {"w": spec}})

    def release_compiled(self):
        self.released = True


@pytest.mark.parametrize("mlp_pays", [False, True])
@pytest.mark.parametrize("cut", [None, "linear", "mlp"])
def test_a_training_cut_by_the_time_limit_leaves_the_answer_undecided_only_where_it_could_change_it(
        monkeypatch, mlp_pays, cut):
    """The check's trainings run a fixed schedule and the time limit only caps them; on the case study, two
    trainings side by side on a contended host cut the MLP at 60 s (p = 0.29) where one at a time it finished
    (p = 0.062). An MLP cut short that does not pay, or a linear law cut short against an MLP that pays, is not an
    answer: ``decided`` is False, the linear law is kept and the reason names the cut and the limit. A cut that
    cannot change the answer (the MLP pays though cut, the linear law loses though cut) leaves it decided."""
    rng = np.random.default_rng(0)
    e_lin = rng.normal(0.0, 0.05, 2000)
    e_mlp = e_lin * (0.3 if mlp_pays else 0.99)

    def fake_train(variant, train, val, **kw):
        is_mlp = any(fn.kind == "mlp" for fn in variant.learned)
        form = "mlp" if is_mlp else "linear"
        return _Trained(e_mlp if is_mlp else e_lin, "time_limit" if form == cut else "completed", 45 if is_mlp else 8)

    monkeypatch.setattr("tnn_dsl.fit.train", fake_train)
    r = compare(EXTENDED, {"U"}, [], [], time_limit=60.0)
    undecided = (cut == "mlp" and not mlp_pays) or (cut == "linear" and mlp_pays)
    assert r["decided"] is (not undecided), r["reason"]
    if undecided:
        assert r["choice"] == "linear" and "not decided" in r["reason"] and "60 s" in r["reason"], r["reason"]
        assert f"the {cut} variant" in r["reason"] and "--mlp-time" in r["reason"]
    else:
        assert r["choice"] == ("mlp" if mlp_pays else "linear"), r["reason"]


def test_the_check_scores_what_the_doctor_scores(monkeypatch):
    """The held-out rows of both variants are the doctor's and ``evaluate``'s: each file's burn-in (its initial
    state's fit) is not scored, and a sensor's missing readings are left out — they are not a diverged run, which the
    held-out test rejects outright (before, a gap in a held-out file made any MLP "not pay", p = 1)."""
    rng = np.random.default_rng(1)
    e_lin = rng.normal(0.0, 0.05, (1000, 2))
    e_lin[:100] = 5.0  # the burn-in: large errors, the same for both, never scored
    e_mlp = e_lin * 0.3
    e_mlp[:100] = 0.0
    e_lin[400:420, 1] = e_mlp[400:420, 1] = np.nan  # a gap in sensor 2's log

    def fake_train(variant, train, val, **kw):
        is_mlp = any(fn.kind == "mlp" for fn in variant.learned)
        return _Trained(e_mlp if is_mlp else e_lin, "completed", 45 if is_mlp else 8, burn_in=100)

    monkeypatch.setattr("tnn_dsl.fit.train", fake_train)
    r = compare(EXTENDED, {"U"}, [], [], time_limit=60.0)
    assert r["choice"] == "mlp" and r["p_value"] < 1e-6, r["reason"]
    assert r["linear"]["val_mae"] == pytest.approx(float(np.nanmean(np.abs(e_lin[100:]))), rel=1e-12)
    assert r["mlp"]["val_mae"] == pytest.approx(0.3 * r["linear"]["val_mae"], rel=1e-12)


def test_a_training_whose_other_route_the_time_limit_cut_is_reported_as_cut(monkeypatch):
    """The trainer fits in windows, polishes as single shooting, then fits as single shooting from the start and keeps
    the better route (``fit.training._best_route``). When the time limit stops that second route, the kept one is
    whole but the choice is not: the training says ``time_limit``, so the MLP check does not take it as decided. A
    second route that ends keeps the first route's own status."""
    import tnn_dsl.fit.training as T

    class _Tr:
        def __init__(self, stopped: str, score: float):
            self.stopped, self.score, self.logged = stopped, score, []
            self.warmup_s = 0.5  # seconds in its programs' first calls

        def wants_single_shooting_finish(self) -> bool:
            return True

        def finish_single_shooting(self, z):
            return z

        def selection_score(self, z) -> float:
            return self.score

        def log(self, msg: str) -> None:
            self.logged.append(msg)

    for second, expect in (("time_limit", "time_limit"), ("completed", "completed")):
        first, other = _Tr("completed", 1.0), _Tr(second, 2.0)
        routes = iter([(first, np.zeros(2)), (other, np.ones(2))])
        monkeypatch.setattr(T, "_fit", lambda *a, **k: next(routes))
        tr, z, info, compile_s = T._best_route(None, [], [], T.make_config(None, {}), None, None, None)
        # the first route's trainer (finished as single shooting on a copy of it, ``_best_route``)
        assert tr is not other and tr.score == first.score and tr.stopped == expect
        assert info["single_stopped"] == second
        assert compile_s == 1.0  # both routes' compilation


@pytest.mark.parametrize("beats", [False, True])
@pytest.mark.parametrize("cut", [False, True])
def test_the_mlp_is_trained_first_and_the_linear_law_only_where_the_mlp_could_be_chosen(monkeypatch, beats, cut):
    """``compare(..., bar=)``: the doctor keeps an MLP only if it beats the doctor's own linear fit (``bar``, K held
    out) by ``MIN_GAIN``. The MLP is trained first; one that does not clear the bar cannot be chosen, so the linear
    clauses are not trained (on the case study that training never decided anything, and side by side with the MLP's
    it was the diagnosis' peak memory). Cut by the time limit there, the answer is not decided; an MLP that clears
    it goes on to the two-sided comparison as before."""
    from tnn_dsl.doctor.selection import MIN_GAIN

    rng = np.random.default_rng(1)
    e_lin = rng.normal(0.0, 0.05, 2000)
    e_mlp = e_lin * 0.3
    mae_mlp = float(np.mean(np.abs(e_mlp)))
    bar = mae_mlp / (1 - MIN_GAIN) * (1.01 if beats else 0.99)
    trained: list[str] = []

    def fake_train(variant, train, val, **kw):
        form = "mlp" if any(fn.kind == "mlp" for fn in variant.learned) else "linear"
        trained.append(form)
        stopped = "time_limit" if cut and form == "mlp" else "completed"
        return _Trained(e_mlp if form == "mlp" else e_lin, stopped, 45 if form == "mlp" else 8)

    monkeypatch.setattr("tnn_dsl.fit.train", fake_train)
    r = compare(EXTENDED, {"U"}, [], [], time_limit=60.0, threads=2, bar=bar)
    if beats:
        assert trained == ["mlp", "linear"] and "linear" in r and r["p_value"] < 0.05
        assert r["choice"] == "mlp" and r["decided"], r["reason"]  # a cut MLP that pays is still an answer
    else:
        assert trained == ["mlp"] and "linear" not in r and "p_value" not in r
        assert r["choice"] == "linear" and r["network"] is EXTENDED
        assert "does not beat the doctor's own linear fit" in r["reason"]
        assert r["decided"] is (not cut)
        assert ("not decided" in r["reason"] and "--mlp-time" in r["reason"]) if cut else (
            "the linear clauses were not trained" in r["reason"])


def test_a_stop_cuts_the_trainings_and_leaves_the_answer_undecided(monkeypatch):
    """The doctor's Ctrl-C (``compare(..., stop=)``, :mod:`tnn_dsl.doctor.stopping`): each training gets a callback that
    stops it (``KeyboardInterrupt``, the trainer keeps its best state: ``stopped: interrupted``) once ``stop()`` is
    true; a training so cut leaves the answer undecided like the time limit, the reason saying Ctrl-C stopped it."""
    rng = np.random.default_rng(1)
    e_lin = rng.normal(0.0, 0.05, 2000)
    stopping = [False]
    seen: list[str] = []

    def fake_train(variant, train, val, callback=None, **kw):
        callback({"phase": "start"})  # before the stop: goes on
        stopping[0] = True
        try:
            callback({"phase": "adam"})
        except KeyboardInterrupt:
            seen.append("stopped")
            return _Trained(e_lin * 1.2, "interrupted", 45)
        return _Trained(e_lin * 1.2, "completed", 45)

    monkeypatch.setattr("tnn_dsl.fit.train", fake_train)
    r = compare(EXTENDED, {"U"}, [], [], time_limit=60.0, bar=float(np.mean(np.abs(e_lin))), stop=lambda: stopping[0])
    assert seen == ["stopped"] and r["choice"] == "linear" and r["decided"] is False
    assert "stopped by Ctrl-C" in r["reason"] and "run to its end decides" in r["reason"], r["reason"]


@pytest.mark.parametrize("n_in", [1, 2, 3])
def test_an_mlp_started_from_a_linear_law_computes_that_law(n_in):
    """``mlp_start``: the MLP variant's hidden layer drawn as the trainer draws it, its output layer fitted to the
    linear law's raw output over the normalised inputs' box; compiled, the MLP gives the linear law's values (to
    1e-6 of the raw output on one or two inputs, 1e-3 on three; outside the box it may part) and every other value
    stays as it was."""
    from tnn_dsl.compiler import compile as compile_network
    from tnn_dsl.compiler.learned import apply
    from tnn_dsl.doctor.mlp_check import mlp_start

    ins = ", ".join(["Q", "T(h)", "Ta"][:n_in])
    net = tnn_dsl.loads(BASE + f"learn U, Qh as linear({ins})\n", "x.thn")
    net_mlp, n = mlp_variant(net, {"U", "Qh"})
    assert n == 1
    rng = np.random.default_rng(n_in)
    lin = compile_network(net, backend="jax")
    start = {k: np.asarray(v, float) for k, v in lin.to_numpy(lin.init_params(seed=0)).items()}
    fn = next(f for f in net.learned if f.kind == "linear")
    start[f"{fn.name}.W"] = rng.normal(0.0, 0.4, (n_in, 2))
    start[f"{fn.name}.b"] = rng.normal(0.0, 0.2, 2)
    start[f"{fn.name}.x_mean"] = rng.normal(300.0, 5.0, n_in)
    start[f"{fn.name}.x_scale"] = rng.uniform(1.0, 20.0, n_in)
    start["U"] = np.asarray(0.025)
    values, dz = mlp_start(net_mlp, start)
    assert dz < 1e-5
    x = start[f"{fn.name}.x_mean"] + start[f"{fn.name}.x_scale"] * rng.uniform(-1.0, 1.0, (200, n_in))
    fn_mlp = next(f for f in net_mlp.learned if f.kind == "mlp")
    mine = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith(fn.name + ".")}
    theirs = {k.split(".", 1)[1]: v for k, v in start.items() if k.startswith(fn.name + ".")}
    np.testing.assert_allclose(apply(np, fn_mlp, mine, x), apply(np, fn, theirs, x), atol=max(dz, 1e-12) * 2)
    assert set(mine) == {"W0", "b0", "W1", "b1", "x_mean", "x_scale", "y_scale"}
    assert values["U"] == start["U"] and not any(k in values for k in (f"{fn.name}.W", f"{fn.name}.b"))
    mlp = compile_network(net_mlp, backend="jax")
    shapes = {k: np.shape(v) for k, v in mlp.to_numpy(mlp.init_params(seed=0)).items()}
    assert all(np.shape(values[k]) == s for k, s in shapes.items() if k in values)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_training_from_given_values_starts_there_and_keeps_their_statistics(backend):
    """``train(start=...)``: the given values replace the initial ones (a learned function's statistics included,
    not recomputed from the data; names the network does not have are ignored), and with no optimisation step at
    all the trained model is the start, its validation error the start's."""
    data, val = [_data(lambda q: 0.02 * (1 + 0.5 * (q - 0.5)), 400, 3)], [_data(lambda q: 0.02, 200, 4)]
    name = EXTENDED.learned[0].name
    start = {f"{name}.W": np.array([[0.3]]), f"{name}.b": np.array([0.1]), f"{name}.x_mean": np.array([40.0]),
             f"{name}.x_scale": np.array([70.0]), f"{name}.y_scale": np.array([0.02]), "not_a_parameter": np.ones(2)}
    trained = tnn_dsl.train(EXTENDED, data, val, backend=backend, start=start, epochs=0, lbfgs_iters=0)
    for k, v in start.items():
        if k != "not_a_parameter":
            np.testing.assert_array_equal(trained.params[k], v)
    assert "not_a_parameter" not in trained.params
    fresh = tnn_dsl.train(EXTENDED, data, val, backend=backend, epochs=0, lbfgs_iters=0)
    q = np.asarray(data[0].inputs)[:, 0]  # Q in SI (a fraction): the trainer's statistics are its mid-range
    assert fresh.params[f"{name}.x_mean"][0] == pytest.approx((q.max() + q.min()) / 2, rel=1e-12)


def test_the_doctors_values_are_found_under_the_extensions_names():
    """``values_for_extension``: the doctor fits its dependences in functions of its own (``dx_params``, targets
    grouped its way); the extension names and groups them anew. Each target's bias, weights and output scale and
    each input's statistics land where the extension's function reads them, so it computes the doctor's law; a
    function with no counterpart gives None."""
    from tnn_dsl.compiler.learned import apply
    from tnn_dsl.doctor.mlp_check import values_for_extension

    two = BASE.replace('sensor T = h  column "T_degC"', 'node k "case"  C = 9 J/K\nG h -- k = 0.1 W/K  as Uk\n'
                       'sensor T = h  column "T_degC"')
    fitted_net = tnn_dsl.loads(two + "learn U, Uk as linear(Q, T(k))\n", "f.thn")
    ext = tnn_dsl.loads(two + "learn Uk, U as linear(T(k), Q)\n", "x.thn")
    g, f = fitted_net.learned[0], ext.learned[0]
    fitted_net = fitted_net.model_copy(update={"learned": [g.model_copy(update={"name": "dx_params"})]})
    g = fitted_net.learned[0]
    params = {"dx_params.W": np.array([[0.3, -0.2], [0.05, 0.4]]), "dx_params.b": np.array([0.1, -0.3]),
              "dx_params.x_mean": np.array([0.5, 300.0]), "dx_params.x_scale": np.array([0.5, 4.0]),
              "dx_params.y_scale": np.array([0.02, 0.1]), "U": np.array(0.021), "x0:0:h": np.array(299.0)}
    values = values_for_extension(ext, fitted_net, params)
    assert values is not None and "dx_params.W" not in values and values["U"] == params["U"]
    x_fit = np.array([[0.2, 301.0], [0.9, 297.5]])  # (Q, T(k)) as the doctor's function reads them
    mine = {k.split(".", 1)[1]: v for k, v in values.items() if k.startswith(f.name + ".")}
    theirs = {k.split(".", 1)[1]: v for k, v in params.items() if k.startswith("dx_params.")}
    z_fit = apply(np, g, theirs, x_fit)  # columns U, Uk
    z_ext = apply(np, f, mine, x_fit[:, ::-1])  # columns Uk, U; inputs T(k), Q
    np.testing.assert_allclose(z_ext, z_fit[:, ::-1], rtol=1e-12)
    np.testing.assert_array_equal(mine["y_scale"], [0.1, 0.02])
    other = tnn_dsl.loads(two + "learn Uk, U as linear(T(h), Q)\n", "x.thn")  # T(h): not in the fit
    assert values_for_extension(other, fitted_net, params) is None
    # a round that also tried the law's curvature fits it as a poly (terms Q, T(k), Q², Q·T(k), T(k)²): with the
    # curved terms at zero its linear law lands in the extension's linear function; a curved term the fit uses
    # goes only into a poly of the extension, term by term
    poly_net = tnn_dsl.loads(two + "learn U, Uk as poly(Q, T(k); degree = 2)\n", "f.thn")
    gp = poly_net.learned[0].model_copy(update={"name": "dx_params"})
    poly_net = poly_net.model_copy(update={"learned": [gp]})
    Wp = np.zeros((5, 2))
    Wp[:2] = params["dx_params.W"]
    pp = {**params, "dx_params.W": Wp}
    lin = values_for_extension(ext, poly_net, pp)
    assert lin is not None and np.array_equal(lin[f"{f.name}.W"], values[f"{f.name}.W"])
    Wp[2, 1] = 0.07  # Uk (column 1) curved in Q
    assert values_for_extension(ext, poly_net, pp) is None
    curved = tnn_dsl.loads(two + "learn Uk, U as poly(T(k), Q; degree = 2)\n", "x.thn")
    cv = values_for_extension(curved, poly_net, pp)
    fc = curved.learned[0]
    z_fit = apply(np, gp, {k.split(".", 1)[1]: v for k, v in pp.items() if k.startswith("dx_params.")}, x_fit)
    z_ext = apply(np, fc, {k.split(".", 1)[1]: v for k, v in cv.items() if k.startswith(fc.name + ".")},
                  x_fit[:, ::-1])
    np.testing.assert_allclose(z_ext, z_fit[:, ::-1], rtol=1e-12)


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_from_the_fit_a_curved_law_makes_the_mlp_pay_and_a_straight_one_does_not(backend):
    """The nested check (``compare(..., start=)``): the linear law is the fit it is given (here the trainer's fit of
    the linear extension), not trained again; the MLP starts as that law, only its weights trained. A curved
    conductance makes it pay against the law it started from; a law the linear clause holds exactly does not."""
    def pos1(v):
        return np.logaddexp(0.0, 4.0 * v) / np.logaddexp(0.0, 4.0)

    laws = {"curved": lambda q: 0.02 * (1 + 12 * (q - 0.5) ** 2),
            "straight": lambda q: 0.02 * float(pos1(1.0 + 0.5 * (q - 0.5) / 0.5))}
    # torch trains at a fraction of JAX's speed: beside another test its MLP's polish ran past 60 s (62.4 s,
    # 2026-12-07) and decided nothing, and trainings cut at different iterations differ (the same MLP twice and
    # with two threads, below, failed so on torch): torch's are given the time to end by their own rules
    limit = 60.0 if backend == "jax" else 600.0
    for shape, law in laws.items():
        train, val = [_data(law, 900, 1)], [_data(law, 500, 2)]
        fit = tnn_dsl.train(EXTENDED, train, val, backend=backend, epochs=100)
        start = values_for_extension_same(fit.params)
        r = compare(EXTENDED, {"U"}, train, val, backend=backend, time_limit=limit, start=start)
        assert r["linear"]["stopped"] == "the doctor's fit" and r["start_dz"] < 1e-6, r
        # the linear row is the given fit's own free run, scored as `evaluate` scores it (not on the burn-in its
        # initial state was fitted to)
        assert r["linear"]["val_mae"] == pytest.approx(fit.evaluate(val)["mae"], rel=1e-9)
        if shape == "curved":
            assert r["choice"] == "mlp" and r["mlp"]["val_mae"] < 0.5 * r["linear"]["val_mae"], r
            # with a second thread the linear law's free run goes beside the MLP's training: the same numbers
            r2 = compare(EXTENDED, {"U"}, train, val, backend=backend, time_limit=limit, start=start, threads=2)
            assert (r2["choice"], r2["linear"]["val_mae"], r2["mlp"]["val_mae"], r2["p_value"]) == (
                r["choice"], r["linear"]["val_mae"], r["mlp"]["val_mae"], r["p_value"])
            # the trained MLP is handed out (the doctor saves it), and it is the model the check measured
            assert r["model"].network == r["network"]
            assert r["model"].evaluate(val)["mae"] == pytest.approx(r["mlp"]["val_mae"], rel=1e-9)
        else:
            assert r["choice"] == "linear" and r["decided"] and "model" not in r, r


def values_for_extension_same(params):
    """The trainer's values of ``EXTENDED`` under its own names, as ``values_for_extension`` gives them."""
    from tnn_dsl.doctor.mlp_check import values_for_extension

    values = values_for_extension(EXTENDED, EXTENDED, params)
    assert values is not None
    return values


@pytest.mark.parametrize("backend,from_fit", [("jax", True), ("jax", False), pytest.param("torch", True,
                                                                                           marks=pytest.mark.slow)])
def test_the_held_out_files_judge_the_laws_and_never_steer_a_training(backend, from_fit):
    """The check's p-value is computed on the held-out files, so no training of the check may stop on them or keep
    the iterate they score best (on real data they may be files kept for validation only): each training validates
    on the end of its own training files (``EARLY_STOP_FRACTION``). Two different held-out runs of the same board
    give the same trained MLP, to the bit, and two different scores of it."""
    curved = lambda q: 0.02 * (1 + 12 * (q - 0.5) ** 2)  # noqa: E731
    train = [_data(curved, 900, 1)]
    start = values_for_extension_same(tnn_dsl.train(EXTENDED, train, backend=backend, epochs=100).params) \
        if from_fit else None
    limit = 60.0 if backend == "jax" else 600.0  # torch's trainings end by their own rules (the test above)
    runs = [compare(EXTENDED, {"U"}, train, [_data(curved, 500, seed)], backend=backend, time_limit=limit,
                    start=start) for seed in (2, 3)]
    for r in runs:
        assert r["choice"] == "mlp" and r["decided"], r["reason"]
    a, b = (r["model"].params for r in runs)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]), err_msg=k)
    assert runs[0]["mlp"]["val_mae"] != runs[1]["mlp"]["val_mae"]


@pytest.mark.parametrize("kept", [True, False], ids=["programs kept", "no program cache"])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_trained_mlps_held_out_programs_are_compiled_beside_its_training(monkeypatch, threads, kept):
    """With two threads and JAX keeping its programs (``tnnc diagnose``'s program cache), the thread that free-ran the
    linear law then free-runs the MLP at its start values, so that the programs of the trained MLP's held-out run are
    read back instead of compiled after its training (issue 18); a failure there changes nothing. With one thread,
    or no cache to keep them in, it is not done."""
    import tnn_dsl.doctor.mlp_check as M

    e_lin = np.random.default_rng(2).normal(0.0, 0.05, 2000)
    calls: list[str] = []

    def fake_errors(model, val):
        if isinstance(model, _Trained):
            calls.append("trained MLP")
            return model.err
        if any(fn.kind == "mlp" for fn in model.network.learned):
            calls.append("MLP at its start")
            raise RuntimeError("a failed warm-up")
        calls.append("linear law")
        return e_lin

    monkeypatch.setattr(M, "_held_out_errors", fake_errors)
    monkeypatch.setattr(M, "_programs_kept", lambda: kept)
    monkeypatch.setattr("tnn_dsl.fit.train", lambda *a, **k: _Trained(0.5 * e_lin, "completed", 45))
    model = tnn_dsl.compile(EXTENDED, "jax")
    start = values_for_extension_same(model.to_numpy(model.init_params(seed=0)))
    r = compare(EXTENDED, {"U"}, [], [], time_limit=60.0, start=start, threads=threads)
    warmed = threads == 2 and kept
    assert sorted(calls) == sorted(["linear law", "trained MLP"] + (["MLP at its start"] if warmed else []))
    if warmed:
        assert calls.index("MLP at its start") > calls.index("linear law")
    assert r["choice"] == "mlp" and r["mlp"]["val_mae"] == pytest.approx(0.5 * r["linear"]["val_mae"])
