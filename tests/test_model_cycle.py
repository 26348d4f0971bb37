"""Physics of the cycle model: balances, reference states, switches, monotonicity."""
from __future__ import annotations

import math

import CoolProp.CoolProp as CP
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from model.batch import inputs_from_row
from model.cycle import (ConvergenceError, InfeasibleOperation, ModelError, counterflow_eps,
                         evaporator, solve)
from model.units import BAR, C_to_K, barg_to_Pa
from model.validation import run_grid

ENERGY_TOL = 1e-6          # issue #2: Q_sink = Q_source + W_total within 1e-6 relative
IC_TOL = 1e-9              # intercooler balances, relative
PROP_TOL = 1e-7            # our property path vs PropsSI, relative
AMB = 1.01325


def nominal(plant, nominal_row, **kw):
    return inputs_from_row({**nominal_row, **kw}, AMB)


def test_nominal_point_matches_published_plant(plant, nominal_row):
    r = solve(nominal(plant, nominal_row), plant)
    assert r.branch == "sp"
    assert 1.9e6 < r.Q_sink < 2.1e6                  # "2.0 MW of heat"
    assert 1.50e6 < r.Q_source < 1.60e6              # "about 1.55 MW from the source"
    assert 33e5 <= r.p_c <= 38.5e5                   # published p_c range
    assert 4.3 < r.COP < 4.8                         # "COP ~ 4.5"
    assert abs(r.T_sink_out - C_to_K(68.0)) < 1.5    # supply ~68 degC
    assert 4.0 < r.pinch < 6.0                       # design assumption 5 K is reproduced
    assert 7.2e5 < r.p_e < 7.4e5                     # "p_e ~ 7.3 bar"
    assert 700 <= r.N_LS <= 1800 and 700 <= r.N_HS <= 1800


def intercooler_checks(r):
    s = r.states
    h2, h_SC, h_g, h_f = s["LS_dis"].h, s["SC_out"].h, s["HS_suc"].h, s["IC_liq"].h
    # energy: LS discharge gas + HS-valve two-phase in = saturated vapour + saturated liquid out
    e_in = r.m_LS * h2 + r.m_HS * h_SC
    e_out = r.m_HS * h_g + r.m_LS * h_f
    assert abs(e_in - e_out) <= IC_TOL * e_out
    # mass: the HS-valve flash vapour, the LS gas and the liquid evaporated by desuperheating the
    # LS gas leave as HS suction vapour; the rest of the liquid feeds the LS valve
    x = (h_SC - h_f) / (h_g - h_f)
    evaporated = r.m_LS * (h2 - h_g) / (h_g - h_f)
    assert abs((x * r.m_HS + r.m_LS + evaporated) - r.m_HS) <= IC_TOL * r.m_HS
    assert abs(((1 - x) * r.m_HS - evaporated) - r.m_LS) <= IC_TOL * r.m_HS


def test_balances_on_every_solved_grid_point(plant):
    seen = []

    def check(inp, p, r):
        assert abs(r.Q_source + r.W_total - r.Q_sink) <= ENERGY_TOL * r.Q_sink
        C_w = p.cp_w * p.rho_w * inp.V_sink
        assert abs(C_w * (r.T_sink_out - inp.T_sink_in) - r.Q_sink) <= ENERGY_TOL * r.Q_sink
        C_s = p.cp_w * p.rho_w * inp.V_source
        assert abs(C_s * (inp.T_source_in - inp.T_source_out) - r.Q_source) <= ENERGY_TOL * r.Q_source
        intercooler_checks(r)
        vals = [r.p_e, r.p_m, r.p_c, r.N_LS, r.N_HS, r.W_LS, r.W_HS, r.COP, r.pinch, r.subcooling]
        assert all(math.isfinite(v) for v in vals)
        assert r.p_e < r.p_m < r.p_c
        seen.append(r.branch)

    out = run_grid(plant, levels=3, check=check)
    definite = 1 - out["convergence_failures"] / out["points"]
    assert definite >= 0.99, out
    assert out["ok"] + out["solved_flagged"] == len(seen)
    assert {"sp", "hs_max"} <= set(seen)      # both sides of the HS-speed switch are exercised


