"""COP-optimal intermediate-pressure set point for a window of operation (SPEC §6).

Objective: the period COP = sum(Q_sink) / sum(W_total) over the window's samples, simulated with the
(adaptive) model at one set point p_m,sp for the whole window, subject to p_e <= p_m,sp <= p_c
(window-wide: the highest p_e and the lowest p_c of the window at the current set points) and the
compressors' speed limits, which the model handles as the plant's controllers do
(``ls_mode="float"``): below the set point the HS compressor can reach at 1800 rpm it runs there and
p_m floats above the set point, so COP(p_m,sp) is *flat* there; at a set point that asks more of the
LS compressor than 1800 rpm gives, T_source,out floats and the heat output drops. A derivative-based
search stalls on plateaus, so the search is:

1. a coarse scan of the bounded range (``coarse_step``, default 0.5 bar) on a few of the window's
   rows (cheap; it only has to find the right bracket), in two levels: every second grid point, then
   the neighbours of the points that solve and are feasible (the same result as the whole grid
   unless the feasible set has a stretch narrower than two grid points);
2. Brent's method on the evaluation rows within one coarse step either side of the best scan point,
   ``xtol`` 0.01 bar: from the bracket the scan found (the best point and its two neighbours, when it
   beats both), else a bounded search (``scipy.optimize.minimize_scalar(method="bounded")``);
3. the better of the Brent result and the best scan point.

On the plateau (every row HS-saturated at the optimum) every set point below the floating p_m gives
the same COP; the recommended set point is then the floating p_m itself (the lowest p_m the HS
compressor can hold), reported with ``hs_saturated`` True.

Evaluation rows: the whole window, or (``representative=k``) k representative operating points —
the window's samples grouped in k equal-count quantiles along the first principal component of their
(normalised) inputs, each group replaced by its mean and weighted by its size. The period COP is then
sum(w Q) / sum(w W). The answer is re-checked on the whole window (COP and heat output at the optimum
and at the actual set point come from the whole window). This is the approximation that makes replay
an order of magnitude cheaper (issue #12); the benchmark states how far it moves the optimum.

``feasible(frame) -> bool`` restricts the set points (e.g. to the region where learned compressor
curves are trusted, issue #8); infeasible candidates count as no solution.

Set points are in bar(g) like the PLC's register (``_barg``); pressures in bar absolute (``_bar_a``).
A sample the model cannot solve at the window's actual set points is left out of the window; a
sample that stops solving at a candidate set point makes that candidate infeasible.
"""
from __future__ import annotations

import bisect
import dataclasses
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from . import batch
from .batch import INPUT_COLUMNS, InputColumns, among, frame_of, matrix, simulate_batch, solve_rows
from .params import PlantParams
from .units import BAR, Pa_to_barg

COARSE_STEP = 0.5         # bar, coarse scan resolution
XTOL = 0.01               # bar, Brent tolerance on the set point
SUBSAMPLE = 12            # rows used by the coarse scan
BOUND_MARGIN = 0.05       # bar, kept clear of p_e and p_c
PLATEAU_RTOL = 1e-9       # COP differences below this (relative) are ties
# The search's shortcuts (issue 12), each switchable so that ``hp-edge bench --only replay`` can
# compare the fast path with the plain search on the same data (module switches: set them before a
# sequential replay in this process; worker processes keep the defaults):
TWO_LEVEL_SCAN = True     # every second grid point first, then the neighbours of feasible ones
EDGE_SHORTCUT = True      # no Brent search when the best grid point is the feasible stretch's edge
BRENT_FROM_BRACKET = True # Brent's parabolic steps from the scan's bracket instead of a bounded search
FINE_STEP = 0.05          # bar: the vectorised search's refinement grid around the best coarse point
SOLVED = ("ok", "negative_pinch")   # row outcomes that count as operated (ls_mode="float")
GUESS_BAR = 1.0           # bar: a row's own solution this close in set point is its warm start
PLATEAU_REUSE_BAR = 0.01  # bar: below a row's floating p_m by this, its plateau solution is reused
COLUMNS = ("Q_sink_kW", "W_total_kW", "p_e_bar", "p_c_bar", "p_m_bar", "hs_saturated", "COP",
           "N_LS_rpm", "N_HS_rpm", "ls_saturated", "T_source_out_C", "eta_is_LS", "eta_is_HS",
           "W_LS_kW", "W_HS_kW")


class OptimizationError(ValueError):
    """No set point can be optimised for this window (no solvable samples, empty range)."""


@dataclass
class SetpointResult:
    p_m_sp_opt_barg: float          # recommended set point [bar(g)]
    p_m_opt_bar_a: float            # intermediate pressure at the optimum, window mean [bar abs]
    p_m_gm_bar_a: float             # geometric mean sqrt(p_e * p_c), window means [bar abs]
    p_m_sp_actual_barg: float       # the window's actual set point (mean) [bar(g)]
    COP_opt: float                  # period COPs (sum Q / sum W)
    COP_actual: float
    COP_gm: float
    Q_sink_opt_kW: float            # mean heat output
    Q_sink_actual_kW: float
    Q_sink_gm_kW: float
    dCOP_opt_pct: float             # (COP_opt / COP_actual - 1) * 100
    dQ_sink_opt_pct: float
    dCOP_gm_pct: float              # optimum against the geometric mean
    dQ_sink_gm_pct: float
    hs_saturated: bool              # optimum on the HS-speed plateau
    bounds_barg: tuple[float, float]
    n_samples: int
    n_dropped: int
    model_evaluations: int          # evaluations of the evaluation rows (or the scan subsample)
    run_time_s: float
    n_eval_rows: int = 0            # rows the search evaluated (representative points or all)
    ls_saturated: bool = False      # at the optimum some sample's LS sits at its speed limit

    def to_dict(self) -> dict:
        d = asdict(self)
        d["bounds_barg"] = list(self.bounds_barg)
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    def summary(self) -> str:
        return (f"optimum p_m,sp {self.p_m_sp_opt_barg:.2f} bar(g) (p_m {self.p_m_opt_bar_a:.2f} bar a"
                f"{', HS at full speed' if self.hs_saturated else ''}); geometric mean "
                f"{self.p_m_gm_bar_a:.2f} bar a; actual set point {self.p_m_sp_actual_barg:.2f} bar(g)\n"
                f"  COP {self.COP_actual:.3f} -> {self.COP_opt:.3f} ({self.dCOP_opt_pct:+.2f} %), heat "
                f"{self.Q_sink_actual_kW:.0f} -> {self.Q_sink_opt_kW:.0f} kW ({self.dQ_sink_opt_pct:+.2f} %); "
                f"against the geometric mean {self.dCOP_gm_pct:+.2f} % COP, {self.dQ_sink_gm_pct:+.2f} % heat\n"
                f"  {self.n_samples} samples ({self.n_dropped} left out), {self.model_evaluations} "
                f"evaluations of {self.n_eval_rows} rows, {self.run_time_s:.2f} s")


