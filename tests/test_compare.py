"""`tnnc compare` and :mod:`tnn_dsl.analysis.comparison`: nesting read from the networks (Bacher & Madsen's Ti ⊂ TiTh ⊂
TiTeTh, Ti ⊂ TiTe ⊂ TiTeTh, TiTh and TiTe not nested; small hand-written networks), the likelihood-ratio logic on
given fits, and the command end to end on a short prefix of the Bacher & Madsen file (both backends)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from scipy.stats import chi2

import tnn_dsl
from tnn_dsl.analysis import comparison as C
from tnn_dsl.analysis import nesting
from tnn_dsl.cli import main

ROOT = Path(__file__).resolve().parents[1]
BUILDING = ROOT / "networks" / "building"
BM = ROOT.parent / "shared" / "data" / "bacher_madsen_inputPRBS1.csv"
needs_data = pytest.mark.skipif(not BM.exists(), reason="Bacher & Madsen data not available")


def _bm(name: str):
    return tnn_dsl.load(BUILDING / f"{name}.thn")


# ---------------------------------------------------------------------------------------------
# Nesting from the IR
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("a, b", [("ti", "tith"), ("tith", "titeth"), ("ti", "tite"), ("tite", "titeth"),
                                  ("ti", "titeth")])
def test_bacher_madsen_chains_are_nested(a, b):
    n = nesting(_bm(a), _bm(b))
    assert n.nested is True, n.summary()
    assert not n.reasons
    back = nesting(_bm(b), _bm(a))
    assert back.nested is False and back.reasons


def test_tith_extension_moves_the_heater_source():
    n = nesting(_bm("ti"), _bm("tith"))
    assert {"node th", "link Rih (th–ti)", "parameter C_th", "parameter Rih"} <= set(n.added)
    assert any("source Q_heat" in r and "th" in r for r in n.reductions)


def test_tite_extension_splits_the_outer_resistance():
    n = nesting(_bm("ti"), _bm("tite"))
    assert "node te" in n.added
    assert any("link Ria" in r and "split in series" in r and "Rie + Rea" in r for r in n.reductions)


@pytest.mark.parametrize("a, b", [("tith", "tite"), ("tite", "tith")])
def test_tith_and_tite_are_not_nested(a, b):
    n = nesting(_bm(a), _bm(b))
    assert n.nested is False
    missing = "th" if a == "tith" else "te"
    assert any(f"node {missing} of building_{a} is missing in building_{b}" in r for r in n.reasons)


SMALL = """
network {name}
input Ta : temperature
input Q  : [W]
boundary amb = Ta
node n1 C = 1000 J/K  free in [10 J/K, 1e5 J/K]
R n1 -- amb = 0.1 K/W  free in [0.001 K/W, 10 K/W]  as R1
source n1 = Q  as Qs
sensor T1 = n1 column "T1"
{extra}
"""


def _small(name: str, extra: str = ""):
    return tnn_dsl.loads(SMALL.format(name=name, extra=extra), f"{name}.thn")


def test_small_added_node_is_nested():
    a = _small("a")
    b = _small("b", "node n2 C = 500 J/K free in [1 J/K, 1e4 J/K]\nR n1 -- n2 = 0.05 K/W free in [0.001 K/W, 1 K/W] "
                    "as R12")
    n = nesting(a, b)
    assert n.nested is True
    assert "node n2" in n.added and "link R12 (n1–n2)" in n.added


def test_small_removed_link_is_not_nested_with_a_reason():
    a = _small("a")
    # b heats and cools n1 through a second node only: R1 joins n1 to n2, not to the outdoors
    text = SMALL.format(name="b", extra="node n2 C = 500 J/K\nR n2 -- amb = 0.1 K/W as R2").replace(
        "R n1 -- amb = 0.1 K/W", "R n1 -- n2 = 0.1 K/W")
    b = tnn_dsl.loads(text, "b.thn")
    # a path n1 – n2 – amb through b's new node n2 exists: that is a series split, still nested
    assert nesting(a, b).nested is True
    # the same with n2 a node a has too: the split no longer reduces to a
    a2 = _small("a2", "node n2 C = 500 J/K\nR n2 -- amb = 0.1 K/W as R2")
    n = nesting(a2, b)
    assert n.nested is False
    assert any("link R1 of a2 (n1–amb) is missing in b" in r and "joins n1–n2" in r for r in n.reasons)


def test_small_fixed_parameter_and_sensors():
    a = _small("a")
    fixed = tnn_dsl.loads(SMALL.format(name="b", extra="").replace(
        "= 0.1 K/W  free in [0.001 K/W, 10 K/W]", "= 0.1 K/W"), "b.thn")
    n = nesting(a, fixed)
    assert n.nested is False and any("R1 is free in a but fixed in b" in r for r in n.reasons)
    # freeing a fixed parameter is an extension
    assert nesting(fixed, a).nested is True and "parameter R1 freed" in nesting(fixed, a).added
    more = _small("b", 'node n2 C = 500 J/K\nR n1 -- n2 = 0.05 K/W as R12\nsensor T2 = n2 column "T2"')
    n = nesting(a, more)
    assert n.nested is False and any("adds sensor T2" in r for r in n.reasons)
    assert nesting(a, _small("b")).nested is False  # the same model: nothing added


def test_small_learned_function_is_undecided():
    a = _small("a")
    b = _small("b", "learn Q[n1] as linear(Ta)")
    n = nesting(a, b)
    assert n.nested is None and any("learned function" in r for r in n.reasons)


def test_renamed_link_and_moved_source():
    a = _small("a", "node n2 C = 500 J/K free in [1 J/K, 1e4 J/K]\nR n1 -- n2 = 0.05 K/W as R12")
    # b: the same link under another name, and the source moved to a new node n3 joined to n1
    b = tnn_dsl.loads(SMALL.format(name="b", extra="node n2 C = 500 J/K free in [1 J/K, 1e4 J/K]\n"
                                                    "R n1 -- n2 = 0.05 K/W as Rx\nnode n3 C = 50 J/K free\n"
                                                    "R n3 -- n1 = 0.01 K/W free as R31")
                      .replace("source n1 = Q", "source n3 = Q"), "b.thn")
    n = nesting(a, b)
    assert n.nested is True, n.summary()
    assert any("link R12 of a (n1–n2) is link Rx in b" in r for r in n.reductions)
    assert any("source Qs heats n1 in a but n3 in b" in r for r in n.reductions)
    # moved to a node a has too: not an extension
    c = tnn_dsl.loads(SMALL.format(name="c", extra="node n2 C = 500 J/K free in [1 J/K, 1e4 J/K]\n"
                                                    "R n1 -- n2 = 0.05 K/W as R12").replace("source n1 = Q",
                                                                                            "source n2 = Q"), "c.thn")
    n = nesting(a, c)
    assert n.nested is False and any("source Qs heats n1 in a but n2 in c" in r for r in n.reasons)


# ---------------------------------------------------------------------------------------------
# The test on given fits (no fitting)
# ---------------------------------------------------------------------------------------------


def _fit(label, name, loglik, k, n=500, aic=None):
    return C.ModelFit(label=label, network=name, file=None, loglik=loglik, k=k, n_obs=n,
                      aic=2 * k - 2 * loglik if loglik is not None else None,
                      bic=k * math.log(n) - 2 * loglik if loglik is not None else None, converged=True,
                      free_run_mae=0.5, free_run_mae_sensors={"Ti": 0.5}, one_step_rms=0.1,
                      one_step_rms_sensors={"Ti": 0.1}, scored_on="training", train_seconds=1.0)


@pytest.fixture
def fake_fits(monkeypatch):
    """``compare_models`` with the fits replaced: ``fits[net name] = (log L, k)``."""
    fits: dict[str, tuple] = {}

    def fake(label, net, exps, vals, objective, options, log):
        ll, k, *n = fits[net.name]
        return _fit(label, net.name, ll, k, *(n or [500]))

    monkeypatch.setattr(C, "fit_and_score", fake)
    monkeypatch.setattr(C, "_experiments", lambda net, data, read: [object()] if data else [])
    return fits


def test_lr_on_given_fits(fake_fits):
    fake_fits.update({"building_ti": (2479.2, 6), "building_tith": (3191.7, 10), "building_tite": (3000.0, 10)})
    c = C.compare_models(_bm("ti"), _bm("tith"), ["x.csv"])
    assert c.lr_test == "nested" and c.larger == "B" and c.df == 4
    assert c.lr == pytest.approx(2 * (3191.7 - 2479.2))
    assert c.p == pytest.approx(chi2.sf(c.lr, 4)) and c.p < 1e-300
    assert c.verdict.startswith("B (building_tith) is better: LR 1425.0 on 4 df, p < 1e-300")
    d = json.loads(json.dumps(c.to_dict()))
    assert d["lr"] == pytest.approx(2 * (d["b"]["loglik"] - d["a"]["loglik"]))
    assert "no held-out data" in " ".join(d["notes"]) and d["held_out"] is False
    # given the other way round: A extends B, the test runs from B to A
    r = C.compare_models(_bm("tith"), _bm("ti"), ["x.csv"])
    assert r.larger == "A" and r.lr == pytest.approx(c.lr) and r.df == 4
    assert r.verdict.startswith("A (building_tith) is better")
    # not nested: withheld, AIC/BIC only
    w = C.compare_models(_bm("tith"), _bm("tite"), ["x.csv"])
    assert w.lr is None and w.df is None and w.p is None and w.lr_test == "withheld"
    assert w.verdict.startswith("not nested: the LR test does not apply; AIC/BIC only")
    assert "AIC prefers A (building_tith)" in w.verdict
    assert w.to_dict()["lr"] is None
    assert "withheld" in w.summary()


def test_lr_not_significant_and_odd_fits(fake_fits):
    fake_fits.update({"building_ti": (1000.0, 6), "building_tith": (1003.0, 10)})
    c = C.compare_models(_bm("ti"), _bm("tith"), ["x.csv"])
    assert c.p == pytest.approx(chi2.sf(6.0, 4))
    assert "not significantly better than A (building_ti) at 5 %" in c.verdict
    fake_fits["building_tith"] = (990.0, 10)  # the larger model fitted worse: a local optimum
    c = C.compare_models(_bm("ti"), _bm("tith"), ["x.csv"])
    assert c.lr == pytest.approx(-20.0) and c.p == 1.0 and any("lower likelihood" in n for n in c.notes)
    fake_fits["building_tith"] = (1100.0, 10, 499)  # different data counted: no test
    c = C.compare_models(_bm("ti"), _bm("tith"), ["x.csv"])
    assert c.lr is None and c.lr_test == "withheld" and c.verdict.startswith("no likelihood-ratio test")
    fake_fits["building_tith"] = (None, None)
    c = C.compare_models(_bm("ti"), _bm("tith"), ["x.csv"])
    assert c.lr is None and any("B has no likelihood" in n for n in c.notes)
    html = c._repr_html_()
    assert "building_tith" in html and "<table" in html


# ---------------------------------------------------------------------------------------------
# End to end
# ---------------------------------------------------------------------------------------------


def _prefix(tmp_path: Path, rows: int) -> Path:
    lines = BM.read_text().splitlines()
    out = tmp_path / f"bm{rows}.csv"
    out.write_text("\n".join(lines[:rows + 1]) + "\n")
    return out


def _check_ti_tith(d: dict, err: str, backend: str, rows: int, heater_pays: bool = True) -> None:
    assert {"objective", "backend", "held_out", "a", "b", "nesting", "lr", "df", "p", "larger", "lr_test",
            "verdict", "notes"} <= set(d)
    for m in ("a", "b"):
        assert {"loglik", "k", "n_obs", "aic", "bic", "free_run_mae", "one_step_rms", "scored_on"} <= set(d[m])
        assert d[m]["n_obs"] == rows and d[m]["scored_on"] == "training"
        assert 0 < d[m]["one_step_rms"] < d[m]["free_run_mae"] < 3.0
        assert d[m]["aic"] == pytest.approx(2 * d[m]["k"] - 2 * d[m]["loglik"])
    assert d["objective"] == "ml" and d["backend"] == backend
    assert d["nesting"]["nested"] is True and d["lr_test"] == "nested" and d["larger"] == "B"
    assert d["df"] == d["b"]["k"] - d["a"]["k"] == 4
    assert d["lr"] == pytest.approx(2 * (d["b"]["loglik"] - d["a"]["loglik"]), rel=1e-12)
    assert d["p"] == pytest.approx(chi2.sf(d["lr"], 4), rel=1e-6, abs=1e-300)
    if heater_pays:
        assert d["lr"] > 20 and d["verdict"].startswith("B (building_tith) is better")  # the heater node pays
    assert "likelihood ratio: LR = 2(log L_B − log L_A)" in err  # the table went to stderr


def _run_ti_tith(tmp_path, capsys, backend: str, rows: int) -> tuple[dict, str]:
    data = _prefix(tmp_path, rows)
    rc = main(["compare", str(BUILDING / "ti.thn"), str(BUILDING / "tith.thn"), str(data), "--time-unit", "h",
               "--backend", backend, "--epochs", "40", "--json", "-", "-q"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    return json.loads(out), err


@needs_data
def test_cli_compare_ti_tith_jax(tmp_path, capsys):
    d, err = _run_ti_tith(tmp_path, capsys, "jax", 250)
    _check_ti_tith(d, err, "jax", 250)


@needs_data
@pytest.mark.slow
def test_cli_compare_ti_tith_torch(tmp_path, capsys):
    """The whole command on torch (its filter is a Python loop with nested derivatives, ~10 ms per row per
    likelihood gradient, and the likelihood is fitted from two starts per model): 60 rows, the table's consistency
    only (the JAX test above checks that the heater node pays on 250 rows); the fast variant is the next test.
    Measured 2026-11-25: passed in 22 min on 2 cores shared with other jobs — the torch filter's speed is issue 18;
    2026-12-04: 192 s alone, the linear models' linearisation now formed once per evaluation on torch too."""
    d, err = _run_ti_tith(tmp_path, capsys, "torch", 60)
    _check_ti_tith(d, err, "torch", 60, heater_pays=False)


