"""Replay of a plant history: the papers' analysis, reproducible for any plant (SPEC §5-6, §9).

``replay(history, params)`` loops the one analysis chain (``model.analysis.chain``) over the history,
causally by default: each window's calibration, learned compressor curves and advice use only the data
up to that window's end — exactly what the gateway would have known then — so a replay of a SCADA
export shows what hp-edge would have advised. ``hindsight=True`` learns the compressors on the whole
history first.

1. measured-side processing (``model.measured.process``): derived quantities and a usable flag with
   a reason per sample (unusable samples are counted per reason, never silently dropped);
2. initial calibration (CF_DSH, CF_con, CF_SC, CF_eva), the clean pressure-drop fit and the first
   compressor learning on the initial window: by default the first ``initial_minutes`` usable
   minutes (commissioning data). Their result is the **fixed model**;
3. CIP periods: runs of samples with the cip flag, or plant stops longer than ``cip_off_minutes``;
4. per window of usable operation (each stretch of operation between CIPs is tiled evenly with
   windows of about ``window_hours``, so windows never straddle a CIP and the windows next to one
   touch it): ``AnalysisChain.window`` — fouling calibration -> the **adaptive model**, the window
   figures, the learned curves and the advice;
5. per CIP: R_th,f and CF_dp,f of the windows just before and just after, and the removed share;
   and (issue 10) ``AnalysisChain.cip`` at its end: the fouling forecast and the cumulated cost of
   fouling restart there (forecast.csv: one row per window, the forecast made at its end).
"""
from __future__ import annotations

import gc
import math
import pickle
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import pandas as pd

from ..calibration import CalibrationResult, calibrate, calibration_frame, spec_from_config
from ..batch import INPUT_COLUMNS, floats
from ..dpfit import DpCleanFit, DpFitError, fit_dp_clean
from ..measured import derived, process, usable_counts
from .. import lockstep
from ..params import PlantParams
from .chain import ROW_COLUMNS, AnalysisChain, ChainSettings, WindowPartial
from .compressors import STAGES, CompressorLearner, observe, preset_stages, recorded_stages
from . import speedkernel

WINDOW_COLUMNS = ROW_COLUMNS
CIP_COLUMNS = ("cip_start", "cip_end", "duration_h", "detected_by", "R_th_f_before_K_per_kW",
               "R_th_f_after_K_per_kW", "R_th_f_removed_pct", "CF_dp_f_before", "CF_dp_f_after")
# issue 10: DIR/forecast.csv, one row per window (the forecast made at the window's end)
FORECAST_COLUMNS = ("window_end", "forecast_at", "R_th_f_forecast_K_per_kW", "R_th_f_forecast_lo_K_per_kW",
                    "R_th_f_forecast_hi_K_per_kW", "fouling_rate_K_per_kW_per_day",
                    "fouling_cost_eur_per_day", "days_to_recommended_cip")
