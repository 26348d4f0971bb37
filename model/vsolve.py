"""``model.cycle._solve`` from a cold start (no guess), for many rows at once, as tasks
(``model.vtasks``) whose flowsheet evaluations run batched.

The scalar solver's answer for a row is not only its root: an operating point fails where any trial
point of its iterations fails (an isentropic efficiency outside (0.05, 1] at a trial condensing
temperature during the branch test fails the row with ``eta_out_of_range``, although the point
the HS would settle at may be fine). To give the same status on every row, this module follows the
scalar cold path step by step, vectorised:

- the branch test's secant on T_c at the set point (``_secant`` with its finite-difference slope,
  10-K step limit and bisection once bracketed; ``solve_Tc``'s p_c_high / p_m_above_p_c diagnosis
  where it fails);
- for rows at an HS speed bound the joint Newton on (T_m, T_c) with its finite-difference Jacobian
  and Broyden updates (``_bound_newton``), and where it gives up the nested secants (T_m outer with a
  finite-difference slope, T_c inner warm-started from the last; the hs_speed_low/high diagnosis);
- the final ``solve_Tc``, which restarts its secant where the last T_c lies within 0.5 K of its
  lower limit.

The trial points are the scalar ones to ~1e-9 (the residuals differ by the tables' round-off), so
every check falls the same way except within ~1e-9 of its limit, and the reason texts are the
scalar's (a number printed from a trial point may differ in its last digit). An evaluation the
tables or the vectorised inner iterations cannot settle gives the row the code ``"fallback"``:
``model.vcycle`` solves it with ``model.cycle``. SI units: K, Pa, W.
"""
from __future__ import annotations

import numpy as np

from .cycle import BOUND_NEWTON_ITER, BOUND_NEWTON_STEP, ENERGY_TOL, MAX_ITER, SPEED_TOL
from .units import BAR
from .vflowsheet import (CONVERGENCE, E_ETA_HS, E_ETA_LS, E_FALLBACK, E_OK, E_ORDER, E_SINK, FALLBACK_WHY,
                         Flowsheet, MSide)
from .vtasks import Eval, Spawn

FALLBACK = "fallback"
SP, HS_MAX, HS_MIN = 0, 1, 2
BRANCHES = ("sp", "hs_max", "hs_min")
_WHAT_TC = "condensing temperature"


def take(d, pos):
    """The rows ``pos`` of an MSide, or of every array in a mapping."""
    if isinstance(d, MSide):
        return d.take(pos)
    return {k: (v[pos] if isinstance(v, np.ndarray) and v.ndim else v) for k in d.keys() for v in (d[k],)}


def eval_messages(fs: Flowsheet, idx, err, T_m, T_c, ms: dict, ev: dict) -> list[str]:
    """The scalar solver's exception messages (reason texts) for evaluation errors ``err``."""
    par = fs.par
    out = []
    for k in range(len(err)):
        e = err[k]
        if e == E_ORDER:
            out.append(f"trial temperatures out of order: T_e={fs.T_e[idx[k]]:.3f} K, "
                       f"T_m={T_m[k]:.3f} K, T_c={T_c[k]:.3f} K")
        elif e == E_SINK:
            out.append("condensing temperature below sink inlet")
        elif e == E_ETA_LS:
            out.append(f"LS isentropic efficiency {ms['eta_LS'][k]:.3f} outside (0.05, 1] at pressure "
                       f"ratio {ms['pi_LS'][k]:.3f}, {ms['n_LS'][k] * par.comp_LS.N_nom:.0f} rpm")
        elif e == E_ETA_HS:
            out.append(f"HS isentropic efficiency {ev['eta_HS'][k]:.3f} outside (0.05, 1] at pressure "
                       f"ratio {ev['pi_HS'][k]:.3f}")
        else:
            out.append(f"scalar path needed: {FALLBACK_WHY[ev['why'][k]] if 'why' in ev else ''}")
    return out


def _reason_of(e: int) -> str:
    if e in CONVERGENCE:
        return "no_convergence"
    if e in (E_ETA_LS, E_ETA_HS):
        return "eta_out_of_range"
    return FALLBACK


