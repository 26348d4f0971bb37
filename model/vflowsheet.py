"""The flowsheet of ``model.cycle`` at trial saturation temperatures, for many rows at once.

``Flowsheet.evaluate(idx, T_m, T_c)`` is ``model.cycle._Point.evaluate`` for the rows ``idx``: the
same physics and the same order of checks, on numpy arrays, with the properties from
``model.cycletables`` and the compressors through their vectorised protocol (``eta_is_v``,
``eta_vol_v``, ``speed_for_flow_v``). Where the scalar evaluation raises, a row carries an error
code instead (``E_*``); the solver (``model.vcycle``) decides what the error means where it occurs,
as the scalar solver does. Rows the tables or the vectorised iterations cannot settle carry
``E_FALLBACK``: the scalar path solves them.

The inner problems are solved per row to round-off, so the residual is the scalar one to ~1e-9
relative and a secant iteration on it follows the scalar iteration's steps:

- the subcooler coupled with the open intercooler (``model.components.subcooler``: the HS flow and
  the SC outlet on the equation of state) as Newton on the subcooling d: with h = h(p_c, T_c - d),
  m = num/(h_g,m - h) and the liquid's secant heat capacity cp = (h_f,c - h)/d, the residual
  m*(h_f,c - h) - eps(m*cp)*C_min*(T_c - T_sink,in) vanishes exactly where the scalar fixed point
  in (m_HS, cp) converges;
- the compressor speeds, the isentropic discharge states and T4 from (p_c, h4) by Newton, each
  warm-started from the row's previous evaluation.

SI units: K, Pa, J/kg, kg/s, W.
"""
from __future__ import annotations

import numpy as np

from .components import evaporator_T_e
from .cycletables import CycleTables
from .params import PlantParams

E_OK, E_ORDER, E_SINK, E_ETA_LS, E_ETA_HS, E_FALLBACK = 0, 1, 2, 3, 4, 9
FALLBACK_WHY = ("", "saturation outside the tables", "LS stage outside the tables or its curve",
                "subcooler iteration", "HS compressor curve", "discharge state outside the tables",
                "non-finite residual")         # why an evaluation needs the scalar path
CONVERGENCE = (E_ORDER, E_SINK)          # model.cycle raises ConvergenceError (no_convergence)
INFEASIBLE = (E_ETA_LS, E_ETA_HS)        # ... InfeasibleOperation (eta_out_of_range)
SC_ITER = 30
SC_TOL = 1e-11                           # subcooling step, relative


def counterflow_eps_v(C_a, C_b, UA):
    """``model.components.counterflow_eps`` for arrays: (effectiveness, C_min)."""
    a_min = C_a < C_b
    C_min = np.where(a_min, C_a, C_b)
    C_max = np.where(a_min, C_b, C_a)
    NTU = UA / C_min
    Cr = C_min / C_max
    x = np.exp(-NTU * (1.0 - Cr))
    eps = np.where(np.abs(1.0 - Cr) < 1e-9, NTU / (1.0 + NTU), (1.0 - x) / (1.0 - Cr * x))
    return eps, C_min


