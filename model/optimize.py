"""COP-optimal intermediate-pressure set point for a window of operation (SPEC §6).

Objective: the period COP = sum(Q_sink) / sum(W_total) over the window's samples, simulated with the
(adaptive) model at one set point p_m,sp for the whole window, subject to p_e <= p_m,sp <= p_c
(window-wide: the highest p_e and the lowest p_c of the window at the current set points). The
compressors' speed limits are the model's: below the set point the HS compressor can reach at
1800 rpm it runs there and p_m floats above the set point, so COP(p_m,sp) is *flat* below that
point (and above the point where the HS would need less than 700 rpm). A derivative-based search
stalls on such plateaus, so the search is:

1. a coarse scan of the whole bounded range (``coarse_step``, default 0.5 bar) on an evenly spaced
   subsample of the window (cheap; it only has to find the right bracket);
2. a bounded Brent search (``scipy.optimize.minimize_scalar(method="bounded")``) on the full window
   within one coarse step either side of the best scan point, ``xtol`` 0.01 bar;
3. the better of the Brent result and the best scan point, both evaluated on the full window.

When the optimum lies on the plateau (every sample HS-saturated there), every set point below the
floating p_m gives the same COP; the recommended set point is then the floating p_m itself (the
lowest p_m the HS compressor can hold), reported with ``hs_saturated`` True.

Set points are in bar(g) like the PLC's register (``_barg``); pressures in bar absolute (``_bar_a``).
A sample the model cannot solve at the window's actual set points is left out of the window; a
sample that stops solving at a candidate set point makes that candidate infeasible.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from .batch import INPUT_COLUMNS, simulate_batch, solved_mask
from .params import PlantParams

COARSE_STEP = 0.5         # bar, coarse scan resolution
XTOL = 0.01               # bar, Brent tolerance on the set point
SUBSAMPLE = 12            # samples used by the coarse scan
BOUND_MARGIN = 0.05       # bar, kept clear of p_e and p_c
PLATEAU_RTOL = 1e-9       # COP differences below this (relative) are ties
_COLUMNS = ("Q_sink_kW", "W_total_kW", "p_e_bar", "p_c_bar", "p_m_bar", "hs_saturated", "COP")


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
    model_evaluations: int          # window (or subsample) simulations
    run_time_s: float

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
                f"  {self.n_samples} samples ({self.n_dropped} left out), {self.model_evaluations} window "
                f"simulations, {self.run_time_s:.2f} s")


class _Window:
    def __init__(self, data: pd.DataFrame, params: PlantParams):
        self.params = params
        self.data = data
        self.evals = 0

    def sim(self, sp, rows=None) -> pd.DataFrame:
        self.evals += 1
        d = self.data if rows is None else self.data.iloc[rows]
        return simulate_batch(d, self.params, p_m_sp=sp, columns=_COLUMNS)


def _period(frame: pd.DataFrame) -> tuple[float, float, bool]:
    """(period COP, mean Q_sink, every sample HS-saturated); NaNs when a sample is not solved."""
    ok = solved_mask(frame)
    Q = frame["Q_sink_kW"].to_numpy(dtype=float)
    W = frame["W_total_kW"].to_numpy(dtype=float)
    if not ok.all():
        return math.nan, math.nan, False
    return float(Q.sum() / W.sum()), float(Q.mean()), bool(frame["hs_saturated"].to_numpy(dtype=float).min() > 0.5)


def optimize_setpoint(data: pd.DataFrame, params: PlantParams, coarse_step: float = COARSE_STEP,
                      xtol: float = XTOL, subsample: int = SUBSAMPLE,
                      bounds_barg: tuple[float, float] | None = None) -> SetpointResult:
    """Optimum p_m,sp for the window ``data`` (canonical inputs incl. the actual ``p_m_sp``)."""
    t0 = time.perf_counter()
    missing = [c for c in INPUT_COLUMNS if c not in data.columns]
    if missing:
        raise OptimizationError(f"window lacks input columns: {', '.join(missing)}")
    amb = params.ambient_pressure / 1e5
    data = data[list(INPUT_COLUMNS)].apply(pd.to_numeric, errors="coerce")
    win = _Window(data, params)
    ref = win.sim(None)
    ok = solved_mask(ref)
    n_dropped = int((~ok).sum())
    if not ok.any():
        raise OptimizationError("the model solves none of the window's samples at their actual set points")
    data = data.loc[ok]
    ref = ref.loc[ok]
    win.data = data
    n = len(data)
    COP_act = float(ref["Q_sink_kW"].sum() / ref["W_total_kW"].sum())
    Q_act = float(ref["Q_sink_kW"].mean())
    p_e = ref["p_e_bar"].to_numpy(dtype=float)
    p_c = ref["p_c_bar"].to_numpy(dtype=float)
    gm_abs = math.sqrt(float(p_e.mean()) * float(p_c.mean()))
    lo = float(p_e.max()) - amb + BOUND_MARGIN
    hi = float(p_c.min()) - amb - BOUND_MARGIN
    if bounds_barg is not None:
        lo, hi = max(lo, bounds_barg[0]), min(hi, bounds_barg[1])
    if not hi > lo:
        raise OptimizationError(f"empty set-point range [{lo:.2f}, {hi:.2f}] bar(g)")

    cache: dict[float, tuple] = {}

    def full(sp: float) -> tuple:
        key = round(sp, 9)
        if key not in cache:
            f = win.sim(sp)
            cache[key] = (_period(f), f)
        return cache[key]

    def neg_cop(sp: float) -> float:
        (cop, _, _), _ = full(sp)
        return -cop if math.isfinite(cop) else 1e6

    # 1. coarse scan on a subsample
    rows = np.unique(np.linspace(0, n - 1, min(subsample, n)).round().astype(int))
    grid = np.arange(lo, hi + 1e-9, coarse_step)
    if grid[-1] < hi - 1e-9:
        grid = np.append(grid, hi)
    scan = []
    for sp in grid:
        f = win.sim(float(sp), rows=rows)
        cop, _, _ = _period(f)
        scan.append(cop if math.isfinite(cop) else -math.inf)
    scan = np.array(scan)
    if not np.isfinite(scan).any():
        raise OptimizationError("no set point in the range solves every sample of the window")
    best = float(scan.max())
    ties = np.flatnonzero(scan >= best - PLATEAU_RTOL * abs(best))
    i = int(ties[-1])       # on a plateau: its upper end (nearest to where p_m follows the set point)
    a, b = max(lo, float(grid[i]) - coarse_step), min(hi, float(grid[i]) + coarse_step)
    # 2. Brent on the full window in the bracket
    res = minimize_scalar(neg_cop, bounds=(a, b), method="bounded", options={"xatol": xtol})
    cands = [float(res.x), float(grid[i])]
    # 3. the better of the two (ties -> the Brent point)
    sp_opt = min(cands, key=lambda s: (neg_cop(s), cands.index(s)))
    (cop_opt, q_opt, saturated), f_opt = full(sp_opt)
    if not math.isfinite(cop_opt):
        raise OptimizationError("the optimum found does not solve every sample")
    p_m_opt = float(f_opt["p_m_bar"].mean())
    if saturated:
        sp_opt = p_m_opt - amb
    gm_sp = min(max(gm_abs - amb, lo), hi)
    (cop_gm, q_gm, _), _ = full(gm_sp)
    return SetpointResult(
        p_m_sp_opt_barg=sp_opt, p_m_opt_bar_a=p_m_opt, p_m_gm_bar_a=gm_abs,
        p_m_sp_actual_barg=float(data["p_m_sp"].mean()), COP_opt=cop_opt, COP_actual=COP_act,
        COP_gm=cop_gm, Q_sink_opt_kW=q_opt, Q_sink_actual_kW=Q_act, Q_sink_gm_kW=q_gm,
        dCOP_opt_pct=100.0 * (cop_opt / COP_act - 1.0), dQ_sink_opt_pct=100.0 * (q_opt / Q_act - 1.0),
        dCOP_gm_pct=100.0 * (cop_opt / cop_gm - 1.0) if math.isfinite(cop_gm) else math.nan,
        dQ_sink_gm_pct=100.0 * (q_opt / q_gm - 1.0) if math.isfinite(q_gm) else math.nan,
        hs_saturated=saturated, bounds_barg=(lo, hi), n_samples=n, n_dropped=n_dropped,
        model_evaluations=win.evals, run_time_s=time.perf_counter() - t0)


def sweep(data: pd.DataFrame, params: PlantParams, step: float = 0.05,
          bounds_barg: tuple[float, float] | None = None) -> pd.DataFrame:
    """Brute-force period COP over set points (for checks): columns p_m_sp_barg, COP, Q_sink_kW."""
    amb = params.ambient_pressure / 1e5
    data = data[list(INPUT_COLUMNS)].apply(pd.to_numeric, errors="coerce")
    ref = simulate_batch(data, params, columns=_COLUMNS)
    ok = solved_mask(ref)
    data, ref = data.loc[ok], ref.loc[ok]
    lo = float(ref["p_e_bar"].max()) - amb + BOUND_MARGIN
    hi = float(ref["p_c_bar"].min()) - amb - BOUND_MARGIN
    if bounds_barg is not None:
        lo, hi = max(lo, bounds_barg[0]), min(hi, bounds_barg[1])
    rows = []
    for sp in np.arange(lo, hi + 1e-9, step):
        cop, q, sat = _period(simulate_batch(data, params, p_m_sp=float(sp), columns=_COLUMNS))
        rows.append({"p_m_sp_barg": float(sp), "COP": cop, "Q_sink_kW": q, "hs_saturated": sat})
    return pd.DataFrame(rows)
