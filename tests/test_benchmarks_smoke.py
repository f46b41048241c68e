"""Keep the benchmarks working: the report writer, the C reference loop, and a tiny end-to-end run of
``benchmarks/bench_rollout.py`` (a few hundred steps; timings are not checked, only that every part runs,
agrees and is reported)."""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import _report  # noqa: E402

HAS_CC = any(shutil.which(c) for c in ("cc", "gcc", "clang"))


# ---------------------------------------------------------------------------------------------
# _report.write_section
# ---------------------------------------------------------------------------------------------


def test_write_section_creates_replaces_and_appends(tmp_path, monkeypatch):
    monkeypatch.setattr(_report, "SPEED_LOOP", 10**5)  # the host's speed in a hundredth of the time
    path = tmp_path / "B.md"
    _report.write_section("alpha", "first body", path=path, command="python a.py")
    text = path.read_text()
    assert text.startswith("# Benchmarks")
    assert "<!-- begin alpha -->" in text and "<!-- end alpha -->" in text
    assert "first body" in text and "python a.py" in text
    for key in ("cpu", "cores", "python", "jax", "torch"):
        assert f"{key} " in text.split("<!-- begin alpha -->")[1]
    speed = re.search(r"Python speed at write ([0-9.]+) s per 10⁵ additions", text)
    assert speed is not None and 0 < float(speed.group(1)) < 60, text

    _report.write_section("beta", "beta body", path=path, command="python b.py")
    path.write_text(path.read_text() + "\nhand-written note\n")
    _report.write_section("alpha", "second body", path=path, command="python a.py --quick")
    text = path.read_text()
    assert "first body" not in text and "second body" in text
    assert text.count("<!-- begin alpha -->") == 1 and text.count("<!-- end alpha -->") == 1
    assert "beta body" in text and "hand-written note" in text
    assert text.index("second body") < text.index("beta body")  # replaced in place, not appended


def test_write_section_refuses_bad_names_and_broken_files(tmp_path):
    path = tmp_path / "B.md"
    with pytest.raises(ValueError):
        _report.write_section("bad name", "x", path=path)
    path.write_text("<!-- begin gamma -->\nno end marker\n")
    with pytest.raises(ValueError, match="no"):
        _report.write_section("gamma", "x", path=path)
    assert path.read_text() == "<!-- begin gamma -->\nno end marker\n"  # untouched


def test_machine_info_names_versions(monkeypatch):
    monkeypatch.setattr(_report, "SPEED_LOOP", 10**5)
    info = _report.machine_info()
    assert int(info["cores"]) >= 1
    assert info["python"].count(".") == 2
    assert info["jax"] != "" and info["torch"] != ""


# ---------------------------------------------------------------------------------------------
# The C loop against the numpy reference backend
# ---------------------------------------------------------------------------------------------


@pytest.mark.skipif(not HAS_CC, reason="no C compiler")
@pytest.mark.parametrize("integrator", ["euler", "rk4"])
def test_c_loop_matches_numpy_backend(integrator):
    from _c_loop import build_c_rollout
    from bench_rollout import NET, case_inputs, random_weights

    import tnn_dsl

    net = tnn_dsl.load(NET)
    model = tnn_dsl.compile(net, "numpy")
    params = random_weights(model, seed=3)
    U = case_inputs(model, 300, 1.0, seed=3)
    U[:, 0] = np.linspace(0.0, 3.0, len(U))  # make the Peltier current vary within the short window
    T0 = np.full(len(model.state_names), 300.0)
    states, _ = model.rollout(params, T0, U, 1.0, integrator, substeps=1)
    c = build_c_rollout(model, params, 1.0, integrator, 1)
    try:
        S = c.rollout(T0, U)
        assert np.max(np.abs(S - states)) < 1e-9
        assert np.max(np.abs(S[-1] - S[0])) > 1e-3  # the states moved: the comparison means something
        Sb = c.rollout_batch(np.stack([T0, T0 + 1.0]), np.stack([U, U]))
        assert np.max(np.abs(Sb[0] - S)) < 1e-12
        assert np.max(np.abs(Sb[1] - S)) > 1e-3
    finally:
        c.close()


# ---------------------------------------------------------------------------------------------
# End to end (tiny sizes)
# ---------------------------------------------------------------------------------------------


