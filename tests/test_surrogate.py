"""The 27-term set-point surrogate (SPEC §6): scaled basis, 70/30 split, R^2 on the held-out part,
JSON with input ranges, refusal outside them."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from model.surrogate import (EXPONENTS, INPUTS, OUTPUTS, Surrogate, SurrogateError,
                             SurrogateRangeError, fit_surrogate, generate_samples, r2_score)

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = ROOT / "config" / "surrogate.json"
EXACT_RTOL = 1e-8          # a polynomial of the basis is reproduced to round-off
MIN_R2_SMALL_DESIGN = 0.5  # floor for the small test design (~200 optima; 0.80-0.97 measured):
                           # catches a broken pipeline; the shipped fit reports its own R^2 (~0.91-0.94)


def _poly_samples(n=200, seed=0):
    """Samples of a known polynomial of the basis in the *unscaled* inputs, at realistic magnitudes."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(0.52, 0.60, n), rng.uniform(5.0, 8.5, n), rng.uniform(22, 40, n)])
    y1 = 2.0 + 0.5 * X[:, 1] + 0.3 * X[:, 2] - 0.002 * X[:, 2] ** 2 + 3.0 * X[:, 0] * X[:, 1]
    y2 = 1.0 - 4.0 * X[:, 0] ** 2 * X[:, 1] * X[:, 2] / 10 + 0.01 * X[:, 1] ** 2 * X[:, 2] ** 2 / 100
    y3 = -0.5 + 0.1 * X[:, 0] * X[:, 1] * X[:, 2]
    cols = {n: X[:, i] for i, (n, _) in enumerate(INPUTS)}
    cols.update({n: y for (n, _), y in zip(OUTPUTS, (y1, y2, y3))})
    return pd.DataFrame(cols)


def test_basis_reproduces_a_polynomial_exactly():
    s = _poly_samples()
    sur = fit_surrogate(s)
    assert len(EXPONENTS) == 27
    assert sur.n_train == 140 and sur.n_test == 60
    for name, _ in OUTPUTS:
        assert sur.r2_test[name] == pytest.approx(1.0, abs=1e-10)
    X = s[[n for n, _ in INPUTS]].to_numpy()
    Y = s[[n for n, _ in OUTPUTS]].to_numpy()
    np.testing.assert_allclose(sur.predict(X, check=False), Y, rtol=EXACT_RTOL)
    # the scaled basis is well conditioned; the unscaled one is not (the papers' 8e7 coefficients)
    assert sur.meta["condition_number"] < 1e4
    raw = np.column_stack([X[:, 0] ** i * X[:, 1] ** j * X[:, 2] ** k for i, j, k in EXPONENTS])
    sv = np.linalg.svd(raw, compute_uv=False)
    assert sv[0] / sv[-1] > 1e6 * sur.meta["condition_number"]


def test_evaluate_matches_predict_and_refuses_outside_ranges():
    sur = fit_surrogate(_poly_samples())
    x = tuple(0.5 * (lo + hi) for lo, hi in sur.ranges)
    one = sur.evaluate(*x)
    np.testing.assert_allclose(one, sur.predict(np.array([x]))[0], rtol=1e-12)
    lo_eta = sur.ranges[0][0]
    with pytest.raises(SurrogateRangeError, match=r"eta_is_product = .* outside the range it was fitted on"):
        sur.evaluate(lo_eta - 1e-3, x[1], x[2])
    with pytest.raises(SurrogateRangeError, match="p_c_bar_a"):
        sur.evaluate(x[0], x[1], float("nan"))
    with pytest.raises(SurrogateRangeError, match="p_e_bar_a"):
        sur.predict(np.array([[x[0], sur.ranges[1][1] + 1.0, x[2]]]))


def test_json_round_trip(tmp_path):
    sur = fit_surrogate(_poly_samples())
    path = tmp_path / "s.json"
    sur.save(path)
    back = Surrogate.load(path)
    x = tuple(0.3 * lo + 0.7 * hi for lo, hi in sur.ranges)
    assert back.evaluate(*x) == sur.evaluate(*x)
    doc = json.loads(path.read_text())
    assert [i["name"] for i in doc["inputs"]] == [n for n, _ in INPUTS]
    assert all("min" in i and "max" in i for i in doc["inputs"])
    assert all(len(o["coefficients"]) == 27 for o in doc["outputs"])
    bad = dict(doc, format="something else")
    with pytest.raises(SurrogateError, match="format"):
        Surrogate.from_dict(bad)
    broken = dict(doc, outputs=doc["outputs"][:2])
    with pytest.raises(SurrogateError, match="invalid surrogate document"):
        Surrogate.from_dict(broken)
    (tmp_path / "t.json").write_text("{not json")
    with pytest.raises(SurrogateError, match="t.json"):
        Surrogate.load(tmp_path / "t.json")


def test_fit_on_model_optima_reports_r2_on_held_out(plant):
    # 90 points per level: with 45 the held-out R^2 of a 27-term fit swung from -0.3 to 0.9 with
    # the split alone (on main too); with 90 it stays within 0.8-0.97 over eight split seeds
    design = {"fouling_levels_K_per_kW": [0.0, 3e-3, 6e-3], "points_per_level": 90, "seed": 3}
    samples, skipped = generate_samples(plant.replace(CF_eva=0.95), design)
    assert len(samples) + sum(skipped.values()) == 270
    assert skipped.get("LS at its speed limit at the optimum", 0) > 0   # capacity-limited points left out
    sur = fit_surrogate(samples, seed=3)
    assert sur.n_test == len(samples) - round(0.7 * len(samples))
    test_rows = sur.meta["test_rows"]
    assert len(test_rows) == sur.n_test
    # R^2 on exactly the held-out rows, recomputed here
    X = samples.loc[test_rows, [n for n, _ in INPUTS]].to_numpy()
    pred = sur.predict(X, check=False)
    for j, (name, _) in enumerate(OUTPUTS):
        y = samples.loc[test_rows, name].to_numpy()
        assert sur.r2_test[name] == pytest.approx(r2_score(y, pred[:, j]), rel=1e-12)
        assert sur.r2_test[name] > MIN_R2_SMALL_DESIGN, (name, sur.r2_test[name])
    # optima are physical: between p_e and p_c, COP never worse than at the reference set point
    assert (samples["p_m_opt_bar_a"] > samples["p_e_bar_a"]).all()
    assert (samples["p_m_opt_bar_a"] < samples["p_c_bar_a"]).all()
    assert (samples["dCOP_pct"] >= -1e-9).all()


def test_shipped_surrogate_loads_and_evaluates_at_the_nominal_point(plant, nominal_row):
    from model.batch import simulate_batch
    sur = Surrogate.load(SHIPPED)
    ref = simulate_batch(pd.DataFrame([{**nominal_row, "p_m_sp": sur.reference_p_m_sp_barg}]), plant).iloc[0]
    p_opt, dcop, dq = sur.evaluate(ref["eta_is_LS"] * ref["eta_is_HS"], ref["p_e_bar"], ref["p_c_bar"])
    assert ref["p_e_bar"] < p_opt < ref["p_c_bar"]
    assert math.isfinite(dcop) and math.isfinite(dq)
    for name, _ in OUTPUTS:
        assert sur.r2_test[name] is not None and sur.n_test > 0
