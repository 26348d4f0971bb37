"""Compressor truth families whose curves have another SHAPE than plant.yaml's polynomials.

plant.yaml describes each compressor by 6-term polynomials in the pressure ratio pi and the speed
ratio n = N/N_nom (basis 1, pi, n, pi^2, pi*n, n^2). A plant judged only on perturbations of those
polynomials cannot show whether the advice survives compressors the model's form does not contain.
The families here use forms that polynomial cannot represent exactly:

  eta_is(pi, n)  = floor + (max - floor) * exp(-((ln(pi/pi_opt)/w_ln_pi)^2 + ((n - n_opt)/w_n)^2) / 2)
                   (a Gaussian peak in ln(pi) and n; with n_opt = None the speed term is absent)
  eta_vol(pi, n) = a - b * (pi^(1/k) - 1) - c * n
                   (clearance-volume re-expansion with polytropic exponent k, and valve throttling
                   growing with speed; c = 0: no speed effect)

so the swept flow phi(n) = eta_vol * n = A(pi) * n - c * n^2 is a quadratic in n and the speed
for a given mass flow has a closed form. ``ShapedCompressor`` is a ``model.params.Compressor`` (same
swept volume and speed range as plant.yaml's machine) that overrides exactly the three methods
model/cycle.py calls: ``eta_is_at``, ``eta_vol_at`` and ``speed_for_flow`` (and their vectorised
twins ``eta_is_v``, ``eta_vol_v``, ``speed_for_flow_v`` that model/vcycle.py calls), with the base class's
contract (linear continuation of phi beyond the speed bounds, ValueError when the flow does not rise
with speed). Its polynomial coefficient fields hold NaN: a family is not a polynomial, and code that
reads coefficients instead of calling the methods must fail loudly rather than use wrong numbers.

The families and their parameters live in config/simulator.yaml (``compressor_families:``); this
module holds the physics and the plausibility check only.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from model.params import Compressor

NAN6 = (math.nan,) * 6
# the range the families must stay plausible over (issue 8, item 8 of the simulator brief)
PI_RANGE = (1.5, 4.0)
RPM_RANGE = (700.0, 1800.0)

# family-parameter keys of one stage in simulator.yaml (compressor_families.NAME.LS/HS)
STAGE_KEYS = ("eta_is_max", "eta_is_floor", "pi_opt", "w_ln_pi", "n_opt", "w_n",
              "vol_a", "vol_b", "vol_k", "vol_c")


@dataclass(frozen=True)
class ShapedCompressor(Compressor):
    """A compressor with a Gaussian eta_is peak and a clearance-law eta_vol (module docstring).

    eta_is_max, eta_is_floor : peak value and far-field asymptote of eta_is [-]
    pi_opt : pressure ratio of the peak [-];  w_ln_pi : its width in ln(pi) [-]
    n_opt : speed ratio N/N_nom of the peak [-] (None: eta_is does not depend on speed);  w_n [-]
    vol_a, vol_b, vol_k, vol_c : eta_vol = vol_a - vol_b*(pi^(1/vol_k) - 1) - vol_c*n [-]
    family : the family's name (for messages and the truth record)
    """
    eta_is_max: float = 0.78
    eta_is_floor: float = 0.60
    pi_opt: float = 2.5
    w_ln_pi: float = 0.5
    n_opt: float | None = None
    w_n: float = 0.5
    vol_a: float = 0.97
    vol_b: float = 0.04
    vol_k: float = 1.3
    vol_c: float = 0.0
    family: str = ""

    # ------------------------------------------------------------------------ efficiencies ----
    def eta_is_at(self, pi: float, n: float) -> float:
        x = math.log(pi / self.pi_opt) / self.w_ln_pi
        q = x * x
        if self.n_opt is not None:
            y = (n - self.n_opt) / self.w_n
            q += y * y
        return self.eta_is_floor + (self.eta_is_max - self.eta_is_floor) * math.exp(-0.5 * q)

    def _vol_A(self, pi: float) -> float:
        """The speed-independent part of eta_vol at pressure ratio pi."""
        return self.vol_a - self.vol_b * (pi ** (1.0 / self.vol_k) - 1.0)

    def eta_vol_at(self, pi: float, n: float) -> float:
        return self._vol_A(pi) - self.vol_c * n

    # ---------------------------------------------------------------------- speed for flow ----
    def speed_for_flow(self, m: float, rho_suc: float, pi: float, n0: float = 1.0) -> tuple[float, float]:
        """Speed ratio n = N/N_nom at which the compressor moves mass flow m [kg/s] with suction
        density rho_suc [kg/m^3] at pressure ratio pi; returns (n, eta_vol).

        phi(n) = eta_vol(pi, n) * n = A n - c n^2 = m / (rho_suc * swept_volume), solved in closed
        form on the rising branch. Outside the speed range phi is continued linearly with its slope
        at the bound (as the base class does), so the speed a flow would need is defined and
        monotone beyond the limits. ValueError when phi does not rise with speed at a bound, or
        when the flow is too small for any positive speed. n0 (a warm start) is not needed.
        """
        A, c = self._vol_A(pi), self.vol_c
        target = m / (rho_suc * self.swept_volume)
        n_lo, n_hi = self.N_min / self.N_nom, self.N_max / self.N_nom
        for edge in (n_lo, n_hi):
            if A - 2.0 * c * edge <= 0.0:
                raise ValueError(f"volumetric-efficiency curve gives a flow that does not rise with "
                                 f"speed at pressure ratio {pi:.3f}, n={edge:.3f}")
        f_hi = (A - c * n_hi) * n_hi
        if target > f_hi:
            n = n_hi + (target - f_hi) / (A - 2.0 * c * n_hi)
            return n, target / n
        f_lo = (A - c * n_lo) * n_lo
        if target < f_lo:
            n = n_lo + (target - f_lo) / (A - 2.0 * c * n_lo)
            if n <= 0.0:
                raise ValueError(f"flow {m:.4g} kg/s is too small for the compressor curve")
            return n, target / n
        # smaller root of c n^2 - A n + target = 0, in the cancellation-free form
        n = 2.0 * target / (A + math.sqrt(A * A - 4.0 * c * target))
        return n, A - c * n

    # ------------------------------------------------ the vectorised protocol (model.vcycle) ----
    def eta_is_v(self, pi, n) -> np.ndarray:
        """``eta_is_at`` for arrays."""
        x = np.log(np.asarray(pi, dtype=float) / self.pi_opt) / self.w_ln_pi
        q = x * x
        if self.n_opt is not None:
            y = (np.asarray(n, dtype=float) - self.n_opt) / self.w_n
            q = q + y * y
        return self.eta_is_floor + (self.eta_is_max - self.eta_is_floor) * np.exp(-0.5 * q)

    def eta_vol_v(self, pi, n) -> np.ndarray:
        """``eta_vol_at`` for arrays."""
        return self._vol_A_v(pi) - self.vol_c * np.asarray(n, dtype=float)

    def _vol_A_v(self, pi) -> np.ndarray:
        return self.vol_a - self.vol_b * (np.asarray(pi, dtype=float) ** (1.0 / self.vol_k) - 1.0)

    def speed_for_flow_v(self, m, rho_suc, pi, n0=None) -> tuple[np.ndarray, np.ndarray]:
        """``speed_for_flow`` for arrays: (n, eta_vol), NaN in rows where it raises ValueError."""
        A, c = self._vol_A_v(pi), self.vol_c
        target = np.asarray(m, dtype=float) / (np.asarray(rho_suc, dtype=float) * self.swept_volume)
        A, target = np.broadcast_arrays(A, target)
        n_lo, n_hi = self.N_min / self.N_nom, self.N_max / self.N_nom
        bad = ~((A - 2.0 * c * n_lo > 0.0) & (A - 2.0 * c * n_hi > 0.0))
        f_hi = (A - c * n_hi) * n_hi
        f_lo = (A - c * n_lo) * n_lo
        above, below = target > f_hi, target < f_lo
        with np.errstate(divide="ignore", invalid="ignore"):
            n_out = np.where(above, n_hi + (target - f_hi) / (A - 2.0 * c * n_hi),
                             n_lo + (target - f_lo) / (A - 2.0 * c * n_lo))
            bad |= below & ~above & ~(n_out > 0.0)
            n_in = 2.0 * target / (A + np.sqrt(A * A - 4.0 * c * target))
            out = above | below
            n = np.where(out, n_out, n_in)
            ev = np.where(out, target / n, A - c * n)
        return np.where(bad, np.nan, n), np.where(bad, np.nan, ev)

    def replace(self, **kw) -> "ShapedCompressor":
        return dataclasses.replace(self, **kw)


def shaped_from(base: Compressor, family: str, stage: dict) -> ShapedCompressor:
    """A ShapedCompressor with ``base``'s swept volume and speed range and the family's curve
    parameters ``stage`` (keys STAGE_KEYS; missing keys take the class defaults)."""
    unknown = set(stage) - set(STAGE_KEYS)
    if unknown:
        raise KeyError(sorted(unknown)[0])
    return ShapedCompressor(swept_volume=base.swept_volume, N_nom=base.N_nom, N_min=base.N_min,
                            N_max=base.N_max, eta_is=NAN6, eta_vol=NAN6, family=family, **stage)


def curve_envelope(comp: Compressor, pi_range: tuple[float, float] = PI_RANGE,
                   rpm_range: tuple[float, float] = RPM_RANGE, points: int = 41) -> dict:
    """Ranges of eta_is, eta_vol and of the flow slope d(eta_vol*n)/dn [-] over a grid of the
    (pi, speed) region, for the plausibility checks of the config and the tests."""
    pis = np.linspace(pi_range[0], pi_range[1], points)
    ns = np.linspace(rpm_range[0], rpm_range[1], points) / comp.N_nom
    ei = np.array([[comp.eta_is_at(p, n) for n in ns] for p in pis])
    ev = np.array([[comp.eta_vol_at(p, n) for n in ns] for p in pis])
    flow = ev * ns[None, :]
    slope = np.diff(flow, axis=1) / np.diff(ns)[None, :]
    return {"eta_is_min": float(ei.min()), "eta_is_max": float(ei.max()),
            "eta_vol_min": float(ev.min()), "eta_vol_max": float(ev.max()),
            "flow_slope_min": float(slope.min()),
            "eta_is_argmax_pi": float(pis[np.unravel_index(ei.argmax(), ei.shape)[0]]),
            "eta_is_argmax_rpm": float(ns[np.unravel_index(ei.argmax(), ei.shape)[1]] * comp.N_nom)}


def polynomial_misfit(comp: Compressor, pi_range: tuple[float, float] = PI_RANGE,
                      rpm_range: tuple[float, float] = RPM_RANGE, points: int = 21) -> dict:
    """Largest error of the best least-squares fit of plant.yaml's 6-term polynomial to comp's
    eta_is and eta_vol over the region: > 0 shows the family is not in the model's form."""
    pis = np.linspace(pi_range[0], pi_range[1], points)
    ns = np.linspace(rpm_range[0], rpm_range[1], points) / comp.N_nom
    P, N = np.meshgrid(pis, ns, indexing="ij")
    P, N = P.ravel(), N.ravel()
    X = np.column_stack([np.ones_like(P), P, N, P * P, P * N, N * N])
    out = {}
    for name, fn in (("eta_is", comp.eta_is_at), ("eta_vol", comp.eta_vol_at)):
        y = np.array([fn(p, n) for p, n in zip(P, N)])
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        out[f"{name}_max_misfit"] = float(np.abs(X @ coef - y).max())
    return out
