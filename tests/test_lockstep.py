"""Windows in lockstep (model.lockstep, model.analysis.stacked, model.vcycle.solve_merged).

- ``Stacked``: a row of a stage's stacked compressors gets its own compressor's vectorised numbers,
  to the bit (the same operations, the constants gathered per row);
- ``solve_merged``: several ``solve_many`` calls with their own parameters (learned compressors,
  R_th,f, condenser factor, CF_dp,f, uncertainty draws, warm starts) in one give each call's
  statuses and its numbers within MERGED_REL (what may differ: the decisions the solver takes over
  all its rows, e.g. how many rows leave the warm path for the scalar solver);
- ``lockstep.run``: the callables' solver calls are answered together, results in order, the same
  numbers on every run, an exception in its place.
"""
from __future__ import annotations

import dataclasses
import re
import threading

import numpy as np
import pandas as pd
import pytest

from model import lockstep
from model.analysis.compressors import LearnedCompressor
from model.analysis.stacked import Stacked, stackable
from model.vcycle import merge_key, solve_many, solve_merged
from test_vcycle import _draw_learner, grid, learned_params

MERGED_REL = 1e-7          # merged calls against separate calls (Q, W, COP, p_m, speeds, T_so)
COMPARED = ("Q_sink_kW", "W_total_kW", "COP", "p_m_bar", "N_LS_rpm", "N_HS_rpm", "T_source_out_C",
            "dp_source_bar")


@pytest.fixture(scope="module")
def learned(plant):
    return learned_params(plant, delta=False)


@pytest.fixture(scope="module")
def draws(plant):
    return _draw_learner(plant)


def _members(plant, learned, draws):
    """Compressors of one stage as windows have them: the configured polynomial, two learned ones
    (different local grids) and a learned one with a draw."""
    learner, ds = draws
    return [plant.comp_HS, learned.comp_HS, learner.compressor("HS"),
            learner.compressor("HS", delta=ds[0]["HS"])]


def test_stacked_rows_get_their_own_compressors_numbers_to_the_bit(plant, learned, draws):
    comps = _members(plant, learned, draws)
    assert stackable(comps) and isinstance(comps[1], LearnedCompressor)
    st = Stacked(comps)
    rng = np.random.default_rng(5)
    k = 400
    g = rng.integers(0, len(comps), k)
    pi = np.where(rng.random(k) < 0.6, rng.normal(2.1, 0.3, k), rng.uniform(1.3, 4.5, k))
    n = np.where(rng.random(k) < 0.6, rng.normal(1.02, 0.1, k), rng.uniform(0.35, 1.5, k))
    m, rho, n0 = rng.uniform(0.1, 2.5, k), rng.uniform(3.0, 30.0, k), rng.uniform(0.5, 1.3, k)
    # the draw of member 3 as per-row differences (what Flowsheet.comp hands over)
    zero = np.zeros((k, 6))
    d_is, d_vol = zero.copy(), zero.copy()
    d_is[g == 3], d_vol[g == 3] = comps[3].delta_is, comps[3].delta_vol
    v = st.view(g, tuple(d_is.T), tuple(d_vol.T))
    got = {"is": v.eta_is_v(pi, n), "vol": v.eta_vol_v(pi, n)}
    n_s, ev_s = v.speed_for_flow_v(m, rho, pi, n0)
    inside = 0
    for j, c in enumerate(comps):
        r = np.flatnonzero(g == j)
        assert len(r) > 50
        np.testing.assert_array_equal(got["is"][r], c.eta_is_v(pi[r], n[r]))
        np.testing.assert_array_equal(got["vol"][r], c.eta_vol_v(pi[r], n[r]))
        ref_n, ref_ev = c.speed_for_flow_v(m[r], rho[r], pi[r], n0[r])
        assert np.isfinite(ref_n).sum() > len(r) // 2
        if isinstance(c, LearnedCompressor):
            # the local grids' speed search: row by row the member's own
            np.testing.assert_array_equal(n_s[r], ref_n)
            np.testing.assert_array_equal(ev_s[r], ref_ev)
            inside += int(c.local_vol.value_v(pi[r], n[r])[1].sum())
        else:
            # the global cubic's Newton stops when all its rows have: other rows, other last step
            np.testing.assert_allclose(n_s[r], ref_n, rtol=1e-12, atol=0)
            np.testing.assert_allclose(ev_s[r], ref_ev, rtol=1e-12, atol=0)
    assert inside > k // 4                       # the local grids did answer


def test_members_of_another_plant_are_not_stacked(plant, learned):
    other = plant.comp_HS.replace(N_max=plant.comp_HS.N_max + 100.0)
    assert not stackable([plant.comp_HS, other])
    with pytest.raises(ValueError, match=re.escape("compressors of different classes, speed ranges or "
                                                   "swept volumes cannot be stacked")):
        Stacked([learned.comp_HS, other])


