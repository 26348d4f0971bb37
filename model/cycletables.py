"""Spline tables of the refrigerant for the vectorised flowsheet (``model.vflowsheet``), in the
coordinates the flowsheet works in: saturation temperatures.

The flowsheet's unknowns are saturation temperatures (T_e, T_m, T_c), so every state it needs is a
function of one saturation temperature T_sat and one more coordinate:

- saturation by temperature: p, h_f, h_g, s_g, rho_g at T_sat (cubic splines on a 0.05-K grid,
  ln p and ln rho_g splined for relative accuracy), and its inverse T_sat(p) by Newton on the same
  spline (so that sat(T_sat(p)).p == p to round-off);
- superheated vapour at (p_sat(T_sat), T_sat + theta): h, s, ln rho as tensor-product cubic splines
  in (T_sat, u), theta = THETA_GRID * expm1(a u)/expm1(a): nodes 0.12 K apart at saturation, a few K
  at 100-200 K, up to 4500 K of superheat (the scalar solver's trial points reach 2000 K and more
  where eta_HS is small and the pressure ratio large, and those rows must follow its path). A map
  with a finite slope at u = 0: theta ~ u^2 turned the vapour's curvature near saturation into
  5e-3 J/kg errors;
- derived from that spline, for direct lookups without Newton in the flowsheet's hot path: h of the
  isentropic state on (T_sat, s - s_g) and the superheat on (T_sat, h - h_g);
- subcooled liquid at (p_sat(T_c), T_c - d): h as a tensor-product cubic spline in (T_c, d).

Evaluation gathers the cell's polynomial coefficients (scaled to the unit cell) and runs Horner on
whole arrays: no scipy call in the hot path. The spline nodes reach PAD nodes beyond the valid
ranges (metastable vapour and liquid included) so that the end conditions stay outside them.

Accuracy against HEOS (``tests/test_vcycle.py`` checks it on random states): saturation p and rho
to 1e-11 relative, h to 1e-6 J/kg, T_sat(p) to 1e-9 K; vapour h to 1e-3 J/kg up to 220 K of
superheat (3e-3 J/kg near saturation above 370 K), 2e-2 J/kg beyond (1e-9 relative), s to 1e-5
J/kg/K, rho to 1e-8 relative; the isentropic h to 3e-3 J/kg and T from h to 1e-6 K; liquid h to
2e-3 J/kg. Outside the tables' ranges the functions return NaN: the caller solves those rows with
the scalar HEOS path. The tables are built from HEOS (~0.9 s CPU) and are deterministic; a
process keeps them in a cache file that later processes read (``cache_file``, ~30 MB).
SI units: K, Pa, J/kg, J/kg/K, kg/m^3.
"""
from __future__ import annotations

import contextlib
import hashlib
import math
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline

from .analysis import speedkernel as _kernels
from .fluid import Fluid
from .heap import release_heap

SAT_T_MIN, SAT_T_MAX, SAT_DT = 200.0, 395.0, 0.05      # K
VAP_T_MIN, VAP_T_MAX, VAP_DT = 230.0, 385.0, 1.0       # K (valid range; nodes 4 K beyond): an
                                                        # ammonia heat pump for district heating
                                                        # evaporates far above -43 degC; colder rows
                                                        # take the scalar HEOS path (~5 MB of RSS less)
THETA_MAX = 4500.0                                      # K of superheat (valid range)
THETA_GRID, VAP_NU, VAP_ALPHA = 5000.0, 300, 7.0        # theta nodes: THETA_GRID*expm1(a u)/expm1(a)
LIQ_T_MIN, LIQ_T_MAX, LIQ_DT = 270.0, 385.0, 1.0        # K (condensing temperature)
LIQ_D_MAX, LIQ_DD = 70.0, 0.5                           # K of subcooling
DS_GRID, DS_ALPHA, DS_MAX = 9000.0, 6.5, 8500.0         # derived table on s - s_g [J/kg/K]: map, valid
DH_GRID, DH_ALPHA, DH_MAX = 1.4e7, 8.5, 1.3e7           # derived table on h - h_g [J/kg]: map, valid
DER_NU = 260                                            # nodes of the derived tables' second axis
T_RANGE = (LIQ_T_MIN, VAP_T_MAX)                        # condensing temperatures every table covers
PAD = 4                                                 # nodes beyond the valid ranges
NEWTON_ITER = 40


