"""Issue 10 in the product: the forecast in the analysis chain (carried across windows, reset at a CIP),
its persistence, CIP detection, the cost terms, the registers, forecast.csv from a replay, price CSVs."""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from model.analysis.cip import (CipConfigError, CipSettings, CipWatch, ForecastState, explain,
                                forecast_window)
from model.analysis.cost import CostError, LevelRuns, PriceSeries, fouling_cost_terms

DAY = 86400.0
T0 = 1.7e9                       # epoch s of the first window
RUNS = LevelRuns([0.0, 2e-3, 4e-3, 6e-3, 8e-3], [2000.0, 2010.0, 2022.0, 2036.0, 2052.0],
                 [430.0, 440.0, 452.0, 466.0, 482.0], [1570.0] * 5)


def _cycle(fs, s, t_first, days, R0=2.5e-3, rate=0.15e-3, seed=0, runs=RUNS):
    """2-h windows from t_first for ``days``, R growing linearly (+ noise); the last WindowForecast."""
    rng = np.random.default_rng(seed)
    wf = None
    for k in range(int(days * 12)):
        a = t_first + k * 7200.0
        t_mid = (a + 3600.0 - t_first) / DAY
        wf = forecast_window(fs, s, start_s=a, end_s=a + 7200.0, R=R0 + rate * t_mid + rng.normal(0, 0.03e-3),
                             R_se=0.03e-3, CF=1.1 + 0.01 * t_mid, CF_se=0.005, runs=runs,
                             V_source_m3_per_h=192.0, dp_clean_bar=0.45)
    return wf


# ------------------------------------------------------------------ the forecast across windows and CIPs

def test_forecast_carries_across_windows_and_restarts_at_a_cip():
    s = CipSettings(electricity_price_eur_per_MWh=100.0, horizon_days=2.0)
    fs = ForecastState()
    first = _cycle(fs, s, T0, 0.4)
    assert first.advice.R_fit is None and "not enough data" in first.fields()["forecast_note"]
    assert math.isnan(first.fields()["R_th_f_forecast_K_per_kW"])
    wf = _cycle(fs, s, T0, 3.0)          # the same state: the windows of the first call plus these
    assert len(fs.t_s) == int(0.4 * 12) + 36 and fs.reset_kind == "first window"
    f = wf.fields()
    assert f["forecast_law"] in ("linear", "kern_seaton")
    assert f["fouling_rate_K_per_kW_per_day"] == pytest.approx(0.15e-3, rel=0.15)
    truth_at = 2.5e-3 + 0.15e-3 * (3.0 + 2.0)
    assert abs(f["R_th_f_forecast_K_per_kW"] - truth_at) < 0.1e-3
    assert f["R_th_f_forecast_lo_K_per_kW"] < f["R_th_f_forecast_K_per_kW"] < f["R_th_f_forecast_hi_K_per_kW"]
    assert f["forecast_at"] == pd.Timestamp(wf.end_s + 2 * DAY, unit="s", tz="UTC").isoformat()
    cum = f["fouling_cost_cum_eur"]
    # the cumulated cost is the integral of the windows' rates (windows touch: no gap)
    assert cum > 0 and fs.tally.uncovered_s == 0
    # a CIP: 2.5 days from the last window's end
    end = wf.end_s
    R_before_fit = fs.last_fit_R.value((end + 3600 - fs.reset_s) / DAY)
    assert fs.cip(end + 3600, end + 3600 + 2.5 * DAY, "cip_flag", s)
    assert not fs.cip(end, end + 60, "cip_flag", s)            # seen already: nothing changes
    c = fs.cips[-1]
    assert c["R_before"] == pytest.approx(R_before_fit) and c["R_after"] is None
    assert fs.t_s == [] and fs.tally.total_eur == 0.0 and fs.reset_s == end + 3600 + 2.5 * DAY
    assert len(fs.cycle_fits) == 1 and fs.cycle_fits[0]["R"]["law"] in ("linear", "kern_seaton")
    after = _cycle(fs, s, fs.reset_s, 0.25, R0=0.85 * 2.5e-3 + 0.85 * 0.15e-3 * 3.0)
    fa = after.fields()
    assert fa["days_since_reset"] == pytest.approx(0.25, abs=1e-9)
    assert math.isnan(fa["R_th_f_forecast_K_per_kW"]) and fa["fouling_cost_cum_eur"] < cum
    assert fs.cips[-1]["R_after"] == pytest.approx(np.median(fs.R[:3]))    # provisional, before a fit
    rem = fs.removal(s)
    assert rem.source == "plant" and rem.n == 1 and rem.share == pytest.approx(0.15, abs=0.05)
    text = explain(after, s)
    assert text[0].startswith("no fouling forecast yet (R_th_f: not enough data: 3 window estimate(s)")


