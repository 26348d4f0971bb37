"""Cost of fouling and cost-optimal CIP timing (SPEC §10, issue 10). Pure functions, units in names.

Cost of fouling, per window
    compressor   P_comp = Q_sink * (1/COP_f - 1/COP_ref)                                   [kW]
    source pump  P_pump = V_source * dp_f / eta_pump,  dp_f = (CF_dp,f - 1) * dp_clean      [kW]
    cost rate    f = (P_comp + P_pump) * 24 h/day * price / 1000                          [EUR/day]

"At equal heat delivered": the model holds T_source,out, so a fouled evaporator does not change the
heat taken from the source; the compressors work harder and that extra work also leaves as heat,
Q_sink,f = Q_sink,ref + (W_f - W_ref). Comparing W_f with W_ref would charge fouling for heat that was
delivered. Instead the heat the plant delivered, Q_sink, is priced at both period COPs
(COP = sum Q_sink / sum W_total of the window, SPEC §3): P_comp is the electricity the fouled plant
needs for Q_sink beyond what the reference plant needs for the same heat. With two model runs on the
same inputs this is P_comp = (W_f - W_ref) * (1 - 1/COP_ref) exactly (tests check it). COP_ref is the
model's COP at the clean level (R_th,f = 0) or at the level right after the last CIP; COP_f is the
adaptive model's at the current R_th,f. The model runs are the caller's (``cop_of_R`` or values).

Prices: a constant [EUR/MWh] or a ``PriceSeries`` (epoch seconds, EUR/MWh; each price holds from its
timestamp to the next). The cumulated cost since the last reset integrates the windows' cost rates
over time (``CostTally``): each second is counted once (a window overlapping the previous one adds
only its part after the previous end); a gap between windows no longer than ``max_gap_s`` is
bridged with the mean of the two neighbouring rates; a longer gap adds nothing (the plant was off,
in a CIP, or unrecorded) and is reported as uncovered time.

CIP timing. A fouling–cleaning cycle is T days of operation, then D days of downtime with cleaning
cost C (direct cost + the heat replaced during the downtime). The time-average cost
    J(T) = (C + integral_0^T f(t) dt) / (T + D)
is minimal where dJ/dT = 0:  f(T) (T + D) = C + integral_0^T f dt,  i.e. f(T*) = J(T*) — clean when
the cost rate reaches the cycle's average. For f = a t and D = 0: a T^2 / 2 = C, T* = sqrt(2 C / a).
A CIP removes only a share s of the fouling (y - floor), so each cycle starts from the residual;
J(T) is evaluated on the periodic steady cycle: y_post - floor = (1 - s) (y(T) - floor), where y(T)
grows from y_post with the fitted law. Kern–Seaton (closed form, E = exp(-T/tau),
U = y_inf - floor):  y_post - floor = (1 - s) U (1 - E) / (1 - (1 - s) E).
With partial cleaning the start level grows with T, which adds (T+D) * integral_0^T df/dT dt to the
left side of the criterion: at the optimum f(T*) < J(T*) (clean somewhat earlier: a later CIP leaves
a dirtier residual for every following cycle). With s = 1, or a fixed start, f(T*) = J(T*) holds.
The linear law (saturation not yet seen) has the steady start (1 - s) r T / s, far beyond anything
observed; by default (``restart="auto"``) a linear-law component restarts from the current cycle's
start level instead, and a Kern–Seaton one from the steady cycle's.
The cost rate as a function of the level is a ``CostCurve``: linear interpolation between levels at
which the caller evaluated the model (linear extrapolation beyond them).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .forecast import FoulingFit, ForecastError
from . import speedkernel as _kernels

HOURS_PER_DAY = 24.0
SECONDS_PER_DAY = 86400.0
DAYS_PER_YEAR = 365.25
DEFAULT_ETA_PUMP = 0.65       # wire-to-water efficiency of a source pump set (pump 0.75 x motor 0.87)
GL_NODES = 48                 # Gauss–Legendre nodes of the cycle integral


class CostError(ValueError):
    """Cost inputs are unusable (a bad price, a non-finite COP, a price series that misses a time)."""


# ---- cost of fouling, one window ------------------------------------------------------------------
def extra_compressor_power_kW(Q_sink_kW, COP_fouled, COP_ref):
    """Extra compressor electric power at equal heat delivered [kW].

    Q_sink_kW : heat delivered in the window [kW] (period mean)
    COP_fouled, COP_ref : period COPs of the model at the current and the reference fouling level [-]
    """
    Q, cf, cr = (np.asarray(x, dtype=float) for x in (Q_sink_kW, COP_fouled, COP_ref))
    if not (np.all(np.isfinite(cf)) and np.all(cf > 0) and np.all(np.isfinite(cr)) and np.all(cr > 0)):
        raise CostError(f"COPs must be finite and > 0, got COP_fouled={COP_fouled!r}, COP_ref={COP_ref!r}")
    out = Q * (1.0 / cf - 1.0 / cr)
    return float(out) if out.ndim == 0 else out


def dp_fouling_bar(CF_dp_f, dp_clean_bar):
    """Extra source pressure drop from fouling, (CF_dp,f - 1) * dp_clean [bar]."""
    return (np.asarray(CF_dp_f, dtype=float) - 1.0) * np.asarray(dp_clean_bar, dtype=float)


def pump_extra_power_kW(V_source_m3_per_h, dp_f_bar, eta_pump: float = DEFAULT_ETA_PUMP):
    """Source-pump electric power for the fouling pressure drop, V * dp_f / eta_pump [kW].

    V_source_m3_per_h : source flow [m3/h]; dp_f_bar : extra pressure drop [bar];
    eta_pump : wire-to-water efficiency [-] (default 0.65)
    """
    if not (isinstance(eta_pump, (int, float)) and 0 < eta_pump <= 1):
        raise CostError(f"eta_pump must be in (0, 1], got {eta_pump!r}")
    P = np.asarray(V_source_m3_per_h, dtype=float) / 3600.0 * np.asarray(dp_f_bar, dtype=float) * 1e5
    out = P / eta_pump / 1e3
    return float(out) if np.ndim(out) == 0 else out


def cost_rate_eur_per_day(P_kW, price_eur_per_MWh):
    """Cost rate of an electric power at a price: P * 24 h/day * price / 1000 [EUR/day]."""
    out = np.asarray(P_kW, dtype=float) * HOURS_PER_DAY * np.asarray(price_eur_per_MWh, dtype=float) / 1e3
    return float(out) if np.ndim(out) == 0 else out


# ---- prices -----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PriceSeries:
    """Electricity prices: each price [EUR/MWh] holds from its timestamp [epoch s] to the next one; the
    last holds for one median step. Times outside [first, last + step) are an error (CostError)."""
    t_s: np.ndarray
    eur_per_MWh: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.t_s, dtype=float).ravel()
        p = np.asarray(self.eur_per_MWh, dtype=float).ravel()
        if len(t) != len(p) or len(t) == 0:
            raise CostError(f"price series: {len(t)} timestamps and {len(p)} prices")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            bad = int(np.flatnonzero(~(np.isfinite(t) & np.isfinite(p)))[0])
            raise CostError(f"price series: row {bad} is not a finite timestamp and price")
        if np.any(np.diff(t) <= 0):
            bad = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
            raise CostError(f"price series: timestamps must increase strictly (row {bad})")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "eur_per_MWh", p)

    @property
    def end_s(self) -> float:
        step = float(np.median(np.diff(self.t_s))) if len(self.t_s) > 1 else 3600.0
        return float(self.t_s[-1] + step)

    def _check(self, a: float, b: float):
        if a < self.t_s[0] or b > self.end_s:
            raise CostError(f"price series covers epoch {self.t_s[0]:.0f} .. {self.end_s:.0f} s; "
                            f"asked for {a:.0f} .. {b:.0f} s")

    def at(self, t_s):
        t = np.asarray(t_s, dtype=float)
        self._check(float(np.min(t)), float(np.max(t)))
        out = self.eur_per_MWh[np.searchsorted(self.t_s, t, side="right") - 1]
        return float(out) if out.ndim == 0 else out

    def mean(self, start_s: float, end_s: float) -> float:
        """Time-weighted mean price over [start_s, end_s]."""
        if end_s <= start_s:
            return self.at(start_s)
        self._check(start_s, end_s)
        edges = np.concatenate([[start_s], self.t_s[(self.t_s > start_s) & (self.t_s < end_s)], [end_s]])
        mids = self.at(edges[:-1])
        return float(np.sum(mids * np.diff(edges)) / (end_s - start_s))


def mean_price(price, start_s: float, end_s: float) -> float:
    """Mean electricity price [EUR/MWh] over a window: a constant, or a PriceSeries' time mean."""
    if isinstance(price, PriceSeries):
        return price.mean(start_s, end_s)
    if isinstance(price, bool) or not isinstance(price, (int, float)) or not math.isfinite(price):
        raise CostError(f"electricity price must be a finite number [EUR/MWh] or a PriceSeries, got {price!r}")
    return float(price)


