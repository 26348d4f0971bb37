"""Plant parameters and cycle inputs (SI units) and their construction from a config dict.

``model/`` never reads YAML: the caller parses config/plant.yaml and passes the dict to
``PlantParams.from_dict``; errors name the key path so the caller can name the file.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .units import BAR, DEFAULT_AMBIENT_BAR, M3H

POLY_BASIS = ("1", "pi", "n", "pi^2", "pi*n", "n^2")   # n = N / nominal_speed_rpm


class ParamError(ValueError):
    """A parameter dict is incomplete or invalid; the message names the key path."""


def _finite(v) -> bool:
    """A finite int or float (not a bool; an integer too large for a float is not finite)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return bool(np.isfinite(float(v)))
    except OverflowError:
        return False


def _short(v, limit: int = 60) -> str:
    text = repr(v)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def poly_basis(pi: float, n: float) -> tuple[float, ...]:
    return (1.0, pi, n, pi * pi, pi * n, n * n)


@dataclass(frozen=True)
class Compressor:
    """Variable-speed reciprocating compressor.

    swept_volume : swept volume flow at the nominal speed [m^3/s]
    N_nom, N_min, N_max : nominal, lowest and highest speed [rpm]
    eta_is, eta_vol : 6 coefficients each on POLY_BASIS (pressure ratio pi, n = N/N_nom) [-]
    drive_factor : electric power / shaft power m*(h_dis - h_suc) [-]: motor, drive and heat losses
        (1 for the model's adiabatic compressor on its shaft; learned from data, SPEC §9)
    """
    swept_volume: float
    N_nom: float
    N_min: float
    N_max: float
    eta_is: tuple[float, ...]
    eta_vol: tuple[float, ...]
    drive_factor: float = 1.0

    def eta_is_at(self, pi: float, n: float) -> float:
        c = self.eta_is
        return c[0] + c[1] * pi + c[2] * n + c[3] * pi * pi + c[4] * pi * n + c[5] * n * n

    def eta_vol_at(self, pi: float, n: float) -> float:
        c = self.eta_vol
        return c[0] + c[1] * pi + c[2] * n + c[3] * pi * pi + c[4] * pi * n + c[5] * n * n

    def speed_for_flow(self, m: float, rho_suc: float, pi: float, n0: float = 1.0) -> tuple[float, float]:
        """Speed ratio n = N/N_nom at which the compressor moves mass flow m [kg/s] with suction
        density rho_suc [kg/m^3] at pressure ratio pi; returns (n, eta_vol).

        Solves phi(n) = eta_vol(pi, n) * n = m / (rho_suc * swept_volume), a cubic in n, by Newton.
        Outside the speed range phi is continued linearly with its slope at the bound, so that the
        speed the flow would need is still defined (and monotone) when it lies beyond the limits;
        callers decide what an out-of-range speed means.
        """
        c = self.eta_vol
        a0 = c[0] + c[1] * pi + c[3] * pi * pi      # eta_vol = a0 + a1 n + a2 n^2
        a1 = c[2] + c[4] * pi
        a2 = c[5]
        target = m / (rho_suc * self.swept_volume)
        n_lo, n_hi = self.N_min / self.N_nom, self.N_max / self.N_nom

        def phi(n: float) -> tuple[float, float]:
            return (a0 + n * (a1 + n * a2)) * n, a0 + n * (2.0 * a1 + 3.0 * n * a2)

        for edge in (n_lo, n_hi):
            if phi(edge)[1] <= 0.0:
                raise ValueError(f"volumetric-efficiency curve gives a flow that does not rise with "
                                 f"speed at pressure ratio {pi:.3f}, n={edge:.3f}")
        f_hi, d_hi = phi(n_hi)
        if target > f_hi:
            n = n_hi + (target - f_hi) / d_hi
            return n, target / n
        f_lo, d_lo = phi(n_lo)
        if target < f_lo:
            n = n_lo + (target - f_lo) / d_lo
            if n <= 0.0:
                raise ValueError(f"flow {m:.4g} kg/s is too small for the compressor curve")
            return n, target / n
        n = min(max(n0, n_lo), n_hi)
        for _ in range(50):
            f, df = phi(n)
            if df <= 0.0:
                raise ValueError(f"volumetric-efficiency curve gives a flow that does not rise with "
                                 f"speed at pressure ratio {pi:.3f}, n={n:.3f}")
            step = (f - target) / df
            n = min(max(n - step, n_lo), n_hi)
            if abs(step) < 1e-13:
                break
        return n, a0 + n * (a1 + n * a2)

    # ---- the vectorised protocol (model.vcycle): numpy arrays in, arrays out, the same numbers as
    # the scalar methods to round-off. A subclass that overrides a scalar method must override its
    # vectorised twin too, or model.vcycle loops the scalar method instead.
    def eta_is_v(self, pi, n) -> np.ndarray:
        """``eta_is_at`` for arrays of pressure ratio pi [-] and speed ratio n [-]."""
        c = self.eta_is
        return c[0] + c[1] * pi + c[2] * n + c[3] * pi * pi + c[4] * pi * n + c[5] * n * n

    def eta_vol_v(self, pi, n) -> np.ndarray:
        """``eta_vol_at`` for arrays."""
        c = self.eta_vol
        return c[0] + c[1] * pi + c[2] * n + c[3] * pi * pi + c[4] * pi * n + c[5] * n * n

    def speed_for_flow_v(self, m, rho_suc, pi, n0=None) -> tuple[np.ndarray, np.ndarray]:
        """``speed_for_flow`` for arrays of m [kg/s], rho_suc [kg/m^3], pi [-] (n0: warm starts of
        the speed ratio, default 1): (n, eta_vol), NaN in rows where the scalar method raises
        ValueError (a curve whose flow does not rise with speed, a flow too small for any speed).
        The same Newton on the cubic; once a step is below 1e-7 the next is below 1e-13 (quadratic
        convergence), so that step is the last (the scalar method takes one more, below 1e-13)."""
        return cubic_speed(self.eta_vol, self.swept_volume, self.N_min / self.N_nom, self.N_max / self.N_nom,
                           m, rho_suc, pi, n0)

    def replace(self, **kw) -> "Compressor":
        return dataclasses.replace(self, **kw)


