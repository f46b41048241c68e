"""Sensitivity (thesis §4.3, eq. 3.2–3.4), Fisher identifiability and the recommendation (issue 5)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tnn_dsl.analysis.identifiability import fisher_analysis
from tnn_dsl.core.errors import TnnError
from tnn_dsl.ir.network import Num, Ref

BACKENDS = ["jax", "torch"]

# ---------------------------------------------------------------------------------------------
# Fisher algebra on given sensitivity matrices (no model)
# ---------------------------------------------------------------------------------------------


def test_fisher_orthogonal_columns_analytic():
    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.standard_normal((400, 3)))
    norms = np.array([50.0, 5.0, 0.5])
    S = Q * norms
    ident = fisher_analysis(S, ["a", "b", "c"], sigma=0.2, max_se=0.1)
    # orthogonal columns: F diagonal, se_i = σ/‖s_i‖ exactly, no correlation
    np.testing.assert_allclose(ident.std_errors, 0.2 / norms, rtol=1e-10)
    np.testing.assert_allclose(ident.correlation, np.eye(3), atol=1e-10)
    assert ident.pairs == []
    assert ident.identifiable("a") and ident.identifiable("b") and not ident.identifiable("c")  # 0.4 > 0.1
    assert [list(w.weights) for w in ident.weak] == [["c"]]
    assert "almost no effect" in ident.weak[0].description
    np.testing.assert_allclose(ident.abs_std_errors, [np.nan] * 3)
    d = json.loads(json.dumps(ident.to_dict()))
    assert d["identifiable"] == {"a": True, "b": True, "c": False}


def test_fisher_proportional_columns_flagged():
    rng = np.random.default_rng(1)
    s = rng.standard_normal(300)
    other = rng.standard_normal(300)
    S = np.column_stack([s, 2.0 * s, other])  # b acts exactly like a (twice as strongly)
    ident = fisher_analysis(S, ["a", "b", "c"], sigma=0.1, nominal={"a": 3.0, "b": 4.0, "c": 1.0})
    assert math.isinf(ident.std_errors[0]) and math.isinf(ident.std_errors[1])
    assert np.isfinite(ident.std_errors[2])
    assert ident.correlation[0, 1] == pytest.approx(-1.0, abs=1e-6)
    assert [(p.a, p.b) for p in ident.pairs] == [("a", "b")]
    assert "almost proportional" in ident.pairs[0].explanation
    # the combination (b kept, a fixed, c free) is determined: se = σ/‖2s − its projection on c‖
    r = 2 * s - other * (other @ (2 * s)) / (other @ other)
    assert ident.pairs[0].combination_std_error == pytest.approx(0.1 / np.linalg.norm(r), rel=1e-8)
    (w,) = ident.weak
    assert set(w.weights) == {"a", "b"} and math.isinf(w.std_error)
    # the null direction: raising a by 1 % and lowering b by 0.5 % leaves the sensors unchanged
    assert w.weights["a"] == pytest.approx(1.0) and w.weights["b"] == pytest.approx(-0.5)
    assert "lowering b" in w.description
    assert not ident.identifiable("a") and ident.identifiable("c")


def test_fisher_rejects_bad_sigma():
    with pytest.raises(TnnError):
        fisher_analysis(np.ones((4, 1)), ["a"], sigma=0.0)


# ---------------------------------------------------------------------------------------------
# The compiled model (skipped until the compiler exists)
# ---------------------------------------------------------------------------------------------

compile_mod = pytest.importorskip("tnn_dsl.compiler.model", reason="the compiler is not there yet")

import tnn_dsl  # noqa: E402
from tnn_dsl.analysis.sensitivities import sensitivity  # noqa: E402
from tnn_dsl.compiler.model import compile as _compile_net  # noqa: E402
from tnn_dsl.studies.casestudy import network_path  # noqa: E402

C2K = 273.15
CASE_INPUTS = {"I": 1.5, "u1": 0.5, "Ta": 22 + C2K, "Tf1": 25 + C2K, "Tf2": 25 + C2K}


@pytest.fixture(scope="module")
def m1():
    return tnn_dsl.load(str(network_path("peltier_heatpipe/m1.thn")))


def _value(net, name, inputs, scale):
    """A parameter's SI value (constants, references to inputs or parameters), times its scale."""
    p = net.param(name)
    if isinstance(p.expr, Num):
        v = p.expr.value
    elif isinstance(p.expr, Ref):
        v = inputs[p.expr.name] if p.expr.name in inputs else _value(net, p.expr.name, inputs, scale)
    else:  # pragma: no cover - the case-study networks use only these
        raise NotImplementedError(p.expr)
    return v * scale.get(name, 1.0)


