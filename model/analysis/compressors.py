"""Compressor curves learned from the plant's own operating data (SPEC §9, issue #8 item 2).

The optimum p_m,sp depends on the compressors' isentropic and volumetric efficiencies more than on
anything else, and a plant's curves are not the data sheet's. The plant measures what is needed to
learn them, every minute:

- eta_is per stage from suction and discharge (p, T) (adiabatic compressors, as in the model);
- m_LS from the evaporator duty, Q_source / (h_suc,LS - h_f(p_m));
- m_HS from the open intercooler, m_LS (h_dis,LS - h_f(p_m)) / (h_g(p_m) - h_SC,out), where T_c is
  the liquid after the subcooler (so h_SC,out is measured); where T_c is the saturated condensate the
  SC outlet is not measured and modelling it would lean on CF_SC, which the initial calibration
  cannot separate from CF_con (one SC-factor error of 2x moved m_HS by 3 %): m_HS then comes from
  the HS power, W_HS / (d * (h_dis - h_suc)), with the LS stage's measured drive factor d (same
  kind of motor and drive). Which of the two a plant has is told from T_sat(p_c) - T_c, or set;
- eta_vol = m / (rho_suc * V_s * N/N_nom) where the speeds are measured (optional tags);
- the drive and heat-loss factor W_el / (m * (h_dis - h_suc)) per stage, used for the power
  prediction; with T_c at the subcooler outlet the HS factor is measured too (cross-check of the
  intercooler balance against the HS power).

Each curve is fitted on plant.yaml's polynomial form (``model.params.POLY_BASIS`` in pi and
n = N/N_nom) by weighted least squares on sufficient statistics that forget old data exponentially
(``half_life_days``: wear shows, and the state stays small), regularised toward the configured curve
(the manufacturer's prior) by pseudo-observations of the prior spread over the whole operating range
with a total weight of ``prior_weight`` samples: where the data is thick it wins, where it is thin the
prior holds the curve. The (pi, n) region the data covers is kept as a decaying 2-D histogram; the
optimizer may extrapolate only ``margin_pi``/``margin_n`` beyond the hull of its covered bins.
Coefficient covariances (residual variance, inflated for the residuals' serial correlation) give the
advice its uncertainty.

Units: SI inside (Pa, K, J/kg, kg/s, W); observation frames carry names with units.
"""
from __future__ import annotations

import copy
import math
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace

import numpy as np
import pandas as pd

from ..batch import floats
from ..fluid import Fluid, PropertyError, get_fluid
from ..proptable import get_tables
from ..params import POLY_BASIS, Compressor, PlantParams
from ..units import BAR, C_to_K, m3h_to_m3s
from . import speedkernel

STAGES = ("LS", "HS")
CURVES = ("eta_is", "eta_vol")
T_C_LOCATIONS = ("auto", "condenser_outlet", "subcooler_outlet")
DAY_S = 86400.0
_Z = (2.5, 1.0, 1.0, 0.3)        # internal scaling: z_pi = (pi - 2.5)/1.0, z_n = (n - 1)/0.3
SPEED_STEP_TOL = 1e-9          # the learned curves' speed search ends with a Newton step below this: the
                               # error after it is ~ the step squared (a further step would be < 1e-17)


class LearningError(ValueError):
    """Settings or a state document are invalid; the message names the key."""


@dataclass(frozen=True)
class LearningSettings:
    """plant.yaml ``compressor_learning`` (every key optional; these are the defaults)."""
    enabled: bool = True
    half_life_days: float = 60.0      # weight of a sample halves every this many days of plant time
    prior_weight: float = 240.0       # the prior curve counts as this many samples over its grid
    min_samples: float = 120.0        # effective samples a curve needs before it replaces the prior
    bin_pi: float = 0.05              # coverage histogram bin widths
    bin_n: float = 0.04
    min_bin_weight: float = 5.0       # effective samples that make a bin "covered"
    margin_pi: float = 0.10           # extrapolation allowed beyond the covered hull
    margin_n: float = 0.06
    T_c_location: str = "auto"        # auto | condenser_outlet | subcooler_outlet
    subcooling_threshold_K: float = 1.5   # auto: T_sat(p_c) - T_c above this -> subcooler outlet
    eta_range: tuple = (0.3, 1.0)     # observations outside are sensor trouble, not compressor data
    local: bool = True                # locally weighted curves where the data is (see LocalCurves)
    local_bandwidth_bins: float = 2.0 # kernel width of the local fits, in bins
    local_prior_weight: float = 20.0  # samples pulling a local fit toward the global one
    prior_sd: float = 0.03            # how far [-] a plant's curve may lie from the data sheet's:
                                      # the uncertainty of the learned curves away from the data
    extrapolation_sd: float = 0.002   # the learned curve's error [-] one margin beyond the data (a
                                      # curvature the data have not shown), growing with the square
                                      # of the distance (see CompressorLearner.shape_sd)

    @classmethod
    def from_dict(cls, d: dict | None) -> "LearningSettings":
        d = dict(d or {})
        known = {f.name: f for f in fields(cls)}
        kw = {}
        for k, v in d.items():
            if k not in known:
                raise LearningError(f"key 'compressor_learning.{k}': unknown (known: "
                                    f"{', '.join(known)})")
            default = known[k].default
            if isinstance(default, bool):
                if not isinstance(v, bool):
                    raise LearningError(f"key 'compressor_learning.{k}': expected true/false, got {v!r}")
            elif isinstance(default, str):
                if v not in T_C_LOCATIONS:
                    raise LearningError(f"key 'compressor_learning.{k}': {v!r} is not one of "
                                        f"{', '.join(T_C_LOCATIONS)}")
            elif isinstance(default, tuple):
                if not (isinstance(v, (list, tuple)) and len(v) == 2 and v[0] < v[1]):
                    raise LearningError(f"key 'compressor_learning.{k}': expected [low, high]")
                v = (float(v[0]), float(v[1]))
            else:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                    raise LearningError(f"key 'compressor_learning.{k}': expected a number > 0, "
                                        f"got {v!r}")
                v = float(v)
            kw[k] = v
        return cls(**kw)


# --------------------------------------------------------------------------------------------------
# observations
# --------------------------------------------------------------------------------------------------
OBS_COLUMNS = ("t", "pi_LS", "n_LS", "eta_is_LS", "eta_vol_LS", "drive_LS", "m_LS_kg_s",
               "pi_HS", "n_HS", "eta_is_HS", "eta_vol_HS", "drive_HS", "m_HS_kg_s", "m_HS_W_kg_s",
               "subcooling_meas_K")


def stage_states(fl: Fluid, p_suc: float, T_suc: float, p_dis: float, T_dis: float,
                 warm: dict | None = None, key: str = ""):
    """(h_suc, rho_suc, h_dis, h_is) [J/kg, kg/m^3] of a compressor from measured suction and
    discharge (p [Pa], T [K]); a suction reading at or below saturation (sensor noise) is taken as
    saturated vapour. Raises PropertyError; returns None where the discharge is not superheated.
    ``warm`` (a dict the caller keeps between rows) warm-starts the isentropic state per ``key``."""
    sat = fl.sat_p(p_suc)
    if T_suc <= sat.T + 0.05:
        h_suc, s_suc, rho_suc = sat.h_g, sat.s_g, sat.rho_g
    else:
        h_suc, s_suc, rho_suc = fl.vapour_pT(p_suc, T_suc)
    if not (p_dis > p_suc and T_dis > fl.sat_p(p_dis).T + 0.5):
        return None
    h_dis, _, _ = fl.vapour_pT(p_dis, T_dis)
    g = warm.get(key) if warm is not None else None
    h_is, T_is, rho_is = fl.isentropic(p_dis, s_suc, g)
    if warm is not None and math.isfinite(rho_is):
        warm[key] = (rho_is, T_is)
    return h_suc, rho_suc, h_dis, h_is


def eta_is_measured(fl: Fluid, p_suc: float, T_suc: float, p_dis: float, T_dis: float,
                    warm: dict | None = None, key: str = "") -> float:
    """Measured isentropic efficiency (h_is - h_suc) / (h_dis - h_suc) [-]; NaN when undefined."""
    if not all(math.isfinite(x) for x in (p_suc, T_suc, p_dis, T_dis)) or p_dis <= p_suc:
        return math.nan
    st = stage_states(fl, p_suc, T_suc, p_dis, T_dis, warm, key)
    if st is None or st[2] - st[0] <= 0:
        return math.nan
    return (st[3] - st[0]) / (st[2] - st[0])


_shared = threading.local()


@contextmanager
def shared_stages():
    """Within it, ``stage_arrays`` answers a call with the same inputs as an earlier one in this
    thread from that call (a window's pass 1 asks for both stages twice: the measured side's
    eta_is and the compressor observations). The arrays returned are shared: read them only."""
    prev = getattr(_shared, "memo", None)
    _shared.memo = {}
    try:
        yield
    finally:
        _shared.memo = prev


def stage_arrays(tab, p_suc, T_suc, p_dis, T_dis) -> dict:
    """``stage_states`` for arrays from the property tables (``model.proptable``): h_suc, s_suc,
    rho_suc, h_dis, h_is [J/kg, J/kg/K, kg/m^3], ``sup`` (the discharge is superheated: p_dis >
    p_suc and T_dis > T_sat(p_dis) + 0.5 K; elsewhere stage_states returns None) and ``handled``
    (the tables answered; other rows need the scalar ``stage_states``)."""
    memo = getattr(_shared, "memo", None)
    if memo is None:
        return _stage_arrays(tab, p_suc, T_suc, p_dis, T_dis)
    ins = tuple(np.asarray(a, dtype=float) for a in (p_suc, T_suc, p_dis, T_dis))
    key = (id(tab),) + tuple(a.tobytes() for a in ins)
    if key not in memo:
        memo[key] = (tab, _stage_arrays(tab, p_suc, T_suc, p_dis, T_dis))   # tab kept: its id stays its own
        rec = getattr(_shared, "record", None)
        if rec is not None:         # copies: the caller's arrays are its own
            rec.append((tab, tuple(a.copy() for a in ins), memo[key][1]))
    return memo[key][1]


@contextmanager
def recorded_stages():
    """``shared_stages`` that also yields a list of every call's (tab, inputs, arrays): the stage
    states of many windows' rows computed at once, handed to each window by ``preset_stages``."""
    prev = getattr(_shared, "record", None)
    with shared_stages():
        _shared.record = rec = []
        try:
            yield rec
        finally:
            _shared.record = prev


def preset_stages(records: list, rows) -> None:
    """Within ``shared_stages``: a later ``stage_arrays`` call whose inputs are the rows ``rows`` (an
    index or slice) of a recorded call (``recorded_stages``) is answered with those rows of its
    arrays. Every array of ``_stage_arrays`` is row by row (property tables, no reduction over
    rows), so the answer is the one the call would compute."""
    memo = _shared.memo
    for tab, ins, arrays in records:
        part = tuple(a[rows] for a in ins)
        key = (id(tab),) + tuple(a.tobytes() for a in part)
        if key not in memo:
            memo[key] = (tab, {k: v[rows] for k, v in arrays.items()})


