"""Fouling forecast (issue 10): Kern–Seaton recovery, linear fallback, not-enough-data, bands, limits."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from model.analysis.forecast import (FitSettings, ForecastError, LawPrior, NotEnoughData, dphi_dk,
                                     fit_fouling, law_prior, phi)

R0, R_INF, TAU = 2.5e-3, 6.0e-3, 15.0        # the simulator's law (config/simulator.yaml), K/kW, days
NOISE = 0.05e-3                              # per 2-h window estimate [K/kW]
EDGE_RTOL = 1e-12                            # the scalar upper edge against the array band (rounding)


def ks(t, R0=R0, R_inf=R_INF, tau=TAU):
    return R0 + (R_inf - R0) * (1 - np.exp(-np.asarray(t) / tau))


def windows(days, hours=2.0):
    """Mid-times of consecutive windows over ``days`` [day]."""
    return np.arange(hours / 48.0, days, hours / 24.0)


def test_phi_and_its_derivative_are_continuous_at_k_zero():
    t = np.array([0.0, 0.5, 3.0, 12.0])
    assert np.allclose(phi(t, 0.0), t)
    assert np.allclose(phi(t, 1e-9), t, rtol=1e-8)
    for k in (1e-7, 1e-4, 0.07, 2.0):
        h = 1e-6 * max(k, 1e-6)
        fd = (phi(t, k + h) - phi(t, k - h)) / (2 * h) if k > h else (phi(t, k + h) - phi(t, k)) / h
        assert np.allclose(dphi_dk(t, k), fd, rtol=1e-4, atol=1e-9)
    assert np.allclose(dphi_dk(t, 0.0), -t * t / 2)


def test_kern_seaton_without_noise_is_recovered_exactly():
    t = windows(12)
    f = fit_fouling(t, ks(t), np.full(len(t), NOISE))
    assert f.law == "kern_seaton"
    assert f.y0 == pytest.approx(R0, rel=1e-6)
    assert f.y_inf == pytest.approx(R_INF, rel=1e-6)
    assert f.tau_days == pytest.approx(TAU, rel=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kern_seaton_with_noise_is_recovered_within_its_errors(seed):
    rng = np.random.default_rng(seed)
    t = windows(12)
    R = ks(t) + rng.normal(0, NOISE, len(t))
    f = fit_fouling(t, R, np.full(len(t), NOISE))
    se = f.std_errors()
    assert f.law == "kern_seaton", f.reason
    # within 3 standard errors and within stated absolute tolerances
    assert abs(f.y0 - R0) <= 3 * se["y0"] and abs(f.y0 - R0) <= 0.05e-3
    assert abs(f.y_inf - R_INF) <= 3 * se["y_inf"] and abs(f.y_inf - R_INF) <= 0.6e-3
    assert abs(f.tau_days - TAU) <= 3 * se["tau_days"] and abs(f.tau_days - TAU) <= 0.3 * TAU
    assert f.s2 == pytest.approx(1.0, abs=0.35)        # se were right: chi2/dof near 1
    assert f.rate(0.0) == pytest.approx((R_INF - R0) / TAU, rel=0.2)
    assert f.rate(t[-1]) < f.rate(0.0)


def test_linear_series_falls_back_to_the_linear_law():
    rng = np.random.default_rng(3)
    t = windows(6)
    R = 1.0e-3 + 0.2e-3 * t + rng.normal(0, NOISE, len(t))
    f = fit_fouling(t, R, np.full(len(t), NOISE))
    assert f.law == "linear"
    assert f.tau_days == math.inf and f.y_inf == math.inf
    se = f.std_errors()
    assert abs(f.r0 - 0.2e-3) <= 3 * se["r0"]
    assert abs(f.y0 - 1.0e-3) <= 3 * se["y0"]
    assert f.rate(3.0) == f.r0
    assert "curvature" in f.reason


def test_early_kern_seaton_data_fall_back_to_linear_with_the_reason():
    """Four days of the simulator's law: the curvature is below the noise, tau >> span."""
    rng = np.random.default_rng(0)
    t = windows(4)
    f = fit_fouling(t, ks(t) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE))
    assert f.law == "linear"
    assert "not significant" in f.reason or "infinite" in f.reason


