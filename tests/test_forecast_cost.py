"""Cost of fouling and cost-optimal CIP timing (issue 10): energy balance against two model runs,
prices, the cumulated cost rule, the T* criterion and the sqrt(2C/a) case."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings, strategies as st

from model.analysis.cost import (CostCurve, CostError, CostTally, FoulingComponent, PriceSeries,
                                 average_cost_eur_per_day, cleaning_cost_eur, compressor_cost_curve,
                                 cost_rate_eur_per_day, cumulative_cost_eur, cycle_cost_eur,
                                 end_cost_rate_eur_per_day, estimate_removal_share,
                                 extra_compressor_power_kW, mean_price, median_interval_days, plan_cip,
                                 pump_cost_curve, pump_extra_power_kW)
from model.analysis.forecast import FoulingFit
from model.batch import simulate_batch, solved_mask

BALANCE_RTOL = 1e-8          # the model closes its energy balance to ~1e-10 per point
CRITERION_RTOL = 1e-6        # f(T*) = J(T*) after the bounded Brent search (exact integrals)


def law(law_: str, y0: float, r0: float, tau: float = math.inf, floor: float = 0.0) -> FoulingFit:
    """A fitted law with given parameters (no uncertainty): the timing tests need exact laws."""
    k = 0.0 if law_ == "linear" else 1.0 / tau
    p = 2 if law_ == "linear" else 3
    return FoulingFit(law_, floor, y0 - floor, r0, k, np.zeros((p, p)), 1.0, 1e-5, 100, 97.0, 0.0, 10.0,
                      "given", math.nan)


# ---- cost of fouling against two model runs done by hand -----------------------------------------------
def test_extra_compressor_power_closes_the_energy_balance_of_two_model_runs(plant):
    """Four operating rows, run once clean (R_th,f = 0) and once fouled (3e-3 K/kW). Same inputs, so the
    same source heat: the fouled plant's extra work all leaves as extra heat, and the electricity at
    equal heat is P = Q_sink,f (1/COP_f - 1/COP_0) = (W_f - W_0)(1 - 1/COP_0)."""
    rows = pd.DataFrame({"T_source_in": [25.0, 24.5, 24.0, 25.3], "T_source_out": [18.0, 18.0, 17.8, 18.2],
                         "T_sink_in": [40.0, 40.5, 39.5, 41.0], "V_source": [192.0, 190.0, 195.0, 188.0],
                         "V_sink": [62.0, 60.0, 64.0, 61.0], "p_m_sp": [16.0, 16.0, 15.5, 16.5]})
    cols = ("Q_sink_kW", "Q_source_kW", "W_total_kW", "COP", "energy_residual")
    clean = simulate_batch(rows, plant.replace(R_th_f=0.0), columns=cols)
    fouled = simulate_batch(rows, plant.replace(R_th_f=3e-6), columns=cols)       # 3e-3 K/kW in K/W
    assert solved_mask(clean).all() and solved_mask(fouled).all()
    for run in (clean, fouled):          # each run closes its own balance: Q_sink = Q_source + W
        assert np.allclose(run["Q_sink_kW"], run["Q_source_kW"] + run["W_total_kW"], rtol=BALANCE_RTOL)
    assert np.allclose(clean["Q_source_kW"], fouled["Q_source_kW"], rtol=1e-12)
    Q0, W0 = clean["Q_sink_kW"].sum(), clean["W_total_kW"].sum()
    Qf, Wf = fouled["Q_sink_kW"].sum(), fouled["W_total_kW"].sum()
    cop0, copf = Q0 / W0, Qf / Wf                                  # period COPs (SPEC §3)
    n = len(rows)
    P = extra_compressor_power_kW(Qf / n, copf, cop0)
    assert P > 0
    assert P == pytest.approx((Wf - W0) / n * (1 - 1 / cop0), rel=BALANCE_RTOL)
    # the work difference splits into the extra electricity at equal heat and the extra heat's electricity
    assert (Wf - W0) / n == pytest.approx(P + (Qf - Q0) / n / cop0, rel=BALANCE_RTOL)
    # a physically sensible size: a few % of the compressor power per 1e-3 K/kW
    assert 0.01 < P / (W0 / n) / 3.0 < 0.06
    # the cost curve through the two runs gives the same figure at the fouled level
    curve = compressor_cost_curve([0.0, 3e-3], [cop0, copf], Qf / n, 100.0)
    assert curve(3e-3) == pytest.approx(P * 24 * 100 / 1000, rel=1e-12)
    assert curve(0.0) == 0.0


def test_pump_power_and_cost_rate_by_hand():
    # 192 m3/h against 0.05 bar at 65 % wire-to-water: 0.05333 m3/s * 5000 Pa / 0.65 = 410.3 W
    assert pump_extra_power_kW(192.0, 0.05) == pytest.approx(192 / 3600 * 5000 / 0.65 / 1000, rel=1e-12)
    assert pump_extra_power_kW(192.0, 0.05, eta_pump=1.0) == pytest.approx(0.266667, rel=1e-5)
    assert cost_rate_eur_per_day(10.0, 100.0) == pytest.approx(24.0)         # 240 kWh/day at 0.1 EUR/kWh
    with pytest.raises(CostError, match=r"eta_pump must be in \(0, 1\], got 0"):
        pump_extra_power_kW(192.0, 0.05, eta_pump=0)
    curve = pump_cost_curve(0.25, 192.0, 100.0)
    assert curve(1.0) == 0.0
    assert curve(1.2) == pytest.approx(cost_rate_eur_per_day(pump_extra_power_kW(192.0, 0.05), 100.0))


def test_bad_cops_are_refused():
    with pytest.raises(CostError, match="COPs must be finite and > 0"):
        extra_compressor_power_kW(2000.0, float("nan"), 4.5)
    with pytest.raises(CostError, match="COPs must be finite and > 0"):
        extra_compressor_power_kW(2000.0, 4.0, 0.0)


# ---- prices ---------------------------------------------------------------------------------------------
def test_price_series_lookup_and_time_mean():
    t0 = 1.7e9
    ps = PriceSeries([t0, t0 + 3600, t0 + 7200], [50.0, 150.0, 100.0])
    assert ps.at(t0 + 10) == 50.0 and ps.at(t0 + 3600) == 150.0
    # 30 min at 50 then 60 min at 150 then 30 min at 100 -> (25 + 150 + 50) / 2 h
    assert ps.mean(t0 + 1800, t0 + 9000) == pytest.approx((0.5 * 50 + 1 * 150 + 0.5 * 100) / 2.0)
    assert mean_price(ps, t0, t0 + 3600) == pytest.approx(50.0)
    assert mean_price(80.0, 0, 1) == 80.0
    with pytest.raises(CostError, match="price series covers epoch 1700000000 .. 1700010800 s"):
        ps.mean(t0 - 60, t0 + 60)
    with pytest.raises(CostError, match=r"timestamps must increase strictly \(row 2\)"):
        PriceSeries([t0, t0 + 10, t0 + 5], [1, 2, 3])
    with pytest.raises(CostError, match="row 1 is not a finite timestamp and price"):
        PriceSeries([t0, t0 + 10], [1, float("nan")])
    with pytest.raises(CostError, match="electricity price must be a finite number"):
        mean_price("cheap", 0, 1)


# ---- cumulated cost ---------------------------------------------------------------------------------------
def test_cost_tally_counts_each_second_once_bridges_short_gaps_and_skips_long_ones():
    h = 3600.0
    tally = CostTally(max_gap_s=h)
    tally = tally.add(0, 2 * h, 24.0)                 # 2 h at 24 EUR/day = 2 EUR
    assert tally.total_eur == pytest.approx(2.0)
    tally = tally.add(h, 3 * h, 48.0)                 # overlaps: only 2h..3h counts, at 48 -> 2 EUR
    assert tally.total_eur == pytest.approx(4.0) and tally.covered_s == 3 * h
    tally = tally.add(3.5 * h, 4.5 * h, 24.0)         # 0.5 h gap bridged at (48+24)/2 -> 0.75 EUR, then 1 EUR
    assert tally.total_eur == pytest.approx(5.75) and tally.bridged_s == 0.5 * h
    tally = tally.add(10 * h, 11 * h, 24.0)           # 5.5 h gap: not priced
    assert tally.total_eur == pytest.approx(6.75) and tally.uncovered_s == 5.5 * h
    assert tally.add(9 * h, 10.5 * h, 100.0) is tally    # nothing new
    run = cumulative_cost_eur([0, h, 3.5 * h, 10 * h], [2 * h, 3 * h, 4.5 * h, 11 * h], [24, 48, 24, 24], h)
    assert np.allclose(run, [2.0, 4.0, 5.75, 6.75])
    with pytest.raises(CostError, match="cost rate must be finite"):
        tally.add(12 * h, 13 * h, float("inf"))


# ---- cost curve, cleaning cost, removal share -----------------------------------------------------------
def test_cost_curve_interpolates_and_extrapolates_linearly():
    c = CostCurve([0.0, 2e-3, 4e-3], [0.0, 50.0, 120.0])
    assert c(1e-3) == pytest.approx(25.0)
    assert c(3e-3) == pytest.approx(85.0)
    assert c(5e-3) == pytest.approx(155.0)
    assert c(-1e-3) == pytest.approx(-25.0)
    assert np.allclose(c(np.array([0.0, 4e-3])), [0.0, 120.0])
    with pytest.raises(CostError, match="cost curve levels must differ"):
        CostCurve([1.0, 1.0], [0.0, 1.0])
    with pytest.raises(CostError, match="R = 0 is not among the levels"):
        compressor_cost_curve([1e-3, 2e-3], [4.5, 4.4], 2000.0, 100.0)


def test_cleaning_cost_by_hand():
    # 2000 EUR + 60 h * 2000 kW = 120 MWh of replacement heat at 45 EUR/MWh
    assert cleaning_cost_eur(2000.0, 60.0, 2000.0, 45.0) == pytest.approx(2000 + 120 * 45)
    # net of the heat pump's own electricity at COP 4 and 100 EUR/MWh: 30 MWh * 100
    assert cleaning_cost_eur(2000.0, 60.0, 2000.0, 45.0, COP_clean=4.0, electricity_eur_per_MWh=100.0) \
        == pytest.approx(2000 + 120 * 45 - 30 * 100)
    with pytest.raises(CostError, match="downtime_h must be a finite number >= 0, got -1"):
        cleaning_cost_eur(2000.0, -1, 2000.0, 45.0)


def test_removal_share_is_learned_from_past_cips():
    none = estimate_removal_share([], [], default_share=0.2, default_spread=0.05)
    assert (none.share, none.spread, none.n, none.source) == (0.2, 0.05, 0, "configured")
    one = estimate_removal_share([4e-3], [3.4e-3])
    assert one.share == pytest.approx(0.15) and one.spread == 0.05 and one.source == "plant"
    many = estimate_removal_share([4e-3, 5e-3, 4.5e-3, np.nan, 0.0], [3.4e-3, 4.0e-3, 3.6e-3, 3e-3, 1e-3])
    assert many.n == 3
    assert many.share == pytest.approx(0.2)                       # median of 0.15, 0.20, 0.20
    assert many.spread == pytest.approx(np.std([0.15, 0.2, 0.2], ddof=1))
    worse = estimate_removal_share([4e-3], [4.2e-3])               # a CIP that seemed to add fouling
    assert worse.share == 0.01
    with pytest.raises(CostError, match="differ in length"):
        estimate_removal_share([1e-3], [])


def test_median_interval():
    assert median_interval_days([0.0, 12.0, 25.0], [9.5, 22.0, 36.0]) == pytest.approx(10.0)
    assert median_interval_days([], []) is None


# ---- cost-optimal CIP timing ---------------------------------------------------------------------------------
def test_linear_cost_growth_without_downtime_gives_sqrt_2C_over_a():
    """f = a t (linear law from a clean start, cost linear in R), D = 0: T* = sqrt(2 C / a)."""
    r, c, C = 0.2e-3, 40.0 / 1e-3, 1500.0          # K/kW/day, EUR/day per K/kW, EUR
    comp = FoulingComponent(law("linear", 0.0, r), 0.15, CostCurve([0.0, 1e-3], [0.0, 40.0]))
    a = c * r
    plan = plan_cip([comp], cip_cost_eur=C, downtime_days=0.0, t_now_days=3.0)
    assert plan.T_opt_days == pytest.approx(math.sqrt(2 * C / a), rel=CRITERION_RTOL)
    assert plan.J_opt_eur_per_day == pytest.approx(math.sqrt(2 * C * a), rel=1e-6)   # J* = a T*
    assert plan.f_end_eur_per_day == pytest.approx(plan.J_opt_eur_per_day, rel=CRITERION_RTOL)
    assert plan.interior and plan.trigger == "level"
    assert plan.days_to_cip == pytest.approx(plan.T_opt_days - 3.0, rel=1e-6)
    # with downtime D: T^2 + 2 D T = 2 C / a
    D = 2.5
    plan_d = plan_cip([comp], cip_cost_eur=C, downtime_days=D, t_now_days=0.0)
    assert plan_d.T_opt_days == pytest.approx(-D + math.sqrt(D * D + 2 * C / a), rel=CRITERION_RTOL)


@pytest.mark.parametrize("law_", ["linear", "kern_seaton"])
def test_criterion_f_equals_J_at_the_optimum_when_the_start_level_is_fixed(law_):
    """Full cleaning (s = 1) or a fixed restart level, any cost curve: f(T*) = J(T*)."""
    fit = law(law_, 1.0e-3, 0.3e-3, tau=12.0)
    curve = CostCurve([0.0, 2e-3, 4e-3, 8e-3], [0.0, 60.0, 150.0, 400.0])     # convex, piecewise linear
    for comp in (FoulingComponent(fit, 1.0, curve, restart="steady"),
                 FoulingComponent(fit, 0.15, curve, restart="current")):
        plan = plan_cip([comp], cip_cost_eur=2500.0, downtime_days=2.5, t_now_days=0.0)
        assert plan.interior
        assert plan.f_end_eur_per_day == pytest.approx(plan.J_opt_eur_per_day, rel=CRITERION_RTOL)
        T = plan.T_opt_days
        J = average_cost_eur_per_day([comp], [0.95 * T, T, 1.05 * T], 2500.0, 2.5)
        assert J[1] <= J[0] and J[1] <= J[2]


def test_partial_cleaning_steady_cycle_and_the_corrected_criterion():
    """s < 1: the cycle restarts from the fixed point y_post = (1 - s) y(T); T* still minimises J, and
    f(T*) < J(T*) (a later CIP leaves a dirtier residual for every following cycle)."""
    fit = law("kern_seaton", 2.5e-3, (6e-3 - 2.5e-3) / 15.0, tau=15.0)
    curve = CostCurve([0.0, 1e-3], [0.0, 40.0])
    comp = FoulingComponent(fit, 0.3, curve)
    assert comp.mode == "steady"
    T = 9.0
    y_post = float(comp.start_level(T))
    y = y_post
    for _ in range(200):                                     # iterate cycles until periodic
        y = 0.7 * float(fit.growth(y, T))
    assert y_post == pytest.approx(y, rel=1e-9)
    assert y_post == pytest.approx(0.7 * float(fit.growth(y_post, T)), rel=1e-12)
    plan = plan_cip([comp], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=0.0)
    Ts = plan.T_opt_days
    J = average_cost_eur_per_day([comp], [0.97 * Ts, Ts, 1.03 * Ts], 1000.0, 2.5)
    assert J[1] <= J[0] and J[1] <= J[2]
    assert plan.f_end_eur_per_day < plan.J_opt_eur_per_day
    assert plan.start_levels["R_th_f"] == pytest.approx(float(comp.start_level(Ts)))
    assert plan.end_levels["R_th_f"] == pytest.approx(float(fit.growth(plan.start_levels["R_th_f"], Ts)))
    # cycle integral: Gauss–Legendre against the closed form for a linear cost of a Kern–Seaton path
    U = 6e-3 - y_post
    closed = 40e3 * (6e-3 * T - U * 15.0 * (1 - math.exp(-T / 15.0)))
    assert cycle_cost_eur([comp], [T])[0] == pytest.approx(closed, rel=1e-10)


def test_level_trigger_follows_the_current_cycle():
    """On the steady cycle the level rule cleans at T*; a cleaner start runs longer; 'age' is T*."""
    R_inf, tau, s = 6e-3, 15.0, 0.3
    curve = CostCurve([0.0, 1e-3], [0.0, 40.0])
    base = FoulingComponent(law("kern_seaton", 3e-3, (R_inf - 3e-3) / tau, tau), s, curve)
    plan = plan_cip([base], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=1.0)
    y_ss = plan.start_levels["R_th_f"]
    steady = FoulingComponent(law("kern_seaton", y_ss, (R_inf - y_ss) / tau, tau), s, curve)
    p_ss = plan_cip([steady], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=1.0)
    assert p_ss.T_opt_days == pytest.approx(plan.T_opt_days, rel=1e-9)     # T* ignores the current start
    assert p_ss.t_cip_days == pytest.approx(p_ss.T_opt_days, rel=1e-6)
    cleaner = FoulingComponent(law("kern_seaton", 2e-3, (R_inf - 2e-3) / tau, tau), s, curve)
    p_c = plan_cip([cleaner], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=1.0)
    assert p_c.t_cip_days > p_c.T_opt_days
    assert cleaner.fit.value(p_c.t_cip_days) == pytest.approx(plan.end_levels["R_th_f"], rel=1e-6)
    p_age = plan_cip([cleaner], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=1.0, trigger="age")
    assert p_age.t_cip_days == p_age.T_opt_days and p_age.trigger == "age"
    late = plan_cip([cleaner], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=40.0)
    assert late.days_to_cip == 0.0 and late.overdue


def test_two_components_add_and_the_saving_against_the_current_interval():
    R = FoulingComponent(law("kern_seaton", 3e-3, 0.2e-3, 15.0), 0.3, CostCurve([0.0, 1e-3], [0.0, 40.0]))
    CF = FoulingComponent(law("kern_seaton", 1.1, 0.02, 20.0, floor=1.0), 0.3,
                          pump_cost_curve(0.25, 192.0, 100.0), name="CF_dp_f")
    T = np.array([5.0, 10.0])
    assert np.allclose(cycle_cost_eur([R, CF], T), cycle_cost_eur([R], T) + cycle_cost_eur([CF], T))
    assert np.allclose(end_cost_rate_eur_per_day([R, CF], T),
                       end_cost_rate_eur_per_day([R], T) + end_cost_rate_eur_per_day([CF], T))
    assert float(CF.start_level(10.0)) >= 1.0
    plan = plan_cip([R, CF], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=2.0, T_current_days=20.0)
    assert set(plan.start_levels) == {"R_th_f", "CF_dp_f"}
    J_cur = float(average_cost_eur_per_day([R, CF], [20.0], 1000.0, 2.5)[0])
    assert plan.J_current_eur_per_day == pytest.approx(J_cur)
    assert plan.saving_eur_per_year == pytest.approx((J_cur - plan.J_opt_eur_per_day) * 365.25)
    assert plan.saving_eur_per_year > 0


def test_uncertain_component_averages_over_sigma_points():
    fit = law("kern_seaton", 3e-3, 0.2e-3, 15.0)
    cov = np.diag([1e-4, 2e-5, 0.02]) ** 2
    import dataclasses
    fit_u = dataclasses.replace(fit, cov=cov)
    comp = FoulingComponent(fit_u, 0.3, CostCurve([0.0, 1e-3], [0.0, 40.0]), uncertain=True)
    v = comp.variants()
    assert len(v) == 6 and sum(w for w, _ in v) == pytest.approx(1.0)
    assert all(c.fit.k >= 0.2 * fit.k and c.fit.r0 >= 0 for _, c in v)
    # a cost linear in the level and a law linear in a0: the a0 pair averages back to the mean
    no_unc = FoulingComponent(fit, 0.3, CostCurve([0.0, 1e-3], [0.0, 40.0]), restart="current")
    only_a0 = FoulingComponent(dataclasses.replace(fit, cov=np.diag([1e-4, 0, 0]) ** 2), 0.3,
                               CostCurve([0.0, 1e-3], [0.0, 40.0]), restart="current", uncertain=True)
    assert cycle_cost_eur([only_a0], [8.0])[0] == pytest.approx(cycle_cost_eur([no_unc], [8.0])[0], rel=1e-9)
    plan = plan_cip([comp], cip_cost_eur=1000.0, downtime_days=2.5, t_now_days=0.0)
    assert plan.interior


def test_cost_curve_on_arrays_is_the_scalar_curve_element_by_element():
    """The cycle plan evaluates the curve on large arrays (extrapolated elements only where needed):
    each element is the scalar call's number to the bit, on both sides of the points and inside;
    NaN stays NaN."""
    c = CostCurve([0.0, 2e-3, 4e-3, 7e-3], [0.0, 50.0, 120.0, 300.0])
    y = np.array([-3e-3, -1e-12, 0.0, 1e-3, 2e-3, 3.3e-3, 7e-3, 7e-3 + 1e-12, 9e-3, np.nan]).reshape(2, 5)
    got = c(y)
    assert got.shape == y.shape
    ref = np.array([c(float(v)) for v in y.ravel()]).reshape(y.shape)
    assert np.array_equal(got, ref, equal_nan=True)
    assert got[0, 0] == pytest.approx(-75.0) and got[1, 3] == pytest.approx(420.0)


def test_stacked_sigma_points_cost_what_each_costs_alone():
    """``cycle_cost_eur`` of an uncertain component (its sigma points in one set of array
    operations) is the weighted sum of its variants' costs computed one at a time, to rounding."""
    import dataclasses
    fit = dataclasses.replace(law("kern_seaton", 3e-3, 0.2e-3, 15.0), cov=np.diag([1e-4, 2e-5, 0.02]) ** 2)
    curve = CostCurve([0.0, 1e-3, 3e-3], [0.0, 40.0, 150.0])
    comp = FoulingComponent(fit, 0.3, curve, uncertain=True)
    T = np.geomspace(0.25, 365.0, 50)
    alone = sum(w * cycle_cost_eur([dataclasses.replace(v, uncertain=False)], T) for w, v in comp.variants())
    assert np.allclose(cycle_cost_eur([comp], T), alone, rtol=1e-12, atol=0.0)


