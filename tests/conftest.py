"""Test-session settings shared by every test file."""

from __future__ import annotations

import gc
import os
import shutil
import sys
import tempfile

NO_SHARED_JAX_CACHE_ENV = "TNN_TEST_NO_JAX_CACHE"
"""Set to 1 to run the tests without the session's shared JAX compilation cache."""


FUSED_XLA_ENV = "TNN_TEST_FUSED_XLA"
"""Set to 1 to run the tests with XLA's default CPU code generation (its MLIR fusion emitters) instead of
:data:`LEAN_TEST_XLA_FLAG`."""

LEAN_TEST_XLA_FLAG = "--xla_cpu_use_fusion_emitters=false"
"""The test session's JAX programs are compiled with XLA's loop emitters, the doctor's lean options
(``tnn_dsl.compiler.backends.adapter.LEAN_XLA_OPTIONS``) for every program: a test runs a program a few times, and
its compilation is most of its cost. Same numbers to round-off (``tests/test_adapter.py`` compares the two code
generators, the reference compiled with :data:`FUSED_XLA_OPTIONS`). Measured (2026-12-06, the AMD host, `CI=true
pytest -q -n 2 --dist worksteal -m "not slow" tests`, 1382 passed each): with XLA's defaults 909 s at 08:03
and 846 s at 09:17, with this flag 715 s at 09:00; the torch-only compiling tests the same (±2 s), the JAX-heavy
ones 15–35 % faster. Set in the environment, so the processes the tests start (``tnnc``, the benchmark scripts) get
it too, and a local Ray's workers, the fleet's one-thread flags after it (``fleet.engine.worker_env``)."""

FUSED_XLA_OPTIONS = {"xla_cpu_use_fusion_emitters": True}
"""``jax.jit(..., compiler_options=FUSED_XLA_OPTIONS)``: a program compiled as outside the tests (XLA's default code
generation), whatever :data:`LEAN_TEST_XLA_FLAG` says; for the tests that compare the two."""


JAX_CACHE_MAX_BYTES = 2**31
"""A size limit for the tests' JAX compilation caches. Any limit turns on JAX's file lock around each entry's read
and write; without one an entry is written in place, and a worker or doctor thread reading it meanwhile got a
truncated program ("Error reading persistent compilation cache entry for 'jit__lambda': … truncated stream", clean
clone of 2026-11-28; XLA then compiled it again)."""


TNNC_CTRL_C = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
               "from tnn_dsl.cli import main; sys.exit(main())"]
"""``tnnc`` in a child process that takes Ctrl-C (SIGINT) as at a terminal, however the test run was started. A shell
without job control starts a background command with SIGINT ignored (``make test &`` in a script, ``nohup``), the
children inherit that, and Python then installs no KeyboardInterrupt handler: a clean clone's ``make test`` started
that way (2026-11-28 06:04) failed both Ctrl-C tests, the training running on for 300 s and the fleet exiting 0."""


def _jax_cache_dir(config) -> str:
    """One JAX persistent compilation cache for the whole test session, shared by the xdist workers (their parent is
    the controlling pytest process): the same networks are compiled in many tests, and a program read back from the
    cache is the program XLA would compile (its key is the program itself). Removed when the session ends."""
    owner = os.getppid() if hasattr(config, "workerinput") else os.getpid()
    return os.path.join(tempfile.gettempdir(), f"tnn_dsl_test_jax_cache_{owner}")


def _inductor_cache_dir(config) -> str:
    """One on-disk cache of torch inductor's compiled graphs for the whole test session, shared by the xdist workers
    and removed when the session ends. Without it inductor writes to ``/tmp/torchinductor_<user>``, kept between
    sessions: a second local run then reads graphs the first one compiled (1.2 GB there after a day of runs, 2026-11-28)
    and is faster than CI's clean machine, which compiles every one (the three torch-compiling test files, ``-n 2``:
    140 s with an empty cache against 107 s with that one). The precompiled headers of inductor's C++ wrapper still go
    to torch's default ``/tmp/torchinductor_<user>/precompiled_headers`` (only ``TMPDIR`` moves them): remove that
    directory too to time a run as CI's clean machine runs it."""
    owner = os.getppid() if hasattr(config, "workerinput") else os.getpid()
    return os.path.join(tempfile.gettempdir(), f"tnn_dsl_test_inductor_cache_{owner}")


