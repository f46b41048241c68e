"""A free run that leaves the physical range stops with a message naming the node and the time (issue 13):
non-finite temperatures, temperatures below absolute zero, temperatures orders of magnitude outside the data's
range. Both backends; the CLI (simulate, evaluate) and the API (``TrainedModel.predict``)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tnn_dsl.cli import main
from tnn_dsl.core.errors import TnnError
from tnn_dsl.data import read_data
from tnn_dsl.fit.model_files import TrainedModel
from tnn_dsl.fit.simulation import plausible_range
from tnn_dsl.lang import loads

sys.path.insert(0, str(Path(__file__).parent))
from test_cli_simulate import RC, rc_data  # noqa: E402

BACKENDS = ["jax", "torch"]
# Valid values (`tnnc check` passes) and a heat source growing with the node's temperature (10/s): the
# temperature overflows within the file.
RUNAWAY = RC.replace("source n = P", "source n = P + 1000 W/K * T(n)")
# Stable but absurd: a 10 MW heat source into a 1 kJ/K node (1e4 K/s).
HOT = RC.replace("source n = P", "source n = P + 10 MW").replace("node n  C = 100 J/K", "node n  C = 1 kJ/K")


def _files(tmp_path: Path, text: str) -> tuple[str, str]:
    net = tmp_path / "net.thn"
    net.write_text(text)
    return str(net), rc_data(tmp_path)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("text, message", [
    (RUNAWAY, "node `n` reached 1.879e+05 K at t = 1 s (sample 2 of 400"),
    (HOT, "node `n` reached"),
])
def test_simulate_stops_naming_the_node_and_time(tmp_path, capsys, backend, text, message):
    net, data = _files(tmp_path, text)
    assert main(["check", "-q", net]) == 0
    out = tmp_path / "sim.csv"
    assert main(["simulate", net, "--data", data, "-o", str(out), "--backend", backend, "--init", "measured"]) == 1
    err = capsys.readouterr().err
    assert "error: the simulation left the physical range: " + message in err
    assert " at t = " in err and "sample " in err and "hint:" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("backend", BACKENDS)
def test_predict_raises_and_can_be_asked_not_to(tmp_path, backend):
    net_path, data = _files(tmp_path, HOT)
    net = loads(Path(net_path).read_text(), net_path)
    tm = TrainedModel(net, {p.name: np.asarray(float(p.value)) for p in net.params if p.is_constant},
                      {"backend": backend})
    with pytest.raises(TnnError, match=r"node `n` reached .* K at t = \d+ s .*far outside the data's temperatures"):
        tm.predict([data], init="measured")
    with pytest.raises(TnnError, match="left the physical range"):
        tm.evaluate([data], init="measured")
    (r,) = tm.predict([data], init="measured", check=False)
    assert np.nanmax(r["y"]) > 1e5


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_plausible_run_is_not_stopped(tmp_path, capsys, backend):
    net, data = _files(tmp_path, RC)
    assert main(["simulate", net, "--data", data, "-o", str(tmp_path / "s.csv"), "--backend", backend]) == 0
    capsys.readouterr()


def test_plausible_range_is_orders_of_magnitude_around_the_data(tmp_path):
    net_path, data = _files(tmp_path, RC)
    net = loads(Path(net_path).read_text(), net_path)
    (exp,) = read_data(net, [data])
    from tnn_dsl.compiler import compile as compile_network

    lo, hi = plausible_range(compile_network(net, backend="jax"), exp)
    assert lo == pytest.approx(293.15 - 100.0)  # 20 … 25 °C, span 10 K: 100 K below, 1000 K above
    assert hi == pytest.approx(exp.outputs.max() + 1000.0) and hi == pytest.approx(1298.15, abs=0.01)


def test_non_finite_and_below_absolute_zero_are_named(tmp_path):
    from tnn_dsl.compiler import compile as compile_network
    from tnn_dsl.fit.simulation import check_rollout

    net_path, data = _files(tmp_path, RC)
    net = loads(Path(net_path).read_text(), net_path)
    (exp,) = read_data(net, [data])
    model = compile_network(net, backend="jax")
    states = np.full((exp.n_steps, 1), 300.0)
    y = states.copy()
    check_rollout(model, exp, states, y)
    states[7, 0] = np.nan
    with pytest.raises(TnnError, match=r"node `n` became NaN at t = 7 s \(sample 8 of 400"):
        check_rollout(model, exp, states, y)
    with pytest.raises(TnnError, match=r"node `n` became infinite"):
        check_rollout(model, exp, np.where(np.isnan(states), np.inf, states), y)
    states[7, 0] = 300.0
    y[9, 0] = -1.0
    with pytest.raises(TnnError, match=r"sensor `Tn` fell to or below absolute zero \(-1 K\) at t = 9 s"):
        check_rollout(model, exp, states, y)
    check_rollout(model, exp, states, y, start=10)  # rows before the run's start are not its own
    y[9, 0] = 0.0
    with pytest.raises(TnnError, match=r"fell to or below absolute zero \(0 K\)"):
        check_rollout(model, exp, states, y)
    y[9, 0] = 150.0  # 143 K below the data's 20 … 25 °C: more than ten spans
    with pytest.raises(TnnError, match=r"sensor `Tn` reached 150 K .*plausible: 193.1"):
        check_rollout(model, exp, states, y)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_network_needing_thousands_of_sub_steps_is_an_error_not_a_run_of_hours(tmp_path, capsys, backend):
    """R = 2e-7 K/W where 0.2 K/W was meant: tau = 2e-5 s at a 1 s sample period."""
    net, data = _files(tmp_path, RC.replace("G n -- amb = 2 W/K", "R n -- amb = 2e-7 K/W"))
    assert main(["check", "-q", net]) == 0
    assert main(["simulate", net, "--data", data, "-o", str(tmp_path / "s.csv"), "--backend", backend]) == 1
    err = capsys.readouterr().err
    assert "the fastest time constant of the network is 2e-05 s (node n): a stable rk4 step" in err
    assert "warning: `R_n_amb` is a resistance of 2e-07 K/W, below" in err  # said before the run
    assert "more than 1,000" in err and "expeuler" in err
    assert main(["simulate", net, "--data", data, "-o", str(tmp_path / "s.csv"), "--backend", backend,
                 "--integrator", "expeuler"]) == 0
    capsys.readouterr()


def test_mutation_run_small(tmp_path):
    """The fast variant of benchmarks/mutation_fuzz.py (10 000 valid mutants, BENCHMARKS.md): 40 valid edited
    networks through check and simulate without an internal error or a silent non-finite output."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import mutation_fuzz

    s = mutation_fuzz.run(40, seed=7, jobs=1, work=tmp_path)
    assert s["valid"] == 40 and s["mutants"] > 40
    assert s["outcomes"].get("rejected by check", 0) > 0 and s["outcomes"].get("simulated", 0) > 20
    assert s["internal_errors"] == 0 and s["silent_non_finite"] == 0 and s["timed_out"] == 0, s["failures"]


