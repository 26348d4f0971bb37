"""One window's fouling forecast, cost of fouling and CIP advice (issue 10): the chain's entry point.

After each fouling calibration the analysis chain calls ``window_cost`` (the window's cost figures)
and ``advise_cip`` (the forecast since the last reset and the CIP plan). Both are pure: the chain
supplies the window estimates since the last reset, the model's period COPs (it already runs the
fixed = clean model and the adaptive model on the window), the removal shares learned from past CIPs
(``cost.estimate_removal_share``) and, optionally, the law of earlier cycles (``forecast.law_prior``
over each completed cycle's prior-free fit). It keeps the running ``cost.CostTally`` since the reset.

What the advice carries maps one-to-one onto the issue's outputs: the fouling rate now
[K/kW per day], R_th,f at the horizon with its 90 % band, the date R_th,f reaches a limit, the
fouling cost per day, days to the recommended CIP and the expected saving per year
(``CipAdvice.row()`` gives forecast.csv's columns).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone

import numpy as np

from .cost import (CipPlan, CostCurve, CostError, CostTally, FoulingComponent, LevelRuns, PriceSeries,
                   RemovalShare, cleaning_cost_eur, compressor_cost_curve, cost_rate_eur_per_day,
                   estimate_removal_share, extra_compressor_power_kW, fouling_cost_curve,
                   fouling_cost_terms, mean_price, median_interval_days as _median_interval,
                   plan_cip, pump_cost_curve, pump_extra_power_kW, DEFAULT_ETA_PUMP, SECONDS_PER_DAY)
from .forecast import (DEFAULT_HORIZON_DAYS, DEFAULT_LEVEL, FitSettings, FoulingFit, ForecastError,
                       LawPrior, LimitCrossing, Prediction, fit_fouling, law_prior)


class CipConfigError(ValueError):
    """plant.yaml's ``cip:`` section has a bad key or value; the message names the key."""


@dataclass(frozen=True)
class CipSettings:
    """Prices, CIP costs and forecast settings (plant.yaml ``cip:``, ``from_config``).

    electricity_price_eur_per_MWh : a constant, a PriceSeries, or None when plant.yaml names a price
        CSV the caller has not loaded (the cost is then not computed, and the notes say why)
    """
    electricity_price_eur_per_MWh: float | PriceSeries | None = 100.0
    eta_pump: float = DEFAULT_ETA_PUMP
    cip_direct_cost_eur: float = 2000.0
    cip_downtime_h: float = 60.0
    replacement_heat_eur_per_MWh: float = 45.0
    removal_share_default: float = 0.15
    removal_share_spread_default: float = 0.05
    dp_removal_share_default: float = 0.30
    horizon_days: float = DEFAULT_HORIZON_DAYS
    band_level: float = DEFAULT_LEVEL
    R_limit_K_per_kW: float | None = None
    current_interval_days: float | None = None
    trigger: str = "level"
    uncertain: bool = True
    fit: FitSettings = field(default_factory=FitSettings)
    # the analysis chain's forecast step (ForecastState, forecast_window)
    enabled: bool = True
    cost_levels_K_per_kW: tuple = (2.0e-3, 4.0e-3, 6.0e-3, 8.0e-3)   # the plan's cost curve (and 0)
    cost_levels_per_window: int = 2      # of them run per window, in turn (the plan averages)
    cost_average_hours: float = 168.0    # the plan's cost curve: mean over this much of operation
    cost_points: int = 4                 # representative operating points of the cost model runs
    tally_max_gap_h: float = 1.0         # gaps between windows bridged in the cumulated cost
    max_estimates: int = 5000            # window estimates kept since the last reset (older thinned)
    price_csv: str | None = None         # plant.yaml's electricity_price_csv (for messages)

    @classmethod
    def from_config(cls, extra: dict | None, price: PriceSeries | None = None, **overrides) -> "CipSettings":
        """plant.yaml's ``cip:`` section (every key optional). ``price``: the series of
        ``cip.electricity_price_csv``, read by the caller (``edge.io.prices``): model/ reads no
        files. CipConfigError names the key."""
        sec = (extra or {}).get("cip")
        if sec is None:
            sec = {}
        if not isinstance(sec, dict):
            raise CipConfigError(f"key 'cip': expected a mapping, got {type(sec).__name__}")
        unknown = sorted(set(sec) - set(CIP_KEYS))
        if unknown:
            raise CipConfigError(f"key 'cip.{unknown[0]}': unknown (known: {', '.join(sorted(CIP_KEYS))})")
        kw: dict = {}
        for key, (attr, check, what) in CIP_KEYS.items():
            if key not in sec:
                continue
            v = sec[key]
            ok = False
            try:
                ok = check(v)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise CipConfigError(f"key 'cip.{key}': expected {what}, got {v!r}")
            if key == "cost_levels_K_per_kW":
                v = tuple(float(x) for x in v)
            elif key in ("cost_points", "max_estimates", "cost_levels_per_window"):
                v = int(v)
            kw[attr] = v
        if "electricity_price_eur_per_MWh" in sec and "electricity_price_csv" in sec:
            raise CipConfigError("key 'cip.electricity_price_csv': give either a constant "
                                 "electricity_price_eur_per_MWh or a price CSV, not both")
        if "electricity_price_csv" in sec:
            kw["price_csv"] = sec["electricity_price_csv"]
            kw["electricity_price_eur_per_MWh"] = price
        elif price is not None:
            kw["electricity_price_eur_per_MWh"] = price
        if "removal_share_default" in kw:
            kw["removal_share_default"] = float(kw["removal_share_default"])
        kw.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kw)


def _num(lo=None, hi=None, lo_open=False, hi_open=False, integer=False):
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return False
        if integer and not float(v).is_integer():
            return False
        if lo is not None and (v <= lo if lo_open else v < lo):
            return False
        return not (hi is not None and (v >= hi if hi_open else v > hi))
    return check