@dataclass(eq=False)
class Point:
    """The period figures of the evaluation rows at one set point. The per-row model outputs are
    ``frame`` (a DataFrame, built on first use when the point came from the vectorised solver) and
    ``col(name)`` (one of its columns as an array, without building it)."""
    sp: float                       # set point [bar(g)]
    COP: float                      # sum(w Q) / sum(w W); NaN when a row is not solved
    Q_sink_kW: float                # weighted mean
    W_kW: float
    hs_saturated: bool              # every row HS-saturated
    _frame: pd.DataFrame | None     # per-row model outputs (None: built from ``cols``)
    beyond: float | None = None     # search: a better set point just outside the feasible set
    _vres: object = None            # ``vres``, or (VResult, first row, end row) not taken yet
    cols: "dict | PartColumns | None" = None   # the frame's columns as arrays (VResult.columns)
    index: object = None            # the frame's index, with ``cols``

    @property
    def vres(self):
        """The vectorised solver's result of these rows (``model.vcycle.VResult``), if any. A
        point of a call over several set points holds the call's result and its rows' range until
        this is first read (most points' never is: only the nearest to a later call's set points
        start it)."""
        v = self._vres
        if type(v) is tuple:
            v = self._vres = _take(v[0], np.arange(v[1], v[2]))
        return v

    @vres.setter
    def vres(self, v) -> None:
        self._vres = v

    @property
    def has_vres(self) -> bool:
        return self._vres is not None

    def __getstate__(self):
        self.vres       # noqa: B018 - a pickled point carries its own rows, not the whole call's
        if "_memo" in self.__dict__:
            return {k: v for k, v in self.__dict__.items() if k != "_memo"}
        return self.__dict__

    @property
    def memo(self) -> dict:
        """Figures its readers derive from the point, kept with it by them (each under its own key,
        with what it was derived with, to check; not pickled)."""
        m = self.__dict__.get("_memo")
        if m is None:
            m = self.__dict__["_memo"] = {}
        return m

    @property
    def ok(self) -> bool:
        return math.isfinite(self.COP)

    @property
    def frame(self) -> pd.DataFrame:
        if self._frame is None:
            from .vcycle import columns_frame
            self._frame = columns_frame(self.cols, self.index)
        return self._frame

    def status_in(self, choices: tuple) -> np.ndarray:
        """``among(self.col("status"), choices)``."""
        return status_in(self.cols, choices) if self.cols is not None else among(self.col("status"), choices)

    def col(self, name: str) -> np.ndarray:
        """The column ``name`` of ``frame`` as an array (floats; objects for status and reason)."""
        if self.cols is not None:
            return self.cols[name]
        v = self._frame[name]
        return v.to_numpy(dtype=float) if pd.api.types.is_numeric_dtype(v.dtype) else v.to_numpy()


def groups(data: pd.DataFrame, k: int, X: np.ndarray | None = None) -> list[np.ndarray]:
    """Row positions of ``data`` in k groups of similar operation: the samples sorted along the
    first principal component of their standardised inputs, split into k nearly equal parts
    (one group per row when k >= len(data)). ``X``: ``matrix(data)`` when the caller has it."""
    X = matrix(data) if X is None else X
    n = len(X)
    if k >= n:
        return [np.array([i]) for i in range(n)]
    sd = X.std(axis=0)
    Z = (X - X.mean(axis=0)) / np.where(sd > 0, sd, 1.0)
    try:
        _, _, Vt = np.linalg.svd(Z, full_matrices=False)
        order = np.argsort(Z @ Vt[0], kind="stable")
    except np.linalg.LinAlgError:
        order = np.arange(n)
    return [g for g in np.array_split(order, k) if len(g)]


