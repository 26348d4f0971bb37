"""Replay of a history with fouling and a CIP (SPEC §5-6, issue #4), and the analysis commands."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from edge.cli import main
from model.measured import process
from model.analysis.replay import CIP_COLUMNS, ReplayError, ReplaySettings, detect_cips, replay
from simulator.synthetic import Noise, Operation, Truth, generate

R_TOL = 0.2e-3             # K/kW per window (issue #4)
CF_DP_TOL = 0.02           # per window (issue #4)
CIP_SHARE_TOL = 5.0        # percentage points, removed share of R_th,f (issue #4)
CF_EVA_REL_TOL = 0.03
REQUIRED_WINDOW_COLUMNS = (
    "window_start", "window_end", "n_samples", "R_th_f_K_per_kW", "R_th_f_share_pct", "CF_dp_f",
    "nrmse_p_e", "nrmse_dp_source", "nrmse_COP_fixed", "nrmse_COP_adaptive", "nrmse_Q_sink_fixed",
    "nrmse_Q_sink_adaptive", "p_m_opt_barg", "p_m_gm_barg", "dCOP_opt_pct", "dQ_sink_opt_pct",
    "p_m_sp_opt_barg", "status", "advice_confident", "dCOP_opt_sd_pct")
REQUIRED_CIP_COLUMNS = ("cip_start", "cip_end", "R_th_f_before_K_per_kW", "R_th_f_after_K_per_kW",
                        "R_th_f_removed_pct", "CF_dp_f_before", "CF_dp_f_after")


@pytest.fixture(scope="module")
def history(plant):
    """Commissioning (2 h, clean), then 10 days later a day with a flagged 6-h CIP after 12 h."""
    op = Operation(hours=26, commissioning_minutes=120, gap_after_commissioning_days=10,
                   cip_starts_h=(12.0,), cip_duration_h=6.0)
    return generate(plant, op, Truth(), Noise(), seed=3)


@pytest.fixture(scope="module")
def result(plant, history):
    return replay(history.history, plant)


def _truth_in(history, start, end):
    ts = pd.to_datetime(history.truth["timestamp"], utc=True)
    m = ((ts >= pd.Timestamp(start)) & (ts <= pd.Timestamp(end)) & (history.truth["running"] == 1)).to_numpy()
    return history.truth[m]


def test_windows_recover_fouling_in_every_window(result, history):
    w = result.windows
    assert set(REQUIRED_WINDOW_COLUMNS) <= set(w.columns)
    ok = w[w["status"] == "ok"]
    assert len(ok) == len(w) >= 8
    for _, row in ok.iterrows():
        tr = _truth_in(history, row["window_start"], row["window_end"])
        assert abs(row["R_th_f_K_per_kW"] - tr["R_th_f_K_per_kW"].mean()) <= R_TOL, row["window_start"]
        assert abs(row["CF_dp_f"] - tr["CF_dp_f"].mean()) <= CF_DP_TOL, row["window_start"]
        assert 0.0 < row["R_th_f_share_pct"] < 100.0
    # the windows next to the CIP touch it and none straddles it
    cip = result.cips.iloc[0]
    ends = pd.to_datetime(ok["window_end"], utc=True)
    starts = pd.to_datetime(ok["window_start"], utc=True)
    c0, c1 = pd.Timestamp(cip["cip_start"]), pd.Timestamp(cip["cip_end"])
    assert not ((starts < c0) & (ends > c0)).any()
    assert (c0 - ends[ends < c0].max()) <= pd.Timedelta(minutes=2)
    assert (starts[starts > c1].min() - c1) <= pd.Timedelta(minutes=20)     # restart ramp only


def test_adaptive_model_beats_fixed_model_on_cop(result):
    """The papers' key result: with fouling, the adaptive model estimates COP better."""
    ok = result.windows[result.windows["status"] == "ok"]
    assert (ok["nrmse_COP_adaptive"] < ok["nrmse_COP_fixed"]).all()
    assert ok["nrmse_COP_adaptive"].mean() < 0.5 * ok["nrmse_COP_fixed"].mean()
    assert ok["nrmse_Q_sink_adaptive"].mean() < ok["nrmse_Q_sink_fixed"].mean()


def test_cip_table_reports_removed_share(result, history):
    cips = result.cips
    assert list(cips.columns) == list(CIP_COLUMNS)
    assert set(REQUIRED_CIP_COLUMNS) <= set(cips.columns)
    assert len(cips) == 1
    c = cips.iloc[0]
    truth = history.cips[0]
    assert pd.Timestamp(c["cip_start"]) == truth["start"]
    assert c["detected_by"] == "cip_flag"
    assert abs(c["R_th_f_removed_pct"] - truth["removed_pct"]) <= CIP_SHARE_TOL
    assert c["R_th_f_after_K_per_kW"] < c["R_th_f_before_K_per_kW"]
    assert c["CF_dp_f_after"] < c["CF_dp_f_before"]


