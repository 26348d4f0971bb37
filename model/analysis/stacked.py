"""One stage's compressors of several windows as one vectorised compressor (``model.lockstep``).

A replay analyses its windows in lockstep: the solver calls of K windows are answered by one call
of ``model.vcycle.solve_many`` whose rows carry their window's own compressor. ``Stacked`` holds the
stage's compressors (``Compressor`` or ``LearnedCompressor``: their global curves, drive factors and
local grids, padded to one array) and ``Stacked.view(group, ...)`` gives the vectorised protocol
(``eta_is_v``, ``eta_vol_v``, ``speed_for_flow_v``) for rows that each name their compressor.

Every row is computed with the same operations as its own compressor's vectorised methods, the
compressor's constants gathered per row instead of broadcast: a row's numbers are its own
compressor's, to the bit (``tests/test_lockstep.py``). The compressors must share their speed
range and swept volume (one plant).
"""
from __future__ import annotations

import numpy as np

from ..params import Compressor, cubic_speed
from . import speedkernel
from .compressors import _Z, LearnedCompressor, local_speed

_SHARED = ("N_nom", "N_min", "N_max", "swept_volume")


def stackable(comps: list) -> bool:
    """Whether ``comps`` can be stacked: each a ``Compressor`` or ``LearnedCompressor`` (exactly:
    a subclass may answer otherwise), with the same speed range and swept volume."""
    if not comps or any(type(c) not in (Compressor, LearnedCompressor) for c in comps):
        return False
    first = comps[0]
    return all(getattr(c, k) == getattr(first, k) for c in comps[1:] for k in _SHARED)


class _Tables:
    """The local grids (``LocalCurves``) of one curve of several compressors in one padded array;
    a compressor without a usable grid has none (every row of it lies outside)."""

    def __init__(self, locals_: list) -> None:
        G = len(locals_)
        self.ok = np.array([loc is not None and bool(loc.ok) for loc in locals_])
        shapes = []
        for loc, ok in zip(locals_, self.ok):
            if ok:
                if "_ca" not in loc.__dict__:
                    loc._cell_v(loc.p0, loc.n0)
                shapes.append(loc._ca.shape)
        NI = max([s[0] for s in shapes] + [2])
        NJ = max([s[1] for s in shapes] + [2])
        self.ca = np.zeros((G, NI, NJ, 6))
        self.p0, self.n0 = np.zeros(G), np.zeros(G)
        self.dpi, self.dn = np.ones(G), np.ones(G)
        self.ni, self.nj = np.zeros(G, dtype=np.intp), np.zeros(G, dtype=np.intp)
        for g, (loc, ok) in enumerate(zip(locals_, self.ok)):
            if ok:
                a = loc._ca
                self.ca[g, :a.shape[0], :a.shape[1]] = a
                self.p0[g], self.n0[g], self.dpi[g], self.dn[g] = loc.p0, loc.n0, loc.dpi, loc.dn
                self.ni[g], self.nj[g] = loc._ni, loc._nj
        self.NI, self.NJ = NI, NJ
        self.any = bool(self.ok.any())
        # rows_at's layout: per (member, pi node) the six coefficients of every n node, contiguous
        self.rows6 = np.ascontiguousarray(self.ca.transpose(0, 1, 3, 2)).reshape(G * NI, 6, NJ)

    def kernel_tables(self) -> tuple:
        """``model.analysis.speedkernel``'s tables of every member."""
        return self.ca, self.p0, self.dpi, self.ni, self.nj, self.ok, self.n0, self.dn

    def value_v(self, g, pi, n) -> tuple[np.ndarray, np.ndarray]:
        """``LocalCurves.value_v`` of each row's own grid (g: the rows' compressors)."""
        fin = np.isfinite(pi) & np.isfinite(n)
        p0, n0 = self.p0[g], self.n0[g]
        x = (np.where(fin, pi, p0) - p0) / self.dpi[g]
        y = (np.where(fin, n, n0) - n0) / self.dn[g]
        i, j = np.floor(x), np.floor(y)
        fx, fy = x - i, y - j
        inside = fin & (i >= 0) & (i < self.ni[g]) & (j >= 0) & (j < self.nj[g]) & self.ok[g]
        ii = np.where(inside, i, 0).astype(np.intp)
        jj = np.where(inside, j, 0).astype(np.intp)
        zp, zn = (pi - _Z[0]) / _Z[1], (n - _Z[2]) / _Z[3]
        NJ = self.NJ
        corner = np.array([0, NJ, 1, NJ + 1])
        k = self.ca.reshape(-1, 6)[((g * self.NI + ii) * NJ + jj)[:, None] + corner]
        zp1, zn1 = zp[:, None], zn[:, None]
        v = (k[:, :, 0] + k[:, :, 1] * zp1 + k[:, :, 2] * zn1 + k[:, :, 3] * (zp * zp)[:, None]
             + k[:, :, 4] * (zp * zn)[:, None] + k[:, :, 5] * (zn * zn)[:, None])
        val = ((1 - fy) * ((1 - fx) * v[:, 0] + fx * v[:, 1])) + (fy * ((1 - fx) * v[:, 2] + fx * v[:, 3]))
        return np.where(inside, val, np.nan), inside