def _stage_arrays(tab, p_suc, T_suc, p_dis, T_dis) -> dict:
    sat = tab.sat(p_suc)
    near = T_suc <= sat.T + 0.05
    h_v, s_v, r_v = tab.vapour(p_suc, T_suc)
    h_suc = np.where(near, sat.h_g, h_v)
    s_suc = np.where(near, sat.s_g, s_v)
    rho_suc = np.where(near, sat.rho_g, r_v)
    T_sat_d = tab.T_sat(p_dis)
    sup = (p_dis > p_suc) & (T_dis > T_sat_d + 0.5)
    h_dis = tab.vapour(p_dis, T_dis)[0]
    h_is = tab.isentropic(p_dis, s_suc)[0]
    handled = (np.isfinite(sat.T) & np.isfinite(T_suc) & np.isfinite(h_suc) & np.isfinite(T_sat_d)
               & np.isfinite(T_dis) & (~sup | (np.isfinite(h_dis) & np.isfinite(h_is))))
    return {"h_suc": h_suc, "s_suc": s_suc, "rho_suc": rho_suc, "h_dis": h_dis, "h_is": h_is,
            "sup": sup, "handled": handled}


def eta_is_arrays(tab, fl: Fluid, p_suc, T_suc, p_dis, T_dis) -> tuple[np.ndarray, np.ndarray]:
    """``eta_is_measured`` for arrays: (eta_is, property_failed) — the tables where they answer,
    ``eta_is_measured`` (HEOS) row by row elsewhere; property_failed marks rows where HEOS raised."""
    n = len(p_suc)
    eta = np.full(n, np.nan)
    failed = np.zeros(n, dtype=bool)
    fin = np.isfinite(p_suc) & np.isfinite(T_suc) & np.isfinite(p_dis) & np.isfinite(T_dis) & (p_dis > p_suc)
    st = stage_arrays(tab, p_suc, T_suc, p_dis, T_dis)
    use = fin & st["handled"]
    with np.errstate(invalid="ignore", divide="ignore"):
        dh = st["h_dis"] - st["h_suc"]
        e = np.where(st["sup"] & (dh > 0), (st["h_is"] - st["h_suc"]) / dh, np.nan)
    eta[use] = e[use]
    warm: dict = {}
    for i in np.flatnonzero(fin & ~st["handled"]):
        try:
            eta[i] = eta_is_measured(fl, p_suc[i], T_suc[i], p_dis[i], T_dis[i], warm, "x")
        except PropertyError:
            failed[i] = True
    return eta, failed


def _observe_row(fl: Fluid, p_e, p_m, p_c, T1, T2, T3, T4, Tc, sc_rows: bool, warm: dict):
    """One sample's states by HEOS (where the tables cannot answer): (h1, rho1, h2, h2s, h3, rho3,
    h4, h4s, h_f(p_m), h_g(p_m), m_HS / m_LS from the intercooler balance (NaN unless T_c is the
    subcooler outlet)), or None where undefined."""
    try:
        st_ls = stage_states(fl, p_e, T1, p_m, T2, warm, "LS")
        st_hs = stage_states(fl, p_m, T3, p_c, T4, warm, "HS")
        if st_ls is None or st_hs is None:
            return None
        h1, rho1, h2, h2s = st_ls
        h3, rho3, h4, h4s = st_hs
        sat_m = fl.sat_p(p_m)
        m_hs = math.nan
        if sc_rows and math.isfinite(Tc):
            sat_c = fl.sat_p(p_c)
            h_sc = fl.liquid_pT(p_c, Tc) if Tc < sat_c.T - 0.05 else sat_c.h_f
            m_hs = (h2 - sat_m.h_f) / (sat_m.h_g - h_sc)      # per kg/s of m_LS
        if not h1 - sat_m.h_f != 0.0:
            return None
    except (PropertyError, ZeroDivisionError, ArithmeticError):
        return None
    return h1, rho1, h2, h2s, h3, rho3, h4, h4s, sat_m.h_f, sat_m.h_g, m_hs


def epoch_seconds(ts) -> np.ndarray:
    """Epoch seconds (float) of timestamps: a Series or DatetimeIndex of datetimes (naive = UTC) or
    anything ``pd.to_datetime`` reads. Whatever the datetime64 unit pandas chose: pandas 3 keeps
    microseconds for most inputs (ISO text without sub-microsecond digits, epoch numbers), and
    before stop 46 the integer count was divided by 1e9 as if it were nanoseconds, so that
    ``observe``'s ``t`` was epoch seconds / 1000 and the learner's forgetting
    (``half_life_days``) ran 1000 times too slowly."""
    dtype = getattr(ts, "dtype", None)
    if not (isinstance(dtype, pd.DatetimeTZDtype) or pd.api.types.is_datetime64_dtype(dtype)):
        ts = pd.to_datetime(ts, utc=True)       # (text with offsets, epoch numbers, objects)
    idx = pd.DatetimeIndex(ts)
    if idx.tz is None:
        idx = idx.tz_localize("UTC")
    return idx.as_unit("ns").asi8 / 1e9


def observe(data: pd.DataFrame, params: PlantParams, settings: LearningSettings | None = None,
            T_c_location: str | None = None) -> pd.DataFrame:
    """Per sample of ``data`` (canonical columns of SPEC §4, degC, bar(g), m3/h, kW, rpm; only usable
    samples should be passed): the compressor observations OBS_COLUMNS (NaN where undefined).

    ``t`` is the sample time [epoch s] from a ``timestamp`` column or a DatetimeIndex (NaN without).
    T_c_location: 'condenser_outlet' or 'subcooler_outlet' (default: the settings', 'auto' decided
    per call from the median measured subcooling)."""
    s = settings or LearningSettings()
    fl = get_fluid(params.fluid, params.backend)
    amb = params.ambient_pressure / BAR
    n = len(data)

    def col(name):
        if name not in data.columns:
            return np.full(n, np.nan)
        return floats(data[name])

    p_e = (col("p_suc_LS") + amb) * BAR
    p_m = (0.5 * (col("p_dis_LS") + col("p_suc_HS")) + amb) * BAR
    p_c = (col("p_dis_HS") + amb) * BAR
    T1, T2, T3, T4, Tc = (C_to_K(col(c)) for c in ("T_suc_LS", "T_dis_LS", "T_suc_HS", "T_dis_HS", "T_c"))
    rc = params.cp_w * params.rho_w
    Q_src = rc * m3h_to_m3s(col("V_source")) * (col("T_source_in") - col("T_source_out"))
    W_LS, W_HS = col("W_LS") * 1e3, col("W_HS") * 1e3
    N_LS, N_HS = col("N_LS"), col("N_HS")
    ls, hs = params.comp_LS, params.comp_HS
    out = {c: np.full(n, np.nan) for c in OBS_COLUMNS}
    if "timestamp" in data.columns:
        out["t"] = epoch_seconds(data["timestamp"])
    elif isinstance(data.index, pd.DatetimeIndex):
        out["t"] = epoch_seconds(data.index)
    tab = get_tables(params.fluid)
    # measured subcooling T_sat(p_c) - T_c (the tables; HEOS for pressures outside them)
    sub = np.full(n, np.nan)
    has = np.isfinite(p_c) & np.isfinite(Tc) & (p_c > 0) & (p_c < fl.p_crit)
    T_sat_c = tab.T_sat(p_c)
    sub[has] = T_sat_c[has] - Tc[has]
    for i in np.flatnonzero(has & ~np.isfinite(T_sat_c)):
        try:
            sub[i] = fl.sat_p(p_c[i]).T - Tc[i]
        except PropertyError:
            pass
    out["subcooling_meas_K"] = sub
    loc = T_c_location or s.T_c_location
    if loc == "auto":
        loc = decide_T_c_location(sub, s)
    lo, hi = s.eta_range
    # per-sample states of both stages: the tables for whole arrays, HEOS row by row where they
    # cannot answer (out of their range)
    valid = (np.isfinite(p_e) & np.isfinite(p_m) & np.isfinite(p_c) & np.isfinite(T1) & np.isfinite(T2)
             & np.isfinite(T3) & np.isfinite(T4) & np.isfinite(Q_src)
             & (0 < p_e) & (p_e < p_m) & (p_m < p_c) & (p_c < fl.p_crit))
    st_ls = stage_arrays(tab, p_e, T1, p_m, T2)
    st_hs = stage_arrays(tab, p_m, T3, p_c, T4)
    sat_m = tab.sat(p_m)
    sc_rows = loc == "subcooler_outlet"
    handled = st_ls["handled"] & st_hs["handled"] & np.isfinite(sat_m.h_f)
    if sc_rows:
        sat_c = tab.sat(p_c)
        handled &= ~np.isfinite(Tc) | np.isfinite(sat_c.h_f)
    cols = ("h1", "rho1", "h2", "h2s", "h3", "rho3", "h4", "h4s", "h_f_m", "h_g_m", "m_HS")
    S = {c: np.full(n, np.nan) for c in cols}
    ok = valid & handled & st_ls["sup"] & st_hs["sup"]
    S["h1"], S["rho1"], S["h2"], S["h2s"] = st_ls["h_suc"], st_ls["rho_suc"], st_ls["h_dis"], st_ls["h_is"]
    S["h3"], S["rho3"], S["h4"], S["h4s"] = st_hs["h_suc"], st_hs["rho_suc"], st_hs["h_dis"], st_hs["h_is"]
    S["h_f_m"], S["h_g_m"] = sat_m.h_f, sat_m.h_g
    with np.errstate(invalid="ignore", divide="ignore"):
        m_ls_all = Q_src / (S["h1"] - S["h_f_m"])
    if sc_rows:
        # the liquid entering the HS valve is measured: the intercooler balance is exact
        h_sc = np.where(np.isfinite(Tc), sat_c.h_f, np.nan)
        for i in np.flatnonzero(ok & np.isfinite(Tc) & (Tc < sat_c.T - 0.05)):
            try:
                h_sc[i] = fl.liquid_pT(p_c[i], Tc[i])
            except PropertyError:
                ok[i] = False
        with np.errstate(invalid="ignore", divide="ignore"):
            S["m_HS"] = m_ls_all * (S["h2"] - S["h_f_m"]) / (S["h_g_m"] - h_sc)
    ok &= np.isfinite(m_ls_all)
    if sc_rows:
        ok &= ~np.isfinite(Tc) | np.isfinite(S["m_HS"])
    for c in cols:
        S[c] = np.where(ok, S[c], np.nan)
    warm: dict = {}
    for i in np.flatnonzero(valid & ~handled):
        row = _observe_row(fl, p_e[i], p_m[i], p_c[i], T1[i], T2[i], T3[i], T4[i], Tc[i], sc_rows, warm)
        if row is not None:
            ok[i] = True
            for c, v in zip(cols[:-1], row[:-1]):
                S[c][i] = v
            S["m_HS"][i] = Q_src[i] / (row[0] - row[8]) * row[10]
    h1, rho1, h2, h2s, h3, rho3, h4, h4s = (S[c] for c in cols[:8])
    with np.errstate(invalid="ignore", divide="ignore"):
        m_ls = np.where(ok, Q_src / (h1 - S["h_f_m"]), np.nan)
        eta_ls = np.where(h2 > h1, (h2s - h1) / (h2 - h1), np.nan)
        eta_hs = np.where(h4 > h3, (h4s - h3) / (h4 - h3), np.nan)
    out["pi_LS"] = np.where(ok, p_m / p_e, np.nan)
    out["pi_HS"] = np.where(ok, p_c / p_m, np.nan)
    out["eta_is_LS"] = np.where(ok & (eta_ls >= lo) & (eta_ls <= hi), eta_ls, np.nan)
    out["eta_is_HS"] = np.where(ok & (eta_hs >= lo) & (eta_hs <= hi), eta_hs, np.nan)
    out["m_LS_kg_s"] = m_ls
    if sc_rows:
        out["m_HS_kg_s"] = np.where(ok, S["m_HS"], np.nan)
    dh_HS = np.where(ok, h4 - h3, np.nan)
    rho_suc = {"LS": np.where(ok, rho1, np.nan), "HS": np.where(ok, rho3, np.nan)}
    with np.errstate(invalid="ignore", divide="ignore"):
        out["drive_LS"] = np.where(ok & np.isfinite(W_LS) & (W_LS > 0), W_LS / (m_ls * (h2 - h1)), np.nan)
        out["m_HS_W_kg_s"] = np.where(ok & np.isfinite(W_HS) & (W_HS > 0), W_HS / dh_HS, np.nan)
    if loc != "subcooler_outlet":
        # T_c is the saturated condensate: the SC outlet is not measured, and modelling it would
        # lean on CF_SC, which the initial calibration cannot separate from CF_con. The HS flow
        # then comes from its electric power with the LS stage's drive factor (same kind of motor
        # and drive; the LS factor is measured: its mass flow comes from the evaporator duty)
        d = out["drive_LS"][np.isfinite(out["drive_LS"])]
        d_ls = float(np.median(d)) if len(d) else 1.0
        out["m_HS_kg_s"] = out["m_HS_W_kg_s"] / d_ls
    with np.errstate(invalid="ignore", divide="ignore"):
        out["drive_HS"] = W_HS / (out["m_HS_kg_s"] * dh_HS)
    for stage, comp, N in (("LS", ls, N_LS), ("HS", hs, N_HS)):
        m = out[f"m_{stage}_kg_s"]
        rho = rho_suc[stage]
        pi = out[f"pi_{stage}"]
        with np.errstate(invalid="ignore", divide="ignore"):
            nn = N / comp.N_nom
            ev = m / (rho * comp.swept_volume * nn)
        measured = np.isfinite(N) & (N > 0) & np.isfinite(m)
        out[f"eta_vol_{stage}"] = np.where(measured & (ev >= 0.3) & (ev <= 1.1), ev, np.nan)
        out[f"n_{stage}"] = np.where(measured, nn, np.nan)
        for i in np.flatnonzero(~measured & np.isfinite(m) & np.isfinite(rho) & np.isfinite(pi)):
            try:   # speed not measured: the speed the prior curve needs for this flow
                out[f"n_{stage}"][i] = comp.speed_for_flow(m[i], rho[i], pi[i])[0]
            except ValueError:
                pass
    return pd.DataFrame(out, index=data.index)