def cubic_speed(c, swept_volume: float, n_lo: float, n_hi: float, m, rho_suc, pi, n0=None):
    """``Compressor.speed_for_flow_v`` for the curve coefficients ``c`` (six scalars, or six arrays
    with one curve per row: a stage's compressors of several windows at once)."""
    c0, c1, c2, c3, c4, c5 = c
    with np.errstate(all="ignore"):
        m, rho_suc, pi = (np.asarray(x, dtype=float) for x in (m, rho_suc, pi))
        a0 = c0 + pi * (c1 + c3 * pi)                    # eta_vol = a0 + a1 n + a2 n^2
        a1 = c2 + c4 * pi
        target = m / (rho_suc * swept_volume)
        # phi(n) = (a0 + a1 n + c5 n^2) n and its slope at the bounds, as polynomials in pi
        f_lo = n_lo * (c0 + n_lo * (c2 + c5 * n_lo)) + pi * (n_lo * (c1 + c4 * n_lo) + c3 * n_lo * pi)
        f_hi = n_hi * (c0 + n_hi * (c2 + c5 * n_hi)) + pi * (n_hi * (c1 + c4 * n_hi) + c3 * n_hi * pi)
        d_lo = (c0 + n_lo * (2.0 * c2 + 3.0 * c5 * n_lo)) + pi * (c1 + 2.0 * c4 * n_lo + c3 * pi)
        d_hi = (c0 + n_hi * (2.0 * c2 + 3.0 * c5 * n_hi)) + pi * (c1 + 2.0 * c4 * n_hi + c3 * pi)
        bad = ~((d_lo > 0.0) & (d_hi > 0.0))
        above, below = target > f_hi, target < f_lo
        out = above | below
        inside = ~(out | bad)
        n = np.ones(target.shape) if n0 is None else np.asarray(n0, dtype=float)
        n = np.minimum(np.maximum(np.where(n == n, n, 1.0), n_lo), n_hi)
        concave = c5 <= 0.0      # the slope is concave in n: positive inside where at both bounds
        for _ in range(50):
            df = a0 + n * (2.0 * a1 + 3.0 * c5 * n)
            if not np.all(concave):
                rising = df > 0.0
                if np.ndim(concave):
                    rising |= concave
                bad |= inside & ~rising
                inside &= rising
            step = np.where(inside, ((a0 + n * (a1 + n * c5)) * n - target) / df, 0.0)
            finite = np.isfinite(step)      # a NaN row (NaN inputs) must not end the others'
            bad |= ~finite                  # iteration (NaN >= 1e-7 is False)
            inside &= finite
            step = np.where(finite, step, 0.0)
            n = np.minimum(np.maximum(n - step, n_lo), n_hi)
            if not np.abs(step).max(initial=0.0) >= 1e-7:
                break
        ev = a0 + n * (a1 + n * c5)
        if out.any():
            n_out = np.where(above, n_hi + (target - f_hi) / d_hi, n_lo + (target - f_lo) / d_lo)
            bad |= below & ~above & ~(n_out > 0.0)
            n = np.where(out, n_out, n)
            ev = np.where(out, target / n_out, ev)
        if bad.any():
            n, ev = np.where(bad, np.nan, n), np.where(bad, np.nan, ev)
    return n, ev


