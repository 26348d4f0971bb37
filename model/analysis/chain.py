"""One analysis chain, called by both the gateway and replay (issue #8 item 1; pvlib's ModelChain).

``AnalysisChain.window(data, state) -> WindowResult`` does, for one window of usable one-minute
samples (canonical columns of SPEC §4, time on a ``timestamp`` column or a DatetimeIndex):

1. the measured side (``model.measured.derived``) and the window's heat-balance closure: a closure
   worse than ``heat_balance_limit_pct`` (after the learned drive factors) marks the window unusable
   for calibration, with the reason (a flow meter drifting is the usual cause);
2. compressor learning (``model.analysis.compressors``): the window's observations not seen before
   are added to the learned curves (causal: nothing after the window's end is used);
3. the fouling calibration (R_th,f, CF_dp,f) of the fixed model -> the adaptive model;
4. the papers' window figures: NRMSE of COP and heat output of the fixed and the adaptive model;
5. the fouling forecast since the last reset, the cost of fouling and the CIP plan
   (``model.analysis.cip``, issue 10; ``AnalysisChain.cip`` resets the forecast at a CIP);
6. the set-point advice with its uncertainty and confidence (``model.analysis.advice``);
7. the compressor drift against commissioning.

``ChainState`` carries what one window hands to the next (the fixed model, the learner, the
previous fouling parameters and recommendation); the gateway persists it in its state directory,
replay keeps it in memory. The result's ``row()`` is a windows.csv row (units in the column names)
and ``advisory_values()`` the advisory block's fields in the HMI's units — one mapping each, here.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields, is_dataclass

import numpy as np
import pandas as pd

from ..batch import INPUT_COLUMNS, InputColumns, floats, matrix, numeric, simulate_batch, simulate_many, solved_mask
from ..calibration import (CalibrationError, CalibrationResult, CalibrationSpec,
                           apply_state, calibrate, evaporator_share)
from ..measured import derived
from ..optimize import OptimizationError, groups, representative
from ..params import PlantParams
from ..units import BAR, M3H
from .. import lockstep
from .advice import (AdviceDraft, AdviceResult, AdviceSettings, check_rows, decide_settling, draft_advice,
                     finish_settling)
from .cip import CipSettings, ForecastState, cost_levels_for, explain, forecast_window
from .cost import CostError, LevelRuns, PriceSeries
from .compressors import STAGES, CompressorLearner, LearningSettings, observe, preset_stages, shared_stages
from .surrogate_tracker import SurrogateTracker, TrackerSettings, optimum_row

DEFAULT_HEAT_BALANCE_LIMIT_PCT = 5.0
_ADVICE_FAILS = (OptimizationError, ValueError, ArithmeticError)   # a window's advice fails, not the run
LS_SATURATED_RPM = 15.0     # a measured LS speed this close to its maximum: at the limit


@dataclass(frozen=True)
class ChainSettings:
    min_samples: int = 30                       # usable samples a window needs
    heat_balance_limit_pct: float = DEFAULT_HEAT_BALANCE_LIMIT_PCT
    optimize: bool = True
    learn_compressors: bool = True
    condenser_correction: bool = True           # scale the condenser unit's UA to the measured p_c
    figure_rows: int = 40                       # samples (evenly spaced) the model figures simulate
    advice: AdviceSettings = AdviceSettings()
    learning: LearningSettings = LearningSettings()
    tracker: TrackerSettings = TrackerSettings()
    use_surrogate: bool = False                 # the tracker's qualified form in place of the search
    cip: CipSettings = CipSettings()            # issue 10: forecast, cost of fouling, CIP plan

    @classmethod
    def from_config(cls, extra: dict | None, cip_price: PriceSeries | None = None,
                    **overrides) -> "ChainSettings":
        """plant.yaml's ``advice``, ``compressor_learning``, ``calibration`` and ``cip`` sections;
        ``cip_price``: the series of ``cip.electricity_price_csv`` (``edge.io.prices``)."""
        extra = extra or {}
        learning = LearningSettings.from_dict(extra.get("compressor_learning"))
        kw = dict(advice=AdviceSettings.from_dict(extra.get("advice")), learning=learning,
                  learn_compressors=learning.enabled,
                  tracker=TrackerSettings.from_dict(extra.get("surrogate_tracker")),
                  cip=CipSettings.from_config(extra, price=cip_price))
        hb = (extra.get("calibration") or {}).get("heat_balance_limit_pct")
        if hb is not None:
            if isinstance(hb, bool) or not isinstance(hb, (int, float)) or not hb > 0:
                raise CalibrationError(f"key 'calibration.heat_balance_limit_pct': expected a number "
                                       f"> 0, got {hb!r}")
            kw["heat_balance_limit_pct"] = float(hb)
        kw.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kw)


@dataclass
class ChainState:
    """What one window hands to the next."""
    fixed: PlantParams                          # plant.yaml + initial calibration + dp_clean fit
    learner: CompressorLearner | None = None
    fouling_previous: dict | None = None        # previous fouling parameters (change penalty)
    last_rec_barg: float | None = None          # previous confident recommendation (dead band)
    last_fouling: CalibrationResult | None = None
    cond_factor: float | None = None            # last window's condenser-unit factor
    T_out_sp_C: float | None = None             # the LS speed controller's T_source,out set point
    tracker: SurrogateTracker | None = None     # the surrogate fitted from the window optima
    forecast: ForecastState = field(default_factory=ForecastState)   # issue 10, since the last reset
    cost_turn: int = 0                          # windows that reached pass 2 (turns the cost levels)


@dataclass
class WindowResult:
    """Everything one window produced. Floats are NaN when not available."""
    window_start: str
    window_end: str
    t_end: float                                # epoch s of the last sample
    n_samples: int
    status: str = "ok"                          # "ok" | "skipped: ..." | "failed: ..."
    heat_balance_pct: float = math.nan
    CF_cond_window: float = math.nan            # condenser-unit UA factor fitted to this window's p_c
    p_c_error_bar: float = math.nan             # model - measured p_c before that correction
    T_source_out_sp_C: float = math.nan         # LS controller set point (T_source,out, LS not at 1800)
    ls_saturated_share: float = math.nan        # samples with the LS at its speed limit
    R_th_f_K_per_kW: float = math.nan
    R_th_f_se_K_per_kW: float = math.nan
    R_th_f_share_pct: float = math.nan
    CF_dp_f: float = math.nan
    CF_dp_f_se: float = math.nan
    dp_fouling_bar: float = math.nan
    nrmse_p_e: float = math.nan                 # fractions (the papers' NRMSE)
    nrmse_dp_source: float = math.nan
    calibration_objective: float = math.nan
    calibration_warnings: str = ""
    nrmse_COP_fixed: float = math.nan
    nrmse_COP_adaptive: float = math.nan
    nrmse_Q_sink_fixed: float = math.nan
    nrmse_Q_sink_adaptive: float = math.nan
    COP_measured: float = math.nan
    COP_fixed: float = math.nan
    COP_adaptive: float = math.nan
    p_m_sp_actual_barg: float = math.nan
    p_m_sp_opt_barg: float = math.nan           # the recommendation as written to the block
    p_m_sp_model_opt_barg: float = math.nan     # the model optimum (trusted region, no dead band)
    p_m_opt_barg: float = math.nan
    p_m_gm_barg: float = math.nan
    dCOP_opt_pct: float = math.nan
    dCOP_opt_sd_pct: float = math.nan
    dQ_sink_opt_pct: float = math.nan
    dCOP_model_opt_pct: float = math.nan
    dQ_sink_model_opt_pct: float = math.nan
    dCOP_gm_pct: float = math.nan
    dQ_sink_gm_pct: float = math.nan
    hs_saturated_opt: bool = False
    advice_trusted_lo_barg: float = math.nan    # the p_m stretch the learned curves vouch for
    advice_trusted_hi_barg: float = math.nan
    optimizer: str = ""                         # "search" | "surrogate:basic" | "surrogate:extended"
    advice_confident: bool = False
    advice_note: str = ""
    optimization_ok: bool = False
    calibration_ok: bool = False
    coverage_share: float = math.nan
    eta_is_LS_resid: float = math.nan
    eta_is_HS_resid: float = math.nan
    eta_is_LS_drift_pct: float = math.nan
    eta_is_HS_drift_pct: float = math.nan
    drive_factor_LS: float = math.nan
    drive_factor_HS: float = math.nan
    T_c_location: str = ""
    # ---- issue 10: fouling forecast since the last reset, cost of fouling, CIP plan (model.analysis.cip)
    days_since_reset: float = math.nan          # the last reset: commissioning (first window) or a CIP's end
    forecast_at: str = ""                       # window end + horizon
    R_th_f_forecast_K_per_kW: float = math.nan
    R_th_f_forecast_lo_K_per_kW: float = math.nan   # prediction band (cip.band_level, 90 %)
    R_th_f_forecast_hi_K_per_kW: float = math.nan
    forecast_law: str = ""                      # "kern_seaton" | "linear" | "" (no forecast)
    fouling_rate_K_per_kW_per_day: float = math.nan
    R_th_f_limit_in_days: float = math.nan      # until the forecast reaches cip.R_th_f_limit_K_per_kW
    fouling_cost_eur_per_day: float = math.nan  # against a clean evaporator (compressors, pumps, lost heat)
    fouling_cost_vs_post_eur_per_day: float = math.nan   # against the level right after the last reset
    fouling_cost_cum_eur: float = math.nan      # since the last reset
    fouling_compressor_kW: float = math.nan     # extra compressor electricity at equal heat
    fouling_pump_kW: float = math.nan           # extra source-pump electricity
    fouling_lost_heat_kW: float = math.nan      # heat not delivered: LS at its speed limit
    electricity_price_eur_per_MWh: float = math.nan
    cip_cost_eur: float = math.nan              # one CIP: direct + heat replaced - electricity saved
    days_to_recommended_cip: float = math.nan
    recommended_cip: str = ""
    cip_interval_opt_days: float = math.nan     # T* of the cost-optimal steady cycle
    cip_cost_opt_eur_per_day: float = math.nan  # J(T*)
    cip_saving_eur_per_year: float = math.nan   # against the plant's median (or configured) interval
    removal_share: float = math.nan             # share of R_th,f a CIP removes (learned or configured)
    forecast_note: str = ""                     # why a figure is missing
    detail: dict = field(default_factory=dict)  # calibration document etc. (not a CSV column)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def row(self) -> dict:
        """A windows.csv row: units in the names (%, bar(g), K/kW), nrmse_* as fractions."""
        # the fields but ``detail`` (all plain values: ``asdict`` would deep-copy detail first)
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "detail"}

    def advisory_values(self) -> dict:
        """Advisory block field name -> value in the block's unit (see config/gateway.yaml)."""
        v = {
            "R_th_f": self.R_th_f_K_per_kW, "R_th_f_share": self.R_th_f_share_pct,
            "CF_dp_f": self.CF_dp_f, "dp_fouling": self.dp_fouling_bar,
            "nrmse_pct": 100.0 * self.calibration_objective,
            "COP_measured": self.COP_measured, "COP_adaptive": self.COP_adaptive,
            "COP_fixed": self.COP_fixed,
        }
        if self.optimization_ok:
            v.update({"p_m_sp_rec": self.p_m_sp_opt_barg, "dCOP_pct": self.dCOP_opt_pct,
                      "dQ_sink_pct": self.dQ_sink_opt_pct, "p_m_gm": self.p_m_gm_barg,
                      "dCOP_sd_pct": self.dCOP_opt_sd_pct})
        v.update({"eta_is_LS_drift": self.eta_is_LS_drift_pct,
                  "eta_is_HS_drift": self.eta_is_HS_drift_pct})
        # issue 10 (NaN = no value yet: not enough windows since the last reset, no plan, ...)
        v.update({"fouling_rate": self.fouling_rate_K_per_kW_per_day,
                  "R_th_f_forecast": self.R_th_f_forecast_K_per_kW,
                  "days_to_cip": self.days_to_recommended_cip,
                  "fouling_cost": self.fouling_cost_eur_per_day,
                  "fouling_cost_cum": self.fouling_cost_cum_eur})
        return {k: float(x) for k, x in v.items() if x is not None}


