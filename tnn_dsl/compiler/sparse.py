"""Constant-structure matrices of a large network, applied by gather and scatter-add.

A compiled network's right-hand side is a handful of products ``x @ M`` by matrices whose *structure* is
fixed by the network (incidence of links, scatter of point flows onto nodes, lag and sensor maps, the static
conductance matrix). For the small networks engineers mostly write (tens of nodes) dense products are the
fastest form (one library kernel each). For large networks (a plate mesh, a multi-zone building) a dense
``(n, n)`` product makes one step cost O(n²) in time and memory, while the matrices hold O(n + links)
non-zeros. This module keeps such a matrix as its non-zeros (:class:`SparseMatrix`) and applies it as

    (x @ M)[..., j] = Σ_{e : col_e = j} x[..., row_e] · val_e

(a gather of ``x`` at the rows, a product by the values, a segment sum over the columns), so that one step
costs O(nodes + links) on every backend. The values may be backend arrays that depend on the parameters
(the conductance matrix); gradients flow through them as through any product.

:class:`Coo` collects entries while the compiler assembles a network; :func:`as_matrix` turns it into a
dense backend array or a :class:`SparseMatrix`, whichever the model was compiled for. Nothing here builds a
dense ``(n, n)`` array when the model is sparse.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["Coo", "SparseMatrix", "as_matrix", "matmul", "concat_columns", "add", "weighted"]


class Coo:
    """Entries ``(row, col, value)`` of a ``(K, N)`` matrix being assembled (numpy; duplicates add up)."""

    __slots__ = ("shape", "rows", "cols", "vals")

    def __init__(self, shape: tuple[int, int]):
        self.shape = (int(shape[0]), int(shape[1]))
        self.rows: list[int] = []
        self.cols: list[int] = []
        self.vals: list[float] = []

    def add(self, row: int, col: int, value: float) -> None:
        self.rows.append(int(row))
        self.cols.append(int(col))
        self.vals.append(float(value))

    def any(self) -> bool:
        return any(v != 0.0 for v in self.vals)

    def dense(self) -> np.ndarray:
        M = np.zeros(self.shape)
        if self.rows:
            np.add.at(M, (np.asarray(self.rows), np.asarray(self.cols)), np.asarray(self.vals))
        return M

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(rows, cols, vals)`` as numpy arrays (int64, int64, float64)."""
        return (np.asarray(self.rows, dtype=np.int64), np.asarray(self.cols, dtype=np.int64),
                np.asarray(self.vals, dtype=np.float64))


class SparseMatrix:
    """A ``(K, N)`` matrix held as its non-zeros and applied from the right of a batch of row vectors:
    ``M.rmatmul(x)`` is ``x @ M`` for ``x (..., K)`` → ``(..., N)``.

    ``rows``, ``cols``: numpy int64 arrays (the structure, fixed); ``vals``: numpy float64 or a backend array
    of shape ``(..., nnz)`` (values that may carry gradients). Entries are kept sorted by column so the
    segment sum runs over sorted indices."""

    __slots__ = ("xp", "shape", "rows", "cols", "vals", "_rows_b", "_cols_b")

    def __init__(self, xp, rows: np.ndarray, cols: np.ndarray, vals: Any, shape: tuple[int, int], *,
                 _sorted: bool = False):
        self.xp = xp
        self.shape = (int(shape[0]), int(shape[1]))
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        if not _sorted and cols.size:
            order = np.argsort(cols, kind="stable")
            rows, cols = rows[order], cols[order]
            vals = _take(xp, vals, order)
        self.rows, self.cols = rows, cols
        self.vals = xp.asarray(vals) if isinstance(vals, np.ndarray) else vals
        self._rows_b = _index(xp, rows)
        self._cols_b = _index(xp, cols)

    @property
    def nnz(self) -> int:
        return int(self.rows.size)

    def rmatmul(self, x: Any) -> Any:
        """``x @ M`` for ``x (..., K)``: ``(..., N)``."""
        xp = self.xp
        if self.nnz == 0:
            return xp.zeros((*xp.shape(x)[:-1], self.shape[1])) if hasattr(x, "shape") else xp.zeros(self.shape[1:])
        g = _gather_last(xp, x, self._rows_b) * self.vals
        return _segment_sum_last(xp, g, self._cols_b, self.shape[1])

    # -- structural operations (values follow by a static gather) ---------------------------------------

    def select_rows(self, lo: int, hi: int) -> SparseMatrix:
        """Rows ``lo:hi`` as a ``(hi − lo, N)`` matrix."""
        keep = np.nonzero((self.rows >= lo) & (self.rows < hi))[0]
        return SparseMatrix(self.xp, self.rows[keep] - lo, self.cols[keep], _take(self.xp, self.vals, keep),
                            (hi - lo, self.shape[1]), _sorted=True)

    def diagonal(self, n: int) -> Any:
        """The first ``n`` diagonal entries ``M[i, i]`` (``(..., n)``)."""
        on = np.nonzero((self.rows == self.cols) & (self.rows < n))[0]
        v = _take(self.xp, self.vals, on)
        if on.size == 0:
            return self.xp.zeros((n,))
        return _segment_sum_last(self.xp, v, _index(self.xp, self.rows[on]), n)