def test_plan_inputs_are_checked_and_the_date_is_reset_plus_t_cip():
    comp = FoulingComponent(law("linear", 0.0, 0.2e-3), 0.2, CostCurve([0.0, 1e-3], [0.0, 40.0]))
    with pytest.raises(CostError, match="needs at least one fouling component"):
        plan_cip([], cip_cost_eur=1.0, downtime_days=0.0, t_now_days=0.0)
    with pytest.raises(CostError, match="cip_cost_eur must be a finite number >= 0, got -5"):
        plan_cip([comp], cip_cost_eur=-5, downtime_days=0.0, t_now_days=0.0)
    with pytest.raises(CostError, match="trigger must be 'level' or 'age'"):
        plan_cip([comp], cip_cost_eur=1.0, downtime_days=0.0, t_now_days=0.0, trigger="soon")
    with pytest.raises(CostError, match="removal share must be in"):
        FoulingComponent(comp.fit, 1.5, comp.cost_eur_per_day)
    with pytest.raises(CostError, match="removes nothing has no steady cycle"):
        FoulingComponent(comp.fit, 0.0, comp.cost_eur_per_day, restart="steady").start_level(5.0)
    plan = plan_cip([comp], cip_cost_eur=1500.0, downtime_days=0.0, t_now_days=0.0)
    reset = dt.datetime(2024, 3, 1, tzinfo=dt.timezone.utc)
    assert plan.recommended_date(reset) == reset + dt.timedelta(days=plan.t_cip_days)
    assert plan.recommended_date(1.7e9) == pytest.approx(1.7e9 + plan.t_cip_days * 86400)
    cheap = FoulingComponent(law("linear", 0.0, 1e-9), 0.2, CostCurve([0.0, 1e-3], [0.0, 40.0]))
    never = plan_cip([cheap], cip_cost_eur=1e6, downtime_days=2.0, t_now_days=0.0)
    assert not never.interior and "cleaning does not pay" in never.notes[0]