def test_too_few_windows_is_not_enough_data_not_a_number():
    with pytest.raises(NotEnoughData) as exc:
        fit_fouling([0.1, 0.5, 1.0, 1.5, 2.0], [1e-3] * 5, [1e-5] * 5)
    assert str(exc.value) == ("not enough data: 5 window estimate(s) over 1.90 days since the last reset; "
                              "a forecast needs >= 6 over >= 1 days")
    assert exc.value.n == 5


def test_too_short_a_span_is_not_enough_data():
    t = np.linspace(0.0, 0.9, 11)
    with pytest.raises(NotEnoughData, match=r"11 window estimate\(s\) over 0.90 days"):
        fit_fouling(t, 1e-3 + 1e-4 * t, np.full(11, 1e-5))


def test_non_finite_estimates_are_dropped_and_counted():
    t = windows(3)
    R = 1e-3 + 1e-4 * t
    R[[2, 5]] = np.nan
    f = fit_fouling(t, R, np.full(len(t), 1e-5))
    assert f.n == len(t) - 2 and f.n_dropped == 2
    t6 = np.array([0.0, 0.3, 0.6, 0.9, 1.2, 1.5])
    R6 = np.array([1, 1, 1, np.nan, 1, 1.0]) * 1e-3
    with pytest.raises(NotEnoughData, match=r"5 window estimate\(s\) over 1.50 days"):  # NaN does not count
        fit_fouling(t6, R6, np.full(6, 1e-5))


@pytest.mark.parametrize("args, message", [
    (([0, 1, 2], [1, 2], None), "t_days, y and se differ in length: 3, 2, 3"),
    (([-1.0, 0, 1, 2, 3, 4], [1] * 6, None), "t_days must be >= 0 (days since the last reset), got -1"),
])
def test_malformed_input_is_a_forecast_error(args, message):
    with pytest.raises(ForecastError) as exc:
        fit_fouling(*args)
    assert str(exc.value) == message


def test_settings_and_arguments_are_checked():
    with pytest.raises(ForecastError, match="law must be"):
        fit_fouling(windows(3), np.ones(36), law="exp")
    with pytest.raises(ForecastError, match="overlap must be a number >= 1"):
        fit_fouling(windows(3), np.ones(36), overlap=0.5)
    with pytest.raises(ForecastError, match="forecast setting alpha"):
        FitSettings(alpha=1.5)


def test_physical_bounds_hold_for_falling_data():
    """R falling with time (e.g. loose deposits washing off) cannot give R_inf < R0: the rate is 0."""
    rng = np.random.default_rng(5)
    t = windows(5)
    f = fit_fouling(t, 3e-3 - 0.1e-3 * t + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE))
    assert f.r0 == 0.0 and f.rate(1.0) == 0.0
    assert f.y0 == pytest.approx(np.mean(3e-3 - 0.1e-3 * t), abs=0.05e-3)
    g = fit_fouling(t, -1e-4 + 0 * t + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE))
    assert g.y0 >= 0.0                                   # floor


@settings(max_examples=40, deadline=None)
@given(R0_=st.floats(0.0, 5e-3), dR=st.floats(0.0, 4e-3), tau=st.floats(1.0, 200.0),
       span=st.floats(1.0, 20.0), noise=st.floats(1e-6, 2e-4), seed=st.integers(0, 2 ** 16))
def test_fit_respects_the_bounds_and_the_band_brackets_the_curve(R0_, dR, tau, span, noise, seed):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, span, 30)
    R = ks(t, R0_, R0_ + dR, tau) + rng.normal(0, noise, len(t))
    f = fit_fouling(t, R, np.full(len(t), noise))
    assert f.y0 >= 0.0 and f.r0 >= 0.0 and f.k >= 0.0 and f.tau_days > 0
    assert f.y_inf >= f.y0
    tt = np.linspace(0, span + 10, 25)
    lo, hi = f.band(tt)
    v = f.value(tt)
    assert np.all(lo <= v + 1e-15) and np.all(v <= hi + 1e-15) and np.all(lo >= 0.0)
    assert np.all(np.diff(v) >= -1e-15)                  # non-decreasing
    mlo, mhi = f.band(tt, kind="mean")
    assert np.all(mhi - mlo <= hi - lo + 1e-15)          # the mean band is inside the prediction band


