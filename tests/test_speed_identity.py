"""The replay's faster paths give the same numbers to the bit as the plain ones they replace
(issue #12): rows as input columns instead of a DataFrame, a point's solver result taken when
first read, the trusted stretch's distances and the search's shape scores for many points in one
call, the forecast's phi for many k at once, the sample usability without a Python loop."""
from __future__ import annotations

import dataclasses
import math
import pickle
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from model.analysis.advice import AdviceSettings, _distances, _operating_points, _scorer, _shape_at, _shape_many
from model.analysis.compressors import CompressorLearner, observe
from model.analysis.forecast import phi, phi_many
from model.batch import INPUT_COLUMNS, InputColumns, matrix
from model.measured import RAMP_REL_PER_MIN, SETTLE_MIN, process
from model.optimize import Evaluator, representative
from model.vcycle import solve_many, take_rows


@pytest.fixture(scope="module")
def learned(plant):
    """Half a day of the simulator at 16 then 13 bar(g), its usable samples, a learner on them and
    an evaluator of 8 representative rows at 12 set points (some outside the covered region)."""
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    cfg = load_simulator_config()
    cfg = replace(cfg, control=replace(cfg.control, p_m_sp_schedule=((0.0, 16.0), (0.25, 13.0))))
    hist = export_history(0.5, cfg=cfg).history
    use = process(hist, plant)["usable"].to_numpy()
    data = hist.loc[use].reset_index(drop=True)
    learner = CompressorLearner(plant)
    learner.update(observe(data.assign(timestamp=pd.to_datetime(data["timestamp"], utc=True)), plant))
    rows, w = representative(data[list(INPUT_COLUMNS)].astype(float), 8)
    ev = Evaluator(rows, w, plant)
    pts = ev.at_many([None, *np.arange(8.0, 20.0, 1.0)])
    return data, learner, ev, pts


def test_rows_as_input_columns_solve_as_the_dataframe(learned, plant):
    data, *_ = learned
    rows = data[list(INPUT_COLUMNS)].iloc[::7].reset_index(drop=True)
    sp = np.linspace(9.0, 18.0, len(rows))
    a = solve_many(rows, plant, p_m_sp=sp).frame()
    b = solve_many(InputColumns.of(rows), plant, p_m_sp=sp).frame()
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    assert np.array_equal(matrix(rows), matrix(InputColumns.of(rows)), equal_nan=True)


def test_a_points_solver_result_is_its_rows_of_the_call_and_pickles_alone(learned):
    _, _, ev, pts = learned
    n = len(ev.rows)
    p = pts[3]
    assert type(p._vres) is tuple                # not taken yet
    whole, a, b = p._vres
    assert (a, b) == (3 * n, 4 * n) and len(whole) == len(pts) * n
    expected = take_rows(whole, np.arange(a, b))
    got = p.vres
    assert len(got) == n
    for k, v in expected.values.items():
        assert np.array_equal(v, got.values[k], equal_nan=True), k
    q = pickle.loads(pickle.dumps(pts[5]))
    assert len(q.vres) == n and len(q.vres.status) == n


def test_a_points_columns_are_its_rows_of_the_calls_columns(learned):
    """A point of a call over several set points reads its columns when first asked
    (``PartColumns``): each is the call's ``VResult.columns`` for its rows; the mapping pickles as
    the plain dict of all of them, and an unknown column is a KeyError."""
    from model.optimize import COLUMNS, PartColumns
    _, _, ev, pts = learned
    n = len(ev.rows)
    p = pts[3]
    assert isinstance(p.cols, PartColumns)
    if type(p._vres) is tuple:                   # (another test may have taken its rows already)
        assert p._vres[1:] == (3 * n, 4 * n)
    own = p.vres.columns(COLUMNS)                # the call's result's rows of this point
    assert list(p.cols) == [*COLUMNS, "status", "reason"] and len(p.cols) == len(COLUMNS) + 2
    for c in (*COLUMNS, "status", "reason"):
        assert len(p.cols[c]) == n
        assert np.array_equal(p.cols[c], own[c], equal_nan=c not in ("status", "reason")), c
        assert p.cols[c].dtype == own[c].dtype
    back = pickle.loads(pickle.dumps(p.cols))
    assert type(back) is dict and list(back) == list(p.cols)
    with pytest.raises(KeyError):
        p.cols["no such column"]


def test_weighted_mean_is_np_average_to_the_bit_and_status_in_is_among(learned):
    """The trusted stretch's p_m of a point (``weighted_mean``) is ``np.average``'s number, NaN and
    the zero-weight error included; a point's solved-rows test over its call's rows once
    (``status_in``) is ``among`` of its own status."""
    from model.batch import among
    from model.optimize import SOLVED, weighted_mean
    rng = np.random.default_rng(11)
    for n in (1, 2, 7, 8, 40, 129):
        for _ in range(20):
            a = rng.normal(10.0, 3.0, n) * 10.0 ** rng.integers(-3, 4)
            w = rng.integers(1, 30, n).astype(float)
            assert weighted_mean(a, w) == float(np.average(a, weights=w))
    a[0] = np.nan
    assert math.isnan(weighted_mean(a, w))
    with pytest.raises(ZeroDivisionError, match="^Weights sum to zero, can't be normalized$"):
        weighted_mean(np.ones(3), np.zeros(3))
    assert weighted_mean(np.arange(4), np.ones(4)) == 1.5            # not float64: numpy's own path
    _, _, ev, pts = learned
    for p in pts:
        for choices in (SOLVED, ("ok",), ("ls_speed_high", "ls_speed_low")):
            assert np.array_equal(p.status_in(choices), among(p.col("status"), choices))


def test_distances_and_shape_scores_of_many_points_equal_point_by_point(learned, plant):
    _, learner, ev, pts = learned
    offsets = {"LS": (0.01, -0.02), "HS": (0.0, 0.01)}
    ok = [p for p in pts if p.ok]
    assert len(ok) >= 8
    # point by point, as trusted_stretch used to compute them
    one = []
    for p in ok:
        op = _operating_points(p, plant)
        d = 0.0
        for st in ("LS", "HS"):
            if learner.learned(st, "eta_is"):
                pi, n = op[st]
                d_pi, d_n = offsets[st]
                d = max(d, float(np.max(learner.coverage_distance(st, pi - d_pi, n - d_n))))
        one.append(d)
    many = _distances(learner, plant, offsets, ok)
    assert many == one                           # exactly
    assert min(one) <= 1.0 < max(one)            # within the margin and beyond it
    s = AdviceSettings()
    assert s.shape_k and s.search_k

    def shape_one(p):                            # _shape_at as it was written for one point
        if not p.ok:
            return 0.0
        op = _operating_points(p, plant)
        W = {st: p.col(f"W_{st}_kW") for st in ("LS", "HS")}
        tot = W["LS"] + W["HS"]
        var = np.zeros(len(tot))
        for st in ("LS", "HS"):
            if learner.learned(st, "eta_is"):
                pi, n = op[st]
                u = s.shape_k * learner.shape_sd(st, pi - offsets[st][0], n - offsets[st][1])
                var += (W[st] / tot * u / p.col(f"eta_is_{st}")) ** 2
        return float(100.0 * np.mean(np.sqrt(var)))
    shapes = _shape_many(learner, plant, offsets, s, pts)
    assert shapes == [shape_one(p) for p in pts]
    assert shapes == [_shape_at(learner, plant, offsets, s, p) for p in pts]
    assert len(set(shapes)) > 3
    score = _scorer(learner, plant, offsets, s)
    assert score.many(ok) == [score(p) for p in ok]
    assert _shape_many(None, plant, offsets, s, pts) == [0.0] * len(pts)


def test_phi_of_many_k_is_phi_of_each():
    t = np.array([0.0, 0.1, 1.0, 3.7, 20.0, 140.0])
    ks = np.concatenate([[0.0], np.geomspace(1e-5, 5.0, 40)])
    P = phi_many(t, ks)
    assert P.tobytes() == np.stack([phi(t, k) for k in ks]).tobytes()
    rng = np.random.default_rng(4)
    t = np.sort(rng.uniform(0.0, 200.0, 301))
    for ks in (rng.uniform(0.0, 3.0, 61), np.array([0.0]), np.array([0.7]), np.array([0.2, 0.0, 1e-9, 0.0])):
        assert phi_many(t, ks).tobytes() == np.stack([phi(t, k) for k in ks]).tobytes()