def direct_steady(net, inputs, scale):
    """The case study's steady state by one direct linear solve in numpy, written from the thesis's
    equations (the Peltier terms S·T·I are linear in the absolute temperature, so ``A T = b`` exactly)."""
    nodes = net.node_names
    idx = {n: i for i, n in enumerate(nodes)}
    n = len(nodes)
    A = np.zeros((n, n))
    b = np.zeros(n)
    fixed = {bd.name: _value(net, bd.temperature, inputs, scale) for bd in net.boundaries}

    def conduct(x, y, g):
        for p, q in ((x, y), (y, x)):
            if p in idx:
                A[idx[p], idx[p]] -= g
                if q in idx:
                    A[idx[p], idx[q]] += g
                else:
                    b[idx[p]] -= g * fixed[q]

    for link in net.links:
        v = _value(net, link.value, inputs, scale)
        conduct(link.a, link.b, 1.0 / v if link.form == "R" else v)
    for pe in net.peltiers:
        S = _value(net, pe.seebeck, inputs, scale)
        I = _value(net, pe.current, inputs, scale)
        R = _value(net, pe.resistance, inputs, scale)
        qh, qc = scale.get(f"{pe.name}.Q_hot", 1.0), scale.get(f"{pe.name}.Q_cold", 1.0)
        A[idx[pe.hot], idx[pe.hot]] += qh * S * I       # Q_hot = S·T_hot·I + ½R I²
        b[idx[pe.hot]] -= qh * 0.5 * R * I**2
        A[idx[pe.cold], idx[pe.cold]] -= qc * S * I     # Q_cold = −S·T_cold·I + ½R I²
        b[idx[pe.cold]] -= qc * 0.5 * R * I**2
        if pe.r_internal:
            conduct(pe.hot, pe.cold, 1.0 / _value(net, pe.r_internal, inputs, scale))
    for f in net.fluids:
        mcp = _value(net, f.mdot, inputs, scale) * _value(net, f.cp, inputs, scale)
        g = mcp * (1 - math.exp(-_value(net, f.ua, inputs, scale) / mcp)) * scale.get(f"{f.name}.Q", 1.0)
        A[idx[f.node], idx[f.node]] -= g
        b[idx[f.node]] -= g * _value(net, f.inlet, inputs, scale)
    T = np.linalg.solve(A, b)
    return np.array([T[idx[s.node]] for s in net.sensors])


def _richardson(f, h: float = 1e-3):
    """Central finite difference at 1 with one Richardson step: error O(h⁴) + roundoff ~ 1e-16·|f|/h."""
    d1 = (f(1 + h) - f(1 - h)) / (2 * h)
    d2 = (f(1 + h / 2) - f(1 - h / 2)) / h
    return (4 * d2 - d1) / 3


@pytest.fixture(scope="module")
def m1_reports(m1):
    return {b: sensitivity(m1, inputs=CASE_INPUTS, backend=b) for b in BACKENDS}


@pytest.fixture(params=BACKENDS)
def m1_report(request, m1_reports):
    return m1_reports[request.param]


