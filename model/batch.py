"""Row-by-row simulation of a DataFrame of inputs, warm-started from the previous row.

Input columns use the canonical units of SPEC §4 (degC, m3/h, bar(g)); outputs use the keys of
``CycleResult.to_dict`` plus ``status`` and ``reason`` per row:

- ``ok``: solved within every limit;
- ``ls_speed_high`` / ``ls_speed_low`` / ``negative_pinch``: solved, but outside an operating
  limit. Outputs are still returned: on measured data this usually means the model's compressor
  curve or UA is slightly off, not that the point is impossible (SPEC §3);
- anything else (``bad_input``, ``no_convergence``, ``p_m_sp_below_p_e``, ...): no outputs (NaN).
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .cycle import CycleResult, InfeasibleOperation, ModelError, solve
from .fluid import get_fluid
from .params import CycleInputs, PlantParams
from .units import C_to_K, K_to_C, barg_to_Pa, m3h_to_m3s

# The batch entry points (simulate_batch here, model.optimize.Evaluator) solve all rows at once with
# model.vcycle.solve_many (numpy over the rows, HEOS spline tables); False: row by row with the scalar
# model.cycle.solve, warm-started from the previous row (the benchmark compares the two)
VECTORISED = True

INPUT_COLUMNS = ("T_source_in", "T_source_out", "T_sink_in", "V_source", "V_sink", "p_m_sp")
SOLVED_WITH_FLAG = ("ls_speed_high", "ls_speed_low", "negative_pinch")


def floats(s: pd.Series) -> np.ndarray:
    """``pd.to_numeric(s, errors="coerce").to_numpy(dtype=float)`` (a new array): a float64 column
    as it is, without ``to_numeric``'s checks (~25 us a call, a dozen calls a window)."""
    if getattr(s, "dtype", None) == np.float64:     # (a duplicated label's frame: to_numeric's error)
        return s.to_numpy(dtype=float, copy=True)
    return pd.to_numeric(s, errors="coerce").to_numpy(dtype=float)


def numeric(df: pd.DataFrame, columns) -> pd.DataFrame:
    """``df[columns].apply(pd.to_numeric, errors="coerce")``: the columns as numbers (NaN where
    not), on ``df``'s index; column by column without ``DataFrame.apply``'s machinery (the
    windows' hot path), the same frame. When every column is float64 already: one (columns x
    rows) block, the block pandas consolidates the dict of columns into (the same layout and
    numbers), without building the dict's Series."""
    columns = list(columns)
    if not len(df):
        return df[columns].apply(pd.to_numeric, errors="coerce")
    cols = [df[c] for c in columns]
    if all(getattr(s, "dtype", None) == np.float64 for s in cols) and len(set(columns)) == len(columns):
        block = np.empty((len(columns), len(df)))
        for i, s in enumerate(cols):
            block[i] = s.to_numpy()
        return pd.DataFrame(block.T, index=df.index, columns=columns, copy=False)
    return pd.DataFrame({c: pd.to_numeric(s, errors="coerce") for c, s in zip(columns, cols)},
                        index=df.index, columns=columns)


def _block(df, columns) -> np.ndarray | None:
    """A new (columns x rows) float array of a DataFrame whose columns are ``columns`` exactly, in
    their order (the representative rows, a window's numeric inputs): ``to_numpy(dtype=float)``
    of the whole frame, which converts each column as the column's own ``to_numpy(dtype=float)``
    does (~10 us, where a column read costs ~30 us); None for any other frame."""
    if not isinstance(df, pd.DataFrame) or len(df.columns) != len(columns) \
            or list(df.columns) != list(columns):
        return None
    return np.array(df.to_numpy(dtype=float).T, order="C")


