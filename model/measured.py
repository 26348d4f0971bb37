"""Measured side (SPEC §4): canonical plant tags -> derived quantities and a usable flag per sample.

Input: a DataFrame with the canonical columns of SPEC §4 (degC, bar(g), m3/h, kW, 0/1), one row per
one-minute sample. Output: a DataFrame on the same index with the derived columns (units in the
names) plus ``usable`` (bool) and ``reason`` (empty when usable; otherwise the first reason found,
e.g. ``off``, ``cip``, ``ramping``, ``missing: T_sink_in``, ``out_of_range: V_sink=512``).
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .analysis.compressors import eta_is_arrays
from .components import evaporator_UA
from .columns import REQUIRED  # the one list of SPEC §4's required names (re-exported here)
from .fluid import PropertyError, get_fluid
from .proptable import get_tables
from .params import PlantParams
from .units import BAR, C_to_K

# Plausible ranges [canonical units] used when the caller passes none (the gateway passes the
# tag map's ranges). A value outside is marked bad, never clamped.
DEFAULT_RANGES = {
    "T_sink_in": (0, 90), "T_sink_out": (0, 100), "T_source_in": (0, 50), "T_source_out": (-5, 50),
    "V_sink": (0, 200), "V_source": (0, 400), "p_source_in": (0, 10), "p_source_out": (0, 10),
    "T_suc_LS": (-40, 60), "T_dis_LS": (-20, 200), "T_suc_HS": (-20, 100), "T_dis_HS": (0, 220),
    "p_suc_LS": (-0.9, 25), "p_dis_LS": (0, 40), "p_suc_HS": (0, 40), "p_dis_HS": (0, 60),
    "T_c": (0, 110), "T_e": (-40, 40), "W_LS": (0, 1500), "W_HS": (0, 1500), "p_m_sp": (0, 40),
}

MIN_POWER_KW = 20.0          # below this total compressor power the heat pump counts as off
RAMP_REL_PER_MIN = 0.10      # |dW_total| / W_total per minute above this: ramping
SETTLE_MIN = 10              # minutes after a start (or a CIP) that count as ramping


def _range_reasons(df: pd.DataFrame, ranges: dict) -> pd.Series:
    reason = pd.Series("", index=df.index, dtype=object)
    for col in REQUIRED:
        if col not in df.columns:
            reason[:] = np.where(reason == "", f"missing: {col}", reason)
            continue
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(dtype=float)
        bad_nan = ~np.isfinite(v)
        reason[:] = np.where((reason == "") & bad_nan, f"missing: {col}", reason)
        lo, hi = ranges.get(col, (-np.inf, np.inf))
        with np.errstate(invalid="ignore"):
            out = np.isfinite(v) & ((v < lo) | (v > hi))
        if out.any():
            txt = np.array([f"out_of_range: {col}={x:.6g}" for x in np.where(out, v, 0.0)], dtype=object)
            reason[:] = np.where((reason == "") & out, txt, reason)
    return reason


def derived(df: pd.DataFrame, params: PlantParams) -> pd.DataFrame:
    """The derived quantities of SPEC §4 per sample (no usability judgement), on ``df``'s index.

    Columns: p_e_bar, p_m_bar, p_c_bar [bar absolute], dp_source_bar [bar], Q_sink_kW,
    Q_source_kW, W_total_kW [kW], COP [-], T_e_sat_C [degC, saturation at p_e], superheat_K [K],
    pi_LS, pi_HS [-], eta_is_LS_meas, eta_is_HS_meas [-], UA_eva_kW_K [kW/K],
    R_th_f_K_per_kW [K/kW] (point estimate against the clean evaporator with the current CF_eva),
    heat_balance_pct [%] (Q_sink - Q_source - W_total relative to Q_sink: ~0 for adiabatic
    compressors with drive factor 1; a flow meter drifting shows here).
    """
    out, _ = _derived(df, params)
    return out


def _derived(df: pd.DataFrame, params: PlantParams):
    n = len(df)
    amb = params.ambient_pressure / BAR
    num = {c: pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=float) if c in df.columns
           else np.full(n, np.nan) for c in REQUIRED + ("W_LS", "W_HS")}
    out = pd.DataFrame(index=df.index)
    out["p_e_bar"] = num["p_suc_LS"] + amb
    # the intermediate pressure is measured twice (LS discharge, HS suction): average them
    out["p_m_bar"] = 0.5 * (num["p_dis_LS"] + num["p_suc_HS"]) + amb
    out["p_c_bar"] = num["p_dis_HS"] + amb
    out["dp_source_bar"] = num["p_source_in"] - num["p_source_out"]
    rc = params.cp_w * params.rho_w / 3600.0 / 1e3      # kW per (m3/h * K)
    out["Q_sink_kW"] = rc * num["V_sink"] * (num["T_sink_out"] - num["T_sink_in"])
    out["Q_source_kW"] = rc * num["V_source"] * (num["T_source_in"] - num["T_source_out"])
    W = num["W_LS"] + num["W_HS"]
    out["W_total_kW"] = W
    with np.errstate(divide="ignore", invalid="ignore"):
        out["COP"] = np.where(W > 0, out["Q_sink_kW"].to_numpy() / W, np.nan)
        out["pi_LS"] = out["p_m_bar"] / out["p_e_bar"]
        out["pi_HS"] = out["p_c_bar"] / out["p_m_bar"]
        out["heat_balance_pct"] = 100.0 * (out["Q_sink_kW"] - out["Q_source_kW"] - W) / out["Q_sink_kW"]

    fl = get_fluid(params.fluid, params.backend)
    tab = get_tables(params.fluid)
    p_e = out["p_e_bar"].to_numpy() * BAR
    p_m = out["p_m_bar"].to_numpy() * BAR
    p_c = out["p_c_bar"].to_numpy() * BAR
    C_src = params.cp_w * params.rho_w * num["V_source"] / 3600.0
    # vectorised property tables (model.proptable); HEOS row by row where they cannot answer
    has_e = np.isfinite(p_e) & (p_e > 0) & (p_e < fl.p_crit)
    T_e_sat = np.where(has_e, tab.T_sat(p_e), np.nan)
    prop_fail = np.zeros(n, dtype=bool)
    for i in np.flatnonzero(has_e & ~np.isfinite(T_e_sat)):
        try:
            T_e_sat[i] = fl.sat_p(p_e[i]).T
        except PropertyError:
            prop_fail[i] = True
    eta_LS, fail_LS = eta_is_arrays(tab, fl, p_e, C_to_K(num["T_suc_LS"]), p_m, C_to_K(num["T_dis_LS"]))
    eta_HS, fail_HS = eta_is_arrays(tab, fl, p_m, C_to_K(num["T_suc_HS"]), p_c, C_to_K(num["T_dis_HS"]))
    # as the sample-by-sample evaluation did: a failure leaves the later quantities of the row unset
    eta_LS[prop_fail] = np.nan
    eta_HS[prop_fail | fail_LS] = np.nan
    prop_fail |= fail_LS | fail_HS
    out["T_e_sat_C"] = T_e_sat - 273.15
    out["superheat_K"] = num["T_suc_LS"] - out["T_e_sat_C"]
    out["eta_is_LS_meas"] = eta_LS
    out["eta_is_HS_meas"] = eta_HS
    # invert the evaporator on the measured evaporating temperature (model.components)
    UA = evaporator_UA(C_to_K(num["T_source_in"]), C_to_K(num["T_source_out"]), T_e_sat, C_src)
    out["UA_eva_kW_K"] = UA / 1e3
    with np.errstate(divide="ignore", invalid="ignore"):
        out["R_th_f_K_per_kW"] = (1.0 / UA - 1.0 / params.UA_eva_clean) * 1e3
    return out, {"num": num, "W": W, "T_e_sat": T_e_sat, "prop_fail": prop_fail}


def process(df: pd.DataFrame, params: PlantParams, ranges: dict | None = None) -> pd.DataFrame:
    """Derived quantities of SPEC §4 for each one-minute sample (``derived``) plus ``usable``
    [bool] and ``reason`` [str]."""
    ranges = {**DEFAULT_RANGES, **(ranges or {})}
    n = len(df)
    out, aux = _derived(df, params)
    num, W, T_e_sat, prop_fail = aux["num"], aux["W"], aux["T_e_sat"], aux["prop_fail"]

    # ---- usability ---------------------------------------------------------------------------
    reason = _range_reasons(df, ranges)
    running = (pd.to_numeric(df["running"], errors="coerce").to_numpy(dtype=float)
               if "running" in df.columns else (np.nan_to_num(W) > MIN_POWER_KW).astype(float))
    cip = (pd.to_numeric(df["cip"], errors="coerce").to_numpy(dtype=float)
           if "cip" in df.columns else np.zeros(n))
    on = (running > 0.5) & (np.nan_to_num(W) > MIN_POWER_KW)
    # ramping: the first SETTLE_MIN samples after a start, and fast power changes
    # (minutes counted from a start; a record that begins running counts as settled): a sample is
    # ramping unless the run of running-without-CIP samples it ends is longer than SETTLE_MIN
    run = on & (cip < 0.5)
    idx = np.arange(n)
    last_stop = np.maximum.accumulate(np.where(run, -1, idx)) if n else idx
    ramp = ~run | ((last_stop >= 0) & (idx - last_stop <= SETTLE_MIN))
    with np.errstate(divide="ignore", invalid="ignore"):
        dW = np.abs(np.diff(W, prepend=np.nan)) / W
    ramp |= np.nan_to_num(dW, nan=0.0) > RAMP_REL_PER_MIN
    physical = np.full(n, "", dtype=object)
    physical[~(num["T_source_in"] > num["T_source_out"])] = "inconsistent: source not cooled"
    physical[np.isfinite(T_e_sat) & ~(num["T_source_out"] > T_e_sat - 273.15)] = \
        "inconsistent: T_source_out not above evaporating temperature"
    physical[~(num["T_sink_out"] > num["T_sink_in"])] = "inconsistent: sink not heated"
    physical[prop_fail] = "inconsistent: refrigerant state outside property range"
    # the first reason that applies, in this order
    why = reason.to_numpy(dtype=object)
    final = np.full(n, "", dtype=object)
    for cond, val in reversed(((cip > 0.5, "cip"), (~on, "off"), (why != "", why),
                               (physical != "", physical), (ramp, "ramping"))):
        final = np.where(cond, val, final)
    if "quality" in df.columns:   # upstream marks (gateway: stale, frozen, comm fault)
        q = df["quality"].fillna("").astype(str).to_numpy()
        final = np.where((final == "") & (q != ""), q, final)
    out["usable"] = final == ""
    out["reason"] = final
    return out


def usable_counts(processed: pd.DataFrame) -> dict[str, int]:
    """How many samples are unusable per reason (reason text up to the first ':' / '=')."""
    r = processed.loc[~processed["usable"], "reason"].astype(str)
    keys = r.str.replace(r"=.*$", "", regex=True)
    return {str(k): int(v) for k, v in keys.value_counts().items()}