@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.floats(0.01, 0.99), min_size=1, max_size=5, unique=True),
       rate=st.floats(0.0, 500.0), hours=st.floats(0.5, 48.0))
def test_splitting_a_window_does_not_change_the_cumulated_cost(cuts, rate, hours):
    """Contiguous windows at one rate cost rate * duration however the time is cut into windows."""
    end = hours * 3600.0
    edges = [0.0] + sorted(c * end for c in cuts) + [end]
    tally = CostTally()
    for a, b in zip(edges[:-1], edges[1:]):
        tally = tally.add(a, b, rate)
    assert tally.total_eur == pytest.approx(rate * hours / 24.0, rel=1e-12, abs=1e-12)
    assert tally.covered_s == pytest.approx(end) and tally.bridged_s == 0.0 and tally.uncovered_s == 0.0


@settings(max_examples=60, deadline=None)
@given(R_start=st.floats(0.0, 5e-3), dR=st.floats(1e-5, 5e-3), tau=st.floats(2.0, 60.0),
       s=st.floats(0.05, 1.0), T=st.floats(0.5, 60.0))
def test_steady_start_is_the_fixed_point_of_cleaning_and_growth(R_start, dR, tau, s, T):
    fit = law("kern_seaton", R_start, dR / tau, tau)
    comp = FoulingComponent(fit, s, CostCurve([0.0, 1e-3], [0.0, 40.0]))
    y_post = float(comp.start_level(T))
    assert 0.0 <= y_post <= fit.y_inf
    assert y_post == pytest.approx((1 - s) * float(fit.growth(y_post, T)), rel=1e-9, abs=1e-15)
    tc = comp.crossing_times(np.array([T]), np.array([y_post + 0.5 * (fit.y_inf - y_post)]))[0, 0]
    if tc < T:                                    # the path reaches the midway level at tc
        assert float(fit.growth(y_post, tc)) == pytest.approx(y_post + 0.5 * (fit.y_inf - y_post), rel=1e-9)


