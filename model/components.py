"""Component physics that more than one caller needs, written once (SI units).

- the flooded evaporator's closed form (SPEC §3) and its inversion on a measured evaporating
  temperature (SPEC §4);
- the counterflow effectiveness of one heat-exchanger zone (the condenser unit's three zones).

The functions take plain floats or numpy arrays (elementwise); nothing here calls CoolProp.
"""
from __future__ import annotations

import math

import numpy as np


def _exp(x):
    return np.exp(x) if isinstance(x, np.ndarray) else math.exp(x)


def evaporator_T_e(T_in, T_out, UA, C):
    """Evaporating temperature [K] of the flooded evaporator.

    T_in, T_out : source water in and out [K]; UA : conductance [W/K] with
    1/UA = 1/(CF_eva*U*A) + R_th,f; C : source capacity rate c_p*rho*V [W/K].
    Refrigerant at T_e along the whole surface: NTU = UA/C and
    T_e = (T_out*e^NTU - T_in) / (e^NTU - 1).
    """
    e = _exp(UA / C)
    return (T_out * e - T_in) / (e - 1.0)


def evaporator_UA(T_in, T_out, T_e, C):
    """Conductance [W/K] that carries the source duty at evaporating temperature T_e [K]:
    NTU = ln((T_in - T_e)/(T_out - T_e)), UA = NTU*C. NaN where T_in > T_out > T_e fails."""
    if isinstance(T_in, np.ndarray) or isinstance(T_e, np.ndarray) or isinstance(C, np.ndarray):
        T_in, T_out, T_e, C = (np.asarray(x, dtype=float) for x in (T_in, T_out, T_e, C))
        ok = (T_in > T_out) & (T_out > T_e) & (C > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(ok, np.log((T_in - T_e) / (T_out - T_e)) * C, np.nan)
    if not (T_in > T_out > T_e and C > 0):
        return math.nan
    return math.log((T_in - T_e) / (T_out - T_e)) * C


def counterflow_eps(C_a: float, C_b: float, UA: float) -> tuple[float, float]:
    """(effectiveness, C_min) of a counterflow exchanger between capacity rates C_a, C_b [W/K]."""
    C_min, C_max = (C_a, C_b) if C_a < C_b else (C_b, C_a)
    NTU = UA / C_min
    Cr = C_min / C_max
    if abs(1.0 - Cr) < 1e-9:
        return NTU / (1.0 + NTU), C_min
    x = math.exp(-NTU * (1.0 - Cr))
    return (1.0 - x) / (1.0 - Cr * x), C_min