def test_prediction_band_covers_at_about_its_nominal_rate():
    """200 seeded cases of the simulator's law with noise, 2 days ahead: the 90 % prediction band
    covers a new window estimate in 80-98 % of them, the mean band covers the true curve in >= 80 %."""
    rng = np.random.default_rng(2024)
    hit_new = hit_true = 0
    n_cases = 200
    for _ in range(n_cases):
        R0_ = rng.uniform(1e-3, 4.5e-3)
        span = rng.uniform(6.0, 12.0)
        t = windows(span)
        f = fit_fouling(t, ks(t, R0_) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE))
        t_f = t[-1] + 2.0
        truth = float(ks(t_f, R0_))
        lo, hi = f.band(t_f, 0.90)
        hit_new += lo <= truth + rng.normal(0, NOISE) <= hi
        mlo, mhi = f.band(t_f, 0.90, kind="mean")
        hit_true += mlo <= truth <= mhi
    assert 0.80 <= hit_new / n_cases <= 0.98
    assert hit_true / n_cases >= 0.80


def test_horizon_prediction_and_limit_crossing():
    rng = np.random.default_rng(7)
    t = windows(10)
    f = fit_fouling(t, ks(t) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE))
    p = f.at_horizon()                                   # default 7 days after the last estimate
    assert p.t_days == pytest.approx(t[-1] + 7.0)
    assert p.lo < p.value < p.hi and p.level == 0.90
    assert abs(p.value - ks(p.t_days)) < 0.3e-3
    limit = 5.5e-3
    c = f.reach(limit)
    assert c.mean_days is not None and c.mean_days > t[-1]
    assert f.value(c.mean_days) == pytest.approx(limit, rel=1e-9)
    assert c.upper_days is not None and c.upper_days <= c.mean_days
    assert f.band(c.upper_days)[1] == pytest.approx(limit, rel=1e-6)
    assert f.reach(f.y_inf + 1e-3).mean_days is None                 # above the asymptote: never
    now_above = f.reach(1e-3)
    assert now_above.mean_days == t[-1] and now_above.upper_days == t[-1]


def test_linear_law_limit_crossing_is_closed_form():
    t = windows(4)
    f = fit_fouling(t, 1e-3 + 0.25e-3 * t, np.full(len(t), 1e-5))
    assert f.law == "linear"
    assert f.reach(3e-3).mean_days == pytest.approx(8.0, rel=1e-6)


def test_cf_dp_f_is_fitted_with_its_own_floor():
    rng = np.random.default_rng(11)
    t = windows(12)
    CF = 1.0 + ks(t, 0.08, 0.40, 20.0) + rng.normal(0, 0.005, len(t))
    f = fit_fouling(t, CF, np.full(len(t), 0.005), floor=1.0)
    assert f.floor == 1.0 and f.y0 >= 1.0
    assert abs(f.value(14.0) - (1.0 + ks(14.0, 0.08, 0.40, 20.0))) < 0.02
    g = fit_fouling(t, np.full(len(t), 0.98), np.full(len(t), 0.005), floor=1.0)
    assert g.y0 == 1.0 and g.band(3.0)[0] >= 1.0


def test_overlapping_windows_widen_the_covariance():
    rng = np.random.default_rng(2)
    t = windows(8)
    R = ks(t) + rng.normal(0, NOISE, len(t))
    a = fit_fouling(t, R, np.full(len(t), NOISE))
    b = fit_fouling(t, R, np.full(len(t), NOISE), overlap=8.0)
    assert b.law == a.law
    assert np.allclose(b.cov, 8.0 * a.cov, rtol=1e-9)
    assert b.dof == pytest.approx(a.dof / 8.0)


