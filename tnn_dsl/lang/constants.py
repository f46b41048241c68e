"""The values of constant expressions, with the values the user wrote, for the validation pass.

A parameter written as an expression of other constants (``C = c0 - 8 J/K``, ``R = 0.3 * 0 K/W``) has a
value before any data is read; :class:`ConstValues` computes it on the IR (SI, floats; no ``eval``),
with the semantics of the compiled model (:mod:`tnn_dsl.compiler.expressions`, which this layer may not
import), so the validation pass can apply to it the checks a written number gets. Every problem is
reported at its source position: a division by zero (a divisor that is constant and zero, also inside an
expression that reads inputs or temperatures), ``0 ^ -1``, the logarithm or square root of a value out of
their domain, an overflow to infinity.
"""

from __future__ import annotations

import math
from typing import Callable

from ..ir import Binary, Call, Num, Param, Ref, Span, Table, Temp, Unary

_BAD = object()
"""The value of a (sub-)expression whose problem was reported: no further report depends on it."""


class ConstValues:
    """``value(name)``: the SI value of a parameter whose expression reads only constants, ``None`` if
    it reads an input, a temperature or a parameter with a problem. Each expression is evaluated once;
    problems go to ``err(message, span, hint)``."""

    def __init__(self, params: dict[str, Param], exprs: dict[str, object],
                 err: Callable[[str, Span | None, str | None], None]):
        self.params = params
        self.exprs = exprs
        self.err = err
        self.values: dict[str, object] = {}
        self.active: set[str] = set()

    def value(self, name: str) -> float | None:
        v = self._param(name)
        return v if isinstance(v, float) else None

    def _param(self, name: str):
        if name in self.values:
            return self.values[name]
        if name in self.active or name not in self.params:
            return _BAD  # a cycle or an unknown name: reported by the validation pass
        self.active.add(name)
        v = self._eval(self.exprs.get(name, self.params[name].expr), name)
        self.active.discard(name)
        self.values[name] = v
        return v

    # -- one expression ---------------------------------------------------------------------

    def _eval(self, e, owner: str):
        """A float, ``None`` (not constant) or ``_BAD`` (a problem was reported)."""
        if isinstance(e, Num):
            return float(e.value)
        if isinstance(e, Ref):
            return self._param(e.name) if e.kind == "param" else (None if e.kind == "input" else _BAD)
        if isinstance(e, Temp):
            return None
        if isinstance(e, Unary):
            a = self._eval(e.arg, owner)
            return -a if isinstance(a, float) else a
        if isinstance(e, Binary):
            return self._binary(e, self._eval(e.left, owner), self._eval(e.right, owner), owner)
        if isinstance(e, Call):
            args = [self._eval(a, owner) for a in e.args]
            if any(a is _BAD for a in args):
                return _BAD
            if any(a is None for a in args):
                return None
            return self._call(e, args, owner)
        if isinstance(e, Table):
            x = self._eval(e.x, owner)
            return _interp(x, e.xs, e.ys) if isinstance(x, float) else x
        return _BAD

    def _binary(self, e: Binary, a, b, owner: str):
        if e.op == "/" and isinstance(b, float) and b == 0.0:
            if a is not _BAD:
                self.err(f"division by zero in `{owner}`", e.span, _zero_hint(e.right))
            return _BAD
        if a is _BAD or b is _BAD:
            return _BAD
        if a is None or b is None:
            return None
        op = e.op
        if op == "^":
            if a == 0.0 and b < 0:
                self.err(f"division by zero in `{owner}`: 0 raised to the negative power {b:g}", e.span,
                         _zero_hint(e.left))
                return _BAD
            if a < 0 and not b.is_integer():
                self.err(f"`{owner}` is not a real number: {a:g} raised to the power {b:g}", e.span,
                         "a negative value has no real power that is not a whole number")
                return _BAD
            try:
                v = a**b
            except OverflowError:
                v = math.inf
        else:
            v = a + b if op == "+" else a - b if op == "-" else a * b if op == "*" else a / b
        return self._finite(v, e, owner)

    def _call(self, e: Call, args: list[float], owner: str):
        fn, x = e.fn, args[0]
        if fn == "log" and x <= 0:
            self.err(f"`log` of {x:g} in `{owner}`: the logarithm needs a positive argument", e.span,
                     "with the written values the argument of `log` is not positive")
            return _BAD
        if fn == "sqrt" and x < 0:
            self.err(f"`sqrt` of {x:g} in `{owner}`: the square root needs an argument of at least 0", e.span,
                     "with the written values the argument of `sqrt` is negative")
            return _BAD
        if fn == "parallel" and (any(a == 0.0 for a in args) or sum(1.0 / a for a in args) == 0.0):
            self.err(f"division by zero in `{owner}`: `parallel` of {', '.join(f'{a:g}' for a in args)}", e.span,
                     "`parallel(a, b, ...)` is 1 / (1/a + 1/b + ...): no argument may be zero, nor their "
                     "inverses sum to zero")
            return _BAD
        if fn == "exp":
            v = math.exp(x) if x <= 709 else math.inf
        elif fn == "log":
            v = math.log(x)
        elif fn == "sqrt":
            v = math.sqrt(x)
        elif fn == "abs":
            v = abs(x)
        elif fn == "min":
            v = min(args)
        elif fn == "max":
            v = max(args)
        elif fn == "series":
            v = sum(args)
        elif fn == "parallel":
            v = 1.0 / sum(1.0 / a for a in args)
        else:  # mean
            v = sum(args) / len(args)
        return self._finite(float(v), e, owner)

    def _finite(self, v: float, e, owner: str):
        if math.isfinite(v):
            return v
        self.err(f"`{owner}` is not a finite number: this part evaluates to {v:g}", e.span,
                 "with the written values the result overflows the double-precision range")
        return _BAD


def _zero_hint(divisor) -> str:
    if isinstance(divisor, Num):
        return "the divisor is written as 0"
    return "with the written values the divisor evaluates to 0"


def _interp(x: float, xs: list[float], ys: list[float]) -> float:
    """Piecewise-linear in ``x`` through ``(xs, ys)`` (``xs`` increasing), constant beyond the ends."""
    if not xs:
        return math.nan
    if x <= xs[0]:
        return float(ys[0])
    if x >= xs[-1]:
        return float(ys[-1])
    for x0, x1, y0, y1 in zip(xs, xs[1:], ys, ys[1:]):
        if x <= x1:
            return float(y0 + (y1 - y0) * (x - x0) / (x1 - x0))
    return float(ys[-1])


__all__ = ["ConstValues"]
