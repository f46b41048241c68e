"""The ``.thn`` language: text in, validated IR out.

Owns: the grammar loading and the Lark parser with its catalogue of malformed examples (``parser``), unit
parsing and dimension algebra (``units``, pint underneath), the one validation pass (``validate``; the values of
constant expressions: ``constants``), and the printer back to ``.thn`` text (``printer``: :func:`print_thn`).
May import: ``tnn_dsl.core``, ``tnn_dsl.ir``.
"""

from __future__ import annotations

from .parser import load, loads, parse
from .printer import print_thn
from .sources import include_path_scope
from .units import UnitError, format_dim, parse_quantity, unit_scale
from .validation import magnitude_warnings, validate, value_problem

__all__ = [
    "include_path_scope", "load", "loads", "parse", "print_thn", "UnitError", "format_dim", "parse_quantity",
    "unit_scale", "validate", "value_problem", "magnitude_warnings",
]
