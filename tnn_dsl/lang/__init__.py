"""The ``.thn`` language: text in, validated IR out.

Owns: the grammar loading and the Lark parser with its catalogue of malformed examples (``parser``), unit
parsing and dimension algebra (``units``, pint underneath), and the one validation pass (``validate``).
May import: ``tnn_dsl.core``, ``tnn_dsl.ir``.
"""

from __future__ import annotations

from .parser import load, loads, parse
from .units import UnitError, format_dim, parse_quantity, unit_scale
from .validation import validate

__all__ = [
    "load", "loads", "parse", "UnitError", "format_dim", "parse_quantity", "unit_scale", "validate"
]
