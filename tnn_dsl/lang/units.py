"""Units: ``NUMBER UNIT`` literals to SI values and dimensions, and the dimension algebra used by the
static checks of ``_validate``.

A dimension (``_ir.Dim``) is a dict of exponents over the SI base units ``kg m s K A mol cd``; ``{}`` is
dimensionless. Conversion is done by `pint <https://pint.readthedocs.io>`_; the registry is created once,
lazily (with pint's import about 0.45 s), and only for a unit that is not among the common ones
(:data:`COMMON_UNITS`, pint's own results for them).

Temperatures: a lone temperature unit (``23 degC``, ``296 K``, ``70 degF``) is an *absolute* temperature
and converts to kelvin (``23 degC`` -> 296.15). Inside a compound unit (``W/degC``, ``J/(kg*degC)``,
``1/degC``) a temperature unit is a temperature *difference* (1 degC = 1 K, 1 degF = 5/9 K).
Percent (``%``) is the dimensionless factor 0.01: ``0.01 W/%`` is 1 W per unit fraction.
"""

from __future__ import annotations

import math
import re
from functools import lru_cache

from ..ir import Dim

BASE = ("kg", "m", "s", "K", "A", "mol", "cd")
_PINT_DIM = {
    "[mass]": "kg",
    "[length]": "m",
    "[time]": "s",
    "[temperature]": "K",
    "[current]": "A",
    "[substance]": "mol",
    "[luminosity]": "cd",
}

TEMPERATURE_UNITS = {
    # name in files -> (scale to kelvin, offset in kelvin): T_K = scale * x + offset
    "K": (1.0, 0.0),
    "kelvin": (1.0, 0.0),
    "degC": (1.0, 273.15),
    "°C": (1.0, 273.15),
    "celsius": (1.0, 273.15),
    "degF": (5.0 / 9.0, 273.15 - 32.0 * 5.0 / 9.0),
    "°F": (5.0 / 9.0, 273.15 - 32.0 * 5.0 / 9.0),
    "fahrenheit": (5.0 / 9.0, 273.15 - 32.0 * 5.0 / 9.0),
}

TEMPERATURE = {"K": 1.0}
DIMENSIONLESS: dict[str, float] = {}


class UnitError(ValueError):
    """A unit the registry does not know, or cannot convert. ``hint`` says what to write instead."""

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.hint = hint


@lru_cache(maxsize=1)
def _registry():
    import pint

    return pint.UnitRegistry(autoconvert_offset_to_baseunit=False)


_OFFSET_WORDS = {"degC": "delta_degC", "°C": "delta_degC", "celsius": "delta_degC",
                 "degF": "delta_degF", "°F": "delta_degF", "fahrenheit": "delta_degF"}


def _normalise(unit: str) -> str:
    """Text as written -> text pint parses: ``%`` -> ``percent``, ``[%]`` -> ``percent``, offset
    temperature units inside a compound unit -> their ``delta_`` form."""
    u = unit.strip()
    if u.startswith("[") and u.endswith("]"):
        u = u[1:-1].strip()
    u = u.replace("%", "percent").replace("µ", "u").replace("Ω", "ohm")
    if u in TEMPERATURE_UNITS:
        return u
    for word, delta in _OFFSET_WORDS.items():
        u = re.sub(rf"(?<![A-Za-z_]){re.escape(word)}(?![A-Za-z0-9_])", delta, u)
    return u


