"""The trainer's one flat vector ``z``: each trainable array (a slot) maps to its values by a transform — ``log`` for
positive parameters, a scaled sigmoid for bounded ones, identity (scaled) otherwise — and sigmoid MLPs move in
tanh coordinates (exact maps both ways)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ir import POSITIVE_ROLES


@dataclass
class _Slot:
    name: str
    shape: tuple[int, ...]
    start: int
    size: int
    transform: str  # log | sigmoid | ident | lower | upper
    lo: float = 0.0
    hi: float = 1.0
    offset: float = 0.0
    scale: float = 1.0


def _make_slot(name: str, spec, value: np.ndarray, start: int, role: str | None) -> _Slot:
    shape = tuple(int(s) for s in np.shape(value))
    size = int(np.prod(shape)) if shape else 1
    lo = spec.lower if spec.lower is not None and np.isfinite(spec.lower) else None
    hi = spec.upper if spec.upper is not None and np.isfinite(spec.upper) else None
    positive = bool(spec.positive) or (role in POSITIVE_ROLES)
    if spec.kind != "physical":
        return _Slot(name, shape, start, size, "ident", offset=0.0, scale=1.0)
    if positive and lo is not None:
        lo = max(lo, 0.0)
    if positive and lo is None:
        lo = 0.0
    if lo is not None and hi is not None and hi > lo:
        return _Slot(name, shape, start, size, "sigmoid", lo=float(lo), hi=float(hi))
    if lo is not None:
        return _Slot(name, shape, start, size, "log" if lo == 0.0 and positive else "lower", lo=float(lo))
    if hi is not None:
        return _Slot(name, shape, start, size, "upper", hi=float(hi))
    v = float(np.max(np.abs(value))) if size else 0.0
    scale = 1.0 if role in ("temperature", "offset") else (v if v > 0 else 1.0)
    return _Slot(name, shape, start, size, "ident", offset=0.0, scale=scale)


def _to_z(slot: _Slot, value: np.ndarray) -> np.ndarray:
    v = np.asarray(value, dtype=float).reshape(-1)
    t = slot.transform
    if t == "log":
        return np.log(np.maximum(v, 1e-300))
    if t == "lower":
        return np.log(np.maximum(v - slot.lo, 1e-12 * max(1.0, abs(slot.lo))))
    if t == "upper":
        return np.log(np.maximum(slot.hi - v, 1e-12 * max(1.0, abs(slot.hi))))
    if t == "sigmoid":
        p = np.clip((v - slot.lo) / (slot.hi - slot.lo), 1e-6, 1 - 1e-6)
        return np.log(p) - np.log1p(-p)
    return (v - slot.offset) / slot.scale


def _from_z(slot: _Slot, zs, ops):
    t = slot.transform
    if t == "log":
        v = ops.exp(zs)
    elif t == "lower":
        v = slot.lo + ops.exp(zs)
    elif t == "upper":
        v = slot.hi - ops.exp(zs)
    elif t == "sigmoid":
        v = slot.lo + (slot.hi - slot.lo) * ops.sigmoid(zs)
    else:
        v = slot.offset + slot.scale * zs if (slot.offset != 0.0 or slot.scale != 1.0) else zs
    return v.reshape(slot.shape)


class _NumpyOps:
    backend = "numpy"

    @staticmethod
    def exp(x):
        return np.exp(x)

    @staticmethod
    def sigmoid(x):
        return 0.5 * (1.0 + np.tanh(0.5 * x))


def _tanh_to_sigmoid(p: dict, fn: str, K: int) -> None:
    """In place: weights ``W'k, b'k`` of a tanh MLP with ``K`` hidden layers → the weights of the sigmoid
    MLP computing the same function (``p["<fn>.Wk"]``, ``p["<fn>.bk"]``; numpy, JAX or torch arrays).

    With σ(a) = ½ + ½·tanh(a/2), hidden unit k of the sigmoid net is ½ + ½·t_k with t_k the tanh net's
    unit: first layer ``W0 = 2W'0, b0 = 2b'0``; hidden → hidden ``Wk = 4W'k, bk = 2b'k − 2·Σ_rows W'k``;
    last layer ``WK = 2W'K, bK = b'K − Σ_rows W'K``. A linear change of coordinates: the trainer runs
    Adam and L-BFGS on the primed (centred, unit-slope) weights."""
    for k in range(K + 1):
        W, b = p[f"{fn}.W{k}"], p[f"{fn}.b{k}"]
        if k == 0:
            p[f"{fn}.W0"], p[f"{fn}.b0"] = 2.0 * W, 2.0 * b
        elif k < K:
            p[f"{fn}.W{k}"], p[f"{fn}.b{k}"] = 4.0 * W, 2.0 * b - 2.0 * W.sum(0)
        else:
            p[f"{fn}.W{k}"], p[f"{fn}.b{k}"] = 2.0 * W, b - W.sum(0)


def _sigmoid_to_tanh(p: dict, fn: str, K: int) -> None:
    """In place, numpy: the inverse of :func:`_tanh_to_sigmoid`."""
    for k in range(K + 1):
        W, b = np.asarray(p[f"{fn}.W{k}"], dtype=float), np.asarray(p[f"{fn}.b{k}"], dtype=float)
        if k == 0:
            p[f"{fn}.W0"], p[f"{fn}.b0"] = W / 2.0, b / 2.0
        elif k < K:
            p[f"{fn}.W{k}"], p[f"{fn}.b{k}"] = W / 4.0, (b + W.sum(0) / 2.0) / 2.0
        else:
            p[f"{fn}.W{k}"], p[f"{fn}.b{k}"] = W / 2.0, b + W.sum(0) / 2.0