class Outcome:
    """Per-row result of the cold path: ``code`` ('' where solved, else the scalar's reason code or
    "fallback"), ``msg`` (the reason text), ``branch`` (SP/HS_MAX/HS_MIN), T_m, T_c [K]; ``flag``
    and ``flag_msg`` where a solved row's status is the solver's (not the limit checks').

    For warm starts of a later call (``model.vwarm``): ``T_c_sp`` [K], the condensing temperature
    of the branch test at the set point (rows at an HS bound); ``in_branch``, ``in_T_m``,
    ``in_T_c``: the solution at the input's T_source,out of a row whose LS floated (-1/NaN
    elsewhere: there it is the row's solution)."""

    def __init__(self, n: int) -> None:
        self.code = np.full(n, "", dtype=object)
        self.msg = np.full(n, "", dtype=object)
        self.branch = np.zeros(n, dtype=np.int8)
        self.T_m = np.full(n, np.nan)
        self.T_c = np.full(n, np.nan)
        self.flag = np.full(n, "", dtype=object)       # a solved row's status set by the solver
        self.flag_msg = np.full(n, "", dtype=object)
        self.T_c_sp = np.full(n, np.nan)
        self.in_branch = np.full(n, -1, dtype=np.int8)
        self.in_T_m = np.full(n, np.nan)
        self.in_T_c = np.full(n, np.nan)

    def note_input(self, rows) -> None:
        """The rows' present solution is their input point's (before their LS floats)."""
        self.in_branch[rows], self.in_T_m[rows], self.in_T_c[rows] = self.branch[rows], self.T_m[rows], self.T_c[rows]

    def fail(self, rows, codes, msgs) -> None:
        for r, c, m in zip(rows, codes, msgs):
            if not self.code[r]:
                self.code[r], self.msg[r] = c, m


class Raised:
    """What a row's evaluation raised, per position of a problem's rows: ``cls`` 0 nothing, 1 a
    ConvergenceError, 2 an InfeasibleOperation (``code`` its reason), 3 the scalar path is needed;
    ``msg`` the exception's text. The first exception of a row counts."""

    def __init__(self, n: int) -> None:
        self.cls = np.zeros(n, dtype=np.int8)
        self.code = np.full(n, "", dtype=object)
        self.msg = np.full(n, "", dtype=object)

    def put(self, pos, cls, codes, msgs) -> None:
        for p, c, code, m in zip(pos, cls, codes, msgs):
            if not self.cls[p]:
                self.cls[p], self.code[p], self.msg[p] = c, code, m

    def put_eval(self, fs, pos, idx, err, T_m, T_c, ms, ev) -> None:
        """Evaluation errors ``err`` (E_*) of the rows ``pos`` (their flowsheet rows ``idx``)."""
        bad = np.flatnonzero(err != E_OK)
        if not len(bad):
            return
        e = err[bad]
        msgs = eval_messages(fs, idx[bad], e, T_m[bad], T_c[bad], take(ms, bad), take(ev, bad))
        cls = np.where(np.isin(e, CONVERGENCE), 1, np.where(e == E_FALLBACK, 3, 2))
        self.put(pos[bad], cls, [_reason_of(x) for x in e], msgs)

    def clear(self, pos) -> None:
        self.cls[pos] = 0


