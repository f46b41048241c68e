"""Evaluate IR expressions (:mod:`tnn_dsl.ir.network` ``Expr`` trees) against an array namespace ``xp``.

No ``eval``: an expression is turned once into a tree of small Python closures
(:func:`compile_expr`), which the compiled model calls every step. Constant sub-trees are folded to
Python floats at compile time, so they cost nothing per step.

Semantics (all quantities SI, temperatures in kelvin):

* ``a ^ b`` is ``a ** b``; ``-a`` negation.
* ``exp log sqrt abs``; ``min(a, b, ...)``, ``max(a, b, ...)`` element-wise;
  ``series(a, b, ...) = a + b + ...``; ``parallel(a, b, ...) = 1 / (1/a + 1/b + ...)``
  (``a·b/(a + b)`` for two); ``mean(a, b, ...)`` the arithmetic mean.
* ``table(x; x0: y0, x1: y1, ...)``: piecewise-linear in ``x``, constant beyond the ends.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

import numpy as np

from ..ir import Binary, Call, Expr, Num, Ref, Table, Temp, Unary
from .backends import _interp_segments, interp_with

Getter = Callable[[Any], Any]
"""``getter(env) -> value``: how a compiled expression reads a parameter, input or temperature."""


def dependencies(expr) -> tuple[set[str], set[str]]:
    """``(ref names, temperature nodes)`` an expression reads (``Ref`` names are params or inputs)."""
    from ..ir import walk

    nodes = list(walk(expr))
    return {e.name for e in nodes if isinstance(e, Ref)}, {e.node for e in nodes if isinstance(e, Temp)}


_FLOAT_CALLS = {
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "abs": abs,
}


def _is_const(v) -> bool:
    return isinstance(v, float)


def compile_expr(expr, xp, ref: Callable[[str], Getter | float],
                 temp: Callable[[str], Getter | float]) -> Callable[[Any], Any]:
    """Turn ``expr`` into ``fn(env) -> value`` (a backend array, or a Python float if constant).

    ``ref(name)`` and ``temp(node)`` return either a getter ``g(env)`` or a Python float (a value known
    at compile time, folded into constants). ``env`` is whatever the getters understand.
    """
    node = _build(expr, xp, ref, temp)
    if _is_const(node):
        value = node
        return lambda env: value
    return node


def _build(e, xp, ref, temp):  # returns float or closure(env)
    if isinstance(e, Num):
        return float(e.value)
    if isinstance(e, Ref):
        return ref(e.name)
    if isinstance(e, Temp):
        return temp(e.node)
    if isinstance(e, Unary):
        a = _build(e.arg, xp, ref, temp)
        if _is_const(a):
            return -a
        return lambda env: -a(env)
    if isinstance(e, Binary):
        a = _build(e.left, xp, ref, temp)
        b = _build(e.right, xp, ref, temp)
        op = e.op
        if _is_const(a) and _is_const(b):
            return float(_binop(op, a, b))
        fa = (lambda env, a=a: a) if _is_const(a) else a
        fb = (lambda env, b=b: b) if _is_const(b) else b
        if op == "+":
            return lambda env: fa(env) + fb(env)
        if op == "-":
            return lambda env: fa(env) - fb(env)
        if op == "*":
            return lambda env: fa(env) * fb(env)
        if op == "/":
            return lambda env: fa(env) / fb(env)
        if op == "^":
            if _is_const(b) and b == 2.0:
                return lambda env: fa(env) * fa(env)
            return lambda env: fa(env) ** fb(env)
        raise ValueError(f"unknown operator {op!r}")
    if isinstance(e, Call):
        args = [_build(a, xp, ref, temp) for a in e.args]
        fn = e.fn
        if all(_is_const(a) for a in args):
            return float(_call_float(fn, args))
        fs = [(lambda env, a=a: a) if _is_const(a) else a for a in args]
        if fn in ("exp", "log", "sqrt", "abs"):
            if len(fs) != 1:
                raise ValueError(f"{fn}() takes one argument, got {len(fs)}")
            f0, op = fs[0], getattr(xp, fn)
            return lambda env: op(_arr(xp, f0(env)))
        if fn in ("min", "max"):
            op = xp.minimum if fn == "min" else xp.maximum

            def mm(env):
                out = fs[0](env)
                for f in fs[1:]:
                    out = op(out, f(env))
                return out

            return mm
        if fn == "series":
            return lambda env: _sum(f(env) for f in fs)
        if fn == "parallel":
            if len(fs) == 2:
                f0, f1 = fs

                def par2(env):
                    a, b = f0(env), f1(env)
                    return a * b / (a + b)

                return par2
            return lambda env: 1.0 / _sum(1.0 / f(env) for f in fs)
        if fn == "mean":
            n = float(len(fs))
            return lambda env: _sum(f(env) for f in fs) / n
        raise ValueError(f"unknown function {fn!r}")
    if isinstance(e, Table):
        x = _build(e.x, xp, ref, temp)
        lo, hi, slope, y0 = _interp_segments(e.xs, e.ys)
        if _is_const(x):
            return float(np.interp(x, e.xs, e.ys))
        if len(lo) == 0:
            return y0
        lo_a, hi_a, s_a = xp.asarray(lo), xp.asarray(hi), xp.asarray(slope)
        return lambda env: interp_with(xp, _arr(xp, x(env)), lo_a, hi_a, s_a, y0)
    raise TypeError(f"not an expression: {type(e).__name__}")


def _sum(it):
    out = None
    for v in it:
        out = v if out is None else out + v
    return out


def _arr(xp, v):
    return xp.asarray(v) if isinstance(v, (int, float)) else v


def _binop(op, a, b):
    if op == "+":
        return a + b
    if op == "-":
        return a - b
    if op == "*":
        return a * b
    if op == "/":
        return a / b if b != 0 else math.copysign(math.inf, a) if a != 0 else math.nan
    if op == "^":
        try:
            return a**b if not (a < 0 and not float(b).is_integer()) else math.nan
        except OverflowError:
            return math.inf
    raise ValueError(op)


def _call_float(fn, args):
    if fn in _FLOAT_CALLS:
        x = args[0]
        if fn == "log" and x <= 0:
            return -math.inf if x == 0 else math.nan
        if fn == "sqrt" and x < 0:
            return math.nan
        if fn == "exp" and x > 709:
            return math.inf
        return _FLOAT_CALLS[fn](x)
    if fn == "min":
        return min(args)
    if fn == "max":
        return max(args)
    if fn == "series":
        return sum(args)
    if fn == "parallel":
        return 1.0 / sum(1.0 / a for a in args)
    if fn == "mean":
        return sum(args) / len(args)
    raise ValueError(f"unknown function {fn!r}")


def evaluate(expr: Expr, xp: Any, values: Mapping[str, Any] | None = None,
             temps: Mapping[str, Any] | None = None) -> Any:
    """Evaluate ``expr`` once: ``values`` maps parameter and input names to values, ``temps`` node
    (or boundary) names to temperatures (K). Convenience wrapper around :func:`compile_expr`."""
    values = dict(values or {})
    temps = dict(temps or {})

    def ref(name):
        if name not in values:
            raise KeyError(f"expression reads {name!r}, which has no value")
        return lambda env: values[name]

    def temp(node):
        if node not in temps:
            raise KeyError(f"expression reads T({node}), which has no value")
        return lambda env: temps[node]

    return compile_expr(expr, xp, ref, temp)(None)


__all__ = ["compile_expr", "evaluate", "dependencies"]
