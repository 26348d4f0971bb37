"""The two-stage ammonia heat pump as a quasi-steady-state flowsheet (SPEC §3).

Given T_source,out as an input, the evaporator side is explicit (closed-form T_e). What remains is
small: the condensing temperature T_c (the condenser zone's UA must carry its duty) and, when the HS
compressor sits at a speed bound, the intermediate saturation temperature T_m. The HS-speed limit is
a branch choice, not a kink inside one Newton iteration:

- branch ``"sp"``:     N_HS free, p_m = p_m,sp          -> 1 unknown  (T_c)
- branch ``"hs_max"``: N_HS = N_max, p_m floats above   -> 2 unknowns (T_m outer, T_c inner)
- branch ``"hs_min"``: N_HS = N_min, p_m floats below   -> 2 unknowns

Each residual evaluation is explicit apart from tiny scalar loops (compressor speed from flow, the
HS mass flow through the intercooler balance), so the secant iterations converge in 2-4 steps when
warm-started from the previous point. Failures always raise a ``ModelError`` subclass, never None/NaN.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .components import counterflow_eps, evaporator_T_e, subcooler
from .fluid import Fluid, PropertyError, SatState, get_fluid
from .params import CycleInputs, PlantParams
from .units import BAR, K_to_C, Pa_to_barg

ENERGY_TOL = 1e-10        # condenser-zone residual, relative to Q_source
SPEED_TOL = 1e-9          # HS speed-bound residual, relative to nominal speed
MAX_ITER = 40
SC_TOL = 1e-10            # SC liquid secant heat capacity vs the EOS, relative
BOUND_NEWTON_ITER = 12    # joint (T_m, T_c) Newton at an HS speed bound: iterations before fallback
BOUND_NEWTON_STEP = 5.0   # K, largest step of either temperature


class ModelError(Exception):
    """Base of every model failure; ``reason`` is a short machine-readable code."""

    def __init__(self, message: str, reason: str = "error", result: "CycleResult | None" = None):
        super().__init__(message)
        self.reason = reason
        self.result = result


class ConvergenceError(ModelError):
    """The solver did not find a solution (no root bracketed, iteration limit, property failure)."""


class InfeasibleOperation(ModelError):
    """The point was solved but violates an operating limit (e.g. LS speed outside 700-1800 rpm).

    ``result`` carries the complete solved state, so batch callers can still use it.
    """


@dataclass(frozen=True)
class State:
    T: float    # [K]
    p: float    # [Pa]
    h: float    # [J/kg]


@dataclass
class CycleResult:
    """A solved operating point. SI units: Pa (absolute), K, W, kg/s, J/kg."""
    branch: str
    p_e: float
    p_m: float
    p_c: float
    T_e: float
    T_m: float
    T_c: float
    N_LS: float
    N_HS: float
    eta_is_LS: float
    eta_is_HS: float
    eta_vol_LS: float
    eta_vol_HS: float
    m_LS: float
    m_HS: float
    Q_source: float
    Q_sink: float
    Q_DSH: float
    Q_con: float
    Q_SC: float
    W_LS: float             # electric power: shaft power m*(h_dis - h_suc) times the drive factor
    W_HS: float
    T_sink_out: float
    T_w_SC_out: float       # water between SC and condenser [K]
    T_w_con_out: float      # water between condenser and DSH [K]
    dp_source: float
    superheat: float
    subcooling: float
    pinch: float
    dsh_condensing: bool    # DSH outlet reached saturation (its surplus UA left unused)
    states: dict[str, State] = field(default_factory=dict)
    T_source_out: float = math.nan   # source outlet [K]: the input, or where it floats (ls_limit)
    ls_limit: str = ""               # "max"/"min": LS at that speed bound, T_source_out floating
    iterations: int = 0
    _slope_c: float = 0.0   # d(residual)/dT_c from the last solve (warm start)
    _slope_m: float = 0.0   # d(n_HS)/dT_m from the last solve (warm start)
    _warm: dict = field(default_factory=dict)   # (p, rho, T) of the isentropic discharge states
    _cp_l: float = 0.0      # SC liquid secant heat capacity from the last solve (warm start)
    _jac: tuple | None = None   # d(r, n_HS)/d(T_m, T_c) at a speed bound (warm start)
    _rho_l: float | None = None # SC outlet liquid density (warm start)
    _slope_T: float = math.nan  # d((N_LS - bound)/N_nom)/dT_source,out where the LS floated (warm start)

    @property
    def W_total(self) -> float:
        return self.W_LS + self.W_HS

    @property
    def COP(self) -> float:
        return self.Q_sink / self.W_total

    @property
    def hs_saturated(self) -> bool:
        return self.branch == "hs_max"

    @property
    def W_shaft(self) -> float:
        """Shaft power of both stages m*(h_dis - h_suc) [W] (adiabatic compressors)."""
        return (self.m_LS * (self.states["LS_dis"].h - self.states["LS_suc"].h)
                + self.m_HS * (self.states["HS_dis"].h - self.states["HS_suc"].h))

    @property
    def energy_residual(self) -> float:
        """(Q_source + W_shaft - Q_sink) / Q_sink: must be ~0 (adiabatic compressors)."""
        return (self.Q_source + self.W_shaft - self.Q_sink) / self.Q_sink

    def to_dict(self, ambient_pressure: float = 1.01325e5, states: bool = True) -> dict:
        """Canonical keys and units (bar absolute, degC, kW, rpm) as printed by `hp-edge point`."""
        d = {
            "branch": self.branch, "hs_saturated": self.hs_saturated,
            "p_e_bar": self.p_e / BAR, "p_m_bar": self.p_m / BAR, "p_c_bar": self.p_c / BAR,
            "p_m_barg": Pa_to_barg(self.p_m, ambient_pressure / BAR),
            "T_e_C": K_to_C(self.T_e), "T_m_C": K_to_C(self.T_m), "T_c_C": K_to_C(self.T_c),
            "N_LS_rpm": self.N_LS, "N_HS_rpm": self.N_HS,
            "Q_sink_kW": self.Q_sink / 1e3, "Q_source_kW": self.Q_source / 1e3,
            "Q_DSH_kW": self.Q_DSH / 1e3, "Q_con_kW": self.Q_con / 1e3, "Q_SC_kW": self.Q_SC / 1e3,
            "W_LS_kW": self.W_LS / 1e3, "W_HS_kW": self.W_HS / 1e3, "W_total_kW": self.W_total / 1e3,
            "COP": self.COP, "T_sink_out_C": K_to_C(self.T_sink_out),
            "eta_is_LS": self.eta_is_LS, "eta_is_HS": self.eta_is_HS,
            "eta_vol_LS": self.eta_vol_LS, "eta_vol_HS": self.eta_vol_HS,
            "m_LS_kg_s": self.m_LS, "m_HS_kg_s": self.m_HS,
            "superheat_K": self.superheat, "subcooling_K": self.subcooling, "pinch_K": self.pinch,
            "dp_source_bar": self.dp_source / BAR, "energy_residual": self.energy_residual,
            "T_source_out_C": K_to_C(self.T_source_out), "ls_limit": self.ls_limit,
        }
        if states:
            d["states"] = {k: {"T_C": K_to_C(s.T), "p_bar": s.p / BAR, "h_J_kg": s.h}
                           for k, s in self.states.items()}
        return d


# --------------------------------------------------------------------------------------------------
# components
# --------------------------------------------------------------------------------------------------
def evaporator(inp: CycleInputs, params: PlantParams) -> tuple[float, float]:
    """(Q_source [W], T_e [K]) of the flooded evaporator (closed form: model.components)."""
    C = params.cp_w * params.rho_w * inp.V_source
    dT = inp.T_source_in - inp.T_source_out
    if not (C > 0.0 and dT > 0.0):
        raise InfeasibleOperation(
            f"source must be cooled with positive flow (V_source={inp.V_source:.4g} m3/s, "
            f"T_in-T_out={dT:.4g} K)", reason="bad_source")
    return C * dT, evaporator_T_e(inp.T_source_in, inp.T_source_out, params.UA_eva, C)


# --------------------------------------------------------------------------------------------------
# the flowsheet for fixed (T_m, T_c)
# --------------------------------------------------------------------------------------------------
class _Point:
    """Evaluates the flowsheet at trial saturation temperatures; keeps warm-start guesses."""

    def __init__(self, inp: CycleInputs, params: PlantParams, fluid: Fluid, guess: CycleResult | None):
        self.inp, self.par, self.fl = inp, params, fluid
        self.Q_source, self.T_e = evaporator(inp, params)
        if self.T_e <= fluid.T_triple + 1.0:
            raise InfeasibleOperation(f"evaporating temperature {K_to_C(self.T_e):.2f} degC is below "
                                      "the fluid's range", reason="T_e_low")
        self.sat_e = fluid.sat_T(self.T_e)
        self.p_e = self.sat_e.p
        self.T1 = self.T_e + params.superheat
        self.h1, self.s1, self.rho1 = fluid.vapour_pT(self.p_e, self.T1)
        self.C_w = params.cp_w * params.rho_w * inp.V_sink
        if not self.C_w > 0.0:
            raise InfeasibleOperation(f"sink flow must be positive (V_sink={inp.V_sink:.4g} m3/s)",
                                      reason="bad_sink")
        self.UA_DSH = params.CF_DSH * params.U_DSH * params.A_DSH
        self.UA_con = params.CF_con * params.U_con * params.A_con
        self.UA_SC = params.CF_SC * params.U_SC * params.A_SC
        self.eps_con = 1.0 - math.exp(-self.UA_con / self.C_w)
        # warm-start memory
        self.n_LS = guess.N_LS / params.comp_LS.N_nom if guess else 1.0
        self.n_HS = guess.N_HS / params.comp_HS.N_nom if guess else 1.0
        self.m_HS = guess.m_HS if guess else None
        self.cp_l = guess._cp_l if guess else None     # SC liquid secant heat capacity (warm start)
        self._rho_l = guess._rho_l if guess else None  # SC outlet liquid density (warm start)
        if guess:
            for stage, g in guess._warm.items():
                setattr(self, "_g_" + stage, g)
        self._ls_cache: tuple | None = None
        self._memo: tuple | None = None
        self.evals = 0

    def ls_side(self, sat_m: SatState):
        """LS stage for intermediate saturation state sat_m (depends on T_m only)."""
        if self._ls_cache is not None and self._ls_cache[0] == sat_m.T:
            return self._ls_cache[1]
        par, fl = self.par, self.fl
        m_LS = self.Q_source / (self.h1 - sat_m.h_f)
        pi = sat_m.p / self.p_e
        n, ev = par.comp_LS.speed_for_flow(m_LS, self.rho1, pi, self.n_LS)
        self.n_LS = n
        eta = par.comp_LS.eta_is_at(pi, n)
        if not 0.05 < eta <= 1.0:
            raise InfeasibleOperation(f"LS isentropic efficiency {eta:.3f} outside (0.05, 1] at "
                                      f"pressure ratio {pi:.3f}, {n * par.comp_LS.N_nom:.0f} rpm",
                                      reason="eta_out_of_range")
        h2s, T2s, rho2s = fl.isentropic(sat_m.p, self.s1, self._rhoT_guess("LS", sat_m.p))
        self._remember("LS", sat_m.p, rho2s, T2s)
        h2 = self.h1 + (h2s - self.h1) / eta
        out = (m_LS, n, ev, eta, h2s, T2s, rho2s, h2)
        self._ls_cache = (sat_m.T, out)
        return out

    def _h_liq(self, sat_c: SatState, T: float) -> float:
        """Liquid enthalpy at (p_c, T) by Newton from the last liquid density of this point's
        solve (or of its warm start), by the (P,T) flash the first time."""
        h, rho = self.fl.liquid_pT_rho(sat_c.p, T, self._rho_l)
        self._rho_l = rho
        return h

    def _rhoT_guess(self, stage: str, p: float):
        g = getattr(self, "_g_" + stage, None)
        if g is None:
            return None
        p0, rho0, T0 = g
        # scale the previous density with pressure (ideal-gas-like), keep T
        return (rho0 * p / p0, T0 * (p / p0) ** 0.2)

    def _remember(self, stage: str, p: float, rho: float, T: float) -> None:
        setattr(self, "_g_" + stage, (p, rho, T))

    def evaluate(self, T_m: float, T_c: float, full: bool = False):
        """Residual of the condenser zone [-] (and HS speed ratio) at (T_m, T_c).

        The last evaluation is memoised: the solver asks again for the converged point."""
        memo = self._memo
        if memo is not None and memo[0] == T_m and memo[1] == T_c:
            d = memo[2]
            return d if full else (d["r"], d["n_HS"])
        d = self._evaluate(T_m, T_c)
        self._memo = (T_m, T_c, d)
        return d if full else (d["r"], d["n_HS"])

    def _evaluate(self, T_m: float, T_c: float) -> dict:
        self.evals += 1
        par, fl, inp = self.par, self.fl, self.inp
        if not (self.T_e < T_m < T_c):
            raise ConvergenceError(f"trial temperatures out of order: T_e={self.T_e:.3f} K, "
                                   f"T_m={T_m:.3f} K, T_c={T_c:.3f} K", reason="no_convergence")
        sat_m = fl.sat_T(T_m)
        sat_c = fl.sat_T(T_c)
        m_LS, n_LS, ev_LS, eta_LS, h2s, T2s, rho2s, h2 = self.ls_side(sat_m)
        dT_SC = T_c - inp.T_sink_in
        if dT_SC <= 0.0:
            raise ConvergenceError("condensing temperature below sink inlet", reason="no_convergence")
        # HS mass flow: intercooler balance m_HS*(h_g,m - h_SC,out) = m_LS*(h2 - h_f,m). The SC outlet
        # depends on m_HS and on the liquid's capacity rate, taken as the secant heat capacity over the
        # SC's actual range, (h_f(T_c) - h(p_c, T_SC,out)) / (T_c - T_SC,out), with the outlet enthalpy
        # from the equation of state: a fixed point in (m_HS, cp_l) that contracts fast (cp_l of liquid
        # ammonia varies a few % over 20 K). At convergence the SC outlet state is exact and its duty
        # m*(h_f - h_SC) equals the eps-NTU duty.
        num = m_LS * (h2 - sat_m.h_f)
        cp_l = self.cp_l if self.cp_l else (sat_c.h_f - fl.h_liq_sat(T_c - 5.0)) / 5.0
        try:
            m, h_SC, T_SC, cp_l = subcooler(num, sat_m.h_g - sat_c.h_f, sat_c.h_f, T_c, inp.T_sink_in,
                                            self.C_w, self.UA_SC, cp_l, self.m_HS,
                                            lambda T: self._h_liq(sat_c, T), tol=SC_TOL)
        except ArithmeticError as exc:
            raise ConvergenceError(str(exc), reason="no_convergence") from None
        self.m_HS, self.cp_l = m, cp_l
        Q_SC = m * (sat_c.h_f - h_SC)
        # HS compressor
        pi_HS = sat_c.p / sat_m.p
        n_HS, ev_HS = par.comp_HS.speed_for_flow(m, sat_m.rho_g, pi_HS, self.n_HS)
        self.n_HS = n_HS
        eta_HS = par.comp_HS.eta_is_at(pi_HS, n_HS)
        if not 0.05 < eta_HS <= 1.0:
            raise InfeasibleOperation(f"HS isentropic efficiency {eta_HS:.3f} outside (0.05, 1] at "
                                      f"pressure ratio {pi_HS:.3f}", reason="eta_out_of_range")
        h4s, T4s, rho4s = fl.isentropic(sat_c.p, sat_m.s_g, self._rhoT_guess("HS", sat_c.p))
        self._remember("HS", sat_c.p, rho4s, T4s)
        h4 = sat_m.h_g + (h4s - sat_m.h_g) / eta_HS
        # actual discharge temperature from the equation of state (Newton warm-started at the
        # isentropic state); the DSH's vapour capacity rate is the secant over its whole range
        T4, rho4 = fl.vapour_ph(sat_c.p, h4, (rho4s, T4s))
        # condenser unit, water SC -> condenser -> DSH
        T_w1 = inp.T_sink_in + Q_SC / self.C_w
        Q_con = self.eps_con * self.C_w * (T_c - T_w1)
        T_w2 = T_w1 + Q_con / self.C_w
        cp_v = (h4 - sat_c.h_g) / (T4 - T_c)
        eps_D, C_min_D = counterflow_eps(m * cp_v, self.C_w, self.UA_DSH)
        Q_DSH = eps_D * C_min_D * (T4 - T_w2)
        Q_DSH_max = m * (h4 - sat_c.h_g)
        dsh_condensing = Q_DSH > Q_DSH_max
        if dsh_condensing:
            Q_DSH = Q_DSH_max
        h_DSH = h4 - Q_DSH / m
        r = (Q_con - m * (h_DSH - sat_c.h_f)) / self.Q_source
        d = dict(sat_m=sat_m, sat_c=sat_c, m_LS=m_LS, n_LS=n_LS, ev_LS=ev_LS, eta_LS=eta_LS,
                 h2s=h2s, T2s=T2s, rho2s=rho2s, h2=h2, m_HS=m, n_HS=n_HS, ev_HS=ev_HS, eta_HS=eta_HS,
                 h4s=h4s, T4s=T4s, rho4s=rho4s, h4=h4, T4=T4, rho4=rho4, cp_l=cp_l, cp_v=cp_v,
                 Q_SC=Q_SC, h_SC=h_SC, T_SC=T_SC,
                 Q_con=Q_con, Q_DSH=Q_DSH, h_DSH=h_DSH, T_w1=T_w1, T_w2=T_w2,
                 dsh_condensing=dsh_condensing, r=r)
        return d


# --------------------------------------------------------------------------------------------------
# scalar root finding: secant with a remembered slope, bracketed fallback
# --------------------------------------------------------------------------------------------------
def _secant(f, x0: float, slope: float, tol: float, lo: float, hi: float, what: str):
    """Root of f in [lo, hi] from x0 using a secant iteration seeded with ``slope``.

    Returns (x, f(x), slope). Falls back to bisection-safeguarded steps once a sign change is
    bracketed. Raises ConvergenceError with the reason when no root is found.
    """
    x = min(max(x0, lo), hi)
    fx = f(x)
    if abs(fx) < tol:
        return x, fx, slope
    a = b = None          # bracket: f(a) < 0 < f(b) in terms of sign of fx
    fa = fb = None
    if not (slope and math.isfinite(slope)):
        h = 1e-3 if abs(x) > 1 else 1e-4
        x1 = x + h if x + h <= hi else x - h
        slope = (f(x1) - fx) / (x1 - x)
    for _ in range(MAX_ITER):
        if fx < 0:
            a, fa = x, fx
        else:
            b, fb = x, fx
        if slope == 0.0 or not math.isfinite(slope):
            raise ConvergenceError(f"{what}: zero slope", reason="no_convergence")
        xn = x - fx / slope
        if a is not None and b is not None:
            left, right = (a, b) if a < b else (b, a)
            if not (left < xn < right):
                xn = 0.5 * (a + b)
        else:
            # no bracket yet: limit the step and stay in [lo, hi]
            step = max(min(xn - x, 10.0), -10.0)
            xn = min(max(x + step, lo), hi)
            if xn == x:
                raise ConvergenceError(f"{what}: no root in [{lo:.3f}, {hi:.3f}]", reason="no_convergence")
        fn = f(xn)
        if xn != x:
            s_new = (fn - fx) / (xn - x)
            if s_new != 0.0 and math.isfinite(s_new):
                slope = s_new
        x, fx = xn, fn
        if abs(fx) < tol:
            return x, fx, slope
    raise ConvergenceError(f"{what}: no convergence in {MAX_ITER} iterations (residual {fx:.3g})",
                           reason="no_convergence")


# --------------------------------------------------------------------------------------------------
# solve one point
# --------------------------------------------------------------------------------------------------
LS_MODES = ("flag", "float")
LS_SPEED_TOL = 1e-7       # LS speed-bound residual when T_source,out floats, relative to nominal speed
LS_SPEED_LOOSE = 1e-3     # ... accepted when the iteration cannot get closer (non-smooth curves)
LS_FLOAT_QUICK_ITER = 4   # Newton steps from a nearby floating point before the full search


def solve(inp: CycleInputs, params: PlantParams, guess: CycleResult | None = None,
          fluid: Fluid | None = None, ls_mode: str = "flag") -> CycleResult:
    """Solve one operating point.

    Parameters
    ----------
    inp : CycleInputs
        Water temperatures [K], flows [m^3/s], p_m set point [Pa absolute].
    params : PlantParams
    guess : CycleResult, optional
        A nearby solution (the previous minute) for a warm start.
    ls_mode : "flag" or "float"
        What an LS speed outside 700-1800 rpm means. "flag" (measured data; the default): T_source,out
        is what the plant achieved, so such a point says the model is off; it raises
        InfeasibleOperation (``ls_speed_high``/``ls_speed_low``) with the solved state attached.
        "float" (prediction; the optimizer): the LS speed controller saturates as the plant's does:
        at N_max the compressor cannot carry the duty and T_source,out floats above the input (less
        heat from the source), at N_min it floats below. The result's ``T_source_out`` and
        ``ls_limit`` ("max"/"min") say so; Q_source is the floating point's.

    Raises
    ------
    InfeasibleOperation
        Solved, but outside an operating limit (``result`` attached), or the inputs cannot be
        operated (source not cooled, set point below p_e, ...).
    ConvergenceError
        No solution found; the message says why.
    """
    if ls_mode not in LS_MODES:
        raise ValueError(f"ls_mode must be one of {', '.join(LS_MODES)}, got {ls_mode!r}")
    fluid = fluid or get_fluid(params.fluid, params.backend)
    try:
        if ls_mode == "float":
            res = _solve_ls_float(inp, params, guess, fluid)
        else:
            res = _solve(inp, params, guess, fluid)
        _check_limits(res, params)
        return res
    except PropertyError as exc:
        raise ConvergenceError(f"property evaluation failed: {exc}", reason="property_error") from exc
    except ValueError as exc:   # compressor curve outside its valid shape
        raise ConvergenceError(str(exc), reason="compressor_curve") from exc
    except ZeroDivisionError as exc:
        raise ConvergenceError(f"degenerate state: {exc}", reason="no_convergence") from exc


OVERLOAD = ("eta_out_of_range", "hs_speed_high", "p_c_high")   # failures at too much LS duty


def _solve_ls_float(inp: CycleInputs, params: PlantParams, guess: CycleResult | None,
                    fluid: Fluid) -> CycleResult:
    """The LS speed controller with its saturation: T_source,out at the input when the LS speed that
    carries that duty is within its range, else floating where N_LS sits at the violated bound.

    N_LS falls monotonically as T_source,out rises (less duty, and a warmer evaporator): a secant on
    T_source,out seeded with "speed proportional to duty", safeguarded by bisection. At the input's
    T_source,out the duty may be so far beyond the LS stage that the flowsheet cannot be solved at all
    (the HS stage overloaded, the condenser beyond its design pressure): that counts as "speed above
    the maximum" too, and a trial point that cannot be solved counts as being on the input's side."""
    ls = params.comp_LS
    T_sp, T_in = inp.T_source_out, inp.T_source_in
    if guess is not None and guess.ls_limit and math.isfinite(guess._slope_T):
        quick = _ls_float_from(inp, params, guess, fluid)
        if quick is not None:
            return quick
    try:
        res: CycleResult | None = _solve(inp, params, guess, fluid)
        err = None
    except InfeasibleOperation as exc:
        if exc.reason not in OVERLOAD:
            raise
        res, err = None, exc
    if res is not None and ls.N_min <= res.N_LS <= ls.N_max:
        return res
    limit = "max" if res is None or res.N_LS > ls.N_max else "min"
    N_b = ls.N_max if limit == "max" else ls.N_min
    lo, hi = (T_sp, T_in - 0.05) if limit == "max" else (max(T_sp - 15.0, fluid.T_triple + 5.0), T_sp)
    far = hi if limit == "max" else lo          # the end where the bound is surely met
    last = {"res": res if res is not None else guess}

    def g(T_out: float) -> float | None:
        """(N_LS - N_b)/N_nom at T_out, None when the point cannot be solved."""
        try:
            r = _solve(inp.replace(T_source_out=T_out), params, last["res"], fluid)
        except ModelError:
            return None
        last["res"] = r
        return (r.N_LS - N_b) / ls.N_nom

    sgn0 = 1.0 if limit == "max" else -1.0      # sign of g on the input's side
    near, f_near = T_sp, (None if res is None else (res.N_LS - N_b) / ls.N_nom)
    beyond = f_beyond = None                    # a point where the bound is met (sign change)
    if res is None:
        # the input cannot be solved at all: first the far end (the least duty). If even that
        # cannot be solved, or the bound is not met there, no floating point exists: the input's
        # failure is the answer (searching the bracket toward it would only repeat the failure)
        f_far = g(far)
        if f_far is None or f_far * sgn0 > 0:
            raise err
        beyond, f_beyond = far, f_far
    if res is not None:
        x = T_in - (T_in - T_sp) * N_b / res.N_LS          # duty proportional to speed
    else:
        x = T_sp + 0.5 * (far - T_sp)
    if guess is not None and guess.ls_limit == limit and min(lo, hi) < guess.T_source_out < max(lo, hi):
        x = guess.T_source_out                              # where it floated a minute ago
    x = min(max(x, lo), hi)
    best = None                                 # the closest solved point (fallback)
    for _ in range(2 * MAX_ITER):
        fx = g(x)
        if fx is not None and (best is None or abs(fx) < best[0]):
            best = (abs(fx), last["res"])
        if fx is not None and abs(fx) < LS_SPEED_TOL:
            out = last["res"]
            out.ls_limit = limit
            p_x, p_f = near if near != x else beyond, f_near if near != x else f_beyond
            if p_x is not None and p_f is not None and p_x != x:
                out._slope_T = (fx - p_f) / (x - p_x)
            return out
        if fx is None or fx * sgn0 > 0:
            prev = (near, f_near)
            near, f_near = x, fx
        else:
            prev = (beyond, f_beyond)
            beyond, f_beyond = x, fx
        # next trial: secant through the two newest finite points, kept inside the bracket
        xn = None
        p_x, p_f = prev
        if fx is not None and p_f is not None and p_f != fx and p_x is not None:
            xn = x - fx * (x - p_x) / (fx - p_f)
        elif fx is not None and f_near is not None and beyond is not None and f_beyond != f_near:
            xn = near - f_near * (near - beyond) / (f_near - f_beyond)
        a, b = near, (beyond if beyond is not None else far)
        if beyond is None and x == far:
            break                                             # even at the far end: not met
        if xn is None or not min(a, b) < xn < max(a, b):
            xn = 0.5 * (a + b)
        x = xn
    if best is not None and best[0] < LS_SPEED_LOOSE:
        # a compressor curve that is not smooth to round-off (learned, locally weighted) can keep
        # the residual above LS_SPEED_TOL: a speed within LS_SPEED_LOOSE of the bound is the bound
        out = best[1]
        out.ls_limit = limit
        return out
    if err is not None:
        raise err
    raise InfeasibleOperation(
        f"LS compressor at {N_b:.0f} rpm: no source outlet temperature in "
        f"{K_to_C(lo):.2f}..{K_to_C(hi):.2f} degC carries its flow",
        reason=f"ls_speed_{'high' if limit == 'max' else 'low'}", result=res)