# ---- cumulated cost since the last reset --------------------------------------------------------------
@dataclass(frozen=True)
class CostTally:
    """Running cost since the last reset; ``add`` returns the updated tally (see the module rule)."""
    max_gap_s: float = 3600.0
    total_eur: float = 0.0
    covered_s: float = 0.0         # time inside windows
    bridged_s: float = 0.0         # short gaps, priced at the neighbours' mean rate
    uncovered_s: float = 0.0       # long gaps, not priced
    last_end_s: float | None = None
    last_rate_eur_per_day: float | None = None

    def add(self, start_s: float, end_s: float, rate_eur_per_day: float) -> "CostTally":
        if not (math.isfinite(start_s) and math.isfinite(end_s) and end_s >= start_s):
            raise CostError(f"window [{start_s!r}, {end_s!r}] is not a finite interval")
        if not math.isfinite(rate_eur_per_day):
            raise CostError(f"cost rate must be finite, got {rate_eur_per_day!r}")
        total, cov, br, unc = self.total_eur, self.covered_s, self.bridged_s, self.uncovered_s
        a = start_s
        if self.last_end_s is not None:
            if end_s <= self.last_end_s:          # nothing new
                return self
            gap = start_s - self.last_end_s
            if gap <= 0:
                a = self.last_end_s
            elif gap <= self.max_gap_s:
                total += 0.5 * (self.last_rate_eur_per_day + rate_eur_per_day) * gap / SECONDS_PER_DAY
                br += gap
            else:
                unc += gap
        total += rate_eur_per_day * (end_s - a) / SECONDS_PER_DAY
        cov += end_s - a
        return CostTally(self.max_gap_s, total, cov, br, unc, float(end_s), float(rate_eur_per_day))


def cumulative_cost_eur(start_s, end_s, rate_eur_per_day, max_gap_s: float = 3600.0) -> np.ndarray:
    """Running cost [EUR] after each window (windows in time order; the CostTally rule)."""
    tally = CostTally(max_gap_s)
    out = []
    for a, b, f in zip(np.asarray(start_s, float), np.asarray(end_s, float), np.asarray(rate_eur_per_day, float)):
        tally = tally.add(float(a), float(b), float(f))
        out.append(tally.total_eur)
    return np.array(out)


