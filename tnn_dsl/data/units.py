"""Units of data columns: temperatures to and from kelvin, and the SI factor of a column unit."""

from __future__ import annotations

from typing import Any

__all__ = ["to_kelvin", "from_kelvin", "unit_factor", "unit_scale_offset"]


def to_kelvin(x: Any, unit: str) -> Any:
    """Temperatures (any array shape) from ``unit`` (``degC``, ``K``, ``degF``) to kelvin."""
    if unit == "degC":
        return x + 273.15
    if unit == "K":
        return x + 0.0
    if unit == "degF":
        return (x - 32.0) * (5.0 / 9.0) + 273.15
    raise ValueError(f"unknown temperature unit {unit!r}")


def from_kelvin(x: Any, unit: str) -> Any:
    """Temperatures (any array shape) from kelvin to ``unit`` (``degC``, ``K``, ``degF``)."""
    if unit == "degC":
        return x - 273.15
    if unit == "K":
        return x + 0.0
    if unit == "degF":
        return (x - 273.15) * (9.0 / 5.0) + 32.0
    raise ValueError(f"unknown temperature unit {unit!r}")


def unit_factor(unit: str | None) -> float:
    """The factor that takes a value in ``unit`` to SI (``"%"`` → 0.01, ``"kW"`` → 1000, ``None`` → 1).
    Raises ``ValueError`` for a unit that is not known (or is an absolute temperature scale)."""
    scale, offset = unit_scale_offset(unit)
    if offset != 0.0:
        raise ValueError(f"the unit {unit!r} is an absolute temperature; declare the input `: temperature`")
    return scale


def unit_scale_offset(unit: str | None) -> tuple[float, float]:
    """(scale, offset) with SI = scale·x + offset, from ``tnn_dsl.lang.units`` (pint underneath)."""
    if unit is None or unit.strip().strip("[]").strip() in ("", "1", "-"):
        return 1.0, 0.0
    from ..lang import UnitError, unit_scale

    try:
        return unit_scale(unit)
    except UnitError as err:
        raise ValueError(err.message) from None
