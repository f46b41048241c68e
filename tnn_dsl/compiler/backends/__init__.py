"""Array namespaces (``xp``) so the physics, expressions and learned functions are written once.

``get_xp(backend, dtype)`` returns a small namespace object with the operations the model needs:
``exp log sqrt abs expm1 minimum maximum where softplus sigmoid tanh relu silu matmul stack concat sum
zeros zeros_like ones broadcast_to broadcast_all interp asarray solve``. Every function takes and returns
backend arrays; Python floats are accepted wherever an array is and act as weakly-typed scalars.

Backends: ``"jax"`` (``jax.numpy``; importing it enables ``jax_enable_x64``), ``"torch"`` and ``"numpy"``
(a reference namespace without autodiff, used for nominal checks and reference loops).
"""

from __future__ import annotations

import numpy as np

BACKENDS = ("jax", "torch", "numpy")
DTYPES = ("float64", "float32")


def _interp_segments(xs, ys):
    """Segment form of a piecewise-linear table: ``(lo (k-1,), hi (k-1,), slope (k-1,), y0)`` so that
    ``y(x) = y0 + Σ slope·(clip(x, lo, hi) − lo)``, constant beyond the ends. ``xs`` strictly increasing."""
    xs = np.asarray(xs, dtype=np.float64)
    ys = np.asarray(ys, dtype=np.float64)
    if xs.ndim != 1 or xs.shape != ys.shape or xs.size < 1:
        raise ValueError("interp: xs and ys must be 1-D of the same length >= 1")
    if xs.size > 1 and not np.all(np.diff(xs) > 0):
        raise ValueError("interp: xs must be strictly increasing")
    lo, hi = xs[:-1], xs[1:]
    slope = np.diff(ys) / np.diff(xs) if xs.size > 1 else np.zeros(0)
    return lo, hi, slope, float(ys[0])


class NumpyXP:
    """The numpy namespace (no autodiff)."""

    name = "numpy"

    def __init__(self, dtype: str = "float64"):
        if dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
        self.dtype_name = dtype
        self.dtype = np.float64 if dtype == "float64" else np.float32

    # elementwise
    exp = staticmethod(np.exp)
    log = staticmethod(np.log)
    sqrt = staticmethod(np.sqrt)
    abs = staticmethod(np.abs)
    expm1 = staticmethod(np.expm1)
    tanh = staticmethod(np.tanh)
    minimum = staticmethod(np.minimum)
    maximum = staticmethod(np.maximum)
    where = staticmethod(np.where)

    @staticmethod
    def softplus(x):
        return np.logaddexp(x, 0.0)

    @staticmethod
    def sigmoid(x):
        return 0.5 * (1.0 + np.tanh(0.5 * x))

    @staticmethod
    def relu(x):
        return np.maximum(x, 0.0)

    def silu(self, x):
        return x * self.sigmoid(x)

    # structure
    matmul = staticmethod(np.matmul)

    @staticmethod
    def stack(xs, axis=0):
        return np.stack(np.broadcast_arrays(*xs), axis=axis)

    @staticmethod
    def concat(xs, axis=0):
        return np.concatenate(xs, axis=axis)

    @staticmethod
    def sum(x, axis=None):
        return np.sum(x, axis=axis)

    @staticmethod
    def broadcast_to(x, shape):
        return np.broadcast_to(x, shape)

    @staticmethod
    def broadcast_all(*xs):
        return np.broadcast_arrays(*xs)

    @staticmethod
    def moveaxis(x, src, dst):
        return np.moveaxis(x, src, dst)

    def zeros(self, shape):
        return np.zeros(shape, dtype=self.dtype)

    def ones(self, shape):
        return np.ones(shape, dtype=self.dtype)

    @staticmethod
    def zeros_like(x):
        return np.zeros_like(x)

    def asarray(self, x, dtype=None):
        return np.asarray(x, dtype=self.dtype if dtype is None else dtype)

    @staticmethod
    def shape(x):
        return tuple(np.shape(x))

    @staticmethod
    def solve(a, b):
        """Solve ``a x = b`` for ``b`` of shape (..., n)."""
        return np.linalg.solve(a, b[..., None])[..., 0]

    @staticmethod
    def stop_gradient(x):
        return x

    def interp(self, x, xs, ys):
        """Piecewise-linear interpolation of the table (xs, ys) at ``x`` (any shape), constant beyond
        the ends. ``xs``, ``ys`` are numbers (not differentiated)."""
        return interp_with(self, x, *_interp_segments(xs, ys))

    def to_numpy(self, x):
        return np.asarray(x)


def interp_with(xp, x, lo, hi, slope, y0):
    """``y0 + Σ slope·(clip(x, lo, hi) − lo)`` with the segment arrays of :func:`_interp_segments`
    (numbers or arrays of shape (k-1,)); ``x`` any shape → same shape."""
    if len(lo) == 0:
        return x * 0.0 + y0
    lo_a, hi_a, s_a = (xp.asarray(v) for v in (lo, hi, slope))
    xe = x[..., None] if hasattr(x, "shape") else xp.asarray(x)[..., None]
    clipped = xp.minimum(xp.maximum(xe, lo_a), hi_a)
    return y0 + xp.sum((clipped - lo_a) * s_a, axis=-1)


def get_xp(backend: str, dtype: str = "float64"):
    """The array namespace for ``backend`` (``"jax" | "torch" | "numpy"``) and ``dtype``."""
    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
    if backend == "jax":
        from .jax_ops import JaxXP

        return JaxXP(dtype)
    if backend == "torch":
        from .torch_ops import TorchXP

        return TorchXP(dtype)
    if backend == "numpy":
        return NumpyXP(dtype)
    raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


__all__ = ["get_xp", "BACKENDS", "DTYPES", "NumpyXP", "interp_with"]