@needs_data
def test_one_step_rms_backends_agree(tmp_path):
    """The one-step RMS and free-run MAE of one fitted model, computed on JAX and on torch (fast variant of the
    torch end-to-end test: the fit is JAX's, the filter runs on both)."""
    net = _bm("ti")
    exps = C._experiments(net, [_prefix(tmp_path, 150)], {"time_unit": "h"})
    fit = C.fit_and_score("A", net, exps, [], "ml", {"backend": "jax", "epochs": 40}, None)
    notes: list[str] = []
    rms_t, per_t, _ = C._one_step(fit.trained, "ml", "torch", exps, exps, notes)
    assert fit.one_step_rms is not None and 0 < fit.one_step_rms < fit.free_run_mae
    assert rms_t == pytest.approx(fit.one_step_rms, rel=1e-8)
    assert per_t["Ti"] == pytest.approx(fit.one_step_rms_sensors["Ti"], rel=1e-8)
    assert fit.trained.evaluate(exps, backend="torch")["mae"] == pytest.approx(fit.free_run_mae, rel=1e-8)
    assert not notes


@needs_data
def test_cli_compare_not_nested_output_error(tmp_path, capsys):
    data = _prefix(tmp_path, 150)
    lines = BM.read_text().splitlines()
    val = tmp_path / "val.csv"
    val.write_text("\n".join([lines[0], *lines[151:251]]) + "\n")
    js = tmp_path / "cmp.json"
    rc = main(["compare", str(BUILDING / "tith.thn"), str(BUILDING / "tite.thn"), str(data), "--val", str(val),
               "--time-unit", "h", "--objective", "output-error", "--epochs", "40", "--json", str(js), "-q"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    d = json.loads(js.read_text())
    assert d["nesting"]["nested"] is False and d["nesting"]["reasons"]
    assert d["lr"] is None and d["df"] is None and d["p"] is None and d["lr_test"] == "withheld"
    assert d["verdict"].startswith("not nested: the LR test does not apply; AIC/BIC only")
    assert any("only indicative" in n for n in d["notes"])
    assert all(d[m]["one_step_rms"] is not None and d[m]["one_step_rms"] > 0 for m in ("a", "b"))
    assert d["held_out"] is True and all(d[m]["scored_on"] == "validation" for m in ("a", "b"))
    assert not any("no held-out data" in n for n in d["notes"])
    assert any("noise levels fitted" in n for n in d["a"]["notes"])
    assert "not nested" in out and "free-run MAE, K (validation)" in out  # the table on stdout


def test_cli_compare_errors(tmp_path, capsys):
    bad = tmp_path / "bad.thn"
    bad.write_text("network bad\nnode x C = \n")
    rc = main(["compare", str(bad), str(BUILDING / "ti.thn"), str(tmp_path / "none.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and "bad.thn:2:" in err and "error" in err and "Traceback" not in err
    rc = main(["compare", str(BUILDING / "ti.thn"), str(BUILDING / "tith.thn"), str(tmp_path / "none.csv"),
               "--time-unit", "h", "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "none.csv" in err and "Traceback" not in err
    data = tmp_path / "d.csv"
    data.write_text("t,Ta,Ps,Ph,yTi\n0,1,0,1,20\n")
    rc = main(["compare", str(BUILDING / "ti.thn"), str(BUILDING / "tith.thn"), str(data), "--json", str(data)])
    err = capsys.readouterr().err
    assert rc == 1 and "--json" in err and "Traceback" not in err
