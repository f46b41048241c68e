"""The case-study generator (tnn_dsl.studies.casestudy; shared/spec/case-study.md)."""

from __future__ import annotations

import json
import os

import numpy as np
import pandas as pd
import pytest

from tnn_dsl.studies.casestudy import (
    HOLD_S,
    case_study_inputs,
    generate_case_study,
    step_sequence,
    truth_network_path,
    widened_bounds,
)


def _runs(x: np.ndarray) -> list[tuple[int, int]]:
    """(start, length) of each run of equal values."""
    change = np.flatnonzero(np.diff(x) != 0) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [len(x)]])
    return list(zip(starts.tolist(), (ends - starts).tolist()))


# ---------------------------------------------------------------------------------------------
# inputs (no simulation)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2, 7, 100])
def test_steps_hold_times_and_bounds(seed):
    sig = case_study_inputs(seed, 4 * 3600)
    assert all(v.shape == (14401,) for v in sig.values())
    for name, (lo, hi) in (("I", (0.0, 3.0)), ("u1", (0.0, 1.0))):
        x = sig[name]
        assert lo <= x.min() and x.max() <= hi
        runs = _runs(x)
        assert len(runs) >= 4 * 3600 // 600
        for _start, length in runs[:-1]:  # the last run is cut by the end of the set
            assert HOLD_S[0] <= length <= HOLD_S[1]
        assert runs[-1][1] <= HOLD_S[1]
    np.testing.assert_array_equal(sig["Ta"], 22.0)
    np.testing.assert_array_equal(sig["Tf1"], 25.0)
    np.testing.assert_array_equal(sig["Tf2"], 25.0)


def test_inputs_are_deterministic_and_seeds_independent():
    a, b = case_study_inputs(1, 3600), case_study_inputs(1, 3600)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    c = case_study_inputs(2, 3600)
    assert not np.array_equal(a["I"], c["I"])
    # I and u1 come from independent streams: they do not switch together
    sw_i = set(np.flatnonzero(np.diff(a["I"]) != 0))
    sw_u = set(np.flatnonzero(np.diff(a["u1"]) != 0))
    assert sw_i != sw_u


def test_levels_are_uniform_over_the_bounds():
    rng = np.random.default_rng(0)
    x = step_sequence(rng, 2_000_000, 0.0, 3.0)
    levels = np.array([x[s] for s, _ in _runs(x)])
    holds = np.array([n for _, n in _runs(x)][:-1])
    assert len(levels) > 4000
    hist, _ = np.histogram(levels, bins=6, range=(0, 3))
    expected = len(levels) / 6
    assert np.all(np.abs(hist - expected) < 5 * np.sqrt(expected))  # ~5 σ
    assert holds.min() == 120 and holds.max() == 600
    assert abs(holds.mean() - 360) < 5


@pytest.mark.parametrize("p", [0.1, 0.4])
def test_widening_keeps_switch_times_and_stretches_levels(p):
    base, wide = case_study_inputs(100, 7200), case_study_inputs(100, 7200, widen=p)
    b = widened_bounds(p)
    assert b == {"I": (0.0, 3.0 * (1 + p)), "u1": (-p, 1 + p)}
    for name in ("I", "u1"):
        np.testing.assert_array_equal(np.diff(base[name]) != 0, np.diff(wide[name]) != 0)
        lo, hi = b[name]
        assert lo <= wide[name].min() and wide[name].max() <= hi
    # the same uniform draw mapped to the wider interval
    lo0, hi0 = (0.0, 3.0)
    lo, hi = b["I"]
    np.testing.assert_allclose((wide["I"] - lo) / (hi - lo), (base["I"] - lo0) / (hi0 - lo0), atol=1e-6)


def test_truth_network_is_found():
    p = truth_network_path()
    assert p.name == "truth.thn" and p.is_file()


# ---------------------------------------------------------------------------------------------
# the true system: the shipped network against the spec's equations, written out by hand
# ---------------------------------------------------------------------------------------------

NODES = ("ph", "pc", "hs", "hx1", "hp", "hx2", "base")
C = dict(ph=40, pc=40, hs=600, hx1=300, hp=60, hx2=300, base=800)