def test_initial_window_and_counts(result, history):
    assert result.initial.n_samples == 90          # the first 90 usable minutes
    assert pd.Timestamp(result.initial_window[1]) < pd.Timestamp(history.cips[0]["start"])
    assert abs(result.initial.params["CF_eva"] / history.params.CF_eva - 1) <= CF_EVA_REL_TOL
    assert result.unusable["cip"] == 360
    assert result.n_rows == len(history.history)
    # the 10-day hole after commissioning ends a segment: no window spans it
    assert any("gap" in n for n in result.notes)
    after_gap = pd.Timestamp(history.history["timestamp"].iloc[120])
    assert (pd.to_datetime(result.windows["window_start"], utc=True) >= after_gap).all()
    assert result.windows_skipped == {"too few usable samples": 1}     # the commissioning tail
    text = result.summary()
    for word in ("initial calibration", "CIPs: 1", "COP NRMSE", "removed", "WARNING"):
        assert word in text


def test_optimization_per_window(result):
    ok = result.windows[result.windows["status"] == "ok"]
    assert ok["optimization_ok"].all()
    assert ok["p_m_sp_model_opt_barg"].notna().all() and ok["p_m_opt_barg"].notna().all()
    assert (ok["dCOP_model_opt_pct"] >= 0).all()
    # (where the optimum lies against the geometric mean is a property of the curves: tested on the
    # data sheet's curves in test_model_cycle; here the advice only searches where the learned
    # curves have data, which on this one-set-point history is near 10 bar(g))
    assert ((ok["p_m_sp_model_opt_barg"] > 2.0) & (ok["p_m_sp_model_opt_barg"] < 30.0)).all()
    # confident advice recommends the model's optimum (or keeps a previous one within the dead
    # band); otherwise the current set point with a reason, and no expected change
    conf = ok["advice_confident"].astype(bool)
    assert (ok.loc[~conf, "p_m_sp_opt_barg"] == ok.loc[~conf, "p_m_sp_actual_barg"]).all()
    assert (ok.loc[~conf, "dCOP_opt_pct"] == 0.0).all() and (ok.loc[~conf, "advice_note"] != "").all()
    assert (ok.loc[conf, "dCOP_opt_pct"] >= 0).all()   # 0: a confident "keep"


def test_cip_without_flag_is_found_by_the_long_stop(plant, history):
    h = history.history.copy()
    h["cip"] = 0.0
    processed = process(h, plant)
    ts = pd.DatetimeIndex(pd.to_datetime(h["timestamp"], utc=True))
    found = detect_cips(ts, processed, np.zeros(len(h), bool), off_minutes=360)
    assert len(found) == 1 and found[0]["detected_by"] == "plant_off"
    assert found[0]["start"] == history.cips[0]["start"]
    # a stop shorter than the threshold is not a CIP
    assert detect_cips(ts, processed, np.zeros(len(h), bool), off_minutes=400) == []


def test_windows_are_row_positions_tiling_the_usable_record(plant, history):
    """``plan_windows`` gives each window as row positions (not a mask over the whole record: a
    plant-year's masks were 1.9 GB): the usable rows after the initial window in [a, b) of each
    window's own span, disjoint, in time order; together every usable row outside the CIP and
    the initial window except those of windows skipped for too few samples. A record whose
    timestamps are not in order (replay sorts them first) gives the same windows by its masks."""
    from model.analysis.replay import plan_windows
    h = history.history
    processed = process(h, plant)
    ts = pd.DatetimeIndex(pd.to_datetime(h["timestamp"], utc=True))
    s = ReplaySettings.from_config(plant.extra)
    init = np.arange(120)
    plan, skipped, cips = plan_windows(ts, processed, h, init, s, [])
    usable = processed["usable"].to_numpy(dtype=bool)
    assert len(plan) >= 8 and plan[0][1] and len(cips) == 1
    seen = np.zeros(len(h), dtype=int)
    for pos, _ in plan:
        assert pos.dtype.kind == "i" and np.all(np.diff(pos) > 0) and len(pos) >= s.min_samples
        assert usable[pos].all() and (ts[pos] > ts[init[-1]]).all()
        assert (ts[pos[-1]] - ts[pos[0]]) <= pd.Timedelta(hours=s.window_hours * 1.5)
        seen[pos] += 1
    assert seen.max() == 1
    c = cips[0]
    inside_cip = (ts >= c["start"]) & (ts < c["end"])
    expected = usable & (ts > ts[init[-1]]) & ~inside_cip
    assert not skipped and np.array_equal(seen == 1, expected)
    # the new segment after the CIP starts a window
    after = [k for k, (pos, new) in enumerate(plan) if new]
    assert len(after) == 2 and ts[plan[after[1]][0][0]] >= c["end"]
    # two running rows out of time order: the same windows (by their rows' timestamps)
    i = int(plan[3][0][10])
    assert plan[3][0][11] == i + 1          # both usable, in one window: the segment is out of order
    order = np.arange(len(h))
    order[[i, i + 1]] = order[[i + 1, i]]
    plan2, _, _ = plan_windows(ts[order], processed.iloc[order].reset_index(drop=True),
                               h.iloc[order].reset_index(drop=True), init, s, [])
    assert [sorted(ts[order][p]) for p, _ in plan2] == [list(ts[p]) for p, _ in plan]


