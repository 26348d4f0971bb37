"""Calibration of the model's correction factors on a window of measured samples (SPEC §5).

Objective (SPEC §5): F = sum_k w_k * NRMSE_k with NRMSE_k = sqrt(mean((sim - meas)^2)) / mean(meas),
over bounded parameters. F is a weighted sum of *norms*, not a sum of squares, so it is minimised
exactly by iteratively re-weighted least squares (IRLS) around ``scipy.optimize.least_squares``
(trust-region reflective, bounds): each round minimises sum_k a_k * NRMSE_k^2 with the weights
a_k = w_k / NRMSE_k frozen at the previous round's values. At the fixed point the gradient of that
sum equals 2 * grad F, so the rounds converge to a stationary point of F itself; the reported
``objective`` is always F. Rounds stop when F changes by less than ``tolerance`` (relative).

Standard errors and correlations come from a central-difference Jacobian of the residuals at the
solution, each target's residuals divided by that target's RMSE (its noise level as seen by the
model): cov = s^2 (J^T J)^-1. Parameters at a bound are included (flagged). An identifiability
warning names the parameters when two are correlated beyond |r| = ``correlation_limit``, when the
Jacobian is rank-deficient, and also when one is tied to a combination of the others (multiple
correlation beyond the limit) or its standard error exceeds ``SE_RANGE_LIMIT`` of its bound range
(pairwise |r| alone hovers around 0.95 for the condenser factors and misses some windows). With Q_source an input of the model, Q_sink = Q_source + W_total holds in
every solved point, so Q_sink and W_total carry the same information about the condenser factors:
the default initial calibration can determine p_c, not how DSH, condenser and SC share it.

Fast path: p_e depends only on the evaporator (CF_eva, R_th_f) and dp_source only on CF_dp_f, both in
closed form, so a calibration whose targets are only p_e and dp_source (the fouling calibration)
needs no cycle solve: it is vectorised over the window.

Separable path (``_separable``): when, moreover, every parameter is the only one that moves its
target (the fouling calibration: R_th,f moves p_e, CF_dp,f the pressure drop) and there is no change
penalty, F is least where each parameter minimises its own target's sum of squares: CF_dp,f in
closed form (the pressure drop is proportional to it), R_th,f by scipy's bounded Brent (xatol 1e-9
of the scaled range; the method adds 1.5e-8 of the value). The same optimum as the IRLS rounds,
which stop at ``tolerance`` (the fouling windows' R_th,f within 1e-5 of the range of theirs, the
objective never higher), in a quarter of the time: scipy's least-squares machinery around ~50
cheap residuals was most of a fouling calibration.

Parameter values are in configuration units (R_th_f in K/kW); the model uses SI (K/W).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline
from scipy.optimize import least_squares, minimize_scalar

from .batch import INPUT_COLUMNS, SOLVED_WITH_FLAG, InputColumns, numeric, simulate_many
from .fluid import get_fluid
from .params import PlantParams
from .units import BAR, M3H, T0

# parameter name (config) -> (PlantParams field, config unit -> SI factor, unit label)
PARAMETERS = {
    "CF_DSH": ("CF_DSH", 1.0, "-"),
    "CF_con": ("CF_con", 1.0, "-"),
    "CF_SC": ("CF_SC", 1.0, "-"),
    "CF_eva": ("CF_eva", 1.0, "-"),
    "R_th_f_K_per_kW": ("R_th_f", 1e-3, "K/kW"),
    "CF_dp_f": ("CF_dp_f", 1.0, "-"),
}
# target name -> (measured column of model.measured.process, model column of simulate_batch)
TARGETS = {
    "p_e": ("p_e_bar", "p_e_bar"),
    "dp_source": ("dp_source_bar", "dp_source_bar"),
    "Q_sink": ("Q_sink_kW", "Q_sink_kW"),
    "W_total": ("W_total_kW", "W_total_kW"),
    "COP": ("COP", "COP"),
    "p_c": ("p_c_bar", "p_c_bar"),
    "p_m": ("p_m_bar", "p_m_bar"),
}
FAST_TARGETS = ("p_e", "dp_source")
FAST_PARAMETERS = ("CF_eva", "R_th_f_K_per_kW", "CF_dp_f")
# the one target each fast-path parameter moves (``evaporator_outputs``: p_e through UA_eva, the
# source pressure drop through CF_dp_f, in proportion) and whether the target is linear in it
FAST_MOVES = {"CF_eva": ("p_e", False), "R_th_f_K_per_kW": ("p_e", False), "CF_dp_f": ("dp_source", True)}
SEPARABLE = True                  # the separable path (``_separable``); False: IRLS + TRF always
SEPARABLE_XATOL = 1e-9            # scaled-parameter xatol of its bounded Brent (which adds sqrt(eps)*|x|)
STATISTICS = ("nrmse", "rmse")

DEFAULT_TOLERANCE = 1e-5          # SPEC §5
CORRELATION_LIMIT = 0.95          # |r| beyond which two parameters are reported as not separable
RANK_RCOND = 1e-8                 # singular value ratio below which J counts as rank-deficient
SE_RANGE_LIMIT = 0.25             # standard error beyond this share of the bound range: not determined
JAC_STEP = 1e-4                   # central-difference step, share of each parameter's bound range
MAX_ROUNDS = 8                    # IRLS rounds
NRMSE_FLOOR = 1e-9                # keeps IRLS weights finite when a target is fitted exactly
BOUND_EPS = 1e-6                  # share of the range within which a parameter sits "at a bound"
START_NUDGE = 1e-3                # a start on a bound is moved this share of the range inside: TRF
                                  # takes a vanishing first step from a bound and stops on ftol


class CalibrationError(ValueError):
    """The calibration cannot be set up or run (bad configuration, no usable samples, ...)."""


@dataclass(frozen=True)
class Goal:
    """One calibration target: ``target`` a key of TARGETS, ``weight`` >= 0, ``statistic``."""
    target: str
    weight: float
    statistic: str = "nrmse"

    def __post_init__(self):
        if self.target not in TARGETS:
            raise CalibrationError(f"unknown calibration target {self.target!r}; known: {', '.join(TARGETS)}")
        if not (math.isfinite(self.weight) and self.weight >= 0):
            raise CalibrationError(f"target {self.target}: weight must be a number >= 0, got {self.weight!r}")
        if self.statistic not in STATISTICS:
            raise CalibrationError(f"target {self.target}: statistic {self.statistic!r} is not one of "
                                   f"{', '.join(STATISTICS)}")


@dataclass(frozen=True)
class BoundedParam:
    """A calibration parameter in configuration units (R_th_f in K/kW)."""
    name: str
    start: float
    lower: float
    upper: float

    def __post_init__(self):
        if self.name not in PARAMETERS:
            raise CalibrationError(f"unknown calibration parameter {self.name!r}; known: {', '.join(PARAMETERS)}")
        if not (math.isfinite(self.lower) and math.isfinite(self.upper) and self.lower < self.upper):
            raise CalibrationError(f"parameter {self.name}: bounds must be finite with lower < upper, "
                                   f"got [{self.lower!r}, {self.upper!r}]")
        if not self.lower <= self.start <= self.upper:
            raise CalibrationError(f"parameter {self.name}: start {self.start!r} outside its bounds "
                                   f"[{self.lower!r}, {self.upper!r}]")


@dataclass(frozen=True)
class CalibrationSpec:
    """What to calibrate: goals, bounded parameters, tolerance and the rolling change penalty.

    change_penalty : lambda >= 0; adds lambda * sum_i ((theta_i - theta_prev,i) / range_i)^2 to the
        objective when the previous window's parameters are given (rolling use).
    use_flagged_rows : keep samples the model solves outside the LS speed range (SPEC §3).
    """
    kind: str
    goals: tuple[Goal, ...]
    parameters: tuple[BoundedParam, ...]
    tolerance: float = DEFAULT_TOLERANCE
    correlation_limit: float = CORRELATION_LIMIT
    change_penalty: float = 0.0
    use_flagged_rows: bool = True

    def __post_init__(self):
        if not self.goals or not self.parameters:
            raise CalibrationError(f"{self.kind} calibration needs at least one goal and one parameter")
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise CalibrationError(f"{self.kind} calibration: a parameter is listed twice ({', '.join(names)})")
        if sum(g.weight for g in self.goals) <= 0:
            raise CalibrationError(f"{self.kind} calibration: the goal weights sum to zero")

    @property
    def fast(self) -> bool:
        return (all(g.target in FAST_TARGETS for g in self.goals)
                and all(p.name in FAST_PARAMETERS for p in self.parameters))


# SPEC §5 defaults (used when config/plant.yaml has no calibration section)
DEFAULT_SPECS = {
    "initial": CalibrationSpec(
        kind="initial",
        goals=(Goal("Q_sink", 1 / 3), Goal("W_total", 1 / 3), Goal("p_e", 1 / 3)),
        parameters=tuple(BoundedParam(n, 1.0, 0.5, 2.0) for n in ("CF_DSH", "CF_con", "CF_SC", "CF_eva"))),
    "fouling": CalibrationSpec(
        kind="fouling",
        goals=(Goal("p_e", 0.5), Goal("dp_source", 0.5)),
        parameters=(BoundedParam("R_th_f_K_per_kW", 0.0, 0.0, 8e-3), BoundedParam("CF_dp_f", 1.0, 1.0, 3.0))),
}


def spec_from_config(extra: dict, kind: str) -> CalibrationSpec:
    """The ``calibration.<kind>`` section of plant.yaml (``params.extra``) as a CalibrationSpec.

    Missing section -> SPEC §5 defaults. Errors name the key path.
    """
    sec = (extra or {}).get("calibration") or {}
    if not isinstance(sec, dict):
        raise CalibrationError("key 'calibration': expected a mapping")
    default = DEFAULT_SPECS.get(kind)
    node = sec.get(kind)
    if node is None:
        if default is None:
            raise CalibrationError(f"key 'calibration.{kind}': missing and there is no default")
        return default
    base = f"calibration.{kind}"
    if not isinstance(node, dict):
        raise CalibrationError(f"key '{base}': expected a mapping")
    known = {"parameters", "goals", "tolerance", "correlation_limit", "change_penalty",
             "use_flagged_rows", "window_minutes", "window_hours", "min_samples",
             "limits"}   # limits: commissioning plausibility, read by edge/commissioning.py
    for k in node:
        if k not in known:
            raise CalibrationError(f"key '{base}.{k}': unknown (known: {', '.join(sorted(known))})")

    def number(v, path, lo=None):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or \
                not (isinstance(v, float) or abs(v) < 2**1023) or not math.isfinite(v):
            raise CalibrationError(f"key '{path}': expected a number, got {repr(v)[:60]}")
        if lo is not None and v < lo:
            raise CalibrationError(f"key '{path}': must be >= {lo}, got {v!r}")
        return float(v)

    params = default.parameters if default else ()
    if "parameters" in node:
        ps = []
        if not isinstance(node["parameters"], dict) or not node["parameters"]:
            raise CalibrationError(f"key '{base}.parameters': expected a mapping name -> {{start, bounds}}")
        for name, p in node["parameters"].items():
            path = f"{base}.parameters.{name}"
            if not isinstance(p, dict) or set(p) - {"start", "bounds"} or "bounds" not in p:
                raise CalibrationError(f"key '{path}': expected {{start: x, bounds: [lo, hi]}}, got {p!r}")
            b = p["bounds"]
            if not (isinstance(b, (list, tuple)) and len(b) == 2):
                raise CalibrationError(f"key '{path}.bounds': expected [lower, upper], got {b!r}")
            lo, hi = number(b[0], f"{path}.bounds"), number(b[1], f"{path}.bounds")
            start = number(p.get("start", lo), f"{path}.start")
            try:
                ps.append(BoundedParam(str(name), start, lo, hi))
            except CalibrationError as exc:
                raise CalibrationError(f"key '{path}': {exc}") from None
        params = tuple(ps)
    goals = default.goals if default else ()
    if "goals" in node:
        gs = []
        if not isinstance(node["goals"], dict) or not node["goals"]:
            raise CalibrationError(f"key '{base}.goals': expected a mapping target -> {{weight, statistic}}")
        for name, g in node["goals"].items():
            path = f"{base}.goals.{name}"
            if not isinstance(g, dict) or set(g) - {"weight", "statistic"}:
                raise CalibrationError(f"key '{path}': expected {{weight: w, statistic: nrmse}}, got {g!r}")
            try:
                gs.append(Goal(str(name), number(g.get("weight", 1.0), f"{path}.weight", 0.0),
                               str(g.get("statistic", "nrmse"))))
            except CalibrationError as exc:
                raise CalibrationError(f"key '{path}': {exc}") from None
        goals = tuple(gs)
    try:
        return CalibrationSpec(
            kind=kind, goals=goals, parameters=params,
            tolerance=number(node.get("tolerance", DEFAULT_TOLERANCE), f"{base}.tolerance", 1e-12),
            correlation_limit=number(node.get("correlation_limit", CORRELATION_LIMIT),
                                     f"{base}.correlation_limit", 0.0),
            change_penalty=number(node.get("change_penalty", 0.0), f"{base}.change_penalty", 0.0),
            use_flagged_rows=bool(node.get("use_flagged_rows", True)))
    except CalibrationError as exc:
        raise CalibrationError(f"key '{base}': {exc}") from None


# --------------------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------------------
@dataclass
class CalibrationResult:
    """Outcome of one calibration. Parameter values and standard errors in configuration units."""
    kind: str
    params: dict[str, float]
    nrmse: dict[str, float]               # per target (the goal's statistic)
    objective: float                      # sum_k w_k * statistic_k (SPEC §5), without the penalty
    penalty: float
    iterations: int                       # least-squares iterations (Jacobian evaluations), all rounds
    rounds: int                           # IRLS rounds
    model_evaluations: int                # evaluations of the model over the whole window
    run_time_s: float
    std_errors: dict[str, float]          # NaN for parameters at a bound or not identifiable
    correlation: dict[str, dict[str, float]]
    warnings: list[str]
    identifiable: bool
    condition_number: float
    n_samples: int
    n_dropped: dict[str, int]             # samples left out, per reason
    success: bool
    message: str
    start: dict[str, float] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    at_bound: list[str] = field(default_factory=list)
    window_start: str | None = None
    window_end: str | None = None

    def apply(self, params: PlantParams) -> PlantParams:
        """``params`` with the calibrated values (SI inside the model)."""
        return apply_values(params, self.params)

    def to_dict(self) -> dict:
        def clean(v):
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, np.integer)):
                return clean(v.item())
            return v
        return clean({k: getattr(self, k) for k in self.__dataclass_fields__})

    @classmethod
    def from_dict(cls, d: dict) -> "CalibrationResult":
        def unclean(v):
            if v is None:
                return math.nan
            if isinstance(v, dict):
                return {k: unclean(x) for k, x in v.items()}
            return v
        kw = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        for k in ("params", "nrmse", "std_errors", "correlation", "start"):
            if k in kw:
                kw[k] = unclean(kw[k])
        for k in ("objective", "penalty", "condition_number"):
            if k in kw and kw[k] is None:
                kw[k] = math.nan
        if "bounds" in kw:
            kw["bounds"] = {k: tuple(v) for k, v in kw["bounds"].items()}
        missing = [k for k in ("kind", "params") if k not in kw]
        if missing:
            raise CalibrationError(f"calibration state lacks {', '.join(missing)}")
        defaults = dict(nrmse={}, objective=math.nan, penalty=0.0, iterations=0, rounds=0,
                        model_evaluations=0, run_time_s=0.0, std_errors={}, correlation={},
                        warnings=[], identifiable=True, condition_number=math.nan, n_samples=0,
                        n_dropped={}, success=True, message="")
        return cls(**{**defaults, **kw})

    def summary(self) -> str:
        """A few lines a service engineer can read."""
        lines = [f"{self.kind} calibration on {self.n_samples} samples"
                 + (f" ({self.window_start} .. {self.window_end})" if self.window_start else "")
                 + ("" if self.success else f"  FAILED: {self.message}")]
        for name, v in self.params.items():
            unit = PARAMETERS[name][2]
            se = self.std_errors.get(name, math.nan)
            se_txt = f" +- {se:.3g}" if math.isfinite(se) else ""
            flag = "  (at bound)" if name in self.at_bound else ""
            lines.append(f"  {name:<16} {v:.6g}{se_txt} {unit if unit != '-' else ''}{flag}")
        lines.append("  NRMSE: " + ", ".join(f"{k} {100 * v:.3f} %" for k, v in self.nrmse.items()))
        lines.append(f"  objective {self.objective:.6g}, {self.iterations} iterations in {self.rounds} rounds, "
                     f"{self.model_evaluations} model evaluations, {self.run_time_s:.2f} s")
        if self.n_dropped:
            lines.append("  samples left out: " + ", ".join(f"{k}: {v}" for k, v in self.n_dropped.items()))
        for w in self.warnings:
            lines.append(f"  WARNING: {w}")
        return "\n".join(lines)


def apply_values(params: PlantParams, values: dict[str, float]) -> PlantParams:
    """Set calibration parameters given in configuration units (unknown names raise)."""
    kw = {}
    for name, v in values.items():
        if name not in PARAMETERS:
            raise CalibrationError(f"unknown calibration parameter {name!r}")
        fld, factor, _ = PARAMETERS[name]
        kw[fld] = float(v) * factor
    return params.replace(**kw)


def current_values(params: PlantParams, names) -> dict[str, float]:
    return {n: getattr(params, PARAMETERS[n][0]) / PARAMETERS[n][1] for n in names}


# --------------------------------------------------------------------------------------------------
# model evaluation
# --------------------------------------------------------------------------------------------------
class _PsatTable:
    """Vectorised saturation pressure p_sat(T): cubic spline of ln p on a 0.25-K grid of CoolProp
    values (interpolation error < 1e-8 relative; checked in the tests)."""

    def __init__(self, fluid_name: str, backend: str):
        fl = get_fluid(fluid_name, backend)
        lo, hi = math.ceil(fl.T_triple) + 0.5, math.floor(fl.T_crit) - 1.0
        self.T = np.arange(lo, hi, 0.25)
        self.lnp = np.log([fl.sat_T(float(t)).p for t in self.T])
        self.spline = CubicSpline(self.T, self.lnp)
        self.lo, self.hi = self.T[0], self.T[-1]

    def __call__(self, T: np.ndarray) -> np.ndarray:
        T = np.asarray(T, dtype=float)
        out = np.exp(self.spline(np.clip(T, self.lo, self.hi)))
        return np.where((T >= self.lo) & (T <= self.hi), out, np.nan)


_PSAT: dict[tuple[str, str], _PsatTable] = {}


def p_sat(T_K, fluid: str = "Ammonia", backend: str = "HEOS") -> np.ndarray:
    """Saturation pressure [Pa] at temperatures T_K [K], vectorised (NaN outside the table)."""
    key = (fluid, backend)
    if key not in _PSAT:
        _PSAT[key] = _PsatTable(fluid, backend)
    return _PSAT[key](T_K)


EVAPORATOR_INPUTS = ("T_source_in", "T_source_out", "V_source")


def evaporator_outputs(data: pd.DataFrame | dict, params: PlantParams) -> dict[str, np.ndarray]:
    """p_e_bar [bar abs] and dp_source_bar [bar] per row in closed form (no cycle solve).

    data : canonical inputs T_source_in, T_source_out [degC], V_source [m3/h].
    """
    return _evaporator_from(_evaporator_rows(data, params), params)


def _evaporator_rows(data, params: PlantParams) -> tuple:
    """What ``evaporator_outputs`` computes of the rows alone (the water side's temperatures [K],
    capacity flow, the rows it answers, the clean pressure drop): the same for every R_th,f and
    CF_dp,f (a fouling calibration evaluates one window's rows ~20 times)."""
    T_in = np.asarray(data["T_source_in"], dtype=float) + T0
    T_out = np.asarray(data["T_source_out"], dtype=float) + T0
    V = np.asarray(data["V_source"], dtype=float) * M3H
    C = params.cp_w * params.rho_w * V
    with np.errstate(invalid="ignore"):
        ok = (C > 0) & (T_in > T_out)
    return T_in, T_out, C, ok, params.dp_clean(V)


def _evaporator_from(rows: tuple, params: PlantParams) -> dict[str, np.ndarray]:
    """``evaporator_outputs`` of the rows' part ``_evaporator_rows``."""
    T_in, T_out, C, ok, dp_clean = rows
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        e = np.exp(params.UA_eva / C)
        T_e = (T_out * e - T_in) / (e - 1.0)
        p_e = np.where(ok, p_sat(T_e, params.fluid, params.backend), np.nan) / BAR
    dp = params.CF_dp_f * dp_clean / BAR
    return {"p_e_bar": p_e, "dp_source_bar": dp}


def calibration_frame(raw: pd.DataFrame, processed: pd.DataFrame, mask=None) -> pd.DataFrame:
    """Model inputs (canonical columns of ``raw``) beside the measured targets of ``processed``
    (``model.measured.process``), for the usable rows (and ``mask`` when given)."""
    use = processed["usable"].to_numpy(dtype=bool, copy=True)
    if mask is not None:
        use &= np.asarray(mask, dtype=bool)
    inputs = numeric(raw.loc[use], INPUT_COLUMNS)
    meas = processed.loc[use, sorted({m for m, _ in TARGETS.values()} & set(processed.columns))]
    return pd.concat([inputs, meas], axis=1)


class _Problem:
    def __init__(self, data: pd.DataFrame, params: PlantParams, spec: CalibrationSpec):
        self.spec = spec
        self.params = params
        self.names = [p.name for p in spec.parameters]
        self.lo = np.array([p.lower for p in spec.parameters])
        self.hi = np.array([p.upper for p in spec.parameters])
        self.evals = 0
        self.dropped: dict[str, int] = {}
        missing = [c for c in INPUT_COLUMNS if c not in data.columns]
        missing += [TARGETS[g.target][0] for g in spec.goals if TARGETS[g.target][0] not in data.columns]
        if missing:
            raise CalibrationError(f"{spec.kind} calibration: columns missing from the window: "
                                   f"{', '.join(sorted(set(missing)))}")
        cols = list(INPUT_COLUMNS) + sorted({TARGETS[g.target][0] for g in spec.goals})
        d = numeric(data, cols)
        finite = np.isfinite(d.to_numpy(dtype=float)).all(axis=1)
        if (~finite).sum():
            self.dropped["missing value"] = int((~finite).sum())
        self.data = d.loc[finite]
        # self.data's columns as float arrays, and what the residuals derive from them alone (per data)
        self._cols: dict = {}
        self.model_cols = sorted({TARGETS[g.target][1] for g in spec.goals})
        self.last_good: dict[str, np.ndarray] = {}
        # the first model evaluation's solutions (``model.vcycle.VResult``, the rows of self.data):
        # every later evaluation starts each row from its own solution there
        self.seed = None
        self._inputs = None      # self.data's model inputs, read once (InputColumns)
        if len(self.data) == 0:
            raise CalibrationError(f"{spec.kind} calibration: no usable samples in the window")

    def theta(self, x: np.ndarray) -> np.ndarray:
        return self.lo + x * (self.hi - self.lo)

    def col(self, name: str) -> np.ndarray:
        """``self.data[name]`` as floats, converted once per ``self.data`` (the residuals run
        hundreds of times a window on the same rows)."""
        a = self._cols.get(name)
        if a is None:
            a = self._cols[name] = self.data[name].to_numpy(dtype=float)
        return a

    def _mean(self, name: str):
        """``np.mean(self.col(name))``, computed once per ``self.data`` (an NRMSE's normaliser)."""
        m = self._cols.get(("_mean", name))
        if m is None:
            m = self._cols[("_mean", name)] = np.mean(self.col(name))
        return m

    def outputs(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        self.evals += 1
        par = apply_values(self.params, dict(zip(self.names, theta)))
        if self.spec.fast:
            # the rows' part once per rows and water-side parameters (the calibrated ones are not)
            key = (par.cp_w, par.rho_w, tuple(par.dp_clean_coef))
            rows = self._cols.get(("_evaporator", key))
            if rows is None:
                rows = self._cols[("_evaporator", key)] = _evaporator_rows(
                    {c: self.col(c) for c in EVAPORATOR_INPUTS}, par)
            return _evaporator_from(rows, par)
        if self._inputs is None:
            self._inputs = InputColumns.of(self.data)
        # every row warm from its solution at the start values: a few Newton rounds instead of the
        # cold path's 35-60 (stop 45: the replay's initial calibration 1.4 -> 0.55 CPU-s, the
        # factors within 6e-9 relative of the cold-started ones). Always from the same solutions,
        # not the previous evaluation's: the outputs at a theta do not depend on the order of the
        # evaluations, so the finite differences see no start-dependent noise (from the previous
        # evaluation, 0.4 CPU-s, the optimizer stopped short of a bound it reaches cold)
        cols, v = simulate_many(self._inputs, par, columns=tuple(self.model_cols), seed=self.seed,
                                with_result=True, as_columns=True)
        if self.seed is None:
            self.seed = v
        st = np.asarray(cols["status"])
        solved = st == "ok"
        if self.spec.use_flagged_rows:
            solved |= np.isin(st, SOLVED_WITH_FLAG)
        out = {c: np.where(solved, np.asarray(cols[c], dtype=float), np.nan) for c in self.model_cols}
        out["_status"] = st
        return out

    def select_rows(self, out: dict) -> None:
        """Drop the rows the model cannot simulate at the start values (counted per reason)."""
        ok = np.ones(len(self.data), dtype=bool)
        for c in self.model_cols:
            ok &= np.isfinite(out[c])
        if (~ok).any():
            st = out.get("_status")
            reasons = pd.Series(st[~ok] if st is not None else ["model failed"] * int((~ok).sum()))
            for r, k in reasons.value_counts().items():
                key = f"model: {r}"
                self.dropped[key] = self.dropped.get(key, 0) + int(k)
            self.data = self.data.loc[ok]
            self._cols = {}
            self._inputs = None
            if self.seed is not None:
                from .vcycle import take_rows          # (the vectorised solver's module: on first use)
                self.seed = take_rows(self.seed, np.flatnonzero(ok))
            if len(self.data) == 0:
                raise CalibrationError(f"{self.spec.kind} calibration: the model solves none of the samples")
        for g in self.spec.goals:
            meas = self.col(TARGETS[g.target][0])
            if g.statistic == "nrmse" and not np.mean(meas) > 0:
                raise CalibrationError(f"{self.spec.kind} calibration: mean of measured {g.target} is "
                                       f"{np.mean(meas):.4g}; NRMSE needs a positive mean")

    def errors(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        """sim - meas per goal, divided by the goal's normaliser (mean of meas for NRMSE)."""
        out = self.outputs(theta)
        errs = {}
        for g in self.spec.goals:
            mcol, scol = TARGETS[g.target]
            meas = self.col(mcol)
            sim = out[scol]
            bad = ~np.isfinite(sim)
            if bad.any():     # a row the model solved at the start fails here: keep its last value
                prev = self.last_good.get(scol)
                sim = np.where(bad, prev if prev is not None else meas, sim)
            self.last_good[scol] = sim
            norm = self._mean(mcol) if g.statistic == "nrmse" else 1.0
            errs[g.target] = (sim - meas) / norm
        return errs


def _stat(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e * e)))


# --------------------------------------------------------------------------------------------------
# calibration
# --------------------------------------------------------------------------------------------------
def calibrate(data: pd.DataFrame, params: PlantParams, spec: CalibrationSpec,
              previous: dict[str, float] | None = None, window: tuple[str, str] | None = None
              ) -> CalibrationResult:
    """Calibrate ``spec.parameters`` on the samples of ``data``.

    data : one row per sample with the model inputs (INPUT_COLUMNS, canonical units) and the
        measured target columns (see TARGETS; e.g. from ``calibration_frame``).
    params : the model the parameters are set on (e.g. the fixed model for a fouling calibration).
    previous : the previous window's parameter values (config units), for the change penalty.
    """
    t_start = time.perf_counter()
    prob = _Problem(data, params, spec)
    x0 = np.array([(p.start - p.lower) / (p.upper - p.lower) for p in spec.parameters])
    prob.select_rows(prob.outputs(prob.theta(x0)))
    weights = np.array([g.weight for g in spec.goals])
    prev = None
    if previous is not None and spec.change_penalty > 0:
        prev = np.array([(previous[p.name] - p.lower) / (p.upper - p.lower) for p in spec.parameters])

    def stats(x):
        e = prob.errors(prob.theta(x))
        return e, np.array([_stat(e[g.target]) for g in spec.goals])

    def penalty(x):
        return 0.0 if prev is None else float(spec.change_penalty * np.sum((x - prev) ** 2))

    _, s0 = stats(x0)
    F = float(weights @ s0) + penalty(x0)
    x = np.clip(x0, START_NUDGE, 1.0 - START_NUDGE)
    alpha = weights / np.maximum(s0, NRMSE_FLOOR)
    iterations = rounds = 0
    message, success = "", True
    n = len(prob.data)
    pairs = _separable(spec, prev) if SEPARABLE else None
    if pairs is not None:
        x, iterations, success, message = _solve_separable(prob, x, pairs)
        rounds = 1
    else:
        for rounds in range(1, MAX_ROUNDS + 1):
            a = alpha.copy()

            def resid(xx, a=a):
                e = prob.errors(prob.theta(xx))
                parts = [math.sqrt(ak / n) * e[g.target] for ak, g in zip(a, spec.goals)]
                if prev is not None:
                    parts.append(np.sqrt(2.0 * spec.change_penalty) * (xx - prev))
                return np.concatenate(parts)

            sol = least_squares(resid, x, bounds=(0.0, 1.0), method="trf", diff_step=JAC_STEP,
                                ftol=spec.tolerance, xtol=spec.tolerance, gtol=spec.tolerance)
            iterations += int(sol.njev or 0)
            x = np.clip(sol.x, 0.0, 1.0)
            _, s = stats(x)
            F_new = float(weights @ s) + penalty(x)
            if not sol.success:
                success, message = False, sol.message
            alpha = weights / np.maximum(s, NRMSE_FLOOR)
            done = abs(F_new - F) <= spec.tolerance * max(abs(F), 1e-300)
            F = F_new
            if done:
                break
        else:
            message = f"objective still changing after {MAX_ROUNDS} re-weighting rounds"
    e_fin, s_fin = stats(x)
    theta = prob.theta(x)
    ident = _identifiability(prob, x, e_fin, spec)
    pen = penalty(x)
    ts = (str(window[0]), str(window[1])) if window else (None, None)
    return CalibrationResult(
        kind=spec.kind, params=dict(zip(prob.names, map(float, theta))),
        nrmse={g.target: float(v) for g, v in zip(spec.goals, s_fin)},
        objective=float(weights @ s_fin), penalty=pen, iterations=iterations, rounds=rounds,
        model_evaluations=prob.evals, run_time_s=time.perf_counter() - t_start,
        std_errors=ident["std_errors"], correlation=ident["correlation"], warnings=ident["warnings"],
        identifiable=not ident["warnings"], condition_number=ident["condition_number"],
        n_samples=n, n_dropped=prob.dropped, success=success, message=message or "converged",
        start={p.name: p.start for p in spec.parameters},
        bounds={p.name: (p.lower, p.upper) for p in spec.parameters}, at_bound=ident["at_bound"],
        window_start=ts[0], window_end=ts[1])


def _separable(spec: CalibrationSpec, prev) -> list[tuple[int, str, bool]] | None:
    """(parameter index, target, linear) for each parameter when the problem separates: the fast
    path, no change penalty, and every parameter the only one that moves its target (FAST_MOVES),
    which a goal of positive weight scores — the fouling calibration's R_th,f (p_e) and CF_dp,f
    (the source pressure drop). Then sum_k w_k RMSE_k (what the IRLS rounds minimise) is least
    where each parameter minimises its own target's sum of squares alone. None otherwise."""
    if not spec.fast or prev is not None:
        return None
    pairs = [(i, *FAST_MOVES[p.name]) for i, p in enumerate(spec.parameters)]
    targets = [t for _, t, _ in pairs]
    if len(set(targets)) != len(targets):
        return None
    if not all(any(g.target == t and g.weight > 0 for g in spec.goals) for t in targets):
        return None
    return pairs


def _solve_separable(prob: _Problem, x: np.ndarray, pairs) -> tuple[np.ndarray, int, bool, str]:
    """Each parameter of a separable problem (``_separable``) on its own target's sum of squared
    errors over its bound range (scaled 0..1): a target linear in it in closed form (two
    evaluations), else bounded Brent (xatol SEPARABLE_XATOL). Returns (x, iterations, success, message)."""
    x = x.copy()
    iterations, success, messages = 0, True, []

    def sse(i: int, target: str, xi: float) -> float:
        xx = x.copy()
        xx[i] = xi
        e = prob.errors(prob.theta(xx))[target]
        return float(e @ e)

    for i, target, linear in pairs:
        if linear:
            xx = x.copy()
            xx[i] = 0.0
            e0 = prob.errors(prob.theta(xx))[target]
            xx[i] = 1.0
            d = prob.errors(prob.theta(xx))[target] - e0
            dd = float(d @ d)
            x[i] = min(max(-float(e0 @ d) / dd, 0.0), 1.0) if dd > 0 else x[i]
            iterations += 1
            continue
        res = minimize_scalar(lambda v, i=i, t=target: sse(i, t, v), bounds=(0.0, 1.0), method="bounded",
                              options={"xatol": SEPARABLE_XATOL})
        iterations += int(res.nit)
        x[i] = float(res.x)
        if not res.success:
            success = False
            messages.append(f"{prob.names[i]}: {res.message}")
    return x, iterations, success, "; ".join(messages)


def _identifiability(prob: _Problem, x: np.ndarray, e: dict, spec: CalibrationSpec) -> dict:
    """Standard errors, correlations and identifiability warnings from the Jacobian at x."""
    names = prob.names
    k = len(names)
    span = prob.hi - prob.lo
    at_lo = x <= BOUND_EPS
    at_hi = x >= 1.0 - BOUND_EPS
    at_bound = [names[i] for i in range(k) if at_lo[i] or at_hi[i]]
    # all parameters, also those at a bound: the local curvature still says whether the targets can
    # separate them (a parameter that ran to a bound is often one the targets do not determine)
    free = list(range(k))
    # noise level of each target as the model sees it; targets fitted exactly carry no noise estimate
    rmse = {g.target: max(_stat(e[g.target]), NRMSE_FLOOR) for g in spec.goals}
    goals = [g for g in spec.goals if g.weight > 0]
    J = np.zeros((sum(len(e[g.target]) for g in goals), k))
    for i in range(k):
        h = JAC_STEP
        xp, xm = x.copy(), x.copy()
        xp[i] = min(x[i] + h, 1.0)
        xm[i] = max(x[i] - h, 0.0)
        ep, em = prob.errors(prob.theta(xp)), prob.errors(prob.theta(xm))
        d_theta = (xp[i] - xm[i]) * span[i]
        J[:, i] = np.concatenate([(ep[g.target] - em[g.target]) / rmse[g.target] for g in goals]) / d_theta
    prob.errors(prob.theta(x))       # restore last_good to the solution
    std = {n: math.nan for n in names}
    corr = {n: {m: math.nan for m in names} for n in names}
    warnings: list[str] = []
    cond = math.nan
    norms_all = np.linalg.norm(J, axis=0)
    insensitive = [names[i] for i in range(k) if norms_all[i] == 0.0]
    if insensitive:
        # e.g. a DSH that condenses at the bound: no target moves with the factor. Said so here; the
        # other parameters are analysed without it (it would make every covariance singular)
        warnings.append(f"the targets do not depend on {', '.join(insensitive)}: not identifiable")
        free = [i for i in free if norms_all[i] > 0.0]
    if free:
        Jf = J[:, free]
        norms = np.linalg.norm(Jf, axis=0)
        Jn = Jf / norms
        sv = np.linalg.svd(Jn, compute_uv=False)
        cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
        m = J.shape[0]
        s2 = m / max(m - len(free), 1)        # residuals are per-target standardised
        A = Jf.T @ Jf
        rank_def = not (sv[-1] > RANK_RCOND * sv[0])
        if rank_def:
            _, _, Vt = np.linalg.svd(Jn)
            v = Vt[-1]
            involved = [f"{v[j]:+.2f}*{names[free[j]]}" for j in np.argsort(-np.abs(v)) if abs(v[j]) > 0.1]
            warnings.append(f"rank-deficient problem (condition number {cond:.3g}): the targets cannot "
                            f"determine the combination {' '.join(involved)} (scaled parameters)")
            cov = s2 * np.linalg.pinv(A)
        else:
            cov = s2 * np.linalg.inv(A)
        d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        for a, i in enumerate(free):
            std[names[i]] = float(d[a]) if not rank_def else math.nan
            for b, j in enumerate(free):
                r = cov[a, b] / (d[a] * d[b]) if d[a] > 0 and d[b] > 0 else math.nan
                corr[names[i]][names[j]] = float(r)
        for a in range(len(free)):
            for b in range(a + 1, len(free)):
                r = corr[names[free[a]]][names[free[b]]]
                if math.isfinite(r) and abs(r) > spec.correlation_limit:
                    warnings.append(f"{names[free[a]]} and {names[free[b]]} are correlated (r = {r:+.3f}): "
                                    f"the targets cannot separate them")
        if not rank_def:
            named = " ".join(warnings)
            C = np.array([[corr[names[i]][names[j]] for j in free] for i in free])
            try:
                Ci = np.linalg.inv(C)
            except np.linalg.LinAlgError:
                Ci = None
            for a, i in enumerate(free):
                n_i = names[i]
                # a parameter tied to a *combination* of the others (no single pair beyond the limit)
                if Ci is not None and len(free) > 2 and n_i not in named and Ci[a, a] > 0:
                    rho = math.sqrt(max(0.0, 1.0 - 1.0 / Ci[a, a]))
                    if rho > spec.correlation_limit:
                        partners = [names[free[b]] for b in range(len(free))
                                    if b != a and abs(C[a, b]) > 0.3]
                        warnings.append(f"{n_i} is determined only jointly with {', '.join(partners) or 'the others'}"
                                        f" (multiple correlation {rho:.3f})")
                # a parameter the targets hardly constrain within its bounds
                if d[a] > SE_RANGE_LIMIT * span[i]:
                    warnings.append(f"{n_i}: standard error {d[a]:.3g} is {100 * d[a] / span[i]:.0f} % of its "
                                    f"bound range: the targets hardly determine it")
    return dict(std_errors=std, correlation=corr, warnings=warnings, condition_number=cond,
                at_bound=at_bound)


# --------------------------------------------------------------------------------------------------
# state
# --------------------------------------------------------------------------------------------------
def apply_state(params: PlantParams, initial: dict | None = None, dp_clean: dict | None = None,
                fouling: dict | None = None) -> PlantParams:
    """The model after the stored calibrations (dicts as saved by the state files).

    initial, fouling : ``CalibrationResult.to_dict()``; dp_clean : ``DpCleanFit.to_dict()``.
    Without ``fouling`` this is the fixed model; with it, the adaptive model.
    """
    p = params
    if initial is not None:
        p = apply_values(p, initial["params"])
    if dp_clean is not None:
        c = dp_clean["coef_bar"]
        p = p.replace(dp_clean_coef=(c[0] * BAR, c[1] * BAR / M3H, c[2] * BAR / M3H ** 2))
    if fouling is not None:
        p = apply_values(p, fouling["params"])
    return p


def evaporator_share(params: PlantParams) -> float:
    """R_th,f share of the total evaporator thermal resistance [-]."""
    return params.R_th_f / (1.0 / params.UA_eva_clean + params.R_th_f)
