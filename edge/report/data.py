"""Every data access of the report, in one place: a replay directory or the gateway's history
database with its state directory -> one ``ReportData`` in the report's own column names.

The report's names are those of the replay output contract (windows.csv, cip.csv, forecast.csv,
samples.csv; units in the names, %, bar(g)). Older or gateway-side names are mapped here and only
here (``WINDOW_ALIASES``, ``CIP_ALIASES``, ``ADVICE_TO_WINDOW``, ``MEASURED_TO_SAMPLE``), so a
renamed column is one line to adapt. A missing optional file or column is not an error: the field
stays empty (NaN / None) and a note says what was missing; the figure that needs it says "not
available" and why.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from edge import statefiles

# --------------------------------------------------------------------------- the report's columns

WINDOW_COLUMNS = (
    "window_start", "window_end", "n_samples", "status", "R_th_f_K_per_kW", "R_th_f_se_K_per_kW",
    "R_th_f_share_pct", "CF_dp_f", "CF_dp_f_se", "dp_fouling_bar", "nrmse_p_e", "nrmse_dp_source",
    "nrmse_COP_fixed", "nrmse_COP_adaptive", "nrmse_Q_sink_fixed", "nrmse_Q_sink_adaptive",
    "COP_measured", "COP_fixed", "COP_adaptive", "p_m_sp_actual_barg", "p_m_sp_opt_barg",
    "p_m_gm_barg", "p_m_opt_barg", "dCOP_opt_pct", "dCOP_opt_sd_pct", "dQ_sink_opt_pct",
    "dCOP_gm_pct", "dQ_sink_gm_pct", "advice_confident", "advice_note", "hs_saturated_opt",
    "calibration_warnings", "eta_is_LS_drift_pct", "eta_is_HS_drift_pct")
CIP_COLUMNS = ("cip_start", "cip_end", "duration_h", "detected_by", "R_th_f_before_K_per_kW",
               "R_th_f_after_K_per_kW", "R_th_f_removed_pct", "CF_dp_f_before", "CF_dp_f_after")
FORECAST_COLUMNS = ("window_end", "forecast_at", "R_th_f_forecast_K_per_kW",
                    "R_th_f_forecast_lo_K_per_kW", "R_th_f_forecast_hi_K_per_kW",
                    "fouling_rate_K_per_kW_per_day", "fouling_cost_eur_per_day",
                    "days_to_recommended_cip")
MODEL_INPUTS = ("T_source_in", "T_source_out", "T_sink_in", "V_source", "V_sink")
SAMPLE_COLUMNS = (
    "timestamp", "usable", "reason", "window_start", "COP_measured", "COP_fixed", "COP_adaptive",
    "Q_sink_kW_measured", "Q_sink_kW_fixed", "Q_sink_kW_adaptive", "p_e_bar_measured",
    "p_e_bar_fixed", "p_e_bar_adaptive", "eta_is_LS_meas", "eta_is_HS_meas", "eta_is_LS_model",
    "eta_is_HS_model", "pi_LS", "pi_HS", "N_LS_rpm", "N_HS_rpm", "p_m_sp_barg") + MODEL_INPUTS
MODEL_COLUMNS = ("COP_fixed", "COP_adaptive", "Q_sink_kW_fixed", "Q_sink_kW_adaptive",
                 "p_e_bar_fixed", "p_e_bar_adaptive")
TIME_COLUMNS = {"window_start", "window_end", "cip_start", "cip_end", "forecast_at", "timestamp"}

# (report column) -> [(column in the file, how to convert: "pct" fraction -> %, "gauge" bar a -> bar(g))]
WINDOW_ALIASES = {
    "R_th_f_share_pct": [("R_th_f_share_pct", None), ("R_th_f_share", "pct")],
    "p_m_gm_barg": [("p_m_gm_barg", None), ("p_m_gm_bar_a", "gauge")],
    "p_m_opt_barg": [("p_m_opt_barg", None), ("p_m_opt_bar_a", "gauge")],
}
CIP_ALIASES = {
    "R_th_f_before_K_per_kW": [("R_th_f_before_K_per_kW", None), ("R_th_f_before", None)],
    "R_th_f_after_K_per_kW": [("R_th_f_after_K_per_kW", None), ("R_th_f_after", None)],
}
# gateway advice table field -> report window column (edge/service.py's advisory values)
ADVICE_TO_WINDOW = {
    "R_th_f": "R_th_f_K_per_kW", "R_th_f_share": "R_th_f_share_pct", "CF_dp_f": "CF_dp_f",
    "dp_fouling": "dp_fouling_bar", "p_m_sp_rec": "p_m_sp_opt_barg", "p_m_gm": "p_m_gm_barg",
    "dCOP_pct": "dCOP_opt_pct", "dQ_sink_pct": "dQ_sink_opt_pct", "COP_measured": "COP_measured",
    "COP_adaptive": "COP_adaptive", "COP_fixed": "COP_fixed", "dCOP_sd_pct": "dCOP_opt_sd_pct",
    "dCOP_opt_sd_pct": "dCOP_opt_sd_pct", "advice_confident": "advice_confident",
    "advice_note": "advice_note", "p_m_opt": "p_m_opt_barg",
}
# measured-side column (model.measured.process and the tag map, as the gateway stores them and
# as process() returns them for a history CSV) -> report sample column
MEASURED_TO_SAMPLE = {
    "COP": "COP_measured", "Q_sink_kW": "Q_sink_kW_measured", "p_e_bar": "p_e_bar_measured",
    "eta_is_LS_meas": "eta_is_LS_meas", "eta_is_HS_meas": "eta_is_HS_meas", "pi_LS": "pi_LS",
    "pi_HS": "pi_HS", "N_LS": "N_LS_rpm", "N_HS": "N_HS_rpm", "p_m_sp": "p_m_sp_barg",
    "usable": "usable", "reason": "reason", **{c: c for c in MODEL_INPUTS},
}
STATE_DOCS = {"initial": statefiles.INITIAL_CALIBRATION, "dp_clean": statefiles.DP_CLEAN,
              "fouling": statefiles.FOULING_CALIBRATION, "compressors": "compressors.json"}


class ReportSourceError(ValueError):
    """The report's source cannot be read; the message names the file."""


