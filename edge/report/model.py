"""The model's side of the report, computed with model/: the fixed model from the state documents,
per-sample fixed and adaptive values where the source does not carry them, COP against the set
point at three fouling levels, and the compressor curves in use.

``model_for_report`` is the one place that turns the plant file and the state documents into the
model the report draws (learned compressor curves join there when they exist).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .data import MODEL_INPUTS, ReportData

DEFAULT_MAX_MODEL_SAMPLES = 3000   # per-sample model values: at most this many samples (each model)
SWEEP_STEP_BAR = 0.1               # set-point resolution of the COP curves [bar]
_SIM_COLUMNS = ("Q_sink_kW", "COP", "p_e_bar", "N_LS_rpm", "N_HS_rpm")


def model_for_report(plant_params, state_docs: dict):
    """The fixed model the report draws: plant.yaml's parameters (``plant_params``, a
    PlantParams) with the initial calibration and the clean pressure-drop fit of ``state_docs``
    (keys ``initial``, ``dp_clean``, ``compressors``: dicts as stored by edge.statefiles, None
    when absent), with the learned compressor curves of ``compressors`` when it is there (as the
    analysis chain uses them). Fouling is added per window by ``with_fouling``.
    """
    from model.analysis.compressors import CompressorLearner, LearningError
    from model.calibration import apply_state

    fixed = apply_state(plant_params, state_docs.get("initial"), state_docs.get("dp_clean"))
    doc = state_docs.get("compressors")
    if doc is not None:
        try:
            fixed = CompressorLearner.from_dict(doc, plant_params).apply(fixed)
        except LearningError:
            pass        # model_notes says the curves could not be read
    return fixed


def model_notes(state_docs: dict) -> list[str]:
    """What the report's fixed model lacks, in words for the header."""
    notes = []
    if state_docs.get("initial") is None:
        notes.append("no initial calibration: the fixed model is the data sheet (plant.yaml)")
    if state_docs.get("dp_clean") is None:
        notes.append("no clean pressure-drop fit: plant.yaml's dp_clean_coef is used")
    doc = state_docs.get("compressors")
    if doc is not None:
        if isinstance(doc, dict) and doc.get("format") == "hp-edge-compressors/1":
            notes.append("the compressor curves are the ones learned from the plant's data "
                         "(compressors.json), as the analysis used them at the period's end")
        else:
            notes.append("compressors.json cannot be read: the report draws plant.yaml's curves")
    else:
        notes.append("no learned compressor curves: the report draws plant.yaml's curves")
    return notes


def with_fouling(fixed, R_th_f_K_per_kW: float, CF_dp_f: float = 1.0):
    """The adaptive model: the fixed model with a fouling calibration's two parameters."""
    from model.calibration import apply_values

    CF = CF_dp_f if CF_dp_f is not None and math.isfinite(CF_dp_f) else 1.0
    return apply_values(fixed, {"R_th_f_K_per_kW": float(R_th_f_K_per_kW), "CF_dp_f": float(CF)})


def _model_frame(samples: pd.DataFrame) -> pd.DataFrame:
    f = samples[list(MODEL_INPUTS)].copy()
    f["p_m_sp"] = samples["p_m_sp_barg"].to_numpy(dtype=float)
    return f


def window_for_samples(t: pd.Series, windows: pd.DataFrame, rule: str) -> np.ndarray:
    """Index into ``windows`` (rows with status ok, sorted by window_end) of the calibration that
    gives each sample's adaptive model; -1 where there is none.

    rule ``causal``: the latest window ending at or before the sample (the gateway's knowledge);
    rule ``containing``: the window the sample lies in, else the latest one before it (replay).
    """
    ends = windows["window_end"].to_numpy(dtype="datetime64[ns]")
    starts = windows["window_start"].to_numpy(dtype="datetime64[ns]")
    tt = pd.DatetimeIndex(t).tz_convert("UTC").tz_localize(None).to_numpy(dtype="datetime64[ns]")
    before = np.searchsorted(ends, tt, side="right") - 1
    if rule == "causal" or not len(windows):
        return before
    j = np.searchsorted(starts, tt, side="right") - 1
    inside = (j >= 0) & (tt <= ends[np.clip(j, 0, None)])
    return np.where(inside, j, before)


@dataclass
class ModelValues:
    """What ``add_model_values`` did, for the captions."""
    n_candidates: int = 0            # usable samples with every model input
    n_simulated: int = 0
    step: int = 1                    # every step-th candidate was simulated
    n_without_calibration: int = 0   # simulated samples with no calibration before them
    notes: list[str] = field(default_factory=list)

    @property
    def caption(self) -> str:
        if self.n_simulated == 0:
            return ""
        txt = (f"model values on one usable sample in {self.step} ({self.n_simulated} of "
               f"{self.n_candidates}, to bound the report's run time)" if self.step > 1 else
               f"model values on all {self.n_simulated} usable samples")
        return txt


