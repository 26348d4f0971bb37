"""The validation grid of issue #2, shared by `hp-edge bench` and the tests.

Grid: T_source,in 15-30 degC, T_source,out 3-8 K lower, T_sink,in 35-50 degC, V_source and V_sink
40-110 % of nominal, p_m,sp 8-22 bar(g), R_th,f 0-8e-3 K/kW (a full factorial of ``levels`` values
per axis). Every point either solves (within limits, or outside the LS speed range with its state
attached) or raises a typed ModelError with its reason; nothing returns None or NaN.
"""
from __future__ import annotations

import itertools
from collections import Counter

import numpy as np

from .cycle import InfeasibleOperation, ModelError, solve
from .fluid import get_fluid
from .params import CycleInputs, PlantParams
from .units import C_to_K, barg_to_Pa, m3h_to_m3s

V_SOURCE_NOM = 192.0   # m3/h, SPEC §2
V_SINK_NOM = 62.0      # m3/h


def grid(levels: int = 3):
    """Yield (CycleInputs, R_th_f [K/W]) over the full factorial grid."""
    amb = 1.01325
    ax = lambda lo, hi: np.linspace(lo, hi, levels)  # noqa: E731
    for T_in, drop, T_sink, fs, fk, psp, R in itertools.product(
            ax(15, 30), ax(3, 8), ax(35, 50), ax(0.4, 1.1), ax(0.4, 1.1), ax(8, 22), ax(0, 8e-3)):
        yield CycleInputs(C_to_K(T_in), C_to_K(T_in - drop), C_to_K(T_sink),
                          m3h_to_m3s(V_SOURCE_NOM * fs), m3h_to_m3s(V_SINK_NOM * fk),
                          barg_to_Pa(psp, amb)), R * 1e-3


def run_grid(params: PlantParams, levels: int = 3, check=None) -> dict:
    """Solve every grid point cold; ``check(result)`` is called on each solved state.

    Returns counts: solved within limits, solved but outside an operating limit (state attached),
    typed infeasible without a state, and convergence failures, with reasons.
    """
    fluid = get_fluid(params.fluid, params.backend)
    outcome: Counter = Counter()
    reasons: Counter = Counter()
    max_res = 0.0
    total = 0
    for inp, R in grid(levels):
        total += 1
        p = params.replace(R_th_f=R)
        try:
            res = solve(inp, p, fluid=fluid)
            outcome["ok"] += 1
        except InfeasibleOperation as exc:
            res = exc.result
            outcome["solved_flagged" if res is not None else "infeasible"] += 1
            reasons[exc.reason] += 1
        except ModelError as exc:
            res = None
            outcome["failed"] += 1
            reasons[exc.reason] += 1
        if res is not None:
            max_res = max(max_res, abs(res.energy_residual))
            if check is not None:
                check(inp, p, res)
    return {"points": total, "ok": outcome["ok"], "solved_flagged": outcome["solved_flagged"],
            "infeasible_typed": outcome["infeasible"], "convergence_failures": outcome["failed"],
            "reasons": dict(reasons), "max_energy_residual": max_res}
