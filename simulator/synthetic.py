"""Synthetic one-minute plant history with known ("true") parameters, for tests and benchmarks.

The plant is ``model.cycle`` itself with hidden correction factors, a hidden clean pressure-drop
curve, fouling that grows while the plant runs (Kern-Seaton asymptotic law, as in the simulator),
CIP stops that remove a known share of it, daily variation of the boundary conditions, and Gaussian
sensor noise. Because the plant *is* the model (no model-form discrepancy), calibration on this data
must recover the truth to within what the noise allows; the richer plant with model-form
discrepancy is ``simulator/``.

Sensor mapping and LS controller: the simulator's own (simulator/sensors.py), with T_c at the
condenser outlet (saturated liquid at p_c), p_source_out fixed and p_source_in = p_source_out +
dp_source, W_LS/W_HS = shaft power. When the LS would need more than its maximum speed it runs there
and T_source,out floats above the set point (below it at the minimum speed). The HS speed limit is
the model's own branch switch.

This module lived in model/ until the plant emulators got one home in simulator/ (issue 8).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from model.cycle import CycleResult, ModelError
from model.fluid import get_fluid
from model.params import CycleInputs, PlantParams
from model.units import BAR, C_to_K, K_to_C, M3H, barg_to_Pa

from .sensors import LSController, sensor_values

DAY_MIN = 1440
CANONICAL = ("T_sink_in", "T_sink_out", "T_source_in", "T_source_out", "V_sink", "V_source",
             "p_source_in", "p_source_out", "T_suc_LS", "T_dis_LS", "T_suc_HS", "T_dis_HS",
             "p_suc_LS", "p_dis_LS", "p_suc_HS", "p_dis_HS", "T_c", "T_e", "W_LS", "W_HS",
             "p_m_sp", "N_LS", "N_HS", "running", "cip")
_TEMPS = ("T_sink_in", "T_sink_out", "T_source_in", "T_source_out", "T_suc_LS", "T_dis_LS",
          "T_suc_HS", "T_dis_HS", "T_c", "T_e")
_PRESSURES = ("p_source_in", "p_source_out", "p_suc_LS", "p_dis_LS", "p_suc_HS", "p_dis_HS")
_FLOWS = ("V_sink", "V_source")
_POWERS = ("W_LS", "W_HS")


@dataclass(frozen=True)
class Truth:
    """Hidden plant parameters (config units: K/kW, bar with m3/h)."""
    CF_DSH: float = 0.90
    CF_con: float = 1.06
    CF_SC: float = 1.12
    CF_eva: float = 0.93
    dp_clean_coef_bar: tuple[float, float, float] = (0.03, 0.0, 1.12e-5)   # 0.44 bar at 192 m3/h
    R_th_f_inf_K_per_kW: float = 6.0e-3      # Kern-Seaton asymptote
    tau_days: float = 6.0                    # fouling time constant (plant running time)
    CF_dp_f_inf: float = 1.4
    tau_dp_days: float = 8.0
    cip_removal_share: float = 0.15          # share of R_th,f removed by each CIP
    cip_dp_removal_share: float = 0.30       # share of (CF_dp,f - 1) removed by each CIP

    def params(self, nominal: PlantParams) -> PlantParams:
        c = self.dp_clean_coef_bar
        return nominal.replace(CF_DSH=self.CF_DSH, CF_con=self.CF_con, CF_SC=self.CF_SC,
                               CF_eva=self.CF_eva, R_th_f=0.0, CF_dp_f=1.0,
                               dp_clean_coef=(c[0] * BAR, c[1] * BAR / M3H, c[2] * BAR / M3H ** 2))


@dataclass(frozen=True)
class Noise:
    """Gaussian sensor noise: absolute on temperatures [K] and pressures [bar], relative on flows
    and powers [-]."""
    sigma_T_K: float = 0.1
    sigma_p_bar: float = 0.02
    rel_flow: float = 0.01
    rel_power: float = 0.01


@dataclass(frozen=True)
class Operation:
    """Boundary conditions and schedule.

    Daily sinusoids (peak at ``peak_hour`` UTC) around the nominal point of SPEC §2. The first
    ``commissioning_minutes`` are a site acceptance test on a clean evaporator: the source flow is
    stepped through ``commissioning_flows`` so that the clean pressure-drop curve can be fitted.
    CIPs start at ``cip_starts_h`` (hours of recorded history from its first row) and last
    ``cip_duration_h``; with ``cip_flag`` False the PLC's cip tag stays 0 (only the long stop reveals
    the CIP). ``gap_after_commissioning_days`` leaves that much running time out of the record after
    the commissioning rows (the timestamps jump, the fouling has grown meanwhile): a commissioning
    export followed by an export weeks later, without simulating the weeks in between.
    """
    start: str = "2024-03-01T00:00:00Z"
    hours: float = 24.0
    commissioning_minutes: int = 120
    commissioning_flows: tuple[float, ...] = (150.0, 170.0, 192.0, 210.0)
    T_source_in_C: float = 24.5
    T_source_in_amp_K: float = 1.0
    T_source_out_sp_C: float = 18.0
    T_sink_in_C: float = 40.0
    T_sink_in_amp_K: float = 2.0
    V_source_m3h: float = 192.0
    V_source_amp: float = 0.04
    V_sink_m3h: float = 62.0
    V_sink_amp: float = 0.10
    peak_hour: float = 15.0
    p_m_sp_barg: float = 10.0
    p_m_sp_schedule: tuple[tuple[float, float], ...] = ()   # (from hour, set point bar(g)) steps
    cip_starts_h: tuple[float, ...] = ()
    cip_duration_h: float = 48.0
    cip_flag: bool = True
    gap_after_commissioning_days: float = 0.0
    p_source_out_barg: float = 1.5


@dataclass
class SyntheticHistory:
    history: pd.DataFrame              # canonical columns (SPEC §4) + timestamp, with noise
    truth: pd.DataFrame                # per row: R_th_f_K_per_kW, CF_dp_f, running, cip, status
    cips: list[dict] = field(default_factory=list)   # start, end, R/CF before and after, shares
    params: PlantParams | None = None  # the hidden true parameters (without fouling)

    def to_csv(self, path) -> None:
        self.history.to_csv(path, index=False)


def generate(nominal: PlantParams, operation: Operation = Operation(), truth: Truth = Truth(),
             noise: Noise = Noise(), seed: int = 0, progress=None) -> SyntheticHistory:
    """One-minute history of a plant whose hidden parameters are ``truth``.

    progress : callable(done, total), optional — called every few hundred rows.
    """
    rng = np.random.default_rng(seed)
    true = truth.params(nominal)
    fluid = get_fluid(true.fluid, true.backend)
    amb = true.ambient_pressure / BAR
    n = int(round(operation.hours * 60))
    t0 = pd.Timestamp(operation.start)
    t0 = t0.tz_localize("UTC") if t0.tzinfo is None else t0.tz_convert("UTC")
    op = operation
    ncom = min(op.commissioning_minutes, n)
    offset = np.arange(n, dtype=float)
    offset[ncom:] += op.gap_after_commissioning_days * DAY_MIN
    stamps = t0 + pd.to_timedelta(offset, unit="min")
    hour_of_day = (stamps.hour + stamps.minute / 60.0).to_numpy(dtype=float)
    daily = np.cos(2.0 * math.pi * (hour_of_day - operation.peak_hour) / 24.0)
    T_src_in = op.T_source_in_C + op.T_source_in_amp_K * daily
    T_sink_in = op.T_sink_in_C - op.T_sink_in_amp_K * daily
    V_src = op.V_source_m3h * (1.0 + op.V_source_amp * daily)
    V_sink = op.V_sink_m3h * (1.0 + op.V_sink_amp * np.cos(2.0 * math.pi * (hour_of_day - 8.0) / 24.0))
    minutes = np.arange(n)
    p_sp = np.full(n, op.p_m_sp_barg)
    for from_h, sp in op.p_m_sp_schedule:
        p_sp[minutes >= from_h * 60] = sp
    # commissioning: clean plant, source flow stepped through the listed values
    steps = np.array_split(np.arange(ncom), len(op.commissioning_flows)) if ncom else []
    for idx, flow in zip(steps, op.commissioning_flows):
        V_src[idx] = flow
    # CIP schedule
    cip = np.zeros(n, dtype=bool)
    for s in op.cip_starts_h:
        a, b = int(round(s * 60)), int(round((s + op.cip_duration_h) * 60))
        cip[max(a, 0):min(b, n)] = True
    running = ~cip

    rows = {c: np.full(n, np.nan) for c in CANONICAL}
    R_true = np.zeros(n)
    CF_true = np.ones(n)
    status = np.empty(n, dtype=object)
    R, CF = 0.0, 1.0       # clean at commissioning
    tau = truth.tau_days * DAY_MIN
    tau_dp = truth.tau_dp_days * DAY_MIN
    cips: list[dict] = []
    guess: CycleResult | None = None
    ls = LSController()
    for i in range(n):
        if i > 0 and cip[i] and not cip[i - 1]:
            before = (R, CF)
            R *= 1.0 - truth.cip_removal_share
            CF = 1.0 + (CF - 1.0) * (1.0 - truth.cip_dp_removal_share)
            cips.append({"start": stamps[i], "R_th_f_before": before[0], "R_th_f_after": R,
                         "CF_dp_f_before": before[1], "CF_dp_f_after": CF,
                         "removed_pct": 100.0 * truth.cip_removal_share})
        if i > 0 and not cip[i] and cip[i - 1] and cips:
            cips[-1]["end"] = stamps[i]
        if i == ncom and op.gap_after_commissioning_days > 0:    # running time left out of the record
            g = op.gap_after_commissioning_days * DAY_MIN
            R = truth.R_th_f_inf_K_per_kW - (truth.R_th_f_inf_K_per_kW - R) * math.exp(-g / tau)
            CF = truth.CF_dp_f_inf - (truth.CF_dp_f_inf - CF) * math.exp(-g / tau_dp)
        if running[i] and i >= ncom:      # fouling grows only in operation, from the end of the SAT
            R = truth.R_th_f_inf_K_per_kW - (truth.R_th_f_inf_K_per_kW - R) * math.exp(-1.0 / tau)
            CF = truth.CF_dp_f_inf - (truth.CF_dp_f_inf - CF) * math.exp(-1.0 / tau_dp)
        R_true[i], CF_true[i] = R, CF
        rows["p_m_sp"][i] = p_sp[i]
        rows["running"][i] = float(running[i])
        rows["cip"][i] = float(cip[i] and op.cip_flag)
        if not running[i]:
            _standstill(rows, i, T_src_in[i], T_sink_in[i], fluid, amb, op)
            status[i] = "off"
            guess = None
            continue
        par = true.replace(R_th_f=R * 1e-3, CF_dp_f=CF)
        inp = CycleInputs(C_to_K(T_src_in[i]), C_to_K(op.T_source_out_sp_C), C_to_K(T_sink_in[i]),
                          V_src[i] * M3H, V_sink[i] * M3H, barg_to_Pa(p_sp[i], amb))
        try:
            res, T_out, limit = ls.solve(inp, par, guess)
        except ModelError as exc:
            status[i] = exc.reason
            _standstill(rows, i, T_src_in[i], T_sink_in[i], fluid, amb, op)
            rows["running"][i] = 0.0
            guess = None
            ls.T_out_float = None
            continue
        guess = res
        if not limit:
            ls.T_out_float = None
        status[i] = "ok" if not limit else "ls_speed_limit"
        values = sensor_values(res, T_source_in_C=T_src_in[i], T_sink_in_C=T_sink_in[i],
                               V_source_m3h=V_src[i], V_sink_m3h=V_sink[i],
                               T_source_out_C=K_to_C(T_out), ambient_bar=amb,
                               p_source_out_bar_g=op.p_source_out_barg)
        for c, v in values.items():
            rows[c][i] = v
        if progress is not None and i % 500 == 0:
            progress(i, n)
    if progress is not None:
        progress(n, n)
    hist = pd.DataFrame({"timestamp": stamps.strftime("%Y-%m-%dT%H:%M:%SZ")})
    clean = {c: rows[c].copy() for c in CANONICAL}
    for c in CANONICAL:
        v = rows[c]
        if c in _TEMPS:
            v = v + rng.normal(0.0, noise.sigma_T_K, n)
        elif c in _PRESSURES:
            v = v + rng.normal(0.0, noise.sigma_p_bar, n)
        elif c in _FLOWS:
            v = v * (1.0 + rng.normal(0.0, noise.rel_flow, n))
        elif c in _POWERS:
            v = v * (1.0 + rng.normal(0.0, noise.rel_power, n))
        hist[c] = v
    truth_frame = pd.DataFrame({
        "timestamp": hist["timestamp"], "R_th_f_K_per_kW": R_true, "CF_dp_f": CF_true,
        "running": running.astype(int), "cip": cip.astype(int), "status": status,
        "p_e_bar": clean["p_suc_LS"] + amb})
    Q = true.cp_w * true.rho_w / 3600e3 * clean["V_sink"] * (clean["T_sink_out"] - clean["T_sink_in"])
    with np.errstate(invalid="ignore", divide="ignore"):
        truth_frame["COP"] = Q / (clean["W_LS"] + clean["W_HS"])
    truth_frame["Q_sink_kW"] = Q
    return SyntheticHistory(history=hist, truth=truth_frame, cips=cips, params=true)


def _standstill(rows, i, T_src_in: float, T_sink_in: float, fluid, amb: float, op: Operation) -> None:
    """Plant stopped: no flow, no power, refrigerant pressures equalised near the source water."""
    p_eq = fluid.sat_T(C_to_K(T_src_in)).p / BAR - amb
    for c in ("T_source_in", "T_source_out", "T_suc_LS", "T_dis_LS", "T_suc_HS", "T_dis_HS", "T_c", "T_e"):
        rows[c][i] = T_src_in
    rows["T_sink_in"][i] = T_sink_in
    rows["T_sink_out"][i] = T_sink_in
    for c in ("V_sink", "V_source", "W_LS", "W_HS", "N_LS", "N_HS"):
        rows[c][i] = 0.0
    for c in ("p_suc_LS", "p_dis_LS", "p_suc_HS", "p_dis_HS"):
        rows[c][i] = p_eq
    rows["p_source_out"][i] = op.p_source_out_barg
    rows["p_source_in"][i] = op.p_source_out_barg