class Flowsheet:
    """Row constants, warm-start memory and the flowsheet evaluation for N rows.

    T_si, T_so, T_ki : source in, source out, sink in [K]; V_s, V_k : source, sink flow [m^3/s].
    comp_LS, comp_HS : objects with the vectorised compressor protocol.
    """

    def __init__(self, params: PlantParams, tab: CycleTables, comp_LS, comp_HS,
                 T_si, T_so, T_ki, V_s, V_k) -> None:
        self.par, self.tab, self.ls, self.hs = params, tab, comp_LS, comp_HS
        n = len(T_si)
        self.n = n
        self.T_si, self.T_ki, self.V_s, self.V_k = T_si, T_ki, V_s, V_k
        rc = params.cp_w * params.rho_w
        self.C_s = rc * V_s
        self.C_w = rc * V_k
        self.UA_DSH = params.CF_DSH * params.U_DSH * params.A_DSH
        self.UA_con = params.CF_con * params.U_con * params.A_con
        self.UA_SC = params.CF_SC * params.U_SC * params.A_SC
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            self.eps_con = 1.0 - np.exp(-self.UA_con / self.C_w)
        self.T_so = np.array(T_so, dtype=float)
        self.Q_s, self.T_e, self.p_e = np.zeros(n), np.zeros(n), np.zeros(n)
        self.h_g_e, self.h1, self.s1, self.rho1 = (np.zeros(n) for _ in range(4))
        self.src_ok = np.zeros(n, dtype=bool)
        # warm-start memory: speed ratios, table coordinates of the discharge states, subcooling
        self.n_LS, self.n_HS = np.ones(n), np.ones(n)
        self.u2s, self.u4s, self.u4, self.d_SC = (np.full(n, np.nan) for _ in range(4))
        self.set_source(np.arange(n), self.T_so)

    # ---- source side: explicit in T_source,out ---------------------------------------------------
    def set_source(self, idx, T_so) -> None:
        """Evaporator duty and temperature, LS suction state for the rows idx at T_source,out [K]."""
        par, tab = self.par, self.tab
        self.T_so[idx] = T_so
        C = self.C_s[idx]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            self.Q_s[idx] = C * (self.T_si[idx] - T_so)
            T_e = evaporator_T_e(self.T_si[idx], T_so, par.UA_eva, C)
        self.T_e[idx] = T_e
        p_e, _, h_g, _, _ = tab.sat(T_e)
        h1, s1, rho1 = tab.vapour(T_e, np.full(len(T_e), par.superheat))
        self.p_e[idx], self.h_g_e[idx] = p_e, h_g
        self.h1[idx], self.s1[idx], self.rho1[idx] = h1, s1, rho1
        self.src_ok[idx] = np.isfinite(p_e) & np.isfinite(h1) & np.isfinite(rho1)

    def ls_speed(self, idx, T_m, sat_m=None):
        """LS speed ratio [-] (and the saturation state at T_m) for the rows idx: the LS side alone,
        which T_source,out and T_m fix."""
        p_m, h_f_m = (sat_m[0], sat_m[1]) if sat_m is not None else self.tab.sat(T_m)[:2]
        m_LS = self.Q_s[idx] / (self.h1[idx] - h_f_m)
        pi = p_m / self.p_e[idx]
        n_LS, ev = self.ls.speed_for_flow_v(m_LS, self.rho1[idx], pi, self.n_LS[idx])
        return n_LS, ev, m_LS, pi

    # ---- intermediate side: fixed by T_m ----------------------------------------------------------
    def m_side(self, idx, T_m) -> dict:
        """Saturation at T_m and the LS stage for the rows idx (``_Point.ls_side``)."""
        tab, ls = self.tab, self.ls
        sat = tab.sat(T_m)
        p_m, h_f_m, h_g_m, s_g_m, rho_g_m = sat
        with np.errstate(divide="ignore", invalid="ignore"):
            n_LS, ev_LS, m_LS, pi = self.ls_speed(idx, T_m, sat)
            eta = ls.eta_is_v(pi, n_LS)
        err = np.where(np.isfinite(p_m) & np.isfinite(n_LS), E_OK, E_FALLBACK)
        err = np.where((err == E_OK) & ~((eta > 0.05) & (eta <= 1.0)), E_ETA_LS, err)
        _, h2s, rho2s, u2s = tab.vapour_from("s", T_m, self.s1[idx], self.u2s[idx])
        err = np.where((err == E_OK) & ~np.isfinite(h2s), E_FALLBACK, err)
        h1 = self.h1[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            h2 = h1 + (h2s - h1) / eta
        good = err == E_OK
        self.n_LS[idx[good]], self.u2s[idx[good]] = n_LS[good], u2s[good]
        return dict(T_m=T_m, p_m=p_m, h_f_m=h_f_m, h_g_m=h_g_m, s_g_m=s_g_m, rho_g_m=rho_g_m,
                    m_LS=m_LS, n_LS=n_LS, ev_LS=ev_LS, eta_LS=eta, pi_LS=pi, h2s=h2s, h2=h2,
                    err=err)

    # ---- the flowsheet at (T_m, T_c) --------------------------------------------------------------
    def evaluate(self, idx, T_m, T_c, ms: dict | None = None, full: bool = False) -> dict:
        """Condenser-zone residual r [-] (relative to Q_source) and HS speed ratio n_HS [-] at
        (T_m, T_c) [K] for the rows idx, with ``err`` (E_*) where the scalar evaluation raises.
        ``ms``: ``m_side(idx, T_m)`` when T_m is the same as there. ``full``: every state."""
        if ms is None:
            ms = self.m_side(idx, T_m)
        tab, hs = self.tab, self.hs
        T_e = self.T_e[idx]
        err = np.where((T_e < T_m) & (T_m < T_c), E_OK, E_ORDER)
        p_c, h_f_c, h_g_c, _, _ = tab.sat(T_c)
        why = np.zeros(len(idx), dtype=np.int8)          # which check sent a row to the scalar path
        why = np.where((err == E_OK) & ~np.isfinite(p_c), 1, why)
        err = np.where((err == E_OK) & ~np.isfinite(p_c), E_FALLBACK, err)
        why = np.where((err == E_OK) & (ms["err"] == E_FALLBACK), 2, why)
        err = np.where(err == E_OK, ms["err"], err)
        T_ki = self.T_ki[idx]
        dT = T_c - T_ki
        err = np.where((err == E_OK) & ~(dT > 0.0), E_SINK, err)
        h_g_m, h_f_m = ms["h_g_m"], ms["h_f_m"]
        C_w = self.C_w[idx]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            num = ms["m_LS"] * (ms["h2"] - h_f_m)
            m, h_SC, d_SC, sc_ok = self._subcooler(idx, T_c, dT, num, h_g_m, h_f_c, C_w, err == E_OK)
            why = np.where((err == E_OK) & ~sc_ok, 3, why)
            err = np.where((err == E_OK) & ~sc_ok, E_FALLBACK, err)
            Q_SC = m * (h_f_c - h_SC)
            pi_HS = p_c / ms["p_m"]
            n_HS, ev_HS = hs.speed_for_flow_v(m, ms["rho_g_m"], pi_HS, self.n_HS[idx])
            why = np.where((err == E_OK) & ~np.isfinite(n_HS), 4, why)
            err = np.where((err == E_OK) & ~np.isfinite(n_HS), E_FALLBACK, err)
            eta_HS = hs.eta_is_v(pi_HS, n_HS)
            err = np.where((err == E_OK) & ~((eta_HS > 0.05) & (eta_HS <= 1.0)), E_ETA_HS, err)
            th4s, h4s, rho4s, u4s = tab.vapour_from("s", T_c, ms["s_g_m"], self.u4s[idx])
            h4 = h_g_m + (h4s - h_g_m) / eta_HS
            u0 = np.where(np.isfinite(self.u4[idx]), self.u4[idx], u4s)
            th4, _, rho4, u4 = tab.vapour_from("h", T_c, h4, u0)
            why = np.where((err == E_OK) & ~(np.isfinite(th4) & np.isfinite(th4s)), 5, why)
            err = np.where((err == E_OK) & ~(np.isfinite(th4) & np.isfinite(th4s)), E_FALLBACK, err)
            T4 = T_c + th4
            T_w1 = T_ki + Q_SC / C_w
            Q_con = self.eps_con[idx] * C_w * (T_c - T_w1)
            T_w2 = T_w1 + Q_con / C_w
            cp_v = (h4 - h_g_c) / th4
            eps_D, C_min_D = counterflow_eps_v(m * cp_v, C_w, self.UA_DSH)
            Q_DSH = eps_D * C_min_D * (T4 - T_w2)
            Q_DSH_max = m * (h4 - h_g_c)
            dsh_condensing = Q_DSH > Q_DSH_max
            Q_DSH = np.where(dsh_condensing, Q_DSH_max, Q_DSH)
            h_DSH = h4 - Q_DSH / m
            r = (Q_con - m * (h_DSH - h_f_c)) / self.Q_s[idx]
        why = np.where((err == E_OK) & ~np.isfinite(r), 6, why)
        err = np.where((err == E_OK) & ~np.isfinite(r), E_FALLBACK, err)
        good = err == E_OK
        g = idx[good]
        self.n_HS[g], self.u4s[g], self.u4[g], self.d_SC[g] = n_HS[good], u4s[good], u4[good], d_SC[good]
        out = dict(r=r, n_HS=n_HS, err=err, eta_HS=eta_HS, pi_HS=pi_HS, why=why)
        if full:
            out.update(ms)
            out.update(err=err, T_c=T_c, p_c=p_c, h_f_c=h_f_c, h_g_c=h_g_c, m_HS=m, h_SC=h_SC,
                       T_SC=T_c - d_SC, Q_SC=Q_SC, ev_HS=ev_HS, h4s=h4s, h4=h4, T4=T4, rho4=rho4,
                       T_w1=T_w1, T_w2=T_w2, Q_con=Q_con, Q_DSH=Q_DSH, cp_v=cp_v, h_DSH=h_DSH,
                       dsh_condensing=dsh_condensing)
        return out

    def _subcooler(self, idx, T_c, dT, num, h_g_m, h_f_c, C_w, todo):
        """(m_HS [kg/s], h_SC [J/kg], subcooling d [K], ok) of the subcooler and the intercooler:
        Newton on d (module docstring), warm-started from the row's last subcooling."""
        tab, UA = self.tab, self.UA_SC
        d = self.d_SC[idx]
        cold = ~((d > 0.0) & (d < dT))
        if cold.any():
            # liquid capacity at saturation and the flow without subcooling: eps-NTU gives d
            _, cp0 = tab.liquid(T_c, np.zeros(len(T_c)), deriv=True)
            C0 = num / (h_g_m - h_f_c) * cp0
            eps, C_min = counterflow_eps_v(C0, C_w, UA)
            d = np.where(cold, eps * C_min * dT / C0, d)
        d = np.where(todo & (d > 0.0) & (d < dT), d, np.where(todo, 0.5 * dT, 1.0))
        ok = np.zeros(len(d), dtype=bool)
        for _ in range(SC_ITER):
            h, h_T = tab.liquid(T_c, d, deriv=True)
            h_d = -h_T                                   # dh/dd at p_c
            g = h_g_m - h
            m = num / g
            dq = h_f_c - h
            cp = dq / d
            C = m * cp
            eps, C_min = counterflow_eps_v(C, C_w, UA)
            Q_e = eps * C_min * dT
            C2 = C * (1.0 + 1e-7)
            eps2, C_min2 = counterflow_eps_v(C2, C_w, UA)
            dQ_dC = (eps2 * C_min2 * dT - Q_e) / (C2 - C)
            dm = m * h_d / g
            dC = dm * cp - m * (h_d + cp) / d
            R = m * dq - Q_e
            dR = dm * dq - m * h_d - dQ_dC * dC
            step = R / dR
            ok = np.abs(step) <= SC_TOL * d
            if np.all(ok | ~todo):
                break
            dn = d - step
            dn = np.where(dn <= 0.0, 0.5 * d, np.where(dn >= dT, 0.5 * (d + dT), dn))
            d = np.where(ok | ~todo, d, dn)
        ok &= todo & (d > 1e-6) & np.isfinite(m)
        return m, h, d, ok

    def warm_copy(self):
        """The warm-start memory (to restore after trial evaluations elsewhere)."""
        return tuple(a.copy() for a in (self.n_LS, self.n_HS, self.u2s, self.u4s, self.u4, self.d_SC))