def secant_v(F, x0, slope0, tol: float, lo, hi, what: str, on_conv=None):
    """``model.cycle._secant`` for many rows (a task): ``yield from F(pos, x)`` -> (f, ok) evaluates
    the rows at positions pos (ok False where the evaluation raised; F records what). Returns (x, fx,
    slope, kind, msg): kind 0 converged, 1 an evaluation raised, 2 the secant raised
    ConvergenceError (msg its text). ``on_conv(pos, x)``: called as rows converge."""
    n = len(x0)
    x = np.minimum(np.maximum(x0, lo), hi)
    kind = np.full(n, -1, dtype=np.int8)         # -1 still iterating
    msg = np.full(n, "", dtype=object)
    pos = np.arange(n)
    fx, ok = yield from F(pos, x)
    fx = np.array(fx, dtype=float)
    kind[~ok] = 1
    kind[ok & (np.abs(fx) < tol)] = 0
    if on_conv is not None and (kind == 0).any():
        on_conv(pos[kind == 0], x[kind == 0])
    slope = np.array(slope0, dtype=float)
    act = np.flatnonzero(kind == -1)
    need = act[~((slope[act] != 0.0) & np.isfinite(slope[act]))]
    if len(need):                                # finite-difference slope
        xa = x[need]
        h = np.where(np.abs(xa) > 1.0, 1e-3, 1e-4)
        x1 = np.where(xa + h <= hi[need], xa + h, xa - h)
        f1, ok = yield from F(need, x1)
        kind[need[~ok]] = 1
        slope[need] = (f1 - fx[need]) / (x1 - xa)
        act = act[kind[act] == -1]
    a, b = np.full(n, np.nan), np.full(n, np.nan)
    for _ in range(MAX_ITER):
        if not len(act):
            break
        xa, fa, sa = x[act], fx[act], slope[act]
        neg = fa < 0
        a[act] = np.where(neg, xa, a[act])
        b[act] = np.where(neg, b[act], xa)
        zero = (sa == 0.0) | ~np.isfinite(sa)
        xn = xa - fa / sa
        aa, bb = a[act], b[act]
        both = np.isfinite(aa) & np.isfinite(bb)
        xb = np.where((np.minimum(aa, bb) < xn) & (xn < np.maximum(aa, bb)), xn, 0.5 * (aa + bb))
        step = np.minimum(np.maximum(xn - xa, -10.0), 10.0)
        xn = np.where(both, xb, np.minimum(np.maximum(xa + step, lo[act]), hi[act]))
        noroot = ~both & (xn == xa) & ~zero
        for k in np.flatnonzero(zero):
            kind[act[k]], msg[act[k]] = 2, f"{what}: zero slope"
        for k in np.flatnonzero(noroot):
            kind[act[k]], msg[act[k]] = 2, f"{what}: no root in [{lo[act[k]]:.3f}, {hi[act[k]]:.3f}]"
        keep = ~(zero | noroot)
        act, xa, fa, xn = act[keep], xa[keep], fa[keep], xn[keep]
        if not len(act):
            break
        fn, ok = yield from F(act, xn)
        s_new = (fn - fa) / (xn - xa)
        upd = (xn != xa) & (s_new != 0.0) & np.isfinite(s_new)
        slope[act] = np.where(upd, s_new, slope[act])
        x[act], fx[act] = xn, fn
        kind[act[~ok]] = 1
        act = act[ok]
        conv = np.abs(fx[act]) < tol
        kind[act[conv]] = 0
        if on_conv is not None and conv.any():
            on_conv(act[conv], x[act[conv]])
        act = act[~conv]
    for k in act:
        kind[k], msg[k] = 2, f"{what}: no convergence in {MAX_ITER} iterations (residual {fx[k]:.3g})"
    return x, fx, slope, kind, msg