def _requests(plant, learned, draws):
    """Calls as windows make them: own compressors, fouling, condenser factors, CF_dp,f, set points,
    draws, a warm start; "float" mode."""
    learner, ds = draws
    df = grid(full=False).iloc[::5].reset_index(drop=True)
    n = len(df)
    a = learned.replace(R_th_f=3e-6, CF_dp_f=1.4, CF_DSH=0.9, CF_con=0.9, CF_SC=0.9)
    b = plant.replace(comp_LS=learner.compressor("LS"), comp_HS=learner.compressor("HS"), CF_dp_f=1.1)
    c = plant
    guess = solve_many(df, a, p_m_sp=df["p_m_sp"] + 0.3, ls_mode="float")
    deltas = {f"{st}_{cv[4:]}": np.repeat([d[st][cv] for d in ds[:2]], n, axis=0)
              for st in ("LS", "HS") for cv in ("eta_is", "eta_vol")}
    two = pd.concat([df, df], ignore_index=True)
    return [
        dict(rows=df, params=a, ls_mode="float"),
        dict(rows=df, params=b, ls_mode="float", R_th_f=np.linspace(0.0, 5e-6, n), cond_factor=1.1),
        dict(rows=df, params=c, ls_mode="float", p_m_sp=9.0),
        dict(rows=df, params=a, ls_mode="float", guess=guess),
        dict(rows=two, params=b, ls_mode="float", R_th_f=np.repeat([0.0, 2e-6], n), deltas=deltas),
    ]


def test_merged_calls_answer_as_separate_calls(plant, learned, draws):
    kws = _requests(plant, learned, draws)
    captured = []
    sep = [solve_many(**kw).frame() for kw in kws]
    one = lockstep.run([(lambda kw=kw: solve_many(**kw)) for kw in kws],
                       answer=lambda batch: captured.append(len(batch)) or lockstep.answer_requests(batch))
    assert captured == [len(kws)]                 # one round: every call in it
    keys = [merge_key(dict(kw, force_scalar=None, gi=None)) for kw in kws]
    assert all(k is not None and k == keys[0] for k in keys)
    for kw, s, o in zip(kws, sep, one):
        o = o.frame()
        assert (o["status"].to_numpy() == s["status"].to_numpy()).all()
        solved = s["Q_sink_kW"].notna().to_numpy()
        assert solved.sum() >= len(s) // 3
        for k in COMPARED:
            x, y = o[k].to_numpy()[solved], s[k].to_numpy()[solved]
            assert np.max(np.abs(x - y) / np.maximum(np.abs(y), 1.0)) <= MERGED_REL, k
    # the calls had their own parameters: the condenser factor, CF_dp,f and fouling show
    assert not np.allclose(sep[0]["dp_source_bar"], sep[1]["dp_source_bar"])
    assert not np.allclose(sep[0]["COP"].fillna(0), sep[2]["COP"].fillna(0))


def test_solve_merged_is_the_same_as_through_threads(plant, learned, draws):
    kws = _requests(plant, learned, draws)[:3]
    full = [dict(kw, force_scalar=None, guess=None, gi=None, p_m_sp=kw.get("p_m_sp"),
                 R_th_f=None if kw.get("R_th_f") is None else np.asarray(kw["R_th_f"], dtype=float),
                 cond_factor=None if kw.get("cond_factor") is None else np.full(len(kw["rows"]), kw["cond_factor"]),
                 deltas={}) for kw in kws]
    a = solve_merged(full)
    b = lockstep.run([(lambda kw=kw: solve_many(**kw)) for kw in kws])
    for x, y in zip(a, b):
        pd.testing.assert_frame_equal(x.frame(), y.frame())


@pytest.mark.parametrize("kernels", [True, False])
def test_a_merged_call_of_pairs_stacked_already_reuses_the_stacks_to_the_bit(plant, learned, draws,
                                                                            monkeypatch, kernels):
    """A lockstep's later rounds ask for fewer of its windows: a merged call whose compressor pairs
    are all members of a recent call's stacks takes those stacks (each row its pair's member
    there) and answers to the bit as stacks of its own pairs would; other pairs get stacks of
    their own, the last ``STACKED_KEPT`` kept. Compiled kernels or numpy alike."""
    import model.vcycle as V
    from model.analysis import speedkernel
    if kernels:
        assert speedkernel.enable()
    else:
        for k in ("_KERNEL", "_CURVE", "_LIQ", "_SAT", "_DER", "_SC_PRE", "_SC_POST"):
            monkeypatch.setattr(speedkernel, k, None)
    monkeypatch.setattr(V, "_STACKED", [])
    kws = _requests(plant, learned, draws)[:3]
    full = [dict(kw, force_scalar=None, guess=None, gi=None, p_m_sp=kw.get("p_m_sp"),
                 R_th_f=None if kw.get("R_th_f") is None else np.asarray(kw["R_th_f"], dtype=float),
                 cond_factor=None if kw.get("cond_factor") is None else np.full(len(kw["rows"]), kw["cond_factor"]),
                 deltas={}) for kw in kws]
    solve_merged(full)
    stacks = V._STACKED[0]
    assert len(stacks[1]) == 3 and len(stacks[2].comps) == 3
    sub = [full[2], full[1]]                  # two of its pairs, in another order
    got = solve_merged(sub)
    assert V._STACKED == [stacks]             # reused, nothing new kept
    V._STACKED.clear()
    fresh = solve_merged(sub)
    assert len(V._STACKED) == 1 and len(V._STACKED[0][2].comps) == 2
    for x, y in zip(got, fresh):
        pd.testing.assert_frame_equal(x.frame(), y.frame(), check_exact=True)
    # a pair not stacked yet: stacks of its own, the newest first, at most STACKED_KEPT kept
    for i in range(V.STACKED_KEPT + 1):
        comp = dataclasses.replace(plant.comp_LS, eta_is=tuple(c * (1.0 + 1e-3 * (i + 1))
                                                               for c in plant.comp_LS.eta_is))
        solve_merged([dict(full[0], params=plant.replace(comp_LS=comp)), full[0]])
        assert V._STACKED[0][2].comps[0] is comp
    assert len(V._STACKED) == V.STACKED_KEPT


