"""Learned functions (``learn ... as const | linear | poly(d) | mlp(...) | table(...)``).

A learned function maps ``x (..., n_in)`` (node temperatures in K, inputs in SI, parameter values) to a
raw output ``z (..., n_out)``; :func:`target_value` turns ``z`` into the value of each target.

Arrays of one function (keys without the ``"<fn>."`` prefix the model's parameter table adds):

======== ================================================ ==========
kind     weights                                          stats
======== ================================================ ==========
all      —                                                ``x_mean (n_in,)``, ``x_scale (n_in,)``, ``y_scale (n_out,)``
const    ``c (n_out,)``
linear   ``W (n_in, n_out)``, ``b (n_out,)``
poly     ``W (n_monomials, n_out)``, ``b (n_out,)``       monomials of degree 1…d of the normalised x
mlp      ``W0 (n_in, h0)``, ``b0``, …, ``Wk (h_{k-1}, n_out)``, ``bk``
table    ``values (n_knots, n_out)``                      one input; knots in the input's SI unit
======== ================================================ ==========

The input is normalised ``xn = (x − x_mean)/x_scale`` (not for ``table``, whose knots are SI values).
The last layer is initialised to zero, so an untrained function has ``z = 0`` and every target equals
its nominal value.
"""

from __future__ import annotations

import itertools
import math
from typing import Any, Mapping

import numpy as np

from ..ir import LearnFunction

WEIGHT_NAMES_FIXED = {"const": ("c",), "linear": ("W", "b"), "poly": ("W", "b"), "table": ("values",)}
STAT_NAMES = ("x_mean", "x_scale", "y_scale")
_SOFTPLUS4 = math.log1p(math.exp(4.0))


def monomial_index(n_in: int, degree: int) -> np.ndarray:
    """Index array ``(n_monomials, degree)`` into ``[1, xn_0, …, xn_{n_in-1}]``: every monomial of degree
    1…``degree`` exactly once (index 0 is the constant 1)."""
    combos = [c for c in itertools.combinations_with_replacement(range(n_in + 1), degree) if any(c)]
    return np.asarray(combos, dtype=np.int64).reshape(len(combos), degree)


def array_shapes(fn, n_in: int, n_out: int) -> dict[str, tuple[tuple[int, ...], str]]:
    """``{array name: (shape, "weights" | "stat")}`` for function ``fn`` (a ``LearnFunction``)."""
    out: dict[str, tuple[tuple[int, ...], str]] = {}
    kind = fn.kind
    if kind == "const":
        out["c"] = ((n_out,), "weights")
    elif kind == "linear":
        out["W"] = ((n_in, n_out), "weights")
        out["b"] = ((n_out,), "weights")
    elif kind == "poly":
        d = int(fn.degree or 2)
        if d < 1:
            raise ValueError(f"poly degree must be >= 1, got {d}")
        out["W"] = ((len(monomial_index(n_in, d)), n_out), "weights")
        out["b"] = ((n_out,), "weights")
    elif kind == "mlp":
        sizes = [n_in, *[int(h) for h in fn.hidden], n_out]
        for k in range(len(sizes) - 1):
            out[f"W{k}"] = ((sizes[k], sizes[k + 1]), "weights")
            out[f"b{k}"] = ((sizes[k + 1],), "weights")
    elif kind == "table":
        if n_in != 1:
            raise ValueError(f"a table takes exactly one input, got {n_in}")
        if len(fn.knots) < 2:
            raise ValueError("a table needs at least two knots")
        out["values"] = ((len(fn.knots), n_out), "weights")
    else:
        raise ValueError(f"unknown learned function kind {kind!r}")
    out["x_mean"] = ((n_in,), "stat")
    out["x_scale"] = ((n_in,), "stat")
    out["y_scale"] = ((n_out,), "stat")
    return out


def init_arrays(fn, n_in: int, n_out: int, rng: np.random.Generator, *, x_mean=None, x_scale=None,
                y_scale=None) -> dict[str, np.ndarray]:
    """Initial arrays (float64 numpy) of ``fn``: hidden MLP layers Glorot-uniform, biases and the last
    layer zero (so ``z = 0``); stats from the keyword arguments (default 0, 1, 1)."""
    shapes = array_shapes(fn, n_in, n_out)
    arrays: dict[str, np.ndarray] = {}
    last_w = f"W{len(fn.hidden)}" if fn.kind == "mlp" else None
    for name, (shape, _) in shapes.items():
        if fn.kind == "mlp" and name.startswith("W") and name != last_w:
            fan_in, fan_out = shape
            lim = math.sqrt(6.0 / (fan_in + fan_out))
            arrays[name] = rng.uniform(-lim, lim, size=shape)
        else:
            arrays[name] = np.zeros(shape)
    arrays["x_mean"] = np.broadcast_to(np.asarray(0.0 if x_mean is None else x_mean, float), (n_in,)).copy()
    arrays["x_scale"] = np.broadcast_to(np.asarray(1.0 if x_scale is None else x_scale, float), (n_in,)).copy()
    arrays["y_scale"] = np.broadcast_to(np.asarray(1.0 if y_scale is None else y_scale, float), (n_out,)).copy()
    return arrays