class _RowGrids:
    """``LocalCurves``' speed-search interface (``rows_at``, ``value_dn_rows``) for rows that each
    name their grid: what ``local_speed`` needs."""

    def __init__(self, t: _Tables, g: np.ndarray) -> None:
        self.t, self.g = t, g
        self.n0, self.dn, self.nj = t.n0[g], t.dn[g], t.nj[g]

    def rows_at(self, pi):
        t, g = self.t, self.g
        fin = np.isfinite(pi)
        p0 = t.p0[g]
        x = (np.where(fin, pi, p0) - p0) / t.dpi[g]
        i = np.floor(x)
        inside = fin & (i >= 0) & (i < t.ni[g]) & (self.nj > 0) & t.ok[g]
        ii = np.where(inside, i, 0).astype(np.intp)
        fx = x - i
        zp = (pi - _Z[0]) / _Z[1]
        zp1, zp2 = zp[:, None], (zp * zp)[:, None]
        f = fx[:, None]
        base = g * t.NI + ii
        k0, k1 = t.rows6[base], t.rows6[base + 1]               # (rows, 6, n nodes)
        out = np.empty((len(ii), t.NJ, 3))
        out[:, :, 0] = (1.0 - f) * (k0[:, 0] + k0[:, 1] * zp1 + k0[:, 3] * zp2) \
            + f * (k1[:, 0] + k1[:, 1] * zp1 + k1[:, 3] * zp2)
        out[:, :, 1] = (1.0 - f) * (k0[:, 2] + k0[:, 4] * zp1) + f * (k1[:, 2] + k1[:, 4] * zp1)
        out[:, :, 2] = (1.0 - f) * k0[:, 5] + f * k1[:, 5]
        return out, inside

    def kernel_tables(self, rows: int) -> tuple:
        """``model.analysis.speedkernel``'s tables (every member) and the rows' members."""
        return self.t.kernel_tables(), self.g

    def value_dn_rows(self, Q, inside_pi, rows, n, left=None):
        n0, dn = self.n0[rows], self.dn[rows]
        fin = np.isfinite(n)
        y = (np.where(fin, n, n0) - n0) / dn
        j = np.floor(y)
        fy = y - j
        if left is not None:
            shift = left & (fy == 0.0) & (j > 0)
            j, fy = np.where(shift, j - 1, j), np.where(shift, 1.0, fy)
        inside = inside_pi[rows] & fin & (j >= 0) & (j < self.nj[rows])
        jj = np.where(inside, j, 0).astype(np.intp)
        zn = (n - _Z[2]) / _Z[3]
        a, b = Q[rows, jj], Q[rows, jj + 1]
        va = a[:, 0] + (a[:, 1] + a[:, 2] * zn) * zn
        vb = b[:, 0] + (b[:, 1] + b[:, 2] * zn) * zn
        da = a[:, 1] + 2.0 * a[:, 2] * zn
        db = b[:, 1] + 2.0 * b[:, 2] * zn
        val = (1 - fy) * va + fy * vb
        d = (vb - va) / dn + ((1 - fy) * da + fy * db) / _Z[3]
        return np.where(inside, val, np.nan), np.where(inside, d, np.nan), inside


