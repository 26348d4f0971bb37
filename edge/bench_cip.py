"""The CIP policy benchmark on the simulator (issue 10, ``hp-edge bench --only cip``), BOPTEST-style.

The simulated plant (config/simulator.yaml: its Kern–Seaton fouling law, R_th,f 2.5e-3 K/kW at the
start, R_inf 6e-3 K/kW, tau 15 days of operation; its profiles, lags and noise) runs with CIPs on request,
minute by minute from Python (``simulator.export.MinuteStepper``), for ``days`` (120) under each policy:

* a CIP every T days of operation after each restart, T = 5, 8, 12, 20 ("fixed");
* hp-edge's advice applied as it is given ("advised"): the analysis chain runs on the plant's one-minute
  rows every ``window_hours`` (2 h) of plant time, causally (``model.measured.process`` ->
  ``AnalysisChain.window`` with optimize=False and learn_compressors=False: the CIP policy needs the
  fouling calibration, not the set point), CIPs are found in the rows as the gateway finds them
  (``model.analysis.cip.CipWatch``) and reset the forecast (``AnalysisChain.cip``); a CIP is requested
  when the recommended date (window end + days_to_recommended_cip) has come.

The fixed model is commissioned first, as on a site: the initial calibration and the clean pressure-drop
fit on 100 minutes of the same plant with a clean evaporator.

The CIP and the prices (``SIM_CIP``, ``PRICES``) are chosen so that cleaning pays at all. With the
simulator's own CIP (2.5 days down, 15 % of R_th,f removed) and any replacement heat dearer than the
heat pump's own (electricity price / COP, about 21 EUR/MWh here), never cleaning is cheapest: fouling
costs this plant at most ~90 EUR/day (R_inf against clean), a CIP removing 15 % saves ~15 EUR/day, and
2.5 days without the heat pump cost more than that saves. The bench's CIP takes 1 day and removes 30 %
(the upper end plants report), electricity costs 100 EUR/MWh, replacement heat 25 EUR/MWh and a CIP 150
EUR direct. The advisor starts from a configured removal share of 25 % (``ADVISOR_REMOVAL_SHARE``) and
learns the plant's from its CIPs.

Accounting (``Account``): against the network's heat demand, which is the heat the same plant would
deliver with a clean evaporator at the same minute (``CleanPlant``, one model solve per solve
interval); heat not delivered is bought at the replacement heat price, heat delivered beyond it
(a fouled plant's extra compressor work also leaves as heat) displaces bought heat:
    total = electricity + source pumps' extra + CIP direct + heat bought during CIPs
            + heat bought (or displaced, < 0) while running   (the lost capacity at the LS limit shows here)
The baseline (a plant that never fouls and never stops: its electricity) is the same for every policy
over the same days; excess = total - baseline is what the policies change. Runs are compared as in
``model.analysis.cip_policy``: each run goes on to its policy's first CIP at or after the horizon (at
most ``max_extra_days`` more), that CIP's cost and downtime included, so a CIP just before the end does
not tilt the comparison; ``cycle_total_eur`` = the baseline of exactly ``days`` + the excess per day over
the complete cycles x ``days``. ``total_eur_at_horizon`` is the plain total of the first ``days``.

Sharing: all policies run the same plant until the first of them asks for a CIP; a run is copied
(``copy.deepcopy`` of the stepper) where the policies sharing it disagree, so the common part is
simulated once. The plant's quasi-steady state is re-solved every ``solve_interval_s`` (300 s of plant
time instead of the shipped 60 s: the profiles change over hours; this makes the run about twice as
fast).
"""
from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

DAY_S = 86400.0
FIXED_DAYS = (5.0, 8.0, 12.0, 20.0)
TARGETS = {"advised_vs_best_max": 0.02, "advised_below_median": True,
           "forecast_within_tol_share_min": 0.80, "truth_in_band_share_min": 0.80,
           "forecast_tol_K_per_kW": 0.3e-3, "forecast_horizon_days": 2.0,
           "min_days_after_reset": 2.0, "forecast_step_ms_max": 50.0}
PRICES = {"electricity_eur_per_MWh": 100.0, "replacement_heat_eur_per_MWh": 25.0,
          "cip_direct_cost_eur": 150.0}