def add_model_values(data: ReportData, fixed, max_samples: int = DEFAULT_MAX_MODEL_SAMPLES) -> ModelValues:
    """Fill the per-sample fixed- and adaptive-model columns (COP, Q_sink, p_e) and the model's
    compressor speeds of ``data.samples`` in place, on at most ``max_samples`` usable samples
    (evenly subsampled). The adaptive model of a sample follows ``data.adaptive_rule``."""
    from model.batch import simulate_batch, solved_mask

    mv = ModelValues()
    s = data.samples
    if s is None or not len(s):
        return mv
    inputs = _model_frame(s)
    cand = np.flatnonzero((s["usable"].to_numpy(dtype=float) > 0.5)
                          & np.isfinite(inputs.to_numpy(dtype=float)).all(axis=1))
    mv.n_candidates = len(cand)
    if not len(cand):
        mv.notes.append("no usable sample carries every model input: no model values")
        return mv
    mv.step = max(1, math.ceil(len(cand) / max(1, int(max_samples))))
    rows = cand[:: mv.step]
    mv.n_simulated = len(rows)
    frame = inputs.iloc[rows]
    out = {c: np.full(len(s), np.nan) for c in
           ("COP_fixed", "Q_sink_kW_fixed", "p_e_bar_fixed", "COP_adaptive", "Q_sink_kW_adaptive",
            "p_e_bar_adaptive", "N_LS_model", "N_HS_model")}
    fx = simulate_batch(frame, fixed, columns=_SIM_COLUMNS)
    ok = solved_mask(fx)
    for src, dst in (("COP", "COP_fixed"), ("Q_sink_kW", "Q_sink_kW_fixed"),
                     ("p_e_bar", "p_e_bar_fixed"), ("N_LS_rpm", "N_LS_model"),
                     ("N_HS_rpm", "N_HS_model")):
        out[dst][rows[ok]] = fx[src].to_numpy(dtype=float)[ok]
    w = data.windows
    w = w[w["status"] == "ok"].dropna(subset=["R_th_f_K_per_kW"]).sort_values("window_end")
    w = w.reset_index(drop=True)
    which = window_for_samples(s["timestamp"].iloc[rows], w,
                               "causal" if data.kind == "gateway" else "containing")
    mv.n_without_calibration = int((which < 0).sum())
    for j in np.unique(which[which >= 0]):
        sel = which == j
        adaptive = with_fouling(fixed, w.at[j, "R_th_f_K_per_kW"], w.at[j, "CF_dp_f"])
        ad = simulate_batch(frame.iloc[np.flatnonzero(sel)], adaptive, columns=_SIM_COLUMNS)
        okj = solved_mask(ad)
        idx = rows[sel][okj]
        for src, dst in (("COP", "COP_adaptive"), ("Q_sink_kW", "Q_sink_kW_adaptive"),
                         ("p_e_bar", "p_e_bar_adaptive")):
            out[dst][idx] = ad[src].to_numpy(dtype=float)[okj]
    for c, v in out.items():
        s[c] = v
    if mv.n_without_calibration:
        mv.notes.append(f"{mv.n_without_calibration} simulated samples lie before the first "
                        "calibration of the period: they have no adaptive-model value")
    return mv


def add_eta_model(data: ReportData, fixed) -> None:
    """eta_is_LS_model / eta_is_HS_model where missing: the curve in use at each sample's measured
    pressure ratio and speed (measured speed, else the fixed model's)."""
    s = data.samples
    if s is None or not len(s):
        return
    for stage, comp in (("LS", fixed.comp_LS), ("HS", fixed.comp_HS)):
        col = f"eta_is_{stage}_model"
        have = s[col].to_numpy(dtype=float)
        if np.isfinite(have).any():
            continue
        N = s[f"N_{stage}_rpm"].to_numpy(dtype=float)
        if f"N_{stage}_model" in s.columns:
            N = np.where(np.isfinite(N) & (N > 0), N, s[f"N_{stage}_model"].to_numpy(dtype=float))
        pi = s[f"pi_{stage}"].to_numpy(dtype=float)
        n = N / comp.N_nom
        usable = s["usable"].to_numpy(dtype=float) > 0.5
        good = usable & np.isfinite(pi) & np.isfinite(n) & (n > 0)
        eta = np.full(len(s), np.nan)
        eta[good] = [comp.eta_is_at(float(p), float(x)) for p, x in zip(pi[good], n[good])]
        s[col] = eta