def test_a_prior_from_earlier_cycles_gives_kern_seaton_on_a_short_cycle():
    """Two days after a CIP the curvature is invisible; the plant's law from the previous cycle is not.
    Over 40 seeded cycles, forecasting 7 days past the data: the prior halves the mean error and its
    band covers the truth in >= 80 %."""
    rng = np.random.default_rng(4)
    t1 = windows(10)
    first = fit_fouling(t1, ks(t1) + rng.normal(0, NOISE, len(t1)), np.full(len(t1), NOISE))
    assert first.law == "kern_seaton"
    prior = law_prior([first])
    assert prior.n_cycles == 1
    assert abs(1 / prior.k - TAU) < 0.3 * TAU and abs(prior.y_inf - R_INF) < 0.6e-3
    R_post, t2, t_f = 4.4e-3, windows(2), 9.0
    truth = ks(t_f, R_post)
    err_free, err_prior, covered = [], [], 0
    for _ in range(40):
        R2 = ks(t2, R_post) + rng.normal(0, NOISE, len(t2))
        free = fit_fouling(t2, R2, np.full(len(t2), NOISE))
        with_prior = fit_fouling(t2, R2, np.full(len(t2), NOISE), prior=prior)
        assert free.law == "linear" and with_prior.law == "kern_seaton"
        assert "prior" in with_prior.reason
        err_free.append(abs(free.value(t_f) - truth))
        err_prior.append(abs(with_prior.value(t_f) - truth))
        lo, hi = with_prior.band(t_f)
        covered += lo <= truth <= hi
    assert np.mean(err_prior) < 0.5 * np.mean(err_free)
    assert covered / 40 >= 0.80


def test_law_prior_skips_linear_fits_and_combines_cycles():
    rng = np.random.default_rng(8)
    fits = []
    for R_start in (2.5e-3, 4.2e-3):
        t = windows(11)
        fits.append(fit_fouling(t, ks(t, R_start) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE)))
    t = windows(3)
    lin = fit_fouling(t, 1e-3 + 1e-4 * t, np.full(len(t), NOISE))
    assert lin.law == "linear"
    assert law_prior([lin, None]) is None
    p = law_prior(fits + [lin])
    assert p.n_cycles == 2
    ks_k = [f.k for f in fits]
    assert min(ks_k) <= p.k <= max(ks_k)
    assert p.k_sd >= 0.1 * p.k and p.y_inf_sd >= 0.1 * p.y_inf
    with pytest.raises(ForecastError, match="a law prior needs"):
        LawPrior(-1.0, 0.1, 6e-3, 1e-3, 1)


def test_forced_laws():
    t = windows(6)
    R = ks(t)
    assert fit_fouling(t, R, law="linear").law == "linear"
    f = fit_fouling(windows(3), ks(windows(3)), law="kern_seaton")
    assert f.law == "kern_seaton" and f.reason == "law forced by the caller"
    with pytest.raises(ForecastError, match="cannot be fitted"):
        fit_fouling(t, 1e-3 + 1e-4 * t, law="kern_seaton")


def test_to_dict_is_plain_numbers():
    t = windows(4)
    d = fit_fouling(t, 1e-3 + 1e-4 * t, np.full(len(t), 1e-5)).to_dict()
    assert d["law"] == "linear" and d["y_inf"] is None and d["tau_days"] is None
    assert all(isinstance(v, (int, float, str, dict, type(None))) for v in d.values())


def test_the_profile_finds_the_best_k_as_a_tight_bounded_search_does():
    """``_profile``'s nested grids (array evaluations, in place of a bounded Brent search since stop
    32) find the least-squares k of a Kern–Seaton series to within PROFILE_K_RTOL of a bounded
    search at a tight tolerance, with an objective no worse than its by more than
    PROFILE_OBJ_RTOL; and where the profile falls toward k = 0 (a straight line), a k within 1e-5
    of the bracket's top, as the bounded search on (0, b) with tolerance 1e-6 b ends."""
    from scipy import optimize as sopt
    from model.analysis.forecast import _ls_at, _ls_many, _profile
    PROFILE_K_RTOL, PROFILE_OBJ_RTOL = 1e-5, 1e-10
    rng = np.random.default_rng(3)
    for tau, noise in ((4.0, 0.002), (12.0, 0.004), (30.0, 0.003)):
        t = np.linspace(0.1, 25.0, 150)
        y = 0.3 * (1.0 - np.exp(-t / tau)) + rng.normal(0.0, noise, len(t))
        sw = np.full(len(t), 100.0)
        k_hi = 50.0 / (t.max() - t.min())
        k, v, v0 = _profile(t, y, sw, k_hi, lambda k: _ls_at(k, t, y, sw)[2], lambda ks: _ls_many(ks, t, y, sw)[2])
        ref = sopt.minimize_scalar(lambda k: _ls_at(k, t, y, sw)[2], bounds=(0.5 * k, 2.0 * k), method="bounded",
                                   options={"xatol": 1e-12 * k})
        assert abs(k - ref.x) <= PROFILE_K_RTOL * ref.x, (tau, k, ref.x)
        assert v <= ref.fun * (1.0 + PROFILE_OBJ_RTOL)
        assert v0 == pytest.approx(_ls_at(0.0, t, y, sw)[2], rel=1e-12)      # the straight line's
        assert abs(1.0 / k - tau) < 0.25 * tau          # the law's time constant, through the noise
    # a straight line: the profile falls toward k = 0
    t = np.linspace(0.1, 25.0, 150)
    y = 0.01 * t
    sw = np.ones(len(t))
    k_hi = 50.0 / (t.max() - t.min())
    k, v, v0 = _profile(t, y, sw, k_hi, lambda k: _ls_at(k, t, y, sw)[2], lambda ks: _ls_many(ks, t, y, sw)[2])
    b = np.geomspace(k_hi * 1e-4, k_hi, 60)[1]
    assert 0.0 < k <= 1e-5 * b and v0 <= v


