"""The doctor's wall-clock budget (``tnn_dsl.diagnose(..., budget_s=)``, ``tnnc diagnose --budget``): no piece of work
starts once it is spent, and the score test stops between its chunks.

Issue 18: the torch doctor with ``--budget 60`` on the case study ran 117 s: its score test (51 s) started before the
deadline and ran to its end, and the round's first fit (18 s) started after it. Here a clock of the session's own is
moved past the deadline at a chosen call (the real one keeps running for the engines, whose fits see a deadline far
away), so the test says exactly where the work stopped, whatever the machine's speed."""

from __future__ import annotations

import os
import time
import types

import pytest

import tnn_dsl
import tnn_dsl.doctor.session as session_mod
from tnn_dsl.doctor.engine import _Engine
from tnn_dsl.studies.planted import plant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}  # heater fraction (SI of [%])
BUDGET_S = 1e5  # never reached by the real clock: only the session's clock, moved on, spends it


class _SessionClock:
    """``time`` for the session module: the real monotonic clock plus an offset the test sets."""

    def __init__(self):
        self.offset = 0.0

    def monotonic(self) -> float:
        return time.monotonic() + self.offset

    def spend(self) -> None:
        self.offset = 10 * BUDGET_S


@pytest.fixture
def clock(monkeypatch):
    c = _SessionClock()
    monkeypatch.setattr(session_mod, "_time", types.SimpleNamespace(monotonic=c.monotonic))
    return c


def _planted(backend):
    """TCLab with ``U1`` depending on ``T(h1)``, 200 training and 100 held-out samples: enough for the score test to
    rank the planted dependence first (r² 0.88 on both backends) and to run in two chunks; torch's doctor simulates
    step by step, so 400 + 300 samples had cost its two tests 17–19 s each (5–6 s now, 2026-12-07)."""
    net = tnn_dsl.load(TCLAB)
    pl = plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.01, seed=3, n_train=200, n_val=100,
               hold=(20, 150), backend=backend)
    return net, pl


def _count_fits_after(monkeypatch, clock) -> list[int]:
    """Counts the engines' fits started while the session's budget is spent."""
    late = [0]
    real_fit = _Engine.fit

    def fit(self, *a, **k):
        if clock.offset > 0:
            late[0] += 1
        return real_fit(self, *a, **k)

    monkeypatch.setattr(_Engine, "fit", fit)
    return late


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_the_score_test_stops_between_chunks_when_the_budget_is_spent(backend, clock, monkeypatch):
    """The budget runs out while the score test's second chunk of candidate columns is computed: no third chunk is
    computed, no candidate is ranked or fitted, and the verdict says where the budget stopped the work."""
    net, pl = _planted(backend)
    chunks = [0]
    real_point = _Engine.point_derivs

    def point_derivs(self, *a, **k):  # one call per chunk of the score test's candidate columns
        chunks[0] += 1
        if chunks[0] == 2:
            clock.spend()
        return real_point(self, *a, **k)

    monkeypatch.setattr(_Engine, "point_derivs", point_derivs)
    late = _count_fits_after(monkeypatch, clock)
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=2, mlp_check=False, backend=backend,
                         budget_s=BUDGET_S)
    assert chunks[0] == 2, chunks
    assert late[0] == 0
    assert not d.accepted and not d.scores and not d.findings
    where = "in round 1's score test"
    assert d.verdict.startswith(f"not decided: the budget ({BUDGET_S:g} s) ran out {where}"), d.verdict
    assert d.to_dict()["budget"] == {"seconds": BUDGET_S, "ran_out": where, "interrupted": False}


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_no_candidate_fit_starts_once_the_budget_is_spent(backend, clock, monkeypatch):
    """The budget runs out just as the score test ends: its ranking is reported, and no fit starts — the round's
    first fit used to run regardless."""
    net, pl = _planted(backend)
    real_score = session_mod._score_forced

    def score_forced(*a, **k):
        out = real_score(*a, **k)
        clock.spend()
        return out

    monkeypatch.setattr(session_mod, "_score_forced", score_forced)
    late = _count_fits_after(monkeypatch, clock)
    lines: list[str] = []
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=2, mlp_check=False, backend=backend,
                         budget_s=BUDGET_S, progress=lines.append)
    assert late[0] == 0
    assert d.scores and d.scores[0]["r2"] > 0.5, d.scores[:1]  # the planted dependence is there to be fitted
    assert not d.accepted and not d.findings
    where = "in round 1, before its candidates were fitted"
    assert d.verdict.startswith(f"not decided: the budget ({BUDGET_S:g} s) ran out {where}"), d.verdict
    assert any("no candidate is fitted" in line for line in lines), lines


def test_the_score_tests_thread_ahead_hands_on_results_errors_and_stops():
    """The score test's chunks computed one ahead on a thread of their own (issue 18): results in order, an error
    raised where its chunk is asked for, a stop before a chunk ends the work there (None), and closing early lets
    the thread go."""
    from tnn_dsl.doctor.scoring import _Ahead

    def make(part):
        if part == [3]:
            raise ValueError("chunk 3 failed")
        return (part[0] * 2,)

    ahead = _Ahead(make, [[1], [2], [3], [4]])
    assert ahead.next() == (2,) and ahead.next() == (4,)
    with pytest.raises(ValueError, match="chunk 3"):
        ahead.next()
    ahead.close()
    calls = [0]

    def stop():
        calls[0] += 1
        return calls[0] > 1  # spent after the first chunk started

    ahead = _Ahead(make, [[1], [2], [4]], stop)
    assert ahead.next() == (2,) and ahead.next() is None
    ahead.close()
    ahead = _Ahead(make, [[1], [2], [4], [5]])  # closed with results still to come
    ahead.close()
    assert not ahead._thread.is_alive()