# ---- cost rate as a function of the fouling level ------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CostCurve:
    """f(level) [EUR/day]: linear interpolation between (level, f) points, linear extrapolation."""
    levels: np.ndarray
    eur_per_day: np.ndarray

    def __post_init__(self):
        x = np.asarray(self.levels, dtype=float).ravel()
        f = np.asarray(self.eur_per_day, dtype=float).ravel()
        if len(x) != len(f) or len(x) < 2:
            raise CostError(f"a cost curve needs >= 2 (level, cost) points, got {len(x)} and {len(f)}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(f))):
            raise CostError("cost curve points must be finite")
        order = np.argsort(x)
        x, f = x[order], f[order]
        if np.any(np.diff(x) <= 0):
            raise CostError("cost curve levels must differ")
        object.__setattr__(self, "levels", x)
        object.__setattr__(self, "eur_per_day", f)

    def __call__(self, y):
        x, f = self.levels, self.eur_per_day
        y = np.asarray(y, dtype=float)
        out = np.interp(y, x, f)
        if out.ndim == 0:
            if y < x[0]:
                out = f[0] + (f[1] - f[0]) / (x[1] - x[0]) * (y - x[0])
            elif y > x[-1]:
                out = f[-1] + (f[-1] - f[-2]) / (x[-1] - x[-2]) * (y - x[-1])
            return float(out)
        # the extrapolated elements only (the cycle plan's ~6,000 calls a replay on arrays of up to
        # ~10^5 levels, most of them inside the points): the same numbers, element by element
        lo, hi = y < x[0], y > x[-1]
        if lo.any():
            out[lo] = f[0] + (f[1] - f[0]) / (x[1] - x[0]) * (y[lo] - x[0])
        if hi.any():
            out[hi] = f[-1] + (f[-1] - f[-2]) / (x[-1] - x[-2]) * (y[hi] - x[-1])
        return out


def compressor_cost_curve(R_K_per_kW, COP, Q_sink_kW: float, price_eur_per_MWh: float,
                          COP_ref: float | None = None) -> CostCurve:
    """Cost rate of the compressors' extra electricity as a function of R_th,f [K/kW].

    R_K_per_kW, COP : levels at which the model was run on the window's operation and its period COPs
    Q_sink_kW : heat delivered [kW]; price_eur_per_MWh : mean electricity price
    COP_ref : reference COP; default the COP at R = 0, which must then be among the levels
    """
    R = np.asarray(R_K_per_kW, dtype=float)
    cop = np.asarray(COP, dtype=float)
    if COP_ref is None:
        at0 = np.flatnonzero(R == 0.0)
        if not len(at0):
            raise CostError("no COP_ref given and R = 0 is not among the levels")
        COP_ref = float(cop[at0[0]])
    P = extra_compressor_power_kW(Q_sink_kW, cop, COP_ref)
    return CostCurve(R, cost_rate_eur_per_day(P, price_eur_per_MWh))


# ---- the analysis chain's cost of fouling: model runs at several levels, lost capacity included ----
@dataclass(frozen=True, eq=False)
class LevelRuns:
    """The adaptive model run on one window's operation at several R_th,f levels (the LS speed
    controller saturating as the plant's does, ``simulate_batch(..., ls_mode="float")``): period
    means over the same rows of the heat delivered, the compressors' power and the heat taken from
    the source [kW], per level [K/kW]. R = 0 (a clean evaporator) must be among the levels."""
    R_K_per_kW: np.ndarray
    Q_sink_kW: np.ndarray
    W_kW: np.ndarray
    Q_source_kW: np.ndarray

    def __post_init__(self):
        arrs = [np.asarray(getattr(self, k), dtype=float).ravel()
                for k in ("R_K_per_kW", "Q_sink_kW", "W_kW", "Q_source_kW")]
        if len({len(a) for a in arrs}) != 1 or len(arrs[0]) < 2:
            raise CostError(f"level runs need >= 2 levels of equal length, got {[len(a) for a in arrs]}")
        if not all(np.all(np.isfinite(a)) for a in arrs):
            raise CostError("level runs must be finite")
        R, Q, W, Qs = arrs
        if not (np.all(W > 0) and np.all(Qs > 0) and np.all(Q > W)):
            raise CostError("level runs need Q_sink > W > 0 and Q_source > 0 at every level")
        order = np.argsort(R)
        R, Q, W, Qs = (a[order] for a in (R, Q, W, Qs))
        if np.any(np.diff(R) <= 0):
            raise CostError("level runs: levels must differ")
        if R[0] != 0.0:
            raise CostError("level runs: R = 0 (a clean evaporator) must be among the levels")
        for k, a in zip(("R_K_per_kW", "Q_sink_kW", "W_kW", "Q_source_kW"), (R, Q, W, Qs)):
            object.__setattr__(self, k, a)

    def at(self, R_K_per_kW):
        """(Q_sink, W, Q_source) [kW] at a level (or an array of levels), linearly interpolated
        (extrapolated beyond the outer levels)."""
        x = self.R_K_per_kW
        y = np.stack([self.Q_sink_kW, self.W_kW, self.Q_source_kW])          # (3, n)
        R = np.asarray(R_K_per_kW, dtype=float)
        i = np.clip(np.searchsorted(x, R, side="right") - 1, 0, len(x) - 2)
        u = (R - x[i]) / (x[i + 1] - x[i])
        out = y[:, i] + (y[:, i + 1] - y[:, i]) * u
        return tuple(float(v) for v in out) if R.ndim == 0 else tuple(out)


def fouling_cost_terms(fouled, reference, price_eur_per_MWh: float,
                       replacement_heat_eur_per_MWh: float) -> dict:
    """Cost of operating at the fouled level against the reference level, at equal heat.

    fouled, reference : (Q_sink, W, Q_source) [kW] of the same operation (``LevelRuns.at``); the
        fouled values may be arrays (one cost per level)
    Compressors: the electricity the fouled plant needs for the heat it delivers beyond what the
        reference plant needs for that heat, P_comp = Q_f (1/COP_f - 1/COP_r) = W_f - Q_f W_r/Q_r.
    Lost capacity: where fouling drives the LS compressor to its speed limit, T_source,out floats
        and the plant takes less heat from the source; the reference plant would have made
        L = (Qs_r - Qs_f) * COP_r/(COP_r - 1) = (Qs_r - Qs_f) * Q_r/Qs_r more heat of it, which is
        bought at the replacement heat price instead of made at the electricity price / COP_r:
        it costs L * max(p_heat - p/COP_r, 0) (nothing when bought heat is cheaper).
    Returns P_compressor_kW, lost_heat_kW, cost_eur_per_day (both parts, 24 h/day).
    """
    Qf, Wf, Qsf = (np.asarray(v, dtype=float) for v in fouled)
    Qr, Wr, Qsr = (float(v) for v in reference)
    if not (Qr > Wr > 0 and Qsr > 0 and np.all(Qf > 0)):
        raise CostError(f"reference run must have Q_sink > W > 0, got {reference!r}")
    p = float(price_eur_per_MWh)
    ph = float(replacement_heat_eur_per_MWh)
    if not (math.isfinite(p) and math.isfinite(ph) and ph >= 0):
        raise CostError(f"prices must be finite (heat >= 0), got {p!r}, {ph!r}")
    P = Wf - Qf * Wr / Qr
    L = np.maximum(Qsr - Qsf, 0.0) * Qr / Qsr
    cost = HOURS_PER_DAY / 1e3 * (p * P + L * max(ph - p * Wr / Qr, 0.0))
    if P.ndim:
        return {"P_compressor_kW": P, "lost_heat_kW": L, "cost_eur_per_day": cost}
    return {"P_compressor_kW": float(P), "lost_heat_kW": float(L), "cost_eur_per_day": float(cost)}


def fouling_cost_curve(runs: LevelRuns, price_eur_per_MWh: float,
                       replacement_heat_eur_per_MWh: float) -> CostCurve:
    """f(R_th,f) [EUR/day] against a clean evaporator (``fouling_cost_terms`` at each level;
    linear between them): the compressor part and lost capacity, not the pumps."""
    f = fouling_cost_terms((runs.Q_sink_kW, runs.W_kW, runs.Q_source_kW), runs.at(0.0), price_eur_per_MWh,
                           replacement_heat_eur_per_MWh)["cost_eur_per_day"]
    return CostCurve(runs.R_K_per_kW, np.atleast_1d(f))


def pump_cost_curve(dp_clean_bar: float, V_source_m3_per_h: float, price_eur_per_MWh: float,
                    eta_pump: float = DEFAULT_ETA_PUMP) -> CostCurve:
    """Cost rate of the source pump's extra electricity as a function of CF_dp,f (linear, 0 at 1)."""
    f1 = cost_rate_eur_per_day(pump_extra_power_kW(V_source_m3_per_h, dp_clean_bar, eta_pump),
                               price_eur_per_MWh)
    return CostCurve(np.array([1.0, 2.0]), np.array([0.0, f1]))


def cleaning_cost_eur(direct_eur: float, downtime_h: float, heat_kW: float,
                      replacement_heat_eur_per_MWh: float, *, COP_clean: float | None = None,
                      electricity_eur_per_MWh: float = 0.0) -> float:
    """C = direct cost + heat replaced during the downtime [EUR]; with COP_clean the heat pump's own
    electricity for that heat (at the clean COP), which the downtime saves, is subtracted."""
    for name, v in (("direct_eur", direct_eur), ("downtime_h", downtime_h), ("heat_kW", heat_kW),
                    ("replacement_heat_eur_per_MWh", replacement_heat_eur_per_MWh)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise CostError(f"{name} must be a finite number >= 0, got {v!r}")
    C = direct_eur + downtime_h * heat_kW / 1e3 * replacement_heat_eur_per_MWh
    if COP_clean is not None:
        if not COP_clean > 0:
            raise CostError(f"COP_clean must be > 0, got {COP_clean!r}")
        C -= downtime_h * heat_kW / COP_clean / 1e3 * electricity_eur_per_MWh
    return float(C)


# ---- the share a CIP removes ---------------------------------------------------------------------------
@dataclass(frozen=True)
class RemovalShare:
    share: float
    spread: float
    n: int                 # CIPs it was learned from (0: configured)
    source: str            # "plant" | "configured"


def estimate_removal_share(R_before, R_after, *, default_share: float = 0.15,
                           default_spread: float = 0.05, min_share: float = 0.01) -> RemovalShare:
    """Share of R_th,f a CIP removes, (R_before - R_after)/R_before, from the plant's past CIPs.

    The median over the CIPs with finite values and R_before > 0, clipped to [min_share, 1]; its
    spread is the sample standard deviation (the configured spread with fewer than 2 CIPs). Without
    any usable CIP: the configured default.
    """
    if not 0 < default_share <= 1:
        raise CostError(f"default removal share must be in (0, 1], got {default_share!r}")
    b, a = np.asarray(R_before, dtype=float).ravel(), np.asarray(R_after, dtype=float).ravel()
    if len(b) != len(a):
        raise CostError(f"R_before and R_after differ in length: {len(b)}, {len(a)}")
    ok = np.isfinite(b) & np.isfinite(a) & (b > 0)
    if not ok.any():
        return RemovalShare(float(default_share), float(default_spread), 0, "configured")
    shares = (b[ok] - a[ok]) / b[ok]
    s = float(np.clip(np.median(shares), min_share, 1.0))
    spread = float(np.std(shares, ddof=1)) if len(shares) >= 2 else float(default_spread)
    return RemovalShare(s, spread, int(len(shares)), "plant")


# ---- cost-optimal CIP timing ----------------------------------------------------------------------------
@dataclass(frozen=True)
class FoulingComponent:
    """One fouling quantity in the cycle: its law, the share a CIP removes, its cost rate f(level).

    uncertain : average the cycle cost over the fit's parameter uncertainty (sigma points of the
        parameters' covariance, mean +- sqrt(3) sd along each Cholesky direction, weights 1/6; the
        linear law's centre point weighs 1/3; a0, r0 >= 0 and k >= k/5 kept). The optimum then
        minimises the expected J, which does not jump between distant minima as a fit wobbles.
    """
    fit: FoulingFit
    removal_share: float
    cost_eur_per_day: Callable
    name: str = "R_th_f"
    restart: str = "auto"          # "auto" | "steady" | "current" (see the module docstring)
    uncertain: bool = False

    def __post_init__(self):
        if not 0 <= self.removal_share <= 1:
            raise CostError(f"{self.name}: removal share must be in [0, 1], got {self.removal_share!r}")
        if self.restart not in ("auto", "steady", "current"):
            raise CostError(f"{self.name}: restart must be 'auto', 'steady' or 'current', got {self.restart!r}")

    @property
    def mode(self) -> str:
        if self.restart != "auto":
            return self.restart
        return "steady" if self.fit.law == "kern_seaton" else "current"

    def start_level(self, T_days):
        """Level right after a CIP on the cycle of length T (array over T)."""
        fit, s = self.fit, self.removal_share
        T = np.asarray(T_days, dtype=float)
        if self.mode == "current":
            return np.full(T.shape, fit.y0)
        if fit.law == "kern_seaton":
            E = np.exp(-fit.k * T)
            U = fit.y_inf - fit.floor
            return fit.floor + (1 - s) * U * (1 - E) / (1 - (1 - s) * E)
        if s <= 0:
            raise CostError(f"{self.name}: a CIP that removes nothing has no steady cycle under the linear law")
        return fit.floor + (1 - s) * fit.r0 * T / s

    def levels(self, T_days, tau_days):
        """Levels at times tau of the cycle of length T: T of shape (m,), tau (m, q) -> (m, q)."""
        y_post = self.start_level(T_days)
        return self.fit.growth(np.asarray(y_post)[..., None], tau_days)

    def crossing_times(self, T_days, x):
        """Times [day] at which the cycle of length T (shape (m,)) reaches the levels x (shape (b,)),
        clipped to [0, T]: shape (m, b). The path is non-decreasing, so the times are sorted."""
        fit = self.fit
        T = np.asarray(T_days, dtype=float)[:, None]
        y_post = np.asarray(self.start_level(T_days), dtype=float)[:, None]
        x = np.asarray(x, dtype=float)[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            if fit.law == "kern_seaton":
                tau = np.log((fit.y_inf - y_post) / (fit.y_inf - x)) / fit.k
                tau = np.where(x >= fit.y_inf, np.inf, tau)
            elif fit.r0 > 0:
                tau = (x - y_post) / fit.r0
            else:
                tau = np.full(np.broadcast_shapes(x.shape, y_post.shape), np.inf)
        tau = np.where((x <= y_post) | np.isnan(tau), 0.0, tau)
        return np.minimum(np.maximum(tau, 0.0), T)

    def variants(self) -> list:
        """[(weight, component)]: itself, or its sigma points when ``uncertain``."""
        if not self.uncertain:
            return [(1.0, self)]
        fit = self.fit
        mean = np.array([fit.a0, fit.r0, fit.k][: fit.cov.shape[0]])
        p = len(mean)
        C = np.asarray(fit.cov, dtype=float)
        if not np.all(np.isfinite(C)):
            return [(1.0, self)]
        vals, vecs = np.linalg.eigh(0.5 * (C + C.T))
        L = vecs * np.sqrt(np.clip(vals, 0.0, None))
        out = [] if p == 3 else [(1.0 / 3.0, self)]
        for j in range(p):
            for sign in (1.0, -1.0):
                x = mean + sign * math.sqrt(3.0) * L[:, j]
                kw = {"a0": max(x[0], 0.0), "r0": max(x[1], 0.0)}
                if p == 3:
                    kw["k"] = max(x[2], 0.2 * fit.k)
                out.append((1.0 / 6.0, dataclasses.replace(self, fit=dataclasses.replace(fit, **kw),
                                                           uncertain=False)))
        return out


_GL_X, _GL_W = np.polynomial.legendre.leggauss(GL_NODES)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W      # on [0, 1]


def _expand(components) -> list:
    return [vc for comp in components for vc in comp.variants()]


_GL16_X, _GL16_W = np.polynomial.legendre.leggauss(16)
_GL16_X, _GL16_W = 0.5 * (_GL16_X + 1.0), 0.5 * _GL16_W


def _runs(expanded) -> list:
    """``expanded`` as runs of consecutive variants that ``_stacked_cost`` takes in one set of array
    operations (one component's sigma points: the same CostCurve, law, mode, removal share and
    floor); every other variant a run of its own. [(stackable, [(w, component), ...])]."""
    runs: list = []
    last = None
    for wv, c in expanded:
        f = c.cost_eur_per_day
        key = None
        if isinstance(f, CostCurve) and not (c.mode == "steady" and c.fit.law != "kern_seaton"
                                             and c.removal_share <= 0):
            key = (id(f), c.fit.law, c.mode, c.removal_share, c.fit.floor)
        if key is not None and key == last:
            runs[-1][1].append((wv, c))
        else:
            runs.append((key is not None, [(wv, c)]))
        last = key
    return runs


def _pieces(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start, length) of the pieces between a cycle's ``edges`` (V, m, p + 1: 0, the crossing
    times, T), only as many consecutive pieces per cycle as the longest stretch of pieces of
    non-zero length takes (the rest have length 0: levels below the start, or not reached).

    Most pieces have length 0 (76 % over a replay's CIP plans: a cycle crosses one or two of the
    cost curve's breakpoints), and each is 16 nodes of exact zeros in the integral's sum. Each
    cycle keeps a window of whole pieces around its non-zero ones: numpy sums a row of up to 128
    numbers in eight running sums by position modulo 8, and a piece is 16 numbers, so every
    running sum meets the same non-zero terms in the same order and the row's sum is the sum
    with every piece to the bit (the window falls back to every piece past 8 pieces, where numpy
    splits a row differently)."""
    a, h = edges[:, :, :-1], np.diff(edges, axis=2)
    p = h.shape[2]
    if p < 2 or p > 8:
        return a, h
    nz = h != 0.0
    first = np.where(nz.any(axis=2), nz.argmax(axis=2), 0)
    last = np.where(nz.any(axis=2), p - 1 - nz[:, :, ::-1].argmax(axis=2), 0)
    width = int((last - first).max()) + 1 if h.size else p
    if width >= p:
        return a, h
    start = np.minimum(first, p - width)
    idx = start[:, :, None] + np.arange(width)
    return np.take_along_axis(a, idx, axis=2), np.take_along_axis(h, idx, axis=2)


def _stacked_cost(members, T) -> np.ndarray:
    """Each member's integral_0^T f(level) dt (before its weight), shape (V, len(T)), for a run of
    ``_runs``: the operations of ``FoulingComponent.start_level``, ``crossing_times`` and ``levels``
    and of ``_cycle_cost``'s CostCurve branch, element by element in the same order, with the
    members' parameters along a leading axis (so the same numbers as one member at a time)."""
    comps = [c for _, c in members]
    c0 = comps[0]
    f, s, mode, law, floor = c0.cost_eur_per_day, c0.removal_share, c0.mode, c0.fit.law, c0.fit.floor
    col = lambda vals: np.array(vals, dtype=float)[:, None]     # noqa: E731 -- (V, 1)
    k, r0 = col([c.fit.k for c in comps]), col([c.fit.r0 for c in comps])
    y0, y_inf = col([c.fit.y0 for c in comps]), col([c.fit.y_inf for c in comps])
    V, m = len(comps), len(T)
    Tm = T[None, :]
    if mode == "current":
        y_post = np.broadcast_to(y0, (V, m))
    elif law == "kern_seaton":
        E = np.exp(-k * Tm)
        U = y_inf - floor
        y_post = floor + (1 - s) * U * (1 - E) / (1 - (1 - s) * E)
    else:
        y_post = floor + (1 - s) * r0 * Tm / s
    if _kernels._KERNEL is not None:        # the rest compiled, to the bit (numpy's on a NaN level)
        got = _kernels.cycle_cost(np.broadcast_to(y_post, (V, m)), k[:, 0], r0[:, 0], y_inf[:, 0],
                                  law == "kern_seaton", f.levels, f.eur_per_day, T, _GL16_X, _GL16_W)
        if got is not None:
            return got
    # crossing_times(T, f.levels): (V, m, b)
    yp = y_post[:, :, None]
    x = np.asarray(f.levels, dtype=float)[None, None, :]
    k3, r03, yi3 = k[:, :, None], r0[:, :, None], y_inf[:, :, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        if law == "kern_seaton":
            tau = np.log((yi3 - yp) / (yi3 - x)) / k3
            tau = np.where(x >= yi3, np.inf, tau)
        else:
            tau = np.where(r03 > 0, (x - yp) / r03, np.inf)
    tau = np.where((x <= yp) | np.isnan(tau), 0.0, tau)
    T3 = T[None, :, None]
    ct = np.minimum(np.maximum(tau, 0.0), T3)
    edges = np.concatenate([np.zeros((V, m, 1)), ct, np.broadcast_to(T3, (V, m, 1))], axis=2)
    a, h = _pieces(edges)
    a, h = a[:, :, :, None], h[:, :, :, None]
    # (the largest arrays of the cycle plan, V x m x 16 per level: each operation of the expressions
    # a + h x, yi - (yi - yp) exp(-k tau) and f(level) w in place in one buffer, the same numbers)
    tau = h * _GL16_X[None, None, None, :]
    tau += a
    tau = tau.reshape(V, m, -1)
    wts = (h * _GL16_W[None, None, None, :]).reshape(V, m, -1)
    # levels(T, tau): growth from y_post
    if law == "kern_seaton":
        lv = np.multiply(-k3, tau)
        np.exp(lv, out=lv)
        lv *= yi3 - yp
        np.subtract(yi3, lv, out=lv)
    else:
        lv = yp + r03 * tau
    fl = f(lv)          # (a CostCurve: a new array)
    fl *= wts
    return fl.sum(axis=2)


def _cycle_cost(expanded, T) -> np.ndarray:
    """Sum of w * integral_0^T f(level) dt. A CostCurve is piecewise linear: the integral is split
    where the path crosses its breakpoints, and each smooth piece gets 16 Gauss–Legendre nodes
    (exact to rounding for these laws); any other cost callable gets 48 nodes over [0, T]. A
    component's sigma points in one set of array operations (``_stacked_cost``), added in order;
    with the compiled kernels (``speedkernel.cycle_cost``) a variant alone goes there too (the same
    numbers: tests/test_forecast_cost.py)."""
    total = np.zeros(T.shape)
    for stackable, members in _runs(expanded):
        if stackable and (len(members) > 1 or _kernels._KERNEL is not None):
            S = _stacked_cost(members, T)
            for j, (wv, _) in enumerate(members):
                total += wv * S[j]
            continue
        wv, c = members[0]
        f = c.cost_eur_per_day
        if isinstance(f, CostCurve):
            edges = np.concatenate([np.zeros((len(T), 1)), c.crossing_times(T, f.levels), T[:, None]], axis=1)
            a, h = _pieces(edges[None])
            a, h = a[0, :, :, None], h[0, :, :, None]
            tau = (a + h * _GL16_X[None, None, :]).reshape(len(T), -1)
            wts = (h * _GL16_W[None, None, :]).reshape(len(T), -1)
            total += wv * (np.asarray(f(c.levels(T, tau))) * wts).sum(axis=1)
        else:
            tau = T[:, None] * _GL_X[None, :]
            total += wv * (np.asarray(f(c.levels(T, tau))) * _GL_W[None, :]).sum(axis=1) * T
    return total


def _end_rate(expanded, T) -> np.ndarray:
    out = np.zeros(T.shape)
    for wv, c in expanded:
        out += wv * np.asarray(c.cost_eur_per_day(c.levels(T, T[:, None])[:, 0]))
    return out


def cycle_cost_eur(components: Sequence[FoulingComponent], T_days) -> np.ndarray:
    """Fouling cost over the cycle's operation, integral_0^T f dt [EUR], for each T (Gauss–Legendre,
    split at a CostCurve's breakpoints; the sigma-point mean for ``uncertain`` components)."""
    return _cycle_cost(_expand(components), np.atleast_1d(np.asarray(T_days, dtype=float)))


def end_cost_rate_eur_per_day(components: Sequence[FoulingComponent], T_days) -> np.ndarray:
    """f at the end of the cycle of length T [EUR/day] (the sigma-point mean where ``uncertain``)."""
    return _end_rate(_expand(components), np.atleast_1d(np.asarray(T_days, dtype=float)))


def average_cost_eur_per_day(components, T_days, cip_cost_eur: float, downtime_days: float):
    """J(T) = (C + integral_0^T f dt) / (T + D) [EUR/day] for each T."""
    T = np.atleast_1d(np.asarray(T_days, dtype=float))
    return (cip_cost_eur + _cycle_cost(_expand(components), T)) / (T + downtime_days)


@dataclass(frozen=True)
class CipPlan:
    T_opt_days: float                   # optimal operating time of the steady cycle, T*
    J_opt_eur_per_day: float            # J(T*)
    f_end_eur_per_day: float            # cost rate at the end of the optimal cycle, f(T*)
    t_now_days: float                   # now, days since the last reset
    t_cip_days: float                   # recommended CIP, days since the last reset (the trigger rule)
    days_to_cip: float                  # max(0, t_cip - now): 0 = due or overdue
    trigger: str                        # "level" | "age"
    interior: bool                      # False: T* at the search range's end
    start_levels: dict                  # level after a CIP on the optimal cycle, per component
    end_levels: dict                    # level at the end of the optimal cycle, per component
    T_current_days: float | None = None
    J_current_eur_per_day: float | None = None
    saving_eur_per_year: float | None = None   # (J(T_current) - J(T*)) * 365.25
    notes: tuple = field(default_factory=tuple)
    pays: bool = True                   # False: J still falls at the searched range's end (never clean)

    @property
    def overdue(self) -> bool:
        return self.days_to_cip <= 0.0

    def recommended_date(self, reset):
        """reset + t_cip: a datetime/Timestamp (plus a timedelta) or epoch seconds (float)."""
        import datetime as _dt
        if isinstance(reset, (int, float)):
            return float(reset) + self.t_cip_days * SECONDS_PER_DAY
        return reset + _dt.timedelta(days=self.t_cip_days)


def current_cost_rate_eur_per_day(components: Sequence[FoulingComponent], t_days):
    """f(t) on the current cycle's forecast (each component's fitted mean curve) [EUR/day]."""
    t = np.asarray(t_days, dtype=float)
    return sum(np.asarray(c.cost_eur_per_day(c.fit.value(t))) for c in components)


def plan_cip(components: Sequence[FoulingComponent], *, cip_cost_eur: float, downtime_days: float,
             t_now_days: float, T_current_days: float | None = None, trigger: str = "level",
             T_min_days: float = 0.25, T_max_days: float = 365.0, n_grid: int = 100) -> CipPlan:
    """The cost-optimal cycle (T*, J(T*)), when to clean in the current cycle, and the saving.

    T* minimises J(T) on the steady cycle (module docstring): a geometric grid of ``n_grid`` values
    of T in [T_min_days, T_max_days], three nested linear grids between the best point's neighbours,
    and a parabola through the last three (T* to ~1e-6 of its value).
    trigger : "level" (default) — clean when the current cycle's forecast cost rate reaches f(T*),
        the rate at which the optimal steady cycle ends; on the steady cycle this is T* itself, and a
        cycle that started cleaner (commissioning, a good CIP) or dirtier runs longer or shorter
        accordingly; "age" — clean T* days after the reset. Where the forecast never reaches f(T*)
        within T_max_days, the age rule is used (and said in ``notes``).
    T_current_days : the current interval (the plant's median, or configured) for the saving.
    """
    if not components:
        raise CostError("plan_cip needs at least one fouling component")
    for name, v in (("cip_cost_eur", cip_cost_eur), ("downtime_days", downtime_days), ("t_now_days", t_now_days)):
        if not (math.isfinite(v) and v >= 0):
            raise CostError(f"{name} must be a finite number >= 0, got {v!r}")
    if not 0 < T_min_days < T_max_days:
        raise CostError(f"need 0 < T_min_days < T_max_days, got {T_min_days!r}, {T_max_days!r}")
    if trigger not in ("level", "age"):
        raise CostError(f"trigger must be 'level' or 'age', got {trigger!r}")

    expanded = _expand(components)

    def J(T):
        T = np.atleast_1d(np.asarray(T, dtype=float))
        return (cip_cost_eur + _cycle_cost(expanded, T)) / (T + downtime_days)

    grid = np.geomspace(T_min_days, T_max_days, n_grid)
    Jg = J(grid)
    if not np.all(np.isfinite(Jg)):
        raise CostError("the cycle cost is not finite on the search range (check the cost curves)")
    i = int(np.argmin(Jg))
    T_opt, J_opt = float(grid[i]), float(Jg[i])
    a, b = grid[max(i - 1, 0)], grid[min(i + 1, n_grid - 1)]
    for n_fine in (41, 21, 21):                  # nested vectorised grids, then a parabola
        g = np.linspace(a, b, n_fine)
        Jf = J(g)
        j = int(np.argmin(Jf))
        if Jf[j] <= J_opt:
            T_opt, J_opt = float(g[j]), float(Jf[j])
        a, b = g[max(j - 1, 0)], g[min(j + 1, n_fine - 1)]
    if 0 < j < n_fine - 1:
        y0_, y1_, y2_ = Jf[j - 1], Jf[j], Jf[j + 1]
        den = y0_ - 2 * y1_ + y2_
        if den > 0:
            T_par = float(g[j] + 0.5 * (g[1] - g[0]) * (y0_ - y2_) / den)
            J_par = float(J(T_par)[0])
            if J_par <= J_opt:
                T_opt, J_opt = T_par, J_par
    f_end = float(_end_rate(expanded, np.array([T_opt]))[0])
    interior = 0 < i < n_grid - 1
    notes = []
    if not interior:
        notes.append("optimum at the end of the searched range "
                     f"[{T_min_days:g}, {T_max_days:g}] days" + (": cleaning does not pay for itself"
                                                                 if i == n_grid - 1 else ""))
    starts = {c.name: float(np.asarray(c.start_level(T_opt)).ravel()[0]) for c in components}
    ends = {c.name: float(c.levels(np.array([T_opt]), np.array([[T_opt]]))[0, 0]) for c in components}
    now = float(t_now_days)
    t_cip = T_opt
    if trigger == "level":
        tt = np.concatenate([[0.0], np.geomspace(1e-3, now + T_max_days, 400)])
        ft = current_cost_rate_eur_per_day(components, tt)
        hit = np.flatnonzero(ft >= f_end)
        if not len(hit):
            notes.append("the current forecast does not reach the optimal cycle's end cost rate; "
                         "using the age rule")
            trigger = "age"
        elif hit[0] == 0:
            t_cip = 0.0
        else:
            lo, hi = tt[hit[0] - 1], tt[hit[0]]
            for _ in range(3):                        # nested grids: the bracket shrinks 1/200 each
                g = np.linspace(lo, hi, 201)
                k_ = int(np.flatnonzero(current_cost_rate_eur_per_day(components, g) >= f_end)[0])
                lo, hi = g[max(k_ - 1, 0)], g[k_]
            t_cip = float(hi)
    Tc = Jc = saving = None
    if T_current_days is not None:
        if not (math.isfinite(T_current_days) and T_current_days > 0):
            raise CostError(f"current interval must be > 0 days, got {T_current_days!r}")
        Tc = float(T_current_days)
        Jc = float(J(Tc)[0])
        saving = (Jc - J_opt) * DAYS_PER_YEAR
    return CipPlan(T_opt, J_opt, f_end, now, t_cip, max(0.0, t_cip - now), trigger, interior, starts, ends,
                   Tc, Jc, saving, tuple(notes), pays=i < n_grid - 1)


def median_interval_days(reset_days: Sequence[float], cip_start_days: Sequence[float]) -> float | None:
    """The plant's median operating time between a reset and the next CIP's start [day] (None when
    there is no complete cycle). reset_days[i] is the reset before cip_start_days[i]."""
    r = np.asarray(reset_days, dtype=float)
    c = np.asarray(cip_start_days, dtype=float)
    if len(r) != len(c):
        raise CostError(f"{len(r)} resets and {len(c)} CIP starts")
    d = c - r
    d = d[np.isfinite(d) & (d > 0)]
    return float(np.median(d)) if len(d) else None