def speeds_for_curves(data: ReportData, fixed, stage: str) -> tuple[np.ndarray, str]:
    """Speeds [rpm] at which to draw the curve in use: the 10th, 50th and 90th percentile of the
    period's speeds (measured, else the model's), else the nominal speed."""
    comp = fixed.comp_LS if stage == "LS" else fixed.comp_HS
    s = data.samples
    if s is not None and len(s):
        usable = s["usable"].to_numpy(dtype=float) > 0.5
        for col, what in ((f"N_{stage}_rpm", "measured"), (f"N_{stage}_model", "model")):
            if col in s.columns:
                N = s[col].to_numpy(dtype=float)[usable]
                N = N[np.isfinite(N) & (N > 0)]
                if len(N) >= 3:
                    return np.unique(np.round(np.percentile(N, [10, 50, 90]), -1)), what
    return np.array([comp.N_nom]), "nominal"


# --------------------------------------------------------------------------- COP vs set point


def representative_point(data: ReportData) -> dict | None:
    """Median boundary conditions (and set point) of the period's usable samples, or None."""
    s = data.samples
    if s is None or not len(s):
        return None
    usable = s["usable"].to_numpy(dtype=float) > 0.5
    cols = list(MODEL_INPUTS) + ["p_m_sp_barg"]
    sub = s.loc[usable, cols].apply(pd.to_numeric, errors="coerce").dropna()
    if not len(sub):
        return None
    med = sub.median()
    return {"T_source_in": float(med["T_source_in"]), "T_source_out": float(med["T_source_out"]),
            "T_sink_in": float(med["T_sink_in"]), "V_source": float(med["V_source"]),
            "V_sink": float(med["V_sink"]), "p_m_sp": float(med["p_m_sp_barg"]),
            "n_samples": int(len(sub))}


def fouling_levels(windows: pd.DataFrame) -> list[tuple[str, float, float]]:
    """(label, R_th_f [K/kW], CF_dp_f): clean, the period's median and its highest R_th,f."""
    levels = [("clean", 0.0, 1.0)]
    ok = windows[(windows["status"] == "ok")].dropna(subset=["R_th_f_K_per_kW"])
    if len(ok):
        R = ok["R_th_f_K_per_kW"].to_numpy(dtype=float)
        CF = ok["CF_dp_f"].to_numpy(dtype=float)
        i_med = int(np.argsort(R)[(len(R) - 1) // 2])
        i_max = int(np.argmax(R))
        levels.append(("median of the period", float(R[i_med]), float(CF[i_med])))
        if i_max != i_med:
            levels.append(("highest of the period", float(R[i_max]), float(CF[i_max])))
    return levels


@dataclass
class CopCurve:
    label: str
    R_th_f_K_per_kW: float
    p_m_sp_barg: np.ndarray           # swept set points [bar(g)]
    COP: np.ndarray                   # NaN where the model has no solution
    p_m_sp_opt_barg: float = math.nan
    COP_opt: float = math.nan
    p_m_gm_barg: float = math.nan
    COP_gm: float = math.nan
    hs_saturated_opt: bool = False
    note: str = ""


def cop_curves(fixed, point: dict, levels, step: float = SWEEP_STEP_BAR) -> list[CopCurve]:
    """COP against p_m,sp at ``point`` for each fouling level: the model's curve
    (model.batch.simulate_batch with a set-point override) and its optimum
    (model.optimize.optimize_setpoint, which also handles the HS-speed plateau)."""
    from model.batch import simulate_batch, solved_mask
    from model.optimize import OptimizationError, optimize_setpoint

    amb = fixed.ambient_pressure / 1e5
    row = pd.DataFrame([{k: point[k] for k in (*MODEL_INPUTS, "p_m_sp")}])
    curves = []
    for label, R, CF in levels:
        params = with_fouling(fixed, R, CF)
        try:
            opt = optimize_setpoint(row, params)
        except OptimizationError as exc:
            curves.append(CopCurve(label, R, np.array([]), np.array([]), note=str(exc)))
            continue
        lo, hi = opt.bounds_barg
        grid = np.arange(lo, hi + 1e-9, step)
        rep = pd.concat([row] * len(grid), ignore_index=True)
        sim = simulate_batch(rep, params, p_m_sp=grid, columns=("COP",))
        cop = np.where(solved_mask(sim), sim["COP"].to_numpy(dtype=float), np.nan)
        curves.append(CopCurve(label, R, grid, cop, p_m_sp_opt_barg=opt.p_m_sp_opt_barg,
                               COP_opt=opt.COP_opt, p_m_gm_barg=opt.p_m_gm_bar_a - amb,
                               COP_gm=opt.COP_gm, hs_saturated_opt=opt.hs_saturated))
    return curves