def _usable_reasons_by_loop(h: pd.DataFrame, on: np.ndarray, cip: np.ndarray, W: np.ndarray,
                            reason: np.ndarray, physical: np.ndarray) -> np.ndarray:
    """The reasons as ``process`` assigned them sample by sample before (the reference)."""
    n = len(h)
    ramp = np.zeros(n, dtype=bool)
    since = SETTLE_MIN
    for i in range(n):
        since = since + 1 if (on[i] and cip[i] < 0.5) else 0
        ramp[i] = since <= SETTLE_MIN
    with np.errstate(divide="ignore", invalid="ignore"):
        dW = np.abs(np.diff(W, prepend=np.nan)) / W
    ramp |= np.nan_to_num(dW, nan=0.0) > RAMP_REL_PER_MIN
    out = np.full(n, "", dtype=object)
    for i in range(n):
        if cip[i] > 0.5:
            out[i] = "cip"
        elif not on[i]:
            out[i] = "off"
        elif reason[i]:
            out[i] = reason[i]
        elif physical[i]:
            out[i] = physical[i]
        elif ramp[i]:
            out[i] = "ramping"
    return out


@pytest.mark.parametrize("start_running", [True, False])
def test_sample_usability_equals_the_sample_by_sample_rules(learned, plant, start_running):
    """Starts, stops, CIP flags (and a NaN one), missing and out-of-range values: the same reason
    for every sample as the rules applied one sample after the other."""
    data, *_ = learned
    h = data.iloc[:600].copy().reset_index(drop=True)
    rng = np.random.default_rng(3)
    for a in rng.integers(0, 580, 8):
        h.loc[a:a + rng.integers(1, 15), "running"] = 0
    h.loc[rng.integers(0, 600, 6), "cip"] = 1
    h.loc[int(rng.integers(0, 600)), "cip"] = np.nan
    h.loc[rng.integers(0, 600, 4), "T_sink_in"] = np.nan
    h.loc[rng.integers(0, 600, 4), "T_sink_out"] = 500.0
    h.loc[0, "running"] = 1 if start_running else 0
    got = process(h, plant)
    on = (pd.to_numeric(h["running"]).to_numpy() > 0.5) & (np.nan_to_num(
        h["W_LS"].to_numpy(float) + h["W_HS"].to_numpy(float)) > 20.0)
    cip = pd.to_numeric(h["cip"]).to_numpy(float)
    W = h["W_LS"].to_numpy(float) + h["W_HS"].to_numpy(float)
    # the range and physical reasons are what process found (their own code is unchanged): take
    # them from rows where they are the reason, and check the order of the rules around them
    from model.measured import DEFAULT_RANGES, _range_reasons
    rng_reason = _range_reasons(h, DEFAULT_RANGES).to_numpy(dtype=object)
    phys = np.where(~(h["T_sink_out"].to_numpy(float) > h["T_sink_in"].to_numpy(float)),
                    "inconsistent: sink not heated", "").astype(object)
    expected = _usable_reasons_by_loop(h, on, cip, W, rng_reason, phys)
    assert list(got["reason"]) == list(expected)
    assert set(got["reason"]) >= {"", "off", "cip", "ramping"}
    assert math.isclose(got["usable"].mean(), np.mean(expected == ""))


