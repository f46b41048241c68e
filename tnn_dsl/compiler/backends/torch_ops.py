"""The PyTorch array namespace (explicit dtype everywhere; never changes torch's global default).

:class:`FusedTorchXP` is the namespace of code traced for ``torch.compile`` (the compiled forward and adjoint
scans in ``model.py`` and ``torch_adjoint.py``): there a product of a vector or a batch of vectors by a small
matrix is written as a multiply-and-sum, which inductor fuses with its neighbours into C++ loops instead of
calling a library ``mm`` per product: in the compiled C++ wrapper each ``mm`` is a call through torch's
dispatcher per scan iteration (the case study M2's reverse scan made 20 a step). Eager torch keeps
``torch.matmul``, one dispatch instead of three. JAX applies the rule to unbatched vectors only
(:func:`~tnn_dsl.compiler.backends.jax_ops.matmul`): XLA's batched ``dot`` is faster there.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from . import ArrayNamespace, _interp_segments, interp_with


class TorchXP(ArrayNamespace):
    name = "torch"
    _module = torch

    sigmoid = staticmethod(torch.sigmoid)
    relu = staticmethod(torch.relu)

    def _t(self, x):
        return x if isinstance(x, torch.Tensor) else torch.as_tensor(x, dtype=self.dtype)

    def minimum(self, a, b):
        return torch.minimum(self._t(a), self._t(b))

    def maximum(self, a, b):
        return torch.maximum(self._t(a), self._t(b))

    def where(self, c, a, b):
        return torch.where(self._t(c), self._t(a), self._t(b))

    @staticmethod
    def softplus(x):
        # threshold 40: log1p(exp(x)) == x to float64 round-off there, as jax.nn.softplus computes
        return F.softplus(x, beta=1.0, threshold=40.0)

    @staticmethod
    def silu(x):
        return F.silu(x)

    matmul = staticmethod(torch.matmul)

    def stack(self, xs, axis=0):
        xs = [self._t(x) for x in xs]
        return torch.stack(torch.broadcast_tensors(*xs), dim=axis)

    def concat(self, xs, axis=0):
        return torch.cat([self._t(x) for x in xs], dim=axis)

    @staticmethod
    def sum(x, axis=None):
        return torch.sum(x) if axis is None else torch.sum(x, dim=axis)

    def broadcast_to(self, x, shape):
        return torch.broadcast_to(self._t(x), tuple(shape))

    def broadcast_all(self, *xs):
        return torch.broadcast_tensors(*[self._t(x) for x in xs])

    @staticmethod
    def moveaxis(x, src, dst):
        return torch.movedim(x, src, dst)

    def zeros(self, shape):
        return torch.zeros(tuple(shape), dtype=self.dtype)

    def ones(self, shape):
        return torch.ones(tuple(shape), dtype=self.dtype)

    @staticmethod
    def zeros_like(x):
        return torch.zeros_like(x)

    def asarray(self, x, dtype=None):
        dt = self.dtype if dtype is None else dtype
        if isinstance(x, torch.Tensor):
            return x if x.dtype == dt else x.to(dt)
        return torch.as_tensor(np.asarray(x), dtype=dt)

    @staticmethod
    def shape(x):
        return tuple(x.shape) if isinstance(x, torch.Tensor) else tuple(np.shape(x))

    @staticmethod
    def solve(a, b):
        """``a⁻¹ b``; NaN where ``a`` is singular (as JAX's solve gives), never an exception."""
        x, info = torch.linalg.solve_ex(a, b.unsqueeze(-1))
        x = x.squeeze(-1)
        return torch.where((info != 0).unsqueeze(-1), torch.full_like(x, float("nan")), x)

    @staticmethod
    def stop_gradient(x):
        return x.detach() if isinstance(x, torch.Tensor) else x

    def interp(self, x, xs, ys):
        return interp_with(self, self._t(x), *_interp_segments(xs, ys))

    @staticmethod
    def to_numpy(x):
        return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


SMALL_MATMUL = 256
"""Largest ``K·N`` of a matrix that :class:`FusedTorchXP` multiplies vectors by with multiply-and-sum."""


def fused_matmul(a, b):
    """``a @ b``; for vectors ``a (..., K)`` and a small matrix ``b (K, N)`` (``K·N ≤`` :data:`SMALL_MATMUL`) as a
    multiply-and-sum. Same value as ``torch.matmul`` up to the order of the additions.

    A batch of vectors ``a (B, K)`` (or more leading axes, flattened) is multiplied batch-last: ``sum(aᵀ[:, None,
    :]·b[:, :, None], 0) (N, B)``, returned transposed as ``(B, N)``. Inductor then lays the product and what is
    computed from it (an MLP's activations, their gradients) out with the batch as the contiguous axis, and its SIMD
    kernels (:data:`~tnn_dsl.compiler.model.TORCH_SIMD_MIN_WINDOW_STEPS`) run along the windows instead of along the
    3–18 units, nodes or links of a layer, where most lanes were masked tails. Case study M3, RK4, 256 windows × 390
    samples, forward + gradient in µs per window-step, JAX and the variants alongside in one process (a throwaway A/B
    script, 2026-12-03, about 02:30–02:35 UTC; BENCHMARKS.md, "SIMD kernels along the windows"): SIMD kernels along the
    units 7.90, along the windows 7.00, batch-last without SIMD kernels 9.27 (JAX 4.59); without SIMD kernels the layout
    changes nothing measurable (M2's training, ``python benchmarks/bench_train.py --only m2 --backends torch-compiled``,
    the trees before and after alternately: 65, 64 against 72, 60 s to within 10 %)."""
    if (isinstance(a, torch.Tensor) and a.ndim >= 1 and isinstance(b, torch.Tensor) and b.ndim == 2
            and b.shape[0] == a.shape[-1] and b.numel() <= SMALL_MATMUL):
        if a.ndim == 1:
            return torch.sum(a[:, None] * b, dim=0)
        lead = a.shape[:-1]
        rows = a.reshape(-1, a.shape[-1]).T  # (K, B)
        return torch.sum(rows[:, None, :] * b[:, :, None], dim=0).T.reshape(*lead, b.shape[1])
    return torch.matmul(a, b)


class FusedTorchXP(TorchXP):
    """:class:`TorchXP` for code traced by ``torch.compile`` (see the module docstring)."""

    matmul = staticmethod(fused_matmul)
