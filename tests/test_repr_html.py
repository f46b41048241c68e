"""Notebook views: ``_repr_html_`` of the diagnosis, the sensitivity report and the trained model.

Each view must be a balanced HTML fragment, show the numbers of the text summary, escape user text and
never raise (a broken view falls back to ``<pre>`` of the text summary)."""

from __future__ import annotations

import html
import math
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.analysis import residuals as R
from tnn_dsl.analysis.sensitivities import sensitivity
from tnn_dsl.data import Experiment
from tnn_dsl.doctor import Diagnosis, Finding
from tnn_dsl.fit import TrainedModel

SCRIPT = "<script>alert(1)</script>"
VOID = {"br", "hr", "img", "meta", "input", "link", "wbr", "col", "source"}
C2K = 273.15
SERIES = """
network series
units temperature = degC
input Q  : [W]
input Ta : temperature
boundary amb = Ta
node h  C = 400 J/K
node m  C = 2 J/K
node s  C = 900 J/K
source h = Q
R h -- m   = 0.5 K/W  as R_a
R m -- s   = 0.8 K/W  as R_b free
R s -- amb = 2 K/W    as R_c free
sensor T_h = h  column "T_h"
sensor T_s = s  column "T_s"
"""


class _Balance(HTMLParser):
    """Records every start tag and fails on an end tag that does not close the innermost open one."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.tags: list[str] = []
        self.errors: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        self.tags.append(tag)
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag: str) -> None:
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1] if self.stack else 'nothing'}")
        else:
            self.stack.pop()

    def handle_data(self, data: str) -> None:
        self.text.append(data)


def check_html(fragment: str) -> str:
    """Assert ``fragment`` is balanced and self-contained; returns its text (entities decoded)."""
    assert isinstance(fragment, str) and fragment
    p = _Balance()
    p.feed(fragment)
    p.close()
    assert not p.errors, p.errors
    assert not p.stack, f"unclosed: {p.stack}"
    assert "script" not in p.tags and "link" not in p.tags and "style" not in p.tags
    assert "table" in p.tags or "pre" in p.tags
    return " ".join(p.text)


def _numbers(fragment_text: str, *values: float, digits: int = 4) -> None:
    for v in values:
        assert f"{v:.{digits}g}" in fragment_text, (f"{v:.{digits}g}", fragment_text)


# --- the diagnosis -----------------------------------------------------------------------------


def _diagnosis(words: str = "U1 depends on T(h1)") -> Diagnosis:
    """A diagnosis as ``diagnose`` assembles it (two rounds: one accepted, one rejected), built by hand."""
    res = R.ResidualSummary(errors={"T1": {"mae": 0.31, "max": 1.2, "n": 100}},
                            whiteness={"T1": {"white": False, "ljung_box_p": 1.3e-9}}, sigma={"T1": 0.0213})
    acc = Finding(rank=1, kind="param_dependence", target="U1", depends_on=["T(h1)"],
                  clause="learn U1 as linear(h1)", val_mae_after=0.0617, val_max_after=0.25,
                  evidence={"val_mae_before": 0.3125, "p_value": 2.5e-7, "n_eff": 412.0,
                            "indistinguishable_from": [{"candidate": "R_hp2 depends on u1", "cos": 0.987}]},
                  accepted=True, words=words, round=1)
    rej = Finding(rank=2, kind="heat_load", target="Q[h2]", depends_on=["Q2"], clause="learn Q[h2] as linear(Q2)",
                  val_mae_after=0.0611, val_max_after=0.24,
                  evidence={"val_mae_before": 0.0617, "p_value": 0.43, "n_eff": 380.0, "reason": "no gain"},
                  accepted=False, words="a heat load on h2 depending on Q2", round=2)
    return Diagnosis(
        network="tclab", baseline={"val_mae": 0.3125, "val_max": 1.21, "train_mae": 0.298}, residuals=res,
        scores=[{"rank": 1, "words": words, "k": 1, "r2": 0.912, "p": 1e-30}], findings=[acc, rej],
        extended_text="network tclab\n", extended_file=None,
        extended={"val_mae": 0.0617, "val_max": 0.25, "clauses": ["learn U1 as linear(h1)"], "form": "linear"},
        diff="", verdict=words, left="white noise")


def test_diagnosis_view_shows_the_summary_numbers() -> None:
    d = _diagnosis()
    text = check_html(d._repr_html_())
    summary = d.summary()
    for v in (0.3125, 0.0617, 1.21, 0.298):
        assert f"{v:.4g}" in summary
    _numbers(text, 0.3125, 0.0617, 1.21, 0.298, 0.0611)
    _numbers(text, 2.5e-7, 0.43, 1.3e-9, digits=2)
    for s in ("U1 depends on T(h1)", "T(h1)", "ACCEPTED", "rejected", "learn U1 as linear(h1)", "no gain",
              "R_hp2 depends on u1", "white noise", "NOT white"):
        assert s in text, s
    assert "warnings" in text and "extension" in text


def test_diagnosis_summary_unchanged_by_the_row_functions() -> None:
    s = _diagnosis().summary()
    assert "  [ACCEPTED] round 1: U1 depends on T(h1)" in s
    assert "      held-out MAE 0.3125 → 0.0617 K, held-out test p = 2.5e-07 (N_eff = 412)" in s
    assert "      held-out MAE 0.0617 → 0.0611 K, held-out test p = 0.43 (N_eff = 380); no gain" in s
    assert "      caution: to first order the data cannot tell this apart from R_hp2 depends on u1 (|cos| = 0.987)" in s
    assert "  residual T1: NOT white (Ljung–Box p = 1.3e-09), noise σ ≈ 0.0213 K" in s


def test_diagnosis_view_escapes_user_text() -> None:
    out = _diagnosis(words=SCRIPT)._repr_html_()
    assert SCRIPT not in out and html.escape(SCRIPT) in out
    check_html(out)


def test_diagnosis_view_falls_back_to_the_summary(monkeypatch: pytest.MonkeyPatch) -> None:
    d = _diagnosis(words=SCRIPT)

    def broken() -> str:
        raise KeyError("boom")

    monkeypatch.setattr(d, "_html", broken)
    out = d._repr_html_()
    assert out.startswith("<pre>") and html.escape(SCRIPT) in out and SCRIPT not in out
    assert html.unescape(out[5:-6]) == d.summary()
    d.baseline = {}  # the summary fails too: still a string, no exception
    assert d._repr_html_().startswith("<pre>")


def test_diagnosis_view_of_a_real_run() -> None:
    from tnn_dsl.studies.planted import plant

    net = tnn_dsl.load(str(Path(__file__).parents[1] / "networks" / "tclab" / "tclab.thn"))
    pl = plant(net, {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}, None, noise=0.02, seed=5, n_train=600, n_val=300,
               hold=(30, 200))
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=1, max_rounds=1, mlp_check=False)
    text = check_html(d._repr_html_())
    _numbers(text, d.baseline["val_mae"], d.baseline["val_max"], d.baseline["train_mae"])
    assert d.verdict in text and "tclab" in text
    for r in d.finding_rows():
        assert r["cause"] in text


# --- the sensitivity report ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def series_net() -> tnn_dsl.Network:
    return tnn_dsl.loads(SERIES, "series.thn")


def _series_data(net: tnn_dsl.Network) -> Experiment:
    n, dt = 241, 10.0
    q = np.where((np.arange(n) // 30) % 2 == 0, 30.0, 5.0)
    u = np.column_stack([q, np.full(n, 20 + C2K)])
    model = tnn_dsl.compile(net, backend="numpy")
    p = model.init_params(seed=0)
    _, y = model.rollout(p, model.steady_state(p, u[0]), u, dt, integrator="expeuler")
    return Experiment(name="steps", path="", t=np.arange(n) * dt, dt=dt, inputs=u, outputs=np.asarray(y),
                      input_names=tuple(net.input_names), output_names=tuple(s.name for s in net.sensors))


@pytest.fixture(scope="module", params=["jax", "torch"])
def series_report(request: pytest.FixtureRequest, series_net: tnn_dsl.Network) -> object:
    return sensitivity(series_net, _series_data(series_net), backend=request.param, sigma=0.05,
                       integrator="expeuler", fisher_params=["R_a", "R_b", "R_c"])


def test_sensitivity_view_shows_ranking_and_verdicts(series_report: object) -> None:
    rep = series_report
    table = rep.table()
    text = check_html(rep._repr_html_())
    assert rep.backend in text
    for p in rep.parameters:
        assert p.name in text
        from tnn_dsl.analysis.common import _fmt

        assert _fmt(p.sensitivity, 4) in table and _fmt(p.sensitivity, 4) in text
    ident = rep.identifiability
    assert ident is not None
    for r in ident.rows():
        assert r["verdict"] in text and r["name"] in text
    assert "NOT separately identifiable" in text  # R_a and R_b in series, no sensor between them
    for r in rep.recommendations:
        assert r.verdict.upper() in text and r.reason in text


def test_sensitivity_table_unchanged_by_the_row_functions(series_report: object) -> None:
    rep = series_report
    lines = rep.table().splitlines()
    assert lines[0].startswith("Steady-state sensitivity of T_h, T_s (network series")
    rows = rep.ranking_rows()
    assert [r["name"] for r in rows] == rep.ranking
    first = next(ln for ln in lines if ln.startswith("  1  "))
    assert rows[0]["name"] in first
    assert sum(1 for ln in lines if "NOT separately identifiable" in ln) == sum(
        1 for r in rep.identifiability.rows() if not r["identifiable"])


def test_sensitivity_view_escapes_and_never_raises(series_report: object) -> None:
    import dataclasses

    rep = dataclasses.replace(series_report, network=SCRIPT, notes=[SCRIPT])
    out = rep._repr_html_()
    assert SCRIPT not in out and html.escape(SCRIPT) in out
    check_html(out)
    broken = dataclasses.replace(series_report, parameters=[None])  # nothing can format this
    out = broken._repr_html_()
    assert isinstance(out, str) and out.startswith("<pre>")


# --- the trained model -------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["jax", "torch"])
def trained(request: pytest.FixtureRequest, series_net: tnn_dsl.Network) -> TrainedModel:
    backend = request.param
    model = tnn_dsl.compile(series_net, backend="numpy")
    params = model.init_params(seed=0)
    params.update({"R_b": np.array(0.9), "R_c": np.array(1.8)})
    tm = TrainedModel(series_net, params, {"backend": backend, "rollout": "free", "stopped": "patience",
                                           "warnings": ["few data"], "config": {"integrator": "expeuler"}})
    exp = _series_data(series_net)
    tm.meta["metrics"] = {"train": tm.evaluate([exp], backend=backend), "validation": {"mae": 0.0123,
                                                                                       "max_error": 0.0456}}
    return tm


def test_trained_model_view_shows_fitted_and_nominal(trained: TrainedModel) -> None:
    text = check_html(trained._repr_html_())
    summary = trained.summary()
    assert trained.backend in text and "series" in text
    for s in ("0.8 K/W", "0.9 K/W", "2 K/W", "1.8 K/W", "+12.5 %", "-10.0 %", "few data"):
        assert s in summary and s in text, s
    assert "R_a" not in text  # not free
    mae = trained.meta["metrics"]["train"]["mae"]
    assert math.isfinite(mae)
    _numbers(text, mae, 0.0123, 0.0456)
    assert f"{mae:.4g}" in summary


def test_trained_model_table_matches_inspect(trained: TrainedModel) -> None:
    from tnn_dsl.cli._inspect import parameter_table
    from tnn_dsl.fit.model_files import format_row, format_value

    rows = parameter_table(trained)
    assert [r["name"] for r in rows] == ["R_b", "R_c"]
    assert rows[0]["unit"] == "K/W" and rows[0]["change_pct"] == pytest.approx(12.5)
    assert format_value(23.0, "degC") == "23 degC"
    assert all(format_row(r) in trained.summary() for r in rows)
    assert {r["name"] for r in parameter_table(trained, all_params=True)} >= {"R_a", "C_h", "R_b"}


def test_trained_model_view_escapes_and_never_raises(trained: TrainedModel, monkeypatch: pytest.MonkeyPatch) -> None:
    net = trained.network.model_copy(update={"name": SCRIPT})
    tm = TrainedModel(net, trained.params, dict(trained.meta, warnings=[SCRIPT]))
    out = tm._repr_html_()
    assert SCRIPT not in out and html.escape(SCRIPT) in out
    check_html(out)

    def broken(all_params: bool = False) -> list:
        raise ValueError("damaged")

    monkeypatch.setattr(tm, "parameter_table", broken)  # view and summary both fail: the repr as <pre>
    out = tm._repr_html_()
    assert out.startswith("<pre>TrainedModel(") and SCRIPT not in out and html.escape(SCRIPT) in out


def test_a_nested_mlp_check_is_said_so_and_its_weights_have_no_standard_errors() -> None:
    """An MLP chosen by the check from the doctor's fit (``linear`` row ``stopped: "the doctor's fit"``): the summary
    says the MLP was trained from the linear law, with both held-out MAEs, and under the values that those are the
    law's the MLP started from, its own weights without standard errors."""
    d = _diagnosis()
    d.extended.update(form="mlp", val_mae=0.05, uncertainty={
        "method": "Gauss–Newton", "statements": [],
        "estimates": [{"name": "U1 at T(h1) = 40 °C", "value": 0.031, "se": 0.002, "unit": "W/K", "status": "ok"}]},
        mlp_check={"choice": "mlp", "reason": "the MLP pays on held-out data (p = 0.012, MAE −29 %)",
                   "linear": {"val_mae": 0.0617, "stopped": "the doctor's fit"},
                   "mlp": {"val_mae": 0.05, "stopped": "completed"}})
    s = d.summary()
    assert ("linear or MLP: an MLP trained from the doctor's linear law (held-out MAE linear 0.0617 K, MLP 0.05 K): "
            "mlp — the MLP pays on held-out data") in s, s
    assert "U1 at T(h1) = 40 °C = 0.031 ± 0.002 W/K" in s
    assert "started as this law, every other value held at the above, and trained its own weights only" in s
    d.extended["form"] = "linear"
    assert "trained its own weights only" not in d.summary()
