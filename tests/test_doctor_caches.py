"""JAX's caches of compiled programs emptied before the model doctor's MLP check (issue 18: the doctor lets the
selection's programs go, but JAX keeps them in its own caches; ``benchmarks/bench_diagnose.py`` measured the case
study's peak with two threads at 580–614 MB with them, 557–558 MB without). Only the command line, which owns its
process, asks for it: a library caller's own jitted functions are left alone by default."""

from __future__ import annotations

import json
import os
import subprocess
import sys
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


_OWN_CACHE_SCRIPT = """
import json, os, sys
import jax, jax.numpy as jnp
from jax import monitoring
from tnn_dsl.compiler.backends.jax_ops import keep_programs_for_this_process
events = []
monitoring.register_event_listener(lambda e, **k: events.append(e))
d = keep_programs_for_this_process(min_compile_s=float(sys.argv[1]))
f = lambda x: jnp.tanh(x) @ x.T + 1.0
a = jnp.ones((40, 40))
y1 = jax.jit(f)(a)
kept = sorted(os.listdir(d)) if d else []
jax.clear_caches()  # as the doctor lets a program go: the next call compiles it again, or reads it back
y2 = jax.jit(f)(a)
print(json.dumps({"dir": d, "kept": len(kept), "equal": bool((y1 == y2).all()),
                  "hits": events.count("/jax/compilation_cache/cache_hits"),
                  "again": keep_programs_for_this_process() is None}))
"""


def _own_cache(env_extra: dict, threshold: float) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", _OWN_CACHE_SCRIPT, str(threshold)], capture_output=True, text=True,
                         env=env, cwd=str(ROOT), timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_process_of_ours_reads_a_program_it_let_go_back_from_a_cache_of_its_own_removed_at_exit(tmp_path):
    """``tnnc diagnose`` keeps the programs that took a while to compile in a cache directory of its process's own
    (``jax_ops.keep_programs_for_this_process``, issue 18): a program compiled again after JAX's caches were emptied
    is read back (the same numbers), the directory goes when the process ends, and a second call changes nothing."""
    got = _own_cache({}, 0.0)
    assert got["dir"] and got["kept"] >= 1 and got["hits"] == 1 and got["equal"] and got["again"]
    assert not Path(got["dir"]).exists()
    # above the threshold only: a program that compiled in less is compiled again, not written
    got = _own_cache({}, 60.0)
    assert got["dir"] and got["kept"] == 0 and got["hits"] == 0
    # a cache the environment names is the one used, and left as it is
    named = tmp_path / "users_cache"
    got = _own_cache({"JAX_COMPILATION_CACHE_DIR": str(named)}, 0.0)
    assert got["dir"] is None and got["hits"] == 1 and named.is_dir() and any(named.iterdir())


def _set_up_after(prelude: str) -> list[str]:
    """In a fresh interpreter without a cache in its environment: ``prelude``, then
    ``keep_programs_for_this_process()`` → ``[its result, JAX's cache directory after it]`` as printed."""
    script = (prelude + "from tnn_dsl.compiler.backends.jax_ops import keep_programs_for_this_process as k\n"
              "import jax; print(k(), jax.config.jax_compilation_cache_dir)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=str(ROOT),
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_the_cache_of_its_own_is_not_set_up_after_jax_has_compiled():
    """JAX sets its cache up at its first compilation and ignores a directory named later: the call then changes
    nothing (a test running the command in its own process, whose session already compiled)."""
    assert _set_up_after("import jax.numpy as jnp; jnp.sin(jnp.ones(3)).block_until_ready()\n") == ["None", "None"]


def test_without_a_writable_temporary_directory_nothing_is_set_up():
    """A temporary directory that cannot be made leaves JAX's configuration as it was: the command runs on, its
    programs compiled again as without the cache (no traceback for a read-only /tmp)."""
    prelude = ("import tempfile\n"
               "def no_tmp(**kw):\n    raise PermissionError('read-only file system')\n"
               "tempfile.mkdtemp = no_tmp\n")
    assert _set_up_after(prelude) == ["None", "None"]


def test_tnnc_diagnose_keeps_its_programs_for_its_own_process_on_jax_only(tmp_path, monkeypatch):
    import tnn_dsl.doctor
    from tnn_dsl.cli import main
    from tnn_dsl.compiler.backends import jax_ops

    src = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
    if not src.is_file():
        pytest.skip("shared data not present")
    data = tmp_path / "prbs.csv"
    data.write_text("".join(src.read_text().splitlines(keepends=True)[:300]))
    asked: list = []
    monkeypatch.setattr(jax_ops, "keep_programs_for_this_process", lambda: asked.append(True))

    def fake(*args, **kwargs):
        raise _Called  # stops the command here

    monkeypatch.setattr(tnn_dsl.doctor, "diagnose", fake)
    net = str(ROOT / "networks" / "tclab" / "tclab.thn")
    assert main(["diagnose", net, str(data), "--quiet", "--backend", "torch"]) != 0 and asked == []
    assert main(["diagnose", net, str(data), "--quiet"]) != 0 and asked == [True]