def matrix(df: "pd.DataFrame | InputColumns", columns=INPUT_COLUMNS) -> np.ndarray:
    """``df[list(columns)].to_numpy(dtype=float)`` column by column, without building the sub-frame
    (the windows' hot path): the same numbers in the same (Fortran) memory order, so that
    reductions over it add in the same order."""
    out = _block(df, columns)
    if out is not None:
        return out.T
    out = np.empty((len(columns), len(df)))
    cols = df.cols if isinstance(df, InputColumns) else None
    for i, c in enumerate(columns):
        out[i] = df[c].to_numpy(dtype=float) if cols is None else cols[c]
    return out.T


class InputColumns:
    """Rows for ``model.vcycle.solve_many`` as input columns (float arrays of one length) instead
    of a DataFrame: what the solver reads of its rows, without pandas' cost per column and call
    (the optimizer's evaluations of the same rows at many set points)."""
    __slots__ = ("cols", "n")

    def __init__(self, cols: dict) -> None:
        self.cols = cols
        self.n = len(next(iter(cols.values()))) if cols else 0

    @classmethod
    def of(cls, df: pd.DataFrame, columns=INPUT_COLUMNS) -> "InputColumns":
        """``df``'s columns among ``columns`` as floats (``to_numpy(dtype=float)``, as the solver reads
        a DataFrame)."""
        block = _block(df, columns)
        if block is not None:       # (each column a row of one new array)
            return cls(dict(zip(columns, block)))
        return cls({c: df[c].to_numpy(dtype=float) for c in columns if c in df.columns})

    def take(self, idx: np.ndarray) -> "InputColumns":
        """The rows ``idx`` (new arrays)."""
        return InputColumns({c: a[idx] for c, a in self.cols.items()})

    @property
    def columns(self):
        return self.cols.keys()

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, c: str) -> np.ndarray:
        return self.cols[c]


def among(values: np.ndarray, choices) -> np.ndarray:
    """``np.isin(values, choices)`` for a few string choices, as equality tests (isin sorts)."""
    values = np.asarray(values)
    out = values == choices[0]
    for c in choices[1:]:
        out |= values == c
    return np.asarray(out, dtype=bool)


OUTPUT_KEYS = (
    "p_e_bar", "p_m_bar", "p_c_bar", "p_m_barg", "T_e_C", "T_m_C", "T_c_C", "N_LS_rpm", "N_HS_rpm",
    "Q_sink_kW", "Q_source_kW", "W_LS_kW", "W_HS_kW", "W_total_kW", "COP", "T_sink_out_C",
    "eta_is_LS", "eta_is_HS", "eta_vol_LS", "eta_vol_HS", "m_LS_kg_s", "m_HS_kg_s", "subcooling_K",
    "pinch_K", "dp_source_bar", "T_dis_LS_C", "T_dis_HS_C", "energy_residual", "hs_saturated",
    "T_source_out_C", "ls_saturated",
)


def inputs_from_row(row, ambient_bar: float) -> CycleInputs:
    """CycleInputs (SI) from canonical-unit values (a mapping with INPUT_COLUMNS)."""
    return CycleInputs(
        T_source_in=C_to_K(float(row["T_source_in"])), T_source_out=C_to_K(float(row["T_source_out"])),
        T_sink_in=C_to_K(float(row["T_sink_in"])), V_source=m3h_to_m3s(float(row["V_source"])),
        V_sink=m3h_to_m3s(float(row["V_sink"])), p_m_sp=barg_to_Pa(float(row["p_m_sp"]), ambient_bar))


def result_row(res: CycleResult, ambient_pressure: float) -> dict:
    d = res.to_dict(ambient_pressure, states=False)
    d["T_dis_LS_C"] = K_to_C(res.states["LS_dis"].T)
    d["T_dis_HS_C"] = K_to_C(res.states["HS_dis"].T)
    d["T_source_out_C"] = K_to_C(res.T_source_out)
    d["ls_saturated"] = bool(res.ls_limit)
    return {k: d[k] for k in OUTPUT_KEYS}