def spec_rhs(T: dict, I: float, u1: float, Ta: float, Tf1: float, Tf2: float) -> dict:
    """dT/dt (K/s) of the true system as shared/spec/case-study.md states it; all temperatures K."""
    mean = lambda a, b: 0.5 * (T[a] + T[b])  # noqa: E731
    R = {
        ("ph", "hs"): 0.08, ("pc", "hx1"): 0.05, ("hs", "amb"): 0.3, ("base", "hs"): 2.0,
        ("base", "hx1"): 2.0, ("base", "amb"): 3.0, ("pc", "ph"): 1.5,
        # the spec's law, floored at 0.1 as truth.thn documents (binds only far out of distribution)
        ("hx1", "hp"): 0.2 * max(0.1, 1 + 1.5 * (u1 - 0.5) - 0.02 * (mean("hx1", "hp") - 298.15)),
        ("hp", "hx2"): 0.2 * max(0.1, 1 + 1.2 * (u1 - 0.5) - 0.02 * (mean("hp", "hx2") - 298.15)),
        ("hp", "amb"): 10.0 * (1 + 0.3 * (u1 - 0.5)),
    }
    temp = dict(T, amb=Ta)
    Q = {n: 0.0 for n in NODES}
    for (a, b), r in R.items():
        q = (temp[b] - temp[a]) / r
        if a in Q:
            Q[a] += q
        if b in Q:
            Q[b] -= q
    S, Rel = 0.05, 2.0
    Q["pc"] += -S * T["pc"] * I + 0.5 * Rel * I**2
    Q["ph"] += S * T["ph"] * I + 0.5 * Rel * I**2
    mcp = 0.002 * 4186
    eff = 1 - np.exp(-5.0 / mcp)
    Q["hx1"] += mcp * eff * (Tf1 - T["hx1"])
    Q["hx2"] += mcp * eff * (Tf2 - T["hx2"])
    return {n: Q[n] / C[n] for n in NODES}


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_truth_network_matches_the_spec(backend):
    import tnn_dsl
    from tnn_dsl.compiler.model import compile as compile_network

    net = tnn_dsl.load(str(truth_network_path()))
    model = compile_network(net, backend=backend, dtype="float64")
    params = model.init_params(seed=0)
    assert tuple(model.state_names) == NODES and tuple(model.output_names) == ("T_out",)
    rng = np.random.default_rng(3)
    for _ in range(5):
        T = {n: 273.15 + rng.uniform(10, 60) for n in NODES}
        u = dict(I=rng.uniform(0, 4), u1=rng.uniform(-0.4, 1.4), Ta=295.15, Tf1=298.15, Tf2=298.15 + rng.uniform(-3, 3))
        x = np.array([T[n] for n in NODES])
        uu = np.array([u[i.name] for i in net.inputs])
        conv = (lambda a: __import__("torch").as_tensor(a)) if backend == "torch" else (lambda a: a)
        got = np.asarray(model.rhs(params, conv(x), conv(uu)))
        want = spec_rhs(T, **u)
        np.testing.assert_allclose(got, [want[n] for n in NODES], rtol=1e-10, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# generation (a 10-minute horizon: fast)
# ---------------------------------------------------------------------------------------------

SHORT = (600.0, 600.0, 600.0)  # jax: the same shapes in every test, so the compiled rollouts are reused
SHORTER = (300.0, 300.0, 300.0)  # torch: its per-step cost is higher


def _gen(out, backend, **kw):
    args = dict(widen=(0.4,), n_ood=2, durations=SHORT if backend == "jax" else SHORTER, backend=backend)
    args.update(kw)
    return generate_case_study(out, **args)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_generate_short_case_study(tmp_path, backend):
    res = _gen(tmp_path / "cs", backend)
    assert res["cached"] is False
    names = sorted(os.listdir(tmp_path / "cs"))
    assert names == ["manifest.json", "ood_40_0.csv", "ood_40_1.csv", "train.csv", "val.csv"]
    df = pd.read_csv(res["train"])
    cols = ["time_s", "I", "u1", "Ta", "Tf1", "Tf2", "T_out"] + [f"T_{n}" for n in NODES]
    assert list(df.columns) == cols
    n = 601 if backend == "jax" else 301
    assert len(df) == n and df["time_s"].iloc[-1] == n - 1
    np.testing.assert_array_equal(df["Ta"], 22.0)
    np.testing.assert_array_equal(df["Tf2"], 25.0)
    # the inputs are exactly the generator's
    sig = case_study_inputs(1, n - 1)
    np.testing.assert_array_equal(df["I"], sig["I"])  # levels have 6 decimals: written exactly
    np.testing.assert_array_equal(df["u1"], sig["u1"])
    # T_out is hx2 (no noise)
    np.testing.assert_allclose(df["T_out"], df["T_hx2"], atol=1e-12)
    # the run starts at the steady state of the first inputs: nothing moves until an input switches
    first_switch = min([n - 1] + [int(np.flatnonzero(np.diff(sig[k]) != 0)[0]) for k in ("I", "u1")
                                  if np.any(np.diff(sig[k]) != 0)])
    assert first_switch >= 119
    for n in NODES:
        x = df[f"T_{n}"].to_numpy()[: first_switch + 1]
        assert np.ptp(x) < 1e-8, n
    # ... and then it does move
    assert np.ptp(df["T_out"]) > 0.05
    wide = pd.read_csv(res["ood"]["40"][0])
    assert wide["I"].max() <= 4.2 and wide["u1"].min() >= -0.4 and wide["u1"].max() <= 1.4
    man = json.loads((tmp_path / "cs" / "manifest.json").read_text())
    assert man["settings"]["widen"] == [0.4] and set(man["files"]) == set(names) - {"manifest.json"}


def test_generation_is_deterministic_cached_and_backend_independent(tmp_path):
    a = _gen(tmp_path / "a", "jax")
    b = _gen(tmp_path / "b", "jax")
    for k in ("train", "val"):
        assert open(a[k], "rb").read() == open(b[k], "rb").read()
    mtime = os.path.getmtime(a["train"])
    again = _gen(tmp_path / "a", "jax")
    assert again["cached"] is True and os.path.getmtime(a["train"]) == mtime
    # another setting, or a damaged file, regenerates
    with open(a["val"], "a") as f:
        f.write("garbage\n")
    assert _gen(tmp_path / "a", "jax")["cached"] is False
    c = _gen(tmp_path / "c", "torch")
    for k in ("train", "val"):
        x, y = pd.read_csv(a[k]), pd.read_csv(c[k])
        np.testing.assert_allclose(x.to_numpy()[:301], y.to_numpy(), rtol=0, atol=1e-9)


def test_noise_is_seeded_gaussian_on_t_out_only(tmp_path):
    res = _gen(tmp_path / "n", "jax", noise=0.05, widen=(), n_ood=0, durations=(1800.0, 600.0, 600.0))
    df = pd.read_csv(res["train"])
    e = (df["T_out"] - df["T_hx2"]).to_numpy()
    assert abs(e.std() - 0.05) < 0.003 and abs(e.mean()) < 0.005
    res2 = _gen(tmp_path / "n2", "jax", noise=0.05, widen=(), n_ood=0, durations=(1800.0, 600.0, 600.0))
    np.testing.assert_array_equal(pd.read_csv(res2["train"])["T_out"], df["T_out"])


def test_an_unphysical_truth_is_refused(tmp_path):
    from tnn_dsl import TnnError

    # a heat pipe whose resistance to ambient is negative (−0.1 K/W): it runs away once the inputs move
    text = truth_network_path().read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("R hp  -- amb")]
    lines.append("R hp -- amb = 0.05 K/W * (u1 - 3)  as R_bad")
    bad = tmp_path / "bad_truth.thn"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(TnnError) as ei:
        generate_case_study(tmp_path / "out", widen=(), n_ood=0, durations=SHORT, truth_path=bad)
    msg = ei.value.format()
    assert "unphysical" in msg or "did not converge" in msg
    assert not (tmp_path / "out" / "manifest.json").exists()


