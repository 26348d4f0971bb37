"""Polynomial surrogate of the set-point optimization (SPEC §6, the papers' Eq. 12).

Inputs x = (eta_is,LS * eta_is,HS, p_e [bar a], p_c [bar a]), each *scaled* to z in [-1, 1] over the
range the surrogate was fitted on; basis: the 27 products z1^i * z2^j * z3^k, i, j, k in 0..2.
Outputs: the optimal intermediate pressure p_m_opt_bar_a [bar a], and the changes of the period COP
and of the heat output [%] at the optimum against operation at the *reference* set point.

Definition of the inputs (what the gateway must feed): the adaptive model's state at the reference
set point (``reference_p_m_sp_barg``, default 10 bar(g), the operators' business-as-usual practice of
SPEC §2) for the current boundary conditions: its two isentropic efficiencies and its p_e and p_c.

Fitting data: the adaptive model's optima (``model.optimize``) for operating points drawn at random
(seeded) within configured ranges at each of a grid of fouling levels; a seeded 70/30 train/test
split; R^2 per output on both parts. The published coefficients (up to 8e7) show an unscaled basis
and cannot be reused; scaling makes the least-squares problem well conditioned.

Evaluation refuses inputs outside the fitted ranges (``SurrogateRangeError`` names the input, its
value and the range): a polynomial extrapolates badly.
"""
from __future__ import annotations

import itertools
import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .batch import simulate_batch
from .optimize import OptimizationError, optimize_setpoint
from .params import PlantParams

FORMAT = "hp-edge-surrogate/1"
INPUTS = (("eta_is_product", "-"), ("p_e_bar_a", "bar a"), ("p_c_bar_a", "bar a"))
OUTPUTS = (("p_m_opt_bar_a", "bar a"), ("dCOP_pct", "%"), ("dQ_sink_pct", "%"))
EXPONENTS = tuple(itertools.product(range(3), repeat=3))     # 27 terms, (i, j, k)
TRAIN_SHARE = 0.7

# default sampling design: fouling levels x random operating points
DEFAULT_DESIGN = {
    "reference_p_m_sp_barg": 10.0,
    "fouling_levels_K_per_kW": [0.0, 1.5e-3, 3.0e-3, 4.5e-3, 6.0e-3, 7.5e-3],
    "points_per_level": 60,
    "T_source_in_C": [22.0, 27.0],         # wastewater 23-25 degC (SPEC §2), with margin
    "source_cooling_K": [4.0, 8.0],        # T_source,in - T_source,out
    "T_sink_in_C": [37.0, 43.0],           # district-heating return ~40 degC
    "V_source_m3h": [170.0, 210.0],
    "V_sink_m3h": [50.0, 74.0],
    "seed": 1,
}


class SurrogateError(ValueError):
    """A surrogate file is invalid, or a fit cannot be made."""


class SurrogateRangeError(SurrogateError):
    """An input lies outside the range the surrogate was fitted on."""


def _basis(Z: np.ndarray) -> np.ndarray:
    """Design matrix (n, 27) from scaled inputs Z (n, 3)."""
    pw = [[np.ones(len(Z)), Z[:, d], Z[:, d] ** 2] for d in range(3)]
    return np.column_stack([pw[0][i] * pw[1][j] * pw[2][k] for i, j, k in EXPONENTS])


def r2_score(y: np.ndarray, yhat: np.ndarray) -> float:
    ss_res = float(np.sum((y - yhat) ** 2))
    ss_tot = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 - ss_res / ss_tot if ss_tot > 0 else math.nan