def simulate_batch(df: pd.DataFrame, params: PlantParams, p_m_sp=None,
                   columns: tuple[str, ...] = OUTPUT_KEYS, ls_mode: str = "flag") -> pd.DataFrame:
    """Simulate every row of ``df`` (canonical input columns) with warm starts.

    p_m_sp : float [bar(g)] or array, optional
        Overrides the ``p_m_sp`` column (used by the set-point optimizer).
    columns : which output keys to keep (fewer is faster to assemble).
    ls_mode : "flag" (measured data: an LS speed out of range is a flagged row) or "float"
        (prediction: the LS saturates and T_source,out floats; see model.cycle.solve).
    """
    if VECTORISED:
        from .vcycle import solve_many
        return solve_many(df, params, p_m_sp=p_m_sp, ls_mode=ls_mode).frame(columns, df.index)
    rows = solve_rows(df, params, p_m_sp, ls_mode)
    return frame_of(rows, params, columns, df.index)


def simulate_many(df: "pd.DataFrame | InputColumns", params: PlantParams, columns: tuple[str, ...] = OUTPUT_KEYS,
                  ls_mode: str = "flag", R_th_f=None, cond_factor=None, seed=None,
                  seed_rows: "pd.DataFrame | InputColumns | None" = None, with_result: bool = False,
                  as_columns: bool = False):
    """``simulate_batch`` with per-row evaporator fouling ``R_th_f`` [K/W] and condenser-unit
    factors ``cond_factor`` (scalars or arrays; each row answered as with
    ``params.replace(R_th_f=...)`` and ``model.analysis.chain.scale_condenser(params, k)``), in one
    call of the vectorised solver. ``seed``: a ``model.vcycle.VResult`` of nearby solutions to start
    from, of the rows ``seed_rows`` (each row starts from the nearest of them; None: the same rows
    in the same order). ``with_result``: return (frame, VResult) (VResult None on the scalar
    path). With VECTORISED off: the scalar rows, one ``simulate_batch`` per distinct value. ``df``
    may be ``InputColumns`` (rows read again and again, e.g. a secant's): the frame then has a
    RangeIndex. ``as_columns``: the frame's columns as a dict of arrays (``columns`` as floats, then
    status and reason), not the frame (the same numbers; no DataFrame where a caller reads a few
    columns, e.g. a secant's trials)."""
    n = len(df)
    if isinstance(df, InputColumns) and not VECTORISED:
        df = pd.DataFrame(df.cols)
    R = None if R_th_f is None else np.broadcast_to(np.asarray(R_th_f, dtype=float), (n,))
    K = None if cond_factor is None else np.broadcast_to(np.asarray(cond_factor, dtype=float), (n,))
    if VECTORISED:
        from .optimize import nearest_rows
        from .vcycle import solve_many
        gidx = None
        if seed is not None and seed_rows is not None:
            gidx = nearest_rows(df, seed_rows)
        elif seed is not None and len(seed) != n:
            seed = None
        vres = solve_many(df, params, ls_mode=ls_mode, R_th_f=R, cond_factor=K, guess=seed,
                          guess_index=gidx)
        if as_columns:
            cols = vres.columns(columns)
            return (cols, vres) if with_result else cols
        frame = vres.frame(columns, df.index if isinstance(df, pd.DataFrame) else None)
        return (frame, vres) if with_result else frame
    keys = list(zip(R if R is not None else [None] * n, K if K is not None else [None] * n))
    parts, order = [], []
    for key in dict.fromkeys(keys):
        pos = np.flatnonzero([k == key for k in keys])
        par = params
        if key[0] is not None:
            par = par.replace(R_th_f=float(key[0]))
        if key[1] is not None:
            par = par.replace(CF_DSH=par.CF_DSH * key[1], CF_con=par.CF_con * key[1],
                              CF_SC=par.CF_SC * key[1])
        parts.append(simulate_batch(df.iloc[pos].reset_index(drop=True), par, columns=columns,
                                    ls_mode=ls_mode))
        order.append(pos)
    if not parts:
        frame = simulate_batch(df, params, columns=columns, ls_mode=ls_mode)
    else:
        frame = pd.concat(parts, ignore_index=True).iloc[np.argsort(np.concatenate(order), kind="stable")]
        frame.index = df.index
    if as_columns:
        frame = {c: (frame[c].to_numpy() if c in ("status", "reason") else frame[c].to_numpy(dtype=float))
                 for c in (*columns, "status", "reason")}
    return (frame, None) if with_result else frame


