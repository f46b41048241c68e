"""Data loading (tnn_dsl.data): CSV/Parquet → Experiment, units, time, resampling, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tnn_dsl import DataError
from tnn_dsl.data import Experiment, from_kelvin, read_data, split_by_time, to_kelvin, write_csv
from tnn_dsl.ir.network import Input, Network, Sensor

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
if not DATA.is_dir():  # the project's own copy, if any
    DATA = Path(__file__).resolve().parents[1] / "data"
needs_data = pytest.mark.skipif(not (DATA / "tclab_kuntz_rawlings_prbs_openloop.csv").is_file(),
                                reason="shared data not present")


# ---------------------------------------------------------------------------------------------
# networks built directly as IR (the data loader needs only inputs, sensors and the unit)
# ---------------------------------------------------------------------------------------------


def tclab_net(unit: str = "degC") -> Network:
    return Network(
        name="tclab", temperature_unit=unit,
        inputs=[Input(name="Q1", unit="%", column="Q1_pct"), Input(name="Q2", unit="%", column="Q2_pct")],
        sensors=[Sensor(name="T1", node="h1", column="T1_degC"), Sensor(name="T2", node="h2", column="T2_degC")],
    )


def building_net(cols=("Ta", "Ps", "Ph", "yTi"), ps_unit="kW/m^2", ph_unit="kW") -> Network:
    ta, ps, ph, ti = cols
    return Network(
        name="building",
        inputs=[Input(name="Ta", is_temperature=True, column=ta), Input(name="Ps", unit=ps_unit, column=ps),
                Input(name="Ph", unit=ph_unit, column=ph)],
        sensors=[Sensor(name="Ti", node="i", column=ti)],
    )


def mixed_net(unit: str) -> Network:
    """One % input, one temperature input, two sensors."""
    return Network(
        name="mixed", temperature_unit=unit,
        inputs=[Input(name="Q", unit="%", column="Q"), Input(name="Ta", is_temperature=True, column="Ta")],
        sensors=[Sensor(name="A", node="a", column="TA"), Sensor(name="B", node="b", column="TB")],
    )


def write(path: Path, text: str) -> str:
    path.write_text(text, encoding="utf-8")
    return str(path)


def raises_data_error(fn, *args, **kw) -> DataError:
    with pytest.raises(DataError) as ei:
        fn(*args, **kw)
    return ei.value


# ---------------------------------------------------------------------------------------------
# Hypothesis: random valid frames round-trip
# ---------------------------------------------------------------------------------------------

finite = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, allow_infinity=False, width=64)


@st.composite
def frames(draw):
    n = draw(st.integers(min_value=2, max_value=30))
    dt = draw(st.sampled_from([0.5, 1.0, 2.0, 12.34, 60.0, 300.0, 900.0, 0.1234]))
    unit = draw(st.sampled_from(["degC", "K", "degF"]))
    sep = draw(st.sampled_from([",", ";", "\t"]))
    q = np.array(draw(st.lists(st.floats(0, 100, allow_nan=False, width=64), min_size=n, max_size=n)))
    ta = np.array(draw(st.lists(st.floats(-40, 60, allow_nan=False, width=64), min_size=n, max_size=n)))
    ya = np.array(draw(st.lists(finite, min_size=n, max_size=n)))
    yb = np.array(draw(st.lists(finite, min_size=n, max_size=n)))
    na = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    ya = np.where(na, np.nan, ya)
    order = draw(st.permutations(["time_s", "Q", "Ta", "TA", "TB", "extra"]))
    t0 = draw(st.sampled_from([0.0, 10.0, 1e6]))
    return dict(n=n, dt=dt, unit=unit, sep=sep, q=q, ta=ta, ya=ya, yb=yb, order=order, t0=t0)


def _cell(v: float) -> str:
    return "" if np.isnan(v) else repr(float(v))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(f=frames())
def test_random_frames_round_trip(tmp_path, f):
    n, dt = f["n"], f["dt"]
    cols = {"time_s": f["t0"] + np.arange(n) * dt, "Q": f["q"], "Ta": f["ta"], "TA": f["ya"], "TB": f["yb"],
            "extra": np.arange(n) * 3.0}
    lines = [f["sep"].join(f["order"])]
    for k in range(n):
        lines.append(f["sep"].join(_cell(cols[c][k]) for c in f["order"]))
    p = write(tmp_path / "frame.csv", "\n".join(lines) + "\n")
    (exp,) = read_data(mixed_net(f["unit"]), p)
    assert exp.dt == dt
    np.testing.assert_allclose(exp.t, np.arange(n) * dt, rtol=0, atol=1e-9 * dt * n)
    np.testing.assert_allclose(exp.inputs[:, 0], f["q"] * 0.01, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(exp.inputs[:, 1], to_kelvin(f["ta"], f["unit"]), rtol=1e-12)
    assert np.array_equal(np.isnan(exp.outputs[:, 0]), np.isnan(f["ya"]))
    np.testing.assert_allclose(exp.outputs[:, 0], to_kelvin(f["ya"], f["unit"]), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(exp.outputs[:, 1], to_kelvin(f["yb"], f["unit"]), rtol=1e-12, atol=1e-9)
    assert exp.input_names == ("Q", "Ta") and exp.output_names == ("A", "B")
    assert exp.time_column == "time_s" and exp.notes == ()
    # and back out through write_csv in the file's unit
    out = tmp_path / "out.csv"
    write_csv(out, exp.t, {"A": exp.outputs[:, 0], "B": exp.outputs[:, 1], "Q": exp.inputs[:, 0]}, f["unit"],
              kelvin=["A", "B"], digits=17)
    back = out.read_text().splitlines()
    assert back[0] == "time_s,A,B,Q"
    row = back[1].split(",")
    if np.isnan(f["ya"][0]):
        assert row[1] == ""
    else:
        assert float(row[1]) == pytest.approx(f["ya"][0], abs=1e-9)
    assert float(row[2]) == pytest.approx(f["yb"][0], abs=1e-9)


VALID = "time_s,Q,Ta,TA,TB\n0,10,20,30,31\n1,10,20,30.5,31\n2,50,21,,32\n3,50,21,31,33\n4,0,22,31.5,33\n"

mutations = st.one_of(
    st.tuples(st.just("delete"), st.integers(0, len(VALID) - 1), st.integers(1, 12)),
    st.tuples(st.just("insert"), st.integers(0, len(VALID)), st.text(min_size=1, max_size=6)),
    st.tuples(st.just("truncate"), st.integers(0, len(VALID)), st.just(0)),
    st.tuples(st.just("swap_lines"), st.integers(1, 5), st.integers(1, 5)),
    st.tuples(st.just("dup_line"), st.integers(1, 5), st.just(0)),
    st.tuples(st.just("cell"), st.integers(0, 29),
              st.sampled_from(["abc", "", "nan", "1e999", "--", "1,5", '"x"', "inf"])),
)


def _mutate(text: str, m) -> str:
    kind, a, b = m
    if kind == "delete":
        return text[:a] + text[a + b:]
    if kind == "insert":
        return text[:a] + b + text[a:]
    if kind == "truncate":
        return text[:a]
    lines = text.splitlines()
    if not lines:
        return text
    if kind == "swap_lines":
        a, b = min(a, len(lines) - 1), min(b, len(lines) - 1)
        lines[a], lines[b] = lines[b], lines[a]
        return "\n".join(lines) + "\n"
    if kind == "dup_line":
        a = min(a, len(lines) - 1)
        return "\n".join(lines[: a + 1] + [lines[a]] + lines[a + 1:]) + "\n"
    # cell: replace the (a % 25)-th data cell
    r = min(1 + (a // 5) % 5, len(lines) - 1)
    cells = lines[r].split(",")
    cells[a % len(cells)] = b
    lines[r] = ",".join(cells)
    return "\n".join(lines) + "\n"


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ms=st.lists(mutations, min_size=1, max_size=3))
def test_random_corruptions_give_data_error_or_a_valid_experiment(tmp_path, ms):
    text = VALID
    for m in ms:
        text = _mutate(text, m)
    p = write(tmp_path / "bad.csv", text)
    try:
        exps = read_data(mixed_net("degC"), p)
    except DataError as err:
        report = err.format()
        assert "error:" in report
        for d in err.diagnostics:  # every positioned diagnostic points into this file
            if d.span is not None:
                assert d.span.file == p and d.span.line >= 1 and d.span.col >= 1
        return
    assert exps  # a long gap splits the file into segments (tests/test_data_reliability.py)
    for exp in exps:
        assert exp.inputs.shape == (exp.n_steps, 2) and np.all(np.isfinite(exp.inputs))
        assert np.all(np.diff(exp.t) > 0)


# ---------------------------------------------------------------------------------------------
# Each error, with its position
# ---------------------------------------------------------------------------------------------


def test_missing_column_names_it_and_lists_the_columns(tmp_path):
    p = write(tmp_path / "a.csv", "time_s,Q1_pct,Q2,T1_degC,T2_degC\n0,1,2,3,4\n1,1,2,3,4\n")
    err = raises_data_error(read_data, tclab_net(), p)
    msg = err.format()
    assert f"{p}:1:1: error: column 'Q2_pct' (input Q2) not found" in msg
    assert "'time_s', 'Q1_pct', 'Q2', 'T1_degC', 'T2_degC'" in msg
    assert "hint:" in msg


def test_all_missing_columns_reported_at_once(tmp_path):
    p = write(tmp_path / "a.csv", "time_s,x,y\n0,1,2\n1,1,2\n")
    err = raises_data_error(read_data, tclab_net(), p)
    assert len(err.diagnostics) == 4


@pytest.mark.parametrize("text,line,what", [
    ("", 1, "empty"),
    ("\n\n", 1, "empty"),
    ("time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n", 1, "no data rows"),
    ("time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n", 2, "only one data row"),
])
def test_empty_and_one_row_files(tmp_path, text, line, what):
    p = write(tmp_path / "e.csv", text)
    err = raises_data_error(read_data, tclab_net(), p)
    assert what in err.format()
    assert err.diagnostics[0].span.line == line


def test_text_in_numeric_column_gives_row_and_value(tmp_path):
    p = write(tmp_path / "t.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n1,1,oops,3,4\n2,1,2,3,4\n")
    err = raises_data_error(read_data, tclab_net(), p)
    d = err.diagnostics[0]
    assert (d.span.line, d.span.col, d.span.end_col) == (3, 5, 9)
    assert "'oops'" in d.message and "Q2_pct" in d.message and "line 3" in d.message
    assert "^^^^" in err.format()


def test_nan_in_input_names_the_rows(tmp_path):
    rows = "\n".join(f"{k},{'' if k in (3, 4, 5, 9) else 1},2,3,4" for k in range(12))
    p = write(tmp_path / "n.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n" + rows + "\n")
    err = raises_data_error(read_data, tclab_net(), p)
    (d,) = err.diagnostics
    assert "input Q1" in d.message and "lines 5-7, 11" in d.message
    assert d.span.line == 5


def test_nan_in_sensor_is_kept(tmp_path):
    p = write(tmp_path / "s.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n1,1,2,NaN,4\n2,1,2,,4\n3,1,2,3,4\n")
    (exp,) = read_data(tclab_net(), p)
    assert np.isnan(exp.outputs[1:3, 0]).all() and np.isfinite(exp.outputs[:, 1]).all()


def test_non_monotonic_and_duplicate_time(tmp_path):
    p = write(tmp_path / "m.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n2,1,2,3,4\n1,1,2,3,4\n1,1,2,3,4\n")
    err = raises_data_error(read_data, tclab_net(), p)
    msgs = [d.message for d in err.diagnostics]
    assert any("time goes backwards at line 4" in m for m in msgs)
    assert any("duplicate time '1' at line 5" in m for m in msgs)


def test_ragged_row(tmp_path):
    p = write(tmp_path / "r.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n1,1,2,3\n")
    err = raises_data_error(read_data, tclab_net(), p)
    assert err.diagnostics[0].span.line == 3 and "expected 5 fields" in err.diagnostics[0].message


def test_missing_file_and_no_time_column(tmp_path):
    err = raises_data_error(read_data, tclab_net(), tmp_path / "nope.csv")
    assert "not found" in err.format()
    p = write(tmp_path / "nt.csv", "Q1_pct,Q2_pct,T1_degC,T2_degC\n1,2,3,4\n1,2,3,4\n")
    err = raises_data_error(read_data, tclab_net(), p)
    assert "no time column" in err.format() and "--time-col" in err.format()
    (exp,) = read_data(tclab_net(), p, dt=5.0)  # equally spaced rows by --dt
    assert exp.dt == 5.0 and exp.t.tolist() == [0.0, 5.0] and "no time column" in exp.notes[0]


def test_problems_in_several_files_reported_together(tmp_path):
    a = write(tmp_path / "a.csv", "")
    b = write(tmp_path / "b.csv", "time_s,x\n0,1\n1,2\n")
    err = raises_data_error(read_data, tclab_net(), [a, b])
    files = {d.span.file for d in err.diagnostics}
    assert files == {a, b}


# ---------------------------------------------------------------------------------------------
# Time handling, units, resampling
# ---------------------------------------------------------------------------------------------


def test_time_column_choice_and_suffix_units(tmp_path):
    p = write(tmp_path / "h.csv", "time_h,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,3,4\n0.5,1,2,3,4\n1,1,2,3,4\n")
    (exp,) = read_data(tclab_net(), p)
    assert exp.dt == 1800.0 and exp.t[-1] == 3600.0
    (exp,) = read_data(tclab_net(), p, time_col="time_h", time_unit="min")
    assert exp.dt == 30.0
    err = raises_data_error(read_data, tclab_net(), p, time_col="clock")
    assert "time column 'clock' not found" in err.format()


def test_iso_timestamps_with_time_zone(tmp_path):
    p = write(tmp_path / "z.csv", ",Q1_pct,Q2_pct,T1_degC,T2_degC\n2021-03-28 00:00:00+01:00,1,2,3,4\n"
                                  "2021-03-28 00:15:00+01:00,1,2,3,4\n2021-03-27 23:30:00+00:00,1,2,3,4\n")
    (exp,) = read_data(tclab_net(), p)
    assert exp.dt == 900.0 and exp.t.tolist() == [0.0, 900.0, 1800.0]
    assert exp.start == "2021-03-28 00:00:00+01:00" and exp.time_column == ""


def test_irregular_sampling_is_resampled(tmp_path):
    # inputs: a step; sensor: a ramp T = 20 + t (linear interpolation is exact for it)
    t = np.array([0.0, 1.0, 2.5, 3.0, 4.2, 5.0, 6.1, 7.0])
    q = np.array([0, 0, 100, 100, 50, 50, 0, 0.0])
    rows = "\n".join(f"{a},{b},0,{20 + a},{20 + 2 * a}" for a, b in zip(t, q))
    p = write(tmp_path / "i.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n" + rows + "\n")
    (exp,) = read_data(tclab_net(), p, dt=1.0)
    assert exp.t.tolist() == list(np.arange(8.0))
    np.testing.assert_allclose(exp.outputs[:, 0], 273.15 + 20 + exp.t)
    np.testing.assert_allclose(exp.outputs[:, 1], 273.15 + 20 + 2 * exp.t)
    # the interval mean of the held input: [2,3) holds 0 for 0.5 s and 100 % for 0.5 s → 0.5
    np.testing.assert_allclose(exp.inputs[:, 0], [0, 0, 0.5, 1.0, 0.6, 0.5, 0.05, 0.0], atol=1e-12)
    # the held signal's integral (heat delivered) over [0, 7) s is preserved: 0.5·1 + 1.2·1 + 0.8·0.5 + 1.1·0.5
    assert exp.inputs[:-1, 0].sum() * exp.dt == pytest.approx(2.65, abs=1e-12)
    assert any("resampled" in n and "irregular" in n for n in exp.notes)


def test_resampling_keeps_nan_sensor_gaps(tmp_path):
    p = write(tmp_path / "g.csv",
              "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,1,2,20,4\n1.5,1,2,,4\n3,1,2,23,4\n4,1,2,24,4\n")
    (exp,) = read_data(tclab_net(), p, dt=1.0)
    y = exp.outputs[:, 0] - 273.15
    assert y[0] == pytest.approx(20.0) and np.isnan(y[1]) and np.isnan(y[2]) and y[3] == pytest.approx(23.0)


def test_decimal_comma_in_semicolon_files_and_leading_blank_lines(tmp_path):
    p = write(tmp_path / "eu.csv", "\n\ntime_s;Q1_pct;Q2_pct;T1_degC;T2_degC\n0;1,5;2;20,25;4\n1;1;2;x;4\n")
    err = raises_data_error(read_data, tclab_net(), p)
    (d,) = err.diagnostics
    assert d.span.line == 5 and d.span.col == 7 and "'x'" in d.message
    p = write(tmp_path / "eu.csv", "time_s;Q1_pct;Q2_pct;T1_degC;T2_degC\n0;1,5;2;20,25;4\n1;1;2;3;4\n")
    (exp,) = read_data(tclab_net(), p)
    assert exp.inputs[0, 0] == pytest.approx(0.015) and exp.outputs[0, 0] == pytest.approx(293.4)


def test_missing_sensor_column_can_be_allowed(tmp_path):
    p = write(tmp_path / "u.csv", "time_s,Q1_pct,Q2_pct,T1_degC\n0,1,2,3\n1,1,2,3\n")
    (exp,) = read_data(tclab_net(), p, require_outputs=False)
    assert np.isnan(exp.outputs[:, 1]).all() and exp.output_columns == ("T1_degC", None)
    assert any("T2_degC" in n for n in exp.notes)


def test_parquet_round_trip(tmp_path):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    df = pd.DataFrame({"time_s": [0.0, 2.0, 4.0], "Q1_pct": [0, 50, 100], "Q2_pct": [1, 2, 3],
                       "T1_degC": [20.0, np.nan, 22.0], "T2_degC": [1.0, 2.0, 3.0]})
    p = str(tmp_path / "d.parquet")
    df.to_parquet(p)
    (exp,) = read_data(tclab_net(), p)
    assert exp.dt == 2.0 and exp.inputs[:, 0].tolist() == [0.0, 0.5, 1.0] and np.isnan(exp.outputs[1, 0])
    df.loc[1, "Q1_pct"] = np.nan
    df.to_parquet(p)
    err = raises_data_error(read_data, tclab_net(), p)
    assert f"{p}: input Q1" in err.format() and "rows 2" in err.format()


def test_split_by_time(tmp_path):
    rows = "\n".join(f"{k},{k},0,{k},{k}" for k in range(10))
    p = write(tmp_path / "s.csv", "time_s,Q1_pct,Q2_pct,T1_degC,T2_degC\n" + rows + "\n")
    (exp,) = read_data(tclab_net(), p)
    a, b = split_by_time(exp, 0.7)
    assert (a.n_steps, b.n_steps) == (7, 3) and b.t[0] == 7.0 and a.name == "s[:70%]" and b.name == "s[70%:]"
    np.testing.assert_array_equal(np.concatenate([a.inputs, b.inputs]), exp.inputs)
    with pytest.raises(DataError):
        split_by_time(exp, 0.95)


def test_temperature_conversions_are_inverse():
    x = np.linspace(-50, 150, 11)
    for u in ("degC", "K", "degF"):
        np.testing.assert_allclose(from_kelvin(to_kelvin(x, u), u), x, atol=1e-12)
    assert to_kelvin(32.0, "degF") == pytest.approx(273.15) and to_kelvin(0.0, "degC") == 273.15


# ---------------------------------------------------------------------------------------------
# The real files
# ---------------------------------------------------------------------------------------------


NETWORKS = Path(__file__).resolve().parents[1] / "networks"


def _shipped(rel: str) -> Network:
    import tnn_dsl

    return tnn_dsl.load(str(NETWORKS / rel))


@needs_data
def test_real_tclab_files():
    net = _shipped("tclab/tclab.thn")
    prbs, steps, cool = read_data(net, [DATA / "tclab_kuntz_rawlings_prbs_openloop.csv",
                                        DATA / "tclab_apmonitor_energy_balance_steps.csv",
                                        DATA / "tclab_kuntz_rawlings_closedloop_cooldown.csv"])
    iq1 = list(prbs.input_names).index("Q1")
    it1 = list(prbs.output_names).index("T1")
    assert prbs.inputs.shape[0] == 5100 and prbs.dt == 1.0 and prbs.notes == ()
    assert prbs.outputs[0, it1] == pytest.approx(43.457 + 273.15)
    assert set(np.round(prbs.inputs[:, iq1], 6)) <= {0.2, 0.3, 0.4}  # 20/30/40 % as fractions
    # APMonitor's clock jitters (0.99 … 1.021 s): resampled to 1 s, and said so
    assert steps.dt == 1.0 and any("irregular" in n for n in steps.notes)
    assert steps.n_steps == 599 and steps.inputs[:, iq1].max() == pytest.approx(1.0)
    assert 19 < steps.outputs[0, it1] - 273.15 < 22
    assert cool.n_steps == 5100 and np.all(np.isfinite(cool.outputs))


@needs_data
@pytest.mark.parametrize("rel", ["building/ti.thn", "building/tith.thn", "building/tite.thn", "building/titeth.thn"])
def test_real_building_file_with_the_shipped_building_networks(rel):
    net = _shipped(rel)
    (bm,) = read_data(net, DATA / "bacher_madsen_inputPRBS1.csv")
    assert bm.input_names == ("Ta", "Ps", "Ph") and bm.output_names == ("Ti",)
    assert bm.inputs.shape == (1691, 3) and bm.outputs.shape == (1691, 1) and bm.dt == 300.0
    np.testing.assert_allclose(bm.inputs[0], [1.1802 + 273.15, 23.0051071428571, 4825.33333333333], rtol=1e-12)
    assert bm.outputs[0, 0] == pytest.approx(21.1590634257453 + 273.15, rel=1e-14)


@needs_data
def test_real_building_files():
    (bm,) = read_data(building_net(), DATA / "bacher_madsen_inputPRBS1.csv")
    # `t` is hours; the TimeDate column says so, and the loader infers it (with a note)
    assert bm.dt == 300.0 and bm.n_steps == 1691 and bm.t[-1] == pytest.approx(140.83333 * 3600, rel=1e-6)
    assert any("hours" in n for n in bm.notes)
    assert bm.inputs[0, 2] == pytest.approx(4825.333333, rel=1e-6)  # kW → W
    assert bm.outputs[0, 0] == pytest.approx(21.1590634257453 + 273.15)
    (bm2,) = read_data(building_net(), DATA / "bacher_madsen_inputPRBS1.csv", time_col="t", time_unit="h")
    np.testing.assert_array_equal(bm2.outputs, bm.outputs)
    (lp,) = read_data(building_net(("Ta", "Ps", "Thm", "yTi"), ps_unit="1", ph_unit="1"),
                      DATA / "leprince_fiftyshades_blg_1.csv")
    assert lp.dt == 900.0 and lp.n_steps == 4181 and lp.start == "2021-11-22 09:00:00" and lp.time_column == "t"
    (dg,) = read_data(building_net(("Ta", "Th", "Ph", "Ti"), ps_unit="1"), DATA / "darkgreybox_demo_data.csv")
    assert dg.dt == 3600.0 and dg.n_steps == 792 and dg.start.startswith("2019-12-23 00:00:00")
    (ps,) = read_data(building_net(("T_ext", "I_sol", "P_hea", "T_int"), ps_unit="W/m^2", ph_unit="W"),
                      DATA / "pysip_armadillo_data_H2.csv")
    assert ps.dt == 1800.0 and ps.n_steps == 233 and ps.time_column == "Time"
    for e in (bm, lp, dg, ps):
        assert isinstance(e, Experiment) and np.all(np.isfinite(e.inputs))
        assert 250 < np.nanmin(e.outputs) and np.nanmax(e.outputs) < 320  # kelvin, indoor temperatures


@settings(max_examples=300, deadline=None)
@given(cells=st.lists(st.one_of(st.text(alphabet="0123456789.eE+- \t", max_size=8),
                                st.floats(allow_nan=False).map(repr),
                                st.sampled_from(["", "nan", "NA", "-", "1,5", "inf", "1_0", "x"])), max_size=12))
def test_plain_numbers_agree_with_pandas_or_leave_the_column_to_it(cells):
    """The numeric fast path (no pandas import) reads a column exactly as ``pandas.to_numeric(errors="coerce")``
    does, or declines it (None) and pandas' parser with its diagnostics decides."""
    import pandas as pd

    from tnn_dsl.data.tables import _plain_numbers

    text = np.array(cells, dtype=object)
    got = _plain_numbers(text)
    if got is None:
        return
    want = pd.to_numeric(pd.Series(text, dtype=object).str.strip(), errors="coerce").to_numpy(dtype=np.float64)
    assert got.shape == want.shape
    assert np.array_equal(got, want, equal_nan=True), (cells, got, want)


