"""The model doctor on the thesis case study from M1 (issue 17's acceptance): from ``m1.thn`` (the heat pipe's
``learn R_hp1, R_hp2, R_hpa as const``) and the generated data (`../shared/spec/case-study.md`: all three
heat-pipe resistances depend on ``u1`` and two on temperature), the extension names only heat-pipe elements with
``u1``, pays at least 5-fold on the held-out set, and every value is within 50 % of the truth or reported as not
identifiable one by one.

The full 4 h / 2 h data sets are slow (about 4 min, marked slow); the CI variant (one round) checks the names, the
gain and that every value comes with a standard error on 80 / 40 minutes of data, which pin the law's shape but not
the split between the series resistances (R_hp1 0.203 ± 0.107 and R_hp2 0.193 ± 0.113 K/W there, both reported as
poorly determined; their sum 0.396 against the truth's 0.4; 2026-12-03, commit c439e3a).
"""

from __future__ import annotations

import os

import pytest

import tnn_dsl
from tnn_dsl.studies.casestudy import generate_case_study

HERE = os.path.dirname(os.path.abspath(__file__))
M1 = os.path.join(os.path.dirname(HERE), "networks", "peltier_heatpipe", "m1.thn")

# case-study.md: the truth at u1 = 0.5 and 25 °C, and d/du1 (K/W per unit of u1)
TRUTH = {"R_hp1": (0.2, 0.2 * 1.5), "R_hp2": (0.2, 0.2 * 1.2), "R_hpa": (10.0, 10.0 * 0.3),
         "pe.seebeck": (0.05, None), "pe.resistance": (2.0, None)}


def _close_or_said(name: str, value: float, truth: float, unsure: set[str]) -> bool:
    return abs(value - truth) <= 0.5 * abs(truth) or name in unsure


@pytest.mark.parametrize("length", [pytest.param("short", id="80min"),
                                    pytest.param("full", id="4h", marks=pytest.mark.slow)])
def test_m1_extension_names_the_heat_pipe_with_u1_pays_and_says_what_it_cannot_tell(length, tmp_path):
    durations = (80 * 60.0, 40 * 60.0, 60.0) if length == "short" else None
    generate_case_study(tmp_path / "cs", widen=(), n_ood=0, durations=durations)
    # 80 min (noise σ ≈ 1e-4 K) also pin the heat pipe's temperature dependence, which the truth has (−0.02/K on
    # R_hp1 and R_hp2): a second round names the three resistances depending on T(hp) too, and a third took a
    # conduction path pc–hp (0.0014 → 0.00063 K, p = 0.054, confirmed by halving; 2026-11-26), a compensation the
    # 4 h data do not show. The fast variant runs round 1 (the u1 law, the finding this test is about: 28 s alone
    # against 40 s for two rounds, 2026-12-02); the 4 h one runs them all. Rounds after the first are covered by
    # tests/test_doctor_rounds.py and the hidden-effect suite's look-ahead cases.
    rounds = 1 if length == "short" else 4
    d = tnn_dsl.diagnose(M1, [str(tmp_path / "cs" / "train.csv")], [str(tmp_path / "cs" / "val.csv")],
                         mlp_check=False, output=str(tmp_path / "m1x.thn"), max_rounds=rounds)
    acc = d.accepted
    assert acc, d.summary()
    assert len({f.words for f in acc}) == len(acc), d.summary()  # no finding said twice
    # only heat-pipe elements, every one on u1 (one round on 80 min; four on 4 h, which name u1 only)
    allowed = [["u1"]]
    assert acc[0].depends_on == ["u1"], d.summary()
    for f in acc:
        assert f.kind == "param_dependence" and f.depends_on in allowed, d.summary()
        assert set(f.target.split(", ")) <= {"R_hp1", "R_hp2", "R_hpa"}, d.summary()
    written = tnn_dsl.load(str(tmp_path / "m1x.thn"))
    for fn in written.learned:
        assert {t.name for t in fn.targets} <= {"R_hp1", "R_hp2", "R_hpa"}, fn
        assert {i.name for i in fn.inputs} <= {"u1"}, fn
    assert d.baseline["val_mae"] / d.extended["val_mae"] >= 5, d.summary()
    u = d.extended["uncertainty"]
    assert all(e["se"] > 0 or e["status"] == "not identifiable" for e in u["estimates"]), u
    if length == "short":
        return  # 80 minutes pin the law's shape, not the split of the series resistances: the values need 4 h
    # each value within 50 % of the truth, or named among what these sensors cannot determine one by one
    unsure = {e["name"] for e in u["estimates"] if e["status"] != "ok"}
    for s in u["statements"]:
        if "correlated" in s or "not identifiable" in s:
            head = s.split(" are correlated")[0].split(" are not identifiable")[0].split(" is not identifiable")[0]
            unsure |= {part.strip() for part in head.replace(" and ", ", ").split(", ")}
    est = {e["name"]: e for e in u["estimates"]}
    checked = 0
    for name, e in est.items():
        for target, (level, slope) in TRUTH.items():
            if name == target or name.startswith(f"{target} at "):
                assert _close_or_said(name, e["value"], level, unsure), (name, e, d.summary())
                checked += 1
            elif slope is not None and name == f"d{target}/du1":
                assert _close_or_said(name, e["value"], slope, unsure), (name, e, d.summary())
                checked += 1
    assert checked >= 5, sorted(est)


@pytest.mark.slow
def test_a_law_grown_over_two_rounds_is_told_once(tmp_path):
    """Dependences only, on 80 / 40 minutes: R_hp1 is found depending on T(hx1) in one round and on u1 in a later
    one (one learned function, grown). The earlier finding keeps the words it was accepted with and points to the
    later one, which gives the final law: before, both printed the final law, word for word (slow, ~2 min; the CI
    case-study test checks that no accepted finding is said twice)."""
    generate_case_study(tmp_path / "cs", widen=(), n_ood=0, durations=(80 * 60.0, 40 * 60.0, 60.0))
    d = tnn_dsl.diagnose(M1, [str(tmp_path / "cs" / "train.csv")], [str(tmp_path / "cs" / "val.csv")],
                         mlp_check=False, kinds=("param_dependence",))
    acc = d.accepted
    assert len({f.words for f in acc}) == len(acc), d.summary()
    grown = [f for f in acc if "(grown in round" in f.words]
    assert grown, d.summary()
    for f in grown:
        later = next(g for g in acc if g.round > f.round and g.target == f.target)
        assert f"(grown in round {later.round}: the final law of {f.target} is given there)" in f.words
        assert later.words != f.words
