"""One adapter over the two autodiff backends: conversions, a few array operations and the transforms
(value-and-gradient, ...) that the trainer, the sensitivity pass, the doctor, the filter and the
controller need. Everything above :mod:`tnn_dsl.compiler` talks to JAX or torch through it."""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["Backend"]


class Backend:
    """A tiny array namespace over jax.numpy / torch, and the backend's value-and-gradient."""

    def __init__(self, backend: str, dtype: str = "float64"):
        self.backend = backend
        self.dtype_name = dtype
        if backend == "jax":
            import jax
            import jax.numpy as jnp

            jax.config.update("jax_enable_x64", True)
            self.jax, self.xp = jax, jnp
            self.dtype = jnp.float64 if dtype == "float64" else jnp.float32
        elif backend == "torch":
            import torch

            self.torch = self.xp = torch
            self.dtype = torch.float64 if dtype == "float64" else torch.float32
        else:
            raise ValueError(backend)

    # -- conversions ----------------------------------------------------------------------
    def asarray(self, x):
        x = np.asarray(x)
        if self.backend == "jax":
            return self.xp.asarray(x, dtype=self.dtype) if x.dtype.kind == "f" else self.xp.asarray(x)
        t = self.torch.from_numpy(np.ascontiguousarray(x))
        return t.to(self.dtype) if x.dtype.kind == "f" else t

    def tree(self, d):
        if isinstance(d, dict):
            return {k: self.tree(v) for k, v in d.items()}
        if isinstance(d, (list, tuple)):
            return [self.tree(v) for v in d]
        return self.asarray(d)

    @staticmethod
    def numpy(x) -> np.ndarray:
        if hasattr(x, "detach"):
            x = x.detach().cpu()
        return np.asarray(x, dtype=np.float64)

    # -- operations -----------------------------------------------------------------------
    def exp(self, x):
        return self.xp.exp(x)

    def sigmoid(self, x):
        return self.jax.nn.sigmoid(x) if self.backend == "jax" else self.torch.sigmoid(x)

    def where(self, c, a, b):
        return self.xp.where(c, a, b)

    def abs(self, x):
        return self.xp.abs(x)

    def sum(self, x):
        return self.xp.sum(x)

    def amax(self, x, axes):
        return self.xp.max(x, axis=axes) if self.backend == "jax" else self.torch.amax(x, dim=axes)

    # -- autodiff -------------------------------------------------------------------------
    def value_and_grad(self, f: Callable) -> Callable[..., tuple[float, np.ndarray]]:
        """``g(z_numpy, data) -> (float, grad numpy)`` for a scalar ``f(z, data)``."""
        if self.backend == "jax":
            vg = self.jax.jit(self.jax.value_and_grad(f))

            def g(z, data):
                v, gr = vg(self.xp.asarray(z, dtype=self.dtype), data)
                return float(v), np.asarray(gr, dtype=np.float64)

            return g
        torch = self.torch

        def g(z, data):
            zt = torch.tensor(np.asarray(z), dtype=self.dtype, requires_grad=True)
            v = f(zt, data)
            (gr,) = torch.autograd.grad(v, zt)
            return float(v.detach()), gr.detach().cpu().numpy().astype(np.float64)

        return g
