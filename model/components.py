"""Component physics that more than one caller needs, written once (SI units).

- the flooded evaporator's closed form (SPEC §3) and its inversion on a measured evaporating
  temperature (SPEC §4);
- the counterflow effectiveness of one heat-exchanger zone (the condenser unit's three zones).

The functions take plain floats or numpy arrays (elementwise); nothing here calls CoolProp.
"""
from __future__ import annotations

import math

import numpy as np


def _exp(x):
    return np.exp(x) if isinstance(x, np.ndarray) else math.exp(x)


def evaporator_T_e(T_in, T_out, UA, C):
    """Evaporating temperature [K] of the flooded evaporator.

    T_in, T_out : source water in and out [K]; UA : conductance [W/K] with
    1/UA = 1/(CF_eva*U*A) + R_th,f; C : source capacity rate c_p*rho*V [W/K].
    Refrigerant at T_e along the whole surface: NTU = UA/C and
    T_e = (T_out*e^NTU - T_in) / (e^NTU - 1).
    """
    e = _exp(UA / C)
    return (T_out * e - T_in) / (e - 1.0)


def evaporator_UA(T_in, T_out, T_e, C):
    """Conductance [W/K] that carries the source duty at evaporating temperature T_e [K]:
    NTU = ln((T_in - T_e)/(T_out - T_e)), UA = NTU*C. NaN where T_in > T_out > T_e fails."""
    if isinstance(T_in, np.ndarray) or isinstance(T_e, np.ndarray) or isinstance(C, np.ndarray):
        T_in, T_out, T_e, C = (np.asarray(x, dtype=float) for x in (T_in, T_out, T_e, C))
        ok = (T_in > T_out) & (T_out > T_e) & (C > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(ok, np.log((T_in - T_e) / (T_out - T_e)) * C, np.nan)
    if not (T_in > T_out > T_e and C > 0):
        return math.nan
    return math.log((T_in - T_e) / (T_out - T_e)) * C


def counterflow_eps(C_a: float, C_b: float, UA: float) -> tuple[float, float]:
    """(effectiveness, C_min) of a counterflow exchanger between capacity rates C_a, C_b [W/K]."""
    C_min, C_max = (C_a, C_b) if C_a < C_b else (C_b, C_a)
    NTU = UA / C_min
    Cr = C_min / C_max
    if abs(1.0 - Cr) < 1e-9:
        return NTU / (1.0 + NTU), C_min
    x = math.exp(-NTU * (1.0 - Cr))
    return (1.0 - x) / (1.0 - Cr * x), C_min


def subcooler(num: float, dh: float, h_f: float, T_c: float, T_w_in: float, C_w: float,
              UA: float, cp: float, m0: float | None = None, h_liq=None, tol: float = 1e-10,
              max_iter: int = 40):
    """The subcooler coupled with the open intercooler: HS mass flow, SC outlet and duty.

    The HS flow m satisfies the intercooler balance m*(h_g,m - h_SC) = num (num = m_LS*(h_dis,LS -
    h_f,m), dh = h_g,m - h_f,c); the SC (counterflow eps-NTU against sink water C_w entering at T_w_in)
    cools saturated liquid (h_f at T_c) to h_SC, with the liquid's capacity rate m*cp. For a given cp
    the balance is solved by a secant on the fixed-point residual (no property call), and
    h_SC = h_f - cp*(T_c - T_SC).

    With ``h_liq`` (the EOS liquid enthalpy h(p_c, T)) cp is iterated to the secant over the SC's
    actual range, (h_f - h_liq(T_SC)) / (T_c - T_SC), until it changes by less than ``tol``
    relative: the outlet is then on the EOS and the eps-NTU duty equals m*(h_f - h_SC). From the
    third iteration on, the fixed point in cp is accelerated by a secant step on cp_new(cp) - cp.

    Returns (m, h_SC, T_SC, cp). Raises ArithmeticError when it does not converge.
    """
    dT = T_c - T_w_in
    m = m0 if m0 else num / dh
    if dT <= 0.0:
        return num / dh, h_f, T_c, cp

    def G(x: float) -> float:
        eps, C_min = counterflow_eps(x * cp, C_w, UA)
        return num / (dh + eps * C_min * dT / x)

    prev = None           # (cp, cp_new - cp) of the previous iteration (secant acceleration)
    for _ in range(max_iter):
        x0, r0 = m, G(m) - m
        x1 = x0 + r0
        for _ in range(max_iter):
            if abs(r0) <= 1e-14 * x0:
                x1 = x0 + r0
                break
            r1 = G(x1) - x1
            if abs(r1) <= 1e-14 * x1 or r1 == r0:
                x1 = x1 + r1
                break
            x0, r0, x1 = x1, r1, x1 - r1 * (x1 - x0) / (r1 - r0)
        else:
            raise ArithmeticError("subcooler: HS mass flow did not converge")
        m = x1
        eps, C_min = counterflow_eps(m * cp, C_w, UA)
        T_SC = T_c - eps * C_min * dT / (m * cp)
        h = h_f - cp * (T_c - T_SC)
        if h_liq is None or T_c - T_SC <= 1e-6:
            return num / (dh + h_f - h), h, T_SC, cp
        h = h_liq(T_SC)
        cp_new = (h_f - h) / (T_c - T_SC)
        done = abs(cp_new - cp) <= tol * cp
        if done:
            return num / (dh + h_f - h), h, T_SC, cp_new
        r = cp_new - cp
        nxt = cp_new
        if prev is not None and r != prev[1]:
            sec = cp - r * (cp - prev[0]) / (r - prev[1])
            if sec > 0.0 and abs(sec - cp_new) < abs(r):
                nxt = sec
        prev = (cp, r)
        cp = nxt
    raise ArithmeticError("subcooler: outlet state did not converge")
