"""Compiled kernels for a replay's hottest arithmetic (numba, optional).

- the learned curves' speed search (``compressors.local_speed``): for every row of every flowsheet
  evaluation, the LS and HS speed at which the learned volumetric curve passes the stage's mass
  flow. The numpy version works on all rows at once but pays numpy's per-call cost in every Newton
  step and a (rows x speed nodes) table per search; this kernel walks each row on its own (about 4
  curve evaluations a row);
- the stacked compressors' curves (``stacked._View._curve``: eta_is and eta_vol of rows that each
  name their window's compressor, on its local grid where that covers);
- the liquid table (``CycleTables.liq_raw``, the subcooler's inner loop);
- the saturation table (``CycleTables.sat_raw``; ``CycleTables.sat`` with its range check) and the
  isentropic / superheat-from-enthalpy lookups (``CycleTables._derived``) around their ``exp`` and
  ``log1p``, which stay numpy's;
- the vapour table (``CycleTables.vapour``: the evaporator's suction state at every source-side
  change) before its ``exp``: one cell's cubics per row instead of numpy's (rows, 4, 4, 3) gather;
- the compressor learner's distance to its covered bins (``CompressorLearner.coverage_distance``:
  the nearest rectangle per point, without the (points, bins) arrays);
- the subcooler's Newton step (``Flowsheet._subcooler``) in two halves around numpy's ``exp`` of
  the effectiveness (``subcooler``: the same iteration, the same exits);
- the fouling forecast's least squares for many k (``forecast._ls_many`` after numpy's ``expm1``:
  ``ls_rows``), whose sums over the estimates are numpy's pairwise sums (``_pw``, the order of
  numpy's ``add.reduce`` of a contiguous row);
- the CIP plan's cycle integrals (``cost._stacked_cost``: ``cycle_cost``) around numpy's ``log`` of
  the crossing times and ``exp`` of the levels at the Gauss nodes: the crossing times, the window
  of whole pieces, the nodes, the cost curve (``np.interp`` and its extrapolation) and the sums.

Each computes every row with the same floating-point operations in the same order as the numpy
version (``rows_at``, ``value_dn_rows`` and the ``phi`` of ``local_speed``; ``_Tables.value_v``;
the bicubic of ``liq_raw``; the spline and Newton arithmetic of the others), so its numbers are
the numpy version's to the bit
(``tests/test_speedkernel.py``): a replay gives the same results with them or without them. Only
pure arithmetic is compiled: numpy's ``exp``/``log`` (SIMD) differ from libm's in the last bit for
some arguments, so the flowsheet's other steps stay in numpy. numba is an optional extra
(``pip install 'hp-edge[fast]'``, also in ``[fleet]``); only ``model.analysis.replay`` turns the
kernels on (``enable``), so the gateway daemon never imports numba. Without numba everything runs on
numpy. ``_KERNEL`` is the switch for all of them.
"""
from __future__ import annotations

import math
import warnings

import numpy as np

_KERNEL = None          # the compiled search once ``enable`` succeeded: every kernel's switch
_CURVE = None           # the compiled stacked curve (set with _KERNEL)
_LIQ = None             # the compiled liquid table (set with _KERNEL)
_SAT = _DER = None      # the compiled saturation table and isentropic / T-from-h lookups
_SC_PRE = _SC_POST = None   # the subcooler's Newton step, before and after its exp
_SATF = _VAP = None     # the saturation table with its range check and the vapour table
_RECT = None            # the learner's distance to its covered bins
_LS = None              # the forecast's least squares for many k
_CCN = _CCS = None      # the cycle integrals' nodes and sums
_TRIED = False


def _search(ca, p0, dpi, ni, nj, ok, n0g, dng, g, C, DL, has_dl, target, pi, nstart, has_n0,
            n_lo, n_hi, z0, z1, z2, z3, tol, n_out, ev_out):
    """Row by row ``local_speed``: ca (members, pi nodes, n nodes, 6) the local grids' polynomials,
    p0 .. dng per member, g the rows' members, C (rows, 6) the global curves, DL (rows, 6) the curve
    differences (used when has_dl), nstart the start speeds (when has_n0)."""
    for r in range(target.shape[0]):
        m = g[r]
        t = target[r]
        p = pi[r]
        # rows_at: the pi cell of the row's grid
        fin = math.isfinite(p)
        x = ((p if fin else p0[m]) - p0[m]) / dpi[m]
        i = np.floor(x)
        in_pi = fin and i >= 0 and i < ni[m] and nj[m] > 0 and ok[m]
        ii = int(i) if in_pi else 0
        fx = x - i
        zp = (p - z0) / z1
        zp2 = zp * zp
        c0, c1, c2, c3, c4, c5 = C[r, 0], C[r, 1], C[r, 2], C[r, 3], C[r, 4], C[r, 5]
        a0, a1, a2, a3, a4, a5 = DL[r, 0], DL[r, 1], DL[r, 2], DL[r, 3], DL[r, 4], DL[r, 5]
        # phi at the three first speeds: n_lo, n_hi, the start
        ns = nstart[r] if has_n0 else 1.0
        if ns != ns:
            ns = 1.0
        else:
            if ns < n_lo:
                ns = n_lo
            if ns > n_hi:
                ns = n_hi
        # (three calls, not a loop over a 3-array: two array allocations a row cost the kernel 17 %)
        njm, n0m, dnm = nj[m], n0g[m], dng[m]
        f_lo, d_lo = _phi(ca, m, ii, fx, zp, zp2, in_pi, njm, n0m, dnm, p, n_lo, n_lo >= n_hi,
                          c0, c1, c2, c3, c4, c5, has_dl, a0, a1, a2, a3, a4, a5, z2, z3)
        f_hi, d_hi = _phi(ca, m, ii, fx, zp, zp2, in_pi, njm, n0m, dnm, p, n_hi, n_hi >= n_hi,
                          c0, c1, c2, c3, c4, c5, has_dl, a0, a1, a2, a3, a4, a5, z2, z3)
        f_0, d_0 = _phi(ca, m, ii, fx, zp, zp2, in_pi, njm, n0m, dnm, p, ns, ns >= n_hi,
                        c0, c1, c2, c3, c4, c5, has_dl, a0, a1, a2, a3, a4, a5, z2, z3)
        bad = (not (d_lo > 0.0 and d_hi > 0.0)) or not math.isfinite(t)
        above = t > f_hi
        below = t < f_lo
        if above:
            nx = n_hi + (t - f_hi) / d_hi
        else:
            nx = n_lo + (t - f_lo) / d_lo
        if below and not above and not (nx > 0.0):
            bad = True
        n = ns
        if not (above or below or bad):
            a, b = n_lo, n_hi
            for it in range(60):
                na = n
                if it == 0:
                    f, df = f_0, d_0
                else:
                    f, df = _phi(ca, m, ii, fx, zp, zp2, in_pi, njm, n0m, dnm, p, na, na >= n_hi,
                                 c0, c1, c2, c3, c4, c5, has_dl, a0, a1, a2, a3, a4, a5, z2, z3)
                if f > t:
                    b = na
                else:
                    a = na
                step = (f - t) / df if df > 0 else 0.0
                nn = na - step
                if not (a <= nn and nn <= b):
                    nn = 0.5 * (a + b)
                n = nn
                if abs(nn - na) < tol:
                    break
        if above or below:
            n = nx
        if bad:
            n_out[r] = np.nan
            ev_out[r] = np.nan
        else:
            n_out[r] = n
            ev_out[r] = t / n


