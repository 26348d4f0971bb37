"""model.vcycle (the flowsheet solved for many rows at once) against the scalar solver row by row.

The reference is ``model.cycle.solve`` without a guess, one row at a time (HEOS through model.fluid):
what a row gives on its own. (``solve_rows`` warm-starts each row from the previous one, and the
scalar solver's outcome depends on its start where a trial point fails: see model/vcycle.py.)

Status rule: every row has the scalar status, except a row solved by both whose status differs only
because a limit-deciding quantity lies within NEAR_LIMIT of its threshold (N_LS against the LS speed
bounds widened by LS_SPEED_LOOSE, the pinch against 0 K); such rows must stay below 0.5 % of the grid.
"""
from __future__ import annotations

import itertools
import math
import re

import CoolProp.CoolProp as CP
import numpy as np
import pandas as pd
import pytest

from model.analysis.compressors import OBS_COLUMNS, CompressorLearner
from model.batch import OUTPUT_KEYS, frame_of, inputs_from_row, simulate_batch
from model.components import counterflow_eps
from model.cycle import LS_SPEED_LOOSE, InfeasibleOperation, ModelError, solve
from model.cycletables import THETA_MAX, VAP_T_MAX, VAP_T_MIN, get_cycle_tables
from model.fluid import Fluid
from model.params import Compressor
from model.units import BAR, C_to_K
from model.vcycle import _Looped, solve_many, vectorized

AGREE_REL = 1e-6          # Q_sink, W_total, COP, p_c, p_m, N_LS, N_HS: relative
T_SO_ABS = 1e-6           # K, the (floating) source outlet temperature
ENERGY_TOL = 1e-6         # |Q_sink - Q_source - W_shaft| / Q_sink in every solved row
EOS_TOL = 1e-6            # SC outlet enthalpy against the EOS at (p_c, T_SC), relative
COMP_REL = 1e-12          # vectorised compressor methods against the scalar ones
NEAR_LIMIT = 1e-6         # status exemption distance (relative to N_nom; K for the pinch)
AMB = 1.01325
DRAW_REL = 1e-9       # per-row draws against one call per draw (the same iterations)
SET_POINTS = np.arange(4.0, 24.01, 1.0)
NOMINAL = {"T_source_in": 25.0, "T_source_out": 18.0, "T_sink_in": 40.0, "V_source": 192.0,
           "V_sink": 62.0}
COMPARED = ("Q_sink_kW", "W_total_kW", "COP", "p_c_bar", "p_m_bar", "N_LS_rpm", "N_HS_rpm")


def grid(full: bool) -> pd.DataFrame:
    """Operating points x set points 4..24 bar(g): the nominal point, source 22-26 degC (outlet
    18 degC, and 16.5 degC where the LS saturates), sink 38-45 degC at 45-75 m3/h, 192 and 230 m3/h
    of source water (230: beyond the LS stage at 1800 rpm)."""
    ops = [NOMINAL]
    T_in = (22.0, 24.0, 26.0) if full else (22.0, 26.0)
    for a, b, c, d, e in itertools.product(T_in, (18.0, 16.5), (38.0, 45.0), (192.0, 230.0), (45.0, 75.0)):
        if full or (b == 18.0) != (d == 230.0):
            ops.append({"T_source_in": a, "T_source_out": b, "T_sink_in": c, "V_source": d, "V_sink": e})
    base = pd.DataFrame(ops)
    df = base.loc[base.index.repeat(len(SET_POINTS))].reset_index(drop=True)
    df["p_m_sp"] = np.tile(SET_POINTS, len(base))
    return df


def scalar_frame(df: pd.DataFrame, params, ls_mode: str) -> pd.DataFrame:
    rows = []
    for i in range(len(df)):
        try:
            res = solve(inputs_from_row(df.iloc[i], AMB), params, ls_mode=ls_mode)
            rows.append(("ok", "", res))
        except InfeasibleOperation as exc:
            rows.append((exc.reason, str(exc), exc.result))
        except ModelError as exc:
            rows.append((exc.reason, str(exc), None))
    return frame_of(rows, params)