def _ls_float_from(inp: CycleInputs, params: PlantParams, guess: CycleResult, fluid: Fluid
                   ) -> CycleResult | None:
    """The floating T_source,out by Newton from a nearby point that floated at the same LS speed
    bound (its T_source,out and slope dN_LS/dT_source,out): typically two solves instead of a solve
    at the input plus a secant. Where the LS at its bound carries the duty at a T_source,out beyond
    the input's (above it at N_max, below at N_min), the speed needed AT the input is beyond the
    bound (N_LS falls monotonically as T_source,out rises), so this is the answer of the full search.
    None when it does not converge in a few steps or ends on the input's side: the caller searches."""
    ls = params.comp_LS
    limit = guess.ls_limit
    N_b = ls.N_max if limit == "max" else ls.N_min
    T_sp, T_in = inp.T_source_out, inp.T_source_in
    lo, hi = (T_sp, T_in - 0.05) if limit == "max" else (max(T_sp - 15.0, fluid.T_triple + 5.0), T_sp)
    x, slope, last = min(max(guess.T_source_out, lo), hi), guess._slope_T, guess
    x_prev = f_prev = None
    try:
        for _ in range(LS_FLOAT_QUICK_ITER):
            r = _solve(inp.replace(T_source_out=x), params, last, fluid)
            f = (r.N_LS - N_b) / ls.N_nom
            if x_prev is not None and x != x_prev and f != f_prev:
                slope = (f - f_prev) / (x - x_prev)
            if abs(f) < LS_SPEED_TOL:
                inside = x > T_sp + 1e-9 if limit == "max" else x < T_sp - 1e-9
                if not inside:
                    return None
                r.ls_limit = limit
                r._slope_T = slope
                return r
            if not (slope < 0.0 and math.isfinite(slope)):
                return None
            x_prev, f_prev, last = x, f, r
            x = x - f / slope
            if not lo <= x <= hi:
                return None
    except ModelError:
        return None
    return None