class TcSolver:
    """``_solve``'s inner ``solve_Tc`` for the rows idx (flowsheet rows), with its memory: the last
    T_c (``T_c_guess``) and secant slope (``slope_c``) of each row, updated on success as the
    scalar's nonlocal variables are. Positions ("pos") index idx."""

    def __init__(self, fs: Flowsheet, idx, T_c_guess, T_c_max: float) -> None:
        self.fs, self.idx = fs, idx
        self.T_c_guess = np.array(T_c_guess, dtype=float)
        self.slope_c = np.zeros(len(idx))
        self.T_c_lo = fs.T_ki[idx] + 0.05
        self.T_c_max = T_c_max

    def solve(self, pos, T_m, raised: Raised, ms: MSide | None = None, on_conv=None):
        """(T_c, n_HS) at T_m [K] for the positions pos (a task); NaN and an entry in ``raised``
        (indexed by position) where solve_Tc raises, after its diagnosis (p_c_high, p_m_above_p_c).
        ``on_conv(positions, T_c, n_HS)``: called as rows converge (their answer is final then)."""
        fs, idx = self.fs, self.idx[pos]
        lo = np.maximum(self.T_c_lo[pos], T_m + 0.05)
        hi = np.full(len(pos), self.T_c_max)
        n_HS = np.full(len(pos), np.nan)
        sub = Raised(len(pos))
        have = [ms]                     # the intermediate side: from the first evaluation (all rows)

        def F(p, x):
            if have[0] is None:
                ev = yield Eval(fs, idx[p], T_m[p], x)
                have[0] = mp = ev["ms"]
            else:
                mp = take(have[0], p)
                ev = yield Eval(fs, idx[p], T_m[p], x, mp)
            sub.put_eval(fs, p, idx[p], ev["err"], T_m[p], x, mp, ev)
            n_HS[p] = ev["n_HS"]
            return ev["r"], ev["err"] == E_OK

        x0 = np.minimum(np.maximum(self.T_c_guess[pos], lo + 0.5), hi)
        done = None if on_conv is None else (lambda p, x: on_conv(pos[p], x, n_HS[p]))   # noqa: E731
        x, _, slope, kind, msg = yield from secant_v(F, x0, self.slope_c[pos], ENERGY_TOL, lo, hi, _WHAT_TC, done)
        ms = have[0]
        sec = np.flatnonzero(kind == 2)
        sub.put(sec, np.ones(len(sec), dtype=np.int8), ["no_convergence"] * len(sec), msg[sec])
        cv = np.flatnonzero(kind != 0)
        cv = cv[sub.cls[cv] == 1]                     # ConvergenceError: the scalar's diagnosis
        if len(cv):
            yield from self._diagnose(pos[cv], idx[cv], T_m[cv], take(ms, cv), lo[cv], cv, sub)
        solved = kind == 0
        g = pos[solved]
        self.T_c_guess[g], self.slope_c[g] = x[solved], slope[solved]
        bad = np.flatnonzero(~solved)
        raised.put(pos[bad], sub.cls[bad], sub.code[bad], sub.msg[bad])
        return np.where(solved, x, np.nan), np.where(solved, n_HS, np.nan)

    def _diagnose(self, pos, idx, T_m, ms, lo, at, sub: Raised):
        """The ``except ConvergenceError`` of ``solve_Tc`` for rows whose entry in ``sub`` (at
        positions ``at``) is a ConvergenceError: p_c_high where even T_c_max leaves the duty
        unrejected, p_m_above_p_c where the condenser would work below p_m (either evaluation may
        raise instead), else the ConvergenceError stands."""
        fs, par = self.fs, self.fs.par
        k = len(idx)
        new = Raised(k)
        T_cm = np.full(k, self.T_c_max)
        ev = yield Eval(fs, idx, T_m, T_cm, ms)
        new.put_eval(fs, np.arange(k), idx, ev["err"], T_m, T_cm, ms, ev)
        high = np.flatnonzero((new.cls == 0) & (ev["r"] < 0.0))
        new.put(high, [2] * len(high), ["p_c_high"] * len(high),
                [f"the sink cannot take the heat: condensing pressure would exceed the design limit "
                 f"{par.p_c_max / BAR:.1f} bar(a)"] * len(high))
        check = np.flatnonzero((new.cls == 0) & (T_m + 0.05 >= self.T_c_lo[pos]))
        if len(check):
            ms2 = take(ms, check)
            ev2 = yield Eval(fs, idx[check], T_m[check], lo[check], ms2)
            new.put_eval(fs, check, idx[check], ev2["err"], T_m[check], lo[check], ms2, ev2)
            above = check[(ev2["err"] == E_OK) & (ev2["r"] > 0.0)]
            new.put(above, [2] * len(above), ["p_m_above_p_c"] * len(above),
                    [f"intermediate pressure {ms['p_m'][j] / BAR:.2f} bar(a) is not below the "
                     f"condensing pressure the sink allows" for j in above])
        repl = np.flatnonzero(new.cls != 0)
        sub.clear(at[repl])
        sub.put(at[repl], new.cls[repl], new.code[repl], new.msg[repl])