@dataclass
class ReportData:
    """What the report shows, in the report's column names (see the module docstring).

    windows : one row per calibration window (replay) or advice (gateway), WINDOW_COLUMNS
    cips : CIP_COLUMNS; forecast : FORECAST_COLUMNS or None; samples : SAMPLE_COLUMNS or None
    state : the state documents (initial, dp_clean, fouling, compressors), None when absent
    coverage : {n_rows, n_usable, unusable: {reason: n}, scope: text} or None
    """
    kind: str                              # "replay" | "gateway"
    source: str                            # what was read, for the header
    plant: str                             # plant file (or meta.json's plant)
    params: object                         # model.params.PlantParams of the plant file
    period: tuple[pd.Timestamp | None, pd.Timestamp | None]
    windows: pd.DataFrame
    cips: pd.DataFrame
    forecast: pd.DataFrame | None
    samples: pd.DataFrame | None
    state: dict[str, dict | None]
    coverage: dict | None
    window_hours: float
    adaptive_rule: str                     # how the per-sample adaptive model is chosen
    meta: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    recomputed_samples: bool = False       # per-sample model values computed by the report


# --------------------------------------------------------------------------- helpers


def utc(t) -> pd.Timestamp | None:
    """ISO 8601 text / Timestamp -> UTC Timestamp (UTC when naive); None stays None."""
    if t is None or (isinstance(t, float) and math.isnan(t)):
        return None
    ts = pd.Timestamp(t)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def _times(s: pd.Series) -> pd.Series:
    return pd.to_datetime(s, utc=True, errors="coerce", format="ISO8601")


def _bool(s: pd.Series) -> pd.Series:
    """true/false, 1/0, True/False text -> float 1.0/0.0 (NaN when unknown)."""
    def one(v):
        if isinstance(v, (bool, np.bool_)):
            return float(v)
        if isinstance(v, (int, float, np.integer, np.floating)):
            return float(v) if math.isfinite(v) else math.nan
        t = str(v).strip().lower()
        return 1.0 if t in ("true", "1", "yes") else 0.0 if t in ("false", "0", "no") else math.nan
    return s.map(one).astype(float)


