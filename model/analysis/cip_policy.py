"""CIP policies run against a plant over a horizon (issue 10, the policy benchmark), simulator-free.

``run_cip_policy(plant, policy, horizon_days)`` closes the loop: the plant advances in steps and
reports what the gateway would see (window estimates of R_th,f, CIP ends); after each step the
policy says whether to start a CIP now, and the plant starts one when asked. The plant keeps the
true cost (fouling cost rate integrated over its operation + each CIP's cost). Any object with the
``PolicyPlant`` methods can be plugged in: ``ReducedPlant`` here (Kern–Seaton truth, noisy window
estimates, a cost rate that is a function of R_th,f); the simulator in CIP-on-request mode with the
analysis chain producing the estimates is the full benchmark's plant.

Policies: ``FixedInterval(T)`` (a CIP every T days of operation after each reset) and
``ForecastAdvisor`` (hp-edge's advice as the operator would apply it: refit the forecast every few
hours on the window estimates since the last reset, plan the CIP with ``plan_cip``, start it when
the recommended date has come). The advisor learns the removal share from its own CIPs: R before =
the last fit's value at the CIP's start, R after = the next cycle's fitted start level.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import numpy as np

from .cost import (CostCurve, FoulingComponent, RemovalShare, estimate_removal_share,
                   median_interval_days, plan_cip)
from .forecast import FitSettings, ForecastError, fit_fouling, law_prior


@dataclass(frozen=True)
class WindowEstimate:
    """One calibrated window: start and end [day since the run's start], R_th,f and its se [K/kW]."""
    start_days: float
    end_days: float
    R_K_per_kW: float
    R_se_K_per_kW: float

    @property
    def mid_days(self) -> float:
        return 0.5 * (self.start_days + self.end_days)


@dataclass(frozen=True)
class CipEvent:
    """A CIP that ended: start and end (the reset) [day since the run's start]."""
    start_days: float
    end_days: float


class PolicyPlant(Protocol):
    t_days: float                                  # plant time since the run started [day]
    running: bool                                  # False during a CIP

    def advance(self, dt_days: float) -> list: ...   # WindowEstimate / CipEvent finished in the step
    def request_cip(self) -> None: ...
    def total_cost_eur(self) -> float: ...


class CipPolicy(Protocol):
    def observe(self, event) -> None: ...
    def wants_cip(self, t_days: float) -> bool: ...


_GL8 = np.polynomial.legendre.leggauss(8)


# ---- the reduced plant ---------------------------------------------------------------------------------
@dataclass
class ReducedPlant:
    """Kern–Seaton fouling while running, partial CIPs with downtime, noisy window estimates.

    R values in K/kW; cost_curve: f(R) [EUR/day] relative to a clean evaporator; cip_cost_eur per CIP.
    Defaults: the simulator's fouling (config/simulator.yaml) and a noise of 0.05e-3 K/kW per window.
    """
    cost_curve: Callable
    cip_cost_eur: float
    R_initial: float = 2.5e-3
    R_inf: float = 6.0e-3
    tau_days: float = 15.0
    removal_share: float = 0.15
    downtime_days: float = 2.5
    window_hours: float = 2.0
    noise_K_per_kW: float = 0.05e-3
    seed: int = 0
    t_days: float = 0.0
    running: bool = True
    R: float = field(init=False)
    cost_eur: float = field(init=False, default=0.0)
    cips: list = field(init=False, default_factory=list)
    truth: list = field(init=False, default_factory=list)    # (t_days, true R) at each window end
    _cip_end: float = field(init=False, default=math.inf)
    _cip_start: float = field(init=False, default=math.nan)
    _win_start: float = field(init=False, default=0.0)
    _win_acc: float = field(init=False, default=0.0)          # integral of R over the open window
    _rng: np.random.Generator = field(init=False)

    def __post_init__(self):
        self.R = self.R_initial
        self._rng = np.random.default_rng(self.seed)

    def _grow(self, R, dt):
        return self.R_inf - (self.R_inf - R) * math.exp(-dt / self.tau_days)

    def _run(self, a: float, b: float) -> float:
        """Operate from a to b: cost over the interval (Gauss–Legendre), R advanced; returns mean R."""
        x, w = _GL8
        dt = b - a
        tau = 0.5 * (x + 1) * dt
        R_t = self.R_inf - (self.R_inf - self.R) * np.exp(-tau / self.tau_days)
        self.cost_eur += float(np.sum(np.asarray(self.cost_curve(R_t)) * w) * 0.5 * dt)
        mean_R = float(np.sum(R_t * w) * 0.5)
        self.R = self._grow(self.R, dt)
        return mean_R

    def advance(self, dt_days: float) -> list:
        events: list = []
        end = self.t_days + dt_days
        win = self.window_hours / 24.0
        while self.t_days < end - 1e-12:
            if not self.running:
                if self._cip_end <= end:
                    self.t_days = self._cip_end
                    self.running = True
                    self._win_start = self.t_days
                    events.append(CipEvent(self._cip_start, self._cip_end))
                    self._cip_end = math.inf
                    continue
                self.t_days = end
                break
            nxt = min(end, self._win_start + win)
            mean_R = self._run(self.t_days, nxt)
            self._win_acc += mean_R * (nxt - self.t_days)
            self.t_days = nxt
            if nxt >= self._win_start + win - 1e-12:
                true_mean = self._win_acc / win
                self._win_acc = 0.0
                est = true_mean + self._rng.normal(0.0, self.noise_K_per_kW)
                events.append(WindowEstimate(self._win_start, nxt, est, self.noise_K_per_kW))
                self.truth.append((nxt, self.R))
                self._win_start = nxt
        return events

    def request_cip(self) -> None:
        if not self.running:
            return
        self.cips.append((self.t_days, self.R))
        self._cip_start = self.t_days
        self.cost_eur += self.cip_cost_eur
        self.R = (1.0 - self.removal_share) * self.R
        self.running = False
        self._win_acc = 0.0
        self._cip_end = self.t_days + self.downtime_days

    def total_cost_eur(self) -> float:
        return self.cost_eur


# ---- policies --------------------------------------------------------------------------------------------
@dataclass
class FixedInterval:
    """A CIP every ``interval_days`` of operation after each reset."""
    interval_days: float
    reset_days: float = 0.0

    def observe(self, event) -> None:
        if isinstance(event, CipEvent):
            self.reset_days = event.end_days

    def wants_cip(self, t_days: float) -> bool:
        return t_days - self.reset_days >= self.interval_days - 1e-9


@dataclass
class ForecastAdvisor:
    """hp-edge's advice applied as given: refit every ``refit_hours``, CIP when the date has come."""
    cost_curve: CostCurve                 # f(R_th,f [K/kW]) [EUR/day], relative to clean
    cip_cost_eur: float
    downtime_days: float
    default_share: float = 0.15
    default_spread: float = 0.05
    refit_hours: float = 6.0
    T_current_days: float | None = None   # configured current interval (else the plant's median)
    settings: FitSettings = field(default_factory=FitSettings)
    use_prior: bool = True                # earlier cycles' law as the prior of the current fit
    uncertain: bool = True                # plan on the expected J over the fit's uncertainty
    trigger: str = "level"                 # plan_cip's trigger rule
    reset_days: float = 0.0
    _t: list = field(default_factory=list)
    _R: list = field(default_factory=list)
    _se: list = field(default_factory=list)
    _last_fit_at: float = -math.inf
    _fit: object = None
    _due_days: float = math.inf
    _pairs: list = field(default_factory=list)       # [R_before, R_after or nan]
    _resets: list = field(default_factory=list)
    _cycle_fits: list = field(default_factory=list)  # prior-free fit of each completed cycle
    _cip_starts: list = field(default_factory=list)
    forecast_days: float = 2.0            # horizon of the logged forecasts (accuracy figures)
    trail: list = field(default_factory=list)        # (t, T_opt, law, share) per refit
    forecasts: list = field(default_factory=list)    # (t made, t target, days since reset, value, lo, hi)
    fit_seconds: list = field(default_factory=list)

    def observe(self, event) -> None:
        if isinstance(event, WindowEstimate):
            self._t.append(event.mid_days - self.reset_days)
            self._R.append(event.R_K_per_kW)
            self._se.append(event.R_se_K_per_kW)
        elif isinstance(event, CipEvent):
            before = (self._fit.value(event.start_days - self.reset_days) if self._fit is not None
                      else (float(np.mean(self._R[-3:])) if self._R else math.nan))
            self._pairs.append([before, math.nan])
            try:          # the cycle's own evidence on the law, without the prior (no double counting)
                self._cycle_fits.append(fit_fouling(self._t, self._R, self._se, settings=self.settings))
            except ForecastError:
                pass
            self._resets.append(self.reset_days)
            self._cip_starts.append(event.start_days)
            self.reset_days = event.end_days
            self._t, self._R, self._se = [], [], []
            self._fit, self._due_days, self._last_fit_at = None, math.inf, -math.inf

    def share(self) -> RemovalShare:
        p = np.array(self._pairs, dtype=float).reshape(-1, 2)
        return estimate_removal_share(p[:, 0], p[:, 1], default_share=self.default_share,
                                      default_spread=self.default_spread)

    def refit(self, t_days: float) -> None:
        self._last_fit_at = t_days
        t0 = time.perf_counter()
        try:
            prior = law_prior(self._cycle_fits) if self.use_prior else None
            fit = fit_fouling(self._t, self._R, self._se, prior=prior, settings=self.settings)
        except ForecastError:
            return
        self._fit = fit
        now = t_days - self.reset_days
        p = fit.at_horizon(self.forecast_days, now)
        self.forecasts.append((t_days, t_days + self.forecast_days, now, p.value, p.lo, p.hi))
        if self._pairs and not math.isfinite(self._pairs[-1][1]):
            self._pairs[-1][1] = fit.y0
        share = self.share()
        T_cur = self.T_current_days or median_interval_days(self._resets, self._cip_starts)
        plan = plan_cip([FoulingComponent(fit, share.share, self.cost_curve, uncertain=self.uncertain)],
                        cip_cost_eur=self.cip_cost_eur, downtime_days=self.downtime_days,
                        t_now_days=t_days - self.reset_days, T_current_days=T_cur, trigger=self.trigger)
        self.fit_seconds.append(time.perf_counter() - t0)
        self._due_days = self.reset_days + plan.t_cip_days
        self.trail.append((t_days, plan.T_opt_days, fit.law, share.share))

    def wants_cip(self, t_days: float) -> bool:
        if t_days - self._last_fit_at >= self.refit_hours / 24.0 - 1e-9:
            self.refit(t_days)
        return t_days >= self._due_days


# ---- running a policy ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PolicyRun:
    """Costs of one policy. ``total_cost_eur``: everything inside the horizon. ``cost_per_day_eur``:
    over complete fouling–cleaning cycles — the run goes on to the policy's first CIP at or after the
    horizon (at most ``max_extra_days`` more), that CIP's cost and downtime included — so a CIP just
    before the horizon's end, or an unpaid stretch just after a CIP, does not tilt the comparison.
    ``cycle_total_eur`` = cost_per_day_eur * horizon_days, the figure the comparison uses."""
    name: str
    total_cost_eur: float
    cost_per_day_eur: float
    cycle_total_eur: float
    n_cips: int
    cip_starts_days: tuple
    horizon_days: float
    end_days: float


def run_cip_policy(plant, policy, horizon_days: float = 120.0, step_hours: float = 2.0,
                   name: str = "", max_extra_days: float = 60.0) -> PolicyRun:
    """Advance ``plant`` in steps; after each step ask ``policy``. Bounded: at most
    (horizon + max_extra_days) / step steps."""
    if not (horizon_days > 0 and step_hours > 0 and max_extra_days >= 0):
        raise ValueError("horizon_days and step_hours must be > 0, max_extra_days >= 0")
    step = step_hours / 24.0
    n_steps = int(math.ceil((horizon_days + max_extra_days) / step - 1e-9))
    starts: list[float] = []
    raw = None
    closing_downtime = 0.0
    for _ in range(n_steps):
        for ev in plant.advance(step):
            policy.observe(ev)
        if raw is None and plant.t_days >= horizon_days - 1e-9:
            raw = plant.total_cost_eur()
        if plant.running and policy.wants_cip(plant.t_days):
            starts.append(plant.t_days)
            plant.request_cip()
            if plant.t_days >= horizon_days - 1e-9:
                closing_downtime = getattr(plant, "downtime_days", 0.0)
                break
    end = plant.t_days
    total = plant.total_cost_eur()
    per_day = total / (end + closing_downtime)
    inside = [t for t in starts if t < horizon_days - 1e-9]
    return PolicyRun(name, raw if raw is not None else total, per_day, per_day * horizon_days,
                     len(inside), tuple(inside), horizon_days, end)


def compare_policies(make_plant: Callable[[], object], make_advisor: Callable[[], object],
                     fixed_intervals_days: Sequence[float] = (5.0, 8.0, 12.0, 20.0),
                     horizon_days: float = 120.0, step_hours: float = 2.0) -> dict:
    """Total cost of each fixed interval and of the advisor on fresh plants from ``make_plant``.

    Compared on ``PolicyRun.cycle_total_eur``. Returns {"fixed": {T: PolicyRun}, "advised": PolicyRun,
    "best_fixed_eur", "median_fixed_eur", "advised_vs_best": ratio - 1, "advised_below_median": bool}.
    """
    fixed = {T: run_cip_policy(make_plant(), FixedInterval(T), horizon_days, step_hours, f"every {T:g} d")
             for T in fixed_intervals_days}
    advised = run_cip_policy(make_plant(), make_advisor(), horizon_days, step_hours, "hp-edge advice")
    totals = np.array([r.cycle_total_eur for r in fixed.values()])
    best, median = float(totals.min()), float(np.median(totals))
    return {"fixed": fixed, "advised": advised, "best_fixed_eur": best, "median_fixed_eur": median,
            "advised_vs_best": advised.cycle_total_eur / best - 1.0,
            "advised_below_median": advised.cycle_total_eur < median}


# ---- the simulator-free benchmark -------------------------------------------------------------------------
# Scenarios of the reduced plant: the simulator's fouling law (config/simulator.yaml: R 2.5e-3 K/kW at
# the start, R_inf 6e-3 K/kW, tau 15 d, 2.5 d CIPs removing 15 %) and the same with CIPs removing 30 %
# (the upper end of what plants report). Cost rate 40 EUR/day per 1e-3 K/kW: 16.7 kW of extra
# compressor power at 100 EUR/MWh (the model at the nominal point gives 13-18 kW per 1e-3 K/kW over
# R_th,f 1-6e-3 K/kW). A CIP costs 1000 EUR net: with this cost rate a CIP that removes 15 % pays for
# itself only below about 1100 EUR (30 %: 1600 EUR); above that the optimum is "never clean" and
# every fixed interval is a loss, which would test nothing.
COST_PER_K_PER_KW_EUR_PER_DAY = 40.0e3
BENCH_CIP_COST_EUR = 1000.0
SCENARIOS = {"simulator_law_15pct": {"removal_share": 0.15}, "strong_cip_30pct": {"removal_share": 0.30}}


def bench_curve() -> CostCurve:
    return CostCurve([0.0, 1e-3], [0.0, COST_PER_K_PER_KW_EUR_PER_DAY * 1e-3])


def forecast_accuracy(plant: ReducedPlant, advisor: ForecastAdvisor, min_days_after_reset: float = 2.0,
                      tol_K_per_kW: float = 0.3e-3) -> dict:
    """The logged forecasts (``advisor.forecast_days`` ahead) made >= min_days_after_reset after a reset
    whose target lies before the next CIP: share within +-tol of the truth, share with the truth
    inside the band."""
    tr = np.array(plant.truth)
    cip_starts = np.array([c[0] for c in plant.cips] + [math.inf])
    n = ok = inband = 0
    for t_made, t_target, since, v, lo, hi in advisor.forecasts:
        if since < min_days_after_reset:
            continue
        nxt = cip_starts[np.searchsorted(cip_starts, t_made, side="right")]
        if t_target > nxt or t_target > tr[-1, 0]:
            continue
        j = int(np.searchsorted(tr[:, 0], t_target))
        t0, R0_, t1, R1_ = tr[j - 1, 0], tr[j - 1, 1], tr[j, 0], tr[j, 1]
        truth = R0_ + (R1_ - R0_) * (t_target - t0) / (t1 - t0) if t1 > t0 else R1_
        n += 1
        ok += abs(v - truth) <= tol_K_per_kW
        inband += lo <= truth <= hi
    return {"n_forecasts": n, "within_tol_share": ok / n if n else math.nan,
            "truth_in_band_share": inband / n if n else math.nan, "tol_K_per_kW": tol_K_per_kW,
            "horizon_days": advisor.forecast_days}


def bench_cip(seeds: Sequence[int] = (0, 1, 2), horizon_days: float = 120.0) -> dict:
    """The simulator-free part of ``hp-edge bench --only cip``: the policy comparison on the reduced
    plant per scenario and seed, the forecast accuracy there, and the time of one window's advice
    (forecast of R_th,f and CF_dp,f + cost + CIP plan). JSON-able."""
    from .cip import CipSettings, advise_cip

    out: dict = {"targets": {"advised_vs_best_max": 0.02, "advised_below_median": True,
                             "forecast_within_0.3e-3_share_min": 0.80, "truth_in_band_share_min": 0.80,
                             "advice_one_window_ms_max": 50.0},
                 "cost_per_K_per_kW_eur_per_day": COST_PER_K_PER_KW_EUR_PER_DAY,
                 "cip_cost_eur": BENCH_CIP_COST_EUR, "scenarios": {}}
    curve = bench_curve()
    for name, kw in SCENARIOS.items():
        rows = []
        for seed in seeds:
            plants: list = []
            advisors: list = []

            def make_plant(seed=seed):
                plants.append(ReducedPlant(curve, BENCH_CIP_COST_EUR, seed=seed, **kw))
                return plants[-1]

            def make_advisor():
                advisors.append(ForecastAdvisor(curve, BENCH_CIP_COST_EUR, 2.5))
                return advisors[-1]
            res = compare_policies(make_plant, make_advisor, horizon_days=horizon_days)
            adv = advisors[-1]
            acc = forecast_accuracy(plants[-1], adv)      # the advised run's plant (made last)
            rows.append({"seed": seed,
                         "fixed_cycle_total_eur": {f"{T:g}": r.cycle_total_eur for T, r in res["fixed"].items()},
                         "fixed_raw_total_eur": {f"{T:g}": r.total_cost_eur for T, r in res["fixed"].items()},
                         "advised_cycle_total_eur": res["advised"].cycle_total_eur,
                         "advised_raw_total_eur": res["advised"].total_cost_eur,
                         "advised_cips": res["advised"].n_cips,
                         "advised_vs_best": res["advised_vs_best"],
                         "advised_below_median": bool(res["advised_below_median"]),
                         "refit_ms_median": 1e3 * float(np.median(adv.fit_seconds)), **acc})
        out["scenarios"][name] = rows

    # one window's advice on a 10-day cycle of 2-h windows (R_th,f and CF_dp,f), best and median of 20
    rng = np.random.default_rng(0)
    t = np.arange(1 / 24, 10.0, 2 / 24)
    R = 4.4e-3 + 1.6e-3 * (1 - np.exp(-t / 15.0)) + rng.normal(0, 0.05e-3, len(t))
    CF = 1.2 + 0.2 * (1 - np.exp(-t / 20.0)) + rng.normal(0, 0.005, len(t))
    settings = CipSettings()
    times = []
    for _ in range(20):
        t0 = time.perf_counter()
        advice = advise_cip(t_days=t, R_K_per_kW=R, R_se_K_per_kW=np.full(len(t), 0.05e-3),
                            t_now_days=float(t[-1]), cop_levels=((0.0, 3e-3, 6e-3), (4.9, 4.62, 4.37)),
                            Q_sink_kW=2000.0, settings=settings, start_s=0.0, end_s=7200.0, CF_dp_f=CF,
                            CF_dp_f_se=np.full(len(t), 0.005), V_source_m3_per_h=192.0, dp_clean_bar=0.25)
        times.append(time.perf_counter() - t0)
    out["advice_one_window_ms"] = {"median": 1e3 * float(np.median(times)), "max": 1e3 * float(np.max(times)),
                                   "windows": int(len(t)), "plan": advice.plan is not None}
    return out