def test_replay_errors(plant, history):
    with pytest.raises(ReplayError, match="timestamp"):
        replay(history.history.drop(columns=["timestamp"]), plant)
    with pytest.raises(ReplayError, match="initial window has 0 usable samples"):
        replay(history.history, plant, initial_window=("2030-01-01", "2030-01-02"))
    with pytest.raises(ReplayError, match="window_hours"):
        ReplaySettings.from_config({}, window_hours=-1.0)


# ---- commands ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def csv_file(plant, tmp_path_factory):
    """A short export with a few broken rows: commissioning, then 4 h of fouled operation."""
    op = Operation(hours=6, commissioning_minutes=120, gap_after_commissioning_days=10)
    h = generate(plant, op, Truth(), Noise(), seed=8).history.astype(object)
    h.loc[7, "timestamp"] = "not a time"
    h.loc[200, "T_sink_in"] = "#VALUE!"
    h = pd.concat([h, h.iloc[[250]]], ignore_index=True)          # a repeated timestamp
    path = tmp_path_factory.mktemp("hist") / "history.csv"
    h.to_csv(path, index=False)
    return path


def test_replay_command_writes_tables(csv_file, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["replay", str(csv_file), "--out", str(out), "--no-optimize"]) == 0
    text = capsys.readouterr().out
    assert "bad timestamp: 1" in text and "duplicate timestamp: 1" in text and "T_sink_in: 1" in text
    assert "missing: T_sink_in: 1" in text                 # the unusable row, counted per reason
    w = pd.read_csv(out / "windows.csv")
    assert set(REQUIRED_WINDOW_COLUMNS) <= set(w.columns) and len(w) >= 1
    c = pd.read_csv(out / "cip.csv")
    assert list(c.columns) == list(CIP_COLUMNS) and len(c) == 0
    assert (out / "summary.txt").read_text().strip()
    assert json.loads((out / "initial_calibration.json").read_text())["kind"] == "initial"