SAMPLE_COLUMNS = ("timestamp", "usable", "reason", "window_start", "COP_measured", "COP_fixed",
                  "COP_adaptive", "Q_sink_kW_measured", "Q_sink_kW_fixed", "Q_sink_kW_adaptive",
                  "p_e_bar_measured", "p_e_bar_fixed", "p_e_bar_adaptive", "eta_is_LS_meas", "eta_is_HS_meas", "eta_is_LS_model",
                  "eta_is_HS_model", "pi_LS", "pi_HS", "N_LS_rpm", "N_HS_rpm", "p_m_sp_barg",
                  "heat_balance_pct")


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
    hindsight: bool = False           # learn the compressors on the whole history first
    surrogate: bool = True            # as the gateway's "optimizer: auto": the surrogate fitted
                                      # from the windows' optima replaces the search once it qualifies
    lockstep_windows: int = 64        # consecutive windows analysed in lockstep (run_windows); a
                                      # window's surrogate is the one of the windows before its chunk

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
        return cls(**kw)

    def __post_init__(self):
        """The settings' checks, however they were built (plant.yaml, the CLI or code)."""
        for name in ("window_hours", "min_samples", "initial_minutes", "cip_off_minutes", "cip_windows",
                     "max_gap_minutes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ReplayError(f"replay setting {name} must be a number > 0, got {v!r}")
        v = self.lockstep_windows
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 256:
            raise ReplayError(f"replay setting lockstep_windows must be a whole number 1..256, got {v!r}")


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
    samples: pd.DataFrame | None = None   # per-minute series (SAMPLE_COLUMNS)
    compressors: dict | None = None       # the learner's state at the end (compressors.json)
    surrogate_tracker: dict | None = None  # the tracker's rows and fits at the end
    meta: dict = field(default_factory=dict)
    when_to_clean: list[str] = field(default_factory=list)   # issue 10: the last window's CIP advice

    @property
    def forecast(self) -> pd.DataFrame:
        """forecast.csv: FORECAST_COLUMNS, one row per window (NaN where there is no forecast)."""
        w = self.windows
        if not len(w):
            return pd.DataFrame(columns=list(FORECAST_COLUMNS))
        return w[list(FORECAST_COLUMNS)].copy()

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
        def rng_of(frame, col, fmt, scale=1.0):
            return f"{fmt.format(frame[col].min() * scale)} .. {fmt.format(frame[col].max() * scale)}"
        if len(ok):
            def rng(col, fmt, scale=1.0):
                return rng_of(ok, col, fmt, scale)
            L.append(f"  fouling resistance R_th,f  {rng('R_th_f_K_per_kW', '{:.2f}', 1e3)} e-3 K/kW, "
                     f"{rng('R_th_f_share_pct', '{:.0f}')} % of the evaporator resistance")
            L.append(f"  pressure-drop factor CF_dp,f {rng('CF_dp_f', '{:.3f}')}")
            L.append(f"  COP NRMSE: fixed model {100 * ok['nrmse_COP_fixed'].mean():.2f} %, adaptive "
                     f"{100 * ok['nrmse_COP_adaptive'].mean():.2f} %; heat output NRMSE: fixed "
                     f"{100 * ok['nrmse_Q_sink_fixed'].mean():.2f} %, adaptive "
                     f"{100 * ok['nrmse_Q_sink_adaptive'].mean():.2f} % (means over windows)")
            adv = ok[ok["optimization_ok"].astype(bool)]
            if len(adv):
                conf = adv[adv["advice_confident"].astype(bool)]
                L.append(f"  set-point advice in {len(adv)} windows, confident in {len(conf)} "
                         f"({100 * len(conf) / len(adv):.0f} %)")
                if len(conf):
                    L.append(f"    recommended p_m,sp {rng_of(conf, 'p_m_sp_opt_barg', '{:.2f}')} bar(g) "
                             f"(geometric mean {rng_of(conf, 'p_m_gm_barg', '{:.2f}')}); expected COP "
                             f"{conf['dCOP_opt_pct'].mean():+.2f} % (sd {conf['dCOP_opt_sd_pct'].mean():.2f} %)"
                             f" and heat {conf['dQ_sink_opt_pct'].mean():+.2f} % on average against the "
                             f"actual set points")
                notes_ = adv.loc[~adv["advice_confident"].astype(bool), "advice_note"]
                if len(notes_):
                    # the reasons without their numbers (they group across windows): a number or
                    # range becomes "…", an aside in parentheses goes
                    top = (notes_.str.replace(r"\s*\(.*?\)", "", regex=True)
                           .str.replace(r"[-+]?\d[\d.]*(?:-[-+]?\d[\d.]*)?", "…", regex=True)
                           .str.replace(r"\s+", " ", regex=True).value_counts())
                    L.append("    not confident: " + "; ".join(f"{k.strip()} ({v})" for k, v in top.head(3).items()))
            for st in STAGES:
                d = ok[f"eta_is_{st}_drift_pct"].dropna()
                if len(d):
                    L.append(f"  {st} compressor eta_is against commissioning: {d.iloc[-1]:+.2f} points "
                             f"(last window)")
            if self.compressors:
                loc = self.compressors.get("T_c_location", "")
                L.append(f"  T_c is read as the {loc.replace('_', ' ')}; drive factors LS "
                         f"{ok['drive_factor_LS'].iloc[-1]:.3f}, HS {ok['drive_factor_HS'].iloc[-1]:.3f}")
            tr = self.meta.get("surrogate_tracker")
            if tr:
                fits = "; ".join(
                    f"{k}: R2 p_m,opt {f['r2'].get('p_m_opt_bar_a', float('nan')):.4f}, dCOP "
                    f"{f['r2'].get('dCOP_pct', float('nan')):.4f}, {100 * f['share_within_tol']:.0f} % "
                    f"within 0.3 bar{' (qualified)' if f['qualified'] else ''}"
                    for k, f in tr["fits"].items()) or "no fit yet"
                used = int(ok["optimizer"].astype(str).str.startswith("surrogate").sum())
                L.append(f"  surrogate from the window optima: {tr['rows']} rows; {fits}; used in "
                         f"{used} windows")
        if len(self.cips):
            L.append(f"CIPs: {len(self.cips)}")
            for _, c in self.cips.iterrows():
                L.append(f"  {c['cip_start']} .. {c['cip_end']} ({c['duration_h']:.1f} h, {c['detected_by']}): "
                         f"R_th,f {1e3 * c['R_th_f_before_K_per_kW']:.2f} -> {1e3 * c['R_th_f_after_K_per_kW']:.2f} e-3 K/kW "
                         f"({c['R_th_f_removed_pct']:.1f} % removed), CF_dp,f {c['CF_dp_f_before']:.3f} -> "
                         f"{c['CF_dp_f_after']:.3f}")
        else:
            L.append("CIPs: none detected")
        if self.when_to_clean:
            L.append("When to clean (forecast since the last reset, cost of fouling, cost-optimal CIP):")
            L += ["  " + x for x in self.when_to_clean]
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
           progress=None, chain_settings: ChainSettings | None = None,
           executor=None, commissioning: dict | None = None) -> ReplayResult:
    """Replay ``history`` (canonical columns + ``timestamp``) on the plant ``params`` (plant.yaml).

    initial_window : (start, end) timestamps; default the first ``initial_minutes`` usable minutes.
    processed : the output of ``model.measured.process`` when the caller already has it.
    progress : callable(done, total) called once per window.
    chain_settings : default from plant.yaml (advice, compressor_learning).
    executor : anything with concurrent.futures' ``submit`` (a ProcessPoolExecutor, a Dask
        ``distributed.Client``): the windows' expensive analysis runs there (``run_windows``); the
        results are identical to the sequential replay with the surrogate off (None: in this
        process). Either way consecutive windows run in lockstep, ``settings.lockstep_windows`` at a
        time (``run_windows``): with the surrogate on, a window uses the surrogate fitted from the
        windows before its chunk (1: from every window before it, as the gateway does).
    commissioning : {"initial": doc, "dp_clean": doc, "compressors": doc or None} as the gateway's
        state directory stores them: the plant was commissioned before the history starts; no
        initial window is taken from the history and windows start at its first sample.
    """
    with fewer_collections(), one_blas_thread(), replay_memory():
        return _replay(history, params, settings, initial_window, processed, progress, chain_settings,
                       executor, commissioning)