def test_forecast_state_survives_json_and_gives_the_same_next_window():
    s = CipSettings(electricity_price_eur_per_MWh=100.0)
    fs = ForecastState()
    _cycle(fs, s, T0, 2.0)
    fs.cip(T0 + 2 * DAY, T0 + 4 * DAY, "plant_off", s)
    _cycle(fs, s, T0 + 4 * DAY, 1.5, seed=1)
    doc = json.loads(json.dumps(fs.to_dict()))              # what chain_state.json holds
    back = ForecastState.from_dict(doc)
    assert back.to_dict() == fs.to_dict()
    kw = dict(start_s=T0 + 5.5 * DAY, end_s=T0 + 5.5 * DAY + 7200, R=2.9e-3, R_se=0.03e-3, CF=1.12,
              CF_se=0.005, runs=RUNS, V_source_m3_per_h=192.0, dp_clean_bar=0.45)
    a, b = forecast_window(fs, s, **kw).fields(), forecast_window(back, s, **kw).fields()
    assert a == b
    with pytest.raises(CostError, match="not a forecast state"):
        ForecastState.from_dict({**doc, "R": doc["R"][:-1]})


def test_the_priors_are_kept_until_a_cip_replaces_the_cycle_fits():
    """``ForecastState.priors`` answers from the earlier cycles' fits; kept between windows (the same
    objects), recomputed when a CIP hands on a new list of cycle fits, never from a stale list, and
    not part of the persisted state."""
    from model.analysis.forecast import fit_fouling, law_prior
    rng = np.random.default_rng(5)

    def ks_fit(tau, y_inf):
        t = np.linspace(0.0, 40.0, 240)
        y = y_inf * (1.0 - np.exp(-t / tau)) + 1e-3 + rng.normal(0.0, 0.01e-3, len(t))
        f = fit_fouling(t, y, np.full(len(t), 0.01e-3))
        assert f.law == "kern_seaton"
        return f

    f1, f2 = ks_fit(8.0, 2e-3), ks_fit(15.0, 3e-3)
    fs = ForecastState()
    assert fs.priors() == (None, None)
    fs.cycle_fits = [{"R": f1.to_state(), "CF": None}]
    a = fs.priors()
    assert a[0] == law_prior([f1]) and a[1] is None and fs.priors()[0] is a[0]
    fs.cycle_fits = fs.cycle_fits + [{"R": f2.to_state(), "CF": None}]     # as ForecastState.cip does
    b = fs.priors()
    assert b[0] == law_prior([f1, f2]) and b[0] != a[0] and b[0].n_cycles == 2
    assert "_priors" not in fs.to_dict() and ForecastState.from_dict(fs.to_dict()).priors() == b


def test_estimates_are_bounded_by_thinning_the_older_half():
    s = CipSettings(electricity_price_eur_per_MWh=100.0, max_estimates=100)
    fs = ForecastState()
    _cycle(fs, s, T0, 10.0)                  # 120 windows
    assert len(fs.t_s) <= 100 and fs.t_s == sorted(fs.t_s)
    assert fs.t_s[-1] == T0 + 120 * 7200 - 3600              # the newest are kept


def test_cip_watch_finds_cips_as_replay_does():
    w = CipWatch(off_minutes=360)
    t = T0
    assert [w.feed(t + 60 * i, False, False) for i in range(3)] == [None] * 3
    # a short stop without the flag is not a CIP; with the flag it is
    assert [w.feed(t + 60 * i, True, False) for i in range(3, 30)] == [None] * 27
    assert w.feed(t + 60 * 30, False, False) is None
    for i in range(31, 40):
        w.feed(t + 60 * i, True, i == 35)
    assert w.feed(t + 60 * 40, False, False) == (t + 60 * 31, t + 60 * 40, "cip_flag")
    # a long stop without the flag is one, and it survives a restart of the gateway half way
    for i in range(41, 200):
        w.feed(t + 60 * i, True, False)
    doc = json.loads(json.dumps(w.to_dict()))
    w2 = CipWatch(off_minutes=360)
    w2.restore(doc)
    for i in range(200, 420):
        assert w2.feed(t + 60 * i, True, False) is None
    assert w2.feed(t + 60 * 420, False, False) == (t + 60 * 41, t + 60 * 420, "plant_off")
    # a hole in the samples that long: whatever happened, the forecast restarts
    assert w2.feed(t + 60 * 421 + 7 * 3600, False, False) == (t + 60 * 420, t + 60 * 421 + 7 * 3600, "gap")


