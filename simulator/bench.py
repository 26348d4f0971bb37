"""Simulator benchmarks for ``hp-edge bench`` (targets of issue #3):
plant step <= 5 ms; >= 500 register-read requests/s on loopback while the plant steps at 60x;
30 days exported in <= 2 min. Also the truth evaluator (simulator/truth.py; goal ~0.2 s per 2-h
window) and where each compressor family puts the optimum against plant.yaml's curves (the table
of config/simulator.yaml). Returns plain numbers; the caller prints JSON.
"""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pandas as pd

TARGETS = {"plant_step_ms": 5.0, "reads_per_s": 500.0, "export_30d_s": 120.0}
FAMILIES = ("ratio_only", "speed_peak", "low_peak")


def bench_plant_step(plant_hours: float = 12.0, warm_days: float = 3.0) -> dict:
    """Wall time per plant tick (5 plant seconds; a model solve every 12th tick, the hidden-truth
    record every 12th and a COP-optimum scan every 720th included), on a plant warmed up for
    warm_days so that fouling puts the LS compressor at its speed limit part of the time."""
    from .plant import Plant
    plant = Plant()
    plant.advance_to(plant.t + warm_days * 86400.0)
    plant.drain_truth()
    n = int(plant_hours * 3600.0 / plant.dt)
    times = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        plant.tick()
        times[i] = time.perf_counter() - t0
    plant.drain_truth()
    solve_ticks = times[np.arange(1, n + 1) % plant._solve_every == 0]
    return {"plant_step_ms": float(times.mean() * 1e3),
            "plant_step_p99_ms": float(np.percentile(times, 99) * 1e3),
            "plant_step_with_solve_ms": float(np.median(solve_ticks) * 1e3),
            "plant_step_max_ms": float(times.max() * 1e3),
            "plant_ticks": n}


async def _reads(speed: float, seconds: float, clients: int) -> dict:
    from pymodbus.client import AsyncModbusTcpClient

    from .server import PlantSimulator
    sim = PlantSimulator(port=0, speed=speed)
    await sim.start()
    counts = [0] * clients
    errors = [0] * clients
    try:
        await sim.wait_ticks(1)
        t_plant0 = sim.plant_time

        async def worker(i: int, deadline: float) -> None:
            c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)
            await c.connect()
            try:
                while time.perf_counter() < deadline:
                    r = await c.read_input_registers(0, count=32, device_id=sim.cfg.device_id)
                    if r.isError():
                        errors[i] += 1
                    counts[i] += 1
            finally:
                c.close()

        t0 = time.perf_counter()
        await asyncio.gather(*(worker(i, t0 + seconds) for i in range(clients)))
        el = time.perf_counter() - t0
        plant_rate = (sim.plant_time - t_plant0) / el
    finally:
        await sim.stop()
    return {"reads_per_s": sum(counts) / el, "read_errors": sum(errors), "read_clients": clients,
            "plant_speed_achieved": plant_rate}


def bench_reads(speed: float = 60.0, seconds: float = 3.0, clients: int = 1) -> dict:
    """Register-read requests per second (32 input registers each) from `clients` pymodbus clients
    on loopback while the plant steps at `speed` x wall time."""
    return asyncio.run(_reads(speed, seconds, clients))


def bench_export(days: float = 30.0) -> dict:
    from .export import export_history
    res = export_history(days)
    return {"export_days": days, "export_s": res.seconds,
            "export_30d_s": res.seconds * 30.0 / days, "export_rows": res.rows}


def bench_truth(days: float = 1.0, window_min: int = 120, R_start_K_per_kW: float = 4.0e-3) -> dict:
    """Truth evaluator on each family: a day's export starting fouled (the LS reaches its speed
    limit in the warm hours), 2-h windows of 24 minutes: seconds per window optimum, and how well
    re-solving a window at its own set point reproduces the plant's truth COP."""
    from .config import load_simulator_config
    from .export import export_history
    from .truth import TruthModel
    base = load_simulator_config()
    times, repro, evals = [], [], []
    for fam in FAMILIES:
        cfg = base.with_compressor_family(fam).with_sections(
            fouling={"R_th_f_initial_K_per_kW": R_start_K_per_kW})
        truth = export_history(days, cfg=cfg, with_truth=True).truth
        tm = TruthModel(cfg)
        for a in range(0, len(truth) - window_min + 1, window_min):
            win = truth.iloc[a:a + window_min]
            w = tm.window(win)
            run = win[(win["running"] == 1) & (win["cip"] == 0)]
            idx = np.unique(np.linspace(0, len(run) - 1, min(24, len(run))).round().astype(int))
            sub = run.iloc[idx]
            repro.append(abs(w.cop_actual()[0] / (sub["Q_sink_kW"].sum() / sub["W_electric_kW"].sum()) - 1))
            t0 = time.perf_counter()
            opt = w.optimum()
            times.append(time.perf_counter() - t0)
            evals.append(opt["evaluations"])
    t = np.array(times)
    return {"truth_window_optimum_s_median": float(np.median(t)),
            "truth_window_optimum_s_max": float(t.max()),
            "truth_window_evaluations_median": float(np.median(evals)),
            "truth_windows": len(t), "truth_repro_cop_rel_err_max": float(max(repro))}