def test_a_replay_holds_blas_to_one_thread_and_gives_it_back(monkeypatch):
    """model.analysis.replay.one_blas_thread (threadpoolctl, the fast extra, which make test
    installs); without threadpoolctl it changes nothing and says nothing."""
    import sys
    import threadpoolctl
    from model.analysis.replay import one_blas_thread
    before = [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]
    assert before                                     # numpy's BLAS is loaded
    with one_blas_thread():
        assert [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"] \
            == [1] * len(before)
    assert [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"] == before
    monkeypatch.setitem(sys.modules, "threadpoolctl", None)      # not installed
    with one_blas_thread():
        assert [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"] \
            == before


def test_the_measured_side_of_a_block_of_windows_is_each_windows_own(learned, plant, monkeypatch):
    """A replay's pass 1 computes the measured side (derived, with the stage states the compressor
    observations ask for again) of 32 windows in one call and hands each window its rows: the same
    frames to the bit as the window's own call, and no stage state computed twice."""
    import model.analysis.compressors as C
    from model.measured import derived
    data, *_ = learned
    data = data.assign(timestamp=pd.to_datetime(data["timestamp"], utc=True))
    cuts = [(0, 100), (100, 220), (220, 260)]
    block = data.iloc[: cuts[-1][1]]
    with C.recorded_stages() as records:
        der_all = derived(block, plant)
    assert len(records) == 2                      # the LS and the HS stage
    real = C._stage_arrays
    calls = []
    monkeypatch.setattr(C, "_stage_arrays", lambda *a: calls.append(1) or real(*a))
    for a, b in cuts:
        win = data.iloc[a:b].reset_index(drop=True)
        with C.shared_stages():
            der_own = derived(win, plant)
            obs_own = observe(win, plant)
        n_own = len(calls)
        with C.shared_stages():
            C.preset_stages(records, slice(a, b))
            obs_pre = observe(win, plant)
        assert len(calls) == n_own                # answered from the block's states
        pd.testing.assert_frame_equal(der_all.iloc[a:b].reset_index(drop=True), der_own, check_exact=True)
        pd.testing.assert_frame_equal(obs_pre, obs_own, check_exact=True)
    # outside recorded_stages nothing is kept; preset only fills this context's memo
    with C.shared_stages():
        derived(block.iloc[:10], plant)
        assert getattr(C._shared, "record", None) is None


def test_plant_params_replace_is_dataclasses_replace(plant):
    import dataclasses
    q = plant.replace(R_th_f=1.5e-4, CF_DSH=1.1, comp_LS=plant.comp_LS.replace(N_max=3100.0))
    r = dataclasses.replace(plant, R_th_f=1.5e-4, CF_DSH=1.1, comp_LS=plant.comp_LS.replace(N_max=3100.0))
    assert q == r and q.__dict__ == r.__dict__ and hash(q) == hash(r) and type(q) is type(r)
    assert plant.R_th_f != 1.5e-4                 # the original untouched
    assert pickle.loads(pickle.dumps(q)) == q
    with pytest.raises(dataclasses.FrozenInstanceError):
        q.R_th_f = 0.0
    with pytest.raises(TypeError, match=r"^PlantParams.replace: unknown field\(s\) 'R_thf', 'x'$"):
        plant.replace(R_thf=1.0, x=2)


def test_a_results_frame_is_the_plain_dict_frame_in_one_block(learned, plant):
    """``columns_frame`` puts the float columns in as one block: the frame equals the one pandas
    builds from the dict (values, dtypes, order, index) and keeps its layout (one float block of
    columns x rows, C order), so that reductions over it add in the same order."""
    from model.vcycle import columns_frame
    data, *_ = learned
    rows = data[list(INPUT_COLUMNS)].iloc[::5].reset_index(drop=True)
    cols = solve_many(rows, plant, p_m_sp=np.linspace(9.0, 18.0, len(rows))).columns()
    index = pd.RangeIndex(3, 3 + len(rows))
    plain = pd.DataFrame({k: v for k, v in cols.items() if k not in ("status", "reason")}, index=index)
    plain["status"], plain["reason"] = cols["status"], cols["reason"]
    got = columns_frame(cols, index)
    pd.testing.assert_frame_equal(got, plain, check_exact=True)
    fb = [b for b in got._mgr.blocks if b.dtype == np.float64]
    pb = [b for b in plain._mgr.blocks if b.dtype == np.float64]
    assert len(fb) == len(pb) == 1
    assert fb[0].values.shape == pb[0].values.shape == (len(cols) - 2, len(rows))
    assert fb[0].values.flags["C_CONTIGUOUS"] and pb[0].values.flags["C_CONTIGUOUS"]
    empty = columns_frame({k: v[:0] for k, v in cols.items()}, pd.RangeIndex(0))
    assert list(empty.columns) == list(plain.columns) and len(empty) == 0
    short = dict(cols, COP=cols["COP"][:1])
    with pytest.raises(ValueError, match=rf"^column 'COP' has shape \(1,\), the index {len(rows)} rows$"):
        columns_frame(short, index)


def test_simulate_many_answers_input_columns_as_their_dataframe(learned, plant, monkeypatch):
    """The window's model figures and condenser factor hand ``simulate_many`` their rows as input
    columns: the same frame as from the DataFrame (with a RangeIndex), on the vectorised path with
    per-row R_th,f and a seed at other rows, and on the scalar path."""
    import model.batch as batch
    from model.batch import simulate_many
    data, *_ = learned
    rows = data[list(INPUT_COLUMNS)].iloc[::9].reset_index(drop=True)
    R = np.linspace(0.0, 2e-6, len(rows))
    a, va = simulate_many(rows, plant, R_th_f=R, with_result=True)
    b, vb = simulate_many(InputColumns.of(rows), plant, R_th_f=R, with_result=True)
    pd.testing.assert_frame_equal(a, b, check_exact=True)
    other = data[list(INPUT_COLUMNS)].iloc[3::11].reset_index(drop=True)
    c = simulate_many(other, plant, seed=va, seed_rows=rows)
    d = simulate_many(InputColumns.of(other), plant, seed=va, seed_rows=rows)
    pd.testing.assert_frame_equal(c, d, check_exact=True)
    monkeypatch.setattr(batch, "VECTORISED", False)
    e = simulate_many(rows.iloc[:3], plant, R_th_f=R[:3])
    f = simulate_many(InputColumns.of(rows.iloc[:3]), plant, R_th_f=R[:3])
    pd.testing.assert_frame_equal(e, f, check_exact=True)
    assert list(f.index) == [0, 1, 2] and f["status"].tolist() == e["status"].tolist()


def test_simulate_many_as_columns_is_its_frame_as_arrays(learned, plant, monkeypatch):
    """The condenser factor's trials and the window's model figures read ``simulate_many``'s
    answer as arrays (``as_columns``): every asked column of the frame as floats (NaN where a row
    is not solved), status and reason, the same numbers, on the vectorised and the scalar path."""
    import model.batch as batch
    from model.batch import simulate_many, solved_mask
    data, *_ = learned
    rows = data[list(INPUT_COLUMNS)].iloc[::9].reset_index(drop=True)
    rows.loc[2, "T_source_out"] = rows.loc[2, "T_source_in"] + 1.0      # a row the model refuses
    R = np.linspace(0.0, 2e-6, len(rows))
    cols = ("p_c_bar", "COP", "Q_sink_kW")
    for vec in (True, False):
        monkeypatch.setattr(batch, "VECTORISED", vec)
        part = rows if vec else rows.iloc[:4]
        f, vf = simulate_many(part, plant, columns=cols, R_th_f=R[:len(part)], with_result=True)
        c, vc = simulate_many(InputColumns.of(part), plant, columns=cols, R_th_f=R[:len(part)],
                              with_result=True, as_columns=True)
        assert list(c) == [*cols, "status", "reason"]
        for k in cols:
            assert c[k].dtype == np.float64
            np.testing.assert_array_equal(c[k], f[k].to_numpy(dtype=float))
        assert c["status"].tolist() == f["status"].tolist()
        assert c["reason"].tolist() == f["reason"].tolist()
        np.testing.assert_array_equal(solved_mask(c), solved_mask(f))
        assert not solved_mask(c)[2] and solved_mask(c).sum() == len(part) - 1
        assert (vc is None) == (vf is None) == (not vec)


def test_the_windows_sample_columns_make_the_frame_pd_concat_makes():
    """Replay puts the windows' sample columns (``chain._window_samples``: arrays, one text) into
    one frame: the frame ``pd.concat`` of a frame per window gave, to the bit, dtypes and column
    order included (a window without the model series: NaN there)."""
    from model.analysis.replay import frame_of_parts
    rng = np.random.default_rng(3)
    t0 = pd.Timestamp("2026-01-01T00:00:00Z")
    parts = []
    for i, n in enumerate((5, 3, 4)):
        ts = pd.DatetimeIndex([t0 + pd.Timedelta(minutes=10 * i + k) for k in range(n)])
        p = {"timestamp": pd.Series(ts).array, "window_start": ts[0].isoformat()}
        if i != 1:
            p["COP_fixed"] = rng.normal(4.0, 0.1, n)
            p["COP_fixed"][0] = np.nan
        p["eta_is_LS_model"] = rng.normal(0.7, 0.01, n)
        parts.append(p)
    expected = pd.concat([pd.DataFrame(p, index=pd.RangeIndex(len(p["timestamp"]))) for p in parts],
                         ignore_index=True)
    got = frame_of_parts(parts)
    pd.testing.assert_frame_equal(got, expected, check_exact=True)
    assert all(p == {} for p in parts)                    # consumed: a year's arrays not held twice
    assert list(got.columns) == ["timestamp", "window_start", "COP_fixed", "eta_is_LS_model"]
    assert str(got["timestamp"].dtype).startswith("datetime64[") and got["timestamp"].dt.tz is not None
    assert got["COP_fixed"].isna().tolist() == [True] + [False] * 4 + [True] * 3 + [True, False, False, False]


def test_the_advice_given_its_check_rows_is_the_advice_computing_them(learned, plant):
    """The chain computes a window's check rows and representative points once (``check_rows``)
    for the surrogate tracker and the advice: the draft is the one the advice computes alone."""
    from model.analysis.advice import check_rows, draft_advice
    data, learner, _, _ = learned
    adaptive = learner.apply(plant)
    s = AdviceSettings()
    c = check_rows(data, s)
    assert len(c.data) == s.check_rows and len(c.rows) == s.representative_points
    assert c.actual == float(pd.to_numeric(data["p_m_sp"]).mean())
    a = draft_advice(data, adaptive, learner, s)
    b = draft_advice(data, adaptive, learner, s, checked=c)
    for k in ("actual", "lo", "hi", "sp_opt", "COP_opt_rep", "score_opt_rep", "sd_opt", "gm", "dcop_step",
              "reasons", "hs_saturated_opt"):
        assert getattr(a, k) == getattr(b, k) or (getattr(a, k) != getattr(a, k) and getattr(b, k) != getattr(b, k)), k
    pd.testing.assert_frame_equal(a.rows, b.rows, check_exact=True)
    assert repr(a.trusted) == repr(b.trusted) and np.array_equal(a.w, b.w)     # (the path holds NaN)
    # the groups and representative points from the caller's matrix of the rows: the same
    from model.optimize import groups
    X = matrix(c.data)
    assert all(np.array_equal(g, h) for g, h in zip(groups(c.data, 8), groups(c.data, 8, X=X), strict=True))
    r1, w1 = representative(c.data, 8)
    r2, w2 = representative(c.data, 8, groups(c.data, 8, X=X), X=X)
    pd.testing.assert_frame_equal(r1, r2, check_exact=True)
    assert np.array_equal(w1, w2)


SOLVER_REL = 1e-8       # the vectorised solver's answers from other warm starts agree to this (relative)
SOLVER_SP_BAR = 1e-6    # ... and the set points the searches find from them to this [bar]


def _count_solver_calls(monkeypatch) -> list:
    """A one-element list counting the calls of the vectorised solver (``vcycle.solve_many``) from
    now on in this test."""
    import model.vcycle as vcycle
    calls = [0]
    solve = vcycle.solve_many

    def counted(*a, **k):
        calls[0] += 1
        return solve(*a, **k)
    monkeypatch.setattr(vcycle, "solve_many", counted)
    return calls


def test_the_trackers_search_beside_the_advices_is_each_alone_in_the_advices_solver_calls(
        learned, plant, monkeypatch):
    """A window that gives the surrogate tracker a row runs the tracker's search (the model optimum
    without the trusted region) beside the advice's own (``draft_advice``'s ``track``): its set
    points and the reference set point ride in the advice's solver calls (in a replay's lockstep,
    its rounds), and the advice and the tracker's row are what each gives alone, after the other."""
    from model.analysis.advice import draft_advice
    from model.analysis.surrogate_tracker import optimum_row
    data, learner, _, _ = learned
    adaptive = learner.apply(plant)
    s = AdviceSettings()
    calls = _count_solver_calls(monkeypatch)

    def n_calls(f):
        c0 = calls[0]
        out = f()
        return out, calls[0] - c0
    a, n_a = n_calls(lambda: draft_advice(data, adaptive, learner, s))
    row_a, n_t = n_calls(lambda: optimum_row(a.rows, a.w, adaptive, 10.0, 0.0, ev=a.ev, bounds=(a.lo, a.hi)))
    b, n_b = n_calls(lambda: draft_advice(data, adaptive, learner, s, track=10.0))
    row_b, n_r = n_calls(lambda: optimum_row(b.rows, b.w, adaptive, 10.0, 0.0, ev=b.ev, bounds=(b.lo, b.hi),
                                             searched=b.tracked))
    assert a.trusted is not None                    # the advice's search has a trusted region to keep to
    assert n_t == 3 and n_b == n_a and n_r == 0     # alone: 3 calls of its own; beside: none
    assert abs(a.sp_opt - b.sp_opt) <= SOLVER_SP_BAR and a.reasons == b.reasons
    for k in ("COP_opt_rep", "score_opt_rep", "sd_opt", "dcop_step"):
        assert math.isclose(getattr(a, k), getattr(b, k), rel_tol=SOLVER_REL), k
    assert row_a is not None and row_b is not None and row_a.keys() == row_b.keys()
    assert abs(row_a["p_m_opt_bar_a"] - row_b["p_m_opt_bar_a"]) <= SOLVER_SP_BAR
    for k, v in row_a.items():
        assert math.isclose(v, row_b[k], rel_tol=SOLVER_REL, abs_tol=1e-12), k
    # the tracker's search result stays in the process: a pickled draft leaves it out
    assert b.tracked is not None and pickle.loads(pickle.dumps(b)).tracked is None


def test_searches_beside_each_other_are_each_alone_and_keep_their_beyond(learned, plant, monkeypatch):
    """``optimize.searches``: two searches on one evaluator (one kept to a stretch of set points, one
    not) and an extra set point in no more solver calls than the longer one alone; each answer (set
    point, COP, the beyond-check) is the one it gives alone on an evaluator of its own."""
    from model.optimize import search, searches
    _, _, ev0, _ = learned
    rows, w = ev0.rows, ev0.w
    lo, hi = 8.0, 19.0
    calls = _count_solver_calls(monkeypatch)

    def fresh():
        e = Evaluator(rows, w, plant)
        e.at_many([None, 13.0])
        return e

    def feasible(p):             # a stretch below the free optimum: the optimum is beyond it
        return p.sp is not None and p.sp <= 11.0
    specs = [(feasible, None), (None, None)]
    alone, n_alone = [], []
    for f, sc in specs:
        e = fresh()
        c0 = calls[0]
        alone.append(search(e, lo, hi, feasible=f, score=sc))
        n_alone.append(calls[0] - c0)
    e = fresh()
    c0 = calls[0]
    both = searches(e, lo, hi, specs, extra=[10.0])
    assert calls[0] - c0 <= max(n_alone) < sum(n_alone) and 10.0 in e._cache
    for (sp_a, p_a), (sp_b, p_b) in zip(alone, both):
        assert abs(sp_a - sp_b) <= SOLVER_SP_BAR
        assert math.isclose(p_a.COP, p_b.COP, rel_tol=SOLVER_REL)
    assert alone[1][0] > 11.0 + 0.1                 # the free optimum lies above the stretch ...
    assert alone[0][1].beyond is not None and both[0][1].beyond == alone[0][1].beyond   # ... so beyond
    # no candidate at all: the search's OptimizationError is its result, the other one goes on
    none = searches(fresh(), lo, hi, [(lambda p: False, None), (None, None)])
    assert str(none[0]) == ("no set point in the range solves every sample of the window within "
                            "the trusted region")
    assert abs(none[1][0] - alone[1][0]) <= SOLVER_SP_BAR


def test_searches_on_the_scalar_path_are_the_searches_one_after_the_other(learned, plant, monkeypatch):
    """Without the vectorised solver ``searches`` runs each search alone, in order, and hands back
    a search's exception as its result, as the vectorised path does."""
    import model.batch as batch
    from model.optimize import search, searches
    monkeypatch.setattr(batch, "VECTORISED", False)
    _, _, ev0, _ = learned
    rows, w = ev0.rows.iloc[:2], ev0.w[:2]

    def feasible(p):
        return p.sp is not None and p.sp <= 11.0
    a = Evaluator(rows, w, plant)
    a.at_many([10.0])
    sp_a, p_a = search(a, 8.0, 19.0, feasible=feasible)
    got = searches(Evaluator(rows, w, plant), 8.0, 19.0, [(feasible, None), (lambda p: False, None)],
                   extra=[10.0])
    assert got[0][0] == sp_a and got[0][1].COP == p_a.COP
    assert str(got[1]) == ("no set point in the range solves every sample of the window within "
                           "the trusted region")


def test_the_bins_stacked_statistics_are_the_bin_by_bin_ones():
    """The local fits' per-bin statistics live in two stacked arrays, so that a decay is one
    multiplication: after adds and decays (more bins than the first allocation) every bin's
    numbers, ``arrays()`` and ``to_dict()`` are those of one pair of arrays per bin (the plain
    form, written out here), a copy is independent, and the document round-trips."""
    from model.analysis.compressors import _BinStats, _zbasis
    rng = np.random.default_rng(5)
    A_ref, b_ref = {}, {}
    st = _BinStats(0.2, 0.05)
    for step in range(12):
        pi = rng.uniform(1.5, 6.5, 40)
        n = rng.uniform(0.3, 1.0, 40)
        X, y = _zbasis(pi, n), rng.normal(0.7, 0.02, 40)
        f = 0.5 ** rng.uniform(0.0, 0.3)
        for k in A_ref:                                   # the plain form: bin by bin
            A_ref[k] *= f
            b_ref[k] *= f
        st.decay(f)
        keys = list(zip(np.floor(pi / 0.2).astype(int).tolist(), np.floor(n / 0.05).astype(int).tolist()))
        for key in set(keys):
            m = np.array([k == key for k in keys])
            if key not in A_ref:
                A_ref[key], b_ref[key] = np.zeros((6, 6)), np.zeros(6)
            A_ref[key] += X[m].T @ X[m]
            b_ref[key] += X[m].T @ y[m]
        st.add(pi, n, X, y)
    assert len(A_ref) > 16                                # the arrays grew past their first size
    assert st.A.keys() == A_ref.keys()
    for k in A_ref:
        assert np.array_equal(st.A[k], A_ref[k]) and np.array_equal(st.b[k], b_ref[k])
    c, As, bs = st.arrays()
    keys = sorted(A_ref)
    assert np.array_equal(As, np.array([A_ref[k] for k in keys])) and np.array_equal(bs, np.array([b_ref[k] for k in keys]))
    assert np.array_equal(c, np.array([((a + 0.5) * 0.2, (b + 0.5) * 0.05) for a, b in keys]))
    iu = np.triu_indices(6)
    assert st.to_dict() == {"bins": [[a, b, A_ref[(a, b)][iu].tolist(), b_ref[(a, b)].tolist()] for a, b in keys]}
    back = _BinStats.from_dict(st.to_dict(), 0.2, 0.05)
    assert back.to_dict() == st.to_dict()
    cp = st.copy()
    assert len(cp._A) == len(A_ref) < len(st._A)          # the used rows only
    cp.add(np.array([9.9]), np.array([0.1]), _zbasis(np.array([9.9]), np.array([0.1])), np.array([0.7]))
    assert len(cp.A) == len(A_ref) + 1 and len(st.A) == len(A_ref)
    cp.decay(0.5)
    assert st.to_dict() != cp.to_dict() and st.to_dict() == back.to_dict()
    assert _BinStats(0.2, 0.05).arrays()[1].shape == (0, 6, 6)


def test_a_learner_snapshot_is_its_pickled_copy_and_later_updates_leave_it(learned, plant):
    """A replay's in-process window task takes a snapshot of the learner instead of a pickled copy:
    the same state to the bit (every statistic, bin, coverage weight, drive sum, the local curves),
    and the learner's next update changes the learner, not the snapshot."""
    data, _, _, _ = learned
    obs = observe(data.assign(timestamp=pd.to_datetime(data["timestamp"], utc=True)), plant)
    half = len(obs) // 2
    lrn = CompressorLearner(plant)
    lrn.update(obs.iloc[:half])
    lrn.apply(plant)                      # the local curves cached, as pass 1 may leave them
    snap, pickled = lrn.snapshot(), pickle.loads(pickle.dumps(lrn))
    lrn.update(obs.iloc[half:])
    assert snap.to_dict() == pickled.to_dict()
    assert lrn.to_dict() != snap.to_dict()          # the update reached the learner only
    for st in ("LS", "HS"):
        assert snap.drive_factor(st) == pickled.drive_factor(st)
        for c in ("eta_is", "eta_vol"):
            a, b = snap.local_curves(st, c), pickled.local_curves(st, c)
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_array_equal(a.coef, b.coef)
                np.testing.assert_array_equal(a.valid, b.valid)


def test_the_refit_for_correlated_residuals_reuses_the_fits_to_the_bit():
    """``fit_fouling`` refits with a larger overlap when the residuals are serially correlated;
    the least-squares fits do not depend on the overlap and are reused: the result equals a fit at
    that overlap from scratch (with and without a prior)."""
    from model.analysis.forecast import LawPrior, _fit_fouling, fit_fouling
    rng = np.random.default_rng(7)
    t = np.linspace(0.2, 30.0, 240)
    e = np.zeros(len(t))
    for i in range(1, len(t)):
        e[i] = 0.85 * e[i - 1] + rng.normal(0.0, 0.004)
    y = 0.02 + 0.25 * (1.0 - np.exp(-t / 9.0)) + e
    se = np.full(len(t), 0.01)
    for prior in (None, LawPrior(0.1, 0.03, 0.27, 0.05, 2)):
        fit = fit_fouling(t, y, se, prior=prior)
        assert fit.overlap > 1.0 and fit.extra["residual_rho"] > 2.0 / math.sqrt(len(t))   # refitted
        ref = _fit_fouling(t, y, se, overlap=fit.overlap, prior=prior)
        assert (fit.law, fit.reason, fit.a0, fit.r0, fit.k, fit.s2, fit.dof) == \
            (ref.law, ref.reason, ref.a0, ref.r0, ref.k, ref.s2, ref.dof)
        np.testing.assert_array_equal(fit.cov, ref.cov)


def test_numeric_and_floats_are_to_numeric_to_the_bit():
    """``batch.numeric`` (one block when every column is float64) and ``batch.floats`` give what
    ``pd.to_numeric(errors="coerce")`` gives: the same frame (dtypes, index, layout of the block)
    or array, a new one; other dtypes and a duplicated label take to_numeric's own path."""
    from model.batch import floats, numeric
    rng = np.random.default_rng(2)
    df = pd.DataFrame({c: rng.normal(size=9) for c in INPUT_COLUMNS}, index=pd.RangeIndex(3, 12))
    df["T_sink_in"] = np.nan
    cols = list(INPUT_COLUMNS)
    ref = df[cols].apply(pd.to_numeric, errors="coerce")
    got = numeric(df, cols)
    pd.testing.assert_frame_equal(got, ref, check_exact=True)
    assert got._mgr.nblocks == 1 and np.shares_memory(got.to_numpy(), got._mgr.blocks[0].values.T)
    mixed = df.assign(V_sink=["1.5", "x", 3, 4, 5, 6, 7, 8, 9], p_m_sp=np.arange(9))
    pd.testing.assert_frame_equal(numeric(mixed, cols), mixed[cols].apply(pd.to_numeric, errors="coerce"),
                                  check_exact=True)
    for c in ("V_source", "V_sink", "p_m_sp"):
        a = floats(mixed[c])
        np.testing.assert_array_equal(a, pd.to_numeric(mixed[c], errors="coerce").to_numpy(dtype=float))
        assert a.dtype == np.float64 and not np.shares_memory(a, mixed[c].to_numpy())
    dup = pd.concat([df[["V_source"]], df[["V_source"]]], axis=1)
    with pytest.raises(TypeError, match="arg must be a list, tuple, 1-d array, or Series"):
        floats(dup["V_source"])


def test_a_frame_of_the_input_columns_exactly_is_read_as_one_block_to_the_bit():
    """``matrix`` and ``InputColumns.of`` read a frame whose columns are the input columns exactly
    (the representative rows, a window's numeric inputs) with one ``to_numpy`` of the frame: the
    numbers, shape and memory order of the column-by-column reads (reductions add in the same
    order), in new arrays (not the frame's), whatever the frame's blocks; an integer column converts
    as alone; other frames take the column reads."""
    rng = np.random.default_rng(11)
    n = 53
    one = pd.DataFrame(rng.normal(10.0, 3.0, (n, len(INPUT_COLUMNS))), columns=list(INPUT_COLUMNS))
    mixed = pd.DataFrame({c: rng.normal(10.0, 3.0, n) for c in INPUT_COLUMNS}, index=np.arange(n) * 3)
    mixed["V_sink"] = rng.integers(100, 200, n)
    mixed.loc[mixed.index[4], "T_sink_in"] = np.nan
    wider = mixed.assign(extra=1.0)
    reordered = mixed[list(INPUT_COLUMNS)[::-1]]
    for df in (one, mixed, wider, reordered, one.iloc[:0]):
        ref = np.empty((len(INPUT_COLUMNS), len(df)))
        for i, c in enumerate(INPUT_COLUMNS):
            ref[i] = df[c].to_numpy(dtype=float)
        ref = ref.T
        got = matrix(df)
        assert got.shape == ref.shape and got.flags.f_contiguous and np.array_equal(got, ref, equal_nan=True)
        if len(df):
            assert np.array_equal(np.nanstd(got, axis=0), np.nanstd(ref, axis=0), equal_nan=True)
        assert np.array_equal(got.sum(axis=0), ref.sum(axis=0), equal_nan=True)
        assert not np.shares_memory(got, df.to_numpy())
        cols = InputColumns.of(df)
        assert list(cols.columns) == list(INPUT_COLUMNS)
        for c in INPUT_COLUMNS:
            a = cols[c]
            assert a.dtype == np.float64 and a.flags.c_contiguous
            assert np.array_equal(a, df[c].to_numpy(dtype=float), equal_nan=True)
            assert np.array_equal(np.cumsum(a), np.cumsum(df[c].to_numpy(dtype=float)), equal_nan=True)
    part = InputColumns.of(mixed[["p_m_sp", "V_source"]])
    assert list(part.columns) == ["V_source", "p_m_sp"]         # the columns it has, in INPUT_COLUMNS' order


def test_a_merged_results_parts_are_its_rows(learned, plant):
    """``vcycle.split_rows`` (a merged call's parts as copied slices) is ``take_rows`` of each
    part's positions: every field and state array equal, new arrays."""
    from model.vcycle import split_rows
    _, _, ev, _ = learned
    whole = solve_many(ev._input_columns().take(np.tile(np.arange(len(ev.rows)), 3)), plant,
                       p_m_sp=np.repeat([14.0, 15.0, 16.5], len(ev.rows)))
    n = len(ev.rows)
    starts, ends = np.array([0, n, 2 * n - 3]), np.array([n, 2 * n - 3, 3 * n])
    for part, a, b in zip(split_rows(whole, starts, ends), starts, ends):
        ref = take_rows(whole, np.arange(a, b))
        for f in ("status", "reason", "branch", "fallback", "warm", "cold"):
            np.testing.assert_array_equal(getattr(part, f), getattr(ref, f))
        for d in ("values", "state"):
            x, y = getattr(part, d), getattr(ref, d)
            assert list(x) == list(y)
            for k in x:
                np.testing.assert_array_equal(x[k], y[k])
                if isinstance(x[k], np.ndarray) and x[k].ndim:
                    assert not np.shares_memory(x[k], getattr(whole, d)[k])
        assert part.timings == ref.timings


@pytest.mark.parametrize("chunk", [65536, 1, 7, 64])
def test_a_replay_files_csv_is_pandas_to_csv_to_the_byte(tmp_path, monkeypatch, chunk):
    """``replaydir.frame_to_csv`` formats the float columns itself, ``chunk`` rows at a time; the
    file is what ``to_csv(index=False, float_format="%.10g")`` writes, byte for byte, for every kind
    of column a replay's tables hold and the awkward values: NaN, infinities, -0.0, float32, 17
    digits, text that needs quoting, missing text, booleans, integers, times with a zone, a repeated
    name; and columns pandas formats by all their values (times without a zone that are all
    midnights but in a few rows, fractions of a second in one row, durations, missing times)."""
    import edge.replaydir as rd
    from edge.replaydir import frame_to_csv
    monkeypatch.setattr(rd, "CSV_CHUNK_ROWS", chunk)
    rng = np.random.default_rng(7)
    x = rng.standard_normal(200) * 10.0 ** rng.integers(-12, 12, 200)
    x[[3, 17]] = np.nan
    x[[5, 6, 7]] = [np.inf, -np.inf, -0.0]
    frame = pd.DataFrame({
        "t": pd.date_range("2024-03-01", periods=200, freq="min", tz="UTC"),
        "x": x, "y": x.astype(np.float32), "z": 1.0 / 3.0 + np.arange(200),
        "note": [None if i % 7 == 0 else ('a, "b"\nc' if i % 5 == 0 else f"ok {i}") for i in range(200)],
        "ok": np.arange(200) % 3 == 0, "n": np.arange(200) - 100})
    frame.insert(3, "x2", x[::-1])
    frame.columns = [*frame.columns[:3], "x", *frame.columns[4:]]      # "x" twice
    days = pd.Series(pd.date_range("2024-03-01", periods=200, freq="D"))
    days[150] += pd.Timedelta(hours=6)
    subsec = pd.Series(pd.date_range("2024-03-01", periods=200, freq="min"))
    subsec[120] += pd.Timedelta(milliseconds=250)
    subsec[10] = pd.NaT
    dur = pd.Series(pd.to_timedelta(np.arange(200), unit="s"))
    dur[100] += pd.Timedelta(microseconds=5)
    more = pd.DataFrame({"day": days, "sub": subsec, "dur": dur, "x": x})
    for f in (frame, frame.iloc[:0], frame.iloc[:, [0, 3]], more, more.iloc[:64], more[["sub"]]):
        frame_to_csv(f, tmp_path / "fast.csv")
        f.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
        assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "pandas.csv").read_bytes()
        if f is frame:      # the awkward values are there
            rows = (tmp_path / "fast.csv").read_text().split("\n")
            assert rows[0] == "t,x,y,x,z,note,ok,n"
            assert rows[4].split(",")[1:3] == ["", ""] and rows[6].split(",")[1:3] == ["inf", "inf"]
            assert rows[8].split(",")[1:3] == ["-inf", "-inf"] and rows[9].split(",")[1:3] == ["-0", "-0"]
            assert rows[1].split(",")[4] == "0.3333333333"
            assert '"a, ""b""' in rows[6] and rows[7] == 'c",False,-95'


def test_the_scorer_scores_each_point_once_with_the_numbers_of_each_alone(learned, plant, monkeypatch):
    """``_scorer`` computes a point's shape error the first time it meets the point (the search
    scores its candidates again when it compares them); every score is the one computed alone."""
    import model.analysis.advice as advice
    _, learner, ev, pts = learned
    offsets = {"LS": (0.01, -0.02), "HS": (0.0, 0.01)}
    s = AdviceSettings()
    alone = {id(p): _shape_at(learner, plant, offsets, s, p) for p in pts}
    met = []
    real = advice._shape_many
    monkeypatch.setattr(advice, "_shape_many", lambda *a: (met.extend(a[-1]), real(*a))[1])
    score = _scorer(learner, plant, offsets, s)
    first = score.many(pts[:6])
    assert [id(p) for p in met] == [id(p) for p in pts[:6]]
    again = score.many([pts[5], *pts[:8]])                # two new points, one twice in the call
    assert [id(p) for p in met[6:]] == [id(p) for p in pts[6:8]]
    assert again[1:7] == first and again[0] == first[5]
    for p, v in zip(pts[:8], again[1:]):
        assert v == p.COP * (1.0 - 0.01 * s.search_k * alone[id(p)]) if p.ok else v == p.COP
        assert score(p) == v and score.shape(p) == alone[id(p)]
    assert len(met) == 8                                  # nothing computed twice
    assert len({alone[id(p)] for p in pts if p.ok}) > 3


def test_a_points_memo_answers_its_own_inputs_only_and_is_not_pickled(learned, plant):
    """``_operating_points`` and ``_pm_barg`` keep their answer with the point, for the parameters
    and weights they were given: other ones get their own numbers; a pickled point leaves it."""
    from model.analysis.advice import _pm_barg
    from model.optimize import weighted_mean
    _, _, ev, pts = learned
    p = pts[4]
    a = _operating_points(p, plant)
    assert _operating_points(p, plant) is a
    other = plant.replace(comp_LS=plant.comp_LS.replace(N_nom=2.0 * plant.comp_LS.N_nom))
    b = _operating_points(p, other)
    assert np.array_equal(b["LS"][1], 0.5 * a["LS"][1]) and np.array_equal(b["HS"][1], a["HS"][1])
    assert np.array_equal(b["LS"][0], p.col("p_m_bar") / p.col("p_e_bar"))
    w2 = np.arange(1.0, len(ev.w) + 1.0)
    x, y = _pm_barg(p, ev.w, 1.0), _pm_barg(p, w2, 1.0)
    assert x == weighted_mean(p.col("p_m_bar"), ev.w) - 1.0 and y == weighted_mean(p.col("p_m_bar"), w2) - 1.0
    assert x != y and _pm_barg(p, ev.w, 1.01) == x + 1.0 - 1.01
    assert "_memo" in p.__dict__
    q = pickle.loads(pickle.dumps(p))
    assert "_memo" not in q.__dict__ and q.COP == p.COP
    assert _pm_barg(q, ev.w, 1.0) == x


def test_local_curves_from_kept_node_weights_are_the_computed_ones(learned, plant, monkeypatch):
    """A learner's local curves built with the grid weights of an earlier build (``_node_weights``
    keeps the last few, by the inputs' bytes) are the ones built from scratch; other bins get
    their own weights, and the kept arrays are read-only."""
    import model.analysis.compressors as C
    _, learner, _, _ = learned
    key = ("LS", "eta_is")

    def build(lr):
        ps, st = lr._prior_stats[key], lr.stats[key]
        return C.LocalCurves(lr.bins[key], lr._coef(*key), ps.A + st.A, lr.coverage["LS"], lr.s)
    monkeypatch.setattr(C, "_NODE_WEIGHTS", {})
    fresh = build(learner)
    assert fresh.ok and len(C._NODE_WEIGHTS) == 1
    (near, w_all), = C._NODE_WEIGHTS.values()
    assert not near.flags.writeable and not w_all.flags.writeable
    kept = build(learner)
    assert len(C._NODE_WEIGHTS) == 1
    assert np.array_equal(kept.coef, fresh.coef, equal_nan=True) and np.array_equal(kept.valid, fresh.valid)
    moved = learner.snapshot()                    # one more bin far from the others
    moved.bins[key].add(np.array([9.0]), np.array([0.2]), np.ones((1, 6)), np.ones(1))
    c2, _, _ = moved.bins[key].arrays()
    assert len(c2) == len(learner.bins[key].arrays()[0]) + 1
    build(moved)
    assert len(C._NODE_WEIGHTS) == 2
    # the same number of bins, each one bin further in pi: weights of their own, not the kept ones
    doc = learner.bins[key].to_dict()
    doc["bins"] = [[a + 1, b, tri, vec] for a, b, tri, vec in doc["bins"]]
    bins = learner.bins[key]
    shifted = type(bins).from_dict(doc, bins.bin_pi, bins.bin_n)
    args = (learner._coef(*key), learner._prior_stats[key].A + learner.stats[key].A, learner.coverage["LS"],
            learner.s)
    warm = C.LocalCurves(shifted, *args)
    monkeypatch.setattr(C, "_NODE_WEIGHTS", {})
    cold = C.LocalCurves(shifted, *args)
    assert np.array_equal(warm.coef, cold.coef, equal_nan=True)
    assert not np.array_equal(cold.coef, fresh.coef, equal_nan=True)
    monkeypatch.setattr(C, "_NODE_WEIGHTS", {})
    monkeypatch.setattr(C, "_NODE_WEIGHTS_MAX", 1)
    build(learner), build(moved), build(learner)
    assert len(C._NODE_WEIGHTS) == 1


def _guesses_as_results(ev, sps):
    """``Evaluator._guesses`` as it was written: the nearest cached point by a scan of the whole
    cache, its VResult taken, the VResults stacked (``_concat``, as it was)."""
    from model.optimize import GUESS_BAR

    def _concat(vs: list):
        if len(vs) == 1:
            return vs[0]
        n = [len(v) for v in vs]
        kw = {}
        for f in dataclasses.fields(vs[0]):
            vals = [getattr(v, f.name) for v in vs]
            a = vals[0]
            if isinstance(a, np.ndarray) and a.shape[:1] == (n[0],):
                kw[f.name] = np.concatenate(vals)
            elif isinstance(a, dict):
                kw[f.name] = {k: (np.concatenate([d[k] for d in vals])
                                  if isinstance(b, np.ndarray) and b.shape[:1] == (n[0],) else b)
                              for k, b in a.items()}
            else:
                kw[f.name] = a
        return type(vs[0])(**kw)
    n = len(ev.rows)
    parts, index, base = [], [], 0
    for sp in sps:
        got = None
        for e, rmap in ((ev, None), (ev._other, None), (ev._seed, ev._seed_map)):
            if e is None:
                continue
            if sp is None:
                p = e._cache.get(None)
                if p is not None and p.vres is not None and e is not ev:
                    got = p.vres, (np.arange(len(p.vres)) if rmap is None else rmap)
                    break
                continue
            near = [(abs(x - sp), x) for x in e._cache if x is not None and abs(x - sp) <= GUESS_BAR
                    and e._cache[x].has_vres]
            if near:
                v = e._cache[min(near)[1]].vres
                got = v, (np.arange(len(v)) if rmap is None else rmap)
                break
        if got is None:
            index.append(np.full(n, -1))
        else:
            parts.append(got[0])
            index.append(base + got[1])
            base += len(got[0])
    return (_concat(parts), np.concatenate(index)) if parts else (None, None)


def test_a_guess_of_warm_start_states_is_the_guess_of_whole_results(learned, plant):
    """The optimizer's warm starts as the neighbours' states (``WarmStart``, found by bisection in
    the sorted set points) are the states and rows of the VResults the whole-cache scan found, and
    the solver answers the same with either."""
    from model.vcycle import WarmStart
    data, _, ev, _ = learned
    fresh = Evaluator(ev.rows, ev.w, plant, guess_from=ev)       # the other evaluator's points
    fresh.at_many([10.25, 15.0])                                  # and some of its own
    seeded = Evaluator(data[list(INPUT_COLUMNS)].iloc[::9].reset_index(drop=True),
                       np.ones(len(data.iloc[::9])), plant, guess_from=ev)   # other rows: the seed's map
    sets = [[None], [8.0], [8.5], [8.5 + 1e-9, 7.2, 19.9, 20.99, 21.5], [10.25, 9.9, 14.4, 15.6, 30.0],
            [None, 13.37, 12.5, 16.0 - 1e-9]]
    checked = 0
    for e in (ev, fresh, seeded):
        idx = np.arange(len(e.rows))
        for sps in sets:
            new, gi_new = e._guesses(sps, idx)
            old, gi_old = _guesses_as_results(e, sps)
            if old is None:
                assert new is None and gi_new is None
                continue
            assert isinstance(new, WarmStart) and len(new) == len(old)
            assert np.array_equal(gi_new, gi_old)
            assert list(new.state) == list(old.state)
            for k in old.state:
                assert np.array_equal(new.state[k], old.state[k], equal_nan=True), k
            checked += 1
    assert checked >= 10
    e = fresh
    sps = [8.5, 12.3, 17.75]
    new, gi = e._guesses(sps, np.arange(len(e.rows)))
    old, gi_old = _guesses_as_results(e, sps)
    rows = e._input_columns().take(np.tile(np.arange(len(e.rows)), len(sps)))
    sp_all = np.repeat(np.array(sps), len(e.rows))
    a = solve_many(rows, plant, p_m_sp=sp_all, ls_mode="float", guess=new, guess_index=gi)
    b = solve_many(rows, plant, p_m_sp=sp_all, ls_mode="float", guess=old, guess_index=gi_old)
    assert a.warm_rows > 0
    pd.testing.assert_frame_equal(a.frame(), b.frame(), check_exact=True)


def test_shape_scores_of_points_of_different_row_counts_are_each_alone(learned, plant):
    """``_shape_many`` over points of 8 and of 5 rows: each point's mean over its own rows, the
    number a call for the point alone gives (and, alone, the written-out form's)."""
    data, learner, ev, pts = learned
    rows5, w5 = representative(data[list(INPUT_COLUMNS)].astype(float), 5)
    ev5 = Evaluator(rows5, w5, plant)
    pts5 = ev5.at_many([None, 9.0, 12.0, 15.0, 18.0])
    offsets = {"LS": (0.01, -0.02), "HS": (0.0, 0.01)}
    s = AdviceSettings()
    mixed = [pts[1], pts5[0], pts[4], pts5[2], pts5[3], pts[7], pts5[4]]
    assert {len(p.col("W_LS_kW")) for p in mixed} == {5, 8} and sum(p.ok for p in mixed) >= 5
    many = _shape_many(learner, plant, offsets, s, mixed)
    assert many == [_shape_many(learner, plant, offsets, s, [p])[0] for p in mixed]
    for p, u in zip(mixed, many):
        if not p.ok:
            assert u == 0.0
            continue
        W = {st: p.col(f"W_{st}_kW") for st in ("LS", "HS")}
        var = np.zeros(len(W["LS"]))
        for st in ("LS", "HS"):
            if learner.learned(st, "eta_is"):
                pi, n = _operating_points(p, plant)[st]
                u_st = s.shape_k * learner.shape_sd(st, pi - offsets[st][0], n - offsets[st][1])
                var += (W[st] / (W["LS"] + W["HS"]) * u_st / p.col(f"eta_is_{st}")) ** 2
        assert u == float(100.0 * np.mean(np.sqrt(var)))


def test_the_kept_node_weights_stay_bounded_and_right_under_threads(learned, monkeypatch):
    """Replays in threads of one process (a cluster's worker with several threads) share the kept
    grid weights: four threads building local curves of two sets of bins get their own curves
    every time, and the cache stays within its bound. (The eviction's race, which the lock
    excludes, is too narrow under the GIL for a test to show; this checks the answers.)"""
    import threading
    import model.analysis.compressors as C
    _, learner, _, _ = learned
    key = ("LS", "eta_is")
    bins = learner.bins[key]
    doc = bins.to_dict()
    doc["bins"] = [[a + 1, b, tri, vec] for a, b, tri, vec in doc["bins"]]
    sets = [bins, type(bins).from_dict(doc, bins.bin_pi, bins.bin_n)]
    args = (learner._coef(*key), learner._prior_stats[key].A + learner.stats[key].A, learner.coverage["LS"],
            learner.s)
    monkeypatch.setattr(C, "_NODE_WEIGHTS", {})
    want = [C.LocalCurves(b, *args).coef for b in sets]
    monkeypatch.setattr(C, "_NODE_WEIGHTS", {})
    monkeypatch.setattr(C, "_NODE_WEIGHTS_MAX", 1)          # every other build evicts
    bad, errors = [], []

    def work(j):
        try:
            for i in range(40):
                k = (i + j) % 2
                if not np.array_equal(C.LocalCurves(sets[k], *args).coef, want[k], equal_nan=True):
                    bad.append((j, i))
        except Exception as exc:          # noqa: BLE001 - reported below
            errors.append(repr(exc))
    threads = [threading.Thread(target=work, args=(j,)) for j in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads)
    assert errors == [] and bad == []
    assert len(C._NODE_WEIGHTS) == 1


def test_pass_one_takes_the_stage_states_process_computed_for_the_history(plant, monkeypatch):
    """A replay records the stage states ``process`` computes for every sample and answers pass 1's
    calls (the measured side of each block of windows, each window's compressor observations)
    from them: the same windows and samples to the bit as a replay that computes them again (its
    ``processed`` given, so nothing recorded), and no sample's states computed twice."""
    import model.analysis.compressors as C
    from model.analysis.replay import ReplaySettings, replay
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    hist = export_history(0.45, cfg=load_simulator_config()).history
    s = ReplaySettings(surrogate=False)
    real = C._stage_arrays
    rows: list = []
    monkeypatch.setattr(C, "_stage_arrays", lambda *a: rows.append(len(a[1])) or real(*a))
    shared = replay(hist, plant, s)
    n_shared = list(rows)
    rows.clear()
    again = replay(hist, plant, s, processed=process(hist, plant))
    assert len(shared.windows) >= 3 and (shared.windows["status"] == "ok").all()
    pd.testing.assert_frame_equal(shared.windows, again.windows, check_exact=True)
    pd.testing.assert_frame_equal(shared.samples, again.samples, check_exact=True)
    # the history's two stages once each, and the initial window's observations (not in pass 1)
    assert n_shared[:2] == [len(hist), len(hist)] and all(n <= s.initial_minutes for n in n_shared[2:])
    assert sum(rows) > sum(n_shared) + len(hist)     # the other computes pass 1's again


def test_a_calls_points_are_each_points_own_figures(learned, plant):
    """``_points`` makes a solver call's points from its columns at once: each point's COP, heat,
    power, HS saturation and whether every row solved equal ``_point`` on that point's own columns
    to the bit, and the columns it hands each point are those ``PartColumns`` reads — also for set
    points where some rows do not solve."""
    from model.optimize import SOLVED, PartColumns, _Outputs, _point, _points
    data, _, ev, _ = learned
    sps = [None, 2.0, 9.0, 12.5, 16.0, 30.0]
    rows, w = ev.rows, ev.w
    n = len(rows)
    from model.batch import InputColumns
    own = np.asarray(rows["p_m_sp"], dtype=float)
    sp_all = np.concatenate([own if sp is None else np.full(n, sp) for sp in sps])
    vres = solve_many(InputColumns.of(rows).take(np.tile(np.arange(n), len(sps))), plant, p_m_sp=sp_all,
                      ls_mode="float")
    outs, solved = _Outputs(vres), vres.solved()
    got = _points(sps, w, outs, solved, {}, rows.index)
    oks = []
    for j, (sp, p) in enumerate(zip(sps, got)):
        cols = PartColumns(outs, solved, slice(j * n, (j + 1) * n), {})
        q = _point(sp, None, w, cols=cols, index=rows.index)
        for f in ("COP", "Q_sink_kW", "W_kW"):
            a, b = getattr(p, f), getattr(q, f)
            assert (math.isnan(a) and math.isnan(b)) or a == b, (sp, f, a, b)
        assert (p.ok, p.hs_saturated) == (q.ok, q.hs_saturated) and (p.sp == q.sp or sp is None)
        for c in ("Q_sink_kW", "W_total_kW", "hs_saturated", "COP", "p_m_bar"):
            assert np.array_equal(p.cols[c], cols[c], equal_nan=True), c
        assert np.array_equal(p.status_in(SOLVED), q.status_in(SOLVED))
        oks.append(p.ok)
    assert any(oks) and not all(oks)      # some set points solve every row, some do not


def test_a_replay_files_plain_chunks_are_joined_here_to_the_byte(tmp_path, monkeypatch):
    """``frame_to_csv`` joins the lines itself when every field of a chunk is plain (the samples
    table: texts without separators, booleans, integers, floats, missing texts) — the bytes of
    ``to_csv`` — and hands a chunk to pandas as soon as one field needs quoting."""
    import edge.replaydir as rd
    from edge.replaydir import frame_to_csv
    joined = []
    real = rd._fields

    def spy(part, cols, a, fmt):
        got = real(part, cols, a, fmt)
        joined.append(got is not None)
        return got
    monkeypatch.setattr(rd, "_fields", spy)
    monkeypatch.setattr(rd, "CSV_CHUNK_ROWS", 16)
    rng = np.random.default_rng(3)
    n = 50
    x = rng.standard_normal(n) * 10.0 ** rng.integers(-9, 9, n)
    x[[1, 2]] = [np.nan, -0.0]
    t = pd.date_range("2024-03-01", periods=n, freq="min", tz="UTC")
    frame = pd.DataFrame({
        "timestamp": [v.isoformat() for v in t], "usable": rng.random(n) > 0.5,
        "reason": [None if i % 3 else "pump off" for i in range(n)],
        "window": pd.array([pd.NA if i % 4 else "w é" for i in range(n)], dtype="string"),
        "x": x, "y": x.astype(np.float32), "n": np.arange(n) - 7, "t": t})
    frame_to_csv(frame, tmp_path / "fast.csv")
    frame.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "pandas.csv").read_bytes()
    assert joined == [True] * 4                      # 50 rows: 4 chunks, each joined here
    for bad, chunk in (("a,b", 2), ('say "x"', 0), ("two\nlines", 3), ("cr\r", 1)):
        joined.clear()
        f = frame.copy()
        f.loc[16 * chunk + 1, "reason"] = bad
        frame_to_csv(f, tmp_path / "fast.csv")
        f.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
        assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "pandas.csv").read_bytes()
        assert joined == [i != chunk for i in range(4)]
    for f in (frame.iloc[:0], frame[["x"]], frame[["reason"]].fillna("")):
        joined.clear()
        frame_to_csv(f, tmp_path / "fast.csv")
        f.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
        assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "pandas.csv").read_bytes()
    mixed = frame.assign(reason=[1.5 if i == 3 else "ok" for i in range(n)])
    joined.clear()
    frame_to_csv(mixed, tmp_path / "fast.csv")
    mixed.to_csv(tmp_path / "pandas.csv", index=False, float_format="%.10g")
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "pandas.csv").read_bytes()
    assert joined == [False, True, True, True]        # a number among texts: pandas writes it