# ------------------------------------------------------------------ settings

@pytest.mark.parametrize("section, message", [
    ({"direct_cost_eur": -1}, "key 'cip.direct_cost_eur': expected a number >= 0 [EUR], got -1"),
    ({"pump_efficiency": 1.5}, "key 'cip.pump_efficiency': expected a number in (0, 1], got 1.5"),
    ({"trigger": "soon"}, "key 'cip.trigger': expected 'level' or 'age', got 'soon'"),
    ({"horizon_day": 7}, "key 'cip.horizon_day': unknown (known: R_th_f_limit_K_per_kW, band_level, "),
    ({"cost_levels_K_per_kW": [0.0, 2e-3]},
     "key 'cip.cost_levels_K_per_kW': expected a list of 1..20 levels in (0, 0.05] [K/kW], got [0.0, 0.002]"),
    ({"electricity_price_eur_per_MWh": 90, "electricity_price_csv": "p.csv"},
     "key 'cip.electricity_price_csv': give either a constant electricity_price_eur_per_MWh or a price "
     "CSV, not both"),
])
def test_cip_settings_name_the_key(section, message):
    with pytest.raises(CipConfigError) as info:
        CipSettings.from_config({"cip": section})
    assert str(info.value).startswith(message)


def test_cip_settings_from_plant_yaml_and_an_unloaded_price_series():
    s = CipSettings.from_config({"cip": {"direct_cost_eur": 800, "cost_points": 3, "horizon_days": 3}})
    assert (s.cip_direct_cost_eur, s.cost_points, s.horizon_days) == (800, 3, 3)
    s = CipSettings.from_config({"cip": {"electricity_price_csv": "prices.csv"}})
    assert s.electricity_price_eur_per_MWh is None
    wf = forecast_window(ForecastState(), s, start_s=T0, end_s=T0 + 7200, R=2e-3, R_se=1e-5, CF=1.1,
                         CF_se=0.01, runs=RUNS, V_source_m3_per_h=192.0, dp_clean_bar=0.45)
    assert math.isnan(wf.cost_eur_per_day)
    assert ("cost of fouling: the electricity price series (cip.electricity_price_csv: prices.csv) was "
            "not loaded by the caller") in wf.notes
    series = PriceSeries([T0 - 3600, T0 + 3600], [50.0, 150.0])
    s = CipSettings.from_config({"cip": {"electricity_price_csv": "prices.csv"}}, price=series)
    wf = forecast_window(ForecastState(), s, start_s=T0, end_s=T0 + 7200, R=2e-3, R_se=1e-5, CF=1.0,
                         CF_se=0.01, runs=RUNS, V_source_m3_per_h=192.0, dp_clean_bar=0.45)
    assert wf.price_eur_per_MWh == pytest.approx(100.0)


# ------------------------------------------------------------------ cost terms

def test_cost_terms_by_hand_with_lost_capacity():
    """Compressors at equal heat, and the heat lost when the LS sits at its speed limit."""
    fouled, ref = (1900.0, 420.0, 1480.0), (2000.0, 430.0, 1570.0)
    t = fouling_cost_terms(fouled, ref, 100.0, 45.0)
    P = 420.0 - 1900.0 * 430.0 / 2000.0                    # 11 kW
    L = (1570.0 - 1480.0) * 2000.0 / 1570.0                 # the sink heat of the source heat not taken
    assert t["P_compressor_kW"] == pytest.approx(P) and t["lost_heat_kW"] == pytest.approx(L)
    assert t["cost_eur_per_day"] == pytest.approx(24 / 1000 * (100.0 * P + L * (45.0 - 100.0 * 430 / 2000)))
    # replacement heat cheaper than the heat pump's own: lost capacity costs nothing
    cheap = fouling_cost_terms(fouled, ref, 100.0, 10.0)
    assert cheap["cost_eur_per_day"] == pytest.approx(24 / 1000 * 100.0 * P)
    with pytest.raises(CostError, match="R = 0"):
        LevelRuns([1e-3, 2e-3], [2000, 2010], [430, 440], [1570, 1570])


