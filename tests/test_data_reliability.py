"""Data that would be silently made up or wrong (tnn_dsl.data): gaps split a file instead of being interpolated,
empty sensor columns, temperatures in the wrong unit, duplicated column names."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import tnn_dsl
from tnn_dsl import DataError
from tnn_dsl.cli import main
from tnn_dsl.data import read_data, warning_lines
from tnn_dsl.data.reading import GAP_STEPS
from tnn_dsl.ir.network import Input, Network, Sensor

HEADER = "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC"


def tclab_net(unit: str = "degC") -> Network:
    return Network(
        name="tclab", temperature_unit=unit,
        inputs=[Input(name="Q1", unit="%", column="Q1_pct"), Input(name="Q2", unit="%", column="Q2_pct")],
        sensors=[Sensor(name="T1", node="h1", column="T1_degC"), Sensor(name="T2", node="h2", column="T2_degC")],
    )


def mixed_net(unit: str) -> Network:
    return Network(
        name="mixed", temperature_unit=unit,
        inputs=[Input(name="Q", unit="%", column="Q"), Input(name="Ta", is_temperature=True, column="Ta")],
        sensors=[Sensor(name="A", node="a", column="TA")],
    )


def write(path: Path, text: str) -> str:
    path.write_text(text, encoding="utf-8")
    return str(path)


def frame(path: Path, t, t1=None, t2=None, q1=None) -> str:
    """A TCLab-like file at times ``t``; T1 = 20 + t/1000 (a distinct value per row), T2 = 21."""
    t = np.asarray(t, dtype=float)
    t1 = 20 + t / 1000 if t1 is None else t1
    t2 = np.full(len(t), 21.0) if t2 is None else t2
    q1 = (t % 7) * 10 if q1 is None else q1
    cell = lambda v: "" if np.isnan(v) else repr(float(v))  # noqa: E731
    rows = "\n".join(f"{float(a)!r},{cell(b)},50,{cell(c)},{cell(d)}" for a, b, c, d in zip(t, q1, t1, t2))
    return write(path, f"{HEADER}\n{rows}\n")


def raises(fn, *args, **kw) -> DataError:
    with pytest.raises(DataError) as ei:
        fn(*args, **kw)
    return ei.value


# ---------------------------------------------------------------------------------------------
# Gaps
# ---------------------------------------------------------------------------------------------


def test_an_hour_gap_in_a_1_s_file_splits_it_instead_of_inventing_samples(tmp_path):
    t = np.r_[np.arange(600.0), 4200 + np.arange(600.0)]
    p = frame(tmp_path / "train.csv", t)
    a, b = read_data(tclab_net(), p)
    assert (a.name, b.name) == ("train[1/2]", "train[2/2]") and a.path == b.path == p
    assert a.n_steps == b.n_steps == 600 and a.dt == b.dt == 1.0
    np.testing.assert_array_equal(a.t, np.arange(600.0))
    np.testing.assert_array_equal(b.t, 4200 + np.arange(600.0))  # the segment keeps its time in the file
    np.testing.assert_allclose(np.r_[a.outputs[:, 0], b.outputs[:, 0]], 273.15 + 20 + t / 1000, rtol=1e-14)
    for e, lines in ((a, "lines 2–601"), (b, "lines 602–1201")):
        (note,) = e.notes
        assert "split into 2 segment(s)" in note and "3601 s after line 601" in note and lines in note
    # a caller that needs one continuous run gets an error at the row after the gap
    err = raises(read_data, tclab_net(), p, split_gaps=False)
    (d,) = err.diagnostics
    assert d.span.file == p and d.span.line == 602 and d.span.col == 1
    assert "gap of 3601 s" in d.message and "between line 601 and line 602" in d.message and d.hint


def test_rows_with_no_value_at_all_are_missing_rows_long_runs_split_short_ones_masked(tmp_path):
    n = 60
    t = np.arange(float(n))
    nan = np.full(n, np.nan)
    t1, t2, q1 = 20 + t / 1000, np.full(n, 21.0), t % 3
    gone = (t >= 20) & (t < 40)  # 20 empty rows: a gap
    hole = t == 50  # one empty row: a short gap
    for m in (gone, hole):
        t1, t2, q1 = np.where(m, nan, t1), np.where(m, nan, t2), np.where(m, nan, q1)
    p = frame(tmp_path / "e.csv", t, t1=t1, t2=t2, q1=q1)
    text = Path(p).read_text().replace(",50,,", ",,,")  # the Q2 cell too: nothing in those rows
    p = write(tmp_path / "e.csv", text)
    a, b = read_data(tclab_net(), p)  # today: an error (input Q1 has no value on lines 22-41, 52)
    assert a.t.tolist() == list(range(20)) and b.t.tolist() == list(range(40, 60))
    k = 50 - 40
    assert np.isnan(b.outputs[k]).all()  # the hole: no invented reading
    assert np.isfinite(b.inputs[k]).all() and b.inputs[k, 0] == pytest.approx(b.inputs[k - 1, 0])  # held input
    assert np.all(np.isfinite(np.delete(b.outputs, k, axis=0)))
    assert any("short gap" in n and "sensors not interpolated" in n for n in b.notes)
    assert any("21 row(s) with no input and no sensor value" in n for n in a.notes)


def test_a_segment_of_one_row_is_dropped_with_a_note(tmp_path):
    t = np.r_[np.arange(30.0), 100.0, 200 + np.arange(30.0)]
    p = frame(tmp_path / "s.csv", t)
    a, b = read_data(tclab_net(), p)
    assert (a.name, b.name) == ("s[1/2]", "s[2/2]") and b.t[0] == 200.0
    assert all("dropped segment(s) shorter than two steps: line 32 (1 row(s), 0 s)" in e.notes[0] for e in (a, b))
    # only one row on either side of the gaps: nothing left
    p = frame(tmp_path / "s1.csv", [0.0, 100.0, 200.0, 201.0, 202.0, 203.0])
    (e,) = read_data(tclab_net(), p)
    assert e.name == "s1" and e.t.tolist() == [200.0, 201.0, 202.0, 203.0] and "dropped" in e.notes[0]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(40, 120), cuts=st.lists(st.tuples(st.integers(1, 119), st.integers(1, 30)), max_size=4),
       blank=st.booleans(), dt=st.sampled_from([1.0, 2.0, 60.0]))
def test_segments_never_hold_an_interpolated_sensor_value_and_cover_every_measured_row(tmp_path, n, cuts, blank, dt):
    t = np.arange(float(n)) * dt
    miss = np.zeros(n, dtype=bool)
    for at, length in cuts:
        miss[at % n: at % n + length] = True
    miss[0] = False
    kept = np.flatnonzero(~miss)
    assume(kept.size >= 2 and np.median(np.diff(kept)) == 1)  # the file's own period stays dt
    t1 = 20 + np.arange(n) / 1000  # distinct values: any interpolated one is not among the measured
    if blank:  # the missing rows are written, with a time and no values
        nan = np.where(miss, np.nan, 0.0)
        p = frame(tmp_path / "h.csv", t, t1=t1 + nan, t2=21 + nan, q1=(t % 7) + nan)
        p = write(tmp_path / "h.csv", Path(p).read_text().replace(",50,,", ",,,"))
    else:
        p = frame(tmp_path / "h.csv", t[~miss], t1=t1[~miss])
    try:
        exps = read_data(tclab_net(), p)
    except DataError as err:  # only when no segment has two rows
        assert "shorter than two steps" in err.format()
        return
    measured = dict(zip(np.round(t[~miss], 9), 273.15 + t1[~miss]))
    covered = set()
    for e in exps:
        assert e.dt == dt and np.all(np.isfinite(e.inputs))
        for tk, y in zip(e.t, e.outputs[:, 0]):
            key = round(float(tk), 9)
            if np.isfinite(y):
                assert key in measured and y == pytest.approx(measured[key], abs=1e-9)
                covered.add(key)
        # a segment never spans a gap longer than GAP_STEPS periods of missing rows
        inside = [k for k in measured if e.t[0] <= k <= e.t[-1]]
        assert np.all(np.diff(inside) <= GAP_STEPS * dt + 1e-9)
    dropped = set(measured) - covered
    if dropped:  # only rows of one-row segments, and a note says so
        assert any("dropped" in n for e in exps for n in e.notes)
        for k in dropped:
            others = [m for m in measured if m != k]
            assert min(abs(m - k) for m in others) > GAP_STEPS * dt


def test_training_on_a_split_file_and_the_cli_commands(tmp_path, capsys):
    rc_thn = write(tmp_path / "rc.thn", """\