def _phi(ca, m, ii, fx, zp, zp2, in_pi, njm, n0, dn, p, nn, left, c0, c1, c2, c3, c4, c5,
         has_dl, a0, a1, a2, a3, a4, a5, z2, z3):
    """(eta_vol * n, d/dn) of one row at speed ratio nn: ``value_dn_rows`` on the row's pi cell, the
    global curve outside the grid, plus the curve differences (``local_speed``'s ``phi``)."""
    fin = math.isfinite(nn)
    y = ((nn if fin else n0) - n0) / dn
    j = np.floor(y)
    fy = y - j
    if left and fy == 0.0 and j > 0:
        j = j - 1
        fy = 1.0
    inside = in_pi and fin and j >= 0 and j < njm
    zn = (nn - z2) / z3
    if inside:
        jj = int(j)
        # rows_at's node columns jj and jj + 1 (its blend across the pi cell)
        ka, kb = ca[m, ii, jj], ca[m, ii + 1, jj]
        qa0 = (1.0 - fx) * (ka[0] + ka[1] * zp + ka[3] * zp2) + fx * (kb[0] + kb[1] * zp + kb[3] * zp2)
        qa1 = (1.0 - fx) * (ka[2] + ka[4] * zp) + fx * (kb[2] + kb[4] * zp)
        qa2 = (1.0 - fx) * ka[5] + fx * kb[5]
        ka, kb = ca[m, ii, jj + 1], ca[m, ii + 1, jj + 1]
        qb0 = (1.0 - fx) * (ka[0] + ka[1] * zp + ka[3] * zp2) + fx * (kb[0] + kb[1] * zp + kb[3] * zp2)
        qb1 = (1.0 - fx) * (ka[2] + ka[4] * zp) + fx * (kb[2] + kb[4] * zp)
        qb2 = (1.0 - fx) * ka[5] + fx * kb[5]
        va = qa0 + (qa1 + qa2 * zn) * zn
        vb = qb0 + (qb1 + qb2 * zn) * zn
        da = qa1 + 2.0 * qa2 * zn
        db = qb1 + 2.0 * qb2 * zn
        v = (1 - fy) * va + fy * vb
        d = (vb - va) / dn + ((1 - fy) * da + fy * db) / z3
    else:
        v = c0 + c1 * p + c2 * nn + c3 * p * p + c4 * p * nn + c5 * nn * nn
        d = c2 + c4 * p + 2.0 * c5 * nn
    if has_dl:
        v = v + (a0 + a1 * zp + a2 * zn + a3 * zp * zp + a4 * zp * zn + a5 * zn * zn)
        d = d + (a2 + a4 * zp + 2.0 * a5 * zn) / z3
    return v * nn, v + nn * d


def _curve_rows(C, g, pi, n, has_tab, ca, p0, dpi, ni, nj, ok, n0g, dng, has_dl, DL,
                z0, z1, z2, z3, out):
    """Row by row ``stacked._View._curve``: the global curve of the row's member g (C (members, 6)),
    where the member's local grid covers (pi, n) its blend (``_Tables.value_v``), plus the row's
    curve difference DL (rows, 6) when has_dl."""
    for r in range(pi.shape[0]):
        m = g[r]
        p = pi[r]
        q = n[r]
        v = C[m, 0] + C[m, 1] * p + C[m, 2] * q + C[m, 3] * p * p + C[m, 4] * p * q + C[m, 5] * q * q
        if has_tab:
            fin = math.isfinite(p) and math.isfinite(q)
            x = ((p if fin else p0[m]) - p0[m]) / dpi[m]
            y = ((q if fin else n0g[m]) - n0g[m]) / dng[m]
            i = np.floor(x)
            j = np.floor(y)
            if fin and i >= 0 and i < ni[m] and j >= 0 and j < nj[m] and ok[m]:
                fx = x - i
                fy = y - j
                ii = int(i)
                jj = int(j)
                zp = (p - z0) / z1
                zn = (q - z2) / z3
                pp = zp * zp
                pn = zp * zn
                nn = zn * zn
                k = ca[m, ii, jj]
                v0 = k[0] + k[1] * zp + k[2] * zn + k[3] * pp + k[4] * pn + k[5] * nn
                k = ca[m, ii + 1, jj]
                v1 = k[0] + k[1] * zp + k[2] * zn + k[3] * pp + k[4] * pn + k[5] * nn
                k = ca[m, ii, jj + 1]
                v2 = k[0] + k[1] * zp + k[2] * zn + k[3] * pp + k[4] * pn + k[5] * nn
                k = ca[m, ii + 1, jj + 1]
                v3 = k[0] + k[1] * zp + k[2] * zn + k[3] * pp + k[4] * pn + k[5] * nn
                v = ((1 - fy) * ((1 - fx) * v0 + fx * v1)) + (fy * ((1 - fx) * v2 + fx * v3))
        if has_dl:
            zp = (p - z0) / z1
            zn = (q - z2) / z3
            v = v + (DL[r, 0] + DL[r, 1] * zp + DL[r, 2] * zn + DL[r, 3] * zp * zp + DL[r, 4] * zp * zn
                     + DL[r, 5] * zn * zn)
        out[r] = v