def _runs_by_hand(res) -> list:
    """(Q_sink, W, Q_source) [kW], weighted means over the window's cost rows, of the adaptive model
    run by hand at R_th,f 0 and at the window's level (every row must solve)."""
    from model.batch import simulate_batch, solved_mask
    rows, w = res.detail["cost_rows"]
    adaptive = res.detail["adaptive_params"]
    cols = ("Q_sink_kW", "W_total_kW", "Q_source_kW")
    runs = []
    for R in (0.0, res.R_th_f_K_per_kW):
        f = simulate_batch(rows, adaptive.replace(R_th_f=R * 1e-3), columns=cols, ls_mode="float")
        assert solved_mask(f).all()
        runs.append(tuple(float(np.sum(w * f[c]) / np.sum(w)) for c in cols))
    return runs


def test_chain_cost_closes_against_two_model_runs_by_hand(plant):
    """The chain's fouling cost of a window = the terms of two model runs on its cost rows, at 0 and at
    the window's R_th,f, done here by hand (+ the source pump)."""
    from model.analysis.chain import AnalysisChain, ChainSettings
    from model.calibration import spec_from_config
    from simulator.synthetic import Noise, Operation, Truth, generate

    h = generate(plant, Operation(hours=2.2, commissioning_minutes=0), Truth(), Noise(), seed=5).history
    chain = AnalysisChain(plant, spec_from_config(plant.extra, "fouling"),
                          ChainSettings(optimize=False, learn_compressors=False,
                                        cip=CipSettings(electricity_price_eur_per_MWh=120.0,
                                                        replacement_heat_eur_per_MWh=60.0)))
    state = chain.new_state(None, None)
    data = h.iloc[20:140]
    res = chain.window(data, state)
    assert res.ok, res.status
    runs = _runs_by_hand(res)
    Qr, Wr, Qsr = runs[0]
    Qf, Wf, Qsf = runs[1]
    comp = Wf - Qf * Wr / Qr
    assert res.fouling_compressor_kW == pytest.approx(comp, rel=1e-9)
    V = data["V_source"].to_numpy(dtype=float)
    dp_clean = float(np.mean(state.fixed.dp_clean(V / 3600.0)) / 1e5)
    pump = np.mean(V) / 3600.0 * max(res.CF_dp_f - 1.0, 0.0) * dp_clean * 1e5 / 0.65 / 1e3
    assert res.fouling_pump_kW == pytest.approx(pump, rel=1e-9)
    lost = max(Qsr - Qsf, 0.0) * Qr / Qsr
    expected = 24 / 1000 * (120.0 * (comp + pump) + lost * max(60.0 - 120.0 * Wr / Qr, 0.0))
    assert res.fouling_cost_eur_per_day == pytest.approx(expected, rel=1e-9)
    # and the energy balance of each run closes: Q_sink = Q_source + W
    for Q, W, Qs in runs:
        assert Q == pytest.approx(Qs + W, rel=1e-6)
    assert res.fouling_cost_cum_eur == pytest.approx(res.fouling_cost_eur_per_day * (
        pd.Timestamp(res.window_end) - pd.Timestamp(res.window_start)).total_seconds() / DAY, rel=1e-9)


def test_cost_levels_turn_with_every_analysed_window_and_the_post_reset_level_is_interpolated(plant):
    """Each analysed window runs R_th,f 0, its own level and the next two cost levels in turn (pass
    2, whatever the windows before were priced); the cost against the level after the last reset is
    the two runs' terms with that level interpolated between the levels run."""
    from model.analysis.chain import AnalysisChain, ChainSettings
    from model.analysis.cip import cost_levels_for
    from model.analysis.cost import cost_rate_eur_per_day, pump_extra_power_kW
    from model.calibration import spec_from_config
    from simulator.synthetic import Noise, Operation, Truth, generate

    c = CipSettings(electricity_price_eur_per_MWh=120.0, replacement_heat_eur_per_MWh=60.0)
    h = generate(plant, Operation(hours=8.2, commissioning_minutes=0), Truth(), Noise(), seed=6).history
    chain = AnalysisChain(plant, spec_from_config(plant.extra, "fouling"),
                          ChainSettings(optimize=False, learn_compressors=False, cip=c))
    state = chain.new_state(None, None)
    checked = 0
    for k in range(4):
        R_post, CF_post = state.forecast.R_post, state.forecast.CF_post
        res = chain.window(h.iloc[20 + 120 * k:140 + 120 * k], state)
        assert res.ok, res.status
        assert state.cost_turn == k + 1
        d = res.detail["cip"]
        assert d["levels_K_per_kW"] == sorted({0.0, res.R_th_f_K_per_kW, *cost_levels_for(c, k)})
        assert cost_levels_for(c, k) == ([2e-3, 4e-3] if k % 2 == 0 else [6e-3, 8e-3])
        if R_post is None or d["runs"] is None:
            continue
        assert R_post not in d["levels_K_per_kW"]
        runs = LevelRuns(np.array(d["levels_K_per_kW"]), d["runs"]["Q_sink_kW"], d["runs"]["W_kW"],
                         d["runs"]["Q_source_kW"])
        t = fouling_cost_terms(runs.at(res.R_th_f_K_per_kW), runs.at(R_post), 120.0, 60.0)
        V = h["V_source"].iloc[20 + 120 * k:140 + 120 * k].to_numpy(dtype=float)
        dp_clean = float(np.mean(state.fixed.dp_clean(V / 3600.0)) / 1e5)
        cf_post = CF_post if CF_post is not None else 1.0
        pump = pump_extra_power_kW(float(np.mean(V)), max((res.CF_dp_f - cf_post) * dp_clean, 0.0), c.eta_pump)
        assert res.fouling_cost_vs_post_eur_per_day == pytest.approx(
            t["cost_eur_per_day"] + cost_rate_eur_per_day(pump, 120.0), rel=1e-9)
        checked += 1
    assert checked >= 2