def test_every_grid_failure_is_typed_with_a_reason(plant):
    from model.validation import grid
    n = 0
    for inp, R in list(grid(3))[::7]:
        try:
            solve(inp, plant.replace(R_th_f=R))
        except InfeasibleOperation as exc:
            assert exc.reason and str(exc)
            if exc.result is not None:
                assert math.isfinite(exc.result.COP)
            n += 1
        except ConvergenceError as exc:
            assert exc.reason and str(exc)
            n += 1
    assert n > 0


def test_states_agree_with_coolprop_reference(plant, nominal_row):
    r = solve(nominal(plant, nominal_row), plant)
    s = r.states
    ref = lambda out, a, av, b, bv: CP.PropsSI(out, a, av, b, bv, "Ammonia")  # noqa: E731
    # saturation points
    assert s["con_out"].h == pytest.approx(ref("H", "P", r.p_c, "Q", 0), rel=PROP_TOL)
    assert s["HS_suc"].h == pytest.approx(ref("H", "P", r.p_m, "Q", 1), rel=PROP_TOL)
    assert s["IC_liq"].h == pytest.approx(ref("H", "P", r.p_m, "Q", 0), rel=PROP_TOL)
    assert r.T_c == pytest.approx(ref("T", "P", r.p_c, "Q", 0), rel=PROP_TOL)
    assert r.p_e == pytest.approx(ref("P", "T", r.T_e, "Q", 1), rel=PROP_TOL)
    # superheated LS suction (1 K above saturation)
    assert s["LS_suc"].T - r.T_e == pytest.approx(plant.superheat, abs=1e-9)
    assert s["LS_suc"].h == pytest.approx(ref("H", "P", r.p_e, "T", s["LS_suc"].T), rel=PROP_TOL)
    # isentropic discharge states have the suction entropy
    s_suc = ref("S", "P", r.p_e, "T", s["LS_suc"].T)
    assert ref("S", "P", r.p_m, "H", s["LS_dis_is"].h) == pytest.approx(s_suc, rel=PROP_TOL)
    s_hs = ref("S", "P", r.p_m, "Q", 1)
    assert ref("S", "P", r.p_c, "H", s["HS_dis_is"].h) == pytest.approx(s_hs, rel=PROP_TOL)
    # compressor definition: h_dis = h_suc + (h_is - h_suc)/eta_is, W = m (h_dis - h_suc)
    assert s["LS_dis"].h - s["LS_suc"].h == pytest.approx(
        (s["LS_dis_is"].h - s["LS_suc"].h) / r.eta_is_LS, rel=1e-12)
    assert r.W_LS == pytest.approx(r.m_LS * (s["LS_dis"].h - s["LS_suc"].h), rel=1e-12)
    # reported discharge temperatures come from a (p, h) flash
    assert s["HS_dis"].T == pytest.approx(ref("T", "P", r.p_c, "H", s["HS_dis"].h), rel=PROP_TOL)


def test_compressor_mass_flow_definition(plant, nominal_row):
    r = solve(nominal(plant, nominal_row), plant)
    rho1 = CP.PropsSI("D", "P", r.p_e, "T", r.states["LS_suc"].T, "Ammonia")
    ls = plant.comp_LS
    assert r.m_LS == pytest.approx(r.eta_vol_LS * rho1 * ls.swept_volume * r.N_LS / ls.N_nom, rel=1e-9)
    rho3 = CP.PropsSI("D", "P", r.p_m, "Q", 1, "Ammonia")
    hs = plant.comp_HS
    assert r.m_HS == pytest.approx(r.eta_vol_HS * rho3 * hs.swept_volume * r.N_HS / hs.N_nom, rel=1e-7)


