"""Array namespaces (``xp``) so the physics, expressions and learned functions are written once.

``get_xp(backend, dtype)`` returns a small namespace object with the operations the model needs:
``exp log sqrt abs expm1 minimum maximum where softplus sigmoid tanh relu silu matmul stack concat sum
zeros zeros_like ones broadcast_to broadcast_all interp asarray solve``. Every function takes and returns
backend arrays; Python floats are accepted wherever an array is and act as weakly-typed scalars.

Backends: ``"jax"`` (``jax.numpy``; importing it enables ``jax_enable_x64``), ``"torch"`` and ``"numpy"``
(a reference namespace without autodiff, used for nominal checks and reference loops).
"""

from __future__ import annotations

from typing import Any

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


ELEMENTWISE = ("exp", "log", "sqrt", "abs", "expm1", "tanh")
"""Elementwise functions every namespace takes from its array module unchanged."""


class ArrayNamespace:
    """What every namespace shares: its ``name``, its float ``dtype`` and the :data:`ELEMENTWISE` functions of its
    array module ``_module`` (numpy, jax.numpy or torch), set once per subclass unless the subclass defines them.
    Subclasses add what differs between modules (``stack``, ``concat``, ``where``, ``softplus`` …)."""

    name = ""
    _module: Any = None
    _from_module: tuple[str, ...] = ELEMENTWISE

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if cls._module is None:
            return
        for op in cls._from_module:
            if not hasattr(cls, op):
                setattr(cls, op, staticmethod(getattr(cls._module, op)))

    def __init__(self, dtype: str = "float64"):
        if dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {DTYPES}, got {dtype!r}")
        self.dtype_name = dtype
        self.dtype = getattr(self._module, dtype)

    def silu(self, x):
        return x * self.sigmoid(x)

    def interp(self, x, xs, ys):
        """Piecewise-linear interpolation of the table (xs, ys) at ``x`` (any shape), constant beyond
        the ends. ``xs``, ``ys`` are numbers (not differentiated)."""
        return interp_with(self, x, *_interp_segments(xs, ys))

    def asarrays(self, xs: list) -> list:
        """``[asarray(x) for x in xs]`` in the namespace's dtype; a backend with a per-call cost (JAX's device
        transfer) converts them in one call."""
        return [self.asarray(x) for x in xs]

    @staticmethod
    def to_numpy(x):
        return np.asarray(x)


class NumpyLike(ArrayNamespace):
    """The body of the numpy and JAX namespaces (``jax.numpy`` mirrors numpy's names)."""

    _from_module = ELEMENTWISE + ("minimum", "maximum", "where", "matmul", "zeros_like")

    def stack(self, xs, axis=0):
        return self._module.stack(self._module.broadcast_arrays(*xs), axis=axis)

    def concat(self, xs, axis=0):
        return self._module.concatenate(xs, axis=axis)

    def sum(self, x, axis=None):
        return self._module.sum(x, axis=axis)

    def broadcast_to(self, x, shape):
        return self._module.broadcast_to(x, shape)

    def broadcast_all(self, *xs):
        return self._module.broadcast_arrays(*xs)

    def moveaxis(self, x, src, dst):
        return self._module.moveaxis(x, src, dst)

    def zeros(self, shape):
        return self._module.zeros(shape, dtype=self.dtype)

    def ones(self, shape):
        return self._module.ones(shape, dtype=self.dtype)

    def asarray(self, x, dtype=None):
        return self._module.asarray(x, dtype=self.dtype if dtype is None else dtype)

    def shape(self, x):
        return tuple(self._module.shape(x))

    def solve(self, a, b):
        """Solve ``a x = b`` for ``b`` of shape (..., n)."""
        return self._module.linalg.solve(a, b[..., None])[..., 0]


class NumpyXP(NumpyLike):
    """The numpy namespace (no autodiff)."""

    name = "numpy"
    _module = np

    @staticmethod
    def softplus(x):
        return np.logaddexp(x, 0.0)

    @staticmethod
    def sigmoid(x):
        return 0.5 * (1.0 + np.tanh(0.5 * x))

    @staticmethod
    def relu(x):
        return np.maximum(x, 0.0)

    @staticmethod
    def stop_gradient(x):
        return x


def interp_with(xp, x, lo, hi, slope, y0):
    """``y0 + Σ slope·(clip(x, lo, hi) − lo)`` with the segment arrays of :func:`_interp_segments`
    (numbers or arrays of shape (k-1,)); ``x`` any shape → same shape."""
    if len(lo) == 0:
        return x * 0.0 + y0
    lo_a, hi_a, s_a = (xp.asarray(v) for v in (lo, hi, slope))
    xe = x[..., None] if hasattr(x, "shape") else xp.asarray(x)[..., None]
    clipped = xp.minimum(xp.maximum(xe, lo_a), hi_a)
    return y0 + xp.sum((clipped - lo_a) * s_a, axis=-1)


def get_xp(backend: str, dtype: str = "float64") -> Any:
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


__all__ = ["get_xp", "BACKENDS", "DTYPES", "ELEMENTWISE", "ArrayNamespace", "NumpyLike", "NumpyXP", "interp_with"]