def _liq_rows(C, base, tx, d, d0, inv_dd, dscale, h_out, dh_out):
    """Row by row ``CycleTables.liq_raw``: the liquid table's bicubic C (cells, 16) at the rows' T_c
    cell offsets ``base`` and unit coordinates ``tx`` and subcooling d."""
    ncell = C.shape[0]
    for r in range(d.shape[0]):
        y = (d[r] - d0) * inv_dd
        if math.isfinite(y):
            j = int(y)
        else:
            y = np.nan
            j = 0
        k = base[r] + j
        if k < -ncell or k >= ncell:
            raise IndexError("liquid table index out of bounds")
        if k < 0:
            k += ncell
        x = tx[r]
        a0 = ((C[k, 0] * x + C[k, 4]) * x + C[k, 8]) * x + C[k, 12]
        a1 = ((C[k, 1] * x + C[k, 5]) * x + C[k, 9]) * x + C[k, 13]
        a2 = ((C[k, 2] * x + C[k, 6]) * x + C[k, 10]) * x + C[k, 14]
        a3 = ((C[k, 3] * x + C[k, 7]) * x + C[k, 11]) * x + C[k, 15]
        t = y - j
        h_out[r] = ((a0 * t + a1) * t + a2) * t + a3
        dh_out[r] = ((3.0 * a0 * t + 2.0 * a1) * t + a2) * dscale


def _idx(x, hi):
    """``np.minimum(np.maximum(x.astype(np.intp), 0), hi)``: numpy's cast of a NaN, an infinity or a
    number beyond the integers is the smallest integer on x86, so those rows read index 0."""
    if not (x > -9.2e18 and x < 9.2e18):
        return 0
    i = int(x)
    if i < 0:
        return 0
    return hi if i > hi else i


def _sat_rows(C, T, x0, inv_dt, out):
    """``CycleTables.sat_raw`` without its two ``exp``: the spline columns (ln p, h_f, h_g, s_g,
    ln rho_g) at T (rows within the table: the index is not clamped, as there)."""
    n = C.shape[0]
    for r in range(T.shape[0]):
        t = (T[r] - x0) * inv_dt
        if not (t > -9.2e18 and t < 9.2e18):
            i = -9223372036854775807 - 1
        else:
            i = int(t)
        k = i + n if i < 0 else i
        if k < 0 or k >= n:
            raise IndexError("saturation table index out of bounds")
        t = t - i
        for q in range(5):
            out[q, r] = ((C[k, 0, q] * t + C[k, 1, q]) * t + C[k, 2, q]) * t + C[k, 3, q]


def _sat_full_rows(C, T, x0, inv_dt, nm2, t_lo, t_hi, out):
    """``CycleTables.sat`` without its two ``exp``: the spline columns (ln p, h_f, h_g, s_g,
    ln rho_g) at T, NaN where T lies outside [t_lo, t_hi] (those rows are evaluated at t_lo there
    and then replaced: the same NaN), the cell index clamped as ``_sat_eval`` clamps it."""
    for r in range(T.shape[0]):
        Tr = T[r]
        if not (Tr >= t_lo and Tr <= t_hi):
            for q in range(5):
                out[q, r] = np.nan
            continue
        t = (Tr - x0) * inv_dt
        i = _idx(t, nm2)
        t = t - i
        for q in range(5):
            out[q, r] = ((C[i, 0, q] * t + C[i, 1, q]) * t + C[i, 2, q]) * t + C[i, 3, q]


def _vap_rows(V, T, theta, u, x0, inv_dx, nxm2, nu1, u0, inv_du, num2, t_lo, t_hi, th_max, out):
    """``CycleTables.vapour`` without its ``exp`` and ``u_of_theta`` (u, numpy's log1p, is given):
    (h, s, ln rho) at (T_sat, theta), NaN outside the table (``vap_ok``); per row the cell's cubics
    in the T_sat coordinate (``_vap_cubics``) and then in u (``_cubic``), in numpy's order."""
    for r in range(T.shape[0]):
        Tr = T[r]
        th = theta[r]
        if not (Tr >= t_lo and Tr <= t_hi and th >= 0.0 and th <= th_max):
            for q in range(3):
                out[q, r] = np.nan
            continue
        x = (Tr - x0) * inv_dx
        i = _idx(x, nxm2)
        tx = x - i
        y = (u[r] - u0) * inv_du
        j = _idx(y, num2)
        k = i * nu1 + j
        t = y - j
        for q in range(3):
            a0 = ((V[k, 0, 0, q] * tx + V[k, 1, 0, q]) * tx + V[k, 2, 0, q]) * tx + V[k, 3, 0, q]
            a1 = ((V[k, 0, 1, q] * tx + V[k, 1, 1, q]) * tx + V[k, 2, 1, q]) * tx + V[k, 3, 1, q]
            a2 = ((V[k, 0, 2, q] * tx + V[k, 1, 2, q]) * tx + V[k, 2, 2, q]) * tx + V[k, 3, 2, q]
            a3 = ((V[k, 0, 3, q] * tx + V[k, 1, 3, q]) * tx + V[k, 2, 3, q]) * tx + V[k, 3, 3, q]
            out[q, r] = ((a0 * t + a1) * t + a2) * t + a3