def test_closed_form_evaporator_temperature(plant, nominal_row):
    for R in (0.0, 2e-6, 6e-6):
        p = plant.replace(R_th_f=R)
        inp = nominal(plant, nominal_row)
        Q, T_e = evaporator(inp, p)
        lmtd = ((inp.T_source_in - T_e) - (inp.T_source_out - T_e)) / math.log(
            (inp.T_source_in - T_e) / (inp.T_source_out - T_e))
        assert p.UA_eva * lmtd == pytest.approx(Q, rel=1e-12)
        # hand calculation at the nominal point without fouling: UA 275.88 kW/K, C 222.5 kW/K
        if R == 0.0:
            C = 4180 * 998 * 192 / 3600
            ntu = 3000 * 91.96 / C
            T_e_hand = (291.15 * math.exp(ntu) - 298.15) / (math.exp(ntu) - 1)
            assert T_e == pytest.approx(T_e_hand, abs=1e-9)
            assert T_e - 273.15 == pytest.approx(15.149, abs=0.01)


def test_hs_saturates_at_10_bar_set_point(plant, nominal_row):
    r = solve(nominal(plant, nominal_row, p_m_sp=10.0), plant)
    assert r.branch == "hs_max" and r.hs_saturated
    assert r.N_HS == pytest.approx(plant.comp_HS.N_max, abs=1e-6)
    assert r.p_m / BAR - AMB >= 12.0                     # p_m floats at >= 12 bar(g)
    assert r.p_m > barg_to_Pa(10.0)
    r16 = solve(nominal(plant, nominal_row, p_m_sp=16.0), plant)
    assert r16.branch == "sp" and r16.p_m == pytest.approx(barg_to_Pa(16.0), rel=1e-12)


def test_switch_is_continuous_and_warm_start_crosses_it(plant, nominal_row):
    prev = None
    pms = []
    for psp in np.arange(10.0, 16.01, 0.25):
        prev = solve(nominal(plant, nominal_row, p_m_sp=float(psp)), plant, guess=prev)
        pms.append((psp, prev.p_m, prev.branch))
    # p_m is max(floating value, set point): non-decreasing along the sweep
    assert all(b[1] >= a[1] - 1e-6 for a, b in zip(pms, pms[1:]))
    assert pms[0][2] == "hs_max" and pms[-1][2] == "sp"
    # warm and cold solutions agree
    for psp in (11.0, 13.5, 14.0, 18.0):
        inp = nominal(plant, nominal_row, p_m_sp=psp)
        cold = solve(inp, plant)
        warm = solve(inp, plant, guess=solve(nominal(plant, nominal_row, p_m_sp=psp - 0.7), plant))
        assert warm.COP == pytest.approx(cold.COP, rel=1e-8)
        assert warm.p_m == pytest.approx(cold.p_m, rel=1e-8)


def test_optimum_above_geometric_mean_and_beats_10_bar_practice(plant, nominal_row):
    r10 = solve(nominal(plant, nominal_row, p_m_sp=10.0), plant)
    best, prev = None, None
    for psp in np.arange(12.0, 22.0, 0.1):
        prev = solve(nominal(plant, nominal_row, p_m_sp=float(psp)), plant, guess=prev)
        if best is None or prev.COP > best.COP:
            best = prev
    gm = math.sqrt(best.p_e * best.p_c)
    assert best.p_m > gm
    gain = best.COP / r10.COP - 1
    assert 0.01 <= gain <= 0.03


def test_fouling_lowers_p_e_and_cop_monotonically(plant, nominal_row):
    inp = nominal(plant, nominal_row)
    p_e, cop = [], []
    for R in np.linspace(0, 8e-6, 9):
        try:
            r = solve(inp, plant.replace(R_th_f=float(R)))
        except InfeasibleOperation as exc:      # heavy fouling pushes the LS past 1800 rpm
            assert exc.reason == "ls_speed_high"
            r = exc.result
        p_e.append(r.p_e)
        cop.append(r.COP)
    assert all(np.diff(p_e) < 0) and all(np.diff(cop) < 0)