def _levels(v):
    return (isinstance(v, (list, tuple)) and 1 <= len(v) <= 20
            and all(_num(0.0, 0.05, lo_open=True)(x) for x in v) and len(set(v)) == len(v))


# plant.yaml key -> (CipSettings field, check, what the message says is expected)
CIP_KEYS = {
    "enabled": ("enabled", lambda v: isinstance(v, bool), "true or false"),
    "electricity_price_eur_per_MWh": ("electricity_price_eur_per_MWh", _num(), "a number [EUR/MWh]"),
    "electricity_price_csv": ("price_csv", lambda v: isinstance(v, str) and v.strip() != "",
                              "a path to a CSV with columns timestamp, eur_per_MWh"),
    "pump_efficiency": ("eta_pump", _num(0.0, 1.0, lo_open=True), "a number in (0, 1]"),
    "direct_cost_eur": ("cip_direct_cost_eur", _num(0.0), "a number >= 0 [EUR]"),
    "downtime_h": ("cip_downtime_h", _num(0.0, 24.0 * 60), "a number of hours in 0..1440"),
    "replacement_heat_eur_per_MWh": ("replacement_heat_eur_per_MWh", _num(0.0), "a number >= 0 [EUR/MWh]"),
    "removal_share_default": ("removal_share_default", _num(0.0, 1.0, lo_open=True), "a share in (0, 1]"),
    "dp_removal_share_default": ("dp_removal_share_default", _num(0.0, 1.0), "a share in 0..1"),
    "horizon_days": ("horizon_days", _num(0.0, 365.0), "a number of days in 0..365"),
    "band_level": ("band_level", _num(0.0, 1.0, lo_open=True, hi_open=True), "a level in (0, 1), e.g. 0.9"),
    "R_th_f_limit_K_per_kW": ("R_limit_K_per_kW", lambda v: v is None or _num(0.0, 0.05, lo_open=True)(v),
                              "a number > 0 [K/kW] or null"),
    "current_interval_days": ("current_interval_days", lambda v: v is None or _num(0.0, 3650, lo_open=True)(v),
                              "a number of days > 0 or null"),
    "trigger": ("trigger", lambda v: v in ("level", "age"), "'level' or 'age'"),
    "cost_levels_K_per_kW": ("cost_levels_K_per_kW", _levels, "a list of 1..20 levels in (0, 0.05] [K/kW]"),
    "cost_levels_per_window": ("cost_levels_per_window", _num(1, 20, integer=True), "a whole number in 1..20"),
    "cost_average_hours": ("cost_average_hours", _num(0.0, 24.0 * 30, lo_open=True),
                           "a number of hours in (0, 720]"),
    "cost_points": ("cost_points", _num(1, 100, integer=True), "a whole number in 1..100"),
    "tally_max_gap_h": ("tally_max_gap_h", _num(0.0, 240.0), "a number of hours in 0..240"),
    "max_estimates": ("max_estimates", _num(100, 100000, integer=True), "a whole number in 100..100000"),
}


@dataclass(frozen=True)
class WindowCost:
    """Cost of fouling in one window; powers [kW], rates [EUR/day]."""
    P_compressor_vs_clean_kW: float
    P_compressor_vs_post_kW: float          # nan without the post-CIP COP
    P_pump_kW: float
    price_eur_per_MWh: float
    cost_eur_per_day: float                 # compressor (vs clean) + pump
    cost_vs_post_eur_per_day: float         # compressor (vs post-CIP) + pump; nan without it

    @property
    def extra_kWh_per_day(self) -> float:
        return (self.P_compressor_vs_clean_kW + self.P_pump_kW) * 24.0


def window_cost(*, Q_sink_kW: float, COP_adaptive: float, COP_clean: float, V_source_m3_per_h: float,
                dp_fouling_bar: float, price, start_s: float, end_s: float, COP_post: float | None = None,
                eta_pump: float = DEFAULT_ETA_PUMP) -> WindowCost:
    """The window's cost of fouling at equal heat delivered (see ``model.analysis.cost``).

    Q_sink_kW : heat delivered (mean over the window) [kW]
    COP_adaptive, COP_clean, COP_post : period COPs of the model at the window's R_th,f, at R_th,f = 0
        (the fixed model) and at the level right after the last CIP [-]
    V_source_m3_per_h, dp_fouling_bar : mean source flow [m3/h] and fouling pressure drop [bar]
        (a negative dp_fouling_bar, CF_dp,f below 1 within its noise, prices no pump saving: 0)
    price : constant [EUR/MWh] or PriceSeries; start_s, end_s : the window [epoch s]
    """
    p = mean_price(price, start_s, end_s)
    Pc = extra_compressor_power_kW(Q_sink_kW, COP_adaptive, COP_clean)
    Pp = pump_extra_power_kW(V_source_m3_per_h, max(dp_fouling_bar, 0.0), eta_pump)
    Ppost = (extra_compressor_power_kW(Q_sink_kW, COP_adaptive, COP_post) if COP_post is not None
             else math.nan)
    return WindowCost(Pc, Ppost, Pp, p, cost_rate_eur_per_day(Pc + Pp, p),
                      cost_rate_eur_per_day(Ppost + Pp, p) if COP_post is not None else math.nan)


@dataclass(frozen=True)
class CipAdvice:
    t_now_days: float                      # days since the last reset
    R_fit: FoulingFit | None
    CF_fit: FoulingFit | None
    R_forecast: Prediction | None          # at t_now + horizon
    R_limit: LimitCrossing | None
    plan: CipPlan | None
    removal: RemovalShare
    notes: tuple = ()

    @property
    def fouling_rate_K_per_kW_per_day(self) -> float:
        return self.R_fit.rate(self.t_now_days) if self.R_fit is not None else math.nan

    @property
    def days_to_cip(self) -> float:
        return self.plan.days_to_cip if self.plan is not None else math.nan

    def row(self) -> dict:
        """forecast.csv's figures of this window (NaN where there is no forecast yet)."""
        f = self.R_forecast
        return {"R_th_f_forecast_K_per_kW": f.value if f else math.nan,
                "R_th_f_forecast_lo_K_per_kW": f.lo if f else math.nan,
                "R_th_f_forecast_hi_K_per_kW": f.hi if f else math.nan,
                "fouling_rate_K_per_kW_per_day": self.fouling_rate_K_per_kW_per_day,
                "days_to_recommended_cip": self.days_to_cip}