def concat_columns(xp, blocks: list[SparseMatrix]) -> SparseMatrix:
    """``[B_1 | B_2 | …]`` (the same number of rows), columns offset block by block."""
    rows, cols, vals, off = [], [], [], 0
    for b in blocks:
        rows.append(b.rows)
        cols.append(b.cols + off)
        vals.append(b.vals)
        off += b.shape[1]
    return SparseMatrix(xp, np.concatenate(rows), np.concatenate(cols), _concat_vals(xp, vals),
                        (blocks[0].shape[0], off), _sorted=True)


def add(xp, a: SparseMatrix, b: SparseMatrix) -> SparseMatrix:
    """``a + b`` (same shape): the entries of both."""
    return SparseMatrix(xp, np.concatenate([a.rows, b.rows]), np.concatenate([a.cols, b.cols]),
                        _concat_vals(xp, [a.vals, b.vals]), a.shape)


def weighted(xp, rows: np.ndarray, cols: np.ndarray, coef: np.ndarray, which: np.ndarray, w: Any,
             shape: tuple[int, int]) -> SparseMatrix:
    """A matrix with entries ``coef_e · w[..., which_e]`` at ``(rows_e, cols_e)``: the structure is static
    (``cols`` sorted), ``w (..., k)`` a backend vector (e.g. the conductances of a group of links)."""
    vals = _take(xp, w, which) * xp.asarray(coef)
    return SparseMatrix(xp, rows, cols, vals, shape, _sorted=True)


def as_matrix(xp, coo: Coo, sparse: bool) -> Any:
    """The matrix of ``coo`` as a dense backend array (``sparse=False``) or a :class:`SparseMatrix`."""
    if not sparse:
        return xp.asarray(coo.dense())
    r, c, v = coo.arrays()
    return SparseMatrix(xp, r, c, v, coo.shape)


def matmul(xp, x: Any, M: Any) -> Any:
    """``x @ M`` for a dense backend matrix or a :class:`SparseMatrix`."""
    if isinstance(M, SparseMatrix):
        return M.rmatmul(x)
    return xp.matmul(x, M)


# -- backend primitives ----------------------------------------------------------------------------------


def _index(xp, idx: np.ndarray) -> Any:
    if xp.name == "torch":
        import torch

        return torch.as_tensor(idx, dtype=torch.int64)
    if xp.name == "jax":
        import jax.numpy as jnp

        return jnp.asarray(idx, dtype=jnp.int32 if idx.size == 0 or idx.max(initial=0) < 2**31 else jnp.int64)
    return idx


def _take(xp, v: Any, idx: np.ndarray) -> Any:
    """``v[..., idx]`` for a numpy or backend array (a static index)."""
    if isinstance(v, np.ndarray):
        return v[..., idx]
    return _gather_last(xp, v, _index(xp, idx))


def _gather_last(xp, x: Any, idx: Any) -> Any:
    if xp.name == "torch":
        return x.index_select(-1, idx)
    return x[..., idx]


def _segment_sum_last(xp, v: Any, idx: Any, n: int) -> Any:
    """``out[..., j] = Σ_{e : idx_e = j} v[..., e]`` (``idx`` sorted)."""
    if xp.name == "torch":
        import torch

        out = torch.zeros((*v.shape[:-1], n), dtype=v.dtype)
        return out.index_add(-1, idx, v)
    if xp.name == "jax":
        import jax
        import jax.numpy as jnp

        s = jax.ops.segment_sum(jnp.moveaxis(v, -1, 0), idx, num_segments=n, indices_are_sorted=True)
        return jnp.moveaxis(s, 0, -1)
    v = np.asarray(v)
    out = np.zeros((n, *v.shape[:-1]), dtype=v.dtype)
    np.add.at(out, idx, np.moveaxis(v, -1, 0))
    return np.moveaxis(out, 0, -1)


def _concat_vals(xp, vals: list) -> Any:
    if all(isinstance(v, np.ndarray) for v in vals):
        return np.concatenate(vals, axis=-1)
    vs = [xp.asarray(v) if isinstance(v, np.ndarray) else v for v in vals]
    shapes = [tuple(xp.shape(v)[:-1]) for v in vs]
    batch = np.broadcast_shapes(*shapes) if shapes else ()
    vs = [xp.broadcast_to(v, (*batch, xp.shape(v)[-1])) for v in vs]
    return xp.concat(vs, axis=-1)
