"""Warm starts of ``model.vcycle.solve_many``: every row from a nearby solved state.

A row's cold path (``model.vsolve``, ``model.vfloat``) follows the scalar solver step by step,
35-60 sequential evaluation rounds for the hardest rows, and a round costs its numpy calls whatever
its rows. From a nearby solution the root of the guessed branch is found directly: Newton on all
rows at once, the Jacobian by finite differences in the same batched evaluation (one step per
unknown), ~3 rounds; then the branch is checked the way the scalar solver decides it. A row's
problems (all in the same rounds):

- input point: the solution at the input's T_source,out in the branch of the guess's input point,
  "sp" (T_m at the set point, unknown T_c: condenser-zone residual r = 0) or an HS speed bound
  (unknowns T_m, T_c: r = 0 and n_HS at the bound);
- set-point test (input at an HS bound): T_c at the set point, where the scalar solver's branch
  test looks: the HS speed needed there must lie beyond the bound. Rows whose own guess had no
  solution (they borrow the nearest solved set point of the same operating point) run the cold
  path's exact branch test instead, whose failure is then their answer;
- floating point ("float" mode, the row floats): T_source,out with N_LS on its bound, T_c (and T_m
  at an HS bound); the scalar LS search's first trial is evaluated once (``model.vfloat.
  _first_trial``);
- the cold search at an HS bound: its start, the middle of the T_m interval, is evaluated once
  (the screen below).

A row's answer must be the cold path's, and the cold path can fail on its way where the root
exists (its outcome depends on its trial points). A row leaves the warm path when an evaluation of
its problems raises (``E_*``: compressor curve, tables, order of temperatures, SC iteration), a
step leaves the domain, a Newton step does not halve the residual (0.9 for a step cut to
STEP_MAX: the start is not near a root of this branch), a problem has not converged in
WARM_ROUNDS steps, or a check fails:

- "sp" input: n_HS at the root within [n_min, n_max] (widened by SPEED_TOL), the set point above
  1.001 p_e, T_c in the cold secant's range (above T_sink,in + 0.05 K and T_m + 0.05 K, at most
  T_c_max). An "sp" input needing an HS bound, or an HS-bound input whose set point holds,
  changes branch once and stays warm from the root at hand;
- HS-bound input: the set-point test beyond the bound; T_m in the cold path's interval (hs_max:
  T_m_sp .. T_c,sp - 0.1 K; hs_min: T_e + 0.05 K .. T_m_sp; set point at or below 1.001 p_e:
  hs_max in T_e + 0.05 K .. T_c,0 - 0.1 K); and the screen of the cold search's start T_m0: the
  evaluations there raise nothing, the condenser carries the duty at T_c_max there (else the cold
  search fails p_c_high on its way), the HS speed on the condensing curve there (linearised) lies
  on the far side of the bound from the root by more than HS_SCREEN and falls with T_m, steeply
  enough that a secant step from T_m0 lands short of the root or beyond it by less than
  HS_OVERSHOOT times its distance (where that curve flattens or turns, the cold search walks away
  and fails, or finds another root);
- "float" mode: N_LS at the input within its range (then the input point is the answer), or
  beyond it, and then the floating root inside the scalar search's interval on that side
  (T_sp < T_so <= T_in - 0.05 K at N_max), in a consistent branch (n_HS in range at "sp", T_m
  beyond the set point at a bound; the other branch is tried once), and no failing first trial
  where the scalar search makes one (from an "sp" input, beyond the root).

Rows that leave (and rows without any usable guess) take the cold path: up to SCALAR_COLD_MAX of
them the scalar solver (0.2-6 ms a row against 5-60 vector rounds of ~0.45 ms), more the vector
cold path, started as they leave. Tolerances are the scalar solver's (ENERGY_TOL, SPEED_TOL; the LS
bound to WARM_LS_TOL = LS_SPEED_TOL / 10, T_source,out within ~1e-7 K of the cold path's). The
screen is not a proof that the cold search succeeds: on the test grids (set points +-0.25..2 bar,
fouling steps, condenser factors, learned curves and draws, unrelated guesses; rows up to 1.8
times the LS stage's speed) no status differs from the cold path's (tests/test_vcycle.py states
the rule near limits). SI units.
"""
from __future__ import annotations

import numpy as np

from .cycle import ENERGY_TOL, LS_SPEED_TOL, OVERLOAD, SPEED_TOL
from .vflowsheet import E_OK, Flowsheet, MSide
from .vsolve import HS_MAX, HS_MIN, SP, Raised, TcSolver
from .vtasks import Eval, Spawn

WARM_ROUNDS = 8          # Newton steps of a problem before its row goes cold
MAX_ROUNDS = 400         # evaluation rounds of the warm path in all (a safety net: the Newton
#                          problems have WARM_ROUNDS, the cold branch test its own limits)
FD_STEP = 1e-3           # K, finite-difference step of every unknown
STEP_MAX = 2.0           # K, the largest Newton step of any unknown
IN, SPT, FLT = 1, 2, 3   # problem roles: input point, set-point test, floating point
PROGRESS = 0.5           # a full Newton step must reduce the scaled residual at least by this factor
PROGRESS_LIMITED = 0.9   # ... a step cut to STEP_MAX by this one
HS_SCREEN = 0.01         # HS speed ratio margin of the screen of the cold path's start at an HS bound
HS_OVERSHOOT = 3.0       # ... the largest overshoot of its first secant step, in its distance to the root
SCALAR_COLD_MAX = 4      # at most this many rows leaving the warm path go to the scalar solver
SPT_TOL = 1e-7           # condenser residual of the set-point test where its HS speed is clear of the
SPT_MARGIN = 1e-4        # bounds by this (speed ratio; its error there is ~1e-8)
WARM_LS_TOL = 0.1 * LS_SPEED_TOL   # the LS speed ratio on its bound (T_source,out to ~1e-7 K)
LAST_STEP = 1e-4         # K: a Newton step at most this long, from residuals below LAST_FN times
LAST_FN = 1e3            # the tolerances, is the last (the outputs are moved by it, linearised),
LAST_ERR = 1e-10         # ... or one after which the error left is below this [K]
# the evaluation outputs the assembly needs, kept per problem where it converges
ASSEMBLY_KEYS = ("err", "h2", "h_g_m", "m_LS", "m_HS", "h4", "Q_SC", "Q_con", "Q_DSH", "T_w1", "T_w2",
                 "T_SC", "T4", "cp_v", "n_LS", "n_HS", "p_m", "p_c", "eta_LS", "eta_HS", "ev_LS",
                 "ev_HS", "h_SC", "h_f_c")
INPUT_KEYS = ("T_si", "T_so_in", "T_ki", "V_s", "V_k")     # a row's operating point [K, m^3/s]
STATE_KEYS = ("branch", "T_m", "T_c", "T_so", "ls_limit", "in_branch", "in_T_m", "in_T_c", "T_c_sp",
              "n_LS", "n_HS", "d_SC", "dT_SC", "phi_HS") + INPUT_KEYS + ("T_m_sp",)