def test_reading_a_plain_numeric_csv_does_not_import_pandas(tmp_path):
    """pandas holds 60–90 MB for the rest of the process (issue 18's diagnosis memory): a CSV of plain numbers, blank
    cells and a numeric time column is read without it; a missing-value marker still goes through its parser."""
    import subprocess
    import sys

    csv = tmp_path / "d.csv"
    csv.write_text("time,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,10,0,20.5,21\n1,10,0,,21.25\n2,20,5,20.75,21.5\n")
    marked = tmp_path / "m.csv"
    marked.write_text("time,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,10,0,20.5,21\n1,10,0,NA,21.25\n2,20,5,20.75,21.5\n")
    code = ("import sys, json; sys.path.insert(0, sys.argv[1]); import test_data as T; from tnn_dsl.data import "
            "read_data; out = []\nfor p in sys.argv[2:]:\n    e = read_data(T.tclab_net(), p)[0]\n"
            "    out.append(['pandas' in sys.modules, e.outputs[:, 0].tolist()])\nprint(json.dumps(out))")
    res = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent), str(csv), str(marked)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    import json

    (plain_pandas, plain_t1), (marked_pandas, marked_t1) = json.loads(res.stdout.strip().splitlines()[-1])
    assert plain_pandas is False and marked_pandas is True
    assert plain_t1[0] == pytest.approx(293.65) and plain_t1[1] != plain_t1[1]  # kelvin; the blank cell is NaN
    assert marked_t1[1] != marked_t1[1]