def _rect_min_rows(q0, q1, c, half0, half1, s0, s1, out):
    """``compressors._rect_distance(q, c, half, scale).min(axis=1)``: per point the distance to the
    nearest rectangle (NaN when any is NaN, as numpy's min), without the (points, rectangles)
    arrays."""
    m = c.shape[0]
    for r in range(q0.shape[0]):
        best = np.inf
        for j in range(m):
            a = _nmax(abs(q0[r] - c[j, 0]) - half0, 0.0) / s0
            b = _nmax(abs(q1[r] - c[j, 1]) - half1, 0.0) / s1
            v = math.sqrt(a * a + b * b)
            if v != v:
                best = v
                break
            if v < best:
                best = v
        out[r] = best


def _der_rows(C, T, lw, x0, inv_dx, nxm2, w0, inv_alpha, inv_dw, nwm2, out):
    """``CycleTables._derived`` after its ``log1p`` (lw = log1p(dv * expm1(alpha)/grid)): the
    bicubic at the rows' (T_sat, w)."""
    nw1 = nwm2 + 1
    for r in range(T.shape[0]):
        x = (T[r] - x0) * inv_dx
        i = _idx(x, nxm2)
        y = (lw[r] * inv_alpha - w0) * inv_dw
        j = _idx(y, nwm2)
        k = i * nw1 + j
        tx = x - i
        ty = y - j
        a0 = ((C[k, 0] * tx + C[k, 4]) * tx + C[k, 8]) * tx + C[k, 12]
        a1 = ((C[k, 1] * tx + C[k, 5]) * tx + C[k, 9]) * tx + C[k, 13]
        a2 = ((C[k, 2] * tx + C[k, 6]) * tx + C[k, 10]) * tx + C[k, 14]
        a3 = ((C[k, 3] * tx + C[k, 7]) * tx + C[k, 11]) * tx + C[k, 15]
        out[r] = ((a0 * ty + a1) * ty + a2) * ty + a3


def _nmin(a, b):
    """``np.minimum`` of two numbers (NaN wins)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


def _nmax(a, b):
    """``np.maximum`` of two numbers (NaN wins)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


def _sc_pre(LC, base, tx, d, d0, inv_dd, dscale, num, h_g_m, h_f_c, C_w, UA, h, h_T, g, m, dq, cp, C,
            C_min, Cr, NTU, arg):
    """One Newton step of ``Flowsheet._subcooler`` up to its ``exp``: the liquid at d, the flow and
    the capacities, and for the capacity C and its finite-difference step C*(1 + 1e-7) (rows k + r)
    ``counterflow_eps_v``'s C_min, Cr, NTU and the exponent NTU*(Cr - 1)."""
    k = d.shape[0]
    _liq_rows(LC, base, tx, d, d0, inv_dd, dscale, h, h_T)
    for r in range(k):
        g[r] = h_g_m[r] - h[r]
        m[r] = num[r] / g[r]
        dq[r] = h_f_c[r] - h[r]
        cp[r] = dq[r] / d[r]
        C[r] = m[r] * cp[r]
        for q in range(2):
            c = C[r] if q == 0 else C[r] * (1.0 + 1e-7)
            s = r + q * k
            cmin = _nmin(c, C_w[r])
            cr = cmin / _nmax(c, C_w[r])
            ntu = UA[r] / cmin
            C_min[s] = cmin
            Cr[s] = cr
            NTU[s] = ntu
            arg[s] = ntu * (cr - 1.0)


def _sc_post(x, C_min, Cr, NTU, dT, d, d_hi, h_T, g, m, dq, cp, C, step, finish):
    """The rest of the Newton step after ``exp`` (x = exp(arg)): the step; 1 when every row's step is
    below SC_FINISH of d (d untouched: the caller finishes), else d updated as numpy does and 2 when
    every row is small or has no step, 0 to go on."""
    k = d.shape[0]
    all_small = True
    for r in range(k):
        q0 = r
        q1 = r + k
        cr, ntu = Cr[q0], NTU[q0]
        eps = ntu / (1.0 + ntu) if abs(1.0 - cr) < 1e-9 else (1.0 - x[q0]) / (1.0 - cr * x[q0])
        cr2, ntu2 = Cr[q1], NTU[q1]
        eps2 = ntu2 / (1.0 + ntu2) if abs(1.0 - cr2) < 1e-9 else (1.0 - x[q1]) / (1.0 - cr2 * x[q1])
        Q_e = eps * C_min[q0] * dT[r]
        dQ_dC = (eps2 * C_min[q1] * dT[r] - Q_e) / (C[r] * 1e-7)
        mr = m[r]
        dm = -mr * h_T[r] / g[r]
        st = (mr * dq[r] - Q_e) / (dm * dq[r] + mr * h_T[r] - dQ_dC * (dm * cp[r] + mr * (h_T[r] - cp[r]) / d[r]))
        step[r] = st
        if not (abs(st) <= finish * d[r]):
            all_small = False
    if all_small:
        return 1
    stop = True
    for r in range(k):
        st = step[r]
        dr = d[r]
        if abs(st) <= finish * dr:
            continue
        if st == st:
            stop = False
        dn = dr - st
        if dn != dn:
            dn = 0.5 * dr
        if dn <= 0.0:
            d[r] = 0.5 * dr
        elif dn > d_hi[r]:
            d[r] = 0.5 * (dr + d_hi[r])
        else:
            d[r] = dn
    return 2 if stop else 0


