"""CIP advice per window and the policy check without the simulator (issue 10).

The reduced plant has the simulator's fouling law (config/simulator.yaml) and a cost rate linear in
R_th,f; the advisor refits the forecast on noisy 2-h window estimates every 6 h and starts a CIP when
its recommended date has come. It must beat the median fixed interval (5, 8, 12, 20 days) and stay
within 2 % of the best fixed interval in hindsight, on the cycle-complete totals of 120 days.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from model.analysis.cip import CipSettings, advise_cip, window_cost
from model.analysis.cip_policy import (SCENARIOS, BENCH_CIP_COST_EUR, CipEvent, FixedInterval, ForecastAdvisor,
                                       ReducedPlant, WindowEstimate, bench_curve, compare_policies,
                                       forecast_accuracy, run_cip_policy)
from model.analysis.cost import CostCurve, PriceSeries, RemovalShare

POLICY_TOLERANCE = 0.02        # the issue's target: at most 2 % above the best fixed interval


def test_reduced_plant_follows_kern_seaton_and_integrates_its_cost():
    curve = CostCurve([0.0, 1e-3], [0.0, 40.0])
    plant = ReducedPlant(curve, 1000.0, noise_K_per_kW=0.0)
    events = plant.advance(3.0)
    ests = [e for e in events if isinstance(e, WindowEstimate)]
    assert len(ests) == 36
    R_true = 6e-3 - 3.5e-3 * math.exp(-3.0 / 15.0)
    assert plant.R == pytest.approx(R_true, rel=1e-12)
    # cost = 40e3 * integral of R: closed form of the Kern–Seaton path
    closed = 40e3 * (6e-3 * 3.0 - 3.5e-3 * 15.0 * (1 - math.exp(-3.0 / 15.0)))
    assert plant.total_cost_eur() == pytest.approx(closed, rel=1e-10)
    w = ests[5]                           # a noise-free estimate is the window's mean R
    mean_R = 6e-3 - 3.5e-3 * 15.0 / (w.end_days - w.start_days) * (
        math.exp(-w.start_days / 15.0) - math.exp(-w.end_days / 15.0))
    assert w.R_K_per_kW == pytest.approx(mean_R, rel=1e-10)
    plant.request_cip()
    assert not plant.running and plant.R == pytest.approx(0.85 * R_true)
    assert plant.total_cost_eur() == pytest.approx(closed + 1000.0)
    events = plant.advance(3.0)
    cip = [e for e in events if isinstance(e, CipEvent)]
    assert len(cip) == 1 and cip[0].start_days == pytest.approx(3.0) and cip[0].end_days == pytest.approx(5.5)
    assert plant.running and plant.t_days == pytest.approx(6.0)


@pytest.mark.parametrize("T, horizon, starts, end", [
    (8.0, 40.0, (8.0, 18.5, 29.0, 39.5), 50.0),       # resets at 10.5, 21, 31.5, 42; closing CIP at 50
    (10.0, 30.0, (10.0, 22.5), 35.0),                 # resets at 12.5, 25; closing CIP at 35
])
def test_fixed_interval_and_the_cycle_complete_total(T, horizon, starts, end):
    """A fixed interval counts operating days after each reset; the run goes on to the first CIP at or
    after the horizon and prices whole cycles: per day = all cost / (end + that CIP's downtime)."""
    curve = CostCurve([0.0, 1e-3], [0.0, 40.0])
    plant = ReducedPlant(curve, 1000.0)
    run = run_cip_policy(plant, FixedInterval(T), horizon_days=horizon)
    assert run.cip_starts_days == pytest.approx(starts)
    assert run.n_cips == len(starts)
    assert run.end_days == pytest.approx(end)
    assert len(plant.cips) == len(starts) + 1
    assert run.cost_per_day_eur == pytest.approx(plant.total_cost_eur() / (end + 2.5), rel=1e-12)
    assert run.cycle_total_eur == pytest.approx(run.cost_per_day_eur * horizon, rel=1e-12)
    assert run.total_cost_eur < plant.total_cost_eur()          # the raw total stops at the horizon


@pytest.mark.parametrize("scenario, seed, default_share", [
    ("simulator_law_15pct", 0, 0.15),          # the simulator's law, its share configured
    ("strong_cip_30pct", 1, 0.15),             # CIPs remove 30 %, the advisor must learn it
])
def test_advised_policy_beats_the_median_fixed_interval_and_nearly_the_best(scenario, seed, default_share):
    """Also the forecasts the advisor made on the way: 2 days ahead, made >= 2 days after a CIP,
    within +-0.3e-3 K/kW of the truth and the truth inside the 90 % band, each in >= 80 %."""
    curve = bench_curve()
    kw = SCENARIOS[scenario]
    plants, advisors = [], []

    def make_plant():
        plants.append(ReducedPlant(curve, BENCH_CIP_COST_EUR, seed=seed, **kw))
        return plants[-1]

    def make_advisor():
        advisors.append(ForecastAdvisor(curve, BENCH_CIP_COST_EUR, 2.5, default_share=default_share))
        return advisors[-1]
    res = compare_policies(make_plant, make_advisor)
    totals = sorted(r.cycle_total_eur for r in res["fixed"].values())
    assert totals[0] < totals[-1] * 0.97               # the intervals differ: the check can fail
    adv = res["advised"]
    assert adv.cycle_total_eur < res["median_fixed_eur"]
    assert adv.cycle_total_eur <= (1 + POLICY_TOLERANCE) * res["best_fixed_eur"]
    assert 5 <= adv.n_cips <= 14
    share = advisors[-1].share()
    assert share.source == "plant" and abs(share.share - kw["removal_share"]) < 0.04
    acc = forecast_accuracy(plants[-1], advisors[-1])
    assert acc["n_forecasts"] > 150
    assert acc["within_tol_share"] >= 0.80
    assert acc["truth_in_band_share"] >= 0.80


# ---- one window's advice (the chain's entry point) --------------------------------------------------------
def _cycle(days=10.0, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(1 / 24, days, 2 / 24)
    R = 4.4e-3 + 1.6e-3 * (1 - np.exp(-t / 15.0)) + rng.normal(0, 0.05e-3, len(t))
    CF = 1.2 + 0.2 * (1 - np.exp(-t / 20.0)) + rng.normal(0, 0.005, len(t))
    return t, R, CF


def test_window_cost_at_equal_heat_and_with_a_price_series():
    c = window_cost(Q_sink_kW=2000.0, COP_adaptive=4.4, COP_clean=4.8, V_source_m3_per_h=192.0,
                    dp_fouling_bar=0.05, price=100.0, start_s=0, end_s=7200, COP_post=4.6)
    assert c.P_compressor_vs_clean_kW == pytest.approx(2000 * (1 / 4.4 - 1 / 4.8))
    assert c.P_compressor_vs_post_kW == pytest.approx(2000 * (1 / 4.4 - 1 / 4.6))
    assert c.P_pump_kW == pytest.approx(192 / 3600 * 5000 / 0.65 / 1000)
    assert c.cost_eur_per_day == pytest.approx((c.P_compressor_vs_clean_kW + c.P_pump_kW) * 2.4)
    assert c.extra_kWh_per_day == pytest.approx((c.P_compressor_vs_clean_kW + c.P_pump_kW) * 24)
    ps = PriceSeries([0.0, 3600.0], [50.0, 150.0])
    c2 = window_cost(Q_sink_kW=2000.0, COP_adaptive=4.4, COP_clean=4.8, V_source_m3_per_h=192.0,
                     dp_fouling_bar=0.05, price=ps, start_s=0, end_s=7200)
    assert c2.price_eur_per_MWh == pytest.approx(100.0)
    assert math.isnan(c2.cost_vs_post_eur_per_day)


def test_advise_cip_gives_every_figure_of_the_issue():
    t, R, CF = _cycle()
    s = CipSettings(R_limit_K_per_kW=5.6e-3, current_interval_days=20.0)
    a = advise_cip(t_days=t, R_K_per_kW=R, R_se_K_per_kW=np.full(len(t), 0.05e-3), t_now_days=float(t[-1]),
                   cop_levels=((0.0, 3e-3, 6e-3), (4.9, 4.62, 4.37)), Q_sink_kW=2000.0, settings=s,
                   start_s=0.0, end_s=7200.0, CF_dp_f=CF, CF_dp_f_se=np.full(len(t), 0.005),
                   V_source_m3_per_h=192.0, dp_clean_bar=0.25)
    assert a.R_fit.law == "kern_seaton" and a.CF_fit is not None and a.CF_fit.floor == 1.0
    assert a.notes == ()
    row = a.row()
    assert row["R_th_f_forecast_lo_K_per_kW"] < row["R_th_f_forecast_K_per_kW"] < row["R_th_f_forecast_hi_K_per_kW"]
    assert a.R_forecast.t_days == pytest.approx(t[-1] + 7.0)
    truth = 4.4e-3 + 1.6e-3 * (1 - math.exp(-(t[-1] + 7.0) / 15.0))
    assert abs(row["R_th_f_forecast_K_per_kW"] - truth) < 0.3e-3
    assert row["fouling_rate_K_per_kW_per_day"] == pytest.approx(1.6e-3 / 15 * math.exp(-t[-1] / 15), rel=0.5)
    assert row["days_to_recommended_cip"] >= 0.0
    assert a.R_limit.mean_days is not None
    assert set(a.plan.start_levels) == {"R_th_f", "CF_dp_f"}
    assert a.plan.saving_eur_per_year is not None and a.plan.T_current_days == 20.0
    med = advise_cip(t_days=t, R_K_per_kW=R, R_se_K_per_kW=np.full(len(t), 0.05e-3), t_now_days=float(t[-1]),
                     cop_levels=((0.0, 6e-3), (4.9, 4.37)), Q_sink_kW=2000.0, settings=s,
                     start_s=0.0, end_s=7200.0, median_interval_days=11.0)
    assert med.plan.T_current_days == 11.0 and med.CF_fit is None


def test_advise_cip_without_enough_data_says_so_and_has_no_numbers():
    t = np.array([0.05, 0.15, 0.25])
    a = advise_cip(t_days=t, R_K_per_kW=[1e-3] * 3, R_se_K_per_kW=[1e-5] * 3, t_now_days=0.3,
                   cop_levels=((0.0, 3e-3), (4.9, 4.6)), Q_sink_kW=2000.0, settings=CipSettings(),
                   start_s=0.0, end_s=7200.0)
    assert a.R_fit is None and a.plan is None and a.R_forecast is None
    assert a.notes[0].startswith("R_th_f: not enough data: 3 window estimate(s)")
    row = a.row()
    assert all(math.isnan(v) for v in row.values())


def test_advise_cip_reports_an_unusable_cost_curve_but_keeps_the_forecast():
    t, R, _ = _cycle(4.0)
    a = advise_cip(t_days=t, R_K_per_kW=R, R_se_K_per_kW=np.full(len(t), 0.05e-3), t_now_days=float(t[-1]),
                   cop_levels=((0.0,), (4.9,)), Q_sink_kW=2000.0, settings=CipSettings(), start_s=0.0,
                   end_s=7200.0, removal=RemovalShare(0.2, 0.05, 3, "plant"))
    assert a.R_forecast is not None and a.plan is None
    assert a.notes == ("CIP plan: the cost curve needs a model COP at an R_th,f level above 0",)
    assert a.removal.share == 0.2