def _spawn(task):
    """Start ``task`` beside the current task (nothing for None)."""
    if task is not None:
        yield Spawn(task)


def bound_newton(fs: Flowsheet, idx, T_m, T_c, bound, lo, hi, T_c_lo, T_c_max, give_up=None):
    """``model.cycle._bound_newton`` from a cold start (finite-difference Jacobian) for the rows
    idx (a task): (T_m, T_c, ok); ok False where the scalar function returns None. ``give_up(pos)``:
    a task to start for the rows (positions) as soon as the function would return None for them."""
    n = len(idx)
    ok = (lo <= T_m) & (T_m <= hi) & (T_c_lo < T_c) & (T_c <= T_c_max) & (T_m < T_c - 0.05)
    done = np.zeros(n, dtype=bool)
    act = np.flatnonzero(ok)
    if give_up is not None and not ok.all():
        yield from _spawn(give_up(np.flatnonzero(~ok)))
    if not len(act):
        return T_m, T_c, done
    # F at the start and the two finite-difference points in one evaluation of 3x the rows
    h = 1e-3
    m3 = np.concatenate([T_m[act], T_m[act] + h, T_m[act]])
    c3 = np.concatenate([T_c[act], T_c[act], T_c[act] + h])
    ev = yield Eval(fs, np.concatenate([idx[act]] * 3), m3, c3)
    k = len(act)
    good = (ev["err"][:k] == E_OK) & (ev["err"][k:2 * k] == E_OK) & (ev["err"][2 * k:] == E_OK)
    r, nh = ev["r"], ev["n_HS"] - np.concatenate([bound[act]] * 3)
    F0, F1 = np.zeros(n), np.zeros(n)
    Ja, Jb, Jc, Jd = (np.zeros(n) for _ in range(4))
    F0[act], F1[act] = r[:k], nh[:k]
    Ja[act], Jb[act] = (r[k:2 * k] - r[:k]) / h, (r[2 * k:] - r[:k]) / h
    Jc[act], Jd[act] = (nh[k:2 * k] - nh[:k]) / h, (nh[2 * k:] - nh[:k]) / h
    if give_up is not None and not good.all():
        yield from _spawn(give_up(act[~good]))
    act = act[good]
    T_m, T_c = T_m.copy(), T_c.copy()
    for _ in range(BOUND_NEWTON_ITER):
        if not len(act):
            break
        conv = (np.abs(F0[act]) < ENERGY_TOL) & (np.abs(F1[act]) < SPEED_TOL)
        done[act[conv]] = True
        act = act[~conv]
        if not len(act):
            break
        a, b, c, d = Ja[act], Jb[act], Jc[act], Jd[act]
        f0, f1 = F0[act], F1[act]
        det = a * d - b * c
        fin = (det != 0.0) & np.isfinite(det)
        dm = -(d * f0 - b * f1) / det
        dc = -(a * f1 - c * f0) / det
        big = np.maximum(np.abs(dm), np.abs(dc))
        shrink = big > BOUND_NEWTON_STEP
        dm = np.where(shrink, dm * BOUND_NEWTON_STEP / big, dm)
        dc = np.where(shrink, dc * BOUND_NEWTON_STEP / big, dc)
        m1, c1 = T_m[act] + dm, T_c[act] + dc
        inside = fin & (lo[act] <= m1) & (m1 <= hi[act]) & (T_c_lo[act] < c1) & (c1 <= T_c_max) & (m1 < c1 - 0.05)
        if give_up is not None and not inside.all():
            yield from _spawn(give_up(act[~inside]))
        act, dm, dc, m1, c1 = act[inside], dm[inside], dc[inside], m1[inside], c1[inside]
        a, b, c, d, f0, f1 = a[inside], b[inside], c[inside], d[inside], f0[inside], f1[inside]
        if not len(act):
            break
        ev = yield Eval(fs, idx[act], m1, c1)
        good = ev["err"] == E_OK
        g0, g1 = ev["r"], ev["n_HS"] - bound[act]
        dd = dm * dm + dc * dc
        u0 = (g0 - f0) - (a * dm + b * dc)
        u1 = (g1 - f1) - (c * dm + d * dc)
        Ja[act], Jb[act] = a + u0 * dm / dd, b + u0 * dc / dd
        Jc[act], Jd[act] = c + u1 * dm / dd, d + u1 * dc / dd
        T_m[act], T_c[act], F0[act], F1[act] = m1, c1, g0, g1
        if give_up is not None and not good.all():
            yield from _spawn(give_up(act[~good]))
        act = act[good]
    if give_up is not None and len(act):
        yield from _spawn(give_up(act))                   # not converged in its iterations
    return T_m, T_c, done