def test_mutation_run_detectors_can_fail(tmp_path, monkeypatch):
    """The benchmark's two counters see what they count: an exception escaping main, a NaN written."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import mutation_fuzz

    import tnn_dsl.cli

    def broken(argv):
        raise ZeroDivisionError("planted")

    monkeypatch.setattr(tnn_dsl.cli, "main", broken)
    rc, err = mutation_fuzz._cli(["check", "x.thn"])
    assert rc == 3 and "ZeroDivisionError: planted" in err
    out = tmp_path / "o.csv"
    out.write_text("time_s,T1\n0,20\n1,nan\n")
    assert mutation_fuzz._silent_bad(out, "degC") == "non-finite value written"
    out.write_text("time_s,T1\n0,20\n1,40000\n")
    assert "implausible temperature written" in mutation_fuzz._silent_bad(out, "degC")
    out.write_text("time_s,T1\n0,20\n1,30\n")
    assert mutation_fuzz._silent_bad(out, "degC") is None


ROOT = Path(__file__).resolve().parents[1]


# numpy's overflow warnings are errors here: an absurd value gets the message, not a RuntimeWarning printed above
# it (the burn-in fit's step decrement overflowed on the Seebeck mutant until 2026-11-28)
@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("source, old, new, argv, message", [
    # found by the mutation run: a singular steady-state solve (torch raised), an overflowing burn-in fit
    # (numpy's least squares raised), a temperature of exactly 0 K written as a result
    ("tclab/tclab.thn", "G h1 -- h2  = 0.02 W/K", "G h1 -- h2  = 1e308 W/K", ["--integrator", "expeuler"],
     "the steady state of the first inputs could not be computed (not finite)"),
    ("peltier_heatpipe/nominal.thn", "seebeck = 0.05 V/K", "seebeck = 99999999999 V/K", [],
     "the simulation left the physical range: node `ph`"),  # below 0 K, or (the burn-in start kept in range) far above
    ("peltier_heatpipe/m4.thn", "C = 300 J/K", "C = 1e308 J/K", ["--integrator", "euler", "--init", "measured"],
     None),  # a message or a plausible file, depending on the inputs: never 0 K written
])
def test_mutants_that_were_internal_errors(tmp_path, capsys, backend, source, old, new, argv, message):
    import random

    sys.path.insert(0, str(ROOT / "benchmarks"))
    import mutation_fuzz

    src = ROOT / "networks" / source
    text = src.read_text()
    assert old in text
    net = tmp_path / src.name
    net.write_text(text.replace(old, new, 1))
    if "m4" in source:
        net.write_text(net.read_text().replace("R hp  -- hx2  = 0.2 K/W", "R hp -- hx2 = 0.2 K/W * 1e300"))
    data = tmp_path / "d.csv"
    mutation_fuzz.synthetic_csv(loads(net.read_text(), str(net)), data, 30, random.Random(0))
    assert main(["check", "-q", str(net)]) == 0
    rc = main(["simulate", str(net), "--data", str(data), "-o", str(tmp_path / "o.csv"), "--backend", backend, *argv])
    err = capsys.readouterr().err
    assert "internal error" not in err, err
    if message is None:
        assert rc == 1 or mutation_fuzz._silent_bad(tmp_path / "o.csv", "degC") is None
    else:
        assert rc == 1 and message in err, err


def test_the_same_problem_found_twice_is_reported_once():
    with pytest.raises(TnnError) as e:
        loads('network b\nparam Ta = 23 degC\nboundary amb = Ta * -1\nnode a C = 1 kJ/K\nR a -- amb = 8 K/W\n')
    assert len(e.value.diagnostics) == 1 and "at or below absolute zero" in e.value.format()
