"""JAX's caches of compiled programs emptied before the model doctor's MLP check (issue 18: the doctor lets the
selection's programs go, but JAX keeps them in its own caches; ``benchmarks/bench_diagnose.py`` measured the case
study's peak with two threads at 580–614 MB with them, 557–558 MB without). Only the command line, which owns its
process, asks for it: a library caller's own jitted functions are left alone by default."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tnn_dsl.compiler.backends.adapter import drop_compiled_caches
from tnn_dsl.doctor import diagnosis as D

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def test_dropping_the_jax_caches_empties_a_jitted_functions_cache_and_nothing_else_does():
    jax = pytest.importorskip("jax")
    f = jax.jit(lambda x: 2.0 * x + 1.0)
    np.testing.assert_allclose(np.asarray(f(np.ones(3))), 3.0)
    assert f._cache_size() == 1
    assert drop_compiled_caches("torch") is False and drop_compiled_caches("numpy") is False
    assert f._cache_size() == 1
    assert drop_compiled_caches("jax") is True
    assert f._cache_size() == 0
    np.testing.assert_allclose(np.asarray(f(np.ones(3))), 3.0)  # compiled again on its next call


class _Run:
    """A stand-in for the doctor's session: records the phases ``_run`` calls, in order."""

    def __init__(self, log: list, backend: str):
        self.log, self.backend = log, backend

    def __getattr__(self, name: str):
        def phase(*args, **kwargs):
            self.log.append(name)
            return False if name == "selection_round" else None  # one round, nothing found
        return phase


@pytest.mark.parametrize("backend", ["jax", "torch"])
@pytest.mark.parametrize("release", [True, False])
def test_the_caches_are_emptied_after_the_selection_and_before_the_mlp_check_only_when_asked(monkeypatch, backend,
                                                                                             release):
    log: list = []
    monkeypatch.setattr(D, "drop_compiled_caches", lambda name: log.append(("drop", name)))
    D._run(_Run(log, backend), 2, release)
    assert log[-2:] == ["compare_with_mlp", "result"]
    if release:
        assert log.index(("drop", backend)) == log.index("release_programs") + 1 == log.index("compare_with_mlp") - 1
    else:
        assert not [e for e in log if isinstance(e, tuple)]


def test_diagnose_passes_the_choice_on_and_leaves_a_callers_caches_by_default(monkeypatch):
    seen: list = []
    monkeypatch.setattr(D, "_Session", lambda *a, **k: "session")
    monkeypatch.setattr(D, "_run", lambda run, max_rounds, release: seen.append((run, release)))
    D.diagnose("net.thn", ["train.csv"])
    D.diagnose("net.thn", ["train.csv"], release_jax_caches=True)
    assert seen == [("session", False), ("session", True)]


class _Called(Exception):
    pass


def test_tnnc_diagnose_owns_its_process_and_asks_for_it(tmp_path, monkeypatch):
    import pandas as pd

    import tnn_dsl.doctor
    from tnn_dsl.cli import main

    src = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
    if not src.is_file():
        pytest.skip("shared data not present")
    data = tmp_path / "prbs.csv"
    pd.read_csv(src).iloc[:300].to_csv(data, index=False)

    calls: list = []

    def fake(*args, **kwargs):
        calls.append(kwargs)
        raise _Called  # stops the command here (it reports an internal error)

    monkeypatch.setattr(tnn_dsl.doctor, "diagnose", fake)
    assert main(["diagnose", str(ROOT / "networks" / "tclab" / "tclab.thn"), str(data), "--quiet"]) != 0
    assert len(calls) == 1 and calls[0]["release_jax_caches"] is True