def solve_cold(fs: Flowsheet, idx, T_m_sp, p_m_sp, T_c_max: float, out: Outcome, on_done=None):
    """``model.cycle._solve`` without a guess for the rows idx (their inputs passed the checks), as a
    task: fills ``out`` (code '' and branch, T_m, T_c where solved). The rows whose joint Newton
    gives up continue with the nested secants as tasks of their own, beside the others: the outcome
    of every row is final when all tasks have ended. ``on_done(rows)``: a task to start for
    flowsheet rows as soon as their outcome is final."""
    hs = fs.par.comp_HS
    n_max, n_min = hs.N_max / hs.N_nom, hs.N_min / hs.N_nom
    n = len(idx)
    T_c_lo = fs.T_ki[idx] + 0.05
    T_e = fs.T_e[idx]
    T_m_sp = T_m_sp[idx]
    tc = TcSolver(fs, idx, fs.T_ki[idx] + 1.3 * fs.Q_s[idx] / fs.C_w[idx] + 3.0, T_c_max)
    raised = Raised(n)

    def finish(pos):
        """Record the outcome of the rows pos (their solution is in ``out`` already)."""
        bad = pos[raised.cls[pos] != 0]
        out.fail(idx[bad], [FALLBACK if c == 3 else code for c, code in zip(raised.cls[bad], raised.code[bad])],
                 raised.msg[bad])
        if on_done is not None and len(pos):
            yield Spawn(on_done(idx[pos]))

    below = p_m_sp[idx] <= fs.p_e[idx] * 1.001       # the set point cannot be held: HS flat out
    branch = np.where(below, HS_MAX, SP).astype(np.int8)
    lo = np.where(below, T_e + 0.05, T_m_sp)
    hi = np.where(below, tc.T_c_guess - 0.1, np.nan)
    test = np.flatnonzero(~below)
    if len(test):
        # the branch test: the HS speed needed AT the set point
        T_c, n_sp = yield from tc.solve(test, T_m_sp[test], raised)
        out.T_c_sp[idx[test]] = T_c
        up, down = n_sp > n_max + SPEED_TOL, n_sp < n_min - SPEED_TOL
        branch[test] = np.where(up, HS_MAX, np.where(down, HS_MIN, SP))
        lo[test] = np.where(down, T_e[test] + 0.05, T_m_sp[test])
        hi[test] = np.where(down, T_m_sp[test], T_c - 0.1)
        sp = test[~(up | down) & np.isfinite(T_c)]
        yield from _final(tc, sp, T_m_sp[sp], SP, out, raised)
        yield from finish(test[(raised.cls[test] != 0) | ~(up | down)])
    r = np.flatnonzero((branch != SP) & (raised.cls == 0))
    if not len(r):
        return
    T_m0 = np.where((lo[r] < T_m_sp[r]) & (T_m_sp[r] < hi[r]), T_m_sp[r], 0.5 * (lo[r] + hi[r]))
    bound = np.where(branch[r] == HS_MAX, n_max, n_min)

    def nested(p):
        """The rows (positions p in r) whose joint Newton gave up: the nested secants."""
        q = r[p]
        yield from _nested(tc, q, T_m0[p], bound[p], lo[q], hi[q], branch[q], out, raised)
        yield from finish(q)

    T_m, T_c, ok = yield from bound_newton(fs, idx[r], T_m0, tc.T_c_guess[r], bound, lo[r], hi[r],
                                           np.maximum(T_c_lo[r], T_e[r] + 0.1), T_c_max, nested)
    j = r[ok]
    tc.T_c_guess[j] = T_c[ok]
    for b in (HS_MAX, HS_MIN):
        sel = branch[j] == b
        yield from _final(tc, j[sel], T_m[ok][sel], b, out, raised)
    yield from finish(j)


