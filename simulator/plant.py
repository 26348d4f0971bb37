"""The simulated plant: model/ with hidden true parameters, controllers, lags, fouling, CIP, noise.

Plant time advances in fixed ticks (``time.tick_s``), so a seed fixes the whole run, whatever the
wall-clock speed. Once per solve interval the quasi-steady state is solved with the boundary
conditions of that moment; between solves every sensor follows its steady value through a
first-order lag, and white noise is drawn per tick.

What the plant is and the model is not (on purpose; calibration must cope):
- hidden correction factors and perturbed compressor curves (config ``truth``);
- overall U of each heat exchanger varying with its water flow, 1/U = 1/U_nom * (s*(V_nom/V)^0.8 + 1-s);
- fouling (Kern-Seaton) and a growing source pressure-drop factor, partially removed by each CIP;
- lags, noise, and the register types' quantization (applied by the server / export).

Sensor mapping and the LS controller: simulator/sensors.py (shared with the synthetic histories
and the truth evaluator). HS speed holds p_m at the set-point register, p_m floats above it at
1800 rpm (the model's hs_max branch). The set point follows the register, and the PLC's own
schedule (control.p_m_sp_schedule) when one is configured: the schedule's steps are the operator's
local set point (``local_sp_bar_g``), which the plant follows except while the PLC's remote mode
is active (``remote``, set by the server's remote-set-point program, simulator/remote.py).

Compressors: plant.yaml's polynomials perturbed (truth.compressors.LS/HS), or a family of another
shape (truth.compressors.family, simulator/compressors.py).

CIPs: scheduled (cip.mode: schedule) or on request (cip.mode: on_request, ``request_cip()``).

Step-by-step use from Python (no server): ``Plant.tick()`` / ``advance_to(t)``; the one-minute rows
export_history writes come from ``simulator.export.MinuteStepper``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

from model.cycle import ModelError
from model.fluid import get_fluid
from model.params import Compressor, CycleInputs, PlantParams
from model.units import BAR, M3H, T0

from .compressors import curve_envelope, shaped_from
from .config import (NOMINAL, PERTURBED, FlowCfg, SimConfigError, SimulatorConfig, load_simulator_config,
                     load_yaml_file)
from .profiles import DAY, Boundary, CipSchedule, Fouling, Profiles
from .sensors import LSController, sensor_values

# plant-provided measurement tags (SPEC §4 canonical names) and their lag class
MEASURED = (
    ("T_sink_in", "temperature"), ("T_sink_out", "temperature"),
    ("T_source_in", "temperature"), ("T_source_out", "temperature"),
    ("V_sink", "flow"), ("V_source", "flow"),
    ("p_source_in", "pressure"), ("p_source_out", "pressure"),
    ("T_suc_LS", "temperature"), ("T_dis_LS", "temperature"),
    ("T_suc_HS", "temperature"), ("T_dis_HS", "temperature"),
    ("T_c", "temperature"), ("T_e", "temperature"),
    ("p_suc_LS", "pressure"), ("p_dis_LS", "pressure"),
    ("p_suc_HS", "pressure"), ("p_dis_HS", "pressure"),
    ("W_LS", "power"), ("W_HS", "power"),
    ("N_LS", "speed"), ("N_HS", "speed"),
)
NAMES = tuple(n for n, _ in MEASURED)
INDEX = {n: i for i, n in enumerate(NAMES)}
FLAGS = ("running", "cip")


@dataclass
class SteadyPoint:
    """The plant's quasi-steady state at one solve (engineering units) and its hidden truth."""
    values: dict[str, float]
    res: object | None          # model CycleResult (None when stopped or failed)
    T_source_out_C: float
    ls_limit: str               # "" | "max" | "min": LS at a speed bound, T_source_out floating
    p_m_sp_bar_g: float = math.nan   # the set point this state was solved at