def advise_cip(*, t_days, R_K_per_kW, R_se_K_per_kW, t_now_days: float, cop_levels,
               Q_sink_kW: float, settings: CipSettings, start_s: float, end_s: float,
               CF_dp_f=None, CF_dp_f_se=None, V_source_m3_per_h: float | None = None,
               dp_clean_bar: float | None = None, removal: RemovalShare | None = None,
               dp_removal_share: float | None = None, R_prior: LawPrior | None = None,
               CF_prior: LawPrior | None = None, overlap: float = 1.0,
               median_interval_days: float | None = None, cost_curve: CostCurve | None = None,
               cip_cost_eur: float | None = None) -> CipAdvice:
    """Forecast since the last reset and the cost-optimal CIP for one window.

    t_days, R_K_per_kW, R_se_K_per_kW : window estimates since the last reset (t in days since it,
        best the windows' mid-times); CF_dp_f, CF_dp_f_se the same for CF_dp,f (optional)
    t_now_days : now, days since the last reset (the window's end)
    cop_levels : ((R_K_per_kW, ...), (COP, ...)) model period COPs of this window's operation at a
        few R_th,f levels, R = 0 among them (the fixed model); at least one level > 0
    Q_sink_kW : heat delivered [kW]; start_s, end_s : the window [epoch s] (for the price)
    V_source_m3_per_h, dp_clean_bar : for the pump's share (omit both to leave the pump out)
    removal : the share of R_th,f a CIP removes (default: the configured one); dp_removal_share likewise
    median_interval_days : the plant's median past operating time between CIPs, for the saving
        (``cost.median_interval_days``); else settings.current_interval_days
    cost_curve, cip_cost_eur : the analysis chain's f(R_th,f) [EUR/day] (``cost.fouling_cost_curve``:
        lost capacity included) and the cost of one CIP [EUR]; they replace ``cop_levels`` and the
        cleaning cost computed from Q_sink_kW and the settings
    Without enough data since the reset the advice has no forecast and no plan, and says why.
    """
    s = settings
    removal = removal or RemovalShare(s.removal_share_default, s.removal_share_spread_default, 0, "configured")
    notes: list[str] = []
    try:
        R_fit = fit_fouling(t_days, R_K_per_kW, R_se_K_per_kW, prior=R_prior, overlap=overlap,
                            settings=s.fit)
    except ForecastError as exc:
        return CipAdvice(float(t_now_days), None, None, None, None, None, removal, (f"R_th_f: {exc}",))
    CF_fit = None
    if CF_dp_f is not None and V_source_m3_per_h is not None and dp_clean_bar is not None:
        try:
            CF_fit = fit_fouling(t_days, CF_dp_f, CF_dp_f_se, floor=1.0, prior=CF_prior, overlap=overlap,
                                 settings=s.fit)
        except ForecastError as exc:
            notes.append(f"CF_dp_f: {exc}")
    forecast = R_fit.at_horizon(s.horizon_days, t_now_days, s.band_level)
    limit = (R_fit.reach(s.R_limit_K_per_kW, t_now_days, s.band_level)
             if s.R_limit_K_per_kW is not None else None)
    plan = None
    try:
        price = mean_price(_price(s), start_s, end_s)
        if cost_curve is None:
            if cop_levels is None:
                raise CostError("no cost of fouling for this window (see the notes)")
            levels, cops = cop_levels
            if not any(x > 0 for x in levels):
                raise CostError("the cost curve needs a model COP at an R_th,f level above 0")
            cost_curve = compressor_cost_curve(levels, cops, Q_sink_kW, price)
        comps = [FoulingComponent(R_fit, removal.share, cost_curve, "R_th_f", uncertain=s.uncertain)]
        if CF_fit is not None:
            share_dp = s.dp_removal_share_default if dp_removal_share is None else dp_removal_share
            # the pumps' share of the cost is small (~1 % of the compressors'): planned on the mean
            # curve, without the sigma points (half the plan's time)
            comps.append(FoulingComponent(CF_fit, share_dp, pump_cost_curve(dp_clean_bar, V_source_m3_per_h, price,
                                                                            s.eta_pump),
                                          "CF_dp_f", uncertain=False))
        if cip_cost_eur is not None:
            C = float(cip_cost_eur)
        else:
            levels, cops = cop_levels
            cop_clean = cops[list(levels).index(0.0)] if 0.0 in list(levels) else None
            C = cleaning_cost_eur(s.cip_direct_cost_eur, s.cip_downtime_h, Q_sink_kW,
                                  s.replacement_heat_eur_per_MWh, COP_clean=cop_clean,
                                  electricity_eur_per_MWh=price)
        plan = plan_cip(comps, cip_cost_eur=max(C, 0.0), downtime_days=s.cip_downtime_h / 24.0,
                        t_now_days=t_now_days, trigger=s.trigger,
                        T_current_days=(median_interval_days if median_interval_days is not None
                                        else s.current_interval_days))
    except (CostError, ValueError) as exc:
        notes.append(f"CIP plan: {exc}")
    return CipAdvice(float(t_now_days), R_fit, CF_fit, forecast, limit, plan, removal, tuple(notes))


def _price(s: CipSettings):
    if s.electricity_price_eur_per_MWh is None:
        raise CostError(f"the electricity price series (cip.electricity_price_csv: {s.price_csv}) "
                        "was not loaded by the caller")
    return s.electricity_price_eur_per_MWh