def test_a_cost_level_the_model_cannot_run_is_dropped_not_the_window(plant):
    """A cost level at which the window's operating points do not solve (50e-3 K/kW: the evaporator
    fouled far past anything the compressors can hold) leaves the window's runs; the window is
    still priced from its other levels, as by hand from R_th,f 0 and its own level."""
    from model.analysis.chain import AnalysisChain, ChainSettings
    from model.batch import simulate_batch, solved_mask
    from model.calibration import spec_from_config
    from simulator.synthetic import Noise, Operation, Truth, generate

    c = CipSettings(electricity_price_eur_per_MWh=120.0, replacement_heat_eur_per_MWh=60.0,
                    cost_levels_K_per_kW=(2e-3, 50e-3), cost_levels_per_window=2)
    h = generate(plant, Operation(hours=2.2, commissioning_minutes=0), Truth(), Noise(), seed=5).history
    chain = AnalysisChain(plant, spec_from_config(plant.extra, "fouling"),
                          ChainSettings(optimize=False, learn_compressors=False, cip=c))
    state = chain.new_state(None, None)
    res = chain.window(h.iloc[20:140], state)
    assert res.ok, res.status
    d = res.detail["cip"]
    assert d["levels_dropped_K_per_kW"] == [50e-3]
    assert d["levels_K_per_kW"] == sorted([0.0, 2e-3, res.R_th_f_K_per_kW])
    rows, _ = res.detail["cost_rows"]
    adaptive = res.detail["adaptive_params"]
    assert not solved_mask(simulate_batch(rows, adaptive.replace(R_th_f=50e-6), ls_mode="float")).any()
    runs = _runs_by_hand(res)
    comp = runs[1][1] - runs[1][0] * runs[0][1] / runs[0][0]
    assert math.isfinite(res.fouling_cost_eur_per_day)
    assert res.fouling_compressor_kW == pytest.approx(comp, rel=1e-9)


# ------------------------------------------------------------------ the registers

def test_registers_carry_the_forecast():
    """Exact register words of the five issue-10 fields for known values (float32, ABCD)."""
    from edge.advisory import encode_advisory
    from edge.config import load_config
    from model.analysis.chain import WindowResult
    from tests.conftest import ROOT

    adv = load_config(ROOT / "config" / "gateway.yaml", load_plant=False).advisory
    r = WindowResult("2024-03-01T00:00:00+00:00", "2024-03-01T02:00:00+00:00", 0.0, 120,
                     R_th_f_K_per_kW=3e-3, fouling_rate_K_per_kW_per_day=1.25e-4,
                     R_th_f_forecast_K_per_kW=4.5e-3, days_to_recommended_cip=3.5,
                     fouling_cost_eur_per_day=182.0, fouling_cost_cum_eur=1234.5)
    values = {k: v for k, v in r.advisory_values().items() if k in {f.name for f in adv.fields}}
    words = encode_advisory(adv, values, (), 0)
    assert {f.name: f.offset for f in adv.fields if 36 <= f.offset < 48} == {
        "fouling_rate": 36, "R_th_f_forecast": 38, "days_to_cip": 40, "fouling_cost": 42,
        "fouling_cost_cum": 44}
    assert words[36:46] == [0x3903, 0x126F, 0x3B93, 0x74BC, 0x4060, 0x0000, 0x4336, 0x0000,
                            0x449A, 0x5000]
    # no forecast yet: NaN (0x7FC0 0x0000), never a stale number
    empty = WindowResult("2024-03-01T00:00:00+00:00", "2024-03-01T02:00:00+00:00", 0.0, 120)
    words = encode_advisory(adv, {k: v for k, v in empty.advisory_values().items()
                                  if k in {f.name for f in adv.fields}}, (), 0)
    assert words[36:46] == [0x7FC0, 0x0000] * 5