def decide_T_c_location(subcooling_K, settings: LearningSettings | None = None) -> str:
    """'subcooler_outlet' when the median measured subcooling T_sat(p_c) - T_c exceeds the threshold,
    else 'condenser_outlet' (the saturated condensate reads ~0 K, within its sensor's noise)."""
    s = settings or LearningSettings()
    v = np.asarray(subcooling_K, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return "condenser_outlet"
    return "subcooler_outlet" if float(np.median(v)) > s.subcooling_threshold_K else "condenser_outlet"


# --------------------------------------------------------------------------------------------------
# fitting on decaying sufficient statistics
# --------------------------------------------------------------------------------------------------
def _zbasis(pi, n) -> np.ndarray:
    """Scaled basis (1, z_pi, z_n, z_pi^2, z_pi z_n, z_n^2) as rows (k, 6)."""
    zp = (np.asarray(pi, dtype=float) - _Z[0]) / _Z[1]
    zn = (np.asarray(n, dtype=float) - _Z[2]) / _Z[3]
    return np.column_stack([np.ones_like(zp), zp, zn, zp * zp, zp * zn, zn * zn])


def _to_poly(a: np.ndarray) -> tuple[float, ...]:
    """Scaled-basis coefficients -> POLY_BASIS coefficients (1, pi, n, pi^2, pi*n, n^2)."""
    p0, sp, n0, sn = _Z
    a0, a1, a2, a3, a4, a5 = a
    # z_pi = (pi - p0)/sp, z_n = (n - n0)/sn ; expand
    c_pp = a3 / sp ** 2
    c_pn = a4 / (sp * sn)
    c_nn = a5 / sn ** 2
    c_p = a1 / sp - 2 * a3 * p0 / sp ** 2 - a4 * n0 / (sp * sn)
    c_n = a2 / sn - 2 * a5 * n0 / sn ** 2 - a4 * p0 / (sp * sn)
    c_1 = (a0 - a1 * p0 / sp - a2 * n0 / sn + a3 * p0 ** 2 / sp ** 2 + a4 * p0 * n0 / (sp * sn)
           + a5 * n0 ** 2 / sn ** 2)
    return (float(c_1), float(c_p), float(c_n), float(c_pp), float(c_pn), float(c_nn))


def _zvalue(a, pi: float, n: float) -> float:
    """Scaled-basis polynomial ``a`` at one point."""
    zp = (pi - _Z[0]) / _Z[1]
    zn = (n - _Z[2]) / _Z[3]
    return a[0] + a[1] * zp + a[2] * zn + a[3] * zp * zp + a[4] * zp * zn + a[5] * zn * zn


def _poly_matrix() -> np.ndarray:
    """Linear map M with poly = M @ a (so a covariance transforms as M C M^T)."""
    return np.array([_to_poly(e) for e in np.eye(6)]).T


@dataclass
class _Stats:
    """Decaying sufficient statistics of one curve: sum w x x^T, sum w x y, sum w y^2, sum w,
    and the lag-1 autocorrelation of the residuals (EW mean) for the covariance inflation."""
    A: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    b: np.ndarray = field(default_factory=lambda: np.zeros(6))
    yy: float = 0.0
    w: float = 0.0
    rho1: float = 0.0

    def decay(self, f: float) -> None:
        self.A *= f
        self.b *= f
        self.yy *= f
        self.w *= f

    def add(self, X: np.ndarray, y: np.ndarray) -> None:
        self.A += X.T @ X
        self.b += X.T @ y
        self.yy += float(y @ y)
        self.w += len(y)

    def to_dict(self) -> dict:
        return {"A": self.A.tolist(), "b": self.b.tolist(), "yy": self.yy, "w": self.w,
                "rho1": self.rho1}

    @classmethod
    def from_dict(cls, d: dict) -> "_Stats":
        return cls(np.array(d["A"], dtype=float).reshape(6, 6), np.array(d["b"], dtype=float),
                   float(d["yy"]), float(d["w"]), float(d.get("rho1", 0.0)))


@dataclass
class _Coverage:
    """Decaying 2-D histogram of (pi, n) with fixed bin widths: bin key -> weight."""
    bin_pi: float
    bin_n: float
    bins: dict = field(default_factory=dict)

    def decay(self, f: float) -> None:
        for k in list(self.bins):
            self.bins[k] *= f
            if self.bins[k] < 1e-3:
                del self.bins[k]

    def add(self, pi: np.ndarray, n: np.ndarray) -> None:
        ip = np.floor(pi / self.bin_pi).astype(int)
        jn = np.floor(n / self.bin_n).astype(int)
        for a, b in zip(ip.tolist(), jn.tolist()):
            self.bins[(a, b)] = self.bins.get((a, b), 0.0) + 1.0

    def centers(self, min_weight: float) -> np.ndarray:
        pts = [((a + 0.5) * self.bin_pi, (b + 0.5) * self.bin_n)
               for (a, b), w in self.bins.items() if w >= min_weight]
        return np.array(pts, dtype=float).reshape(-1, 2)

    def to_dict(self) -> dict:
        return {"bin_pi": self.bin_pi, "bin_n": self.bin_n,
                "bins": [[a, b, w] for (a, b), w in sorted(self.bins.items())]}

    @classmethod
    def from_dict(cls, d: dict) -> "_Coverage":
        return cls(float(d["bin_pi"]), float(d["bin_n"]),
                   {(int(a), int(b)): float(w) for a, b, w in d["bins"]})


class _BinStats:
    """Decaying sufficient statistics of one curve per coverage bin (for the local fits). The
    bins' (6, 6) and (6,) statistics are rows of two stacked arrays (in the order the bins were
    first seen; ``A`` and ``b`` give them per bin), so that a decay is one multiplication of the
    used rows: element by element the numbers of multiplying each bin's arrays (a year's replay
    has hundreds of bins, two numpy calls each per window before)."""

    def __init__(self, bin_pi: float, bin_n: float) -> None:
        self.bin_pi, self.bin_n = bin_pi, bin_n
        self._index: dict = {}                  # bin -> row of _A and _b
        self._A = np.zeros((0, 6, 6))
        self._b = np.zeros((0, 6))

    def _row(self, key) -> int:
        """The row of bin ``key`` (a new one of zeros the first time)."""
        i = self._index.get(key)
        if i is None:
            i = len(self._index)
            if i == len(self._A):               # room for more bins: doubled
                cap = max(16, 2 * len(self._A))
                A, b = np.zeros((cap, 6, 6)), np.zeros((cap, 6))
                A[:i], b[:i] = self._A[:i], self._b[:i]
                self._A, self._b = A, b
            self._index[key] = i
        return i

    @property
    def A(self) -> dict:
        """bin -> its (6, 6) statistic (a view of its row)."""
        return {k: self._A[i] for k, i in self._index.items()}

    @property
    def b(self) -> dict:
        """bin -> its (6,) statistic (a view of its row)."""
        return {k: self._b[i] for k, i in self._index.items()}

    def copy(self) -> "_BinStats":
        """An independent copy (of the used rows only: a window's snapshot of the learner)."""
        out = _BinStats(self.bin_pi, self.bin_n)
        n = len(self._index)
        out._index = dict(self._index)
        out._A, out._b = self._A[:n].copy(), self._b[:n].copy()
        return out

    def decay(self, f: float) -> None:
        n = len(self._index)
        self._A[:n] *= f
        self._b[:n] *= f

    def add(self, pi: np.ndarray, n: np.ndarray, X: np.ndarray, y: np.ndarray) -> None:
        ip = np.floor(pi / self.bin_pi).astype(int)
        jn = np.floor(n / self.bin_n).astype(int)
        keys = list(zip(ip.tolist(), jn.tolist()))
        rows: dict = {}             # bin -> its samples' positions, ascending (a mask's rows)
        for pos, key in enumerate(keys):
            rows.setdefault(key, []).append(pos)
        for key in set(keys):
            m = np.array(rows[key])
            Xm, ym = X[m], y[m]
            i = self._row(key)
            self._A[i] += Xm.T @ Xm
            self._b[i] += Xm.T @ ym

    def arrays(self):
        keys = sorted(self._index)
        if not keys:
            return np.zeros((0, 2)), np.zeros((0, 6, 6)), np.zeros((0, 6))
        rows = [self._index[k] for k in keys]
        c = np.array([((a + 0.5) * self.bin_pi, (b + 0.5) * self.bin_n) for a, b in keys])
        return c, self._A[rows], self._b[rows]

    def to_dict(self) -> dict:
        iu = np.triu_indices(6)
        return {"bins": [[a, b, self._A[i][iu].tolist(), self._b[i].tolist()]
                         for (a, b), i in sorted(self._index.items())]}

    @classmethod
    def from_dict(cls, d: dict, bin_pi: float, bin_n: float) -> "_BinStats":
        out = cls(bin_pi, bin_n)
        iu = np.triu_indices(6)
        for a, b, tri, vec in d.get("bins", []):
            A = np.zeros((6, 6))
            A[iu] = tri
            A = A + A.T - np.diag(np.diag(A))
            i = out._row((int(a), int(b)))
            out._A[i] = A
            out._b[i] = np.array(vec, dtype=float)
        return out


def _sq_norm(q: np.ndarray, c: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Per point of q (k, 2) and centre of c (m, 2): the squared norm of their difference scaled
    by h, (k, m). Coordinate by coordinate: the same numbers as summing a (k, m, 2) array over its
    last axis (two terms), without numpy's slow reduction over an axis of length two."""
    z0 = (q[:, 0, None] - c[None, :, 0]) / h[0]
    z1 = (q[:, 1, None] - c[None, :, 1]) / h[1]
    return z0 ** 2 + z1 ** 2


def _rect_distance(q: np.ndarray, c: np.ndarray, half: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Per point of q (k, 2) and rectangle (centre c (m, 2), half widths ``half``): the distance
    to the rectangle, each coordinate scaled by ``scale``, (k, m) (0 inside)."""
    g0 = np.maximum(np.abs(q[:, 0, None] - c[None, :, 0]) - half[0], 0.0) / scale[0]
    g1 = np.maximum(np.abs(q[:, 1, None] - c[None, :, 1]) - half[1], 0.0) / scale[1]
    return np.sqrt(g0 ** 2 + g1 ** 2)


_NODE_WEIGHTS: dict = {}       # _node_weights' recent answers (a learner's coverage changes seldom)
_NODE_WEIGHTS_MAX = 8
_NODE_WEIGHTS_LOCK = threading.Lock()   # (a cluster's worker may run several replays in threads)


def _node_weights(nodes: np.ndarray, cov: np.ndarray, centres: np.ndarray, h: np.ndarray,
                  scale: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``LocalCurves``' grid weights: per node whether the data reach it (within 1.5 margins
    ``scale`` of a covered bin's rectangle: centre ``cov``, half widths ``half``; other nodes fall
    back to the global fit), and the Gaussian kernel weights (nodes x bin centres ``centres``,
    bandwidths ``h``; below 1e-4 set to 0). Both depend on the grid and the bins only, which stay
    the same from window to window most of the time, while the bins' statistics change every
    window: the last few answers are kept (by the inputs' exact bytes: the same arrays) and
    handed out read-only."""
    key = tuple(a.tobytes() for a in (nodes, cov, centres, h, scale, half)) + (nodes.shape, cov.shape,
                                                                               centres.shape)
    got = _NODE_WEIGHTS.get(key)
    if got is None:
        near = _rect_distance(nodes, cov, half, scale).min(axis=1) <= 1.5
        w_all = np.exp(-0.5 * _sq_norm(nodes, centres, h))
        w_all[w_all < 1e-4] = 0.0
        near.setflags(write=False)
        w_all.setflags(write=False)
        got = (near, w_all)
        with _NODE_WEIGHTS_LOCK:
            while len(_NODE_WEIGHTS) >= _NODE_WEIGHTS_MAX:
                _NODE_WEIGHTS.pop(next(iter(_NODE_WEIGHTS)))
            _NODE_WEIGHTS[key] = got
    return got


class LocalCurves:
    """Locally weighted quadratic curves on a grid of nodes over the covered region.

    A single quadratic in (pi, n) over all the data misses a curve whose shape it cannot follow
    (a peak between two clusters of operation) by up to ~0.007 in eta_is, which moved the optimum
    by a bar on the simulator's 'speed_peak' plant. At each node the same polynomial form is fitted
    to the data nearby only (Gaussian weights over the coverage bins, ``local_bandwidth_bins`` wide),
    pulled toward the global fit with ``local_prior_weight`` samples where the nearby data is thin;
    between nodes the four surrounding local polynomials are blended bilinearly. Outside the grid
    (where the data is not) the global fit answers.
    """

    def __init__(self, bins: "_BinStats", global_coef: np.ndarray, global_A: np.ndarray,
                 coverage: "_Coverage", settings: "LearningSettings") -> None:
        s = settings
        centres, As, bs = bins.arrays()
        self.ok = False
        cov = coverage.centers(s.min_bin_weight)
        if len(centres) == 0 or len(cov) == 0:
            return
        self.dpi, self.dn = bins.bin_pi, bins.bin_n
        h = np.array([s.local_bandwidth_bins * self.dpi, s.local_bandwidth_bins * self.dn])
        lo = cov.min(axis=0) - np.array([s.margin_pi, s.margin_n])
        hi = cov.max(axis=0) + np.array([s.margin_pi, s.margin_n])
        self.p0 = math.floor(lo[0] / self.dpi) * self.dpi
        self.n0 = math.floor(lo[1] / self.dn) * self.dn
        npi = int(math.ceil((hi[0] - self.p0) / self.dpi)) + 2
        nn = int(math.ceil((hi[1] - self.n0) / self.dn)) + 2
        # the grid's nodes row by row in pi ("ij" order): meshgrid's raveled arrays, without it
        nodes = np.column_stack([np.repeat(self.p0 + self.dpi * np.arange(npi), nn),
                                 np.tile(self.n0 + self.dn * np.arange(nn), npi)])
        near, w_all = _node_weights(nodes, cov, centres, h, np.array([s.margin_pi, s.margin_n]),
                                    0.5 * np.array([coverage.bin_pi, coverage.bin_n]))
        coef = np.full((len(nodes), 6), np.nan)
        G = global_A / max(np.trace(global_A) / 6.0, 1e-300)      # normalised global precision
        # all nodes at once: the weighted bin statistics (k, 6, 6) and (k, 6), then one batched solve
        k_near = np.flatnonzero(near)
        if len(k_near):
            w = w_all[k_near]
            A = (w @ As.reshape(len(As), 36)).reshape(-1, 6, 6)
            fitted = np.trace(A, axis1=1, axis2=2) > 0
            mu = s.local_prior_weight
            A_tot = A + mu * G
            b_tot = w @ bs + mu * (G @ global_coef)
            idx = k_near[fitted]
            try:        # every node in one call (LAPACK's gesv per node: each node's numbers as alone)
                coef[idx] = np.linalg.solve(A_tot[fitted], b_tot[fitted][:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:       # a singular node: node by node, skipping it
                for k, Ak, bk in zip(idx, A_tot[fitted], b_tot[fitted]):
                    try:
                        coef[k] = np.linalg.solve(Ak, bk)
                    except np.linalg.LinAlgError:
                        continue
        self.coef = coef.reshape(npi, nn, 6)
        self.valid = np.isfinite(self.coef).all(axis=2)
        # the outermost ring of nodes answers with the global curve, so that the blend meets the
        # global fit continuously where the grid ends (a jump there broke the LS speed search)
        self.valid[[0, -1], :] = False
        self.valid[:, [0, -1]] = False
        self.global_coef = global_coef
        self.ok = bool(self.valid.any())

    def _arrays(self) -> None:
        """Every node's coefficients as one array (the global curve where a node has no local fit)."""
        c = np.where(self.valid[:, :, None], self.coef, np.asarray(self.global_coef)[None, None, :])
        self._ca = np.ascontiguousarray(c, dtype=float)
        self._ni, self._nj = c.shape[0] - 1, c.shape[1] - 1

    def _fast(self) -> None:
        """The same as nested lists, for the scalar path: the curves are evaluated millions of times
        per replay, in plain floats."""
        if "_ca" not in self.__dict__:
            self._arrays()
        self._c = self._ca.tolist()

    def __getstate__(self):
        d = dict(self.__dict__)
        d.pop("_c", None)       # rebuilt on first use (keeps pickles small)
        d.pop("_ca", None)
        return d

    def _cell(self, pi: float, n: float, left: bool = False):
        """(i, j, fx, fy, zp, zn) of (pi, n), None outside the grid. ``left``: on a node line in n,
        take the cell below (one-sided derivative from the left)."""
        if not (self.ok and math.isfinite(pi) and math.isfinite(n)):
            return None
        if "_c" not in self.__dict__:
            self._fast()
        x = (pi - self.p0) / self.dpi
        y = (n - self.n0) / self.dn
        i, j = int(math.floor(x)), int(math.floor(y))
        fy = y - j
        if left and fy == 0.0 and j > 0:
            j, fy = j - 1, 1.0
        if not (0 <= i < self._ni and 0 <= j < self._nj):
            return None
        return i, j, x - i, fy, (pi - _Z[0]) / _Z[1], (n - _Z[2]) / _Z[3]

    def value(self, pi: float, n: float) -> float | None:
        """The local curve at (pi, n), None outside the grid's valid nodes. Between nodes the four
        surrounding polynomials are blended bilinearly; a node without a local fit contributes the
        global curve (continuous where the local region ends)."""
        cell = self._cell(pi, n)
        if cell is None:
            return None
        i, j, fx, fy, zp, zn = cell
        r0, r1 = self._c[i], self._c[i + 1]
        pp, pn, nn = zp * zp, zp * zn, zn * zn
        v = [c[0] + c[1] * zp + c[2] * zn + c[3] * pp + c[4] * pn + c[5] * nn
             for c in (r0[j], r1[j], r0[j + 1], r1[j + 1])]
        return ((1 - fy) * ((1 - fx) * v[0] + fx * v[1])) + (fy * ((1 - fx) * v[2] + fx * v[3]))

    # ---- the same for arrays (model.vcycle): (values, inside), the values NaN outside the grid
    def _cell_v(self, pi, n, left=None):
        """Arrays (inside, i, j, fx, fy, zp, zn) of ``_cell`` (``left``: a boolean array)."""
        if not self.ok:
            pi, n = np.broadcast_arrays(np.asarray(pi, dtype=float), np.asarray(n, dtype=float))
            z = np.zeros(pi.shape, dtype=np.intp)
            self._ca = np.zeros((2, 2, 6))
            return np.zeros(pi.shape, dtype=bool), z, z, pi * 0.0, pi * 0.0, pi * 0.0, pi * 0.0
        if "_ca" not in self.__dict__:
            self._arrays()
        pi, n = np.broadcast_arrays(np.asarray(pi, dtype=float), np.asarray(n, dtype=float))
        fin = np.isfinite(pi) & np.isfinite(n)
        x = (np.where(fin, pi, self.p0) - self.p0) / self.dpi
        y = (np.where(fin, n, self.n0) - self.n0) / self.dn
        i, j = np.floor(x), np.floor(y)
        fy = y - j
        if left is not None:
            shift = left & (fy == 0.0) & (j > 0)
            j, fy = np.where(shift, j - 1, j), np.where(shift, 1.0, fy)
        inside = fin & (i >= 0) & (i < self._ni) & (j >= 0) & (j < self._nj) & self.ok
        ii = np.where(inside, i, 0).astype(np.intp)
        jj = np.where(inside, j, 0).astype(np.intp)
        return inside, ii, jj, x - i, fy, (pi - _Z[0]) / _Z[1], (n - _Z[2]) / _Z[3]

    def _corners_v(self, ii, jj, zp, zn, deriv: bool):
        c = self._ca
        pp, pn, nn = zp * zp, zp * zn, zn * zn
        out = []
        for di, dj in ((0, 0), (1, 0), (0, 1), (1, 1)):
            k = c[ii + di, jj + dj]
            v = k[:, 0] + k[:, 1] * zp + k[:, 2] * zn + k[:, 3] * pp + k[:, 4] * pn + k[:, 5] * nn
            out.append((v, k[:, 2] + k[:, 4] * zp + 2.0 * k[:, 5] * zn) if deriv else v)
        return out

    def value_v(self, pi, n) -> tuple[np.ndarray, np.ndarray]:
        """``value`` for arrays: (values, inside); NaN where ``value`` is None. The same operations
        as ``_cell_v`` and ``_corners_v``, with the four corners gathered in one step."""
        if not self.ok:
            return self._value_v(pi, n)
        if "_ca" not in self.__dict__:
            self._cell_v(self.p0, self.n0)
        pi = np.asarray(pi, dtype=float)
        n = np.asarray(n, dtype=float)
        if pi.shape != n.shape:
            pi, n = np.broadcast_arrays(pi, n)
        fin = np.isfinite(pi) & np.isfinite(n)
        all_fin = fin.all()
        x = ((pi if all_fin else np.where(fin, pi, self.p0)) - self.p0) / self.dpi
        y = ((n if all_fin else np.where(fin, n, self.n0)) - self.n0) / self.dn
        i, j = np.floor(x), np.floor(y)
        fx, fy = x - i, y - j
        inside = (i >= 0) & (i < self._ni) & (j >= 0) & (j < self._nj)
        if not all_fin:
            inside &= fin
        every = inside.all()
        ii = (i if every else np.where(inside, i, 0)).astype(np.intp)
        jj = (j if every else np.where(inside, j, 0)).astype(np.intp)
        zp, zn = (pi - _Z[0]) / _Z[1], (n - _Z[2]) / _Z[3]
        c = self._ca
        stride = c.shape[1]
        corner = np.array([0, stride, 1, stride + 1])       # (0, 0), (1, 0), (0, 1), (1, 1)
        k = c.reshape(-1, 6)[(ii * stride + jj)[:, None] + corner]          # (rows, 4, 6)
        zp1, zn1 = zp[:, None], zn[:, None]
        v = (k[:, :, 0] + k[:, :, 1] * zp1 + k[:, :, 2] * zn1 + k[:, :, 3] * (zp * zp)[:, None]
             + k[:, :, 4] * (zp * zn)[:, None] + k[:, :, 5] * (zn * zn)[:, None])
        val = ((1 - fy) * ((1 - fx) * v[:, 0] + fx * v[:, 1])) + (fy * ((1 - fx) * v[:, 2] + fx * v[:, 3]))
        if every:
            return val, inside
        return np.where(inside, val, np.nan), inside

    def _value_v(self, pi, n) -> tuple[np.ndarray, np.ndarray]:
        inside, ii, jj, fx, fy, zp, zn = self._cell_v(pi, n)
        v = self._corners_v(ii, jj, zp, zn, False)
        val = ((1 - fy) * ((1 - fx) * v[0] + fx * v[1])) + (fy * ((1 - fx) * v[2] + fx * v[3]))
        return np.where(inside, val, np.nan), inside

    def value_dn_v(self, pi, n, left=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``value_dn`` for arrays (``left`` a boolean array): (values, d/dn, inside)."""
        inside, ii, jj, fx, fy, zp, zn = self._cell_v(pi, n, left)
        (v0, d0), (v1, d1), (v2, d2), (v3, d3) = self._corners_v(ii, jj, zp, zn, True)
        lo = (1 - fx) * v0 + fx * v1
        hi = (1 - fx) * v2 + fx * v3
        val = (1 - fy) * lo + fy * hi
        d = (hi - lo) / self.dn + ((1 - fy) * ((1 - fx) * d0 + fx * d1)
                                   + fy * ((1 - fx) * d2 + fx * d3)) / _Z[3]
        nan = np.nan
        return np.where(inside, val, nan), np.where(inside, d, nan), inside

    def rows_at(self, pi) -> tuple[np.ndarray, np.ndarray]:
        """For a speed search at fixed pressure ratios ``pi`` (one per row): every node column's
        polynomial at that pi, blended across the pi cell, as a quadratic in z_n (rows, columns, 3),
        and whether pi lies inside the grid. ``value_dn_rows`` then evaluates ``value_dn_v`` at any n
        with a third of the work (the pi part is done once per search, not once per step)."""
        if not self.ok:
            inside, ii, _, fx, _, zp, _ = self._cell_v(pi, np.full(np.shape(pi), self.n0))
        else:
            # ``_cell_v``'s pi part alone (its n part at n0 is inside whenever the grid has a cell)
            if "_ca" not in self.__dict__:
                self._cell_v(self.p0, self.n0)
            pi = np.asarray(pi, dtype=float)
            fin = np.isfinite(pi)
            x = ((pi if fin.all() else np.where(fin, pi, self.p0)) - self.p0) / self.dpi
            i = np.floor(x)
            inside = fin & (i >= 0) & (i < self._ni) & (self._nj > 0)
            ii = np.where(inside, i, 0).astype(np.intp)
            fx = x - i
            zp = (pi - _Z[0]) / _Z[1]
        c = self._ca
        zp1, zp2 = zp[:, None], (zp * zp)[:, None]
        f = fx[:, None]
        out = np.empty((len(ii), c.shape[1], 3))
        k0, k1 = c[ii], c[ii + 1]                               # (rows, columns, 6)
        # the same operations as blending the two stacked quadratics, written into one array
        out[:, :, 0] = (1.0 - f) * (k0[:, :, 0] + k0[:, :, 1] * zp1 + k0[:, :, 3] * zp2) \
            + f * (k1[:, :, 0] + k1[:, :, 1] * zp1 + k1[:, :, 3] * zp2)
        out[:, :, 1] = (1.0 - f) * (k0[:, :, 2] + k0[:, :, 4] * zp1) + f * (k1[:, :, 2] + k1[:, :, 4] * zp1)
        out[:, :, 2] = (1.0 - f) * k0[:, :, 5] + f * k1[:, :, 5]
        return out, inside & self.ok

    def kernel_tables(self, rows: int) -> tuple:
        """``model.analysis.speedkernel``'s tables of this grid (one member) and the rows' member."""
        if "_ca" not in self.__dict__:
            self._cell_v(self.p0, self.n0)
        return ((self._ca[None], np.array([self.p0], dtype=float), np.array([self.dpi], dtype=float),
                 np.array([self._ni], dtype=np.intp), np.array([self._nj], dtype=np.intp),
                 np.array([bool(self.ok)]), np.array([self.n0], dtype=float),
                 np.array([self.dn], dtype=float)), np.zeros(rows, dtype=np.intp))

    def value_dn_rows(self, Q: np.ndarray, inside_pi: np.ndarray, rows: np.ndarray, n, left=None):
        """``value_dn_v`` at (pi of ``rows_at``, n) for the rows ``rows`` of ``Q``: (values, d/dn,
        inside); the same numbers to round-off."""
        n = np.asarray(n, dtype=float)
        fin = np.isfinite(n)
        all_fin = fin.all()
        y = ((n if all_fin else np.where(fin, n, self.n0)) - self.n0) / self.dn
        j = np.floor(y)
        fy = y - j
        if left is not None:
            shift = left & (fy == 0.0) & (j > 0)
            if shift.any():
                j, fy = np.where(shift, j - 1, j), np.where(shift, 1.0, fy)
        inside = inside_pi[rows] & (j >= 0) & (j < self._nj)
        if not all_fin:
            inside &= fin
        every = inside.all()
        jj = (j if every else np.where(inside, j, 0)).astype(np.intp)
        zn = (n - _Z[2]) / _Z[3]
        a, b = Q[rows, jj], Q[rows, jj + 1]                    # the cell's two node columns (rows, 3)
        va = a[:, 0] + (a[:, 1] + a[:, 2] * zn) * zn
        vb = b[:, 0] + (b[:, 1] + b[:, 2] * zn) * zn
        da = a[:, 1] + 2.0 * a[:, 2] * zn
        db = b[:, 1] + 2.0 * b[:, 2] * zn
        val = (1 - fy) * va + fy * vb
        d = (vb - va) / self.dn + ((1 - fy) * da + fy * db) / _Z[3]
        if every:
            return val, d, inside
        nan = np.nan
        return np.where(inside, val, nan), np.where(inside, d, nan), inside

    def value_dn(self, pi: float, n: float, left: bool = False) -> tuple[float, float] | None:
        """(value, d value / d n) at (pi, n) (the derivative of the bilinear blend, exact within a
        cell), None outside the grid."""
        cell = self._cell(pi, n, left)
        if cell is None:
            return None
        i, j, fx, fy, zp, zn = cell
        r0, r1 = self._c[i], self._c[i + 1]
        pp, pn, nn = zp * zp, zp * zn, zn * zn
        cs = (r0[j], r1[j], r0[j + 1], r1[j + 1])
        v = [c[0] + c[1] * zp + c[2] * zn + c[3] * pp + c[4] * pn + c[5] * nn for c in cs]
        dv = [c[2] + c[4] * zp + 2.0 * c[5] * zn for c in cs]
        lo = (1 - fx) * v[0] + fx * v[1]
        hi = (1 - fx) * v[2] + fx * v[3]
        val = (1 - fy) * lo + fy * hi
        d = (hi - lo) / self.dn + ((1 - fy) * ((1 - fx) * dv[0] + fx * dv[1])
                                   + fy * ((1 - fx) * dv[2] + fx * dv[3])) / _Z[3]
        return val, d


@dataclass(frozen=True)
class LearnedCompressor(Compressor):
    """A compressor whose learned curves are evaluated locally (``LocalCurves``) where the data
    is, and by the global polynomial (the inherited coefficients) elsewhere."""
    local_is: object = field(default=None, compare=False, hash=False, repr=False)
    local_vol: object = field(default=None, compare=False, hash=False, repr=False)
    delta_is: tuple | None = None      # an uncertainty draw: scaled-basis coefficients added
    delta_vol: tuple | None = None

    def eta_is_at(self, pi: float, n: float) -> float:
        v = self.local_is.value(pi, n) if self.local_is is not None else None
        v = v if v is not None else Compressor.eta_is_at(self, pi, n)
        return v + _zvalue(self.delta_is, pi, n) if self.delta_is is not None else v

    def eta_vol_at(self, pi: float, n: float) -> float:
        v = self.local_vol.value(pi, n) if self.local_vol is not None else None
        v = v if v is not None else Compressor.eta_vol_at(self, pi, n)
        return v + _zvalue(self.delta_vol, pi, n) if self.delta_vol is not None else v

    def _vol_dn(self, pi: float, n: float, left: bool = False) -> tuple[float, float]:
        """eta_vol and its derivative in n at (pi, n) (``left``: one-sided from below on a node
        line); the value is exactly ``eta_vol_at``'s."""
        r = self.local_vol.value_dn(pi, n, left)
        if r is None:
            c = self.eta_vol
            v = Compressor.eta_vol_at(self, pi, n)
            d = c[2] + c[4] * pi + 2.0 * c[5] * n
        else:
            v, d = r
        a = self.delta_vol
        if a is not None:
            zp = (pi - _Z[0]) / _Z[1]
            zn = (n - _Z[2]) / _Z[3]
            v = v + _zvalue(a, pi, n)
            d = d + (a[2] + a[4] * zp + 2.0 * a[5] * zn) / _Z[3]
        return v, d

    # ---- the vectorised protocol (model.vcycle): the same numbers as the scalar methods
    def eta_is_v(self, pi, n) -> np.ndarray:
        """``eta_is_at`` for arrays."""
        return self._curve_v(self.local_is, Compressor.eta_is_v(self, pi, n), self.delta_is, pi, n)

    def eta_vol_v(self, pi, n) -> np.ndarray:
        """``eta_vol_at`` for arrays."""
        return self._curve_v(self.local_vol, Compressor.eta_vol_v(self, pi, n), self.delta_vol, pi, n)

    @staticmethod
    def _curve_v(local, glob, delta, pi, n) -> np.ndarray:
        v = np.asarray(glob, dtype=float)
        if local is not None:
            loc, inside = local.value_v(pi, n)
            v = np.where(inside, loc, v)
        return v + _zvalue(delta, pi, n) if delta is not None else v

    def _vol_dn_v(self, pi, n, left) -> tuple[np.ndarray, np.ndarray]:
        """``_vol_dn`` for arrays (``left`` a boolean array)."""
        v, d, inside = self.local_vol.value_dn_v(pi, n, left)
        c = self.eta_vol
        v = np.where(inside, v, Compressor.eta_vol_v(self, pi, n))
        d = np.where(inside, d, c[2] + c[4] * pi + 2.0 * c[5] * n)
        a = self.delta_vol
        if a is not None:
            zp = (pi - _Z[0]) / _Z[1]
            zn = (n - _Z[2]) / _Z[3]
            v = v + _zvalue(a, pi, n)
            d = d + (a[2] + a[4] * zp + 2.0 * a[5] * zn) / _Z[3]
        return v, d

    def speed_for_flow_v(self, m, rho_suc, pi, n0=None) -> tuple[np.ndarray, np.ndarray]:
        """``speed_for_flow`` for arrays (the contract of ``Compressor.speed_for_flow_v``: NaN in
        rows where the scalar method raises ValueError)."""
        if self.local_vol is None or not self.local_vol.ok:
            return Compressor.speed_for_flow_v(self, m, rho_suc, pi, n0)
        m, rho_suc, pi = (np.asarray(x, dtype=float) for x in (m, rho_suc, pi))
        if not (m.shape == rho_suc.shape == pi.shape):
            m, rho_suc, pi = np.broadcast_arrays(m, rho_suc, pi)
        return local_speed(self.local_vol, self.eta_vol, self.delta_vol, m / (rho_suc * self.swept_volume),
                           pi, n0, self.N_min / self.N_nom, self.N_max / self.N_nom)

    def speed_for_flow(self, m: float, rho_suc: float, pi: float, n0: float = 1.0) -> tuple[float, float]:
        """As Compressor.speed_for_flow (same contract), by safeguarded Newton with the analytic
        derivative of the blended curve: phi(n) = eta_vol(pi, n) * n = m / (rho_suc * swept_volume),
        continued linearly beyond the speed bounds (with the one-sided slope inside the range)."""
        if self.local_vol is None or not self.local_vol.ok:
            return Compressor.speed_for_flow(self, m, rho_suc, pi, n0)
        target = m / (rho_suc * self.swept_volume)
        n_lo, n_hi = self.N_min / self.N_nom, self.N_max / self.N_nom

        def phi(n: float) -> tuple[float, float]:
            v, d = self._vol_dn(pi, n, left=n >= n_hi)
            return v * n, v + n * d

        lo_edge, hi_edge = phi(n_lo), phi(n_hi)
        for edge, (_, slope) in ((n_lo, lo_edge), (n_hi, hi_edge)):
            if slope <= 0.0:
                raise ValueError(f"volumetric-efficiency curve gives a flow that does not rise with "
                                 f"speed at pressure ratio {pi:.3f}, n={edge:.3f}")
        f_hi, d_hi = hi_edge
        if target > f_hi:
            n = n_hi + (target - f_hi) / d_hi
            return n, target / n
        f_lo, d_lo = lo_edge
        if target < f_lo:
            n = n_lo + (target - f_lo) / d_lo
            if n <= 0.0:
                raise ValueError(f"flow {m:.4g} kg/s is too small for the compressor curve")
            return n, target / n
        a, b = n_lo, n_hi
        n = min(max(n0, n_lo), n_hi)
        for _ in range(60):
            f, df = phi(n)
            if f > target:
                b = n
            else:
                a = n
            step = (f - target) / df if df > 0 else 0.0
            nn = n - step
            if not a <= nn <= b:
                nn = 0.5 * (a + b)
            if abs(nn - n) < SPEED_STEP_TOL:
                n = nn
                break
            n = nn
        return n, target / n


LEGACY_KS_RANGE = (1e5, 1e8)     # a state without "t_unit" whose t_last lies here was written in ks


def _t_last_of(d: dict) -> float | None:
    """A state document's ``t_last`` in epoch seconds. Documents written before stop 46 carry no
    ``t_unit``; with pandas 3 their times were epoch seconds / 1000 (``epoch_seconds``): such a
    value (1e5-1e8: the years 1973-5138 in kiloseconds, 1970-1973 in seconds) is read as
    kiloseconds, so that the first update after the upgrade decays the statistics by the time that
    really passed instead of wiping them. A value in seconds (written under pandas 2, whose
    datetimes were nanoseconds) is read as it is."""
    t = d.get("t_last")
    if t is None:
        return None
    t = float(t)
    if not math.isfinite(t):        # (a damaged state: no later sample would pass the time test)
        raise ValueError(f"t_last must be a finite number of epoch seconds, got {d.get('t_last')!r}")
    if d.get("t_unit") == "s":
        return t
    lo, hi = LEGACY_KS_RANGE
    return t * 1000.0 if lo <= t < hi else t


class CompressorLearner:
    """Learns eta_is and eta_vol (per stage) and the drive factors from observations.

    prior : the configured compressors (plant.yaml's curves)
    """

    def __init__(self, prior: PlantParams, settings: LearningSettings | None = None) -> None:
        self.s = settings or LearningSettings()
        self.prior = {"LS": prior.comp_LS, "HS": prior.comp_HS}
        self.stats = {(st, c): _Stats() for st in STAGES for c in CURVES}
        self.bins = {(st, c): _BinStats(self.s.bin_pi, self.s.bin_n) for st in STAGES for c in CURVES}
        self.coverage = {st: _Coverage(self.s.bin_pi, self.s.bin_n) for st in STAGES}
        self._local: dict = {}
        self.drive = {st: [0.0, 0.0] for st in STAGES}          # decaying sum w*x, sum w
        self.subcooling = [0.0, 0.0]                             # decaying sum, weight
        self.t_last: float | None = None
        self.n_seen = 0
        self.commissioning: dict | None = None                  # curves frozen at commissioning
        self._prior_stats = {(st, c): self._prior_pseudo(st, c) for st in STAGES for c in CURVES}
        self._fit_cache: dict | None = None

    # ---------------------------------------------------------------------------- update
    def _prior_pseudo(self, stage: str, curve: str) -> _Stats:
        comp = self.prior[stage]
        pi = np.linspace(1.3, 4.5, 17)
        n = np.linspace(comp.N_min / comp.N_nom, comp.N_max / comp.N_nom, 9)
        P, N = np.meshgrid(pi, n)
        P, N = P.ravel(), N.ravel()
        f = comp.eta_is_at if curve == "eta_is" else comp.eta_vol_at
        y = np.array([f(a, b) for a, b in zip(P, N)])
        X = _zbasis(P, N)
        w = self.s.prior_weight / len(y)
        st = _Stats()
        st.add(X * math.sqrt(w), y * math.sqrt(w))
        st.w = self.s.prior_weight
        return st

    def update(self, obs: pd.DataFrame, t_now: float | None = None) -> int:
        """Add a batch of observations (``observe``'s frame); older data decays to t_now (default:
        the batch's last time). Returns how many samples carried a usable eta_is observation."""
        t = obs["t"].to_numpy(dtype=float) if "t" in obs else np.full(len(obs), np.nan)
        if t_now is None:
            t_now = float(np.nanmax(t)) if np.isfinite(t).any() else (self.t_last or 0.0)
        if self.t_last is not None and t_now > self.t_last:
            f = 0.5 ** ((t_now - self.t_last) / (self.s.half_life_days * DAY_S))
            for v in self.stats.values():
                v.decay(f)
            for v in self.bins.values():
                v.decay(f)
            for v in self.coverage.values():
                v.decay(f)
            for v in self.drive.values():
                v[0] *= f
                v[1] *= f
            self.subcooling[0] *= f
            self.subcooling[1] *= f
        if self.t_last is None or t_now > self.t_last:
            self.t_last = t_now
        used = 0
        for stage in STAGES:
            pi = obs[f"pi_{stage}"].to_numpy(dtype=float)
            n = obs[f"n_{stage}"].to_numpy(dtype=float)
            for curve in CURVES:
                y = obs[f"{curve}_{stage}"].to_numpy(dtype=float)
                ok = np.isfinite(pi) & np.isfinite(n) & np.isfinite(y)
                if ok.sum() < 3:
                    continue
                X = _zbasis(pi[ok], n[ok])
                st = self.stats[(stage, curve)]
                # serial correlation of the residuals against the current fit (EW mean of the lag-1
                # coefficient), for the covariance inflation: one-minute residuals are not independent
                a = self._coef(stage, curve)
                r = y[ok] - X @ a
                if len(r) >= 10 and np.std(r) > 0:
                    rho = float(np.corrcoef(r[:-1], r[1:])[0, 1])
                    if math.isfinite(rho):
                        k = min(1.0, len(r) / max(st.w + len(r), 1.0))
                        st.rho1 = (1 - k) * st.rho1 + k * max(0.0, min(rho, 0.98))
                st.add(X, y[ok])
                self.bins[(stage, curve)].add(pi[ok], n[ok], X, y[ok])
                if curve == "eta_is":
                    used = max(used, int(ok.sum()))
            ok = np.isfinite(pi) & np.isfinite(n) & np.isfinite(obs[f"eta_is_{stage}"].to_numpy(dtype=float))
            self.coverage[stage].add(pi[ok], n[ok])
            d = obs[f"drive_{stage}"].to_numpy(dtype=float)
            d = d[np.isfinite(d) & (d > 0.5) & (d < 2.0)]
            if len(d):
                self.drive[stage][0] += float(np.sum(d))
                self.drive[stage][1] += float(len(d))
        sub = obs["subcooling_meas_K"].to_numpy(dtype=float) if "subcooling_meas_K" in obs else []
        sub = np.asarray(sub)[np.isfinite(sub)]
        if len(sub):
            self.subcooling[0] += float(np.sum(sub))
            self.subcooling[1] += float(len(sub))
        self.n_seen += used
        self._fit_cache = None
        self._local = {}
        return used

    def freeze_commissioning(self) -> None:
        """Keep the curves as they are now as the commissioning reference (for the drift figure)."""
        self.commissioning = {"curves": self.curves_dict(), "coverage": {
            st: self.coverage[st].to_dict() for st in STAGES}}

    # ---------------------------------------------------------------------------- results
    def _coef(self, stage: str, curve: str) -> np.ndarray:
        ps = self._prior_stats[(stage, curve)]
        st = self.stats[(stage, curve)]
        A = ps.A + st.A
        return np.linalg.solve(A, ps.b + st.b)

    def learned(self, stage: str, curve: str) -> bool:
        return self.stats[(stage, curve)].w >= self.s.min_samples

    def covariance(self, stage: str, curve: str) -> np.ndarray:
        """Covariance of the scaled-basis coefficients, (P + A_data / s^2)^-1: s^2 the data's
        residual variance inflated by (1 + rho1)/(1 - rho1) for serially correlated residuals, and
        P the prior's precision as far as the data sheet deserves it: the prior's pseudo-
        observations scaled so that the curve's prior standard deviation, averaged over the prior's
        grid, is ``prior_sd`` (a plant's curve may differ from the data sheet's by a few points
        anywhere). The fit itself keeps its ``prior_weight``; only the uncertainty changes: inside
        the data it is the data's, away from it it grows toward ``prior_sd``, so a recommendation
        that extrapolates the curves carries an uncertainty that says so."""
        ps = self._prior_stats[(stage, curve)]
        st = self.stats[(stage, curve)]
        a = np.linalg.solve(ps.A + st.A, ps.b + st.b)
        if st.w > 6:
            sse = st.yy - 2 * a @ st.b + a @ st.A @ a
            s2 = max(sse, 0.0) / (st.w - 6)
        else:
            s2 = 0.02 ** 2
        s2 = max(s2, 1e-8) * (1 + st.rho1) / (1 - st.rho1)
        # ps.A = prior_weight * mean over the grid of x x^T; the prior variance at a grid point
        # averages trace(G^-1 M) / k over the grid for precision k M (M = mean x x^T): 6 / k
        P = ps.A * (6.0 / (self.s.prior_weight * self.s.prior_sd ** 2))
        return np.linalg.inv(P + st.A / s2)

    def rmse(self, stage: str, curve: str) -> float:
        st = self.stats[(stage, curve)]
        if st.w <= 6:
            return math.nan
        a = self._coef(stage, curve)
        return math.sqrt(max(st.yy - 2 * a @ st.b + a @ st.A @ a, 0.0) / st.w)

    def drive_factor(self, stage: str) -> float:
        s, w = self.drive[stage]
        return s / w if w >= self.s.min_samples / 4 else 1.0

    def T_c_location(self) -> str:
        if self.s.T_c_location != "auto":
            return self.s.T_c_location
        s, w = self.subcooling
        if w <= 0:
            return "condenser_outlet"
        return "subcooler_outlet" if s / w > self.s.subcooling_threshold_K else "condenser_outlet"

    def local_curves(self, stage: str, curve: str) -> LocalCurves | None:
        """The locally weighted curve of a learned (stage, curve), cached until the next update."""
        if not (self.s.local and self.learned(stage, curve)):
            return None
        key = (stage, curve)
        if key not in self._local:
            ps, st = self._prior_stats[key], self.stats[key]
            lc = LocalCurves(self.bins[key], self._coef(stage, curve), ps.A + st.A,
                             self.coverage[stage], self.s)
            self._local[key] = lc if lc.ok else None
        return self._local[key]

    def prior_share(self, stage: str, pi, n, curve: str = "eta_is") -> np.ndarray:
        """How much of the learned curve at (pi, n) is still the prior's shape rather than the data's:
        mu / (mu + W), W the effective samples near (pi, n) under the local fits' kernel
        (``local_bandwidth_bins`` bins wide) and mu ``local_prior_weight``: ~0 where the plant has
        run a lot, 1 far from any data. Where the data are thin the learned curve follows the data
        sheet's shape, and its error is about ``prior_sd`` times this share (``shape_sd`` adds the
        extrapolation past the data's edge: one standard deviation plus the in-data tolerance
        covers 84-93 % of the true errors near the data, two 92-99.6 %: tests/test_compressors.py)."""
        pi = np.atleast_1d(np.asarray(pi, dtype=float))
        n = np.atleast_1d(np.asarray(n, dtype=float))
        key = ("W", stage, curve)
        if key not in self._local:
            c, As, _ = self.bins[(stage, curve)].arrays()
            self._local[key] = (c, As[:, 0, 0].copy() if len(As) else np.zeros(0))
        c, wb = self._local[key]
        if not len(c):
            return np.ones(len(pi))
        h = self.s.local_bandwidth_bins * np.array([self.s.bin_pi, self.s.bin_n])
        q = np.column_stack([pi, n])
        W = np.exp(-0.5 * _sq_norm(q, c, h)) @ wb
        mu = self.s.local_prior_weight
        out = mu / (mu + W)
        return np.where(np.isfinite(q).all(axis=1), out, 1.0)

    def shape_sd(self, stage: str, pi, n, curve: str = "eta_is") -> np.ndarray:
        """One standard deviation [-] of the learned curve's shape error at (pi, n): the prior's
        share there times ``prior_sd`` (where the data are thin the curve is the data sheet's shape)
        and, in quadrature, ``extrapolation_sd`` x d^2, d the distance beyond the covered bins in
        margins (``coverage_distance``; at most ``prior_sd``). The second term is the error of a
        curve carried past the data's edge along the slope the data show: a curvature c the data
        have not shown costs c/2 x distance^2 (0.002 one margin_pi of 0.10 out: c = 0.4 per unit
        pi^2, a curve whose peak lies 0.05 above the line the data show, half a unit of pi away).
        Inside the covered bins it is 0."""
        u = self.s.prior_sd * self.prior_share(stage, pi, n, curve)
        if self.s.extrapolation_sd:
            d = self.coverage_distance(stage, pi, n)
            u = np.hypot(u, np.minimum(self.s.extrapolation_sd * d ** 2, self.s.prior_sd))
        return u

    def compressor(self, stage: str, delta: dict | None = None) -> Compressor:
        """The stage's Compressor with the learned curves (the prior's where not learned yet;
        locally weighted where the data is) and drive factor. ``delta``: scaled-basis coefficient
        differences added to the learned curves (an uncertainty draw)."""
        comp = self.prior[stage]
        kw = {}
        for curve in CURVES:
            if self.learned(stage, curve):
                kw[curve] = _to_poly(self._coef(stage, curve))
        kw["drive_factor"] = self.drive_factor(stage)
        base = comp.replace(**kw)
        local = {c: self.local_curves(stage, c) for c in CURVES}
        if all(v is None for v in local.values()) and not delta:
            return base
        fields_ = {f.name: getattr(base, f.name) for f in fields(Compressor)}
        d = delta or {}
        return LearnedCompressor(**fields_, local_is=local["eta_is"], local_vol=local["eta_vol"],
                                 delta_is=tuple(d["eta_is"]) if "eta_is" in d else None,
                                 delta_vol=tuple(d["eta_vol"]) if "eta_vol" in d else None)

    def apply(self, params: PlantParams) -> PlantParams:
        """``params`` with the learned compressors."""
        return params.replace(comp_LS=self.compressor("LS"), comp_HS=self.compressor("HS"))

    def draws(self, k: int, rng: np.random.Generator) -> list[dict]:
        """k draws from the learned coefficients' covariance (scaled basis) as differences to the
        learned curves, per stage: [{"LS": {"eta_is": da, "eta_vol": da}, "HS": {...}}, ...] (only
        learned curves vary); ``compressor(stage, delta=draw[stage])`` applies one."""
        out = []
        chol = {}
        for st in STAGES:
            for c in CURVES:
                if self.learned(st, c):
                    C = self.covariance(st, c)
                    w, V = np.linalg.eigh((C + C.T) / 2)
                    chol[(st, c)] = (self._coef(st, c), V * np.sqrt(np.clip(w, 0, None)))
        for _ in range(k):
            d = {st: {} for st in STAGES}
            for (st, c), (a, L) in chol.items():
                d[st][c] = L @ rng.standard_normal(6)      # a difference to the learned curve
            out.append(d)
        return out

    def coverage_distance(self, stage: str, pi, n, reference: dict | None = None) -> np.ndarray:
        """Distance of (pi, n) points to the covered region, in units of the margin (<= 1: within
        the allowed extrapolation; 0: inside a covered bin). The region is local: the bins where the
        compressor has run for at least ``min_bin_weight`` effective samples, not the hull between
        them (a curve's peak can hide in a gap between two clusters of data, e.g. between the
        operation at two set points). inf when nothing is covered. ``reference``: a coverage
        document (commissioning) instead of the current one."""
        if reference is not None:
            cov = _Coverage.from_dict(reference)
            c = cov.centers(self.s.min_bin_weight)
        else:           # the covered bins' centres, cached until the next update
            cov = self.coverage[stage]
            key = ("centers", stage)
            if key not in self._local:
                self._local[key] = cov.centers(self.s.min_bin_weight)
            c = self._local[key]
        q = np.column_stack([np.atleast_1d(pi), np.atleast_1d(n)]).astype(float)
        if len(c) == 0:
            return np.full(len(q), np.inf)
        half = 0.5 * np.array([cov.bin_pi, cov.bin_n])
        scale = np.array([self.s.margin_pi, self.s.margin_n])
        # per query and bin: the distance to the bin's rectangle, scaled by the margin
        if speedkernel._KERNEL is not None:
            d = speedkernel.rect_min(q, c, half, scale)
        else:
            d = _rect_distance(q, c, half, scale).min(axis=1)
        return np.where(np.isfinite(q).all(axis=1), d, np.inf)

    def eta_is(self, stage: str, pi, n) -> np.ndarray:
        """The stage's learned eta_is at the points (pi, n): ``eta_is_at``'s numbers, for arrays."""
        pi, n = np.broadcast_arrays(np.atleast_1d(np.asarray(pi, dtype=float)),
                                    np.atleast_1d(np.asarray(n, dtype=float)))
        return np.asarray(self.compressor(stage).eta_is_v(pi, n), dtype=float)

    def drift_pct(self, stage: str, pi: float, n: float) -> float:
        """eta_is now minus at commissioning at (pi, n), in percentage points; NaN when there is no
        commissioning reference or (pi, n) lies outside the region it covered."""
        if self.commissioning is None:
            return math.nan
        ref_cov = self.commissioning["coverage"][stage]
        if not self.coverage_distance(stage, pi, n, reference=ref_cov)[0] <= 1.0:
            return math.nan
        c = self.commissioning["curves"][stage]["eta_is"]
        ref = Compressor(1.0, 1.0, 0.5, 2.0, tuple(c), tuple(c))
        return 100.0 * (self.compressor(stage).eta_is_at(pi, n) - ref.eta_is_at(pi, n))

    def curves_dict(self) -> dict:
        """The curves in use in plant.yaml's form (POLY_BASIS coefficients), per stage."""
        out = {}
        for st in STAGES:
            comp = self.compressor(st)
            out[st] = {"eta_is": list(comp.eta_is), "eta_vol": list(comp.eta_vol),
                       "drive_factor": comp.drive_factor,
                       "learned": {c: self.learned(st, c) for c in CURVES},
                       "samples": {c: self.stats[(st, c)].w for c in CURVES},
                       "rmse": {c: self.rmse(st, c) for c in CURVES}}
        return out

    def summary(self) -> dict:
        return {"curves": self.curves_dict(), "T_c_location": self.T_c_location(),
                "basis": list(POLY_BASIS), "n_seen": self.n_seen}

    # ---------------------------------------------------------------------------- state
    def to_dict(self) -> dict:
        return {
            "format": "hp-edge-compressors/1",
            "settings": {f.name: getattr(self.s, f.name) for f in fields(self.s)},
            "t_last": self.t_last, "t_unit": "s", "n_seen": self.n_seen,
            "stats": {f"{st}.{c}": v.to_dict() for (st, c), v in self.stats.items()},
            "bins": {f"{st}.{c}": v.to_dict() for (st, c), v in self.bins.items()},
            "coverage": {st: v.to_dict() for st, v in self.coverage.items()},
            "drive": self.drive, "subcooling": self.subcooling,
            "commissioning": self.commissioning,
            "curves": self.curves_dict(), "T_c_location": self.T_c_location(),
        }

    @classmethod
    def from_dict(cls, d: dict, prior: PlantParams,
                  settings: LearningSettings | None = None) -> "CompressorLearner":
        if not isinstance(d, dict) or d.get("format") != "hp-edge-compressors/1":
            raise LearningError("compressor state: not a 'hp-edge-compressors/1' document")
        try:
            s = settings or LearningSettings.from_dict(
                {k: v for k, v in d.get("settings", {}).items()})
            obj = cls(prior, s)
            obj.t_last = _t_last_of(d)
            obj.n_seen = int(d.get("n_seen", 0))
            for key, v in d["stats"].items():
                st, c = key.split(".")
                obj.stats[(st, c)] = _Stats.from_dict(v)
            for st, v in d["coverage"].items():
                obj.coverage[st] = _Coverage.from_dict(v)
            for key, v in (d.get("bins") or {}).items():
                st, c = key.split(".")
                obj.bins[(st, c)] = _BinStats.from_dict(v, obj.s.bin_pi, obj.s.bin_n)
            obj.drive = {k: [float(a), float(b)] for k, (a, b) in d["drive"].items()}
            obj.subcooling = [float(x) for x in d["subcooling"]]
            obj.commissioning = d.get("commissioning")
        except (KeyError, TypeError, ValueError) as exc:
            raise LearningError(f"compressor state: {exc}") from exc
        return obj

    def copy(self) -> "CompressorLearner":
        return CompressorLearner.from_dict(self.to_dict(), _params_stub(self.prior), self.s)

    def snapshot(self) -> "CompressorLearner":
        """This learner as it is now, unchanged by its later updates: what a pickled copy gives (a
        replay's window task in one process), at a fraction of the cost. ``update`` changes the
        statistics' arrays, the coverage and bin dicts and the drive and subcooling sums in place,
        so those are copied; the prior, the settings, the prior's pseudo-statistics and the
        commissioning curves are never changed after construction and are shared; the cached local
        curves (rebuilt from the statistics on demand, replaced by ``update``) are shared entries of
        a dict of the snapshot's own."""
        out = copy.copy(self)
        out.stats = {k: _Stats(v.A.copy(), v.b.copy(), v.yy, v.w, v.rho1) for k, v in self.stats.items()}
        out.bins = {k: v.copy() for k, v in self.bins.items()}
        out.coverage = {k: _Coverage(v.bin_pi, v.bin_n, dict(v.bins)) for k, v in self.coverage.items()}
        out.drive = {k: list(v) for k, v in self.drive.items()}
        out.subcooling = list(self.subcooling)
        out._local = dict(self._local)
        out._fit_cache = None if self._fit_cache is None else dict(self._fit_cache)
        return out


def _params_stub(prior: dict):
    """A minimal object with comp_LS/comp_HS for rebuilding a learner."""
    class _P:
        comp_LS = prior["LS"]
        comp_HS = prior["HS"]
    return _P()


def with_settings(learner: CompressorLearner, **kw) -> CompressorLearner:
    return CompressorLearner.from_dict(learner.to_dict(), _params_stub(learner.prior),
                                       replace(learner.s, **kw))


def local_speed(loc, c, dl, target, pi, n0, n_lo: float, n_hi: float) -> tuple[np.ndarray, np.ndarray]:
    """The learned curves' speed search (``LearnedCompressor.speed_for_flow_v``) for the targets
    eta_vol * n = ``target`` at pressure ratios ``pi``: ``loc`` answers ``rows_at`` and
    ``value_dn_rows`` (a ``LocalCurves``, or ``model.analysis.stacked``'s tables of several
    compressors), ``c`` the global curve's six coefficients (scalars, or one array per row each),
    ``dl`` the curve differences (None, six scalars or six arrays per row). Safeguarded Newton on
    phi(n) = eta_vol(pi, n) n, continued linearly beyond the speed bounds; NaN rows where the
    scalar method raises. With ``model.analysis.speedkernel`` enabled (replay) the compiled search,
    the same numbers to the bit."""
    if speedkernel._KERNEL is not None:
        tables = getattr(loc, "kernel_tables", None)
        if tables is not None:
            tab, g = tables(len(target))
            return speedkernel.run(tab, g, c, dl, target, pi, n0, n_lo, n_hi)
    Q, in_pi = loc.rows_at(pi)
    c_rows = np.ndim(c[0]) > 0                          # one global curve per row (stacked)
    rowwise = dl is not None and np.ndim(dl[0]) > 0     # per-row draws (Flowsheet.comp)
    zp_all = (pi - _Z[0]) / _Z[1]

    def phi(rows, nn):
        """(eta_vol * n, d/dn) of rows ``rows`` at speed ratios nn (``_vol_dn_v``'s numbers)."""
        v, d, inside = loc.value_dn_rows(Q, in_pi, rows, nn, nn >= n_hi)
        if not inside.all():
            p = pi[rows]
            k = [x[rows] for x in c] if c_rows else c
            v = np.where(inside, v, k[0] + k[1] * p + k[2] * nn + k[3] * p * p + k[4] * p * nn
                         + k[5] * nn * nn)
            d = np.where(inside, d, k[2] + k[4] * p + 2.0 * k[5] * nn)
        if dl is not None:
            a = [x[rows] for x in dl] if rowwise else dl
            zp = zp_all[rows]
            zn = (nn - _Z[2]) / _Z[3]
            v = v + (a[0] + a[1] * zp + a[2] * zn + a[3] * zp * zp + a[4] * zp * zn
                     + a[5] * zn * zn)
            d = d + (a[2] + a[4] * zp + 2.0 * a[5] * zn) / _Z[3]
        return v * nn, v + nn * d

    m_rows = len(target)
    every = np.arange(m_rows)
    n = np.ones_like(target) if n0 is None else np.asarray(n0, dtype=float)
    n = np.minimum(np.maximum(n, n_lo), n_hi)                # np.clip's numbers, NaN kept
    fin = np.isfinite(n)
    if not fin.all():
        n = np.where(fin, n, 1.0)
    # both ends and the first Newton point in one call (row by row the same numbers as three)
    f_b, d_b = phi(np.concatenate([every, every, every]),
                   np.concatenate([np.full_like(target, n_lo), np.full_like(target, n_hi), n]))
    f_lo, f_hi, f_0 = f_b[:m_rows], f_b[m_rows:2 * m_rows], f_b[2 * m_rows:]
    d_lo, d_hi, d_0 = d_b[:m_rows], d_b[m_rows:2 * m_rows], d_b[2 * m_rows:]
    bad = ~((d_lo > 0.0) & (d_hi > 0.0)) | ~np.isfinite(target)   # NaN inputs: NaN out, unbisected
    above, below = target > f_hi, target < f_lo
    with np.errstate(divide="ignore", invalid="ignore"):
        n_out = np.where(above, n_hi + (target - f_hi) / d_hi, n_lo + (target - f_lo) / d_lo)
        bad |= below & ~above & ~(n_out > 0.0)
    a, b = np.full_like(target, n_lo), np.full_like(target, n_hi)
    act = np.flatnonzero(~(above | below | bad))
    first = True
    for _ in range(60):
        if not len(act):
            break
        na = n[act]
        if first:
            f, df, first = f_0[act], d_0[act], False
        else:
            f, df = phi(act, na)
        hi = f > target[act]
        b[act] = np.where(hi, na, b[act])
        a[act] = np.where(hi, a[act], na)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(df > 0, (f - target[act]) / df, 0.0)
        nn = na - step
        aa, bb = a[act], b[act]
        nn = np.where((aa <= nn) & (nn <= bb), nn, 0.5 * (aa + bb))
        n[act] = nn
        act = act[~(np.abs(nn - na) < SPEED_STEP_TOL)]
    n = np.where(above | below, n_out, n)
    with np.errstate(divide="ignore", invalid="ignore"):
        ev = target / n
    return np.where(bad, np.nan, n), np.where(bad, np.nan, ev)