def iso(t_s: float) -> str:
    """Epoch seconds -> ISO 8601 UTC ('' for a non-finite time)."""
    if t_s is None or not math.isfinite(t_s):
        return ""
    return datetime.fromtimestamp(float(t_s), timezone.utc).isoformat()


# ---- what the analysis chain keeps between windows ------------------------------------------------------
KEEP_CYCLES = 5          # earlier cycles' fits kept for the law prior
KEEP_CIPS = 20           # past CIPs kept for the removal share and the median interval


def _f(x) -> float:
    return math.nan if x is None else float(x)


@dataclass
class ForecastState:
    """The fouling forecast's memory since the last reset (commissioning or a CIP's end), and what
    the plant's past CIPs taught: the analysis chain keeps it in ``ChainState.forecast``; the
    gateway persists it (``to_dict``/``from_dict``) in chain_state.json.

    reset_s : the last reset [epoch s]; None until the first window (which then is the reset)
    t_s, span_s, R, R_se, CF, CF_se : the window estimates since the reset (mid-time, window length
        [s]; R_th,f and its se [K/kW]; CF_dp,f and its se), at most ``CipSettings.max_estimates``
        (the older half thinned to every second estimate when more)
    tally : the cumulated cost of fouling since the reset (``cost.CostTally``)
    cips : past CIPs, newest last: start_s, end_s, detected_by, the reset before it (reset_s),
        R_before/R_after and CF_before/CF_after (the levels the forecast had at the CIP's start and
        the next cycle's start level), for the removal share and the median interval
    cycle_fits : each completed cycle's prior-free fits (``FoulingFit.to_state``), for ``law_prior``
    last_fit_R, last_fit_CF : the current cycle's latest fits; R_post, CF_post : its start level
    """
    reset_s: float | None = None
    reset_kind: str = ""
    t_s: list = field(default_factory=list)
    span_s: list = field(default_factory=list)
    R: list = field(default_factory=list)
    R_se: list = field(default_factory=list)
    CF: list = field(default_factory=list)
    CF_se: list = field(default_factory=list)
    tally: CostTally = field(default_factory=CostTally)
    cips: list = field(default_factory=list)
    cycle_fits: list = field(default_factory=list)
    last_fit_R: FoulingFit | None = None
    last_fit_CF: FoulingFit | None = None
    R_post: float | None = None
    CF_post: float | None = None
    curve_pts: list = field(default_factory=list)   # [t_end_s, level K/kW, f EUR/day] (not reset)
    cip_costs: list = field(default_factory=list)   # [t_end_s, cost of one CIP EUR] (not reset)
    n_windows: int = 0                              # windows priced

    # ---- the plan's cost curve: the windows of the last cost_average_hours -------------------------

    def add_curve(self, t_end_s: float, points, cip_cost_eur: float, s: CipSettings) -> None:
        cut = t_end_s - s.cost_average_hours * 3600.0
        self.curve_pts = [p for p in self.curve_pts if p[0] > cut] + [[float(t_end_s), float(x), float(f)]
                                                                        for x, f in points]
        self.cip_costs = [c for c in self.cip_costs if c[0] > cut] + [[float(t_end_s), float(cip_cost_eur)]]
        self.n_windows += 1

    def average_curve(self) -> CostCurve | None:
        """f(R_th,f) [EUR/day]: at each cost level the mean over the windows that ran it (0 at 0):
        the plan sees the plant's typical operation and prices, not the last two hours'."""
        if not self.curve_pts:
            return None
        pts = np.array(self.curve_pts, dtype=float)
        lv = np.unique(pts[:, 1])
        f = [float(np.mean(pts[pts[:, 1] == x, 2])) for x in lv]
        return CostCurve(np.concatenate([[0.0], lv]), np.concatenate([[0.0], f]))

    def average_cip_cost(self) -> float | None:
        return float(np.mean([c[1] for c in self.cip_costs])) if self.cip_costs else None

    # ---- estimates -------------------------------------------------------------------------------
    def days(self, t_s) -> np.ndarray:
        return (np.asarray(t_s, dtype=float) - (self.reset_s or 0.0)) / SECONDS_PER_DAY

    def add(self, start_s: float, end_s: float, R: float, R_se: float, CF: float, CF_se: float,
            max_estimates: int = 5000) -> None:
        for lst, v in ((self.t_s, 0.5 * (start_s + end_s)), (self.span_s, end_s - start_s),
                       (self.R, R), (self.R_se, R_se), (self.CF, CF), (self.CF_se, CF_se)):
            lst.append(float(v))
        if len(self.t_s) > max_estimates:                 # thin the older half to every second one
            half = len(self.t_s) // 2
            keep = list(range(0, half, 2)) + list(range(half, len(self.t_s)))
            for name in ("t_s", "span_s", "R", "R_se", "CF", "CF_se"):
                lst = getattr(self, name)
                setattr(self, name, [lst[i] for i in keep])

    def overlap(self) -> float:
        """How many windows share a sample (window length / spacing, >= 1): 8 for the gateway's
        2-h windows every 15 min, 1 for replay's tiling."""
        if len(self.t_s) < 2:
            return 1.0
        spacing = float(np.median(np.diff(self.t_s)))
        return max(1.0, float(np.median(self.span_s)) / spacing) if spacing > 0 else 1.0

    def level_at(self, t_s: float) -> tuple[float, float]:
        """(R_th,f, CF_dp,f) the current cycle had at t_s: its latest fits' values, else the mean of
        the last three estimates (NaN without any)."""
        out = []
        for fit, ys in ((self.last_fit_R, self.R), (self.last_fit_CF, self.CF)):
            if fit is not None:
                out.append(fit.value(float(self.days([t_s])[0])))
            elif ys:
                out.append(float(np.nanmean(ys[-3:])))
            else:
                out.append(math.nan)
        return out[0], out[1]

    # ---- CIPs --------------------------------------------------------------------------------------------
    def cip(self, start_s: float, end_s: float, detected_by: str, settings: CipSettings) -> bool:
        """A CIP from start_s to end_s [epoch s] ended: remember what it did and reset the forecast.
        False (nothing changes) for a CIP that ended at or before the last reset (seen already)."""
        if not (math.isfinite(start_s) and math.isfinite(end_s) and end_s >= start_s):
            raise CostError(f"a CIP needs finite start <= end, got {start_s!r}, {end_s!r}")
        if self.reset_s is not None and end_s <= self.reset_s:
            return False
        R_b, CF_b = self.level_at(start_s)
        fits = {}
        if self.t_s:
            t = self.days(self.t_s)
            for key, y, se, floor in (("R", self.R, self.R_se, 0.0), ("CF", self.CF, self.CF_se, 1.0)):
                try:           # the cycle's own evidence on the law (prior-free: no double counting)
                    fits[key] = fit_fouling(t, y, se, floor=floor, overlap=self.overlap(),
                                            settings=settings.fit).to_state()
                except ForecastError:
                    pass
        if fits:
            self.cycle_fits = (self.cycle_fits + [fits])[-KEEP_CYCLES:]
        self.cips = (self.cips + [{"start_s": float(start_s), "end_s": float(end_s),
                                   "detected_by": str(detected_by), "reset_s": self.reset_s,
                                   "R_before": R_b, "R_after": None, "CF_before": CF_b,
                                   "CF_after": None}])[-KEEP_CIPS:]
        self.reset_s, self.reset_kind = float(end_s), str(detected_by)
        for name in ("t_s", "span_s", "R", "R_se", "CF", "CF_se"):
            setattr(self, name, [])
        self.tally = CostTally(settings.tally_max_gap_h * 3600.0)
        self.last_fit_R = self.last_fit_CF = None
        self.R_post = self.CF_post = None
        return True

    def _learned_cips(self) -> list:
        """CIPs the plant's figures are learned from (not those inferred from a hole in the record)."""
        return [c for c in self.cips if c["detected_by"] != "gap"]

    def removal(self, s: CipSettings) -> RemovalShare:
        c = self._learned_cips()
        return estimate_removal_share([_f(x["R_before"]) for x in c], [_f(x["R_after"]) for x in c],
                                      default_share=s.removal_share_default,
                                      default_spread=s.removal_share_spread_default)

    def dp_removal(self) -> float | None:
        """Share of (CF_dp,f - 1) a CIP removes, the median over past CIPs (None without any)."""
        sh = [(_f(c["CF_before"]) - _f(c["CF_after"])) / (_f(c["CF_before"]) - 1.0)
              for c in self._learned_cips() if _f(c["CF_before"]) > 1.001 and math.isfinite(_f(c["CF_after"]))]
        return float(np.clip(np.median(sh), 0.0, 1.0)) if sh else None

    def median_interval_days(self) -> float | None:
        c = [x for x in self._learned_cips() if x["reset_s"] is not None]
        return _median_interval([x["reset_s"] / SECONDS_PER_DAY for x in c],
                                [x["start_s"] / SECONDS_PER_DAY for x in c]) if c else None

    def priors(self) -> tuple[LawPrior | None, LawPrior | None]:
        """The earlier cycles' laws as priors (``law_prior``) for R_th,f and CF_dp,f. They change only
        when a CIP replaces ``cycle_fits`` (a new list, never changed in place): the last answer is
        kept with the list it came from (0.8 s of a plant-year's replay, every window's)."""
        got = self.__dict__.get("_priors")
        if got is not None and got[0] is self.cycle_fits:
            return got[1]
        out = []
        for key in ("R", "CF"):
            fits = []
            for f in self.cycle_fits:
                if f.get(key):
                    try:
                        fits.append(FoulingFit.from_state(f[key]))
                    except ForecastError:
                        pass
            try:
                out.append(law_prior(fits))
            except ForecastError:
                out.append(None)
        self.__dict__["_priors"] = (self.cycle_fits, (out[0], out[1]))
        return out[0], out[1]

    def _after_window(self) -> None:
        """The current cycle's start level (its fit's y0; before a fit, the median of its first
        three estimates) is the last CIP's 'after' and the reference of the cost vs post-CIP."""
        for fit, ys, attr, key in ((self.last_fit_R, self.R, "R_post", "R_after"),
                                   (self.last_fit_CF, self.CF, "CF_post", "CF_after")):
            if fit is not None:
                v = fit.y0
            elif ys:
                v = float(np.nanmedian(ys[:3]))
            else:
                continue
            if not math.isfinite(v):
                continue
            setattr(self, attr, float(v))
            if self.cips and self.cips[-1]["end_s"] == self.reset_s:
                self.cips[-1][key] = float(v)

    # ---- persistence -------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"reset_s": self.reset_s, "reset_kind": self.reset_kind, "t_s": self.t_s,
                "span_s": self.span_s, "R": self.R, "R_se": self.R_se, "CF": self.CF, "CF_se": self.CF_se,
                "tally": asdict(self.tally), "cips": self.cips, "cycle_fits": self.cycle_fits,
                "last_fit_R": self.last_fit_R.to_state() if self.last_fit_R else None,
                "last_fit_CF": self.last_fit_CF.to_state() if self.last_fit_CF else None,
                "R_post": self.R_post, "CF_post": self.CF_post, "curve_pts": self.curve_pts,
                "cip_costs": self.cip_costs, "n_windows": self.n_windows}

    @classmethod
    def from_dict(cls, d: dict) -> "ForecastState":
        """The state of ``to_dict``; CostError naming what is wrong when it is not one."""
        try:
            lists = {k: [_f(x) for x in d.get(k) or []] for k in ("t_s", "span_s", "R", "R_se", "CF", "CF_se")}
            if len({len(v) for v in lists.values()}) != 1:
                raise ValueError("estimate lists of different lengths")
            tally = CostTally(**{k: v for k, v in (d.get("tally") or {}).items()
                                 if k in CostTally.__dataclass_fields__})
            cips = []
            for c in d.get("cips") or []:
                cips.append({"start_s": float(c["start_s"]), "end_s": float(c["end_s"]),
                             "detected_by": str(c.get("detected_by", "")),
                             "reset_s": None if c.get("reset_s") is None else float(c["reset_s"]),
                             **{k: None if c.get(k) is None else float(c[k])
                                for k in ("R_before", "R_after", "CF_before", "CF_after")}})
            fits = [{k: v for k, v in f.items() if k in ("R", "CF")} for f in d.get("cycle_fits") or []]
            for f in fits:                                   # refuse a torn fit now, not at the CIP
                for v in f.values():
                    if v is not None:
                        FoulingFit.from_state(v)
            curve = [[float(a), float(b), float(c)] for a, b, c in d.get("curve_pts") or []]
            costs = [[float(a), float(b)] for a, b in d.get("cip_costs") or []]
            reset = d.get("reset_s")
            return cls(None if reset is None else float(reset), str(d.get("reset_kind", "")), **lists,
                       tally=tally, cips=cips, cycle_fits=fits,
                       last_fit_R=FoulingFit.from_state(d["last_fit_R"]) if d.get("last_fit_R") else None,
                       last_fit_CF=FoulingFit.from_state(d["last_fit_CF"]) if d.get("last_fit_CF") else None,
                       R_post=None if d.get("R_post") is None else float(d["R_post"]),
                       CF_post=None if d.get("CF_post") is None else float(d["CF_post"]),
                       curve_pts=curve, cip_costs=costs, n_windows=int(d.get("n_windows", 0)))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise CostError(f"not a forecast state: {exc}") from None