def load_params(cfg: SimulatorConfig) -> PlantParams:
    return PlantParams.from_dict(load_yaml_file(cfg.plant_file))


def true_params(nominal: PlantParams, cfg: SimulatorConfig) -> PlantParams:
    """Nominal parameters with the hidden truth applied (fouling and flow effects come later)."""
    t = cfg.truth
    comps = true_compressors(nominal, cfg)
    return nominal.replace(CF_eva=t.CF_eva, CF_con=t.CF_con, CF_DSH=t.CF_DSH, CF_SC=t.CF_SC,
                           R_th_f=0.0, CF_dp_f=1.0, comp_LS=comps["LS"], comp_HS=comps["HS"])


def true_compressors(nominal: PlantParams, cfg: SimulatorConfig) -> dict[str, Compressor]:
    """{"LS": ..., "HS": ...}: the plant's real compressors. Family "perturbed": plant.yaml's
    polynomials with eta' = scale*eta + pi_tilt*(pi - 2.5) + n_tilt*(n - 1); "nominal":
    plant.yaml's polynomials; any other: a ShapedCompressor with the family's parameters (same
    swept volume and speed range)."""
    t = cfg.truth
    family = t.compressor_family
    out: dict[str, Compressor] = {}
    for name in ("LS", "HS"):
        comp = getattr(nominal, f"comp_{name}")
        if family == NOMINAL:
            pass
        elif family == PERTURBED:
            ct = t.compressors.get(name)
            if ct is not None:
                ei = [ct.eta_is_scale * c for c in comp.eta_is]
                ei[0] -= 2.5 * ct.eta_is_pi_tilt      # + tilt*(pi - 2.5)
                ei[1] += ct.eta_is_pi_tilt
                ev = [ct.eta_vol_scale * c for c in comp.eta_vol]
                ev[0] -= ct.eta_vol_n_tilt            # + tilt*(n - 1)
                ev[2] += ct.eta_vol_n_tilt
                comp = comp.replace(eta_is=tuple(ei), eta_vol=tuple(ev))
        else:
            where = f"{cfg.path or '<simulator config>'}: compressor_families.{family}.{name}"
            try:
                comp = shaped_from(comp, family, cfg.compressor_families[family][name])
            except KeyError as exc:
                raise SimConfigError(f"{where}: unknown key {exc}") from None
            env = curve_envelope(comp, rpm_range=(comp.N_min, comp.N_max))
            if not (env["flow_slope_min"] > 0 and 0.05 < env["eta_is_min"] and env["eta_is_max"] <= 1.0
                    and 0.0 < env["eta_vol_min"] and env["eta_vol_max"] <= 1.0):
                raise SimConfigError(
                    f"{where}: the curves are not physical over pressure ratio 1.5-4 and "
                    f"{comp.N_min:.0f}-{comp.N_max:.0f} rpm (eta_is {env['eta_is_min']:.3f}.."
                    f"{env['eta_is_max']:.3f}, eta_vol {env['eta_vol_min']:.3f}..{env['eta_vol_max']:.3f}, "
                    f"lowest flow slope {env['flow_slope_min']:.3f}; need 0.05 < eta_is <= 1, "
                    f"0 < eta_vol <= 1 and a flow rising with speed)")
        out[name] = comp
    return out


def flow_factor(V: float, V_nom: float, share: float, exponent: float) -> float:
    """U(V)/U(V_nom) when the water-side film (share of the resistance at V_nom) scales with V^exp."""
    if V <= 0:
        return 0.0
    return 1.0 / (share * (V_nom / V) ** exponent + 1.0 - share)