def test_steady_scan_matches_direct_linear_solve(m1, m1_report):
    rep = m1_report
    checked = 0
    for p in rep.parameters:
        ys = np.array([direct_steady(m1, CASE_INPUTS, {p.name: a}) for a in rep.alphas])
        np.testing.assert_allclose(p.outputs, ys, rtol=1e-9, atol=1e-9, err_msg=p.name)
        slope = np.polyfit(rep.alphas, ys[:, 0], 1)[0]
        assert abs(p.slope[0] - slope) <= 1e-6 * abs(slope) + 1e-9, p.name
        # eq. 3.4 (autodiff) against a central finite difference of the direct solve
        fd = _richardson(lambda a: direct_steady(m1, CASE_INPUTS, {p.name: a}))
        assert abs(p.autodiff[0] - fd[0]) <= 1e-6 * abs(fd[0]) + 1e-8, (p.name, p.autodiff, fd)
        checked += 1
    assert checked >= 25
    # capacities do not enter the steady state
    for p in rep.parameters:
        if p.group == "capacity":
            assert abs(p.sensitivity) < 1e-9 and "steady state" in p.note


def test_peltier_terms_rank_first(m1_report):
    rep = m1_report
    # overall, the Peltier terms lead (then the fluid heat exchangers: heat flows and UA)
    assert [p.group for p in rep.parameters[:2]] == ["peltier", "peltier"], rep.ranking[:4]
    # among the thesis's Figure 5.3 candidates (resistances and Peltier terms) the first four are Peltier's,
    # then the heat-pipe and heat-sink resistances
    fig = [p for p in rep.parameters if p.group in ("peltier", "link")]
    assert all(p.group == "peltier" for p in fig[:4]), [(p.name, p.group) for p in fig[:5]]
    assert {"pe.Q_cold", "pe.seebeck", "pe.current", "pe.Q_hot"} == {p.name for p in fig[:4]}
    links = [p.name for p in fig if p.group == "link"]
    assert set(links[:3]) <= {"R_hp1", "R_hp2", "R_hs_amb", "R_pc_hx1"}, links[:3]
    # ṁ and cp enter only as ṁ·cp: identical sensitivities
    np.testing.assert_allclose(rep["f2.mdot"].slope, rep["f2.cp"].slope, rtol=1e-9)
    # the exact derivative ranks the same leaders (the slope is its ±20 % average)
    for p in rep.parameters[:6]:
        assert p.autodiff_sensitivity == pytest.approx(p.sensitivity, rel=0.2)
    assert all(r.verdict in ("candidate", "fix") for r in rep.recommendations)
    assert "give a data file" in next(r.reason for r in rep.recommendations if r.verdict == "candidate")


