"""Measured-side processing: derived values recover the model's truth; unusable rows have reasons."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from model.batch import inputs_from_row
from model.cycle import solve
from model.measured import process, usable_counts
from model.units import K_to_C

AMB = 1.01325
ETA_TOL = 1e-6       # measured eta_is from exact model states
R_TOL = 1e-9         # K/kW, point estimate of R_th,f from exact model states


def measured_rows(plant, nominal_row, n=20, R=1.5e-6):
    p = plant.replace(R_th_f=R)
    r = solve(inputs_from_row(nominal_row, AMB), p)
    s = r.states
    row = dict(nominal_row, T_sink_out=K_to_C(r.T_sink_out), p_source_in=2.5,
               p_source_out=2.5 - r.dp_source / 1e5, T_suc_LS=K_to_C(s["LS_suc"].T),
               T_dis_LS=K_to_C(s["LS_dis"].T), T_suc_HS=K_to_C(s["HS_suc"].T) + 0.5,
               T_dis_HS=K_to_C(s["HS_dis"].T), p_suc_LS=r.p_e / 1e5 - AMB, p_dis_LS=r.p_m / 1e5 - AMB,
               p_suc_HS=r.p_m / 1e5 - AMB, p_dis_HS=r.p_c / 1e5 - AMB, T_c=K_to_C(r.T_c),
               T_e=K_to_C(r.T_e), W_LS=r.W_LS / 1e3, W_HS=r.W_HS / 1e3, running=1, cip=0)
    ts = pd.date_range("2026-03-01", periods=n, freq="1min", tz="UTC")
    return pd.DataFrame([row] * n, index=ts), r


def test_derived_values_recover_model_truth(plant, nominal_row):
    df, r = measured_rows(plant, nominal_row)
    m = process(df, plant)
    assert m["usable"].all()
    row = m.iloc[5]
    assert row["p_e_bar"] == pytest.approx(r.p_e / 1e5, rel=1e-12)
    assert row["COP"] == pytest.approx(r.COP, rel=1e-9)
    assert row["Q_sink_kW"] == pytest.approx(r.Q_sink / 1e3, rel=1e-9)
    assert row["eta_is_LS_meas"] == pytest.approx(r.eta_is_LS, abs=ETA_TOL)
    assert row["R_th_f_K_per_kW"] == pytest.approx(1.5e-3, abs=R_TOL)
    assert row["superheat_K"] == pytest.approx(plant.superheat, abs=1e-6)
    assert row["dp_source_bar"] == pytest.approx(r.dp_source / 1e5, rel=1e-9)


def test_unusable_rows_carry_reasons(plant, nominal_row):
    df, _ = measured_rows(plant, nominal_row, n=40)
    df.iloc[3, df.columns.get_loc("V_sink")] = np.nan
    df.iloc[4, df.columns.get_loc("T_e")] = 500.0
    df.iloc[6, df.columns.get_loc("cip")] = 1
    df.iloc[8:12, df.columns.get_loc("running")] = 0     # stop ...
    df.iloc[8:12, df.columns.get_loc("W_LS")] = 0.0
    df.iloc[8:12, df.columns.get_loc("W_HS")] = 0.0       # ... and restart: ramping afterwards
    m = process(df, plant)
    assert m["reason"].iloc[3] == "missing: V_sink"
    assert m["reason"].iloc[4] == "out_of_range: T_e=500"
    assert m["reason"].iloc[6] == "cip"
    assert list(m["reason"].iloc[8:12]) == ["off"] * 4
    assert m["reason"].iloc[7] == "ramping"             # the minute after a CIP sample
    assert list(m["reason"].iloc[12:22]) == ["ramping"] * 10
    assert m["usable"].iloc[22]
    counts = usable_counts(m)
    assert counts == {"ramping": 11, "off": 4, "missing: V_sink": 1, "out_of_range: T_e": 1, "cip": 1}


def test_custom_ranges_mark_bad_never_clamp(plant, nominal_row):
    df, _ = measured_rows(plant, nominal_row, n=3)
    m = process(df, plant, ranges={"T_sink_out": (0.0, 60.0)})
    assert not m["usable"].any()
    assert m["reason"].iloc[0].startswith("out_of_range: T_sink_out=")
    assert df["T_sink_out"].iloc[0] > 60.0        # the input is untouched