# ------------------------------------------------------------------ price CSVs

@pytest.mark.parametrize("text, message", [
    ("time,eur_per_MWh\n2024-03-01T00:00Z,80\n",
     "line 1: no column 'timestamp' in the header (expected timestamp, eur_per_MWh)"),
    ("timestamp,price\n2024-03-01T00:00Z,80\n",
     "line 1: no column 'eur_per_MWh' in the header (expected timestamp, eur_per_MWh)"),
    ("timestamp,eur_per_MWh\n2024-03-01T00:00Z,80\n2024-03-01T01:00Z,8O\n",
     "line 3: price '8O' is not a number [EUR/MWh]"),
    ("timestamp,eur_per_MWh\n2024-03-01T00:00Z,80\n\n2024-13-01T01:00Z,81\n",
     "line 4: timestamp '2024-13-01T01:00Z' is not ISO 8601 (e.g. 2024-03-01T06:00:00Z; UTC when naive)"),
    ("timestamp,eur_per_MWh\n2024-03-01T01:00Z,80\n2024-03-01T01:00Z,81\n",
     "line 3: timestamp '2024-03-01T01:00Z' is not after the one at line 2 (prices must be in time "
     "order, once each)"),
    ("timestamp,eur_per_MWh\n2024-03-01T00:00Z,nan\n", "line 2: price 'nan' is outside -10000..100000 EUR/MWh"),
    ("timestamp,eur_per_MWh\n2024-03-01T00:00Z,80,1\n", "line 2: 3 fields, the header has 2"),
    ("timestamp,eur_per_MWh\n", "no prices after the header"),
])
def test_price_csv_errors_name_the_file_and_the_line(tmp_path, text, message):
    from edge.io.prices import PriceFileError, read_price_csv
    path = tmp_path / "prices.csv"
    path.write_text(text)
    with pytest.raises(PriceFileError) as info:
        read_price_csv(path)
    assert str(info.value) == f"{path}: {message}"


def test_price_csv_reads_a_spot_export_with_semicolons_and_decimal_commas(tmp_path):
    from edge.io.prices import price_for_plant, read_price_csv
    path = tmp_path / "spot.csv"
    path.write_text("timestamp;area;eur_per_MWh\n2024-03-01 00:00;DK1;84,10\n2024-03-01 01:00;DK1;-3,5\n")
    ps = read_price_csv(path)
    assert list(ps.t_s) == [pd.Timestamp("2024-03-01T00:00Z").timestamp(), pd.Timestamp("2024-03-01T01:00Z").timestamp()]
    assert list(ps.eur_per_MWh) == [84.10, -3.5]
    assert ps.mean(ps.t_s[0], ps.t_s[0] + 7200) == pytest.approx((84.10 - 3.5) / 2)
    # plant.yaml names it relative to its own folder
    got = price_for_plant({"cip": {"electricity_price_csv": "spot.csv"}}, tmp_path / "plant.yaml")
    assert list(got.eur_per_MWh) == [84.10, -3.5]
    assert price_for_plant({"cip": {"electricity_price_eur_per_MWh": 90}}, tmp_path / "plant.yaml") is None


def test_check_config_names_plant_yaml_and_the_bad_price_file(tmp_path, capsys):
    import shutil

    import yaml

    from edge.cli import main
    from tests.conftest import ROOT
    cfg = tmp_path / "config"
    shutil.copytree(ROOT / "config", cfg)
    plant = yaml.safe_load((cfg / "plant.yaml").read_text())
    del plant["cip"]["electricity_price_eur_per_MWh"]
    plant["cip"]["electricity_price_csv"] = "prices.csv"
    (cfg / "plant.yaml").write_text(yaml.safe_dump(plant))
    (cfg / "prices.csv").write_text("timestamp,eur_per_MWh\n2024-03-01T00:00Z,80\n2024-03-01T01:00Z,x\n")
    assert main(["check-config", "--config", str(cfg / "gateway.yaml")]) == 2
    err = capsys.readouterr().err
    assert (f"plant.yaml: key 'cip.electricity_price_csv': {cfg / 'prices.csv'}: line 3: price 'x' is not "
            "a number [EUR/MWh]") in err


# ------------------------------------------------------------------ replay: forecast.csv