def test_networks_that_read_a_file_alike_have_one_key_and_read_the_same_experiments(tmp_path):
    """``columns_read``: the case study's five networks read their files alike (one key: the study reads each
    out-of-distribution file once for all five); another column, unit or temperature unit is another key, and a
    network with the same key reads the same arrays."""
    import tnn_dsl
    from tnn_dsl.data import columns_read

    root = Path(__file__).resolve().parents[1] / "networks" / "peltier_heatpipe"
    keys = {columns_read(tnn_dsl.load(root / f"m{i}.thn")) for i in range(1, 5)}
    assert len(keys) == 1
    base = tclab_net()
    renamed = base.model_copy(update={"sensors": [base.sensors[0], base.sensors[1].model_copy(update={"column": "x"})]})
    watts = base.model_copy(update={"inputs": [base.inputs[0].model_copy(update={"unit": "W"}), base.inputs[1]]})
    assert len({columns_read(n) for n in (base, renamed, watts, tclab_net("K"))}) == 4
    csv = tmp_path / "d.csv"
    csv.write_text("time,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,10,0,20.5,21\n1,10,0,,21.25\n2,20,5,20.75,21.5\n")
    twin = tclab_net().model_copy(update={"name": "another"})
    assert columns_read(twin) == columns_read(base)
    (a,), (b,) = read_data(base, csv), read_data(twin, csv)
    np.testing.assert_array_equal(a.inputs, b.inputs)
    np.testing.assert_array_equal(a.outputs, b.outputs)


def test_cells_around_which_any_whitespace_stands_are_read_as_their_numbers(tmp_path):
    """A cell is read stripped of what ``str.strip`` strips, a non-breaking space or a form feed too (spreadsheet
    exports), as before the reader skipped stripping files without whitespace."""
    csv = tmp_path / "d.csv"
    csv.write_text("time,Q1_pct,Q2_pct,T1_degC,T2_degC\n0,10\xa0,0,20.5,21\n1,10,0,\x0c20.75,21.25\n", encoding="utf-8")
    (e,) = read_data(tclab_net(), csv)
    np.testing.assert_allclose(e.inputs[:, 0], [0.10, 0.10])
    np.testing.assert_allclose(e.outputs[:, 0], [293.65, 293.9])