def activation(xp, name: str):
    """The activation function ``name`` of an MLP's hidden layers."""
    if name in ("sigmoid", "tanh", "relu", "softplus", "silu"):
        return getattr(xp, name)
    raise ValueError(f"unknown activation {name!r}")


def apply_normalised(xp, fn, arrays, xn, mono_idx=None):
    """``z (..., n_out)`` from the normalised input ``xn = (x − x_mean)/x_scale (..., n_in)``.
    For ``table`` the raw input is recovered from the stats. ``mono_idx`` (poly) may be passed
    precomputed (:func:`monomial_index`)."""
    kind = fn.kind
    if kind == "const":
        c = arrays["c"]
        if xn is None:
            return c
        return xn[..., :1] * 0.0 + c if xp.shape(xn)[-1] > 0 else c
    if kind == "linear":
        if xp.shape(arrays["W"])[0] == 0:
            return arrays["b"]
        return xp.matmul(xn, arrays["W"]) + arrays["b"]
    if kind == "poly":
        idx = monomial_index(xp.shape(xn)[-1], int(fn.degree or 2)) if mono_idx is None else mono_idx
        ones = xn[..., :1] * 0.0 + 1.0
        X = xp.concat([ones, xn], axis=-1)
        feats = X[..., idx[:, 0]]
        for j in range(1, idx.shape[1]):
            feats = feats * X[..., idx[:, j]]
        return xp.matmul(feats, arrays["W"]) + arrays["b"]
    if kind == "mlp":
        act = activation(xp, fn.activation)
        n_layers = len(fn.hidden) + 1
        h = xn
        for k in range(n_layers):
            h = xp.matmul(h, arrays[f"W{k}"]) + arrays[f"b{k}"]
            if k < n_layers - 1:
                h = act(h)
        return h
    if kind == "table":
        x = xn[..., 0] * arrays["x_scale"][0] + arrays["x_mean"][0]
        return table_apply(xp, fn.knots, arrays["values"], x)
    raise ValueError(f"unknown learned function kind {kind!r}")


def table_apply(xp, knots, values, x):
    """Piecewise-linear interpolation of trainable ``values (n_knots, n_out)`` at the fixed ``knots`` (SI,
    increasing) for ``x (...)`` → ``(..., n_out)``; constant beyond the ends."""
    k = np.asarray(knots, dtype=np.float64)
    lo, hi = xp.asarray(k[:-1]), xp.asarray(k[1:])
    inv = xp.asarray(1.0 / np.diff(k))
    w = (xp.minimum(xp.maximum(x[..., None], lo), hi) - lo) * inv  # (..., n_seg) in [0, 1]
    return values[0] + xp.matmul(w, values[1:] - values[:-1])


def normalise(x, arrays):
    """``(x − x_mean)/x_scale``."""
    return (x - arrays["x_mean"]) / arrays["x_scale"]


def apply(xp: Any, fn: LearnFunction, arrays: Mapping[str, Any], x: Any) -> Any:
    """The raw output ``z (..., n_out)`` of ``fn`` for ``x (..., n_in)`` (SI; node temperatures in K)."""
    return apply_normalised(xp, fn, arrays, normalise(x, arrays))


def pos1(xp, v):
    """``softplus(4v)/softplus(4)``: positive, 1 at v = 1, ≈ v for v ≳ 0.5."""
    return xp.softplus(4.0 * v) / _SOFTPLUS4


def target_value(xp: Any, z: Any, nominal: Any, positive: bool, y_scale: Any, replace: bool = False) -> Any:
    """The value of one target from its raw output ``z``.

    * positive parameter (R, G, C, τ): ``nominal · pos1(1 + z)``;
    * otherwise: ``nominal + y_scale·z``, or ``y_scale·z`` with ``replace`` (a replaced flow).
    """
    if positive:
        return nominal * pos1(xp, 1.0 + z)
    if replace:
        return y_scale * z
    return nominal + y_scale * z


__all__ = ["array_shapes", "init_arrays", "apply", "apply_normalised", "normalise", "target_value", "pos1",
           "monomial_index", "table_apply", "activation", "STAT_NAMES"]