def representative(data: pd.DataFrame, k: int, parts: list[np.ndarray] | None = None,
                   X: np.ndarray | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """k representative rows of ``data`` (canonical inputs) and their weights (sample counts):
    each group of ``groups(data, k)`` replaced by its mean (the data itself when k >= len(data)).
    ``X``: ``matrix(data)`` when the caller has it."""
    X = matrix(data) if X is None else X
    parts = parts if parts is not None else groups(data, k, X=X)
    rows = np.array([X[g].mean(axis=0) for g in parts])
    w = np.array([len(g) for g in parts], dtype=float)
    return pd.DataFrame(rows, columns=list(INPUT_COLUMNS)), w


class Evaluator:
    """Simulates evaluation rows at a set point (one value for all rows), with a cache.

    Every row remembers its solutions: a row is warm-started from its own solution at the nearest
    set point already evaluated (within ``GUESS_BAR``; the Brent steps and the uncertainty draws
    then converge in one or two flowsheet evaluations), else from the previous row's. On the
    HS-speed plateau the solution does not depend on the set point (the HS runs flat out and p_m
    floats above it), so a row that ran there at one set point answers every lower set point without
    a solve. ``guess_from``: another Evaluator on the same rows (other parameters, e.g. an
    uncertainty draw) whose solutions are warm starts too. The results depend on the order of the
    calls only within the solver's tolerances, and a given sequence of calls always gives the same
    numbers."""

    def __init__(self, rows: pd.DataFrame, weights: np.ndarray, params: PlantParams,
                 ls_mode: str = "float", guess_from: "Evaluator | None" = None,
                 seed: tuple | None = None) -> None:
        self.rows = rows.reset_index(drop=True)
        self.w = np.asarray(weights, dtype=float)
        self.params = params
        self.ls_mode = ls_mode
        self.evals = 0
        self.solves = 0
        self._cache: dict[float | None, Point] = {}
        self._warm_keys: list[float] = []   # the cached set points whose points hold a solver result, sorted
        self._in: InputColumns | None = None
        self._own_sp = self._input_columns()["p_m_sp"] if "p_m_sp" in self.rows else None
        self._mem: list[list] = [[] for _ in range(len(self.rows))]     # per row: [(sp, row)]
        self._plateau: list = [None] * len(self.rows)                   # per row: (p_m_barg, row)
        # the vectorised solver's plateaus: per row the floating p_m [bar(g)] (NaN: none yet) and
        # (the solver call's VResult, the row's position in it)
        self._plateau_v = np.full(len(self.rows), np.nan)
        self._plateau_src: list = [None] * len(self.rows)
        self._other = guess_from if guess_from is not None and len(guess_from.rows) == len(self.rows) \
            else None
        # the vectorised solver starts rows from another evaluator's rows too when they are other
        # rows (e.g. the window's samples from its representative points): each from the nearest
        self._seed = guess_from if guess_from is not None and self._other is None else None
        if self._seed is None and seed is not None and seed[0] is not None:
            # (VResult, its rows): solutions of other rows at their own set points (e.g. the
            # condenser factor's), a start for these rows at theirs, each from the nearest
            self._seed = Evaluator._holding(seed[1], params, seed[0])
        self._seed_map = nearest_rows(self._input_columns(), self._seed._input_columns()) \
            if self._seed is not None else None

    @staticmethod
    def _holding(rows: pd.DataFrame, params: PlantParams, vres) -> "Evaluator":
        """An Evaluator of ``rows`` whose own-set-point solution is ``vres`` (a seed)."""
        ev = Evaluator(rows, np.ones(len(rows)), params)
        p = _point(None, None, ev.w, cols=vres.columns(COLUMNS), index=ev.rows.index)
        p.vres = vres
        ev._cache[None] = p
        return ev

    def _nearest(self, i: int, sp: float):
        """The warm start of row i at set point sp: its own solution nearest in set point (the
        condensing temperature interpolated to sp from the two nearest where both held the set
        point), else the other evaluator's, else None (the previous row's)."""
        for own, mem in ((True, self._mem[i]), (False, self._other._mem[i] if self._other is not None else ())):
            near = sorted(((abs(x - sp), x, row) for x, row in mem if abs(x - sp) <= GUESS_BAR),
                          key=lambda t: t[0])
            if not near:
                continue
            g = near[0][2][2]
            if own and len(near) >= 2 and near[0][0] > 0.0:
                (_, x0, r0), (_, x1, r1) = near[0], near[1]
                a, b = r0[2], r1[2]
                if x1 != x0 and a.branch == b.branch == "sp" and not a.ls_limit and not b.ls_limit:
                    g = dataclasses.replace(a, T_c=a.T_c + (b.T_c - a.T_c) * (sp - x0) / (x1 - x0))
            return g
        return None

    @staticmethod
    def _key(sp: float | None) -> float | None:
        """The cache's key of set point ``sp`` (None: the rows' own)."""
        return None if sp is None else round(float(sp), 9)

    def holds(self, sps) -> bool:
        """Whether every set point of ``sps`` is cached (``at_many`` would not solve)."""
        return all(self._key(sp) in self._cache for sp in sps)

    def at(self, sp: float | None, rows: np.ndarray | None = None) -> Point:
        """Figures at set point ``sp`` [bar(g)] (None: each row's own p_m_sp). ``rows`` picks a
        subset (not cached)."""
        key = self._key(sp)
        if rows is None and key in self._cache:
            return self._cache[key]
        if batch.VECTORISED:
            if rows is None:
                return self.at_many([sp])[0]
            return self._solve_v([sp], np.asarray(rows, dtype=int))[0]
        self.evals += 1
        idx = np.arange(len(self.rows)) if rows is None else np.asarray(rows, dtype=int)
        w = self.w if rows is None else self.w[idx]
        sps = self._own_sp[idx] if sp is None else np.full(len(idx), float(sp))
        amb = self.params.ambient_pressure / BAR
        out: list = [None] * len(idx)
        todo = []
        for j, (i, x) in enumerate(zip(idx, sps)):
            pl = self._plateau[i]
            if pl is not None and x <= pl[0] - PLATEAU_REUSE_BAR:
                out[j] = pl[1]
            else:
                todo.append(j)
        if todo:
            sel = idx[todo]
            solved = solve_rows(self.rows.iloc[sel], self.params, p_m_sp=sps[todo], ls_mode=self.ls_mode,
                                guesses=[self._nearest(i, x) for i, x in zip(sel, sps[todo])])
            self.solves += len(todo)
            for j, i, x, r in zip(todo, sel, sps[todo], solved):
                out[j] = r
                res = r[2]
                if res is None:
                    continue
                self._mem[i].append((float(x), r))
                if res.branch == "hs_max" and r[0] in SOLVED:
                    p_float = float(Pa_to_barg(res.p_m, amb))
                    if self._plateau[i] is None:
                        self._plateau[i] = (p_float, r)
        f = frame_of(out, self.params, COLUMNS, self.rows.index[idx])
        p = _point(sp, f, w)
        if rows is None:
            self._cache[key] = p
        return p


    def at_many(self, sps) -> list[Point]:
        """``at`` for several set points (None: the rows' own); with VECTORISED the ones not cached
        yet are solved in one call of the vectorised solver."""
        keys = [self._key(sp) for sp in sps]
        if not batch.VECTORISED:
            return [self.at(sp) for sp in sps]
        todo = list(dict.fromkeys(k for k in keys if k not in self._cache))
        if todo:
            for k, p in zip(todo, self._solve_v(todo, np.arange(len(self.rows)))):
                self._cache[k] = p
                if k is not None:
                    bisect.insort(self._warm_keys, k)
        return [self._cache[k] for k in keys]

    def _solve_v(self, sps: list, idx: np.ndarray) -> list[Point]:
        """The rows ``idx`` at each set point of ``sps`` (None: their own), one solve_many call."""
        from .vcycle import solve_many
        k, n = len(sps), len(idx)
        self.evals += k
        own = self._own_sp[idx] if self._own_sp is not None else np.full(n, np.nan)
        sp_all = np.concatenate([own if sp is None else np.full(n, float(sp)) for sp in sps])
        row_all = np.tile(idx, k)
        guess, gidx = self._guesses(sps, idx)
        # a row that ran on the HS-speed plateau answers every set point PLATEAU_REUSE_BAR or more
        # below its floating p_m without a solve (as the scalar path's ``at``)
        p_pl = self._plateau_v[row_all]
        with np.errstate(invalid="ignore"):
            reuse = np.isfinite(p_pl) & (sp_all <= p_pl - PLATEAU_REUSE_BAR)
        todo = np.flatnonzero(~reuse)
        self.solves += len(todo)
        sub = None
        if len(todo):
            sub = solve_many(self._input_columns().take(row_all[todo]), self.params, p_m_sp=sp_all[todo],
                             ls_mode=self.ls_mode, guess=guess,
                             guess_index=None if gidx is None else gidx[todo])
            self._note_plateaus(sub, row_all[todo])
        vres = sub if len(todo) == len(row_all) else self._with_plateaus(sub, todo, reuse, row_all)
        solved, shared, outs = vres.solved(), {}, _Outputs(vres)
        w = self.w[idx]
        index = self.rows.index[idx]
        out = []
        for j, p in enumerate(_points(sps, w, outs, solved, shared, index)):
            # a one-set-point call's result is the point's own; else taken when first read
            p.vres = vres if k == 1 else (vres, j * n, (j + 1) * n)
            out.append(p)
        return out

    def _note_plateaus(self, vres, rows: np.ndarray) -> None:
        """Remember, for each row of this evaluator first seen on the HS-speed plateau in ``vres``
        (a solver call over ``rows``), its floating p_m and where its solution is."""
        on = (np.asarray(vres.branch) == "hs_max") & among(np.asarray(vres.status, dtype=object), SOLVED)
        on &= np.isnan(self._plateau_v[rows])
        for pos in np.flatnonzero(on):
            i = int(rows[pos])
            if np.isnan(self._plateau_v[i]):          # the first of a row's plateaus in the call
                self._plateau_v[i] = float(vres.values["p_m_barg"][pos])
                self._plateau_src[i] = (vres, int(pos))

    def _with_plateaus(self, sub, todo: np.ndarray, reuse: np.ndarray, row_all: np.ndarray):
        """The call's whole result: the rows ``todo`` from ``sub`` (the solver's answer, None when
        every row was on a known plateau), the rows ``reuse`` (a mask) the plateau solutions of
        their rows."""
        from .vcycle import concat_rows, take_rows
        order = np.empty(len(row_all), dtype=int)
        parts, base = [], 0
        if sub is not None:
            order[todo] = np.arange(len(todo))
            parts.append(sub)
            base = len(todo)
        groups: dict = {}
        for p in np.flatnonzero(reuse):
            src, pos = self._plateau_src[int(row_all[p])]
            g = groups.setdefault(id(src), (src, [], []))
            g[1].append(pos)
            g[2].append(p)
        for src, pos, at in groups.values():
            parts.append(take_rows(src, np.asarray(pos, dtype=int)))
            order[np.asarray(at, dtype=int)] = base + np.arange(len(pos))
            base += len(pos)
        return take_rows(concat_rows(parts), order)

    def _input_columns(self) -> InputColumns:
        """The rows' input columns as floats, read once (the solver's rows for every call)."""
        if self._in is None:
            self._in = InputColumns.of(self.rows)
        return self._in

    def _guess_for(self, sp):
        """(warm-start state, its rows, its per-row keys, row index into it) to start set point
        ``sp`` from: this evaluator's own solution at the nearest set point within GUESS_BAR, else
        the other evaluator's (``guess_from``: other parameters) at the same or nearest one, else
        the seed evaluator's (other rows, each row from the nearest) likewise; None when there is
        none. For None (the rows' own set points) only another evaluator's own set points serve."""
        for ev, rmap in ((self, None), (self._other, None), (self._seed, self._seed_map)):
            if ev is None:
                continue
            if sp is None:
                p = ev._cache.get(None)
                if p is not None and p.has_vres and ev is not self:
                    st, m, rk = _state_of(p)
                    return st, m, rk, (np.arange(m) if rmap is None else rmap)
                continue
            # the nearest cached set point with a solver result (of the two beside sp: the
            # distances of set points on one side grow with their distance, ties go to the
            # smaller set point as before)
            keys = ev._warm_keys
            i = bisect.bisect_left(keys, sp)
            near = [(abs(x - sp), x) for x in keys[max(i - 1, 0):i + 1] if abs(x - sp) <= GUESS_BAR]
            if near:
                st, m, rk = _state_of(ev._cache[min(near)[1]])
                return st, m, rk, (np.arange(m) if rmap is None else rmap)
        return None

    def _guesses(self, sps: list, idx: np.ndarray):
        """(guess, guess_index) for solve_many over ``sps`` x rows ``idx`` (the guess a
        ``model.vcycle.WarmStart``: the neighbours' warm-start states, which is all the solver
        reads of a VResult guess), or (None, None) when no set point has a solved neighbour. Only
        whole-row evaluations serve."""
        if len(idx) != len(self.rows):
            return None, None
        from .vcycle import WarmStart
        n = len(idx)
        parts, index, base = [], [], 0
        for sp in sps:
            g = self._guess_for(sp)
            if g is None:
                index.append(np.full(n, -1))
            else:
                parts.append(g[:3])
                index.append(base + g[3])
                base += g[1]
        if not parts:
            return None, None
        if len(parts) == 1:
            return WarmStart(*parts[0][:2]), index[0] if len(index) == 1 else np.concatenate(index)
        # the states stacked as ``vcycle.stack_rows`` does (its per-row test made once per solver
        # result, in ``_row_keys``): a key per-row in every part concatenated, else the first part's
        first, _, rk0 = parts[0]
        state = {}
        for k, x in first.items():
            if k in rk0 and all(k in rk for _, _, rk in parts):
                state[k] = np.concatenate([st[k] for st, _, _ in parts])
            else:
                state[k] = x
        return WarmStart(state, base), np.concatenate(index)


def _row_keys(v) -> frozenset:
    """The keys of a solver result's warm-start state whose values are per-row arrays (kept with
    the result: a call's result serves many points)."""
    rk = v.__dict__.get("_row_keys")
    if rk is None:
        m = len(v)
        rk = v.__dict__["_row_keys"] = frozenset(
            k for k, x in v.state.items() if isinstance(x, np.ndarray) and x.shape[:1] == (m,))
    return rk


def _state_of(p: Point) -> tuple[dict, int, frozenset]:
    """(``p.vres.state``, ``len(p.vres)``, the state's per-row keys) without taking the point's rows
    of its call's result when they are not taken yet: the state's per-row arrays sliced to them
    (the same numbers as ``take_rows``' copies)."""
    v = p._vres
    if type(v) is tuple:
        whole, a, b = v
        rk = _row_keys(whole)
        return {k: (x[a:b] if k in rk else x) for k, x in whole.state.items()}, b - a, rk
    return v.state, len(v), _row_keys(v)


def draw_points(rows: pd.DataFrame, w: np.ndarray, params: PlantParams, sps: list, R_th_f,
                deltas: dict, guess_from: "Evaluator | None" = None,
                ls_mode: str = "float") -> list[list[Point]]:
    """The rows at each set point of ``sps`` under K parameter draws in one call of the vectorised
    solver: out[k][j] is the Point ``Evaluator(rows, w, draw k, ls_mode, guess_from).at_many(sps)[j]``
    gives, draw k being ``params`` with R_th,f ``R_th_f[k]`` and the learned curves' differences
    ``deltas[key][k]`` (``model.vcycle.solve_many``'s ``deltas`` keys, (K, 6) arrays). Each draw's
    rows start from ``guess_from``'s solutions as such an Evaluator's would, so the answers are
    those of K separate Evaluators."""
    from .vcycle import solve_many
    R = np.asarray(R_th_f, dtype=float)
    k, m, n = len(R), len(sps), len(rows)
    probe = Evaluator(rows, w, params, ls_mode=ls_mode, guess_from=guess_from)
    idx = np.arange(n)
    guess, gidx = probe._guesses(list(sps), idx)
    own = probe._own_sp if probe._own_sp is not None else np.full(n, np.nan)
    sp_one = np.concatenate([own if sp is None else np.full(n, float(sp)) for sp in sps])
    vres = solve_many(probe._input_columns().take(np.tile(idx, m * k)), params, p_m_sp=np.tile(sp_one, k),
                      ls_mode=ls_mode, guess=guess, guess_index=None if guess is None else np.tile(gidx, k),
                      R_th_f=np.repeat(R, m * n),
                      deltas={key: np.repeat(np.asarray(a, dtype=float), m * n, axis=0)
                              for key, a in deltas.items()})
    solved, shared, outs = vres.solved(), {}, _Outputs(vres)
    out = []
    for d in range(k):
        pts = []
        for j, sp in enumerate(sps):
            part = slice((d * m + j) * n, (d * m + j + 1) * n)
            pts.append(_point(sp, None, probe.w, cols=PartColumns(outs, solved, part, shared),
                              index=probe.rows.index))
        out.append(pts)
    return out


def nearest_rows(rows, other) -> np.ndarray:
    """For each row of ``rows`` the position of the nearest row of ``other`` in the standardised
    inputs (INPUT_COLUMNS, scaled by ``other``'s spread or 1). Both DataFrames or
    ``model.batch.InputColumns``."""
    a = matrix(rows)
    b = matrix(other)
    sd = np.nanstd(np.vstack([a, b]), axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    d = (((a[:, None, :] - b[None, :, :]) / sd) ** 2).sum(axis=2)
    return np.argmin(np.nan_to_num(d, nan=np.inf), axis=1).astype(int)


def _take(v, idx: np.ndarray):
    """The rows ``idx`` of a VResult (``model.vcycle.take_rows``)."""
    from .vcycle import take_rows
    return take_rows(v, idx)


class _Outputs:
    """A solver call's outputs that ``PartColumns`` reads (COLUMNS, status, reason)."""
    __slots__ = ("values", "status", "reason")

    def __init__(self, vres) -> None:
        self.values = {c: vres.values[c] for c in COLUMNS}
        self.status, self.reason = vres.status, vres.reason


class PartColumns(Mapping):
    """``VResult.columns(COLUMNS)``'s arrays for the rows ``part`` (a slice) of a solver call, each
    made when first read: the same numbers (a point's readers want a few of its 17 columns, and a
    call answers many points). ``solved``: the call's ``VResult.solved()``. Pickles as the plain
    dict of every column."""
    __slots__ = ("_out", "_solved", "_part", "_got", "_shared")

    def __init__(self, vres, solved: np.ndarray, part: slice, shared: dict | None = None) -> None:
        """``vres``: the call's VResult or its ``_Outputs`` (shared by the call's points)."""
        # of the call's result only what the columns need (not its warm-start state: a point may
        # outlive the call's other points)
        self._out = vres if isinstance(vres, _Outputs) else _Outputs(vres)
        self._solved, self._part, self._got = solved, part, {}
        self._shared = {} if shared is None else shared     # the call's whole-row tests

    def status_in(self, choices: tuple) -> np.ndarray:
        """``among(self["status"], choices)``: the test over the call's rows once, then these."""
        whole = self._shared.get(choices)
        if whole is None:
            whole = self._shared[choices] = among(np.asarray(self._out.status, dtype=object), choices)
        return whole[self._part]

    def __getitem__(self, key: str) -> np.ndarray:
        a = self._got.get(key)
        if a is None:
            v, part = self._out, self._part
            if key in ("status", "reason"):
                a = np.asarray(getattr(v, key), dtype=object)[part]
            elif key in COLUMNS:
                a = np.where(self._solved[part], np.asarray(v.values[key], dtype=float)[part], np.nan)
            else:
                raise KeyError(key)
            self._got[key] = a
        return a

    def __iter__(self):
        return iter((*COLUMNS, "status", "reason"))

    def __len__(self) -> int:
        return len(COLUMNS) + 2

    def __reduce__(self):
        return dict, (dict(self.items()),)


def status_in(cols, choices: tuple) -> np.ndarray:
    """``among(cols["status"], choices)`` of a point's columns (a dict or ``PartColumns``)."""
    if isinstance(cols, PartColumns):
        return cols.status_in(choices)
    return among(cols["status"], choices)


def weighted_mean(a: np.ndarray, w: np.ndarray) -> float:
    """``np.average(a, weights=w)`` of two float arrays of one length: its operations (the
    products' sum over the weights' sum), without its checks and dispatch (~10 us a call, ~100
    calls a window)."""
    a, w = np.asarray(a), np.asarray(w)
    if a.shape != w.shape or a.ndim != 1 or a.dtype != np.float64 or w.dtype != np.float64:
        return float(np.average(a, weights=w))
    scl = w.sum()
    if scl == 0.0:
        raise ZeroDivisionError("Weights sum to zero, can't be normalized")
    return float(np.multiply(a, w).sum() / scl)


def _points(sps: list, w: np.ndarray, outs: "_Outputs", solved: np.ndarray, shared: dict, index) -> list[Point]:
    """``[_point(sp, None, w, cols=PartColumns(outs, solved, part j, shared), index=index) for j,
    sp in enumerate(sps)]`` for a solver call over the set points ``sps`` (n = len(w) rows each):
    the columns the figures need and the points' sums in one array operation each, the points'
    columns handed the rows of them. The same numbers: every column is row by row, each point's
    rows are a contiguous row of the (points x rows) arrays, which numpy sums as the 1-D array the
    point's own call sums, and the weights' sum is each point's."""
    k, n = len(sps), len(w)
    ok = status_in(PartColumns(outs, solved, slice(0, k * n), shared), SOLVED).reshape(k, n).all(axis=1)
    got = {c: np.where(solved, np.asarray(outs.values[c], dtype=float), np.nan).reshape(k, n)
           for c in ("Q_sink_kW", "W_total_kW", "hs_saturated")}
    for a in got.values():          # the points share them: read only
        a.flags.writeable = False
    Q, W = got["Q_sink_kW"], got["W_total_kW"]
    wQ, wW, ws = (w * Q).sum(axis=1), (w * W).sum(axis=1), w.sum()
    sat = got["hs_saturated"].min(axis=1) > 0.5
    out = []
    for j, sp in enumerate(sps):
        cols = PartColumns(outs, solved, slice(j * n, (j + 1) * n), shared)
        for c, a in got.items():
            cols._got[c] = a[j]
        x = math.nan if sp is None else sp
        if not ok[j]:
            out.append(Point(x, math.nan, math.nan, math.nan, False, None, cols=cols, index=index))
        else:
            out.append(Point(x, float(wQ[j] / wW[j]), float(wQ[j] / ws), float(wW[j] / ws), bool(sat[j]),
                             None, cols=cols, index=index))
    return out


def _point(sp, frame: pd.DataFrame | None, w: np.ndarray, cols: "dict | PartColumns | None" = None,
           index=None) -> Point:
    """The Point of a frame of per-row outputs, or of its columns ``cols`` with ``index``."""
    get = (lambda k: cols[k]) if cols is not None else (lambda k: frame[k].to_numpy(dtype=float))  # noqa: E731
    ok = status_in(cols, SOLVED) if cols is not None else among(frame["status"].to_numpy(), SOLVED)
    Q = get("Q_sink_kW")
    W = get("W_total_kW")
    x = math.nan if sp is None else sp
    if not ok.all():
        return Point(x, math.nan, math.nan, math.nan, False, frame, cols=cols, index=index)
    sat = bool(get("hs_saturated").min() > 0.5)
    wQ, wW, ws = (w * Q).sum(), (w * W).sum(), w.sum()      # (each once: the same sums)
    return Point(x, float(wQ / wW), float(wQ / ws), float(wW / ws), sat, frame, cols=cols, index=index)


def search(ev: Evaluator, lo: float, hi: float, coarse_step: float = COARSE_STEP,
           xtol: float = XTOL, subsample: int = SUBSAMPLE,
           feasible: Callable[[Point], bool] | None = None,
           anchor: float | None = None,
           score: Callable[[Point], float] | None = None) -> tuple[float, Point]:
    """The set point in [lo, hi] with the highest period COP of the evaluator's rows (see the module
    docstring); ``feasible`` rejects candidates. With ``anchor`` (a set point known to be feasible,
    e.g. the actual one) the coarse scan marches out from it in both directions and stops where the
    candidates become infeasible: the feasible set is one stretch around the operating point.
    Returns (set point, its Point) with the plateau convention applied. Raises OptimizationError when
    no candidate solves (and is feasible). ``score``: what is maximised (default the COP; the
    advice passes a COP discounted for the learned curves' shape error away from the data)."""
    if batch.VECTORISED:
        return _search_v(ev, lo, hi, coarse_step, xtol, feasible, score)
    n = len(ev.rows)

    def value(p: Point) -> float:
        if not p.ok or (feasible is not None and not feasible(p)):
            return -math.inf
        return p.COP if score is None else score(p)

    rows = np.unique(np.linspace(0, n - 1, min(subsample, n)).round().astype(int))
    grid = np.arange(lo, hi + 1e-9, coarse_step)
    if grid[-1] < hi - 1e-9:
        grid = np.append(grid, hi)
    sub = rows if len(rows) < n else None
    probe = np.array([n // 2])

    def scan_value(sp: float) -> float:
        # a candidate the middle row already rules out (feasibility needs every row) costs one solve
        if feasible is not None and n > 1 and not math.isfinite(value(ev.at(sp, probe))):
            return -math.inf
        return value(ev.at(sp, sub))
    # the scan in two levels: every second grid point first, then the grid points next to every
    # candidate that survived. Every feasible stretch of two or more grid points holds a first-level
    # point, so this equals scanning the whole grid unless a stretch is a single grid point (a set
    # point range narrower than one coarse step, between two first-level points)
    scan = np.full(len(grid), -np.inf)
    done = np.zeros(len(grid), dtype=bool)
    for k in range(0, len(grid), 2 if TWO_LEVEL_SCAN else 1):
        scan[k], done[k] = scan_value(float(grid[k])), True
    if len(grid) % 2 == 0:
        scan[-1], done[-1] = scan_value(float(grid[-1])), True
    for k in np.flatnonzero(np.isfinite(scan) & done):
        for j in (k - 1, k + 1):
            if 0 <= j < len(grid) and not done[j]:
                scan[j], done[j] = scan_value(float(grid[j])), True
    if not np.isfinite(scan).any():
        raise OptimizationError("no set point in the range solves every sample of the window"
                                + (" within the trusted region" if feasible else ""))
    best = float(scan.max())
    ties = np.flatnonzero(scan >= best - PLATEAU_RTOL * abs(best))
    i = int(ties[-1])       # on a plateau: its upper end (nearest to where p_m follows the set point)
    a, b = max(lo, float(grid[i]) - coarse_step), min(hi, float(grid[i]) + coarse_step)
    # keep Brent inside the feasible stretch around the best scan point
    if feasible is not None:
        j = i
        while j > 0 and np.isfinite(scan[j - 1]):
            j -= 1
        a = max(a, float(grid[j]) if j < i else float(grid[i]))
        j = i
        while j < len(grid) - 1 and np.isfinite(scan[j + 1]):
            j += 1
        b = min(b, float(grid[j]) if j > i else float(grid[i]))

    def neg(sp: float) -> float:
        v = value(ev.at(sp))
        return -v if math.isfinite(v) else 1e6

    cands = [float(grid[i])]
    if b - a > xtol:
        x0 = float(grid[i])
        inward = x0 + xtol if x0 == a else (x0 - xtol if x0 == b else None)
        if EDGE_SHORTCUT and inward is not None and neg(inward) > neg(x0):
            # the best grid point sits at the edge of the feasible stretch and the COP falls away
            # from it: the optimum is the edge itself (to within xtol), no search needed
            pass
        elif BRENT_FROM_BRACKET and a < x0 < b and neg(x0) < min(neg(a), neg(b)):
            # the scan already brackets the optimum (the grid point beats both neighbours): Brent's
            # parabolic steps from that bracket (its points are cached) need ~half the evaluations
            # of a bounded search that starts afresh; same tolerance
            res = minimize_scalar(neg, bracket=(a, x0, b), method="brent",
                                  options={"xtol": xtol / (10.0 * max(abs(x0), 1.0))})
            x_b = float(res.x)
            if not a <= x_b <= b:       # never: Brent stays inside its bracket
                x_b = x0
            cands.insert(0, x_b)
        else:
            res = minimize_scalar(neg, bounds=(a, b), method="bounded", options={"xatol": xtol})
            cands.insert(0, float(res.x))
    sp_opt = min(cands, key=lambda s: (neg(s), cands.index(s)))
    p = ev.at(sp_opt)
    if not math.isfinite(value(p)):
        raise OptimizationError("the optimum found does not solve every sample")
    # does the COP still rise just outside the feasible stretch? (the optimum lies beyond it)
    p.beyond = None
    if feasible is not None:
        for nb in (sp_opt - 0.5 * coarse_step, sp_opt + 0.5 * coarse_step):
            if lo <= nb <= hi:
                q = ev.at(nb)
                sq, sp_ = (q.COP, p.COP) if score is None else (score(q), score(p))
                if q.ok and not feasible(q) and sq > sp_ * (1.0 + PLATEAU_RTOL):
                    p.beyond = float(nb)
    if p.hs_saturated:   # plateau: the set point that just reaches the floating p_m
        amb = ev.params.ambient_pressure
        p_m = float(np.average(p.col("p_m_bar"), weights=ev.w)) * 1e5
        sp_opt = float(Pa_to_barg(p_m, amb / 1e5))
    return sp_opt, p


def _search_v(ev: Evaluator, lo: float, hi: float, coarse_step: float, xtol: float,
              feasible: Callable[[Point], bool] | None,
              score: Callable[[Point], float] | None = None) -> tuple[float, Point]:
    """``search`` in three batched calls of the vectorised solver: the whole coarse grid; a fine grid
    (FINE_STEP) over the best coarse point's feasible neighbours; the vertex of the parabola through
    the best fine point and its neighbours (to ``xtol``, as Brent's method would), kept when it is
    better. Then the same beyond-check and plateau convention as the scalar search. (The steps are
    ``_search_steps``'; ``searches`` runs several such searches on one evaluator together.)"""
    out = _drive(ev, [_search_steps(ev, lo, hi, coarse_step, xtol, feasible, score)])[0]
    if isinstance(out, BaseException):
        raise out
    return out


def _search_steps(ev: Evaluator, lo: float, hi: float, coarse_step: float, xtol: float,
                  feasible: Callable[[Point], bool] | None,
                  score: Callable[[Point], float] | None = None):
    """``_search_v``'s search as a generator: it yields the set points it needs next (the driver,
    ``_drive``, evaluates them with ``ev.at_many``; the search then reads them from the cache) and
    returns (set point, its Point)."""
    def value(p: Point) -> float:
        if not p.ok or (feasible is not None and not feasible(p)):
            return -math.inf
        return p.COP if score is None else score(p)

    def values(points: list) -> np.ndarray:
        """``value`` of each point; a score with ``many`` (the advice's) scores them in one call."""
        many = getattr(score, "many", None)
        if many is None:
            return np.array([value(p) for p in points])
        keep = [p.ok and (feasible is None or feasible(p)) for p in points]
        got = iter(many([p for p, k in zip(points, keep) if k]))
        return np.array([next(got) if k else -math.inf for k in keep])

    grid = np.arange(lo, hi + 1e-9, coarse_step)
    if grid[-1] < hi - 1e-9:
        grid = np.append(grid, hi)
    yield list(grid)
    scan = values(ev.at_many(list(grid)))
    if not np.isfinite(scan).any():
        raise OptimizationError("no set point in the range solves every sample of the window"
                                + (" within the trusted region" if feasible else ""))
    best = float(scan.max())
    i = int(np.flatnonzero(scan >= best - PLATEAU_RTOL * abs(best))[-1])
    j0 = i
    while j0 > 0 and np.isfinite(scan[j0 - 1]):
        j0 -= 1
    j1 = i
    while j1 < len(grid) - 1 and np.isfinite(scan[j1 + 1]):
        j1 += 1
    a = float(grid[max(i - 1, j0)])
    b = float(grid[min(i + 1, j1)])
    cands = [float(grid[i])]
    if b - a > xtol:
        fine = np.unique(np.append(np.arange(a, b + 1e-9, FINE_STEP), [a, b]))
        yield list(fine)
        fv = values(ev.at_many(list(fine)))
        k = int(np.flatnonzero(fv >= np.nanmax(fv) - PLATEAU_RTOL * abs(np.nanmax(fv)))[-1])
        cands.insert(0, float(fine[k]))
        if 0 < k < len(fine) - 1 and np.isfinite(fv[k - 1]) and np.isfinite(fv[k + 1]):
            x0, x1, x2 = fine[k - 1], fine[k], fine[k + 1]
            y0, y1, y2 = fv[k - 1], fv[k], fv[k + 1]
            den = (x1 - x0) * (y1 - y2) - (x1 - x2) * (y1 - y0)
            if den != 0.0:
                xv = x1 - 0.5 * ((x1 - x0) ** 2 * (y1 - y2) - (x1 - x2) ** 2 * (y1 - y0)) / den
                if x0 < xv < x2 and abs(xv - x1) > 0.1 * xtol:
                    cands.insert(0, float(xv))
    yield cands
    vals = [value(ev.at(c)) for c in cands]
    sp_opt = cands[int(np.argmax(vals))]
    p = ev.at(sp_opt)
    if not math.isfinite(value(p)):
        raise OptimizationError("the optimum found does not solve every sample")
    if feasible is not None:
        # (the beyond-check's answer is kept on the point: a search without ``feasible`` leaves
        # it as it is, so that a search run beside this one on the same evaluator, ``searches``,
        # that ends at the same cached point does not overwrite it)
        p.beyond = None
        nbs = [x for x in (sp_opt - 0.5 * coarse_step, sp_opt + 0.5 * coarse_step) if lo <= x <= hi]
        yield nbs
        for nb, q in zip(nbs, ev.at_many(nbs)):
            sq, sp_ = (q.COP, p.COP) if score is None else (score(q), score(p))
            if q.ok and not feasible(q) and sq > sp_ * (1.0 + PLATEAU_RTOL):
                p.beyond = float(nb)
    if p.hs_saturated:
        amb = ev.params.ambient_pressure
        p_m = float(np.average(p.col("p_m_bar"), weights=ev.w)) * 1e5
        sp_opt = float(Pa_to_barg(p_m, amb / 1e5))
    return sp_opt, p


def _drive(ev: Evaluator, steps: list, extra: list = ()) -> list:
    """Run the generators ``steps`` (``_search_steps``) on ``ev`` together: at each turn the set
    points that the live ones ask for and the cache does not hold yet are solved in one
    ``ev.at_many`` call (one call of the vectorised solver, one round of a replay's lockstep), a
    generator whose points are all cached going on at once. ``extra``: set points solved with the
    first call. Returns per generator what it returned, or the exception it raised."""
    out: list = [None] * len(steps)
    asks: dict[int, list] = {}

    def go(i: int) -> None:
        while True:
            try:
                pts = next(steps[i])
            except StopIteration as stop:
                out[i] = stop.value
                return
            except Exception as exc:        # noqa: BLE001 -- handed to the caller as the search's result
                out[i] = exc
                return
            if not ev.holds(pts):
                asks[i] = pts
                return

    for i in range(len(steps)):
        go(i)
    first = list(extra)
    while asks or first:
        ev.at_many(first + [x for i in sorted(asks) for x in asks[i]])
        first = []
        ready = sorted(asks)
        asks.clear()
        for i in ready:
            go(i)
    return out


def searches(ev: Evaluator, lo: float, hi: float, specs: list, extra: list = (),
             coarse_step: float = COARSE_STEP, xtol: float = XTOL) -> list:
    """Several ``search``es over one evaluator and range, each spec (feasible, score); per spec its
    (set point, Point), or the exception it raised (OptimizationError where no candidate solves; the
    caller raises what it cannot take).
    ``extra``: further set points to solve on the way (cached in ``ev``). With the vectorised
    solver the searches take their steps together, so that each step is one solver call for all of
    them (in a replay's lockstep, the advice's search and the surrogate tracker's cost the rounds of
    one); each search's answer is the one it gives alone, within the solver's tolerances (the warm
    starts come from what the cache holds). Without it, one after the other."""
    if not batch.VECTORISED:
        if extra:
            ev.at_many(list(extra))
        out = []
        for feasible, score in specs:
            try:
                out.append(search(ev, lo, hi, coarse_step, xtol, feasible=feasible, score=score))
            except Exception as exc:        # noqa: BLE001 -- as the vectorised path: the search's result
                out.append(exc)
        return out
    return _drive(ev, [_search_steps(ev, lo, hi, coarse_step, xtol, f, s) for f, s in specs], list(extra))


def column_max(values) -> float:
    """The largest value that is not NaN (NaN when there is none): ``pd.Series.max``'s, of a
    column or an array."""
    a = np.asarray(values, dtype=float)
    a = a[~np.isnan(a)]
    return float(a.max()) if len(a) else math.nan


def column_min(values) -> float:
    """The smallest value that is not NaN (NaN when there is none), as ``column_max``."""
    a = np.asarray(values, dtype=float)
    a = a[~np.isnan(a)]
    return float(a.min()) if len(a) else math.nan


def window_range(ref, ambient_bar: float,
                 bounds_barg: tuple[float, float] | None = None) -> tuple[float, float]:
    """[highest p_e, lowest p_c] of the window at its actual set points, as set points [bar(g)]
    with BOUND_MARGIN; intersected with ``bounds_barg``. ``ref``: the rows' model outputs (a
    DataFrame, or a mapping of the two columns as arrays); rows not solved (NaN) left out."""
    lo = column_max(ref["p_e_bar"]) - ambient_bar + BOUND_MARGIN
    hi = column_min(ref["p_c_bar"]) - ambient_bar - BOUND_MARGIN
    if bounds_barg is not None:
        lo, hi = max(lo, bounds_barg[0]), min(hi, bounds_barg[1])
    if not hi > lo:
        raise OptimizationError(f"empty set-point range [{lo:.2f}, {hi:.2f}] bar(g)")
    return lo, hi


def optimize_setpoint(data: pd.DataFrame, params: PlantParams, coarse_step: float = COARSE_STEP,
                      xtol: float = XTOL, subsample: int = SUBSAMPLE,
                      bounds_barg: tuple[float, float] | None = None,
                      representative_points: int | None = None,
                      feasible: Callable[[Point], bool] | None = None) -> SetpointResult:
    """Optimum p_m,sp for the window ``data`` (canonical inputs incl. the actual ``p_m_sp``).

    representative_points : search on that many representative points instead of every sample
        (the reported COPs and heat outputs are still those of the whole window).
    """
    t0 = time.perf_counter()
    missing = [c for c in INPUT_COLUMNS if c not in data.columns]
    if missing:
        raise OptimizationError(f"window lacks input columns: {', '.join(missing)}")
    amb = params.ambient_pressure / 1e5
    data = batch.numeric(data, INPUT_COLUMNS).reset_index(drop=True)
    full = Evaluator(data, np.ones(len(data)), params)
    ref = full.at(None)
    ok = np.isin(ref.frame["status"].to_numpy(), SOLVED)
    n_dropped = int((~ok).sum())
    if not ok.any():
        raise OptimizationError("the model solves none of the window's samples at their actual set points")
    data = data.loc[ok].reset_index(drop=True)
    full = Evaluator(data, np.ones(len(data)), params)
    ref = full.at(None)
    n = len(data)
    lo, hi = window_range(ref.frame, amb, bounds_barg)
    if representative_points and representative_points < n:
        rows, w = representative(data, representative_points)
        ev = Evaluator(rows, w, params)
    else:
        ev = full
    sp_opt, p = search(ev, lo, hi, coarse_step, xtol, subsample, feasible)
    opt = full.at(sp_opt) if ev is not full else p
    if not opt.ok:
        raise OptimizationError("the optimum found does not solve every sample of the window")
    p_e = ref.frame["p_e_bar"].to_numpy(dtype=float)
    p_c = ref.frame["p_c_bar"].to_numpy(dtype=float)
    gm_abs = math.sqrt(float(p_e.mean()) * float(p_c.mean()))
    gm = full.at(min(max(gm_abs - amb, lo), hi))
    return SetpointResult(
        p_m_sp_opt_barg=sp_opt, p_m_opt_bar_a=float(opt.frame["p_m_bar"].mean()), p_m_gm_bar_a=gm_abs,
        p_m_sp_actual_barg=float(data["p_m_sp"].mean()), COP_opt=opt.COP, COP_actual=ref.COP,
        COP_gm=gm.COP, Q_sink_opt_kW=opt.Q_sink_kW, Q_sink_actual_kW=ref.Q_sink_kW,
        Q_sink_gm_kW=gm.Q_sink_kW,
        dCOP_opt_pct=100.0 * (opt.COP / ref.COP - 1.0),
        dQ_sink_opt_pct=100.0 * (opt.Q_sink_kW / ref.Q_sink_kW - 1.0),
        dCOP_gm_pct=100.0 * (opt.COP / gm.COP - 1.0) if gm.ok else math.nan,
        dQ_sink_gm_pct=100.0 * (opt.Q_sink_kW / gm.Q_sink_kW - 1.0) if gm.ok else math.nan,
        hs_saturated=p.hs_saturated, bounds_barg=(lo, hi), n_samples=n, n_dropped=n_dropped,
        model_evaluations=full.evals + (ev.evals if ev is not full else 0),
        run_time_s=time.perf_counter() - t0, n_eval_rows=len(ev.rows),
        ls_saturated=bool(np.nan_to_num(opt.frame["ls_saturated"].to_numpy(dtype=float)).max() > 0.5))


def sweep(data: pd.DataFrame, params: PlantParams, step: float = 0.05,
          bounds_barg: tuple[float, float] | None = None) -> pd.DataFrame:
    """Brute-force period COP over set points (for checks): columns p_m_sp_barg, COP, Q_sink_kW."""
    amb = params.ambient_pressure / 1e5
    data = batch.numeric(data, INPUT_COLUMNS).reset_index(drop=True)
    ev = Evaluator(data, np.ones(len(data)), params)
    ref = ev.at(None)
    ok = np.isin(ref.frame["status"].to_numpy(), SOLVED)
    ev = Evaluator(data.loc[ok], np.ones(int(ok.sum())), params)
    lo, hi = window_range(ev.at(None).frame, amb, bounds_barg)
    rows = []
    for sp in np.arange(lo, hi + 1e-9, step):
        p = ev.at(float(sp))
        rows.append({"p_m_sp_barg": float(sp), "COP": p.COP, "Q_sink_kW": p.Q_sink_kW,
                     "hs_saturated": p.hs_saturated})
    return pd.DataFrame(rows)