@pytest.fixture(scope="module")
def replayed(tmp_path_factory, plant):
    """44 h: commissioning, fouling, a flagged 6-h CIP at 34 h, 4 h after it; replayed by the CLI."""
    from edge.cli import main
    from simulator.synthetic import Noise, Operation, Truth, generate

    d = tmp_path_factory.mktemp("replay")
    h = generate(plant, Operation(hours=44, commissioning_minutes=90, cip_starts_h=(34.0,), cip_duration_h=6.0),
                 Truth(), Noise(), seed=4)
    path = d / "history.csv"
    h.history.to_csv(path, index=False)
    out = d / "out"
    assert main(["replay", str(path), "--out", str(out), "--no-optimize", "--forecast-horizon-days", "2"]) == 0
    return out, h


def test_replay_writes_forecast_csv_with_the_issue_columns(replayed):
    from model.analysis.replay import FORECAST_COLUMNS
    out, h = replayed
    f = pd.read_csv(out / "forecast.csv")
    w = pd.read_csv(out / "windows.csv")
    assert list(f.columns) == ["window_end", "forecast_at", "R_th_f_forecast_K_per_kW",
                               "R_th_f_forecast_lo_K_per_kW", "R_th_f_forecast_hi_K_per_kW",
                               "fouling_rate_K_per_kW_per_day", "fouling_cost_eur_per_day",
                               "days_to_recommended_cip"] == list(FORECAST_COLUMNS)
    assert len(f) == len(w) and (f["window_end"] == w["window_end"]).all()
    cip_end = h.cips[0]["end"]
    ends = pd.to_datetime(f["window_end"], utc=True)
    has = f["R_th_f_forecast_K_per_kW"].notna()
    before, after = has & (ends < cip_end), ends > cip_end
    assert before.sum() >= 2                      # > 1 day of windows before the CIP: a forecast
    assert not has[after].any()                   # 4 h since the CIP: not enough data, no number
    g = f[has]
    assert (pd.to_datetime(g["forecast_at"], utc=True) - pd.to_datetime(g["window_end"], utc=True)
            == pd.Timedelta(days=2)).all()
    assert (g["R_th_f_forecast_lo_K_per_kW"] < g["R_th_f_forecast_K_per_kW"]).all()
    assert (g["R_th_f_forecast_K_per_kW"] < g["R_th_f_forecast_hi_K_per_kW"]).all()
    assert (g["fouling_rate_K_per_kW_per_day"] > 0).all()
    last = w[has & before].iloc[-1]
    assert g["R_th_f_forecast_K_per_kW"].iloc[-1] > last["R_th_f_K_per_kW"]
    ok = w["status"] == "ok"
    assert f.loc[ok, "fouling_cost_eur_per_day"].notna().all()
    # the cumulated cost restarts at the CIP, the forecast counts days from its end
    assert w.loc[after, "fouling_cost_cum_eur"].max() < w.loc[before, "fouling_cost_cum_eur"].max()
    assert w.loc[after, "days_since_reset"].max() < 0.2
    text = (out / "summary.txt").read_text()
    assert "When to clean (forecast since the last reset, cost of fouling, cost-optimal CIP):" in text
    assert "since the last CIP" in text


# ------------------------------------------------------------------ the gateway: CIPs and restarts

def _minutes(cip_after_min: int, cip_minutes: float, after_min: int):
    """One-minute samples of the simulator's plant: a flagged CIP requested after cip_after_min."""
    from edge.aggregate import Sample
    from simulator.config import load_simulator_config
    from simulator.export import MinuteStepper

    st = MinuteStepper(load_simulator_config().with_sections(
        cip={"mode": "on_request", "duration_days": cip_minutes / 1440.0}), with_truth=False)
    out = []
    for m in range(cip_after_min + int(cip_minutes) + after_min):
        if m == cip_after_min:
            st.plant.request_cip()
        row, _ = st.step()
        ts = pd.Timestamp(row.pop("timestamp")).timestamp()
        vals = {k: float(v) for k, v in row.items()}
        out.append(Sample(ts, vals, {k: "nan" for k, v in vals.items() if not math.isfinite(v)},
                          12, 12, 0, 0, ""))
    return out


def _advisor(tmp_path):
    from dataclasses import replace

    from edge.config import load_config
    from edge.service import ModelAdvisor, StateDir
    from edge.store import HistoryStore
    from tests.conftest import ROOT

    c = replace(load_config(ROOT / "config" / "gateway.yaml"), state_dir=tmp_path / "state",
                history_db=tmp_path / "h.sqlite", optimizer="model")
    store = HistoryStore(c.history_db, c.history_retention_days).open()
    return ModelAdvisor(c, store, StateDir(c.state_dir, ROOT / "config" / "surrogate.json")), store