def empty_state(n: int) -> dict:
    """Per-row warm-start state (SI): the solution (branch -1 where none; ls_limit 1 at N_max, -1 at
    N_min), the input point's solution where the LS floated, T_c of the branch test at the set
    point, and the flowsheet's inner warm-start memory."""
    st = {k: np.full(n, np.nan) for k in STATE_KEYS}
    for k in ("branch", "in_branch", "ls_limit"):
        st[k] = np.full(n, -1 if k != "ls_limit" else 0, dtype=np.int8)
    return st


def take_state(st: dict, gi) -> dict:
    """The guess rows gi (-1: none) of a state."""
    gi = np.asarray(gi, dtype=np.intp)
    none = gi < 0
    at = np.where(none, 0, gi)
    out = {k: v[at] if len(v) else np.zeros(len(gi), v.dtype) for k, v in st.items()}
    out["branch"][none] = -1
    out["in_branch"][none] = -1
    return out


def usable(st: dict, ls_mode: str) -> np.ndarray:
    """Rows of a state that can start a row warm."""
    ok = (st["branch"] >= 0) & np.isfinite(st["T_c"]) & np.isfinite(st["T_m"])
    if ls_mode == "float":
        # a floating guess needs its input point; a non-floating one is its own input point
        ok &= (st["ls_limit"] == 0) | (st["in_branch"] >= 0)
    return ok


def borrow(st: dict, gi, need, inputs: dict, T_m_sp, ls_mode: str) -> np.ndarray:
    """``gi`` with the rows ``need`` (whose guess row has no usable solution) mapped to the usable
    guess row of the same operating point (the INPUT_KEYS equal) whose set point lies nearest,
    where there is one."""
    gi = np.array(gi, copy=True)
    need = np.flatnonzero(need)
    donors = np.flatnonzero(usable(st, ls_mode))
    if not len(need) or not len(donors):
        return gi
    D = np.stack([st[k][donors] for k in INPUT_KEYS], axis=1)
    N = np.stack([inputs[k][need] for k in INPUT_KEYS], axis=1)
    for a in range(0, len(need), 256):                       # (need x donors) at a time
        same = np.all(N[a:a + 256, None, :] == D[None, :, :], axis=2)
        dist = np.where(same, np.abs(st["T_m_sp"][donors][None, :] - T_m_sp[need[a:a + 256], None]), np.inf)
        j = np.argmin(dist, axis=1)
        has = np.isfinite(dist[np.arange(len(j)), j])
        gi[need[a:a + 256][has]] = donors[j[has]]
    return gi


class WarmPlan:
    """Which rows start warm, and the flowsheet rows their floating problems need beside their own:
    in "float" mode three copies of every warm row (``extra``: the rows copied, appended after the
    n rows): the floating point, its T_source,out step, the scalar search's first trial."""

    def __init__(self, n: int, cand, g: dict, ls_mode: str, borrowed=None) -> None:
        self.n = n
        self.rows = np.flatnonzero(cand & usable(g, ls_mode))
        self.borrowed = np.zeros(len(self.rows), bool) if borrowed is None else np.asarray(borrowed)[self.rows]
        w = len(self.rows)
        self.copies = ls_mode == "float"
        self.extra = np.concatenate([self.rows] * 3) if self.copies else np.zeros(0, dtype=np.intp)
        self.f_base = n + np.arange(w)
        self.f_fd = n + w + np.arange(w)
        self.f_x0 = n + 2 * w + np.arange(w)


_PROBLEM_ARRAYS = ("own", "role", "src", "fso", "br", "has_m", "has_so", "T_m_fix", "bound", "n_b", "so_lo",
                   "so_hi", "conv", "dead", "age", "fnorm", "full_step", "ms_ok", "n_HS", "n_LS", "s_ev", "s_j",
                   "last_dx")
_FLOATS = ("T_m_fix", "bound", "n_b", "so_lo", "so_hi", "fnorm", "n_HS", "n_LS", "last_dx")
_BOOLS = ("has_m", "has_so", "conv", "dead", "full_step", "ms_ok")