@settings(max_examples=80, deadline=None)
@given(levels=st.lists(st.floats(0.0, 8e-3), min_size=2, max_size=9, unique=True),
       r0=st.floats(1e-6, 1e-3), tau=st.floats(2.0, 200.0), R0=st.floats(0.0, 4e-3),
       s=st.floats(0.05, 1.0), law_=st.sampled_from(["kern_seaton", "linear"]),
       restart=st.sampled_from(["auto", "current"]))
def test_a_cycles_cost_over_its_non_zero_pieces_is_the_cost_over_every_piece(levels, r0, tau, R0, s, law_,
                                                                              restart):
    """The cycle cost integrates only a window of whole pieces around each cycle's pieces of
    non-zero length (``cost._pieces``; the others are exact zeros of the sum): the numbers of
    integrating every piece, to the bit, for 1 to 10 pieces (past 8 every piece is kept), both laws,
    both restarts, sigma points stacked and alone, levels below the start and out of reach."""
    import dataclasses
    import model.analysis.cost as C
    from model.analysis import speedkernel
    levels = sorted(levels)
    cost = CostCurve(levels, [1e4 * x * (1 + 0.3 * i) for i, x in enumerate(levels)])
    cov = np.diag([1e-4, 2e-5, 0.02][: 3 if law_ == "kern_seaton" else 2]) ** 2
    fit = dataclasses.replace(law(law_, R0, r0, tau), cov=cov)
    comps = [FoulingComponent(fit, s, cost, restart=restart, uncertain=True),
             FoulingComponent(fit, s, cost, restart=restart, name="alone")]
    expanded = C._expand(comps)
    T = np.concatenate([np.geomspace(0.25, 365.0, 40), np.linspace(3.0, 4.0, 21)])
    orig = C._pieces
    keep, speedkernel._KERNEL = speedkernel._KERNEL, None     # numpy's pieces (the kernel: test_speedkernel)
    try:
        got = C._cycle_cost(expanded, T)
        C._pieces = lambda e: (e[:, :, :-1], np.diff(e, axis=2))
        ref = C._cycle_cost(expanded, T)
    finally:
        C._pieces = orig
        speedkernel._KERNEL = keep
    assert np.array_equal(got, ref)


