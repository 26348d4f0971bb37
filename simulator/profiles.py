"""Boundary conditions of the simulated plant: daily profiles, weather drift, fouling, CIP.

All functions of plant time t [epoch s]; the random parts draw from a numpy Generator the caller
owns, so a given seed reproduces the same weather, demand and CIP dates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .config import CipCfg, FoulingCfg, ProfileCfg

DAY = 86400.0
HOUR = 3600.0


@dataclass(frozen=True)
class Boundary:
    """Water-side boundary conditions at one moment (engineering units)."""
    T_source_in_C: float
    T_sink_in_C: float
    V_source_m3h: float
    V_sink_m3h: float
    p_source_in_bar_g: float
    weather: float               # dimensionless weather state (for the truth log)


class Profiles:
    """Daily sinusoids plus a slow Ornstein-Uhlenbeck 'weather' state."""

    def __init__(self, cfg: ProfileCfg, rng: np.random.Generator, t0: float):
        self.cfg = cfg
        self.rng = rng
        self.t = t0
        self.weather = float(rng.normal(0.0, cfg.weather_sigma)) if cfg.weather_sigma > 0 else 0.0

    @staticmethod
    def _daily(t: float, peak_hour: float) -> float:
        """cos wave of period one day, +1 at peak_hour (UTC), -1 twelve hours later."""
        hour = (t % DAY) / HOUR
        return math.cos(2.0 * math.pi * (hour - peak_hour) / 24.0)

    def advance(self, t: float) -> Boundary:
        """Advance the weather state to t (exact OU transition) and return the boundary at t."""
        c = self.cfg
        dt = t - self.t
        if dt > 0 and c.weather_sigma > 0:
            a = math.exp(-dt / (c.weather_tau_h * HOUR))
            self.weather = self.weather * a + c.weather_sigma * math.sqrt(1.0 - a * a) * float(
                self.rng.normal())
        self.t = max(self.t, t)
        w = self.weather
        T_src = (c.T_source_in_mean_C + c.T_source_in_daily_amp_K * self._daily(t, c.T_source_in_peak_hour)
                 + c.weather_T_source_K * w)
        T_src = min(max(T_src, c.limits_T_source_in_C[0]), c.limits_T_source_in_C[1])
        T_sink = c.T_sink_in_mean_C + c.T_sink_in_daily_amp_K * self._daily(t, c.T_sink_in_peak_hour)
        V_sink = c.V_sink_mean_m3h * (1.0 + c.V_sink_daily_amp * self._daily(t, c.V_sink_peak_hour)
                                      + c.weather_V_sink * w)
        V_sink = min(max(V_sink, c.limits_V_sink_m3h[0]), c.limits_V_sink_m3h[1])
        V_src = c.V_source_mean_m3h * (1.0 + c.V_source_daily_amp * self._daily(t, c.V_source_peak_hour))
        return Boundary(T_src, T_sink, V_src, V_sink, c.p_source_in_bar_g, w)


class Fouling:
    """Evaporator fouling, Kern-Seaton asymptotic law integrated from the current state:
        dR/dt = (R_inf - R)/tau,  d(CF-1)/dt = ((CF_inf-1) - (CF-1))/tau_dp
    (from a clean start R(t) = R_inf (1 - exp(-t/tau))). Grows only while the plant runs.
    R in K/kW (config unit); the plant converts to K/W for the model.
    """

    def __init__(self, cfg: FoulingCfg):
        self.cfg = cfg
        self.R = cfg.R_th_f_initial_K_per_kW
        self.CF_dp = cfg.CF_dp_f_initial

    def advance(self, dt: float) -> None:
        c = self.cfg
        a = math.exp(-dt / (c.tau_days * DAY))
        self.R = c.R_th_f_inf_K_per_kW - (c.R_th_f_inf_K_per_kW - self.R) * a
        b = math.exp(-dt / (c.tau_dp_days * DAY))
        self.CF_dp = c.CF_dp_f_inf - (c.CF_dp_f_inf - self.CF_dp) * b

    def clean(self, removal_share: float, dp_removal_share: float) -> None:
        self.R *= 1.0 - removal_share
        self.CF_dp = 1.0 + (self.CF_dp - 1.0) * (1.0 - dp_removal_share)


class CipSchedule:
    """CIP start times: first after first_after_days, then every interval_days, each +- jitter."""

    def __init__(self, cfg: CipCfg, rng: np.random.Generator, t0: float):
        self.cfg = cfg
        self.rng = rng
        self._nominal = t0 + cfg.first_after_days * DAY
        self.next_start = self._jittered(self._nominal)

    def _jittered(self, t: float) -> float:
        j = self.cfg.jitter_days
        return t + (float(self.rng.uniform(-j, j)) * DAY if j > 0 else 0.0)

    def pop(self) -> tuple[float, float]:
        """Return (start, end) of the due CIP and schedule the next one."""
        start = self.next_start
        end = start + self.cfg.duration_days * DAY
        self._nominal += self.cfg.interval_days * DAY
        self.next_start = max(self._jittered(self._nominal), end + DAY)
        return start, end