def _pw_leaf(a, i0, n):
    """numpy's pairwise sum of a[i0:i0 + n] for n <= 128 (``_pw``)."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[i0 + i]
        return res
    r0, r1, r2, r3 = a[i0], a[i0 + 1], a[i0 + 2], a[i0 + 3]
    r4, r5, r6, r7 = a[i0 + 4], a[i0 + 5], a[i0 + 6], a[i0 + 7]
    i = 8
    m = n - n % 8
    while i < m:
        j = i0 + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[i0 + i]
        i += 1
    return res


def _pw(a, i0, n):
    """numpy's sum of a[i0:i0 + n] (float64, contiguous): ``add.reduce``'s pairwise summation
    (``pairwise_sum`` in numpy's loops_utils.h: below 8 terms in order; up to 128 in eight running
    sums by position modulo 8, combined as ((0+1)+(2+3))+((4+5)+(6+7)), then the rest in order;
    beyond 128 the sum of the two halves, split at a multiple of 8). The halves' recursion runs on
    an explicit stack: numba's cache cannot load a recursive function."""
    if n <= 128:
        return _pw_leaf(a, i0, n)
    start = np.empty(64, np.int64)      # the nodes on the path from the root: start, length, and
    size = np.empty(64, np.int64)       # whether its right half is under way (its left half's
    right = np.zeros(64, np.bool_)      # sum in ``left``)
    left = np.empty(64)
    top = 0
    start[0], size[0] = i0, n
    while True:
        m = size[top]
        if m > 128:                      # an inner node: its left half first
            right[top] = False
            h = m // 2
            h -= h % 8
            start[top + 1], size[top + 1] = start[top], h
            top += 1
            continue
        v = _pw_leaf(a, start[top], m)
        top -= 1
        while top >= 0 and right[top]:          # right halves done: their parents' sums
            v = left[top] + v
            top -= 1
        if top < 0:
            return v
        left[top], right[top] = v, True         # a left half done: its right half next
        h = size[top] // 2
        h -= h % 8
        start[top + 1], size[top + 1] = start[top] + h, size[top] - h
        top += 1


def _ls_rows(P, sw, y, ks, has_prior, wp, yp, a_out, r_out, ssr_out):
    """``forecast._ls_many`` after its ``phi_many`` (P (K, n)): per k the normal equations' sums, the
    non-negative solution and the data rows' sum of squares, element by element as numpy's version
    (its row sums ``_pw``)."""
    K, n = P.shape
    w2 = np.empty(n)
    wy = np.empty(n)
    buf = np.empty(n)
    for i in range(n):
        w2[i] = sw[i] * sw[i]
        wy[i] = w2[i] * y[i]
    g00 = _pw(w2, 0, n)
    gh0 = _pw(wy, 0, n)
    for k in range(K):
        for i in range(n):
            buf[i] = P[k, i] * w2[i]
        G01 = _pw(buf, 0, n)
        for i in range(n):
            buf[i] = (P[k, i] * P[k, i]) * w2[i]
        G11 = _pw(buf, 0, n)
        for i in range(n):
            buf[i] = P[k, i] * wy[i]
        h1 = _pw(buf, 0, n)
        G00 = g00
        h0 = gh0
        if has_prior:
            inv_k = 1.0 / ks[k] if ks[k] > 0 else 0.0
            wp2 = wp * wp if ks[k] > 0 else 0.0
            G00 = G00 + wp2
            G01 = G01 + wp2 * inv_k
            G11 = G11 + wp2 * inv_k ** 2
            h0 = h0 + wp2 * yp
            h1 = h1 + wp2 * yp * inv_k
        det = G00 * G11 - G01 * G01
        a_u = (G11 * h0 - G01 * h1) / det
        r_u = (G00 * h1 - G01 * h0) / det
        a_e = _nmax(h0 / G00, 0.0)
        r_e = _nmax(h1 / G11, 0.0) if G11 > 0 else 0.0
        ok_u = math.isfinite(a_u) and math.isfinite(r_u) and a_u >= 0 and r_u >= 0
        if ok_u:
            a, r = a_u, r_u
        elif (a_e * a_e * G00 + 2 * a_e * 0.0 * G01 + 0.0 * 0.0 * G11 - 2 * (a_e * h0 + 0.0 * h1)
              <= 0.0 * 0.0 * G00 + 2 * 0.0 * r_e * G01 + r_e * r_e * G11 - 2 * (0.0 * h0 + r_e * h1)):
            a, r = a_e, 0.0
        else:
            a, r = 0.0, r_e
        for i in range(n):
            v = sw[i] * (y[i] - a - r * P[k, i])
            buf[i] = v * v
        a_out[k] = a
        r_out[k] = r
        ssr_out[k] = _pw(buf, 0, n)


def _cc_nodes(yp, L, kk, r0, yi, x, T, ks, X16, W16):
    """``cost._stacked_cost`` from the levels after each cycle's reset ``yp`` (V, m) to the Gauss
    nodes: the crossing times of the cost curve's levels x (Kern–Seaton (``ks``): from L, numpy's
    log of (y_inf - yp) / (y_inf - x); linear: (x - yp) / r0), clipped to [0, T]; the pieces between
    them and the window of whole pieces around each cycle's non-zero ones (``cost._pieces``: its
    width the largest of all cycles', every piece below 2 or above 8); the nodes' times and weights
    (V, m, width x 16)."""
    V, m = yp.shape
    b = x.shape[0]
    p = b + 1
    E = np.empty((V, m, p + 1))
    for v in range(V):
        for j in range(m):
            y = yp[v, j]
            E[v, j, 0] = 0.0
            for q in range(b):
                if ks:
                    tau = L[v, j, q] / kk[v]
                    if x[q] >= yi[v]:
                        tau = np.inf
                elif r0[v] > 0:
                    tau = (x[q] - y) / r0[v]
                else:
                    tau = np.inf
                if x[q] <= y or tau != tau:
                    tau = 0.0
                E[v, j, q + 1] = _nmin(_nmax(tau, 0.0), T[j])
            E[v, j, p] = T[j]
    first = np.zeros((V, m), np.int64)
    every = p < 2 or p > 8 or V * m == 0
    width = p
    if not every:
        width = 0
        for v in range(V):
            for j in range(m):
                f = -1
                last = 0
                for i in range(p):
                    if E[v, j, i + 1] - E[v, j, i] != 0.0:
                        if f < 0:
                            f = i
                        last = i
                if f < 0:
                    f = 0
                first[v, j] = f
                if last - f + 1 > width:
                    width = last - f + 1
        if width >= p:
            every = True
            width = p
    w16 = width * 16
    tau_out = np.empty((V, m, w16))
    wts = np.empty((V, m, w16))
    for v in range(V):
        for j in range(m):
            st = 0 if every else min(first[v, j], p - width)
            for w in range(width):
                a = E[v, j, st + w]
                h = E[v, j, st + w + 1] - a
                for q in range(16):
                    tau_out[v, j, w * 16 + q] = h * X16[q] + a
                    wts[v, j, w * 16 + q] = h * W16[q]
    return tau_out, wts


