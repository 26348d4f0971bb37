"""Fit the compressor efficiency polynomials to a manufacturer table (issue #2, `fit-compressor`).

Table columns: speed_rpm, p_suc_bar, T_suc_C, p_dis_bar, m_dot_kg_s, power_kW (pressures absolute,
power = shaft power of an adiabatic compressor). Per row:
  eta_vol = m_dot / (rho_suc * V_swept_nom * N / N_nom)
  eta_is  = m_dot * (h_is(p_dis, s_suc) - h_suc) / power
Both are fitted by linear least squares on POLY_BASIS (1, pi, n, pi^2, pi*n, n^2), n = N / N_nom.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from .fluid import PropertyError, get_fluid
from .params import POLY_BASIS, Compressor, poly_basis
from .units import BAR, C_to_K

TABLE_COLUMNS = ("speed_rpm", "p_suc_bar", "T_suc_C", "p_dis_bar", "m_dot_kg_s", "power_kW")


class TableError(ValueError):
    """The manufacturer table is unusable; the message names the column or row."""


@dataclass
class FitResult:
    eta_is: tuple[float, ...]
    eta_vol: tuple[float, ...]
    r2_is: float
    r2_vol: float
    max_err_is: float
    max_err_vol: float
    n_rows: int


def read_table(path: str) -> pd.DataFrame:
    """Read and check the table; errors name the column or the data row (1 = first data row)."""
    try:
        raw = pd.read_csv(path, dtype=str, skipinitialspace=True, keep_default_na=False)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise TableError(f"{path}: cannot read table: {exc}") from exc
    raw.columns = [c.strip() for c in raw.columns]
    missing = [c for c in TABLE_COLUMNS if c not in raw.columns]
    if missing:
        raise TableError(f"{path}: missing column(s) {', '.join(repr(c) for c in missing)}; "
                         f"expected {', '.join(TABLE_COLUMNS)}")
    if raw.empty:
        raise TableError(f"{path}: the table has no data rows")
    out = {}
    for c in TABLE_COLUMNS:
        vals = pd.to_numeric(raw[c].str.strip().replace("", "nan"), errors="coerce")
        bad = vals.isna() | ~np.isfinite(vals)
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise TableError(f"{path}: row {i + 1} (line {i + 2}): column {c!r}: "
                             f"{raw[c].iloc[i]!r} is not a number")
        if (vals <= 0).any():
            i = int(np.flatnonzero((vals <= 0).to_numpy())[0])
            raise TableError(f"{path}: row {i + 1} (line {i + 2}): column {c!r}: "
                             f"{raw[c].iloc[i]!r} must be > 0")
        out[c] = vals.to_numpy(dtype=float)
    df = pd.DataFrame(out)
    bad = df["p_dis_bar"] <= df["p_suc_bar"]
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        raise TableError(f"{path}: row {i + 1} (line {i + 2}): p_dis_bar must exceed p_suc_bar")
    return df


def efficiencies(df: pd.DataFrame, comp: Compressor, fluid_name: str = "Ammonia") -> pd.DataFrame:
    """Per-row (pi, n, eta_is, eta_vol) of a checked table."""
    fl = get_fluid(fluid_name, "HEOS")
    rows = []
    for i, r in enumerate(df.itertuples(index=False)):
        p_suc, p_dis, T_suc = r.p_suc_bar * BAR, r.p_dis_bar * BAR, C_to_K(r.T_suc_C)
        try:
            sat = fl.sat_p(p_suc)
            if T_suc <= sat.T:
                raise TableError(f"row {i + 1}: suction temperature {r.T_suc_C} degC is not above "
                                 f"saturation {sat.T - 273.15:.2f} degC at {r.p_suc_bar} bar")
            h, s, rho = fl.vapour_pT(p_suc, T_suc)
            h_is, _, _ = fl.isentropic(p_dis, s)
        except PropertyError as exc:
            raise TableError(f"row {i + 1}: {exc}") from exc
        n = r.speed_rpm / comp.N_nom
        rows.append((p_dis / p_suc, n, r.m_dot_kg_s * (h_is - h) / (r.power_kW * 1e3),
                     r.m_dot_kg_s / (rho * comp.swept_volume * n)))
    return pd.DataFrame(rows, columns=["pi", "n", "eta_is", "eta_vol"])


def fit(df: pd.DataFrame, comp: Compressor, fluid_name: str = "Ammonia") -> FitResult:
    eff = efficiencies(df, comp, fluid_name)
    if len(eff) < len(POLY_BASIS):
        raise TableError(f"need at least {len(POLY_BASIS)} rows to fit {len(POLY_BASIS)} coefficients, "
                         f"got {len(eff)}")
    X = np.array([poly_basis(p, n) for p, n in zip(eff["pi"], eff["n"])])
    if np.linalg.matrix_rank(X) < X.shape[1]:
        raise TableError("the table does not vary pressure ratio and speed enough to fit "
                         f"{len(POLY_BASIS)} coefficients (rank-deficient)")

    def lsq(y):
        c, *_ = np.linalg.lstsq(X, y, rcond=None)
        pred = X @ c
        ss_res = float(np.sum((y - pred) ** 2))
        ss_tot = float(np.sum((y - y.mean()) ** 2))
        r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0
        return tuple(float(v) for v in c), r2, float(np.max(np.abs(y - pred)))

    ci, r2i, ei = lsq(eff["eta_is"].to_numpy())
    cv, r2v, ev = lsq(eff["eta_vol"].to_numpy())
    return FitResult(ci, cv, r2i, r2v, ei, ev, len(eff))


def synthetic_table(comp: Compressor, p_suc_bar: float, T_sh_K: float = 1.0,
                    pis=(1.5, 2.0, 2.5, 3.0, 3.5, 4.0), speeds=(700, 1000, 1250, 1500, 1800),
                    fluid_name: str = "Ammonia") -> pd.DataFrame:
    """A manufacturer-style table generated from a known compressor (tests, examples)."""
    fl = get_fluid(fluid_name, "HEOS")
    p_suc = p_suc_bar * BAR
    T_suc = fl.sat_p(p_suc).T + T_sh_K
    h, s, rho = fl.vapour_pT(p_suc, T_suc)
    rows = []
    for N in speeds:
        n = N / comp.N_nom
        for pi in pis:
            p_dis = pi * p_suc
            m = comp.eta_vol_at(pi, n) * rho * comp.swept_volume * n
            h_is, _, _ = fl.isentropic(p_dis, s)
            W = m * (h_is - h) / comp.eta_is_at(pi, n)
            rows.append((N, p_suc_bar, T_suc - 273.15, p_dis / BAR, m, W / 1e3))
    return pd.DataFrame(rows, columns=list(TABLE_COLUMNS))
