"""Clean source-side pressure drop dp_clean(V_source) fitted on a clean window (SPEC §3, §5).

dp_source = CF_dp,f * dp_clean(V_source): the fouling factor CF_dp,f is only as good as this curve.
Forms:
- ``quadratic``: dp = c0 + c1*V + c2*V^2, least squares on V scaled to [-1, 1] (well conditioned).
  Needs a real spread of flows (a site acceptance test that steps the source flow);
- ``pure_quadratic``: dp = c2*V^2 (turbulent flow through the origin). The only safe choice when the
  window's flows are narrow: a full quadratic fitted on a few percent of flow range extrapolates
  wildly;
- ``auto`` (default): ``quadratic`` when the flows span at least ``min_relative_span``
  (max/min - 1) and the fitted curve rises over the fitted range, else ``pure_quadratic``; the result
  says which was used and why.
Units: V in m3/h, dp in bar (as in config/plant.yaml ``source_pressure_drop.dp_clean_coef``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

MIN_RELATIVE_SPAN = 0.2      # flows must span >= 20 % for a full quadratic
MIN_SAMPLES = 10
FORMS = ("auto", "quadratic", "pure_quadratic")


class DpFitError(ValueError):
    """The clean pressure-drop fit cannot be made (too few samples, bad values, unknown form)."""


@dataclass
class DpCleanFit:
    coef_bar: tuple[float, float, float]     # c0 [bar], c1 [bar/(m3/h)], c2 [bar/(m3/h)^2]
    form: str
    r2: float
    rmse_bar: float
    n_samples: int
    V_range_m3h: tuple[float, float]
    note: str = ""
    window_start: str | None = None
    window_end: str | None = None
    extra: dict = field(default_factory=dict)

    def dp(self, V_m3h):
        c0, c1, c2 = self.coef_bar
        V = np.asarray(V_m3h, dtype=float)
        return c0 + c1 * V + c2 * V * V

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["coef_bar"] = [float(c) for c in self.coef_bar]
        d["V_range_m3h"] = [float(v) for v in self.V_range_m3h]
        d["r2"] = float(self.r2) if math.isfinite(self.r2) else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "DpCleanFit":
        c = d.get("coef_bar")
        if not (isinstance(c, (list, tuple)) and len(c) == 3):
            raise DpFitError(f"dp_clean state: 'coef_bar' must be 3 numbers, got {c!r}")
        kw = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
        kw["coef_bar"] = tuple(float(x) for x in c)
        kw["V_range_m3h"] = tuple(kw.get("V_range_m3h", (math.nan, math.nan)))
        kw["r2"] = math.nan if kw.get("r2") is None else float(kw["r2"])
        kw.setdefault("form", "quadratic")
        kw.setdefault("rmse_bar", math.nan)
        kw.setdefault("n_samples", 0)
        return cls(**kw)


def fit_dp_clean(V_m3h, dp_bar, form: str = "auto", min_relative_span: float = MIN_RELATIVE_SPAN,
                 window: tuple[str, str] | None = None) -> DpCleanFit:
    """Fit dp_clean(V) on the samples of a clean window (non-finite pairs are left out)."""
    if form not in FORMS:
        raise DpFitError(f"dp_clean form {form!r} is not one of {', '.join(FORMS)}")
    V = np.asarray(V_m3h, dtype=float)
    dp = np.asarray(dp_bar, dtype=float)
    ok = np.isfinite(V) & np.isfinite(dp) & (V > 0)
    V, dp = V[ok], dp[ok]
    if len(V) < MIN_SAMPLES:
        raise DpFitError(f"clean pressure-drop fit needs at least {MIN_SAMPLES} samples with flow, got {len(V)}")
    v_lo, v_hi = float(V.min()), float(V.max())
    span = v_hi / v_lo - 1.0
    note = ""
    use = form
    if form == "auto":
        use = "quadratic" if span >= min_relative_span else "pure_quadratic"
        if use == "pure_quadratic":
            note = (f"flows span only {100 * span:.1f} % (< {100 * min_relative_span:.0f} %): "
                    "fitted dp = c2*V^2 through the origin")
    if use == "quadratic":
        mid, half = 0.5 * (v_lo + v_hi), 0.5 * (v_hi - v_lo)
        if half <= 0:
            raise DpFitError("clean pressure-drop fit: all samples have the same flow")
        z = (V - mid) / half
        a = np.linalg.lstsq(np.column_stack([np.ones_like(z), z, z * z]), dp, rcond=None)[0]
        # back to V: a0 + a1 z + a2 z^2 with z = (V - mid)/half
        c2 = a[2] / half ** 2
        c1 = a[1] / half - 2.0 * a[2] * mid / half ** 2
        c0 = a[0] - a[1] * mid / half + a[2] * mid ** 2 / half ** 2
        coef = (float(c0), float(c1), float(c2))
        slope_lo = c1 + 2 * c2 * v_lo
        if form == "auto" and not slope_lo > 0:
            use = "pure_quadratic"
            note = "the full quadratic does not rise over the fitted flows: fitted dp = c2*V^2"
    if use == "pure_quadratic":
        c2 = float(np.sum(V * V * dp) / np.sum(V ** 4))
        coef = (0.0, 0.0, c2)
    pred = coef[0] + coef[1] * V + coef[2] * V * V
    ss_res = float(np.sum((dp - pred) ** 2))
    ss_tot = float(np.sum((dp - dp.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan
    ws = (str(window[0]), str(window[1])) if window else (None, None)
    return DpCleanFit(coef_bar=coef, form=use, r2=r2, rmse_bar=math.sqrt(ss_res / len(V)),
                      n_samples=int(len(V)), V_range_m3h=(v_lo, v_hi), note=note,
                      window_start=ws[0], window_end=ws[1])
