"""The simulated plant without a server: hidden truth, sensor consistency, controllers, fouling,
CIP, determinism, register encoding and config errors."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pymodbus.client.mixin import ModbusClientMixin

from model.fluid import get_fluid
from model.units import BAR, T0
from simulator.config import (SimConfigError, config_from_dict, load_simulator_config, read_tags)
from simulator.faults import Faults, parse_cli_fault
from simulator.plant import NAMES, Plant, flow_factor
from simulator.profiles import DAY, Fouling
from simulator.registers import encode, quantize

CFG = load_simulator_config()
TAGS = read_tags(CFG.tags_file)
AMB = CFG.ambient_pressure_bar
P_TOL = 1e-6       # bar: exact identities of the steady state
T_TOL = 1e-6       # K


NOMINAL_SOURCE = {"T_source_in_mean_C": 25.0, "T_source_in_daily_amp_K": 0.0,   # SPEC §2 point
                  "weather_T_source_K": 0.0, "limits_T_source_in_C": (24.0, 26.0)}


@pytest.fixture(scope="module")
def sim_plant():
    return Plant(CFG)


def cfg_with(**sections):
    """CFG with some sections replaced: cfg_with(cip={'first_after_days': 0.02}, ...)."""
    kw = {}
    for name, changes in sections.items():
        kw[name] = dataclasses.replace(getattr(CFG, name), **changes)
    return CFG.replace(**kw)


def test_hidden_truth_differs_from_plant_yaml(sim_plant):
    nom, tru = sim_plant.nominal, sim_plant.true
    for cf in ("CF_eva", "CF_con", "CF_DSH", "CF_SC"):
        assert getattr(nom, cf) == 1.0 and getattr(tru, cf) == getattr(CFG.truth, cf) != 1.0
    assert tru.comp_LS.eta_is != nom.comp_LS.eta_is and tru.comp_HS.eta_vol != nom.comp_HS.eta_vol
    # the perturbation is the documented one: eta' = scale*eta + tilt*(pi - 2.5)
    ct = CFG.truth.compressors["LS"]
    pi, n = 3.1, 0.9
    want = ct.eta_is_scale * nom.comp_LS.eta_is_at(pi, n) + ct.eta_is_pi_tilt * (pi - 2.5)
    assert tru.comp_LS.eta_is_at(pi, n) == pytest.approx(want, rel=1e-12)


def test_heat_transfer_varies_with_flow_as_m_to_0_8():
    f = CFG.flow_dependence
    assert flow_factor(f.V_source_nom_m3h, f.V_source_nom_m3h, 0.5, 0.8) == pytest.approx(1.0)
    # all resistance on the water side: U ~ V^0.8 exactly
    assert flow_factor(0.5 * 192, 192, 0.999999, 0.8) == pytest.approx(0.5 ** 0.8, rel=1e-5)
    p = Plant(CFG)
    lo = p.effective_params(150.0, 50.0)
    hi = p.effective_params(220.0, 70.0)
    assert lo.CF_eva < CFG.truth.CF_eva * 1.0001 and hi.CF_eva > lo.CF_eva
    assert hi.CF_con > lo.CF_con and hi.CF_SC > lo.CF_SC


def test_sensors_consistent_with_model_state(sim_plant):
    v, r = sim_plant.steady.values, sim_plant.steady.res
    fl = get_fluid()
    assert v["p_suc_LS"] == pytest.approx(r.p_e / BAR - AMB, abs=P_TOL)
    assert v["p_dis_LS"] == v["p_suc_HS"] == pytest.approx(r.p_m / BAR - AMB, abs=P_TOL)
    assert v["p_dis_HS"] == pytest.approx(r.p_c / BAR - AMB, abs=P_TOL)
    assert v["T_e"] + T0 == pytest.approx(fl.sat_p(r.p_e).T, abs=1e-6)
    assert v["T_suc_LS"] == pytest.approx(v["T_e"] + sim_plant.true.superheat, abs=T_TOL)
    assert v["T_suc_HS"] + T0 == pytest.approx(fl.sat_p(r.p_m).T, abs=1e-6)
    assert v["T_c"] + T0 == pytest.approx(fl.sat_p(r.p_c).T, abs=1e-6)      # condenser outlet
    assert v["T_dis_LS"] > v["T_suc_HS"] and v["T_dis_HS"] > v["T_c"]
    # water-side energy balance: Q_sink = Q_source + W (adiabatic compressors, motor eff 1)
    rc = sim_plant.true.cp_w * sim_plant.true.rho_w / 3600 / 1e3
    Q_sink = rc * v["V_sink"] * (v["T_sink_out"] - v["T_sink_in"])
    Q_src = rc * v["V_source"] * (v["T_source_in"] - v["T_source_out"])
    assert Q_sink == pytest.approx(Q_src + v["W_LS"] + v["W_HS"], rel=1e-6)
    assert v["p_source_in"] - v["p_source_out"] == pytest.approx(r.dp_source / BAR, abs=1e-12)
    assert v["p_source_out"] < v["p_source_in"]


def test_lags_and_noise_around_steady_state():
    p = Plant(CFG)
    samples = []
    for _ in range(240):                 # 20 plant minutes
        p.tick()
        samples.append(p.noisy.copy())
    s = np.array(samples)
    i = NAMES.index("T_e")
    assert np.std(np.diff(s[:, i])) > 0.5 * CFG.noise["T_e"]          # white noise per tick
    assert abs(s[-1, i] - p.steady.values["T_e"]) < 6 * CFG.noise["T_e"] + 0.3


def test_deterministic_for_a_seed():
    a, b, c = Plant(CFG), Plant(CFG), Plant(CFG.replace(seed=CFG.seed + 1))
    for p in (a, b, c):
        p.advance_to(p.t + 3 * 3600)
    assert np.array_equal(a.noisy, b.noisy)
    assert a.truth() == b.truth()
    assert not np.array_equal(a.noisy, c.noisy)


def test_setpoint_moves_p_m_and_is_clamped():
    p = Plant(CFG)
    p.set_p_m_sp(12.5)
    p.advance_to(p.t + 3600)
    r = p.steady.res
    p_m = r.p_m / BAR - AMB
    assert p_m == pytest.approx(12.5, abs=1e-6) or (r.hs_saturated and p_m > 12.5)
    assert p.measured["p_dis_LS"] == pytest.approx(p_m, abs=0.1)
    assert p.set_p_m_sp(99.0) == CFG.control.p_m_sp_limits_bar_g[1]
    assert p.set_p_m_sp(float("nan")) == CFG.control.p_m_sp_limits_bar_g[1]   # ignored


def test_business_as_usual_setpoint_saturates_hs():
    p = Plant(cfg_with(profiles=NOMINAL_SOURCE))
    p.set_p_m_sp(10.0)
    p.advance_to(p.t + 120)
    r = p.steady.res
    assert r.hs_saturated and r.N_HS == pytest.approx(1800.0, abs=1e-3)
    assert r.p_m / BAR - AMB > 10.5


def test_ls_speed_limits_float_T_source_out():
    fouled = Plant(cfg_with(profiles=NOMINAL_SOURCE,
                            fouling={"R_th_f_initial_K_per_kW": 6.0e-3, "R_th_f_inf_K_per_kW": 6.0e-3}))
    sp = fouled.steady
    assert sp.ls_limit == "max" and sp.res.N_LS == pytest.approx(1800.0, abs=0.5)
    assert sp.T_source_out_C > CFG.control.T_source_out_sp_C + 0.05
    warm = cfg_with(profiles={"T_source_in_mean_C": 20.5, "T_source_in_daily_amp_K": 0.0,
                              "weather_T_source_K": 0.0, "limits_T_source_in_C": (20.0, 21.0)})
    low = Plant(warm).steady
    assert low.ls_limit == "min" and low.res.N_LS == pytest.approx(700.0, abs=0.5)
    assert low.T_source_out_C < CFG.control.T_source_out_sp_C - 0.05


def test_kern_seaton_fouling_law():
    c = dataclasses.replace(CFG.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0)
    f = Fouling(c)
    t = 7.3 * DAY
    for _ in range(73):
        f.advance(0.1 * DAY)
    tau = c.tau_days * DAY
    assert f.R == pytest.approx(c.R_th_f_inf_K_per_kW * (1 - math.exp(-t / tau)), rel=1e-12)
    assert f.CF_dp == pytest.approx(1 + (c.CF_dp_f_inf - 1) * (1 - math.exp(-t / (c.tau_dp_days * DAY))),
                                    rel=1e-12)
    R, CF = f.R, f.CF_dp
    f.clean(0.15, 0.3)
    assert f.R == pytest.approx(0.85 * R) and f.CF_dp - 1 == pytest.approx(0.7 * (CF - 1))


def test_cip_stops_the_plant_and_removes_fouling():
    cfg = cfg_with(cip={"first_after_days": 0.25, "jitter_days": 0.0, "duration_days": 0.25,
                        "interval_days": 5.0})
    p = Plant(cfg)
    p.advance_to(p.t0 + 0.25 * DAY - 1)
    assert p.running and p.cip_window is None
    R_before = p.fouling.R
    p.advance_to(p.t0 + 0.45 * DAY)
    assert not p.running and p.flags == {"running": 0, "cip": 1}
    m = p.measured
    assert m["N_LS"] == m["N_HS"] == m["W_LS"] == m["W_HS"] == m["V_source"] == 0.0
    assert p.fouling.R == pytest.approx(R_before, rel=1e-12)       # no growth while stopped
    assert math.isnan(p.truth()["COP"])
    start, end = p.cip_window
    assert start == pytest.approx(p.t0 + 0.25 * DAY) and end - start == pytest.approx(0.25 * DAY)
    p.advance_to(end + p.dt)
    assert p.running and p.cip_count == 1 and p.flags["cip"] == 0
    # removal share applied at restart; growth resumes (one tick at most here)
    assert p.fouling.R == pytest.approx(R_before * (1 - cfg.cip.removal_share), rel=5e-5)
    assert p.cip_schedule.next_start == pytest.approx(p.t0 + 5.25 * DAY)


def test_cop_optimum_is_at_least_as_good_as_the_current_setpoint(sim_plant):
    opt = sim_plant.cop_optimum()
    r = sim_plant.steady.res
    assert opt["COP_opt"] >= r.COP - 1e-9
    assert r.p_e / BAR - AMB < opt["p_m_opt_bar_g"] < r.p_c / BAR - AMB


def _decode(name, regs):
    t = TAGS[name]
    if t.byte_order in ("BADC", "DCBA"):
        regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
    return ModbusClientMixin.convert_from_registers(
        regs, getattr(ModbusClientMixin.DATATYPE, t.type.upper()),
        word_order="little" if t.byte_order in ("CDAB", "DCBA") else "big")


@pytest.mark.parametrize("name,value,words", [
    ("T_e", -5.0, [65486]),                     # int16 x0.1: -50
    ("T_sink_in", 40.004, [4000]),              # int16 x0.01, rounded
    ("V_source", 192.0, [19200]),
    ("p_source_in", 2.5, [0x4020, 0x0000]),     # float32 ABCD
    ("p_suc_LS", 2.5, [0x0000, 0x4020]),        # float32 CDAB: word swap
    ("T_e", float("nan"), [0x8000]),            # sentinel -32768
    ("V_sink", 1e9, [65534]),                   # saturates below the 65535 sentinel
])
def test_register_encoding_golden(name, value, words):
    assert encode(TAGS[name], value) == words


def test_quantize_matches_register_round_trip():
    rng = np.random.default_rng(0)
    for name, t in TAGS.items():
        if name in ("plc_clock", "life_counter"):
            continue
        lo, hi = t.range
        xs = rng.uniform(lo, hi, 20)
        q = quantize(t, xs)
        back = np.array([_decode(name, encode(t, x)) * t.scale + t.offset for x in xs])
        assert np.allclose(q, back, rtol=1e-12, atol=1e-12), name


def test_config_errors_name_file_and_key(tmp_path):
    with pytest.raises(SimConfigError, match=r"simulator.yaml: cip: unknown key 'every'"):
        config_from_dict({"cip": {"every": 3}}, tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"removal_share"):
        config_from_dict({"cip": {"removal_share": 1.5}}, tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"faults\[0\]: key 'tag' is required"):
        config_from_dict({"faults": [{"kind": "stuck"}]}, tmp_path / "simulator.yaml")
    bad = tmp_path / "tags.yaml"
    bad.write_text("tags:\n  T_e: {register: input, address: 0, type: int16, colour: red}\n")
    with pytest.raises(SimConfigError, match=r"tags.yaml: line 2: tag 'T_e': unknown key 'colour'"):
        read_tags(bad)


def test_fault_specs_validate():
    f = Faults(TAGS)
    with pytest.raises(SimConfigError, match="no sentinel"):
        f.enable("nan", tag="N_LS")
    with pytest.raises(SimConfigError, match="unknown tag"):
        f.enable("stuck", tag="nope")
    with pytest.raises(SimConfigError, match="system"):
        f.enable("stuck", tag="life_counter")
    spec = parse_cli_fault("out_of_range:T_c:value=150")
    assert spec.kind == "out_of_range" and spec.tag == "T_c" and spec.value == 150.0
    assert parse_cli_fault("frozen:at_h=2,duration_h=0.5").duration_h == 0.5


def test_simulator_config_shapes_are_checked(tmp_path):
    """Found by the input campaign: a truth that is not a mapping was a ValueError traceback."""
    with pytest.raises(SimConfigError, match=r"simulator.yaml: key 'truth' must be a mapping"):
        config_from_dict({"truth": "CF_eva"}, tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"lags_s: key 'speed' must be a finite number, got null"):
        config_from_dict({"lags_s": {"speed": None}}, tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"time: key 'tick_s' must be a finite number, got 1000000"):
        config_from_dict({"time": {"tick_s": 10**400}}, tmp_path / "simulator.yaml")