def _normalise(df: pd.DataFrame, columns, aliases: dict, ambient_bar: float, what: str,
               notes: list[str], optional: set[str]) -> pd.DataFrame:
    """``df`` with exactly ``columns`` (aliases resolved, times parsed, absent ones NaN)."""
    out = pd.DataFrame(index=df.index)
    absent = []
    for c in columns:
        candidates = aliases.get(c, [(c, None)])
        for src, conv in candidates:
            if src in df.columns:
                v = df[src]
                if conv == "pct":
                    v = 100.0 * pd.to_numeric(v, errors="coerce")
                elif conv == "gauge":
                    v = pd.to_numeric(v, errors="coerce") - ambient_bar
                out[c] = v
                break
        else:
            out[c] = math.nan
            absent.append(c)
    for c in columns:
        if c in TIME_COLUMNS:
            out[c] = _times(out[c])
        elif c in ("advice_confident", "hs_saturated_opt", "usable"):
            out[c] = _bool(out[c])
        elif c in ("status", "detected_by", "calibration_warnings", "advice_note", "reason"):
            out[c] = out[c].map(lambda v: "" if pd.isna(v) else str(v)).astype(str)
        else:
            out[c] = pd.to_numeric(out[c], errors="coerce")
    missing = [c for c in absent if c not in optional]
    if missing and len(df):
        notes.append(f"{what} has no column(s) {', '.join(missing)}")
    return out.reset_index(drop=True)


