"""Vectorised refrigerant properties for the measured side: spline tables built from the equation of
state once per process.

The measured side (SPEC §4, §9) needs, for every one-minute sample, the saturation state at three
pressures and the superheated-vapour state at four (p, T) points plus two isentropic states: a
scalar HEOS call costs 6-12 us, ~130 us per sample, ~6 s for a month of samples and again for every
window that re-derives its samples. These tables answer the same questions for whole arrays at
once (a month in well under a second):

- saturation: T, h_f, h_g, s_g, rho_g as cubic splines in ln p on 3000 nodes (spaced evenly in
  1/T, about evenly in ln p): T_sat within 1e-12 K of HEOS;
- superheated vapour: h, s, rho as bicubic splines in (ln p, theta) with theta = T - T_sat(p) the
  superheat, on nodes dense near saturation (theta = 220 K * u^2): within ~1e-3 J/kg in h, ~1e-6
  J/kg/K in s and ~1e-8 relative in rho of HEOS over 0.5-80 bar and 0-220 K of superheat
  (``tests/test_proptable.py`` checks the bounds);
- isentropic states (p, s) -> (h, T, rho) by a vectorised Newton on the spline in theta.

Values outside the tables' range come back as NaN; callers evaluate those rows with the scalar
``model.fluid`` functions. Building the tables takes ~0.2 s (HEOS at ~20,000 points) on first use in
a process; they are deterministic, so every process computes the same numbers. SI units: Pa, K,
J/kg, J/kg/K, kg/m^3.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline, RectBivariateSpline

from .fluid import Fluid

SAT_NODES = 3000
SAT_P_MIN = 0.2e5             # Pa
SAT_P_MAX_REL = 0.90          # of the critical pressure (h_f, h_g steepen toward it)
VAP_P_MIN, VAP_P_MAX = 0.5e5, 80e5
VAP_NODES = (160, 100)        # (ln p, theta)
THETA_MAX = 220.0             # K of superheat
NEWTON_ITER = 30


@dataclass
class SatArrays:
    T: np.ndarray
    h_f: np.ndarray
    h_g: np.ndarray
    s_g: np.ndarray
    rho_g: np.ndarray


class PropertyTables:
    """Spline tables of one fluid (see the module docstring). Read-only once built."""

    def __init__(self, name: str = "Ammonia") -> None:
        fl = Fluid(name, "HEOS")
        self.name = name
        self.p_crit = fl.p_crit
        # nodes evenly spaced in ln p, placed by temperature ((Q,T) inputs are ~20x cheaper than
        # (P,Q)): T_sat at the pressure nodes from the ancillary-free inversion of a fine T grid
        T_lo, T_hi = fl.sat_p(SAT_P_MIN).T, fl.sat_p(SAT_P_MAX_REL * fl.p_crit).T
        u = np.linspace(0.0, 1.0, SAT_NODES)
        T_nodes = 1.0 / (1.0 / T_lo + u * (1.0 / T_hi - 1.0 / T_lo))    # ~even in ln p (Clausius)
        sats = [fl.sat_T(float(T)) for T in T_nodes]
        x = np.log([s_.p for s_ in sats])
        cols = {k: np.array([getattr(s_, k) for s_ in sats]) for k in ("T", "h_f", "h_g", "s_g", "rho_g")}
        self._sat = {k: CubicSpline(x, v) for k, v in cols.items()}
        self._sat_range = (float(x[0]), float(x[-1]))
        # superheated vapour on (ln p, theta)
        xp = np.linspace(math.log(VAP_P_MIN), math.log(VAP_P_MAX), VAP_NODES[0])
        th = THETA_MAX * np.linspace(0.0, 1.0, VAP_NODES[1]) ** 2
        H = np.empty((len(xp), len(th)))
        S = np.empty_like(H)
        R = np.empty_like(H)
        T_sat = self._sat["T"](xp)
        for i, v in enumerate(xp):
            p = math.exp(v)
            for j, t in enumerate(th):
                H[i, j], S[i, j], R[i, j] = fl.vapour_pT(p, float(T_sat[i]) + t)
        self._h = RectBivariateSpline(xp, th, H)
        self._s = RectBivariateSpline(xp, th, S)
        self._rho = RectBivariateSpline(xp, th, R)
        self._vap_range = (xp[0], xp[-1])

    # ---- saturation ---------------------------------------------------------------------------
    def sat(self, p) -> SatArrays:
        """Saturation state at pressures p [Pa] (NaN outside the table)."""
        x, ok = self._lnp(p, self._sat_range)
        out = {k: np.where(ok, f(x), np.nan) for k, f in self._sat.items()}
        return SatArrays(**out)

    def T_sat(self, p) -> np.ndarray:
        x, ok = self._lnp(p, self._sat_range)
        return np.where(ok, self._sat["T"](x), np.nan)

    # ---- superheated vapour -------------------------------------------------------------------
    def vapour(self, p, T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h, s, rho) of superheated vapour at (p [Pa], T [K]); NaN below saturation or outside."""
        x, ok = self._lnp(p, self._vap_range)
        th = np.asarray(T, dtype=float) - self._sat["T"](x)
        ok &= np.isfinite(th) & (th >= 0.0) & (th <= THETA_MAX)
        x, th = np.where(ok, x, self._vap_range[0]), np.where(ok, th, 0.0)
        h = self._h.ev(x, th)
        s = self._s.ev(x, th)
        rho = self._rho.ev(x, th)
        nan = np.nan
        return np.where(ok, h, nan), np.where(ok, s, nan), np.where(ok, rho, nan)

    def isentropic(self, p, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h, T, rho) of superheated vapour at pressure p [Pa] and entropy s [J/kg/K] (NaN where
        the state is not superheated vapour within the table)."""
        x, ok = self._lnp(p, self._vap_range)
        s = np.asarray(s, dtype=float)
        ok &= np.isfinite(s)
        x = np.where(ok, x, self._vap_range[0])
        s_lo = self._s.ev(x, np.zeros_like(x))
        s_hi = self._s.ev(x, np.full_like(x, THETA_MAX))
        ok &= (s >= s_lo) & (s <= s_hi)
        # Newton in theta on the monotone, concave s(theta) (ds/dtheta = c_p/T), safeguarded by
        # bisection, on the rows not yet converged; started from the ideal-gas step off saturation
        # with the saturated vapour's c_p: theta0 = T_sat (exp((s - s_g) / c_p) - 1)
        T_sat = self._sat["T"](x)
        cp0 = T_sat * self._s.ev(x, np.zeros_like(x), dy=1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            th0 = T_sat * np.expm1(np.where(cp0 > 0, (s - s_lo) / cp0, 0.0))
        th = np.where(ok, np.clip(np.nan_to_num(th0, nan=0.0, posinf=THETA_MAX), 0.0, THETA_MAX), 0.0)
        a, b = np.zeros_like(x), np.full_like(x, THETA_MAX)
        act = np.flatnonzero(ok)
        for _ in range(NEWTON_ITER):
            if not len(act):
                break
            xa, ta = x[act], th[act]
            f = self._s.ev(xa, ta) - s[act]
            df = self._s.ev(xa, ta, dy=1)
            aa = np.where(f < 0, ta, a[act])
            bb = np.where(f >= 0, ta, b[act])
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(df > 0, f / df, 0.0)
            nxt = ta - step
            # a row on its root (f == 0: step 0, on the bracket's end) stays there; a Newton step
            # that leaves the bracket bisects it
            nxt = np.where(((nxt > aa) & (nxt < bb)) | (f == 0), nxt, 0.5 * (aa + bb))
            th[act], a[act], b[act] = nxt, aa, bb
            act = act[np.abs(nxt - ta) > 1e-9]
        T = T_sat + th
        h = self._h.ev(x, th)
        rho = self._rho.ev(x, th)
        nan = np.nan
        return np.where(ok, h, nan), np.where(ok, T, nan), np.where(ok, rho, nan)

    @staticmethod
    def _lnp(p, rng) -> tuple[np.ndarray, np.ndarray]:
        p = np.asarray(p, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.log(np.where(p > 0, p, np.nan))
        ok = np.isfinite(x) & (x >= rng[0]) & (x <= rng[1])
        return np.where(ok, x, rng[0]), ok


class NoTables:
    """A stand-in that answers nothing (NaN everywhere): every caller then evaluates every row with
    the scalar HEOS functions, as before the tables existed. ``use_tables(False)`` selects it, so a
    benchmark can compare the tables with the equation of state on the same data."""

    def sat(self, p) -> SatArrays:
        nan = np.full(np.shape(p), np.nan)
        return SatArrays(nan, nan, nan, nan, nan)

    def T_sat(self, p) -> np.ndarray:
        return np.full(np.shape(p), np.nan)

    def vapour(self, p, T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nan = np.full(np.broadcast(np.asarray(p), np.asarray(T)).shape, np.nan)
        return nan, nan, nan

    def isentropic(self, p, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.vapour(p, s)


_LOCK = threading.Lock()
_TABLES: dict[str, PropertyTables] = {}
_ENABLED = True


def use_tables(enabled: bool) -> bool:
    """Switch the tables on (the default) or off in this process (off: HEOS row by row, the exact
    and slow path; for benchmarks). Returns the previous setting."""
    global _ENABLED
    prev, _ENABLED = _ENABLED, bool(enabled)
    return prev


def get_tables(name: str = "Ammonia") -> PropertyTables | NoTables:
    """The fluid's tables, built on first use in this process (thread-safe; read-only after);
    a ``NoTables`` when ``use_tables(False)``."""
    if not _ENABLED:
        return NoTables()
    t = _TABLES.get(name)
    if t is None:
        with _LOCK:
            t = _TABLES.get(name)
            if t is None:
                t = _TABLES[name] = PropertyTables(name)
    return t