@dataclass(frozen=True)
class PlantParams:
    """Design data of SPEC §2 plus calibration parameters, SI units."""
    fluid: str
    backend: str
    ambient_pressure: float            # [Pa]
    cp_w: float                        # water heat capacity [J/kg/K]
    rho_w: float                       # water density [kg/m^3]
    U_eva: float                       # [W/m^2/K]
    A_eva: float                       # [m^2]
    superheat: float                   # LS suction superheat [K]
    U_DSH: float
    A_DSH: float
    U_con: float
    A_con: float
    U_SC: float
    A_SC: float
    design_pinch: float                # [K], reported, not imposed
    p_c_max: float                     # condenser design pressure [Pa abs]: above it, infeasible
    comp_LS: Compressor
    comp_HS: Compressor
    dp_clean_coef: tuple[float, float, float]   # dp_clean = c0 + c1 V + c2 V^2, V [m^3/s], dp [Pa]
    CF_DSH: float = 1.0
    CF_con: float = 1.0
    CF_SC: float = 1.0
    CF_eva: float = 1.0
    R_th_f: float = 0.0                # evaporator fouling resistance [K/W]
    CF_dp_f: float = 1.0
    extra: dict = field(default_factory=dict, compare=False, hash=False)  # calibration settings etc.

    def replace(self, **kw) -> "PlantParams":
        """``dataclasses.replace(self, **kw)`` without the generated ``__init__`` (the solver asks for
        ~60 a window: per-row parameters, calibration trials): the same fields, no
        ``__post_init__`` to run, values taken as given as ``replace`` does."""
        bad = [k for k in kw if k not in _PLANT_FIELDS]
        if bad:
            raise TypeError(f"PlantParams.replace: unknown field(s) {', '.join(map(repr, bad))}")
        new = object.__new__(type(self))
        d = new.__dict__
        d.update(self.__dict__)
        d.update(kw)
        return new

    # derived conductances [W/K]
    @property
    def UA_eva_clean(self) -> float:
        return self.CF_eva * self.U_eva * self.A_eva

    @property
    def UA_eva(self) -> float:
        return 1.0 / (1.0 / self.UA_eva_clean + self.R_th_f)

    def dp_clean(self, V_source):
        c0, c1, c2 = self.dp_clean_coef
        return c0 + c1 * V_source + c2 * V_source * V_source

    @classmethod
    def from_dict(cls, d: dict) -> "PlantParams":
        """Build from the plant.yaml dict (units in the key names: bar, m3/h, kJ, K/kW, ...)."""
        errors: list[str] = []

        class _Missing(Exception):
            pass

        def get(path: str):
            node = d
            for part in path.split("."):
                if not isinstance(node, dict) or part not in node:
                    errors.append(f"missing key '{path}'")
                    raise _Missing
                node = node[part]
            return node

        def collect(fn, *a, default=float("nan")):
            try:
                return fn(*a)
            except _Missing:
                return default
            except ParamError as exc:
                errors.append(str(exc))
                return default

        def num(path: str, positive: bool = True) -> float:
            v = get(path)
            if not _finite(v):
                raise ParamError(f"key '{path}': expected a number, got {_short(v)}")
            if positive and v <= 0:
                raise ParamError(f"key '{path}': must be > 0, got {v!r}")
            return float(v)

        def coeffs(path: str) -> tuple[float, ...]:
            v = get(path)
            if (not isinstance(v, (list, tuple)) or len(v) != len(POLY_BASIS)
                    or not all(_finite(x) for x in v)):
                raise ParamError(f"key '{path}': expected {len(POLY_BASIS)} numbers on the basis "
                                 f"{', '.join(POLY_BASIS)}, got {_short(v)}")
            return tuple(float(x) for x in v)

        def compressor(name: str) -> Compressor:
            base = f"compressors.{name}"
            N_nom = num(f"{base}.nominal_speed_rpm")
            comp = Compressor(
                swept_volume=num(f"{base}.swept_volume_m3_per_h") * M3H,
                N_nom=N_nom, N_min=num(f"{base}.speed_min_rpm"), N_max=num(f"{base}.speed_max_rpm"),
                eta_is=coeffs(f"{base}.eta_is"), eta_vol=coeffs(f"{base}.eta_vol"))
            if comp.N_min >= comp.N_max:
                raise ParamError(f"key '{base}.speed_min_rpm': must be below speed_max_rpm")
            return comp

        def dp_coef():
            dp = get("source_pressure_drop.dp_clean_coef")
            if not (isinstance(dp, (list, tuple)) and len(dp) == 3 and all(_finite(x) for x in dp)):
                raise ParamError("key 'source_pressure_drop.dp_clean_coef': expected 3 numbers "
                                 "[bar, bar/(m3/h), bar/(m3/h)^2]")
            # config: dp [bar] with V [m3/h]  ->  SI: dp [Pa] with V [m3/s]
            return (dp[0] * BAR, dp[1] * BAR / M3H, dp[2] * BAR / M3H ** 2)
        if not isinstance(d, dict):
            raise ParamError(f"expected a mapping of keys, got {type(d).__name__}")
        cal = d.get("calibrated", {}) or {}
        if not isinstance(cal, dict):
            errors.append("key 'calibrated': expected a mapping")
            cal = {}

        def calnum(key: str, default: float) -> float:
            v = cal.get(key, default)
            if not _finite(v) or v < 0:
                raise ParamError(f"key 'calibrated.{key}': expected a number >= 0, got {_short(v)}")
            return float(v)

        def text(key: str, default: str) -> str:
            v = d.get(key, default)
            if not isinstance(v, str) or not v:
                errors.append(f"key '{key}': expected a name, got {_short(v)}")
                return default
            return v

        def ambient() -> float:
            v = d.get("ambient_pressure_bar", DEFAULT_AMBIENT_BAR)
            if not _finite(v) or not 0.5 <= v <= 1.2:
                raise ParamError(f"key 'ambient_pressure_bar': expected a number of bar within "
                                 f"0.5..1.2, got {_short(v)}")
            return float(v)

        kwargs = dict(
            fluid=text("fluid", "Ammonia"), backend=text("property_backend", "HEOS"),
            ambient_pressure=collect(ambient, default=DEFAULT_AMBIENT_BAR) * BAR,
            cp_w=collect(num, "water.cp_kJ_per_kgK") * 1e3, rho_w=collect(num, "water.rho_kg_per_m3"),
            U_eva=collect(num, "evaporator.U_W_per_m2K"), A_eva=collect(num, "evaporator.A_m2"),
            superheat=collect(num, "evaporator.superheat_K"),
            U_DSH=collect(num, "desuperheater.U_W_per_m2K"), A_DSH=collect(num, "desuperheater.A_m2"),
            U_con=collect(num, "condenser.U_W_per_m2K"), A_con=collect(num, "condenser.A_m2"),
            design_pinch=collect(num, "condenser.design_pinch_K"),
            p_c_max=collect(num, "condenser.design_pressure_bar_a") * BAR,
            U_SC=collect(num, "subcooler.U_W_per_m2K"), A_SC=collect(num, "subcooler.A_m2"),
            comp_LS=collect(compressor, "LS", default=None), comp_HS=collect(compressor, "HS", default=None),
            dp_clean_coef=collect(dp_coef, default=(0.0, 0.0, 0.0)),
            CF_DSH=collect(calnum, "CF_DSH", 1.0), CF_con=collect(calnum, "CF_con", 1.0), CF_SC=collect(calnum, "CF_SC", 1.0),
            CF_eva=collect(calnum, "CF_eva", 1.0), R_th_f=collect(calnum, "R_th_f_K_per_kW", 0.0) * 1e-3,
            CF_dp_f=collect(calnum, "CF_dp_f", 1.0),
            extra={k: v for k, v in d.items()
                   if k in ("calibration", "optimization", "surrogate", "advice", "compressor_learning",
                            "surrogate_tracker", "cip")},
        )
        if errors:
            raise ParamError("\n".join(errors))
        return cls(**kwargs)


_PLANT_FIELDS = frozenset(f.name for f in dataclasses.fields(PlantParams))


@dataclass(frozen=True)
class CycleInputs:
    """One quasi-steady operating point (one-minute average), SI units.

    T_source_in, T_source_out, T_sink_in : water temperatures [K]
    V_source, V_sink : water volume flows [m^3/s]
    p_m_sp : intermediate-pressure set point, absolute [Pa]
    """
    T_source_in: float
    T_source_out: float
    T_sink_in: float
    V_source: float
    V_sink: float
    p_m_sp: float

    def replace(self, **kw) -> "CycleInputs":
        return dataclasses.replace(self, **kw)