def test_calibrate_and_optimize_commands(csv_file, tmp_path, capsys):
    state = tmp_path / "state"
    assert main(["calibrate", "initial", str(csv_file), "--state-dir", str(state)]) == 0
    out = capsys.readouterr().out
    assert "CF_eva" in out and "WARNING" in out and "clean pressure drop" in out
    assert (state / "initial_calibration.json").exists() and (state / "dp_clean.json").exists()
    win = "2024-03-11T04:30/2024-03-11T06:30"
    assert main(["calibrate", "fouling", str(csv_file), "--window", win, "--state-dir", str(state),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert 3e-3 < doc["params"]["R_th_f_K_per_kW"] < 6e-3 and 0.3 < doc["R_th_f_share"] < 0.8
    assert json.loads((state / "fouling_calibration.json").read_text())["params"] == doc["params"]
    assert main(["optimize", str(csv_file), "--window", win, "--state-dir", str(state)]) == 0
    assert "optimum p_m,sp" in capsys.readouterr().out
    # errors: exit code 2 and a message that says what is wrong
    assert main(["optimize", str(csv_file), "--window", "2024-03-11T04:30", "--state-dir", str(state)]) == 2
    assert "expected START/END" in capsys.readouterr().err
    assert main(["calibrate", "fouling", str(csv_file), "--window", "2031-01-01/2031-01-02",
                 "--state-dir", str(state)]) == 2
    assert "no rows between" in capsys.readouterr().err


def test_history_without_required_columns_names_them(csv_file, tmp_path, capsys):
    thin = tmp_path / "thin.csv"
    pd.read_csv(csv_file).drop(columns=["W_HS", "p_source_out"]).to_csv(thin, index=False)
    for argv in (["replay", str(thin), "--out", str(tmp_path / "o")],
                 ["calibrate", "initial", str(thin), "--state-dir", str(tmp_path / "s")]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.endswith(f"{thin}: missing column(s) p_source_out, W_HS "
                            "(canonical history columns, SPEC §4)"), err
    assert not (tmp_path / "o").exists() and not (tmp_path / "s").exists()   # nothing written


P_E_MODEL_TOL_BAR = 0.03   # bar: a window's mean adaptive-model p_e against the measured mean


def test_samples_carry_the_models_evaporating_pressure(result):
    """samples.csv has the fixed and adaptive models' p_e on the figure rows (the report's p_e
    panel): fouling lowers the evaporating pressure, so the adaptive (fouled) model's p_e lies below
    the clean model's wherever the window found fouling, and it follows the measured p_e."""
    s = result.samples
    w = result.windows.set_index("window_start")
    both = s.dropna(subset=["p_e_bar_fixed", "p_e_bar_adaptive"])
    assert len(both) >= 10 * (w["status"] == "ok").sum()
    R = w.loc[both["window_start"], "R_th_f_K_per_kW"].to_numpy(dtype=float)
    fouled = R > 0.5e-3                     # K/kW
    assert fouled.sum() > len(both) // 2
    fx, ad = both["p_e_bar_fixed"].to_numpy(), both["p_e_bar_adaptive"].to_numpy()
    assert (ad[fouled] < fx[fouled]).all()
    # the calibration fits p_e: per window the adaptive model's mean p_e meets the measured mean
    # (per sample the sensor noise remains), and it is closer to the measurement than the clean model
    meas = both["p_e_bar_measured"].to_numpy()
    bias = pd.Series(ad - meas).groupby(both["window_start"].to_numpy()).mean()
    assert bias.abs().max() < P_E_MODEL_TOL_BAR
    assert np.sqrt(np.mean((ad - meas) ** 2)) < np.sqrt(np.mean((fx - meas) ** 2))


def test_plant_year_bench_runs_and_adds_up(tmp_path):
    """``hp-edge bench --only plant_year`` on a short history: every window replayed, its CPU per
    window the total over the windows, the quarters' costs in the same range, the fleet task's
    cost the history's reading, the replay and the directory's writing, the arithmetic of the
    extrapolation as stated (from the task's cost)."""
    from edge.bench_fleet import bench_plant_year
    out = bench_plant_year(days=1.5, work_dir=tmp_path)
    assert out["windows"] >= 15 and out["windows_ok"] >= out["windows"] - 2
    assert out["cpu_s_per_window"] == pytest.approx(out["cpu_s"] / out["windows"])
    q = out["cpu_s_per_window_by_quarter"]
    assert 1 <= len(q) <= 4 and all(0 < x < 20 * out["cpu_s_per_window"] for x in q)
    assert out["read_history_cpu_s"] > 0 and out["write_dir_cpu_s"] > 0
    parts = out["read_history_cpu_s"] + out["cpu_s"] + out["write_dir_cpu_s"]
    assert out["task_cpu_s"] == pytest.approx(parts)
    assert out["task_cpu_s_per_window"] == pytest.approx(out["task_cpu_s"] / out["windows"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["histories"]     # the scratch directory gone
    year_s = 365 * out["windows_per_plant_day"] * out["task_cpu_s_per_window"]
    assert out["extrapolation"]["one_task_per_plant_min"] == pytest.approx(7 * year_s / 60)
    assert out["extrapolation"]["windows_spread_evenly_min"] == pytest.approx(100 * year_s / 16 / 60)
    assert out["pass"]["plant_years_100_on_16_workers"] is (7 * year_s / 60 <= 10.0)
    assert out["max_rss_mb"] > 50
    parts = out["parts"]                     # where it goes (edge.benchparts; tests/test_benchparts.py)
    assert parts["cpu_s"]["replay"] == out["cpu_s"]
    assert parts["calls"]["pass2_windows"] == out["windows"]
    assert parts["calls"]["pass3"] == parts["calls"]["pass2"] >= 1          # one of each per chunk
    assert 0 < parts["cpu_s"]["pass2_solver"] < parts["cpu_s"]["pass2"] < out["cpu_s"]


def test_a_replay_collects_garbage_less_often_and_restores_the_threshold():
    """``fewer_collections``: the collector's first threshold is GC_THRESHOLD0 inside (never lowered
    where the process set it higher) and the process's own thresholds after, also after an error."""
    import gc
    from model.analysis.replay import GC_THRESHOLD0, fewer_collections
    old = gc.get_threshold()
    try:
        gc.set_threshold(700, 11, 12)
        with fewer_collections():
            assert gc.get_threshold() == (GC_THRESHOLD0, 11, 12)
        assert gc.get_threshold() == (700, 11, 12)
        gc.set_threshold(50_000, 10, 10)
        with pytest.raises(ZeroDivisionError), fewer_collections():
            assert gc.get_threshold() == (50_000, 10, 10)
            1 / 0
        assert gc.get_threshold() == (50_000, 10, 10)
    finally:
        gc.set_threshold(*old)
