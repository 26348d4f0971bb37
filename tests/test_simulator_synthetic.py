"""The synthetic histories with known truth (simulator/synthetic.py) use the simulator's own sensor
map and LS controller (simulator/sensors.py): without noise their rows are exactly that mapping."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from model.fluid import get_fluid
from model.params import PlantParams
from model.units import BAR, T0
from simulator.config import load_simulator_config
from simulator.sensors import N_TOL
from simulator.synthetic import Noise, Operation, Truth, generate

QUIET = Noise(sigma_T_K=0.0, sigma_p_bar=0.0, rel_flow=0.0, rel_power=0.0)


@pytest.fixture(scope="module")
def fouled():
    with open(load_simulator_config().plant_file) as fh:
        plant = PlantParams.from_dict(yaml.safe_load(fh))
    # 20 days of fouling before the record: the LS runs at its speed limit part of the day
    op = Operation(hours=12, commissioning_minutes=0, gap_after_commissioning_days=20,
                   T_source_in_C=23.5, p_m_sp_barg=16.0, peak_hour=6.0)
    return generate(plant, op, Truth(), QUIET, seed=1)


def test_rows_are_the_shared_sensor_map(fouled):
    h, t = fouled.history, fouled.truth
    amb = fouled.params.ambient_pressure / BAR
    fl = get_fluid()
    for i in (0, len(h) // 2, len(h) - 1):
        row = h.iloc[i]
        p_c = (row["p_dis_HS"] + amb) * BAR
        assert row["T_c"] + T0 == pytest.approx(fl.sat_p(p_c).T, abs=1e-6)   # condenser outlet
        assert row["T_suc_LS"] == pytest.approx(row["T_e"] + fouled.params.superheat, abs=1e-9)
        assert row["p_dis_LS"] == row["p_suc_HS"]
        assert row["p_source_out"] == Operation().p_source_out_barg
    ok = (t["status"] == "ok").to_numpy()
    lim = (t["status"] == "ls_speed_limit").to_numpy()
    assert ok.any() and lim.any()
    assert np.allclose(h["T_source_out"].to_numpy()[ok], 18.0, atol=1e-9)
    assert (h["T_source_out"].to_numpy()[lim] > 18.0).all()
    assert np.abs(h["N_LS"].to_numpy()[lim] - 1800.0).max() < N_TOL