SIM_CIP = {"removal_share": 0.30, "duration_days": 1.0}    # the bench's CIP (module docstring)
ADVISOR_REMOVAL_SHARE = 0.25      # the advisor's configured share until it has learned the plant's
CONTEXT = 15                      # rows before a block that the measured-side processing needs


@dataclass
class Account:
    """Cost of one run in parts [EUR], against the network's heat demand: the heat the plant would
    deliver with a clean evaporator at the same minute (``CleanPlant``). Heat the plant does not
    deliver is bought at the replacement heat price; heat it delivers beyond the demand (a fouled
    plant's extra compressor work also leaves as heat) displaces bought heat and is credited.

        electricity    compressors' electric power x price
        pumps          the source pumps' extra power for the fouling pressure drop
                       (V dp (1 - 1/CF_dp,f) / eta_pump) x price
        cip_direct     each CIP's direct cost
        downtime_heat  while a CIP stops the plant: the demand bought
        running_heat   while running: (demand - heat delivered) bought (< 0: a credit); the lost
                       capacity at the LS speed limit shows here
        total          the sum of the five
        baseline       what a plant that never fouls and never stops would cost: its electricity
                       (the same for every policy over the same days)
        excess         total - baseline: the cost of fouling and cleaning
    """
    price: float
    heat_price: float
    cip_direct: float
    eta_pump: float = 0.65
    electricity_eur: float = 0.0
    pumps_eur: float = 0.0
    cip_direct_eur: float = 0.0
    downtime_heat_eur: float = 0.0
    running_heat_eur: float = 0.0
    baseline_eur: float = 0.0
    electricity_MWh: float = 0.0
    heat_MWh: float = 0.0
    demand_MWh: float = 0.0
    downtime_min: int = 0
    n_cips: int = 0
    last_demand_kW: float = math.nan
    last_rate: float = math.nan          # the minute's true cost of fouling [EUR/day] (NaN: not running)

    @property
    def total_eur(self) -> float:
        return (self.electricity_eur + self.pumps_eur + self.cip_direct_eur + self.downtime_heat_eur
                + self.running_heat_eur)

    @property
    def excess_eur(self) -> float:
        return self.total_eur - self.baseline_eur

    def minute(self, plant, clean: tuple[float, float]) -> None:
        """Account one minute at the plant's state now (before the minute's ticks); ``clean`` is
        (Q_sink, W) [kW] of the clean plant at the same boundary conditions."""
        Qc, Wc = clean
        h = 1.0 / 60.0 / 1e3                        # kW for one minute -> MWh
        self.last_demand_kW = Qc
        self.demand_MWh += Qc * h
        self.baseline_eur += Wc * h * self.price
        sp = plant.steady
        self.last_rate = math.nan
        if not plant.running or sp.res is None:
            self.downtime_min += 1
            self.downtime_heat_eur += Qc * h * self.heat_price
            return
        r = sp.res
        W = r.W_total / 1e3 / plant.cfg.truth.motor_efficiency
        Q = r.Q_sink / 1e3
        CF = plant.fouling.CF_dp
        pump = plant.boundary.V_source_m3h / 3600.0 * r.dp_source * (1.0 - 1.0 / CF) / self.eta_pump / 1e3
        self.electricity_MWh += W * h
        self.electricity_eur += W * h * self.price
        self.pumps_eur += max(pump, 0.0) * h * self.price
        self.heat_MWh += Q * h
        self.running_heat_eur += (Qc - Q) * h * self.heat_price
        self.last_rate = 24.0 / 1e3 * ((W - Wc + max(pump, 0.0)) * self.price + (Qc - Q) * self.heat_price)

    def cip(self) -> None:
        self.n_cips += 1
        self.cip_direct_eur += self.cip_direct

    def closing_cip(self, downtime_days: float, baseline_W_kW: float) -> None:
        """A CIP at the run's end: its direct cost and its downtime's heat (the last demand), not
        simulated; the baseline runs on for those days."""
        self.cip()
        self.downtime_heat_eur += self.last_demand_kW * downtime_days * 24.0 / 1e3 * self.heat_price
        self.baseline_eur += baseline_W_kW * downtime_days * 24.0 / 1e3 * self.price

    def parts(self) -> dict:
        return {"electricity_eur": self.electricity_eur, "pumps_eur": self.pumps_eur,
                "cip_direct_eur": self.cip_direct_eur, "downtime_heat_eur": self.downtime_heat_eur,
                "running_heat_eur": self.running_heat_eur}