network rc "one node"
units temperature = degC
input P : [W]  column "P_W"
param Ta = 20 degC
boundary amb = Ta
node n  C = 100 J/K  free
G n -- amb = 2 W/K
source n = P
sensor Tn = n  column "T_n"
""")
    t = np.r_[np.arange(200.0), 3800 + np.arange(200.0)]
    P = np.where((t % 100) >= 50, 10.0, 0.0)
    T = 20 + 5 * (P > 0) * (1 - np.exp(-((t % 100) - 50).clip(0) / 50))
    rows = "\n".join(f"{a:g},{b:g},{float(c)!r}" for a, b, c in zip(t, P, T))
    data = write(tmp_path / "rc.csv", "time_s,P_W,T_n\n" + rows + "\n")
    tm = tnn_dsl.train(rc_thn, data, backend="jax", epochs=3, lbfgs_iters=3, seed=0)
    names = [r["name"] for r in tm.meta["data"]["train"]]
    assert names == ["rc[1/2]", "rc[2/2]"]
    model = tmp_path / "model"
    tm.save(str(model))
    assert main(["evaluate", str(model), data]) == 0
    out = capsys.readouterr().out
    assert "rc[1/2]" in out and "rc[2/2]" in out
    # simulate needs one continuous run: a clear error, not a traceback
    rc = main(["simulate", rc_thn, "--data", data, "-o", str(tmp_path / "sim.csv")])
    err = capsys.readouterr().err
    assert rc == 1 and f"{data}:202:1: error: gap of 3601 s" in err and "Traceback" not in err


# ---------------------------------------------------------------------------------------------
# Empty sensor columns
# ---------------------------------------------------------------------------------------------


def test_an_all_nan_sensor_column_is_a_warning_and_no_sensor_data_an_error(tmp_path):
    p = write(tmp_path / "n.csv", f"{HEADER}\n0,1,2,20,\n1,1,2,21,nan\n2,1,2,22,\n")
    (e,) = read_data(tclab_net(), p)
    (w,) = e.warnings
    assert w.severity == "warning" and w.span.line == 1 and w.span.col == 30
    text = warning_lines([e])[0]
    assert text.startswith(f"{p}:1:30: warning: sensor T2 (column 'T2_degC') has no value in any row")
    assert "hint:" in text and "^^^^^^^" in text
    # not needed (simulate): a note, not a warning
    (e,) = read_data(tclab_net(), p, require_outputs=False)
    assert e.warnings == () and any("T2" in n and "no value" in n for n in e.notes)
    p = write(tmp_path / "n2.csv", f"{HEADER}\n0,1,2,,\n1,1,2,,\n")
    err = raises(read_data, tclab_net(), p)
    (d,) = err.diagnostics
    assert d.span.line == 1 and d.span.col == 22 and "no sensor column has a value in any row" in d.message
    assert "'T1_degC' (sensor T1), 'T2_degC' (sensor T2)" in d.message and d.hint


# ---------------------------------------------------------------------------------------------
# Temperatures in the wrong unit
# ---------------------------------------------------------------------------------------------


def test_kelvin_in_a_degc_file_is_a_warning_naming_the_column_range_and_unit(tmp_path):
    p = write(tmp_path / "k.csv", "time_s,Q,Ta,TA\n0,1,278.15,293.2\n1,1,279.0,301.7\n2,1,280,299\n")
    (e,) = read_data(mixed_net("degC"), p)
    ws = {w.message.split(" (")[0]: w for w in e.warnings}
    assert set(ws) == {"input Ta", "sensor A"}
    w = ws["sensor A"]
    assert "reads 293.2 … 301.7 degC, which looks like kelvin" in w.message
    assert w.span.line == 1 and w.span.col == 13 and "`units temperature = K`" in w.hint
    # the same file declared in K: no warning
    (e,) = read_data(mixed_net("K"), p)
    assert e.warnings == ()


def test_celsius_in_a_kelvin_file_and_below_absolute_zero_are_warnings(tmp_path):
    p = write(tmp_path / "c.csv", "time_s,Q,Ta,TA\n0,1,5,20.5\n1,1,6,24\n")
    (e,) = read_data(mixed_net("K"), p)
    assert len(e.warnings) == 2
    w = next(w for w in e.warnings if "sensor A" in w.message)
    assert "reads 20.5 … 24 K" in w.message and "look like degC" in w.message and "`units temperature = degC`" in w.hint
    (e,) = read_data(mixed_net("degC"), p)
    assert e.warnings == ()  # plausible in degC
    p = write(tmp_path / "z.csv", "time_s,Q,Ta,TA\n0,1,5,20.5\n1,1,6,-999\n2,1,6,21\n")
    (e,) = read_data(mixed_net("degC"), p)
    (w,) = e.warnings
    assert "sensor A (column 'TA') reads -999 degC at line 3, below absolute zero" in w.message
    assert (w.span.line, w.span.col) == (3, 7) and "empty" in w.hint


# ---------------------------------------------------------------------------------------------
# Duplicated column names
# ---------------------------------------------------------------------------------------------


def test_a_duplicated_column_name_is_an_error_at_its_second_occurrence(tmp_path):
    p = write(tmp_path / "d.csv", "time_s,Q1_pct,T1_degC,Q2_pct,T1_degC,T2_degC\n0,1,20,2,30,4\n1,1,20,2,30,4\n")
    err = raises(read_data, tclab_net(), p)
    (d,) = err.diagnostics
    assert (d.span.line, d.span.col) == (1, 30)
    assert "column 'T1_degC' appears twice (columns 3 and 5)" in d.message and "rename" in d.hint
    assert err.format().startswith(f"{p}:1:30: error: column 'T1_degC' appears twice")
    # the time column, three times
    p = write(tmp_path / "d2.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC,time_s,time_s\n0,1,2,3,4,0,0\n1,1,2,3,4,1,1\n")
    (d,) = raises(read_data, tclab_net(), p).diagnostics
    assert "column 'time_s' appears 3 times (columns 1, 6 and 7)" in d.message and d.span.col == 38
    # a duplicated column the network does not read is harmless
    p = write(tmp_path / "d3.csv", f"{HEADER},note,note\n0,1,2,3,4,a,b\n1,1,2,3,4,c,d\n")
    (e,) = read_data(tclab_net(), p)
    assert e.n_steps == 2


def _kelvin_in_degc_file(tmp_path):
    """A one-node degC network and a data file whose temperatures are written in kelvin: ``(net path, data)``."""
    net = tmp_path / "one.thn"
    net.write_text('network one "one node"\nunits temperature = degC\ninput Ta : temperature column "Ta"\n'
                   'boundary amb = Ta\nnode n C = 100 J/K free in [1 J/K, 1000 J/K]\n'
                   'R n -- amb = 0.5 K/W as Rn\nsensor y = n column "y"\n')
    rows = "\n".join(f"{k},{293.15 + 0.01 * k:.4f},{293.5 + 0.005 * k:.4f}" for k in range(60))
    return net, write(tmp_path / "k.csv", f"time,Ta,y\n{rows}\n")


def test_tnnc_train_quiet_still_prints_data_warnings(tmp_path, capsys):
    """``-q`` hides progress and notes, never a data warning (kelvin values in a degC file)."""
    from tnn_dsl.cli import main

    net, data = _kelvin_in_degc_file(tmp_path)
    rc = main(["train", str(net), data, "-o", str(tmp_path / "m"), "--epochs", "2", "--lbfgs-iters", "0", "-q"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "warning:" in err and "looks like kelvin" in err and "note:" not in err


def test_tnnc_diagnose_quiet_prints_data_warnings_first(tmp_path, capsys, monkeypatch):
    """``tnnc diagnose --quiet`` prints the data's warnings before the doctor runs (the doctor itself is replaced
    here: this test is about what the command prints)."""
    import tnn_dsl.doctor
    from tnn_dsl.cli import main

    net, data = _kelvin_in_degc_file(tmp_path)

    from tnn_dsl.core import TnnError

    def not_run(*a, **k):
        raise TnnError("the doctor is not run in this test")

    monkeypatch.setattr(tnn_dsl.doctor, "diagnose", not_run)
    rc = main(["diagnose", str(net), data, "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and "not run in this test" in err
    assert "warning:" in err and "looks like kelvin" in err
    assert err.index("looks like kelvin") < err.index("not run in this test")
