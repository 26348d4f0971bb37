"""The truth evaluator (simulator/truth.py): it reproduces the plant's own truth, its optimum is
not beaten by a brute-force sweep, the HS-saturation plateau convention, the families' optima
against plant.yaml's curves, and clear errors."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from simulator.config import load_simulator_config
from simulator.export import export_history
from simulator.truth import TruthError, TruthModel, condition_row

CFG = load_simulator_config()
FAMILIES = ("ratio_only", "speed_peak", "low_peak")
COP_REPRO_RTOL = 1e-4      # re-solved minutes vs the plant's truth; the floating T_source,out at the
                           # LS speed limit is found to 0.3 rpm, worth up to ~3e-5 in COP
COP_REPRO_RTOL_FREE = 1e-8 # minutes with the LS inside its range: the same equations, re-solved
SWEEP_STEP = 0.05          # bar, the brute-force comparison
SWEEP_RTOL = 1e-6          # the optimum may trail the sweep's best point only by solver noise
MIN_OPT_SHIFT = 0.5        # bar: each family's true optimum against plant.yaml's curves


@pytest.fixture(scope="module")
def history():
    """17 plant hours on the speed_peak family, fouled so that the LS reaches its speed limit in
    the afternoon, with the set point at 10 bar(g) from 07:12 to 09:36."""
    cfg = CFG.with_compressor_family("speed_peak").with_sections(
        fouling={"R_th_f_initial_K_per_kW": 5.5e-3},
        control={"p_m_sp_schedule": [[0.0, 16.0], [0.3, 10.0], [0.4, 16.0]]})
    return cfg, export_history(0.7, cfg=cfg, with_truth=True).truth


def _subsampled(truth: pd.DataFrame, max_rows: int) -> pd.DataFrame:
    run = truth[(truth["running"] == 1) & (truth["cip"] == 0)]
    idx = np.unique(np.linspace(0, len(run) - 1, min(max_rows, len(run))).round().astype(int))
    return run.iloc[idx]


@pytest.mark.parametrize("start", [0, 440, 780])     # morning, 10 bar(g), LS-limited afternoon
def test_cop_at_the_actual_set_point_reproduces_the_plants_truth(history, start):
    cfg, truth = history
    win = truth.iloc[start:start + 120]
    w = TruthModel(cfg).window(win)
    sub = _subsampled(win, 24)
    limited = (sub["ls_limit"].fillna("") != "").any()
    tol = COP_REPRO_RTOL if limited else COP_REPRO_RTOL_FREE
    COP, Q, W = w.cop_actual()
    assert w.n_rows == 24
    assert COP == pytest.approx(sub["Q_sink_kW"].sum() / sub["W_electric_kW"].sum(), rel=tol)
    assert Q == pytest.approx(sub["Q_sink_kW"].mean(), rel=tol)
    assert W == pytest.approx(sub["W_electric_kW"].mean(), rel=tol)
    sp = sub["p_m_sp_solved_bar_g"].unique()
    assert len(sp) == 1                                  # one set point in each of these windows
    assert w.cop_at(float(sp[0]))[0] == pytest.approx(COP, rel=tol)


def test_the_test_history_has_what_the_reproduction_test_needs(history):
    _, truth = history
    assert (truth["ls_limit"].iloc[:120].fillna("") == "").all()
    assert (truth["p_m_sp_solved_bar_g"].iloc[440:560] == 10.0).all()
    assert (truth["ls_limit"].iloc[780:900].fillna("") == "max").any()


@pytest.mark.parametrize("family,R_K_per_kW", [("speed_peak", 0.0), ("ratio_only", 5.5e-3)])
def test_optimum_is_not_worse_than_a_brute_force_sweep(family, R_K_per_kW):
    tm = TruthModel(CFG.with_compressor_family(family))
    rows = [condition_row(T_source_in_C=T, V_sink_m3h=V, R_th_f_K_per_kW=R_K_per_kW)
            for T, V in ((25.0, 62.0), (24.0, 55.0), (24.5, 70.0))]
    w = tm.window(rows)
    opt = w.optimum()
    lo, hi = opt["bounds_barg"]
    sweep = [(w.cop_at(sp)[0], sp) for sp in np.arange(lo, hi + 1e-9, SWEEP_STEP)]
    best_cop, best_sp = max(sweep)
    assert opt["COP_opt"] >= best_cop * (1 - SWEEP_RTOL)
    assert w.cop_at(opt["p_m_sp_opt_barg"])[0] == pytest.approx(opt["COP_opt"], rel=1e-12)
    if not opt["hs_saturated"]:
        assert abs(opt["p_m_sp_opt_barg"] - best_sp) <= SWEEP_STEP


def test_plateau_reports_the_set_point_that_just_reaches_the_floating_p_m():
    # low_peak at the nominal point, fouled to 3e-3 K/kW: the optimum is the lowest p_m the HS can
    # hold at full speed
    w = TruthModel(CFG.with_compressor_family("low_peak")).window([condition_row(R_th_f_K_per_kW=3e-3)])
    opt = w.optimum()
    assert opt["hs_saturated"]
    pt = w.point_at(opt["p_m_sp_opt_barg"])
    assert opt["p_m_sp_opt_barg"] == pytest.approx(float(pt.p_m_barg.min()), abs=1e-6)
    assert w.cop_at(opt["p_m_sp_opt_barg"] - 3.0)[0] == pytest.approx(opt["COP_opt"], rel=1e-9)  # flat
    assert w.cop_at(opt["p_m_sp_opt_barg"] + 0.5)[0] < opt["COP_opt"]


@pytest.mark.parametrize("family", FAMILIES)
def test_each_familys_optimum_differs_from_plant_yamls_curves(family):
    """At the nominal point, clean and fouled: what the benchmark needs to prove anything."""
    nominal = TruthModel(CFG.with_compressor_family("nominal"))
    fam = TruthModel(CFG.with_compressor_family(family))
    for R in (0.0, 5.5e-3):
        row = [condition_row(R_th_f_K_per_kW=R)]
        a = nominal.window(row).optimum()["p_m_sp_opt_barg"]
        b = fam.window(row).optimum()["p_m_sp_opt_barg"]
        assert abs(a - b) >= MIN_OPT_SHIFT, (family, R, a, b)


def test_set_points_are_clamped_like_a_plc_write():
    w = TruthModel(CFG.with_sections(control={"p_m_sp_limits_bar_g": [12.0, 20.0]},
                                     remote_setpoint={"bounds_bar_g": [12.0, 20.0]})).window(
        [condition_row()])
    assert w.point_at(25.0).p_m_sp_barg == 20.0 and w.cop_at(25.0) == w.cop_at(20.0)
    assert w.point_at(8.0).p_m_sp_barg == 12.0 and w.cop_at(8.0) == w.cop_at(12.0)


def test_errors_are_clear(history):
    cfg, truth = history
    tm = TruthModel(cfg)
    with pytest.raises(TruthError, match=r"truth rows lack the column\(s\) V_sink_m3h, running"):
        tm.window(truth.drop(columns=["V_sink_m3h", "running"]))
    with pytest.raises(TruthError, match=r"truth rows come from compressor family 'speed_peak', this "
                                         r"model is 'perturbed'"):
        TruthModel(CFG).window(truth.iloc[:10])
    stopped = truth.iloc[:10].assign(running=0)
    with pytest.raises(TruthError, match="the window has no running minute"):
        tm.window(stopped)
    w = tm.window(truth.iloc[:30], max_rows=3)
    with pytest.raises(TruthError, match=r"minute 2024-03-01T00:00:00Z cannot run at p_m,sp 35.000 bar\(g\)"):
        w.cop_at(35.0)
    with pytest.raises(TruthError, match="set point must be finite"):
        w.cop_at(math.nan)
    with pytest.raises(TruthError, match=r"empty set-point range"):
        w.optimum(12.0, 11.0)