def test_ls_speed_limit_raises_typed_error_with_result(plant, nominal_row):
    with pytest.raises(InfeasibleOperation) as ei:
        # heavy fouling at nominal duty: p_e drops, the LS must move more volume than 1800 rpm allows
        solve(nominal(plant, nominal_row), plant.replace(R_th_f=4e-6))
    assert ei.value.reason == "ls_speed_high"
    assert ei.value.result is not None and ei.value.result.N_LS > 1800
    assert "LS compressor speed" in str(ei.value) and "above its maximum 1800 rpm" in str(ei.value)


def test_bad_inputs_raise_typed_errors(plant, nominal_row):
    with pytest.raises(InfeasibleOperation) as ei:
        solve(nominal(plant, nominal_row, T_source_out=26.0), plant)
    assert ei.value.reason == "bad_source"
    with pytest.raises(ModelError):
        solve(nominal(plant, nominal_row, V_sink=0.0), plant)


def test_counterflow_effectiveness_limits():
    eps, cmin = counterflow_eps(1000.0, 1000.0, 1000.0)
    assert eps == pytest.approx(0.5) and cmin == 1000.0
    eps, _ = counterflow_eps(1000.0, 1e12, 1000.0)
    assert eps == pytest.approx(1 - math.exp(-1.0), rel=1e-6)


def test_tabular_backend_within_1e5_of_heos(plant, nominal_row):
    tab = plant.replace(backend="BICUBIC&HEOS")
    for kw in ({}, {"p_m_sp": 10.0}, {"T_sink_in": 45.0, "V_sink": 55.0}):
        a = solve(nominal(plant, nominal_row, **kw), plant)
        b = solve(nominal(plant, nominal_row, **kw), tab)
        for k in ("p_m", "p_c", "Q_sink", "W_total", "COP", "N_HS"):
            assert getattr(b, k) == pytest.approx(getattr(a, k), rel=1e-5), k


@settings(max_examples=60, deadline=None)
@given(T_in=st.floats(18, 28), drop=st.floats(4, 8), T_sink=st.floats(36, 46),
       fs=st.floats(0.8, 1.05), fk=st.floats(0.8, 1.1), psp=st.floats(9, 21), R=st.floats(0, 4e-3))
def test_energy_balance_property(plant, T_in, drop, T_sink, fs, fk, psp, R):
    inp = inputs_from_row({"T_source_in": T_in, "T_source_out": T_in - drop, "T_sink_in": T_sink,
                           "V_source": 192 * fs, "V_sink": 62 * fk, "p_m_sp": psp}, AMB)
    try:
        r = solve(inp, plant.replace(R_th_f=R * 1e-3))
    except InfeasibleOperation as exc:
        if exc.result is None:
            return
        r = exc.result
    assert abs(r.energy_residual) <= ENERGY_TOL
    intercooler_checks(r)


EOS_TOL = 1e-6             # issue #8 item 3: every reported state agrees with the EOS, relative


@pytest.mark.parametrize("kw", [{}, {"p_m_sp": 10.0}, {"V_sink": 50.0, "T_sink_in": 44.0},
                                {"V_source": 170.0, "T_source_in": 23.0, "p_m_sp": 20.0}])