def test_lockstep_results_in_order_exceptions_in_place_and_bounded(plant):
    df = grid(full=False).iloc[:6]
    seen = []

    def ok(sp):
        return lambda: [float(np.nanmean(solve_many(df, plant, p_m_sp=sp, ls_mode="float").frame()["p_m_bar"]))
                        for _ in range(3)]

    def bad():
        solve_many(df, plant, p_m_sp=8.0)
        raise RuntimeError("window 2 broke")

    t = threading.Thread(target=lambda: seen.append(lockstep.run([ok(10.0), bad, ok(14.0)])))
    t.start()
    t.join(timeout=120)
    assert not t.is_alive()
    out = seen[0]
    assert isinstance(out[1], lockstep.Failed) and str(out[1].exc) == "window 2 broke"
    assert out[0][0] < out[2][0]                 # in order: 10 bar(g) below 14 bar(g)
    again = lockstep.run([ok(10.0), bad, ok(14.0)])
    assert again[0] == out[0] and again[2] == out[2]
    # outside run, solve_many answers itself
    assert lockstep.request({}) is None


def test_a_bad_call_in_a_round_gets_its_own_error(plant):
    df = grid(full=False).iloc[:4]

    def bad():
        return solve_many(df, plant, deltas={"HS_vol": np.zeros((4, 6))})

    out = lockstep.run([lambda: solve_many(df, plant).frame(), bad])
    assert isinstance(out[1], lockstep.Failed)
    assert str(out[1].exc) == "deltas['HS_vol']: the HS compressor has no learned curves (Compressor)"
    assert out[0]["status"].notna().all()


# ---- the replay in lockstep -------------------------------------------------------------------------
LOCKSTEP_REPLAY_REL = 1e-6     # a replay's window figures in lockstep against window by window


@pytest.fixture(scope="module")
def day():
    from simulator.export import export_history
    return export_history(1.0, seed=5).history


def test_replay_in_lockstep_agrees_with_window_by_window(plant, day):
    """Windows analysed 4 at a time (two chunks and a rest) against one at a time (the gateway's
    order): the same statuses and decisions, the figures within LOCKSTEP_REPLAY_REL."""
    from model.analysis.replay import ReplaySettings, replay
    one = replay(day, plant, ReplaySettings.from_config(plant.extra, surrogate=False, lockstep_windows=1))
    four = replay(day, plant, ReplaySettings.from_config(plant.extra, surrogate=False, lockstep_windows=4))
    a, b = one.windows, four.windows
    assert len(a) >= 9 and (a["status"] == "ok").sum() >= 8
    assert (a["optimization_ok"].astype(bool)).sum() >= 8
    compared = 0
    for c in a.columns:
        x, y = a[c], b[c]
        if x.dtype.kind == "f":
            xv, yv = x.to_numpy(), y.to_numpy()
            assert (np.isnan(xv) == np.isnan(yv)).all(), c
            f = np.isfinite(xv)
            assert np.all(np.abs(xv[f] - yv[f]) <= LOCKSTEP_REPLAY_REL * np.maximum(np.abs(xv[f]), 1.0)), c
            compared += int(f.sum())
        else:
            assert (x.astype(str) == y.astype(str)).all(), c
    assert compared > 200


@pytest.mark.parametrize("value", [0, -3, 2.5, True, 257, "16"])
def test_lockstep_windows_setting_is_checked(plant, value):
    from model.analysis.replay import ReplayError, ReplaySettings
    extra = dict(plant.extra, calibration={**(plant.extra.get("calibration") or {}),
                                           "replay": {"lockstep_windows": value}})
    with pytest.raises(ReplayError) as e:
        ReplaySettings.from_config(extra)
    assert str(e.value) == f"replay setting lockstep_windows must be a whole number 1..256, got {value!r}"
    # built in code, not from plant.yaml: the same check
    with pytest.raises(ReplayError) as e:
        ReplaySettings(lockstep_windows=value)
    assert str(e.value) == f"replay setting lockstep_windows must be a whole number 1..256, got {value!r}"