def _cc_sums(ex, tau, wts, yp, r0, yi, ks, cx, cf, out):
    """The rest of ``cost._stacked_cost``: the levels at the nodes (Kern–Seaton: y_inf - ex (y_inf -
    yp), ex numpy's exp(-k tau); linear: yp + r0 tau), the cost curve there (``CostCurve``:
    ``np.interp`` between its points, linear beyond them), times the weights, summed per cycle as
    numpy sums a row. False where a level or a cost is NaN (the caller then runs numpy's version,
    whose ``interp`` of NaN this does not follow)."""
    V, m, w16 = tau.shape
    nx = cx.shape[0]
    s_lo = (cf[1] - cf[0]) / (cx[1] - cx[0])
    s_hi = (cf[nx - 1] - cf[nx - 2]) / (cx[nx - 1] - cx[nx - 2])
    buf = np.empty(w16)
    for v in range(V):
        for j in range(m):
            y = yp[v, j]
            for q in range(w16):
                if ks:
                    lv = yi[v] - ex[v, j, q] * (yi[v] - y)
                else:
                    lv = y + r0[v] * tau[v, j, q]
                if lv != lv:
                    return False
                if lv < cx[0]:
                    fv = cf[0] + s_lo * (lv - cx[0])
                elif lv > cx[nx - 1]:
                    fv = cf[nx - 1] + s_hi * (lv - cx[nx - 1])
                else:
                    i = nx - 1
                    while cx[i] > lv:
                        i -= 1
                    if i == nx - 1 or cx[i] == lv:
                        fv = cf[i]
                    else:
                        fv = (cf[i + 1] - cf[i]) / (cx[i + 1] - cx[i]) * (lv - cx[i]) + cf[i]
                if fv != fv:
                    return False
                buf[q] = fv * wts[v, j, q]
            out[v, j] = _pw(buf, 0, w16)
    return True


def enable() -> bool:
    """Compile the kernel (once per process; numba's on-disk cache makes later processes quick).
    False, and the numpy search stays, when numba is not installed or fails to compile."""
    global _KERNEL, _CURVE, _LIQ, _SAT, _DER, _SC_PRE, _SC_POST, _SATF, _VAP, _RECT, _LS, _CCN, _CCS, _TRIED
    if _KERNEL is not None or _TRIED:
        return _KERNEL is not None
    _TRIED = True
    try:
        import numba
    except ImportError:
        return False
    try:
        jit = numba.njit(cache=True, error_model="numpy", fastmath=False)
        phi = jit(_phi)
        glb = dict(_search.__globals__)
        glb["_phi"] = phi
        search = type(_search)(_search.__code__, glb, _search.__name__)
        _KERNEL, _CURVE, _LIQ = jit(search), jit(_curve_rows), jit(_liq_rows)
        _SAT = jit(_sat_rows)
        idx, nmin, nmax = jit(_idx), jit(_nmin), jit(_nmax)
        glb = dict(_der_rows.__globals__, _idx=idx, _nmin=nmin, _nmax=nmax, _liq_rows=_LIQ)
        _DER = jit(type(_der_rows)(_der_rows.__code__, glb, _der_rows.__name__))
        _SC_PRE = jit(type(_sc_pre)(_sc_pre.__code__, glb, _sc_pre.__name__))
        _SC_POST = jit(_sc_post)
        _SATF = jit(type(_sat_full_rows)(_sat_full_rows.__code__, glb, _sat_full_rows.__name__))
        _VAP = jit(type(_vap_rows)(_vap_rows.__code__, glb, _vap_rows.__name__))
        _RECT = jit(type(_rect_min_rows)(_rect_min_rows.__code__, glb, _rect_min_rows.__name__))
        glb = dict(_ls_rows.__globals__, _nmax=nmax, _nmin=nmin)
        glb["_pw_leaf"] = jit(_pw_leaf)
        glb["_pw"] = jit(type(_pw)(_pw.__code__, glb, _pw.__name__))
        _LS = jit(type(_ls_rows)(_ls_rows.__code__, glb, _ls_rows.__name__))
        _CCN = jit(type(_cc_nodes)(_cc_nodes.__code__, glb, _cc_nodes.__name__))
        _CCS = jit(type(_cc_sums)(_cc_sums.__code__, glb, _cc_sums.__name__))
        _probe()
    except Exception as exc:     # noqa: BLE001 -- any numba failure: the numpy search stays
        _KERNEL = _CURVE = _LIQ = _SAT = _DER = _SC_PRE = _SC_POST = _SATF = _VAP = _RECT = _LS = _CCN = _CCS = None
        # the same numbers either way, but a replay several times slower: say so once
        warnings.warn(f"numba {getattr(numba, '__version__', '?')} is installed but hp-edge's compiled kernels "
                      f"did not compile ({type(exc).__name__}: {exc}); replays run on numpy: the same "
                      "numbers, slower", RuntimeWarning, stacklevel=2)
        return False
    return True


def active() -> bool:
    return _KERNEL is not None


