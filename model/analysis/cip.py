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
from dataclasses import dataclass, field

from .cost import (CipPlan, CostCurve, CostError, FoulingComponent, PriceSeries, RemovalShare,
                   cleaning_cost_eur, compressor_cost_curve, cost_rate_eur_per_day,
                   extra_compressor_power_kW, mean_price, plan_cip, pump_cost_curve, pump_extra_power_kW,
                   DEFAULT_ETA_PUMP)
from .forecast import (DEFAULT_HORIZON_DAYS, DEFAULT_LEVEL, FitSettings, FoulingFit, ForecastError,
                       LawPrior, LimitCrossing, Prediction, fit_fouling)


@dataclass(frozen=True)
class CipSettings:
    """Prices, CIP costs and forecast settings (the proposed plant.yaml ``cip:`` section)."""
    electricity_price_eur_per_MWh: float | PriceSeries = 100.0
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
               median_interval_days: float | None = None) -> CipAdvice:
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
        price = mean_price(s.electricity_price_eur_per_MWh, start_s, end_s)
        levels, cops = cop_levels
        if not any(x > 0 for x in levels):
            raise CostError("the cost curve needs a model COP at an R_th,f level above 0")
        comps = [FoulingComponent(R_fit, removal.share, compressor_cost_curve(levels, cops, Q_sink_kW, price),
                                  "R_th_f", uncertain=s.uncertain)]
        if CF_fit is not None:
            share_dp = s.dp_removal_share_default if dp_removal_share is None else dp_removal_share
            comps.append(FoulingComponent(CF_fit, share_dp, pump_cost_curve(dp_clean_bar, V_source_m3_per_h, price,
                                                                            s.eta_pump),
                                          "CF_dp_f", uncertain=s.uncertain))
        cop_clean = cops[list(levels).index(0.0)] if 0.0 in list(levels) else None
        C = cleaning_cost_eur(s.cip_direct_cost_eur, s.cip_downtime_h, Q_sink_kW, s.replacement_heat_eur_per_MWh,
                              COP_clean=cop_clean, electricity_eur_per_MWh=price)
        plan = plan_cip(comps, cip_cost_eur=max(C, 0.0), downtime_days=s.cip_downtime_h / 24.0,
                        t_now_days=t_now_days, trigger=s.trigger,
                        T_current_days=(median_interval_days if median_interval_days is not None
                                        else s.current_interval_days))
    except (CostError, ValueError) as exc:
        notes.append(f"CIP plan: {exc}")
    return CipAdvice(float(t_now_days), R_fit, CF_fit, forecast, limit, plan, removal, tuple(notes))