def _solve(inp: CycleInputs, params: PlantParams, guess: CycleResult | None, fluid: Fluid) -> CycleResult:
    pt = _Point(inp, params, fluid, guess)
    hs = params.comp_HS
    if inp.p_m_sp >= fluid.p_crit:
        raise InfeasibleOperation("p_m set point above the critical pressure", reason="p_m_sp_high")
    T_m_sp = fluid.sat_p(inp.p_m_sp).T
    tol_r = ENERGY_TOL
    T_c_max = fluid.sat_p(min(params.p_c_max, fluid.p_crit * 0.98)).T
    T_c_lo = inp.T_sink_in + 0.05

    slope_c = guess._slope_c if guess else 0.0
    T_c_guess = [guess.T_c if guess else
                 inp.T_sink_in + 1.3 * pt.Q_source / pt.C_w + 3.0]

    def solve_Tc(T_m: float) -> float:
        nonlocal slope_c
        lo = max(T_c_lo, T_m + 0.05)
        f = lambda Tc: pt.evaluate(T_m, Tc)[0]  # noqa: E731
        try:
            T_c, _, slope_c = _secant(f, min(max(T_c_guess[0], lo + 0.5), T_c_max), slope_c, tol_r,
                                      lo, T_c_max, "condensing temperature")
        except ConvergenceError:
            if f(T_c_max) < 0.0:   # even at the design pressure the condenser cannot reject the duty
                raise InfeasibleOperation(
                    f"the sink cannot take the heat: condensing pressure would exceed the design "
                    f"limit {params.p_c_max / BAR:.1f} bar(a)", reason="p_c_high") from None
            if T_m + 0.05 >= T_c_lo and f(lo) > 0.0:   # the condenser would work below p_m
                raise InfeasibleOperation(
                    f"intermediate pressure {fluid.sat_T(T_m).p / BAR:.2f} bar(a) is not below the "
                    f"condensing pressure the sink allows", reason="p_m_above_p_c") from None
            raise
        T_c_guess[0] = T_c
        return T_c

    def n_HS_at(T_m: float) -> float:
        T_c = solve_Tc(T_m)
        return pt.evaluate(T_m, T_c)[1]

    n_max, n_min = hs.N_max / hs.N_nom, hs.N_min / hs.N_nom
    slope_m = guess._slope_m if guess else 0.0
    # Branch choice. The HS speed needed to hold p_m falls monotonically as p_m rises, so the speed
    # needed AT the set point decides: within the range -> "sp"; above N_max -> the HS runs at N_max
    # and p_m floats above the set point; below N_min -> at N_min, p_m floats below.
    T_m = T_m_sp
    joint = None
    if guess is not None and guess.branch == "hs_max" and inp.p_m_sp > pt.p_e * 1.001:
        # the previous point ran the HS flat out: solve that branch directly. Where the HS at full
        # speed holds p_m above the set point, the speed needed AT the set point is above the
        # maximum (it falls as p_m rises), which is the branch test below without its T_c solve
        joint = _bound_newton(pt, max(guess.T_m, T_m_sp), guess.T_c, n_max, T_m_sp, guess.T_c + 10.0,
                              max(T_c_lo, pt.T_e + 0.1), T_c_max, guess._jac)
        if joint is not None and not joint[0] > T_m_sp + 1e-6:
            joint = None
    if joint is not None:
        branch = "hs_max"
    elif inp.p_m_sp <= pt.p_e * 1.001:
        # a set point at or below p_e cannot be held: the HS runs flat out and p_m floats
        branch, bound, lo, hi = "hs_max", n_max, pt.T_e + 0.05, T_c_guess[0] - 0.1
    else:
        n_sp = n_HS_at(T_m_sp)
        if n_sp > n_max + SPEED_TOL:
            branch, bound, lo, hi = "hs_max", n_max, T_m_sp, T_c_guess[0] - 0.1
        elif n_sp < n_min - SPEED_TOL:
            branch, bound, lo, hi = "hs_min", n_min, pt.T_e + 0.05, T_m_sp
        else:
            branch = "sp"
    jac = None
    if joint is not None:
        T_m, T_c_guess[0], jac = joint
        slope_c = jac[0][1]
    elif branch != "sp":
        warm = guess is not None and guess.branch == branch and lo < guess.T_m < hi
        T_m0 = guess.T_m if warm else (T_m_sp if lo < T_m_sp < hi else 0.5 * (lo + hi))
        # first a joint Newton on (T_m, T_c), Broyden-updated from the previous point's Jacobian
        # (~4 flowsheet evaluations instead of ~15 for the nested secants); the nested secants below
        # remain the fallback and say why a point has no solution
        joint = _bound_newton(pt, T_m0, guess.T_c if warm else T_c_guess[0], bound, lo, hi,
                              max(T_c_lo, pt.T_e + 0.1), T_c_max, guess._jac if warm else None)
        if joint is not None:
            T_m, T_c_guess[0], jac = joint
            slope_c = jac[0][1]
        g = lambda Tm: n_HS_at(Tm) - bound  # noqa: E731
        try:
            if joint is None:
                T_m, _, slope_m = _secant(g, T_m0, slope_m, SPEED_TOL, lo, hi,
                                          f"intermediate pressure at HS speed bound ({branch})")
        except ConvergenceError:
            # N_HS falls as p_m rises; no root in [lo, hi] means the bound cannot be met at all
            if branch == "hs_min" and g(lo) < 0.0:
                raise InfeasibleOperation(
                    f"HS compressor at its minimum speed {hs.N_min:.0f} rpm moves more than the LS "
                    f"stage delivers: duty below the HS turndown", reason="hs_speed_low") from None
            if branch == "hs_max" and g(hi) > 0.0:
                raise InfeasibleOperation(
                    f"HS compressor at its maximum speed {hs.N_max:.0f} rpm cannot carry the LS "
                    f"stage's flow at any intermediate pressure", reason="hs_speed_high") from None
            raise

    T_c = solve_Tc(T_m)
    s = pt.evaluate(T_m, T_c, full=True)
    return _assemble(pt, s, branch, T_m, T_c, slope_c, slope_m, jac)