@pytest.mark.parametrize("chunk", [16384, 7])
def test_samples_timestamps_are_isoformat(monkeypatch, chunk):
    """``replay.isoformat`` (numpy for UTC whole seconds, ``chunk`` at a time) gives
    ``Timestamp.isoformat`` of each time, also for the times it leaves to pandas (fractions, other
    zones, none)."""
    import model.analysis.replay as rp
    from model.analysis.replay import isoformat
    monkeypatch.setattr(rp, "ISO_CHUNK", chunk)
    cases = [pd.Series(pd.date_range("2024-03-01", periods=300, freq="min", tz="UTC")),
             pd.Series(pd.to_datetime(["2024-03-01T00:00:00.5Z", "2024-03-01T00:01:00Z"], utc=True,
                                      format="ISO8601")),
             pd.Series(pd.to_datetime(["1969-12-31T23:59:59Z", "2024-02-29T12:00:00+02:00"], utc=True,
                                      format="ISO8601")),
             pd.Series(pd.date_range("2024-03-01", periods=5, freq="min", tz="Europe/Copenhagen")),
             pd.Series(pd.to_datetime(["2024-03-01T00:00:00Z"], utc=True).as_unit("s")),
             pd.Series(pd.to_datetime(["2024-03-01T00:00:00Z"], utc=True)).iloc[:0]]
    for ts in cases:
        assert list(isoformat(ts)) == [v.isoformat() for v in ts]
    assert isoformat(cases[0])[61] == "2024-03-01T01:01:00+00:00"
    assert isoformat(cases[2])[1] == "2024-02-29T10:00:00+00:00"