ROW_COLUMNS = tuple(k for k in WindowResult.__dataclass_fields__ if k != "detail")


@dataclass
class WindowTask:
    """One window after pass 1 (``AnalysisChain.prepare``): what the expensive analysis needs, and
    nothing of the chain's state (picklable; CoolProp state is built where it runs)."""
    res: WindowResult                           # filled as far as pass 1 got
    data: pd.DataFrame                          # the window's samples (with a timestamp column)
    fixed: PlantParams
    learner: CompressorLearner | None = None    # after this window's update
    der: pd.DataFrame | None = None             # measured side (model.measured.derived + inputs)
    obs: pd.DataFrame | None = None             # compressor observations
    T_out_sp_C: float | None = None             # the LS controller's T_source,out set point
    ls_saturated: np.ndarray | None = None      # samples with the LS at its speed limit
    fouling: CalibrationResult | None = None    # calibrated in pass 1 (change penalty)
    samples: bool = False                       # return the per-sample series (replay)
    done: bool = False                          # res is final (skipped or failed in pass 1)
    tracker: SurrogateTracker | None = None     # the qualified surrogate as of pass 1 (optimizer: auto)
    cost_turn: int = 0                          # the window's turn of the cost levels (cost_levels_for)

    def obs_col(self, name: str) -> np.ndarray:
        """``self.obs[name].to_numpy()``, read once: pass 1, pass 2 and the window's samples read
        the same observation columns (~30 us a read). Not pickled (``__getstate__``)."""
        got = self.__dict__.setdefault("_obs_cols", {})
        a = got.get(name)
        if a is None:
            a = got[name] = self.obs[name].to_numpy()
        return a

    def __getstate__(self):
        d = dict(self.__dict__)
        d.pop("_obs_cols", None)
        return d