@dataclass
class CipWatch:
    """Finds CIPs in a stream of one-minute samples as replay does (``replay.detect_cips``): a stop
    (plant off or CIP in progress) that carries the CIP flag, or lasts ``off_minutes`` or longer,
    is a CIP from its first stopped sample to the first sample after it. The gateway feeds it each
    stored sample; a hole in the samples longer than ``off_minutes`` counts as a CIP too
    (``detected_by`` "gap": whatever happened, the forecast restarts; such CIPs teach no removal
    share). State (a stop in progress) persists with the chain's state."""
    off_minutes: float = 360.0
    down_since: float | None = None
    flagged: bool = False
    last_ts: float | None = None

    def feed(self, ts: float, down: bool, cip_flag: bool) -> tuple[float, float, str] | None:
        """One sample: ts [epoch s], down (reason off or cip), the CIP flag. Returns (start, end,
        detected_by) when a CIP has just ended."""
        out = None
        if (self.last_ts is not None and self.down_since is None
                and ts - self.last_ts >= 60.0 * self.off_minutes):
            out = (self.last_ts, float(ts), "gap")
        self.last_ts = float(ts) if self.last_ts is None else max(self.last_ts, float(ts))
        if down or cip_flag:
            if self.down_since is None:
                self.down_since = float(ts)
            self.flagged = self.flagged or bool(cip_flag)
            return out
        if self.down_since is None:
            return out
        start, flagged = self.down_since, self.flagged
        self.down_since, self.flagged = None, False
        if flagged or (ts - start) >= 60.0 * self.off_minutes:
            return (start, float(ts), "cip_flag" if flagged else "plant_off")
        return out

    def to_dict(self) -> dict:
        return {"down_since": self.down_since, "flagged": self.flagged, "last_ts": self.last_ts}

    def restore(self, d: dict | None) -> None:
        d = d or {}
        for k in ("down_since", "last_ts"):
            v = d.get(k)
            setattr(self, k, float(v) if isinstance(v, (int, float)) and not isinstance(v, bool)
                    and math.isfinite(v) else None)
        self.flagged = bool(d.get("flagged", False)) and self.down_since is not None


