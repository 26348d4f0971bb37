"""Plausibility limits of the commissioning (initial) calibration.

``hp-edge calibrate initial`` saves the fixed model that every later fouling estimate is measured
against. A calibration that fits badly, or that parks its factors on their bounds, or a clean
pressure-drop fit worse than the mean of its own data, is the sign of wrong input (e.g. swapped
columns), not of a plant: it is refused unless ``--force``, naming the limit that failed.

Limits (plant.yaml ``calibration.initial.limits``; every key optional, defaults below):

* ``max_objective_pct``: the weighted NRMSE objective of SPEC §5, in percent (default 5);
* ``max_parameters_at_bound``: how many parameters may end at a bound of their range (default 1:
  with the default targets one condenser-unit factor may, as they are not separately
  identifiable);
* ``min_dp_clean_r2``: R² of the clean pressure-drop fit (default 0: a fit worse than the mean of
  the data says the flow or pressure columns are not what they claim).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

DEFAULT_LIMITS = {"max_objective_pct": 5.0, "max_parameters_at_bound": 1,
                  "min_dp_clean_r2": 0.0}


@dataclass(frozen=True)
class CommissioningLimits:
    max_objective_pct: float = DEFAULT_LIMITS["max_objective_pct"]
    max_parameters_at_bound: int = DEFAULT_LIMITS["max_parameters_at_bound"]
    min_dp_clean_r2: float = DEFAULT_LIMITS["min_dp_clean_r2"]

    @classmethod
    def from_config(cls, extra: dict | None) -> CommissioningLimits:
        """plant.yaml ``calibration.initial.limits`` (``params.extra``); ValueError names the key."""
        cal = (extra or {}).get("calibration") or {}
        ini = cal.get("initial") if isinstance(cal, dict) else None
        node = ini.get("limits") if isinstance(ini, dict) else None
        if node is None:
            return cls()
        base = "calibration.initial.limits"
        if not isinstance(node, dict):
            raise ValueError(f"key '{base}': expected a mapping")
        unknown = sorted(set(node) - set(DEFAULT_LIMITS), key=str)
        if unknown:
            raise ValueError(f"key '{base}.{unknown[0]}': unknown (known: "
                             f"{', '.join(DEFAULT_LIMITS)})")
        kw = {}
        for key, v in node.items():
            ok = not isinstance(v, bool) and isinstance(v, (int, float)) \
                and (isinstance(v, float) or abs(v) < 2**1023) and math.isfinite(v)
            if key == "max_parameters_at_bound":
                ok = ok and isinstance(v, int) and v >= 0
            elif key == "max_objective_pct":
                ok = ok and v > 0
            if not ok:
                want = "an integer >= 0" if key == "max_parameters_at_bound" else \
                    ("a number > 0" if key == "max_objective_pct" else "a number")
                raise ValueError(f"key '{base}.{key}': expected {want}, got {v!r}"[:160])
            kw[key] = v
        return cls(**kw)

    def failures(self, initial, dp_clean) -> list[str]:
        """Which limits the initial calibration ``initial`` (model.calibration.CalibrationResult)
        and the clean pressure-drop fit ``dp_clean`` (model.dpfit.DpCleanFit) fail; empty when
        they are plausible."""
        out = []
        obj = 100.0 * initial.objective
        if not math.isfinite(obj) or obj > self.max_objective_pct:
            nrmse = ", ".join(f"{k} {100 * v:.2f} %" for k, v in initial.nrmse.items())
            out.append(f"calibration objective {obj:.2f} % exceeds max_objective_pct "
                       f"{self.max_objective_pct:g} % (NRMSE {nrmse})")
        at_bound = list(initial.at_bound)
        if len(at_bound) > self.max_parameters_at_bound:
            where = ", ".join(f"{n} {initial.params.get(n, math.nan):.4g} (bounds "
                              f"{initial.bounds[n][0]:g}..{initial.bounds[n][1]:g})"
                              if n in initial.bounds else n for n in at_bound)
            out.append(f"{len(at_bound)} parameters at a bound ({where}), more than "
                       f"max_parameters_at_bound {self.max_parameters_at_bound}")
        r2 = math.nan if dp_clean.r2 is None else float(dp_clean.r2)
        if not math.isfinite(r2) or r2 < self.min_dp_clean_r2:
            out.append(f"clean pressure-drop fit R^2 {r2:.3g} is below min_dp_clean_r2 "
                       f"{self.min_dp_clean_r2:g} (flow and pressure columns do not explain "
                       "each other)")
        return out
