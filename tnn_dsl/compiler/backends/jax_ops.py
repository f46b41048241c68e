"""The JAX array namespace. Importing this module enables ``jax_enable_x64`` (float64 by default), and where the
environment names JAX's persistent compilation cache (``JAX_COMPILATION_CACHE_DIR``) keeps every program there
(:func:`cache_every_program`).

Products by small matrices (``matmul``) are written so that XLA fuses them with their neighbours instead of
calling a library ``dot`` per product (on CPU each ``dot`` is a separate kernel launch, which dominates the
cost of a thermal network's right-hand side: 7×7 matrices, hundreds of thousands of steps):

* a small matrix (``K·N ≤`` :data:`SMALL_MATMUL`) applied to an unbatched vector ``a (K,)`` becomes
  ``sum(a[:, None] · b, 0)`` (a fused multiply-and-reduce);
* everything else stays ``jnp.matmul``: with a batch axis XLA's ``dot`` is faster than a reduction over the
  middle axis, and faster than static gathers (slices + concatenate) for the 0/±1 incidence matrices.

Measured on the case study (benchmarks/bench_rollout.py): see the architecture notes, "Compiled model".
"""

from __future__ import annotations

import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

CACHE_THRESHOLDS = {"JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": ("jax_persistent_cache_min_compile_time_secs", 0.0),
                    "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": ("jax_persistent_cache_min_entry_size_bytes", 0)}
"""JAX's thresholds below which a compiled program is not written to its persistent cache (by default those that
took under a second to compile: every program of a thermal network's simulations and fits), by the environment
variable that sets each, and the value :func:`cache_every_program` gives them."""


def cache_every_program() -> bool:
    """Where the environment names JAX's persistent compilation cache (``JAX_COMPILATION_CACHE_DIR``, which JAX
    reads itself), keep every program in it: each threshold of :data:`CACHE_THRESHOLDS` the environment does not set
    goes to 0. A second run of the same job (``tnnc diagnose`` or ``tnnc train`` on files of the same lengths) then
    reads its programs instead of compiling them (issue 18: a third of a diagnosis is compiling). Returns whether
    the cache is on."""
    if not os.environ.get("JAX_COMPILATION_CACHE_DIR", "").strip():
        return False
    for env, (option, value) in CACHE_THRESHOLDS.items():
        if not os.environ.get(env, "").strip():
            jax.config.update(option, value)
    return True


cache_every_program()

PRIVATE_CACHE_MIN_COMPILE_S = 0.15
"""Programs that took at least this long to compile go into :func:`keep_programs_for_this_process`'s cache; the
smaller ones (most of a thermal network's, a few ms each) cost more to write than to compile again."""


def programs_kept() -> bool:
    """Whether this process writes the programs it compiles to a persistent compilation cache (the environment's,
    :func:`cache_every_program`, or :func:`keep_programs_for_this_process`'s): a program compiled ahead on an idle
    core is then read back, not compiled again, by whatever asks for the same program later, even through another
    ``jax.jit`` object (the model doctor's MLP check)."""
    return bool(os.environ.get("JAX_COMPILATION_CACHE_DIR", "").strip() or jax.config.jax_compilation_cache_dir)


def keep_programs_for_this_process(min_compile_s: float = PRIVATE_CACHE_MIN_COMPILE_S) -> str | None:
    """For a process of ours that lets compiled programs go and needs the same ones again later (``tnnc diagnose``:
    the doctor lets each network's programs go to stay within its memory, then the next round's score test, the
    final extended fit and the MLP check compile some of them again): JAX's persistent compilation cache in a fresh
    temporary directory of this process's own, keeping every program that took ``min_compile_s`` or more to compile,
    removed when the process exits. A program compiled again is then read back instead (the same executable, so the
    same numbers). Returns the directory; None, and nothing changed, where the environment or JAX's configuration
    already names a cache (that one is used, :func:`cache_every_program`) or JAX has compiled in this process
    already: it sets its cache up once, at the first compilation, and ignores a directory named later (a test
    calling the command in its own process); or no temporary directory can be made.

    On the case study (``python benchmarks/bench_diagnose.py --threads 2 --no-write``, seven pairs alternating with
    no cache, the AMD host in a fast hour, 2026-12-07): about 2 s (3 %) faster on average, 58.0–63.8 s against
    59.8–65.8 s, one pair the other way; peak 577–595 against 574–582 MB; about 40 programs written (3 MB) — issue 18.
    Keeping every program (threshold 0) did not pay: writing the small ones cost what reading the large ones saved
    (BENCHMARKS.md)."""
    import atexit
    import shutil
    import tempfile

    if programs_kept():
        return None
    try:  # JAX's own record of whether its cache was set up (at the first compilation); not public
        from jax._src import compilation_cache as _jax_cache

        if getattr(_jax_cache, "_cache_checked", False):
            return None
    except ImportError:  # pragma: no cover - a JAX without it: the directory may go unused
        pass
    try:
        path = tempfile.mkdtemp(prefix="tnn_programs_")
    except OSError:  # no writable temporary directory: the programs are compiled again, as without the cache
        return None
    atexit.register(shutil.rmtree, path, ignore_errors=True)  # only the directory made just above
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


from . import NumpyLike  # noqa: E402

SMALL_MATMUL = 256
"""Largest ``K·N`` of a matrix that an unbatched vector is multiplied by with multiply-and-sum."""


def matmul(a, b):
    """``a @ b``; for an unbatched vector ``a (K,)`` and a small matrix ``b (K, N)`` (``K·N ≤``
    :data:`SMALL_MATMUL`) as ``sum(a[:, None]·b, 0)``, which XLA fuses with its neighbours (see the module
    docstring). Same value as ``jnp.matmul`` up to the order of the additions."""
    a = jnp.asarray(a)
    if a.ndim == 1 and getattr(b, "ndim", None) == 2 and b.shape[0] == a.shape[0] and b.size <= SMALL_MATMUL:
        return jnp.sum(a[:, None] * b, axis=0)
    return jnp.matmul(a, b)


def sigmoid(x):
    """``1/(1 + e^−x)`` computed as ``½ + ½·tanh(x/2)``: the same function (to round-off), and XLA's CPU
    ``tanh`` is cheaper than its ``logistic`` (float64: 4.2 vs 6.0 ns per element; float32: 1.7 vs 2.8)."""
    return 0.5 + 0.5 * jnp.tanh(0.5 * x)


class JaxXP(NumpyLike):
    name = "jax"
    _module = jnp

    softplus = staticmethod(jax.nn.softplus)
    sigmoid = staticmethod(sigmoid)
    relu = staticmethod(jax.nn.relu)
    matmul = staticmethod(matmul)
    stop_gradient = staticmethod(jax.lax.stop_gradient)

    def asarrays(self, xs: list) -> list:
        """One device transfer for the whole list (one ``jnp.asarray`` per constant was most of ``init_params`` on a
        10 000-node plate's 40 000 constants; docs/measurement-log.md, "Large networks")."""
        dt = np.dtype(self.dtype)
        return list(jax.device_put([np.asarray(x, dtype=dt) for x in xs]))
