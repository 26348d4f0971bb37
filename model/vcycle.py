"""Many operating points at once: ``model.cycle.solve`` vectorised over the rows of a frame.

``solve_many(rows, params, p_m_sp=None, ls_mode="flag")`` answers what ``model.batch.solve_rows``
answers row by row, for all rows together with numpy arrays: the same physics (``model.vflowsheet``
evaluates the flowsheet of ``model.cycle._Point``), properties from spline tables of HEOS
(``model.cycletables``), the compressors through their vectorised protocol (``eta_is_v``,
``eta_vol_v``, ``speed_for_flow_v``; ``vectorized`` loops the scalar methods of a compressor class
that does not provide them), and the scalar solver's path (``model.vsolve``, ``model.vfloat``), so
that the status of every row is the scalar solver's and solved values agree to ~1e-8 (the floating
LS: to the scalar's own LS-speed tolerance, ~1e-7).

The reference is ``model.cycle.solve`` without a guess (a cold start), row by row: it is what a row
gives on its own. ``solve_rows`` warm-starts each row from the previous one, and the scalar solver's
outcome depends on its start where a trial point fails (see ``model.vsolve``): on a grid of set
points 4..24 bar(g) the two differed on 9 % of the rows (``solve_rows`` solves rows at the HS bound
that the cold start fails with ``eta_out_of_range`` during its branch test at the set point).

The solver's phases run as tasks whose flowsheet evaluations are batched (``model.vtasks``): at a
few hundred rows an evaluation costs its numpy calls, not its rows, so the cost is the number of
sequential evaluation rounds, which the scalar path of the slowest rows sets (~35-60 rounds).

Rows the vectorised path cannot settle (states outside the tables, a vectorised inner iteration
that does not converge, a floating LS that settles in no branch) are solved by ``model.cycle.solve``
(cold) one by one: ``VResult.fallback_rows`` counts them. Units at the interface are those of
``model.batch`` (degC, m3/h, bar(g) in; bar absolute, degC, kW, rpm out); SI inside.

Warm starts (``guess``, ``model.vwarm``): from a previous result's ``state`` (SI), every row's root
in its guessed branch by Newton on all rows at once, then the scalar solver's branch checks; rows
those do not settle take the cold path (a few of them the scalar solver). The answers are the cold
path's. Per-row ``R_th_f`` and ``cond_factor`` batch what would be calls with other parameters.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .batch import INPUT_COLUMNS, OUTPUT_KEYS, InputColumns, among, inputs_from_row, result_row
from .cycle import LS_MODES, LS_SPEED_LOOSE, InfeasibleOperation, ModelError, solve
from .cycletables import get_cycle_tables
from .fluid import get_fluid
from .params import Compressor, PlantParams
from .units import BAR, C_to_K, K_to_C, Pa_to_barg, barg_to_Pa, m3h_to_m3s
from .vflowsheet import Flowsheet
from .vfloat import FloatLS
from . import lockstep
from .vtasks import run
from .vsolve import FALLBACK, HS_MAX, Outcome, solve_cold
from .vwarm import SCALAR_COLD_MAX, WarmPlan, WarmSolve, borrow, empty_state, take_state, usable

SOLVED_FLAGS = ("ls_speed_high", "ls_speed_low", "negative_pinch")
# beyond model.batch.OUTPUT_KEYS: the subcooler's states (its outlet on the equation of state)
EXTRA_KEYS = ("Q_SC_kW", "T_SC_C", "h_SC_J_kg", "h_con_out_J_kg", "T_w_SC_out_C")
_PROTOCOL = (("eta_is_at", "eta_is_v"), ("eta_vol_at", "eta_vol_v"), ("speed_for_flow", "speed_for_flow_v"))


# --------------------------------------------------------------------------------------------------
# the compressor protocol
# --------------------------------------------------------------------------------------------------
def _owner(cls, name: str):
    for k in cls.__mro__:
        if name in k.__dict__:
            return k
    return None


class _Looped:
    """The vectorised protocol for a compressor that has only the scalar methods: loops them."""

    def __init__(self, comp: Compressor) -> None:
        self.comp = comp

    def eta_is_v(self, pi, n) -> np.ndarray:
        pi, n = np.broadcast_arrays(np.asarray(pi, dtype=float), np.asarray(n, dtype=float))
        return np.array([self.comp.eta_is_at(a, b) for a, b in zip(pi.tolist(), n.tolist())])

    def eta_vol_v(self, pi, n) -> np.ndarray:
        pi, n = np.broadcast_arrays(np.asarray(pi, dtype=float), np.asarray(n, dtype=float))
        return np.array([self.comp.eta_vol_at(a, b) for a, b in zip(pi.tolist(), n.tolist())])

    def speed_for_flow_v(self, m, rho_suc, pi, n0=None):
        m, rho_suc, pi = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (m, rho_suc, pi)))
        n0 = np.ones(m.shape) if n0 is None else np.broadcast_to(np.asarray(n0, dtype=float), m.shape)
        out = np.full((len(m), 2), np.nan)
        for k, (a, b, c, d) in enumerate(zip(m.tolist(), rho_suc.tolist(), pi.tolist(), n0.tolist())):
            if not all(map(math.isfinite, (a, b, c))):
                continue
            try:
                out[k] = self.comp.speed_for_flow(a, b, c, d if math.isfinite(d) else 1.0)
            except (ValueError, ZeroDivisionError):
                pass
        return out[:, 0], out[:, 1]


def vectorized(comp: Compressor):
    """``comp`` itself when its class provides the vectorised protocol for every scalar method it
    defines (the vectorised method is defined in the same class as the scalar one, or below it);
    otherwise an adapter that loops the scalar methods (a subclass that overrides ``eta_is_at`` but
    inherits ``Compressor.eta_is_v`` would get the base class's polynomial: never used)."""
    cls = type(comp)
    for scalar, vec in _PROTOCOL:
        o_v, o_s = _owner(cls, vec), _owner(cls, scalar)
        if o_v is None or not issubclass(o_v, o_s):
            return _Looped(comp)
    return comp


# --------------------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------------------
@dataclass
class VResult:
    """Outputs of ``solve_many``: ``values[key]`` (or ``result.key``) for every key of
    ``model.batch.OUTPUT_KEYS`` (bar absolute, degC, kW, rpm; booleans for hs_saturated,
    ls_saturated; NaN where a row has no solution), ``status`` and ``reason`` per row (the codes of
    ``model.batch.solve_rows``), ``branch`` ("sp", "hs_max", "hs_min", "" unsolved), ``fallback``
    (rows solved by the scalar path) and their count ``fallback_rows``; ``warm``/``cold`` (rows
    answered on the warm path / the vectorised cold path) and their counts; ``state``: per row, in
    SI, what a later call needs to start from this one (``model.vwarm.STATE_KEYS``: the solution's
    branch, T_m, T_c [K], T_source,out [K] and LS limit, the input point's solution where the LS
    floated, T_c of the branch test at the set point, the inner iterations' last values, the
    row's operating point and set point)."""
    values: dict
    status: np.ndarray
    reason: np.ndarray
    branch: np.ndarray
    fallback: np.ndarray
    timings: dict = field(default_factory=dict)
    state: dict = field(default_factory=dict)
    warm: np.ndarray | None = None
    cold: np.ndarray | None = None

    @property
    def fallback_rows(self) -> int:
        return int(self.fallback.sum())

    @property
    def warm_rows(self) -> int:
        """Rows answered on the warm path (``solve_many(guess=...)``)."""
        return 0 if self.warm is None else int(self.warm.sum())

    @property
    def cold_rows(self) -> int:
        """Rows answered on the vectorised cold path (without a guess, or having left the warm
        path); rows the input checks decide and rows of the scalar path are neither."""
        return 0 if self.cold is None else int(self.cold.sum())

    def __len__(self) -> int:
        return len(self.status)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.values[key]

    def __getattr__(self, key: str):
        values = self.__dict__.get("values")
        if values is not None and key in values:
            return values[key]
        raise AttributeError(key)

    def solved(self) -> np.ndarray:
        """Rows with outputs: 'ok' and the flagged statuses."""
        return among(self.status, ("ok",) + SOLVED_FLAGS)

    def frame(self, columns: tuple[str, ...] = OUTPUT_KEYS, index=None) -> pd.DataFrame:
        """The frame of ``model.batch.frame_of``: ``columns`` (floats, NaN where unsolved; the
        booleans as 1.0/0.0) plus status and reason."""
        return columns_frame(self.columns(columns),
                             index if index is not None else pd.RangeIndex(len(self.status)))

    def columns(self, columns: tuple[str, ...] = OUTPUT_KEYS) -> dict[str, np.ndarray]:
        """``frame``'s columns as arrays (no DataFrame: the optimizer's hot path)."""
        solved = self.solved()
        out = {k: np.where(solved, np.asarray(self.values[k], dtype=float), np.nan) for k in columns}
        out["status"] = np.asarray(self.status, dtype=object)
        out["reason"] = np.asarray(self.reason, dtype=object)
        return out


def columns_frame(cols: dict[str, np.ndarray], index) -> pd.DataFrame:
    """The DataFrame of ``VResult.columns``' arrays (status and reason last). The float columns go
    in as one (columns x rows) block, the block pandas would consolidate a dict of them into (the
    same layout, so reductions over the frame add in the same order), without its copies."""
    keys = [k for k in cols if k not in ("status", "reason")]
    n = len(index)
    block = np.empty((len(keys), n))
    for i, k in enumerate(keys):
        if np.shape(cols[k]) != (n,):       # a row assignment would broadcast what pandas refuses
            raise ValueError(f"column {k!r} has shape {np.shape(cols[k])}, the index {n} rows")
        block[i] = cols[k]
    frame = pd.DataFrame(block.T, index=index, columns=keys, copy=False)
    frame["status"] = cols["status"]
    frame["reason"] = cols["reason"]
    return frame


# --------------------------------------------------------------------------------------------------
# solve
# --------------------------------------------------------------------------------------------------
def _inputs(rows, p_m_sp, amb_bar: float):
    """The rows' input columns as float arrays (rows: a DataFrame or ``model.batch.InputColumns``)."""
    missing = [c for c in INPUT_COLUMNS if c not in rows.columns and not (c == "p_m_sp" and p_m_sp is not None)]
    if missing:
        raise KeyError(f"input columns missing: {', '.join(missing)}")
    n = len(rows)
    if isinstance(rows, InputColumns):      # already floats (arrays the caller does not reuse)
        cols = {c: rows.cols[c] for c in INPUT_COLUMNS if c in rows.cols}
    else:
        cols = {c: rows[c].to_numpy(dtype=float) for c in INPUT_COLUMNS if c in rows.columns}
    if p_m_sp is not None:
        cols["p_m_sp"] = np.broadcast_to(np.asarray(p_m_sp, dtype=float), (n,)).copy()
    return cols


@dataclass(frozen=True)
class WarmStart:
    """Earlier solutions' warm-start state (``VResult.state``: per row, in SI) to start a call from:
    what ``solve_many(guess=...)`` reads of a VResult guess, without its outputs (``n`` rows)."""
    state: dict
    n: int

    def __len__(self) -> int:
        return self.n


def solve_many(rows: "pd.DataFrame | InputColumns", params: PlantParams, p_m_sp=None, ls_mode: str = "flag",
               force_scalar=None, guess: "VResult | None" = None, guess_index=None, R_th_f=None,
               cond_factor=None, deltas: dict | None = None) -> VResult:
    """Solve every row of ``rows`` (canonical input columns ``model.batch.INPUT_COLUMNS``: degC,
    m3/h, bar(g); a DataFrame or ``model.batch.InputColumns``); ``p_m_sp`` [bar(g), scalar or per row] overrides the set-point column. ``ls_mode``
    as in ``model.cycle.solve``: "flag" (an LS speed out of range is a flagged row) or "float" (the
    LS saturates at its speed bound and T_source,out floats). ``force_scalar``: a boolean mask of rows
    to solve with the scalar path regardless (for comparisons). Returns a ``VResult`` with the keys
    of ``model.batch.OUTPUT_KEYS`` and ``EXTRA_KEYS``.

    guess : VResult or WarmStart, optional
        A previous result with a nearby solution of every row (same row order; or ``guess_index``):
        rows start from it on the warm path (``model.vwarm``: Newton on the guessed branch, then the
        scalar solver's branch checks); rows it cannot settle take the cold path. The answers are
        the cold path's (see ``model.vwarm`` for what a warm row is checked against).
    guess_index : int array, optional
        Row i starts from row ``guess_index[i]`` of ``guess`` (-1: cold).
    R_th_f : float or array [K/W], optional
        Per-row evaporator fouling resistance in place of ``params.R_th_f``.
    cond_factor : float or array [-], optional
        Per-row factor on the condenser unit's conductances CF_DSH, CF_con, CF_SC
        (``model.analysis.chain.scale_condenser``). With either, every row is answered as by
        ``solve_many`` with ``params.replace(...)`` of its own values.
    deltas : dict, optional
        Per-row differences to the learned compressor curves (uncertainty draws, ``model.analysis.
        compressors.CompressorLearner.draws``): keys "LS_is", "LS_vol", "HS_is", "HS_vol", each an
        (n, 6) array of scaled-basis coefficients; the stage's compressor must be a
        ``LearnedCompressor``. Row i is answered as with that compressor's ``delta_is``/``delta_vol``
        set to its row (the draws of a window in one call instead of one call per draw).

    The properties are HEOS's (``model.cycletables``) whatever ``params.backend`` says: with a
    tabular backend the scalar solver deviates from HEOS by up to ~1e-5, and so from these answers;
    only the rows that go to the scalar path use the configured backend."""
    if ls_mode not in LS_MODES:
        raise ValueError(f"ls_mode must be one of {', '.join(LS_MODES)}, got {ls_mode!r}")
    n = len(rows)
    per_row = {}
    for name, v in (("R_th_f", R_th_f), ("cond_factor", cond_factor)):
        if v is not None:
            a = np.asarray(v, dtype=float)
            if a.ndim > 1 or (a.ndim == 1 and len(a) != n):
                raise ValueError(f"{name} must be a scalar or one value per row ({n}), got shape {a.shape}")
            if not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite")
            per_row[name] = np.broadcast_to(a, (n,)).copy()
    dl = {}
    for key, v in (deltas or {}).items():
        if key not in DELTA_KEYS:
            raise ValueError(f"deltas: unknown key {key!r} (known: {', '.join(DELTA_KEYS)})")
        if v is None:
            continue
        a = np.asarray(v, dtype=float)
        if a.shape != (n, 6) or not np.all(np.isfinite(a)):
            raise ValueError(f"deltas[{key!r}] must be finite, shape ({n}, 6), got shape {a.shape}")
        comp = params.comp_LS if key.startswith("LS") else params.comp_HS
        if not hasattr(comp, "delta_is"):
            raise ValueError(f"deltas[{key!r}]: the {key[:2]} compressor has no learned curves "
                             f"({type(comp).__name__})")
        dl[key] = a
    gi = None
    if guess is not None:
        if not getattr(guess, "state", None):
            raise ValueError("guess has no warm-start state (give a VResult of solve_many)")
        if guess_index is None:
            if len(guess) != n:
                raise ValueError(f"guess has {len(guess)} rows for {n} rows (give guess_index)")
            gi = np.arange(n)
        else:
            gi = np.asarray(guess_index, dtype=np.intp)
            if gi.shape != (n,) or np.any(gi >= len(guess)) or np.any(gi < -1):
                raise ValueError(f"guess_index must give one row of guess (0..{len(guess) - 1}) or -1 per row")
    elif guess_index is not None:
        raise ValueError("guess_index without guess")
    req = dict(rows=rows, params=params, p_m_sp=p_m_sp, ls_mode=ls_mode, force_scalar=force_scalar,
               guess=guess, gi=gi, R_th_f=per_row.get("R_th_f"), cond_factor=per_row.get("cond_factor"),
               deltas=dl)
    ans = lockstep.request(req)         # under model.lockstep.run: answered with other threads' calls
    return ans if ans is not None else solve_direct(req)


def solve_direct(req: dict) -> VResult:
    """A validated ``solve_many`` call (its keyword arguments, ``guess_index`` resolved to ``gi``)."""
    with np.errstate(all="ignore"):          # failed rows carry NaN through the arrays
        return _solve_many(req["rows"], req["params"], req["p_m_sp"], req["ls_mode"], req["force_scalar"],
                           req["guess"], req["gi"], req["R_th_f"], req["cond_factor"], req["deltas"])


DELTA_KEYS = ("LS_is", "LS_vol", "HS_is", "HS_vol")
# the parameters that may differ between calls answered together (solve_merged): per row in the
# flowsheet; every other field must be equal
PER_ROW_FIELDS = ("comp_LS", "comp_HS", "CF_DSH", "CF_con", "CF_SC", "R_th_f", "CF_dp_f", "extra")


def merge_key(req: dict):
    """Requests (``solve_many``'s keyword arguments, validated) with the same key can be answered
    by one ``solve_merged`` call; None: this one cannot (it is answered alone)."""
    from .analysis.stacked import stackable
    params = req["params"]
    if req.get("force_scalar") is not None or not stackable([params.comp_LS]) \
            or not stackable([params.comp_HS]):
        return None
    shared = tuple((f.name, getattr(params, f.name)) for f in dataclasses.fields(params)
                   if f.name not in PER_ROW_FIELDS)
    comps = tuple(tuple(getattr(getattr(params, st), k) for k in ("N_nom", "N_min", "N_max", "swept_volume"))
                  for st in ("comp_LS", "comp_HS"))
    return req["ls_mode"], shared, comps


# the last merged calls' stacked compressors, newest first: [(the call's parameter pairs,
# {(id(comp_LS), id(comp_HS)): member}, Stacked LS, Stacked HS)] (the compressors are frozen
# dataclasses: the same objects, the same stacks). One: a lockstep of 64 windows' stacks hold
# ~11 MB (4 kept: peak +45 MB in a plant-year replay for 6 fewer builds of 56, ~7 ms)
_STACKED: list = []
STACKED_KEPT = 1


def solve_merged(reqs: list[dict]) -> list[VResult]:
    """Several ``solve_many`` calls (their keyword arguments, validated; one ``merge_key``) in one:
    the rows of all, each with its call's parameters (its own compressors through
    ``model.analysis.stacked.Stacked``, R_th,f, condenser and CF_dp,f factors, curve differences)
    and warm start. Returns each call's VResult. Row by row the operations are those of the
    separate call; what can differ are the decisions the solver takes over all its rows at once
    (how many rows leave the warm path for the scalar solver, when the global-curve speed search
    stops), within the solver's tolerances."""
    from .analysis.stacked import Stacked
    t0 = time.process_time()
    p0 = reqs[0]["params"]
    amb = p0.ambient_pressure / BAR
    cols_l = [_inputs(r["rows"], r.get("p_m_sp"), amb) for r in reqs]
    sizes = [len(r["rows"]) for r in reqs]
    ends = np.cumsum(sizes)
    starts = ends - np.asarray(sizes)
    n = int(ends[-1]) if len(ends) else 0
    cols = {c: np.concatenate([x[c] for x in cols_l]) for c in cols_l[0]}
    pairs, keys, ids = [], [], {}
    for r in reqs:                             # one stacked member per distinct compressor pair
        key = (id(r["params"].comp_LS), id(r["params"].comp_HS))
        if key not in ids:
            ids[key] = len(pairs)
            pairs.append(r["params"])
        keys.append(key)
    kept = list(_STACKED)
    last = next((e for e in kept if all(k in e[1] for k in ids)), None)
    if last is not None:
        # every pair a member of a recent call's stacks (a lockstep's later rounds ask for fewer
        # of its windows): those stacks, each row its pair's member there. A row reads its own
        # member's curves and grid only, so a larger stack gives it the same numbers
        ids, comps = last[1], (last[2], last[3])
    else:
        comps = (Stacked([p.comp_LS for p in pairs]), Stacked([p.comp_HS for p in pairs]))
        # (pairs: the compressors stay alive with their ids)
        _STACKED[:] = [(pairs, ids, *comps)] + kept[:STACKED_KEPT - 1]
    group = np.repeat(np.asarray([ids[k] for k in keys], dtype=np.intp), sizes)

    def per_row(f):
        # each call's value (a number, or one per row) over its rows; numbers alone repeated at once
        vals = [f(r, m) for r, m in zip(reqs, sizes)]
        if all(isinstance(v, (float, int)) and not isinstance(v, bool) for v in vals):
            return np.repeat(np.asarray(vals, dtype=float), sizes)
        return np.concatenate([np.broadcast_to(np.asarray(v, dtype=float), (m,)) for v, m in zip(vals, sizes)])

    R = per_row(lambda r, m: r["params"].R_th_f if r.get("R_th_f") is None else r["R_th_f"])
    cf = np.stack([per_row(lambda r, m, k=k: getattr(r["params"], k) if r.get("cond_factor") is None
                           else getattr(r["params"], k) * r["cond_factor"])
                   for k in ("CF_DSH", "CF_con", "CF_SC")])
    cf_dp = per_row(lambda r, m: r["params"].CF_dp_f)
    keys = sorted({k for r in reqs for k in (r.get("deltas") or {})})
    deltas = {k: np.concatenate([(r.get("deltas") or {}).get(k, np.zeros((m, 6))) for r, m in zip(reqs, sizes)])
              for k in keys}
    parts = [(int(a), int(b), None if r.get("guess") is None else (r["guess"].state, r["gi"]))
             for r, a, b in zip(reqs, starts, ends)]

    def row_params(i):
        j = int(np.searchsorted(ends, i, side="right"))
        r = reqs[j]
        return _row_params(r["params"], r.get("R_th_f"), r.get("cond_factor"), i - int(starts[j]),
                           r.get("deltas") or None)

    with np.errstate(all="ignore"):
        v = _solve_core(t0, cols, n, p0, reqs[0]["ls_mode"], None, R, None, deltas, parts, comps, row_params,
                        group, cf, cf_dp)
    return split_rows(v, starts, ends)


def split_rows(v: VResult, starts, ends) -> list[VResult]:
    """``[take_rows(v, np.arange(a, b)) for a, b in zip(starts, ends)]``: which fields are per-row
    arrays is found once for all the parts, and each part's rows are a copied slice (the same
    arrays as the index's; a merged call splits into one part per request, ~60 of them)."""
    m = len(v)

    def per_row(val) -> bool:
        return isinstance(val, np.ndarray) and val.shape[:1] == (m,)
    plan = []
    for f in dataclasses.fields(v):
        val = getattr(v, f.name)
        if per_row(val):
            plan.append((f.name, 1, val))
        elif isinstance(val, dict):
            plan.append((f.name, 2, [(a, b, per_row(b)) for a, b in val.items()]))
        else:
            plan.append((f.name, 0, val))
    out = []
    for a, b in zip(starts, ends):
        a, b = int(a), int(b)
        kw = {}
        for name, kind, val in plan:
            if kind == 1:
                kw[name] = val[a:b].copy()
            elif kind == 2:
                kw[name] = {k: (x[a:b].copy() if rows else x) for k, x, rows in val}
            else:
                kw[name] = val
        out.append(type(v)(**kw))
    return out


def take_rows(v: VResult, idx: np.ndarray) -> VResult:
    """The rows ``idx`` of a VResult (every per-row array sliced)."""
    m = len(v)
    kw = {}
    for f in dataclasses.fields(v):
        val = getattr(v, f.name)
        if isinstance(val, np.ndarray) and val.shape[:1] == (m,):
            val = val[idx]
        elif isinstance(val, dict):
            val = {a: (b[idx] if isinstance(b, np.ndarray) and b.shape[:1] == (m,) else b)
                   for a, b in val.items()}
        kw[f.name] = val
    return type(v)(**kw)


def _per_row(vals, ms) -> bool:
    """Each of ``vals`` an array whose first axis is its part's rows (``ms``)."""
    return all(isinstance(x, np.ndarray) and x.shape[:1] == (m,) for x, m in zip(vals, ms))


def stack_rows(dicts: list, ms: list) -> dict:
    """Dicts of parts of ``ms`` rows each (a VResult's values or warm-start state) as one: every
    per-row array (in every part) concatenated, anything else the first part's."""
    # (the rule as one loop per key that stops at the first part failing it: ~4,000 calls of ~20-40
    # keys a replay, where the generator expressions cost more than the concatenations)
    nd, out = np.ndarray, {}
    rest = list(zip(dicts[1:], ms[1:]))
    for a, b in dicts[0].items():
        if not (isinstance(b, nd) and b.shape[:1] == (ms[0],)):
            out[a] = b
            continue
        vals = [b]
        for d, m in rest:
            x = d.get(a, _ABSENT)
            if not (isinstance(x, nd) and x.shape[:1] == (m,)):
                break
            vals.append(x)
        else:
            out[a] = np.concatenate(vals)
            continue
        out[a] = b
    return out


_ABSENT = object()


def concat_rows(parts: list) -> VResult:
    """The VResults ``parts`` one after the other (``stack_rows``' rule for every field)."""
    if len(parts) == 1:
        return parts[0]
    ms = [len(v) for v in parts]
    kw = {}
    for f in dataclasses.fields(parts[0]):
        vals = [getattr(v, f.name) for v in parts]
        if isinstance(vals[0], dict):
            kw[f.name] = stack_rows(vals, ms)
        else:
            kw[f.name] = np.concatenate(vals) if _per_row(vals, ms) else vals[0]
    return type(parts[0])(**kw)


def _row_params(params: PlantParams, R_th_f, cond, i: int, deltas: dict | None = None) -> PlantParams:
    """The parameters of row i (``params`` with its own R_th_f, condenser factor and curve
    differences)."""
    kw = {}
    if R_th_f is not None:
        kw["R_th_f"] = float(R_th_f[i])
    if cond is not None:
        k = float(cond[i])
        kw.update(CF_DSH=params.CF_DSH * k, CF_con=params.CF_con * k, CF_SC=params.CF_SC * k)
    for st in ("LS", "HS"):
        d = {f"delta_{c}": tuple(float(x) for x in deltas[f"{st}_{c}"][i])
             for c in ("is", "vol") if deltas and f"{st}_{c}" in deltas}
        if d:
            kw[f"comp_{st}"] = dataclasses.replace(getattr(params, f"comp_{st}"), **d)
    return params.replace(**kw) if kw else params


def _solve_many(rows, params, p_m_sp, ls_mode, force_scalar, guess, gi, R_th_f, cond,
                deltas=None) -> VResult:
    t0 = time.process_time()
    cols = _inputs(rows, p_m_sp, params.ambient_pressure / BAR)
    n = len(rows)
    return _solve_core(t0, cols, n, params, ls_mode, force_scalar, R_th_f, cond, deltas,
                       [(0, n, None if guess is None else (guess.state, gi))],
                       (vectorized(params.comp_LS), vectorized(params.comp_HS)),
                       lambda i: _row_params(params, R_th_f, cond, i, deltas))


def _solve_core(t0, cols, n, params, ls_mode, force_scalar, R_th_f, cond, deltas, parts, comps,
                row_params, group=None, cf=None, cf_dp=None) -> VResult:
    """``_solve_many`` on inputs ``cols`` (SI conversion here) of n rows: ``parts`` (start, end,
    warm) the row ranges of the calls answered together (warm: (guess state, guess_index) or None),
    ``comps`` the flowsheet's (LS, HS) compressors, ``row_params(i)`` row i's parameters for the
    scalar path; ``group``/``cf``/``cf_dp``: per row, the stacked compressors' member, the condenser
    unit's (CF_DSH, CF_con, CF_SC) and CF_dp,f (``solve_merged``)."""
    amb_bar = params.ambient_pressure / BAR
    fluid = get_fluid(params.fluid, params.backend)
    tab = get_cycle_tables(params.fluid)
    status = np.full(n, "", dtype=object)
    reason = np.full(n, "", dtype=object)
    fallback = np.zeros(n, dtype=bool)
    # ---- inputs (SI) and the checks the scalar solver makes before iterating
    fin = np.all([np.isfinite(cols[c]) for c in INPUT_COLUMNS], axis=0) if n else np.zeros(0, bool)
    for i in np.flatnonzero(~fin):
        bad = [c for c in INPUT_COLUMNS if not math.isfinite(cols[c][i])]
        status[i], reason[i] = "bad_input", f"missing or non-finite: {', '.join(bad)}"
    z = lambda a: np.where(fin, a, 1.0)   # noqa: E731  (placeholders in rows already decided)
    T_si, T_so = C_to_K(z(cols["T_source_in"])), C_to_K(np.where(fin, cols["T_source_out"], 0.0))
    T_ki = C_to_K(z(cols["T_sink_in"]))
    V_s, V_k = m3h_to_m3s(z(cols["V_source"])), m3h_to_m3s(z(cols["V_sink"]))
    p_sp = barg_to_Pa(z(cols["p_m_sp"]), amb_bar)
    fs = Flowsheet(params, tab, comps[0], comps[1], T_si, T_so, T_ki, V_s, V_k, R_th_f, cond, deltas, group, cf,
                   cf_dp)
    _precheck(fs, fluid, p_sp, status, reason, fallback)
    if force_scalar is not None:
        fallback |= (status == "") & np.asarray(force_scalar, dtype=bool)
    T_m_sp = tab.T_sat(p_sp)
    fallback |= (status == "") & ~np.isfinite(T_m_sp)
    T_c_max = fluid.sat_p(min(params.p_c_max, fluid.p_crit * 0.98)).T
    todo = np.flatnonzero((status == "") & ~fallback)
    out = Outcome(n)
    ls_limit = np.full(n, "", dtype=object)
    cold = np.zeros(n, dtype=bool)
    ws = None
    if len(todo):
        # the cold path of every row; in "float" mode a row floats as soon as its outcome at the
        # input is final, beside the rows still being solved (model.vtasks)
        on_done = FloatLS(fs, T_m_sp, p_sp, T_c_max, out, ls_limit).task if ls_mode == "float" else None

        def go_cold(r, codes=None, msgs=None):
            """The cold path of rows r (a task); ``codes``/``msgs``: the input point's failure the
            cold branch test has found already ("float" mode goes on from there)."""
            cold[r] = True
            if codes is None:
                return solve_cold(fs, r, T_m_sp, p_sp, T_c_max, out, on_done)
            out.code[r], out.msg[r] = codes, msgs
            return on_done(r)

        tasks = []
        if any(w is not None for _, _, w in parts):
            cand = np.zeros(n, dtype=bool)
            cand[todo] = True
            gs, losts = [], []
            for a, b, w in parts:             # each call's rows from its own guess
                if w is None:
                    gs.append(empty_state(b - a))
                    losts.append(np.zeros(b - a, dtype=bool))
                    continue
                st, gi = w
                g = take_state(st, gi)
                inputs = dict(T_si=T_si[a:b], T_so_in=T_so[a:b], T_ki=T_ki[a:b], V_s=V_s[a:b], V_k=V_k[a:b])
                lost = cand[a:b] & (gi >= 0) & ~usable(g, ls_mode)
                if lost.any():
                    gi = borrow(st, gi, lost, inputs, T_m_sp[a:b], ls_mode)
                    g = take_state(st, gi)
                gs.append(g)
                losts.append(lost)
            g = gs[0] if len(gs) == 1 else {k: np.concatenate([x[k] for x in gs]) for k in gs[0]}
            plan = WarmPlan(n, cand, g, ls_mode, losts[0] if len(losts) == 1 else np.concatenate(losts))
            if len(plan.rows):
                fs.append(plan.extra)
                _seed_memory(fs, plan, g)
                ws = WarmSolve(fs, plan, g, T_m_sp, p_sp, T_c_max, ls_mode)
                tasks.append(ws.task(go_cold))
            todo = np.setdiff1d(todo, plan.rows)
            for a, b, w in parts:
                mine = (todo >= a) & (todo < b)
                if w is not None and np.count_nonzero(mine) <= SCALAR_COLD_MAX:
                    # a few rows of a call with a guess but none themselves: the scalar solver (the
                    # vector cold path costs its rounds, 5-60, whatever its rows)
                    fallback[todo[mine]] = True
                    todo = todo[~mine]
        if len(todo):
            tasks.append(go_cold(todo))
        run(*tasks)
    t1 = t2 = time.process_time()
    ci = np.flatnonzero(cold)             # the cold rows' outcomes, by array tests (every row)
    codes = out.code[ci]
    fb = codes == FALLBACK
    fallback[ci[fb]] = True
    why = ci[(codes != "") & ~fb]
    status[why], reason[why] = out.code[why], out.msg[why]
    warm = np.zeros(n, dtype=bool)
    state = empty_state(n)
    state.update(T_si=T_si, T_so_in=T_so.copy(), T_ki=T_ki, V_s=V_s, V_k=V_k, T_m_sp=T_m_sp)
    values = _empty_values(n)
    solved = np.flatnonzero(cold & (status == "") & ~fallback)
    if len(solved):
        _assemble(fs, solved, solved, out.T_m[solved], out.T_c[solved], out.branch[solved] == HS_MAX,
                  ls_limit[solved] != "", out.flag, out.flag_msg, values, status, reason, fallback, amb_bar)
        _cold_state(fs, solved, out, ls_limit, state)
    branch = np.array(["", "sp", "hs_max", "hs_min"], dtype=object)[np.where(
        cold & (status == "") & ~fallback, out.branch + 1, 0)]
    if ws is not None and ws.scalar.any():
        fallback[ws.rows[ws.scalar]] = True      # the few rows that left the warm path
    if ws is not None and ws.failed.any():
        # rows whose cold branch test (run on the warm path for rows without a usable guess) failed
        f = np.flatnonzero(ws.failed)
        r = ws.rows[f]
        status[r], reason[r], cold[r] = ws.fail_code[f], ws.fail_msg[f], True
    if ws is not None and ws.ok.any():
        pos = np.flatnonzero(ws.ok)
        dst = ws.plan.rows[pos]
        warm[dst] = True
        src, T_m, T_c, br, lim, s = ws.results(pos)
        no_flag = np.full(n, "", dtype=object)
        _assemble(fs, src, dst, T_m, T_c, br == HS_MAX, lim != 0, no_flag, no_flag,
                  values, status, reason, fallback, amb_bar, s=s)
        ws.fill_state(pos, state)
        named = status[dst] == ""               # as on the cold path: flagged rows have no branch name
        branch[dst[named]] = np.array(["sp", "hs_max", "hs_min"], dtype=object)[br[named]]
    t3 = time.process_time()
    for i in np.flatnonzero(fallback):
        branch[i] = _scalar_row(i, cols, row_params(i), fluid, ls_mode, amb_bar, values, status, reason, state)
    status[(status == "")] = "ok"
    timings = {"solve_s": t1 - t0, "assemble_s": t3 - t2, "fallback_s": time.process_time() - t3,
               "warm_rounds": ws.rounds if ws is not None else 0}
    return VResult(values, status, reason, branch, fallback, timings, state, warm, cold & ~fallback)


def _seed_memory(fs: Flowsheet, plan: WarmPlan, g: dict) -> None:
    """The flowsheet's inner warm-start memory (speeds, subcooling) of the warm rows and their copies
    from the guess: the inner iterations start where they ended."""
    idx = np.concatenate([plan.rows, plan.n + np.arange(len(plan.extra))])
    src = np.concatenate([plan.rows, plan.extra])
    for k in ("n_LS", "n_HS", "d_SC", "dT_SC", "phi_HS"):
        v = g[k][src]
        good = np.isfinite(v)
        getattr(fs, k)[idx[good]] = v[good]


def _cold_state(fs: Flowsheet, rows, out: Outcome, ls_limit, state: dict) -> None:
    """The warm-start state of rows solved on the cold path."""
    state["branch"][rows] = out.branch[rows]
    state["T_m"][rows], state["T_c"][rows] = out.T_m[rows], out.T_c[rows]
    state["T_so"][rows] = fs.T_so[rows]
    lim = ls_limit[rows]
    state["ls_limit"][rows] = np.where(lim == "max", 1, np.where(lim == "min", -1, 0))
    fl = lim != ""
    state["in_branch"][rows] = np.where(fl, out.in_branch[rows], out.branch[rows])
    state["in_T_m"][rows] = np.where(fl, out.in_T_m[rows], out.T_m[rows])
    state["in_T_c"][rows] = np.where(fl, out.in_T_c[rows], out.T_c[rows])
    state["T_c_sp"][rows] = out.T_c_sp[rows]
    for k in ("n_LS", "n_HS", "d_SC", "dT_SC", "phi_HS"):
        state[k][rows] = getattr(fs, k)[rows]


def _precheck(fs: Flowsheet, fluid, p_sp, status, reason, fallback) -> None:
    """The checks of ``_Point`` and ``_solve`` before any iteration, in their order (rows that
    pass them all, the usual case, are found at once)."""
    n = len(status)
    dT = fs.T_si[:n] - fs.T_so[:n]
    fine = ((fs.C_s[:n] > 0.0) & (dT > 0.0) & (fs.T_e[:n] > fluid.T_triple + 1.0) & fs.src_ok[:n]
            & (fs.C_w[:n] > 0.0) & (p_sp < fluid.p_crit))
    for i in np.flatnonzero((status == "") & ~fine):
        C, dT = fs.C_s[i], fs.T_si[i] - fs.T_so[i]
        if not (C > 0.0 and dT > 0.0):
            status[i] = "bad_source"
            reason[i] = (f"source must be cooled with positive flow (V_source={fs.V_s[i]:.4g} m3/s, "
                         f"T_in-T_out={dT:.4g} K)")
        elif not fs.T_e[i] > fluid.T_triple + 1.0:
            if math.isfinite(fs.T_e[i]):
                status[i] = "T_e_low"
                reason[i] = (f"evaporating temperature {K_to_C(fs.T_e[i]):.2f} degC is below the "
                             "fluid's range")
            else:
                fallback[i] = True
        elif not fs.src_ok[i]:
            fallback[i] = True                # outside the tables (or above the critical point)
        elif not fs.C_w[i] > 0.0:
            status[i] = "bad_sink"
            reason[i] = f"sink flow must be positive (V_sink={fs.V_k[i]:.4g} m3/s)"
        elif p_sp[i] >= fluid.p_crit:
            status[i], reason[i] = "p_m_sp_high", "p_m set point above the critical pressure"


def _empty_values(n: int) -> dict:
    values = {k: np.full(n, np.nan) for k in OUTPUT_KEYS + EXTRA_KEYS}
    values["hs_saturated"] = np.zeros(n, dtype=bool)
    values["ls_saturated"] = np.zeros(n, dtype=bool)
    return values


def _assemble(fs: Flowsheet, rows, dst, T_m, T_c, hs_sat, ls_sat, flag, flag_msg, values, status, reason,
              fallback, amb_bar, s: dict | None = None) -> None:
    """Every output of ``CycleResult.to_dict`` at the solved (T_m, T_c) of the flowsheet rows
    ``rows`` into the output rows ``dst`` (``s``: the flowsheet's full evaluation there, when known),
    and the limit checks of ``model.cycle._check_limits``; ``flag``/``flag_msg`` (per output row): a
    status the solver set."""
    par, tab = fs.par, fs.tab
    ls_c, hs_c = par.comp_LS, par.comp_HS
    if s is None:
        s = fs.evaluate(rows, T_m, T_c, full=True)
    bad = s["err"] != 0
    th2 = tab.theta_from_h(T_m, s["h2"], s["h_g_m"])
    bad |= ~np.isfinite(th2)
    fallback[dst[bad]] = True                 # not expected: the path solved these points
    m_LS, m_HS = s["m_LS"], s["m_HS"]
    h1, h2, h4, h_g_m = fs.h1[rows], s["h2"], s["h4"], s["h_g_m"]
    if hasattr(fs.ls, "view"):                  # stacked: each row its own compressors' factors
        g = fs.group[rows]
        d_LS, d_HS = fs.ls.drive[g], fs.hs.drive[g]
    else:
        d_LS, d_HS = ls_c.drive_factor, hs_c.drive_factor
    W_LS = m_LS * (h2 - h1) * d_LS
    W_HS = m_HS * (h4 - h_g_m) * d_HS
    cf_dp = fs.cf_dp[rows]
    Q_source = fs.Q_s[rows]
    Q_sink = s["Q_SC"] + s["Q_con"] + s["Q_DSH"]
    C_w = fs.C_w[rows]
    T_sink_out = s["T_w2"] + s["Q_DSH"] / C_w
    T_SC_out, T4 = s["T_SC"], s["T4"]
    T_DSH_out = T4 - s["Q_DSH"] / (m_HS * s["cp_v"])
    T_ki = fs.T_ki[rows]
    pinch = np.minimum.reduce([T_SC_out - T_ki, T_c - s["T_w1"], T_c - s["T_w2"],
                               T_DSH_out - s["T_w2"], T4 - T_sink_out])
    W_shaft = m_LS * (h2 - h1) + m_HS * (h4 - h_g_m)
    N_LS, N_HS = s["n_LS"] * ls_c.N_nom, s["n_HS"] * hs_c.N_nom
    W_total = W_LS + W_HS
    v = {
        "p_e_bar": fs.p_e[rows] / BAR, "p_m_bar": s["p_m"] / BAR, "p_c_bar": s["p_c"] / BAR,
        "p_m_barg": Pa_to_barg(s["p_m"], amb_bar), "T_e_C": K_to_C(fs.T_e[rows]), "T_m_C": K_to_C(T_m),
        "T_c_C": K_to_C(T_c), "N_LS_rpm": N_LS, "N_HS_rpm": N_HS, "Q_sink_kW": Q_sink / 1e3,
        "Q_source_kW": Q_source / 1e3, "W_LS_kW": W_LS / 1e3, "W_HS_kW": W_HS / 1e3,
        "W_total_kW": W_total / 1e3, "COP": Q_sink / W_total, "T_sink_out_C": K_to_C(T_sink_out),
        "eta_is_LS": s["eta_LS"], "eta_is_HS": s["eta_HS"], "eta_vol_LS": s["ev_LS"],
        "eta_vol_HS": s["ev_HS"], "m_LS_kg_s": m_LS, "m_HS_kg_s": m_HS, "subcooling_K": T_c - T_SC_out,
        "pinch_K": pinch, "dp_source_bar": cf_dp * par.dp_clean(fs.V_s[rows]) / BAR,
        "T_dis_LS_C": K_to_C(T_m + th2), "T_dis_HS_C": K_to_C(T4),
        "energy_residual": (Q_source + W_shaft - Q_sink) / Q_sink,
        "hs_saturated": hs_sat, "T_source_out_C": K_to_C(fs.T_so[rows]),
        "ls_saturated": ls_sat,
        "Q_SC_kW": s["Q_SC"] / 1e3, "T_SC_C": K_to_C(T_SC_out), "h_SC_J_kg": s["h_SC"],
        "h_con_out_J_kg": s["h_f_c"], "T_w_SC_out_C": K_to_C(s["T_w1"]),
    }
    keep = ~bad
    for k, a in v.items():
        values[k][dst[keep]] = a[keep]
    tol = LS_SPEED_LOOSE * ls_c.N_nom
    # the rows a status is set for (a solver's flag, or a limit missed), picked with array tests;
    # each of them then as before, in row order (the comparisons are False for NaN either way)
    flagged = flag[dst] != ""
    with np.errstate(invalid="ignore"):
        act = keep & (flagged | (N_LS > ls_c.N_max + tol) | (N_LS < ls_c.N_min - tol) | (pinch < 0.0))
    for j in np.flatnonzero(act):
        i = dst[j]
        if flag[i]:
            status[i], reason[i] = flag[i], flag_msg[i]
        elif N_LS[j] > ls_c.N_max + tol:
            status[i] = "ls_speed_high"
            reason[i] = f"LS compressor speed {N_LS[j]:.0f} rpm above its maximum {ls_c.N_max:.0f} rpm"
        elif N_LS[j] < ls_c.N_min - tol:
            status[i] = "ls_speed_low"
            reason[i] = f"LS compressor speed {N_LS[j]:.0f} rpm below its minimum {ls_c.N_min:.0f} rpm"
        elif pinch[j] < 0.0:
            status[i], reason[i] = "negative_pinch", f"negative pinch {pinch[j]:.3f} K in the condenser unit"


def _scalar_row(i, cols, params, fluid, ls_mode, amb_bar, values, status, reason, state) -> str:
    """Row i by ``model.cycle.solve`` without a guess (the reference), into the outputs and the
    warm-start state; returns the branch of its solution ("" where none)."""
    vals = {c: cols[c][i] for c in INPUT_COLUMNS}
    try:
        res = solve(inputs_from_row(vals, amb_bar), params, fluid=fluid, ls_mode=ls_mode)
        st, why = "ok", ""
    except InfeasibleOperation as exc:
        st, why, res = exc.reason, str(exc), exc.result
    except ModelError as exc:
        st, why, res = exc.reason, str(exc), None
    status[i], reason[i] = ("" if st == "ok" else st), why
    if res is None:
        return ""
    for k, v in result_row(res, params.ambient_pressure).items():
        values[k][i] = v
    sc = res.states["SC_out"]
    extra = {"Q_SC_kW": res.Q_SC / 1e3, "T_SC_C": K_to_C(sc.T), "h_SC_J_kg": sc.h,
             "h_con_out_J_kg": res.states["con_out"].h, "T_w_SC_out_C": K_to_C(res.T_w_SC_out)}
    for k, v in extra.items():
        values[k][i] = v
    state["branch"][i] = ("sp", "hs_max", "hs_min").index(res.branch)
    state["T_m"][i], state["T_c"][i], state["T_so"][i] = res.T_m, res.T_c, res.T_source_out
    state["ls_limit"][i] = {"max": 1, "min": -1}.get(res.ls_limit, 0)
    if not res.ls_limit:                      # the input point of a floating row is not kept
        state["in_branch"][i], state["in_T_m"][i], state["in_T_c"][i] = state["branch"][i], res.T_m, res.T_c
    return res.branch


# --------------------------------------------------------------------------------------------------
# benchmark: hp-edge bench --only vcycle (bench_vcycle, with bench_warm)
# --------------------------------------------------------------------------------------------------
BENCH_COMPARED = ("Q_sink_kW", "W_total_kW", "COP", "p_c_bar", "p_m_bar", "N_LS_rpm", "N_HS_rpm")
BENCH_SET_POINTS = tuple(np.linspace(6.5, 30.5, 25))    # bar(g): the bounded range p_e..p_c at nominal


def bench_rows(n_ops: int) -> pd.DataFrame:
    """n_ops operating points near the nominal point (an optimizer window's representative rows:
    8 fixed ones, more drawn with a fixed seed) times BENCH_SET_POINTS."""
    fixed = [(25, 18, 40, 192, 62), (24, 18, 40, 200, 62), (26, 18, 42, 192, 55), (23, 17.5, 39, 185, 65),
             (25, 18, 44, 210, 60), (24.5, 17.8, 41, 195, 70), (25.5, 18.2, 40.5, 205, 58),
             (24.8, 18, 43, 188, 62)]
    rng = np.random.default_rng(11)
    more = [(rng.uniform(23, 26), rng.uniform(17.5, 18.5), rng.uniform(39, 44), rng.uniform(185, 215),
             rng.uniform(55, 70)) for _ in range(max(n_ops - len(fixed), 0))]
    ops = pd.DataFrame((fixed + more)[:n_ops], columns=list(INPUT_COLUMNS[:5]), dtype=float)
    df = ops.loc[ops.index.repeat(len(BENCH_SET_POINTS))].reset_index(drop=True)
    df["p_m_sp"] = np.tile(BENCH_SET_POINTS, len(ops))
    return df


def bench_sample_rows(n: int = 40) -> pd.DataFrame:
    """n operating points of ``bench_rows`` at one set point each (a window's sample minutes),
    spread over 8.5..22.5 bar(g)."""
    df = bench_rows(n)
    k = len(BENCH_SET_POINTS)
    pick = np.arange(n) * k + 2 + (np.arange(n) * 7) % (k - 10)
    return df.iloc[pick].reset_index(drop=True)


def _best_cpu(f, k: int):
    """(least CPU time [s] of ``k`` calls of ``f``, the last result)."""
    best, res = math.inf, None
    for _ in range(k):
        t0 = time.process_time()
        res = f()
        best = min(best, time.process_time() - t0)
    return best, res


def bench_warm(params: PlantParams, rows: pd.DataFrame, ls_mode: str, repeat: int = 5,
               shift: float = 0.5) -> dict:
    """CPU time [ms] of ``solve_many`` on ``rows`` cold, and warm-started from the same rows solved
    ``shift`` bar lower; how many rows went warm, cold, to the scalar path, and how the warm answers
    compare with the cold ones (statuses, largest relative deviation)."""
    guess = solve_many(rows.assign(p_m_sp=rows["p_m_sp"] - shift), params, ls_mode=ls_mode)
    t_c, cold = _best_cpu(lambda: solve_many(rows, params, ls_mode=ls_mode), max(2, repeat // 2))
    t_w, warm = _best_cpu(lambda: solve_many(rows, params, ls_mode=ls_mode, guess=guess), repeat)
    # the same without the rows that have no solution here or in the guess (their cold paths set
    # the time of a warm call)
    sub = rows[guess.solved() & cold.solved()].reset_index(drop=True)
    g_sub = solve_many(sub.assign(p_m_sp=sub["p_m_sp"] - shift), params, ls_mode=ls_mode)
    t_s, w_sub = _best_cpu(lambda: solve_many(sub, params, ls_mode=ls_mode, guess=g_sub), repeat)
    both = cold.solved() & warm.solved()
    dev = max((float(np.max(np.abs(warm[c][both] - cold[c][both]) / np.abs(cold[c][both])))
               for c in BENCH_COMPARED), default=0.0) if both.any() else 0.0
    return {"rows": len(rows), "cold_cpu_ms": round(t_c * 1e3, 2), "warm_cpu_ms": round(t_w * 1e3, 2),
            "speedup": round(t_c / t_w, 1), "warm_rows": warm.warm_rows, "cold_rows": warm.cold_rows,
            "fallback_rows": warm.fallback_rows, "warm_rounds": warm.timings.get("warm_rounds", 0),
            "status_mismatch_vs_cold": int((warm.status != cold.status).sum()),
            "max_rel_deviation_vs_cold": dev,
            "statuses": {s: int(c) for s, c in zip(*np.unique(warm.status, return_counts=True))},
            "solved_rows_only": {"rows": len(sub), "warm_cpu_ms": round(t_s * 1e3, 2),
                                 "warm_rows": w_sub.warm_rows, "cold_rows": w_sub.cold_rows,
                                 "fallback_rows": w_sub.fallback_rows}}


def bench_vcycle(params: PlantParams, ls_mode: str = "float", ops=(8, 40), repeat: int = 5) -> dict:
    """CPU time [ms] of solve_many against the scalar loop (model.batch.solve_rows, warm-started as
    the optimizer calls it) and the reference (model.cycle.solve row by row without a guess), on
    ``bench_rows(k)`` for each k in ``ops`` (8 -> 200 rows, 40 -> 1000 rows); the largest deviations
    from the reference. Returns a JSON-able dict."""
    from .batch import frame_of, solve_rows
    t = time.process_time()
    get_cycle_tables(params.fluid)
    out = {"ls_mode": ls_mode, "tables_build_cpu_s": round(time.process_time() - t, 3), "cases": []}

    for k in ops:
        df = bench_rows(k)
        solve_many(df.iloc[:5], params, ls_mode=ls_mode)
        t_v, vr = _best_cpu(lambda: solve_many(df, params, ls_mode=ls_mode), repeat)
        t_s, _ = _best_cpu(lambda: solve_rows(df, params, ls_mode=ls_mode), 2 if len(df) <= 200 else 1)
        t0 = time.process_time()
        ref = frame_of([_reference_row(df.iloc[i], params, ls_mode) for i in range(len(df))], params)
        t_c = time.process_time() - t0
        got = vr.frame()
        both = (got["Q_sink_kW"].notna() & ref["Q_sink_kW"].notna()).to_numpy()
        dev = {c: float(np.max(np.abs(got[c] - ref[c]).to_numpy()[both] / np.abs(ref[c]).to_numpy()[both]))
               for c in BENCH_COMPARED} if both.any() else {}
        out["cases"].append({
            "rows": len(df), "operating_points": k, "set_points": len(BENCH_SET_POINTS),
            "vector_cpu_ms": round(t_v * 1e3, 2), "vector_us_per_row": round(t_v * 1e6 / len(df), 1),
            "scalar_solve_rows_cpu_ms": round(t_s * 1e3, 1), "scalar_cold_cpu_ms": round(t_c * 1e3, 1),
            "speedup_vs_solve_rows": round(t_s / t_v, 1), "speedup_vs_cold": round(t_c / t_v, 1),
            "fallback_rows": vr.fallback_rows,
            "status_mismatch_vs_cold": int((got["status"] != ref["status"]).sum()),
            "statuses": {s: int(c) for s, c in zip(*np.unique(vr.status, return_counts=True))},
            "max_rel_deviation_vs_cold": dev,
            "max_abs_deviation_T_source_out_K": float(np.max(np.abs(got["T_source_out_C"] - ref["T_source_out_C"])
                                                             .to_numpy()[both])) if both.any() else math.nan,
            "max_abs_energy_residual": float(np.nanmax(np.abs(got["energy_residual"]))),
        })
    # warm starts: the same rows solved 0.5 bar lower as the guess (bench_warm)
    out["warm"] = [bench_warm(params, bench_sample_rows(40), ls_mode, repeat)]
    out["warm"] += [bench_warm(params, bench_rows(k), ls_mode, repeat) for k in ops]
    out["target"] = {"rows": 200, "vector_cpu_ms": 5.0, "warm_200_rows_cpu_ms": 5.0, "warm_40_rows_cpu_ms": 3.0}
    return out


def _reference_row(row, params: PlantParams, ls_mode: str):
    try:
        return "ok", "", solve(inputs_from_row(row, params.ambient_pressure / BAR), params, ls_mode=ls_mode)
    except InfeasibleOperation as exc:
        return exc.reason, str(exc), exc.result
    except ModelError as exc:
        return exc.reason, str(exc), None