# ---- one window's forecast step (the analysis chain) ---------------------------------------------------
@dataclass
class WindowForecast:
    """What one window's forecast step found (NaN / None where not available, notes say why)."""
    end_s: float
    horizon_days: float
    days_since_reset: float = math.nan
    reset_s: float | None = None
    reset_kind: str = ""
    price_eur_per_MWh: float = math.nan
    cost_eur_per_day: float = math.nan            # against a clean evaporator: all parts
    cost_vs_post_eur_per_day: float = math.nan    # against the level right after the last reset
    cum_eur: float = math.nan                     # since the last reset
    P_compressor_kW: float = math.nan             # extra compressor electricity at equal heat
    P_pump_kW: float = math.nan                   # extra source-pump electricity
    lost_heat_kW: float = math.nan                # heat not delivered (LS at its speed limit)
    cip_cost_eur: float = math.nan                # one CIP: direct + heat replaced - electricity saved
    advice: CipAdvice | None = None
    notes: list = field(default_factory=list)

    def fields(self) -> dict:
        """The analysis chain's WindowResult fields (windows.csv columns; forecast.csv's subset)."""
        a = self.advice
        f = a.R_forecast if a is not None else None
        plan = a.plan if a is not None else None
        lim = a.R_limit if a is not None else None
        lim_days = (lim.mean_days - a.t_now_days if lim is not None and lim.mean_days is not None
                    else math.nan)
        if plan is not None and not plan.pays:          # no CIP date: cleaning does not pay
            plan = None
        due = (self.end_s + plan.days_to_cip * SECONDS_PER_DAY) if plan is not None else math.nan
        return {
            "days_since_reset": self.days_since_reset,
            "forecast_at": iso(self.end_s + self.horizon_days * SECONDS_PER_DAY) if f else "",
            "R_th_f_forecast_K_per_kW": f.value if f else math.nan,
            "R_th_f_forecast_lo_K_per_kW": f.lo if f else math.nan,
            "R_th_f_forecast_hi_K_per_kW": f.hi if f else math.nan,
            "forecast_law": a.R_fit.law if a is not None and a.R_fit is not None else "",
            "fouling_rate_K_per_kW_per_day": a.fouling_rate_K_per_kW_per_day if a is not None else math.nan,
            "R_th_f_limit_in_days": lim_days,
            "fouling_cost_eur_per_day": self.cost_eur_per_day,
            "fouling_cost_vs_post_eur_per_day": self.cost_vs_post_eur_per_day,
            "fouling_cost_cum_eur": self.cum_eur,
            "fouling_compressor_kW": self.P_compressor_kW,
            "fouling_pump_kW": self.P_pump_kW,
            "fouling_lost_heat_kW": self.lost_heat_kW,
            "electricity_price_eur_per_MWh": self.price_eur_per_MWh,
            "cip_cost_eur": self.cip_cost_eur,
            "days_to_recommended_cip": plan.days_to_cip if plan is not None else math.nan,
            "recommended_cip": iso(due) if plan is not None else "",
            "cip_interval_opt_days": plan.T_opt_days if plan is not None else math.nan,
            "cip_cost_opt_eur_per_day": plan.J_opt_eur_per_day if plan is not None else math.nan,
            "cip_saving_eur_per_year": (plan.saving_eur_per_year if plan is not None
                                        and plan.saving_eur_per_year is not None else math.nan),
            "removal_share": a.removal.share if a is not None else math.nan,
            "forecast_note": "; ".join(self.notes),
        }


