"""The model doctor's hidden-effect suite (issue 6 acceptance), as tests.

One known deficiency is planted in simulated data (``benchmarks/diagnose_suite.py`` defines the networks, the
planted effects and the scoring; ``tnn_dsl.studies.planted.plant`` simulates candidate kinds, edited ``.thn`` truths
the structural ones); ``tnn_dsl.diagnose`` sees only the nominal network and the data.

* Fast seeded variants (run in CI): every kind once on the small TCLab-like board
  (``tests/hidden_nets/tclab_board.thn``, fixed realistic values), sensor noise 0.01 K, short data. Each
  asserts that the doctor's first answer is the planted cause (or a candidate with identical equations, listed
  in the suite with its reason), that it is accepted, that the dependence variable is named where there is
  one, and that the held-out MAE is at least halved. The null run asserts that nothing is accepted. A kind
  the doctor cannot find yet is ``xfail(strict=True)`` with the reason, so that it fails loudly once fixed.
* The full grid (three networks × every kind × noise 0, 0.01, 0.05 K × two seeds + null runs) is
  ``@pytest.mark.slow`` and checks the issue's targets on the totals; the same grid is the benchmark
  ``python benchmarks/diagnose_suite.py`` whose table is in BENCHMARKS.md.

The runs share networks and data shapes, so most of their compilations come from the test session's JAX
compilation cache (``conftest.py``). This module used to switch to a cache of its own, which JAX ignored once the
worker had compiled anything (it opens its cache once per process) and which, had this module compiled first,
would have cut that worker off from the session's cache.
"""

from __future__ import annotations

