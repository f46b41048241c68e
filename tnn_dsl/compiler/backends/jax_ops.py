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