FORECAST_FIELDS = tuple(WindowForecast(0.0, 0.0).fields())


def cost_levels_for(s: CipSettings, turn: int) -> list:
    """The cost levels [K/kW] a window runs: ``cost_levels_per_window`` of ``cost_levels_K_per_kW``,
    in turn (``turn``: the window's place among the analysed windows, ``ChainState.cost_turn``)."""
    L = list(s.cost_levels_K_per_kW)
    k = min(s.cost_levels_per_window, len(L))
    return sorted({L[(turn * k + j) % len(L)] for j in range(k)})


def forecast_window(fs: ForecastState, s: CipSettings, *, start_s: float, end_s: float, R: float,
                    R_se: float, CF: float, CF_se: float, runs: LevelRuns | None,
                    V_source_m3_per_h: float, dp_clean_bar: float) -> WindowForecast:
    """After a window's fouling calibration: add its estimates to ``fs`` (the first window is the
    reset when there is none), price the window's fouling, add it to the cumulated cost, and fit
    the forecast since the reset and plan the CIP (``advise_cip`` with the plant's removal share,
    median interval and earlier cycles' law).

    start_s, end_s : the window [epoch s]; R, R_se [K/kW] and CF, CF_se: its calibration
    runs : the adaptive model at R_th,f levels on the window's operation (``LevelRuns``; None when
        the model solved none of its operating points: no cost, the forecast still runs)
    V_source_m3_per_h, dp_clean_bar : mean source flow and clean pressure drop there
    """
    wf = WindowForecast(float(end_s), float(s.horizon_days))
    if fs.reset_s is None:
        fs.reset_s, fs.reset_kind = float(start_s), "first window"
        fs.tally = CostTally(s.tally_max_gap_h * 3600.0)
    wf.reset_s, wf.reset_kind = fs.reset_s, fs.reset_kind
    if end_s <= fs.reset_s:
        wf.notes.append(f"window ends before the last reset ({iso(fs.reset_s)}): not used")
        return wf
    start_s = max(float(start_s), fs.reset_s)
    fs.add(start_s, end_s, R, R_se, CF, CF_se, s.max_estimates)
    wf.days_since_reset = (end_s - fs.reset_s) / SECONDS_PER_DAY
    Q0 = math.nan
    try:
        price = mean_price(_price(s), start_s, end_s)
        wf.price_eur_per_MWh = price
        if runs is None:
            raise CostError("the model solved none of the window's operating points at the fouling levels")
        ref, now = runs.at(0.0), runs.at(R)
        t = fouling_cost_terms(now, ref, price, s.replacement_heat_eur_per_MWh)
        dp_ok = math.isfinite(dp_clean_bar) and math.isfinite(V_source_m3_per_h)
        pump = pump_extra_power_kW(V_source_m3_per_h, max((CF - 1.0) * dp_clean_bar, 0.0), s.eta_pump) \
            if dp_ok and math.isfinite(CF) else 0.0
        wf.P_compressor_kW, wf.lost_heat_kW, wf.P_pump_kW = t["P_compressor_kW"], t["lost_heat_kW"], pump
        wf.cost_eur_per_day = t["cost_eur_per_day"] + cost_rate_eur_per_day(pump, price)
        if fs.R_post is not None:
            tp = fouling_cost_terms(now, runs.at(fs.R_post), price, s.replacement_heat_eur_per_MWh)
            cf_post = fs.CF_post if fs.CF_post is not None else 1.0
            pump_p = pump_extra_power_kW(V_source_m3_per_h, max((CF - cf_post) * dp_clean_bar, 0.0),
                                         s.eta_pump) if dp_ok and math.isfinite(CF) else 0.0
            wf.cost_vs_post_eur_per_day = tp["cost_eur_per_day"] + cost_rate_eur_per_day(pump_p, price)
        fs.tally = fs.tally.add(start_s, float(end_s), wf.cost_eur_per_day)
        window_curve = fouling_cost_curve(runs, price, s.replacement_heat_eur_per_MWh)
        Q0, W0, _ = ref
        wf.cip_cost_eur = cleaning_cost_eur(s.cip_direct_cost_eur, s.cip_downtime_h, Q0,
                                            s.replacement_heat_eur_per_MWh, COP_clean=Q0 / W0,
                                            electricity_eur_per_MWh=price)
        grid = [x for x in s.cost_levels_K_per_kW if np.any(np.isclose(runs.R_K_per_kW, x, rtol=0, atol=1e-12))]
        fs.add_curve(end_s, [(x, window_curve(x)) for x in grid], wf.cip_cost_eur, s)
    except CostError as exc:
        wf.notes.append(f"cost of fouling: {exc}")
    curve, C = fs.average_curve(), fs.average_cip_cost()
    wf.cum_eur = fs.tally.total_eur
    R_prior, CF_prior = fs.priors()
    use_cf = math.isfinite(dp_clean_bar) and math.isfinite(V_source_m3_per_h) and dp_clean_bar > 0
    a = advise_cip(t_days=fs.days(fs.t_s), R_K_per_kW=fs.R, R_se_K_per_kW=fs.R_se,
                   t_now_days=wf.days_since_reset, cop_levels=None, Q_sink_kW=Q0, settings=s,
                   start_s=start_s, end_s=float(end_s), CF_dp_f=fs.CF if use_cf else None,
                   CF_dp_f_se=fs.CF_se if use_cf else None,
                   V_source_m3_per_h=V_source_m3_per_h if use_cf else None,
                   dp_clean_bar=dp_clean_bar if use_cf else None, removal=fs.removal(s),
                   dp_removal_share=fs.dp_removal(), R_prior=R_prior, CF_prior=CF_prior,
                   overlap=fs.overlap(), median_interval_days=fs.median_interval_days(),
                   cost_curve=curve, cip_cost_eur=None if C is None else max(C, 0.0))
    wf.advice = a
    wf.notes += [n for n in a.notes if not (curve is None and n.startswith("CIP plan: no cost"))]
    fs.last_fit_R, fs.last_fit_CF = a.R_fit, a.CF_fit
    fs._after_window()
    return wf