def test_bench_rollout_tiny_run(tmp_path):
    out_md = tmp_path / "BENCHMARKS.md"
    out_json = tmp_path / "r.json"
    cmd = [sys.executable, str(BENCH / "bench_rollout.py"), "--steps", "300", "--batch", "4", "--slow-steps", "60",
           "--repeats", "1", "--only", "jax,torch,numpy,c", "--output", str(out_md), "--json", str(out_json)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    data = json.loads(out_json.read_text())
    impls = {(r["impl"], r["case"]) for r in data["rows"]}
    expected = {("JAX", "single"), ("JAX", "batch"), ("torch (eager)", "single"), ("torch (eager)", "batch"),
                ("numpy reference", "single"), ("numpy reference", "batch")}
    if HAS_CC:
        expected |= {("C loop", "single"), ("C loop", "batch")}
    assert expected <= impls
    for r in data["rows"]:
        assert r["fwd_us_per_step"] is not None and math.isfinite(r["fwd_us_per_step"]) and r["fwd_us_per_step"] > 0
        if r["impl"] in ("JAX", "torch (eager)"):
            assert r["grad_us_per_step"] > 0
    if HAS_CC:
        assert data["c_max_abs_diff_K"] <= 1e-9
    agree = data["agreement"]
    assert agree["torch_vs_jax_states_single_K"] <= 1e-9
    assert agree["torch_vs_jax_states_batch_K"] <= 1e-9
    assert agree["torch_vs_jax_grad_batch_rel"] <= 1e-6
    whats = [t["what"] for t in data["targets"]]
    assert any("JAX single sequence" in w for w in whats) and any(w.startswith("torch eager / JAX") for w in whats)
    text = out_md.read_text()
    assert "<!-- begin rollout -->" in text and "<!-- end rollout -->" in text
    assert "Machine:" in text and "bench_rollout.py" in text


def test_bench_xla_floor_quick_run(tmp_path):
    """The XLA-floor benchmark runs, counts the model's fusions and writes its section (timings unchecked)."""
    out_md = tmp_path / "BENCHMARKS.md"
    res = subprocess.run([sys.executable, str(BENCH / "bench_xla_floor.py"), "--quick", "--output", str(out_md)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    text = out_md.read_text()
    assert "<!-- begin xla-floor -->" in text and "<!-- end xla-floor -->" in text
    m = re.search(r"has (\d+) fusions in its loop body", text)
    assert m and 5 <= int(m.group(1)) <= 200, text
    assert text.count("| batch leading") == 2 and text.count("| batch trailing") == 2


def test_run_all_discovers_benchmarks():
    res = subprocess.run([sys.executable, str(BENCH / "run_all.py"), "--list"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0
    assert "benchmarks/bench_rollout.py" in res.stdout.split()
    assert "_report" not in res.stdout and "run_all" not in res.stdout


@pytest.mark.skipif(not (ROOT.parent / "shared" / "data" / "bacher_madsen_inputPRBS1.csv").exists(),
                    reason="shared building data not present")
def test_bench_real_data_fits_tiny_run(tmp_path):
    """The real-data benchmark trains Ti three ways (a few epochs), scores each and writes its section."""
    out_md = tmp_path / "BENCHMARKS.md"
    out_json = tmp_path / "r.json"
    cmd = [sys.executable, str(BENCH / "bench_real_data_fits.py"), "--quick", "--only", "ti", "--epochs", "5",
           "--lbfgs-iters", "5", "--output", str(out_md), "--json", str(out_json)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads(out_json.read_text())["rows"]
    assert [r["way"] for r in rows] == ["default", "free+estimate", "windows"]
    for r in rows:
        for key in ("train_mae", "heldout_mae", "continued_mae", "fit_s"):
            assert math.isfinite(r[key]) and r[key] > 0, (key, r)
    text = out_md.read_text()
    assert "<!-- begin real-data-fits -->" in text and "<!-- end real-data-fits -->" in text
    assert text.count("| ti | B&M (1184 / 507) |") == 3


def test_bench_scaling_tiny_run(tmp_path):
    # one size on one backend, both forms: every column is filled and the slope table is printed (a 4 × 4 plate: the
    # same code paths as 225 nodes, 9 against 15 s here; 21 s in CI at 225, 2026-12-05)
    out = tmp_path / "scaling.json"
    cmd = [sys.executable, str(BENCH / "bench_scaling.py"), "--sizes", "16", "--backends", "jax",
           "--no-write", "--json", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    data = json.loads(out.read_text())
    rows = data["sizes"]
    assert [(r["nodes"], r["form"]) for r in rows] == [(16, "sparse"), (16, "dense")]
    for r in rows:
        assert "error" not in r, r
        assert r["us_per_step"] > 0 and r["steady_residual"] < 1e-9
    assert data["end_to_end"] == []
    assert "log-log slope" in res.stdout


def test_bench_diagnose_splits_the_progress_lines_into_phases():
    """The diagnosis benchmark's phase table: a candidate's fit lines are one phase, each phase gets the highest RSS
    sampled in it (with its anonymous and file-backed parts at that sample) and its length."""
    import bench_diagnose

    lines = [(0.0, "[ 0.0 s] building candidates from the network ..."),
             (2.0, "[ 2.0 s] round 1: score test over 3 candidates ..."),
             (5.0, "[ 5.0 s]   fitting a depends on u (k=1) ..."), (6.0, "[ 6.0 s]     fitted in 1 s (4 iterations)"),
             (7.0, "[ 7.0 s]   continuing a depends on u ..."),
             (9.0, "[ 9.0 s] fitting it again from the values written in the file ...")]
    trace = [(0.5, 100.0, 60.0, 40.0), (3.0, 900.0, 800.0, 100.0), (3.5, 850.0, 700.0, 150.0),
             (5.5, 400.0, 300.0, 100.0), (8.0, 450.0, 320.0, 130.0), (9.5, 300.0, 200.0, 100.0)]
    rows = bench_diagnose.phases({"lines": lines, "trace": trace, "wall_s": 10.0})
    assert len(rows) == 4
    assert rows[1].startswith("| 2.0 | 3.0 | round 1: score test") and rows[1].endswith("| 900 (800 + 100) |")
    assert "fitting candidates" in rows[2] and rows[2].startswith("| 5.0 | 4.0 |")
    assert rows[2].endswith("| 450 (320 + 130) |")
    assert "fitting it again" in rows[3]


def test_bench_train_curves_put_the_runs_side_by_side():
    """``bench_train.py --curve``: per model, each backend's validation MAE (mK) at the epochs both logged, a blank
    where one run had ended, and the epoch each run ended at."""
    import bench_train

    rows = [{"model": "m3", "backend": "jax", "last_epoch": 1300,
             "curve": [(0, "start", 0.1), (50, "adam", 0.0142), (1300, "lbfgs", 0.0028)]},
            {"model": "m3", "backend": "torch-compiled", "curve": [(0, "start", 0.1), (50, "adam", 0.0142)],
             "last_epoch": 1030},
            {"model": "m3", "backend": "torch", "error": "not finished within 60 s"}]
    text = bench_train._curves(rows)
    lines = text.splitlines()
    assert lines[0] == "M3 validation MAE (mK) every 50 epochs:"
    assert "| epoch | jax | torch-compiled |" in lines
    assert "| 50 | 14.2000 (adam) | 14.2000 (adam) |" in lines
    assert "| 1300 | 2.8000 (lbfgs) |  |" in lines
    assert "| ended at | 1300 | 1030 |" in lines


def test_bench_train_spread_groups_the_repeated_runs_by_backend():
    """``bench_train.py --polish-jitter REL --repeats N``: the final MAEs of each backend's runs (mK), their range,
    median and max / min, whatever the seed in the row's label; failed runs left out."""
    import bench_train

    label = " (polish start × (1 + 1e-12·ε), seed {})"
    rows = [{"model": "m3", "backend": "jax" + label.format(k), "final_val_mae": v}
            for k, v in ((1, 0.003351), (2, 0.003321), (3, 0.002915))]
    rows += [{"model": "m3", "backend": "torch-compiled" + label.format(1), "final_val_mae": 0.0028},
             {"model": "m3", "backend": "torch-compiled" + label.format(2), "error": "not finished within 60 s"}]
    lines = bench_train._spread(rows).splitlines()
    assert "| M3 | jax | 3.351, 3.321, 2.915 | 2.915 | 3.321 | 3.351 | 1.15 |" in lines
    assert "| M3 | torch-compiled | 2.800 | 2.800 | 2.800 | 2.800 | 1.00 |" in lines