def _bound_newton(pt: _Point, T_m: float, T_c: float, bound: float, lo: float, hi: float,
                  T_c_lo: float, T_c_max: float, J: tuple | None):
    """(T_m, T_c) where the condenser zone carries its duty (residual r = 0) and the HS compressor
    runs at its speed bound (n_HS = bound), by Newton on both at once with Broyden updates of the
    Jacobian (finite differences when no previous Jacobian is given). Returns (T_m, T_c, J) at the
    same tolerances as the nested secants, or None when it does not converge quickly or leaves the
    domain (the caller then falls back to the nested secants)."""
    if not (lo <= T_m <= hi and T_c_lo < T_c <= T_c_max and T_m < T_c - 0.05):
        return None
    try:
        r, n = pt.evaluate(T_m, T_c)
        F = (r, n - bound)
        if J is None or not all(map(math.isfinite, (*J[0], *J[1]))):
            h = 1e-3
            r1, n1 = pt.evaluate(T_m + h, T_c)
            r2, n2 = pt.evaluate(T_m, T_c + h)
            J = ((r1 - r) / h, (r2 - r) / h), ((n1 - n) / h, (n2 - n) / h)
        for _ in range(BOUND_NEWTON_ITER):
            if abs(F[0]) < ENERGY_TOL and abs(F[1]) < SPEED_TOL:
                return T_m, T_c, J
            (a, b), (c, d) = J
            det = a * d - b * c
            if det == 0.0 or not math.isfinite(det):
                return None
            dm = -(d * F[0] - b * F[1]) / det
            dc = -(a * F[1] - c * F[0]) / det
            big = max(abs(dm), abs(dc))
            if big > BOUND_NEWTON_STEP:
                dm, dc = dm * BOUND_NEWTON_STEP / big, dc * BOUND_NEWTON_STEP / big
            T_m1, T_c1 = T_m + dm, T_c + dc
            if not (lo <= T_m1 <= hi and T_c_lo < T_c1 <= T_c_max and T_m1 < T_c1 - 0.05):
                return None
            r, n = pt.evaluate(T_m1, T_c1)
            F1 = (r, n - bound)
            # Broyden: J += (dF - J dx) dx^T / (dx . dx)
            dd = dm * dm + dc * dc
            u0 = (F1[0] - F[0]) - (a * dm + b * dc)
            u1 = (F1[1] - F[1]) - (c * dm + d * dc)
            J = ((a + u0 * dm / dd, b + u0 * dc / dd), (c + u1 * dm / dd, d + u1 * dc / dd))
            T_m, T_c, F = T_m1, T_c1, F1
    except ModelError:
        return None
    return None


