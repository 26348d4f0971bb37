"""The LS speed controller's saturation (``ls_mode="float"`` of ``model.cycle.solve``) for many rows.

``model.cycle._solve_ls_float``: a row whose LS speed at the input T_source,out lies outside
[N_min, N_max] floats: T_source,out moves (up at N_max, down at N_min) until N_LS sits on the violated
bound; a row that cannot be solved at the input for too much duty (``OVERLOAD``) floats where the
cold solve at the far end of the range (T_source,in - 0.05 K) solves with N_LS <= N_max, and keeps
its failure otherwise (that far-end solve follows the scalar cold path, ``model.vsolve``).

The scalar solver finds the floating point by a secant on T_source,out whose trials are warm-started
full solves; here the root itself is solved, more directly, for the branch the row has there:

- "sp" (T_m at the set point): N_LS depends on T_source,out alone (the LS side), a 1-D secant
  safeguarded by its bracket; then the branch test at the floating point confirms "sp";
- at an HS speed bound (T_m floats): (T_source,out, T_m, T_c) by Newton with a finite-difference
  Jacobian and Broyden updates on (r, n_HS - bound, n_LS - n_bound); the branch holds where T_m lies
  on the bound's side of the set point.

The scalar search reaches that root unless its trials fail: it counts a trial that cannot be solved
as lying on the input's side. Its first trial (duty-proportional) lies beyond the root for a convex
N_LS(T_so); where the condenser cannot work above p_m there (p_m_above_p_c), the search walks away
from the root and fails the row (``ls_speed_high``/``low`` with the input's point, or the input's
failure): ``_first_trial`` reproduces that (one evaluation decides it for rows from an "sp" input;
a trial from an HS-bound point starts with the joint Newton at the bound, which holds at less duty,
and is not checked). A row that settles in neither, or outside the scalar search's range, goes to
the scalar path. The root is solved to 1e-11 in the LS speed ratio, the scalar one to 1e-7:
T_source,out differs by the scalar's tolerance (~5e-7 K). SI units.
"""
from __future__ import annotations

import numpy as np

from .cycle import ENERGY_TOL, LS_SPEED_LOOSE, OVERLOAD, SPEED_TOL
from .units import K_to_C
from .vflowsheet import E_OK, Flowsheet
from .vsolve import FALLBACK, HS_MAX, HS_MIN, SP, Outcome, Raised, TcSolver, solve_cold
from .vtasks import Eval, LSReq, Spawn

LS_TOL = 1e-11           # LS speed ratio on its bound
MAX_ITER = 40
STEP_MAX = 2.0           # K, the largest step of the joint Newton


