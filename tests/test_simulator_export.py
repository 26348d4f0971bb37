"""History export: canonical columns, determinism, CIP rows, scheduled faults, the CLI, and the
round trip through the measured-side processing (model.measured.process)."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
import yaml

from edge.cli import main
from model.measured import process
from model.params import PlantParams
from simulator.config import FaultSpec, load_simulator_config, read_tags
from simulator.export import export_history, read_history

CFG = load_simulator_config()
TAGS = read_tags(CFG.tags_file)
CANONICAL = [n for n in TAGS if n not in ("plc_clock", "life_counter", "closed_loop_enable")]
# a CIP early on, so that two plant days hold running, stopped and restarted rows
SHORT_CIP = CFG.replace(cip=dataclasses.replace(CFG.cip, first_after_days=0.5, jitter_days=0.0,
                                                duration_days=0.5, interval_days=10.0))
COP_REL_TOL = 0.03       # measured (noisy, quantized, lagged) vs hidden steady COP, median
DP_ABS_TOL = 0.01        # bar


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    res = export_history(2.0, d / "history.csv", cfg=SHORT_CIP, truth_path=d / "truth.csv")
    return res, d


def test_columns_timestamps_and_files(exported):
    res, d = exported
    assert res.rows == 2 * 1440
    hist = pd.read_csv(d / "history.csv")
    assert list(hist.columns) == ["timestamp"] + CANONICAL
    assert hist["timestamp"].iloc[0] == "2024-03-01T00:00:00Z"
    assert hist["timestamp"].iloc[1] == "2024-03-01T00:01:00Z"
    truth = pd.read_csv(d / "truth.csv")
    assert len(truth) == res.rows and (truth["timestamp"] == hist["timestamp"]).all()
    for col in ("R_th_f_K_per_kW", "CF_dp_f", "CF_eva", "COP", "p_m_opt_bar_g"):
        assert col in truth.columns


def test_cip_rows_and_restart(exported):
    res, _ = exported
    h, t = res.history, res.truth
    cip = h["cip"] == 1
    assert 0.2 < cip.mean() < 0.3                            # half a day of two
    assert (h.loc[cip, "running"] == 0).all()
    inside = cip & cip.shift(1, fill_value=False) & cip.shift(-1, fill_value=False)
    assert (h.loc[inside, ["W_LS", "W_HS", "N_LS", "N_HS", "V_source"]] == 0).all().all()
    after = t["cip_count"] == 1
    assert after.any() and (h.loc[after & (h["cip"] == 0), "running"] == 1).all()
    R = t["R_th_f_K_per_kW"].to_numpy()
    i = int(np.argmax(after.to_numpy()))
    assert R[i] == pytest.approx(R[i - 1] * (1 - SHORT_CIP.cip.removal_share), rel=1e-4)


def test_round_trip_through_measured_processing(exported):
    _, d = exported
    hist = read_history(d / "history.csv")
    truth = pd.read_csv(d / "truth.csv")
    with open(CFG.plant_file) as fh:
        params = PlantParams.from_dict(yaml.safe_load(fh))
    out = process(hist, params, ranges={n: TAGS[n].range for n in CANONICAL})
    reasons = out["reason"].to_numpy()
    cip = hist["cip"].to_numpy() == 1
    assert (reasons[cip] == "cip").all()
    usable = out["usable"].to_numpy()
    assert usable[~cip].mean() > 0.9                       # running rows are usable, minus ramps
    cop_err = np.abs(out["COP"].to_numpy()[usable] / truth["COP"].to_numpy()[usable] - 1)
    assert np.median(cop_err) < COP_REL_TOL
    dp_true = truth["CF_dp_f"].to_numpy()[usable] * params.dp_clean(hist["V_source"].to_numpy()[usable] / 3600) / 1e5
    assert np.median(np.abs(out["dp_source_bar"].to_numpy()[usable] - dp_true)) < DP_ABS_TOL
    # the point estimate of R_th,f follows the hidden truth (offset by the hidden CF_eva)
    est = out["R_th_f_K_per_kW"].to_numpy()[usable]
    tru = truth["R_th_f_K_per_kW"].to_numpy()[usable]
    assert np.corrcoef(est, tru)[0, 1] > 0.5


def test_deterministic_and_seeded():
    a = export_history(0.05).history
    b = export_history(0.05).history
    c = export_history(0.05, seed=CFG.seed + 7).history
    pd.testing.assert_frame_equal(a, b)
    assert not a.equals(c)


def test_scheduled_faults_reach_the_history():
    faults = (FaultSpec(kind="stuck", tag="T_dis_HS", at_h=0.5, duration_h=0.5),
              FaultSpec(kind="nan", tag="T_e", at_h=1.0, duration_h=0.25),
              FaultSpec(kind="out_of_range", tag="V_sink", at_h=1.5, duration_h=0.25))
    h = export_history(2.0 / 24, cfg=CFG.replace(faults=faults)).history
    stuck = h["T_dis_HS"].iloc[31:60]
    assert stuck.nunique() == 1 and h["T_dis_HS"].iloc[61:90].nunique() > 1
    assert h["T_e"].iloc[60:75].isna().all() and h["T_e"].iloc[76:].notna().all()
    assert (h["V_sink"].iloc[90:105] > TAGS["V_sink"].range[1]).all()
    out = process(h.set_index(pd.to_datetime(h["timestamp"])).drop(columns="timestamp"),
                  PlantParams.from_dict(yaml.safe_load(open(CFG.plant_file))),
                  ranges={n: TAGS[n].range for n in CANONICAL})
    assert out["reason"].iloc[62].startswith("missing: T_e")
    assert out["reason"].iloc[92].startswith("out_of_range: V_sink")


def test_cli_export(tmp_path, capsys):
    rc = main(["simulate", "--export", str(tmp_path / "h.csv"), "--days", "0.025",
               "--truth", str(tmp_path / "t.csv"), "--seed", "3"])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert info["rows"] == 36 and info["seed"] == 3
    assert len(pd.read_csv(tmp_path / "h.csv")) == 36 == len(pd.read_csv(tmp_path / "t.csv"))


def test_cli_export_starts_at_commissioning_unless_asked(tmp_path, capsys):
    # replay's default initial window is "the first 90 usable minutes, which commissioning data
    # are": an export therefore starts with a clean evaporator unless --start-fouled is given
    main(["simulate", "--export", str(tmp_path / "h.csv"), "--days", "0.01",
          "--truth", str(tmp_path / "t.csv"), "--seed", "3"])
    clean = pd.read_csv(tmp_path / "t.csv")
    main(["simulate", "--export", str(tmp_path / "h2.csv"), "--days", "0.01",
          "--truth", str(tmp_path / "t2.csv"), "--seed", "3", "--start-fouled"])
    fouled = pd.read_csv(tmp_path / "t2.csv")
    capsys.readouterr()
    r_col = [c for c in clean.columns if c.startswith("R_th_f")][0]
    cf_col = [c for c in clean.columns if c.startswith("CF_dp_f")][0]
    assert clean[r_col].iloc[0] < 1e-5 and clean[cf_col].iloc[0] == pytest.approx(1.0, abs=1e-4)
    assert fouled[r_col].iloc[0] == pytest.approx(2.5e-3, rel=0.01)