# glibc's mallopt parameters (malloc.h) and the values a replay runs with in a process that was
# started with a small MALLOC_TRIM_THRESHOLD_ (a Dask worker: 65536 from its nanny; edge.fleet)
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
TASK_MMAP_THRESHOLD = 32 * 1024 * 1024      # glibc's own ceiling for its dynamic threshold
TASK_TRIM_THRESHOLD = 2 * TASK_MMAP_THRESHOLD
DEFAULT_MMAP_THRESHOLD = 128 * 1024
_memory_depth = 0                         # replay_memory's nesting in this process


def _glibc():
    """glibc's C library (ctypes), or None (another C library, or none to be found)."""
    import ctypes
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version          # glibc only
        return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
    except (OSError, AttributeError):
        return None


@contextmanager
def replay_memory():
    """A replay's memory settings for the duration, in a process started with glibc's trim
    threshold below TASK_TRIM_THRESHOLD (a Dask worker has 65536 from its nanny, unless started as
    ``edge.fleet.Cluster`` starts them): freed memory up to TASK_TRIM_THRESHOLD stays with the
    process and arrays up to TASK_MMAP_THRESHOLD come from its heap, as in a process without the
    setting (with it glibc gives every freed array back to the OS and takes fresh pages again: 4.6x
    the page faults of a 10-day replay, system time 0.3 -> 0.8 s); afterwards the process's own
    thresholds are set again and what it holds is given back (``malloc_trim``). Nested: the
    outermost applies (the settings are the process's: replays in several threads of one process
    have them for the first one's span). Does nothing elsewhere (no such setting or one that is not
    a size, another C library): the replay's numbers cannot change."""
    global _memory_depth
    if _memory_depth:
        yield
        return
    import os
    trim = os.environ.get("MALLOC_TRIM_THRESHOLD_")
    libc = _glibc() if trim is not None else None
    try:
        trim_v = int(trim) if libc is not None else None
        mmap_v = int(os.environ.get("MALLOC_MMAP_THRESHOLD_") or DEFAULT_MMAP_THRESHOLD)
    except ValueError:
        trim_v = None
    if trim_v is None or not 0 <= trim_v < TASK_TRIM_THRESHOLD or mmap_v < 0:
        yield
        return
    libc.mallopt(M_MMAP_THRESHOLD, max(mmap_v, TASK_MMAP_THRESHOLD))
    libc.mallopt(M_TRIM_THRESHOLD, TASK_TRIM_THRESHOLD)
    _memory_depth += 1
    try:
        yield
    finally:
        _memory_depth -= 1
        libc.mallopt(M_TRIM_THRESHOLD, trim_v)
        libc.mallopt(M_MMAP_THRESHOLD, mmap_v)
        libc.malloc_trim(0)


