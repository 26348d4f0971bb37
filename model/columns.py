"""The canonical names of SPEC §4: tag names of the default tag map and columns of every history
CSV, with the quantity each one measures (its canonical unit is ``units.CANONICAL_UNITS``).

Pure data: no imports beyond the standard library, so that the gateway's configuration check can
name a missing tag without loading CoolProp.
"""
from __future__ import annotations

# name -> (quantity, what it is)
CANONICAL: dict[str, tuple[str, str]] = {
    "T_sink_in": ("temperature", "sink water at the subcooler inlet"),
    "T_sink_out": ("temperature", "sink water at the desuperheater outlet"),
    "T_source_in": ("temperature", "source water at the evaporator inlet"),
    "T_source_out": ("temperature", "source water at the evaporator outlet"),
    "V_sink": ("volume_flow", "sink water flow"),
    "V_source": ("volume_flow", "source water flow"),
    "p_source_in": ("pressure", "source water pressure at the evaporator inlet"),
    "p_source_out": ("pressure", "source water pressure at the evaporator outlet"),
    "T_suc_LS": ("temperature", "ammonia at the low-stage suction"),
    "T_dis_LS": ("temperature", "ammonia at the low-stage discharge"),
    "T_suc_HS": ("temperature", "ammonia at the high-stage suction"),
    "T_dis_HS": ("temperature", "ammonia at the high-stage discharge"),
    "p_suc_LS": ("pressure", "ammonia pressure at the low-stage suction"),
    "p_dis_LS": ("pressure", "ammonia pressure at the low-stage discharge"),
    "p_suc_HS": ("pressure", "ammonia pressure at the high-stage suction"),
    "p_dis_HS": ("pressure", "ammonia pressure at the high-stage discharge"),
    "T_c": ("temperature", "ammonia at the condenser outlet"),
    "T_e": ("temperature", "ammonia at the evaporator inlet"),
    "W_LS": ("power", "low-stage compressor electric power"),
    "W_HS": ("power", "high-stage compressor electric power"),
    "p_m_sp": ("pressure", "intermediate-pressure set point"),
    "N_LS": ("speed", "low-stage compressor speed"),
    "N_HS": ("speed", "high-stage compressor speed"),
    "running": ("dimensionless", "heat pump in operation (0/1)"),
    "cip": ("dimensionless", "cleaning in place in progress (0/1)"),
}
OPTIONAL: tuple[str, ...] = ("N_LS", "N_HS", "running", "cip")
REQUIRED: tuple[str, ...] = tuple(n for n in CANONICAL if n not in OPTIONAL)
