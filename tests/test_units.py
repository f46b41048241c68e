"""Units: literals to SI and dimensions, temperature handling, dimension algebra."""

from __future__ import annotations

import pytest

from tnn_dsl.lang.units import (
    COMMON_UNITS,
    UnitError,
    _convert,
    _convert_with_pint,
    describe_dim,
    dim_div,
    dim_eq,
    dim_mul,
    dim_pow,
    format_dim,
    is_temperature_unit,
    parse_quantity,
    unit_dim,
)

R = {"kg": -1.0, "m": -2.0, "s": 3.0, "K": 1.0}
G = {"kg": 1.0, "m": 2.0, "s": -3.0, "K": -1.0}


@pytest.mark.parametrize("value, unit, si, dim", [
    (0.08, "K/W", 0.08, R),
    (0.05, "W/K", 0.05, G),
    (40, "J/K", 40.0, G | {"s": -2.0}),
    (0.01, "W/%", 1.0, {"kg": 1.0, "m": 2.0, "s": -3.0}),
    (50, "%", 0.5, {}),
    (50, "[%]", 0.5, {}),
    (3, "[1]", 3.0, {}),
    (2, "[A]", 2.0, {"A": 1.0}),
    (4186, "J/(kg*K)", 4186.0, {"m": 2.0, "s": -2.0, "K": -1.0}),
    (1e-3, "m^2", 1e-3, {"m": 2.0}),
    (2, "ohm", 2.0, {"kg": 1.0, "m": 2.0, "s": -3.0, "A": -2.0}),
    (0.05, "V/K", 0.05, {"kg": 1.0, "m": 2.0, "s": -3.0, "A": -1.0, "K": -1.0}),
    (0.002, "kg/s", 0.002, {"kg": 1.0, "s": -1.0}),
    (20, "s", 20.0, {"s": 1.0}),
    (2, "min", 120.0, {"s": 1.0}),
    (1.5, "h", 5400.0, {"s": 1.0}),
    (23, "degC", 296.15, {"K": 1.0}),
    (300, "K", 300.0, {"K": 1.0}),
    (32, "degF", 273.15, {"K": 1.0}),
    (212, "degF", 373.15, {"K": 1.0}),
    (0.02, "1/K", 0.02, {"K": -1.0}),
    (2, "W/degC", 2.0, G),  # inside a compound unit degC is a difference
    (9, "W/degF", 9 * 9 / 5, G),
    (7, None, 7.0, {}),
])
def test_parse_quantity(value, unit, si, dim):
    v, d = parse_quantity(value, unit)
    assert v == pytest.approx(si, rel=1e-12)
    assert dim_eq(d, dim)


@pytest.mark.parametrize("unit", ["furlongs/fortnite", "Wat", "W/", "degc", "K^x"])
def test_unknown_units_raise_with_hint(unit):
    with pytest.raises(UnitError) as info:
        parse_quantity(1.0, unit)
    assert unit in info.value.message
    assert info.value.hint


def test_degc_hint():
    with pytest.raises(UnitError) as info:
        parse_quantity(1.0, "degc")
    assert "degC" in info.value.hint


def test_temperature_units():
    assert is_temperature_unit("degC") and is_temperature_unit("K") and is_temperature_unit("degF")
    assert not is_temperature_unit("W/K") and not is_temperature_unit(None)


def test_dimension_algebra():
    W = unit_dim("W")
    assert dim_eq(dim_mul(G, unit_dim("K")), W)
    assert dim_eq(dim_div(unit_dim("K"), W), R)
    assert dim_eq(dim_pow(unit_dim("m"), 2), unit_dim("m^2"))
    assert dim_eq(dim_pow(unit_dim("m^2"), 0.5), unit_dim("m"))
    assert dim_mul(R, G) == {}


def test_format_and_describe():
    assert format_dim(R) == "K/W"
    assert format_dim(G) == "W/K"
    assert format_dim({}) == "1"
    assert describe_dim(R) == "a resistance (K/W)"
    assert "K" in format_dim({"K": 2.0, "A": -1.0})


@pytest.mark.parametrize("unit", sorted(COMMON_UNITS))
def test_each_common_unit_is_what_pint_makes_of_it(unit):
    """The table that spares a file of common units pint's import is pint's own answer, to the bit, bare and in a
    data column's brackets."""
    assert COMMON_UNITS[unit] == _convert_with_pint(unit) == _convert_with_pint(f"[{unit}]")
    assert _convert(f"[ {unit} ]") == COMMON_UNITS[unit]


def test_a_network_in_common_units_is_read_without_pint():
    """The case study and a building model parse, validate and convert without importing pint (about 0.45 s of every
    command); a unit outside the table still goes to pint."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = ("import sys, tnn_dsl\n"
            "for f in ('networks/peltier_heatpipe/m1.thn', 'networks/building/ti.thn'):\n"
            "    tnn_dsl.load(f)\n"
            "print('pint' in sys.modules)\n"
            "from tnn_dsl.lang.units import parse_quantity\n"
            "print(parse_quantity(1.0, 'BTU/h'), 'pint' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    first, second = out.stdout.splitlines()
    assert first == "False"
    assert second.endswith("True") and second.startswith("(0.29307")