def explain(wf: WindowForecast, s: CipSettings) -> list[str]:
    """When to clean and why, in words (replay's summary.txt, the demo screen, the advice detail)."""
    a = wf.advice
    since = {"first window": "the first analysed window", "cip_flag": "the last CIP",
             "plant_off": "the last CIP (a long stop)", "gap": "a hole in the record"}.get(wf.reset_kind,
                                                                                         "the last reset")
    out = []
    if a is None or a.R_fit is None:
        why = "; ".join(wf.notes) or "no window estimates since the last reset"
        out.append(f"no fouling forecast yet ({why})")
    else:
        fit, f = a.R_fit, a.R_forecast
        out.append(f"R_th,f rises {1e3 * a.fouling_rate_K_per_kW_per_day:.3f}e-3 K/kW per day ({fit.law.replace('_', '-')} "
                   f"law on {fit.n} window estimates over {fit.span_days:.1f} days since {since}, "
                   f"{iso(wf.reset_s)[:16]}); in {s.horizon_days:g} days {1e3 * f.value:.2f}e-3 K/kW "
                   f"({100 * s.band_level:.0f} % band {1e3 * f.lo:.2f} .. {1e3 * f.hi:.2f})")
        if a.R_limit is not None:
            lim = a.R_limit
            out.append(f"  it reaches the limit {1e3 * lim.limit:.2f}e-3 K/kW "
                       + ("never within 10 years" if lim.mean_days is None
                          else f"in {lim.mean_days - a.t_now_days:.1f} days"))
    if math.isfinite(wf.cost_eur_per_day):
        post = (f", {wf.cost_vs_post_eur_per_day:.0f} EUR/day against the level after the reset"
                if math.isfinite(wf.cost_vs_post_eur_per_day) else "")
        out.append(f"fouling costs {wf.cost_eur_per_day:.0f} EUR/day against a clean evaporator{post} "
                   f"(compressors +{wf.P_compressor_kW:.1f} kW at equal heat, source pumps "
                   f"+{wf.P_pump_kW:.1f} kW, heat output lost at the LS speed limit {wf.lost_heat_kW:.0f} kW; "
                   f"electricity {wf.price_eur_per_MWh:.0f} EUR/MWh); {wf.cum_eur:.0f} EUR since {since}")
    plan = a.plan if a is not None else None
    if plan is None:
        if a is not None and a.R_fit is not None:
            out.append("no CIP plan (" + ("; ".join(wf.notes) or "see the notes") + ")")
        return out
    rem = a.removal
    share = (f"{100 * rem.share:.0f} % of R_th,f ("
             + (f"learned from {rem.n} CIP(s): the forecast's levels before and after each"
                if rem.source == "plant" else "configured") + ")")
    if not plan.pays:
        out.append(f"cleaning does not pay for itself at these prices: a CIP costs {wf.cip_cost_eur:.0f} EUR "
                   f"(direct {s.cip_direct_cost_eur:.0f} EUR, {s.cip_downtime_h:g} h of heat replaced at "
                   f"{s.replacement_heat_eur_per_MWh:g} EUR/MWh net of the electricity saved) and removes "
                   f"{share}; the cost-optimal interval is beyond {plan.T_opt_days:.0f} days")
        return out
    due = iso(wf.end_s + plan.days_to_cip * SECONDS_PER_DAY)[:16]
    when = "now (due)" if plan.overdue else f"in {plan.days_to_cip:.1f} days ({due} UTC)"
    rule = ("when the forecast cost rate reaches " f"{plan.f_end_eur_per_day:.0f} EUR/day, the rate at which "
            "the cost-optimal cycle ends" if plan.trigger == "level"
            else f"{plan.T_opt_days:.1f} days after the reset (the age rule)")
    out.append(f"recommended CIP {when}: {rule}. Cost-optimal cycle: {plan.T_opt_days:.1f} days of "
               f"operation + {s.cip_downtime_h / 24:.2g} days of cleaning, {plan.J_opt_eur_per_day:.0f} EUR/day "
               f"on average (fouling + a CIP of {wf.cip_cost_eur:.0f} EUR that removes {share})")
    if plan.saving_eur_per_year is not None and plan.T_current_days is not None:
        out.append(f"  against the current interval of {plan.T_current_days:.1f} days this saves "
                   f"{plan.saving_eur_per_year:.0f} EUR/year")
    return out
