"""The compiled speed search (model.analysis.speedkernel): the numpy search's numbers to the bit.

The kernel is numba's (the ``fast`` extra, installed by ``make test``); without numba it is never
used, so there is nothing to compare and these tests are skipped.

- a learned compressor's ``speed_for_flow_v`` (its own grid, with and without a start speed, with a
  curve draw as six scalars and as six per-row arrays), rows inside and outside the grid, beyond the
  speed range, NaN inputs: equal to the numpy search bit for bit;
- stacked compressors (``model.analysis.stacked``) likewise, rows of four members in one call;
- the saturation table (with and without its range check), the vapour table, the isentropic /
  superheat lookups and the subcooler's Newton step: the
  lookups on their ranges with NaN and out-of-range coordinates, the solver on the operating grid x
  set points, equal to numpy to the bit;
- a replay with the kernel gives the same windows as without it.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from model.analysis import speedkernel
from model.analysis.compressors import LearnedCompressor, local_speed
from model.analysis.stacked import Stacked
from test_vcycle import _draw_learner, learned_params

pytest.importorskip("numba", reason="the compiled speed search needs numba (the 'fast' extra)")


@pytest.fixture(scope="module")
def kernel():
    assert speedkernel.enable(), "numba is installed but the speed kernel did not compile"
    yield       # it stays on for the rest of the session, as after any replay: numpy's numbers


def _both(fn):
    """(numpy result, kernel result) of ``fn()``."""
    keep = speedkernel._KERNEL
    speedkernel._KERNEL = None
    try:
        ref = fn()
    finally:
        speedkernel._KERNEL = keep
    assert speedkernel.active()
    return ref, fn()


def _rows(k: int, seed: int):
    rng = np.random.default_rng(seed)
    pi = np.where(rng.random(k) < 0.6, rng.normal(2.1, 0.3, k), rng.uniform(1.2, 4.8, k))
    m, rho = rng.uniform(0.05, 3.0, k), rng.uniform(3.0, 30.0, k)
    n0 = rng.uniform(0.3, 1.6, k)
    # a few rows the search must refuse or carry: NaN inputs, a start speed NaN, zero flow
    pi[:3] = [np.nan, 2.0, 2.2]
    m[3:5] = [np.nan, 0.0]
    n0[5] = np.nan
    return m, rho, pi, n0


def _equal(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)       # NaN in the same places, every other bit equal


def test_learned_compressor_speeds_equal_the_numpy_search_to_the_bit(plant, kernel):
    learner, draws = _draw_learner(plant)
    comp = learner.compressor("HS")
    drawn = learner.compressor("HS", delta=draws[0]["HS"])
    assert isinstance(comp, LearnedCompressor) and comp.local_vol.ok
    m, rho, pi, n0 = _rows(3000, 11)
    for c in (comp, drawn):
        ref, got = _both(lambda: c.speed_for_flow_v(m, rho, pi, n0))
        _equal(ref, got)
        ref, got = _both(lambda: c.speed_for_flow_v(m, rho, pi))
        _equal(ref, got)
        # the search covered what it should: solved rows, rows beyond the range, refused rows
        n = got[0]
        assert np.isfinite(n).sum() > 2000
        assert (n > c.N_max / c.N_nom).any() and (n < c.N_min / c.N_nom).any()
        assert np.isnan(n[[0, 3]]).all()
    # a draw as per-row arrays (what Flowsheet.comp hands over for uncertainty draws)
    rows = len(m)
    per_row = tuple(np.full(rows, x) * np.linspace(0.5, 1.5, rows) for x in drawn.delta_vol)
    target = m / (rho * comp.swept_volume)
    lo, hi = comp.N_min / comp.N_nom, comp.N_max / comp.N_nom
    ref, got = _both(lambda: local_speed(comp.local_vol, comp.eta_vol, per_row, target, pi, n0, lo, hi))
    _equal(ref, got)
    assert np.isfinite(got[0]).sum() > 2000


def _four_members(plant, stage: str, draw: int) -> list:
    """A stage's compressors of four windows: the prior, a fit without a local grid, a learned grid,
    the same with one of its uncertainty draws."""
    learned = learned_params(plant, delta=False)
    learner, draws = _draw_learner(plant)
    return [getattr(plant, f"comp_{stage}"), getattr(learned, f"comp_{stage}"), learner.compressor(stage),
            learner.compressor(stage, delta=draws[draw][stage])]


def test_stacked_speeds_equal_the_numpy_search_to_the_bit(plant, kernel):
    comps = _four_members(plant, "LS", 1)
    st = Stacked(comps)
    k = 4000
    g = np.random.default_rng(3).integers(0, len(comps), k)
    m, rho, pi, n0 = _rows(k, 12)
    zero = np.zeros((k, 6))
    d_vol = zero.copy()
    d_vol[g == 3] = comps[3].delta_vol
    v = st.view(g, None, tuple(d_vol.T))
    ref, got = _both(lambda: v.speed_for_flow_v(m, rho, pi, n0))
    _equal(ref, got)
    assert np.isfinite(got[0][g == 1]).sum() > 500
    ref, got = _both(lambda: st.view(g).speed_for_flow_v(m, rho, pi))
    _equal(ref, got)
    # members all on learned grids: the view hands every row to the kernel at once
    grids = Stacked(comps[2:])
    g2 = (g % 2).astype(np.intp)
    calls = []
    run = speedkernel.run
    speedkernel.run = lambda *a: calls.append(len(a[4])) or run(*a)
    try:
        for d in (None, tuple((d_vol * (g == 3)[:, None]).T)):
            ref, got = _both(lambda: grids.view(g2, None, d).speed_for_flow_v(m, rho, pi, n0))
            _equal(ref, got)
            assert np.isfinite(got[0]).sum() > 3000
    finally:
        speedkernel.run = run
    assert calls == [k, k]


def test_stacked_curves_equal_numpy_to_the_bit(plant, kernel):
    """The compiled stacked curve (``speedkernel.curve``): eta_is and eta_vol of rows of four members
    (the prior, a fit without grid, learned grids with and without a draw), inside and outside the
    grids, NaN inputs, with and without per-row curve differences."""
    comps = _four_members(plant, "HS", 2)
    st = Stacked(comps)
    k = 5000
    rng = np.random.default_rng(5)
    g = rng.integers(0, len(comps), k)
    _, _, pi, _ = _rows(k, 13)
    n = rng.uniform(0.2, 1.7, k)
    n[7:9] = [np.nan, np.inf]
    calls = []
    curve = speedkernel.curve
    d_is = np.zeros((k, 6))
    d_is[g == 3] = comps[3].delta_is
    for view in (st.view(g), st.view(g, tuple(d_is.T), tuple(d_is.T[::-1]))):
        for f in (view.eta_is_v, view.eta_vol_v):
            with np.errstate(all="ignore"):          # the inf row
                ref, got = _both(lambda: f(pi, n))
            np.testing.assert_array_equal(ref, got)
            assert np.isfinite(got).sum() > 4500
    # the grids answered rows (not only the global curves), and the kernel ran
    with np.errstate(all="ignore"):
        inside = st.t_is.value_v(g, pi, n)[1]
    assert inside.sum() > 500 and (~inside & np.isfinite(pi) & np.isfinite(n)).sum() > 500
    speedkernel.curve = lambda *a: calls.append(len(a[2])) or curve(*a)
    try:
        st.view(g).eta_is_v(pi, n)
    finally:
        speedkernel.curve = curve
    assert calls == [k]


def test_liquid_table_equals_numpy_to_the_bit(kernel):
    """The compiled liquid table (``CycleTables.liq_raw``, the subcooler's inner loop): h and dh/dT
    over the table's range of T_c and subcooling, NaN and inf subcooling, node lines."""
    from model.cycletables import LIQ_D_MAX, T_RANGE, get_cycle_tables
    tab = get_cycle_tables()
    rng = np.random.default_rng(8)
    k = 6000
    T_c = rng.uniform(T_RANGE[0], T_RANGE[1] - 1e-9, k)
    d = rng.uniform(0.0, LIQ_D_MAX, k)
    d[:4] = [np.nan, np.inf, 0.0, 0.5]
    T_c[10:20] = np.round(T_c[10:20])               # on the table's T nodes
    calls = []
    liq = speedkernel.liq
    speedkernel.liq = lambda *a: calls.append(len(a[3])) or liq(*a)
    try:
        ref, got = _both(lambda: tab.liq_raw(tab.liq_row(T_c), d))
    finally:
        speedkernel.liq = liq
    _equal(ref, got)
    assert calls == [k] and np.isfinite(got[0]).sum() == k - 2 and np.isnan(got[0][:2]).all()


def test_saturation_and_derived_lookups_equal_numpy_to_the_bit(kernel):
    """The compiled saturation table (``sat_raw``) and the isentropic / superheat-from-h lookups
    (``isen_raw``, ``tofh_raw``): over their ranges, on nodes, with NaN and out-of-range
    coordinates (clamped cells, as numpy's)."""
    from model.cycletables import DH_MAX, DS_MAX, T_RANGE, VAP_T_MIN, get_cycle_tables
    tab = get_cycle_tables()
    rng = np.random.default_rng(9)
    k = 5000
    T = rng.uniform(VAP_T_MIN, T_RANGE[1], k)
    T[:10] = np.round(T[:10])
    ref, got = _both(lambda: tab.sat_raw(T))
    _equal(ref, got)
    assert np.isfinite(got[0]).all() and np.isfinite(got[4]).all()
    ds, dh = rng.uniform(0.0, DS_MAX, k), rng.uniform(0.0, DH_MAX, k)
    ds[:4] = dh[:4] = [np.nan, 0.0, -1.0, np.inf]
    Tx = T.copy()
    Tx[4:7] = [np.nan, 100.0, 900.0]              # outside the table: numpy's clamped cells
    for f, dv in ((tab.isen_raw, ds), (tab.tofh_raw, dh)):
        with np.errstate(all="ignore"):             # as in the flowsheet: failed rows carry NaN
            ref, got = _both(lambda: f(Tx, dv))
        np.testing.assert_array_equal(ref, got)
        assert not np.isfinite(got[[0, 3, 4]]).any() and np.isfinite(got[7:]).all()


def test_checked_saturation_and_vapour_tables_equal_numpy_to_the_bit(kernel, monkeypatch):
    """The compiled saturation table with its range check (``CycleTables.sat``) and the vapour
    table (``CycleTables.vapour``, the evaporator's suction state): over and beyond their ranges,
    on nodes and range ends, NaN and infinite coordinates -> NaN rows where numpy has them, every
    other bit equal; and both ran in the kernel."""
    from model.cycletables import SAT_T_MAX, SAT_T_MIN, THETA_MAX, VAP_T_MAX, VAP_T_MIN, get_cycle_tables
    tab = get_cycle_tables()
    rng = np.random.default_rng(10)
    k = 8000
    calls = []
    for name in ("sat_full", "vapour"):
        f = getattr(speedkernel, name)
        monkeypatch.setattr(speedkernel, name, lambda *a, f=f, name=name: calls.append(name) or f(*a))
    T = rng.uniform(SAT_T_MIN - 5.0, SAT_T_MAX + 5.0, k)
    T[:6] = [np.nan, np.inf, -np.inf, SAT_T_MIN, SAT_T_MAX, 1e300]
    T[6:20] = np.round(T[6:20], 1)                   # on the table's nodes
    with np.errstate(all="ignore"):
        ref, got = _both(lambda: tab.sat(T))
    _equal(ref, got)
    outside = ~((T >= SAT_T_MIN) & (T <= SAT_T_MAX))
    assert np.array_equal(np.isnan(got[0]), outside) and outside.sum() > 100 and np.isfinite(got[1][3:5]).all()
    Tv = rng.uniform(VAP_T_MIN - 5.0, VAP_T_MAX + 5.0, k)
    th = rng.uniform(-5.0, 60.0, k)
    th[:300] = rng.uniform(0.0, THETA_MAX, 300)      # the whole superheat range
    th[300:305] = [np.nan, np.inf, 0.0, THETA_MAX, -0.0]
    Tv[305:310] = [np.nan, VAP_T_MIN, VAP_T_MAX, np.inf, 0.0]
    with np.errstate(all="ignore"):
        ref, got = _both(lambda: tab.vapour(Tv, th))
    _equal(ref, got)
    ok = tab.vap_ok(Tv, th)
    assert np.array_equal(np.isfinite(got[2]), ok) and (~ok).sum() > 100 and ok[302:304].all()
    assert calls == ["sat_full", "vapour"]


def test_coverage_distance_equals_numpy_to_the_bit(plant, kernel, monkeypatch):
    """The learner's distance to its covered bins (``CompressorLearner.coverage_distance``) with the
    compiled nearest rectangle: points inside bins, between them, far out, on bin edges, NaN and
    infinite coordinates, a commissioning reference: numpy's numbers to the bit; and the kernel ran."""
    learner = _draw_learner(plant)[0]
    rng = np.random.default_rng(11)
    k = 4000
    calls = []
    f = speedkernel.rect_min
    monkeypatch.setattr(speedkernel, "rect_min", lambda *a: calls.append(len(a[0])) or f(*a))
    for st, pi0, n0 in (("LS", 2.4, 1.05), ("HS", 1.9, 1.0)):
        pi, n = rng.normal(pi0, 0.8, k), rng.normal(n0, 0.3, k)
        pi[:4], n[4:8] = [np.nan, np.inf, -np.inf, pi0], [np.nan, np.inf, n0, -1.0]
        c = learner.coverage[st].centers(learner.s.min_bin_weight)
        pi[8:12], n[8:12] = c[:4, 0] + 0.5 * learner.coverage[st].bin_pi, c[:4, 1]   # on a bin's edge
        ref, got = _both(lambda: learner.coverage_distance(st, pi, n))
        np.testing.assert_array_equal(ref, got)
        assert (got == 0).sum() > k // 10 and (got > 1).sum() > k // 10 and np.isinf(got[:8]).sum() >= 5
        ref_doc = learner.coverage[st].to_dict()
        ref, got = _both(lambda: learner.coverage_distance(st, pi[:50], n[:50], reference=ref_doc))
        np.testing.assert_array_equal(ref, got)
    assert calls == [k, 50, k, 50]


def test_flowsheet_with_the_kernels_solves_to_the_bit(plant, kernel, monkeypatch):
    """``solve_many`` on the operating grid x set points (rows that solve, rows beyond the LS speed
    range, cold and warm subcooler starts): the same frame with the compiled saturation, lookups
    and subcooler Newton as with numpy, and the subcooler ran in the kernel."""
    from model.vcycle import solve_many
    from test_vcycle import grid
    df = grid(full=True)
    calls = []
    sc = speedkernel.subcooler
    monkeypatch.setattr(speedkernel, "subcooler", lambda *a: calls.append(len(a[6])) or sc(*a))
    ref, got = _both(lambda: solve_many(df, plant).frame())
    assert sum(calls) > 10 * len(df)
    num = [c for c in got.columns if pd.api.types.is_numeric_dtype(got[c])]
    pd.testing.assert_frame_equal(ref[num], got[num], check_exact=True)
    pd.testing.assert_frame_equal(ref.drop(columns=num), got.drop(columns=num))
    assert got["status"].eq("ok").sum() > len(df) // 3 and got["status"].ne("ok").sum() > len(df) // 3


def test_forecast_least_squares_equal_numpy_to_the_bit(kernel):
    """``forecast._ls_many`` (a0, r0, ssr for many k) with and without the kernel: estimates from 1 to
    2,000 (numpy's pairwise sums below 8, up to 128 and split in halves beyond), with and without
    the prior's pseudo-observation, grids with k = 0 and single ks; equal to the bit, and each k's
    numbers the same whichever other ks share its call."""
    from model.analysis.forecast import _ls_many
    rng = np.random.default_rng(17)
    for trial, n in enumerate((1, 2, 7, 8, 9, 24, 127, 128, 129, 130, 300, 777, 2000)):
        t = np.sort(rng.uniform(0.0, 60.0, n))
        y = 0.05 + 0.01 * t * np.exp(-t / 40.0) + rng.normal(0.0, 0.004, n)
        sw = 1.0 / rng.uniform(0.002, 0.02, n)
        ks = np.concatenate([[0.0], np.geomspace(1e-4, 3.0, 60)])
        for prior in (None, (float(rng.uniform(1.0, 300.0)), float(rng.uniform(0.0, 0.4)))):
            ref, got = _both(lambda: _ls_many(ks, t, y, sw, prior))
            _equal(ref, got)
            assert np.isfinite(got[2]).all() and (got[2] >= 0.0).all()
            one = [_ls_many([k], t, y, sw, prior) for k in ks[::7]]
            for j, (a, r, ssr) in enumerate(one):
                assert (a[0], r[0], ssr[0]) == (got[0][7 * j], got[1][7 * j], got[2][7 * j])
    # above: unconstrained solutions, both edges, and (one estimate) singular systems
    flat = np.full(5, 0.3)
    ref, got = _both(lambda: _ls_many([0.0, 0.5], np.arange(5.0), flat, np.ones(5)))
    _equal(ref, got)
    assert got[0][0] == pytest.approx(0.3, rel=1e-12) and got[2][0] == pytest.approx(0.0, abs=1e-24)


def test_cycle_costs_equal_numpy_to_the_bit(kernel, monkeypatch):
    """The CIP plan's cycle integrals (``cost._cycle_cost``) with and without the kernel: both laws,
    the three restarts, sigma points stacked and alone beside the pump's component, cost curves of 2
    to 10 points (past 8 pieces every piece integrated), levels below the start and out of reach,
    cycles of 6 hours to a year; equal to the bit. A NaN cycle length makes NaN levels, where the
    kernel hands back to numpy (whose ``interp`` of NaN it does not follow): still numpy's numbers."""
    import dataclasses
    import math
    import model.analysis.cost as C
    from model.analysis.cost import CostCurve, FoulingComponent
    from model.analysis.forecast import FoulingFit

    def law(name, y0, r0, tau, floor=0.0):
        p = 3 if name == "kern_seaton" else 2
        return FoulingFit(name, floor, y0 - floor, r0, 1.0 / tau if p == 3 else 0.0, np.zeros((p, p)), 1.0,
                          1e-5, 100, 97.0, 0.0, 10.0, "given", math.nan)
    calls = []
    orig = speedkernel.cycle_cost
    monkeypatch.setattr(speedkernel, "cycle_cost", lambda *a: (lambda r: calls.append(r is None) or r)(orig(*a)))
    rng = np.random.default_rng(23)
    T = np.concatenate([np.geomspace(0.25, 365.0, 100), np.linspace(3.0, 4.0, 21)])
    for trial in range(60):
        name = ("kern_seaton", "linear")[trial % 2]
        restart = ("auto", "current", "steady")[trial % 3] if name == "kern_seaton" else ("auto", "current")[trial % 4 // 2]
        nlev = 2 + trial % 9
        levels = np.sort(rng.uniform(0.0, 6e-3, nlev))
        cost = CostCurve(levels, np.cumsum(rng.uniform(0.0, 50.0, nlev)))
        cov = np.diag([1e-4, 2e-5, 0.02][: 3 if name == "kern_seaton" else 2]) ** 2
        fit = dataclasses.replace(law(name, rng.uniform(0.0, 3e-3), rng.uniform(0.0, 4e-4), rng.uniform(2.0, 60.0)),
                                  cov=cov)
        comps = [FoulingComponent(fit, float(rng.uniform(0.05, 1.0)), cost, restart=restart, uncertain=trial % 5 > 0),
                 FoulingComponent(law("kern_seaton", 1.1, 0.02, 20.0, floor=1.0), 0.3, CostCurve([1.0, 2.0], [0.0, 9.0]))]
        expanded = C._expand(comps)
        ref, got = _both(lambda: C._cycle_cost(expanded, T))
        _equal([ref], [got])
        assert np.isfinite(got).all()
    assert len(calls) >= 120 and not any(calls)          # every run of variants in the kernel
    calls.clear()
    Tn = T.copy()
    Tn[5] = np.nan
    ref, got = _both(lambda: C._cycle_cost(expanded, Tn))
    _equal([ref], [got])
    assert np.isnan(got[5]) and np.isfinite(np.delete(got, 5)).all() and any(calls)


def test_kernels_that_do_not_compile_are_said_once_and_numpy_stays(monkeypatch):
    """numba installed but a kernel failing to compile: a RuntimeWarning naming the failure, every
    kernel off (numpy's numbers), and no second attempt in the process."""
    import numba
    keep = {k: getattr(speedkernel, k) for k in ("_KERNEL", "_CURVE", "_LIQ", "_SAT", "_DER", "_SC_PRE",
                                                 "_SC_POST", "_SATF", "_VAP", "_RECT", "_LS", "_CCN", "_CCS", "_TRIED")}

    def broken(*a, **k):
        raise TypeError("no LLVM here")

    try:
        for k in keep:
            setattr(speedkernel, k, None)
        speedkernel._TRIED = False
        monkeypatch.setattr(numba, "njit", broken)
        with pytest.warns(RuntimeWarning, match=r"did not compile \(TypeError: no LLVM here\); replays run on numpy"):
            assert speedkernel.enable() is False
        assert not speedkernel.active() and speedkernel._SC_PRE is None and speedkernel._SAT is None
        assert speedkernel._SATF is None and speedkernel._VAP is None and speedkernel._RECT is None
        assert speedkernel._LS is None and speedkernel._CCN is None and speedkernel._CCS is None
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert speedkernel.enable() is False          # tried once: no second warning
    finally:
        for k, v in keep.items():
            setattr(speedkernel, k, v)


def test_replay_with_the_kernel_gives_the_same_windows(plant, kernel, monkeypatch):
    from model.analysis.replay import replay
    from simulator.synthetic import Noise, Operation, Truth, generate
    op = Operation(hours=14, commissioning_minutes=120, gap_after_commissioning_days=3)
    hist = generate(plant, op, Truth(), Noise(), seed=4).history
    rows = []
    run = speedkernel.run
    monkeypatch.setattr(speedkernel, "run", lambda *a: rows.append(len(a[4])) or run(*a))
    ref, got = _both(lambda: replay(hist, plant).windows)
    assert sum(rows) > 10_000             # the replay's speed searches ran in the kernel
    assert len(got) >= 4 and got["status"].eq("ok").sum() >= 3
    num = [c for c in got.columns if pd.api.types.is_numeric_dtype(got[c])]
    pd.testing.assert_frame_equal(ref[num], got[num], check_exact=True)
    pd.testing.assert_frame_equal(ref.drop(columns=num), got.drop(columns=num))