class CleanPlant:
    """The plant with a clean evaporator (R_th,f 0, CF_dp,f 1) at the boundary conditions of the
    simulated plant's present solve (running or not): the heat demand and the baseline. The
    boundary conditions depend on plant time only, so one cache serves every run."""

    def __init__(self) -> None:
        from simulator.sensors import LSController
        self.ls = LSController()
        self.cache: dict[int, tuple[float, float]] = {}
        self.guess = None

    def at(self, plant) -> tuple[float, float]:
        from model.cycle import ModelError
        from simulator.plant import effective_params
        slot = int(plant.k // max(1, round(plant.cfg.time.solve_interval_s / plant.dt)))
        got = self.cache.get(slot)
        if got is not None:
            return got
        b = plant.boundary
        params = effective_params(plant.true, plant.cfg.flow_dependence, b.V_source_m3h, b.V_sink_m3h, 0.0, 1.0)
        try:
            r, _, limit = self.ls.solve(plant.inputs(b), params, self.guess)
            if not limit:
                self.ls.T_out_float = None
            self.guess = r
            got = (r.Q_sink / 1e3, r.W_total / 1e3 / plant.cfg.truth.motor_efficiency)
        except (ModelError, ValueError):
            self.guess = None
            got = self.cache.get(slot - 1, (math.nan, math.nan))
        if len(self.cache) > 4096:
            self.cache.clear()
        self.cache[slot] = got
        return got


class Fixed:
    """A CIP every ``interval_days`` of operation after each restart."""

    def __init__(self, interval_days: float):
        self.T = float(interval_days)
        self.name = f"every {self.T:g} d"

    def wants(self, run: "Run") -> bool:
        return (run.t - run.reset_t) / DAY_S >= self.T - 1e-9


class Advised:
    """hp-edge's advice applied as given: the chain on the run's rows every window, a CIP when the
    recommended date has come."""
    name = "hp-edge advice"

    def __init__(self, chain, state, params, window_s: float, off_minutes: float = 360.0):
        from model.analysis.cip import CipWatch
        self.chain, self.state, self.params = chain, state, params
        self.window_s = window_s
        self.due = math.inf
        self.watch = CipWatch(off_minutes)
        self.rows: list[dict] = []
        self.context: list[dict] = []
        self.block_end: float | None = None
        self.log: list[dict] = []           # per window: the figures the accuracy needs
        self.seconds: list[float] = []      # the forecast step of each window (wall time)
        self.cpu_seconds: list[float] = []  # the same, CPU time of the thread (the machine is shared)
        self.window_seconds: list[float] = []   # the whole chain window
        self.held = False                   # a CIP was asked for: no new date until it has happened
        self.truth_rates: list[float] = []  # the plant's true fouling cost rate per running minute

    def wants(self, run: "Run") -> bool:
        return run.t >= self.due

    def on_minute(self, run: "Run", row: dict) -> None:
        if self.block_end is None:
            self.block_end = run.t0 + self.window_s
        self.rows.append(row)
        if math.isfinite(run.account.last_rate):
            self.truth_rates.append(run.account.last_rate)
        if run.t + 60.0 >= self.block_end - 1e-6:
            self._window(run)
            self.block_end += self.window_s

    def _window(self, run: "Run") -> None:
        import pandas as pd
        from model.measured import process

        block = self.context + self.rows
        df = pd.DataFrame(block)
        df["timestamp"] = pd.to_datetime(df["timestamp"], utc=True)
        pr = process(df, self.params).iloc[len(self.context):]
        rows = df.iloc[len(self.context):]
        self.context = block[-CONTEXT:]
        self.rows = []
        ts = rows["timestamp"].map(lambda t: t.timestamp()).to_numpy()
        cip = rows["cip"].to_numpy(dtype=float) if "cip" in rows.columns else np.zeros(len(rows))
        reason = pr["reason"].astype(str).to_numpy()
        for t, r, c in zip(ts, reason, cip):
            found = self.watch.feed(float(t), r in ("off", "cip"), bool(c > 0.5))
            if found is not None:
                self.chain.cip(self.state, found[0], found[1], found[2])
                self.due = math.inf
                self.held = False
        reset = self.state.forecast.reset_s
        use = pr["usable"].to_numpy(dtype=bool).copy()
        if reset is not None:
            use &= ts >= reset
        data = rows[use]
        if len(data) < self.chain.s.min_samples:
            return
        t0 = time.perf_counter()
        res = self.chain.window(data, self.state)
        self.window_seconds.append(time.perf_counter() - t0)
        if not res.ok:
            return
        self.seconds.append(res.detail.get("cip", {}).get("seconds", math.nan))
        self.cpu_seconds.append(res.detail.get("cip", {}).get("cpu_seconds", math.nan))
        d = res.days_to_recommended_cip
        if not self.held:        # rows from before a CIP that was asked for: no new date
            self.due = res.t_end + d * DAY_S if math.isfinite(d) else math.inf
        truth = float(np.mean(self.truth_rates)) if self.truth_rates else math.nan
        self.truth_rates = []
        self.log.append({"t_end": res.t_end, "since": res.days_since_reset,
                         "value": res.R_th_f_forecast_K_per_kW, "lo": res.R_th_f_forecast_lo_K_per_kW,
                         "hi": res.R_th_f_forecast_hi_K_per_kW, "R": res.R_th_f_K_per_kW,
                         "T_opt": res.cip_interval_opt_days, "days_to_cip": d, "law": res.forecast_law,
                         "share": res.removal_share, "cost": res.fouling_cost_eur_per_day,
                         "truth_cost": truth})


@dataclass
class Run:
    """One simulated plant, its account, and the policies that share it."""
    stepper: object
    account: Account
    policies: list
    t0: float
    reset_t: float
    cip_starts: list = field(default_factory=list)     # days since t0
    R_log: list = field(default_factory=list)          # (t, true R_th,f) per minute (advised run)
    total_at_horizon: float | None = None
    baseline_at_horizon: float | None = None
    done: bool = False
    end_t: float = math.nan
    closing_downtime_days: float = 0.0

    @property
    def t(self) -> float:
        return self.stepper.plant.t

    def split(self, leave: list) -> "Run":
        """A copy of the plant and its account so far for the policies ``leave`` (they go on without
        the CIP the others ask for now)."""
        other = Run(copy.deepcopy(self.stepper), copy.deepcopy(self.account), leave, self.t0, self.reset_t,
                    list(self.cip_starts), [], self.total_at_horizon, self.baseline_at_horizon)
        if any(isinstance(p, Advised) for p in leave):
            other.R_log, self.R_log = self.R_log, []
        self.policies = [p for p in self.policies if p not in leave]
        return other


def commission(params, sim_cfg, minutes: float = 100.0):
    """Initial calibration and clean pressure-drop fit on ``minutes`` of the plant with a clean
    evaporator (no compressor learning: the bench's chain does not learn them either)."""
    import pandas as pd
    from model.calibration import calibrate, calibration_frame, spec_from_config
    from model.dpfit import fit_dp_clean
    from model.measured import process
    from simulator.export import export_history

    clean = sim_cfg.replace(fouling=dataclasses.replace(
        sim_cfg.fouling, R_th_f_initial_K_per_kW=0.0, R_th_f_inf_K_per_kW=0.0, CF_dp_f_initial=1.0,
        CF_dp_f_inf=1.0), faults=())
    h = export_history(minutes / 1440.0, cfg=clean).history
    h["timestamp"] = pd.to_datetime(h["timestamp"], utc=True)
    data = calibration_frame(h, process(h, params))
    initial = calibrate(data, params, spec_from_config(params.extra, "initial"))
    dp = fit_dp_clean(data["V_source"], data["dp_source_bar"])
    return initial.to_dict(), dp.to_dict()


def sim_config(solve_interval_s: float = 300.0, seed: int | None = None, cip: dict | None = None):
    """config/simulator.yaml with CIPs on request (``cip`` overrides, e.g. SIM_CIP), the truth's
    COP-optimal set point not refreshed (not needed here) and the plant solved every
    ``solve_interval_s``."""
    from simulator.config import load_simulator_config
    cfg = load_simulator_config().with_sections(
        cip={"mode": "on_request", **(cip if cip is not None else SIM_CIP)},
        time={"solve_interval_s": float(solve_interval_s), "optimum_interval_s": 1e12})
    return cfg if seed is None else cfg.replace(seed=seed)


def run_policies(params, *, days: float = 120.0, fixed=FIXED_DAYS, advised: bool = True,
                 window_hours: float = 2.0, solve_interval_s: float = 300.0, seed: int | None = None,
                 max_extra_days: float = 25.0, prices: dict | None = None, commissioning=None,
                 sim_cip: dict | None = None, progress=None) -> dict:
    """Run every policy on the simulated plant (see the module docstring). Returns the runs (each
    with its policies, account and CIP days), the advisor, and the settings."""
    from model.analysis.chain import AnalysisChain, ChainSettings
    from model.analysis.cip import CipSettings
    from model.calibration import spec_from_config
    from simulator.export import MinuteStepper

    pr = {**PRICES, **(prices or {})}
    cfg = sim_config(solve_interval_s, seed, sim_cip)
    downtime_days = cfg.cip.duration_days
    stepper = MinuteStepper(cfg)
    acc = Account(pr["electricity_eur_per_MWh"], pr["replacement_heat_eur_per_MWh"], pr["cip_direct_cost_eur"])
    clean = CleanPlant()
    policies: list = [Fixed(T) for T in fixed]
    adv = None
    if advised:
        initial, dp = commissioning or commission(params, cfg)
        cip = CipSettings(electricity_price_eur_per_MWh=pr["electricity_eur_per_MWh"],
                          replacement_heat_eur_per_MWh=pr["replacement_heat_eur_per_MWh"],
                          cip_direct_cost_eur=pr["cip_direct_cost_eur"], cip_downtime_h=24.0 * downtime_days,
                          removal_share_default=ADVISOR_REMOVAL_SHARE,
                          horizon_days=TARGETS["forecast_horizon_days"])
        chain = AnalysisChain(params, spec_from_config(params.extra, "fouling"),
                              ChainSettings.from_config(params.extra, optimize=False, learn_compressors=False,
                                                        cip=cip))
        adv = Advised(chain, chain.new_state(initial, dp), params, window_hours * 3600.0)
        policies.append(adv)
    t0 = stepper.plant.t
    runs = [Run(stepper, acc, policies, t0, t0)]
    horizon_t = t0 + days * DAY_S
    limit_t = horizon_t + max_extra_days * DAY_S
    n_min = int(round((days + max_extra_days) * 1440))
    for m in range(n_min):
        for run in list(runs):
            if run.done:
                continue
            plant = run.stepper.plant
            if plant.running and plant.cip_window is None and not plant.cip_pending:
                want = [p for p in run.policies if p.wants(run)]
                if want and len(want) < len(run.policies):
                    runs.append(run.split([p for p in run.policies if p not in want]))
                if want:
                    run.cip_starts.append((run.t - t0) / DAY_S)
                    if run.t >= horizon_t - 1e-6:       # the closing CIP: counted, not simulated
                        run.account.closing_cip(downtime_days, clean.at(plant)[1])
                        run.closing_downtime_days = downtime_days
                        run.done, run.end_t = True, run.t
                        continue
                    run.account.cip()
                    plant.request_cip()
                    for p in want:          # asked for: the advice restarts after the CIP
                        if isinstance(p, Advised):
                            p.due, p.held = math.inf, True
            was_down = not plant.running
            run.account.minute(plant, clean.at(plant))
            if any(isinstance(p, Advised) for p in run.policies):
                run.R_log.append((run.t, plant.fouling.R))
                row, _ = run.stepper.step()
                for p in run.policies:
                    if isinstance(p, Advised):
                        p.on_minute(run, row)
            else:
                for _ in range(run.stepper.ticks_per_minute):
                    plant.tick()
            if was_down and plant.running:
                run.reset_t = run.t
            if run.total_at_horizon is None and run.t >= horizon_t - 1e-6:
                run.total_at_horizon = run.account.total_eur
                run.baseline_at_horizon = run.account.baseline_eur
            if run.t >= limit_t - 1e-6:
                run.done, run.end_t = True, run.t
        if progress is not None and m % 1440 == 0:
            progress(m // 1440, int(days + max_extra_days))
        if all(r.done for r in runs):
            break
    for run in runs:
        if not run.done:
            run.done, run.end_t = True, run.t
    return {"runs": runs, "advisor": adv, "t0": t0, "days": days, "downtime_days": downtime_days,
            "prices": pr, "sim": {"removal_share": cfg.cip.removal_share,
                                  "dp_removal_share": cfg.cip.dp_removal_share,
                                  "cip_duration_days": downtime_days, "fouling": dataclasses.asdict(cfg.fouling)}}


def run_result(run: Run, t0: float, days: float) -> dict:
    """A run's figures: the parts and their sum, per day over complete cycles, and the total over
    ``days`` built from them (the baseline of exactly those days + the excess per day x days)."""
    a = run.account
    span = (run.end_t - t0) / DAY_S + run.closing_downtime_days
    excess_per_day = a.excess_eur / span
    base = run.baseline_at_horizon if run.baseline_at_horizon is not None else a.baseline_eur
    return {"policies": [p.name for p in run.policies], **a.parts(), "total_eur": a.total_eur,
            "baseline_eur": a.baseline_eur, "excess_eur": a.excess_eur, "days_accounted": span,
            "cost_per_day_eur": a.total_eur / span, "excess_per_day_eur": excess_per_day,
            "cycle_total_eur": base + excess_per_day * days, "total_eur_at_horizon": run.total_at_horizon,
            "baseline_eur_at_horizon": run.baseline_at_horizon,
            "n_cips_in_horizon": sum(1 for d in run.cip_starts if d < days - 1e-9),
            "cip_start_days": [round(d, 3) for d in run.cip_starts],
            "electricity_MWh": a.electricity_MWh, "heat_MWh": a.heat_MWh, "demand_MWh": a.demand_MWh,
            "downtime_days": a.downtime_min / 1440.0}


def forecast_accuracy(adv: Advised, run: Run, t0: float, tol: float = TARGETS["forecast_tol_K_per_kW"],
                      horizon_days: float = TARGETS["forecast_horizon_days"],
                      min_since: float = TARGETS["min_days_after_reset"]) -> dict:
    """The advisor's forecasts made >= min_since days after the last reset whose target (horizon
    days later) lies before the next CIP and inside the run: share within +-tol of the plant's true
    R_th,f there, share with the truth inside the 90 % band."""
    tr = np.array(run.R_log, dtype=float)
    starts = np.array(sorted(t0 + d * DAY_S for d in run.cip_starts) + [math.inf])
    n = ok = inband = 0
    errors = []
    for e in adv.log:
        if not (e["since"] >= min_since and math.isfinite(e["value"])):
            continue
        target = e["t_end"] + horizon_days * DAY_S
        nxt = starts[np.searchsorted(starts, e["t_end"], side="right")]
        if target > nxt or target > tr[-1, 0]:
            continue
        truth = float(np.interp(target, tr[:, 0], tr[:, 1]))
        n += 1
        errors.append(e["value"] - truth)
        ok += abs(e["value"] - truth) <= tol
        inband += e["lo"] <= truth <= e["hi"]
    err = np.abs(errors) if errors else np.array([math.nan])
    return {"n_forecasts": n, "within_tol_share": ok / n if n else math.nan,
            "truth_in_band_share": inband / n if n else math.nan, "tol_K_per_kW": tol,
            "horizon_days": horizon_days, "abs_error_median_K_per_kW": float(np.median(err)),
            "abs_error_p90_K_per_kW": float(np.percentile(err, 90)),
            "bias_median_K_per_kW": float(np.median(errors)) if errors else math.nan}


def bench_cip(params=None, *, days: float = 120.0, fixed=FIXED_DAYS, window_hours: float = 2.0,
              solve_interval_s: float = 300.0, seed: int | None = None, reduced: bool = True,
              progress=None) -> dict:
    """``hp-edge bench --only cip``: the policies on the simulator (module docstring), the forecast
    accuracy of the advised run, the forecast step's time per window, and the simulator-free check
    on the reduced plant (``model.analysis.cip_policy.bench_cip``). JSON-able."""
    if params is None:
        from edge.config import find_config
        from edge.plantfile import load_plant
        params = load_plant(find_config("plant.yaml", None))
    wall = time.perf_counter()
    out = run_policies(params, days=days, fixed=fixed, window_hours=window_hours,
                       solve_interval_s=solve_interval_s, seed=seed, progress=progress)
    t0, adv = out["t0"], out["advisor"]
    by_policy = {}
    adv_run = None
    for run in out["runs"]:
        r = run_result(run, t0, days)
        for p in run.policies:
            by_policy[p.name] = r
        if adv in run.policies:
            adv_run = run
    fixed_tot = {f"{T:g}": by_policy[f"every {T:g} d"]["cycle_total_eur"] for T in fixed}
    fixed_ex = {f"{T:g}": by_policy[f"every {T:g} d"]["excess_per_day_eur"] for T in fixed}
    totals = np.array(list(fixed_tot.values()))
    best, median = float(totals.min()), float(np.median(totals))
    ex = np.array(list(fixed_ex.values()))
    a = by_policy[Advised.name]["cycle_total_eur"]
    a_ex = by_policy[Advised.name]["excess_per_day_eur"]
    sec = np.array([s for s in adv.seconds if math.isfinite(s)])
    cpu = np.array([s for s in adv.cpu_seconds if math.isfinite(s)])
    pairs = np.array([(e["cost"], e["truth_cost"]) for e in adv.log
                      if math.isfinite(e["cost"]) and math.isfinite(e["truth_cost"])])
    result = {
        "targets": TARGETS, "prices": out["prices"], "simulator": out["sim"], "days": days,
        "window_hours": window_hours, "solve_interval_s": solve_interval_s,
        "policies": by_policy,
        "fixed_cycle_total_eur": fixed_tot, "advised_cycle_total_eur": a,
        "best_fixed_eur": best, "best_fixed_interval_days": float(fixed[int(np.argmin(totals))]),
        "median_fixed_eur": median, "advised_vs_best": a / best - 1.0,
        "advised_below_median": bool(a < median), "advised_saving_vs_median_eur": median - a,
        # the part the policies change: cost of fouling and cleaning per day, over complete cycles
        "fixed_excess_per_day_eur": fixed_ex, "advised_excess_per_day_eur": a_ex,
        "advised_excess_vs_best": a_ex / float(ex.min()) - 1.0,
        "advised_excess_vs_median": a_ex / float(np.median(ex)) - 1.0,
        "forecast": forecast_accuracy(adv, adv_run, t0),
        "forecast_step_ms": {"median": 1e3 * float(np.median(sec)), "p95": 1e3 * float(np.percentile(sec, 95)),
                             "max": 1e3 * float(np.max(sec)), "windows": int(len(sec)),
                             "cpu_median": 1e3 * float(np.median(cpu)), "cpu_p95": 1e3 * float(np.percentile(cpu, 95)),
                             "cpu_max": 1e3 * float(np.max(cpu))},
        # the chain's cost of fouling against the plant's true one over the same 2-h blocks
        "cost_of_fouling_eur_per_day": {"chain_mean": float(pairs[:, 0].mean()),
                                        "truth_mean": float(pairs[:, 1].mean()),
                                        "ratio_of_means": float(pairs[:, 0].mean() / pairs[:, 1].mean()),
                                        "windows": int(len(pairs))},
        "chain_window_s": {"median": float(np.median(adv.window_seconds)),
                           "max": float(np.max(adv.window_seconds))},
        "advised_trail": _trail(adv.log, t0),
    }
    if reduced:
        from model.analysis.cip_policy import bench_cip as reduced_bench
        result["reduced_plant"] = reduced_bench(seeds=(0,))
    result["wall_s"] = time.perf_counter() - wall
    return result


def _trail(log: list, t0: float) -> list:
    """Every 12th window of the advised run: what the advice said (days since t0)."""
    out = []
    for e in log[::12]:
        out.append({"day": round((e["t_end"] - t0) / DAY_S, 2), "since_reset_days": round(e["since"], 2),
                    "R_th_f_e-3": round(1e3 * e["R"], 3), "law": e["law"],
                    "T_opt_days": None if not math.isfinite(e["T_opt"]) else round(e["T_opt"], 2),
                    "days_to_cip": None if not math.isfinite(e["days_to_cip"]) else round(e["days_to_cip"], 2),
                    "removal_share": None if not math.isfinite(e["share"]) else round(e["share"], 3),
                    "cost_eur_per_day": None if not math.isfinite(e["cost"]) else round(e["cost"], 1)})
    return out
