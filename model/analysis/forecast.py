"""Fouling forecast since the last reset (SPEC §10, issue 10): Kern–Seaton or linear, with bands.

The data are the window estimates of one fouling quantity since the last reset (commissioning or the
end of a CIP): ``t_days`` [day] since that reset, ``y`` in the data's unit (R_th,f in K/kW; CF_dp,f
dimensionless) and ``se`` each window's standard error (same unit). ``floor`` is the quantity's clean
value: 0 for R_th,f, 1 for CF_dp,f.

Laws
    Kern–Seaton   y(t) = y0 + (y_inf - y0) * (1 - exp(-t/tau))
    linear        y(t) = y0 + r * t                               (the fallback, tau not identifiable)

Both are fitted in one family with the parameters a0 = y0 - floor, r0 = dy/dt at t = 0 [1/day] and
k = 1/tau [1/day]:

    y(t) = floor + a0 + r0 * phi_k(t),   phi_k(t) = (1 - exp(-k t)) / k   (= t at k = 0)

so the linear law is the k = 0 member, y_inf = floor + a0 + r0/k, and the physical bounds
y_inf >= y0 >= floor, tau > 0 are a0 >= 0, r0 >= 0, k >= 0. For a fixed k the model is linear in
(a0, r0); the fit profiles the weighted sum of squares over k (a grid, then a bounded Brent
refinement) with a non-negative least-squares solve for (a0, r0) at each k.

Weights: w_i = 1/se_i'^2 with se_i' = max(se_i, se_floor_share * median(se)); a missing or
non-positive se counts as the median. The weights are relative: the residual scale
s^2 = sum(w_i * res_i^2) / (n - p) is estimated from the data (p = 3 Kern–Seaton, 2 linear), so
standard errors that are right only up to a common factor still give honest bands.

Law choice (stated rule). Kern–Seaton is used only when all of these hold, else the linear law:
  1. n >= min_windows_kern_seaton (10);
  2. the curvature is significant: F = (SSR_lin - SSR_KS) / (SSR_KS / (n - 3)) has a p-value below
     ``alpha`` (0.05) on F(1, n - 3) (the linear law is the nested k = 0 case);
  3. the covariance pins tau down: se(k)/k <= max_rel_se_k (0.5);
  4. tau is not far beyond the data: tau <= max_tau_span_ratio (10) * span;
  5. k is inside its search range (0, 50/span) — at the upper end the law is a step, not a trend.

Prior from earlier cycles (optional, ``law_prior``): the plant's 1/tau and y_inf from the completed
cycles' own (prior-free) fits enter as Gaussian pseudo-observations, weighted with the data's
residual scale; the law is then Kern–Seaton from the first day after a CIP.

Not enough data (``NotEnoughData``, never a number): fewer than ``min_windows`` (6) finite
estimates, or a span (last t - first t) shorter than ``min_span_days`` (1 day: shorter spans see
the daily cycle of the operation, not the fouling trend).

Uncertainty. Cov = s^2 * (J^T W J)^-1 from the Jacobian J of the chosen law at the optimum,
multiplied by ``overlap`` when consecutive estimates share data, or by (1 + rho)/(1 - rho) when the
residuals' lag-1 autocorrelation rho is larger than chance (2/sqrt(n)) and that is more: estimates
whose errors follow the daily operation are not independent (``fit_fouling``). With g(t) the gradient of y(t) with
respect to the parameters and q the (1 + level)/2 quantile of Student's t with n - p degrees of
freedom (divided by ``overlap``):

    mean band        y(t) +- q * sqrt(g^T Cov g)
    prediction band  y(t) +- q * sqrt(g^T Cov g + s^2 * se_typ^2),   se_typ = median(se')

The prediction band is for a new window estimate at t (the parameter uncertainty plus the windows'
residual scatter); the lower edge is never below ``floor``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from . import speedkernel as _kernels

LAWS = ("kern_seaton", "linear")
DEFAULT_LEVEL = 0.90
DEFAULT_HORIZON_DAYS = 7.0
T_MAX_DAYS = 3650.0          # limit crossings further away than this are reported as never (None)


class ForecastError(ValueError):
    """The forecast cannot be made from these inputs; the message says why."""


class NotEnoughData(ForecastError):
    """Too few windows, or too short a span, since the last reset: no forecast, not a number."""

    def __init__(self, n: int, span_days: float, min_windows: int, min_span_days: float):
        self.n, self.span_days = n, span_days
        self.min_windows, self.min_span_days = min_windows, min_span_days
        super().__init__(f"not enough data: {n} window estimate(s) over {span_days:.2f} days since the "
                         f"last reset; a forecast needs >= {min_windows} over >= {min_span_days:g} days")


@dataclass(frozen=True)
class FitSettings:
    """Thresholds of the fit (see the module docstring for the rule each one enters)."""
    min_windows: int = 6
    min_span_days: float = 1.0
    min_windows_kern_seaton: int = 10
    alpha: float = 0.05
    max_rel_se_k: float = 0.5
    max_tau_span_ratio: float = 10.0
    se_floor_share: float = 0.25
    autocorrelation: bool = True       # widen for serially correlated residuals (module docstring)

    def __post_init__(self):
        checks = (("min_windows", self.min_windows >= 3), ("min_span_days", self.min_span_days > 0),
                  ("min_windows_kern_seaton", self.min_windows_kern_seaton >= 4),
                  ("alpha", 0 < self.alpha < 1), ("max_rel_se_k", self.max_rel_se_k > 0),
                  ("max_tau_span_ratio", self.max_tau_span_ratio > 0),
                  ("se_floor_share", 0 <= self.se_floor_share <= 1))
        for name, ok in checks:
            if not ok:
                raise ForecastError(f"forecast setting {name}: invalid value {getattr(self, name)!r}")


@dataclass(frozen=True)
class Prediction:
    """A forecast value with its band; ``t_days`` since the reset."""
    t_days: float
    value: float
    lo: float
    hi: float
    level: float


@dataclass(frozen=True)
class LimitCrossing:
    """When the mean and the band's upper edge first reach ``limit`` at or after ``t_from_days``
    (days since the reset; None = not within T_MAX_DAYS, i.e. never)."""
    limit: float
    t_from_days: float
    mean_days: float | None
    upper_days: float | None
    level: float


def phi(t, k: float):
    """phi_k(t) = (1 - exp(-k t))/k [day], = t at k = 0."""
    t = np.asarray(t, dtype=float)
    if k == 0.0:
        return t.copy()
    return -np.expm1(-k * t) / k


def phi_many(t, ks) -> np.ndarray:
    """``phi`` for each k of ``ks`` (K, n): the same element operations in one array."""
    t = np.asarray(t, dtype=float)
    k = np.asarray(ks, dtype=float)
    zero = k == 0.0
    kc = k[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        # -expm1(-k t) / k as expm1(-k t) / -k (IEEE division is exact in sign: the same
        # numbers), in place; the rows of k = 0 then t
        out = np.expm1(-kc * t)
        out /= -np.where(zero, 1.0, k)[:, None]
    if zero.any():
        out[zero] = t
    return out


def dphi_dk(t, k: float):
    """d phi_k(t) / dk [day^2]; a series near k t = 0 (where the closed form cancels)."""
    t = np.asarray(t, dtype=float)
    x = k * t
    series = -t * t / 2.0 + k * t ** 3 / 3.0 - k * k * t ** 4 / 8.0
    if k == 0.0:
        return series
    with np.errstate(invalid="ignore", divide="ignore"):
        closed = (t * np.exp(-x) - phi(t, k)) / k
    return np.where(x < 1e-3, series, closed)


@dataclass(frozen=True, eq=False)
class FoulingFit:
    """The fitted law since the last reset, in the data's unit and days since the reset."""
    law: str                      # "kern_seaton" | "linear"
    floor: float                  # clean value (0 for R_th,f, 1 for CF_dp,f)
    a0: float                     # y0 - floor
    r0: float                     # dy/dt at t = 0 [1/day]
    k: float                      # 1/tau [1/day]; 0 for the linear law
    cov: np.ndarray               # covariance of (a0, r0, k) (KS) or (a0, r0) (linear)
    s2: float                     # residual variance factor of the weighted fit
    se_typ: float                 # median effective standard error of the windows
    n: int
    dof: float
    t_first: float                # first and last data time [day since reset]
    t_last: float
    reason: str                   # why this law
    p_curvature: float            # p-value of the curvature F-test (nan when not tested)
    n_dropped: int = 0            # non-finite estimates left out
    overlap: float = 1.0
    extra: dict = field(default_factory=dict)

    # ---- parameters in physical terms -----------------------------------------------------------
    @property
    def y0(self) -> float:
        return self.floor + self.a0

    @property
    def y_inf(self) -> float:
        """Asymptote (inf for the linear law)."""
        return self.floor + self.a0 + self.r0 / self.k if self.k > 0 else math.inf

    @property
    def tau_days(self) -> float:
        return 1.0 / self.k if self.k > 0 else math.inf

    @property
    def span_days(self) -> float:
        return self.t_last - self.t_first

    def std_errors(self) -> dict:
        """Standard errors of y0, r0, and (Kern–Seaton) y_inf and tau_days (delta method)."""
        c = self.cov
        out = {"y0": math.sqrt(max(c[0, 0], 0.0)), "r0": math.sqrt(max(c[1, 1], 0.0))}
        if self.law == "kern_seaton":
            k, r0 = self.k, self.r0
            g_inf = np.array([1.0, 1.0 / k, -r0 / k ** 2])
            out["y_inf"] = math.sqrt(max(float(g_inf @ c @ g_inf), 0.0))
            out["tau_days"] = math.sqrt(max(c[2, 2], 0.0)) / k ** 2
        return out

    # ---- the curve ------------------------------------------------------------------------------
    def value(self, t_days):
        """y(t) in the data's unit; t_days since the reset (scalar or array)."""
        v = self.floor + self.a0 + self.r0 * phi(t_days, self.k)
        return float(v) if np.ndim(v) == 0 else v

    def rate(self, t_days):
        """dy/dt at t [unit per day]."""
        r = self.r0 * np.exp(-self.k * np.asarray(t_days, dtype=float))
        return float(r) if np.ndim(r) == 0 else r

    def growth(self, y_start, t_days):
        """The law's growth from the level y_start over t_days (used for the next cycles):
        Kern–Seaton y_inf - (y_inf - y_start) exp(-t/tau); linear y_start + r0 t."""
        t = np.asarray(t_days, dtype=float)
        if self.law == "kern_seaton":
            return self.y_inf - (self.y_inf - np.asarray(y_start)) * np.exp(-self.k * t)
        return np.asarray(y_start) + self.r0 * t

    def _gradient(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        if self.law == "kern_seaton":
            return np.stack([np.ones_like(t), phi(t, self.k), self.r0 * dphi_dk(t, self.k)], axis=1)
        return np.stack([np.ones_like(t), t], axis=1)

    def band(self, t_days, level: float = DEFAULT_LEVEL, kind: str = "prediction"):
        """(lo, hi) at t: ``kind`` "prediction" (a new window estimate) or "mean" (the curve)."""
        if not 0 < level < 1:
            raise ForecastError(f"band level must be in (0, 1), got {level!r}")
        if kind not in ("prediction", "mean"):
            raise ForecastError(f"band kind must be 'prediction' or 'mean', got {kind!r}")
        scalar = np.ndim(t_days) == 0
        G = self._gradient(t_days)
        var = np.einsum("ij,jk,ik->i", G, self.cov, G)
        if kind == "prediction":
            var = var + self.s2 * self.se_typ ** 2
        q = special.stdtrit(max(self.dof, 1.0), 0.5 + level / 2.0)     # Student's t quantile
        v = np.atleast_1d(self.value(t_days))
        half = q * np.sqrt(np.maximum(var, 0.0))
        lo, hi = np.maximum(v - half, self.floor), v + half
        return (float(lo[0]), float(hi[0])) if scalar else (lo, hi)

    def _upper_edge(self, level: float):
        """The prediction band's upper edge at one t as a plain-float function: ``band``'s sums in
        scalar arithmetic (``reach`` bisects on it; 50 array calls cost ~30x more)."""
        q = float(special.stdtrit(max(self.dof, 1.0), 0.5 + level / 2.0))
        c = [[float(x) for x in row] for row in np.asarray(self.cov, dtype=float)]
        extra = self.s2 * self.se_typ ** 2
        base, r0, k, ks = self.floor + self.a0, self.r0, self.k, self.law == "kern_seaton"

        # g' C g with g = (1, phi, r0 dphi/dk) (Kern–Seaton) or (1, t) (linear): the sums
        # sum(g_i sum(c_ij g_j)) written out, term by term in the same order (from 0)
        if ks:
            (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = c

            def hi(t: float) -> float:
                if k == 0.0:
                    ph = t
                else:
                    ph = -math.expm1(-k * t) / k
                x = k * t
                series = -t * t / 2.0 + k * t ** 3 / 3.0 - k * k * t ** 4 / 8.0
                g2 = r0 * (series if (k == 0.0 or x < 1e-3) else (t * math.exp(-x) - ph) / k)
                var = (0 + 1.0 * (0 + c00 * 1.0 + c01 * ph + c02 * g2)
                       + ph * (0 + c10 * 1.0 + c11 * ph + c12 * g2)
                       + g2 * (0 + c20 * 1.0 + c21 * ph + c22 * g2)) + extra
                return base + r0 * ph + q * math.sqrt(max(var, 0.0))
            return hi
        (c00, c01), (c10, c11) = c

        def hi(t: float) -> float:
            ph = t if k == 0.0 else -math.expm1(-k * t) / k
            var = (0 + 1.0 * (0 + c00 * 1.0 + c01 * t) + t * (0 + c10 * 1.0 + c11 * t)) + extra
            return base + r0 * ph + q * math.sqrt(max(var, 0.0))
        return hi

    def predict(self, t_days: float, level: float = DEFAULT_LEVEL, kind: str = "prediction") -> Prediction:
        lo, hi = self.band(float(t_days), level, kind)
        return Prediction(float(t_days), self.value(float(t_days)), lo, hi, level)

    def at_horizon(self, horizon_days: float = DEFAULT_HORIZON_DAYS, t_now_days: float | None = None,
                   level: float = DEFAULT_LEVEL) -> Prediction:
        """The forecast ``horizon_days`` after now (default now: the last estimate's time)."""
        if not horizon_days >= 0:
            raise ForecastError(f"forecast horizon must be >= 0 days, got {horizon_days!r}")
        now = self.t_last if t_now_days is None else float(t_now_days)
        return self.predict(now + horizon_days, level)

    def reach(self, limit: float, t_now_days: float | None = None, level: float = DEFAULT_LEVEL,
              t_max_days: float = T_MAX_DAYS) -> LimitCrossing:
        """First time (days since the reset, >= now) the mean and the prediction band's upper edge
        reach ``limit``; now when already there; None when not within ``t_max_days`` from now."""
        now = self.t_last if t_now_days is None else float(t_now_days)
        if not math.isfinite(limit):
            raise ForecastError(f"limit must be a finite number, got {limit!r}")
        # mean: closed form (the curve is non-decreasing)
        if self.value(now) >= limit:
            t_mean = float(now)
        elif self.r0 <= 0.0:
            t_mean = None
        elif self.law == "kern_seaton":
            t_mean = (None if limit >= self.y_inf
                      else -self.tau_days * math.log((self.y_inf - limit) / (self.y_inf - self.y0)))
        else:
            t_mean = (limit - self.y0) / self.r0
        if t_mean is not None and t_mean - now > t_max_days:
            t_mean = None
        # upper edge: first grid crossing, then bisection
        grid = now + np.concatenate([[0.0], np.geomspace(1e-3, t_max_days, 400)])
        hi = self.band(grid, level)[1]
        above = np.flatnonzero(hi >= limit)
        if not len(above):
            t_up = None
        elif above[0] == 0:
            t_up = float(now)
        else:
            a, b = float(grid[above[0] - 1]), float(grid[above[0]])
            upper = self._upper_edge(level)
            for _ in range(50):
                m = 0.5 * (a + b)
                if upper(m) >= limit:
                    b = m
                else:
                    a = m
            t_up = float(b)
        return LimitCrossing(limit, now, t_mean, t_up, level)

    def to_dict(self) -> dict:
        """Plain numbers for state files and result rows (inf -> None)."""
        def num(x):
            return None if not math.isfinite(x) else float(x)
        se = self.std_errors()
        return {"law": self.law, "floor": self.floor, "y0": self.y0, "y_inf": num(self.y_inf),
                "tau_days": num(self.tau_days), "r0_per_day": self.r0, "se": {k: num(v) for k, v in se.items()},
                "n": self.n, "t_first_days": self.t_first, "t_last_days": self.t_last, "s2": self.s2,
                "reason": self.reason, "p_curvature": num(self.p_curvature)}

    def to_state(self) -> dict:
        """Everything needed to rebuild the fit (``from_state``), as plain JSON numbers; the
        analysis chain keeps the earlier cycles' fits in its state file (for ``law_prior``)."""
        cov = np.asarray(self.cov, dtype=float)
        return {"law": self.law, "floor": self.floor, "a0": self.a0, "r0": self.r0, "k": self.k,
                "cov": [[float(x) if math.isfinite(x) else None for x in row] for row in cov],
                "s2": self.s2, "se_typ": self.se_typ, "n": self.n, "dof": self.dof,
                "t_first": self.t_first, "t_last": self.t_last, "reason": self.reason,
                "p_curvature": self.p_curvature if math.isfinite(self.p_curvature) else None,
                "n_dropped": self.n_dropped, "overlap": self.overlap}

    @classmethod
    def from_state(cls, d: dict) -> "FoulingFit":
        """The fit of ``to_state``; ForecastError when the document is not one."""
        try:
            law = d["law"]
            if law not in LAWS:
                raise ValueError(f"law {law!r}")
            cov = np.array([[math.inf if x is None else float(x) for x in row] for row in d["cov"]])
            p = 3 if law == "kern_seaton" else 2
            if cov.shape != (p, p):
                raise ValueError(f"covariance of shape {cov.shape} for the {law} law")
            pc = d.get("p_curvature")
            return cls(law, float(d["floor"]), float(d["a0"]), float(d["r0"]), float(d["k"]), cov,
                       float(d["s2"]), float(d["se_typ"]), int(d["n"]), float(d["dof"]),
                       float(d["t_first"]), float(d["t_last"]), str(d.get("reason", "")),
                       math.nan if pc is None else float(pc), int(d.get("n_dropped", 0)),
                       float(d.get("overlap", 1.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise ForecastError(f"not a fouling fit: {exc}") from None

    def summary(self, unit: str = "", scale: float = 1.0, scale_label: str = "") -> str:
        se = self.std_errors()
        f = (lambda v: f"{v * scale:.4g}{scale_label}")
        s = f"{self.law} law on {self.n} estimates over {self.span_days:.2f} d: y0 {f(self.y0)} {unit}"
        if self.law == "kern_seaton":
            s += (f", y_inf {f(self.y_inf)} +- {f(se['y_inf'])} {unit}, tau {self.tau_days:.3g} +- "
                  f"{se['tau_days']:.2g} d")
        else:
            s += f", rate {f(self.r0)} +- {f(se['r0'])} {unit}/d"
        return s + f" ({self.reason})"


@dataclass(frozen=True)
class LawPrior:
    """What earlier cycles say about the plant's Kern–Seaton law: 1/tau [1/day] and y_inf, each with
    a standard deviation. Used as Gaussian pseudo-observations in the fit (see ``law_prior``)."""
    k: float
    k_sd: float
    y_inf: float
    y_inf_sd: float
    n_cycles: int

    def __post_init__(self):
        vals = (self.k, self.k_sd, self.y_inf, self.y_inf_sd)
        if not (all(math.isfinite(v) for v in vals) and self.k > 0 and self.k_sd > 0 and self.y_inf_sd > 0):
            raise ForecastError(f"a law prior needs finite k > 0, y_inf and positive spreads, got {vals!r}")


def law_prior(fits, min_sd_share: float = 0.1) -> LawPrior | None:
    """Combine earlier cycles' Kern–Seaton fits (their last fit before each CIP) into a prior.

    Inverse-variance means of k = 1/tau and y_inf; the spread is the larger of the combined standard
    error, the cycles' sample standard deviation (with >= 2 cycles) and ``min_sd_share`` of the mean
    (a plant's law drifts between cycles). Linear-law fits carry no curvature and are skipped;
    None when no Kern–Seaton fit is left.
    """
    ks = [f for f in fits if f is not None and f.law == "kern_seaton"]
    if not ks:
        return None
    out = []
    for get, se_key in ((lambda f: f.k, None), (lambda f: f.y_inf, "y_inf")):
        v = np.array([get(f) for f in ks])
        se = np.array([math.sqrt(max(f.cov[2, 2], 0.0)) if se_key is None else f.std_errors()[se_key]
                       for f in ks])
        se = np.where(np.isfinite(se) & (se > 0), se, np.abs(v))
        w = 1.0 / se ** 2
        mean = float(np.sum(w * v) / np.sum(w))
        sd = max(math.sqrt(1.0 / np.sum(w)), float(np.std(v, ddof=1)) if len(v) >= 2 else 0.0,
                 min_sd_share * abs(mean))
        out += [mean, sd]
    return LawPrior(out[0], out[1], out[2], out[3], len(ks))


def _weights(se: np.ndarray, share: float) -> np.ndarray:
    good = np.isfinite(se) & (se > 0)
    if not good.any():
        return np.ones_like(se)
    med = float(np.median(se[good]))
    se_eff = np.where(good, np.maximum(se, share * med), med)
    return se_eff


def _ls_many(ks, t, y, sw, prior_row=None):
    """Non-negative weighted least squares of y ~ a0 + r0 phi_k(t) for each k in ks (closed form: the
    unconstrained 2x2 solution, else the better of the two one-parameter edges), with the prior's
    y_inf pseudo-observation where k > 0 (prior_row = (weight, y_inf - floor)).
    Returns arrays (a0, r0, ssr of the data rows).

    The sums over the estimates are row sums (numpy's pairwise summation; not a matrix product,
    whose order is the BLAS library's), so each k's numbers do not depend on the other ks and the
    compiled kernel (``speedkernel.ls_rows``, ~5x quicker at the forecast's sizes) gives them to
    the bit."""
    ks = np.atleast_1d(np.asarray(ks, dtype=float))
    P = phi_many(t, ks)                                         # (K, n)
    if _kernels._KERNEL is not None:       # (the kernels' switch, as everywhere)
        return _kernels.ls_rows(P, sw, y, ks, prior_row)
    w2 = sw * sw
    wy = w2 * y
    G00 = np.full(len(ks), w2.sum())
    G01 = (P * w2).sum(axis=1)
    G11 = ((P * P) * w2).sum(axis=1)
    h0 = np.full(len(ks), wy.sum())
    h1 = (P * wy).sum(axis=1)
    if prior_row is not None:
        wp, yp = prior_row
        inv_k = np.where(ks > 0, 1.0 / np.where(ks > 0, ks, 1.0), 0.0)
        wp2 = np.where(ks > 0, wp * wp, 0.0)
        G00, G01, G11 = G00 + wp2, G01 + wp2 * inv_k, G11 + wp2 * inv_k ** 2
        h0, h1 = h0 + wp2 * yp, h1 + wp2 * yp * inv_k
    det = G00 * G11 - G01 * G01
    with np.errstate(divide="ignore", invalid="ignore"):
        a_u = (G11 * h0 - G01 * h1) / det
        r_u = (G00 * h1 - G01 * h0) / det
        a_e = np.maximum(h0 / G00, 0.0)                        # r0 = 0 edge
        r_e = np.where(G11 > 0, np.maximum(h1 / G11, 0.0), 0.0)  # a0 = 0 edge

    def obj(a, r):                                             # the augmented objective
        v = a * a * G00 + 2 * a * r * G01 + r * r * G11 - 2 * (a * h0 + r * h1)
        return v
    ok_u = np.isfinite(a_u) & np.isfinite(r_u) & (a_u >= 0) & (r_u >= 0)
    use_edge_a = obj(a_e, 0.0) <= obj(0.0, r_e)
    a = np.where(ok_u, a_u, np.where(use_edge_a, a_e, 0.0))
    r = np.where(ok_u, r_u, np.where(use_edge_a, 0.0, r_e))
    res = sw[None, :] * (y[None, :] - a[:, None] - r[:, None] * P)
    return a, r, (res * res).sum(axis=1)


def _ls_at(k: float, t, y, sw, prior_row=None):
    a, r, ssr = _ls_many([k], t, y, sw, prior_row)
    return float(a[0]), float(r[0]), float(ssr[0])


def _profile(t, yc, sw, k_hi, objective, grid_objective):
    """argmin over k in [0, k_hi] of objective(k): a geometric grid of k (``grid_objective``
    evaluates it on an array), then PROFILE_NESTED linear grids of PROFILE_POINTS between the best
    k > 0's neighbours (each between the previous one's best point's neighbours; the last step
    ~1.6e-4 of k), and the vertex of the parabola through the last one's best point and its
    neighbours — each grid one array evaluation (a bounded Brent search here, before stop 32, took
    ~17 evaluations of one k each, the forecast's largest cost). ``objective`` (one k) is kept for
    callers that have no array form."""
    ks = np.concatenate([[0.0], np.geomspace(k_hi * 1e-4, k_hi, 60)])
    vals = grid_objective(ks)
    i = int(np.argmin(vals[1:])) + 1
    a, b = ks[i - 1], ks[min(i + 1, len(ks) - 1)]
    k_best, v_best = float(ks[i]), float(vals[i])
    g = gv = None
    linear = False          # the last grid evaluated was a linear one (the parabola's spacing)
    grids = [None] * PROFILE_NESTED
    if a == 0.0 and b > 0.0:
        # the best k is the grid's smallest: where the profile still falls toward k = 0, down to
        # 1e-6 of the bracket (where a bounded search on (0, b) with tolerance 1e-6 b ends)
        grids.insert(0, np.geomspace(1e-6 * b, b, 2 * PROFILE_POINTS - 1))
    for grid in grids:
        if not b > a:
            break
        g, linear = (np.linspace(a, b, PROFILE_POINTS), True) if grid is None else (grid, False)
        gv = np.asarray(grid_objective(g), dtype=float)
        j = int(np.argmin(gv))
        if gv[j] <= v_best and g[j] > 0.0:
            k_best, v_best = float(g[j]), float(gv[j])
        a, b = g[max(j - 1, 0)], g[min(j + 1, len(g) - 1)]
    if linear and 0 < j < len(g) - 1 and np.isfinite(gv[j - 1:j + 2]).all():
        y0, y1, y2 = gv[j - 1], gv[j], gv[j + 1]
        den = y0 - 2.0 * y1 + y2
        if den > 0:
            k_par = float(g[j] + 0.5 * (g[1] - g[0]) * (y0 - y2) / den)
            if g[j - 1] < k_par < g[j + 1] and k_par > 0.0:
                v_par = float(np.asarray(grid_objective(np.array([k_par])), dtype=float)[0])
                if v_par <= v_best:
                    k_best, v_best = k_par, v_par
    return k_best, v_best, float(vals[0])


def _prior_covariance(J: np.ndarray, k: float, r0: float, s2: float, overlap: float,
                      prior: LawPrior) -> np.ndarray:
    """Covariance of (a0, r0, k) of a Kern–Seaton fit with the prior ``prior``, from the weighted
    Jacobian ``J`` of (a0, r0, k) at the fit, the residual variance factor s2 and the overlap.

    Computed in (a0, y_inf - floor, k), where the prior is two independent pseudo-observations
    (a diagonal information) and nothing is divided by k, then mapped to (a0, r0 = k (y_inf - floor
    - a0), k). The same matrix as inverting the information in (a0, r0, k), where the prior on y_inf
    enters through the gradient (1, 1/k, -r0/k^2) — except where the data show no growth and the
    best k tends to 0 with r0/k held: that information is then near-singular (condition ~1e16),
    and the band's upper edge depended on where the search over k stopped near 0 (up to 45 % of the
    data's range between two searches that both found k ~ 1e-9 d^-1). Here it does not."""
    T = np.array([[1.0, 0.0, 0.0], [-k, k, r0 / k], [0.0, 0.0, 1.0]])    # d(a0, r0, k)/d(a0, Y, k)
    Jy = J @ T
    info = Jy.T @ Jy / (max(s2, 1e-300) * overlap)
    info[1, 1] += 1.0 / prior.y_inf_sd ** 2
    info[2, 2] += 1.0 / prior.k_sd ** 2
    try:
        C = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
    return T @ C @ T.T


PROFILE_NESTED = 3      # the profile's nested linear grids after its geometric one ...
PROFILE_POINTS = 21     # ... of this many points each


def fit_fouling(t_days, y, se=None, *, law: str = "auto", floor: float = 0.0, overlap: float = 1.0,
                prior: LawPrior | None = None, settings: FitSettings | None = None) -> FoulingFit:
    """Fit the fouling law to the window estimates since the last reset (``_fit_fouling``), then
    look at the residuals in time order: where they are serially correlated beyond chance (lag-1
    autocorrelation rho > 2/sqrt(n); a daily pattern in the estimates, or windows sharing data),
    the n estimates carry the information of about n (1 - rho)/(1 + rho) independent ones, and the
    fit is redone with overlap = (1 + rho)/(1 - rho) (at most n/4) when that is larger than the
    given one: wider bands and a law choice that needs more evidence (``FitSettings.autocorrelation``)."""
    s = settings or FitSettings()
    memo: dict = {}     # the least-squares profiles do not depend on overlap: the refit reuses them
    fit = _fit_fouling(t_days, y, se, law=law, floor=floor, overlap=overlap, prior=prior, settings=s,
                       memo=memo)
    if not s.autocorrelation:
        return fit
    t = np.asarray(t_days, dtype=float).ravel()
    yy = np.asarray(y, dtype=float).ravel()
    keep = np.isfinite(t) & np.isfinite(yy)
    order = np.argsort(t[keep], kind="stable")
    e = (yy[keep] - fit.value(t[keep]))[order]
    e = e - e.mean()
    n = len(e)
    den = float(np.sum(e * e))
    rho = float(np.sum(e[1:] * e[:-1]) / den) if den > 0 and n > 3 else 0.0
    fit.extra["residual_rho"] = rho
    if not rho > 2.0 / math.sqrt(n):
        return fit
    eff = min((1.0 + rho) / max(1.0 - rho, 1e-6), n / 4.0)
    if eff <= overlap:
        return fit
    out = _fit_fouling(t_days, y, se, law=law, floor=floor, overlap=eff, prior=prior, settings=s,
                       memo=memo)
    out.extra["residual_rho"] = rho
    return out


def _fit_fouling(t_days, y, se=None, *, law: str = "auto", floor: float = 0.0, overlap: float = 1.0,
                 prior: LawPrior | None = None, settings: FitSettings | None = None,
                 memo: dict | None = None) -> FoulingFit:
    """Fit the fouling law to the window estimates since the last reset.

    t_days : days since the last reset (commissioning or a CIP's end) of each estimate [day], >= 0
    y : the estimates (R_th,f [K/kW], or CF_dp,f [-] with floor=1)
    se : their standard errors (same unit); None = equal weights
    law : "auto" (the stated rule), "kern_seaton" or "linear" (forced)
    floor : clean value of the quantity (lower bound of y0)
    overlap : estimates sharing data with each other (window length / spacing, >= 1)
    prior : the plant's law from earlier cycles (``law_prior``). With a prior the Kern–Seaton law is
        fitted with k and y_inf as Gaussian pseudo-observations (weighted with the data's residual
        scale s^2 of the fit without the prior) and used unless ``law="linear"``.
    memo : a dict shared by calls on the same data (t_days, y, se, floor, prior) that differ in
        ``overlap`` or ``law`` only: the least-squares fits (which depend on neither) are computed
        once and reused, the same numbers.
    Raises NotEnoughData, or ForecastError for malformed input.
    """
    s = settings or FitSettings()
    if law not in ("auto",) + LAWS:
        raise ForecastError(f"law must be 'auto', 'kern_seaton' or 'linear', got {law!r}")
    if not (isinstance(overlap, (int, float)) and overlap >= 1.0):
        raise ForecastError(f"overlap must be a number >= 1, got {overlap!r}")
    t = np.asarray(t_days, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    se = np.full(t.shape, np.nan) if se is None else np.asarray(se, dtype=float).ravel()
    if not (len(t) == len(y) == len(se)):
        raise ForecastError(f"t_days, y and se differ in length: {len(t)}, {len(y)}, {len(se)}")
    keep = np.isfinite(t) & np.isfinite(y)
    n_dropped = int((~keep).sum())
    t, y, se = t[keep], y[keep], se[keep]
    if len(t) and t.min() < 0:
        raise ForecastError(f"t_days must be >= 0 (days since the last reset), got {t.min():.4g}")
    n = len(t)
    span = float(t.max() - t.min()) if n else 0.0
    if n < s.min_windows or span < s.min_span_days:
        raise NotEnoughData(n, span, s.min_windows, s.min_span_days)

    se_eff = _weights(se, s.se_floor_share)
    sw = 1.0 / se_eff
    yc = y - floor
    se_typ = float(np.median(se_eff))
    k_hi = 50.0 / span

    def cov_of(J, ssr_, p, info_prior=None):
        s2_ = ssr_ / max(n - p, 1)
        info = J.T @ J / (max(s2_, 1e-300) * overlap)
        if info_prior is not None:
            info = info + info_prior
        try:
            C = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            C = np.full((p, p), np.inf)
        return C, s2_

    memo = {} if memo is None else memo
    # ---- the family without a prior: best k > 0 and the linear member ---------------------------
    if "free" not in memo:
        k_ks, ssr_ks, ssr_lin = _profile(t, yc, sw, k_hi, lambda k: _ls_at(k, t, yc, sw)[2],
                                         lambda ks: _ls_many(ks, t, yc, sw)[2])
        a_ks, r_ks, ssr_ks = _ls_at(k_ks, t, yc, sw)
        a_lin, r_lin, ssr_lin = _ls_at(0.0, t, yc, sw)
        if ssr_ks > ssr_lin:
            k_ks, a_ks, r_ks, ssr_ks = 0.0, a_lin, r_lin, ssr_lin
        memo["free"] = (k_ks, a_ks, r_ks, ssr_ks, a_lin, r_lin, ssr_lin)
    k_ks, a_ks, r_ks, ssr_ks, a_lin, r_lin, ssr_lin = memo["free"]

    def linear_fit(reason):
        J = np.stack([sw, sw * t], axis=1)
        cov_lin, s2_lin = cov_of(J, ssr_lin, 2)
        return FoulingFit("linear", float(floor), a_lin, r_lin, 0.0, cov_lin, s2_lin, se_typ, n,
                          (n - 2) / overlap, float(t.min()), float(t.max()), reason, p_curv, n_dropped,
                          float(overlap))

    p_curv = math.nan
    if prior is not None and law != "linear":
        s2_0 = max(min(ssr_ks, ssr_lin) / max(n - 3, 1), 1e-300)
        wp = math.sqrt(s2_0) / prior.y_inf_sd
        row = (wp, prior.y_inf - floor)

        def grid_objective(ks):
            a, r, ssr_d = _ls_many(ks, t, yc, sw, row)
            with np.errstate(divide="ignore", invalid="ignore"):
                y_inf = np.where(ks > 0, a + r / np.where(ks > 0, ks, 1.0), np.inf)
            v = ssr_d + s2_0 * ((y_inf - row[1]) / prior.y_inf_sd) ** 2 + s2_0 * ((ks - prior.k) / prior.k_sd) ** 2
            return np.where(ks > 0, v, np.inf)
        if "prior" not in memo:
            k_p, _, _ = _profile(t, yc, sw, max(k_hi, 10 * prior.k),
                                 lambda k: float(grid_objective(np.array([k]))[0]), grid_objective)
            memo["prior"] = (k_p, *_ls_at(k_p, t, yc, sw, row))
        k_p, a_p, r_p, ssr_p = memo["prior"]
        if k_p <= 0 or r_p <= 0:
            raise ForecastError("the Kern–Seaton law with the prior cannot be fitted to these data")
        J = np.stack([sw, sw * phi(t, k_p), sw * r_p * dphi_dk(t, k_p)], axis=1)
        s2_p = ssr_p / max(n - 3, 1)
        cov_p = _prior_covariance(J, k_p, r_p, s2_p, overlap, prior)
        reason = (f"Kern–Seaton with the law of {prior.n_cycles} earlier cycle(s) as prior "
                  f"(tau {1 / prior.k:.3g} d, y_inf {prior.y_inf:.4g})")
        return FoulingFit("kern_seaton", float(floor), a_p, r_p, k_p, cov_p, s2_p, se_typ, n,
                          (n - 3) / overlap, float(t.min()), float(t.max()), reason, p_curv, n_dropped,
                          float(overlap))

    # ---- Kern–Seaton covariance and the law rule ------------------------------------------------
    if n > 3 and k_ks > 0:
        J = np.stack([sw, sw * phi(t, k_ks), sw * r_ks * dphi_dk(t, k_ks)], axis=1)
        cov_ks, s2_ks = cov_of(J, ssr_ks, 3)
        F = max(ssr_lin - ssr_ks, 0.0) / (max(ssr_ks, 1e-300) / (n - 3))
        p_curv = float(special.fdtrc(1, (n - 3) / overlap, F)) if F > 0 else 1.0   # F test's p
    else:
        cov_ks, s2_ks = np.full((3, 3), np.inf), math.inf
    rel_se_k = (math.sqrt(cov_ks[2, 2]) / k_ks if k_ks > 0 and np.isfinite(cov_ks[2, 2])
                and cov_ks[2, 2] >= 0 else math.inf)
    failures = []
    if n < s.min_windows_kern_seaton:
        failures.append(f"{n} < {s.min_windows_kern_seaton} estimates")
    if k_ks <= 0 or r_ks <= 0:
        failures.append("no curvature (best tau infinite)")
    else:
        if not p_curv < s.alpha:
            failures.append(f"curvature not significant (F-test p = {p_curv:.3g} >= {s.alpha:g})")
        if not rel_se_k <= s.max_rel_se_k:
            failures.append(f"se(1/tau)/(1/tau) = {rel_se_k:.3g} > {s.max_rel_se_k:g}")
        if 1.0 / k_ks > s.max_tau_span_ratio * span:
            failures.append(f"tau {1.0 / k_ks:.3g} d > {s.max_tau_span_ratio:g} x span {span:.3g} d")
        if k_ks >= 0.999 * k_hi:
            failures.append(f"tau {1.0 / k_ks:.3g} d at the lower end of its range (a step, not a trend)")
    if law == "linear":
        return linear_fit("law forced by the caller")
    if law == "kern_seaton":
        if k_ks <= 0 or r_ks <= 0 or not np.isfinite(cov_ks).all():
            raise ForecastError("the Kern–Seaton law cannot be fitted to these data: "
                                + ("; ".join(failures) or "singular covariance"))
        reason = "law forced by the caller"
    elif failures:
        return linear_fit("; ".join(failures))
    else:
        reason = f"curvature significant (F-test p = {p_curv:.3g}), se(1/tau)/(1/tau) = {rel_se_k:.2f}"
    return FoulingFit("kern_seaton", float(floor), a_ks, r_ks, k_ks, cov_ks, s2_ks, se_typ, n,
                      (n - 3) / overlap, float(t.min()), float(t.max()), reason, p_curv, n_dropped,
                      float(overlap))