def learned_params(plant, delta: bool = False):
    """The plant with LearnedCompressors: a CompressorLearner fed synthetic observations in two
    clusters per stage (local curves where they are), optionally with an uncertainty draw."""
    rng = np.random.default_rng(0)
    k = 3000
    obs = {c: np.full(k, np.nan) for c in OBS_COLUMNS}
    obs["t"] = np.arange(k) * 60.0
    for st, pi0, n0 in (("LS", 2.4, 1.05), ("HS", 1.9, 1.0)):
        pi = np.concatenate([rng.normal(pi0, 0.2, k // 2), rng.normal(pi0 + 0.5, 0.15, k - k // 2)])
        n = np.concatenate([rng.normal(n0, 0.1, k // 2), rng.normal(n0 + 0.1, 0.06, k - k // 2)])
        obs[f"pi_{st}"], obs[f"n_{st}"] = pi, n
        obs[f"eta_is_{st}"] = (0.77 - 0.03 * (pi - 2.4) ** 2 - 0.12 * (n - 1.0) ** 2 + 0.01 * np.sin(4 * pi)
                               + rng.normal(0, 0.002, k))
        obs[f"eta_vol_{st}"] = 0.93 - 0.03 * pi - 0.08 * (n - 0.9) ** 2 + rng.normal(0, 0.002, k)
        obs[f"drive_{st}"] = np.full(k, 1.03)
    learner = CompressorLearner(plant)
    learner.update(pd.DataFrame(obs))
    if not delta:
        return learner.apply(plant)
    d = learner.draws(1, np.random.default_rng(1))[0]
    return plant.replace(comp_LS=learner.compressor("LS", delta=d["LS"]),
                         comp_HS=learner.compressor("HS", delta=d["HS"]))


@pytest.fixture(scope="module")
def learned(plant):
    return learned_params(plant, delta=False)


@pytest.fixture(scope="module")
def learned_delta(plant):
    return learned_params(plant, delta=True)


def near_limit(params, a: pd.Series, b: pd.Series) -> bool:
    """A row solved by both whose statuses may differ: a limit-deciding value within NEAR_LIMIT."""
    ls = params.comp_LS
    tol = LS_SPEED_LOOSE * ls.N_nom
    for r in (a, b):
        if not math.isfinite(r["N_LS_rpm"]):
            return False
        d = min(abs(r["N_LS_rpm"] - (ls.N_max + tol)), abs(r["N_LS_rpm"] - (ls.N_min - tol)))
        if d <= NEAR_LIMIT * ls.N_nom or abs(r["pinch_K"]) <= NEAR_LIMIT:
            return True
    return False


def check_agreement(params, df: pd.DataFrame, ls_mode: str) -> dict:
    vr = solve_many(df, params, ls_mode=ls_mode)
    got = vr.frame()
    ref = scalar_frame(df, params, ls_mode)
    differ = np.flatnonzero(got["status"].to_numpy() != ref["status"].to_numpy())
    exempt = [i for i in differ if near_limit(params, got.iloc[i], ref.iloc[i])]
    assert len(exempt) == len(differ), got.iloc[[i for i in differ if i not in exempt]][["status", "reason"]]
    assert len(exempt) <= 0.005 * len(df)
    same = np.setdiff1d(np.arange(len(df)), differ)
    # the same reason texts; a number printed from a trial point may differ in its last digit
    mask = lambda texts: [re.sub(r"-?\d+\.?\d*", "#", t) for t in texts]   # noqa: E731
    assert mask(got["reason"].to_numpy()[same]) == mask(ref["reason"].to_numpy()[same])
    solved = got["Q_sink_kW"].notna().to_numpy() & ref["Q_sink_kW"].notna().to_numpy()
    assert solved.sum() > 0.3 * len(df)
    assert (got["Q_sink_kW"].notna() == ref["Q_sink_kW"].notna()).to_numpy()[same].all()
    for k in COMPARED:
        rel = np.abs(got[k].to_numpy() - ref[k].to_numpy()) / np.abs(ref[k].to_numpy())
        assert rel[solved].max() <= AGREE_REL, (k, rel[solved].max())
    for k in ("hs_saturated", "ls_saturated"):
        assert (got[k].to_numpy()[solved] == ref[k].to_numpy()[solved]).all(), k
    dT = np.abs(got["T_source_out_C"].to_numpy() - ref["T_source_out_C"].to_numpy())[solved]
    assert dT.max() <= T_SO_ABS
    assert np.abs(got["energy_residual"].to_numpy()[solved]).max() <= ENERGY_TOL
    if params.comp_LS.drive_factor == 1.0 and params.comp_HS.drive_factor == 1.0:
        q = got.loc[solved]
        bal = (q["Q_sink_kW"] - q["Q_source_kW"] - q["W_total_kW"]).abs() / q["Q_sink_kW"]
        assert bal.max() <= ENERGY_TOL
    return {"rows": len(df), "fallback": vr.fallback_rows, "solved": int(solved.sum()),
            "floated": int(got["ls_saturated"].eq(1.0).sum()), "hs_max": int(got["hs_saturated"].eq(1.0).sum())}


# ---------------------------------------------------------------------------------------------------
# 1. agreement with the scalar solver
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_agrees_with_the_scalar_solver_on_the_default_plant(plant, ls_mode):
    info = check_agreement(plant, grid(full=True), ls_mode)
    assert info["hs_max"] > 50                        # the plateau below the HS's reach is in the grid
    assert info["solved"] - info["hs_max"] > 100      # and the set point held ("sp")
    if ls_mode == "float":
        assert info["floated"] > 50                   # rows where the LS saturates


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_agrees_on_a_fouled_evaporator(plant, ls_mode):
    check_agreement(plant.replace(R_th_f=5e-6), grid(full=False), ls_mode)    # 5e-3 K/kW


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_agrees_with_learned_compressors(plant, learned, ls_mode):
    assert learned.comp_HS.local_is is not None and learned.comp_LS.local_vol is not None
    check_agreement(learned, grid(full=False), ls_mode)


def test_agrees_with_an_uncertainty_draw_of_the_learned_curves(learned_delta):
    assert learned_delta.comp_HS.delta_is is not None
    check_agreement(learned_delta, grid(full=False).iloc[::3], "float")


def _draw_learner(plant):
    """A learner with local curves (``learned_params``'s observations) and three of its draws."""
    rng = np.random.default_rng(0)
    k = 3000
    obs = {c: np.full(k, np.nan) for c in OBS_COLUMNS}
    obs["t"] = np.arange(k) * 60.0
    for st, pi0, n0 in (("LS", 2.4, 1.05), ("HS", 1.9, 1.0)):
        obs[f"pi_{st}"] = rng.normal(pi0, 0.25, k)
        obs[f"n_{st}"] = rng.normal(n0, 0.1, k)
        obs[f"eta_is_{st}"] = 0.77 - 0.03 * (obs[f"pi_{st}"] - 2.4) ** 2 + rng.normal(0, 0.002, k)
        obs[f"eta_vol_{st}"] = 0.93 - 0.03 * obs[f"pi_{st}"] + rng.normal(0, 0.002, k)
        obs[f"drive_{st}"] = np.full(k, 1.03)
    learner = CompressorLearner(plant)
    learner.update(pd.DataFrame(obs))
    return learner, learner.draws(3, np.random.default_rng(7))


def test_per_row_curve_draws_answer_as_one_call_per_draw(plant):
    """``solve_many(deltas=...)``: the uncertainty draws of a window in one call give every row the
    numbers a call with that draw's compressors (and its R_th,f) gives."""
    learner, draws = _draw_learner(plant)
    df = grid(full=False).iloc[::6].reset_index(drop=True)
    n = len(df)
    R = [0.0, 2e-6, 4e-6]
    sep = []
    for d, r in zip(draws, R):
        par = plant.replace(comp_LS=learner.compressor("LS", delta=d["LS"]),
                            comp_HS=learner.compressor("HS", delta=d["HS"]), R_th_f=r)
        sep.append(solve_many(df, par, ls_mode="float").frame())
    base = plant.replace(comp_LS=learner.compressor("LS", delta=draws[0]["LS"]),
                         comp_HS=learner.compressor("HS", delta=draws[0]["HS"]))
    deltas = {f"{st}_{c[4:]}": np.repeat([d[st][c] for d in draws], n, axis=0)
              for st in ("LS", "HS") for c in ("eta_is", "eta_vol")}
    one = solve_many(pd.concat([df] * 3, ignore_index=True), base, ls_mode="float",
                     R_th_f=np.repeat(R, n), deltas=deltas).frame()
    ref = pd.concat(sep, ignore_index=True)
    assert (one["status"].to_numpy() == ref["status"].to_numpy()).all()
    solved = ref["Q_sink_kW"].notna().to_numpy()
    assert solved.sum() > n                       # most rows of each draw solve
    for k in ("Q_sink_kW", "W_total_kW", "COP", "p_m_bar", "N_LS_rpm", "N_HS_rpm", "T_source_out_C"):
        a, b = one[k].to_numpy()[solved], ref[k].to_numpy()[solved]
        assert np.max(np.abs(a - b) / np.maximum(np.abs(b), 1.0)) <= DRAW_REL, k
    # the draws differ from each other, so the rows did get their own curves
    cop = one["COP"].to_numpy().reshape(3, n)
    both = np.isfinite(cop).all(axis=0)
    assert np.max(np.abs(cop[0, both] - cop[1, both])) > 1e-4


def test_per_row_curve_draws_are_checked(plant):
    df = grid(full=False).iloc[:4]
    learner, draws = _draw_learner(plant)
    base = plant.replace(comp_LS=learner.compressor("LS", delta=draws[0]["LS"]))
    with pytest.raises(ValueError, match=re.escape("deltas: unknown key 'LS_eta' (known: LS_is, LS_vol, "
                                                   "HS_is, HS_vol)")):
        solve_many(df, base, deltas={"LS_eta": np.zeros((4, 6))})
    with pytest.raises(ValueError, match=re.escape("deltas['LS_is'] must be finite, shape (4, 6), got "
                                                   "shape (3, 6)")):
        solve_many(df, base, deltas={"LS_is": np.zeros((3, 6))})
    with pytest.raises(ValueError, match=re.escape("deltas['HS_vol']: the HS compressor has no learned "
                                                   "curves (Compressor)")):
        solve_many(df, base, deltas={"HS_vol": np.zeros((4, 6))})


def test_frame_layout_equals_frame_of_and_the_set_point_override(plant):
    df = grid(full=False).iloc[:42]
    got = solve_many(df.drop(columns="p_m_sp"), plant, p_m_sp=14.0).frame(index=df.index)
    ref = simulate_batch(df.drop(columns="p_m_sp"), plant, p_m_sp=14.0)
    assert list(got.columns) == list(OUTPUT_KEYS) + ["status", "reason"] == list(ref.columns)
    assert (got.dtypes == ref.dtypes).all() and got.index.equals(ref.index)
    assert np.allclose(got["p_m_barg"].dropna(), 14.0) or got["hs_saturated"].eq(1.0).any()
    sp = np.linspace(8.0, 20.0, len(df))
    a = solve_many(df.drop(columns="p_m_sp"), plant, p_m_sp=sp).frame()
    b = solve_many(df.assign(p_m_sp=sp), plant).frame()
    pd.testing.assert_frame_equal(a, b)


def test_bad_inputs_get_the_scalar_statuses(plant):
    rows = pd.DataFrame([{**NOMINAL, "p_m_sp": 16.0}] * 5)
    rows.loc[0, "T_source_in"] = np.nan
    rows.loc[1, "T_source_out"] = 26.0                 # not cooled
    rows.loc[2, "V_sink"] = 0.0
    rows.loc[3, "p_m_sp"] = 120.0                      # above the critical pressure
    got = solve_many(rows, plant).frame()
    ref = simulate_batch(rows, plant)
    assert got["status"].tolist() == ref["status"].tolist()
    assert got["reason"].tolist() == ref["reason"].tolist()
    with pytest.raises(ValueError, match="ls_mode must be one of flag, float"):
        solve_many(rows, plant, ls_mode="clamp")


# ---------------------------------------------------------------------------------------------------
# 2. the subcooler outlet on the equation of state
# ---------------------------------------------------------------------------------------------------
def test_subcooler_outlet_is_the_eos_liquid_state(plant):
    df = pd.DataFrame([{**NOMINAL, "p_m_sp": 16.0}, {**NOMINAL, "p_m_sp": 10.0},
                       {**NOMINAL, "V_sink": 50.0, "T_sink_in": 44.0, "p_m_sp": 16.0},
                       {**NOMINAL, "V_source": 170.0, "T_source_in": 23.0, "p_m_sp": 20.0}])
    vr = solve_many(df, plant)
    assert (vr.status == "ok").all() and vr.fallback_rows == 0
    UA_SC = plant.CF_SC * plant.U_SC * plant.A_SC
    for i in range(len(df)):
        p_c, T_SC, T_c = vr["p_c_bar"][i] * BAR, C_to_K(vr["T_SC_C"][i]), C_to_K(vr["T_c_C"][i])
        h_SC, h_f = vr["h_SC_J_kg"][i], vr["h_con_out_J_kg"][i]
        assert T_SC < T_c - 1.0                                       # really subcooled
        h_ref = CP.PropsSI("H", "P", p_c, "T", T_SC, "Ammonia")
        assert abs(h_SC - h_ref) <= EOS_TOL * abs(h_ref)
        assert h_f == pytest.approx(CP.PropsSI("H", "P", p_c, "Q", 0, "Ammonia"), rel=EOS_TOL)
        # the SC's duty three ways: refrigerant side, water side, eps-NTU with the secant capacity
        Q_SC = vr["Q_SC_kW"][i] * 1e3
        m_HS = vr["m_HS_kg_s"][i]
        assert m_HS * (h_f - h_SC) == pytest.approx(Q_SC, rel=1e-9)
        C_w = plant.cp_w * plant.rho_w * df["V_sink"][i] / 3600.0
        T_ki = C_to_K(df["T_sink_in"][i])
        assert C_w * (C_to_K(vr["T_w_SC_out_C"][i]) - T_ki) == pytest.approx(Q_SC, rel=1e-9)
        eps, C_min = counterflow_eps(m_HS * (h_f - h_SC) / (T_c - T_SC), C_w, UA_SC)
        assert eps * C_min * (T_c - T_ki) == pytest.approx(Q_SC, rel=1e-8)
        assert vr["subcooling_K"][i] == pytest.approx(T_c - T_SC, abs=1e-9)


# ---------------------------------------------------------------------------------------------------
# 3. the vectorised compressor protocol
# ---------------------------------------------------------------------------------------------------
def _compressors(plant, learned, learned_delta):
    from simulator.compressors import NAN6, ShapedCompressor
    hs = plant.comp_HS
    shaped = ShapedCompressor(swept_volume=hs.swept_volume, N_nom=hs.N_nom, N_min=hs.N_min, N_max=hs.N_max,
                              eta_is=NAN6, eta_vol=NAN6, n_opt=1.1, w_n=0.4, vol_c=0.05, family="test")
    return {"polynomial": plant.comp_LS, "learned": learned.comp_HS, "learned_delta": learned_delta.comp_HS,
            "shaped": shaped}


@pytest.mark.parametrize("kind", ["polynomial", "learned", "learned_delta", "shaped"])
def test_vectorised_compressor_methods_equal_the_scalar_ones(plant, learned, learned_delta, kind):
    comp = _compressors(plant, learned, learned_delta)[kind]
    assert vectorized(comp) is comp
    rng = np.random.default_rng(3)
    k = 600
    pi, n = rng.uniform(1.3, 4.5, k), rng.uniform(0.35, 1.5, k)
    m, rho, n0 = rng.uniform(0.1, 2.5, k), rng.uniform(3.0, 30.0, k), rng.uniform(0.5, 1.3, k)
    if kind.startswith("learned"):                     # half of the points inside the local grid
        pi[: k // 2], n[: k // 2] = rng.normal(2.2, 0.3, k // 2), rng.normal(1.05, 0.1, k // 2)
        assert comp.local_is.value_v(pi, n)[1].sum() > k // 4
    for vec, sca in ((comp.eta_is_v, comp.eta_is_at), (comp.eta_vol_v, comp.eta_vol_at)):
        ref = np.array([sca(a, b) for a, b in zip(pi, n)])
        np.testing.assert_allclose(vec(pi, n), ref, rtol=COMP_REL, atol=0)
    n_v, ev_v = comp.speed_for_flow_v(m, rho, pi, n0)
    ref = []
    for a, b, c, d in zip(m, rho, pi, n0):
        try:
            ref.append(comp.speed_for_flow(a, b, c, d))
        except ValueError:
            ref.append((np.nan, np.nan))
    ref = np.array(ref)
    assert np.isfinite(ref[:, 0]).sum() > k // 2
    assert (np.isnan(n_v) == np.isnan(ref[:, 0])).all()
    np.testing.assert_allclose(n_v, ref[:, 0], rtol=COMP_REL, atol=0)
    np.testing.assert_allclose(ev_v, ref[:, 1], rtol=COMP_REL, atol=0)


@pytest.mark.parametrize("kind", ["polynomial", "learned", "shaped"])
def test_a_row_with_nan_inputs_leaves_the_other_rows_speeds_as_they_are(plant, learned, learned_delta, kind):
    comp = _compressors(plant, learned, learned_delta)[kind]
    m, rho, pi = np.array([0.8, 1.2, 1.6]), np.array([8.0, 9.0, 10.0]), np.array([2.0, 2.3, 2.6])
    n_ref, ev_ref = comp.speed_for_flow_v(m, rho, pi)
    assert np.isfinite(n_ref).all()
    n, ev = comp.speed_for_flow_v(np.array([0.8, np.nan, 1.6]), rho, pi)
    assert np.isnan(n[1]) and np.isnan(ev[1])
    np.testing.assert_allclose(n[[0, 2]], n_ref[[0, 2]], rtol=COMP_REL, atol=0)
    np.testing.assert_allclose(ev[[0, 2]], ev_ref[[0, 2]], rtol=COMP_REL, atol=0)


def test_a_compressor_without_the_protocol_is_looped(plant):
    class Derated(Compressor):
        def eta_is_at(self, pi, n):
            return Compressor.eta_is_at(self, pi, n) - 0.02

    comp = Derated(**{f: getattr(plant.comp_HS, f) for f in ("swept_volume", "N_nom", "N_min", "N_max",
                                                             "eta_is", "eta_vol", "drive_factor")})
    v = vectorized(comp)
    assert isinstance(v, _Looped)               # the inherited polynomial eta_is_v would be wrong
    assert v.eta_is_v([2.0], [1.0])[0] == pytest.approx(comp.eta_is_at(2.0, 1.0), rel=1e-15)
    params = plant.replace(comp_HS=comp)
    df = pd.DataFrame([{**NOMINAL, "p_m_sp": sp} for sp in (10.0, 16.0, 20.0)])
    got = solve_many(df, params).frame()
    ref = scalar_frame(df, params, "flag")
    assert got["status"].tolist() == ref["status"].tolist()
    np.testing.assert_allclose(got["COP"], ref["COP"], rtol=AGREE_REL)


# ---------------------------------------------------------------------------------------------------
# 4. the scalar fallback
# ---------------------------------------------------------------------------------------------------
def test_rows_outside_the_tables_or_forced_get_the_scalar_answer(plant):
    cold = {**NOMINAL, "T_source_in": -67.5, "T_source_out": -72.5, "p_m_sp": 16.0}  # T_e below 200 K
    df = pd.DataFrame([cold] + [{**NOMINAL, "p_m_sp": sp} for sp in (8.0, 16.0, 22.0)])
    force = np.array([False, True, False, True])
    vr = solve_many(df, plant, ls_mode="float", force_scalar=force)
    assert vr.fallback.tolist() == [True, True, False, True] and vr.fallback_rows == 3
    got, ref = vr.frame(), scalar_frame(df, plant, "float")
    assert got["status"].tolist() == ref["status"].tolist()
    assert got["reason"].tolist() == ref["reason"].tolist()
    pd.testing.assert_frame_equal(got.iloc[[1, 3]], ref.iloc[[1, 3]])   # the forced rows: identical
    free = solve_many(df.iloc[[1, 3]], plant, ls_mode="float").frame()
    for k in COMPARED:
        np.testing.assert_allclose(free[k], ref[k].iloc[[1, 3]], rtol=AGREE_REL)


# ---------------------------------------------------------------------------------------------------
# the tables against HEOS
# ---------------------------------------------------------------------------------------------------
def test_tables_agree_with_heos():
    """Documented accuracy of model.cycletables on random states: saturation (p, rho to 1e-11
    relative, h to 1e-6 J/kg, T_sat(p) to 1e-9 K), superheated vapour up to 220 K of superheat
    (h to 2e-3 J/kg, 3e-3 above 370 K, s to 1e-5 J/kg/K, rho to 2e-8 relative; beyond, to 4500 K, 5e-2 J/kg, 5e-9
    relative) and its inverses (theta to 3e-6 K), the isentropic state (h to 3e-3 J/kg) and T from
    h (to 1e-6 K) by direct lookup, subcooled liquid (h to 3e-3 J/kg)."""
    tab, fl = get_cycle_tables(), Fluid()
    rng = np.random.default_rng(7)
    T = rng.uniform(200.0, 395.0, 300)
    p, h_f, h_g, s_g, rho_g = tab.sat(T)
    ref = np.array([[s.p, s.h_f, s.h_g, s.s_g, s.rho_g] for s in (fl.sat_T(float(t)) for t in T)])
    assert np.max(np.abs(p / ref[:, 0] - 1)) < 1e-11 and np.max(np.abs(rho_g / ref[:, 4] - 1)) < 1e-11
    assert np.max(np.abs(h_f - ref[:, 1])) < 1e-6 and np.max(np.abs(h_g - ref[:, 2])) < 1e-6
    assert np.max(np.abs(s_g - ref[:, 3])) < 1e-8
    assert np.max(np.abs(tab.T_sat(ref[:, 0]) - T)) < 1e-9
    T_sat = rng.uniform(VAP_T_MIN, VAP_T_MAX, 600)
    theta = np.concatenate([rng.uniform(0.0, 3.0, 200), rng.uniform(0.0, 220.0, 300),
                            rng.uniform(220.0, THETA_MAX, 100)])
    h, s, rho = tab.vapour(T_sat, theta)
    p = tab.p_sat(T_sat)
    ref = np.array([fl.vapour_pT(float(a), float(b + c)) for a, b, c in zip(p, T_sat, theta)])
    lim = np.where(theta <= 220.0, np.where(T_sat > 370.0, 3e-3, 2e-3), 5e-2)   # module docstring
    assert (np.abs(h - ref[:, 0]) <= lim).all()
    assert np.max(np.abs(s - ref[:, 1])[theta <= 220.0]) < 1e-5
    assert np.max(np.abs(rho / ref[:, 2] - 1)) < 2e-8
    for key, col in (("s", 1), ("h", 0)):
        th, _, _, _ = tab.vapour_from(key, T_sat, ref[:, col])
        assert np.max(np.abs(th - theta)[theta <= 220.0]) < 3e-6
    # the direct lookups of the flowsheet: isentropic discharge state, T from (p, h)
    T_c = rng.uniform(VAP_T_MIN + 50.0, 380.0, 300)
    T_m = T_c - rng.uniform(1.0, 45.0, 300)
    s_g = np.array([fl.sat_T(float(t)).s_g for t in T_m])
    ref = np.array([fl.isentropic(fl.sat_T(float(a)).p, float(b)) for a, b in zip(T_c, s_g)])
    assert np.max(np.abs(tab.h_isentropic(T_c, s_g) - ref[:, 0])) < 3e-3
    h = ref[:, 0] + rng.uniform(0.0, 4e5, 300)
    T_ref = np.array([fl.vapour_ph(fl.sat_T(float(a)).p, float(b))[0] for a, b in zip(T_c, h)])
    assert np.max(np.abs(T_c + tab.theta_from_h(T_c, h) - T_ref)) < 1e-6
    T_c, d = rng.uniform(270.0, 385.0, 300), rng.uniform(0.0, 70.0, 300)
    h_l = tab.liquid(T_c, d)
    ref = [fl.liquid_pT(fl.sat_T(float(a)).p, float(a - b)) for a, b in zip(T_c, d)]
    assert np.max(np.abs(h_l - ref)) < 3e-3
    assert np.isnan(tab.vapour(np.array([150.0, VAP_T_MIN - 0.5]), np.array([10.0, 10.0]))[0]).all()  # outside: NaN


# ---------------------------------------------------------------------------------------------------
# 5. warm starts (solve_many(guess=...)) and per-row parameters
# ---------------------------------------------------------------------------------------------------
# Status rule for a warm start: every row has the cold solve's status, except a row whose cold or warm
# answer sits within a small distance of a limit that decides a status or a branch: N_LS within
# NEAR_LS_RPM of a speed bound or of a flag threshold (bound -+ LS_SPEED_LOOSE * N_nom), N_HS at a
# speed bound within NEAR_HS_REL, the pinch within NEAR_PINCH_K of 0.
NEAR_LS_RPM = 1.5
NEAR_HS_REL = 1e-6
NEAR_PINCH_K = 1e-6


def near_limit_warm(params, a: pd.Series, b: pd.Series) -> bool:
    ls, hs = params.comp_LS, params.comp_HS
    tol = LS_SPEED_LOOSE * ls.N_nom
    for r in (a, b):
        n_ls, n_hs, pinch = r["N_LS_rpm"], r["N_HS_rpm"], r["pinch_K"]
        if math.isfinite(n_ls) and min(abs(n_ls - x) for x in (ls.N_min, ls.N_max, ls.N_min - tol,
                                                               ls.N_max + tol)) <= NEAR_LS_RPM:
            return True
        if math.isfinite(n_hs) and min(abs(n_hs / x - 1.0) for x in (hs.N_min, hs.N_max)) <= NEAR_HS_REL:
            return True
        if math.isfinite(pinch) and abs(pinch) <= NEAR_PINCH_K:
            return True
    return False


def check_warm(params, df: pd.DataFrame, ls_mode: str, guess, min_warm: float = 0.5, **kw) -> dict:
    """The warm solve against the cold one (solve_many without a guess: the scalar cold path)."""
    cold = solve_many(df, params, ls_mode=ls_mode, **kw)
    vr = solve_many(df, params, ls_mode=ls_mode, guess=guess, **kw)
    got, ref = vr.frame(), cold.frame()
    n = len(df)
    assert vr.warm_rows + vr.cold_rows + vr.fallback_rows <= n
    assert vr.warm_rows >= min_warm * cold.solved().sum()
    differ = np.flatnonzero(got["status"].to_numpy() != ref["status"].to_numpy())
    exempt = [i for i in differ if near_limit_warm(params, got.iloc[i], ref.iloc[i])]
    assert len(exempt) == len(differ), got.iloc[[i for i in differ if i not in exempt]][["status", "reason"]]
    assert len(exempt) <= 0.005 * n
    solved = got["Q_sink_kW"].notna().to_numpy() & ref["Q_sink_kW"].notna().to_numpy()
    same = np.setdiff1d(np.arange(n), differ)
    assert (got["Q_sink_kW"].notna() == ref["Q_sink_kW"].notna()).to_numpy()[same].all()
    near = [i for i in range(n) if near_limit_warm(params, got.iloc[i], ref.iloc[i])]
    assert (vr.branch == cold.branch)[np.setdiff1d(same, near)].all()
    for k in COMPARED:
        rel = np.abs(got[k].to_numpy() - ref[k].to_numpy()) / np.abs(ref[k].to_numpy())
        assert rel[solved].max() <= AGREE_REL, (k, rel[solved].max())
    dT = np.abs(got["T_source_out_C"].to_numpy() - ref["T_source_out_C"].to_numpy())[solved]
    assert dT.max() <= T_SO_ABS
    assert np.abs(got["energy_residual"].to_numpy()[solved]).max() <= ENERGY_TOL
    return {"warm": vr.warm_rows, "cold": vr.cold_rows, "fallback": vr.fallback_rows, "result": vr}


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
@pytest.mark.parametrize("shift", [0.5, -0.5])
def test_warm_from_a_nearby_set_point_gives_the_cold_answers(plant, ls_mode, shift):
    df = grid(full=False)
    guess = solve_many(df.assign(p_m_sp=df["p_m_sp"] - shift), plant, ls_mode=ls_mode)
    info = check_warm(plant, df, ls_mode, guess)
    assert info["warm"] > 150
    # and again from that warm result (its state is a guess too), at the next set point
    check_warm(plant, df.assign(p_m_sp=df["p_m_sp"] + shift), ls_mode, info["result"])


def test_warm_on_the_full_grid_gives_the_cold_answers(plant):
    """The full grid reaches far beyond the LS stage (N_LS up to 3300 rpm), where the cold search at
    an HS bound depends on its path: those rows must leave the warm path."""
    df = grid(full=True)
    guess = solve_many(df.assign(p_m_sp=df["p_m_sp"] + 0.5), plant.replace(R_th_f=plant.R_th_f + 1e-6),
                       ls_mode="float")
    check_warm(plant, df, "float", guess)


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_warm_after_a_fouling_step_gives_the_cold_answers(plant, ls_mode):
    df = grid(full=False)
    guess = solve_many(df, plant, ls_mode=ls_mode)
    check_warm(plant.replace(R_th_f=plant.R_th_f + 1e-6), df, ls_mode, guess)    # +1e-3 K/kW


def test_warm_onto_an_uncertainty_draw_of_the_learned_curves(learned, learned_delta):
    df = grid(full=False).iloc[::2].reset_index(drop=True)
    guess = solve_many(df, learned, ls_mode="float")
    check_warm(learned_delta, df, "float", guess)


def test_a_guess_from_unrelated_rows_still_gives_the_cold_answers(plant):
    df = grid(full=False)
    rng = np.random.default_rng(5)
    other = solve_many(df.sample(frac=1.0, random_state=2).reset_index(drop=True), plant, ls_mode="float")
    check_warm(plant, df, "float", other, min_warm=0.0)
    # rows of another plant's operating points entirely, mapped at random (-1: no guess)
    far = solve_many(grid(full=False).assign(T_sink_in=30.0, V_sink=90.0).iloc[:60], plant, ls_mode="float")
    index = rng.integers(-1, 60, len(df))
    cold = solve_many(df, plant, ls_mode="float")
    vr = solve_many(df, plant, ls_mode="float", guess=far, guess_index=index)
    assert (vr.status == cold.status).all()
    np.testing.assert_allclose(vr["COP"], cold["COP"], rtol=AGREE_REL)
    assert not vr.warm[index < 0].any()


SWITCH_ROWS_MIN = 5      # rows of the grid whose guess ran at the set point and whose answer is at an HS bound


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_a_row_whose_guess_ran_at_the_set_point_stays_warm_at_an_hs_bound(plant, ls_mode):
    """A row whose guess ran at its set point ("sp") but which needs the HS at a speed bound at the new
    set point changes branch once and stays warm: the "sp" root is the HS-bound problem's set-point
    test (until stop 43 the switch dropped that test and the row went to the cold path), and its
    answer is the cold path's."""
    df = grid(full=False)
    guess = solve_many(df.assign(p_m_sp=df["p_m_sp"] + 1.0), plant, ls_mode=ls_mode)
    cold = solve_many(df, plant, ls_mode=ls_mode)
    switch = ((np.asarray(guess.branch) == "sp") & np.isin(np.asarray(cold.branch), ["hs_max", "hs_min"])
              & (np.asarray(cold.status) == "ok"))
    assert switch.sum() >= SWITCH_ROWS_MIN
    info = check_warm(plant, df, ls_mode, guess)
    vr = info["result"]
    assert np.asarray(vr.warm)[switch].all()
    assert (np.asarray(vr.branch)[switch] == np.asarray(cold.branch)[switch]).all()


def test_guess_arguments_are_checked(plant):
    df = grid(full=False).iloc[:10]
    g = solve_many(df, plant)
    with pytest.raises(ValueError, match="guess has 10 rows for 5 rows"):
        solve_many(df.iloc[:5], plant, guess=g)
    with pytest.raises(ValueError, match="guess_index must give one row of guess"):
        solve_many(df, plant, guess=g, guess_index=np.full(10, 10))
    with pytest.raises(ValueError, match="R_th_f must be a scalar or one value per row"):
        solve_many(df, plant, R_th_f=np.zeros(3))


@pytest.mark.parametrize("ls_mode", ["flag", "float"])
def test_per_row_fouling_and_condenser_factor_equal_separate_calls(plant, ls_mode):
    base = grid(full=False)
    df = base[base["p_m_sp"].isin([6.0, 10.0, 14.0, 18.0, 22.0])].reset_index(drop=True)
    n = len(df)
    R = np.array([0.0, 3e-6, 6e-6])[np.arange(n) % 3]               # K/W
    k = np.array([1.0, 0.95, 1.04, 1.0])[np.arange(n) % 4]
    vr = solve_many(df, plant, ls_mode=ls_mode, R_th_f=R, cond_factor=k)
    warm = solve_many(df, plant, ls_mode=ls_mode, R_th_f=R, cond_factor=k,
                      guess=solve_many(df.assign(p_m_sp=df["p_m_sp"] - 0.5), plant, ls_mode=ls_mode,
                                       R_th_f=R, cond_factor=k))
    assert warm.warm_rows > 0.5 * n
    got, hot = vr.frame(), warm.frame()
    for r, f in {(a, b) for a, b in zip(R, k)}:
        rows = np.flatnonzero((R == r) & (k == f))
        p = plant.replace(R_th_f=r, CF_DSH=plant.CF_DSH * f, CF_con=plant.CF_con * f, CF_SC=plant.CF_SC * f)
        ref = solve_many(df.iloc[rows], p, ls_mode=ls_mode).frame()
        for frame in (got, hot):
            part = frame.iloc[rows].reset_index(drop=True)
            assert part["status"].tolist() == ref["status"].tolist()
            both = part["Q_sink_kW"].notna().to_numpy()
            assert (both == ref["Q_sink_kW"].notna().to_numpy()).all()
            for c in COMPARED + ("T_source_out_C",):
                a, b = part[c].to_numpy()[both], ref[c].to_numpy()[both]
                tol = 1e-9 if frame is got else AGREE_REL
                assert np.all(np.abs(a - b) <= tol * np.abs(b)), (c, r, f)


def test_learner_eta_is_for_arrays_is_the_scalar_curve_to_the_bit(plant):
    """``CompressorLearner.eta_is`` (the windows' residuals and samples.csv's model eta_is) answers
    arrays with the compressor's vectorised curve: the scalar ``eta_is_at``'s numbers to the bit,
    on the local grid, beyond it (the global curve) and on its node lines."""
    learner, _ = _draw_learner(plant)
    rng = np.random.default_rng(21)
    for st in ("LS", "HS"):
        comp = learner.compressor(st)
        assert comp.local_is is not None and comp.local_is.ok
        pi = np.concatenate([rng.normal(2.2, 0.6, 3000), comp.local_is.p0 + comp.local_is.dpi * np.arange(5)])
        n = np.concatenate([rng.normal(1.0, 0.3, 3000), comp.local_is.n0 + comp.local_is.dn * np.arange(5)])
        got = learner.eta_is(st, pi, n)
        ref = np.array([comp.eta_is_at(a, b) for a, b in zip(pi, n)])
        np.testing.assert_array_equal(got, ref)
        inside = comp.local_is.value_v(pi, n)[1]
        assert 500 < inside.sum() < len(pi) - 500
    assert learner.eta_is("LS", 2.4, 1.05).shape == (1,)