def _assemble(pt: _Point, s: dict, branch: str, T_m: float, T_c: float, slope_c: float,
              slope_m: float, jac: tuple | None = None) -> CycleResult:
    inp, par, fl = pt.inp, pt.par, pt.fl
    sat_m, sat_c, sat_e = s["sat_m"], s["sat_c"], pt.sat_e
    m_LS, m_HS = s["m_LS"], s["m_HS"]
    W_LS = m_LS * (s["h2"] - pt.h1) * par.comp_LS.drive_factor
    W_HS = m_HS * (s["h4"] - sat_m.h_g) * par.comp_HS.drive_factor
    Q_sink = s["Q_SC"] + s["Q_con"] + s["Q_DSH"]
    T_sink_out = s["T_w2"] + s["Q_DSH"] / pt.C_w
    T_SC_out = s["T_SC"]
    T_DSH_out = s["T4"] - s["Q_DSH"] / (m_HS * s["cp_v"])
    pinch = min(T_SC_out - inp.T_sink_in, T_c - s["T_w1"], T_c - s["T_w2"],
                T_DSH_out - s["T_w2"], s["T4"] - T_sink_out)
    p_e, p_m, p_c = sat_e.p, sat_m.p, sat_c.p
    T4, rho4 = s["T4"], s["rho4"]
    states = {
        "eva_out": State(pt.T_e, p_e, sat_e.h_g),
        "LS_suc": State(pt.T1, p_e, pt.h1),
        "LS_dis_is": State(s["T2s"], p_m, s["h2s"]),
        "LS_dis": State(fl.vapour_ph(p_m, s["h2"], (s["rho2s"], s["T2s"]))[0], p_m, s["h2"]),
        "HS_suc": State(T_m, p_m, sat_m.h_g),
        "HS_dis_is": State(s["T4s"], p_c, s["h4s"]),
        "HS_dis": State(T4, p_c, s["h4"]),
        "DSH_out": State(fl.vapour_ph(p_c, s["h_DSH"], (rho4, T4))[0] if not s["dsh_condensing"] else T_c,
                         p_c, s["h_DSH"]),
        "con_out": State(T_c, p_c, sat_c.h_f),
        "SC_out": State(T_SC_out, p_c, s["h_SC"]),
        "HS_valve_out": State(T_m, p_m, s["h_SC"]),
        "IC_liq": State(T_m, p_m, sat_m.h_f),
        "LS_valve_out": State(pt.T_e, p_e, sat_m.h_f),
    }
    return CycleResult(
        branch=branch, p_e=p_e, p_m=p_m, p_c=p_c, T_e=pt.T_e, T_m=T_m, T_c=T_c,
        N_LS=s["n_LS"] * par.comp_LS.N_nom, N_HS=s["n_HS"] * par.comp_HS.N_nom,
        eta_is_LS=s["eta_LS"], eta_is_HS=s["eta_HS"], eta_vol_LS=s["ev_LS"], eta_vol_HS=s["ev_HS"],
        m_LS=m_LS, m_HS=m_HS, Q_source=pt.Q_source, Q_sink=Q_sink, Q_DSH=s["Q_DSH"],
        Q_con=s["Q_con"], Q_SC=s["Q_SC"], W_LS=W_LS, W_HS=W_HS, T_sink_out=T_sink_out,
        T_w_SC_out=s["T_w1"], T_w_con_out=s["T_w2"],
        dp_source=par.CF_dp_f * par.dp_clean(inp.V_source), superheat=par.superheat,
        subcooling=T_c - T_SC_out, pinch=pinch, dsh_condensing=s["dsh_condensing"], states=states,
        T_source_out=inp.T_source_out,
        iterations=pt.evals, _slope_c=slope_c, _slope_m=slope_m, _cp_l=pt.cp_l or 0.0, _jac=jac,
        _rho_l=pt._rho_l,
        _warm={k: getattr(pt, "_g_" + k) for k in ("LS", "HS") if getattr(pt, "_g_" + k, None)})


def _check_limits(res: CycleResult, params: PlantParams) -> None:
    ls = params.comp_LS
    tol = LS_SPEED_LOOSE * ls.N_nom        # a floating LS sits on its bound to within this
    if res.N_LS > ls.N_max + tol:
        raise InfeasibleOperation(f"LS compressor speed {res.N_LS:.0f} rpm above its maximum "
                                  f"{ls.N_max:.0f} rpm", reason="ls_speed_high", result=res)
    if res.N_LS < ls.N_min - tol:
        raise InfeasibleOperation(f"LS compressor speed {res.N_LS:.0f} rpm below its minimum "
                                  f"{ls.N_min:.0f} rpm", reason="ls_speed_low", result=res)
    if res.pinch < 0.0:
        raise InfeasibleOperation(f"negative pinch {res.pinch:.3f} K in the condenser unit",
                                  reason="negative_pinch", result=res)