def family_optima(R_fouled_K_per_kW: float = 5.5e-3) -> dict:
    """Where each family puts the optimum p_m,sp at SPEC §2's nominal point (clean, fouled), against
    plant.yaml's curves on the same plant: the TruthModel optimum of the "nominal" family (same
    controllers), and model.optimize with plant.yaml's curves and the plant's true heat exchangers
    and fouling, fed the T_source_out the plant showed at 16 and at 10 bar(g) (what hp-edge would
    measure). For each: the true COP there and the regret of following it."""
    from model.optimize import optimize_setpoint

    from .config import load_simulator_config
    from .truth import TruthModel, condition_row
    base = load_simulator_config()
    nominal = TruthModel(base.with_compressor_family("nominal"))
    out: dict = {}
    for fam in ("perturbed",) + FAMILIES:
        tm = TruthModel(base.with_compressor_family(fam))
        for label, R in (("clean", 0.0), ("fouled", R_fouled_K_per_kW)):
            row = condition_row(R_th_f_K_per_kW=R)
            w = tm.window([row])
            opt = w.optimum()
            rec = {"R_th_f_K_per_kW": R, "p_m_sp_opt_barg": opt["p_m_sp_opt_barg"],
                   "opt_hs_saturated": opt["hs_saturated"], "COP_opt": opt["COP_opt"]}
            for sp in (10.0, 16.0):
                rec[f"COP_at_{sp:g}"] = w.cop_at(sp)[0]
            d = nominal.window([row]).optimum()["p_m_sp_opt_barg"]
            rec["default_curves_opt_barg"] = d
            rec["default_curves_regret_pct"] = 100 * (1 - w.cop_at(d)[0] / opt["COP_opt"])
            par0 = nominal.params_at(192.0, 62.0, R, 1.0)
            for sp in (16.0, 10.0):
                pt = w.point_at(sp)
                T_out = float(pt.T_source_out_C[0])     # floats when the LS is at 1800 rpm
                df = pd.DataFrame([{"T_source_in": row["T_source_in_C"], "T_source_out": T_out,
                                    "T_sink_in": row["T_sink_in_C"], "V_source": row["V_source_m3h"],
                                    "V_sink": row["V_sink_m3h"], "p_m_sp": sp}])
                m = optimize_setpoint(df, par0)
                rec[f"model_optimize_at_{sp:g}_barg"] = m.p_m_sp_opt_barg
                rec[f"model_optimize_at_{sp:g}_regret_pct"] = 100 * (1 - w.cop_at(m.p_m_sp_opt_barg)[0]
                                                                      / opt["COP_opt"])
                rec[f"T_source_out_at_{sp:g}_C"] = T_out
                rec[f"ls_limit_at_{sp:g}"] = pt.ls_limit[0]
            out[f"{fam}_{label}"] = rec
    return out


def bench_simulator(export_days: float = 30.0, read_seconds: float = 3.0) -> dict:
    """All simulator figures in one dict (keys: plant_step_ms, reads_per_s, export_30d_s, ...),
    with the issue's targets and whether each is met."""
    out: dict = {}
    out.update(bench_plant_step())
    out.update(bench_reads(seconds=read_seconds))
    out.update(bench_export(export_days))
    out.update(bench_truth())
    out["family_optima"] = family_optima()
    out["targets"] = TARGETS
    out["targets_met"] = {
        "plant_step_ms": out["plant_step_ms"] <= TARGETS["plant_step_ms"],
        "reads_per_s": out["reads_per_s"] >= TARGETS["reads_per_s"],
        "export_30d_s": out["export_30d_s"] <= TARGETS["export_30d_s"],
    }
    return out


if __name__ == "__main__":   # python -m simulator.bench
    import json
    print(json.dumps(bench_simulator(), indent=2))