@dataclass
class WindowPartial:
    """One window after pass 2 (``AnalysisChain.analyse``)."""
    res: WindowResult
    fouling: CalibrationResult | None = None
    cond_factor: float | None = None
    draft: AdviceDraft | None = None            # the advice up to its dead band
    adaptive: PlantParams | None = None         # the window's adaptive model (calibration succeeded)
    der: pd.DataFrame | None = None             # the measured side
    ev_rows: pd.DataFrame | None = None         # the advice's representative rows and weights
    ev_w: np.ndarray | None = None
    surrogate: dict | None = None               # the surrogate's prediction taken in place of the search
    tracker_row: dict | None = None             # the surrogate tracker's row of this window (pass 2)
    seed: tuple | None = None                   # (VResult, rows): the advice's representative points
                                                # at the actual set points
    cost_runs: dict | None = None               # the cost of fouling's model runs (pass 2, ``_cost_runs``)
    samples: dict | None = None                 # per-sample model series (replay's samples.csv)


COST_COLUMNS = ("Q_sink_kW", "W_total_kW", "Q_source_kW")     # what the cost of fouling's runs give


def _nrmse(sim: np.ndarray, meas: np.ndarray) -> float:
    ok = np.isfinite(sim) & np.isfinite(meas)
    if ok.sum() == 0 or not np.mean(meas[ok]) > 0:
        return math.nan
    return float(np.sqrt(np.mean((sim[ok] - meas[ok]) ** 2)) / np.mean(meas[ok]))


def _ratio(num, den) -> float:
    n = np.asarray(num, dtype=float)
    d = np.asarray(den, dtype=float)
    ok = np.isfinite(n) & np.isfinite(d)
    s = d[ok].sum()
    return float(n[ok].sum() / s) if s > 0 else math.nan


def _epoch(t) -> float:
    """Epoch seconds of a number, ISO 8601 text (UTC when naive), datetime or Timestamp."""
    if isinstance(t, (int, float)) and not isinstance(t, bool):
        return float(t)
    ts = pd.Timestamp(t)
    return float((ts.tz_localize("UTC") if ts.tzinfo is None else ts).timestamp())


def _times(data: pd.DataFrame) -> pd.DatetimeIndex:
    if "timestamp" in data.columns:
        return pd.DatetimeIndex(pd.to_datetime(data["timestamp"], utc=True))
    if isinstance(data.index, pd.DatetimeIndex):
        return data.index.tz_localize("UTC") if data.index.tz is None else data.index
    raise ValueError("window data needs a 'timestamp' column or a DatetimeIndex")


def scale_condenser(params: PlantParams, k: float) -> PlantParams:
    """The condenser unit's three conductances (DSH, condenser, SC) scaled by k."""
    return params.replace(CF_DSH=params.CF_DSH * k, CF_con=params.CF_con * k, CF_SC=params.CF_SC * k)


def condenser_factor(der: pd.DataFrame, params: PlantParams, k0: float = 1.0,
                     points: int = 8, tol_bar: float = 0.002,
                     solution: list | None = None, X: np.ndarray | None = None) -> tuple[float, float]:
    """The factor k on the condenser unit's conductance that makes the model's mean condensing
    pressure equal the measured one over the window (evaluated on ``points`` representative
    operating points at the actual set points), and the model's p_c error before it [bar].

    The initial calibration cannot separate CF_DSH, CF_con and CF_SC (Q_sink and W_total carry the
    same information once Q_source is an input), and a data sheet that is not the plant's leaves the
    fixed model's p_c off by up to a bar at conditions other than commissioning's (the water-side
    film changes with the sink flow): every pressure ratio the learned compressor curves are read at
    moves with it. p_c is measured every minute, so the chain corrects it per window like R_th,f for
    the evaporator. A secant on ln k (p_c falls as k rises; first step from a typical slope of
    COND_SLOPE_BAR bar per unit of ln k), k within [0.3, 3], halving a step back toward the last
    solved k where the model cannot solve every point; (NaN, err) when it does not converge. The
    answer depends on the start ``k0`` only within ``tol_bar`` (the chain starts every window at 1,
    so windows are independent of each other). ``solution``: a list that gets (VResult, rows) of
    the representative points at the factor returned (the chain's later runs start from it).
    ``X``: ``matrix(der)`` when the caller has it."""
    X = matrix(der) if X is None else X
    parts = groups(der, points, X=X)
    rows, w = representative(der, points, parts, X=X)
    meas = der["p_c_bar"].to_numpy(dtype=float)
    target = float(np.nansum([w[i] * np.nanmean(meas[g]) for i, g in enumerate(parts)]) / w.sum())
    lo, hi = math.log(0.3), math.log(3.0)
    rows_in = InputColumns.of(rows)      # read once, not at every trial

    last = [None]       # the previous trial's solution: each trial starts from it

    def err(x: float) -> float:
        f, v = simulate_many(rows_in, params, columns=("p_c_bar",), cond_factor=math.exp(x),
                             seed=last[0], with_result=True, as_columns=True)
        if not solved_mask(f).all():
            return math.nan
        last[0] = v
        return float(np.sum(w * f["p_c_bar"]) / w.sum()) - target

    def found(k: float) -> float:
        if solution is not None and last[0] is not None:
            solution.append((last[0], rows))
        return k

    e1 = err(0.0)
    if not math.isfinite(e1) or not math.isfinite(target):
        return math.nan, e1
    x0, f0 = 0.0, e1
    if abs(f0) < tol_bar:
        return found(1.0), e1
    x1 = math.log(k0) if abs(math.log(k0)) > 1e-6 else min(max(e1 / COND_SLOPE_BAR, -0.5), 0.5)
    for _ in range(COND_MAX_ITER):
        f1 = err(x1)
        backs = 0
        while not math.isfinite(f1) and backs < 6:      # unsolvable there: back toward the last k
            x1 = 0.5 * (x0 + x1)
            f1 = err(x1)
            backs += 1
        if not math.isfinite(f1):
            return math.nan, e1
        if abs(f1) < tol_bar:
            return found(math.exp(x1)), e1
        if f1 == f0:
            break
        x0, f0, x1 = x1, f1, min(max(x1 - f1 * (x1 - x0) / (f1 - f0), lo), hi)
    return math.nan, e1


