"""Refrigerant properties through CoolProp's low-level ``AbstractState`` interface.

One cached AbstractState per fluid and backend; SI in, SI out [K, Pa, J/kg, J/kg/K, kg/m^3].

Measured traps this module avoids (see issue #2):
- ``PropsSI`` costs ~100 us per call: never used here.
- A (P,T) flash next to saturation raises in HEOS and is silently wrong with tabular backends:
  saturated states use (P,Q)/(Q,T); the 1-K superheated suction state uses a (P,T) flash with the
  gas phase imposed, always on HEOS.
- A (P,S) flash costs ~80 us in HEOS; the isentropic discharge state is found instead by a 2-D Newton
  on (rho, T) with analytic derivatives of the Helmholtz EOS (~3 us per step, 2-4 steps warm).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import CoolProp.CoolProp as CP
from CoolProp import AbstractState

_BACKENDS = ("HEOS", "BICUBIC&HEOS", "TTSE&HEOS")


class PropertyError(RuntimeError):
    """A property call failed or did not converge (state outside the fluid's valid region)."""


@dataclass(frozen=True)
class SatState:
    """Saturated liquid and vapour at one pressure."""
    p: float        # [Pa]
    T: float        # saturation temperature [K]
    h_f: float      # saturated liquid enthalpy [J/kg]
    h_g: float      # saturated vapour enthalpy [J/kg]
    s_g: float      # saturated vapour entropy [J/kg/K]
    rho_g: float    # saturated vapour density [kg/m^3]


class Fluid:
    """Property wrapper for one pure fluid. Not thread-safe: use one instance per thread."""

    def __init__(self, name: str = "Ammonia", backend: str = "HEOS"):
        if backend not in _BACKENDS:
            raise ValueError(f"property backend {backend!r} is not one of {', '.join(_BACKENDS)}")
        self.name = name
        self.backend = backend
        self._heos = AbstractState("HEOS", name)
        self._gas = AbstractState("HEOS", name)
        self._gas.specify_phase(CP.iphase_gas)
        self._liq = AbstractState("HEOS", name)
        self._liq.specify_phase(CP.iphase_liquid)
        self._liq_rho = AbstractState("HEOS", name)      # liquid by (rho, T) Newton (no flash)
        self._tab = None if backend == "HEOS" else AbstractState(backend, name)
        self.T_crit = self._heos.T_critical()
        self.p_crit = self._heos.p_critical()
        self.T_triple = self._heos.Ttriple()
        self.rho_crit = self._heos.rhomass_critical()
        self._sat_cache: dict[tuple[str, float], SatState] = {}

    # ---- saturation -------------------------------------------------------------------------
    def _sat(self, kind: str, value: float) -> SatState:
        key = (kind, value)
        hit = self._sat_cache.get(key)
        if hit is not None:
            return hit
        AS = self._tab or self._heos
        try:
            if kind == "T":
                AS.update(CP.QT_INPUTS, 1.0, value)
            else:
                AS.update(CP.PQ_INPUTS, value, 1.0)
            p, T = AS.p(), AS.T()
            h_g, s_g, rho_g = AS.hmass(), AS.smass(), AS.rhomass()
            AS.update(CP.QT_INPUTS, 0.0, T)
            h_f = AS.hmass()
        except ValueError as exc:
            raise PropertyError(f"{self.name} saturation at {kind}={value:.6g}: {exc}") from exc
        sat = SatState(p=p, T=T, h_f=h_f, h_g=h_g, s_g=s_g, rho_g=rho_g)
        if len(self._sat_cache) > 4096:
            self._sat_cache.clear()
        self._sat_cache[key] = sat
        return sat

    def sat_T(self, T: float) -> SatState:
        """Saturation state at temperature T [K]."""
        if not (self.T_triple < T < self.T_crit):
            raise PropertyError(f"{self.name}: T={T:.3f} K outside the two-phase range "
                                f"{self.T_triple:.2f}..{self.T_crit:.2f} K")
        return self._sat("T", T)

    def sat_p(self, p: float) -> SatState:
        """Saturation state at pressure p [Pa]."""
        if not (0.0 < p < self.p_crit):
            raise PropertyError(f"{self.name}: p={p:.6g} Pa outside the two-phase range")
        return self._sat("p", p)

    def h_liq_sat(self, T: float) -> float:
        """Saturated-liquid enthalpy at T [K] (subcooled liquid enthalpy to < 0.1 % here)."""
        return self.sat_T(T).h_f

    def liquid_pT(self, p: float, T: float) -> float:
        """Enthalpy [J/kg] of (subcooled) liquid at pressure p [Pa] and temperature T [K], from the
        equation of state with the liquid phase imposed (exact next to saturation, ~9 us)."""
        try:
            self._liq.update(CP.PT_INPUTS, p, T)
            return self._liq.hmass()
        except ValueError as exc:
            raise PropertyError(f"{self.name} liquid at p={p:.6g} Pa, T={T:.4f} K: {exc}") from exc

    def liquid_pT_rho(self, p: float, T: float, rho: float | None) -> tuple[float, float]:
        """(h [J/kg], rho [kg/m^3]) of (subcooled) liquid at (p, T), by Newton on p(rho, T) from the
        density ``rho`` of a nearby liquid state (~5 us against ~9 us for the (P,T) flash); the
        (P,T) flash when no guess is given or Newton leaves the liquid side. Converged to 1e-12 in
        density, so the result does not depend on the guess beyond round-off."""
        if rho is not None and rho > 0.0:
            AS = self._liq_rho
            rho_c = self.rho_crit
            for _ in range(8):
                try:
                    AS.update(CP.DmassT_INPUTS, rho, T)
                    f = AS.p() - p
                    dp = AS.first_partial_deriv(CP.iP, CP.iDmass, CP.iT)
                except ValueError:
                    break
                if not dp > 0.0:
                    break
                step = f / dp
                rho -= step
                if not rho > rho_c:
                    break
                if abs(step) <= 1e-12 * rho:
                    AS.update(CP.DmassT_INPUTS, rho, T)
                    return AS.hmass(), rho
        try:
            self._liq.update(CP.PT_INPUTS, p, T)
            return self._liq.hmass(), self._liq.rhomass()
        except ValueError as exc:
            raise PropertyError(f"{self.name} liquid at p={p:.6g} Pa, T={T:.4f} K: {exc}") from exc

    # ---- superheated vapour -----------------------------------------------------------------
    def vapour_pT(self, p: float, T: float) -> tuple[float, float, float]:
        """(h, s, rho) of superheated vapour at (p, T). Uses HEOS with the gas phase imposed, which
        is exact and safe right next to saturation (the LS suction is only 1 K superheated)."""
        rho = self._rho_pT(p, T)
        if rho is not None:
            return self._gas.hmass(), self._gas.smass(), rho
        try:
            self._gas.update(CP.PT_INPUTS, p, T)
            return self._gas.hmass(), self._gas.smass(), self._gas.rhomass()
        except ValueError as exc:
            raise PropertyError(f"{self.name} vapour at p={p:.6g} Pa, T={T:.4f} K: {exc}") from exc

    def _rho_pT(self, p: float, T: float) -> float | None:
        """Vapour density at (p, T) by Newton on p(rho, T) (the HEOS (P,T) flash costs ~50 us; this
        ~10 us), started from the gas with a compressibility of 0.9 (always the same start, so the
        result does not depend on what this process computed before: a replay's windows give the
        same numbers in any worker); leaves ``_gas`` at the solution. None when it does not converge
        on the vapour branch."""
        AS = self._gas
        rho = p / (0.9 * 488.2 * T)
        for _ in range(12):
            try:
                AS.update(CP.DmassT_INPUTS, rho, T)
                f = AS.p() - p
                dp = AS.first_partial_deriv(CP.iP, CP.iDmass, CP.iT)
            except ValueError:
                return None
            if not dp > 0.0:
                return None
            step = f / dp
            rho -= step
            if rho <= 0.0:
                return None
            if abs(step) <= 1e-11 * rho:
                AS.update(CP.DmassT_INPUTS, rho, T)
                if rho > AS.rhomolar_critical() * AS.molar_mass():
                    return None
                return rho
        return None

    def isentropic(self, p: float, s: float, guess: tuple[float, float] | None = None
                   ) -> tuple[float, float, float]:
        """(h, T, rho) of superheated vapour at pressure p [Pa] and entropy s [J/kg/K].

        ``guess`` is (rho, T) of a nearby solution (warm start). With a tabular backend the (P,S)
        table lookup is used directly (far from saturation, where tables are accurate).
        """
        if self._tab is not None:
            try:
                self._tab.update(CP.PSmass_INPUTS, p, s)
                return self._tab.hmass(), self._tab.T(), self._tab.rhomass()
            except ValueError as exc:
                raise PropertyError(f"{self.name} (p={p:.6g}, s={s:.6g}): {exc}") from exc
        rho, T = self._newton_rhoT(p, s, CP.iSmass, guess)
        if rho is None:   # Newton failed (not expected in the superheated region): slow flash
            try:
                self._heos.update(CP.PSmass_INPUTS, p, s)
                return self._heos.hmass(), self._heos.T(), self._heos.rhomass()
            except ValueError as exc:
                raise PropertyError(f"{self.name} isentropic state p={p:.6g}, s={s:.6g}: {exc}") from exc
        return self._gas.hmass(), T, rho

    def vapour_ph(self, p: float, h: float, guess: tuple[float, float] | None = None
                  ) -> tuple[float, float]:
        """(T, rho) of superheated vapour from pressure p [Pa] and enthalpy h [J/kg].

        A HEOS (h,p) flash costs ~75 us; the (rho, T) Newton seeded with a nearby state ~10 us."""
        if self._tab is not None:
            try:
                self._tab.update(CP.HmassP_INPUTS, h, p)
                return self._tab.T(), self._tab.rhomass()
            except ValueError as exc:
                raise PropertyError(f"{self.name} (p={p:.6g}, h={h:.6g}): {exc}") from exc
        rho, T = self._newton_rhoT(p, h, CP.iHmass, guess)
        if rho is None:
            return self.T_ph(p, h), math.nan
        return T, rho

    def _newton_rhoT(self, p: float, target: float, key: int, guess):
        """Solve p(rho, T) = p and key(rho, T) = target on the gas branch; (None, None) if no luck."""
        AS = self._gas
        if guess is None:
            sat = self.sat_p(p) if p < self.p_crit else None
            T = (sat.T + 40.0) if sat else 450.0
            rho = p / (488.2 * T)       # ideal gas, R_specific of ammonia = 8.314/0.017031
        else:
            rho, T = guess
        for _ in range(30):
            try:
                AS.update(CP.DmassT_INPUTS, rho, T)
                f1 = AS.p() - p
                f2 = AS.keyed_output(key) - target
                a = AS.first_partial_deriv(CP.iP, CP.iDmass, CP.iT)
                b = AS.first_partial_deriv(CP.iP, CP.iT, CP.iDmass)
                c = AS.first_partial_deriv(key, CP.iDmass, CP.iT)
                d = AS.first_partial_deriv(key, CP.iT, CP.iDmass)
            except ValueError:
                return None, None
            det = a * d - b * c
            if det == 0.0 or not math.isfinite(det):
                return None, None
            d_rho = (f1 * d - b * f2) / det
            d_T = (a * f2 - c * f1) / det
            lam = 1.0             # damp steps that would leave the physical domain
            while rho - lam * d_rho <= 0.0 or abs(lam * d_T) > 0.3 * T:
                lam *= 0.5
            rho -= lam * d_rho
            T -= lam * d_T
            if abs(d_T) < 1e-9 * T and abs(f1) < 1e-9 * p:
                AS.update(CP.DmassT_INPUTS, rho, T)
                return rho, T
        return None, None

    def T_ph(self, p: float, h: float) -> float:
        """Temperature [K] from pressure [Pa] and enthalpy [J/kg] (any phase; slow HEOS flash)."""
        try:
            self._heos.update(CP.HmassP_INPUTS, h, p)
            return self._heos.T()
        except ValueError as exc:
            raise PropertyError(f"{self.name} (p={p:.6g}, h={h:.6g}): {exc}") from exc


_LOCAL = threading.local()


def get_fluid(name: str = "Ammonia", backend: str = "HEOS") -> Fluid:
    """The Fluid for (name, backend) of the calling thread (AbstractState is not thread-safe)."""
    cache = getattr(_LOCAL, "fluids", None)
    if cache is None:
        cache = _LOCAL.fluids = {}
    key = (name, backend)
    f = cache.get(key)
    if f is None:
        f = cache[key] = Fluid(name, backend)
    return f