GC_THRESHOLD0 = 20_000     # allocations between the cyclic GC's young collections during a replay


@contextmanager
def one_blas_thread():
    """The BLAS libraries loaded (OpenBLAS, MKL, ...) limited to one thread for the duration, then
    restored (threadpoolctl). A replay computes in one thread at a time (the lockstep threads take
    turns) and its matrices are small: BLAS's extra threads only spin between calls. On a 120-day
    replay they burned 17 % of the CPU time without shortening it (the surrogate's refits on
    thousands of rows), and beside other workers they would take cores from them. Dask's workers
    start with one BLAS thread already; this gives a replay the same wherever it runs. Without
    threadpoolctl (the ``fast`` extra) BLAS keeps its threads: the same numbers, more CPU."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


@contextmanager
def fewer_collections():
    """The cyclic garbage collector's first threshold raised to GC_THRESHOLD0 (Python's 700) for the
    duration, then restored. A replay allocates millions of short-lived containers (numpy's and
    pandas' small objects) and keeps its windows' results: with the default the collector ran
    ~2,000 times per 30-day replay (1.5 CPU-s, two thirds of it full collections scanning every
    object alive, a cost that grew with a plant-year's results). Collections only free cyclic
    garbage sooner or later: the numbers cannot change."""
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], GC_THRESHOLD0), *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _replay(history, params, settings, initial_window, processed, progress, chain_settings, executor,
            commissioning) -> ReplayResult:
    t0 = time.perf_counter()
    speedkernel.enable()            # the compiled speed search when numba is installed
    s = settings or ReplaySettings.from_config(params.extra)
    history = history.reset_index(drop=True)
    ts = _timestamps(history)
    if not ts.is_monotonic_increasing:
        order = np.argsort(ts.to_numpy(), kind="stable")
        history = history.iloc[order].reset_index(drop=True)
        ts = ts[order]
    history_stages: list = []       # the stage states of every sample, for pass 1 (tasks)
    if processed is None:
        with recorded_stages() as history_stages:
            processed = process(history, params)
    else:
        processed = processed.reset_index(drop=True)
    usable = processed["usable"].to_numpy(dtype=bool)
    notes: list[str] = []

    chain = AnalysisChain(params, spec_from_config(params.extra, "fouling"),
                          chain_settings or ChainSettings.from_config(params.extra, optimize=s.optimize,
                                                                      min_samples=int(s.min_samples),
                                                                      use_surrogate=bool(s.surrogate)
                                                                      and executor is None))
    if executor is not None and chain.s.use_surrogate:
        # the surrogate learns from each window's optimum in window order and would have to be
        # ahead of the windows analysed in parallel: a parallel replay runs the search everywhere
        chain = AnalysisChain(chain.plant, chain.spec, replace(chain.s, use_surrogate=False))
    if executor is not None and s.surrogate:
        notes.append("parallel replay: the set-point search in every window (the surrogate from the "
                     "window optima is fitted only in a sequential replay, as the gateway runs)")
    if commissioning is not None:
        # ---- commissioned before the history: the stored initial calibration, clean pressure-drop
        # fit and (when there) the commissioning compressor curves; windows from the first sample
        try:
            initial = CalibrationResult.from_dict(commissioning["initial"])
            dpfit = DpCleanFit.from_dict(commissioning["dp_clean"])
            learner = None
            if chain.s.learn_compressors:
                doc = commissioning.get("compressors")
                learner = (CompressorLearner.from_dict(doc, params, chain.s.learning) if doc is not None
                           else CompressorLearner(params, chain.s.learning))
        except (KeyError, TypeError, ValueError) as exc:
            raise ReplayError(f"commissioning state: {exc}") from exc
        init_idx = np.array([], dtype=int)
        iw = (str(initial.window_start), str(initial.window_end))
        notes.append("commissioning from the state directory (initial calibration, clean pressure "
                     "drop" + (", compressor curves" if commissioning.get("compressors") else "") + ")")
    else:
        # ---- initial window -------------------------------------------------------------------
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
        learner = chain.commissioning_learner(history.loc[init_mask].assign(timestamp=ts[init_mask]))
        base = learner.apply(params) if learner is not None else params
        initial = calibrate(init_data, base, spec_from_config(params.extra, "initial"), window=iw)
        try:
            dpfit = fit_dp_clean(init_data["V_source"], init_data["dp_source_bar"], form=s.dp_form, window=iw)
        except DpFitError as exc:
            raise ReplayError(f"clean pressure-drop fit on the initial window: {exc}") from exc
    state = chain.new_state(initial.to_dict(), dpfit.to_dict(), learner)
    if not initial.identifiable:
        notes.append("the initial calibration is not fully identifiable (see its warnings); the fixed "
                     "model still reproduces its targets, but the named factors are not individually "
                     "meaningful")
    if s.hindsight and state.learner is not None:
        state.learner.update(observe(history.loc[usable].assign(timestamp=ts[usable]), state.fixed,
                                     chain.s.learning))
        notes.append("hindsight: the compressor curves were learned on the whole history first")

    plan, skipped, cips = plan_windows(ts, processed, history, init_idx, s, notes)
    rows: list[dict] = []
    sample_parts: list[dict] = []
    when: list[str] = []
    pending = sorted(cips, key=lambda c: c["end"])       # issue 10: CIPs reset the forecast
    if progress is not None:
        progress(0, len(plan))

    def tasks():
        """Pass 1, in window order: each window's task (the learner updated, and so on). The
        measured side (``model.measured.derived``) of PASS1_BLOCK windows at a time, in one call:
        per window it cost ~3 ms of numpy calls on 120 rows (~5 % of a 30-day replay). The stage
        states it and the compressor observations ask for (the property splines, ~3.5 s a
        plant-year) are those ``process`` computed for the whole history, recorded then
        (``preset_stages``: the same numbers, each call's inputs matched to the bit)."""
        for b0 in range(0, len(plan), PASS1_BLOCK):
            block = plan[b0:b0 + PASS1_BLOCK]
            with recorded_stages() as records:
                at = np.concatenate([pos for pos, _ in block])
                rows_in = history.iloc[at]
                if history_stages:      # the measured side's stage states: those of the history
                    preset_stages(history_stages, at)
                der = derived(rows_in, state.fixed)
            for c in INPUT_COLUMNS:         # the model inputs beside it, as the chain adds them
                der[c] = floats(rows_in[c])
            end = 0
            for pos, new_seg in block:
                rows = slice(end, end + len(pos))
                end = rows.stop
                if new_seg:
                    chain.new_segment(state)    # the change penalty never reaches across a CIP or a long stop
                # the stage states the window's compressor observations ask for: the history's
                stages = (history_stages, pos) if history_stages else (records, rows)
                yield chain.prepare(history.iloc[pos].assign(timestamp=ts[pos]), state, samples=True,
                                    pre=(der.iloc[rows].reset_index(drop=True), *stages))

    def cips_before(partial) -> None:
        start = partial.res.window_start
        while pending and start and pending[0]["end"] <= pd.Timestamp(start):
            c_ = pending.pop(0)         # the forecast restarts (pass 3's state; segments are pass 1's)
            chain.cip(state, c_["start"], c_["end"], c_["detected_by"], segment=False)

    n_done = 0
    for chunk in run_windows(chain, tasks(), executor, lockstep_windows=s.lockstep_windows):
        # pass 3, in window order (a chunk's dead-band runs together: AnalysisChain.finish_chunk)
        for partial, res in zip(chunk, chain.finish_chunk(chunk, state, before=cips_before)):
            if res.ok and "cip" in res.detail:
                when = res.detail["cip"]["text"]
            if not res.ok:
                key = res.status.split(":")[0] + ": " + res.status.split(":")[1].strip() if ":" in res.status \
                    else res.status
                skipped[key] = skipped.get(key, 0) + 1
            rows.append(res.row())
            if partial.samples is not None:
                sample_parts.append(partial.samples)
            n_done += 1
            if progress is not None:
                progress(n_done, len(plan))
    windows = pd.DataFrame(rows, columns=list(WINDOW_COLUMNS))
    cip_rows = _cip_table(cips, windows, s.cip_windows)
    samples = _all_samples(history, ts, processed, sample_parts)
    meta = {"period_start": ts[0].isoformat(), "period_end": ts[-1].isoformat(),
            "n_rows": int(len(history)), "n_usable": int(usable.sum()),
            "unusable": usable_counts(processed), "settings": asdict(s)}
    if state.tracker is not None:
        meta["surrogate_tracker"] = state.tracker.summary()
    return ReplayResult(
        windows=windows, cips=pd.DataFrame(cip_rows, columns=list(CIP_COLUMNS)), initial=initial,
        dp_clean=dpfit, n_rows=len(history), n_usable=int(usable.sum()),
        unusable=usable_counts(processed), windows_skipped=skipped, initial_window=iw,
        run_time_s=time.perf_counter() - t0, settings=s, last_fouling=state.last_fouling, notes=notes,
        samples=samples, compressors=state.learner.to_dict() if state.learner is not None else None,
        surrogate_tracker=state.tracker.to_dict() if state.tracker is not None else None, meta=meta,
        when_to_clean=when)


def plan_windows(ts: pd.DatetimeIndex, processed: pd.DataFrame, history: pd.DataFrame,
                 init_idx: np.ndarray, s: ReplaySettings, notes: list[str]):
    """The windows of a replay: (row positions, first window of a segment) pairs, the windows
    skipped per reason, and the CIPs. Operation segments between CIPs (and holes in the record
    longer than max_gap_minutes) are tiled evenly with windows of about window_hours."""
    usable = processed["usable"].to_numpy(dtype=bool)
    cip_flag = (pd.to_numeric(history["cip"], errors="coerce").fillna(0).to_numpy() > 0.5
                if "cip" in history.columns else None)
    cips = detect_cips(ts, processed, cip_flag, s.cip_off_minutes)
    t_init = ts[init_idx[-1]] if len(init_idx) else ts[0] - pd.Timedelta(seconds=1)
    after_init = ts > t_init
    # operation segments between CIPs; each is tiled evenly with windows of about window_hours, so
    # that the windows next to a CIP end at its start and begin at its end
    segments = []
    cur = t_init + pd.Timedelta(seconds=1)
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
    # (row positions, first window after a CIP): positions, not a mask over the whole history per
    # window (a plant-year's 3,600 windows x 525,600 rows of masks were 1.9 GB)
    plan: list[tuple[np.ndarray, bool]] = []
    skipped: dict[str, int] = {}
    for seg_start, seg_end in segments:
        in_seg = after_init & (ts >= seg_start) & (ts < seg_end) & usable
        if not in_seg.any():
            continue
        idx = np.flatnonzero(in_seg)
        first, last = ts[idx[0]], ts[idx[-1]] + pd.Timedelta(minutes=1)
        n_win = max(1, int(round((last - first) / W)))
        edges = [first + (last - first) * (j / n_win) for j in range(n_win + 1)]
        t_seg = ts[idx]
        ordered = bool(t_seg.is_monotonic_increasing)     # the replay sorts the history by time
        new_seg = True
        for a, b in zip(edges[:-1], edges[1:]):
            if ordered:     # the segment's rows in [a, b)
                pos = idx[t_seg.searchsorted(a, side="left"):t_seg.searchsorted(b, side="left")]
            else:
                pos = np.flatnonzero(in_seg & (ts >= a) & (ts < b))
            if len(pos) >= s.min_samples:
                plan.append((pos, new_seg))
                new_seg = False
            elif len(pos):
                skipped["too few usable samples"] = skipped.get("too few usable samples", 0) + 1

    return plan, skipped, cips


_MISSING = object()


def frame_of_parts(parts: list[dict]) -> pd.DataFrame:
    """The windows' sample columns (``chain._window_samples``: arrays of one length per window,
    with a ``timestamp`` column; a scalar is that value in every row) as one frame: what
    ``pd.concat`` of a frame per window gives (the columns in the order they first appear, NaN
    where a window has no such column, a RangeIndex), each column built once from the windows'
    arrays instead of a frame per window and their concatenation. Consumes the parts (each window's
    arrays are let go once its column is built: a plant-year's samples are not held twice)."""
    names = list(dict.fromkeys(k for p in parts for k in p))
    lens = [len(p["timestamp"]) for p in parts]
    cols = {}
    for k in names:
        vals = [p.pop(k, _MISSING) for p in parts]
        if all(isinstance(v, pd.api.extensions.ExtensionArray) for v in vals):
            # (the times: pandas' arrays, joined as pandas joins them)
            cols[k] = pd.concat([pd.Series(v, copy=False) for v in vals], ignore_index=True).array
            continue
        arrs = []
        for v, n in zip(vals, lens):
            if v is _MISSING:
                arrs.append(np.full(n, np.nan))
            elif np.ndim(v) == 0:
                arrs.append(np.full(n, v, dtype=object))
            else:
                arrs.append(np.asarray(v))
        cols[k] = np.concatenate(arrs)
    return pd.DataFrame(cols, index=pd.RangeIndex(sum(lens)))


def _all_samples(history: pd.DataFrame, ts: pd.DatetimeIndex, processed: pd.DataFrame,
                 parts: list[dict]) -> pd.DataFrame:
    num = lambda c: pd.to_numeric(history[c], errors="coerce").to_numpy(dtype=float) \
        if c in history.columns else np.full(len(history), np.nan)  # noqa: E731
    out = pd.DataFrame({
        "timestamp": ts, "usable": processed["usable"].to_numpy(dtype=bool),
        "reason": processed["reason"].to_numpy(),
        "COP_measured": processed["COP"].to_numpy(dtype=float),
        "Q_sink_kW_measured": processed["Q_sink_kW"].to_numpy(dtype=float),
        "p_e_bar_measured": processed["p_e_bar"].to_numpy(dtype=float),
        "eta_is_LS_meas": processed["eta_is_LS_meas"].to_numpy(dtype=float),
        "eta_is_HS_meas": processed["eta_is_HS_meas"].to_numpy(dtype=float),
        "pi_LS": processed["pi_LS"].to_numpy(dtype=float), "pi_HS": processed["pi_HS"].to_numpy(dtype=float),
        "N_LS_rpm": num("N_LS"), "N_HS_rpm": num("N_HS"), "p_m_sp_barg": num("p_m_sp"),
        "heat_balance_pct": processed["heat_balance_pct"].to_numpy(dtype=float)})
    if parts:
        w = frame_of_parts(parts)
        w["timestamp"] = pd.to_datetime(w["timestamp"], utc=True)
        out = out.merge(w, on="timestamp", how="left")
    for c in SAMPLE_COLUMNS:
        if c not in out.columns:
            out[c] = np.nan
    out["timestamp"] = isoformat(out["timestamp"])
    return out[list(SAMPLE_COLUMNS)]


def isoformat(times: pd.Series) -> np.ndarray | pd.Series:
    """``Timestamp.isoformat()`` of every time: UTC times in whole seconds (a history's minutes) by
    numpy, "YYYY-MM-DDTHH:MM:SS+00:00", ISO_CHUNK at a time (a plant-year's 525,600 calls took
    ~1.2 s; its texts at once ~80 MB more peak); any other times one by one."""
    tz = getattr(times.dtype, "tz", None)
    if tz is not None and str(tz) == "UTC" and len(times) and not times.isna().any():
        naive = times.dt.tz_convert(None).to_numpy()
        whole = naive.astype("datetime64[s]")
        if (whole == naive).all():
            out = np.empty(len(whole), dtype=object)
            for a in range(0, len(whole), ISO_CHUNK):
                text = np.datetime_as_string(whole[a:a + ISO_CHUNK], unit="s")
                out[a:a + ISO_CHUNK] = text.astype(object) + "+00:00"
            return out
    return times.map(lambda t: t.isoformat())


ISO_CHUNK = 16384


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
            "R_th_f_before_K_per_kW": Rb, "R_th_f_after_K_per_kW": Ra,
            "R_th_f_removed_pct": 100.0 * (Rb - Ra) / Rb if Rb > 0 else math.nan,
            "CF_dp_f_before": float(before["CF_dp_f"].mean()) if len(before) else math.nan,
            "CF_dp_f_after": float(after["CF_dp_f"].mean()) if len(after) else math.nan})
    return rows


# --------------------------------------------------------------------------------------------------
# the Executor seam
# --------------------------------------------------------------------------------------------------
def _analyse_pickled(chain_blob: bytes, task_blob: bytes) -> WindowPartial:
    """Pass 2 of one window in whichever process the executor chose (CoolProp state and property
    tables are built there on first use, never shipped)."""
    speedkernel.enable()
    chain = pickle.loads(chain_blob)
    return chain.analyse(pickle.loads(task_blob))


def _analyse_chunk(chain: AnalysisChain, task_blobs: list) -> list:
    """Pass 2 of consecutive windows (their pickled tasks) in lockstep (``model.lockstep``): their
    solver calls answered together. A window whose analysis raises raises here, as alone."""
    return _analyse_tasks(chain, [pickle.loads(b) for b in task_blobs])


def _analyse_tasks(chain: AnalysisChain, tasks: list) -> list:
    """``_analyse_chunk`` of the tasks themselves."""
    if len(tasks) == 1:
        return [chain.analyse(tasks[0])]
    out = lockstep.run([(lambda t=t: chain.analyse(t)) for t in tasks])
    for r in out:
        if isinstance(r, lockstep.Failed):
            raise r.exc
    return out


def _analyse_chunk_pickled(chain_blob: bytes, task_blobs: list) -> list:
    """``_analyse_chunk`` in whichever process the executor chose."""
    speedkernel.enable()
    with fewer_collections(), one_blas_thread(), replay_memory():
        return _analyse_chunk(pickle.loads(chain_blob), task_blobs)


def _snapshot(task):
    """A task as pass 1 leaves it, unchanged by pass 1's later windows, for pass 2 in this process:
    of everything in it only the learner is still pass 1's (its next windows update it in place;
    the rest is the window's own or replaced, never changed, by pass 1), so the learner is a
    snapshot (``CompressorLearner.snapshot``) — the numbers of a pickled copy, without pickling."""
    if task.learner is not None:
        task.learner = task.learner.snapshot()
    return task


PASS1_BLOCK = 32          # windows whose measured side pass 1 computes in one call
MAX_PENDING = 16           # windows in flight at an executor (bounds the pickled tasks held)
LOCKSTEP_WINDOWS = ReplaySettings.lockstep_windows   # run_windows' default chunk


def run_windows(chain: AnalysisChain, tasks, executor=None, max_pending: int | None = None,
                lockstep_windows: int | None = None):
    """Yield the tasks' ``chain.analyse(task)`` in the tasks' order, one list per chunk (pass 3
    takes a chunk at a time: ``AnalysisChain.finish_chunk``).

    The tasks are taken in chunks of ``lockstep_windows`` (default LOCKSTEP_WINDOWS) consecutive
    windows whose pass 2 runs in lockstep (``model.lockstep``: each solver step of the chunk's
    windows in one call of the vectorised solver). Each task is frozen the moment pass 1 has
    produced it (pass 1 goes on to change the learner for the next window): pickled for an
    executor, its learner snapshotted here (``_snapshot``; the same numbers). The chunks
    are the same whatever runs them, so the results are too: without an executor the chunks are
    analysed here, one after the other; with one, each chunk is submitted as soon as it is complete,
    at most ``max_pending`` (default MAX_PENDING) windows' worth in flight (at least two chunks).
    With ``lockstep_windows`` 1 and no executor, each window is analysed right after its pass 1
    (the gateway's order, no pickling). Pass 2 depends on nothing but its task."""
    k = max(1, int(lockstep_windows or LOCKSTEP_WINDOWS))
    if executor is None and k == 1:
        for t in tasks:
            yield [chain.analyse(t)]
        return

    def chunks(freeze):
        part = []
        for t in tasks:
            part.append(freeze(t))
            if len(part) == k:
                yield part
                part = []
        if part:
            yield part

    if executor is None:
        for part in chunks(_snapshot):
            yield _analyse_tasks(chain, part)
        return
    chain_blob = pickle.dumps(chain, protocol=pickle.HIGHEST_PROTOCOL)
    max_chunks = max(2, int(max_pending or MAX_PENDING) // k)
    pending: deque = deque()
    for blobs in chunks(lambda t: pickle.dumps(t, protocol=pickle.HIGHEST_PROTOCOL)):
        pending.append(executor.submit(_analyse_chunk_pickled, chain_blob, blobs))
        while len(pending) >= max_chunks:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()