COND_SLOPE_BAR = 9.0      # typical -dp_c/d(ln k) [bar]: the first secant step of condenser_factor
COND_MAX_ITER = 20


class AnalysisChain:
    """The analysis of SPEC §4-6 and §9 for one plant.

    plant : plant.yaml's parameters (data sheet, prior compressor curves)
    fouling_spec : the fouling calibration (``model.calibration.spec_from_config(extra, "fouling")``)
    settings : ChainSettings (plant.yaml ``advice``, ``compressor_learning``)
    """

    def __init__(self, plant: PlantParams, fouling_spec: CalibrationSpec,
                 settings: ChainSettings | None = None) -> None:
        self.plant = plant
        self.spec = fouling_spec
        self.s = settings or ChainSettings()

    # ---------------------------------------------------------------------------- state
    def fixed_model(self, initial: dict | None, dp_clean: dict | None) -> PlantParams:
        """plant.yaml + the initial calibration and the clean pressure-drop fit, no fouling."""
        return apply_state(self.plant, initial, dp_clean).replace(R_th_f=0.0, CF_dp_f=1.0)

    def new_state(self, initial: dict | None, dp_clean: dict | None,
                  learner: CompressorLearner | None = None) -> ChainState:
        fixed = self.fixed_model(initial, dp_clean)
        if learner is None and self.s.learn_compressors:
            learner = CompressorLearner(fixed, self.s.learning)
        tracker = (SurrogateTracker(self.s.tracker)
                   if self.s.tracker.enabled and self.s.optimize and self.s.use_surrogate else None)
        return ChainState(fixed=fixed, learner=learner, tracker=tracker)

    def commissioning_learner(self, data: pd.DataFrame) -> CompressorLearner | None:
        """The compressor curves learned on the commissioning window (frozen as the drift
        reference). Learn them before the initial calibration and calibrate with them applied: the
        condenser factors then do not absorb the difference between the data sheet's compressors and
        the plant's."""
        if not self.s.learn_compressors:
            return None
        learner = CompressorLearner(self.plant, self.s.learning)
        learner.update(observe(data, self.plant, self.s.learning))
        learner.freeze_commissioning()
        return learner

    def new_segment(self, state: ChainState) -> None:
        """After a CIP or a long stop: the change penalty does not reach across it."""
        state.fouling_previous = None

    def cip(self, state: ChainState, start, end, detected_by: str = "cip", segment: bool = True) -> bool:
        """A CIP from ``start`` to ``end`` (epoch s, ISO text or Timestamps) ended: what it removed
        is remembered (the removal share, the interval, the ending cycle's law for the next fits),
        the forecast and the cumulated cost restart at ``end``, and a new segment begins. Replay
        calls it at each detected CIP, the gateway when it sees one. False (nothing changes) for a
        CIP that ended at or before the last reset. ``segment=False``: the caller starts the new
        segment itself (replay does it in pass 1, ahead of pass 3)."""
        if state.forecast.cip(_epoch(start), _epoch(end), detected_by, self.s.cip):
            if segment:
                self.new_segment(state)
            return True
        return False

    # ---------------------------------------------------------------------------- window
    def window(self, data: pd.DataFrame, state: ChainState) -> WindowResult:
        """Analyse one window of usable samples; updates ``state`` (learner, previous values).

        The three passes in one: ``finish(analyse(prepare(data, state)), state)``."""
        return self.finish(self.analyse(self.prepare(data, state)), state)

    def prepare(self, data: pd.DataFrame, state: ChainState, samples: bool = False,
                pre: tuple | None = None) -> WindowTask:
        """Pass 1 (cheap, in window order): the measured side, the compressor observations and the
        learner's update, the heat-balance check, the LS controller's set point and, with a change
        penalty, the fouling calibration. Returns the window's task: plain data that ``analyse``
        turns into the window's results without ``state`` (so tasks can run in any process).
        ``samples``: the task also returns the per-sample model series (replay's samples.csv).
        ``pre``: (der, records, rows) the measured side of ``data`` computed with other windows'
        samples (a replay's block of windows: ``model.measured.derived`` with ``state.fixed`` on
        all their rows, the stage states recorded then, ``compressors.recorded_stages``): ``der``
        this window's rows of it (index 0..n-1), ``rows`` where they are in the records (a
        slice). The same numbers as computed here (every column is row by row)."""
        ts = _times(data)
        data = data.reset_index(drop=True)
        n = len(data)
        res = WindowResult(window_start=ts[0].isoformat() if n else "",
                           window_end=ts[-1].isoformat() if n else "",
                           t_end=float(ts[-1].timestamp()) if n else math.nan, n_samples=n)
        # the surrogate as pass 2 needs it (fits, not the rows: the task may be pickled)
        tracker = state.tracker.for_window() if self.s.use_surrogate and state.tracker is not None else None
        task = WindowTask(res=res, data=data.assign(timestamp=ts), fixed=state.fixed,
                          learner=state.learner, samples=samples, tracker=tracker)
        if n < self.s.min_samples:
            res.status = f"skipped: {n} usable samples, {self.s.min_samples} needed"
            task.done = True
            return task
        fixed = state.fixed
        with shared_stages():       # derived and observe ask for the same compressor states
            if pre is not None:
                preset_stages(pre[1], pre[2])
            return self._prepare(data, task, res, state, fixed, None if pre is None else pre[0])

    def _prepare(self, data, task, res, state, fixed, der=None) -> WindowTask:
        """``prepare`` past its first checks (``der``: the measured side computed already)."""
        der = derived(data, fixed) if der is None else der
        for c in INPUT_COLUMNS:
            if c not in der.columns:    # (a replay's block of windows has them already)
                der[c] = floats(data[c])
        task.der = der
        res.p_m_sp_actual_barg = float(der["p_m_sp"].mean())
        learner = state.learner
        # ---- compressors: observations, coverage before this window, then learn from it
        if learner is not None:
            obs = observe(task.data, fixed, self.s.learning)
            task.obs = obs
            cov = []
            for st in STAGES:
                pi, nn = task.obs_col(f"pi_{st}"), task.obs_col(f"n_{st}")
                ok = np.isfinite(pi) & np.isfinite(nn)
                d = learner.coverage_distance(st, pi[ok], nn[ok]) if ok.any() else np.array([np.inf])
                cov.append(float(np.mean(d <= 1.0)))
            res.coverage_share = min(cov)
            t_last = learner.t_last
            new = obs if t_last is None else obs[obs["t"].to_numpy(dtype=float) > t_last]
            if len(new):
                learner.update(new)
            res.drive_factor_LS = learner.drive_factor("LS")
            res.drive_factor_HS = learner.drive_factor("HS")
            res.T_c_location = learner.T_c_location()
        # ---- heat balance of the window (shaft power: the electric power over the drive factor)
        d_LS = learner.drive_factor("LS") if learner is not None else fixed.comp_LS.drive_factor
        d_HS = learner.drive_factor("HS") if learner is not None else fixed.comp_HS.drive_factor
        W_shaft = floats(data["W_LS"]) / d_LS + floats(data["W_HS"]) / d_HS
        closure = 100.0 * (der["Q_sink_kW"] - der["Q_source_kW"] - W_shaft) / der["Q_sink_kW"]
        res.heat_balance_pct = float(np.nanmedian(closure))
        if not abs(res.heat_balance_pct) <= self.s.heat_balance_limit_pct:
            res.status = (f"failed: measured heat balance does not close ({res.heat_balance_pct:+.1f} % "
                          f"of the heat output, limit {self.s.heat_balance_limit_pct:g} %): check the "
                          f"water flow meters and temperatures")
            task.done = True
            return task
        # ---- the LS speed controller's set point: T_source,out where the LS is not at its limit
        if self.s.optimize or self.s.cip.enabled:
            n_ls = floats(data["N_LS"]) \
                if "N_LS" in data.columns else np.full(len(der), np.nan)
            n_max = fixed.comp_LS.N_max
            free = np.isfinite(n_ls) & (n_ls < n_max - LS_SATURATED_RPM)
            if free.sum() >= 10:
                state.T_out_sp_C = float(np.median(der["T_source_out"].to_numpy(dtype=float)[free]))
            res.T_source_out_sp_C = state.T_out_sp_C if state.T_out_sp_C is not None else math.nan
            task.T_out_sp_C = state.T_out_sp_C
            sat = np.isfinite(n_ls) & (n_ls >= n_max - LS_SATURATED_RPM)
            res.ls_saturated_share = float(sat.mean())
            task.ls_saturated = sat
        # ---- fouling calibration here only when it depends on the previous window's (penalty)
        if self.spec.change_penalty > 0:
            base = learner.apply(fixed) if learner is not None else fixed
            fc = self._calibrate(res, der, base, state.fouling_previous)
            task.fouling = fc
            if fc is not None:
                state.fouling_previous = fc.params
            else:
                task.done = True
        if not task.done:
            task.cost_turn = state.cost_turn
            state.cost_turn += 1
        return task

    def _calibrate(self, res: WindowResult, der: pd.DataFrame, base: PlantParams,
                   previous: dict | None) -> CalibrationResult | None:
        """The window's fouling calibration; None (and ``res.status`` failed) when it fails."""
        # (``der`` itself: the calibration reads the inputs and its goals' columns alone, as it
        # would from a copy of these columns; the copy cost 0.4 ms a window)
        try:
            fc = calibrate(der, base, self.spec, previous=previous,
                           window=(res.window_start, res.window_end))
        except (CalibrationError, ValueError, ArithmeticError) as exc:
            res.status = f"failed: fouling calibration: {exc}"
            return None
        if not fc.success or not all(math.isfinite(v) for v in fc.params.values()):
            res.status = f"failed: fouling calibration: {fc.message}"
            res.detail["calibration"] = fc.to_dict()
            return None
        return fc

    def analyse(self, task: WindowTask) -> WindowPartial:
        """Pass 2 (the expensive part, any order, any process): fouling calibration, the condenser
        unit's factor, the model figures, the compressor residuals and the advice up to its dead
        band (``model.analysis.advice.draft_advice``). Uses nothing but the task."""
        res = task.res
        out = WindowPartial(res=res)
        try:
            if not task.done:
                self._analyse(task, out)
        finally:
            if task.samples:
                out.samples = _window_samples(task, res)
                res.detail.pop("model_series", None)
                res.detail.pop("adaptive_params", None)
        return out

    def _analyse(self, task: WindowTask, out: WindowPartial) -> None:
        res, der, fixed, learner, obs = task.res, task.der, task.fixed, task.learner, task.obs
        base = learner.apply(fixed) if learner is not None else fixed
        # ---- fouling calibration
        fc = task.fouling
        if fc is None:
            fc = self._calibrate(res, der, base, None)
            if fc is None:
                return
        res.calibration_ok = True
        out.fouling = fc
        adaptive = fc.apply(base)
        # the condenser unit's conductance to this window's measured condensing pressure
        seed = None         # solutions of the window's representative points: later runs start there
        # the window's inputs, read once: the condenser factor's and the cost runs' representative
        # points and the model figures read the same six columns of ``der`` (each read ~30 us)
        der_in = InputColumns.of(der)
        X_in = matrix(der_in)
        if self.s.condenser_correction:
            sol = []
            k, err = condenser_factor(der, adaptive, 1.0, self.s.advice.representative_points,
                                      solution=sol, X=X_in)
            seed = sol[0] if sol and math.isfinite(k) else None
            res.CF_cond_window = k
            res.p_c_error_bar = err
            if math.isfinite(k):
                out.cond_factor = k
                adaptive = scale_condenser(adaptive, k)
                base = scale_condenser(base, k)
        res.detail["calibration"] = fc.to_dict()
        res.detail["adaptive_params"] = adaptive
        self._fouling_figures(res, fc, fixed, adaptive, der)
        self._model_figures(res, der, base.replace(R_th_f=0.0, CF_dp_f=1.0), adaptive, seed, der_in)
        # ---- compressor residuals and drift at this window's operating point
        if learner is not None and obs is not None:
            for st in STAGES:
                pi, nn = task.obs_col(f"pi_{st}"), task.obs_col(f"n_{st}")
                e = obs[f"eta_is_{st}"].to_numpy()
                ok = np.isfinite(pi) & np.isfinite(nn) & np.isfinite(e)
                if ok.sum() >= 5:
                    curve = learner.eta_is(st, pi[ok], nn[ok])
                    setattr(res, f"eta_is_{st}_resid", float(np.mean(e[ok] - curve)))
                    setattr(res, f"eta_is_{st}_drift_pct",
                            learner.drift_pct(st, float(np.median(pi[ok])), float(np.median(nn[ok]))))
        # the LS speed controller's set point (pass 1): where the LS is at its speed limit
        # (T_source,out floating above the set point), the advice and the cost of fouling start
        # from the set point, so that a set point giving the LS more capacity can bring
        # T_source,out down, and a cleaner evaporator shows the heat fouling cost
        adv_in = der
        sat = task.ls_saturated
        if sat is not None and sat.any() and task.T_out_sp_C is not None:
            t_out = der["T_source_out"].to_numpy(dtype=float)
            adv_in = der.assign(T_source_out=np.where(sat, np.minimum(t_out, task.T_out_sp_C), t_out))
        out.adaptive, out.der = adaptive, der     # pass 3: forecast, tracker
        # ---- advice up to its dead band
        if self.s.optimize:
            measured = None
            if obs is not None:
                measured = {f"{q}_{st}": np.asarray(task.obs_col(f"{q}_{st}"), dtype=float)
                            for st in STAGES for q in ("pi", "n")}
            # the surrogate fitted from earlier windows' optima, once it qualifies (issue #8 item 7)
            checked = check_rows(adv_in, self.s.advice)
            ev_rows, ev_w = checked.rows, checked.w
            override, used = None, None
            if self.s.use_surrogate and task.tracker is not None:
                pred = task.tracker.predict_setpoint(ev_rows, ev_w, adaptive)
                if pred is not None:
                    override, used = pred
            # the tracker's row of this window (when it takes one) from the advice's own solutions,
            # its search run beside the advice's (``draft_advice``'s ``track``)
            track = (task.tracker.s.reference_p_m_sp_barg
                     if task.tracker is not None and task.tracker.takes_next() else None)
            try:
                out.draft = draft_advice(
                    adv_in, adaptive, learner, self.s.advice,
                    coverage_share=res.coverage_share if learner is not None else 1.0,
                    curve_residual={st: getattr(res, f"eta_is_{st}_resid") for st in STAGES},
                    R_th_f_se_K_per_kW=res.R_th_f_se_K_per_kW, measured=measured, sp_override=override,
                    seed=seed, checked=checked, track=track)
                out.ev_rows, out.ev_w, out.surrogate = ev_rows, ev_w, used
                d = out.draft
                base_pt = d.ev._cache.get(None) if d.ev is not None else None
                if base_pt is not None and base_pt.vres is not None:
                    out.seed = (base_pt.vres, d.rows)
                if track is not None and d.ev is not None:
                    out.ev_rows, out.ev_w = d.rows, d.w
                    out.tracker_row = optimum_row(d.rows, d.w, adaptive, track, res.t_end,
                                                  ev=d.ev, bounds=(d.lo, d.hi), searched=d.tracked)
                d.tracked = None
            except (OptimizationError, ValueError, ArithmeticError) as exc:
                res.status = f"failed: set-point optimization: {exc}"
        # ---- the cost of fouling's model runs (issue 10): every level pass 3 may need
        if self.s.cip.enabled:
            out.cost_runs = self._cost_runs(res, adv_in, adaptive, out.seed, task.cost_turn,
                                            X_in if adv_in is der else None)

    def finish(self, partial: WindowPartial, state: ChainState) -> WindowResult:
        """Pass 3 of one window (``finish_chunk`` of it alone)."""
        return self.finish_chunk([partial], state)[0]

    def finish_chunk(self, partials: list, state: ChainState, before=None) -> list:
        """Pass 3 (in window order) of consecutive windows: what depends on the windows before — the
        fouling forecast, the cost of fouling and the CIP plan (issue 10), the dead band on the
        previous confident recommendation, the surrogate tracker — and the state handed on.
        ``before(partial)`` is called before each window's pass 3 (replay: the CIPs that ended
        before it). Returns the windows' results.

        The dead band's model runs at a kept recommendation (``Settling.runs``: the whole window
        and the uncertainty draws there; until stop 54 ~3 of the dead band's ~4 ms a window of a
        plant-year, one solver call after the other) wait until the chunk's windows are through
        the rest and then run in lockstep (``model.lockstep``: their solver calls answered
        together). No later window's pass 3 depends on them: such a window keeps the
        recommendation the next window's dead band holds to whatever its figures, and a failure
        there (the kept set point does not solve every sample) fails only its own result. The
        advice's figures and the surrogate tracker then take the windows in order, as one window
        at a time would (``tests/test_advice.py``: the same windows as one at a time)."""
        done = []
        for partial in partials:
            if before is not None:
                before(partial)
            res = partial.res
            if partial.fouling is not None:
                state.last_fouling = partial.fouling
            if partial.cond_factor is not None:
                state.cond_factor = partial.cond_factor
            # ---- issue 10: forecast since the last reset, cost of fouling, CIP plan
            if self.s.cip.enabled and partial.cost_runs is not None:
                self._forecast(res, partial, state)
            settling = adv = None
            if partial.draft is not None and res.ok:
                settling, adv = settle_now(partial.draft, state.last_rec_barg)
                if isinstance(adv, AdviceResult) and adv.confident:
                    state.last_rec_barg = adv.p_m_sp_rec_barg
            done.append([partial, settling, adv])
        waiting = [d for d in done if d[2] is None and d[1] is not None]
        if waiting:
            for d, a in zip(waiting, settle_kept([d[1] for d in waiting])):
                d[2] = a
        for partial, settling, adv in done:
            res = partial.res
            if isinstance(adv, Exception):
                res.status = f"failed: set-point optimization: {adv}"
            elif adv is not None:
                used = partial.surrogate
                self._advice_figures(res, adv)
                res.optimizer = (f"surrogate:{used['form']}" if adv.optimizer == "surrogate" and used
                                 else "search")
                if used is not None:
                    res.detail["surrogate"] = used
                if state.tracker is not None and partial.ev_rows is not None:
                    state.tracker.window(partial.ev_rows, partial.ev_w, partial.adaptive, res.t_end,
                                         own=partial.tracker_row)
        return [partial.res for partial, _, _ in done]

    # ---- issue 10 ------------------------------------------------------------------------------
    def _cost_runs(self, res: WindowResult, cost_in: pd.DataFrame, adaptive: PlantParams,
                   seed: tuple | None, turn: int, X: np.ndarray | None = None) -> dict:
        """Pass 2 of the cost of fouling: the adaptive model at R_th,f 0, the window's level and the
        window's turn of the cost levels (``cip.cost_levels_per_window`` of
        ``cip.cost_levels_K_per_kW``, ``cost_levels_for``) on ``cip.cost_points`` representative
        operating points of the window, the LS saturating as the plant's does (heat lost at its
        speed limit is part of the cost); each row starts from the nearest of the advice's
        solutions. In pass 2, so that a replay answers the calls of the windows in lockstep
        together. {"levels": [K/kW], "frames": [per level the runs' columns as arrays, status and
        reason (``simulate_many``'s ``as_columns``)], "rows", "w", "seconds",
        "cpu_seconds"} (the times: the gateway's, one window at a time; in a replay's lockstep they
        include the other windows' turns). ``X``: ``matrix(cost_in)`` when the caller has it."""
        t0, c0 = time.perf_counter(), time.thread_time()
        c = self.s.cip
        R = res.R_th_f_K_per_kW
        levels = sorted({0.0, *cost_levels_for(c, turn), *((R,) if math.isfinite(R) and R >= 0 else ())})
        rows, w = representative(cost_in, c.cost_points, X=X)
        k = len(rows)
        sd, seed_rows = seed if seed is not None else (None, None)
        # the rows once per level (as input columns: the numbers their concatenated frame gives)
        tiled = InputColumns({col: np.tile(a, len(levels)) for col, a in InputColumns.of(rows).cols.items()})
        allf = simulate_many(tiled, adaptive, columns=COST_COLUMNS, ls_mode="float",
                             R_th_f=np.repeat(np.asarray(levels) * 1e-3, k), seed=sd, seed_rows=seed_rows,
                             as_columns=True)
        frames = [{col: a[i * k:(i + 1) * k] for col, a in allf.items()} for i in range(len(levels))]
        return {"levels": levels, "frames": frames, "rows": rows, "w": w,
                "seconds": time.perf_counter() - t0, "cpu_seconds": time.thread_time() - c0}

    def _forecast(self, res: WindowResult, partial: WindowPartial, state: ChainState) -> None:
        """Pass 3 of the cost of fouling and the forecast: pass 2's model runs (``_cost_runs``) as
        the window's ``LevelRuns`` on the operating points the model solves at R_th,f 0 and at the
        window's level (a cost level where one of them fails is left out of the window's runs;
        before stop 24 it left the window without a cost); the plan's cost curve is the cost levels' mean over
        ``cip.cost_average_hours``; the level after the last reset, for the cost against it, is
        interpolated between the levels run), then ``cip.forecast_window``: the estimates join the
        forecast since the last reset, the window is priced, the cost cumulated and the CIP
        planned."""
        t0, c0 = time.perf_counter(), time.thread_time()
        c = self.s.cip
        fs = state.forecast
        der, fixed = partial.der, state.fixed
        R = res.R_th_f_K_per_kW
        cr = partial.cost_runs
        levels, frames, rows, w = cr["levels"], cr["frames"], cr["rows"], cr["w"]
        cols = COST_COLUMNS
        # the operating points the model solves at R_th,f 0 and at the window's level (what the cost
        # needs); a cost level at which one of them fails is dropped, not the window
        solved = [solved_mask(f) for f in frames]
        need = [i for i, x in enumerate(levels) if x == 0.0 or x == R]
        keep = np.logical_and.reduce([solved[i] for i in need])
        used = [i for i in range(len(levels)) if i in need or solved[i][keep].all()]
        dropped = [levels[i] for i in range(len(levels)) if i not in used]
        levels, frames = [levels[i] for i in used], [frames[i] for i in used]
        runs, note = None, ""
        if keep.any():
            ww = w[keep] / w[keep].sum()
            sums = [[float(np.sum(ww * f[k][keep])) for f in frames] for k in cols]
            try:
                runs = LevelRuns(np.array(levels), *sums)
            except CostError as exc:
                note = str(exc)
        V = der["V_source"].to_numpy(dtype=float)
        wf = forecast_window(fs, c, start_s=_epoch(res.window_start), end_s=res.t_end, R=R,
                             R_se=res.R_th_f_se_K_per_kW, CF=res.CF_dp_f, CF_se=res.CF_dp_f_se, runs=runs,
                             V_source_m3_per_h=float(np.nanmean(V)),
                             dp_clean_bar=float(np.nanmean(fixed.dp_clean(V * M3H)) / BAR))
        if note:
            wf.notes.append(f"cost of fouling: {note}")
        for k, v in wf.fields().items():
            setattr(res, k, v)
        res.detail["cip"] = {"text": explain(wf, c), "levels_K_per_kW": levels,
                             "runs": None if runs is None else {"Q_sink_kW": list(runs.Q_sink_kW),
                                                                 "W_kW": list(runs.W_kW),
                                                                 "Q_source_kW": list(runs.Q_source_kW)},
                             "levels_dropped_K_per_kW": dropped,
                             "rows_solved": int(keep.sum()), "rows": int(len(keep)),
                             "seconds": cr["seconds"] + time.perf_counter() - t0,
                             "cpu_seconds": cr["cpu_seconds"] + time.thread_time() - c0}
        res.detail["cost_rows"] = rows.iloc[np.flatnonzero(keep)], w[keep]

    def _fouling_figures(self, res: WindowResult, fc: CalibrationResult, fixed: PlantParams,
                         adaptive: PlantParams, der: pd.DataFrame) -> None:
        R = fc.params.get("R_th_f_K_per_kW", adaptive.R_th_f * 1e3)
        CF = fc.params.get("CF_dp_f", adaptive.CF_dp_f)
        V = der["V_source"].to_numpy(dtype=float) * M3H
        res.R_th_f_K_per_kW = float(R)
        res.R_th_f_se_K_per_kW = float(fc.std_errors.get("R_th_f_K_per_kW", math.nan))
        res.R_th_f_share_pct = 100.0 * evaporator_share(adaptive)
        res.CF_dp_f = float(CF)
        res.CF_dp_f_se = float(fc.std_errors.get("CF_dp_f", math.nan))
        res.dp_fouling_bar = float((CF - 1.0) * np.mean(fixed.dp_clean(V)) / BAR)
        res.nrmse_p_e = fc.nrmse.get("p_e", math.nan)
        res.nrmse_dp_source = fc.nrmse.get("dp_source", math.nan)
        res.calibration_objective = float(fc.objective)
        res.calibration_warnings = "; ".join(fc.warnings)

    def _model_figures(self, res: WindowResult, der: pd.DataFrame, fixed: PlantParams,
                       adaptive: PlantParams, seed: tuple | None = None,
                       inputs: InputColumns | None = None) -> None:
        """The window's model figures (``inputs``: ``InputColumns.of(der)`` when the caller has it)."""
        cols = ("Q_sink_kW", "W_total_kW", "COP", "p_e_bar")
        n = len(der)
        keep = np.unique(np.linspace(0, n - 1, min(int(self.s.figure_rows), n)).round().astype(int))
        # the fixed model is the adaptive one without fouling (R_th,f 0; CF_dp,f does not enter the
        # cycle): both in one call, the fixed rows per-row R_th,f 0 (the rows as input columns and
        # the results as arrays: the numbers DataFrames of them give, without building them)
        m = len(keep)
        inputs = InputColumns.of(der) if inputs is None else inputs
        both_in = InputColumns({c: np.concatenate([a, a]) for c, a in
                                ((c, a[keep]) for c, a in inputs.cols.items())})
        sim = simulate_many(both_in, adaptive, columns=cols,
                            R_th_f=np.r_[np.full(m, fixed.R_th_f), np.full(m, adaptive.R_th_f)],
                            seed=seed[0] if seed else None, seed_rows=seed[1] if seed else None,
                            as_columns=True)
        sim_f = {c: sim[c][:m] for c in (*cols, "status")}
        sim_a = {c: sim[c][m:] for c in (*cols, "status")}
        both = solved_mask(sim_f) & solved_mask(sim_a)
        meas_cop = der["COP"].to_numpy(dtype=float)[keep][both]
        meas_q = der["Q_sink_kW"].to_numpy(dtype=float)[keep][both]
        res.nrmse_COP_fixed = _nrmse(sim_f["COP"][both], meas_cop)
        res.nrmse_COP_adaptive = _nrmse(sim_a["COP"][both], meas_cop)
        res.nrmse_Q_sink_fixed = _nrmse(sim_f["Q_sink_kW"][both], meas_q)
        res.nrmse_Q_sink_adaptive = _nrmse(sim_a["Q_sink_kW"][both], meas_q)
        res.COP_measured = _ratio(der["Q_sink_kW"], der["W_total_kW"])
        res.COP_fixed = _ratio(sim_f["Q_sink_kW"][both], sim_f["W_total_kW"][both])
        res.COP_adaptive = _ratio(sim_a["Q_sink_kW"][both], sim_a["W_total_kW"][both])
        # the per-sample series (replay's samples.csv): the rows' positions in the window and
        # their columns
        res.detail["model_series"] = {"at": der.index.to_numpy()[keep].astype(int),
                                      "fixed": sim_f, "adaptive": sim_a}

    @staticmethod
    def _advice_figures(res: WindowResult, adv: AdviceResult) -> None:
        res.optimization_ok = True
        res.p_m_sp_opt_barg = adv.p_m_sp_rec_barg
        res.p_m_sp_model_opt_barg = adv.p_m_sp_model_opt_barg
        res.p_m_opt_barg = adv.p_m_opt_barg
        res.p_m_gm_barg = adv.p_m_gm_barg
        res.dCOP_opt_pct = adv.dCOP_pct
        res.dCOP_opt_sd_pct = adv.dCOP_sd_pct
        res.dQ_sink_opt_pct = adv.dQ_sink_pct
        res.dCOP_model_opt_pct = adv.dCOP_model_opt_pct
        res.dQ_sink_model_opt_pct = adv.dQ_sink_model_opt_pct
        res.dCOP_gm_pct = adv.dCOP_gm_pct
        res.dQ_sink_gm_pct = adv.dQ_sink_gm_pct
        res.hs_saturated_opt = adv.hs_saturated
        res.advice_trusted_lo_barg = adv.trusted_lo_barg
        res.advice_trusted_hi_barg = adv.trusted_hi_barg
        res.advice_confident = adv.confident
        res.advice_note = adv.note
        res.detail["advice"] = _plain(adv)


