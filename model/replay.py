"""Replay of a plant history: the papers' analysis, reproducible for any plant (SPEC §5-6).

``replay(history, params)`` is a pure function over DataFrames:

1. measured-side processing (``model.measured.process``): derived quantities and a usable flag with
   a reason per sample (unusable samples are counted per reason, never silently dropped);
2. initial calibration (CF_DSH, CF_con, CF_SC, CF_eva) and the clean pressure-drop fit on the initial
   window: by default the first ``initial_minutes`` usable minutes (commissioning data). Their result
   is the **fixed model**;
3. CIP periods: runs of samples with the cip flag, or plant stops longer than ``cip_off_minutes``;
4. per window of usable operation (each stretch of operation between CIPs is tiled evenly with
   windows of about ``window_hours``, so windows never straddle a CIP and the windows next to one
   touch it): the fouling
   calibration (R_th,f, CF_dp,f) on the fixed model -> the **adaptive model**; NRMSE of COP and heat
   output of both models; the set-point optimization with the adaptive model;
5. per CIP: R_th,f and CF_dp,f of the windows just before and just after, and the removed share.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .batch import simulate_batch, solved_mask
from .calibration import (CalibrationError, CalibrationResult, calibrate, calibration_frame,
                          evaporator_share, spec_from_config)
from .dpfit import DpCleanFit, DpFitError, fit_dp_clean
from .measured import process, usable_counts
from .optimize import OptimizationError, optimize_setpoint
from .params import PlantParams
from .units import BAR, M3H

WINDOW_COLUMNS = (
    "window_start", "window_end", "n_samples", "R_th_f_K_per_kW", "R_th_f_se_K_per_kW", "R_th_f_share",
    "CF_dp_f", "CF_dp_f_se", "dp_fouling_bar", "nrmse_p_e", "nrmse_dp_source", "nrmse_COP_fixed",
    "nrmse_COP_adaptive", "nrmse_Q_sink_fixed", "nrmse_Q_sink_adaptive", "COP_measured",
    "COP_fixed", "COP_adaptive", "p_m_sp_actual_barg", "p_m_sp_opt_barg", "p_m_opt_bar_a",
    "p_m_gm_bar_a", "dCOP_opt_pct", "dQ_sink_opt_pct", "dCOP_gm_pct", "dQ_sink_gm_pct",
    "hs_saturated_opt", "calibration_warnings", "status")
CIP_COLUMNS = ("cip_start", "cip_end", "duration_h", "detected_by", "R_th_f_before", "R_th_f_after",
               "R_th_f_removed_pct", "CF_dp_f_before", "CF_dp_f_after")


class ReplayError(ValueError):
    """The history cannot be replayed (no timestamps, no usable initial window, ...)."""


@dataclass(frozen=True)
class ReplaySettings:
    window_hours: float = 2.0
    min_samples: int = 30             # usable samples a window needs
    initial_minutes: int = 90         # default initial window: the first 90 usable minutes
    cip_off_minutes: float = 360.0    # a plant stop longer than this counts as a CIP
    cip_windows: int = 1              # windows averaged on each side of a CIP
    max_gap_minutes: float = 30.0     # a hole in the record longer than this ends a window segment
    optimize: bool = True
    dp_form: str = "auto"

    @classmethod
    def from_config(cls, extra: dict | None, **overrides) -> "ReplaySettings":
        """plant.yaml ``calibration.replay`` (+ fouling.window_hours/min_samples, initial.window_minutes)."""
        cal = (extra or {}).get("calibration") or {}
        kw: dict = {}
        rep = cal.get("replay") or {}
        known = set(cls.__dataclass_fields__)
        for k, v in rep.items():
            if k not in known:
                raise ReplayError(f"key 'calibration.replay.{k}': unknown (known: {', '.join(sorted(known))})")
            kw[k] = v
        fo, ini = cal.get("fouling") or {}, cal.get("initial") or {}
        if "window_hours" in fo:
            kw.setdefault("window_hours", fo["window_hours"])
        if "min_samples" in fo:
            kw.setdefault("min_samples", fo["min_samples"])
        if "window_minutes" in ini:
            kw.setdefault("initial_minutes", ini["window_minutes"])
        kw.update({k: v for k, v in overrides.items() if v is not None})
        s = cls(**kw)
        for name in ("window_hours", "min_samples", "initial_minutes", "cip_off_minutes", "cip_windows",
                     "max_gap_minutes"):
            v = getattr(s, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ReplayError(f"replay setting {name} must be a number > 0, got {v!r}")
        return s


@dataclass
class ReplayResult:
    windows: pd.DataFrame
    cips: pd.DataFrame
    initial: CalibrationResult
    dp_clean: DpCleanFit
    n_rows: int
    n_usable: int
    unusable: dict[str, int]              # samples per reason (model.measured)
    windows_skipped: dict[str, int]       # windows per reason
    initial_window: tuple[str, str]
    run_time_s: float
    settings: ReplaySettings
    last_fouling: CalibrationResult | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        w = self.windows
        ok = w[w["status"] == "ok"] if len(w) else w
        L = [f"replayed {self.n_rows} samples ({self.n_usable} usable) in {self.run_time_s:.1f} s"]
        if self.unusable:
            L.append("  unusable samples: " + ", ".join(f"{k}: {v}" for k, v in self.unusable.items()))
        L.append(f"initial window {self.initial_window[0]} .. {self.initial_window[1]}")
        L += ["  " + x for x in self.initial.summary().splitlines()]
        d = self.dp_clean
        L.append(f"  clean pressure drop ({d.form}): dp = {d.coef_bar[0]:.4g} + {d.coef_bar[1]:.4g}*V + "
                 f"{d.coef_bar[2]:.4g}*V^2 bar (V in m3/h), R^2 {d.r2:.3f}, on {d.n_samples} samples"
                 + (f"; {d.note}" if d.note else ""))
        L.append(f"windows of {self.settings.window_hours:g} h: {len(ok)} calibrated"
                 + (", skipped: " + ", ".join(f"{k}: {v}" for k, v in self.windows_skipped.items())
                    if self.windows_skipped else ""))
        if len(ok):
            def rng(col, fmt, scale=1.0):
                return f"{fmt.format(ok[col].min() * scale)} .. {fmt.format(ok[col].max() * scale)}"
            L.append(f"  fouling resistance R_th,f  {rng('R_th_f_K_per_kW', '{:.2f}', 1e3)} e-3 K/kW, "
                     f"{rng('R_th_f_share', '{:.0f}', 100)} % of the evaporator resistance")
            L.append(f"  pressure-drop factor CF_dp,f {rng('CF_dp_f', '{:.3f}')}")
            L.append(f"  COP NRMSE: fixed model {100 * ok['nrmse_COP_fixed'].mean():.2f} %, adaptive "
                     f"{100 * ok['nrmse_COP_adaptive'].mean():.2f} %; heat output NRMSE: fixed "
                     f"{100 * ok['nrmse_Q_sink_fixed'].mean():.2f} %, adaptive "
                     f"{100 * ok['nrmse_Q_sink_adaptive'].mean():.2f} % (means over windows)")
            if ok["p_m_opt_bar_a"].notna().any():
                L.append(f"  optimal p_m {rng('p_m_opt_bar_a', '{:.2f}')} bar a (geometric mean "
                         f"{rng('p_m_gm_bar_a', '{:.2f}')}); COP +{ok['dCOP_opt_pct'].mean():.2f} % and heat "
                         f"{ok['dQ_sink_opt_pct'].mean():+.2f} % on average against the actual set points")
        if len(self.cips):
            L.append(f"CIPs: {len(self.cips)}")
            for _, c in self.cips.iterrows():
                L.append(f"  {c['cip_start']} .. {c['cip_end']} ({c['duration_h']:.1f} h, {c['detected_by']}): "
                         f"R_th,f {1e3 * c['R_th_f_before']:.2f} -> {1e3 * c['R_th_f_after']:.2f} e-3 K/kW "
                         f"({c['R_th_f_removed_pct']:.1f} % removed), CF_dp,f {c['CF_dp_f_before']:.3f} -> "
                         f"{c['CF_dp_f_after']:.3f}")
        else:
            L.append("CIPs: none detected")
        for n in self.notes:
            L.append(f"note: {n}")
        return "\n".join(L)


def _timestamps(history: pd.DataFrame) -> pd.DatetimeIndex:
    if "timestamp" not in history.columns:
        raise ReplayError("history has no 'timestamp' column")
    ts = pd.to_datetime(history["timestamp"], utc=True, errors="coerce")
    if ts.isna().any():
        raise ReplayError(f"{int(ts.isna().sum())} rows have no valid timestamp (drop them first)")
    return pd.DatetimeIndex(ts)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last+1) index pairs of the True runs of mask."""
    m = np.concatenate([[False], mask, [False]]).astype(int)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def detect_cips(ts: pd.DatetimeIndex, processed: pd.DataFrame, cip_flag: np.ndarray | None,
                off_minutes: float) -> list[dict]:
    """CIP periods: stops (plant off or cip) that carry the cip flag or last longer than off_minutes.

    start = first stopped sample, end = first sample after the stop (or the last sample)."""
    reason = processed["reason"].astype(str).to_numpy()
    down = np.isin(reason, ("off", "cip"))
    if cip_flag is not None:
        down |= cip_flag
    out = []
    for a, b in _runs(down):
        start = ts[a]
        end = ts[b] if b < len(ts) else ts[b - 1]
        flagged = cip_flag is not None and bool(cip_flag[a:b].any())
        dur_min = (end - start).total_seconds() / 60.0
        if flagged or dur_min >= off_minutes:
            out.append({"start": start, "end": end, "i0": a, "i1": b, "duration_h": dur_min / 60.0,
                        "detected_by": "cip_flag" if flagged else "plant_off"})
    return out


