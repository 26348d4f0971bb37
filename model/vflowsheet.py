"""The flowsheet of ``model.cycle`` at trial saturation temperatures, for many rows at once.

``Flowsheet.evaluate(idx, T_m, T_c)`` is ``model.cycle._Point.evaluate`` for the rows ``idx``: the
same physics and the same order of checks, on numpy arrays, with the properties from
``model.cycletables`` and the compressors through their vectorised protocol (``eta_is_v``,
``eta_vol_v``, ``speed_for_flow_v``). Where the scalar evaluation raises, a row carries an error
code instead (``E_*``); the solver (``model.vsolve``) decides what the error means where it occurs,
as the scalar solver does. Rows the tables or the vectorised iterations cannot settle carry
``E_FALLBACK``: the scalar path solves them.

The inner problems are solved per row to round-off, so the residual is the scalar one to ~1e-9
relative and a secant iteration on it follows the scalar iteration's steps:

- the subcooler coupled with the open intercooler (``model.components.subcooler``: the HS flow and
  the SC outlet on the equation of state) as Newton on the subcooling d: with h = h(p_c, T_c - d),
  m = num/(h_g,m - h) and the liquid's secant heat capacity cp = (h_f,c - h)/d, the residual
  m*(h_f,c - h) - eps(m*cp)*C_min*(T_c - T_sink,in) vanishes exactly where the scalar fixed point
  in (m_HS, cp) converges; warm-started from the row's last subcooling, finished by a first-order
  update once the Newton step is below 1e-6 of d (the rest is second order: < 1e-11);
- the compressor speeds by their vectorised ``speed_for_flow_v``, warm-started;
- the isentropic discharge states and T4 from (p_c, h4) by direct lookups (``isen_raw``,
  ``tofh_raw``).

The hot path is written for few numpy calls (at a few hundred rows their fixed cost dominates):
one validity mask per evaluation, error codes only for rows that fail. SI units: K, Pa, J/kg, kg/s, W.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .analysis import speedkernel as _kernels
from .components import evaporator_T_e
from .cycletables import DH_MAX, DS_MAX, LIQ_D_MAX, T_RANGE, VAP_T_MAX, VAP_T_MIN, CycleTables
from .params import PlantParams

E_OK, E_ORDER, E_SINK, E_ETA_LS, E_ETA_HS, E_FALLBACK = 0, 1, 2, 3, 4, 9
FALLBACK_WHY = ("", "saturation outside the tables", "LS stage outside the tables or its curve",
                "subcooler iteration", "HS compressor curve", "discharge state outside the tables",
                "non-finite residual")         # why an evaluation needs the scalar path
CONVERGENCE = (E_ORDER, E_SINK)          # model.cycle raises ConvergenceError (no_convergence)
INFEASIBLE = (E_ETA_LS, E_ETA_HS)        # ... InfeasibleOperation (eta_out_of_range)
SC_ITER = 30
SC_FINISH = 1e-6                         # Newton step (relative) below which one update finishes


class MSide:
    """The intermediate side of rows at their T_m (``Flowsheet.m_side``) as one 2-D array, so that
    taking rows and joining requests are single operations: ``ms["p_m"]`` is a row of it."""
    KEYS = ("T_m", "p_m", "h_f_m", "h_g_m", "s_g_m", "rho_g_m", "m_LS", "n_LS", "ev_LS", "eta_LS",
            "pi_LS", "h2s", "h2", "num", "err")
    _AT = {k: i for i, k in enumerate(KEYS)}
    __slots__ = ("a",)

    def __init__(self, a: np.ndarray) -> None:
        self.a = a

    def __getitem__(self, key: str) -> np.ndarray:
        return self.a[self._AT[key]]

    def keys(self):
        return self.KEYS

    def take(self, pos) -> "MSide":
        return MSide(self.a[:, pos])

    @staticmethod
    def concat(parts) -> "MSide":
        return MSide(np.concatenate([p.a for p in parts], axis=1))


def speed_v(comp, m, rho_suc, pi, n0):
    """``comp.speed_for_flow_v`` with rows whose inputs are not finite (rows failing upstream) kept
    out of its iteration, NaN for them. The shipped compressors now do this themselves; the guard
    stays for a compressor class whose vectorised method does not."""
    ok = np.isfinite(m) & np.isfinite(rho_suc) & np.isfinite(pi)
    if ok.all():
        return comp.speed_for_flow_v(m, rho_suc, pi, n0)
    n, ev = comp.speed_for_flow_v(np.where(ok, m, 1.0), np.where(ok, rho_suc, 10.0), np.where(ok, pi, 2.0), n0)
    return np.where(ok, n, np.nan), np.where(ok, ev, np.nan)


def counterflow_eps_v(C_a, C_b, UA):
    """``model.components.counterflow_eps`` for arrays: (effectiveness, C_min)."""
    C_min = np.minimum(C_a, C_b)
    Cr = C_min / np.maximum(C_a, C_b)
    NTU = UA / C_min
    x = np.exp(NTU * (Cr - 1.0))
    eps = (1.0 - x) / (1.0 - Cr * x)
    near = np.abs(1.0 - Cr) < 1e-9
    if near.any():
        eps = np.where(near, NTU / (1.0 + NTU), eps)
    return eps, C_min


class Flowsheet:
    """Row constants, warm-start memory and the flowsheet evaluation for N rows.

    T_si, T_so, T_ki : source in, source out, sink in [K]; V_s, V_k : source, sink flow [m^3/s].
    comp_LS, comp_HS : objects with the vectorised compressor protocol. Expects numpy's floating-
    point warnings off (``np.errstate(all="ignore")``) around its use: failed rows carry NaN.
    R_th_f : per-row evaporator fouling resistance [K/W] in place of ``params.R_th_f`` (None: the
    params'); cond : per-row factor on CF_DSH, CF_con and CF_SC (``model.analysis.chain.
    scale_condenser``; None: 1). The conductances are computed as ``params.replace(...)`` would give
    them, to the bit.
    """

    def __init__(self, params: PlantParams, tab: CycleTables, comp_LS, comp_HS,
                 T_si, T_so, T_ki, V_s, V_k, R_th_f=None, cond=None, deltas=None, group=None,
                 cf=None, cf_dp=None) -> None:
        self.par, self.tab, self.ls, self.hs = params, tab, comp_LS, comp_HS
        n = len(T_si)
        self.n = n
        # per row: which of a stacked compressor's members answers it (``model.lockstep``)
        self.group = np.zeros(n, dtype=np.intp) if group is None else np.asarray(group, dtype=np.intp)
        self.T_si, self.T_ki, self.V_s, self.V_k = T_si, T_ki, V_s, V_k
        self.R_th_f, self.cond = R_th_f, cond
        # per-row differences to the learned curves (uncertainty draws): {DELTA_KEY: (n, 6) array}
        self.deltas = {k: np.asarray(v, dtype=float) for k, v in (deltas or {}).items() if v is not None}
        rc = params.cp_w * params.rho_w
        self.C_s = rc * V_s
        self.C_w = rc * V_k
        if R_th_f is None:
            self.UA_eva = np.full(n, params.UA_eva)
        else:
            self.UA_eva = 1.0 / (1.0 / params.UA_eva_clean + np.asarray(R_th_f, dtype=float))
        k = np.ones(n) if cond is None else np.asarray(cond, dtype=float)
        # cf: per row (CF_DSH, CF_con, CF_SC) in place of params' times cond (rows of several calls)
        self.cf = None if cf is None else np.asarray(cf, dtype=float)
        CF = ((params.CF_DSH * k), (params.CF_con * k), (params.CF_SC * k)) if cf is None else self.cf
        self.UA_DSH = CF[0] * params.U_DSH * params.A_DSH
        self.UA_con = CF[1] * params.U_con * params.A_con
        self.UA_SC = CF[2] * params.U_SC * params.A_SC
        self.cf_dp = np.full(n, params.CF_dp_f) if cf_dp is None else np.asarray(cf_dp, dtype=float)
        with np.errstate(all="ignore"):
            self.eps_con = 1.0 - np.exp(-self.UA_con / self.C_w)
        self.T_so = np.array(T_so, dtype=float)
        self.Q_s, self.T_e, self.p_e = np.zeros(n), np.zeros(n), np.zeros(n)
        self.h_g_e, self.h1, self.s1, self.rho1 = (np.zeros(n) for _ in range(4))
        self.src_ok = np.zeros(n, dtype=bool)
        # warm-start memory: speed ratios, the HS's swept-flow target, subcooling and its lift T_c - T_sink,in
        self.n_LS, self.n_HS, self.d_SC = np.ones(n), np.ones(n), np.full(n, np.nan)
        self.phi_HS, self.dT_SC = np.full(n, np.nan), np.full(n, np.nan)
        with np.errstate(all="ignore"):
            self.set_source(np.arange(n), self.T_so)

    # ---- source side: explicit in T_source,out ---------------------------------------------------
    def source(self, idx, T_so) -> tuple:
        """(Q_source [W], T_e [K], p_e [Pa], h_g,e, h1 [J/kg], s1 [J/kg/K], rho1 [kg/m^3], ok) of the
        rows idx at T_source,out T_so [K]: the evaporator and the LS suction state."""
        par, tab = self.par, self.tab
        C = self.C_s[idx]
        Q = C * (self.T_si[idx] - T_so)
        T_e = evaporator_T_e(self.T_si[idx], T_so, self.UA_eva[idx], C)
        p_e, _, h_g, _, _ = tab.sat(T_e)
        h1, s1, rho1 = tab.vapour(T_e, np.full(len(T_e), par.superheat))
        ok = np.isfinite(p_e) & np.isfinite(h1) & np.isfinite(rho1) & (T_e <= VAP_T_MAX)
        return Q, T_e, p_e, h_g, h1, s1, rho1, ok

    def set_source(self, idx, T_so) -> None:
        """Evaporator duty and temperature, LS suction state for the rows idx at T_source,out [K]."""
        self.T_so[idx] = T_so
        (self.Q_s[idx], self.T_e[idx], self.p_e[idx], self.h_g_e[idx], self.h1[idx], self.s1[idx],
         self.rho1[idx], self.src_ok[idx]) = self.source(idx, T_so)

    ROW_ARRAYS = ("T_si", "T_ki", "V_s", "V_k", "C_s", "C_w", "UA_eva", "UA_DSH", "UA_con", "UA_SC", "eps_con",
                  "T_so", "Q_s", "T_e", "p_e", "h_g_e", "h1", "s1", "rho1", "src_ok", "n_LS", "n_HS", "d_SC",
                  "phi_HS", "dT_SC", "group", "cf_dp")

    def append(self, sel) -> np.ndarray:
        """Append copies of the rows ``sel`` (their inputs, parameters, source state and memory);
        returns the new rows' indices."""
        sel = np.asarray(sel, dtype=np.intp)
        for name in self.ROW_ARRAYS:
            a = getattr(self, name)
            setattr(self, name, np.concatenate([a, a[sel]]))
        for name in ("R_th_f", "cond"):
            a = getattr(self, name)
            if a is not None:
                a = np.asarray(a, dtype=float)
                setattr(self, name, np.concatenate([a, a[sel]]))
        self.deltas = {k: np.concatenate([a, a[sel]]) for k, a in self.deltas.items()}
        if self.cf is not None:
            self.cf = np.concatenate([self.cf, self.cf[:, sel]], axis=1)
        new = self.n + np.arange(len(sel))
        self.n += len(sel)
        return new

    def copy(self, sel) -> "Flowsheet":
        """A flowsheet of the rows ``sel`` (a row may appear several times) at their present
        T_source,out, with their parameters; fresh warm-start memory."""
        pick = lambda a: None if a is None else np.asarray(a, dtype=float)[sel]   # noqa: E731
        return Flowsheet(self.par, self.tab, self.ls, self.hs, self.T_si[sel], self.T_so[sel],
                         self.T_ki[sel], self.V_s[sel], self.V_k[sel], pick(self.R_th_f), pick(self.cond),
                         {k: a[sel] for k, a in self.deltas.items()}, self.group[sel],
                         None if self.cf is None else self.cf[:, sel], self.cf_dp[sel])

    def comp(self, stage: str, idx):
        """The stage's compressor for the rows idx: with per-row curve differences (``deltas``) a
        ``LearnedCompressor`` whose ``delta_is``/``delta_vol`` hold those rows' coefficients (a
        transient object for one vectorised call); else the flowsheet's own."""
        base = self.ls if stage == "LS" else self.hs
        if hasattr(base, "view"):           # a stage's compressors of several windows (stacked)
            d = {c: (tuple(self.deltas[f"{stage}_{c}"][idx].T) if f"{stage}_{c}" in self.deltas else None)
                 for c in ("is", "vol")}
            return base.view(self.group[idx], d["is"], d["vol"])
        if not self.deltas:
            return base
        kw = {}
        for curve in ("is", "vol"):
            a = self.deltas.get(f"{stage}_{curve}")
            if a is not None:
                kw[f"delta_{curve}"] = tuple(a[idx].T)
        return dataclasses.replace(base, **kw) if kw else base

    def ls_speed_at(self, idx, T_so, T_m) -> np.ndarray:
        """The LS speed ratio [-] of the rows idx at T_source,out T_so and T_m [K] (the LS side alone;
        the rows' stored state is left as it is, so a row may appear several times)."""
        Q, _, p_e, _, h1, _, rho1, _ = self.source(idx, T_so)
        p_m, h_f_m = self.tab.sat(T_m)[:2]
        return speed_v(self.comp("LS", idx), Q / (h1 - h_f_m), rho1, p_m / p_e, self.n_LS[idx])[0]

    def ls_speed(self, idx, T_m, sat_m=None, comp=None):
        """LS speed ratio [-], eta_vol, m_LS [kg/s] and pressure ratio for the rows idx: the LS side
        alone, which T_source,out and T_m [K] fix (``sat_m``: (p_m, h_f,m) when known; ``comp``:
        ``self.comp("LS", idx)`` when the caller has it)."""
        p_m, h_f_m = (sat_m[0], sat_m[1]) if sat_m is not None else self.tab.sat(T_m)[:2]
        m_LS = self.Q_s[idx] / (self.h1[idx] - h_f_m)
        pi = p_m / self.p_e[idx]
        n_LS, ev = speed_v(self.comp("LS", idx) if comp is None else comp, m_LS, self.rho1[idx], pi,
                           self.n_LS[idx])
        return n_LS, ev, m_LS, pi

    # ---- intermediate side: fixed by T_m ----------------------------------------------------------
    def m_side(self, idx, T_m) -> MSide:
        """Saturation at T_m [K] and the LS stage for the rows idx (``_Point.ls_side``)."""
        tab = self.tab
        inside = (T_m >= VAP_T_MIN) & (T_m <= VAP_T_MAX)
        Tq = np.where(inside, T_m, VAP_T_MIN)
        p_m, h_f_m, h_g_m, s_g_m, rho_g_m = tab.sat_raw(Tq)
        ls = self.comp("LS", idx)           # (one for both: a stacked view or a per-row copy)
        n_LS, ev_LS, m_LS, pi = self.ls_speed(idx, Tq, (p_m, h_f_m), ls)
        eta = ls.eta_is_v(pi, n_LS)
        ds = self.s1[idx] - s_g_m
        h2s = tab.isen_raw(Tq, ds)
        h1 = self.h1[idx]
        h2 = h1 + (h2s - h1) / eta
        ok = inside & (n_LS == n_LS) & (ds >= 0.0) & (ds <= DS_MAX)
        eta_ok = (eta > 0.05) & (eta <= 1.0)
        err = np.where(ok, np.where(eta_ok, E_OK, E_ETA_LS), E_FALLBACK)
        good = ok & eta_ok
        if good.all():
            self.n_LS[idx] = n_LS
        else:
            self.n_LS[idx[good]] = n_LS[good]
        return MSide(np.stack([T_m, p_m, h_f_m, h_g_m, s_g_m, rho_g_m, m_LS, n_LS, ev_LS, eta, pi, h2s,
                               h2, m_LS * (h2 - h_f_m), err]))

    # ---- the flowsheet at (T_m, T_c) --------------------------------------------------------------
    def evaluate(self, idx, T_m, T_c, ms: MSide | None = None, full: bool = False) -> dict:
        """Condenser-zone residual r [-] (relative to Q_source) and HS speed ratio n_HS [-] at
        (T_m, T_c) [K] for the rows idx, with ``err`` (E_*) where the scalar evaluation raises.
        ``ms``: ``m_side(idx, T_m)`` when T_m is the same as there (returned as "ms" either way).
        ``full``: every state."""
        if ms is None:
            ms = self.m_side(idx, T_m)
        tab, hs = self.tab, self.comp("HS", idx)
        inside = (T_c >= T_RANGE[0]) & (T_c <= T_RANGE[1])
        Tq = np.where(inside, T_c, T_RANGE[0])
        p_c, h_f_c, h_g_c, s_g_c, _ = tab.sat_raw(Tq)
        T_ki = self.T_ki[idx]
        dT = T_c - T_ki
        h_g_m = ms["h_g_m"]
        C_w = self.C_w[idx]
        m, h_SC, d_SC, sc_ok = self._subcooler(idx, Tq, dT, ms["num"], h_g_m, h_f_c, C_w)
        Q_SC = m * (h_f_c - h_SC)
        pi_HS = p_c / ms["p_m"]
        phi = m / ms["rho_g_m"]                      # the swept flow the HS must move, times V_s
        n0 = self.n_HS[idx] * (phi / self.phi_HS[idx])   # speed about proportional to it
        n_HS, ev_HS = speed_v(hs, m, ms["rho_g_m"], pi_HS, np.where(n0 == n0, n0, self.n_HS[idx]))
        eta_HS = hs.eta_is_v(pi_HS, n_HS)
        ds = ms["s_g_m"] - s_g_c
        h4s = tab.isen_raw(Tq, ds)
        h4 = h_g_m + (h4s - h_g_m) / eta_HS
        dh = h4 - h_g_c
        th4 = tab.tofh_raw(Tq, dh)
        T4 = T_c + th4
        T_w1 = T_ki + Q_SC / C_w
        Q_con = self.eps_con[idx] * C_w * (T_c - T_w1)
        T_w2 = T_w1 + Q_con / C_w
        cp_v = (h4 - h_g_c) / th4
        eps_D, C_min_D = counterflow_eps_v(m * cp_v, C_w, self.UA_DSH[idx])
        Q_DSH = eps_D * C_min_D * (T4 - T_w2)
        Q_DSH_max = m * dh
        dsh_condensing = Q_DSH > Q_DSH_max
        Q_DSH = np.where(dsh_condensing, Q_DSH_max, Q_DSH)
        h_DSH = h4 - Q_DSH / m
        r = (Q_con - m * (h_DSH - h_f_c)) / self.Q_s[idx]
        eta_ok = (eta_HS > 0.05) & (eta_HS <= 1.0)
        tab_ok = (ds >= 0.0) & (ds <= DS_MAX) & (dh >= 0.0) & (dh <= DH_MAX)
        good = ((self.T_e[idx] < T_m) & (T_m < T_c) & inside & (ms["err"] == E_OK) & (dT > 0.0) & sc_ok
                & (n_HS == n_HS) & eta_ok & tab_ok & (r == r))
        if good.all():
            err = np.zeros(len(idx), dtype=np.int8)
            why = err
            self.n_HS[idx], self.d_SC[idx], self.phi_HS[idx], self.dT_SC[idx] = n_HS, d_SC, phi, dT
        else:
            err, why = self._errors(idx, T_m, T_c, inside, ms["err"].astype(np.int8), dT, sc_ok, n_HS,
                                    eta_ok, tab_ok, r)
            g = idx[good]
            self.n_HS[g], self.d_SC[g], self.phi_HS[g], self.dT_SC[g] = n_HS[good], d_SC[good], phi[good], dT[good]
        out = dict(r=r, n_HS=n_HS, err=err, eta_HS=eta_HS, pi_HS=pi_HS, why=why, ms=ms)
        if full:
            out.update({k: ms[k] for k in MSide.KEYS})
            out.update(err=err, T_c=T_c, p_c=p_c, h_f_c=h_f_c, h_g_c=h_g_c, m_HS=m, h_SC=h_SC,
                       T_SC=T_c - d_SC, Q_SC=Q_SC, ev_HS=ev_HS, h4s=h4s, h4=h4, T4=T4,
                       T_w1=T_w1, T_w2=T_w2, Q_con=Q_con, Q_DSH=Q_DSH, cp_v=cp_v, h_DSH=h_DSH,
                       dsh_condensing=dsh_condensing)
        return out

    def _errors(self, idx, T_m, T_c, inside, ms_err, dT, sc_ok, n_HS, eta_ok, tab_ok, r):
        """Error codes in the order the scalar evaluation checks, and why a row needs the scalar
        path (an index of FALLBACK_WHY)."""
        order = (self.T_e[idx] < T_m) & (T_m < T_c)
        checks = ((~order, E_ORDER, 0), (~inside, E_FALLBACK, 1), (ms_err == E_FALLBACK, E_FALLBACK, 2),
                  (ms_err == E_ETA_LS, E_ETA_LS, 0), (~(dT > 0.0), E_SINK, 0), (~sc_ok, E_FALLBACK, 3),
                  (n_HS != n_HS, E_FALLBACK, 4), (~eta_ok, E_ETA_HS, 0), (~tab_ok, E_FALLBACK, 5),
                  (r != r, E_FALLBACK, 6))
        err = np.zeros(len(idx), dtype=np.int8)
        why = np.zeros(len(idx), dtype=np.int8)
        for bad, code, w in reversed(checks):        # the first failing check wins
            err = np.where(bad, code, err)
            why = np.where(bad, w, why)
        return err, np.where(err == E_FALLBACK, why, 0).astype(np.int8)

    def _subcooler(self, idx, T_c, dT, num, h_g_m, h_f_c, C_w):
        """(m_HS [kg/s], h_SC [J/kg], subcooling d [K], ok) of the subcooler and the intercooler:
        Newton on d (module docstring), warm-started from the row's last subcooling."""
        tab, UA = self.tab, self.UA_SC[idx]
        row = tab.liq_row(T_c)
        d = self.d_SC[idx] * (dT / self.dT_SC[idx])    # the subcooling scales about with the lift
        cold = ~((d > 0.0) & (d < dT) & (d <= LIQ_D_MAX))
        if cold.any():
            # the liquid's capacity at saturation and the flow without subcooling: eps-NTU gives d
            _, cp0 = tab.liq_raw(row, np.zeros(len(d)))
            C0 = num / (h_g_m - h_f_c) * cp0
            eps, C_min = counterflow_eps_v(C0, C_w, UA)
            d = np.where(cold, eps * C_min * dT / C0, d)
            d = np.where((d > 0.0) & (d < dT) & (d <= LIQ_D_MAX), d, 0.5 * np.minimum(dT, LIQ_D_MAX))
            d = np.where(d == d, d, 1.0)
        d_hi = np.minimum(dT, LIQ_D_MAX)
        if _kernels._SC_PRE is not None and np.ndim(d) == 1 and np.shape(row[0]) == np.shape(d):
            converged, d, step, h, h_T = _kernels.subcooler(*tab.liq_kernel_args(row), d, num, h_g_m, h_f_c,
                                                            C_w, UA, dT, d_hi, SC_ITER, SC_FINISH)
            return (_sc_finish if converged else _sc_unfinished)(num, h_g_m, h, h_T, d, step, d_hi)
        k = len(d)
        C_w2, UA2 = np.concatenate([C_w, C_w]), np.concatenate([UA, UA])
        for _ in range(SC_ITER):
            h, h_T = tab.liq_raw(row, d)
            g = h_g_m - h
            m = num / g
            dq = h_f_c - h
            cp = dq / d
            C = m * cp
            # the capacity and its finite-difference step in one call (the same numbers as two)
            eps_b, C_min_b = counterflow_eps_v(np.concatenate([C, C * (1.0 + 1e-7)]), C_w2, UA2)
            eps, C_min, eps2, C_min2 = eps_b[:k], C_min_b[:k], eps_b[k:], C_min_b[k:]
            Q_e = eps * C_min * dT
            dQ_dC = (eps2 * C_min2 * dT - Q_e) / (C * 1e-7)
            dm = -m * h_T / g                                 # dh/dd = -h_T
            step = (m * dq - Q_e) / (dm * dq + m * h_T - dQ_dC * (dm * cp + m * (h_T - cp) / d))
            small = np.abs(step) <= SC_FINISH * d
            if small.all():
                return _sc_finish(num, h_g_m, h, h_T, d, step, d_hi)
            dn = d - step
            dn = np.where(dn == dn, dn, 0.5 * d)     # a row without a step (NaN upstream) keeps a
            #                                          valid table index (it fails: sc_ok False)
            d = np.where(small, d, np.where(dn <= 0.0, 0.5 * d, np.where(dn > d_hi, 0.5 * (d + d_hi), dn)))
            if not np.all(small | (step != step)):
                continue
            break
        return _sc_unfinished(num, h_g_m, h, h_T, d, step, d_hi)


def _sc_finish(num, h_g_m, h, h_T, d, step, d_hi):
    """``Flowsheet._subcooler``'s result when every row's Newton step is below SC_FINISH of d: the
    rest of Newton's convergence is second order, so a first-order update finishes it."""
    d_new = np.minimum(d - step, d_hi)       # d_hi = T_c - T_sink,in where eps is 1 to round-off
    h = h + h_T * (d - d_new)
    return num / (h_g_m - h), h, d_new, (d_new > 1e-6) & (d_new == d_new)


def _sc_unfinished(num, h_g_m, h, h_T, d, step, d_hi):
    """``Flowsheet._subcooler``'s result when the iteration stopped with rows not converged (no
    step, or SC_ITER steps): those rows keep d and fail (ok False); h, h_T and step are of the last
    step's start, d after its update."""
    small = np.abs(step) <= SC_FINISH * d
    d_new = np.where(small, np.minimum(d - step, d_hi), d)
    h = h + h_T * (d - d_new)
    return num / (h_g_m - h), h, d_new, small & (d_new > 1e-6)