class FloatLS:
    """The floating LS for one ``solve_many``: ``task(rows)`` is the task that floats the rows (whose
    outcome at the input is final) that need it; ``slots`` holds four copies of every row for the
    joint Newton's finite differences at an HS bound."""

    def __init__(self, fs: Flowsheet, T_m_sp, p_sp, T_c_max: float, out: Outcome, ls_limit) -> None:
        self.fs, self.T_m_sp, self.p_sp, self.T_c_max = fs, T_m_sp, p_sp, T_c_max
        self.out, self.ls_limit = out, ls_limit
        self.slots: Flowsheet | None = None
        self.n = fs.n            # the rows it floats (rows appended later are the warm path's)

    def task(self, todo):
        """Float T_source,out for the rows of ``todo`` that need it (see the module docstring): the
        rows above (below) the LS speed range at the input, and the rows the input overloads, once
        the far end of the range decides they float. Updates the flowsheet's source side, ``out``
        (branch, T_m, T_c, or the failure) and ``ls_limit``."""
        fs, out = self.fs, self.out
        ls = fs.par.comp_LS
        n_lo, n_hi = ls.N_min / ls.N_nom, ls.N_max / ls.N_nom
        T_in, T_sp = fs.T_si, fs.T_so
        solved = todo[out.code[todo] == ""]
        if len(solved):
            n_LS = fs.ls_speed(solved, out.T_m[solved])[0]
            high, low = n_LS > n_hi, n_LS < n_lo
            rows = np.concatenate([solved[high], solved[low]])
            if len(rows):
                # the scalar search's first trial: the duty in proportion to the speed bound
                n_b = np.concatenate([np.full(high.sum(), n_hi), np.full(low.sum(), n_lo)])
                x0 = T_in[rows] - (T_in[rows] - T_sp[rows]) * n_b / np.concatenate([n_LS[high], n_LS[low]])
                limit_max = np.concatenate([np.ones(high.sum(), bool), np.zeros(low.sum(), bool)])
                out.note_input(rows)
                yield Spawn(self._float(rows, x0, limit_max, None))
        # rows that cannot be solved at the input for too much duty: the far end decides
        over = todo[np.isin(out.code[todo], OVERLOAD)]
        if len(over):
            T_sp_over = T_sp[over].copy()
            fs.set_source(over, T_in[over] - 0.05)
            o2 = Outcome(len(fs.T_so))
            yield from solve_cold(fs, over, self.T_m_sp, self.p_sp, self.T_c_max, o2,
                                  lambda rows: self._after_far(rows, o2, T_sp_over, over))

    def _after_far(self, rows, o2: Outcome, T_sp_over, over):
        """Rows the input overloads whose cold solve at the far end (T_source,in - 0.05 K) is final:
        they float where it solves with N_LS <= N_max, else keep the input's failure."""
        fs, out = self.fs, self.out
        ls = fs.par.comp_LS
        n_hi = ls.N_max / ls.N_nom
        T_sp = T_sp_over[np.searchsorted(over, rows)]
        ok = o2.code[rows] == ""
        n_far = np.full(len(rows), np.inf)
        if ok.any():
            n_far[ok] = fs.ls_speed(rows[ok], o2.T_m[rows[ok]])[0]
        go = ok & (n_far <= n_hi)
        fs.set_source(rows[~go], T_sp[~go])
        for i in rows[~ok & (o2.code[rows] == FALLBACK)]:
            out.code[i] = FALLBACK                   # the scalar path settles what the far end gives
        r = rows[go]
        if not len(r):
            return
        out.branch[r], out.T_m[r], out.T_c[r] = o2.branch[r], o2.T_m[r], o2.T_c[r]
        kept = (out.code[r].copy(), out.msg[r].copy())
        out.code[r], out.msg[r] = "", ""
        fs.set_source(r, T_sp[go])
        x0 = T_sp[go] + 0.5 * (fs.T_si[r] - 0.05 - T_sp[go])
        yield from self._float(r, x0, np.ones(len(r), bool), kept)

    def _float(self, rows, x0, limit_max, kept):
        """The floating point of the rows (T_m, T_c and their branch there) from the first trial x0
        [K] of the scalar search; ``kept``: the input's failure (code, message) to restore where the
        search fails, for rows the input overloads (else the input's point is flagged)."""
        fs, out, T_m_sp, T_c_max = self.fs, self.out, self.T_m_sp, self.T_c_max
        ls = fs.par.comp_LS
        n_lo, n_hi = ls.N_min / ls.N_nom, ls.N_max / ls.N_nom
        T_in, T_sp = fs.T_si, fs.T_so[rows].copy()
        lo = np.where(limit_max, T_sp, np.maximum(T_sp - 15.0, fs.tab.T_triple + 5.0))
        hi = np.where(limit_max, T_in[rows] - 0.05, T_sp)
        x0 = np.minimum(np.maximum(x0, lo), hi)
        n_b = np.where(limit_max, n_hi, n_lo)
        state = dict(T_so=x0.copy(), T_m=out.T_m[rows].copy(), T_c=out.T_c[rows].copy(),
                     branch=out.branch[rows].copy(), done=np.zeros(len(rows), bool))
        guess_branch = state["branch"].copy()         # the scalar search's trials start from it
        tried = np.zeros((len(rows), 2), dtype=bool)   # [sp, bound] tried
        for _ in range(2):
            sp = np.flatnonzero(~state["done"] & (state["branch"] == SP) & ~tried[:, 0])
            if len(sp):
                tried[sp, 0] = True
                yield from _float_sp(fs, rows[sp], T_m_sp, T_sp[sp], n_b[sp], lo[sp], hi[sp], T_c_max, state, sp)
            bd = np.flatnonzero(~state["done"] & (state["branch"] != SP) & ~tried[:, 1])
            if len(bd):
                tried[bd, 1] = True
                yield from _float_bound(self._slots(), rows[bd], T_m_sp, n_b[bd], lo[bd], hi[bd], state, bd)
        fails = yield from _first_trial(fs, rows, T_m_sp, x0, n_b, limit_max, guess_branch, state)
        done = state["done"]
        fs.set_source(rows[done], state["T_so"][done])
        fs.set_source(rows[~done], T_sp[~done])
        r = rows[done]
        out.branch[r], out.T_m[r], out.T_c[r] = state["branch"][done], state["T_m"][done], state["T_c"][done]
        self.ls_limit[r] = np.where(limit_max[done], "max", "min")
        # the scalar search fails: the input's solution flagged (or, without one, the input's failure)
        for j in np.flatnonzero(fails):
            i = rows[j]
            if kept is not None:
                out.code[i], out.msg[i] = kept[0][j], kept[1][j]
            else:
                N_b = ls.N_max if limit_max[j] else ls.N_min
                out.flag[i] = "ls_speed_high" if limit_max[j] else "ls_speed_low"
                out.flag_msg[i] = (f"LS compressor at {N_b:.0f} rpm: no source outlet temperature in "
                                   f"{K_to_C(lo[j]):.2f}..{K_to_C(hi[j]):.2f} degC carries its flow")
        for i in rows[~done & ~fails]:
            out.code[i], out.msg[i] = FALLBACK, "LS float not settled"

    def _slots(self) -> tuple:
        """(flowsheet of four copies of every row, row count)."""
        fs = self.fs
        if self.slots is None:
            self.slots = fs.copy(np.tile(np.arange(self.n), 4))
        return self.slots, self.n