def _prior_case(seed: int, n: int = 40, span: float = 20.0, growth: float = 0.0):
    """A cycle's estimates (flat plus ``growth`` per day, noise 0.02) and a prior law from earlier
    cycles: (t, y, se, prior)."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, span, n))
    t[0] = 0.0
    y = 0.4 + growth * t + rng.normal(0.0, 0.02, n)
    return t, y, np.full(n, 0.02), LawPrior(k=0.11, k_sd=0.08, y_inf=0.9, y_inf_sd=0.15, n_cycles=2)


def _jacobian(k, r0, t, se):
    """The weighted Jacobian of (a0, r0, k) at (r0, k), as ``_fit_fouling`` builds it."""
    from model.analysis.forecast import _weights
    sw = 1.0 / _weights(se, FitSettings().se_floor_share)
    return np.stack([sw, sw * phi(t, k), sw * r0 * dphi_dk(t, k)], axis=1)


def test_a_prior_fit_is_the_inverse_information_in_its_own_parameters():
    """Where the data show growth (a well-conditioned fit) the covariance of a fit with a prior,
    computed in (a0, y_inf, k), is the inverse of the information in (a0, r0, k) with the prior on
    y_inf through its gradient (1, 1/k, -r0/k^2) and on k, to COV_RTOL."""
    from model.analysis.forecast import _prior_covariance
    COV_RTOL = 1e-8
    t, y, se, prior = _prior_case(5, growth=0.012)
    fit = fit_fouling(t, y, se, prior=prior)
    assert fit.law == "kern_seaton" and fit.k > 0.2 * prior.k       # curvature seen: not degenerate
    J = _jacobian(fit.k, fit.r0, t, se)
    g = np.array([1.0, 1.0 / fit.k, -fit.r0 / fit.k ** 2])
    info = J.T @ J / (fit.s2 * fit.overlap) + np.outer(g, g) / prior.y_inf_sd ** 2
    info[2, 2] += 1.0 / prior.k_sd ** 2
    direct = np.linalg.inv(info)
    assert np.linalg.cond(info) < 1e8
    np.testing.assert_allclose(fit.cov, direct, rtol=COV_RTOL, atol=COV_RTOL * np.abs(direct).max())
    np.testing.assert_allclose(_prior_covariance(J, fit.k, fit.r0, fit.s2, fit.overlap, prior), fit.cov,
                               rtol=1e-12, atol=0.0)


def test_a_prior_fit_of_a_flat_cycle_has_a_band_that_does_not_depend_on_where_the_search_stopped():
    """A cycle that shows no growth with an earlier cycles' law as prior: the best 1/tau tends to 0
    with r0/k held (the search stops near 1e-9 d^-1). The band's upper edge 7 days ahead — what the
    CIP plan's limit crossing uses — is then the same, to BAND_RTOL of the data's range, whether the
    search stopped at that k or at a hundredth of it (in (a0, r0, k) the information had a
    condition number ~1e16 there: the edge moved by 4 % of the data's range in the first case, by up
    to 45 % in 400 random series at stop 32); and the band still carries the prior's growth: wider
    than the flat data's own scatter."""
    from model.analysis.forecast import _prior_covariance
    BAND_RTOL = 1e-6
    for seed in (2, 3, 6):
        t, y, se, prior = _prior_case(seed)
        fit = fit_fouling(t, y, se, prior=prior)
        assert fit.law == "kern_seaton" and fit.k < 1e-6 * prior.k, (seed, fit.k)      # degenerate
        edges = []
        for scale in (1.0, 0.01):
            k, r0 = fit.k * scale, fit.r0 * scale
            cov = _prior_covariance(_jacobian(k, r0, t, se), k, r0, fit.s2, fit.overlap, prior)
            moved = dataclasses.replace(fit, k=k, r0=r0, cov=cov)
            edges.append(moved.band(fit.t_last + 7.0)[1])
        assert edges[0] == pytest.approx(fit.band(fit.t_last + 7.0)[1], rel=1e-12)
        assert abs(edges[0] - edges[1]) <= BAND_RTOL * np.ptp(y), (seed, edges)
        lo, hi = fit.band(fit.t_last + 7.0, kind="mean")
        assert hi - fit.value(fit.t_last + 7.0) > 0.5 * fit.se_typ        # the prior's possible growth