def _probe() -> None:
    """Compile for the argument types ``run`` passes (one row, no grid)."""
    z = np.zeros((1, 2, 2, 6))
    run((z, np.zeros(1), np.ones(1), np.zeros(1, dtype=np.intp), np.zeros(1, dtype=np.intp),
         np.zeros(1, dtype=bool), np.zeros(1), np.ones(1)), np.zeros(1, dtype=np.intp),
        tuple(np.zeros(1) + k for k in (0.5, 0.0, 0.3, 0.0, 0.0, 0.0)), None,
        np.array([0.5]), np.array([2.0]), None, 0.5, 1.5)
    z1 = np.zeros(1)
    curve(np.zeros((1, 6)), np.zeros(1, dtype=np.intp), z1, z1, (z, z1, z1 + 1, np.zeros(1, dtype=np.intp),
          np.zeros(1, dtype=np.intp), np.zeros(1, dtype=bool), z1, z1 + 1), None)
    liq(np.zeros((2, 16)), np.zeros(1, dtype=np.intp), np.zeros((1, 1)), z1, 0.0, 2.0, -2.0)
    sat(np.zeros((2, 4, 5)), z1, 0.0, 1.0)
    derived(np.zeros((4, 16)), z1, z1, 0.0, 1.0, 0, 0.0, 1.0, 1.0, 0)
    sat_full(np.zeros((2, 4, 5)), z1, 0.0, 1.0, 0, 0.0, 1.0)
    vapour(np.zeros((4, 4, 4, 3)), z1, z1, z1, 0.0, 1.0, 0, 2, 0.0, 1.0, 0, 0.0, 1.0, 1.0)
    rect_min(np.zeros((1, 2)), np.zeros((1, 2)), np.ones(2), np.ones(2))
    ls_rows(np.ones((1, 2)), np.ones(2), np.ones(2), np.ones(1), None)
    ls_rows(np.ones((1, 2)), np.ones(2), np.ones(2), np.ones(1), (1.0, 1.0))
    for ks in (True, False):
        cycle_cost(np.ones((1, 1)), np.ones(1), np.ones(1), np.full(1, 2.0), ks, np.array([0.5, 1.5]),
                   np.array([0.0, 1.0]), np.ones(1), np.zeros(16), np.ones(16))
    subcooler(np.zeros((2, 16)), np.zeros(1, dtype=np.intp), np.zeros((1, 1)), 0.0, 2.0, -2.0, z1 + 0.25,
              z1 + 1.0, z1 + 2.0, z1, z1 + 1.0, z1 + 1.0, z1 + 2.0, z1 + 10.0, 30, 1e-6)


def run(tables: tuple, g, c, dl, target, pi, n0, n_lo: float, n_hi: float):
    """``local_speed``'s (n, eta_vol) with the compiled kernel. ``tables``: (ca (members, pi nodes,
    n nodes, 6), p0, dpi, ni, nj, ok, n0, dn) per member; ``g`` the rows' members; ``c`` the global
    curve (six scalars or six arrays per row), ``dl`` the curve differences (None, six scalars or
    six arrays per row), ``n0`` the start speeds (None: 1)."""
    from .compressors import _Z, SPEED_STEP_TOL
    target = np.ascontiguousarray(target, dtype=float)
    pi = np.ascontiguousarray(pi, dtype=float)
    rows = target.shape[0]
    if isinstance(c, np.ndarray) and c.shape == (6, rows):
        C = np.ascontiguousarray(c.T)         # (a stacked member's curves per row: no copy)
    else:
        C = np.empty((rows, 6))
        for k in range(6):
            C[:, k] = c[k]
    DL = np.zeros((rows, 6))
    if dl is not None:
        for k in range(6):
            DL[:, k] = dl[k]
    ns = np.zeros(rows) if n0 is None else np.ascontiguousarray(np.broadcast_to(
        np.asarray(n0, dtype=float), (rows,)))
    ca, p0, dpi, ni, nj, ok, gn0, gdn = tables
    n_out, ev_out = np.empty(rows), np.empty(rows)
    _KERNEL(ca, p0, dpi, ni, nj, ok, gn0, gdn, np.ascontiguousarray(g, dtype=np.intp), C, DL,
            dl is not None, target, pi, ns, n0 is not None, float(n_lo), float(n_hi),
            float(_Z[0]), float(_Z[1]), float(_Z[2]), float(_Z[3]), float(SPEED_STEP_TOL), n_out, ev_out)
    return n_out, ev_out


def curve(C, g, pi, n, tables: tuple | None, dl) -> np.ndarray:
    """``stacked._View._curve`` with the compiled kernel: C (members, 6) the global curves, g the
    rows' members, pi and n the rows' (1-D, one per row), ``tables`` the members' local grids
    (``_Tables.kernel_tables``; None: none), ``dl`` the rows' curve differences (six arrays or
    None)."""
    from .compressors import _Z
    pi = np.ascontiguousarray(pi, dtype=float)
    n = np.ascontiguousarray(n, dtype=float)
    rows = pi.shape[0]
    has_tab = tables is not None
    if dl is None:
        DL = np.zeros((1, 6))
    else:
        DL = np.empty((rows, 6))
        for k in range(6):
            DL[:, k] = dl[k]
    if tables is None:
        z = np.zeros(1)
        tables = (np.zeros((1, 2, 2, 6)), z, z + 1.0, np.zeros(1, dtype=np.intp), np.zeros(1, dtype=np.intp),
                  np.zeros(1, dtype=bool), z, z + 1.0)
    ca, p0, dpi, ni, nj, ok, gn0, gdn = tables
    out = np.empty(rows)
    _CURVE(np.ascontiguousarray(C, dtype=float), np.ascontiguousarray(g, dtype=np.intp), pi, n,
           has_tab, ca, p0, dpi, ni, nj, ok, gn0, gdn, dl is not None, DL,
           float(_Z[0]), float(_Z[1]), float(_Z[2]), float(_Z[3]), out)
    return out


def liq(C, base, tx, d, d0: float, inv_dd: float, dscale: float):
    """``CycleTables.liq_raw`` with the compiled kernel: (h, dh/dT) at subcooling d of the rows
    (``liq_row``'s base offsets and (rows, 1) unit coordinates tx)."""
    d = np.ascontiguousarray(d, dtype=float)
    h, dh = np.empty(d.shape[0]), np.empty(d.shape[0])
    _LIQ(C, np.ascontiguousarray(base, dtype=np.intp), np.ascontiguousarray(tx[:, 0], dtype=float), d,
         float(d0), float(inv_dd), float(dscale), h, dh)
    return h, dh


def sat(C, T, x0: float, inv_dt: float) -> np.ndarray:
    """``CycleTables.sat_raw``'s spline columns (5, rows) at T, before its two ``exp``."""
    T = np.ascontiguousarray(T, dtype=float)
    out = np.empty((5, T.shape[0]))
    _SAT(C, T, float(x0), float(inv_dt), out)
    return out


