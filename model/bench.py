"""Model benchmark (issue #2 targets), called by `hp-edge bench`.

A 60-point simulated hour of slowly varying one-minute inputs around the nominal point is solved
warm (each point from the previous one) and cold (no guess, property caches cleared); the median
time per point is reported, plus seconds per simulated hour, the largest energy-balance residual,
the tabular backend's speed and deviation from HEOS, and the validation grid's outcome.
"""
from __future__ import annotations

import math
import time

import numpy as np

from .cycle import solve
from .fluid import get_fluid
from .params import CycleInputs, PlantParams
from .units import C_to_K, barg_to_Pa, m3h_to_m3s
from .validation import run_grid

COMPARED = ("p_e", "p_m", "p_c", "N_LS", "N_HS", "Q_sink", "W_LS", "W_HS", "COP", "T_sink_out")


def hour_inputs(n: int = 60) -> list[CycleInputs]:
    """One hour of slowly varying one-minute inputs around the nominal point (SPEC §2)."""
    out = []
    for k in range(n):
        out.append(CycleInputs(
            T_source_in=C_to_K(25.0 + 0.5 * math.sin(k / 20.0)),
            T_source_out=C_to_K(18.0 + 0.1 * math.sin(k / 30.0)),
            T_sink_in=C_to_K(40.0 + 0.3 * math.sin(k / 15.0)),
            V_source=m3h_to_m3s(192.0 * (1 + 0.01 * math.sin(k / 7.0))),
            V_sink=m3h_to_m3s(62.0 * (1 + 0.02 * math.cos(k / 9.0))),
            p_m_sp=barg_to_Pa(16.0)))
    return out


def _time_hour(params: PlantParams, inputs, repeats: int = 5):
    fluid = get_fluid(params.fluid, params.backend)
    solve(inputs[0], params, fluid=fluid)          # load the fluid / tables once
    warm_all, results = [], []
    for _ in range(repeats):
        g, times, res = None, [], []
        for inp in inputs:
            t = time.perf_counter()
            g = solve(inp, params, guess=g, fluid=fluid)
            times.append(time.perf_counter() - t)
            res.append(g)
        warm_all.append(times)
        results = res
    cold = []
    for inp in inputs:
        fluid._sat_cache.clear()
        t = time.perf_counter()
        solve(inp, params, fluid=fluid)
        cold.append(time.perf_counter() - t)
    warm = np.median(np.array(warm_all), axis=0)
    return warm, np.array(cold), results


def bench_model(params: PlantParams, grid_levels: int = 3) -> dict:
    inputs = hour_inputs()
    heos = params.replace(backend="HEOS")
    warm, cold, res_heos = _time_hour(heos, inputs)
    out = {
        "backend": "HEOS",
        "points": len(inputs),
        "warm_ms_median": round(float(np.median(warm)) * 1e3, 4),
        "cold_ms_median": round(float(np.median(cold)) * 1e3, 4),
        "s_per_simulated_hour": round(float(np.sum(warm)), 5),
        "speedup_vs_published_113s": round(113.0 / float(np.sum(warm))),
        "max_energy_residual_hour": float(max(abs(r.energy_residual) for r in res_heos)),
        "targets": {"warm_ms": 1.0, "cold_ms": 6.0, "s_per_hour": 0.1},
    }
    tab = params.replace(backend="BICUBIC&HEOS")
    warm_t, _, res_tab = _time_hour(tab, inputs)
    dev = max(abs(getattr(a, k) - getattr(b, k)) / abs(getattr(a, k))
              for a, b in zip(res_heos, res_tab) for k in COMPARED)
    out["tabular"] = {"backend": "BICUBIC&HEOS",
                      "warm_ms_median": round(float(np.median(warm_t)) * 1e3, 4),
                      "max_rel_deviation_vs_HEOS": float(dev),
                      "compared_outputs": list(COMPARED),
                      "targets": {"warm_ms": 0.3, "max_rel_deviation": 1e-5}}
    t = time.perf_counter()
    grid = run_grid(heos, levels=grid_levels)
    grid["seconds"] = round(time.perf_counter() - t, 2)
    grid["levels_per_axis"] = grid_levels
    grid["definite_share"] = round(1 - grid["convergence_failures"] / grid["points"], 5)
    out["validation_grid"] = grid
    out["max_energy_residual"] = max(out["max_energy_residual_hour"], grid["max_energy_residual"])
    return out