def test_a_window_tasks_observation_columns_are_read_once_and_not_pickled(learned, plant):
    """``WindowTask.obs_col``: pass 1, pass 2 and the window's samples read the same observation
    columns; each is read once (the same array again), its values the column's ``to_numpy()``,
    and a pickled task carries the frame only (the copy reads them anew)."""
    from model.analysis.chain import WindowResult, WindowTask
    data, *_ = learned
    obs = observe(data.assign(timestamp=pd.to_datetime(data["timestamp"], utc=True)), plant)
    task = WindowTask(res=WindowResult("", "", math.nan, len(data)), data=data, fixed=plant, obs=obs)
    for name in ("pi_LS", "n_LS", "pi_HS", "n_HS"):
        a = task.obs_col(name)
        assert np.array_equal(a, obs[name].to_numpy(), equal_nan=True) and a.dtype == np.float64
        assert task.obs_col(name) is a
    copy = pickle.loads(pickle.dumps(task))
    assert "_obs_cols" not in copy.__dict__ and "_obs_cols" in task.__dict__
    assert np.array_equal(copy.obs_col("pi_HS"), task.obs_col("pi_HS"), equal_nan=True)


def test_the_condenser_factor_from_the_callers_input_matrix_is_the_factor_to_the_bit(learned, plant):
    """The chain hands ``condenser_factor`` the window's input matrix it has read once (from the
    window's ``InputColumns``): the same factor, p_c error and representative solutions as the
    factor that reads ``der`` itself."""
    from model.analysis.chain import condenser_factor
    from model.measured import derived
    data, *_ = learned
    der = derived(data, plant)
    for c in INPUT_COLUMNS:
        if c not in der.columns:
            der[c] = data[c].to_numpy(dtype=float)
    X = matrix(InputColumns.of(der))
    assert np.array_equal(X, matrix(der), equal_nan=True) and X.flags.f_contiguous
    sol_a, sol_b = [], []
    a = condenser_factor(der, plant, 1.0, 8, solution=sol_a)
    b = condenser_factor(der, plant, 1.0, 8, solution=sol_b, X=X)
    assert math.isfinite(a[0]) and a == b
    pd.testing.assert_frame_equal(sol_a[0][1], sol_b[0][1], check_exact=True)
    assert np.array_equal(sol_a[0][0]["p_c_bar"], sol_b[0][0]["p_c_bar"], equal_nan=True)