U_MAX = math.log1p(THETA_MAX * math.expm1(VAP_ALPHA) / THETA_GRID) / VAP_ALPHA   # u of THETA_MAX


def theta_of_u(u):
    """Superheat [K] at the vapour table's coordinate u in [0, 1]."""
    return THETA_GRID * np.expm1(VAP_ALPHA * np.asarray(u, dtype=float)) / math.expm1(VAP_ALPHA)


def u_of_theta(theta):
    """The vapour table's coordinate u of superheat theta [K] >= 0."""
    return np.log1p(np.asarray(theta, dtype=float) * (math.expm1(VAP_ALPHA) / THETA_GRID)) / VAP_ALPHA


def _ppoly_unit(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients (n-1, 4, k) of the not-a-knot cubic spline through y (n, k) on the uniform grid
    x, as polynomials in the unit-cell coordinate t = (x - x_i)/dx: ((c0 t + c1) t + c2) t + c3."""
    c = CubicSpline(x, y, axis=0).c                      # (4, n-1, k) in (x - x_i)
    dx = x[1] - x[0]
    scale = dx ** np.arange(3, -1, -1, dtype=float)      # dx^3, dx^2, dx, 1
    return np.ascontiguousarray(np.moveaxis(c * scale[:, None, None], 0, 1))


def _bicubic_unit(x: np.ndarray, u: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Coefficients (cells, 16) of the tensor-product not-a-knot cubic spline through F (nx, nu) on
    uniform grids x, u; cell (i, j) has flat index i*(nu-1)+j and row l*4+k holds the coefficient of
    tx^(3-l) tu^(3-k) (unit-cell coordinates)."""
    nx, nu = F.shape
    cu = _ppoly_unit(u, F.T)                             # (nu-1, 4, nx): along u per x node
    cx = _ppoly_unit(x, cu.transpose(2, 0, 1).reshape(nx, (nu - 1) * 4))   # along x
    # cx: (nx-1, 4[l], (nu-1)*4[k]) -> (nx-1, nu-1, 4[l], 4[k])
    C = cx.reshape(nx - 1, 4, nu - 1, 4).transpose(0, 2, 1, 3)
    return np.ascontiguousarray(C.reshape((nx - 1) * (nu - 1), 16))


class CycleTables:
    """The tables of one fluid (see the module docstring). Read-only once built."""

    def __init__(self, name: str = "Ammonia") -> None:
        fl = Fluid(name, "HEOS")
        self.name = name
        self.T_crit, self.p_crit, self.T_triple = fl.T_crit, fl.p_crit, fl.T_triple
        # ---- saturation by temperature
        T = np.arange(SAT_T_MIN, SAT_T_MAX + 0.5 * SAT_DT, SAT_DT)
        sats = [fl.sat_T(float(t)) for t in T]
        Y = np.array([[math.log(s.p), s.h_f, s.h_g, s.s_g, math.log(s.rho_g)] for s in sats])
        self._sat_c = _ppoly_unit(T, Y)
        self._sat_x0, self._sat_n = T[0], len(T)
        self._sat_T, self._sat_lnp = T, Y[:, 0]
        # ---- superheated vapour on (T_sat, u), theta(u) dense near saturation; the nodes reach
        # beyond the valid ranges so that the splines' end conditions stay outside them
        Tv = np.arange(VAP_T_MIN - 4.0, VAP_T_MAX + 4.0 + 0.5 * VAP_DT, VAP_DT)
        u = np.arange(-PAD, VAP_NU) / (VAP_NU - 1.0)      # PAD nodes of metastable vapour below 0
        th = theta_of_u(u)
        H = np.empty((len(Tv), len(u)))
        S, R = np.empty_like(H), np.empty_like(H)
        p_v = np.exp(self._sat_eval(Tv, 0))
        for i, (t, p) in enumerate(zip(Tv, p_v)):
            for j, tj in enumerate(th):
                H[i, j], S[i, j], R[i, j] = fl.vapour_pT(float(p), float(t + tj))
        # one gather per cell for the three quantities: (cells, 4 [tx power], 4 [tu power], 3)
        self._vap = np.ascontiguousarray(np.stack(
            [_bicubic_unit(Tv, u, F).reshape(-1, 4, 4) for F in (H, S, np.log(R))], axis=-1))
        self._vap_x0, self._vap_nx, self._vap_nu = Tv[0], len(Tv), len(u)
        self._vap_du, self._vap_u0 = u[1] - u[0], u[0]
        # ---- derived from the vapour spline, for direct lookups in the flowsheet: h of the
        # isentropic state on (T_sat, ds = s - s_g) and the superheat on (T_sat, dh = h - h_g)
        gs = self._sat_eval(Tv, slice(2, 4))                      # h_g, s_g at the nodes
        w = np.arange(-PAD, DER_NU) / (DER_NU - 1.0)
        for name, grid, alpha, col, key in (("_isen", DS_GRID, DS_ALPHA, 1, "s"),
                                            ("_tofh", DH_GRID, DH_ALPHA, 0, "h")):
            dv = grid * np.expm1(alpha * w) / math.expm1(alpha)
            tgt = (gs[:, col][:, None] + dv[None, :]).ravel()
            th, h, _, _ = self.vapour_from(key, np.repeat(Tv, len(w)), tgt, None, _build=True)
            F = (h if key == "s" else th).reshape(len(Tv), len(w))
            if not np.all(np.isfinite(F)):
                raise ArithmeticError(f"{name}: the vapour table does not cover its nodes")
            setattr(self, name, _bicubic_unit(Tv, w, F))
        self._der_dw, self._der_w0, self._der_nw = w[1] - w[0], w[0], len(w)
        # ---- subcooled liquid on (T_c, d): h at (p_sat(T_c), T_c - d)
        Tl = np.arange(LIQ_T_MIN - 4.0, LIQ_T_MAX + 4.0 + 0.5 * LIQ_DT, LIQ_DT)
        d = np.arange(-PAD, LIQ_D_MAX / LIQ_DD + 4.5) * LIQ_DD   # PAD nodes of metastable liquid
        p_l = np.exp(self._sat_eval(Tl, 0))
        hf_l = self._sat_eval(Tl, 1)
        HL = np.empty((len(Tl), len(d)))
        for i, (t, p) in enumerate(zip(Tl, p_l)):
            for j, dj in enumerate(d):
                # saturated liquid at d = 0 (the (P,T) flash is not defined there)
                HL[i, j] = hf_l[i] if dj == 0.0 else fl.liquid_pT(float(p), float(t - dj))
        self._liq = _bicubic_unit(Tl, d, HL)
        self._liq_x0, self._liq_nx, self._liq_nd, self._liq_d0 = Tl[0], len(Tl), len(d), d[0]

    # ---- saturation ---------------------------------------------------------------------------
    def _sat_eval(self, T, col):
        """Spline column(s) ``col`` of the saturation table at T (no range check)."""
        t = (np.asarray(T, dtype=float) - self._sat_x0) * (1.0 / SAT_DT)
        i = np.minimum(np.maximum(t.astype(np.intp), 0), self._sat_n - 2)
        t = t - i
        c = self._sat_c[i, :, col]
        if c.ndim == 2:
            return ((c[:, 0] * t + c[:, 1]) * t + c[:, 2]) * t + c[:, 3]
        t = t[:, None]
        return ((c[:, 0] * t + c[:, 1]) * t + c[:, 2]) * t + c[:, 3]

    def sat_ok(self, T) -> np.ndarray:
        T = np.asarray(T, dtype=float)
        return (T >= SAT_T_MIN) & (T <= SAT_T_MAX)

    def sat(self, T) -> tuple[np.ndarray, ...]:
        """(p [Pa], h_f, h_g [J/kg], s_g [J/kg/K], rho_g [kg/m^3]) at saturation temperatures T [K]
        (NaN outside the table)."""
        T = np.asarray(T, dtype=float)
        if _kernels._KERNEL is not None and T.ndim == 1:
            v = _kernels.sat_full(self._sat_c, T, self._sat_x0, 1.0 / SAT_DT, self._sat_n - 2, SAT_T_MIN,
                                  SAT_T_MAX)
            return np.exp(v[0]), v[1], v[2], v[3], np.exp(v[4])
        v = self._sat_eval(np.where(self.sat_ok(T), T, SAT_T_MIN), slice(None))
        v = np.where(self.sat_ok(T)[:, None], v, np.nan)
        return np.exp(v[:, 0]), v[:, 1], v[:, 2], v[:, 3], np.exp(v[:, 4])

    def p_sat(self, T) -> np.ndarray:
        T = np.asarray(T, dtype=float)
        ok = self.sat_ok(T)
        return np.where(ok, np.exp(self._sat_eval(np.where(ok, T, SAT_T_MIN), 0)), np.nan)

    def h_f(self, T) -> np.ndarray:
        T = np.asarray(T, dtype=float)
        ok = self.sat_ok(T)
        return np.where(ok, self._sat_eval(np.where(ok, T, SAT_T_MIN), 1), np.nan)

    def T_sat(self, p) -> np.ndarray:
        """Saturation temperature [K] at pressures p [Pa] (NaN outside the table)."""
        p = np.asarray(p, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            y = np.log(np.where(p > 0, p, np.nan))
        ok = np.isfinite(y) & (y >= self._sat_lnp[0]) & (y <= self._sat_lnp[-1])
        y = np.where(ok, y, self._sat_lnp[0])
        T = np.interp(y, self._sat_lnp, self._sat_T)
        for _ in range(8):
            t = (T - self._sat_x0) * (1.0 / SAT_DT)
            i = np.minimum(np.maximum(t.astype(np.intp), 0), self._sat_n - 2)
            t = t - i
            c = self._sat_c[i, :, 0]
            f = ((c[:, 0] * t + c[:, 1]) * t + c[:, 2]) * t + c[:, 3] - y
            df = ((3.0 * c[:, 0] * t + 2.0 * c[:, 1]) * t + c[:, 2]) * (1.0 / SAT_DT)
            step = f / df
            T = T - step
            if np.all(np.abs(step) < 1e-11):
                break
        return np.where(ok, T, np.nan)

    # ---- superheated vapour -------------------------------------------------------------------
    @staticmethod
    def _bicubic(C, cell, tx, ty, deriv: bool = False):
        """Value (and d/dty in the unit cell) of the bicubic coefficients C at (cell, tx, ty)."""
        g = C[cell]                                       # (N, 16)
        tx = tx[:, None]
        a = ((g[:, 0:4] * tx + g[:, 4:8]) * tx + g[:, 8:12]) * tx + g[:, 12:16]   # (N, 4) in ty
        v = ((a[:, 0] * ty + a[:, 1]) * ty + a[:, 2]) * ty + a[:, 3]
        if not deriv:
            return v
        return v, (3.0 * a[:, 0] * ty + 2.0 * a[:, 1]) * ty + a[:, 2]

    def vap_ok(self, T_sat, theta) -> np.ndarray:
        return ((T_sat >= VAP_T_MIN) & (T_sat <= VAP_T_MAX) & (theta >= 0.0) & (theta <= THETA_MAX))

    def _vap_row(self, Tq):
        """Flat cell offset and unit-cell coordinate of T_sat (no range check)."""
        x = (Tq - self._vap_x0) * (1.0 / VAP_DT)
        i = np.minimum(np.maximum(x.astype(np.intp), 0), self._vap_nx - 2)
        return i * (self._vap_nu - 1), (x - i)[:, None, None]

    def _vap_cubics(self, base, tx, u):
        """(j, t, a): the u cell of u, the unit coordinate in it, and the cell's cubics in t of
        (h, s, ln rho) at the row's T_sat, a (N, 4, 3)."""
        y = (u - self._vap_u0) * (1.0 / self._vap_du)
        j = np.minimum(np.maximum(y.astype(np.intp), 0), self._vap_nu - 2)
        g = self._vap[base + j]                                   # (N, 4, 4, 3)
        a = ((g[:, 0] * tx + g[:, 1]) * tx + g[:, 2]) * tx + g[:, 3]
        return j, y - j, a

    @staticmethod
    def _cubic(a, t):
        """The cubics a (N, 4, k) at t (N,): (N, k)."""
        t = t[:, None]
        return ((a[:, 0] * t + a[:, 1]) * t + a[:, 2]) * t + a[:, 3]

    def vapour(self, T_sat, theta) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h [J/kg], s [J/kg/K], rho [kg/m^3]) of vapour at p_sat(T_sat), T_sat + theta [K]
        (NaN outside the table)."""
        T_sat, theta = np.broadcast_arrays(np.asarray(T_sat, dtype=float), np.asarray(theta, dtype=float))
        ok = self.vap_ok(T_sat, theta)
        if _kernels._KERNEL is not None and T_sat.ndim == 1:
            v = _kernels.vapour(self._vap, T_sat, theta, u_of_theta(np.where(ok, theta, 0.0)), self._vap_x0,
                                1.0 / VAP_DT, self._vap_nx - 2, self._vap_nu - 1, self._vap_u0,
                                1.0 / self._vap_du, self._vap_nu - 2, VAP_T_MIN, VAP_T_MAX, THETA_MAX)
            return v[0], v[1], np.exp(v[2])
        base, tx = self._vap_row(np.where(ok, T_sat, VAP_T_MIN))
        _, t, a = self._vap_cubics(base, tx, u_of_theta(np.where(ok, theta, 0.0)))
        v = np.where(ok[:, None], self._cubic(a, t), np.nan)
        return v[:, 0], v[:, 1], np.exp(v[:, 2])

    def vapour_from(self, key: str, T_sat, target, u0=None, _build: bool = False):
        """The vapour state at p_sat(T_sat) [K] with h [J/kg] (``key`` "h") or s [J/kg/K] (``key``
        "s") equal to target: (theta [K], h, rho, u), u the table coordinate (``u_of_theta``), which
        ``u0`` may give as a warm start. NaN where the state is not superheated vapour within the
        table.

        Per cell the spline is a cubic in u: where the target lies within the current cell, Newton
        on that cubic (no gather per step); elsewhere a Newton step on the cell's cubic toward it,
        safeguarded by a bracket in u that each cell visited narrows (bisection where the step
        leaves it). A warm start needs one cell."""
        q = 0 if key == "h" else 1
        T_sat = np.asarray(T_sat, dtype=float)
        target = np.asarray(target, dtype=float)
        n = len(T_sat)
        pad = (4.0 * VAP_DT) if _build else 0.0      # the table's builder reaches into its pad nodes
        ok = (T_sat >= VAP_T_MIN - pad) & (T_sat <= VAP_T_MAX + pad) & np.isfinite(target)
        base, tx = self._vap_row(np.where(ok, T_sat, VAP_T_MIN))
        if u0 is None:          # linear in theta between saturation and THETA_MAX
            _, t0, a = self._vap_cubics(base, tx, np.zeros(n))
            f_lo = self._cubic(a, t0)[:, q] - target
            _, t1, a = self._vap_cubics(base, tx, np.full(n, U_MAX))
            f_hi = self._cubic(a, t1)[:, q] - target
            with np.errstate(divide="ignore", invalid="ignore"):
                frac = np.minimum(np.maximum(f_lo / (f_lo - f_hi), 0.0), 1.0)
            u = u_of_theta(np.where(np.isfinite(frac), frac, 0.5) * THETA_MAX)
        else:
            u = np.where(np.isfinite(u0), u0, 0.5 * U_MAX)
        u_lo, u_hi = (self._vap_u0, 1.0) if _build else (0.0, U_MAX)
        u = np.minimum(np.maximum(u, u_lo), u_hi)
        du, u_0 = self._vap_du, self._vap_u0
        lo, hi = np.full(n, u_lo), np.full(n, u_hi)
        done = ~ok
        found = np.zeros(n, dtype=bool)
        res, t_fin = np.zeros((n, 4, 3)), np.zeros(n)
        with np.errstate(divide="ignore", invalid="ignore"):
            for _ in range(NEWTON_ITER):
                j, t, a = self._vap_cubics(base, tx, u)
                a0, a1, a2, a3 = a[:, 0, q], a[:, 1, q], a[:, 2, q], a[:, 3, q] - target
                f0, f1 = a3, a0 + a1 + a2 + a3
                inside = (f0 <= 0.0) & (f1 >= 0.0) & ~done
                t = np.minimum(np.maximum(t, 0.0), 1.0)
                if inside.any():
                    for _ in range(8):
                        step = np.where(inside, (((a0 * t + a1) * t + a2) * t + a3)
                                        / ((3.0 * a0 * t + 2.0 * a1) * t + a2), 0.0)
                        t = np.minimum(np.maximum(t - step, 0.0), 1.0)
                        if not np.any(np.abs(step) > 1e-12):
                            break
                    conv = inside & (np.abs(step) <= 1e-12)
                    u = np.where(conv, (j + t) * du + u_0, u)
                    res[conv], t_fin[conv] = a[conv], t[conv]
                    found |= conv
                    done |= conv
                if done.all():
                    break
                # the root lies in another cell: narrow the bracket, step toward it
                cell_lo = j * du + u_0
                left = ~inside & (f0 > 0.0)
                hi = np.where(left, np.minimum(hi, cell_lo), hi)
                lo = np.where(~inside & ~left, np.maximum(lo, cell_lo + du), lo)
                te = np.where(left, 0.0, 1.0)
                fe, dfe = np.where(left, f0, f1), np.where(left, a2, 3.0 * a0 + 2.0 * a1 + a2)
                un = cell_lo + (te - fe / dfe) * du
                un = np.where((un > lo) & (un < hi), un, 0.5 * (lo + hi))
                done |= ~(lo < hi)                       # the bracket closed: no root
                u = np.where(done, u, un)
        ok &= found & (u > u_lo + 1e-9) & (u < u_hi)
        v = self._cubic(res, t_fin)
        nan = np.nan
        h = v[:, 0] if q == 1 else target
        return (np.where(ok, theta_of_u(u), nan), np.where(ok, h, nan), np.where(ok, np.exp(v[:, 2]), nan),
                np.where(ok, u, nan))

    # ---- lean evaluations for the flowsheet's inner loops (no range checks: the caller checks
    # ``T_RANGE``, ``ds``/``dh`` against DS_MAX/DH_MAX and ``d`` against LIQ_D_MAX once) ----------------
    def sat_raw(self, T):
        """(p, h_f, h_g, s_g, rho_g) at T [K] within the table (no checks)."""
        if _kernels._KERNEL is not None and np.ndim(T) == 1:
            v = _kernels.sat(self._sat_c, T, self._sat_x0, 1.0 / SAT_DT)
            return np.exp(v[0]), v[1], v[2], v[3], np.exp(v[4])
        t = (T - self._sat_x0) * (1.0 / SAT_DT)
        i = t.astype(np.intp)
        c = self._sat_c[i]
        t = (t - i)[:, None]
        v = ((c[:, 0] * t + c[:, 1]) * t + c[:, 2]) * t + c[:, 3]
        return np.exp(v[:, 0]), v[:, 1], v[:, 2], v[:, 3], np.exp(v[:, 4])

    def isen_raw(self, T_sat, ds):
        """h [J/kg] of the vapour at p_sat(T_sat) with s = s_g(T_sat) + ds (no checks)."""
        return self._derived(self._isen, T_sat, ds, DS_GRID, DS_ALPHA)

    def tofh_raw(self, T_sat, dh):
        """Superheat [K] of the vapour at p_sat(T_sat) with h = h_g(T_sat) + dh (no checks)."""
        return self._derived(self._tofh, T_sat, dh, DH_GRID, DH_ALPHA)

    def liq_row(self, T_c):
        """The liquid table's row data at T_c, for ``liq_raw`` in a loop over the subcooling."""
        x = (T_c - self._liq_x0) * (1.0 / LIQ_DT)
        i = np.where(np.isfinite(x), np.nan_to_num(x), 0.0).astype(np.intp)   # NaN rows stay NaN
        return i * (self._liq_nd - 1), (x - i)[:, None]

    def liq_kernel_args(self, row) -> tuple:
        """The liquid table as ``speedkernel.subcooler`` takes it: (coefficients, base, tx, d0,
        1/dd, dh/dT scale) at ``liq_row``'s row."""
        return self._liq, row[0], row[1], self._liq_d0, 1.0 / LIQ_DD, -1.0 / LIQ_DD

    def liq_raw(self, row, d):
        """(h, dh/dT at constant pressure) of the liquid at subcooling d [K] (``liq_row``'s T_c).
        Compiled in a replay (``model.analysis.speedkernel``: the same numbers to the bit)."""
        base, tx = row
        if _kernels._KERNEL is not None and np.ndim(d) == 1 and np.shape(base) == np.shape(d):
            return _kernels.liq(self._liq, base, tx, d, self._liq_d0, 1.0 / LIQ_DD, -1.0 / LIQ_DD)
        y = (d - self._liq_d0) * (1.0 / LIQ_DD)
        # a row whose subcooling is not a number (a failed trial upstream) reads node 0 and comes
        # back NaN: an integer cast of NaN is an arbitrary index
        bad = ~np.isfinite(y)
        if bad.any():
            y = np.where(bad, np.nan, y)
            j = np.where(bad, 0, np.nan_to_num(y)).astype(np.intp)
        else:
            j = y.astype(np.intp)
        g = self._liq[base + j]
        a = ((g[:, 0:4] * tx + g[:, 4:8]) * tx + g[:, 8:12]) * tx + g[:, 12:16]
        t = y - j
        h = ((a[:, 0] * t + a[:, 1]) * t + a[:, 2]) * t + a[:, 3]
        return h, ((3.0 * a[:, 0] * t + 2.0 * a[:, 1]) * t + a[:, 2]) * (-1.0 / LIQ_DD)

    # ---- direct lookups derived from the vapour table ---------------------------------------------
    def _derived(self, C, T_sat, dv, grid, alpha):
        if _kernels._KERNEL is not None and np.ndim(T_sat) == 1 and np.shape(dv) == np.shape(T_sat):
            return _kernels.derived(C, T_sat, np.log1p(dv * (math.expm1(alpha) / grid)), self._vap_x0,
                                    1.0 / VAP_DT, self._vap_nx - 2, self._der_w0, 1.0 / alpha,
                                    1.0 / self._der_dw, self._der_nw - 2)
        x = (T_sat - self._vap_x0) * (1.0 / VAP_DT)
        i = np.minimum(np.maximum(x.astype(np.intp), 0), self._vap_nx - 2)
        y = (np.log1p(dv * (math.expm1(alpha) / grid)) * (1.0 / alpha) - self._der_w0) * (1.0 / self._der_dw)
        j = np.minimum(np.maximum(y.astype(np.intp), 0), self._der_nw - 2)
        return self._bicubic(C, i * (self._der_nw - 1) + j, x - i, y - j)

    def h_isentropic(self, T_sat, s):
        """h [J/kg] of vapour at p_sat(T_sat) [K] with entropy s [J/kg/K] (the isentropic discharge
        state); NaN where s lies below saturation or outside the table."""
        T_sat = np.asarray(T_sat, dtype=float)
        ds = np.asarray(s, dtype=float) - self._sat_eval(T_sat, 3)
        ok = (T_sat >= VAP_T_MIN) & (T_sat <= VAP_T_MAX) & (ds >= 0.0) & (ds <= DS_MAX)
        return np.where(ok, self._derived(self._isen, T_sat, np.where(ok, ds, 0.0), DS_GRID, DS_ALPHA), np.nan)

    def theta_from_h(self, T_sat, h, h_g=None):
        """Superheat theta [K] of vapour at p_sat(T_sat) [K] with enthalpy h [J/kg] (``h_g``: the
        saturated vapour's, when known); NaN where h lies below saturation or outside the table."""
        T_sat = np.asarray(T_sat, dtype=float)
        dh = np.asarray(h, dtype=float) - (self._sat_eval(T_sat, 2) if h_g is None else h_g)
        ok = (T_sat >= VAP_T_MIN) & (T_sat <= VAP_T_MAX) & (dh >= 0.0) & (dh <= DH_MAX)
        return np.where(ok, self._derived(self._tofh, T_sat, np.where(ok, dh, 0.0), DH_GRID, DH_ALPHA), np.nan)

    # ---- subcooled liquid ---------------------------------------------------------------------
    def liq_ok(self, T_c, d) -> np.ndarray:
        return (T_c >= LIQ_T_MIN) & (T_c <= LIQ_T_MAX) & (d >= 0.0) & (d <= LIQ_D_MAX)

    def liquid(self, T_c, d, deriv: bool = False):
        """h [J/kg] of liquid at p_sat(T_c) and T_c - d [K] (d >= 0 the subcooling); with ``deriv``
        also dh/dT at constant pressure [J/kg/K] (= -dh/dd). NaN outside the table."""
        T_c, d = np.broadcast_arrays(np.asarray(T_c, dtype=float), np.asarray(d, dtype=float))
        ok = self.liq_ok(T_c, d)
        x = (np.where(ok, T_c, LIQ_T_MIN) - self._liq_x0) * (1.0 / LIQ_DT)
        i = np.minimum(np.maximum(x.astype(np.intp), 0), self._liq_nx - 2)
        y = (np.where(ok, d, 0.0) - self._liq_d0) * (1.0 / LIQ_DD)
        j = np.minimum(np.maximum(y.astype(np.intp), 0), self._liq_nd - 2)
        r = self._bicubic(self._liq, i * (self._liq_nd - 1) + j, x - i, y - j, deriv=deriv)
        if not deriv:
            return np.where(ok, r, np.nan)
        return np.where(ok, r[0], np.nan), np.where(ok, -r[1] * (1.0 / LIQ_DD), np.nan)


_LOCK = threading.Lock()
_TABLES: dict[str, CycleTables] = {}
CACHE_ENV = "HP_EDGE_CACHE_DIR"     # where built tables are kept ("off": nowhere)


def cache_file(name: str) -> Path | None:
    """The file the tables of fluid ``name`` are kept in between processes: in ``$HP_EDGE_CACHE_DIR``
    (``off``: none), else ``$XDG_CACHE_HOME/hp-edge``, else ``~/.cache/hp-edge``. Its name carries
    a digest of the code that builds the tables (this module, ``model.fluid``) and of CoolProp's and
    SciPy's versions: a table built by other code or other property data is never read."""
    d = os.environ.get(CACHE_ENV, "")
    if d.strip().lower() == "off":
        return None
    if not d:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        d = os.path.join(base, "hp-edge")
    import CoolProp
    import scipy
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for part in ((here / "cycletables.py").read_bytes(), (here / "fluid.py").read_bytes(),
                 CoolProp.__version__.encode(), scipy.__version__.encode(), name.encode()):
        h.update(part)
    return Path(d) / f"cycletables-{name}-{h.hexdigest()[:16]}.npz"


def _load(path: Path) -> CycleTables:
    """Tables saved by ``_save`` (no pickle: arrays and typed scalars only)."""
    with np.load(path, allow_pickle=False) as z:
        t = CycleTables.__new__(CycleTables)
        kinds = dict(zip(z["__names__"].tolist(), z["__kinds__"].tolist()))
        for k, kind in kinds.items():
            a = z[k]
            setattr(t, k, a if kind == "array" else str(a) if kind == "str" else int(a) if kind == "int"
                    else float(a) if kind == "float" else np.float64(a))
    return t


def _save(t: CycleTables, path: Path) -> None:
    """``t`` into ``path`` atomically (a temporary file beside it, then renamed)."""
    arrays, kinds = {}, {}
    for k, v in vars(t).items():
        kinds[k] = ("array" if isinstance(v, np.ndarray) else "str" if isinstance(v, str)
                    else "int" if type(v) is int else "float" if type(v) is float else "float64")
        arrays[k] = np.asarray(v)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, __names__=np.array(list(kinds)), __kinds__=np.array(list(kinds.values())), **arrays)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


