"""What the plant's sensors read from a solved state, and the plant's LS capacity controller.

One home for both, used by the simulated plant (simulator/plant.py), the synthetic histories
(simulator/synthetic.py) and the truth evaluator (simulator/truth.py).

Sensor mapping (SPEC §4 canonical names, engineering units):
  T_e = saturation temperature at p_e; T_suc_LS = T_e + superheat at p_e ('LS_suc');
  T_dis_LS = 'LS_dis'; T_suc_HS = saturated vapour at p_m ('HS_suc'); T_dis_HS = 'HS_dis';
  T_c = the "condenser outlet" sensor, which plants place in one of two spots of the shell that
    holds condenser, receiver and subcooler: ``condenser_outlet`` reads the saturated condensate
    at p_c ('con_out', the SC inlet), ``subcooler_outlet`` the subcooled liquid ('SC_out');
  p_suc_LS = p_e, p_dis_LS = p_suc_HS = p_m, p_dis_HS = p_c (gauge, with the ambient pressure);
  W_LS / W_HS = shaft power / motor efficiency [kW]; N_LS / N_HS [rpm];
  p_source_in - p_source_out = dp_source (one of the two given, the other follows).

LS controller (SPEC §2): the LS speed holds T_source,out at its set point. When the LS would need
more than its maximum speed, it runs there and T_source,out floats above the set point; when it
would need less than its minimum speed (or the duty is below the HS turndown), it runs at its
minimum and T_source,out floats below. The floating T_source,out is found by a secant iteration
on N_LS - bound, with a bracketed (brentq) fallback.
"""
from __future__ import annotations

import math

from scipy.optimize import brentq

from model.cycle import ConvergenceError, CycleResult, InfeasibleOperation, solve
from model.fluid import get_fluid
from model.params import CycleInputs, PlantParams
from model.units import BAR, T0

T_C_STATE = {"condenser_outlet": "con_out", "subcooler_outlet": "SC_out"}
N_TOL = 0.3          # rpm: LS speed at its bound, T_source_out floating


def sensor_values(r: CycleResult, *, T_source_in_C: float, T_sink_in_C: float, V_source_m3h: float,
                  V_sink_m3h: float, T_source_out_C: float, ambient_bar: float,
                  p_source_in_bar_g: float | None = None, p_source_out_bar_g: float | None = None,
                  T_c_location: str = "condenser_outlet",
                  motor_efficiency: float = 1.0) -> dict[str, float]:
    """Every plant sensor [degC, bar(g), m3/h, kW, rpm] from the solved state ``r`` (module doc).

    Exactly one of p_source_in_bar_g / p_source_out_bar_g is given; the other is derived from
    the source pressure drop of the solved state.
    """
    if (p_source_in_bar_g is None) == (p_source_out_bar_g is None):
        raise ValueError("give exactly one of p_source_in_bar_g, p_source_out_bar_g")
    try:
        tc_state = T_C_STATE[T_c_location]
    except KeyError:
        raise ValueError(f"T_c location must be one of {', '.join(T_C_STATE)}, got {T_c_location!r}") from None
    st = r.states
    dp = r.dp_source / BAR
    if p_source_in_bar_g is None:
        p_source_in_bar_g = p_source_out_bar_g + dp
    else:
        p_source_out_bar_g = p_source_in_bar_g - dp

    def g(p: float) -> float:      # absolute Pa -> bar(g)
        return p / BAR - ambient_bar
    return {
        "T_sink_in": T_sink_in_C, "T_sink_out": r.T_sink_out - T0,
        "T_source_in": T_source_in_C, "T_source_out": T_source_out_C,
        "V_sink": V_sink_m3h, "V_source": V_source_m3h,
        "p_source_in": p_source_in_bar_g, "p_source_out": p_source_out_bar_g,
        "T_suc_LS": st["LS_suc"].T - T0, "T_dis_LS": st["LS_dis"].T - T0,
        "T_suc_HS": st["HS_suc"].T - T0, "T_dis_HS": st["HS_dis"].T - T0,
        "T_c": st[tc_state].T - T0, "T_e": r.T_e - T0,
        "p_suc_LS": g(r.p_e), "p_dis_LS": g(r.p_m), "p_suc_HS": g(r.p_m), "p_dis_HS": g(r.p_c),
        "W_LS": r.W_LS / 1e3 / motor_efficiency, "W_HS": r.W_HS / 1e3 / motor_efficiency,
        "N_LS": r.N_LS, "N_HS": r.N_HS,
    }


def p_e_estimate(inp: CycleInputs, params: PlantParams) -> float:
    """Evaporating pressure [Pa] of the closed-form flooded evaporator (model.cycle.evaporator)."""
    C = params.cp_w * params.rho_w * inp.V_source
    e = math.exp(params.UA_eva / C)
    T_e = (inp.T_source_out * e - inp.T_source_in) / (e - 1.0)
    return get_fluid(params.fluid, params.backend).sat_T(T_e).p


