"""Ctrl-C during a diagnosis (``tnn_dsl.doctor.stopping``; ``tnnc diagnose``): the first one stops it the way a spent
budget does and the diagnosis returns — and the CLI writes — what it found so far, saying where Ctrl-C stopped it; a
second one aborts. Before, a Ctrl-C threw away every accepted round of a diagnosis that runs for minutes."""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest
from conftest import TNNC_CTRL_C

import tnn_dsl
from tnn_dsl.doctor.engine import _Engine
from tnn_dsl.doctor.stopping import request_stop, stop_requested
from tnn_dsl.studies.planted import plant

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}  # heater fraction (SI of [%])


def _planted(backend: str):
    """U1 depending on T(h1) (+40 % over the data's range), as the budget's tests plant it."""
    net = tnn_dsl.load(TCLAB)
    return net, plant(net, BOUNDS, "param_dependence", "U1", "T(h1)", 0.4, noise=0.01, seed=3, n_train=400,
                      n_val=300, hold=(20, 150), backend=backend)


@pytest.mark.parametrize("backend", ["jax", pytest.param("torch", marks=pytest.mark.slow)])
def test_a_stop_after_round_one_keeps_its_finding(backend):
    """Stop asked for as round 1 accepts the planted dependence (what a Ctrl-C then does): no round 2, the finding and
    its extended model kept, the verdict and ``budget`` saying Ctrl-C stopped the work and where; the request is
    cleared when the diagnosis returns."""
    net, pl = _planted(backend)
    lines: list[str] = []

    def progress(msg: str) -> None:
        lines.append(msg)
        if msg.startswith("round 1: accepted"):
            request_stop()

    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=3, mlp_check=False, backend=backend,
                         progress=progress)
    assert not stop_requested()
    assert [f.target for f in d.accepted] == ["U1"] and d.accepted[0].depends_on == ["T(h1)"]
    assert not any(line.startswith("round 2") for line in lines), lines
    assert "learn U1 as linear(h1)" in d.extended_text
    assert d.decided and d.budget == {"seconds": None, "ran_out": "before round 2", "interrupted": True}
    assert "stopped by Ctrl-C before round 2" in d.verdict, d.verdict


def test_a_stop_during_a_fit_ends_it_after_its_iteration(monkeypatch):
    """Stop asked for during round 1's first candidate fit: that fit ends after the iteration it is in, no other fit
    starts, and the verdict says Ctrl-C stopped the work in round 1 (a finding from the fits that ended is held-out
    tested as with a spent budget; without one the diagnosis is not decided)."""
    net, pl = _planted("jax")
    fits: list[dict] = []
    real_fit = _Engine.fit

    def fit(self, *a, **k):
        if fits and not stop_requested():  # the nominal fit is the first; the round's first fit is the second
            request_stop()
        info = real_fit(self, *a, **k)
        fits.append(info)
        return info

    monkeypatch.setattr(_Engine, "fit", fit)
    d = tnn_dsl.diagnose(net, pl.train, pl.val, top=2, max_rounds=2, mlp_check=False, backend="jax")
    assert len(fits) == 2 and fits[0]["iterations"] > 1 and fits[1]["iterations"] == 1, fits
    assert d.budget == {"seconds": None, "ran_out": "in round 1", "interrupted": True}
    assert d.decided == bool(d.accepted)
    said = "; stopped by Ctrl-C in round 1" if d.accepted else "not decided: stopped by Ctrl-C in round 1"
    assert said in d.verdict, d.verdict


_HANDLER_SCRIPT = """
import os, signal, sys, time
from tnn_dsl.doctor.stopping import ctrl_c_stops, stop_requested
said = []
before = signal.getsignal(signal.SIGINT)
try:
    with ctrl_c_stops(said.append):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)  # the handler runs between bytecodes
        print("first", stop_requested(), said[0] if said else "", flush=True)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
        print("not aborted", flush=True)
except KeyboardInterrupt:
    print("aborted", flush=True)
print("after", signal.getsignal(signal.SIGINT) is before, stop_requested(), flush=True)
with ctrl_c_stops(said.append, enabled=False):
    print("disabled", signal.getsignal(signal.SIGINT) is before, flush=True)
signal.signal(signal.SIGINT, signal.SIG_IGN)
with ctrl_c_stops(said.append):
    print("ignored", signal.getsignal(signal.SIGINT) is signal.SIG_IGN, flush=True)
"""


def test_the_first_sigint_asks_to_stop_and_the_second_aborts():
    """The handler itself, with real signals, in a process of its own (a test runner's worker may run tests outside
    its main thread, where Python delivers no signal): the first SIGINT sets the request and says so, the second
    raises ``KeyboardInterrupt``; the previous handler is back afterwards and the request cleared. Not installed
    where not asked for, or where SIGINT is ignored (a job started in the background)."""
    import sys

    script = "import signal; signal.signal(signal.SIGINT, signal.default_int_handler)" + _HANDLER_SCRIPT
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    lines = res.stdout.splitlines()
    assert res.returncode == 0, res.stderr
    assert lines[0].startswith("first True Ctrl-C: stopping after the current step"), lines
    assert lines[1:] == ["aborted", "after True False", "disabled True", "ignored True"], lines


def _write_csvs(tmp_path, net, pl):
    from tnn_dsl.data import unit_factor, write_csv

    paths = []
    for name, exp in (("train.csv", pl.train[0]), ("val.csv", pl.val[0])):
        cols = {i.column: exp.inputs[:, j] / (1.0 if i.is_temperature else unit_factor(i.unit))
                for j, i in enumerate(net.inputs)}
        cols.update({s.column: exp.outputs[:, j] for j, s in enumerate(net.sensors)})
        write_csv(tmp_path / name, exp.t, cols, net.temperature_unit, kelvin=[s.column for s in net.sensors])
        paths.append(str(tmp_path / name))
    return paths


def test_cli_ctrl_c_writes_what_was_found(tmp_path):
    """``tnnc diagnose`` with SIGINT as its round 1 begins: exit 130, the summary printed, the JSON written and marked
    ``interrupted``, and the message says so."""
    net, pl = _planted("jax")
    train, val = _write_csvs(tmp_path, net, pl)
    out = tmp_path / "d.json"
    proc = subprocess.Popen(TNNC_CTRL_C + ["diagnose", TCLAB, train, "--val", val, "--json", str(out), "--top", "2",
                                           "--max-rounds", "3", "--no-mlp-check"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    err: list[str] = []
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            err.append(line)
            if "round 1: score test" in line:
                proc.send_signal(signal.SIGINT)
                break
        rest_out, rest_err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    err_text = "".join(err) + rest_err
    assert proc.returncode == 130, err_text
    assert "Traceback" not in err_text and "Ctrl-C: stopping after the current step" in err_text, err_text
    doc = json.loads(out.read_text())
    assert doc["budget"]["interrupted"] is True and doc["budget"]["ran_out"].startswith("in round 1"), doc["budget"]
    assert "stopped by Ctrl-C in round 1" in doc["verdict"] and "model doctor" in rest_out
    assert "interrupted: stopped in round 1" in err_text and "written" in err_text