def settle_now(draft: AdviceDraft, previous_rec_barg: float | None) -> tuple:
    """(the dead band's ``Settling``, the ``AdviceResult`` — or the exception that failed the
    window's advice — where it needs no model run, else None: ``settle_kept``)."""
    try:
        st = decide_settling(draft, previous_rec_barg)
        return st, (None if st.runs else finish_settling(st))
    except _ADVICE_FAILS as exc:
        return None, exc


def settle_kept(settlings: list) -> list:
    """``finish_settling`` of each (their model runs in lockstep when there are several): the
    ``AdviceResult`` or the exception that failed the window's advice, in order; any other
    exception is raised."""
    if len(settlings) > 1:
        got = lockstep.run([(lambda st=st: finish_settling(st)) for st in settlings])
    else:
        got = []
        for st in settlings:
            try:
                got.append(finish_settling(st))
            except _ADVICE_FAILS as exc:
                got.append(exc)
    out = []
    for a in got:
        if isinstance(a, lockstep.Failed):
            if not isinstance(a.exc, _ADVICE_FAILS):
                raise a.exc
            a = a.exc
        out.append(a)
    return out


def _plain(obj):
    """``dataclasses.asdict(obj)`` by value for a dataclass whose fields are plain values, dicts of
    them, tuples and dataclasses of such fields (the advice): tuples are shared, not rebuilt
    element by element (immutable; a trusted stretch's path has ~100 of them, which ``asdict``
    copied in ~0.3 ms a window)."""
    out = {}
    for f in fields(obj):
        v = getattr(obj, f.name)
        if isinstance(v, dict):
            v = dict(v)
        elif is_dataclass(v):
            v = _plain(v)
        out[f.name] = v
    return out