@dataclass
class Surrogate:
    ranges: tuple[tuple[float, float], ...]            # per input (min, max) of the training data
    coef: tuple[tuple[float, ...], ...]                # per output, 27 coefficients on EXPONENTS
    r2_test: dict[str, float] = field(default_factory=dict)
    r2_train: dict[str, float] = field(default_factory=dict)
    n_train: int = 0
    n_test: int = 0
    reference_p_m_sp_barg: float = 10.0
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        if len(self.ranges) != 3 or any(not (lo < hi) for lo, hi in self.ranges):
            raise SurrogateError(f"surrogate ranges must be 3 pairs (min < max), got {self.ranges!r}")
        if len(self.coef) != 3 or any(len(c) != len(EXPONENTS) for c in self.coef):
            raise SurrogateError(f"surrogate needs 3 outputs x {len(EXPONENTS)} coefficients")
        self._c = [(0.5 * (lo + hi), 2.0 / (hi - lo)) for lo, hi in self.ranges]
        self._coef = [tuple(float(x) for x in c) for c in self.coef]

    # ---- evaluation ----------------------------------------------------------------------------
    def evaluate(self, eta_is_product: float, p_e_bar_a: float, p_c_bar_a: float) -> tuple[float, float, float]:
        """(p_m_opt_bar_a, dCOP_pct, dQ_sink_pct). Raises SurrogateRangeError outside the fitted ranges."""
        x = (eta_is_product, p_e_bar_a, p_c_bar_a)
        z = []
        for (name, unit), v, (lo, hi), (c, s) in zip(INPUTS, x, self.ranges, self._c):
            if not (lo <= v <= hi):      # also catches NaN
                raise SurrogateRangeError(
                    f"surrogate input {name} = {v:.6g} {unit} is outside the range it was fitted on "
                    f"[{lo:.6g}, {hi:.6g}]; use the model optimization instead")
            z.append((v - c) * s)
        a0, b0, c0 = z
        a = (1.0, a0, a0 * a0)
        b = (1.0, b0, b0 * b0)
        cc = (1.0, c0, c0 * c0)
        terms = [a[i] * b[j] * cc[k] for i, j, k in EXPONENTS]
        return tuple(sum(w * t for w, t in zip(co, terms)) for co in self._coef)

    def predict(self, X: np.ndarray, check: bool = True) -> np.ndarray:
        """Vectorised evaluation of inputs X (n, 3) -> (n, 3); ``check`` refuses out-of-range rows."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        if check:
            for d, ((name, unit), (lo, hi)) in enumerate(zip(INPUTS, self.ranges)):
                bad = ~((X[:, d] >= lo) & (X[:, d] <= hi))
                if bad.any():
                    v = X[bad, d][0]
                    raise SurrogateRangeError(
                        f"surrogate input {name} = {v:.6g} {unit} is outside the range it was fitted "
                        f"on [{lo:.6g}, {hi:.6g}] ({int(bad.sum())} rows)")
        Z = np.column_stack([(X[:, d] - c) * s for d, (c, s) in enumerate(self._c)])
        return _basis(Z) @ np.array(self._coef).T

    # ---- persistence ---------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "description": "p_m,sp optimum surrogate (SPEC §6): 27-term polynomial in scaled inputs "
                           "z = 2*(x - min)/(max - min) - 1; basis z1^i*z2^j*z3^k for 'exponents'",
            "reference_p_m_sp_barg": self.reference_p_m_sp_barg,
            "inputs": [{"name": n, "unit": u, "min": lo, "max": hi}
                       for (n, u), (lo, hi) in zip(INPUTS, self.ranges)],
            "exponents": [list(e) for e in EXPONENTS],
            "outputs": [{"name": n, "unit": u, "coefficients": list(c),
                         "r2_test": self.r2_test.get(n), "r2_train": self.r2_train.get(n)}
                        for (n, u), c in zip(OUTPUTS, self._coef)],
            "n_train": self.n_train, "n_test": self.n_test, "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Surrogate":
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise SurrogateError(f"not a surrogate document (format must be {FORMAT!r})")
        try:
            ins = {i["name"]: i for i in d["inputs"]}
            outs = {o["name"]: o for o in d["outputs"]}
            if [list(e) for e in d["exponents"]] != [list(e) for e in EXPONENTS]:
                raise SurrogateError("surrogate 'exponents' differ from this version's basis")
            ranges = tuple((float(ins[n]["min"]), float(ins[n]["max"])) for n, _ in INPUTS)
            coef = tuple(tuple(float(x) for x in outs[n]["coefficients"]) for n, _ in OUTPUTS)
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, SurrogateError):
                raise
            raise SurrogateError(f"invalid surrogate document: {type(exc).__name__}: {exc}") from exc
        return cls(ranges=ranges, coef=coef,
                   r2_test={n: outs[n].get("r2_test") for n, _ in OUTPUTS},
                   r2_train={n: outs[n].get("r2_train") for n, _ in OUTPUTS},
                   n_train=int(d.get("n_train", 0)), n_test=int(d.get("n_test", 0)),
                   reference_p_m_sp_barg=float(d.get("reference_p_m_sp_barg", 10.0)),
                   meta=d.get("meta", {}))

    def save(self, path) -> None:
        """Atomic write (temp file + fsync + rename)."""
        path = os.fspath(path)
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=1)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)

    @classmethod
    def load(cls, path) -> "Surrogate":
        try:
            with open(path, encoding="utf-8") as fh:
                d = json.load(fh)
        except json.JSONDecodeError as exc:
            raise SurrogateError(f"{path}: not valid JSON ({exc})") from exc
        try:
            return cls.from_dict(d)
        except SurrogateError as exc:
            raise SurrogateError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------------------------------
# fitting
# --------------------------------------------------------------------------------------------------
def design_from_config(extra: dict | None) -> dict:
    """DEFAULT_DESIGN updated by plant.yaml's ``surrogate:`` section (unknown keys raise)."""
    sec = (extra or {}).get("surrogate") or {}
    unknown = set(sec) - set(DEFAULT_DESIGN)
    if unknown:
        raise SurrogateError(f"key 'surrogate.{sorted(unknown)[0]}': unknown (known: "
                             f"{', '.join(sorted(DEFAULT_DESIGN))})")
    return {**DEFAULT_DESIGN, **sec}