def _final(tc: TcSolver, pos, T_m, branch: int, out: Outcome, raised: Raised):
    """``T_c = solve_Tc(T_m)`` once the branch is settled (a task). The scalar starts its secant at
    the last T_c raised to 0.5 K above the lower limit: from the last T_c itself (it returns at
    once) unless that lies closer to the limit; then the secant runs again (warm slope), as here."""
    if not len(pos):
        return
    lo = np.maximum(tc.T_c_lo[pos], T_m + 0.05)
    T_c = tc.T_c_guess[pos].copy()
    again = ~((T_c >= lo + 0.5) & (T_c <= tc.T_c_max))
    if again.any():
        k = np.flatnonzero(again)
        T_c[k], _ = yield from tc.solve(pos[k], T_m[k], raised)
    ok = np.isfinite(T_c)
    rows = tc.idx[pos[ok]]
    out.branch[rows], out.T_m[rows], out.T_c[rows] = branch, T_m[ok], T_c[ok]


def _nested(tc: TcSolver, pos, T_m0, bound, lo, hi, branch, out: Outcome, raised: Raised):
    """The nested secants of ``_solve`` where the joint Newton gave up (a task): a secant on T_m for
    the HS speed bound (cold slope), each trial solving T_c warm from the last, and the
    hs_speed_low/high diagnosis where it raises ConvergenceError."""
    hs = tc.fs.par.comp_HS
    inner = Raised(len(tc.idx))

    def g(p, T_m):
        T_c, n_HS = yield from tc.solve(pos[p], T_m, inner)
        return n_HS - bound[p], np.isfinite(T_c)

    x, _, _, kind, msg = yield from secant_v(g, T_m0, np.zeros(len(pos)), SPEED_TOL, lo, hi, "@")
    q = pos
    conv = (kind == 2) | ((kind == 1) & (inner.cls[q] == 1))
    other = np.flatnonzero((kind == 1) & ~conv)
    raised.put(q[other], inner.cls[q[other]], inner.code[q[other]], inner.msg[q[other]])
    cv = np.flatnonzero(conv)
    if len(cv):
        first = [msg[k].replace("@", f"intermediate pressure at HS speed bound ({BRANCHES[branch[k]]})", 1)
                 if kind[k] == 2 else inner.msg[q[k]] for k in cv]
        diag = Raised(len(tc.idx))
        end = np.where(branch[cv] == HS_MIN, lo[cv], hi[cv])
        _, n_HS = yield from tc.solve(q[cv], end, diag)
        v = n_HS - bound[cv]
        for j, k in enumerate(cv):
            r = q[k]
            if diag.cls[r]:
                raised.put([r], [diag.cls[r]], [diag.code[r]], [diag.msg[r]])
            elif branch[k] == HS_MIN and v[j] < 0.0:
                raised.put([r], [2], ["hs_speed_low"],
                           [f"HS compressor at its minimum speed {hs.N_min:.0f} rpm moves more than the "
                            f"LS stage delivers: duty below the HS turndown"])
            elif branch[k] == HS_MAX and v[j] > 0.0:
                raised.put([r], [2], ["hs_speed_high"],
                           [f"HS compressor at its maximum speed {hs.N_max:.0f} rpm cannot carry the LS "
                            f"stage's flow at any intermediate pressure"])
            else:
                raised.put([r], [1], ["no_convergence"], [first[j]])
    done = np.flatnonzero(kind == 0)
    for b in (HS_MAX, HS_MIN):
        sel = done[branch[done] == b]
        yield from _final(tc, q[sel], x[sel], b, out, raised)
