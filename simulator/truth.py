"""The truth evaluator: what the simulated plant would really have done in a window of its history
at another set point, for judging advice by regret (issue 8) and CIP policies (issue 10).

The export's truth file (``hp-edge simulate --export ... --truth truth.csv``, or the truth rows of
``simulator.export.MinuteStepper``) records per minute what the plant's steady state depended on:
the water-side boundary (T_source_in_C, T_sink_in_C, V_source_m3h, V_sink_m3h), the LS
controller's set point T_source_out_sp_C, the fouling (R_th_f_K_per_kW, CF_dp_f) and whether it
ran. ``TruthModel`` re-solves those minutes with the plant's hidden true parameters - the same
compressors (family or perturbed), correction factors and flow-dependent heat transfer - and the
plant's own controllers (LS speed holds T_source,out or floats at its bound; HS speed holds p_m or
runs flat out, p_m floating), exactly as the plant would have run at that set point::

    tm = TruthModel(cfg)                       # the SimulatorConfig the history was made with
    w = tm.window(truth.iloc[i0:i1])           # a DataFrame slice or a list of truth dicts
    COP, Q_kW, W_kW = w.cop_at(14.0)           # period COP = sum Q_sink / sum W_electric
    best = w.optimum()                         # {"p_m_sp_opt_barg", "COP_opt", ...}
    regret_pct = 100 * (1 - w.cop_at(advice)[0] / best["COP_opt"])

A window uses its running minutes (running == 1, no CIP), evenly subsampled to ``max_rows``.
Set points are clamped into control.p_m_sp_limits_bar_g as the PLC clamps a write. The plant
re-solves its steady state once per minute, so a minute's truth row belongs to the set point it
was solved at (``p_m_sp_solved_bar_g``); ``cop_actual()`` evaluates every minute at that one.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd

from scipy.optimize import minimize_scalar

from model.cycle import CycleResult, ModelError
from model.params import CycleInputs, PlantParams
from model.units import BAR, M3H, T0

from .config import SimulatorConfig, load_simulator_config
from .plant import effective_params, load_params, true_params
from .sensors import LSController

REQUIRED = ("T_source_in_C", "T_sink_in_C", "V_source_m3h", "V_sink_m3h", "T_source_out_sp_C",
            "R_th_f_K_per_kW", "CF_dp_f", "running")
SP_COLUMNS = ("p_m_sp_solved_bar_g", "p_m_sp_bar_g")   # the minute's own set point, first found
BOUND_MARGIN = 0.5         # bar: default search range p_e + margin .. p_c - margin (Plant.cop_optimum)
SCAN_POINTS = 13           # coarse scan of the range ...
SCAN_ROWS = 6              # ... on this many of the window's minutes (evenly spaced)
XTOL = 0.01                # bar: Brent's absolute tolerance on the set point (result within 0.02)


def condition_row(T_source_in_C: float = 25.0, T_sink_in_C: float = 40.0, V_source_m3h: float = 192.0,
                  V_sink_m3h: float = 62.0, R_th_f_K_per_kW: float = 0.0, CF_dp_f: float = 1.0,
                  T_source_out_sp_C: float = 18.0, p_m_sp_bar_g: float = 16.0) -> dict:
    """A truth row for a stated operating condition (default: SPEC §2's nominal point, clean),
    for evaluating a condition rather than a minute of a history: TruthModel(cfg).window([row])."""
    return {"T_source_in_C": T_source_in_C, "T_sink_in_C": T_sink_in_C, "V_source_m3h": V_source_m3h,
            "V_sink_m3h": V_sink_m3h, "T_source_out_sp_C": T_source_out_sp_C,
            "R_th_f_K_per_kW": R_th_f_K_per_kW, "CF_dp_f": CF_dp_f, "running": 1, "cip": 0,
            "p_m_sp_solved_bar_g": p_m_sp_bar_g}


class TruthError(ValueError):
    """A window cannot be evaluated (missing columns, no running minute, an infeasible set point);
    the message says which."""


@dataclass
class WindowPoint:
    """The window at one set point: period figures and what the controllers did."""
    p_m_sp_barg: float          # the set point applied (after the PLC's clamp) [bar(g)]
    COP: float                  # sum Q_sink / sum W_electric
    Q_sink_kW: float            # mean over the window's minutes
    W_kW: float                 # mean electric power
    p_m_barg: np.ndarray        # per minute: the intermediate pressure reached [bar(g)]
    p_e_barg: np.ndarray
    p_c_barg: np.ndarray
    hs_saturated: np.ndarray    # per minute: HS at its maximum speed, p_m floating
    ls_limit: list              # per minute: "" | "max" | "min"
    T_source_out_C: np.ndarray  # per minute: at its set point, or floating at an LS speed bound


class TruthModel:
    """The hidden plant of a simulator config, for re-running minutes of its history.

    sim_cfg : the SimulatorConfig the history was simulated with (its truth, flow dependence,
              controllers and motor efficiency are used; its profiles, noise and faults are not).
    params  : plant.yaml's parameters (default: read from sim_cfg.plant_file).
    """

    def __init__(self, sim_cfg: SimulatorConfig | None = None, params: PlantParams | None = None):
        self.cfg = sim_cfg or load_simulator_config()
        self.nominal = params or load_params(self.cfg)
        self.true = true_params(self.nominal, self.cfg)
        self.amb = self.cfg.ambient_pressure_bar

    def params_at(self, V_source_m3h: float, V_sink_m3h: float, R_th_f_K_per_kW: float,
                  CF_dp_f: float) -> PlantParams:
        """The plant's true effective parameters at these flows and this fouling."""
        return effective_params(self.true, self.cfg.flow_dependence, V_source_m3h, V_sink_m3h,
                                R_th_f_K_per_kW, CF_dp_f)

    def window(self, truth_rows, max_rows: int = 24) -> "TruthWindow":
        """A window of truth rows (DataFrame or list of dicts with the REQUIRED columns)."""
        df = truth_rows if isinstance(truth_rows, pd.DataFrame) else pd.DataFrame(list(truth_rows))
        missing = [c for c in REQUIRED if c not in df.columns]
        if missing:
            raise TruthError(f"truth rows lack the column(s) {', '.join(missing)} (export the truth "
                             "with this version of the simulator)")
        if not max_rows >= 1:
            raise TruthError(f"max_rows must be >= 1, got {max_rows}")
        family = self.cfg.truth.compressor_family
        if "compressor_family" in df.columns:
            seen = sorted(set(df["compressor_family"].dropna().astype(str)) - {family})
            if seen:
                raise TruthError(f"truth rows come from compressor family {seen[0]!r}, this model is "
                                 f"{family!r}: build it with cfg.with_compressor_family({seen[0]!r})")
        vals = df[list(REQUIRED)].apply(pd.to_numeric, errors="coerce")
        ok = (vals["running"] == 1) & np.isfinite(vals.to_numpy(dtype=float)).all(axis=1)
        if "cip" in df.columns:
            ok &= pd.to_numeric(df["cip"], errors="coerce").fillna(1) == 0
        idx = np.flatnonzero(ok.to_numpy())
        if len(idx) == 0:
            raise TruthError("the window has no running minute")
        pick = idx[np.unique(np.linspace(0, len(idx) - 1, min(max_rows, len(idx))).round().astype(int))]
        sp_col = next((c for c in SP_COLUMNS if c in df.columns), None)
        rows = []
        for i in pick:
            r = vals.iloc[i]
            own = float(pd.to_numeric(df[sp_col].iloc[i], errors="coerce")) if sp_col else math.nan
            rows.append(_Row(
                inputs=CycleInputs(T_source_in=r["T_source_in_C"] + T0,
                                   T_source_out=r["T_source_out_sp_C"] + T0,
                                   T_sink_in=r["T_sink_in_C"] + T0, V_source=r["V_source_m3h"] * M3H,
                                   V_sink=r["V_sink_m3h"] * M3H, p_m_sp=math.nan),
                params=self.params_at(r["V_source_m3h"], r["V_sink_m3h"], r["R_th_f_K_per_kW"],
                                      r["CF_dp_f"]),
                own_sp=own, label=str(df["timestamp"].iloc[i]) if "timestamp" in df.columns else f"row {i}"))
        return TruthWindow(self, rows)


@dataclass
class _Row:
    inputs: CycleInputs           # p_m_sp filled per evaluation
    params: PlantParams
    own_sp: float                 # the set point the plant ran at [bar(g)]
    label: str
    guess: CycleResult | None = None
    ls: LSController | None = None


class TruthWindow:
    """The running minutes of a window; ``cop_at``, ``cop_actual``, ``point_at``, ``optimum``."""

    def __init__(self, model: TruthModel, rows: list[_Row]):
        self.model = model
        self.rows = rows
        for r in rows:
            r.ls = LSController()
        self.evaluations = 0                   # window evaluations (each solves every row)
        self._cache: dict[float, WindowPoint | str] = {}

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    # ------------------------------------------------------------------------ evaluation ----
    def clamp(self, p_m_sp_barg: float) -> float:
        lo, hi = self.model.cfg.control.p_m_sp_limits_bar_g
        return min(max(float(p_m_sp_barg), lo), hi)

    def point_at(self, p_m_sp_barg, own: bool = False, rows: list[int] | None = None) -> WindowPoint:
        """Every minute solved at one set point [bar(g)] (own=True: each at its own; rows: only
        these minutes, by position). Raises TruthError naming the minute when one cannot run."""
        sel = self.rows if rows is None else [self.rows[i] for i in rows]
        if own:
            sps = [r.own_sp for r in sel]
            if not all(math.isfinite(s) for s in sps):
                raise TruthError("the truth rows carry no set point (p_m_sp_solved_bar_g)")
            key = None
        else:
            if not math.isfinite(p_m_sp_barg):
                raise TruthError(f"set point must be finite, got {p_m_sp_barg!r}")
            sp = self.clamp(p_m_sp_barg)
            sps = [sp] * len(sel)
            key = round(sp, 9) if rows is None else None
            hit = self._cache.get(key) if key is not None else None
            if isinstance(hit, WindowPoint):
                return hit
            if isinstance(hit, str):
                raise TruthError(hit)
        amb, eta_m = self.model.amb, self.model.cfg.truth.motor_efficiency
        n = len(sel)
        Q = np.empty(n)
        W = np.empty(n)
        p_m, p_e, p_c = np.empty(n), np.empty(n), np.empty(n)
        sat = np.zeros(n, dtype=bool)
        T_out = np.empty(n)
        limits = []
        self.evaluations += 1
        for i, (row, sp) in enumerate(zip(sel, sps)):
            inp = row.inputs.replace(p_m_sp=(self.clamp(sp) + amb) * BAR)
            try:
                res, T_out[i], limit = row.ls.solve(inp, row.params, row.guess)
            except (ModelError, ValueError) as exc:
                row.ls.T_out_float = None
                msg = (f"minute {row.label} cannot run at p_m,sp {sp:.3f} bar(g): "
                       f"{type(exc).__name__}: {exc}")
                if key is not None:
                    self._cache[key] = msg
                raise TruthError(msg) from None
            if not limit:
                row.ls.T_out_float = None
            row.guess = res
            Q[i], W[i] = res.Q_sink / 1e3, res.W_total / 1e3 / eta_m
            p_m[i], p_e[i], p_c[i] = res.p_m / BAR - amb, res.p_e / BAR - amb, res.p_c / BAR - amb
            sat[i] = res.hs_saturated
            limits.append(limit)
        pt = WindowPoint(math.nan if own else sps[0], float(Q.sum() / W.sum()),
                         float(Q.mean()), float(W.mean()), p_m, p_e, p_c, sat, limits, T_out - T0)
        if key is not None:
            self._cache[key] = pt
        return pt

    def cop_at(self, p_m_sp_barg: float) -> tuple[float, float, float]:
        """(period COP, mean Q_sink [kW], mean electric power [kW]) with every minute at this set
        point [bar(g)]. TruthError when a minute cannot run there."""
        pt = self.point_at(p_m_sp_barg)
        return pt.COP, pt.Q_sink_kW, pt.W_kW

    def cop_actual(self) -> tuple[float, float, float]:
        """The same at each minute's own set point (what the plant did)."""
        pt = self.point_at(math.nan, own=True)
        return pt.COP, pt.Q_sink_kW, pt.W_kW

    # --------------------------------------------------------------------------- optimum ----
    def bounds(self) -> tuple[float, float]:
        """Default search range [bar(g)]: highest p_e + 0.5 bar to lowest p_c - 0.5 bar of the
        window (at the minutes' own set points, or mid-range when they carry none), inside the
        PLC's set-point limits."""
        lo_lim, hi_lim = self.model.cfg.control.p_m_sp_limits_bar_g
        try:
            pt = self.point_at(math.nan, own=True)
        except TruthError:
            pt = self.point_at(0.5 * (lo_lim + hi_lim))
        return (max(float(pt.p_e_barg.max()) + BOUND_MARGIN, lo_lim),
                min(float(pt.p_c_barg.min()) - BOUND_MARGIN, hi_lim))

    def optimum(self, lo_barg: float | None = None, hi_barg: float | None = None) -> dict:
        """The COP-optimal set point of the window on the true plant.

        A coarse scan of [lo, hi] (default ``bounds()``) in SCAN_POINTS points on SCAN_ROWS evenly
        spaced minutes finds the bracket (the best point's neighbours); a bounded Brent search on
        every minute refines it to XTOL; the better of that and the best scan point (on every
        minute) wins. On the HS-saturation plateau (every minute's HS at full speed at the
        optimum) every lower set point gives the same COP: the set point reported is the one that
        just reaches the floating p_m (the lowest floating p_m of the window, at which every minute
        still runs as on the plateau), as Plant.cop_optimum does.

        Returns p_m_sp_opt_barg, COP_opt, Q_sink_opt_kW, W_opt_kW, hs_saturated, p_m_opt_barg
        (mean over the minutes), bounds_barg, evaluations (window evaluations, a scan point on the
        subsample counting as one), seconds.
        """
        t0 = time.perf_counter()
        ev0 = self.evaluations
        if lo_barg is None or hi_barg is None:
            lo_d, hi_d = self.bounds()
            lo_barg = lo_d if lo_barg is None else lo_barg
            hi_barg = hi_d if hi_barg is None else hi_barg
        lo, hi = self.clamp(lo_barg), self.clamp(hi_barg)
        if not hi > lo:
            raise TruthError(f"empty set-point range [{lo:.3f}, {hi:.3f}] bar(g)")

        def cop(sp: float, rows=None) -> float:
            try:
                return self.point_at(sp, rows=rows).COP
            except TruthError:
                return -math.inf

        sub = list(np.unique(np.linspace(0, self.n_rows - 1, min(SCAN_ROWS, self.n_rows)).round().astype(int)))
        grid = np.linspace(lo, hi, SCAN_POINTS)
        vals = np.array([cop(float(x), sub) for x in grid])
        if not np.isfinite(vals).any():
            raise TruthError(f"no set point in [{lo:.3f}, {hi:.3f}] bar(g) runs every minute of the window")
        best = float(vals.max())
        i = int(np.flatnonzero(vals >= best - 1e-9 * abs(best))[-1])   # ties (plateau): the upper end
        a, c = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
        res = minimize_scalar(lambda x: -cop(x) if math.isfinite(cop(x)) else 1e6, bounds=(a, c),
                              method="bounded", options={"xatol": XTOL})
        cands = [(cop(float(res.x)), float(res.x)), (cop(float(grid[i])), float(grid[i]))]
        f_opt, sp_opt = max(cands, key=lambda t: t[0])
        if not math.isfinite(f_opt):
            raise TruthError(f"no set point near {grid[i]:.3f} bar(g) runs every minute of the window")
        pt = self.point_at(sp_opt)
        saturated = bool(pt.hs_saturated.all())
        if saturated:
            edge = float(pt.p_m_barg.min())
            try:
                pe = self.point_at(edge)
                if pe.COP >= pt.COP * (1.0 - 1e-9):
                    sp_opt, pt = pe.p_m_sp_barg, pe
            except TruthError:
                pass
        return {"p_m_sp_opt_barg": float(sp_opt), "COP_opt": pt.COP, "Q_sink_opt_kW": pt.Q_sink_kW,
                "W_opt_kW": pt.W_kW, "hs_saturated": saturated, "p_m_opt_barg": float(pt.p_m_barg.mean()),
                "bounds_barg": (lo, hi), "evaluations": self.evaluations - ev0,
                "seconds": time.perf_counter() - t0}