@pytest.mark.parametrize("law_, restart, cov", [
    ("kern_seaton", "auto", np.diag([1e-4, 2e-5, 0.02]) ** 2),
    ("kern_seaton", "current", np.diag([1e-4, 2e-5, 0.02]) ** 2),
    ("linear", "auto", np.diag([1e-4, 3e-4]) ** 2),          # r0's lower sigma point clipped to 0
    ("linear", "current", np.diag([1e-4, 2e-5]) ** 2),
])
def test_sigma_points_in_one_array_give_each_points_own_cycle_cost(law_, restart, cov, monkeypatch):
    """A component's sigma points are integrated in one set of array operations (stop 30): the
    same numbers to the bit as one point after the other, for both laws and restarts, beside a
    component of its own (the pump's)."""
    import dataclasses
    import model.analysis.cost as C
    from model.analysis import speedkernel
    monkeypatch.setattr(speedkernel, "_KERNEL", None)       # numpy's (the kernel: test_speedkernel)
    fit = dataclasses.replace(law(law_, 3e-3, 0.2e-3, 15.0), cov=cov)
    R = FoulingComponent(fit, 0.3, CostCurve([0.0, 1e-3, 4e-3], [0.0, 40.0, 190.0]), restart=restart,
                         uncertain=True)
    CF = FoulingComponent(law("kern_seaton", 1.1, 0.02, 20.0, floor=1.0), 0.3, CostCurve([1.0, 2.0], [0.0, 9.0]))
    expanded = C._expand([R, CF])
    runs = C._runs(expanded)
    assert [len(m) for _, m in runs] == [len(R.variants()), 1] and runs[0][0]
    if law_ == "linear" and restart == "auto":
        assert min(c.fit.r0 for _, c in R.variants()) == 0.0
    T = np.geomspace(0.25, 365.0, 100)
    stacked = C._cycle_cost(expanded, T)
    monkeypatch.setattr(C, "_runs", lambda ex: [(False, [v]) for v in ex])
    one_by_one = C._cycle_cost(expanded, T)
    assert np.array_equal(stacked, one_by_one)
    # every piece integrated, also those of length 0 (``_pieces`` keeps the non-zero ones' window)
    monkeypatch.setattr(C, "_pieces", lambda e: (e[:, :, :-1], np.diff(e, axis=2)))
    every_piece = C._cycle_cost(expanded, T)
    assert np.array_equal(stacked, every_piece)
