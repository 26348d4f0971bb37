"""Set-point optimization (SPEC §6): agreement with a brute-force sweep, the HS-speed plateau, bounds."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from model import batch
from model.batch import simulate_batch
from model.optimize import (COLUMNS, PLATEAU_REUSE_BAR, SOLVED, Evaluator, OptimizationError,
                            optimize_setpoint, sweep)
from simulator.synthetic import Noise, Operation, Truth, generate

SWEEP_STEP = 0.05         # bar, brute-force resolution (issue #4)
AGREE_TOL = 0.05          # bar, optimizer vs brute force (issue #4)


@pytest.fixture(scope="module")
def window(plant):
    """8 one-minute samples of a fouled plant at the business-as-usual set point, and its model."""
    op = Operation(hours=1.5, commissioning_minutes=0, p_m_sp_barg=10.0)
    sh = generate(plant, op, Truth(), Noise(), seed=5)
    true = sh.params.replace(R_th_f=3.5e-6, CF_dp_f=1.2)
    return sh.history.iloc[40:48].reset_index(drop=True), true


@pytest.fixture(scope="module")
def brute(window):
    data, par = window
    return sweep(data, par, step=SWEEP_STEP)


def test_optimizer_agrees_with_brute_force(window, brute):
    data, par = window
    res = optimize_setpoint(data, par)
    best = brute.loc[brute["COP"].idxmax()]
    assert abs(res.p_m_sp_opt_barg - best["p_m_sp_barg"]) <= AGREE_TOL
    assert res.COP_opt >= best["COP"] * (1 - 1e-9)         # at least as good as the best grid point
    assert not res.hs_saturated
    amb = par.ambient_pressure / 1e5
    assert res.p_m_opt_bar_a == pytest.approx(res.p_m_sp_opt_barg + amb, abs=1e-6)


def test_changes_against_actual_and_geometric_mean(window, brute):
    data, par = window
    res = optimize_setpoint(data, par)
    ref = simulate_batch(data, par)
    cop_actual = ref["Q_sink_kW"].sum() / ref["W_total_kW"].sum()
    assert res.COP_actual == pytest.approx(cop_actual, rel=1e-12)
    assert res.dCOP_opt_pct == pytest.approx(100 * (res.COP_opt / cop_actual - 1), rel=1e-9)
    assert res.dQ_sink_opt_pct == pytest.approx(100 * (res.Q_sink_opt_kW / ref["Q_sink_kW"].mean() - 1), rel=1e-9)
    gm = math.sqrt(ref["p_e_bar"].mean() * ref["p_c_bar"].mean())
    assert res.p_m_gm_bar_a == pytest.approx(gm, rel=1e-12)
    assert res.COP_opt >= res.COP_actual and res.COP_opt >= res.COP_gm
    assert res.dCOP_gm_pct >= 0.0
    # the geometric-mean COP is the sweep's COP there (to the sweep's interpolation)
    amb = par.ambient_pressure / 1e5
    near = brute.iloc[(brute["p_m_sp_barg"] - (gm - amb)).abs().argmin()]
    assert res.COP_gm == pytest.approx(near["COP"], rel=2e-3)


def test_bounds_are_p_e_and_p_c(window):
    data, par = window
    res = optimize_setpoint(data, par)
    ref = simulate_batch(data, par)
    amb = par.ambient_pressure / 1e5
    lo, hi = res.bounds_barg
    assert lo >= ref["p_e_bar"].max() - amb
    assert hi <= ref["p_c_bar"].min() - amb
    assert lo <= res.p_m_sp_opt_barg <= hi


def test_plateau_below_hs_saturation(window, brute):
    """Below the set point the HS compressor reaches at 1800 rpm, COP does not depend on it; an
    optimum there is reported as the floating p_m (where the HS starts to hold the set point)."""
    data, par = window
    flat = brute[brute["hs_saturated"]]
    assert len(flat) > 5
    assert np.ptp(flat["COP"].to_numpy()) < 1e-9 * flat["COP"].iloc[0]
    top = float(flat["p_m_sp_barg"].max())
    res = optimize_setpoint(data, par, bounds_barg=(float(flat["p_m_sp_barg"].min()), top - 0.2))
    assert res.hs_saturated
    assert res.COP_opt == pytest.approx(flat["COP"].iloc[0], rel=1e-9)
    amb = par.ambient_pressure / 1e5
    assert res.p_m_sp_opt_barg == pytest.approx(res.p_m_opt_bar_a - amb)
    assert res.p_m_sp_opt_barg > top - 0.2            # the floating p_m lies above the searched range


def test_unsolvable_window_is_a_clear_error(window):
    data, par = window
    bad = data.copy()
    bad["T_source_out"] = bad["T_source_in"] + 1.0          # source heated: no operating point
    with pytest.raises(OptimizationError, match="solves none"):
        optimize_setpoint(bad, par)
    with pytest.raises(OptimizationError, match="empty set-point range"):
        optimize_setpoint(data, par, bounds_barg=(20.0, 19.0))
    with pytest.raises(OptimizationError, match="lacks input columns"):
        optimize_setpoint(pd.DataFrame({"T_source_in": [25.0]}), par)


COL_RTOL = 1e-7           # the scalar and the vectorised solver (tests/test_vcycle: 1e-9 on states)


def test_a_points_columns_are_its_frames_on_the_scalar_and_the_vectorised_path(window, monkeypatch):
    """``Point.col`` reads a column without a DataFrame on the vectorised path and from the frame
    on the scalar one (where status is a string column): the same values either way, and the same
    as ``frame``'s."""
    data, par = window
    w = np.ones(len(data))
    got = {}
    for vec in (True, False):
        monkeypatch.setattr(batch, "VECTORISED", vec)
        p = Evaluator(data, w, par).at(11.0)
        assert p.ok
        for c in COLUMNS:
            assert np.array_equal(p.col(c), p.frame[c].to_numpy(dtype=float), equal_nan=True), c
        assert list(p.col("status")) == list(p.frame["status"]) and set(p.col("status")) <= set(SOLVED)
        got[vec] = p
    for c in ("COP", "p_m_bar", "W_LS_kW", "eta_is_HS"):
        np.testing.assert_allclose(got[True].col(c), got[False].col(c), rtol=COL_RTOL, err_msg=c)