def _read_csv(path: Path) -> pd.DataFrame | None:
    if not path.exists():
        return None
    try:
        return pd.read_csv(path, keep_default_na=True)
    except pd.errors.EmptyDataError:
        return pd.DataFrame()
    except (OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise ReportSourceError(f"{path}: cannot read as CSV: {exc}") from None


def read_state_docs(state_dir: Path) -> dict[str, dict | None]:
    docs = {}
    for key, name in STATE_DOCS.items():
        try:
            docs[key] = statefiles.read_state(name, state_dir)
        except statefiles.StateError as exc:
            raise ReportSourceError(str(exc)) from None
    return docs


def _in_period(t: pd.Series, start, end) -> np.ndarray:
    m = np.ones(len(t), dtype=bool)
    if start is not None:
        m &= (t >= start).to_numpy()
    if end is not None:
        m &= (t <= end).to_numpy()
    return m


def _coverage_from_samples(samples: pd.DataFrame, scope: str) -> dict:
    ok = samples["usable"].to_numpy(dtype=float) > 0.5
    reasons = samples.loc[~ok, "reason"].astype(str).str.replace(r"[=:].*$", "", regex=True)
    counts = {str(k) or "unknown": int(v) for k, v in reasons.value_counts().items()}
    return {"n_rows": int(len(samples)), "n_usable": int(ok.sum()), "unusable": counts,
            "scope": scope}


def samples_from_measured(frame: pd.DataFrame, ts: pd.DatetimeIndex | pd.Series) -> pd.DataFrame:
    """Tag + derived columns (model.measured.process names, as stored by the gateway) -> the
    report's sample columns. Model columns stay NaN (``edge.report.model`` fills them)."""
    out = pd.DataFrame({"timestamp": pd.DatetimeIndex(ts)})
    for src, dst in MEASURED_TO_SAMPLE.items():
        out[dst] = frame[src].to_numpy() if src in frame.columns else math.nan
    for c in SAMPLE_COLUMNS:
        if c not in out.columns:
            out[c] = math.nan
    out["usable"] = _bool(out["usable"])
    out["reason"] = out["reason"].map(lambda v: "" if pd.isna(v) else str(v)).astype(str)
    out["window_start"] = pd.NaT
    return out[list(SAMPLE_COLUMNS)]


# --------------------------------------------------------------------------- replay directory


def load_replay(directory: str | Path, params, plant: str, start=None, end=None,
                history_csv: str | Path | None = None) -> ReportData:
    """A replay output directory (``hp-edge replay --out DIR``), optionally with the history CSV
    it was made from (for per-sample values when DIR has no samples.csv)."""
    d = Path(directory)
    if not d.is_dir():
        raise ReportSourceError(f"{d}: not a directory (expected the output of hp-edge replay)")
    notes: list[str] = []
    amb = params.ambient_pressure / 1e5
    raw_w = _read_csv(d / "windows.csv")
    if raw_w is None:
        raise ReportSourceError(f"{d}: no windows.csv (not a replay output directory)")
    windows = _normalise(raw_w, WINDOW_COLUMNS, WINDOW_ALIASES, amb, "windows.csv", notes,
                         optional={"dCOP_opt_sd_pct", "advice_confident", "advice_note",
                                   "eta_is_LS_drift_pct", "eta_is_HS_drift_pct", "p_m_opt_barg"})
    raw_c = _read_csv(d / "cip.csv")
    if raw_c is None:
        notes.append("no cip.csv: no CIP table")
        raw_c = pd.DataFrame()
    cips = _normalise(raw_c, CIP_COLUMNS, CIP_ALIASES, amb, "cip.csv", notes, optional=set())
    raw_f = _read_csv(d / "forecast.csv")
    forecast = (None if raw_f is None else
                _normalise(raw_f, FORECAST_COLUMNS, {}, amb, "forecast.csv", notes, optional=set()))
    meta = {}
    if (d / "meta.json").exists():
        try:
            meta = json.loads((d / "meta.json").read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            notes.append(f"meta.json unreadable ({exc}): header from the other files")
            meta = {}
    state = read_state_docs(d)
    samples = None
    raw_s = _read_csv(d / "samples.csv")
    coverage = None
    if raw_s is not None:
        samples = _normalise(raw_s, SAMPLE_COLUMNS, {}, amb, "samples.csv", notes,
                             optional=set(MODEL_INPUTS) | {"N_LS_rpm", "N_HS_rpm"})
    elif history_csv is not None:
        samples = _samples_from_csv(history_csv, params, state)
        notes.append(f"per-sample values from {history_csv} (measured side recomputed, model "
                     "values computed by the report)")
    else:
        notes.append("no samples.csv and no --data history CSV: no per-sample figures (time "
                     "series, residuals, compressors) and no representative operating point")
    if samples is not None and history_csv is not None and raw_s is not None:
        # samples.csv lacks the boundary conditions: take them from the history CSV
        if samples[list(MODEL_INPUTS)].isna().all().all():
            extra = _samples_from_csv(history_csv, params, state)
            samples = samples.merge(extra[["timestamp", *MODEL_INPUTS]], on="timestamp",
                                    how="left", suffixes=("_x", ""))
            samples = samples.drop(columns=[c + "_x" for c in MODEL_INPUTS])
    start, end = utc(start), utc(end)
    windows = windows[_in_period(windows["window_end"], start, end)].reset_index(drop=True)
    cips = cips[_in_period(cips["cip_end"], start, None) & _in_period(cips["cip_start"], None, end)]
    cips = cips.reset_index(drop=True)
    if forecast is not None:
        forecast = forecast[_in_period(forecast["window_end"], start, end)].reset_index(drop=True)
    if samples is not None:
        samples = samples[_in_period(samples["timestamp"], start, end)].reset_index(drop=True)
        coverage = _coverage_from_samples(samples, "samples of the period")
    elif meta.get("n_rows") is not None:
        coverage = {"n_rows": int(meta["n_rows"]), "n_usable": int(meta.get("n_usable", 0)),
                    "unusable": dict(meta.get("unusable") or {}),
                    "scope": "the whole replay (meta.json)"}
    else:
        notes.append("no meta.json and no samples: data coverage unknown")
    settings = meta.get("settings") or {}
    return ReportData(
        kind="replay", source=f"replay directory {d}", plant=str(meta.get("plant") or plant),
        params=params, period=_period(start, end, samples, windows, meta), windows=windows,
        cips=cips, forecast=forecast, samples=samples, state=state, coverage=coverage,
        window_hours=float(settings.get("window_hours", 2.0)),
        adaptive_rule="the calibration of the window the sample belongs to (else the latest "
                      "window before it)",
        meta=meta, notes=notes, recomputed_samples=raw_s is None and samples is not None)


def _samples_from_csv(path, params, state) -> pd.DataFrame:
    from model.calibration import apply_state
    from model.measured import process

    from edge.commands.analysis_cmds import CommandError, read_history_csv
    try:
        hist, _, _ = read_history_csv(path)
    except CommandError as exc:
        raise ReportSourceError(str(exc)) from None
    fixed = apply_state(params, state.get("initial"), state.get("dp_clean"))
    processed = process(hist, fixed)
    frame = pd.concat([hist.drop(columns=["timestamp"]), processed], axis=1)
    frame = frame.loc[:, ~frame.columns.duplicated(keep="last")]
    return samples_from_measured(frame, hist["timestamp"])


def _period(start, end, samples, windows, meta):
    if start is not None and end is not None:
        return start, end
    lo, hi = [], []
    if samples is not None and len(samples):
        lo.append(samples["timestamp"].min())
        hi.append(samples["timestamp"].max())
    if len(windows):
        lo.append(windows["window_start"].min())
        hi.append(windows["window_end"].max())
    if meta.get("period_start"):
        lo.append(utc(meta["period_start"]))
    if meta.get("period_end"):
        hi.append(utc(meta["period_end"]))
    lo = [t for t in lo if t is not None and not pd.isna(t)]
    hi = [t for t in hi if t is not None and not pd.isna(t)]
    return (start if start is not None else (min(lo) if lo else None),
            end if end is not None else (max(hi) if hi else None))


# --------------------------------------------------------------------------- gateway history


def load_gateway(history_db: str | Path, state_dir: str | Path, params, plant: str, start=None,
                 end=None, window_hours: float = 2.0, cip_off_minutes: float = 360.0,
                 ranges: dict | None = None) -> ReportData:
    """The gateway's history database (samples and advice tables) and its state directory."""
    from edge.io.historydb import HistoryDbError, read_table, utc_index
    from model.analysis.replay import detect_cips

    notes: list[str] = []
    start, end = utc(start), utc(end)
    try:
        raw = read_table(history_db, "samples", start, end)
        adv = read_table(history_db, "advice", start, end)
    except HistoryDbError as exc:
        raise ReportSourceError(str(exc)) from None
    sd = Path(state_dir)
    if sd.exists() and not sd.is_dir():
        raise ReportSourceError(f"{sd}: not a directory (expected the gateway's state directory)")
    if not sd.exists():
        notes.append(f"no state directory {sd}: no calibration state (as a gateway that was never "
                     "commissioned)")
    state = read_state_docs(sd)
    ts = utc_index(raw["ts"]) if len(raw) else pd.DatetimeIndex([], tz="UTC")
    samples = samples_from_measured(raw, ts)
    if len(raw) and "usable" not in raw.columns:
        raise ReportSourceError(f"{history_db}: samples have no 'usable' column (not a gateway "
                                "history)")
    windows = _windows_from_advice(adv, window_hours, params.ambient_pressure / 1e5, notes)
    # CIPs: the replay's rule (model.analysis.replay.detect_cips) on the stored usable/reason and cip flag
    cip_rows = []
    if len(raw):
        cip_flag = (pd.to_numeric(raw["cip"], errors="coerce").fillna(0).to_numpy() > 0.5
                    if "cip" in raw.columns else None)
        processed = pd.DataFrame({"reason": samples["reason"].str.split(":").str[0]})
        for c in detect_cips(ts, processed, cip_flag, cip_off_minutes):
            cip_rows.append(_cip_effect(c, windows))
    cips = pd.DataFrame(cip_rows, columns=list(CIP_COLUMNS))
    if len(cips):
        for c in ("cip_start", "cip_end"):
            cips[c] = _times(cips[c])
    forecast = _forecast_from_advice(adv, params.ambient_pressure / 1e5, notes)
    if forecast is None:
        notes.append("the gateway's advice rows carry no fouling forecast (none written in the "
                     "period yet, or a gateway from before issue 10): no forecast in this report")
    elif not forecast["R_th_f_forecast_K_per_kW"].notna().any():
        notes.append("no fouling forecast in the period yet (it needs a day of windows since the "
                     "last CIP or commissioning)")
    coverage = _coverage_from_samples(samples, "samples of the period") if len(samples) else None
    if coverage is None:
        notes.append("no samples in the period")
    return ReportData(
        kind="gateway", source=f"gateway history {history_db}, state {sd}", plant=plant,
        params=params, period=_period(start, end, samples, windows, {}), windows=windows,
        cips=cips, forecast=forecast, samples=samples if len(samples) else None, state=state,
        coverage=coverage, window_hours=window_hours,
        adaptive_rule="the latest advice at or before the sample (what the gateway knew then)",
        notes=notes, recomputed_samples=True)


def _forecast_from_advice(adv: pd.DataFrame, ambient_bar: float, notes: list[str]) -> pd.DataFrame | None:
    """The forecast rows (FORECAST_COLUMNS, as replay's forecast.csv) from the window row each
    advice record of the gateway keeps (``detail["window"]``, the windows.csv row of that window);
    None when no record has them."""
    rows = []
    for rec in adv.to_dict("records"):
        w = (rec.get("detail") or {}).get("window") or {}
        if all(k in w for k in FORECAST_COLUMNS):
            rows.append({k: w[k] for k in FORECAST_COLUMNS})
    if not rows:
        return None
    return _normalise(pd.DataFrame(rows), FORECAST_COLUMNS, {}, ambient_bar, "the advice table",
                      notes, optional=set())


def _windows_from_advice(adv: pd.DataFrame, window_hours: float, ambient_bar: float,
                         notes: list[str]) -> pd.DataFrame:
    rows = []
    for rec in adv.to_dict("records"):
        detail = rec.get("detail") or {}
        cal = detail.get("calibration") or {}
        opt = detail.get("optimization") or {}
        end = pd.Timestamp(float(rec["ts"]), unit="s", tz="UTC")
        row = {c: math.nan for c in WINDOW_COLUMNS}
        row["window_end"] = end
        start = utc(cal.get("window_start"))
        if start is None or not end - pd.Timedelta(hours=2 * window_hours) <= start <= end:
            start = end - pd.Timedelta(hours=window_hours)   # not recorded, or not this advice's
        row["window_start"] = start
        for src, dst in ADVICE_TO_WINDOW.items():
            if src in rec and rec[src] is not None:
                row[dst] = rec[src]
        ok = rec.get("ok")
        row["status"] = "ok" if ok in (1, True) else f"failed: {rec.get('message') or 'no advice'}"
        se = cal.get("std_errors") or {}
        row["R_th_f_se_K_per_kW"] = se.get("R_th_f_K_per_kW")
        row["CF_dp_f_se"] = se.get("CF_dp_f")
        nr = cal.get("nrmse") or {}
        row["nrmse_p_e"], row["nrmse_dp_source"] = nr.get("p_e"), nr.get("dp_source")
        row["n_samples"] = detail.get("n_samples", cal.get("n_samples"))
        row["calibration_warnings"] = "; ".join(cal.get("warnings") or [])
        row["p_m_sp_actual_barg"] = opt.get("p_m_sp_actual_barg")
        row["hs_saturated_opt"] = opt.get("hs_saturated")
        if opt.get("p_m_opt_bar_a") is not None and not _finite(row["p_m_opt_barg"]):
            row["p_m_opt_barg"] = opt["p_m_opt_bar_a"] - ambient_bar
        for k in ("dCOP_gm_pct", "dQ_sink_gm_pct"):
            row[k] = opt.get(k)
        rows.append(row)
    frame = pd.DataFrame(rows, columns=list(WINDOW_COLUMNS))
    return _normalise(frame, WINDOW_COLUMNS, {}, 0.0, "advice", notes,
                      optional=set(WINDOW_COLUMNS))


def _cip_effect(c: dict, windows: pd.DataFrame) -> dict:
    """R_th,f and CF_dp,f of the last good window before a CIP and the first after it."""
    ok = windows[windows["status"] == "ok"]
    before = ok[(ok["window_end"] <= c["start"]).to_numpy()].tail(1)
    after = ok[(ok["window_start"] >= c["end"]).to_numpy()].head(1)
    Rb = float(before["R_th_f_K_per_kW"].iloc[0]) if len(before) else math.nan
    Ra = float(after["R_th_f_K_per_kW"].iloc[0]) if len(after) else math.nan
    return {"cip_start": c["start"], "cip_end": c["end"], "duration_h": c["duration_h"],
            "detected_by": c["detected_by"], "R_th_f_before_K_per_kW": Rb,
            "R_th_f_after_K_per_kW": Ra,
            "R_th_f_removed_pct": 100.0 * (Rb - Ra) / Rb if Rb > 0 else math.nan,
            "CF_dp_f_before": float(before["CF_dp_f"].iloc[0]) if len(before) else math.nan,
            "CF_dp_f_after": float(after["CF_dp_f"].iloc[0]) if len(after) else math.nan}


def _finite(v) -> bool:
    try:
        return math.isfinite(float(v))
    except (TypeError, ValueError):
        return False