def test_same_results_on_both_backends(m1_reports):
    a, b = m1_reports["jax"], m1_reports["torch"]
    assert a.ranking == b.ranking
    for pa in a.parameters:
        pb = b[pa.name]
        np.testing.assert_allclose(pa.slope, pb.slope, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(pa.autodiff, pb.autodiff, rtol=1e-8, atol=1e-10)


# --- dynamic sensitivity (eq. 3.2) ---------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
def test_trajectory_sensitivity_matches_finite_differences(backend, m1):
    from tnn_dsl.analysis.sensitivities import _trajectory_sensitivity
    from tnn_dsl.compiler.backends.adapter import backend_of
    from tnn_dsl.data import Experiment

    model = _compile_net(m1, backend=backend, dtype="float64")
    n = 301
    t = np.arange(n)
    sig = {"I": np.where(t < 60, 1.0, 2.5), "u1": np.where(t < 150, 0.3, 0.8), "Ta": 22.0, "Tf1": 25.0, "Tf2": 25.0}
    u = np.column_stack([np.broadcast_to(sig[i.name], (n,)) + (C2K if i.is_temperature else 0.0) for i in m1.inputs])
    exp = Experiment(name="short", path="", t=np.arange(n, dtype=float), dt=1.0, inputs=u,
                     outputs=np.full((n, 1), np.nan), input_names=tuple(m1.input_names), output_names=("T_out",))
    base = model.init_params(seed=0)
    ops = backend_of(model)
    names = ["pe.seebeck", "C_hx2", "pe.Q_hot"]

    def with_scales(s):
        p = dict(base)
        for i, nm in enumerate(names):
            p[f"scale:{nm}"] = s[i]
        return p

    S = _trajectory_sensitivity(model, ops, with_scales, names, exp, "rk4", "steady")
    assert S.shape == (n, 1, 3)

    def run(scales):
        p = with_scales(ops.asarray(scales))
        T0 = model.steady_state(p, ops.asarray(u[0]))
        return ops.numpy(model.rollout(p, T0, ops.asarray(u), 1.0, integrator="rk4")[1])

    h = 1e-5
    for k in range(3):
        e = np.eye(3)[k] * h
        fd = (run(1 + e) - run(1 - e)) / (2 * h)
        np.testing.assert_allclose(S[:, :, k], fd, rtol=1e-5, atol=1e-7, err_msg=names[k])
    assert np.max(np.abs(S[:, 0, 1])) > 1e-3  # a capacity matters along a transient


# --- identifiability: two resistances in series, no sensor between them ------------------------

SERIES = """
network series "two resistances in series with no sensor between them"
units temperature = degC
input Q  : [W]
input Ta : temperature
boundary amb = Ta
node h "heater"      C = 400 J/K
node m "junction"    C = 2 J/K
node s "far block"   C = 900 J/K
source h = Q
R h -- m   = 0.5 K/W  as R_a
R m -- s   = 0.8 K/W  as R_b
R s -- amb = 2 K/W    as R_c
sensor T_h = h  column "T_h"
sensor T_s = s  column "T_s"
"""


@pytest.fixture(scope="module")
def series_net():
    return tnn_dsl.loads(SERIES, "series.thn")


def _series_data(net, tmp_path=None, seconds: int = 3 * 3600, dt: float = 10.0):
    from tnn_dsl.data import Experiment
    from tnn_dsl.studies.casestudy import step_sequence

    n = int(seconds / dt) + 1
    rng = np.random.default_rng(7)
    q = step_sequence(rng, n, 0.0, 40.0, hold=(300, 1500), dt=dt)
    u = np.column_stack([q, np.full(n, 20 + C2K)])
    import jax.numpy as jnp

    model = _compile_net(net, backend="jax", dtype="float64")
    p = model.init_params(seed=0)
    T0 = model.steady_state(p, jnp.asarray(u[0]))
    _, y = model.rollout(p, T0, jnp.asarray(u), dt, integrator="expeuler")
    y = np.asarray(y)
    exp = Experiment(name="series_prbs", path="", t=np.arange(n) * dt, dt=dt, inputs=u, outputs=y,
                     input_names=tuple(net.input_names), output_names=tuple(s.name for s in net.sensors))
    if tmp_path is None:
        return exp
    import pandas as pd

    path = tmp_path / "series.csv"
    pd.DataFrame({"time": exp.t, "Q": q, "Ta": 20.0, "T_h": y[:, 0] - C2K,
                  "T_s": y[:, 1] - C2K}).to_csv(path, index=False)
    return exp, str(path)


@pytest.fixture(scope="module")
def series_reports(series_net):
    exp = _series_data(series_net)
    return {b: sensitivity(series_net, exp, backend=b, sigma=0.05, integrator="expeuler") for b in BACKENDS}


@pytest.mark.parametrize("backend", BACKENDS)
def test_series_resistances_not_separately_identifiable(backend, series_reports):
    rep = series_reports[backend]
    assert set(rep.identifiability.params) == {"C_h", "C_m", "C_s", "R_a", "R_b", "R_c"}
    # C_m alone has almost no effect: its own weak direction
    assert any(list(w.weights) == ["C_m"] and "almost no effect" in w.description for w in rep.identifiability.weak)
    ident = rep.identifiability
    assert ident is not None
    pair = [p for p in ident.pairs if {p.a, p.b} == {"R_a", "R_b"}]
    assert pair, ident.table()
    pr = pair[0]
    assert pr.correlation < -0.95
    assert "sum" in pr.explanation and "no sensor" in pr.explanation and "node m" in pr.explanation
    assert pr.combination == "R_a + R_b" or pr.combination == "R_b + R_a"
    assert pr.combination_std_error < 0.01  # the sum is well determined
    assert not ident.identifiable("R_a") and not ident.identifiable("R_b")
    for name in ("R_c", "C_h", "C_s"):
        assert ident.identifiable(name), ident.table()
    assert not ident.identifiable("C_m")
    # a weak direction trades R_a against R_b (in the ratio of their values: 1 % of R_a = 0.625 % of R_b)
    (weakest,) = [w for w in ident.weak if set(list(w.weights)[:2]) == {"R_a", "R_b"}]
    assert abs(weakest.weights["R_b"] / weakest.weights["R_a"]) == pytest.approx(0.5 / 0.8, rel=0.05)
    assert np.sign(weakest.weights["R_a"]) != np.sign(weakest.weights["R_b"])
    verdict = {r.name: r for r in rep.recommendations}
    kept = [n for n in ("R_a", "R_b") if verdict[n].verdict == "learn"]
    assert len(kept) == 1
    other = ({"R_a", "R_b"} - set(kept)).pop()
    assert (verdict[other].verdict == "fix" and "confounded" in verdict[other].reason
            and "learn only one" in verdict[other].reason)
    assert all(verdict[n].verdict == "learn" for n in ("R_c", "C_h", "C_s"))
    assert verdict["C_m"].verdict == "fix" and "insensitive" in verdict["C_m"].reason


def test_series_same_on_both_backends(series_reports):
    a, b = series_reports["jax"], series_reports["torch"]
    assert a.ranking == b.ranking
    np.testing.assert_allclose(a.identifiability.fisher, b.identifiability.fisher, rtol=1e-7)
    for pa in a.parameters:
        assert pa.dynamic_rms == pytest.approx(b[pa.name].dynamic_rms, rel=1e-7, abs=1e-12)
    assert [(p.a, p.b) for p in a.identifiability.pairs] == [(p.a, p.b) for p in b.identifiability.pairs]
    assert [(r.name, r.verdict) for r in a.recommendations] == [(r.name, r.verdict) for r in b.recommendations]


def test_cli_sensitivity(tmp_path, capsys, series_net):
    from tnn_dsl.cli import main

    thn = tmp_path / "series.thn"
    thn.write_text(SERIES)
    _, csv = _series_data(series_net, tmp_path, seconds=3600)
    out_json, png = tmp_path / "s.json", tmp_path / "s.png"
    rc = main(["sensitivity", str(thn), csv, "--sigma", "0.05", "--integrator", "expeuler",
               "--json", str(out_json), "--plot", str(png)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "Recommendation" in text and "R_a" in text and "Identifiability" in text
    d = json.loads(out_json.read_text())
    assert d["ranking"][0] and d["identifiability"]["correlated_pairs"]
    assert png.stat().st_size > 1000
    # no data and a missing input: a friendly error, exit 1
    rc = main(["sensitivity", str(thn), "--inputs", "Q=10"])
    err = capsys.readouterr().err
    assert rc == 1 and "Ta" in err and "hint:" in err
    rc = main(["sensitivity", str(thn), "--inputs", "Q=10", "Ta=20", "--json", "-"])
    d = json.loads(capsys.readouterr().out)
    assert rc == 0 and d["inputs"]["Ta"] == pytest.approx(20 + C2K)
