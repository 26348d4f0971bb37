"""The surrogate fitted from the analysis windows' optima (issue #8 item 7): the 27-term and the
extended form, judged on a chronological held-out split, and the gateway's switch to it."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from model.analysis.surrogate_tracker import (EXTENDED, SurrogateTracker, TrackerError,
                                              TrackerSettings, optimum_row)
from model.optimize import Evaluator, search, window_range

R2_EXACT = 0.9999           # a form that contains the generating function fits it to round-off
PM_TOL_BAR = 0.3            # issue #8: |p_m,opt error| <= 0.3 bar for 95 % of the test rows


def _rows(n: int, rng, f, t0: float = 0.0) -> list[dict]:
    """n rows with inputs in the plant's range and outputs from f(inputs) -> (p_m_opt, dCOP)."""
    out = []
    for i in range(n):
        x = {"eta_is_product": rng.uniform(0.60, 0.72), "p_e_bar_a": rng.uniform(3.0, 4.5),
             "p_c_bar_a": rng.uniform(38.0, 46.0), "V_sink_m3h": rng.uniform(60.0, 110.0),
             "T_sink_in_C": rng.uniform(40.0, 55.0)}
        pm, dc = f(x)
        out.append({**x, "p_m_opt_bar_a": pm, "dCOP_pct": dc, "t": t0 + 3600.0 * i})
    return out


def _three_inputs(x):
    return (12.0 + 0.9 * x["p_e_bar_a"] + 0.08 * x["p_c_bar_a"] - 4.0 * x["eta_is_product"]
            + 0.002 * x["p_c_bar_a"] ** 2,
            1.0 + 0.05 * (x["p_c_bar_a"] - 40.0) ** 2 - 0.3 * x["p_e_bar_a"])


def _sink_dependent(x):
    pm, dc = _three_inputs(x)
    return pm + 0.05 * (x["V_sink_m3h"] - 85.0), dc + 0.02 * (x["T_sink_in_C"] - 47.0)


def test_both_forms_qualify_on_a_function_of_their_inputs():
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000))
    tr.add(_rows(120, np.random.default_rng(1), _three_inputs))
    fits = tr.refit()
    for form in ("basic", "extended"):
        f = fits[form]
        assert f.qualified, (form, f.r2, f.share_within_tol)
        assert min(f.r2.values()) >= R2_EXACT
        assert f.share_within_tol == 1.0
        assert (f.n_train, f.n_test) == (84, 36)
    assert tr.qualified.form == "extended"          # preferred when both qualify
    x = {"eta_is_product": 0.66, "p_e_bar_a": 3.7, "p_c_bar_a": 42.0, "V_sink_m3h": 85.0,
         "T_sink_in_C": 47.0}
    pm, dc = _three_inputs(x)
    pred = tr.qualified.predict(x)
    assert abs(pred["p_m_opt_bar_a"] - pm) < 1e-6 and abs(pred["dCOP_pct"] - dc) < 1e-6


def test_a_windows_copy_predicts_as_the_tracker_without_its_rows():
    """``for_window``: what a window's task carries (a replay pickles one per window) has the
    fits, the settings and the window count but none of the rows, and answers as the tracker."""
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000, qualified_every=3))
    tr.add(_rows(120, np.random.default_rng(1), _three_inputs))
    tr.refit()
    tr._windows = 1
    view = tr.for_window()
    assert view.rows == [] and len(tr.rows) == 120
    assert view.qualified is not None and view.qualified.form == tr.qualified.form
    x = {"eta_is_product": 0.66, "p_e_bar_a": 3.7, "p_c_bar_a": 42.0, "V_sink_m3h": 85.0,
         "T_sink_in_C": 47.0}
    assert view.qualified.predict(x) == tr.qualified.predict(x)
    assert view.takes_next() == tr.takes_next() is False
    tr._windows = 2
    assert view.takes_next() is False and tr.takes_next() is True   # a snapshot
    tr.refit()                                                      # the tracker refits later
    assert view.fits and view.fits is not tr.fits


def test_the_basic_form_fails_where_the_sink_matters_and_the_extended_one_qualifies():
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000))
    tr.add(_rows(150, np.random.default_rng(2), _sink_dependent))
    fits = tr.refit()
    assert not fits["basic"].qualified
    assert fits["basic"].r2["p_m_opt_bar_a"] < 0.99
    assert fits["extended"].qualified
    assert tr.qualified.form == "extended"


def test_the_split_is_chronological_a_plant_that_changed_does_not_qualify():
    """The newest 30 % of the rows come from a plant whose optimum moved by 0.5 bar: a random split
    would train on both and pass; the chronological one predicts the new rows from the old."""
    rng = np.random.default_rng(3)
    old = _rows(84, rng, _three_inputs)
    new = _rows(36, rng, lambda x: (_three_inputs(x)[0] + 0.5, _three_inputs(x)[1]), t0=84 * 3600.0)
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000))
    tr.add(new + old)                    # added out of order: the split sorts by time
    fits = tr.refit()
    assert all(not f.qualified for f in fits.values())
    assert fits["extended"].share_within_tol == 0.0      # every new row is 0.5 bar off
    assert tr.qualified is None


def test_no_fit_before_min_rows_and_refits_on_its_cadence():
    s = TrackerSettings(min_rows=60, refit_every=12)
    tr = SurrogateTracker(s)
    rows = _rows(72, np.random.default_rng(4), _three_inputs)
    tr.add(rows[:59])
    assert tr.fits == {}
    tr.add(rows[59:60])
    assert tr.fits == {}                 # 60 rows, but the cadence (12) has not come round
    tr.add(rows[60:72])
    assert set(tr.fits) == {"basic", "extended"}