def test_gateway_finds_a_cip_resets_the_forecast_and_keeps_it_over_restarts(tmp_path):
    samples = _minutes(cip_after_min=130, cip_minutes=40, after_min=75)
    adv, store = _advisor(tmp_path)
    try:
        adv.ingest(samples[:130])
        a = adv.advise(samples[129].timestamp)
        assert a.ok, a.message
        fs = adv.cstate.forecast
        assert len(fs.R) == 1 and fs.reset_kind == "first window"
        before = json.loads(json.dumps(fs.to_dict()))
        assert adv.cstate.cost_turn == 1                  # one window analysed: the cost levels' turn
        adv.ingest(samples[130:150])                     # the CIP begins; the gateway stops here
    finally:
        store.close()
    adv, store = _advisor(tmp_path)
    try:
        assert json.loads(json.dumps(adv.cstate.forecast.to_dict())) == before
        assert adv.cstate.cost_turn == 1                  # kept over the restart
        assert adv._watch.down_since is not None          # the stop in progress was remembered
        adv.ingest(samples[150:])
        fs = adv.cstate.forecast
        cip_rows = [s for s in samples if s.values.get("cip", 0) > 0.5]
        first_after = next(s for s in samples if s.timestamp > cip_rows[-1].timestamp)
        assert fs.reset_kind == "cip_flag" and fs.reset_s == first_after.timestamp
        c = fs.cips[-1]
        assert c["start_s"] <= cip_rows[0].timestamp and c["R_before"] == pytest.approx(before["R"][0])
        assert fs.R == [] and fs.tally.total_eur == 0.0
        doc = json.loads((tmp_path / "state" / "chain_state.json").read_text())
        assert doc["forecast"]["reset_s"] == first_after.timestamp
        # the next advice uses samples after the CIP only, and starts the new cycle's forecast
        b = adv.advise(samples[-1].timestamp)
        assert b.ok, b.message
        assert pd.Timestamp(b.detail["window"]["window_start"]).timestamp() >= first_after.timestamp
        assert len(adv.cstate.forecast.R) == 1 and adv.cstate.cost_turn == 2
        assert b.values["fouling_cost_cum"] < a.values["fouling_cost_cum"] * 2
    finally:
        store.close()


# ------------------------------------------------------------------ the bench's accounting

def test_bench_accounting_closes_and_sharing_changes_nothing(plant):
    from edge.bench_cip import run_policies, run_result

    kw = dict(days=0.4, advised=False, max_extra_days=0.3, sim_cip={"removal_share": 0.3, "duration_days": 0.1})
    both = run_policies(plant, fixed=(0.15, 0.25), **kw)
    alone = run_policies(plant, fixed=(0.15,), **kw)
    res = {r.policies[0].name: (r, run_result(r, both["t0"], 0.4)) for r in both["runs"]}
    assert len(both["runs"]) == 2 and all(len(r.policies) == 1 for r in both["runs"])
    for run, r in res.values():
        a = run.account
        parts = ("electricity_eur", "pumps_eur", "cip_direct_eur", "downtime_heat_eur", "running_heat_eur")
        assert r["total_eur"] == pytest.approx(sum(r[k] for k in parts), rel=1e-12)
        assert r["baseline_eur"] + r["excess_eur"] == pytest.approx(r["total_eur"], rel=1e-12)
        assert a.electricity_eur == pytest.approx(a.electricity_MWh * 100.0, rel=1e-12)
        # the heat balance: what was bought (down and running) is the demand not delivered
        closing = run.closing_downtime_days * 24.0 * a.last_demand_kW / 1e3
        assert a.downtime_heat_eur + a.running_heat_eur == pytest.approx(
            (a.demand_MWh + closing - a.heat_MWh) * 25.0, rel=1e-9)
        assert a.cip_direct_eur == 150.0 * len(r["cip_start_days"]) and a.downtime_min > 0
        assert r["cycle_total_eur"] == pytest.approx(
            run.baseline_at_horizon + r["excess_eur"] / r["days_accounted"] * 0.4, rel=1e-12)
    one = run_result(alone["runs"][0], alone["t0"], 0.4)
    shared = next(r for run, r in res.values() if r["policies"] == ["every 0.15 d"])
    for k, v in one.items():      # the same plant, the same decisions: the same figures (to round-off
        if isinstance(v, float):    # of the solver's warm starts)
            assert shared[k] == pytest.approx(v, rel=1e-9), k
        else:
            assert shared[k] == v, k