def effective_params(true: PlantParams, flow: FlowCfg, V_source_m3h: float, V_sink_m3h: float,
                     R_th_f_K_per_kW: float, CF_dp_f: float) -> PlantParams:
    """What the plant really is at these water flows [m3/h] and this fouling: the true parameters
    with the flow-dependent heat-transfer factors (model-form discrepancy) and the fouling."""
    g_eva = flow_factor(V_source_m3h, flow.V_source_nom_m3h, flow.water_side_share_eva, flow.exponent)
    g_con = flow_factor(V_sink_m3h, flow.V_sink_nom_m3h, flow.water_side_share_con, flow.exponent)
    return true.replace(CF_eva=true.CF_eva * g_eva, CF_con=true.CF_con * g_con,
                        CF_DSH=true.CF_DSH * g_con, CF_SC=true.CF_SC * g_con,
                        R_th_f=R_th_f_K_per_kW * 1e-3, CF_dp_f=CF_dp_f)


class Plant:
    """The hidden plant. ``tick()`` advances one tick; ``advance_to(t)`` as many as needed.

    After each tick ``measured`` holds every sensor (engineering units, with noise, before the
    register quantization and before faults), ``flags`` running/cip, ``p_m_sp_bar_g`` the set point.
    ``truth_records`` collects one hidden-truth dict per truth interval (drained by the caller).
    ``set_p_m_sp(bar_g)`` is a client write; ``request_cip()`` asks for a CIP (cip.mode on_request);
    ``cip_log`` lists every CIP (start, end, fouling before and after, requested or scheduled).
    Not thread-safe: one caller at a time (the server steps it in one worker thread).
    """

    def __init__(self, cfg: SimulatorConfig | None = None, params: PlantParams | None = None):
        self.cfg = cfg = cfg or load_simulator_config()
        self.nominal = params or load_params(cfg)
        self.true = true_params(self.nominal, cfg)
        self.amb = cfg.ambient_pressure_bar
        ss = np.random.SeedSequence(cfg.seed)
        weather_ss, noise_ss, cip_ss = ss.spawn(3)
        self._noise_rng = np.random.default_rng(noise_ss)
        self.t0 = cfg.start_epoch
        self.k = 0                                    # ticks done
        self.dt = cfg.time.tick_s
        self._solve_every = max(1, round(cfg.time.solve_interval_s / self.dt))
        self._truth_every = max(1, round(cfg.time.truth_interval_s / self.dt))
        self.profiles = Profiles(cfg.profiles, np.random.default_rng(weather_ss), self.t0)
        self.fouling = Fouling(cfg.fouling)
        self.cip_schedule = (CipSchedule(cfg.cip, np.random.default_rng(cip_ss), self.t0)
                             if cfg.cip.mode == "schedule" else None)
        self.cip_window: tuple[float, float] | None = None
        self.cip_count = 0
        self.cip_pending = False                      # requested, starts at the next tick
        self.cip_requests = 0
        self.cip_log: list[dict] = []
        self.running = True
        self.p_m_sp_bar_g = cfg.control.p_m_sp_bar_g
        self.local_sp_bar_g = cfg.control.p_m_sp_bar_g   # the operator's local set point
        self.remote = False        # the PLC's remote mode: the schedule moves only the local set point
        self._sp_schedule = [(self.t0 + day * DAY, bar) for day, bar in cfg.control.p_m_sp_schedule]
        self._sp_next = 0
        self.sp_steps = 0                             # schedule steps applied (the server follows)
        self._apply_sp_schedule(self.t0)
        self.ls = LSController()
        self.boundary: Boundary = self.profiles.advance(self.t0)
        lag = cfg.lags_s
        self._alpha = np.array([math.exp(-self.dt / getattr(lag, c)) if getattr(lag, c) > 0 else 0.0
                                for _, c in MEASURED])
        self._sigma = np.array([cfg.noise.get(n, 0.0) for n in NAMES])
        self.solve_failures = 0
        self.last_error = ""
        self._guess = None
        self._opt_cache: tuple[int, dict] | None = None
        self.truth_records: list[dict] = []
        self.steady = self._steady_state()
        self._x = self._vector(self.steady.values)   # lagged state: start in steady state
        self._zero_when_off = np.array([INDEX[n] for n in ("N_LS", "N_HS", "W_LS", "W_HS",
                                                             "V_source", "V_sink")])
        self.record_truth = True                     # export computes truth itself
        self.noisy = self._x.copy()
        self._emit()

    # ------------------------------------------------------------------------------ time ----
    @property
    def t(self) -> float:
        """Plant time [epoch s]."""
        return self.t0 + self.k * self.dt

    @property
    def flags(self) -> dict[str, int]:
        return {"running": int(self.running), "cip": int(self.cip_window is not None)}

    def set_p_m_sp(self, bar_g: float) -> float:
        """Apply a new set point (clamped into control.p_m_sp_limits_bar_g); returns what is used.
        The plant follows from the next solve on (within a solve interval plus the lags)."""
        lo, hi = self.cfg.control.p_m_sp_limits_bar_g
        v = min(max(float(bar_g), lo), hi) if math.isfinite(bar_g) else self.p_m_sp_bar_g
        self.p_m_sp_bar_g = v
        return v

    def request_cip(self) -> bool:
        """Ask for a CIP (cip.mode on_request): it starts at the next tick, with the configured
        duration and removal shares. Returns False (and changes nothing) when a CIP is already
        in progress or pending. RuntimeError in cip.mode schedule (the PLC cleans by its own
        schedule there)."""
        if self.cfg.cip.mode != "on_request":
            raise RuntimeError("CIP on request needs cip.mode: on_request in the simulator config "
                               f"(it is {self.cfg.cip.mode!r})")
        if self.cip_window is not None or self.cip_pending:
            return False
        self.cip_pending = True
        self.cip_requests += 1
        return True

    def _apply_sp_schedule(self, t: float) -> None:
        """The PLC's own set-point steps that are due at plant time t (each applied once, so a
        client write in between holds until the next step). They are the operator's local set
        point: in remote mode only ``local_sp_bar_g`` moves (the active set point is the remote
        one), and ``sp_steps`` counts the steps applied to the active set point."""
        while self._sp_next < len(self._sp_schedule) and t >= self._sp_schedule[self._sp_next][0] - 1e-9:
            lo, hi = self.cfg.control.p_m_sp_limits_bar_g
            self.local_sp_bar_g = min(max(float(self._sp_schedule[self._sp_next][1]), lo), hi)
            self._sp_next += 1
            if not self.remote:
                self.set_p_m_sp(self.local_sp_bar_g)
                self.sp_steps += 1

    def advance_to(self, t: float, max_ticks: int | None = None) -> int:
        """Tick until plant time reaches t (at most max_ticks); returns the ticks done."""
        n = 0
        while self.t + self.dt <= t + 1e-9 and (max_ticks is None or n < max_ticks):
            self.tick()
            n += 1
        return n

    def tick(self) -> None:
        self.k += 1
        t = self.t
        self._events(t)
        if self.running:
            self.fouling.advance(self.dt)
        if self.k % self._solve_every == 0:
            self.steady = self._steady_state()
        target = self._vector(self.steady.values)
        self._x = target + (self._x - target) * self._alpha
        self._emit()
        if self.record_truth and self.k % self._truth_every == 0:
            self.truth_records.append(self.truth())

    def _emit(self) -> None:
        noisy = self._x + self._sigma * self._noise_rng.standard_normal(len(NAMES))
        if not self.running:   # a stopped machine reads exact zeros on speed, power and flow
            z = self._zero_when_off
            noisy[z] = np.where(self._x[z] < 0.5, 0.0, noisy[z])
        self.noisy = noisy

    @property
    def measured(self) -> dict[str, float]:
        """Every sensor after the last tick [engineering units], noise included, before the
        register quantization and before faults."""
        return dict(zip(NAMES, self.noisy.tolist()))

    def _events(self, t: float) -> None:
        self._apply_sp_schedule(t)
        start = None
        if self.cip_window is None:
            if self.cip_schedule is not None and t >= self.cip_schedule.next_start:
                start = self.cip_schedule.pop()
            elif self.cip_pending:
                start = (t, t + self.cfg.cip.duration_days * DAY)
        if start is not None:
            self.cip_window = start
            self.cip_log.append({"start": start[0], "end": start[1], "requested": self.cip_pending,
                                 "R_th_f_before_K_per_kW": self.fouling.R,
                                 "CF_dp_f_before": self.fouling.CF_dp})
            self.cip_pending = False
            self.running = False
            self.steady = self._steady_state()
            # compressors and pumps stop at once; temperatures and pressures settle through the lags
            self._x[self._zero_when_off] = 0.0
        elif self.cip_window is not None and t >= self.cip_window[1]:
            c = self.cfg.cip
            self.fouling.clean(c.removal_share, c.dp_removal_share)
            self.cip_log[-1].update({"R_th_f_after_K_per_kW": self.fouling.R,
                                     "CF_dp_f_after": self.fouling.CF_dp})
            self.cip_window = None
            self.cip_count += 1
            self.running = True
            self._guess = None
            self.steady = self._steady_state()

    @staticmethod
    def _vector(values: dict[str, float]) -> np.ndarray:
        return np.array([values[n] for n in NAMES], dtype=float)

    # ----------------------------------------------------------------------- steady state ----
    def effective_params(self, V_source_m3h: float, V_sink_m3h: float) -> PlantParams:
        """True parameters at these flows and the present fouling (what the plant really is now)."""
        return effective_params(self.true, self.cfg.flow_dependence, V_source_m3h, V_sink_m3h,
                                self.fouling.R, self.fouling.CF_dp)

    def inputs(self, b: Boundary, T_source_out_C: float | None = None,
               p_m_sp_bar_g: float | None = None) -> CycleInputs:
        T_out = self.cfg.control.T_source_out_sp_C if T_source_out_C is None else T_source_out_C
        p_sp = self.p_m_sp_bar_g if p_m_sp_bar_g is None else p_m_sp_bar_g
        return CycleInputs(T_source_in=b.T_source_in_C + T0, T_source_out=T_out + T0,
                           T_sink_in=b.T_sink_in_C + T0, V_source=b.V_source_m3h * M3H,
                           V_sink=b.V_sink_m3h * M3H, p_m_sp=(p_sp + self.amb) * BAR)

    def solve_controlled(self, inp: CycleInputs, params: PlantParams, guess=None):
        """Solve with the plant's LS controller (simulator.sensors.LSController.solve):
        returns (result, T_source_out [K], ls_limit). Raises ModelError when unsolvable."""
        return self.ls.solve(inp, params, guess)

    def _steady_state(self) -> SteadyPoint:
        self.boundary = b = self.profiles.advance(self.t)
        if not self.running:
            return self._standstill(b)
        params = self.effective_params(b.V_source_m3h, b.V_sink_m3h)
        try:
            res, T_out, limit = self.solve_controlled(self.inputs(b), params, self._guess)
        except (ModelError, ValueError) as exc:
            # the real plant would keep running: hold the previous steady state, note it in truth
            self.solve_failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            self._guess = None
            prev = getattr(self, "steady", None)
            return prev if prev is not None and prev.res is not None else self._standstill(b)
        if not limit:
            self.ls.T_out_float = None
        self._guess = res
        return SteadyPoint(self._sensor_values(b, res, T_out), res, T_out - T0, limit, self.p_m_sp_bar_g)

    def _sensor_values(self, b: Boundary, r, T_out: float) -> dict[str, float]:
        return sensor_values(r, T_source_in_C=b.T_source_in_C, T_sink_in_C=b.T_sink_in_C,
                             V_source_m3h=b.V_source_m3h, V_sink_m3h=b.V_sink_m3h,
                             T_source_out_C=T_out - T0, ambient_bar=self.amb,
                             p_source_in_bar_g=b.p_source_in_bar_g, T_c_location=self.cfg.sensors.T_c,
                             motor_efficiency=self.cfg.truth.motor_efficiency)

    def _standstill(self, b: Boundary) -> SteadyPoint:
        T_s = self.cfg.control.standstill_T_C
        p_s = get_fluid(self.true.fluid, self.true.backend).sat_T(T_s + T0).p / BAR - self.amb
        v = {n: 0.0 for n in NAMES}
        v.update({"T_sink_in": b.T_sink_in_C, "T_sink_out": b.T_sink_in_C,
                  "T_source_in": b.T_source_in_C, "T_source_out": b.T_source_in_C,
                  "p_source_in": b.p_source_in_bar_g, "p_source_out": b.p_source_in_bar_g})
        for n in ("T_suc_LS", "T_dis_LS", "T_suc_HS", "T_dis_HS", "T_c", "T_e"):
            v[n] = T_s
        for n in ("p_suc_LS", "p_dis_LS", "p_suc_HS", "p_dis_HS"):
            v[n] = p_s
        return SteadyPoint(v, None, b.T_source_in_C, "", self.p_m_sp_bar_g)

    # ------------------------------------------------------------------------------ truth ----
    def cop_optimum(self) -> dict:
        """COP-optimal p_m at the present conditions with the true parameters: a coarse scan of
        p_m,sp between p_e and p_c, refined by a bounded scalar search. Cached per optimum interval."""
        every = max(1, round(self.cfg.time.optimum_interval_s / self.dt))
        slot = self.k // every
        if self._opt_cache is not None and self._opt_cache[0] == slot:
            return self._opt_cache[1]
        out = {"p_m_opt_bar_g": math.nan, "p_m_sp_opt_bar_g": math.nan, "COP_opt": math.nan,
               "opt_hs_saturated": False}
        r0 = self.steady.res
        if self.running and r0 is not None:
            b = self.boundary
            params = self.effective_params(b.V_source_m3h, b.V_sink_m3h)
            amb = self.amb
            cache: dict[float, tuple[float, float, bool]] = {}

            def cop(p_sp_g: float) -> float:
                key = round(p_sp_g, 4)
                if key not in cache:
                    try:
                        r, _, _ = self.solve_controlled(self.inputs(b, p_m_sp_bar_g=p_sp_g), params, r0)
                        cache[key] = (r.COP, r.p_m / BAR - amb, r.hs_saturated)
                    except (ModelError, ValueError):
                        cache[key] = (-math.inf, math.nan, False)
                return cache[key][0]

            saved = self.ls.T_out_float
            lo, hi = r0.p_e / BAR - amb + 0.5, r0.p_c / BAR - amb - 0.5
            grid = np.linspace(lo, hi, 9)
            vals = [cop(p) for p in grid]
            i = int(np.argmax(vals))
            a, c = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
            gr = (math.sqrt(5) - 1) / 2            # golden section on [a, c]
            x1, x2 = c - gr * (c - a), a + gr * (c - a)
            f1, f2 = cop(x1), cop(x2)
            for _ in range(12):
                if f1 >= f2:
                    c, x2, f2 = x2, x1, f1
                    x1 = c - gr * (c - a)
                    f1 = cop(x1)
                else:
                    a, x1, f1 = x1, x2, f2
                    x2 = a + gr * (c - a)
                    f2 = cop(x2)
            self.ls.T_out_float = saved
            best = max(cache, key=lambda k: cache[k][0])
            COP_opt, p_m_opt, hs_sat = cache[best]
            if math.isfinite(COP_opt):
                # on the HS-saturation plateau every lower set point gives the same p_m: report
                # the set point that just reaches it
                out = {"p_m_opt_bar_g": p_m_opt, "p_m_sp_opt_bar_g": p_m_opt if hs_sat else float(best),
                       "COP_opt": COP_opt, "opt_hs_saturated": bool(hs_sat)}
        self._opt_cache = (slot, out)
        return out

    def truth(self) -> dict:
        """Hidden truth at the present tick (plain floats, JSON-ready)."""
        b, sp = self.boundary, self.steady
        params = self.effective_params(b.V_source_m3h, b.V_sink_m3h)
        R_clean = 1e3 / params.UA_eva_clean if params.CF_eva > 0 else math.nan   # K/kW
        rec = {
            "t": self.t,
            "time": datetime.fromtimestamp(self.t, timezone.utc).isoformat().replace("+00:00", "Z"),
            "running": int(self.running), "cip": int(self.cip_window is not None),
            "cip_count": self.cip_count,
            "R_th_f_K_per_kW": self.fouling.R, "CF_dp_f": self.fouling.CF_dp,
            "R_th_f_share_pct": 100.0 * self.fouling.R / (self.fouling.R + R_clean),
            "CF_eva": self.true.CF_eva, "CF_con": self.true.CF_con, "CF_DSH": self.true.CF_DSH,
            "CF_SC": self.true.CF_SC,
            "CF_eva_eff": params.CF_eva, "CF_con_eff": params.CF_con,
            "CF_DSH_eff": params.CF_DSH, "CF_SC_eff": params.CF_SC,
            "p_m_sp_bar_g": self.p_m_sp_bar_g, "T_source_out_C": sp.T_source_out_C,
            "ls_limit": sp.ls_limit, "weather": b.weather, "solve_failures": self.solve_failures,
            # what re-running the plant at another set point needs (simulator.truth.TruthModel)
            "T_source_in_C": b.T_source_in_C, "T_sink_in_C": b.T_sink_in_C,
            "V_source_m3h": b.V_source_m3h, "V_sink_m3h": b.V_sink_m3h,
            "T_source_out_sp_C": self.cfg.control.T_source_out_sp_C,
            "p_m_sp_solved_bar_g": sp.p_m_sp_bar_g,
            "compressor_family": self.cfg.truth.compressor_family,
            "cip_pending": int(self.cip_pending), "cip_requests": self.cip_requests,
        }
        r = sp.res
        if r is not None and self.running:
            amb = self.amb
            rec.update({
                "COP": r.COP, "Q_sink_kW": r.Q_sink / 1e3, "Q_source_kW": r.Q_source / 1e3,
                "W_total_kW": r.W_total / 1e3, "p_e_bar_g": r.p_e / BAR - amb,
                "p_m_bar_g": r.p_m / BAR - amb, "p_c_bar_g": r.p_c / BAR - amb,
                "N_LS": r.N_LS, "N_HS": r.N_HS, "hs_saturated": bool(r.hs_saturated),
                "eta_is_LS": r.eta_is_LS, "eta_is_HS": r.eta_is_HS,
                "p_m_gm_bar_g": math.sqrt(r.p_e * r.p_c) / BAR - amb,
                "eta_vol_LS": r.eta_vol_LS, "eta_vol_HS": r.eta_vol_HS,
                "W_electric_kW": r.W_total / 1e3 / self.cfg.truth.motor_efficiency,
                "subcooling_K": r.subcooling,
            })
            rec.update(self.cop_optimum())
        else:
            rec.update({k: math.nan for k in ("COP", "Q_sink_kW", "Q_source_kW", "W_total_kW",
                                              "p_e_bar_g", "p_m_bar_g", "p_c_bar_g", "N_LS", "N_HS",
                                              "eta_is_LS", "eta_is_HS", "p_m_gm_bar_g",
                                              "eta_vol_LS", "eta_vol_HS", "W_electric_kW",
                                              "subcooling_K",
                                              "p_m_opt_bar_g", "p_m_sp_opt_bar_g", "COP_opt")})
            rec["hs_saturated"] = rec["opt_hs_saturated"] = False
        return rec

    def drain_truth(self) -> list[dict]:
        out, self.truth_records = self.truth_records, []
        return out