def test_predictions_outside_the_training_ranges_are_refused():
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000))
    tr.add(_rows(120, np.random.default_rng(5), _three_inputs))
    tr.refit()
    x = {"eta_is_product": 0.66, "p_e_bar_a": 3.7, "p_c_bar_a": 42.0, "V_sink_m3h": 85.0,
         "T_sink_in_C": 47.0}
    assert tr.qualified.predict(x) is not None
    assert tr.qualified.predict({**x, "p_c_bar_a": 50.0}) is None


def test_state_round_trip_and_a_foreign_document():
    tr = SurrogateTracker(TrackerSettings(min_rows=60, refit_every=10_000))
    tr.add(_rows(100, np.random.default_rng(7), _three_inputs))
    tr.refit()
    back = SurrogateTracker.from_dict(tr.to_dict(), tr.s)
    assert back.rows == tr.rows
    assert back.qualified.form == tr.qualified.form
    x = tr.rows[-1]
    assert back.qualified.predict(x) == tr.qualified.predict(x)
    with pytest.raises(TrackerError) as e:
        SurrogateTracker.from_dict({"format": "x"})
    assert str(e.value) == "surrogate tracker state: not a 'hp-edge-surrogate-tracker/1' document"


@pytest.mark.parametrize("d, msg", [
    ({"min_r2": "high"}, "key 'surrogate_tracker.min_r2': expected a number > 0, got 'high'"),
    ({"enabled": 1}, "key 'surrogate_tracker.enabled': expected true/false, got 1"),
    ({"extra_fouling_K_per_kW": [0.1, -1]},
     "key 'surrogate_tracker.extra_fouling_K_per_kW': expected a list of numbers >= 0"),
])
def test_settings_errors_name_the_key(d, msg):
    with pytest.raises(TrackerError) as e:
        TrackerSettings.from_dict(d)
    assert str(e.value) == msg


def test_unknown_setting_is_named():
    with pytest.raises(TrackerError) as e:
        TrackerSettings.from_dict({"min_rowz": 3})
    assert str(e.value).startswith("key 'surrogate_tracker.min_rowz': unknown (known: enabled, ")


# ------------------------------------------------------------------ on the model

def _window_rows(T_source_in: float, T_sink_in: float, V_sink: float, sp: float = 12.0) -> pd.DataFrame:
    return pd.DataFrame([{"T_source_in": T_source_in, "T_source_out": T_source_in - 5.0,
                          "T_sink_in": T_sink_in, "V_source": 140.0, "V_sink": V_sink, "p_m_sp": sp}])


def test_a_training_row_is_the_models_optimum_over_the_whole_range(plant):
    rows = _window_rows(8.0, 50.0, 85.0)
    w = np.ones(1)
    r = optimum_row(rows, w, plant, 10.0, t=0.0)
    assert r is not None and set(EXTENDED) <= set(r)
    ev = Evaluator(rows, w, plant)
    amb = plant.ambient_pressure / 1e5
    lo, hi = window_range(ev.at(None).frame, amb)
    # the optimum is no worse than the reference set point, and no worse than a scan every 0.25 bar
    assert r["dCOP_pct"] >= -1e-9
    best = max(ev.at(sp).COP for sp in np.arange(lo, hi, 0.25) if ev.at(sp).ok)
    ref = ev.at(10.0)
    assert r["dCOP_pct"] >= 100.0 * (best / ref.COP - 1.0) - 1e-3
    assert r["p_e_bar_a"] < r["p_m_opt_bar_a"] < r["p_c_bar_a"]
    assert r["V_sink_m3h"] == 85.0 and r["T_sink_in_C"] == 50.0
    assert 0.4 < r["eta_is_product"] < 0.8


def test_the_chain_uses_the_qualified_surrogate_and_it_agrees_with_the_search(plant):
    """A tracker trained on the model's own optima over a grid of operating points qualifies; the
    chain's advice then takes the surrogate's optimum, within 0.3 bar of what the search finds."""
    rng = np.random.default_rng(8)
    tr = SurrogateTracker(TrackerSettings(min_rows=40, refit_every=10_000))
    for i in range(60):
        rows = _window_rows(rng.uniform(5.0, 12.0), rng.uniform(45.0, 55.0), rng.uniform(70.0, 100.0))
        tr.add([optimum_row(rows, np.ones(1), plant, 10.0, t=3600.0 * i)])
    fits = tr.refit()
    assert set(fits) == {"basic", "extended"}
    assert tr.qualified is not None, {k: (f.r2, f.share_within_tol) for k, f in fits.items()}
    rows = _window_rows(8.5, 50.0, 85.0)
    pred = tr.predict_setpoint(rows, np.ones(1), plant)
    assert pred is not None
    sp_sur, used = pred
    ev = Evaluator(rows, np.ones(1), plant)
    amb = plant.ambient_pressure / 1e5
    lo, hi = window_range(ev.at(None).frame, amb)
    sp_search, p = search(ev, lo, hi)
    assert abs(sp_sur - sp_search) <= PM_TOL_BAR, (sp_sur, sp_search, used)
    # the advice takes it in place of the search
    from model.analysis.advice import AdviceSettings, advise
    adv = advise(pd.concat([rows] * 3, ignore_index=True), plant, None, AdviceSettings(),
                 sp_override=sp_sur)
    assert adv.optimizer == "surrogate"
    assert math.isclose(adv.p_m_sp_model_opt_barg, sp_sur, abs_tol=1e-9) or p.hs_saturated