import importlib.util
import os
import re
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _load_suite():
    spec = importlib.util.spec_from_file_location("diagnose_suite",
                                                  os.path.join(ROOT, "benchmarks", "diagnose_suite.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("diagnose_suite", mod)  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


S = _load_suite()
CASES = {c.name: c for c in S.CASES}


# ---------------------------------------------------------------------------------------------
# the suite's own machinery (cheap, no diagnosis)
# ---------------------------------------------------------------------------------------------


def test_every_candidate_kind_is_planted_on_every_network():
    kinds = {"dependence", "heat_load", "missing_link", "radiation", "sensor_offset", "wrong_constant",
             "unused_column", "sensor_lag", "thermal_mass", "null"}
    for net in ("tclab", "building", "casestudy"):
        have = {c.kind for c in S.CASES if c.net.split("_")[0] == net.split("_")[0]}
        # a heat capacity behind a source needs a source driven by an input: the case study has none
        assert kinds | ({"source_mass"} if net != "casestudy" else set()) <= have, (net, kinds - have)


def test_planted_candidates_exist_in_the_networks():
    """Every planted candidate and every listed equivalent is a candidate the doctor builds (a renamed
    candidate key would otherwise turn the suite into silent misses)."""
    import tnn_dsl
    from tnn_dsl.doctor.candidates import build_extended

    for c in S.CASES:
        if c.plant is None:
            continue
        spec = S.NETWORKS[c.net]
        net = tnn_dsl.load(spec.path)
        varying = [n for n in net.input_names if spec.bounds[n][1] > spec.bounds[n][0]]
        keys = {x.key for x in build_extended(net, varying).candidates}
        kind, target, dep, _ = c.plant
        assert f"{kind}:{target}:{dep or ''}" in keys, c.name
        assert ":".join(c.truth) in keys, c.name
        for e in c.equivalent:
            if e[2] not in ("fan", "Pocc", "pump"):  # column-driven ones exist only with the column
                assert ":".join(e) in keys, (c.name, e)


@pytest.mark.parametrize("name", ["tclab/sensor_lag", "tclab/thermal_mass", "building/thermal_mass",
                                  "casestudy/thermal_mass", "tclab/source_mass", "building/source_mass"])
def test_structural_truths_differ_from_the_model_but_keep_its_steady_state(name):
    """The edited truths are valid networks whose outputs differ from the nominal model's in transients
    (a lag, an extra mass) but, being series elements, not at steady state."""
    import numpy as np

    import tnn_dsl

    c = CASES[name]
    spec = S.NETWORKS[c.net]
    net = tnn_dsl.load(spec.path)
    truth = (tnn_dsl.load(c.edit[1]) if c.edit[0] == "truth"
             else tnn_dsl.loads(S._edit_text(open(spec.path, encoding="utf-8").read(), c.edit), "truth.thn"))
    u = S._inputs(spec, net.input_names, 6 * spec.hold[1], 7)  # several steps
    rng = np.random.default_rng(0)
    y0 = S._simulate(net, u, spec.dt, 0.0, rng)
    y1 = S._simulate(truth, u, spec.dt, 0.0, rng)
    assert np.max(np.abs(y1 - y0)) > 0.05
    if c.edit[0] != "truth":  # same total resistance: same steady state
        from tnn_dsl.compiler.model import compile as _compile

        m0, m1 = _compile(net, backend="numpy"), _compile(truth, backend="numpy")
        p0, p1 = m0.init_params(), m1.init_params()
        s0 = m0.outputs(p0, m0.steady_state(p0, u[0]), u[0])
        s1 = m1.outputs(p1, m1.steady_state(p1, u[0]), u[0])
        assert np.allclose(s0, s1, atol=1e-8)


def test_scoring_counts_identical_equivalents_and_nulls():
    from types import SimpleNamespace as NS

    def diag(findings, before=1.0, after=0.1):
        return NS(findings=findings, accepted=[f for f in findings if f.accepted],
                  baseline={"val_mae": before}, extended={"val_mae": after}, timings={"total": 1.0})

    def f(kind, target, dep, accepted, rank=1, caution=()):
        twins = [{"key": k, "separated": sep} for k, sep in caution]
        return NS(kind=kind, target=target, depends_on=dep, accepted=accepted, rank=rank, round=1,
                  evidence={"indistinguishable_from": twins})

    c = CASES["tclab/heat_load"]
    r = S.score(c, diag([f("param_dependence", "Q_src_h2", ["Q1"], True)]), 0.01)
    assert not r["first"] and r["first_eq"] and r["accepted"] and r["dep"] and r["ratio"] == pytest.approx(10)
    r = S.score(c, diag([f("heat_load", "Q[h1]", ["Q1"], False, 1), f("heat_load", "Q[h2]", ["Q1"], False, 2)],
                        after=1.0), 0.01)
    assert not r["first_eq"] and not r["accepted"] and r["dep"]  # first answer is the best fit of round 1
    r = S.score(CASES["tclab/null"], diag([f("heat_load", "Q[h1]", [], True)]), 0.01)
    assert r["false_accept"]
    md = S.table([r, S.score(c, diag([f("heat_load", "Q[h2]", ["Q1"], True)]), 0.0)])
    assert "false acceptance 100 %" in md and "| tclab | heat_load | 0 | 1 | 100 % (1/1)" in md
    # a first answer whose caution names the truth (the held-out run did not separate them) is reported apart
    cs = CASES["casestudy/dependence"]
    r = S.score(cs, diag([f("param_dependence", "R_hp2", ["u1"], True, caution=[("param_dependence:R_hp1:u1",
                                                                                  False)])]), 0.01)
    assert not r["first_eq"] and r["first_or_caution"]
    r = S.score(cs, diag([f("param_dependence", "R_hp2", ["u1"], True, caution=[("param_dependence:R_hp1:u1",
                                                                                  True)])]), 0.01)
    assert not r["first_or_caution"]
    assert "named in the first answer's caution | 0 % (0/1)" in S.table([r]).replace(
        " (the data do not tell them apart)", "")


# ---------------------------------------------------------------------------------------------
# fast seeded variants: every kind once on the TCLab-like board (CI)
# ---------------------------------------------------------------------------------------------

_NOT_YET = {
    # kinds the doctor has no candidate for yet (see docs/architecture.md, "Diagnosis")
}
_MISSES: dict[str, str] = {
    # kinds the doctor has candidates for but misses on the fast run; the reason is what the run showed
}

FAST = ["tclab/dependence", "tclab/heat_load", "tclab_nolink/missing_link", "tclab/radiation", "tclab/sensor_offset",
        "tclab/wrong_constant", "tclab/unused_column", "tclab/sensor_lag", "tclab/thermal_mass", "tclab/source_mass",
        "tclab/column_dependence", "tclab/quadratic_load"]


# known misses that take 30 s or more each to confirm run with the slow grid, not in CI
_SLOW_MISSES: set[str] = set()


def _marks(name):
    why = _NOT_YET.get(name) or _MISSES.get(name)
    marks = [pytest.mark.xfail(strict=True, reason=why)] if why else []
    if name in _SLOW_MISSES:
        marks.append(pytest.mark.slow)
    return marks


@pytest.mark.parametrize("name", [pytest.param(n, marks=_marks(n)) for n in FAST])
def test_fast_planted_effect_is_found(name):
    c = CASES[name]
    r = S.run_case(c, noise=0.01, seed=0, quick=True, keep=True)
    msg = f"{name}: first answer {r['first_answer']} (accepted {r['first_accepted']}); {r['verdict']}"
    assert r["first_eq"], msg
    assert r["accepted"], msg
    if "dep" in r:
        assert r["dep"], msg
    if "shape" in r:  # a curved truth: its square is among the accepted findings (the curvature look-ahead)
        assert r["shape"], msg
    assert r["above_noise"] and r["ratio"] >= 2.0, f"{msg}; MAE {r['mae_before']:.3g} → {r['mae_after']:.3g} K"
    if c.edit and c.edit[0] == "lag":  # a structural finding is written: the extension edits the sensor's line, τ
        import tnn_dsl  # as planted (the CI check of test_diagnose.py::test_planted_sensor_lag_is_found_and_written)

        d = r["diagnosis"]
        assert "lag" in d.verdict and c.edit[1] in d.verdict, msg
        ext = tnn_dsl.loads(d.extended_text, "extended.thn")
        sensor = next(s for s in ext.sensors if s.name == c.edit[1])
        assert sensor.lag is not None and ext.param(sensor.lag).value == pytest.approx(c.edit[2], rel=0.1), msg


@pytest.mark.slow  # 85 s; its rule's fast variant: test_doctor_initial.py::test_a_fitted_initial_states_start_up…
def test_a_pump_column_changing_a_heat_exchanger_is_found_on_the_case_study():
    """A pump column changing the heat exchanger's UA (noise-free quick run). ``f2.mdot``, ``f2.cp`` and ``f2.UA``
    depending on it have the same linearised correction, so one of them is fitted for all (the others are fitted in
    its place when its fit is not physical, and beside it when it leads its round: ``fit_twins``); before the start-up
    transient of a fitted initial state was left out of the plausibility ranges, every one was rejected (the
    Peltier's cold side at 661 °C in the first seconds) and nothing was accepted; while only the twin round-off put
    first was fitted, ``f2.mdot`` was accepted at ÷1.47. The answer names the heat exchanger f2 depending on the
    pump, and pays."""
    r = S.run_case(CASES["casestudy/column_dependence"], noise=0.0, seed=0, quick=True)
    first = r["first_answer"] or ""
    named = {f"param_dependence:f2.{p}:pump" for p in ("UA", "mdot", "cp")}
    assert r["first_accepted"] and first in named, r["verdict"]
    assert r["ratio"] >= 2.0, r


def test_a_wrong_constant_far_from_its_written_value_is_named_not_a_dependence():
    """Bacher & Madsen's one-state building with ``Ria`` 40 % off: the score test at the written value ranks the
    wrong constant 15th (the linearisation is poor that far out) and the shortlist's ``Ria`` depending on T(ti) fits
    with a slope of 3e-6; the sub-model of that fit (``fit_nested``) is fitted to convergence and the compensation
    guard prefers it (k = 1)."""
    r = S.run_case(CASES["building/wrong_constant"], noise=0.01, seed=0, quick=True)
    assert r["first"] and r["accepted"], r["verdict"]
    assert r["ratio"] >= 2.0, r


@pytest.mark.slow  # 35–135 s; the look-ahead's fast variant: test_fast_planted_effect_is_found[tclab/quadratic_load]
def test_a_load_growing_with_the_square_of_the_current_is_found_on_the_case_study():
    """``1 W/A²·I²`` at hx2: the line in I alone does not pay (0.134 K against 0.093 K before), the resistances
    depending on I that the score test ranks first diverge; the look-ahead fits the line with its square and accepts
    the pair: a heat load at hx2 in I and I², the square's coefficient within 10 % of the planted 1 W/A²."""
    r = S.run_case(CASES["casestudy/quadratic_load"], noise=0.01, seed=0, quick=True)
    assert r["first_eq"] and r["accepted"] and r["shape"], r["verdict"]
    coef = float(re.search(r"([0-9.]+)·\(I − [0-9.]+\)² W", r["verdict"]).group(1))
    assert coef == pytest.approx(1.0, rel=0.1), r["verdict"]
    assert r["ratio"] >= 2.0, r


@pytest.mark.slow  # 60 s; the rival rule's fast variant: test_doctor_selection.py (the guard it feeds)
def test_a_sensor_offset_beats_the_constant_heat_loads_that_stand_in_for_it():
    """A 0.3 K offset on the case study's only sensor under 0.05 K noise: constant heat loads at hs, ph and hx2 fit
    as well; the offset, ranked 31st by the score test, is fitted as a more physical rival before a heat load is
    accepted, and the guard takes it — also against a heat load at hs depending on T(base) (k = 2), 0.0432 K held out
    against the offset's 0.0521 K but no better on the training rows (4.39995 against 4.4015 K²): a miss from
    2026-12-06 to 2026-12-08, when a smaller rival that ties on the training rows became within noise
    (``selection._ties_on_training``)."""
    r = S.run_case(CASES["casestudy/sensor_offset"], noise=0.05, seed=0, quick=True)
    assert r["first"] and r["accepted"], r["verdict"]


def test_fast_null_data_set_gives_no_finding():
    r = S.run_case(CASES["tclab/null"], noise=0.01, seed=0, quick=True)
    assert not r["false_accept"], r["verdict"]
    assert r["mae_after"] == pytest.approx(r["mae_before"])


# ---------------------------------------------------------------------------------------------
# the full grid (slow; the benchmark runs the same grid and writes BENCHMARKS.md)
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_full_hidden_effect_grid_meets_the_targets():
    rows = [S.run_case(c, noise, seed, quick=False) for c in S.CASES for noise in S.NOISES for seed in range(2)]
    eff = [r for r in rows if r["kind"] != "null"]
    nul = [r for r in rows if r["kind"] == "null"]
    table = S.table(rows)
    dep = [r["dep"] for r in eff if "dep" in r]
    assert sum(r["first_eq"] for r in eff) >= 0.9 * len(eff), table
    assert sum(dep) >= 0.8 * len(dep), table
    assert sum(not r["false_accept"] for r in nul) >= 0.95 * len(nul), table
    assert all(r["ratio"] >= 2 for r in eff if r["above_noise"]), table
