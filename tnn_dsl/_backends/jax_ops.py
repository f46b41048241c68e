"""The JAX array namespace. Importing this module enables ``jax_enable_x64`` (float64 by default)."""

from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from . import _interp_segments, interp_with  # noqa: E402


class JaxXP:
    name = "jax"

    def __init__(self, dtype: str = "float64"):
        self.dtype_name = dtype
        self.dtype = jnp.float64 if dtype == "float64" else jnp.float32

    exp = staticmethod(jnp.exp)
    log = staticmethod(jnp.log)
    sqrt = staticmethod(jnp.sqrt)
    abs = staticmethod(jnp.abs)
    expm1 = staticmethod(jnp.expm1)
    tanh = staticmethod(jnp.tanh)
    minimum = staticmethod(jnp.minimum)
    maximum = staticmethod(jnp.maximum)
    where = staticmethod(jnp.where)
    softplus = staticmethod(jax.nn.softplus)
    sigmoid = staticmethod(jax.nn.sigmoid)
    relu = staticmethod(jax.nn.relu)

    @staticmethod
    def silu(x):
        return x * jax.nn.sigmoid(x)

    matmul = staticmethod(jnp.matmul)

    @staticmethod
    def stack(xs, axis=0):
        return jnp.stack(jnp.broadcast_arrays(*xs), axis=axis)

    @staticmethod
    def concat(xs, axis=0):
        return jnp.concatenate(xs, axis=axis)

    @staticmethod
    def sum(x, axis=None):
        return jnp.sum(x, axis=axis)

    @staticmethod
    def broadcast_to(x, shape):
        return jnp.broadcast_to(x, shape)

    @staticmethod
    def broadcast_all(*xs):
        return jnp.broadcast_arrays(*xs)

    @staticmethod
    def moveaxis(x, src, dst):
        return jnp.moveaxis(x, src, dst)

    def zeros(self, shape):
        return jnp.zeros(shape, dtype=self.dtype)

    def ones(self, shape):
        return jnp.ones(shape, dtype=self.dtype)

    @staticmethod
    def zeros_like(x):
        return jnp.zeros_like(x)

    def asarray(self, x, dtype=None):
        return jnp.asarray(x, dtype=self.dtype if dtype is None else dtype)

    @staticmethod
    def shape(x):
        return tuple(jnp.shape(x))

    @staticmethod
    def solve(a, b):
        return jnp.linalg.solve(a, b[..., None])[..., 0]

    stop_gradient = staticmethod(jax.lax.stop_gradient)

    def interp(self, x, xs, ys):
        return interp_with(self, x, *_interp_segments(xs, ys))

    @staticmethod
    def to_numpy(x):
        return np.asarray(x)