class Stacked:
    """A stage's compressors ``comps`` (``stackable``) as one: ``view(g, ...)`` answers rows whose
    compressor is ``comps[g]``."""

    def __init__(self, comps: list) -> None:
        if not stackable(comps):
            raise ValueError("compressors of different classes, speed ranges or swept volumes cannot be stacked")
        self.comps = list(comps)
        first = comps[0]
        for k in _SHARED:
            setattr(self, k, getattr(first, k))
        self.eta_is = np.array([c.eta_is for c in comps], dtype=float)      # (G, 6) global curves
        self.eta_vol = np.array([c.eta_vol for c in comps], dtype=float)
        self.drive = np.array([c.drive_factor for c in comps], dtype=float)
        learned = [isinstance(c, LearnedCompressor) for c in comps]
        self.t_is = _Tables([c.local_is if lc else None for c, lc in zip(comps, learned)])
        self.t_vol = _Tables([c.local_vol if lc else None for c, lc in zip(comps, learned)])
        # which rows search their speed on the local grid (LearnedCompressor with a usable grid);
        # the others on the global cubic (Compressor.speed_for_flow_v)
        self.local_speed = self.t_vol.ok.copy()

    def view(self, g, delta_is=None, delta_vol=None) -> "_View":
        """The vectorised protocol for rows of compressors ``g`` (with per-row curve differences:
        six arrays each, or None)."""
        return _View(self, np.asarray(g, dtype=np.intp), delta_is, delta_vol)


class _View:
    def __init__(self, st: Stacked, g, delta_is, delta_vol) -> None:
        self.st, self.g = st, g
        self.delta_is, self.delta_vol = delta_is, delta_vol
        for k in _SHARED:
            setattr(self, k, getattr(st, k))

    def _curve(self, C, tables: _Tables, delta, pi, n):
        pi, n = np.broadcast_arrays(np.asarray(pi, dtype=float), np.asarray(n, dtype=float))
        if speedkernel._KERNEL is not None and pi.ndim == 1 and self.g.shape == pi.shape:
            # compiled (replay): the same operations row by row, the same numbers to the bit
            return speedkernel.curve(C, self.g, pi, n, tables.kernel_tables() if tables.any else None, delta)
        c = C[self.g]
        v = c[:, 0] + c[:, 1] * pi + c[:, 2] * n + c[:, 3] * pi * pi + c[:, 4] * pi * n + c[:, 5] * n * n
        if tables.any:
            loc, inside = tables.value_v(self.g, pi, n)
            v = np.where(inside, loc, v)
        if delta is not None:
            a = delta
            zp = (pi - _Z[0]) / _Z[1]
            zn = (n - _Z[2]) / _Z[3]
            v = v + (a[0] + a[1] * zp + a[2] * zn + a[3] * zp * zp + a[4] * zp * zn + a[5] * zn * zn)
        return v

    def eta_is_v(self, pi, n) -> np.ndarray:
        return self._curve(self.st.eta_is, self.st.t_is, self.delta_is, pi, n)

    def eta_vol_v(self, pi, n) -> np.ndarray:
        return self._curve(self.st.eta_vol, self.st.t_vol, self.delta_vol, pi, n)

    def speed_for_flow_v(self, m, rho_suc, pi, n0=None):
        st, g = self.st, self.g
        m, rho_suc, pi = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (m, rho_suc, pi)))
        n_lo, n_hi = st.N_min / st.N_nom, st.N_max / st.N_nom
        loc = st.local_speed[g]
        if speedkernel._KERNEL is not None and g.shape == m.shape and loc.all():
            # every row on its learned grid: the compiled search at once (the loop below's numbers)
            return speedkernel.run(st.t_vol.kernel_tables(), g, st.eta_vol[g].T, self.delta_vol,
                                   m / (rho_suc * st.swept_volume), pi, n0, n_lo, n_hi)
        n = np.full(len(m), np.nan)
        ev = np.full(len(m), np.nan)
        n0a = None if n0 is None else np.broadcast_to(np.asarray(n0, dtype=float), m.shape)
        for on_grid in (True, False):
            r = np.flatnonzero(loc == on_grid)
            if not len(r):
                continue
            gr = g[r]
            c = tuple(st.eta_vol[gr].T)
            sub = lambda a: None if a is None else tuple(x[r] for x in a)  # noqa: E731
            if on_grid:
                nr, er = local_speed(_RowGrids(st.t_vol, gr), c, sub(self.delta_vol),
                                     m[r] / (rho_suc[r] * st.swept_volume), pi[r],
                                     None if n0a is None else n0a[r], n_lo, n_hi)
            else:
                nr, er = cubic_speed(c, st.swept_volume, n_lo, n_hi, m[r], rho_suc[r], pi[r],
                                     None if n0a is None else n0a[r])
            n[r], ev[r] = nr, er
        return n, ev
