"""Compressor truth families of another shape (simulator/compressors.py, simulator.yaml's
compressor_families): plausibility, the Compressor contract model/cycle.py relies on, selection
from the config, Python and the CLI, and that the plant runs with every family."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.cli import main
from model.cycle import solve
from model.units import BAR, T0
from simulator.compressors import (ShapedCompressor, curve_envelope, polynomial_misfit,
                                   shaped_from)
from simulator.config import PERTURBED, SimConfigError, config_from_dict, load_simulator_config
from simulator.plant import Plant, load_params, true_compressors
from simulator.profiles import Boundary

CFG = load_simulator_config()
NOMINAL = load_params(CFG)
FAMILIES = ("ratio_only", "speed_peak", "low_peak")
# physically plausible over pi 1.5-4 and 700-1800 rpm (the brief's ranges)
ETA_IS_RANGE = (0.55, 0.85)
ETA_VOL_RANGE = (0.70, 0.95)
MIN_SHAPE_DIFF = 0.05      # largest |eta_is(family) - eta_is(plant.yaml)| over the region, at least
MIN_POLY_MISFIT = 0.005    # the best 6-term polynomial misses the family's eta_is by at least this
FLOW_RTOL = 1e-12          # speed_for_flow round trip


def comps(family: str) -> dict:
    return true_compressors(NOMINAL, CFG.with_compressor_family(family))


def test_shipped_families_are_the_three_of_the_issue():
    assert set(FAMILIES) <= set(CFG.compressor_families)
    assert CFG.truth.compressor_family == PERTURBED          # today's truth stays the default


@pytest.mark.parametrize("family", FAMILIES)
def test_family_is_plausible_and_of_another_shape(family):
    for stage, comp in comps(family).items():
        assert isinstance(comp, ShapedCompressor) and comp.family == family
        base = getattr(NOMINAL, f"comp_{stage}")
        assert (comp.swept_volume, comp.N_nom, comp.N_min, comp.N_max) == (
            base.swept_volume, base.N_nom, base.N_min, base.N_max)
        env = curve_envelope(comp)
        assert ETA_IS_RANGE[0] <= env["eta_is_min"] and env["eta_is_max"] <= ETA_IS_RANGE[1], env
        assert ETA_VOL_RANGE[0] <= env["eta_vol_min"] and env["eta_vol_max"] <= ETA_VOL_RANGE[1], env
        assert env["flow_slope_min"] > 0.5, env          # eta_vol*n strictly rising with speed
        assert polynomial_misfit(comp)["eta_is_max_misfit"] > MIN_POLY_MISFIT
        pis, ns = np.linspace(1.5, 4.0, 11), np.linspace(700, 1800, 11) / base.N_nom
        diff = max(abs(comp.eta_is_at(p, n) - base.eta_is_at(p, n)) for p in pis for n in ns)
        assert diff > MIN_SHAPE_DIFF
        # a family is not a polynomial: its coefficient fields are NaN, never silently used
        assert all(math.isnan(c) for c in comp.eta_is + comp.eta_vol)


def test_family_shapes_are_the_documented_ones():
    ro, sp, lp = (comps(f) for f in FAMILIES)
    # ratio_only: no speed effect at all
    for c in ro.values():
        assert c.eta_is_at(2.3, 0.5) == c.eta_is_at(2.3, 1.2)
        assert c.eta_vol_at(2.3, 0.5) == c.eta_vol_at(2.3, 1.2)
    # speed_peak: eta_is peaks near 1650 rpm
    assert curve_envelope(sp["HS"])["eta_is_argmax_rpm"] == pytest.approx(1650, abs=30)
    # low_peak: its peak about 10 % below plant.yaml's (0.79)
    for c in lp.values():
        assert curve_envelope(c)["eta_is_max"] == pytest.approx(0.9 * 0.79, abs=0.01)


def test_eta_formulas_by_hand():
    c = shaped_from(NOMINAL.comp_HS, "x", {"eta_is_max": 0.8, "eta_is_floor": 0.6, "pi_opt": 2.0,
                                            "w_ln_pi": 0.5, "n_opt": 1.1, "w_n": 0.4, "vol_a": 0.98,
                                            "vol_b": 0.05, "vol_k": 1.25, "vol_c": 0.1})
    pi, n = 3.0, 0.8
    q = (math.log(1.5) / 0.5) ** 2 + (0.3 / 0.4) ** 2
    assert c.eta_is_at(pi, n) == pytest.approx(0.6 + 0.2 * math.exp(-q / 2), rel=1e-14)
    assert c.eta_vol_at(pi, n) == pytest.approx(0.98 - 0.05 * (3.0 ** 0.8 - 1) - 0.08, rel=1e-14)


@settings(max_examples=200, deadline=None)
@given(family=st.sampled_from(FAMILIES), stage=st.sampled_from(("LS", "HS")),
       pi=st.floats(1.2, 5.0), n=st.floats(0.2, 1.6), rho=st.floats(3.0, 30.0))
def test_speed_for_flow_inverts_the_flow_with_the_base_contract(family, stage, pi, n, rho):
    c = comps(family)[stage]
    n_lo, n_hi = c.N_min / c.N_nom, c.N_max / c.N_nom
    A = c.eta_vol_at(pi, 0.0)
    if n < n_lo:      # below the range: the linear continuation of phi from its lower bound
        phi = c.eta_vol_at(pi, n_lo) * n_lo + (A - 2 * c.vol_c * n_lo) * (n - n_lo)
    elif n > n_hi:
        phi = c.eta_vol_at(pi, n_hi) * n_hi + (A - 2 * c.vol_c * n_hi) * (n - n_hi)
    else:
        phi = c.eta_vol_at(pi, n) * n
    m = phi * rho * c.swept_volume
    n_got, ev = c.speed_for_flow(m, rho, pi)
    assert n_got == pytest.approx(n, rel=FLOW_RTOL, abs=1e-12)
    assert ev * n_got * rho * c.swept_volume == pytest.approx(m, rel=FLOW_RTOL)
    # more flow needs more speed
    assert c.speed_for_flow(m * 1.01, rho, pi)[0] > n_got


def test_speed_for_flow_errors_like_the_base_class():
    falling = shaped_from(NOMINAL.comp_LS, "x", {"vol_a": 0.9, "vol_c": 0.5})   # phi' < 0 at 1800 rpm
    with pytest.raises(ValueError, match="does not rise with speed at pressure ratio 2.000, n=1.200"):
        falling.speed_for_flow(1.0, 10.0, 2.0)
    ok = comps("speed_peak")["LS"]
    with pytest.raises(ValueError, match="too small for the compressor curve"):
        ok.speed_for_flow(1e-6, 10.0, 2.0)


def test_selection_from_python_yaml_and_errors(tmp_path):
    p = Plant(CFG.with_compressor_family("low_peak"))
    assert isinstance(p.true.comp_LS, ShapedCompressor) and p.truth()["compressor_family"] == "low_peak"
    doc = {"truth": {"compressors": {"family": "speed_peak"}},
           "compressor_families": {"speed_peak": CFG.compressor_families["speed_peak"]}}
    cfg = config_from_dict(doc, tmp_path / "simulator.yaml")
    assert cfg.truth.compressor_family == "speed_peak"
    with pytest.raises(SimConfigError, match=r"simulator.yaml: truth.compressors: key 'family': "
                                             r"unknown compressor family 'nope' \(known: perturbed, nominal\)"):
        config_from_dict({"truth": {"compressors": {"family": "nope"}}}, tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"truth.compressors: key 'family': unknown compressor "
                                             r"family 'fast' \(known: perturbed, nominal, low_peak, ratio_only, speed_peak\)"):
        CFG.with_compressor_family("fast")
    with pytest.raises(SimConfigError, match=r"compressor_families.x.HS: unknown key 'eta_max'"):
        config_from_dict({"compressor_families": {"x": {"LS": {}, "HS": {"eta_max": 0.8}}}},
                         tmp_path / "simulator.yaml")
    with pytest.raises(SimConfigError, match=r"compressor_families.x: expected the keys LS and HS"):
        config_from_dict({"compressor_families": {"x": {"LS": {}}}}, tmp_path / "simulator.yaml")


def test_unphysical_family_is_refused_naming_it():
    bad = CFG.replace(compressor_families={**CFG.compressor_families,
                                           "broken": {"LS": {"vol_a": 0.9, "vol_c": 0.5}, "HS": {}}})
    with pytest.raises(SimConfigError, match=r"compressor_families.broken.LS: the curves are not "
                                             r"physical .* a flow rising with speed"):
        Plant(bad.with_compressor_family("broken"))


@pytest.mark.parametrize("family", FAMILIES)
def test_plant_runs_with_every_family_at_10_and_16_bar_clean_and_fouled(family):
    """SPEC §2 nominal point; fouled = 6e-3 K/kW (the fouling asymptote of simulator.yaml)."""
    plant = Plant(CFG.with_compressor_family(family))
    b = Boundary(25.0, 40.0, 192.0, 62.0, 2.5, 0.0)
    for R_K_per_kW in (0.0, 6.0e-3):
        par = plant.effective_params(192.0, 62.0).replace(R_th_f=R_K_per_kW * 1e-3)
        for sp in (10.0, 16.0):
            r, T_out, limit = plant.solve_controlled(plant.inputs(b, p_m_sp_bar_g=sp), par)
            assert 3.5 < r.COP < 5.6, (R_K_per_kW, sp, r.COP)
            assert abs(r.energy_residual) < 1e-6
            assert 700 - 1 <= r.N_LS <= 1800 + 1 and 700 - 1e-6 <= r.N_HS <= 1800 + 1e-6
            p_m = r.p_m / BAR - plant.amb
            assert p_m == pytest.approx(sp, abs=1e-6) or (r.hs_saturated and p_m > sp)
            assert T_out - T0 >= 18.0 - 1e-9 or limit == "min"


def test_cli_simulate_compressors_flag(tmp_path, capsys):
    rc = main(["simulate", "--export", str(tmp_path / "h.csv"), "--days", "0.01",
               "--truth", str(tmp_path / "t.csv"), "--compressors", "ratio_only"])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert info["compressors"] == "ratio_only"
    import pandas as pd
    t = pd.read_csv(tmp_path / "t.csv")
    assert (t["compressor_family"] == "ratio_only").all()
    rc = main(["simulate", "--export", str(tmp_path / "h.csv"), "--days", "0.01", "--compressors", "nope"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "truth.compressors: key 'family': unknown compressor family 'nope'" in err
    assert "hp-edge simulate:" in err and "Traceback" not in err