class WarmSolve:
    """The warm path for the rows of a ``WarmPlan`` on the flowsheet ``fs`` (whose rows n.. are the
    plan's copies). ``task(go_cold)`` runs it (a ``model.vtasks`` task); ``go_cold(rows)`` gives the
    cold task of rows that leave it. ``ok`` marks the rows (positions in the plan's rows) settled
    here; ``results`` and ``fill_state`` give their answers.

    A row's problems (module docstring) are rows of the problem arrays; a row points at its input
    point (``p_in``), set-point test (``p_spt``) and floating point (``p_flt``) problems. A row whose
    answer changes branch against its guess within what the checks see (an "sp" input whose HS speed
    needs a bound, an HS-bound input whose set point turns out to hold, a floating point of the other
    branch) continues warm with a new problem from the root at hand, once; a row that starts to
    float gets its floating problem from the scalar search's first trial."""

    def __init__(self, fs: Flowsheet, plan: WarmPlan, g: dict, T_m_sp, p_sp, T_c_max: float,
                 ls_mode: str) -> None:
        self.fs, self.plan, self.ls_mode, self.T_c_max = fs, plan, ls_mode, T_c_max
        hs, ls = fs.par.comp_HS, fs.par.comp_LS
        self.n_hs = (hs.N_min / hs.N_nom, hs.N_max / hs.N_nom)
        self.n_ls = (ls.N_min / ls.N_nom, ls.N_max / ls.N_nom)
        rows = plan.rows
        w = len(rows)
        self.w, self.rows = w, rows
        self.T_m_sp = T_m_sp[rows]
        self.below = p_sp[rows] <= fs.p_e[rows] * 1.001
        self.T_sp, self.T_in = fs.T_so[rows].copy(), fs.T_si[rows]
        # ---- per row
        self.p_in, self.p_spt, self.p_flt = (np.full(w, -1) for _ in range(3))
        self.lim = np.zeros(w, dtype=np.int8)       # floating problem's bound: +1 N_max, -1 N_min
        self.x0 = np.full(w, np.nan)                # the scalar LS search's first trial [K]
        self.x0_st = np.zeros(w, dtype=np.int8)     # 1 its check is to be evaluated, 2 evaluated
        self.x0_risk = np.zeros(w, bool)
        self.hs_st = np.zeros(w, dtype=np.int8)     # the HS-bound screen: 1 to be evaluated, 2 evaluated
        self.hs_risk = np.zeros(w, bool)
        self.hs_at = np.full((w, 2), np.nan)        # its point (T_m0, T_c0)
        self.hs_n = np.full(w, np.nan)              # n_HS on the condensing curve at T_m0 (linearised)
        self.hs_s = np.full(w, np.nan)              # ... its slope dn_HS/dT_m along the curve [1/K]
        self.msc = np.zeros((len(MSide.KEYS), 0))   # the intermediate side of problems that keep it
        self.sw_in, self.sw_fl = np.zeros(w, bool), np.zeros(w, bool)   # branch switched once
        self.decided, self.ok = np.zeros(w, bool), np.zeros(w, bool)
        self.touched = np.zeros(w, bool)            # rows with news since they were last looked at
        self.leave = np.zeros(w, bool)              # rows that leave the warm path: to the vector cold
        self.gone = np.zeros(w, bool)               # path (gone), or to the scalar one (scalar)
        self.scalar = np.zeros(w, bool)
        self.vector = False
        self.bt_abort = False
        self.handed: list = []                      # (rows, codes, messages) for the cold float path
        self.answer = np.full(w, -1)
        self.rounds = 0
        # ---- problems: arrays with room for more (slots beyond ``self.n_prob`` are dead)
        self.n_prob = 0
        self._grow(4 * w + 16)
        self.evs: list = []                        # the evaluations where problems converged
        known = g["in_branch"][rows] >= 0
        inb = np.where(known, g["in_branch"][rows], g["branch"][rows])
        in_T_m = np.where(known, g["in_T_m"][rows], g["T_m"][rows])
        in_T_c = np.where(known, g["in_T_c"][rows], g["T_c"][rows])
        pos = np.arange(w)
        # borrowed rows (their own guess had no solution) take the cold path's exact branch test
        self.bt_st = np.where(plan.borrowed & ~self.below, 1, 0).astype(np.int8)
        self.bt_n, self.bt_T_c = np.full(w, np.nan), np.full(w, np.nan)
        self.bt_cls = np.zeros(w, dtype=np.int8)
        self.bt_code, self.bt_msg = np.full(w, "", dtype=object), np.full(w, "", dtype=object)
        self.t_n, self.t_T_c = np.full(w, np.nan), np.full(w, np.nan)     # the set-point test's outcome
        self.failed = np.zeros(w, bool)            # rows whose (exact) cold branch test failed
        self.fail_code, self.fail_msg = np.full(w, "", dtype=object), np.full(w, "", dtype=object)
        # the input points, and the set-point problems of those at an HS bound
        spt = np.flatnonzero((inb != SP) & ~self.below & (self.bt_st == 0))
        T_c_sp = g["T_c_sp"][rows[spt]]
        T_c_sp = np.where(np.isfinite(T_c_sp), T_c_sp, in_T_c[spt])
        both = np.concatenate([pos, spt])
        p = self._add(both, np.concatenate([np.full(w, IN), np.full(len(spt), SPT)]), rows[both],
                      np.concatenate([inb, np.full(len(spt), SP)]), self.T_sp[both],
                      np.concatenate([np.where(inb != SP, in_T_m, self.T_m_sp), self.T_m_sp[spt]]),
                      np.concatenate([in_T_c, T_c_sp]))
        self.p_in[:], self.p_spt[spt] = p[:w], p[w:]
        hsp = np.flatnonzero(inb != SP)
        est = in_T_c[hsp].copy()
        est[np.isin(hsp, spt)] = T_c_sp
        self._hs_screen(hsp, inb[hsp], est)
        if ls_mode == "float":
            # floating guesses, and rows whose guess did not float but whose input point ("sp")
            # has its LS speed beyond a bound already: their floating problems start now, beside
            # the input points' (from the guess's floating point, or the scalar search's first trial)
            lim_g = g["ls_limit"][rows]
            cand = np.flatnonzero((lim_g != 0) | ((inb == SP) & ~self.below))
            if len(cand):
                n_in = fs.ls_speed(rows[cand], self.T_m_sp[cand])[0]     # at the input, T_m at the set point
                l_lo, l_hi = self.n_ls
                was = lim_g[cand] != 0
                take = was | (n_in > l_hi) | (n_in < l_lo)
                u, r = cand[take], rows[cand[take]]
                was, n_in = was[take], n_in[take]
                self.lim[u] = np.where(was, lim_g[u], np.where(n_in > l_hi, 1, -1))
                self._first_trial(u, n_in)
                fb = np.where(was, g["branch"][r], SP)
                self.p_flt[u] = self._add_float(u, fb, np.where(was, g["T_so"][r], self.x0[u]),
                                                np.where(fb != SP, g["T_m"][r], self.T_m_sp[u]),
                                                np.where(was, g["T_c"][r], in_T_c[u]))

    # ---------------------------------------------------------------------------------------------
    def _grow(self, cap: int) -> None:
        """Room for cap problems."""
        n = self.n_prob
        for name in _PROBLEM_ARRAYS:
            a = np.zeros(cap, dtype=float if name in _FLOATS else bool if name in _BOOLS else np.intp)
            if name == "dead":
                a[:] = True
            if n:
                a[:n] = getattr(self, name)[:n]
            setattr(self, name, a)
        X = np.zeros((cap, 3))
        msc = np.zeros((len(MSide.KEYS), cap))
        if n:
            X[:n], msc[:, :n] = self.X[:n], self.msc[:, :n]
        self.X, self.msc = X, msc

    def _add(self, own, role, src, br, T_so, T_m, T_c) -> np.ndarray:
        """Append problems (one per row position in own; role IN, SPT or FLT); returns their
        indices."""
        k = len(own)
        if self.n_prob + k > len(self.own):
            self._grow(2 * (self.n_prob + k))
        p = self.n_prob + np.arange(k)
        self.n_prob += k
        br = np.broadcast_to(np.asarray(br, dtype=np.int8), (k,))
        role = np.broadcast_to(np.asarray(role, dtype=np.intp), (k,))
        lim = self.lim[own]
        T_sp, T_in = self.T_sp[own], self.T_in[own]
        flt = role == FLT
        so_lo = np.where(flt, np.where(lim > 0, T_sp, np.maximum(T_sp - 15.0, self.fs.tab.T_triple + 5.0)), -np.inf)
        so_hi = np.where(flt, np.where(lim > 0, T_in - 0.05, T_sp), np.inf)
        self.own[p], self.role[p], self.src[p], self.br[p] = own, role, src, br
        self.fso[p] = np.where(flt, self.plan.f_fd[own] if self.plan.copies else -1, -1)
        self.has_m[p], self.has_so[p], self.T_m_fix[p] = br != SP, flt, self.T_m_sp[own]
        self.bound[p] = np.where(br == HS_MAX, self.n_hs[1], np.where(br == HS_MIN, self.n_hs[0], np.nan))
        self.n_b[p] = np.where(flt, np.where(lim > 0, self.n_ls[1], self.n_ls[0]), np.nan)
        self.so_lo[p], self.so_hi[p] = so_lo, so_hi
        self.conv[p], self.age[p], self.fnorm[p], self.full_step[p], self.ms_ok[p] = False, 0, np.inf, False, False
        self.s_ev[p] = -1
        self.last_dx[p] = np.inf
        X = self.X
        X[p, 0], X[p, 1], X[p, 2] = np.minimum(np.maximum(T_so, so_lo), so_hi), T_m, T_c
        # a start outside the domain fails at once
        bad = ~(np.isfinite(X[p, 0]) & np.isfinite(X[p, 1]) & (X[p, 2] <= self.T_c_max) & (X[p, 1] < X[p, 2] - 0.05))
        self.dead[p] = bad
        self.touched[own[bad]] = True
        return p

    def _add_float(self, own, br, T_so, T_m, T_c) -> np.ndarray:
        """Floating-point problems for the rows own (their ``lim`` set). With T_m at the set point
        N_LS depends on T_source,out alone: one Newton step on the LS side (outside the rounds)
        starts them close to the root in T_source,out."""
        br = np.broadcast_to(np.asarray(br, dtype=np.int8), (len(own),))
        T_so = np.array(T_so, dtype=float)
        j = np.flatnonzero(br == SP)
        if len(j):
            fs, h, k = self.fs, FD_STEP, len(j)
            u = own[j]
            lim, T_sp, T_in = self.lim[u], self.T_sp[u], self.T_in[u]
            lo = np.where(lim > 0, T_sp, np.maximum(T_sp - 15.0, fs.tab.T_triple + 5.0))
            hi = np.where(lim > 0, T_in - 0.05, T_sp)
            x = np.minimum(np.maximum(T_so[j], lo), hi)
            src, T_mj = self.plan.f_base[u], self.T_m_sp[u]
            f2 = fs.ls_speed_at(np.concatenate([src, src]), np.concatenate([x, x + h]), np.concatenate([T_mj, T_mj]))
            f = f2[:k] - np.where(lim > 0, self.n_ls[1], self.n_ls[0])
            step = np.clip(-f * h / (f2[k:] - f2[:k]), -STEP_MAX, STEP_MAX)
            T_so[j] = np.where(np.isfinite(step), np.minimum(np.maximum(x + step, lo), hi), x)
        return self._add(own, FLT, self.plan.f_base[own], br, T_so, T_m, T_c)

    def _float_switch(self, u, q, nHS) -> None:
        """The floating points q of the rows u lie in the branch that is not theirs: the other one,
        once, from the point at hand (as the cold path's second pass)."""
        X = self.X
        br = self.br[q]
        nb = np.where(br != SP, SP, np.where(nHS > self.n_hs[1], HS_MAX, HS_MIN)).astype(np.int8)
        self.sw_fl[u] = True
        self.p_flt[u] = self._add_float(u, nb, X[q, 0], np.where(nb == SP, self.T_m_sp[u], X[q, 1]), X[q, 2])

    def _float_early(self, und) -> None:
        """Floating points that have converged in the branch that is not theirs switch at once,
        without waiting for the input point."""
        pf = self.p_flt[und]
        sel = (pf >= 0) & ~self.sw_fl[und]
        sel[sel] = self.conv[pf[sel]]
        if not sel.any():
            return
        u, q = und[sel], pf[sel]
        T_so, T_m = self.X[q, 0], self.X[q, 1]
        inside = (T_so > self.so_lo[q]) & (T_so <= self.so_hi[q])
        br = self.br[q]
        n_lo, n_hi = self.n_hs
        nHS = self.n_HS[q]
        cons = np.where(br == SP, (nHS >= n_lo - SPEED_TOL) & (nHS <= n_hi + SPEED_TOL),
                        np.where(br == HS_MAX, T_m > self.T_m_sp[u] + 1e-6, T_m < self.T_m_sp[u]))
        sw = inside & ~cons
        if sw.any():
            self._float_switch(u[sw], q[sw], nHS[sw])

    def _first_trial(self, pos, n_in) -> None:
        """The scalar LS search's first trial x0 of the rows pos (LS speed ratio n_in at the input,
        toward their ``lim``), to be checked in the next round."""
        lim = self.lim[pos]
        T_sp, T_in = self.T_sp[pos], self.T_in[pos]
        n_b = np.where(lim > 0, self.n_ls[1], self.n_ls[0])
        lo = np.where(lim > 0, T_sp, np.maximum(T_sp - 15.0, self.fs.tab.T_triple + 5.0))
        hi = np.where(lim > 0, T_in - 0.05, T_sp)
        x0 = np.minimum(np.maximum(T_in - (T_in - T_sp) * n_b / n_in, lo), hi)
        self.x0[pos] = x0
        ok = np.isfinite(x0)
        self.x0_st[pos] = np.where(ok, 1, 2)
        self.x0_risk[pos] = ~ok
        if ok.any():
            self.fs.set_source(self.plan.f_x0[pos[ok]], x0[ok])

    def _hs_screen(self, pos, br, T_c_sp) -> None:
        """Schedule the screen of the cold path's search at an HS bound for the rows pos (branch br;
        T_c_sp [K]: the branch test's condensing temperature, or an estimate): the joint Newton
        (``model.vsolve.bound_newton``) starts in the middle of the T_m interval, and where it gives
        up the nested secants start there too, each T_m trial solving T_c. Far from the root, the
        cold path fails where its start does: an evaluation there raises (an isentropic efficiency
        out of range), or the condensing zone cannot carry the duty even at T_c_max (p_c_high). Those
        rows go cold; the screen evaluates (T_m0, T_c0) and (T_m0, T_c_max)."""
        fs = self.fs
        rows = self.rows[pos]
        T_m_sp, below = self.T_m_sp[pos], self.below[pos]
        T_e = fs.T_e[rows]
        T_c0 = fs.T_ki[rows] + 1.3 * fs.Q_s[rows] / fs.C_w[rows] + 3.0
        lo = np.where(below | (br == HS_MIN), T_e + 0.05, T_m_sp)
        hi = np.where(below, T_c0 - 0.1, np.where(br == HS_MIN, T_m_sp, T_c_sp - 0.1))
        T_m0 = np.where((lo < T_m_sp) & (T_m_sp < hi), T_m_sp, 0.5 * (lo + hi))
        self.hs_at[pos, 0] = T_m0
        self.hs_at[pos, 1] = np.where(below, T_c0, T_c_sp)
        self.hs_st[pos] = 1

    # ---------------------------------------------------------------------------------------------
    def task(self, go_cold):
        fs = self.fs
        h = FD_STEP
        bt = np.flatnonzero(self.bt_st == 1)
        if len(bt):
            yield Spawn(self._abortable(self._branch_test(bt)))
        for it in range(MAX_ROUNDS):
            act = np.flatnonzero(~(self.conv | self.dead))
            chk = np.flatnonzero(self.x0_st == 1)
            hsc = np.flatnonzero(self.hs_st == 1)
            if not (len(act) or len(chk) or len(hsc)):
                wait = np.flatnonzero((self.bt_st == 1) & ~self.decided)
                if not len(wait):
                    break
                if not self.vector and np.count_nonzero(self.leave) + len(wait) <= SCALAR_COLD_MAX:
                    # only the cold branch test of a few rows is left: the scalar solver instead
                    self.bt_abort = True
                    self.decided[wait] = True
                    self.leave[wait] = True
                    break
            self.rounds = it + 1
            X = self.X
            # the intermediate side of a problem with T_m and T_source,out fixed is evaluated once
            fixed = self.ms_ok[act]
            act = np.concatenate([act[fixed], act[~fixed]])
            kf = int(fixed.sum())
            var = act[kf:]
            so = act[self.has_so[act]]
            if len(so):
                fs.set_source(np.concatenate([self.src[so], self.fso[so]]), np.concatenate([X[so, 0], X[so, 0] + h]))
            am = act[self.has_m[act]]
            T_m = np.where(self.has_m, X[:, 1], self.T_m_fix)
            k, km, ks = len(act), len(am), len(so)
            who = np.concatenate([act, act, am, so])
            # checks: the scalar LS search's first trial, the cold path's start at an HS bound, the
            # cold path's first trial at the set point
            fx0 = self.plan.f_x0[chk]
            T_mx = self.T_m_sp[chk]
            hr, hm, hc = self.rows[hsc], self.hs_at[hsc, 0], self.hs_at[hsc, 1]
            new_idx = np.concatenate([self.src[var], self.src[am], self.fso[so], fx0, hr, hr, hr, hr])
            new_T_m = np.concatenate([T_m[var], T_m[am] + h, T_m[so], T_mx, hm, hm, hm + h, hm])
            ms_new = fs.m_side(new_idx, new_T_m) if len(new_idx) else MSide(np.zeros((len(MSide.KEYS), 0)))
            nv = len(var)
            base_ms = MSide.concat([MSide(self.msc[:, act[:kf]]), ms_new.take(slice(0, nv))])
            ms = MSide.concat([base_ms, base_ms, ms_new.take(slice(nv, len(new_idx)))])
            idx = np.concatenate([self.src[act], self.src[act], new_idx[nv:]])
            T_mr = np.concatenate([T_m[act], T_m[act], new_T_m[nv:]])
            T_cr = np.concatenate([X[act, 2], X[act, 2] + h, X[am, 2], X[so, 2],
                                   np.maximum(fs.T_ki[fx0] + 0.05, T_mx + 0.05), hc, hc + h, hc,
                                   np.full(len(hsc), self.T_c_max)])
            ev = yield Eval(fs, idx, T_mr, T_cr, ms=ms, full=True)
            err, r, n_HS, n_LS = ev["err"], ev["r"], ev["n_HS"], ev["n_LS"]
            # keep the intermediate side of the problems that will not change it
            keep = np.flatnonzero(~self.has_m[var] & ~self.has_so[var])
            if len(keep):
                self.msc[:, var[keep]] = ms_new.a[:, keep]
                self.ms_ok[var[keep]] = True
            e = len(who)
            if len(chk):
                self.x0_risk[chk] = (err[e:e + len(chk)] != E_OK) | ~(r[e:e + len(chk)] <= 0.0)
                self.x0_st[chk] = 2
                self.touched[chk] = True
                e += len(chk)
            if len(hsc):
                a, b, c, d = (slice(e + j * len(hsc), e + (j + 1) * len(hsc)) for j in range(4))
                r_c, n_c = (r[b] - r[a]) / h, (n_HS[b] - n_HS[a]) / h
                r_m, n_m = (r[c] - r[a]) / h, (n_HS[c] - n_HS[a]) / h
                self.hs_n[hsc] = n_HS[a] - n_c * r[a] / r_c          # on the curve r = 0 at T_m0
                self.hs_s[hsc] = n_m - n_c * r_m / r_c               # its slope along the curve
                self.hs_risk[hsc] = ((err[a] != E_OK) | (err[b] != E_OK) | (err[c] != E_OK) | (err[d] != E_OK)
                                     | ~(r[d] >= 0.0) | ~(r_c > 0.0) | ~np.isfinite(self.hs_n[hsc] + self.hs_s[hsc]))
                self.hs_st[hsc] = 2
                self.touched[hsc] = True
            if k:
                n0 = len(who)
                self._newton(act, am, so, who, err[:n0], r[:n0], n_HS[:n0], n_LS[:n0], ev)
            yield from self._decide(go_cold)
        yield from self._decide(go_cold, final=True)

    def _abortable(self, task):
        """``task`` (a generator of requests), ended early once ``bt_abort`` is set."""
        value = None
        while not self.bt_abort:
            try:
                req = task.send(value)
            except StopIteration:
                return
            value = yield req
        task.close()

    def _branch_test(self, pos):
        """The cold path's branch test (``model.vsolve.TcSolver`` from its cold start at the set
        point) for the rows pos (a task beside the main one): the HS speed needed there, or the
        failure the cold path stops with."""
        fs = self.fs
        rows = self.rows[pos]
        tc = TcSolver(fs, rows, fs.T_ki[rows] + 1.3 * fs.Q_s[rows] / fs.C_w[rows] + 3.0, self.T_c_max)
        raised = Raised(len(rows))

        def conv(j, T_c, n_sp):                   # rows whose test has converged are settled at once
            u = pos[j]
            self.bt_T_c[u], self.bt_n[u], self.bt_st[u] = T_c, n_sp, 2
            self.touched[u] = True

        T_c, n_sp = yield from tc.solve(np.arange(len(rows)), self.T_m_sp[pos], raised, on_conv=conv)
        left = self.bt_st[pos] == 1
        u = pos[left]
        self.bt_T_c[u], self.bt_n[u] = T_c[left], n_sp[left]
        self.bt_cls[u], self.bt_code[u], self.bt_msg[u] = raised.cls[left], raised.code[left], raised.msg[left]
        self.bt_st[u] = 2
        self.touched[u] = True

    def _newton(self, act, am, so, who, err, r, n_HS, n_LS, ev) -> None:
        """One Newton step of the active problems from their evaluation (the point, then the
        finite-difference steps in T_c, T_m, T_source,out); converged problems keep their outputs.
        One unknown (T_c) and two (T_m, T_c) in closed form, three (with T_source,out) by solve."""
        h = FD_STEP
        k, km = len(act), len(am)
        pm = np.flatnonzero(self.has_m[act])
        ps = np.flatnonzero(self.has_so[act])
        r0, n0 = r[:k], n_HS[:k]
        f1 = n0[pm] - self.bound[am]                          # HS speed at its bound
        f0 = n_LS[:k][ps] - self.n_b[so]                      # LS speed at its bound
        fn = np.abs(r0) * (1.0 / ENERGY_TOL)
        fn[pm] = np.maximum(fn[pm], np.abs(f1) * (1.0 / SPEED_TOL))
        fn[ps] = np.maximum(fn[ps], np.abs(f0) * (1.0 / WARM_LS_TOL))
        good = err[:k] == E_OK
        # the set-point test needs the HS speed there beyond (or within) its bounds, not the root
        # itself to the last digit: a looser residual where the speed is clear of both bounds
        n_lo, n_hi = self.n_hs
        loose = ((self.role[act] == SPT) & (np.abs(r0) < SPT_TOL)
                 & (np.minimum(np.abs(n0 - n_lo), np.abs(n0 - n_hi)) > SPT_MARGIN))
        conv = good & ((fn < 1.0) | loose)
        # Newton from a nearby root converges quadratically: a full step that does not halve the
        # residual (scaled by the tolerances) says the start is not near a root of this branch
        good &= fn <= np.where(self.full_step[act], PROGRESS, PROGRESS_LIMITED) * self.fnorm[act]
        self.fnorm[act] = fn
        c = act[conv]
        if len(c):
            self.conv[c] = True
            self.n_HS[c], self.n_LS[c] = n0[conv], n_LS[:k][conv]
            self.s_ev[c], self.s_j[c] = len(self.evs), np.flatnonzero(conv)   # the outputs: at the end
            self.evs.append(ev)
        # the step: dr/dT_c (every problem), then dn_HS/dT_m etc. where they are unknowns
        r_c = (r[k:2 * k] - r0) * (1.0 / h)
        bad = ~good | (err[k:2 * k] != E_OK)
        dX = np.zeros((k, 3))
        dX[:, 2] = -r0 / r_c
        # the set-point test settles as soon as the HS speed at its root (one Newton step away,
        # within twice that step's length of it) is clear of both bounds, and the isentropic
        # efficiency there of its range, by four times what that distance can change them
        j = np.flatnonzero((self.role[act] == SPT) & ~conv & ~bad & (r_c > 0.0))
        if len(j):
            d = dX[j, 2]
            U = 2.0 * np.abs(d) + 1e-6
            n_c = (n_HS[k + j] - n0[j]) * (1.0 / h)
            eta = ev["eta_HS"]
            e_c = (eta[k + j] - eta[j]) * (1.0 / h)
            n_s, e_s = n0[j] + n_c * d, eta[j] + e_c * d
            dn, de = 4.0 * np.abs(n_c) * U + SPEED_TOL, 4.0 * np.abs(e_c) * U + 1e-3
            clear = ((np.abs(d) < STEP_MAX) & (np.minimum(np.abs(n_s - n_lo), np.abs(n_s - n_hi)) > dn)
                     & (e_s - de > 0.05) & (e_s + de < 1.0))
            q = act[j[clear]]
            if len(q):
                conv[j[clear]] = True
                self.conv[q] = True
                self.touched[self.own[q]] = True
                self.X[q, 2] += d[clear]
                self.n_HS[q] = n_s[clear]
                self.s_ev[q] = -1                          # a test: no outputs kept
        if km:
            q = slice(2 * k, 2 * k + km)
            bad[pm] |= err[q] != E_OK
            a, b = (n_HS[q] - n0[pm]) * (1.0 / h), (n_HS[k:2 * k][pm] - n0[pm]) * (1.0 / h)   # dn/dT_m, dn/dT_c
            c_, d = (r[q] - r0[pm]) * (1.0 / h), r_c[pm]                                      # dr/dT_m, dr/dT_c
            det = a * d - b * c_
            bad[pm] |= ~((det != 0.0) & np.isfinite(det))
            rr = r0[pm]
            dX[pm, 1] = -(d * f1 - b * rr) / det
            dX[pm, 2] = -(a * rr - c_ * f1) / det
        if len(ps):
            # (n_LS - n_b, n_HS - bound, r) in (T_so, T_m, T_c), at the point and its steps
            hm = self.has_m[act][ps]
            mpos = 2 * k + np.searchsorted(pm, ps)            # the T_m step of those with T_m unknown
            rows4 = np.concatenate([ps, k + ps, 2 * k + km + np.arange(len(ps)), mpos[hm]])
            q = who[rows4]
            F = np.stack([n_LS[rows4] - self.n_b[q], np.where(self.has_m[q], n_HS[rows4] - self.bound[q], 0.0),
                          r[rows4]], axis=1)
            n3 = len(ps)
            F0 = F[:n3]
            J = np.zeros((n3, 3, 3))
            J[:, :, 2] = (F[n3:2 * n3] - F0) / h
            J[:, :, 0] = (F[2 * n3:3 * n3] - F0) / h
            bad[ps] |= err[2 * k + km:] != E_OK
            J[hm, :, 1] = (F[3 * n3:] - F0[hm]) / h
            J[~hm, 1, 1] = 1.0
            fin = np.all(np.isfinite(J.reshape(len(ps), 9)), axis=1)
            det = np.where(fin, np.linalg.det(np.where(fin[:, None, None], J, np.eye(3))), np.nan)
            ok3 = fin & (det != 0.0) & np.isfinite(det)
            bad[ps] |= ~ok3
            if ok3.any():
                dX[ps[ok3]] = -np.linalg.solve(J[ok3], F0[ok3][:, :, None])[:, :, 0]
        go = ~conv & ~bad & np.all(np.isfinite(dX), axis=1)
        gi = np.flatnonzero(go)
        dead = act[~conv & ~go]
        if len(gi):
            dX = dX[gi]
            big = np.max(np.abs(dX), axis=1)
            dX *= np.minimum(1.0, STEP_MAX / np.maximum(big, 1e-300))[:, None]
            p = act[gi]
            prev_full = self.full_step[p]
            self.full_step[p] = big <= STEP_MAX
            Xn = self.X[p] + dX
            inside = ((Xn[:, 2] <= self.T_c_max) & (Xn[:, 2] > self.fs.T_ki[self.src[p]] + 0.05)
                      & (Xn[:, 1] < Xn[:, 2] - 0.05) & (Xn[:, 0] > self.so_lo[p]) & (Xn[:, 0] <= self.so_hi[p]))
            self.X[p[inside]] = Xn[inside]
            dead = np.concatenate([dead, p[~inside]])
            # a step this small is the last: the point and every output move by it, linearised
            # with the same differences (what is left is of second order): a step below LAST_STEP
            # from residuals below LAST_FN times the tolerances, or, once Newton converges
            # quadratically (a full step before, this one below a tenth of it), one after which
            # the error left, ~ step^3 / previous step^2, is below LAST_ERR
            prev = self.last_dx[p]
            self.last_dx[p] = big
            quad = prev_full & (big < 0.1 * prev) & (big * big * big < LAST_ERR * prev * prev) & (fn[gi] < 10 * LAST_FN)
            last = inside & (((big <= LAST_STEP) & (fn[gi] < LAST_FN)) | quad)
            if last.any():
                self._last_step(act, gi[last], dX[last], ev, k, km, pm, ps)
            self.age[p] += 1
            dead = np.concatenate([dead, p[(self.age[p] >= WARM_ROUNDS) & ~self.conv[p]]])
        self.dead[dead] = True
        self.touched[self.own[dead]] = True
        self.touched[self.own[c]] = True

    def _last_step(self, act, j, dX, ev, k, km, pm, ps) -> None:
        """Problems act[j] converge by their step dX (already applied to X): their outputs at the
        root from the evaluation at the point and its finite-difference steps (T_c, T_m, T_so)."""
        h = FD_STEP
        p = act[j]
        im = np.searchsorted(pm, j)                        # positions of the T_m / T_so steps
        isp = np.searchsorted(ps, j)
        hm, hso = self.has_m[p], self.has_so[p]
        keys = ASSEMBLY_KEYS[1:]                           # all but "err"
        Y = np.stack([ev[key] for key in keys])           # (keys, evaluated rows)
        y0 = Y[:, j]
        v = y0 + (Y[:, k + j] - y0) * (dX[:, 2] / h)
        if hm.any():
            v[:, hm] += (Y[:, 2 * k + im[hm]] - y0[:, hm]) * (dX[hm, 1] / h)
        if hso.any():
            v[:, hso] += (Y[:, 2 * k + km + isp[hso]] - y0[:, hso]) * (dX[hso, 0] / h)
        out = dict(zip(keys, v))
        out["err"] = ev["err"][j]
        self.conv[p] = True
        self.touched[self.own[p]] = True
        self.n_HS[p], self.n_LS[p] = out["n_HS"], out["n_LS"]
        self.s_ev[p], self.s_j[p] = len(self.evs), np.arange(len(p))
        self.evs.append(out)
        so = p[hso]
        if len(so):                                        # the source side at the final T_so
            self.fs.set_source(self.src[so], self.X[so, 0])

    # ---------------------------------------------------------------------------------------------
    def _decide(self, go_cold, final: bool = False):
        """Settle the rows whose problems allow it (the answer where every check passes, the cold
        path, a task started beside this one, where one fails); start the problems of rows that
        change branch or start to float."""
        back = []
        und = np.flatnonzero(self.touched & ~self.decided)
        self.touched[:] = False
        if self.ls_mode == "float" and len(und):
            self._float_early(und)
        for _ in range(4):
            und = und[~self.decided[und]]
            p1 = self.p_in[und]
            und = und[self.conv[p1] | self.dead[p1] | (self.bt_st[und] == 2)]
            if not len(und) or not self._settle(und, back):
                break
        if final:
            rest = np.flatnonzero(~self.decided)
            self.decided[rest] = True
            back.append(rest)
        if back:
            b = np.concatenate(back)
            if len(b):
                for p in (self.p_in[b], self.p_spt[b], self.p_flt[b]):
                    p = p[p >= 0]
                    self.dead[p[~self.conv[p]]] = True
                self.leave[b] = True
        # the rows that leave: a few go to the scalar solver once the warm path is done (the vector
        # cold path costs its rounds, 5-60, whatever its rows; the scalar one ~0.2-6 ms a row),
        # more start on the vector cold path at once
        for u, code, msg in self.handed:
            for p in (self.p_in[u], self.p_spt[u], self.p_flt[u]):
                p = p[p >= 0]
                self.dead[p[~self.conv[p]]] = True
            self.gone[u] = True
            yield Spawn(go_cold(self.rows[u], code, msg))
        self.handed = []
        lv = np.flatnonzero(self.leave & ~self.gone)
        if len(lv) and (self.vector or np.count_nonzero(self.leave) > SCALAR_COLD_MAX):
            self.vector = True
            self.gone[lv] = True
            yield Spawn(go_cold(self.rows[lv]))
        elif final and len(lv):
            self.scalar[lv] = True

    def _settle(self, und, back: list) -> bool:
        """One pass over the rows und: returns whether a row changed its problems (another pass
        may settle it). The input point's branch as the scalar solver decides it, from the HS speed
        needed at the set point (the set-point test: the exact cold branch test for borrowed rows,
        the "sp" input point's own root, or the set-point problem of an HS-bound input point)."""
        fs, X = self.fs, self.X
        n_lo, n_hi = self.n_hs
        rows, below, T_m_sp = self.rows[und], self.below[und], self.T_m_sp[und]
        p1 = self.p_in[und]
        c1, d1 = self.conv[p1], self.dead[p1]
        br1 = self.br[p1]
        changed = False
        # ---- the exact branch test of borrowed rows: its failure is the row's (cold) answer
        bt = self.bt_st[und] > 0
        btd = self.bt_st[und] == 2
        btf = btd & (self.bt_cls[und] != 0)
        if btf.any():
            j = np.flatnonzero(btf)
            u = und[j]
            code = self.bt_code[u]
            # "float" mode: a failure for too much duty floats from the far end (the cold path)
            over = (self.ls_mode == "float") & np.isin(code, OVERLOAD) & (self.bt_cls[u] != 3)
            go = self.bt_cls[u] == 3
            self.decided[u] = True
            back.append(u[go])
            if over.any():                             # the cold path goes on from that failure
                self.handed.append((u[over], code[over], self.bt_msg[u[over]]))
            f = u[~go & ~over]
            self.failed[f] = True
            self.fail_code[f], self.fail_msg[f] = code[~go & ~over], self.bt_msg[f]
            keep = ~btf
            und, rows, below, T_m_sp = und[keep], rows[keep], below[keep], T_m_sp[keep]
            p1, c1, d1, br1, bt, btd = p1[keep], c1[keep], d1[keep], br1[keep], bt[keep], btd[keep]
        # ---- the set-point test's outcome
        p2 = self.p_spt[und]
        q2 = np.maximum(p2, 0)
        c2, d2 = (p2 >= 0) & self.conv[q2], (p2 >= 0) & self.dead[q2]
        spk = br1 == SP
        ready = np.where(bt, btd, np.where(spk, c1, c2)) & ~below
        n_sp = np.where(bt, self.bt_n[und], np.where(spk, self.n_HS[p1], self.n_HS[q2]))
        T_c_sp = np.where(bt, self.bt_T_c[und], np.where(spk, X[p1, 2], X[q2, 2]))
        r = np.flatnonzero(ready)
        self.t_n[und[r]], self.t_T_c[und[r]] = n_sp[r], T_c_sp[r]
        cold = np.where(bt, False, np.where(spk, d1, (p2 < 0) | d2)) & ~below
        cold |= d1 & ~bt
        t_in = ready & (n_sp >= n_lo - SPEED_TOL) & (n_sp <= n_hi + SPEED_TOL)
        t_up, t_dn = ready & (n_sp > n_hi + SPEED_TOL), ready & (n_sp < n_lo - SPEED_TOL)
        T_m, T_c = X[p1, 1], X[p1, 2]
        T_ki = fs.T_ki[rows]
        span = (T_c > T_ki + 0.05) & (T_c > T_m + 0.05) & (T_c <= self.T_c_max)
        ok_in = t_in & spk & c1 & span
        cold |= t_in & spk & c1 & ~span
        # the set point holds although the input point was at an HS bound (or the "sp" problem of a
        # borrowed row failed): the set-point root is the answer, once to the input's tolerance
        tosp = t_in & ((~spk & ~bt) | (bt & (~spk | d1)))
        cold |= tosp & self.sw_in[und]
        tosp &= ~self.sw_in[und]
        if tosp.any():
            j = np.flatnonzero(tosp)
            u = und[j]
            self.sw_in[u] = True
            q = p1[j]
            self.dead[q[~self.conv[q]]] = True
            nb = ~bt[j]
            if nb.any():                               # the set-point problem becomes the input's
                q = p2[j[nb]]
                self.p_in[u[nb]], self.p_spt[u[nb]] = q, -1
                self.role[q] = IN
                loose = q[self.fnorm[q] >= 1.0]
                self.conv[loose], self.fnorm[loose] = False, np.inf   # iterates again from its point
            if (~nb).any():                            # from the exact branch test's root
                k = j[~nb]
                self.p_in[und[k]] = self._add(und[k], IN, rows[k], SP, self.T_sp[und[k]], T_m_sp[k], T_c_sp[k])
            changed = True
        # the HS speed needed at the set point lies beyond a bound: the HS runs there
        t_b = t_up | t_dn
        want = np.where(t_up, HS_MAX, HS_MIN).astype(np.int8)
        sw = t_b & spk & ~self.sw_in[und] & (c1 | d1 | bt)
        cold |= t_b & spk & self.sw_in[und]
        if sw.any():
            j = np.flatnonzero(sw)
            u = und[j]
            self.sw_in[u] = True
            q = p1[j]
            self.dead[q[~self.conv[q]]] = True
            # the "sp" root is the set-point test of the HS-bound problem (a borrowed row has the
            # exact branch test's instead)
            self.p_spt[u] = np.where(bt[j], -1, q)
            self.p_in[u] = self._add(u, IN, rows[j], want[j], self.T_sp[u], T_m_sp[j], T_c_sp[j])
            self._hs_screen(u, want[j], T_c_sp[j])
            changed = True
        cold |= t_b & ~spk & (br1 != want)
        # ---- input point at an HS bound: the cold path's interval for T_m and the screen of its start
        hs_ok = c1 & ~spk & ((t_b & (br1 == want)) | (below & (br1 == HS_MAX)))
        cold |= c1 & below & (br1 != HS_MAX)
        T_e = fs.T_e[rows]
        T_c0 = T_ki + 1.3 * fs.Q_s[rows] / fs.C_w[rows] + 3.0
        t_T_c = self.t_T_c[und]
        interval = np.where(below, (T_m >= T_e + 0.05) & (T_m <= T_c0 - 0.1),
                            np.where(br1 == HS_MAX, (T_m >= T_m_sp) & (T_m <= t_T_c - 0.1),
                                     (T_m >= T_e + 0.05) & (T_m <= T_m_sp)))
        hs_ok &= self.hs_st[und] == 2                  # the screen of the cold path's start evaluated
        # the HS speed needed falls as T_m rises: at the cold path's start it must lie on the side of
        # the bound that T_m0 lies on against the root, clearly (else a second root may lie between),
        # and falling there too, steeply enough that a secant step from there (the nested search's
        # first, linearised) lands short of the root or beyond it by less than HS_OVERSHOOT times its
        # distance (where the curve flattens the cold search jumps away and fails on its way)
        T_m0 = self.hs_at[und, 0]
        dn = self.hs_n[und] - self.bound[p1]
        side = dn * (T_m0 - T_m)
        T_m1 = T_m0 - dn / self.hs_s[und]
        screen = ~self.hs_risk[und] & (((side < 0.0) & (np.abs(dn) > HS_SCREEN) & (self.hs_s[und] < 0.0)
                                        & (np.abs(T_m1 - T_m) < HS_OVERSHOOT * np.abs(T_m0 - T_m)))
                                       | (np.abs(T_m0 - T_m) < 1e-3))
        good = interval & span & screen
        ok_in |= hs_ok & good
        cold |= hs_ok & ~good
        ok_in &= ~cold
        # ---- the answer: the input point, or in "float" mode the floating point
        if self.ls_mode != "float":
            self._answer(und[ok_in], p1[ok_in])
        elif ok_in.any():
            changed |= self._settle_float(und[ok_in], p1[ok_in], back)
        if cold.any():
            u = und[cold]
            self.decided[u] = True
            back.append(u)
        return changed

    def _answer(self, u, p) -> None:
        self.decided[u] = True
        self.ok[u] = True
        self.answer[u] = p
        q = self.p_flt[u]
        q = q[(q >= 0) & (q != p)]
        self.dead[q[~self.conv[q]]] = True              # the floating problem is not needed

    def _settle_float(self, und, p1, back: list) -> bool:
        """Rows und whose input point p1 passed its checks, in "float" mode: the input point is the
        answer where N_LS lies within its range, else the floating point toward the violated bound
        once it has converged and passed its checks."""
        X = self.X
        l_lo, l_hi = self.n_ls
        n_LS = self.n_LS[p1]
        inr = (n_LS >= l_lo) & (n_LS <= l_hi)
        self._answer(und[inr], p1[inr])
        und, p1, n_LS = und[~inr], p1[~inr], n_LS[~inr]
        if not len(und):
            return False
        L = np.where(n_LS > l_hi, 1, -1).astype(np.int8)
        pf = self.p_flt[und]
        cold = (pf >= 0) & (self.lim[und] != L)
        new = pf < 0
        changed = False
        if new.any():
            j = np.flatnonzero(new)
            u = und[j]
            self.lim[u] = L[j]
            self._first_trial(u, n_LS[j])
            q = p1[j]
            self.p_flt[u] = self._add_float(u, self.br[q], self.x0[u], X[q, 1], X[q, 2])
            changed = True
        have = (pf >= 0) & ~cold
        q = np.maximum(pf, 0)
        cold |= have & self.dead[q]
        cf = have & self.conv[q]
        if cf.any():
            j = np.flatnonzero(cf)
            u, q = und[j], pf[j]
            T_so, T_m = X[q, 0], X[q, 1]
            inside = (T_so > self.so_lo[q]) & (T_so <= self.so_hi[q])
            br = self.br[q]
            n_lo, n_hi = self.n_hs
            nHS = self.n_HS[q]
            T_m_sp = self.T_m_sp[u]
            cons = np.where(br == SP, (nHS >= n_lo - SPEED_TOL) & (nHS <= n_hi + SPEED_TOL),
                            np.where(br == HS_MAX, T_m > T_m_sp + 1e-6, T_m < T_m_sp))
            # the other branch at the floating point, once (as the cold path's second pass)
            sw = inside & ~cons & ~self.sw_fl[u]
            bad = ~inside | (~cons & ~sw)
            if sw.any():
                self._float_switch(u[sw], q[sw], nHS[sw])
                changed = True
            # the first trial: from an "sp" input it lies beyond the root where the search would fail
            x0 = self.x0[u]
            lim = self.lim[u]
            beyond = np.where(lim > 0, x0 > T_so + 1e-9, x0 < T_so - 1e-9)
            risky = (self.br[self.p_in[u]] == SP) & beyond
            bad |= risky & self.x0_risk[u] & (self.x0_st[u] == 2)
            wait = risky & (self.x0_st[u] == 1)
            good = ~bad & ~sw & ~wait
            self._answer(u[good], q[good])
            cold[j[bad]] = True
        if cold.any():
            u = und[cold]
            self.decided[u] = True
            back.append(u)
        return changed

    # ---------------------------------------------------------------------------------------------
    def _lim_of(self, pos) -> np.ndarray:
        """+1/-1 where the answer of the rows pos is a floating point at N_max/N_min, else 0."""
        return np.where(self.role[self.answer[pos]] == FLT, self.lim[pos], 0).astype(np.int8)

    def results(self, pos):
        """(flowsheet rows, T_m, T_c, branch, ls limit, evaluation outputs) of the answers of the
        settled rows pos (positions in the plan's rows)."""
        p = self.answer[pos]
        out = {key: np.empty(len(p)) for key in ASSEMBLY_KEYS}
        ev_of = self.s_ev[p]
        for e in np.unique(ev_of):
            sel = np.flatnonzero(ev_of == e)
            ev, j = self.evs[e], self.s_j[p[sel]]
            for key in ASSEMBLY_KEYS:
                out[key][sel] = ev[key][j]
        return self.src[p], self.X[p, 1], self.X[p, 2], self.br[p], self._lim_of(pos), out

    def fill_state(self, pos, state: dict) -> None:
        """The warm-start state of the settled rows pos into ``state`` (indexed by row)."""
        fs = self.fs
        rows = self.rows[pos]
        p, p1 = self.answer[pos], self.p_in[pos]
        state["branch"][rows] = self.br[p]
        state["T_m"][rows], state["T_c"][rows], state["T_so"][rows] = self.X[p, 1], self.X[p, 2], fs.T_so[self.src[p]]
        state["ls_limit"][rows] = self._lim_of(pos)
        state["in_branch"][rows] = self.br[p1]
        state["in_T_m"][rows], state["in_T_c"][rows] = self.X[p1, 1], self.X[p1, 2]
        state["T_c_sp"][rows] = np.where(np.isfinite(self.t_T_c[pos]), self.t_T_c[pos], self.X[p1, 2])
        for k in ("n_LS", "n_HS", "d_SC", "dT_SC", "phi_HS"):
            state[k][rows] = getattr(fs, k)[self.src[p]]