STALE_TMP_S = 600.0     # a temporary file this old is a write that was killed, not one under way


def _remove_stale(path: Path, name: str) -> None:
    """Beside the file just written: the fluid's files of earlier code (never read again) and the
    temporary files of writes killed half-way (each up to ~33 MB; older than STALE_TMP_S, so that
    another process's write under way is left alone)."""
    now = time.time()
    for old in path.parent.glob(f"cycletables-{name}-*"):
        if old == path:
            continue
        with contextlib.suppress(OSError):
            if old.suffix == ".npz" or now - old.stat().st_mtime > STALE_TMP_S:
                old.unlink()


def _load_or_build(name: str) -> CycleTables:
    """The tables from the cache file when it holds them, else built (~1 s) and kept there when the
    storage lets us: a cache that cannot be read or written (read-only, locked, full, corrupt) costs
    the build, nothing else."""
    try:
        path = cache_file(name)
    except OSError:
        path = None
    if path is not None and path.is_file():
        try:
            return _load(path)
        except Exception:       # noqa: BLE001 - unreadable or damaged: built again below
            pass
    t = CycleTables(name)
    if path is not None:
        with contextlib.suppress(Exception):
            _save(t, path)
            _remove_stale(path, name)
    return t


def get_cycle_tables(name: str = "Ammonia") -> CycleTables:
    """The fluid's tables, built on first use in this process or read from the cache file an
    earlier process left (``cache_file``; the same arrays to the bit); thread-safe, read-only."""
    t = _TABLES.get(name)
    if t is None:
        with _LOCK:
            t = _TABLES.get(name)
            if t is None:
                t = _TABLES[name] = _load_or_build(name)
                release_heap()      # the build's freed heap: ~45 MB of the gateway's RSS
    return t
