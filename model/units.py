"""Unit conversions at the edges of the model.

Inside ``model/`` every quantity is SI: K, Pa (absolute), J/kg, kg/s, W, m^3/s, K/W.
Histories, registers and the HMI use the canonical units of SPEC §4: degC, bar(g), m^3/h, kW.
"""
from __future__ import annotations

T0 = 273.15                     # K at 0 degC
BAR = 1.0e5                     # Pa per bar
M3H = 1.0 / 3600.0              # m^3/s per m^3/h
DEFAULT_AMBIENT_BAR = 1.01325   # standard atmosphere [bar]


def C_to_K(t_C):
    return t_C + T0


def K_to_C(t_K):
    return t_K - T0


def barg_to_Pa(p_barg, ambient_bar: float = DEFAULT_AMBIENT_BAR):
    """Gauge pressure [bar(g)] -> absolute pressure [Pa]."""
    return (p_barg + ambient_bar) * BAR


def Pa_to_barg(p_Pa, ambient_bar: float = DEFAULT_AMBIENT_BAR):
    """Absolute pressure [Pa] -> gauge pressure [bar(g)]."""
    return p_Pa / BAR - ambient_bar


def m3h_to_m3s(v):
    return v * M3H


def m3s_to_m3h(v):
    return v / M3H


# ---------------------------------------------------------------------------------------------
# Engineering units at the edges (tag map, registers): every supported unit and its conversion to
# the canonical unit of SPEC §4, in this one table. A unit not listed here is refused.
#
#   canonical value = value * factor + offset      (pressures: then gauge <-> absolute, below)
#
# Canonical units: temperature degC, pressure bar (gauge in histories and registers; the tag's
# ``pressure: gauge|absolute`` says which one the PLC sends), volume flow m3/h, power kW,
# speed rpm, dimensionless "1" (flags, counters), time s.

PSI_BAR = 0.0689475729316836    # bar per psi (1 lbf/in^2 = 6894.757293168 Pa)

CANONICAL_UNITS: dict[str, str] = {
    "temperature": "degC", "pressure": "bar", "volume_flow": "m3/h", "power": "kW",
    "speed": "rpm", "dimensionless": "1", "time": "s",
}

# unit -> (quantity, factor, offset)
UNITS: dict[str, tuple[str, float, float]] = {
    "degC": ("temperature", 1.0, 0.0),
    "K": ("temperature", 1.0, -T0),
    "degF": ("temperature", 5.0 / 9.0, -32.0 * 5.0 / 9.0),
    "bar": ("pressure", 1.0, 0.0),
    "mbar": ("pressure", 1e-3, 0.0),
    "Pa": ("pressure", 1e-5, 0.0),
    "kPa": ("pressure", 1e-2, 0.0),
    "MPa": ("pressure", 10.0, 0.0),
    "psi": ("pressure", PSI_BAR, 0.0),
    "m3/h": ("volume_flow", 1.0, 0.0),
    "m3/s": ("volume_flow", 3600.0, 0.0),
    "l/s": ("volume_flow", 3.6, 0.0),
    "l/min": ("volume_flow", 0.06, 0.0),
    "W": ("power", 1e-3, 0.0),
    "kW": ("power", 1.0, 0.0),
    "MW": ("power", 1e3, 0.0),
    "rpm": ("speed", 1.0, 0.0),
    "1": ("dimensionless", 1.0, 0.0),
    "s": ("time", 1.0, 0.0),
}
PRESSURE_KINDS = ("gauge", "absolute")


class UnitError(ValueError):
    """A unit that is not in UNITS, or a pressure without its kind or ambient pressure."""


def unit_quantity(unit: str) -> str:
    """'temperature', 'pressure', ... for a supported unit; UnitError names the supported ones."""
    try:
        return UNITS[unit][0]
    except (KeyError, TypeError):
        raise UnitError(f"unsupported unit {unit!r}; supported: {', '.join(UNITS)}") from None


def canonical_linear(unit: str, pressure: str | None = None,
                     ambient_bar: float | None = None) -> tuple[float, float]:
    """(factor, offset) with canonical = value * factor + offset for a value in ``unit``.

    Pressures come out in bar(g): ``pressure`` says whether the value is gauge or absolute, and
    an absolute one needs the ambient pressure [bar] (plant.yaml ``ambient_pressure_bar``).
    """
    quantity, factor, offset = UNITS.get(unit, (None, 0.0, 0.0))
    if quantity is None:
        unit_quantity(unit)   # raises with the list of supported units
    if quantity != "pressure":
        if pressure is not None:
            raise UnitError(f"'pressure: {pressure}' applies to pressure units only, not {unit!r}")
        return factor, offset
    if pressure not in PRESSURE_KINDS:
        raise UnitError(f"a pressure in {unit} needs 'pressure: gauge' or 'pressure: absolute'")
    if pressure == "gauge":
        return factor, offset
    if ambient_bar is None:
        raise UnitError(f"an absolute pressure in {unit} needs the ambient pressure "
                        "(plant.yaml ambient_pressure_bar) to become bar(g)")
    return factor, offset - ambient_bar


def to_canonical(value, unit: str, pressure: str | None = None,
                 ambient_bar: float | None = None):
    """``value`` (a number or numpy array) in ``unit`` -> the canonical unit of its quantity
    (degC, bar(g), m3/h, kW, rpm, 1, s)."""
    factor, offset = canonical_linear(unit, pressure, ambient_bar)
    return value * factor + offset


def from_canonical(value, unit: str, pressure: str | None = None,
                   ambient_bar: float | None = None):
    """The inverse of ``to_canonical``."""
    factor, offset = canonical_linear(unit, pressure, ambient_bar)
    return (value - offset) / factor