_ENERGY_PER_K = (("kg", 1.0), ("m", 2.0), ("s", -2.0), ("K", -1.0))
_POWER = (("kg", 1.0), ("m", 2.0), ("s", -3.0))
_RESISTANCE = (("kg", -1.0), ("m", -2.0), ("s", 3.0), ("K", 1.0))
_SEEBECK = (("kg", 1.0), ("m", 2.0), ("s", -3.0), ("K", -1.0), ("A", -1.0))
COMMON_UNITS: dict[str, tuple[float, float, tuple[tuple[str, float], ...]]] = {
    "K/W": (1.0, 0.0, _RESISTANCE), "K/kW": (0.001, 0.0, _RESISTANCE),
    "W/K": (1.0, 0.0, (("kg", 1.0), ("m", 2.0), ("s", -3.0), ("K", -1.0))),
    "J/K": (1.0, 0.0, _ENERGY_PER_K), "kJ/K": (1000.0, 0.0, _ENERGY_PER_K), "MJ/K": (1000000.0, 0.0, _ENERGY_PER_K),
    "kWh/K": (3600000.0, 0.0, _ENERGY_PER_K),
    "kg/s": (1.0, 0.0, (("kg", 1.0), ("s", -1.0))), "kg/h": (0.0002777777777777778, 0.0, (("kg", 1.0), ("s", -1.0))),
    "J/(kg*K)": (1.0, 0.0, (("m", 2.0), ("s", -2.0), ("K", -1.0))),
    "kJ/(kg*K)": (1000.0, 0.0, (("m", 2.0), ("s", -2.0), ("K", -1.0))),
    "W": (1.0, 0.0, _POWER), "kW": (1000.0, 0.0, _POWER), "mW": (0.001, 0.0, _POWER),
    "W/%": (100.0, 0.0, _POWER), "W/percent": (100.0, 0.0, _POWER), "%": (0.01, 0.0, ()),
    "m^2": (1.0, 0.0, (("m", 2.0),)), "W/m^2": (1.0, 0.0, (("kg", 1.0), ("s", -3.0))),
    "kW/m^2": (1000.0, 0.0, (("kg", 1.0), ("s", -3.0))),
    "V/K": (1.0, 0.0, _SEEBECK), "mV/K": (0.001, 0.0, _SEEBECK),
    "ohm": (1.0, 0.0, (("kg", 1.0), ("m", 2.0), ("s", -3.0), ("A", -2.0))), "A": (1.0, 0.0, (("A", 1.0),)),
    "V": (1.0, 0.0, (("kg", 1.0), ("m", 2.0), ("s", -3.0), ("A", -1.0))),
    "J": (1.0, 0.0, (("kg", 1.0), ("m", 2.0), ("s", -2.0))),
    "s": (1.0, 0.0, (("s", 1.0),)), "min": (60.0, 0.0, (("s", 1.0),)), "h": (3600.0, 0.0, (("s", 1.0),)),
    "Hz": (1.0, 0.0, (("s", -1.0),)), "1/K": (1.0, 0.0, (("K", -1.0),)),
    "m": (1.0, 0.0, (("m", 1.0),)), "mm": (0.001, 0.0, (("m", 1.0),)), "kg": (1.0, 0.0, (("kg", 1.0),)),
    "W/(m*K)": (1.0, 0.0, (("kg", 1.0), ("m", 1.0), ("s", -3.0), ("K", -1.0))),
    "W/(m^2*K)": (1.0, 0.0, (("kg", 1.0), ("s", -3.0), ("K", -1.0))),
}
"""The units thermal networks and their data are written in, as written (a data column's ``[%]`` without its
brackets) -> what pint converts them to (``tests/test_units.py`` checks every entry against pint): a file that
uses only these never imports pint, whose import and registry take about 0.45 s of every command (``tnnc check``
of the case study 0.88 s before; issue 18)."""


@lru_cache(maxsize=512)
def _convert(unit: str) -> tuple[float, float, tuple[tuple[str, float], ...]]:
    """``unit`` -> (scale, offset, dim items): SI value = scale * x + offset."""
    bare = unit.strip()
    if bare.startswith("[") and bare.endswith("]"):
        bare = bare[1:-1].strip()
    if bare in COMMON_UNITS:
        return COMMON_UNITS[bare]
    return _convert_with_pint(unit)


def _convert_with_pint(unit: str) -> tuple[float, float, tuple[tuple[str, float], ...]]:
    """:func:`_convert` of a unit not in :data:`COMMON_UNITS` (or of one that is: the test's reference)."""
    if unit.strip() in ("", "1", "[1]", "[]"):
        return 1.0, 0.0, ()
    text = _normalise(unit)
    if text in TEMPERATURE_UNITS:
        scale, offset = TEMPERATURE_UNITS[text]
        return scale, offset, (("K", 1.0),)
    import pint

    ureg = _registry()
    try:
        q = ureg.Quantity(1.0, text).to_base_units()
    except pint.errors.UndefinedUnitError as err:
        bad = getattr(err, "unit_names", None) or str(err)
        if isinstance(bad, (list, tuple)):
            bad = ", ".join(bad)
        raise UnitError(
            f"unknown unit `{unit}` (`{bad}` is not a unit)",
            hint=_unit_hint(unit),
        ) from None
    except pint.errors.OffsetUnitCalculusError:
        raise UnitError(
            f"cannot use the unit `{unit}`: an absolute temperature scale inside a compound unit",
            hint="write temperature differences in K (1 K = 1 degC), e.g. `W/K`",
        ) from None
    except Exception:  # noqa: BLE001 - pint raises many kinds of parse errors for odd text
        raise UnitError(f"cannot read the unit `{unit}`", hint=_unit_hint(unit)) from None
    dims = []
    for k, v in q.dimensionality.items():
        if k not in _PINT_DIM:
            raise UnitError(f"the unit `{unit}` has a dimension ({k}) this tool does not handle")
        if v:
            dims.append((_PINT_DIM[k], float(v)))
    scale = float(q.magnitude)
    if not math.isfinite(scale) or scale == 0.0:
        raise UnitError(f"cannot use the unit `{unit}`")
    return scale, 0.0, tuple(sorted(dims, key=lambda kv: BASE.index(kv[0])))