def test_heat_pipe_floor_is_inactive_in_distribution(tmp_path):
    """truth.thn floors the heat-pipe factors at 0.1 (the spec's law goes negative for u1 < −1/6). On the
    in-distribution sets the floor must never bind, so the data are the spec's (the floored law itself is
    checked against a hand-written right-hand side in test_truth_network_matches_the_spec)."""
    res = _gen(tmp_path / "cs", "jax")
    for key in ("train", "val"):
        df = pd.read_csv(res[key])
        for a, b, slope in (("hx1", "hp", 1.5), ("hp", "hx2", 1.2)):
            t_mean = 0.5 * (df[f"T_{a}"] + df[f"T_{b}"])
            factor = 1 + slope * (df["u1"] - 0.5) - 0.02 * (t_mean - 25.0)
            assert factor.min() > 0.1, (key, a, b, factor.min())


def test_a_users_file_named_like_the_marker_is_never_replaced_or_removed(tmp_path):
    """``--force`` into a directory holding a file of the generator's marker name that it did not write: refused
    before anything is written, and the file is left as it was."""
    from tnn_dsl import TnnError
    from tnn_dsl.studies.casestudy import _INCOMPLETE

    out = tmp_path / "out"
    out.mkdir()
    (out / _INCOMPLETE).write_text("my notes\n")
    with pytest.raises(TnnError, match="was not written by this generator"):
        generate_case_study(out, widen=(), n_ood=0, durations=SHORT, force=True)
    assert (out / _INCOMPLETE).read_text() == "my notes\n" and sorted(p.name for p in out.iterdir()) == [_INCOMPLETE]