def test_every_reported_state_agrees_with_the_equation_of_state(plant, nominal_row, kw):
    """Single-phase states: h(p, T) from CoolProp equals the reported h; saturated and two-phase
    states sit at the saturation temperature of their pressure. The subcooler outlet in particular:
    its liquid heat capacity is the secant over the SC's actual range, not a 5-K secant at
    saturation (which put it 0.3 K and 2.9 kJ/kg off the EOS at the nominal point)."""
    r = solve(nominal(plant, nominal_row, **kw), plant)
    single = ("LS_suc", "LS_dis_is", "LS_dis", "HS_dis_is", "HS_dis", "SC_out")
    if not r.dsh_condensing:
        single += ("DSH_out",)
    for name in single:
        st = r.states[name]
        h_ref = CP.PropsSI("H", "P", st.p, "T", st.T, "Ammonia")
        assert abs(st.h - h_ref) <= EOS_TOL * abs(h_ref), (name, st, h_ref)
    for name in ("eva_out", "HS_suc", "con_out", "IC_liq", "HS_valve_out", "LS_valve_out"):
        st = r.states[name]
        assert st.T == pytest.approx(CP.PropsSI("T", "P", st.p, "Q", 0, "Ammonia"), rel=EOS_TOL)
    sc = r.states["SC_out"]
    assert sc.T < r.T_c - 1.0                                    # really subcooled
    assert r.subcooling == pytest.approx(r.T_c - sc.T, abs=1e-12)
    # the SC's duty three ways: refrigerant enthalpies, the water side, and eps-NTU with the secant
    Q_ref = r.m_HS * (r.states["con_out"].h - sc.h)
    C_w = plant.cp_w * plant.rho_w * m3(kw.get("V_sink", nominal_row["V_sink"]))
    assert r.Q_SC == pytest.approx(Q_ref, rel=1e-9)
    assert C_w * (r.T_w_SC_out - C_to_K(kw.get("T_sink_in", nominal_row["T_sink_in"]))) == \
        pytest.approx(r.Q_SC, rel=1e-9)
    cp_sec = (r.states["con_out"].h - sc.h) / (r.T_c - sc.T)
    eps, C_min = counterflow_eps(r.m_HS * cp_sec, C_w, plant.CF_SC * plant.U_SC * plant.A_SC)
    assert eps * C_min * (r.T_c - C_to_K(kw.get("T_sink_in", nominal_row["T_sink_in"]))) == \
        pytest.approx(r.Q_SC, rel=1e-8)


def m3(v_m3h):
    return v_m3h / 3600.0


def test_ls_speed_limit_as_a_branch_floats_the_source_outlet(plant, nominal_row):
    """ls_mode='float' (prediction): at more source duty than the LS can carry at 1800 rpm, the LS
    sits at 1800 rpm and T_source,out floats above its set point; flag mode still raises."""
    inp = nominal(plant, nominal_row, V_source=230.0)
    with pytest.raises(InfeasibleOperation) as ei:
        solve(inp, plant)
    assert ei.value.reason == "ls_speed_high"
    r = solve(inp, plant, ls_mode="float")
    assert r.ls_limit == "max"
    assert abs(r.N_LS - plant.comp_LS.N_max) <= 1e-3
    assert r.T_source_out > inp.T_source_out + 0.1
    C_s = plant.cp_w * plant.rho_w * inp.V_source
    assert r.Q_source == pytest.approx(C_s * (inp.T_source_in - r.T_source_out), rel=1e-12)
    assert abs(r.energy_residual) <= ENERGY_TOL
    intercooler_checks(r)
    # within the speed range the two modes are the same point
    r0 = solve(nominal(plant, nominal_row), plant)
    r1 = solve(nominal(plant, nominal_row), plant, ls_mode="float")
    assert r1.ls_limit == "" and r1.COP == pytest.approx(r0.COP, rel=1e-12)
    # a higher p_m costs LS capacity once the LS is at its limit: less heat from the source
    q = [solve(nominal(plant, nominal_row, V_source=230.0, p_m_sp=sp), plant, ls_mode="float").Q_sink
         for sp in (14.0, 17.0, 20.0)]
    assert q[0] > q[1] > q[2]
    with pytest.raises(ValueError, match="ls_mode must be one of flag, float"):
        solve(inp, plant, ls_mode="clamp")


def test_ls_branch_is_continuous_across_saturation(plant, nominal_row):
    """Q_source follows the duty up to where the LS saturates and stays (almost) flat beyond:
    no jump where the branch switches."""
    flows = np.linspace(196.0, 232.0, 19)
    q, lim = [], []
    g = None
    for V in flows:
        g = solve(nominal(plant, nominal_row, V_source=float(V)), plant, guess=g, ls_mode="float")
        q.append(g.Q_source)
        lim.append(g.ls_limit)
    assert lim[0] == "" and lim[-1] == "max"
    steps = np.diff(q)
    assert np.all(steps > -1e3)                       # never drops by more than 1 kW per step
    i = lim.index("max")
    assert abs(steps[i - 1]) < 2.0 * np.max(np.abs(steps[: i - 1]))   # no jump at the switch