def _nrmse(sim: np.ndarray, meas: np.ndarray) -> float:
    ok = np.isfinite(sim) & np.isfinite(meas)
    if ok.sum() == 0 or not np.mean(meas[ok]) > 0:
        return math.nan
    return float(np.sqrt(np.mean((sim[ok] - meas[ok]) ** 2)) / np.mean(meas[ok]))


def replay(history: pd.DataFrame, params: PlantParams, settings: ReplaySettings | None = None,
           initial_window: tuple | None = None, processed: pd.DataFrame | None = None,
           progress=None) -> ReplayResult:
    """Replay ``history`` (canonical columns + ``timestamp``) on the plant ``params`` (plant.yaml).

    initial_window : (start, end) timestamps; default the first ``initial_minutes`` usable minutes.
    processed : the output of ``model.measured.process`` when the caller already has it.
    progress : callable(done, total) called once per window.
    """
    t0 = time.perf_counter()
    s = settings or ReplaySettings.from_config(params.extra)
    history = history.reset_index(drop=True)
    ts = _timestamps(history)
    if not ts.is_monotonic_increasing:
        order = np.argsort(ts.to_numpy(), kind="stable")
        history = history.iloc[order].reset_index(drop=True)
        ts = ts[order]
    if processed is None:
        processed = process(history, params)
    else:
        processed = processed.reset_index(drop=True)
    usable = processed["usable"].to_numpy(dtype=bool)
    notes: list[str] = []

    # ---- initial window -----------------------------------------------------------------------
    if initial_window is not None:
        a, b = (pd.Timestamp(x) for x in initial_window)
        a = a.tz_localize("UTC") if a.tzinfo is None else a
        b = b.tz_localize("UTC") if b.tzinfo is None else b
        init_mask = usable & (ts >= a) & (ts <= b)
    else:
        idx = np.flatnonzero(usable)[: int(s.initial_minutes)]
        init_mask = np.zeros(len(ts), dtype=bool)
        init_mask[idx] = True
    if init_mask.sum() < s.min_samples:
        raise ReplayError(f"initial window has {int(init_mask.sum())} usable samples, fewer than "
                          f"{s.min_samples}")
    init_idx = np.flatnonzero(init_mask)
    iw = (ts[init_idx[0]].isoformat(), ts[init_idx[-1]].isoformat())
    init_data = calibration_frame(history, processed, init_mask)
    initial = calibrate(init_data, params, spec_from_config(params.extra, "initial"), window=iw)
    try:
        dpfit = fit_dp_clean(init_data["V_source"], init_data["dp_source_bar"], form=s.dp_form, window=iw)
    except DpFitError as exc:
        raise ReplayError(f"clean pressure-drop fit on the initial window: {exc}") from exc
    c = dpfit.coef_bar
    fixed = initial.apply(params).replace(
        R_th_f=0.0, CF_dp_f=1.0, dp_clean_coef=(c[0] * BAR, c[1] * BAR / M3H, c[2] * BAR / M3H ** 2))
    if not initial.identifiable:
        notes.append("the initial calibration is not fully identifiable (see its warnings); the fixed "
                     "model still reproduces its targets, but the named factors are not individually "
                     "meaningful")

    # ---- CIPs and windows ---------------------------------------------------------------------
    cip_flag = (pd.to_numeric(history["cip"], errors="coerce").fillna(0).to_numpy() > 0.5
                if "cip" in history.columns else None)
    cips = detect_cips(ts, processed, cip_flag, s.cip_off_minutes)
    after_init = ts > ts[init_idx[-1]]
    # operation segments between CIPs; each is tiled evenly with windows of about window_hours, so
    # that the windows next to a CIP end at its start and begin at its end
    segments = []
    cur = ts[init_idx[-1]] + pd.Timedelta(seconds=1)
    for c_ in cips:
        if c_["start"] > cur:
            segments.append((cur, c_["start"]))
        cur = max(cur, c_["end"])
    segments.append((cur, ts[-1] + pd.Timedelta(seconds=1)))
    # a hole in the record longer than max_gap_minutes also ends a segment (it is not a CIP: the
    # record says nothing about it)
    gaps = np.flatnonzero((ts[1:] - ts[:-1]) > pd.Timedelta(minutes=s.max_gap_minutes))
    if len(gaps):
        notes.append(f"{len(gaps)} gap(s) in the record longer than {s.max_gap_minutes:g} min: "
                     "windows do not span them")
        cut = []
        for a, b in segments:
            pts = [a] + [ts[g + 1] for g in gaps if a < ts[g + 1] < b] + [b]
            cut += list(zip(pts[:-1], pts[1:]))
        segments = cut
    W = pd.Timedelta(hours=s.window_hours)
    plan: list[tuple[np.ndarray, bool]] = []      # (mask, first window after a CIP)
    skipped: dict[str, int] = {}
    for seg_start, seg_end in segments:
        in_seg = after_init & (ts >= seg_start) & (ts < seg_end) & usable
        if not in_seg.any():
            continue
        idx = np.flatnonzero(in_seg)
        first, last = ts[idx[0]], ts[idx[-1]] + pd.Timedelta(minutes=1)
        n_win = max(1, int(round((last - first) / W)))
        edges = [first + (last - first) * (j / n_win) for j in range(n_win + 1)]
        new_seg = True
        for a, b in zip(edges[:-1], edges[1:]):
            m = in_seg & (ts >= a) & (ts < b)
            if m.sum() >= s.min_samples:
                plan.append((m, new_seg))
                new_seg = False
            elif m.any():
                skipped["too few usable samples"] = skipped.get("too few usable samples", 0) + 1

    fouling_spec = spec_from_config(params.extra, "fouling")
    rows = []
    previous = None
    last_fouling = None
    if progress is not None:
        progress(0, len(plan))
    for n_done, (m, new_seg) in enumerate(plan, start=1):
        if new_seg:
            previous = None        # the change penalty never reaches across a CIP or a long stop
        idx = np.flatnonzero(m)
        row = {"window_start": ts[idx[0]].isoformat(), "window_end": ts[idx[-1]].isoformat(),
               "n_samples": int(len(idx)), "status": "ok"}
        data = calibration_frame(history, processed, m)
        try:
            fc = calibrate(data, fixed, fouling_spec, previous=previous,
                           window=(row["window_start"], row["window_end"]))
            last_fouling = fc
            if fouling_spec.change_penalty > 0:
                previous = fc.params
            adaptive = fc.apply(fixed)
            row.update(_window_figures(data, fixed, adaptive, fc, s))
        except (CalibrationError, OptimizationError) as exc:
            row["status"] = f"failed: {exc}"
            key = type(exc).__name__
            skipped[key] = skipped.get(key, 0) + 1
        rows.append(row)
        if progress is not None:
            progress(n_done, len(plan))
    windows = pd.DataFrame(rows, columns=list(WINDOW_COLUMNS))
    cip_rows = _cip_table(cips, windows, s.cip_windows)
    return ReplayResult(
        windows=windows, cips=pd.DataFrame(cip_rows, columns=list(CIP_COLUMNS)), initial=initial,
        dp_clean=dpfit, n_rows=len(history), n_usable=int(usable.sum()),
        unusable=usable_counts(processed), windows_skipped=skipped, initial_window=iw,
        run_time_s=time.perf_counter() - t0, settings=s, last_fouling=last_fouling, notes=notes)