def _share_jax_cache_with_children(config) -> None:
    """The session's JAX cache for the processes the tests start as well (``tnnc`` and the benchmark scripts in
    subprocesses; JAX reads these variables when it is imported): a child then reads what the session already
    compiled instead of compiling it again. Measured (2026-12-02, Intel Xeon, a slow hour: `CI=true pytest -n 2 -m
    "not slow" tests/test_real_data_defaults.py tests/test_benchmarks_smoke.py tests/test_cli_train.py
    tests/test_objective.py tests/test_train.py`, with and without, one after the other): 245.6 against 267.3 s,
    ``bench_real_data_fits.py``'s smoke run 12.7 against 31.9 s (the fits of ``test_real_data_defaults.py`` read
    back). A variable the user set is left as it is. A fleet's Ray workers use it too (`fleet.engine._cache_env`)."""
    os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _jax_cache_dir(config))
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(JAX_CACHE_MAX_BYTES))


def _skip_the_caches_eviction_scan() -> None:
    """No directory scan on each entry written to the session's JAX cache. With a size limit set (for its file lock,
    :data:`JAX_CACHE_MAX_BYTES`), JAX's ``LRUCache.put`` lists every entry of the cache and reads each one's access
    time before writing, to evict the oldest past the limit: a session's cache grows to thousands of entries, so the
    scans' cost grows with the square of their number. Measured (2026-12-04, `pytest -n 2 -m "not slow"` on four
    doctor and training files, timers around JAX's cache calls): 15.7 s of scans in 414 s of tests, for a cache that
    is removed when the session ends and stays far below the limit (24 MB in about 1000 entries after those four
    files, `du` while they ran). The lock stays; only the scan goes. A JAX without this method (another version) is
    left as it is."""
    from jax._src import lru_cache

    if callable(getattr(lru_cache.LRUCache, "_evict_if_needed", None)):
        lru_cache.LRUCache._evict_if_needed = lambda self, *, additional_size=0: None


def _lean_xla_for_the_session() -> None:
    """:data:`LEAN_TEST_XLA_FLAG` added to ``XLA_FLAGS`` (read when JAX starts its CPU backend, at the first
    computation), unless :data:`FUSED_XLA_ENV` is 1 or the flags already choose the emitters."""
    flags = os.environ.get("XLA_FLAGS", "")
    if os.environ.get(FUSED_XLA_ENV) != "1" and "xla_cpu_use_fusion_emitters" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {LEAN_TEST_XLA_FLAG}".strip()


def pytest_configure(config):
    _lean_xla_for_the_session()  # before JAX starts its backend (below, or in a test)
    # set before torch is imported (inductor reads it when it first needs its cache); the workers inherit the
    # controlling process's value; a directory the user named is left to the user
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", _inductor_cache_dir(config))
    # no helper process compiling beside a torch training (tnn_dsl.fit.compile_ahead): xdist already runs one worker
    # per core, and the tests of the helpers start theirs themselves
    os.environ.setdefault("TNN_COMPILE_AHEAD", "0")
    if os.environ.get(NO_SHARED_JAX_CACHE_ENV) != "1":
        import jax

        jax.config.update("jax_compilation_cache_dir", _jax_cache_dir(config))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_compilation_cache_max_size", JAX_CACHE_MAX_BYTES)
        _share_jax_cache_with_children(config)
        _skip_the_caches_eviction_scan()
    # The networks are small: torch's intra-op threads only add synchronisation (measured 47× slower per
    # batched step with 2 threads than with 1 on the 2-core CI machine, benchmarks/bench_rollout.py
    # --torch-threads), and pytest-xdist already runs one worker per core.
    try:
        import torch
    except ImportError:  # pragma: no cover
        return
    torch.set_num_threads(1)


def pytest_runtest_setup(item):
    """Before each test, collect the garbage left by the last one and move every live object to the collector's
    permanent generation (``gc.freeze``): Python's full collections then walk only what the running test made.
    A worker accumulates a million live objects (JAX's and torch's caches of traced and compiled programs, the
    modules' state), and every automatic full collection walked them all, again and again: three doctor and
    torch test files in one process spent 14–19 s of 162–195 s in the collector, 5.6 s with this (2026-11-28).
    What a test leaves reachable stays reachable; what it leaves as garbage is collected here, before freezing."""
    gc.collect()
    gc.freeze()


def pytest_unconfigure(config):
    if not hasattr(config, "workerinput"):  # the controlling process: the workers have stopped
        shutil.rmtree(_jax_cache_dir(config), ignore_errors=True)
        if os.environ.get("TORCHINDUCTOR_CACHE_DIR") == _inductor_cache_dir(config):
            shutil.rmtree(_inductor_cache_dir(config), ignore_errors=True)