class LSController:
    """The plant's controllers around ``model.cycle.solve`` (module doc).

    ``T_out_float`` remembers the last floating T_source,out [K] as the next search's start; the
    caller resets it (None) when the LS is back within its range. One instance per sequence of
    nearby points (the plant, one row of a truth window).
    """

    def __init__(self) -> None:
        self.T_out_float: float | None = None

    def solve(self, inp: CycleInputs, params: PlantParams, guess=None):
        """Solve with the LS controller: T_source,out at its set point, or floating at a speed
        bound. Returns (result, T_source_out [K], ls_limit "" | "max" | "min"). Raises
        ModelError when unsolvable.

        LS above 1800 rpm -> T_source,out rises until N_LS = 1800 ("max"). LS below 700 rpm, or a
        duty below the HS turndown (HS at 700 rpm moving more than the LS delivers) -> T_source,out
        falls until the plant can run at its minimum ("min").
        """
        # a set point at or below p_e: the HS runs flat out and p_m floats, as for any low set point
        p_floor = p_e_estimate(inp, params) * 1.05
        if inp.p_m_sp < p_floor:
            inp = inp.replace(p_m_sp=p_floor)
        first = None
        try:
            return solve(inp, params, guess=guess), inp.T_source_out, ""
        except InfeasibleOperation as exc:
            if exc.reason == "negative_pinch" and exc.result is not None:
                return exc.result, inp.T_source_out, ""
            if exc.reason not in ("ls_speed_high", "ls_speed_low", "hs_speed_low"):
                raise
            if exc.reason != "hs_speed_low" and exc.result is None:
                raise
            limit = "max" if exc.reason == "ls_speed_high" else "min"
            first = exc.result
        comp = params.comp_LS
        N_bound = comp.N_max if limit == "max" else comp.N_min
        state = {"guess": first, "res": None}

        def f(T_out: float) -> float:
            """N_LS - bound; for "min" a duty below the HS turndown counts as too little duty."""
            try:
                r = solve(inp.replace(T_source_out=T_out), params, guess=state["guess"])
            except InfeasibleOperation as e:
                if e.result is None:
                    if limit == "min" and e.reason == "hs_speed_low":
                        state["res"] = None
                        return -1.0
                    raise
                r = e.result
            state["guess"] = state["res"] = r
            return r.N_LS - N_bound

        T_sp, T_in = inp.T_source_out, inp.T_source_in
        edge = T_in - 0.5 if limit == "max" else max(T_sp - 8.0, 275.15)
        if limit == "max":
            clip = lambda x: min(max(x, T_sp), edge)     # noqa: E731
        else:
            clip = lambda x: min(max(x, edge), T_sp)     # noqa: E731
        # the LS speed is roughly proportional to the duty (T_in - T_out): start from that estimate
        # (or the last floating value) and iterate secant steps; fall back to a bracketed search
        prev = self.T_out_float
        x1 = T_in - (T_in - T_sp) * N_bound / first.N_LS if first is not None else T_sp - 0.5
        if prev is not None and (prev - T_sp) * (x1 - T_sp) > 0:
            x1 = prev
        x0, f0 = T_sp, (first.N_LS - N_bound) if first is not None else -1.0
        x1 = clip(x1)
        f1 = f(x1)
        seen = [(x0, f0), (x1, f1)]
        secant = first is not None and state["res"] is not None
        for _ in range(8):
            if not secant or abs(f1) < N_TOL or f1 == f0:
                break
            x0, f0, x1 = x1, f1, clip(x1 - f1 * (x1 - x0) / (f1 - f0))
            f1 = f(x1)
            seen.append((x1, f1))
            secant = state["res"] is not None
        if not (secant and abs(f1) < N_TOL):
            # bracket from the points seen (widen to the edge if needed), then bisect (brentq)
            pos = [p for p in seen if p[1] > 0]
            neg = [p for p in seen if p[1] <= 0]
            if (limit == "max" and not neg) or (limit == "min" and not pos):
                fe = f(edge)
                if (fe > 0) == (limit == "max"):
                    raise ConvergenceError(f"LS speed bound {N_bound:.0f} rpm not reached with "
                                           f"T_source_out at {edge - T0:.2f} degC", reason="ls_bound_search")
                (neg if fe <= 0 else pos).append((edge, fe))
            a = min(pos, key=lambda p: abs(p[1]))[0]
            b = min(neg, key=lambda p: abs(p[1]))[0]
            x1 = brentq(f, min(a, b), max(a, b), xtol=1e-3, maxiter=60)
            if f(x1) < 0 and limit == "min":     # land on the runnable side of the HS turndown
                x1 = clip(x1 - 1e-3)
                f(x1)
        r = state["res"]
        if r is None or not (comp.N_min - 1.0 <= r.N_LS <= comp.N_max + 1.0):
            raise ConvergenceError(f"LS speed bound search failed at T_source_out {x1 - T0:.3f} degC",
                                   reason="ls_bound_search")
        self.T_out_float = x1
        return r, x1, limit