@pytest.mark.parametrize("law_", ["kern_seaton", "linear"])
def test_the_upper_edges_written_out_quadratic_form_is_the_sums_to_the_bit(law_):
    """``_upper_edge`` writes g' C g out term by term: the numbers of the sums
    sum(g_i sum(c_ij g_j)) (Python's float sums from 0, left to right) at every t, through the
    series near k t = 0 and far out."""
    from scipy import special
    rng = np.random.default_rng(5)
    t = windows(10)
    f = fit_fouling(t, ks(t) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE), law=law_)
    assert f.law == law_
    q = float(special.stdtrit(max(f.dof, 1.0), 0.5 + 0.9 / 2.0))
    c = [[float(x) for x in row] for row in np.asarray(f.cov, dtype=float)]
    extra = f.s2 * f.se_typ ** 2

    def ref(x):
        ph = x if f.k == 0.0 else -math.expm1(-f.k * x) / f.k
        if law_ == "kern_seaton":
            series = -x * x / 2.0 + f.k * x ** 3 / 3.0 - f.k * f.k * x ** 4 / 8.0
            d = series if (f.k == 0.0 or f.k * x < 1e-3) else (x * math.exp(-f.k * x) - ph) / f.k
            g = [1.0, ph, f.r0 * d]
        else:
            g = [1.0, x]
        var = 0
        for gi, row in zip(g, c):
            inner = 0
            for cij, gj in zip(row, g):
                inner = inner + cij * gj
            var = var + gi * inner
        return f.floor + f.a0 + f.r0 * ph + q * math.sqrt(max(var + extra, 0.0))
    hi = f._upper_edge(0.9)
    for x in [0.0, 1e-6, 1e-4, 0.5, *rng.uniform(0.0, 400.0, 40), t[-1], 30.0, 3650.0]:
        assert hi(float(x)) == ref(float(x)), x


@pytest.mark.parametrize("law_", ["kern_seaton", "linear"])
def test_the_upper_edge_reach_bisects_on_is_the_prediction_bands(law_):
    """``reach`` bisects on a scalar form of the band's upper edge: the band's numbers, on both
    laws, through the series near k t = 0 and far out; and the crossing it finds is the band's."""
    rng = np.random.default_rng(3)
    t = windows(10)
    f = fit_fouling(t, ks(t) + rng.normal(0, NOISE, len(t)), np.full(len(t), NOISE), law=law_)
    assert f.law == law_
    hi = f._upper_edge(0.9)
    for x in [0.0, 1e-6, 1e-4, 0.5, t[-1], 30.0, 400.0, 3650.0]:
        assert hi(x) == pytest.approx(f.band(x, 0.9)[1], rel=EDGE_RTOL, abs=0.0), x
    c = f.reach(float(f.band(t[-1] + 5.0, 0.9)[1]), level=0.9)
    assert c.upper_days == pytest.approx(t[-1] + 5.0, abs=1e-9)