def _window_samples(task: WindowTask, res: WindowResult) -> dict:
    """Per-sample model series of one window (replay's samples.csv): the model figures' COP, heat
    output and evaporating pressure (on the evenly spaced figure rows) and the learned eta_is curve
    at each sample; as columns (arrays of the window's length; ``window_start`` one text), which
    replay puts into one frame for all windows (``replay.frame_of_parts``)."""
    data = task.data
    ts = data["timestamp"].array            # (compact: not an object array of Timestamps)
    # the columns first, the frame once (inserting them one by one costs pandas' checks each time)
    cols: dict = {"timestamp": ts, "window_start": res.window_start}
    series = res.detail.get("model_series")
    if series is not None:
        at = series["at"]
        for kind in ("fixed", "adaptive"):
            f = series[kind]
            for col, name in (("COP", f"COP_{kind}"), ("Q_sink_kW", f"Q_sink_kW_{kind}"),
                              ("p_e_bar", f"p_e_bar_{kind}")):
                v = np.full(len(ts), np.nan)
                v[at] = f[col]
                cols[name] = v
    learner = task.learner
    if learner is not None:
        obs = task.obs if task.obs is not None else observe(data, task.fixed, learner.s)
        for st in STAGES:
            pi, n = ((task.obs_col(f"pi_{st}"), task.obs_col(f"n_{st}")) if task.obs is not None
                     else (obs[f"pi_{st}"].to_numpy(), obs[f"n_{st}"].to_numpy()))
            ok = np.isfinite(pi) & np.isfinite(n)
            v = np.full(len(obs), np.nan)
            if ok.any():
                v[ok] = learner.eta_is(st, pi[ok], n[ok])
            cols[f"eta_is_{st}_model"] = v
    return cols
