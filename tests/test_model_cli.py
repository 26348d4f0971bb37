"""Model commands: fit-compressor recovers known curves and names bad columns/rows; point output."""
from __future__ import annotations

import json

import pytest

from edge.cli import main
from model.compressor_fit import fit, read_table, synthetic_table

COEF_TOL = 1e-6


def test_fit_recovers_known_coefficients(plant, tmp_path):
    comp = plant.comp_HS.replace(eta_is=(0.55, 0.09, 0.30, -0.018, 0.01, -0.20),
                                 eta_vol=(0.80, -0.025, 0.35, 0.001, -0.01, -0.22))
    table = synthetic_table(comp, p_suc_bar=14.0)
    path = tmp_path / "hs.csv"
    table.to_csv(path, index=False)
    res = fit(read_table(str(path)), plant.comp_HS)     # same swept volume / nominal speed
    assert res.eta_is == pytest.approx(comp.eta_is, abs=COEF_TOL)
    assert res.eta_vol == pytest.approx(comp.eta_vol, abs=COEF_TOL)
    assert res.r2_is > 0.999999 and res.r2_vol > 0.999999


def test_fit_compressor_command_prints_config_snippet(plant, tmp_path, capsys):
    path = tmp_path / "ls.csv"
    synthetic_table(plant.comp_LS, p_suc_bar=7.3).to_csv(path, index=False)
    out_file = tmp_path / "coef.yaml"
    assert main(["fit-compressor", str(path), "--stage", "LS", "--out", str(out_file)]) == 0
    out = capsys.readouterr().out
    assert "eta_is : R^2 = 1.00000" in out
    import yaml
    d = yaml.safe_load(out_file.read_text())
    assert d["compressors"]["LS"]["eta_is"] == pytest.approx(list(plant.comp_LS.eta_is), abs=1e-5)


def test_missing_column_is_named(tmp_path, capsys):
    path = tmp_path / "t.csv"
    path.write_text("speed_rpm,p_suc_bar,T_suc_C,p_dis_bar,power_kW\n1500,7,16,17,200\n")
    assert main(["fit-compressor", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"hp-edge fit-compressor: {path}: missing column(s) 'm_dot_kg_s'; expected "
                           "speed_rpm, p_suc_bar, T_suc_C, p_dis_bar, m_dot_kg_s, power_kW")


def test_non_numeric_row_is_named(plant, tmp_path, capsys):
    path = tmp_path / "t.csv"
    t = synthetic_table(plant.comp_LS, p_suc_bar=7.3).astype(str)
    t.iloc[6, 3] = "n/a"
    t.to_csv(path, index=False)
    assert main(["fit-compressor", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"hp-edge fit-compressor: {path}: row 7 (line 8): column 'p_dis_bar': 'n/a' is not a number"


def test_point_json_has_documented_keys(capsys):
    assert main(["point", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    for k in ("p_e_bar", "p_m_bar", "p_c_bar", "N_LS_rpm", "N_HS_rpm", "Q_sink_kW", "Q_source_kW",
              "W_LS_kW", "W_HS_kW", "W_total_kW", "COP", "T_sink_out_C", "eta_is_LS", "eta_is_HS",
              "eta_vol_LS", "eta_vol_HS", "m_LS_kg_s", "m_HS_kg_s", "superheat_K", "subcooling_K",
              "pinch_K", "dp_source_bar"):
        assert k in d, k
    assert set(d["states"]["LS_suc"]) == {"T_C", "p_bar", "h_J_kg"}
    assert d["status"] == "ok"
    assert abs(d["Q_sink_kW"] - (d["Q_source_kW"] + d["W_total_kW"])) < 1e-6 * d["Q_sink_kW"]


def test_point_table_and_infeasible_exit(capsys):
    assert main(["point", "--p-m-sp", "10"]) == 0
    out = capsys.readouterr().out
    assert "(HS at its limit, p_m floats)" in out and "LS_suc" in out
    assert main(["point", "--T-source-out", "26"]) == 1
    assert "infeasible (bad_source)" in capsys.readouterr().err


def test_point_bad_config_names_file(tmp_path, capsys):
    bad = tmp_path / "plant.yaml"
    bad.write_text("fluid: Ammonia\nwater: {cp_kJ_per_kgK: 4.18}\n")
    with pytest.raises(SystemExit) as ei:
        main(["point", "--config", str(bad)])
    assert ei.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    # every problem is reported at once, each line naming the file and the key
    assert lines[0] == f"hp-edge: {bad}: missing key 'water.rho_kg_per_m3'"
    assert f"hp-edge: {bad}: missing key 'evaporator.U_W_per_m2K'" in lines
    assert f"hp-edge: {bad}: missing key 'source_pressure_drop.dp_clean_coef'" in lines
    assert all(line.startswith(f"hp-edge: {bad}: ") for line in lines)


def test_point_refuses_non_finite_inputs(capsys):
    with pytest.raises(SystemExit) as ei:
        main(["point", "--T-source-in", "nan"])
    assert ei.value.code == 2
    assert "argument --T-source-in: 'nan' is not a finite number" in capsys.readouterr().err