def _float_sp(fs: Flowsheet, rows, T_m_sp, T_sp, n_b, lo, hi, T_c_max, state: dict, at):
    """Rows floating with T_m at the set point (a task): N_LS(T_so) = N_b on the LS side alone
    (bracketed secant), then the branch test at the floating point (the T_c secant from the last
    T_c)."""
    T_m = T_m_sp[rows]
    k = len(rows)

    def f(x):
        n_LS = yield LSReq(fs, np.concatenate([rows] * (len(x) // k)), x, np.concatenate([T_m] * (len(x) // k)))
        return n_LS - np.concatenate([n_b] * (len(x) // k))

    x0 = state["T_so"][at]
    far = np.where(n_b > 1.0, hi, lo)               # N_max: toward T_in; N_min: toward colder
    f3 = yield from f(np.concatenate([T_sp, x0, far]))
    f_sp, f0, f_far = f3[:k], f3[k:2 * k], f3[2 * k:]
    first = np.sign(f0) != np.sign(f_sp)
    a, fa = np.where(first, T_sp, x0), np.where(first, f_sp, f0)
    b, fb = np.where(first, x0, far), np.where(first, f0, f_far)
    ok = np.isfinite(fa) & np.isfinite(fb) & (np.sign(fa) != np.sign(fb))
    x, conv = yield from _bracketed(f, a, fa, b, fb, ok)
    conv &= ok & (x > np.minimum(lo, hi)) & (x <= np.maximum(lo, hi))
    fs.set_source(rows, x)
    # the branch test at the floating point
    T_c0 = np.where(np.isfinite(state["T_c"][at]), state["T_c"][at], fs.T_ki[rows] + 30.0)
    tc = TcSolver(fs, rows, T_c0, T_c_max)
    raised = Raised(len(rows))
    T_c, n_sp = yield from tc.solve(np.arange(len(rows)), T_m, raised)
    hs = fs.par.comp_HS
    up, down = n_sp > hs.N_max / hs.N_nom + SPEED_TOL, n_sp < hs.N_min / hs.N_nom - SPEED_TOL
    good = conv & np.isfinite(T_c) & (raised.cls == 0)
    state["T_so"][at[good]], state["T_m"][at[good]], state["T_c"][at[good]] = x[good], T_m[good], T_c[good]
    state["done"][at[good & ~up & ~down]] = True
    # the HS cannot hold the set point at the floating point: it runs at its bound, T_m floats
    state["branch"][at[good & up]] = HS_MAX
    state["branch"][at[good & down]] = HS_MIN


def _bracketed(f, a, fa, b, fb, ok):
    """Roots of f (all rows at once; ``yield from f(x)``) in brackets [a, b] with f(a), f(b) of
    opposite signs: secant through the two newest points, bisection where it leaves the bracket
    (a task). Returns (x, converged)."""
    x_p, f_p, x, fx = a, fa, b, fb
    conv = np.zeros(len(a), bool)
    for _ in range(MAX_ITER):
        conv = ok & ((np.abs(fx) < LS_TOL) | (np.abs(b - a) < 1e-11))
        if np.all(conv | ~ok):
            break
        xn = x - fx * (x - x_p) / (fx - f_p)
        inside = (xn > np.minimum(a, b)) & (xn < np.maximum(a, b))
        xn = np.where(conv | ~ok, x, np.where(inside, xn, 0.5 * (a + b)))
        fn = yield from f(xn)
        ok &= np.isfinite(fn) | conv
        lo_side = np.sign(fn) == np.sign(fa)
        a, fa = np.where(lo_side & ~conv, xn, a), np.where(lo_side & ~conv, fn, fa)
        b, fb = np.where(~lo_side & ~conv, xn, b), np.where(~lo_side & ~conv, fn, fb)
        x_p, f_p = np.where(conv, x_p, x), np.where(conv, f_p, fx)
        x, fx = np.where(conv, x, xn), np.where(conv, fx, fn)
    return x, conv


def _first_trial(fs: Flowsheet, rows, T_m_sp, x0, n_b, limit_max, guess_branch, state: dict):
    """The scalar search counts a trial that cannot be solved as lying on the input's side. Its first
    trial (the duty-proportional estimate x0) lies beyond the root for a convex N_LS(T_so), with less
    duty; where the condenser then cannot work above p_m (p_m_above_p_c), the search walks away from
    the root and fails the row: every later trial lies beyond that one and none comes within
    LS_SPEED_LOOSE of the bound. A task; returns the rows whose search so fails.

    The scalar trial is a solve warm-started from the input's point. With T_m at the set point
    ("sp") it fails that way exactly where the condenser residual at the lowest condensing
    temperature, T_m + 0.05 K (or T_sink,in + 0.05 K), is already positive: no root above it. That is
    one evaluation here; a row whose evaluation there raises goes to the scalar path. A trial from an
    HS-bound point starts with the joint Newton at the bound, which holds at less duty: not checked."""
    T_so = state["T_so"]
    fails = np.zeros(len(rows), bool)
    beyond = state["done"] & np.where(limit_max, x0 > T_so + 1e-9, x0 < T_so - 1e-9) & (guess_branch == SP)
    chk = np.flatnonzero(beyond)
    if not len(chk):
        return fails
    r = rows[chk]
    fs.set_source(r, x0[chk])
    T_m = T_m_sp[r]
    lo = np.maximum(fs.T_ki[r] + 0.05, T_m + 0.05)
    ev = yield Eval(fs, r, T_m, lo)
    f0 = fs.ls_speed(r, T_m)[0] - n_b[chk]
    fs.set_source(r, T_so[chk])
    raised = ev["err"] != E_OK
    no_root = ~raised & (ev["r"] > 0.0)
    state["done"][chk[raised | no_root]] = False
    fails[chk[no_root & (np.abs(f0) > 2.0 * LS_SPEED_LOOSE)]] = True
    return fails


def _float_bound(slots, rows, T_m_sp, n_b, lo, hi, state: dict, at):
    """Rows floating with the HS at a speed bound (a task): Newton-Broyden on (T_so, T_m, T_c), on
    ``slots`` (a flowsheet with four copies of every row, and the row count: the point and one
    finite-difference step per unknown evaluate together)."""
    g, n = slots
    hs = g.par.comp_HS
    k = len(rows)
    br = state["branch"][at]
    bound = np.where(br == HS_MAX, hs.N_max, hs.N_min) / hs.N_nom
    X = np.stack([state["T_so"][at], state["T_m"][at], state["T_c"][at]], axis=1)
    ok = np.all(np.isfinite(X), axis=1)
    X = np.where(ok[:, None], X, 300.0)
    h = 1e-3
    X4 = np.tile(X, (4, 1))
    for j in range(3):
        X4[(j + 1) * k:(j + 2) * k, j] += h
    s4 = np.concatenate([rows + j * n for j in range(4)])
    F4, e4 = yield from _residual(g, s4, X4, np.tile(bound, 4), np.tile(n_b, 4))
    ok &= np.all(e4.reshape(4, k) == E_OK, axis=0)
    F = F4[:k]
    J = np.stack([(F4[(j + 1) * k:(j + 2) * k] - F) / h for j in range(3)], axis=2)   # (k, 3, 3)
    base = rows
    scale = np.array([ENERGY_TOL, SPEED_TOL, LS_TOL])
    conv = np.zeros(k, bool)
    for _ in range(MAX_ITER):
        conv |= ok & np.all(np.abs(F) < scale, axis=1)
        act = np.flatnonzero(ok & ~conv)
        if not len(act):
            break
        try:
            dX = -np.linalg.solve(J[act], F[act][:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            ok[act] = False
            break
        big = np.max(np.abs(dX), axis=1)
        dX = np.where((big > STEP_MAX)[:, None], dX * (STEP_MAX / np.maximum(big, 1e-300))[:, None], dX)
        Xn = X[act] + dX
        inside = (Xn[:, 0] >= lo[act]) & (Xn[:, 0] <= hi[act]) & (Xn[:, 1] < Xn[:, 2] - 0.05)
        ok[act[~inside]] = False
        act, dX, Xn = act[inside], dX[inside], Xn[inside]
        if not len(act):
            break
        Fn, e = yield from _residual(g, base[act], Xn, bound[act], n_b[act])
        good = e == E_OK
        ok[act[~good]] = False
        dF = Fn - F[act]
        u = dF - np.einsum("kij,kj->ki", J[act], dX)
        J[act] += u[:, :, None] * dX[:, None, :] / np.sum(dX * dX, axis=1)[:, None, None]
        X[act], F[act] = Xn, Fn
    side = np.where(br == HS_MAX, X[:, 1] > T_m_sp[rows] + 1e-6, X[:, 1] < T_m_sp[rows])
    fin = conv & side
    j = at[fin]
    state["T_so"][j], state["T_m"][j], state["T_c"][j] = X[fin, 0], X[fin, 1], X[fin, 2]
    state["done"][j] = True
    back = at[conv & ~side]                         # the HS holds the set point there: "sp"
    state["branch"][back] = SP
    state["T_so"][back] = X[conv & ~side, 0]


def _residual(g: Flowsheet, idx, X, bound, n_b):
    """(r, n_HS - bound, n_LS - n_b) at X = (T_so, T_m, T_c) for the rows idx of g, and err (a
    task)."""
    g.set_source(idx, X[:, 0])
    ev = yield Eval(g, idx, X[:, 1], X[:, 2], full=True)
    err = np.where(g.src_ok[idx], ev["err"], 9)
    F = np.stack([ev["r"], ev["n_HS"] - bound, ev["n_LS"] - n_b], axis=1)
    return F, err