def _unit_hint(unit: str) -> str:
    low = unit.lower()
    if low in ("c", "°c", "degc", "deg_c", "celcius"):
        return "write degrees Celsius as `degC`"
    if low in ("f", "degf"):
        return "write degrees Fahrenheit as `degF`"
    if low in ("ohms", "omega"):
        return "write ohms as `ohm`"
    return ("units are written without spaces, e.g. `W/K`, `J/(kg*K)`, `m^2`, `1/K`; "
            "if this is a name, put an operator between the number and it (`2 * x`)")


def parse_quantity(value: float, unit: str | None) -> tuple[float, Dim]:
    """``value unit`` -> (SI value, Dim). ``unit=None`` is a plain number. Raises :class:`UnitError`.

    >>> parse_quantity(23, "degC")
    (296.15, {'K': 1.0})
    """
    if unit is None:
        return float(value), {}
    scale, offset, dims = _convert(unit)
    return float(value) * scale + offset, dict(dims)


def unit_dim(unit: str) -> Dim:
    """The dimension of a unit text (``"K/W"`` -> ``{"kg": -1, "m": -2, "s": 3, "K": 1}``)."""
    return dict(_convert(unit)[2])


def unit_scale(unit: str) -> tuple[float, float]:
    """(scale, offset) with SI = scale * x + offset (offset only for a lone temperature unit)."""
    s, o, _ = _convert(unit)
    return s, o


def is_temperature_unit(unit: str | None) -> bool:
    """True for a lone temperature unit (``K``, ``degC``, ``degF``), i.e. an absolute temperature."""
    return unit is not None and _normalise(unit) in TEMPERATURE_UNITS


# ---------------------------------------------------------------------------------------------
# Dimension algebra
# ---------------------------------------------------------------------------------------------


def _clean(d: dict[str, float]) -> Dim:
    return {k: float(v) for k in BASE if (v := d.get(k, 0.0)) and abs(v) > 1e-12}


def dim_mul(a: Dim, b: Dim) -> Dim:
    return _clean({k: a.get(k, 0.0) + b.get(k, 0.0) for k in BASE})


def dim_div(a: Dim, b: Dim) -> Dim:
    return _clean({k: a.get(k, 0.0) - b.get(k, 0.0) for k in BASE})


def dim_pow(a: Dim, p: float) -> Dim:
    return _clean({k: a.get(k, 0.0) * p for k in BASE})


def dim_eq(a: Dim, b: Dim) -> bool:
    return _clean(a) == _clean(b)


# names for the dimensions a thermal engineer meets, used in messages
_NAMED: list[tuple[str, str, Dim]] = []


def _named() -> list[tuple[str, str, Dim]]:
    if not _NAMED:
        for unit, what in [
            ("K/W", "a resistance"), ("W/K", "a conductance"), ("J/K", "a capacitance"),
            ("K", "a temperature"), ("W", "a heat flow"), ("s", "a time"), ("A", "a current"),
            ("V/K", "a Seebeck coefficient"), ("ohm", "an electrical resistance"),
            ("kg/s", "a mass flow"), ("J/(kg*K)", "a specific heat"), ("m^2", "an area"),
            ("1", "dimensionless"), ("W/m^2", "a heat flux"), ("V", "a voltage"), ("J", "an energy"),
            ("1/K", "a per-kelvin coefficient"), ("W/percent", "a power per percent"),
            ("m", "a length"), ("kg", "a mass"), ("W/(m*K)", "a thermal conductivity"),
            ("W/(m^2*K)", "a heat transfer coefficient"),
        ]:
            _NAMED.append((unit.replace("percent", "%"), what, unit_dim(unit)))
    return _NAMED


def format_dim(d: Dim) -> str:
    """A readable unit for a dimension: a familiar one (``K/W``) when it matches, else base units
    (``kg*m^2/(s^3*K)``)."""
    for unit, _what, dd in _named():
        if dim_eq(d, dd) and unit != "W/%":
            return unit
    num, den = [], []
    for k in BASE:
        v = d.get(k, 0.0)
        if not v:
            continue
        e = abs(v)
        s = k if e == 1 else f"{k}^{e:g}"
        (num if v > 0 else den).append(s)
    if not num and not den:
        return "1"
    top = "*".join(num) if num else "1"
    if not den:
        return top
    bottom = den[0] if len(den) == 1 else "(" + "*".join(den) + ")"
    return f"{top}/{bottom}"


def describe_dim(d: Dim) -> str:
    """``"a resistance (K/W)"`` or ``"kg*m^2/s^3"`` for an unnamed dimension."""
    for unit, what, dd in _named():
        if dim_eq(d, dd) and unit != "W/%":
            return f"{what} ({unit})" if unit != "1" else "dimensionless"
    return f"`{format_dim(d)}`"


__all__ = [
    "BASE", "COMMON_UNITS", "TEMPERATURE", "DIMENSIONLESS", "TEMPERATURE_UNITS", "UnitError", "parse_quantity",
    "unit_dim", "unit_scale", "is_temperature_unit", "dim_mul", "dim_div", "dim_pow", "dim_eq",
    "format_dim", "describe_dim",
]
