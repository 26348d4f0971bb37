"""Benchmark of the set-point advice by regret against the simulator's truth (issue #8 targets).

For each compressor family of the simulator whose curves differ in *shape* from plant.yaml's
(``ratio_only``, ``speed_peak``, ``low_peak``): a history with its hidden truth is exported (starting
at commissioning with a clean evaporator, fouling as configured, CIPs, and a set-point schedule that
spends days at 16 and at 10 bar(g)); it is replayed causally with plant.yaml (so the learned curves
start from plant.yaml's, the wrong ones); and every window's advice is judged on the simulated plant
itself (``simulator.truth.TruthModel``): the true period COP at the recommended set point against the
true optimum COP of that window (regret), against the window's actual set point (what following
the advice gains or loses), the predicted against the true COP and heat-output changes.

Targets (issue #8): over the windows where the advice is confident, mean regret <= 0.2 % and max
<= 0.6 % of the true optimum COP, captured share of the available gain >= 85 %, correlation of
predicted and true dCOP >= 0.8; confident advice in >= 70 % of the windows; over all windows,
following the advice loses more than 0.1 % COP in <= 5 %; predicted heat-output change within 0.5
points of the truth; median change of the recommendation between consecutive windows <= 0.3 bar;
R_th,f within +-0.2e-3 K/kW.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pandas as pd

FAMILIES = ("ratio_only", "speed_peak", "low_peak")
# plant days from the start: the PLC's set point (bar(g)); 21 days: 16, a few days at 10 and at 13
SCHEDULE = ((0.0, 16.0), (3.0, 10.0), (6.0, 13.0), (9.0, 16.0))
DAYS = 21.0
TARGETS = {"mean_regret_pct": 0.2, "max_regret_pct": 0.6, "captured_share_min": 0.85,
           "dcop_correlation_min": 0.8, "confident_share_min": 0.70, "loss_share_max": 0.05,
           "loss_threshold_pct": 0.1, "dQ_abs_error_pct": 0.5, "median_step_bar": 0.3,
           "R_th_f_abs_error_K_per_kW": 0.2e-3}


def history(family: str, days: float = DAYS, schedule=SCHEDULE, seed: int | None = None):
    """(history, truth, simulator config) of a simulated plant with the given compressor family."""
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    cfg = load_simulator_config().with_compressor_family(family)
    # commissioning with a clean evaporator (as `hp-edge simulate --export` does by default)
    cfg = replace(cfg, control=replace(cfg.control, p_m_sp_schedule=tuple(tuple(x) for x in schedule),
                                       p_m_sp_bar_g=schedule[0][1]),
                  fouling=replace(cfg.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0))
    if seed is not None:
        cfg = cfg.replace(seed=seed)
    res = export_history(days, cfg=cfg, with_truth=True)
    return res.history, res.truth, cfg


def judge(windows: pd.DataFrame, truth: pd.DataFrame, cfg, max_rows: int = 24) -> pd.DataFrame:
    """Per window with advice: the truth at the recommendation, at the actual set point, and the
    true optimum (columns true_*), and the regret."""
    from simulator.truth import TruthModel
    tm = TruthModel(cfg)
    ts = pd.to_datetime(truth["timestamp"], utc=True)
    rows = []
    for _, w in windows.iterrows():
        if not (w["status"] == "ok" and bool(w["optimization_ok"])):
            continue
        a, b = pd.Timestamp(w["window_start"]), pd.Timestamp(w["window_end"])
        sel = truth[((ts >= a) & (ts <= b)).to_numpy()]
        try:
            tw = tm.window(sel, max_rows=max_rows)
            opt = tw.optimum()
            cop_rec, q_rec, _ = tw.cop_at(float(w["p_m_sp_opt_barg"]))
            cop_act, q_act, _ = tw.cop_actual()
        except (ValueError, ArithmeticError) as exc:
            rows.append({"window_start": w["window_start"], "error": str(exc)})
            continue
        R_true = float(sel.loc[sel["running"] == 1, "R_th_f_K_per_kW"].mean()) \
            if "R_th_f_K_per_kW" in sel else math.nan
        rows.append({
            "window_start": w["window_start"], "confident": bool(w["advice_confident"]),
            "p_m_sp_actual_barg": float(w["p_m_sp_actual_barg"]), "p_m_sp_rec_barg": float(w["p_m_sp_opt_barg"]),
            "p_m_sp_model_opt_barg": float(w["p_m_sp_model_opt_barg"]),
            "true_opt_barg": opt["p_m_sp_opt_barg"], "true_COP_opt": opt["COP_opt"],
            "true_COP_rec": cop_rec, "true_COP_actual": cop_act,
            "regret_pct": 100.0 * (1.0 - cop_rec / opt["COP_opt"]),
            "true_dCOP_pct": 100.0 * (cop_rec / cop_act - 1.0),
            "pred_dCOP_pct": float(w["dCOP_opt_pct"]), "pred_dCOP_sd_pct": float(w["dCOP_opt_sd_pct"]),
            "true_dQ_pct": 100.0 * (q_rec / q_act - 1.0), "pred_dQ_pct": float(w["dQ_sink_opt_pct"]),
            "available_pct": 100.0 * (opt["COP_opt"] / cop_act - 1.0),
            "R_th_f_error_K_per_kW": float(w["R_th_f_K_per_kW"]) - R_true
            if math.isfinite(R_true) else math.nan,
        })
    return pd.DataFrame(rows)


def metrics(j: pd.DataFrame, windows: pd.DataFrame) -> dict:
    """The issue's figures from a judged table."""
    j = j[j.get("error", pd.Series(index=j.index, dtype=object)).isna()] if "error" in j else j
    conf = j[j["confident"]]
    n_all = len(windows[windows["status"] == "ok"])
    gain_av = (conf["true_COP_opt"] - conf["true_COP_actual"]).sum()
    gain = (conf["true_COP_rec"] - conf["true_COP_actual"]).sum()
    corr = (float(np.corrcoef(conf["pred_dCOP_pct"], conf["true_dCOP_pct"])[0, 1])
            if len(conf) >= 3 and conf["pred_dCOP_pct"].std() > 0 and conf["true_dCOP_pct"].std() > 0
            else math.nan)
    rec = windows.loc[windows["status"] == "ok", "p_m_sp_opt_barg"].dropna().to_numpy(dtype=float)
    steps = np.abs(np.diff(rec))
    return {
        "windows": int(n_all), "judged": int(len(j)), "confident": int(len(conf)),
        "confident_share": round(len(conf) / len(j), 4) if len(j) else math.nan,
        "mean_regret_confident_pct": round(float(conf["regret_pct"].mean()), 4) if len(conf) else math.nan,
        "max_regret_confident_pct": round(float(conf["regret_pct"].max()), 4) if len(conf) else math.nan,
        "mean_regret_all_pct": round(float(j["regret_pct"].mean()), 4),
        "mean_regret_actual_pct": round(float((100 * (1 - j["true_COP_actual"] / j["true_COP_opt"])).mean()), 4),
        "captured_share": round(float(gain / gain_av), 4) if gain_av > 0 else math.nan,
        "dcop_correlation": round(corr, 4) if math.isfinite(corr) else math.nan,
        "loss_share_all": round(float((j["true_dCOP_pct"] < -TARGETS["loss_threshold_pct"]).mean()), 4),
        "dQ_abs_error_pct_mean": round(float((conf["pred_dQ_pct"] - conf["true_dQ_pct"]).abs().mean()), 4)
        if len(conf) else math.nan,
        "dQ_abs_error_pct_max": round(float((conf["pred_dQ_pct"] - conf["true_dQ_pct"]).abs().max()), 4)
        if len(conf) else math.nan,
        "median_step_bar": round(float(np.median(steps)), 4) if len(steps) else math.nan,
        "R_th_f_abs_error_max_K_per_kW": float(j["R_th_f_error_K_per_kW"].abs().max()),
        "rec_minus_true_opt_bar_mean": round(float((conf["p_m_sp_rec_barg"] - conf["true_opt_barg"]).mean()), 3)
        if len(conf) else math.nan,
    }