def _window_figures(data: pd.DataFrame, fixed: PlantParams, adaptive: PlantParams,
                    fc: CalibrationResult, s: ReplaySettings) -> dict:
    R = fc.params.get("R_th_f_K_per_kW", adaptive.R_th_f * 1e3)
    CF = fc.params.get("CF_dp_f", adaptive.CF_dp_f)
    V = data["V_source"].to_numpy(dtype=float) * M3H
    out = {
        "R_th_f_K_per_kW": R, "R_th_f_se_K_per_kW": fc.std_errors.get("R_th_f_K_per_kW", math.nan),
        "R_th_f_share": evaporator_share(adaptive), "CF_dp_f": CF,
        "CF_dp_f_se": fc.std_errors.get("CF_dp_f", math.nan),
        "dp_fouling_bar": float((CF - 1.0) * np.mean(fixed.dp_clean(V)) / BAR),
        "nrmse_p_e": fc.nrmse.get("p_e", math.nan), "nrmse_dp_source": fc.nrmse.get("dp_source", math.nan),
        "calibration_warnings": "; ".join(fc.warnings),
    }
    cols = ("Q_sink_kW", "W_total_kW", "COP")
    sim_f = simulate_batch(data, fixed, columns=cols)
    sim_a = simulate_batch(data, adaptive, columns=cols)
    both = solved_mask(sim_f) & solved_mask(sim_a)
    meas_cop = data["COP"].to_numpy(dtype=float)[both]
    meas_q = data["Q_sink_kW"].to_numpy(dtype=float)[both]
    out.update({
        "nrmse_COP_fixed": _nrmse(sim_f["COP"].to_numpy(dtype=float)[both], meas_cop),
        "nrmse_COP_adaptive": _nrmse(sim_a["COP"].to_numpy(dtype=float)[both], meas_cop),
        "nrmse_Q_sink_fixed": _nrmse(sim_f["Q_sink_kW"].to_numpy(dtype=float)[both], meas_q),
        "nrmse_Q_sink_adaptive": _nrmse(sim_a["Q_sink_kW"].to_numpy(dtype=float)[both], meas_q),
        "COP_measured": float(meas_q.sum() / data["W_total_kW"].to_numpy(dtype=float)[both].sum()),
        "COP_fixed": float(sim_f["Q_sink_kW"][both].sum() / sim_f["W_total_kW"][both].sum()),
        "COP_adaptive": float(sim_a["Q_sink_kW"][both].sum() / sim_a["W_total_kW"][both].sum()),
        "p_m_sp_actual_barg": float(data["p_m_sp"].mean()),
    })
    if s.optimize:
        opt = optimize_setpoint(data, adaptive)
        out.update({"p_m_sp_opt_barg": opt.p_m_sp_opt_barg, "p_m_opt_bar_a": opt.p_m_opt_bar_a,
                    "p_m_gm_bar_a": opt.p_m_gm_bar_a, "dCOP_opt_pct": opt.dCOP_opt_pct,
                    "dQ_sink_opt_pct": opt.dQ_sink_opt_pct, "dCOP_gm_pct": opt.dCOP_gm_pct,
                    "dQ_sink_gm_pct": opt.dQ_sink_gm_pct, "hs_saturated_opt": opt.hs_saturated})
    return out


def _cip_table(cips: list[dict], windows: pd.DataFrame, k: int) -> list[dict]:
    ok = windows[windows["status"] == "ok"]
    ws = pd.to_datetime(ok["window_start"], utc=True)
    we = pd.to_datetime(ok["window_end"], utc=True)
    rows = []
    for c in cips:
        before = ok[(we <= c["start"]).to_numpy()].tail(k)
        after = ok[(ws >= c["end"]).to_numpy()].head(k)
        Rb = float(before["R_th_f_K_per_kW"].mean()) if len(before) else math.nan
        Ra = float(after["R_th_f_K_per_kW"].mean()) if len(after) else math.nan
        rows.append({
            "cip_start": c["start"].isoformat(), "cip_end": c["end"].isoformat(),
            "duration_h": c["duration_h"], "detected_by": c["detected_by"],
            "R_th_f_before": Rb, "R_th_f_after": Ra,
            "R_th_f_removed_pct": 100.0 * (Rb - Ra) / Rb if Rb > 0 else math.nan,
            "CF_dp_f_before": float(before["CF_dp_f"].mean()) if len(before) else math.nan,
            "CF_dp_f_after": float(after["CF_dp_f"].mean()) if len(after) else math.nan})
    return rows