def sat_full(C, T, x0: float, inv_dt: float, nm2: int, t_lo: float, t_hi: float) -> np.ndarray:
    """``CycleTables.sat``'s spline columns (5, rows) at T, NaN outside [t_lo, t_hi], before its
    two ``exp``."""
    T = np.ascontiguousarray(T, dtype=float)
    out = np.empty((5, T.shape[0]))
    _SATF(C, T, float(x0), float(inv_dt), int(nm2), float(t_lo), float(t_hi), out)
    return out


def vapour(V, T, theta, u, x0, inv_dx, nxm2, nu1, u0, inv_du, num2, t_lo, t_hi, th_max) -> np.ndarray:
    """``CycleTables.vapour``'s (h, s, ln rho) (3, rows), NaN outside the table, before its ``exp``."""
    T = np.ascontiguousarray(T, dtype=float)
    out = np.empty((3, T.shape[0]))
    _VAP(V, T, np.ascontiguousarray(theta, dtype=float), np.ascontiguousarray(u, dtype=float), float(x0),
         float(inv_dx), int(nxm2), int(nu1), float(u0), float(inv_du), int(num2), float(t_lo), float(t_hi),
         float(th_max), out)
    return out


def rect_min(q, c, half, scale) -> np.ndarray:
    """``compressors._rect_distance(q, c, half, scale).min(axis=1)`` (q (k, 2), c (m, 2), m >= 1)."""
    q = np.asarray(q, dtype=float)
    out = np.empty(q.shape[0])
    _RECT(np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), np.ascontiguousarray(c, dtype=float),
          float(half[0]), float(half[1]), float(scale[0]), float(scale[1]), out)
    return out


def derived(C, T, lw, x0, inv_dx, nxm2, w0, inv_alpha, inv_dw, nwm2) -> np.ndarray:
    """``CycleTables._derived`` after its ``log1p`` (``lw``)."""
    T = np.ascontiguousarray(T, dtype=float)
    out = np.empty(T.shape[0])
    _DER(C, T, np.ascontiguousarray(lw, dtype=float), float(x0), float(inv_dx), int(nxm2), float(w0),
         float(inv_alpha), float(inv_dw), int(nwm2), out)
    return out


def subcooler(LC, base, tx, d0, inv_dd, dscale, d, num, h_g_m, h_f_c, C_w, UA, dT, d_hi, iters: int,
              finish: float):
    """``Flowsheet._subcooler``'s Newton iteration from the start d (the same numbers to the bit):
    per step ``_sc_pre``, numpy's ``exp`` of the 2k exponents, ``_sc_post``. Returns (converged, d,
    step, h, h_T) as the numpy loop leaves them: converged when every row's step fell below
    ``finish`` of d (d not yet updated by that step), else d updated and h, h_T, step of the last
    step's start; ``vflowsheet._sc_finish`` / ``_sc_unfinished`` turn them into the result."""
    f = lambda a: np.ascontiguousarray(a, dtype=float)      # noqa: E731
    d = np.array(d, dtype=float)
    num, h_g_m, h_f_c, C_w, UA, dT, d_hi = (f(a) for a in (num, h_g_m, h_f_c, C_w, UA, dT, d_hi))
    base = np.ascontiguousarray(base, dtype=np.intp)
    txv = np.ascontiguousarray(tx[:, 0], dtype=float)
    k = d.shape[0]
    h, h_T, g, m, dq, cp, C, step = (np.empty(k) for _ in range(8))
    C_min, Cr, NTU, arg = (np.empty(2 * k) for _ in range(4))
    for _ in range(iters):
        _SC_PRE(LC, base, txv, d, float(d0), float(inv_dd), float(dscale), num, h_g_m, h_f_c, C_w, UA,
                h, h_T, g, m, dq, cp, C, C_min, Cr, NTU, arg)
        code = _SC_POST(np.exp(arg), C_min, Cr, NTU, dT, d, d_hi, h_T, g, m, dq, cp, C, step, float(finish))
        if code == 1:
            return True, d, step, h, h_T
        if code == 2:
            break
    return False, d, step, h, h_T


def ls_rows(P, sw, y, ks, prior_row) -> tuple:
    """``forecast._ls_many``'s (a0, r0, ssr) per k from P = phi_many(t, ks) (K, n), the square-root
    weights ``sw``, the data ``y`` (n,) and ``prior_row`` ((weight, y_inf - floor) or None)."""
    P = np.ascontiguousarray(P, dtype=float)
    K = P.shape[0]
    a, r, ssr = np.empty(K), np.empty(K), np.empty(K)
    wp, yp = (0.0, 0.0) if prior_row is None else (float(prior_row[0]), float(prior_row[1]))
    _LS(P, np.ascontiguousarray(sw, dtype=float), np.ascontiguousarray(y, dtype=float),
        np.ascontiguousarray(ks, dtype=float), prior_row is not None, wp, yp, a, r, ssr)
    return a, r, ssr


def cycle_cost(yp, k, r0, y_inf, ks: bool, cx, cf, T, X16, W16):
    """``cost._stacked_cost``'s integrals (V, m) from the levels after the resets ``yp`` (V, m) of
    the members (k, r0, y_inf per member; ``ks`` the Kern–Seaton law, else linear), the cost curve's
    points (cx, cf) and the cycle lengths T (m,), with the Gauss nodes X16, W16 on [0, 1]; None
    where a level or cost is NaN (numpy's version answers then)."""
    f = lambda a: np.ascontiguousarray(a, dtype=float)      # noqa: E731
    yp, k, r0, y_inf, cx, cf, T = f(yp), f(k), f(r0), f(y_inf), f(cx), f(cf), f(T)
    L = np.zeros((1, 1, 1))
    if ks:
        with np.errstate(divide="ignore", invalid="ignore"):
            yi3 = y_inf[:, None, None]
            L = np.log((yi3 - yp[:, :, None]) / (yi3 - cx[None, None, :]))
    tau, wts = _CCN(yp, L, k, r0, y_inf, cx, T, bool(ks), f(X16), f(W16))
    ex = tau
    if ks:
        ex = np.multiply(-k[:, None, None], tau)
        np.exp(ex, out=ex)
    out = np.empty(yp.shape)
    return out if _CCS(ex, tau, wts, yp, r0, y_inf, bool(ks), cx, cf, out) else None