def run_family(family: str, days: float = DAYS, schedule=SCHEDULE, params=None, progress=None) -> dict:
    from edge.plantfile import load_plant
    from model.analysis.replay import replay
    params = params or load_plant()
    t0 = time.perf_counter()
    hist, truth, cfg = history(family, days, schedule)
    t1 = time.perf_counter()
    res = replay(hist, params, progress=progress)
    t2 = time.perf_counter()
    j = judge(res.windows, truth, cfg)
    t3 = time.perf_counter()
    m = metrics(j, res.windows)
    m.update({"family": family, "days": days, "seconds_export": round(t1 - t0, 1),
              "seconds_replay": round(t2 - t1, 1), "seconds_judge": round(t3 - t2, 1)})
    return {"metrics": m, "judged": j, "windows": res.windows, "history": hist}


def bench_advice(families=FAMILIES, days: float = DAYS) -> dict:
    """``hp-edge bench --only advice``: every family's figures and the targets."""
    out = {"targets": TARGETS, "schedule_days_barg": [list(x) for x in SCHEDULE], "families": {}}
    for f in families:
        out["families"][f] = run_family(f, days)["metrics"]
    ms = list(out["families"].values())
    out["worst"] = {
        "mean_regret_confident_pct": max(m["mean_regret_confident_pct"] for m in ms),
        "max_regret_confident_pct": max(m["max_regret_confident_pct"] for m in ms),
        "captured_share": min(m["captured_share"] for m in ms),
        "dcop_correlation": min(m["dcop_correlation"] for m in ms),
        "confident_share": min(m["confident_share"] for m in ms),
        "loss_share_all": max(m["loss_share_all"] for m in ms),
        "dQ_abs_error_pct_max": max(m["dQ_abs_error_pct_max"] for m in ms),
        "median_step_bar": max(m["median_step_bar"] for m in ms),
        "R_th_f_abs_error_max_K_per_kW": max(m["R_th_f_abs_error_max_K_per_kW"] for m in ms),
    }
    return out
