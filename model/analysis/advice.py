"""Set-point advice that knows how sure it is (issue #8 items 5 and 6).

For one window of usable samples and the adaptive model with the learned compressor curves:

1. the COP-optimal p_m,sp by ``model.optimize.search`` on a few representative operating points of
   the window (``representative_points``), restricted to the intermediate pressures the learned
   curves vouch for (``trusted_stretch``): the stretch of p_m over which at least
   ``min_coverage_share`` of this window's compressor operating points (pi, n) of both stages lie
   in the covered region (plus its margin), found on a set-point grid (the window's check samples
   placed around the representative points, ``spread_at``), widened by ``extrapolation_share`` of
   its length (at most ``extrapolation_max_bar``). A plant that has run over a wide range of p_m has shown the curves'
   slope along it, and the search may go a share of that range further; the learned curves are not
   extrapolated beyond;
2. a dead band: the previous recommendation is kept unless the new optimum is worth more than
   ``dead_band_pct`` of COP over it in this window's conditions (an operator is not asked to chase
   noise);
3. the expected COP and heat-output change against the window's actual set point, on the whole
   window (every sample simulated at both set points; the LS speed limit as a branch, so lost LS
   capacity shows as lost heat);
4. its uncertainty: the standard deviation of the COP change over ``uncertainty_draws`` draws of the
   learned curve coefficients (and of R_th,f) from their covariance, evaluated on the representative
   points;
5. confidence. The advice is *low-confidence* (the block's status bit; the recommendation is then the
   current set point) when the curves are not learned yet, when fewer than ``min_coverage_share`` of the
   window's samples lie in the region the curves had covered before this window, when the learned
   curve misses this window's measured eta_is by more than ``max_curve_residual`` on average, when
   the plant has run over less than ``min_covered_bar`` of p_m in conditions like the window's (at
   one set point the data show no slope along p_m: where the optimum lies would come from the data
   sheet; not when the stretch starts at the HS plateau, the lowest p_m the plant can hold, and the
   optimum lies at least ``BRACKET_BAR`` below its top: the data then bracket it), when the optimum
   lies beyond the trusted stretch (the COP still rises at its end), or when
   the expected gain is not larger than ``confidence_k`` standard deviations — unless both the gain
   and its uncertainty are below the dead band ("keep the set point" is then a confident answer: the
   model is sure that moving is not worth it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import pandas as pd

from .. import batch
from ..batch import INPUT_COLUMNS, among, matrix, numeric
from ..optimize import (SOLVED, Evaluator, OptimizationError, Point, draw_points, groups,
                        representative, search, searches, weighted_mean, window_range, column_max, column_min)
from ..params import PlantParams
from .compressors import STAGES, CompressorLearner


PI_MIN = 1.25      # the search's lowest pressure ratio of either stage [-]
PLATEAU_TOL_BAR = 0.02   # set points whose p_m lies this close to the path's lowest are on the HS plateau
BRACKET_BAR = 1.0        # a covered stretch from the HS plateau brackets an optimum this far below its top
GRID_TOL_BAR = 1e-9      # the trusted path's p_m steps are multiples of its set-point grid (path_step_bar),
                         # and so are min_covered_bar and gap_max_bar as shipped: a stretch of exactly
                         # 3 bar came out 3.0 +- 1.5e-13, and its sign decided the confidence (stop 51)


class AdviceError(ValueError):
    """Settings are invalid; the message names the key."""


@dataclass(frozen=True)
class AdviceSettings:
    """plant.yaml ``advice`` (every key optional; these are the defaults)."""
    representative_points: int = 8      # operating points the search evaluates per window
    check_rows: int = 40                # samples (evenly spaced) of the whole-window check
    uncertainty_draws: int = 8          # curve draws for the uncertainty of the expected gain
    confidence_k: float = 1.0           # the gain must exceed k standard deviations
    min_coverage_share: float = 0.8     # of the window's samples inside the learned region
    max_curve_residual: float = 0.01    # |mean(eta_is measured - curve)| per stage [-]
    dead_band_pct: float = 0.1          # move the recommendation only for more COP than this [%]:
                                        # a kept recommendation costs the plant up to about this
                                        # plus the model's error (0.2 % gave confident regrets of
                                        # 0.4-0.5 % on plants following a daily cycle, 0.05 % moved
                                        # more often for no gain: hp-edge bench --only advice)
    extrapolation_share: float = 0.35   # the search may go beyond the stretch of p_m the plant has
                                        # run over (in this window's conditions) by this share of
                                        # that stretch's length ...
    extrapolation_max_bar: float = 2.5  # ... and never by more than this [bar]
    path_step_bar: float = 0.5          # set-point grid on which that stretch is found [bar]
    gap_max_bar: float = 3.0            # not confident when the optimum lies in or next to (within
                                        # half this) a stretch this wide the plant has not run in
    min_covered_bar: float = 3.0        # confident only when the plant has run over at least this
                                        # stretch of p_m in conditions like the window's [bar]: at
                                        # one set point the data show no slope along p_m, and the
                                        # optimum would be placed by the data sheet's curves
    shape_k: float = 1.0                # the learned curves' shape error where the data are thin,
                                        # one standard deviation: this many times
                                        # CompressorLearner.shape_sd (prior_sd times the share
                                        # of the curve that is still the prior's, and
                                        # extrapolation_sd x d^2 past the covered bins); its COP
                                        # uncertainty is added to the draws' (0: off)
    search_k: float = 2.0               # the search maximises the COP less this many shape-error
                                        # standard deviations (a ~95 % lower bound: of two set
                                        # points with nearly the same COP, the one the data vouch
                                        # for)
    seed: int = 20240301                # uncertainty draws (fixed: the same window, the same answer)

    @classmethod
    def from_dict(cls, d: dict | None) -> "AdviceSettings":
        d = dict(d or {})
        known = {f.name: f for f in fields(cls)}
        kw = {}
        for k, v in d.items():
            if k not in known:
                raise AdviceError(f"key 'advice.{k}': unknown (known: {', '.join(known)})")
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
            if not ok:
                raise AdviceError(f"key 'advice.{k}': expected a number >= 0, got {v!r}")
            kw[k] = int(v) if isinstance(known[k].default, int) else float(v)
        s = cls(**kw)
        if s.representative_points < 1:
            raise AdviceError("key 'advice.representative_points': must be >= 1")
        if not s.path_step_bar >= 0.05:      # the trusted stretch's set-point grid
            raise AdviceError(f"key 'advice.path_step_bar': must be >= 0.05, got {s.path_step_bar:g}")
        if not 0.0 < s.min_coverage_share <= 1.0:     # a share of the samples (also the trusted path's)
            raise AdviceError(f"key 'advice.min_coverage_share': must be > 0 and <= 1, "
                              f"got {s.min_coverage_share:g}")
        return s


@dataclass
class AdviceResult:
    """The advice of one window (set points in bar(g), changes in %)."""
    p_m_sp_rec_barg: float           # the recommendation as written to the block
    confident: bool
    note: str                        # why not confident (or what was decided), plain words
    p_m_sp_actual_barg: float
    p_m_sp_model_opt_barg: float     # the optimum within the trusted region, before the dead band
    p_m_opt_barg: float              # intermediate pressure at the recommendation (window mean)
    p_m_gm_barg: float               # geometric mean sqrt(p_e p_c) (window means)
    dCOP_pct: float                  # at the recommendation vs the actual set point (whole window)
    dCOP_sd_pct: float
    dQ_sink_pct: float
    dCOP_model_opt_pct: float        # at the model optimum vs actual (what following it would give)
    dQ_sink_model_opt_pct: float
    dCOP_gm_pct: float               # recommendation vs the geometric mean
    dQ_sink_gm_pct: float
    COP_actual_model: float
    hs_saturated: bool
    coverage_share: float            # window samples inside the region covered before the window
    curve_residual: dict             # stage -> mean(eta_meas - curve)
    n_samples: int
    n_eval_rows: int
    evaluations: int                 # set points evaluated (with the draft's ``track``, the tracker's too)
    optimizer: str = "search"        # "search" | "surrogate" (the tracker's qualified form)
    trusted: Trusted | None = None
    trusted_lo_barg: float = math.nan   # the p_m stretch the learned curves vouch for (Trusted)
    trusted_hi_barg: float = math.nan


def _operating_points(p: Point, params: PlantParams) -> dict:
    """Per stage the (pi, n) arrays of an evaluation's rows (kept with the point for these
    parameters: the trusted path's points are the search's grid, which the scorer reads again).
    Read them only."""
    got = p.memo.get("operating_points")
    if got is not None and got[0] is params:
        return got[1]
    p_e, p_m, p_c = (p.col(c) for c in ("p_e_bar", "p_m_bar", "p_c_bar"))
    out = {"LS": (p_m / p_e, p.col("N_LS_rpm") / params.comp_LS.N_nom),
           "HS": (p_c / p_m, p.col("N_HS_rpm") / params.comp_HS.N_nom)}
    p.memo["operating_points"] = (params, out)
    return out


def _distances(learner: CompressorLearner, params: PlantParams, offsets: dict, points: list,
               spread: dict | None = None, share: float | None = None,
               w: np.ndarray | None = None) -> list:
    """Per evaluation of ``points`` (all ok): the largest coverage distance (margin units) of its
    rows over the learned stages, offsets applied; 0 inside the covered hull. One
    ``coverage_distance`` call per stage for the rows of all points (it is row by row: the same
    numbers as a call per point). ``spread`` (``sample_spread``): the rows are representative
    points, and the distance is judged on the window's samples placed around them instead.
    ``share``: not the largest over the rows but the distance within which at least that share of
    them lie (``within_share``; a row's distance the larger of its stages'), the rows weighted by
    ``w`` (the points' weights; each placed sample 1): the points' rows must be as many."""
    if not points:
        return []
    d = np.zeros(len(points))
    ops = [_operating_points(p, params) for p in points]
    bounds = np.concatenate([[0], np.cumsum([len(p.col("p_m_bar")) for p in points])])
    rows = None                     # with ``share``: (points, rows), the larger of the stages'
    for st in STAGES:
        if learner.learned(st, "eta_is"):
            d_pi, d_n = offsets.get(st, (0.0, 0.0))
            if spread is not None and st in spread:
                g, r_pi, d_ns, (n_lo, n_hi) = spread[st]
                pi = np.stack([o[st][0] for o in ops])[:, g] * r_pi      # (points, samples)
                n = np.clip(np.stack([o[st][1] for o in ops])[:, g] + d_ns, n_lo, n_hi)
                dist = learner.coverage_distance(st, pi.ravel() - d_pi, n.ravel() - d_n).reshape(pi.shape)
            elif share is not None:
                pi = np.stack([o[st][0] for o in ops])
                n = np.stack([o[st][1] for o in ops])
                dist = learner.coverage_distance(st, pi.ravel() - d_pi, n.ravel() - d_n).reshape(pi.shape)
            else:
                pi = np.concatenate([o[st][0] for o in ops])
                n = np.concatenate([o[st][1] for o in ops])
                dist = learner.coverage_distance(st, pi - d_pi, n - d_n)
                d = np.maximum(d, np.maximum.reduceat(dist, bounds[:-1]))   # each point's rows' largest
                continue
            if share is None:
                d = np.maximum(d, dist.max(axis=1))
            else:
                rows = dist if rows is None else np.maximum(rows, dist)
    if rows is not None:            # each placed sample weighs 1, the points' rows ``w``
        wr = np.ones(rows.shape[1]) if spread is not None or w is None else np.asarray(w, dtype=float)
        d = within_share(rows, wr, share)
    return [float(x) for x in d]


def within_share(dist: np.ndarray, w: np.ndarray, share: float) -> np.ndarray:
    """Per row of ``dist`` (points x rows): the smallest of its distances within which at least
    ``share`` of the weight ``w`` (per column) lies."""
    order = np.argsort(dist, axis=1, kind="stable")
    ds = np.take_along_axis(dist, order, axis=1)
    cw = np.cumsum(w[order], axis=1)
    k = (cw < share * cw[:, -1:] * (1.0 - 1e-12)).sum(axis=1)
    return ds[np.arange(len(ds)), np.minimum(k, ds.shape[1] - 1)]


def sample_spread(rep: Point, samples: Point, parts: list, params: PlantParams) -> dict | None:
    """Where the window's samples lie around their representative points, from both solved at one
    common set point: per stage (group of each sample, its pressure ratio over its group's, its
    speed minus its group's [of the nominal speed]). At a common p_m a sample's LS ratio p_m / p_e
    is its group's times p_e,group / p_e,sample and its HS ratio p_c / p_m its group's times
    p_c,sample / p_c,group, at any set point; its speed offset is the one at this set point (the
    placed speed is held to the compressor's speed range). Not at the samples' own set points: a
    sample just after a set-point step runs at another speed than its group for that reason alone.
    A group's mean lies inside the group: on the means alone the covered stretch came out wider
    than on the samples (0.5 bar, and confident, in 6 of 84 windows of the replay bench's confident
    reference before stop 52). None when every group is one sample (the path then runs on the
    samples themselves)."""
    if all(len(g) == 1 for g in parts):
        return None
    idx = np.concatenate(parts)
    grp = np.concatenate([np.full(len(g), k) for k, g in enumerate(parts)])
    ok = np.ones(len(idx), dtype=bool)
    cols = {}
    for c in ("p_e_bar", "p_c_bar", "N_LS_rpm", "N_HS_rpm"):
        a, b = np.asarray(samples.col(c), dtype=float)[idx], np.asarray(rep.col(c), dtype=float)[grp]
        ok &= np.isfinite(a) & np.isfinite(b)
        cols[c] = (a, b)
    if not ok.any():
        return None
    (pe_s, pe_g), (pc_s, pc_g) = cols["p_e_bar"], cols["p_c_bar"]
    out = {}
    for st, ratio, comp in (("LS", pe_g / pe_s, params.comp_LS), ("HS", pc_s / pc_g, params.comp_HS)):
        n_s, n_g = cols[f"N_{st}_rpm"]
        out[st] = (grp[ok], ratio[ok], (n_s - n_g)[ok] / comp.N_nom,
                   (comp.N_min / comp.N_nom, comp.N_max / comp.N_nom))
    return out


def spread_at(ev: Evaluator, samples: pd.DataFrame, parts: list, params: PlantParams, xs: list,
              actual: float) -> dict | None:
    """``sample_spread`` at the grid set point of ``xs`` nearest the window's ``actual`` set point:
    the representative points (``ev``) are solved there for the path already, and the window's
    ``samples`` (their groups ``parts``) once, in an Evaluator of their own started from the
    representative points' solutions (one more solver call per window; not the advice's
    whole-window Evaluator, whose later warm starts would then come from this set point: a sample
    that solves at the recommended set point from the representative points' solution there may
    not from a solution a bar away — the volumetric curve's domain at the HS speed limit)."""
    grid = [x for x in xs if x is not None]
    if not grid or all(len(g) == 1 for g in parts):
        return None
    x0 = min(grid, key=lambda x: (abs(x - actual), x))
    rep = ev.at(x0)
    if not rep.ok:
        return None
    smp = Evaluator(samples, np.ones(len(samples)), params, ls_mode=ev.ls_mode, guess_from=ev).at(x0)
    return sample_spread(rep, smp, parts, params)


def _pm_barg(p: Point, w: np.ndarray, amb: float) -> float:
    """The intermediate pressure of an evaluation (weighted mean over its rows) [bar(g)] (kept
    with the point for these weights: the search's feasibility test asks again)."""
    got = p.memo.get("pm_barg")
    if got is not None and got[0] is w and got[1] == amb:
        return got[2]
    v = weighted_mean(p.col("p_m_bar"), w) - amb
    p.memo["pm_barg"] = (w, amb, v)
    return v


@dataclass(frozen=True)
class Trusted:
    """The stretch of intermediate pressure the learned curves vouch for in one window's conditions
    [bar(g)]: covered_lo..covered_hi where the plant's compressors have run (at least
    ``min_coverage_share`` of the window's operating points at those p_m lie within the covered
    (pi, n) region plus its margin), widened on both
    sides by ``extension`` (a share of the covered stretch's length, at most a stated maximum): a
    plant that has run over a wide range of p_m has shown the curves' slope, and the search may go
    that much further; a plant that has only run at one p_m has shown no slope and gets almost no
    extension."""
    covered_lo: float
    covered_hi: float
    extension: float
    gaps: tuple = ()                 # ((a, b), ...): stretches inside covered_lo..covered_hi wider
                                     # than gap_max_bar where the plant has not run
    path: tuple = ()                 # ((p_m [bar(g)], coverage distance [margins], set point
                                     # [bar(g)], NaN: the actual ones), ...) by p_m
    closed_below: bool = False       # the covered stretch starts at the lowest p_m the plant can
                                     # hold (the HS plateau: lower set points give the same p_m)

    def gap_near(self, pm: float, reach: float) -> tuple | None:
        """The first wide gap within ``reach`` bar of ``pm``, or None."""
        for a, b in self.gaps:
            if a - reach <= pm <= b + reach:
                return a, b
        return None

    @property
    def lo(self) -> float:
        return self.covered_lo - self.extension

    @property
    def hi(self) -> float:
        return self.covered_hi + self.extension


def trusted_stretch(ev: Evaluator, learner: CompressorLearner | None, params: PlantParams,
                    offsets: dict, lo: float, hi: float, s: AdviceSettings,
                    samples: tuple | None = None) -> Trusted | None:
    """The window's ``Trusted`` stretch, from the evaluator's rows at set points every
    ``path_step_bar`` over [lo, hi] and at the actual set points (None when no compressor curve is
    learned yet, or when no set point puts the window's operating points inside the covered
    region). ``samples``: (the window's samples (canonical inputs), their groups (the evaluator's
    rows are the groups' means), the actual set point [bar(g)]): the path judges the samples placed
    around the means (``spread_at``) instead of the means."""
    if learner is None or not any(learner.learned(st, "eta_is") for st in STAGES):
        return None
    amb = params.ambient_pressure / 1e5
    xs = [None, *(float(x) for x in np.arange(lo, hi + 1e-9, s.path_step_bar))]
    done = [(x, p) for x, p in zip(xs, ev.at_many(xs)) if p.ok]
    spread = spread_at(ev, samples[0], samples[1], params, xs, samples[2]) if samples is not None else None
    dist = _distances(learner, params, offsets, [p for _, p in done], spread,
                      share=s.min_coverage_share, w=ev.w)
    path = [(_pm_barg(p, ev.w, amb), d, math.nan if x is None else float(x))
            for (x, p), d in zip(done, dist)]
    return stretch_from_path(path, s)


def stretch_from_path(path: list, s: AdviceSettings) -> Trusted | None:
    """The ``Trusted`` stretch from the path ((p_m [bar(g)], coverage distance [margins], set point
    [bar(g)]), ...) in any order; None when no point of it is covered."""
    path = sorted(path)
    pm = np.array([x for x, _, _ in path])
    d = np.array([y for _, y, _ in path])
    cov = np.flatnonzero(d <= 1.0)
    if not len(cov):
        return None
    a, b = float(pm[cov[0]]), float(pm[cov[-1]])
    # wide stretches between covered points where the path leaves the covered region
    gaps = tuple((float(pm[i]), float(pm[j])) for i, j in zip(cov[:-1], cov[1:])
                 if j > i + 1 and pm[j] - pm[i] > s.gap_max_bar + GRID_TOL_BAR)
    # the HS plateau: several set points give the lowest p_m of the path, and the plant has run there
    sp = np.array([z for _, _, z in path])
    floor = (pm <= pm[0] + PLATEAU_TOL_BAR) & np.isfinite(sp)
    closed_below = bool(cov[0] == 0 and len(np.unique(sp[floor])) >= 2)
    return Trusted(a, b, min(s.extrapolation_max_bar, s.extrapolation_share * (b - a)), gaps,
                   tuple((round(x, 4), round(y, 3), round(z, 4)) for x, y, z in path), closed_below)


def too_short(trusted: Trusted, pm_opt: float, s: AdviceSettings) -> bool:
    """True when the plant has run over too short a stretch of p_m (less than ``min_covered_bar``)
    for the data to show where the optimum lies; not when the stretch starts at the HS plateau
    (nothing lower can be held) and the optimum's p_m ``pm_opt`` [bar(g)] lies at least
    ``BRACKET_BAR`` below its top: the plant has run on both sides of it. (Lengths on the path's
    set-point grid are compared with ``GRID_TOL_BAR``: rounding does not decide.)"""
    if trusted.covered_hi - trusted.covered_lo >= s.min_covered_bar - GRID_TOL_BAR:
        return False
    return not (trusted.closed_below and pm_opt <= trusted.covered_hi - BRACKET_BAR + 1e-9)


def _feasible(trusted: Trusted | None, w: np.ndarray, amb: float):
    """Candidate filter: every row solves, and the intermediate pressure lies in the trusted stretch
    (None: no restriction)."""
    if trusted is None:
        return None

    def ok(p: Point) -> bool:
        status = p.col("status")
        if not p.status_in(SOLVED).all():
            return False
        if len(status) == len(w):
            pm = _pm_barg(p, w, amb)
        elif len(status) > 1:           # the scalar search's subsample: its plain mean
            pm = float(p.col("p_m_bar").mean()) - amb
        else:                           # the scalar search's one-row probe: solving is all
            return True
        return trusted.lo - 1e-9 <= pm <= trusted.hi + 1e-9
    return ok


def _shape_at(learner, params: PlantParams, offsets: dict, s: AdviceSettings, p: Point) -> float:
    """The COP uncertainty [%] of an evaluation from the learned curves' shape error where the data
    are thin or left behind: per row and stage an eta_is error of ``shape_k`` x
    ``CompressorLearner.shape_sd`` there (prior_sd x the prior's share of the curve, and the
    extrapolation past the covered bins), as a relative error of the stage's work, weighted by
    the stage's share of the work; the stages in quadrature, the rows averaged (one curve: their
    errors go together). 0 without learned curves, with shape_k 0 or where a row is not solved."""
    return _shape_many(learner, params, offsets, s, [p])[0]


def _shape_many(learner, params: PlantParams, offsets: dict, s: AdviceSettings, points: list) -> list:
    """``_shape_at`` of each of ``points``, with one ``shape_sd`` call per stage for the rows of
    all of them (it is row by row: the same numbers as a call per point)."""
    ok = [p for p in points if p.ok]
    if learner is None or not s.shape_k or not ok:
        return [0.0] * len(points)
    ops = [_operating_points(p, params) for p in ok]
    W = {st: np.concatenate([p.col(f"W_{st}_kW") for p in ok]) for st in STAGES}
    tot = W["LS"] + W["HS"]
    var = np.zeros(len(tot))
    for st in STAGES:
        if not learner.learned(st, "eta_is"):
            continue
        pi = np.concatenate([o[st][0] for o in ops])
        n = np.concatenate([o[st][1] for o in ops])
        d_pi, d_n = offsets.get(st, (0.0, 0.0))
        u = s.shape_k * learner.shape_sd(st, pi - d_pi, n - d_n)
        eta = np.concatenate([p.col(f"eta_is_{st}") for p in ok])
        var += (W[st] / tot * u / eta) ** 2
    sd = np.sqrt(var)
    sizes = [len(p.col("W_LS_kW")) for p in ok]
    if len(set(sizes)) == 1:
        # rows of one length: each point's mean as a row of a 2-D array (numpy's reduction over a
        # contiguous last axis adds each row as it adds the same values in a 1-D array of their own)
        means = (100.0 * np.mean(sd.reshape(len(ok), sizes[0]), axis=1)).tolist()
    else:
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        means = [float(100.0 * np.mean(sd[bounds[k]:bounds[k + 1]])) for k in range(len(ok))]
    got = iter(means)
    return [next(got) if p.ok else 0.0 for p in points]


def _scorer(learner, params: PlantParams, offsets: dict, s: AdviceSettings):
    """What the search maximises: the COP less ``search_k`` shape-error standard deviations
    (None: the COP itself). Each point's shape error is computed once (``_shape_many`` of the
    points not met yet: the same numbers as alone) and kept for the scorer's life: the search
    scores its candidates again when it compares them, and the draft its optimum; ``shape(p)``
    hands the kept ``_shape_at`` out."""
    if learner is None or not s.shape_k or not s.search_k:
        return None
    memo: dict = {}         # id(point) -> (point, its shape error): the point is held, its id kept

    def shapes(points: list) -> list:
        new = list({id(p): p for p in points if id(p) not in memo}.values())
        for p, u in zip(new, _shape_many(learner, params, offsets, s, new)):
            memo[id(p)] = (p, u)
        return [memo[id(p)][1] for p in points]

    def score(p: Point) -> float:
        return p.COP * (1.0 - 0.01 * s.search_k * shapes([p])[0])

    def many(points: list) -> list:
        """``score`` of each of ``points``."""
        return [p.COP * (1.0 - 0.01 * s.search_k * u) for p, u in zip(points, shapes(points))]
    score.many = many
    score.shape = lambda p: shapes([p])[0]
    return score


def _with_draw(params: PlantParams, learner: CompressorLearner, draw: dict) -> PlantParams:
    """``params`` with one uncertainty draw of the learned curves (their drive factors kept)."""
    kw = {}
    for st in STAGES:
        if draw.get(st):
            kw[f"comp_{st}"] = learner.compressor(st, delta=draw[st])
    return params.replace(**kw)


@dataclass
class AdviceDraft:
    """The advice of one window up to the dead band (``draft_advice``): everything that does not
    depend on the previous recommendation. Plain data (picklable): replay computes drafts in
    parallel and settles them in window order (``settle_advice``), the gateway does both at once."""
    settings: AdviceSettings
    amb: float                       # ambient pressure [bar]
    data: pd.DataFrame               # the whole-window check rows (canonical inputs)
    rows: pd.DataFrame               # representative points and their weights
    w: np.ndarray
    adaptive: PlantParams
    learner: CompressorLearner | None
    offsets: dict                    # model - measured compressor operating points, per stage
    trusted: Trusted | None          # the p_m stretch the learned curves vouch for
    lo: float                        # set-point range [bar(g)]
    hi: float
    actual: float                    # the window's actual set point (mean) [bar(g)]
    sp_opt: float                    # the model optimum within the trusted region
    hs_saturated_opt: bool
    COP_opt_rep: float               # representative points' COP at sp_opt
    score_opt_rep: float             # ... discounted for the shape error (the dead band's gain)
    ref: Point                       # check rows at the actual set points
    opt: Point                       # check rows at sp_opt
    gm_p: Point                      # check rows at the geometric mean
    gm: float                        # geometric mean sqrt(p_e p_c) [bar a]
    sd_opt: float                    # sd of the expected gain at sp_opt over the curve draws [%]
    draws_ref: list                  # per draw: representative COP at the actual set points (or None)
    R_th_f_se_K_per_kW: float
    reasons: list                    # low-confidence reasons independent of the recommendation
    dcop_step: float                 # COP change of a step to sp_opt [%]
    coverage_share: float
    curve_residual: dict
    evaluations: int
    optimizer: str = "search"        # "search", or "surrogate" when sp_override was taken
    ev: Evaluator | None = None      # the representative rows' Evaluator (its solutions), in this
                                     # process only: not pickled
    tracked: object = None           # with ``track``: the surrogate tracker's search on ``ev`` (its
                                     # (set point, Point), or the exception it raised), likewise

    def __getstate__(self):
        d = dict(self.__dict__)
        d["ev"] = d["tracked"] = None
        return d


def advise(data: pd.DataFrame, adaptive: PlantParams, learner: CompressorLearner | None,
           settings: AdviceSettings, previous_rec_barg: float | None = None,
           coverage_share: float = 1.0, curve_residual: dict | None = None,
           R_th_f_se_K_per_kW: float = 0.0, measured: dict | None = None,
           sp_override: float | None = None) -> AdviceResult:
    """The advice for the window ``data`` (canonical inputs) on the adaptive model ``adaptive``
    (learned curves applied). ``coverage_share`` and ``curve_residual`` come from the chain (they
    need the measured side), and ``measured`` the per-sample compressor operating points
    ({"pi_LS": array, "n_LS": array, ...}, NaN where unknown). ``sp_override``: the optimum from
    elsewhere (the qualified surrogate, bar(g)) in place of the search, used when it solves and lies
    in the trusted region (otherwise the search runs). Raises OptimizationError when nothing can be
    optimised. ``settle_advice(draft_advice(...), previous_rec_barg)``."""
    return settle_advice(draft_advice(data, adaptive, learner, settings, coverage_share, curve_residual,
                                      R_th_f_se_K_per_kW, measured, sp_override), previous_rec_barg)


def _draw_specs(adaptive: PlantParams, learner: CompressorLearner, s: AdviceSettings,
                R_th_f_se_K_per_kW: float) -> list[tuple[dict, float]]:
    """The uncertainty draws of the learned curves (and of R_th,f) from the fixed seed: the same
    window always gives the same draws. [(curve differences per stage, R_th,f [K/W]), ...]."""
    rng = np.random.default_rng(s.seed)
    out = []
    for d in learner.draws(int(s.uncertainty_draws), rng):
        R = adaptive.R_th_f
        if R_th_f_se_K_per_kW and math.isfinite(R_th_f_se_K_per_kW):
            R = max(0.0, R + 1e-3 * R_th_f_se_K_per_kW * float(rng.standard_normal()))
        out.append((d, R))
    return out


def _draw_params(adaptive: PlantParams, learner: CompressorLearner, s: AdviceSettings,
                 R_th_f_se_K_per_kW: float) -> list[PlantParams]:
    """The adaptive model under each uncertainty draw (``_draw_specs``)."""
    out = []
    for d, R in _draw_specs(adaptive, learner, s, R_th_f_se_K_per_kW):
        par = _with_draw(adaptive, learner, d)
        out.append(par.replace(R_th_f=R) if R != par.R_th_f else par)
    return out


_CURVE_KEY = {"eta_is": "is", "eta_vol": "vol"}


def _draws_at(rows: pd.DataFrame, w: np.ndarray, adaptive: PlantParams, learner: CompressorLearner,
              s: AdviceSettings, R_th_f_se_K_per_kW: float, sps: list,
              guess_from: Evaluator | None) -> list[list[Point]]:
    """The representative rows at the set points ``sps`` under each uncertainty draw: out[k][j] as
    ``Evaluator(rows, w, draw k's parameters, guess_from=guess_from).at_many(sps)[j]``. With the
    vectorised solver every draw in one call (``model.optimize.draw_points``)."""
    specs = _draw_specs(adaptive, learner, s, R_th_f_se_K_per_kW)
    if not specs:
        return []
    base = _with_draw(adaptive, learner, specs[0][0])
    keys = {f"{st}_{_CURVE_KEY[c]}": (st, c) for st in STAGES for c in _CURVE_KEY
            if c in (specs[0][0].get(st) or {})}
    learned = all(hasattr(getattr(base, f"comp_{st}"), "delta_is") for st, _ in keys.values())
    if not (batch.VECTORISED and keys and learned):
        return [Evaluator(rows, w, par, guess_from=guess_from).at_many(sps)
                for par in _draw_params(adaptive, learner, s, R_th_f_se_K_per_kW)]
    deltas = {key: np.array([d[st][c] for d, _ in specs], dtype=float) for key, (st, c) in keys.items()}
    return draw_points(rows, w, base, sps, [R for _, R in specs], deltas, guess_from=guess_from)


@dataclass(frozen=True)
class CheckRows:
    """What the advice evaluates of a window (``check_rows``): the actual set point (the mean over
    all its samples, as windows.csv reports it; a window in which the set point changed must not
    get a third value from the check rows), the positions ``keep`` of the evenly spaced samples of
    the whole-window check (all of them when check_rows >= the window's samples), those samples'
    inputs ``data``, their groups ``parts`` and the representative points ``rows`` with weights
    ``w``."""
    actual: float
    keep: np.ndarray
    data: pd.DataFrame
    parts: list
    rows: pd.DataFrame
    w: np.ndarray


def check_rows(data: pd.DataFrame, settings: AdviceSettings) -> CheckRows:
    """The window's ``CheckRows`` (the chain computes them once for the surrogate tracker and the
    advice)."""
    s = settings
    data = numeric(data, INPUT_COLUMNS).reset_index(drop=True)
    actual = float(data["p_m_sp"].mean())
    keep = np.unique(np.linspace(0, len(data) - 1, min(int(s.check_rows), len(data))).round().astype(int))
    data = data.iloc[keep].reset_index(drop=True)
    X = matrix(data)
    parts = groups(data, s.representative_points, X=X)
    rows, w = representative(data, s.representative_points, parts, X=X)
    return CheckRows(actual, keep, data, parts, rows, w)


def draft_advice(data: pd.DataFrame, adaptive: PlantParams, learner: CompressorLearner | None,
                 settings: AdviceSettings, coverage_share: float = 1.0,
                 curve_residual: dict | None = None, R_th_f_se_K_per_kW: float = 0.0,
                 measured: dict | None = None, sp_override: float | None = None,
                 seed: tuple | None = None, checked: CheckRows | None = None,
                 track: float | None = None) -> AdviceDraft:
    """The model optimum of the window and everything about it (see ``advise``) except the dead
    band against the previous recommendation, which ``settle_advice`` applies. ``seed``: (VResult,
    rows) of nearby solutions at the rows' own set points (the chain's condenser factor's) to start
    the representative points from. ``checked``: ``check_rows(data, settings)`` when the caller has
    them. ``track``: the surrogate tracker's reference set point [bar(g)] when this window gives the
    tracker a row: the tracker's search (the model optimum over the same range, without the trusted
    region or the shape score; ``surrogate_tracker.optimum_row``) then runs beside the advice's own
    and the reference set point is solved on the way (``optimize.searches``: one solver call per
    step for both), its result in ``AdviceDraft.tracked``."""
    s = settings
    amb = adaptive.ambient_pressure / 1e5
    c = checked if checked is not None else check_rows(data, s)
    actual, keep, data, parts, rows, w = c.actual, c.keep, c.data, c.parts, c.rows, c.w
    if measured is not None:
        measured = {k: np.asarray(v, dtype=float)[keep] for k, v in measured.items()}
    # the representative points first: the window's samples start from them (vectorised solver)
    ev = Evaluator(rows, w, adaptive, seed=seed)
    ev.at(None)
    full = Evaluator(data, np.ones(len(data)), adaptive, guess_from=ev)
    ref = full.at(None)
    ok = np.isin(ref.col("status"), SOLVED)
    if not ok.any():
        raise OptimizationError("the model solves none of the window's samples at their actual set points")
    if not ok.all():
        data = data.loc[ok].reset_index(drop=True)
        if measured is not None:
            measured = {k: np.asarray(v, dtype=float)[ok] for k, v in measured.items()}
        parts = groups(data, s.representative_points)
        rows, w = representative(data, s.representative_points, parts)
        ev = Evaluator(rows, w, adaptive)
        ev.at(None)
        full = Evaluator(data, np.ones(len(data)), adaptive, guess_from=ev)
        ref = full.at(None)
    ref_p = {c: ref.col(c) for c in ("p_e_bar", "p_c_bar")}    # (the point's columns: no frame)
    lo, hi = window_range(ref_p, amb)
    # the search range: pressure ratios of both stages at least PI_MIN (below that a stage does
    # almost nothing and the other all of the lift: never the optimum, and where the model's
    # trial points fail slowly)
    lo = max(lo, PI_MIN * column_max(ref_p["p_e_bar"]) - amb)
    hi = min(hi, column_min(ref_p["p_c_bar"]) / PI_MIN - amb)
    if not hi > lo:
        raise OptimizationError(f"empty set-point range [{lo:.2f}, {hi:.2f}] bar(g)")
    # the model's offset from the measured compressor operating points at the actual set point
    offsets = {}
    if measured is not None:
        model_pts = _operating_points(ev.at(None), adaptive)
        for st in STAGES:
            pi_m = np.array([np.nanmean(measured[f"pi_{st}"][g]) for g in parts])
            n_m = np.array([np.nanmean(measured[f"n_{st}"][g]) for g in parts])
            pi_x, n_x = model_pts[st]
            d_pi = float(np.nanmean(pi_x - pi_m)) if np.isfinite(pi_m).any() else 0.0
            d_n = float(np.nanmean(n_x - n_m)) if np.isfinite(n_m).any() else 0.0
            offsets[st] = (d_pi if math.isfinite(d_pi) else 0.0, d_n if math.isfinite(d_n) else 0.0)
    trusted = trusted_stretch(ev, learner, adaptive, offsets, lo, hi, s, (data, parts, actual))
    feasible = _feasible(trusted, ev.w, amb)
    score = _scorer(learner, adaptive, offsets, s)
    optimizer, sp_opt, p_opt = "search", None, None
    if sp_override is not None and math.isfinite(sp_override):
        p = ev.at(min(max(float(sp_override), lo), hi))
        if p.ok and (feasible is None or feasible(p)):
            optimizer, sp_opt, p_opt = "surrogate", p.sp, p
            p_opt.beyond = None
            if p.hs_saturated:      # the plateau convention of the search
                p_m = float(np.average(p.col("p_m_bar"), weights=ev.w))
                sp_opt = p_m - amb
    tracked = None
    if sp_opt is None and track is not None and batch.VECTORISED:
        found, tracked = searches(ev, lo, hi, [(feasible, score), (None, None)], extra=[float(track)])
        if isinstance(found, BaseException):
            raise found
        sp_opt, p_opt = found
    elif sp_opt is None:
        sp_opt, p_opt = search(ev, lo, hi, feasible=feasible, score=score)
    p_e, p_c = ref_p["p_e_bar"], ref_p["p_c_bar"]
    gm = math.sqrt(float(p_e.mean()) * float(p_c.mean()))
    opt, gm_p = full.at_many([sp_opt, min(max(gm - amb, lo), hi)])
    if not opt.ok:
        why = opt.frame.loc[~np.isin(opt.frame["status"].to_numpy(), SOLVED), "reason"].astype(str)
        raise OptimizationError(f"the recommended set point {sp_opt:.2f} bar(g) does not solve every "
                                f"sample of the window ({len(why)} of {len(opt.frame)}: {why.iloc[0]})")
    dcop_step = 100.0 * (opt.COP / ref.COP - 1.0)
    # uncertainty of the expected gain at the optimum: draws of the learned curves (and of R_th,f);
    # the draws' COP at the actual set points is kept for a recommendation the dead band keeps
    sd_opt, draws_ref = math.nan, []
    if learner is not None and s.uncertainty_draws >= 2:
        vals = []
        for b, a in _draws_at(rows, w, adaptive, learner, s, R_th_f_se_K_per_kW, [None, sp_opt], ev):
            draws_ref.append(b.COP if b.ok else None)
            if a.ok and b.ok:
                vals.append(100.0 * (a.COP / b.COP - 1.0))
        if len(vals) >= 2:
            sd_opt = float(np.std(vals, ddof=1))
    p_at = ev.at(sp_opt)
    shape_opt = score.shape(p_at) if score is not None else _shape_at(learner, adaptive, offsets, s, p_at)
    sd_opt = math.hypot(sd_opt, shape_opt)
    # low-confidence reasons that do not depend on the recommendation
    resid = dict(curve_residual or {})
    reasons = []
    if learner is None or not all(learner.learned(st, "eta_is") for st in STAGES):
        reasons.append("compressor curves not learned yet from enough operating data")
    if coverage_share < s.min_coverage_share:
        reasons.append(f"operating point outside the region the learned curves cover "
                       f"({100 * coverage_share:.0f} % of the samples inside)")
    for st, r in resid.items():
        if math.isfinite(r) and abs(r) > s.max_curve_residual:
            reasons.append(f"the learned {st} curve misses this window's measured eta_is by {r:+.3f}")
    if learner is not None and trusted is None and not reasons:
        reasons.append("no set point puts this window's compressor operating points inside the "
                       "region the learned curves cover")
    pm_opt = _pm_barg(ev.at(sp_opt), ev.w, amb) if trusted is not None else math.nan
    if trusted is not None and not reasons and too_short(trusted, pm_opt, s):
        reasons.append(f"in conditions like this window's the plant has run over p_m "
                       f"{trusted.covered_lo:.2f}-{trusted.covered_hi:.2f} bar(g) only (less than "
                       f"{s.min_covered_bar:g} bar): the data do not show where the optimum lies; a "
                       f"few days at another set point will")
    if trusted is not None and not reasons:
        gap = trusted.gap_near(pm_opt, 0.5 * s.gap_max_bar)
        if gap is not None:
            reasons.append(f"the plant has not run between p_m {gap[0]:.2f} and {gap[1]:.2f} bar(g) "
                           f"in conditions like this window's, next to the model's optimum "
                           f"{sp_opt:.2f} bar(g): the curves there are interpolated")
    if p_opt.beyond is not None:
        where = (f"{trusted.lo:.2f}-{trusted.hi:.2f} bar(g): run over {trusted.covered_lo:.2f}-"
                 f"{trusted.covered_hi:.2f}, extended by {trusted.extension:.2f}"
                 if trusted is not None else "the learned region")
        reasons.append(f"the model's optimum lies beyond the p_m the learned curves vouch for "
                       f"({where}; a step to {sp_opt:.2f} bar(g) would gain {dcop_step:+.2f} %; "
                       f"operation there teaches the curves the way on)")
    return AdviceDraft(
        settings=s, amb=amb, data=data, rows=rows, w=w, adaptive=adaptive, learner=learner,
        offsets=offsets, trusted=trusted, lo=lo, hi=hi, actual=actual, sp_opt=float(sp_opt),
        hs_saturated_opt=bool(p_opt.hs_saturated), COP_opt_rep=float(p_opt.COP),
        score_opt_rep=float(score(p_opt)) if score is not None else float(p_opt.COP), ref=ref, opt=opt,
        gm_p=gm_p, gm=gm, sd_opt=sd_opt, draws_ref=draws_ref, R_th_f_se_K_per_kW=R_th_f_se_K_per_kW,
        reasons=reasons, dcop_step=dcop_step, coverage_share=float(coverage_share), curve_residual=resid,
        evaluations=ev.evals + full.evals, optimizer=optimizer, ev=ev, tracked=tracked)


def settle_advice(draft: AdviceDraft, previous_rec_barg: float | None = None) -> AdviceResult:
    """The advice from its draft and the previous confident recommendation: the dead band (keep the
    previous recommendation unless the optimum gains more than ``dead_band_pct`` of COP over it in
    this window's conditions), the expected changes at the recommendation and the confidence.
    Model runs happen here only when the dead band keeps the previous recommendation, and never in
    a window whose draft gave reasons for low confidence (its recommendation is the actual set
    point, its uncertainty the model optimum's). ``finish_settling(decide_settling(...))``."""
    return finish_settling(decide_settling(draft, previous_rec_barg))


@dataclass
class Settling:
    """The dead band's decision on one window (``decide_settling``), before the figures at the
    recommendation (``finish_settling``)."""
    draft: AdviceDraft
    sp_rec: float                    # the recommendation [bar(g)]: the model optimum, or the
                                     # previous recommendation kept
    note: str
    held: bool                       # the previous recommendation kept
    evaluations: int
    ev: Evaluator | None             # the representative rows' evaluator of the dead band's test

    @property
    def runs(self) -> bool:
        """``finish_settling`` runs the model (the whole window and the uncertainty draws at a kept
        recommendation); else it only combines the draft's figures. A window whose settling runs
        the model keeps the previous recommendation: whatever its figures, it does not change the
        recommendation the next window's dead band holds to (confident, it recommends that one
        again; not confident, it leaves it as it was)."""
        return self.sp_rec != self.draft.sp_opt


def decide_settling(draft: AdviceDraft, previous_rec_barg: float | None = None) -> Settling:
    """The dead band of ``settle_advice``: keep ``previous_rec_barg`` or take the model optimum
    (one model run on the representative rows at the previous recommendation, when it is in
    range and the draft gave no reasons for low confidence)."""
    d, s = draft, draft.settings
    if d.reasons:
        # the window cannot be confident: its recommendation is the actual set point whatever the
        # dead band would keep, so the previous recommendation is not evaluated (its held value
        # would only have replaced the model optimum's uncertainty by its own, or failed the window
        # where it does not solve every sample)
        previous_rec_barg = None
    sp_opt, lo, hi, amb = d.sp_opt, d.lo, d.hi, d.amb
    sp_rec, note, held = sp_opt, "", False
    evaluations = d.evaluations
    ev = None
    if previous_rec_barg is not None and math.isfinite(previous_rec_barg) and lo <= previous_rec_barg <= hi:
        # rows start from the draft's own solutions at the nearest set point (same rows, same model)
        ev = Evaluator(d.rows, d.w, d.adaptive, guess_from=d.ev)
        p_prev = ev.at(previous_rec_barg)
        feasible = _feasible(d.trusted, d.w, d.amb)
        # held only where the plant has run (the covered stretch): in the extension the curves
        # are extrapolated, and a value held there on a gain below the dead band carries their
        # shape error from window to window
        t = d.trusted
        held_ok = t is None or t.covered_lo - 1e-9 <= _pm_barg(p_prev, d.w, amb) <= t.covered_hi + 1e-9
        if p_prev.ok and held_ok and (feasible is None or feasible(p_prev)):
            score = _scorer(d.learner, d.adaptive, d.offsets, s)
            gain = 100.0 * (d.score_opt_rep / (p_prev.COP if score is None else score(p_prev)) - 1.0)
            if gain < s.dead_band_pct:
                sp_rec, held = previous_rec_barg, True
                note = f"kept the previous recommendation (the optimum gains {gain:.3f} % more)"
        evaluations += ev.evals
    return Settling(d, sp_rec, note, held, evaluations, ev)


def finish_settling(settling: Settling) -> AdviceResult:
    """``settle_advice`` after the dead band's decision: the expected changes at the recommendation
    (a kept one: the whole window and the uncertainty draws run there, ``Settling.runs``) and the
    confidence."""
    st = settling
    d, s = st.draft, st.draft.settings
    sp_opt, amb = d.sp_opt, d.amb
    sp_rec, note, held, evaluations, ev = st.sp_rec, st.note, st.held, st.evaluations, st.ev
    ref, opt = d.ref, d.opt
    if sp_rec == sp_opt:
        rec, sd = opt, d.sd_opt
    else:
        ev = ev or Evaluator(d.rows, d.w, d.adaptive, guess_from=d.ev)
        full = Evaluator(d.data, np.ones(len(d.data)), d.adaptive, guess_from=ev)
        rec = full.at(sp_rec)
        evaluations += full.evals
        if not rec.ok:
            why = rec.frame.loc[~np.isin(rec.frame["status"].to_numpy(), SOLVED), "reason"].astype(str)
            raise OptimizationError(f"the recommended set point {sp_rec:.2f} bar(g) does not solve every "
                                    f"sample of the window ({len(why)} of {len(rec.frame)}: {why.iloc[0]})")
        sd = math.nan
        if d.learner is not None and s.uncertainty_draws >= 2:
            vals = []
            at_rec = _draws_at(d.rows, d.w, d.adaptive, d.learner, s, d.R_th_f_se_K_per_kW, [sp_rec], ev)
            for (a,), b in zip(at_rec, d.draws_ref):
                if a.ok and b is not None:
                    vals.append(100.0 * (a.COP / b - 1.0))
            if len(vals) >= 2:
                sd = float(np.std(vals, ddof=1))
        sd = math.hypot(sd, _shape_at(d.learner, d.adaptive, d.offsets, s, ev.at(sp_rec)))
    dcop = 100.0 * (rec.COP / ref.COP - 1.0)
    dq = 100.0 * (rec.Q_sink_kW / ref.Q_sink_kW - 1.0)
    gm, gm_p = d.gm, d.gm_p
    reasons = list(d.reasons)
    actual = d.actual
    sd_eff = sd if math.isfinite(sd) else math.inf
    if not reasons and not dcop > s.confidence_k * sd_eff:
        if abs(dcop) < s.dead_band_pct and sd_eff < s.dead_band_pct:
            note = note or "at the optimum: moving the set point is not worth it"
        else:
            reasons.append(f"expected gain {dcop:+.2f} % is not larger than its uncertainty "
                           f"({s.confidence_k:g} x {sd:.2f} %)")
    confident = not reasons
    if not confident:
        note = "; ".join(reasons)
    elif abs(dcop) < s.dead_band_pct and sd_eff < s.dead_band_pct and sp_rec != actual and not held:
        # a confident "keep": the recommendation is the current set point (a held previous
        # recommendation stays as it is: the window's mean set point drifts while a closed loop
        # steps toward it, and the recommendation would follow that drift)
        sp_rec, rec, dcop, dq = actual, ref, 0.0, 0.0
    if not confident:
        sp_rec, dcop, dq, rec = actual, 0.0, 0.0, ref
    return AdviceResult(
        p_m_sp_rec_barg=float(sp_rec), confident=confident, note=note,
        p_m_sp_actual_barg=actual, p_m_sp_model_opt_barg=float(sp_opt),
        p_m_opt_barg=float(pd.Series(rec.col("p_m_bar")).mean()) - amb, p_m_gm_barg=gm - amb,
        dCOP_pct=dcop, dCOP_sd_pct=sd, dQ_sink_pct=dq,
        dCOP_model_opt_pct=100.0 * (opt.COP / ref.COP - 1.0),
        dQ_sink_model_opt_pct=100.0 * (opt.Q_sink_kW / ref.Q_sink_kW - 1.0),
        dCOP_gm_pct=100.0 * (rec.COP / gm_p.COP - 1.0) if gm_p.ok else math.nan,
        dQ_sink_gm_pct=100.0 * (rec.Q_sink_kW / gm_p.Q_sink_kW - 1.0) if gm_p.ok else math.nan,
        COP_actual_model=ref.COP, hs_saturated=bool(d.hs_saturated_opt) and sp_rec == sp_opt,
        coverage_share=float(d.coverage_share), curve_residual=dict(d.curve_residual),
        n_samples=len(d.data), n_eval_rows=len(d.rows), evaluations=evaluations, optimizer=d.optimizer,
        trusted=d.trusted,
        trusted_lo_barg=d.trusted.lo if d.trusted is not None else math.nan,
        trusted_hi_barg=d.trusted.hi if d.trusted is not None else math.nan)