def test_a_row_on_the_hs_plateau_answers_lower_set_points_without_a_solve(window, brute):
    """The vectorised Evaluator, as the scalar one: a row that ran HS-saturated (p_m floating above
    the set point) gives that solution for every set point PLATEAU_REUSE_BAR or more below its
    floating p_m, without solving it again — the figures a fresh solve there gives (the plateau's
    COP does not depend on the set point, test_plateau_below_hs_saturation)."""
    data, par = window
    flat = brute[brute["hs_saturated"]]
    top, low = float(flat["p_m_sp_barg"].max()), float(flat["p_m_sp_barg"].min())
    w = np.ones(len(data))
    amb = par.ambient_pressure / 1e5
    ev = Evaluator(data, w, par)
    first = ev.at(top)
    assert first.ok and first.hs_saturated
    assert (first.col("p_m_bar") - amb >= top + PLATEAU_REUSE_BAR).all()   # floating above: reusable
    solves = ev.solves
    above = float((first.col("p_m_bar") - amb).max()) + 0.1     # above every row's floating p_m
    below, mixed = ev.at_many([low, above])
    assert ev.solves == solves + len(data)           # only the set point above the plateau solved
    assert mixed.ok and mixed.sp == pytest.approx(above, abs=1e-9) and not mixed.hs_saturated
    assert below.hs_saturated and below.COP == first.COP
    for c in ("Q_sink_kW", "W_total_kW", "p_m_bar", "N_HS_rpm", "p_c_bar", "status"):
        assert list(below.col(c)) == list(first.col(c)), c          # the plateau's own rows
    # a fresh solve on the plateau gives the same figures (where its cold start solves every row:
    # at the plateau's low end some rows' cold branch test ends out of the compressor map)
    for sp in sorted(flat["p_m_sp_barg"]):
        fresh = Evaluator(data, w, par).at(sp)
        if fresh.ok:
            break
    assert fresh.ok and fresh.hs_saturated and sp < top
    again = ev.at(sp)
    assert ev.solves == solves + len(data)
    assert again.COP == pytest.approx(fresh.COP, rel=COL_RTOL)
    for c in ("Q_sink_kW", "W_total_kW", "p_m_bar", "N_HS_rpm", "p_c_bar"):
        np.testing.assert_allclose(again.col(c), fresh.col(c), rtol=COL_RTOL, err_msg=c)