Row = tuple  # (status, reason, CycleResult | None) of one simulated row


def solve_rows(df: pd.DataFrame, params: PlantParams, p_m_sp=None, ls_mode: str = "flag",
               guesses: list | None = None) -> list[Row]:
    """``simulate_batch``'s solves: per row (status, reason, CycleResult or None).

    Each row is warm-started from the previous row's solution, or from ``guesses[i]`` where given
    (a solution of the same row nearby, e.g. at another set point or with other parameters)."""
    missing = [c for c in INPUT_COLUMNS if c not in df.columns and not (c == "p_m_sp" and p_m_sp is not None)]
    if missing:
        raise KeyError(f"input columns missing: {', '.join(missing)}")
    amb_bar = params.ambient_pressure / 1e5
    fluid = get_fluid(params.fluid, params.backend)
    n = len(df)
    cols = {c: np.asarray(df[c], dtype=float) for c in INPUT_COLUMNS if c in df.columns}
    if p_m_sp is not None:
        cols["p_m_sp"] = np.broadcast_to(np.asarray(p_m_sp, dtype=float), (n,))
    out: list[Row] = []
    guess = None
    for i in range(n):
        vals = {c: cols[c][i] for c in INPUT_COLUMNS}
        bad = [c for c, v in vals.items() if not math.isfinite(v)]
        if bad:
            out.append(("bad_input", f"missing or non-finite: {', '.join(bad)}", None))
            continue
        g = guesses[i] if guesses is not None and guesses[i] is not None else guess
        try:
            res = solve(inputs_from_row(vals, amb_bar), params, guess=g, fluid=fluid, ls_mode=ls_mode)
            st, why = "ok", ""
        except InfeasibleOperation as exc:
            st, why = exc.reason, str(exc)
            res = exc.result
        except ModelError as exc:
            st, why = exc.reason, str(exc)
            res = None
        out.append((st, why, res))
        if res is not None:
            guess = res
    return out


def frame_of(rows: list[Row], params: PlantParams, columns: tuple[str, ...] = OUTPUT_KEYS,
             index=None) -> pd.DataFrame:
    """The output frame of solved rows (``solve_rows``): ``columns`` plus status and reason."""
    n = len(rows)
    out = {k: np.full(n, np.nan) for k in columns}
    for i, (_, _, res) in enumerate(rows):
        if res is None:
            continue
        row = result_row(res, params.ambient_pressure)
        for k in columns:
            out[k][i] = row[k]
    frame = pd.DataFrame(out, index=index if index is not None else pd.RangeIndex(n))
    status = np.empty(n, dtype=object)
    reason = np.empty(n, dtype=object)
    for i, (st, why, _) in enumerate(rows):
        status[i], reason[i] = st, why
    frame["status"] = status
    frame["reason"] = reason
    return frame


def solved_mask(frame: "pd.DataFrame | dict", allow_flagged: bool = True) -> np.ndarray:
    """Rows with outputs: 'ok', plus speed/pinch-flagged rows when allow_flagged (``frame``: a
    DataFrame or ``simulate_many``'s columns)."""
    status = np.asarray(frame["status"])
    ok = status == "ok"
    if allow_flagged:
        ok |= among(status, SOLVED_WITH_FLAG)
    return ok