def generate_samples(params: PlantParams, design: dict | None = None, progress=None) -> tuple[pd.DataFrame, dict]:
    """Optimization results of the model ``params`` (with its CFs; R_th_f set per fouling level)
    over the design: returns (samples with INPUTS + OUTPUTS columns, counts of skipped points)."""
    dz = {**DEFAULT_DESIGN, **(design or {})}
    rng = np.random.default_rng(int(dz["seed"]))
    ref_sp = float(dz["reference_p_m_sp_barg"])
    levels = [float(x) for x in dz["fouling_levels_K_per_kW"]]
    n_per = int(dz["points_per_level"])
    u = lambda key: rng.uniform(*dz[key], size=n_per)  # noqa: E731
    total = len(levels) * n_per
    rows, skipped, done = [], {}, 0
    for R in levels:
        par = params.replace(R_th_f=R * 1e-3)
        T_in = u("T_source_in_C")
        ops = pd.DataFrame({"T_source_in": T_in, "T_source_out": T_in - u("source_cooling_K"),
                            "T_sink_in": u("T_sink_in_C"), "V_source": u("V_source_m3h"),
                            "V_sink": u("V_sink_m3h"), "p_m_sp": ref_sp})
        ref = simulate_batch(ops, par, columns=("eta_is_LS", "eta_is_HS", "p_e_bar", "p_c_bar"))
        for i in range(n_per):
            done += 1
            if progress is not None:
                progress(done, total)
            st = ref["status"].iat[i]
            if st != "ok":
                skipped[f"reference: {st}"] = skipped.get(f"reference: {st}", 0) + 1
                continue
            try:
                opt = optimize_setpoint(ops.iloc[[i]], par)
            except OptimizationError:
                skipped["optimization failed"] = skipped.get("optimization failed", 0) + 1
                continue
            if opt.ls_saturated:   # capacity-limited: the optimum depends on more than the inputs
                skipped["LS at its speed limit at the optimum"] = \
                    skipped.get("LS at its speed limit at the optimum", 0) + 1
                continue
            r = ref.iloc[i]
            rows.append({"R_th_f_K_per_kW": R, **ops.iloc[i].to_dict(),
                         "eta_is_product": r["eta_is_LS"] * r["eta_is_HS"],
                         "p_e_bar_a": r["p_e_bar"], "p_c_bar_a": r["p_c_bar"],
                         "p_m_opt_bar_a": opt.p_m_sp_opt_barg + params.ambient_pressure / 1e5,
                         "dCOP_pct": opt.dCOP_opt_pct, "dQ_sink_pct": opt.dQ_sink_opt_pct,
                         "hs_saturated": opt.hs_saturated})
    return pd.DataFrame(rows), skipped


def fit_surrogate(samples: pd.DataFrame, train_share: float = TRAIN_SHARE, seed: int = 1,
                  reference_p_m_sp_barg: float = 10.0, meta: dict | None = None) -> Surrogate:
    """Least-squares fit on a seeded ``train_share`` of ``samples``; R^2 on the rest."""
    t0 = time.perf_counter()
    need = [n for n, _ in INPUTS + OUTPUTS]
    missing = [c for c in need if c not in samples.columns]
    if missing:
        raise SurrogateError(f"samples lack columns: {', '.join(missing)}")
    s = samples[need].dropna()
    n = len(s)
    n_train = int(round(train_share * n))
    if n_train < 1.5 * len(EXPONENTS) or n - n_train < 5:
        raise SurrogateError(f"{n} samples are too few for a {len(EXPONENTS)}-term fit with a "
                             f"{100 * (1 - train_share):.0f} % test share")
    perm = np.random.default_rng(seed).permutation(n)
    tr, te = perm[:n_train], perm[n_train:]
    X = s[[n for n, _ in INPUTS]].to_numpy(dtype=float)
    Y = s[[n for n, _ in OUTPUTS]].to_numpy(dtype=float)
    ranges = tuple((float(X[tr, d].min()), float(X[tr, d].max())) for d in range(3))
    scale = [(0.5 * (lo + hi), 2.0 / (hi - lo)) for lo, hi in ranges]
    Z = np.column_stack([(X[:, d] - c) * k for d, (c, k) in enumerate(scale)])
    A = _basis(Z)
    coef, _, rank, sv = np.linalg.lstsq(A[tr], Y[tr], rcond=None)
    if rank < len(EXPONENTS):
        raise SurrogateError(f"the training inputs span only rank {rank} of {len(EXPONENTS)} basis terms")
    pred = A @ coef
    names = [o for o, _ in OUTPUTS]
    sur = Surrogate(
        ranges=ranges, coef=tuple(tuple(coef[:, j]) for j in range(3)),
        r2_test={nm: r2_score(Y[te, j], pred[te, j]) for j, nm in enumerate(names)},
        r2_train={nm: r2_score(Y[tr, j], pred[tr, j]) for j, nm in enumerate(names)},
        n_train=len(tr), n_test=len(te), reference_p_m_sp_barg=reference_p_m_sp_barg,
        meta={**(meta or {}), "condition_number": float(sv[0] / sv[-1]),
              "fit_time_s": time.perf_counter() - t0,
              "test_rows": [int(i) for i in np.sort(s.index.to_numpy()[te])]})
    return sur
