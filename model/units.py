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
