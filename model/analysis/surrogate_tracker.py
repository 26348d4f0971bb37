"""The set-point surrogate fitted from the plant's own optima (issue #8 item 7; SPEC §6 and the
papers' Eq. 12, fitted the papers' way and checked harder).

Every analysis window adds rows: the window's operating point (its representative rows, weighted)
described by the surrogate's inputs (at the reference set point, the adaptive model's
eta_is,LS*eta_is,HS, p_e and p_c; and, for the extended form, the sink flow and return temperature),
and the model optimum's outputs (p_m,opt and the COP change against the reference set point), at the
window's fouling and at the further fouling levels ``extra_fouling_K_per_kW`` (absolute R_th,f), so
the surrogate sees fouling vary beyond what the plant has shown so far. The optimum is the adaptive
model's over the whole set-point range (not limited to the trusted region: the surrogate stands for
the model; the trusted region is applied to its answer as to the search's). Once a form qualifies,
rows are added every ``qualified_every`` windows only, which keeps the check running and saves the
search in between.
Two forms are refitted every ``refit_every`` rows on the rows so far:

- ``basic``: the 27-term product basis of SPEC §6 in the three scaled inputs (``model.surrogate``);
- ``extended``: a full quadratic in the five scaled inputs (21 terms).

Each is judged on a *chronological* held-out split (the newest ``test_share`` of the rows: the
surrogate must predict windows it has not seen, later in time): R^2 on p_m,opt and on dCOP, and the
share of test rows with |p_m,opt error| <= ``pm_tol_bar``. A form *qualifies* when R^2 >=
``min_r2`` on both and that share >= ``min_share`` (issue #8: 0.99, 0.99, 0.3 bar, 95 %); the
gateway's ``optimizer: auto`` then uses the qualified form (the extended one when both do) in place
of the search, and every other part of the advice (the trusted region, the uncertainty, the
confidence) stays as it is.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, fields

import numpy as np
import pandas as pd

from ..optimize import Evaluator, OptimizationError, search, window_range
from ..params import PlantParams

BASIC = ("eta_is_product", "p_e_bar_a", "p_c_bar_a")
EXTENDED = BASIC + ("V_sink_m3h", "T_sink_in_C")
OUTPUTS = ("p_m_opt_bar_a", "dCOP_pct")
FORMS = {"basic": BASIC, "extended": EXTENDED}


class TrackerError(ValueError):
    """Settings or a state document are invalid."""


@dataclass(frozen=True)
class TrackerSettings:
    """plant.yaml ``surrogate_tracker`` (every key optional)."""
    enabled: bool = True
    reference_p_m_sp_barg: float = 10.0
    extra_fouling_K_per_kW: tuple = ()  # further fouling levels per window (absolute R_th,f)
    refit_every: int = 12             # rows between refits
    qualified_every: int = 6          # once qualified: rows from every n-th window only
    max_rows: int = 5000              # oldest rows dropped beyond this
    min_rows: int = 60                # no fit before this many rows
    test_share: float = 0.3
    min_r2: float = 0.99
    pm_tol_bar: float = 0.3
    min_share: float = 0.95

    @classmethod
    def from_dict(cls, d: dict | None) -> "TrackerSettings":
        d = dict(d or {})
        known = {f.name: f for f in fields(cls)}
        kw = {}
        for k, v in d.items():
            if k not in known:
                raise TrackerError(f"key 'surrogate_tracker.{k}': unknown (known: {', '.join(known)})")
            default = known[k].default
            if isinstance(default, bool):
                if not isinstance(v, bool):
                    raise TrackerError(f"key 'surrogate_tracker.{k}': expected true/false, got {v!r}")
            elif isinstance(default, tuple):
                if not (isinstance(v, list) and all(isinstance(x, (int, float)) and
                                                          not isinstance(x, bool) and x >= 0 for x in v)):
                    raise TrackerError(f"key 'surrogate_tracker.{k}': expected a list of numbers >= 0")
                v = tuple(float(x) for x in v)
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise TrackerError(f"key 'surrogate_tracker.{k}': expected a number > 0, got {v!r}")
            kw[k] = type(default)(v) if not isinstance(default, tuple) else v
        return cls(**kw)


def _design(Z: np.ndarray, form: str) -> np.ndarray:
    """Design matrix on scaled inputs: the 27-term product basis (basic) or a full quadratic
    (extended)."""
    if form == "basic":
        cols = []
        pw = [[np.ones(len(Z)), Z[:, d], Z[:, d] ** 2] for d in range(3)]
        for i, j, k in itertools.product(range(3), repeat=3):
            cols.append(pw[0][i] * pw[1][j] * pw[2][k])
        return np.column_stack(cols)
    n = Z.shape[1]
    cols = [np.ones(len(Z))] + [Z[:, d] for d in range(n)]
    cols += [Z[:, a] * Z[:, b] for a in range(n) for b in range(a, n)]
    return np.column_stack(cols)


def _r2(y, yhat) -> float:
    ss = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss if ss > 0 else math.nan


@dataclass
class FormFit:
    form: str
    lo: list
    hi: list
    coef: list                       # per output
    r2: dict = field(default_factory=dict)
    share_within_tol: float = math.nan
    n_train: int = 0
    n_test: int = 0
    qualified: bool = False

    def predict(self, x: dict) -> dict | None:
        """The outputs at inputs ``x`` (names of FORMS[form]); None outside the training ranges."""
        names = FORMS[self.form]
        v = np.array([float(x[k]) for k in names])
        lo, hi = np.array(self.lo), np.array(self.hi)
        if not (np.isfinite(v).all() and (v >= lo).all() and (v <= hi).all()):
            return None
        Z = (2.0 * (v - lo) / (hi - lo) - 1.0)[None, :]
        A = _design(Z, self.form)
        return {o: float((A @ np.array(c))[0]) for o, c in zip(OUTPUTS, self.coef)}


def reference_inputs(rows: pd.DataFrame, w: np.ndarray, params: PlantParams,
                     reference_barg: float, ev: Evaluator | None = None) -> tuple[dict, Evaluator] | None:
    """The surrogate's inputs for evaluation rows (canonical inputs, weights): the model at the
    reference set point, weighted means. None when a row does not solve there. ``ev``: an
    Evaluator of these rows and parameters already at hand (its solutions are reused)."""
    ev = ev if ev is not None else Evaluator(rows, w, params)
    p = ev.at(reference_barg)
    if not p.ok:
        return None
    avg = lambda a: float(np.average(np.asarray(a, dtype=float), weights=ev.w))  # noqa: E731
    x = {"eta_is_product": avg(p.col("eta_is_LS") * p.col("eta_is_HS")),
         "p_e_bar_a": avg(p.col("p_e_bar")), "p_c_bar_a": avg(p.col("p_c_bar")),
         "V_sink_m3h": avg(ev.rows["V_sink"]), "T_sink_in_C": avg(ev.rows["T_sink_in"]),
         "COP_reference": p.COP}
    return x, ev


def optimum_row(rows: pd.DataFrame, w: np.ndarray, params: PlantParams, reference_barg: float,
                t: float, ev: Evaluator | None = None,
                bounds: tuple[float, float] | None = None, searched=None) -> dict | None:
    """One training row: the inputs at the reference set point and the model's optimum over the
    whole set-point range (p_m,opt in bar a, dCOP against the reference in %). None when the model
    cannot answer for these rows. ``ev``: an Evaluator of these rows and parameters at hand (the
    advice's: its solutions are reused), ``bounds``: the set-point range [bar(g)] (default: the
    rows' own, ``window_range``). ``searched``: that search already run on ``ev`` over ``bounds``
    (``advice.draft_advice``'s ``track``: its (set point, Point), or the exception it raised)."""
    r = reference_inputs(rows, w, params, reference_barg, ev)
    if r is None:
        return None
    x, ev = r
    amb = params.ambient_pressure / 1e5
    act = ev.at(None)
    if not act.ok:
        return None
    if searched is not None and bounds is not None:
        if isinstance(searched, OptimizationError):
            return None
        if isinstance(searched, BaseException):
            raise searched
        _, p = searched
    else:
        try:
            lo, hi = bounds if bounds is not None else window_range(act.frame, amb)
            _, p = search(ev, lo, hi)
        except OptimizationError:
            return None
    p_m = float(np.average(p.col("p_m_bar"), weights=ev.w))
    return {**x, "p_m_opt_bar_a": p_m, "dCOP_pct": 100.0 * (p.COP / x["COP_reference"] - 1.0),
            "t": float(t), "R_th_f_K_per_kW": params.R_th_f * 1e3}


class SurrogateTracker:
    """Rows of window optima and the surrogate forms fitted on them."""

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.s = settings or TrackerSettings()
        self.rows: list[dict] = []
        self.fits: dict[str, FormFit] = {}
        self._since = 0
        self._windows = 0             # windows seen since the last rows were taken

    def for_window(self) -> "SurrogateTracker":
        """What a window's pass 2 needs of the tracker (``predict_setpoint``, ``takes_next``): the
        settings, the fits and the window count, without the rows (up to ``max_rows``: a replay
        pickles a copy into every window's task)."""
        t = SurrogateTracker(self.s)
        t.fits, t._since, t._windows = dict(self.fits), self._since, self._windows
        return t

    def takes_next(self) -> bool:
        """Whether the next ``window`` call adds rows (so a caller computes them only then)."""
        return self.s.enabled and (self.qualified is None or self._windows + 1 >= self.s.qualified_every)

    def window(self, rows: pd.DataFrame, w: np.ndarray, params: PlantParams, t: float,
               own: dict | None = None) -> int:
        """Add the rows of one analysis window (evaluation rows ``rows``/``w`` on the adaptive
        model ``params``), unless a form is qualified and this is not an ``qualified_every``-th
        window. ``own``: the window's own-fouling row already computed (``optimum_row`` with the
        advice's Evaluator). Returns the rows added."""
        if not self.s.enabled:
            return 0
        self._windows += 1
        if self.qualified is not None and self._windows < self.s.qualified_every:
            return 0
        self._windows = 0
        new = []
        if own is not None:
            new.append(own)
        else:
            r = optimum_row(rows, w, params, self.s.reference_p_m_sp_barg, t)
            if r is not None:
                new.append(r)
        for R in self.s.extra_fouling_K_per_kW:
            r = optimum_row(rows, w, params.replace(R_th_f=1e-3 * float(R)), self.s.reference_p_m_sp_barg, t)
            if r is not None:
                new.append(r)
        self.add(new)
        return len(new)

    def predict_setpoint(self, rows: pd.DataFrame, w: np.ndarray, params: PlantParams) -> tuple[float, dict] | None:
        """The qualified form's optimum for these rows as a set point [bar(g)] and what it used;
        None when no form is qualified or the inputs lie outside its training ranges."""
        f = self.qualified
        if f is None:
            return None
        r = reference_inputs(rows, w, params, self.s.reference_p_m_sp_barg)
        if r is None:
            return None
        pred = f.predict(r[0])
        if pred is None:
            return None
        amb = params.ambient_pressure / 1e5
        return pred["p_m_opt_bar_a"] - amb, {"form": f.form, **pred}

    def add(self, rows: list[dict]) -> None:
        need = EXTENDED + OUTPUTS
        for r in rows:
            if all(k in r and math.isfinite(float(r[k])) for k in need):
                self.rows.append({k: float(r[k]) for k in need + ("t", "R_th_f_K_per_kW") if k in r})
                self._since += 1
        if len(self.rows) > self.s.max_rows:
            del self.rows[: len(self.rows) - self.s.max_rows]
        if self._since >= self.s.refit_every:
            self.refit()

    def refit(self) -> dict[str, FormFit]:
        """Fit both forms on the rows so far (chronological split); returns the fits."""
        self._since = 0
        n = len(self.rows)
        self.fits = {}
        if n < self.s.min_rows:
            return self.fits
        rows = sorted(self.rows, key=lambda r: r.get("t", 0.0))
        n_test = max(1, int(round(self.s.test_share * n)))
        tr, te = rows[: n - n_test], rows[n - n_test:]
        Y = {o: (np.array([r[o] for r in tr]), np.array([r[o] for r in te])) for o in OUTPUTS}
        for form, names in FORMS.items():
            Xtr = np.array([[r[k] for k in names] for r in tr])
            Xte = np.array([[r[k] for k in names] for r in te])
            lo, hi = Xtr.min(axis=0), Xtr.max(axis=0)
            span = np.where(hi > lo, hi - lo, 1.0)
            Atr = _design(2.0 * (Xtr - lo) / span - 1.0, form)
            Ate = _design(2.0 * (Xte - lo) / span - 1.0, form)
            if len(tr) < 1.5 * Atr.shape[1]:
                continue
            coef, r2 = [], {}
            pred_pm = None
            for o in OUTPUTS:
                c, *_ = np.linalg.lstsq(Atr, Y[o][0], rcond=None)
                coef.append(c.tolist())
                p = Ate @ c
                r2[o] = _r2(Y[o][1], p)
                if o == "p_m_opt_bar_a":
                    pred_pm = p
            share = float(np.mean(np.abs(pred_pm - Y["p_m_opt_bar_a"][1]) <= self.s.pm_tol_bar))
            ok = (all(math.isfinite(v) and v >= self.s.min_r2 for v in r2.values())
                  and share >= self.s.min_share)
            self.fits[form] = FormFit(form, lo.tolist(), (lo + span).tolist(), coef, r2, share,
                                      len(tr), len(te), ok)
        return self.fits

    @property
    def qualified(self) -> FormFit | None:
        """The form the gateway may use (extended preferred), or None."""
        for form in ("extended", "basic"):
            f = self.fits.get(form)
            if f is not None and f.qualified:
                return f
        return None

    def to_dict(self) -> dict:
        return {"format": "hp-edge-surrogate-tracker/1", "rows": self.rows, "since": self._since,
                "windows": self._windows,
                "fits": {k: {**f.__dict__} for k, f in self.fits.items()}}

    def summary(self) -> dict:
        """Rows and the fits' figures (what the replay and the gateway log report)."""
        return {"rows": len(self.rows),
                "qualified": self.qualified.form if self.qualified is not None else None,
                "fits": {k: {"r2": f.r2, "share_within_tol": f.share_within_tol, "n_train": f.n_train,
                             "n_test": f.n_test, "qualified": f.qualified} for k, f in self.fits.items()}}

    @classmethod
    def from_dict(cls, d: dict, settings: TrackerSettings | None = None) -> "SurrogateTracker":
        if not isinstance(d, dict) or d.get("format") != "hp-edge-surrogate-tracker/1":
            raise TrackerError("surrogate tracker state: not a 'hp-edge-surrogate-tracker/1' document")
        obj = cls(settings)
        try:
            obj.rows = [dict(r) for r in d.get("rows", [])]
            obj._since = int(d.get("since", 0))
            obj._windows = int(d.get("windows", 0))
            obj.fits = {k: FormFit(**v) for k, v in (d.get("fits") or {}).items()}
        except (TypeError, ValueError) as exc:
            raise TrackerError(f"surrogate tracker state: {exc}") from exc
        return obj
