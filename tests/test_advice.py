"""Advice that holds on a plant whose compressors are not the data sheet's (issue #8): judged by
regret against the simulator's truth optimum; low confidence where the data cannot tell; one chain
for the gateway and replay."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from model.analysis.chain import AnalysisChain, ChainSettings
from model.calibration import calibrate, calibration_frame, spec_from_config
from model.dpfit import fit_dp_clean
from model.measured import process

# issue #8 targets, over the windows where the advice is confident
MEAN_REGRET_PCT = 0.2
MAX_REGRET_PCT = 0.6
LOSS_PCT = 0.1             # following the advice loses more than this ...
LOSS_SHARE = 0.05          # ... in at most this share of all windows


@pytest.fixture(scope="module")
def judged():
    """Six days of the 'speed_peak' plant (its optimum lies ~3 bar below the data sheet's), the
    bench's history (edge/bench_advice.py) in short: a day at 16 bar(g), one at 10 (the HS flat
    out), one at 13, then back at 16; replayed causally and judged on the truth."""
    from edge.bench_advice import run_family
    return run_family("speed_peak", 6.0, ((0.0, 16.0), (1.0, 10.0), (2.0, 13.0), (3.0, 16.0)))


def test_regret_targets_hold_on_a_plant_with_other_compressor_curves(judged):
    j, w = judged["judged"], judged["windows"]
    m = judged["metrics"]
    conf = j[j["confident"]]
    assert len(conf) >= 4, m
    assert conf["regret_pct"].mean() <= MEAN_REGRET_PCT, m
    assert conf["regret_pct"].max() <= MAX_REGRET_PCT, m
    assert (j["true_dCOP_pct"] < -LOSS_PCT).mean() <= LOSS_SHARE, m
    # where it is confident it moves the plant the right way: predicted and true changes agree
    moved = conf[conf["p_m_sp_rec_barg"] != conf["p_m_sp_actual_barg"]]
    # a confident move costs COP in at most the share of the windows
    assert (moved["true_dCOP_pct"] < -LOSS_PCT).sum() <= LOSS_SHARE * len(j), m
    # not confident means: keep the current set point (the contract of windows.csv)
    nc = w[(w["status"] == "ok") & ~w["advice_confident"].astype(bool)]
    assert (nc["p_m_sp_opt_barg"] == nc["p_m_sp_actual_barg"]).all()
    assert (nc["advice_note"].str.len() > 0).all()
    # the first day (one set point only) cannot show where the optimum lies: it says so
    first = w[pd.to_datetime(w["window_start"]) < pd.to_datetime(w["window_start"].iloc[0]) + pd.Timedelta(hours=20)]
    assert not first["advice_confident"].astype(bool).any()
    assert first["advice_note"].str.contains("the data do not show where the optimum lies").any()
    # once the plant has run at three set points the advice speaks in most windows
    late = w[pd.to_datetime(w["window_start"]) >= pd.to_datetime(w["window_start"].iloc[0]) + pd.Timedelta(days=3)]
    assert late["advice_confident"].astype(bool).mean() >= 0.6, m
    assert m["R_th_f_abs_error_max_K_per_kW"] <= 0.2e-3          # fouling accuracy holds
    # a held recommendation stays put: a confident window that kept the previous recommendation
    # carries exactly the last confident window's value (not the window's mean set point)
    last, held = None, 0
    for _, r in w[w["status"] == "ok"].iterrows():
        if r["advice_confident"]:
            if str(r["advice_note"]).startswith("kept the previous recommendation"):
                assert r["p_m_sp_opt_barg"] == last, (r["window_start"], r["p_m_sp_opt_barg"], last)
                held += 1
            last = r["p_m_sp_opt_barg"]
    assert held >= 1


def test_the_kept_recommendations_model_runs_together_change_nothing(judged, monkeypatch):
    """Pass 3 runs the dead band's model runs at kept recommendations of a chunk's windows together
    (``AnalysisChain.finish_chunk``, ``settle_kept`` in lockstep); one at a time, as the gateway
    settles a window, gives the same windows."""
    import model.analysis.chain as chain_mod
    from edge.plantfile import load_plant
    from model.analysis.replay import replay
    shipped = chain_mod.settle_kept
    sizes = []

    def recorded(settlings):
        sizes.append(len(settlings))
        return shipped(settlings)

    def one_at_a_time(settlings):                  # settle_kept of one: no lockstep
        return [a for st in settlings for a in shipped([st])]
    hist, params = judged["history"], load_plant()
    monkeypatch.setattr(chain_mod, "settle_kept", recorded)
    together = replay(hist, params).windows
    assert max(sizes) >= 2, sizes                   # several kept windows in one chunk
    monkeypatch.setattr(chain_mod, "settle_kept", one_at_a_time)
    alone = replay(hist, params).windows
    assert together.equals(alone)
    assert together.equals(judged["windows"])


def _commissioned(plant, hist):
    """The replay's commissioning on the first 90 usable minutes: (chain, state, processed)."""
    proc = process(hist, plant)
    usable = proc["usable"].to_numpy()
    init = np.zeros(len(hist), bool)
    init[np.flatnonzero(usable)[:90]] = True
    chain = AnalysisChain(plant, spec_from_config(plant.extra, "fouling"),
                          ChainSettings.from_config(plant.extra))
    ts = pd.to_datetime(hist["timestamp"], utc=True)
    learner = chain.commissioning_learner(hist.loc[init].assign(timestamp=ts[init]))
    data = calibration_frame(hist, proc, init)
    initial = calibrate(data, learner.apply(plant), spec_from_config(plant.extra, "initial"))
    dp = fit_dp_clean(data["V_source"], data["dp_source_bar"])
    return chain, chain.new_state(initial.to_dict(), dp.to_dict(), learner), proc, initial, dp, learner


def test_low_confidence_when_the_operating_point_leaves_the_learned_region(plant):
    """Curves learned at 16 bar(g); the plant then runs at 10 bar(g) (the HS flat out, pressure
    ratios the data has not seen): the advice says so and keeps the set point."""
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    cfg = load_simulator_config().with_compressor_family("speed_peak")
    cfg = replace(cfg, control=replace(cfg.control, p_m_sp_schedule=((0.0, 16.0), (0.5, 10.0))),
                  fouling=replace(cfg.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0))
    hist = export_history(0.75, cfg=cfg).history
    chain, state, proc, *_ = _commissioned(plant, hist)
    ts = pd.to_datetime(hist["timestamp"], utc=True)
    usable = proc["usable"].to_numpy()
    day0 = ts[0]

    def window(h0, h1):
        m = usable & (ts >= day0 + pd.Timedelta(hours=h0)).to_numpy() & (ts < day0 + pd.Timedelta(hours=h1)).to_numpy()
        return chain.window(hist.loc[m].assign(timestamp=ts[m]), state)
    for h in range(2, 12, 2):                      # learn the 16-bar region
        window(h, h + 2)
    before = window(10, 12)
    assert before.coverage_share == 1.0
    leave = window(12.5, 14.5)                     # 10 bar(g): HS at 1800 rpm, p_m floating
    assert leave.status == "ok" and leave.optimization_ok
    assert leave.coverage_share < 0.8
    assert not leave.advice_confident
    assert "operating point outside the region the learned curves cover" in leave.advice_note
    assert leave.p_m_sp_opt_barg == leave.p_m_sp_actual_barg
    assert leave.dCOP_opt_pct == 0.0 and leave.dQ_sink_opt_pct == 0.0
    vals = leave.advisory_values()
    assert vals["p_m_sp_rec"] == pytest.approx(10.0, abs=0.01) and vals["dCOP_pct"] == 0.0
    # a window that cannot be confident does not evaluate the previous recommendation: whatever
    # it is, the advice is the same, its uncertainty the model optimum's, and nothing is solved
    from model.analysis import advice as advice_mod
    m = usable & (ts >= day0 + pd.Timedelta(hours=14.5)).to_numpy() & (ts < day0 + pd.Timedelta(hours=16.5)).to_numpy()
    partial = chain.analyse(chain.prepare(hist.loc[m].assign(timestamp=ts[m]), state))
    d = partial.draft
    assert d.reasons                               # outside the learned region: not confident
    solved = []
    real = advice_mod.Evaluator
    advice_mod.Evaluator = lambda *a, **k: solved.append(1) or real(*a, **k)
    try:
        got = [advice_mod.settle_advice(d, prev) for prev in (None, d.sp_opt, d.actual, 0.5 * (d.lo + d.hi))]
    finally:
        advice_mod.Evaluator = real
    assert not solved
    for a in got:
        assert repr(a) == repr(got[0])
        assert not a.confident and a.p_m_sp_rec_barg == d.actual and a.dCOP_sd_pct == d.sd_opt
        assert a.evaluations == d.evaluations
    # the window's advice detail (the gateway's advice table) is asdict's, by value, also with a
    # trusted stretch (a dataclass holding tuples)
    import dataclasses
    from model.analysis.chain import _plain
    mb = usable & (ts >= day0 + pd.Timedelta(hours=10)).to_numpy() & (ts < day0 + pd.Timedelta(hours=12)).to_numpy()
    ab = advice_mod.settle_advice(chain.analyse(chain.prepare(hist.loc[mb].assign(timestamp=ts[mb]), state)).draft)
    assert ab.trusted is not None and len(ab.trusted.path) > 3
    for a in (got[0], ab):
        assert repr(_plain(a)) == repr(dataclasses.asdict(a))


def test_the_gateway_and_replay_give_identical_window_results(plant, tmp_path):
    """The gateway (samples stored through its ingest path, windows read back from the history
    database, state in the state directory) and replay produce the same window results for the
    same data: one chain."""
    from edge import statefiles
    from edge.aggregate import Sample
    from edge.config import load_config
    from edge.service import ModelAdvisor, StateDir
    from edge.store import HistoryStore
    from model.analysis.replay import ReplaySettings, replay
    from simulator.export import export_history
    from pathlib import Path

    hist = export_history(0.4).history                     # 9.6 h of the default plant
    settings = ReplaySettings(window_hours=2.0, min_samples=30)
    res = replay(hist, plant, settings)
    ok = res.windows[res.windows["status"] == "ok"]
    assert len(ok) >= 3
    # the gateway, commissioned with the replay's initial results and commissioning curves
    _, _, _, initial, dp, learner = _commissioned(plant, hist)
    assert initial.params == pytest.approx(res.initial.params, rel=1e-12)
    state = tmp_path / "state"
    statefiles.write_state(statefiles.INITIAL_CALIBRATION, initial.to_dict(), state)
    statefiles.write_state(statefiles.DP_CLEAN, dp.to_dict(), state)
    statefiles.write_state(statefiles.COMPRESSORS, learner.to_dict(), state)
    repo = Path(__file__).resolve().parents[1]
    cfg = replace(load_config(repo / "config" / "gateway.yaml"), state_dir=state,
                  history_db=tmp_path / "h.sqlite", min_window_samples=30)
    store = HistoryStore(cfg.history_db, cfg.history_retention_days).open()
    try:
        adv = ModelAdvisor(cfg, store, StateDir(state))
        ts = pd.to_datetime(hist["timestamp"], utc=True)
        samples = []
        for t, rec in zip(ts, hist.drop(columns=["timestamp"]).to_dict("records")):
            vals = {k: float(v) for k, v in rec.items()}
            bad = {k: "nan" for k, v in vals.items() if not math.isfinite(v)}
            samples.append(Sample(t.timestamp(), vals, bad, 12, 12, 0, 0, ""))
        for k in range(0, len(samples), 30):
            adv.ingest(samples[k:k + 30])
        for _, w in ok.iterrows():
            a, b = pd.Timestamp(w["window_start"]), pd.Timestamp(w["window_end"])
            adv.window_s = (b - a).total_seconds() + 30.0     # exactly this window's samples
            got = adv.advise(b.timestamp())
            d = got.detail["window"]
            assert d["n_samples"] == w["n_samples"]
            for col in ("R_th_f_K_per_kW", "CF_dp_f", "COP_adaptive", "p_m_sp_opt_barg",
                        "dCOP_opt_pct", "dCOP_opt_sd_pct", "coverage_share"):
                assert d[col] == pytest.approx(w[col], rel=1e-9, abs=1e-12), col
            assert d["advice_confident"] == bool(w["advice_confident"])
            assert got.values["p_m_sp_rec"] == pytest.approx(w["p_m_sp_opt_barg"], rel=1e-12)
            assert got.low_confidence == (not bool(w["advice_confident"]))
    finally:
        store.close()


def test_a_drifting_flow_meter_makes_the_window_unusable_for_calibration(plant):
    """Issue #9 item 17: a window whose measured heat balance Q_sink - Q_source - W does not close
    within calibration.heat_balance_limit_pct (5 % of the heat output) is not calibrated, and says
    why; the same window with the meter right is."""
    from simulator.export import export_history
    hist = export_history(0.25).history
    chain, state, proc, *_ = _commissioned(plant, hist)
    ts = pd.to_datetime(hist["timestamp"], utc=True)
    m = proc["usable"].to_numpy() & (ts >= ts[0] + pd.Timedelta(hours=3)).to_numpy()
    good = hist.loc[m].assign(timestamp=ts[m])
    res = chain.window(good, state)
    assert res.status == "ok" and abs(res.heat_balance_pct) < 1.0
    drift = good.assign(V_sink=good["V_sink"] * 1.08)      # the sink flow meter reads 8 % high
    bad = chain.window(drift, state)
    assert bad.status.startswith("failed: measured heat balance does not close (+")
    assert "limit 5 %): check the water flow meters and temperatures" in bad.status
    assert 6.0 < bad.heat_balance_pct < 9.0
    assert not bad.calibration_ok and not bad.optimization_ok
    assert math.isnan(bad.R_th_f_K_per_kW)


def test_the_trusted_stretch_is_where_the_plant_has_run_plus_a_share_of_it(plant):
    """The search's p_m stretch (model.analysis.advice.trusted_stretch): at one set point the plant
    has shown no slope along p_m and the advice says so; after hours at a second set point the
    stretch covers both, extended by extrapolation_share of its length (at most
    extrapolation_max_bar), and the advice is confident."""
    from model.analysis.advice import AdviceSettings
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    s = AdviceSettings()
    cfg = load_simulator_config().with_compressor_family("speed_peak")
    cfg = replace(cfg, control=replace(cfg.control, p_m_sp_schedule=((0.0, 16.0), (0.5, 13.0))),
                  fouling=replace(cfg.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0))
    hist = export_history(1.0, cfg=cfg).history
    chain, state, proc, *_ = _commissioned(plant, hist)
    ts = pd.to_datetime(hist["timestamp"], utc=True)
    usable = proc["usable"].to_numpy()

    def window(h0, h1):
        m = usable & (ts >= ts[0] + pd.Timedelta(hours=h0)).to_numpy() \
            & (ts < ts[0] + pd.Timedelta(hours=h1)).to_numpy()
        return chain.window(hist.loc[m].assign(timestamp=ts[m]), state)
    first = [window(h, h + 2) for h in range(2, 12, 2)]
    assert all(r.status == "ok" and not r.advice_confident for r in first)
    assert all(r.p_m_sp_opt_barg == r.p_m_sp_actual_barg for r in first), [(r.p_m_sp_opt_barg, r.p_m_sp_actual_barg) for r in first]
    assert any("the data do not show where the optimum lies" in r.advice_note for r in first)
    second = [window(h, h + 2) for h in range(12, 24, 2)]
    both = second[-1]
    t = both.detail["advice"]["trusted"]
    lo, hi, ext = t["covered_lo"], t["covered_hi"], t["extension"]
    assert lo < 13.0 and hi > 16.0                  # both set points are covered
    assert ext == pytest.approx(min(s.extrapolation_max_bar, s.extrapolation_share * (hi - lo)))
    assert both.advice_trusted_lo_barg == pytest.approx(lo - ext)
    assert both.advice_trusted_hi_barg == pytest.approx(hi + ext)
    assert lo - ext - 1e-6 <= both.p_m_sp_model_opt_barg <= hi + ext + 1e-6
    # the search stays in the stretch: an optimum at its end with the COP still rising beyond is
    # not confident, and says what a step there would gain
    if not both.advice_confident:
        assert "beyond the p_m the learned curves vouch for" in both.advice_note
        assert both.p_m_sp_opt_barg == both.p_m_sp_actual_barg


def test_a_short_covered_stretch_at_the_hs_plateau_still_brackets_the_optimum():
    """The min_covered_bar rule (model.analysis.advice.too_short): a covered stretch shorter than
    min_covered_bar is not enough to place the optimum, unless it starts at the HS plateau (several
    set points give the same lowest p_m: nothing lower can be held) and the optimum lies at least
    BRACKET_BAR below its top (the plant has run on both sides of it)."""
    from model.analysis.advice import BRACKET_BAR, AdviceSettings, stretch_from_path, too_short
    s = AdviceSettings()
    # on the plateau: set points 8 ... 12.5 all give p_m 12.58; covered from there to 14.5
    plateau = [(12.58, 0.05, sp) for sp in (8.0, 9.0, 10.0, 11.0, 12.0, 12.5)]
    above = [(13.0, 0.3, 13.0), (14.0, 0.8, 14.0), (14.5, 0.9, 14.5), (15.0, 1.4, 15.0), (16.0, 2.5, 16.0)]
    t = stretch_from_path(plateau + [(12.58, 0.05, math.nan)] + above, s)
    assert t.closed_below
    assert (t.covered_lo, t.covered_hi) == (12.58, 14.5)
    assert t.covered_hi - t.covered_lo < s.min_covered_bar
    assert not too_short(t, 12.58, s)                    # the plateau itself
    assert not too_short(t, 14.5 - BRACKET_BAR, s)       # inside, with data BRACKET_BAR above it
    assert too_short(t, 14.5 - BRACKET_BAR + 0.05, s)    # near the top: the data end just above it
    assert too_short(t, 14.5 + t.extension / 2, s)       # in the extension: no data above it
    # the same covered lengths without a plateau: one row per set point
    t2 = stretch_from_path([(12.58, 0.05, 12.5)] + above, s)
    assert not t2.closed_below
    assert too_short(t2, 12.58, s) and too_short(t2, 13.0, s)
    # a plateau the plant has not run at does not close the stretch
    t3 = stretch_from_path([(x, 1.5, sp) for x, _, sp in plateau] + above, s)
    assert not t3.closed_below and t3.covered_lo == 13.0
    # a long enough stretch is never too short
    t4 = stretch_from_path([(10.0, 0.2, 10.0), (11.5, 0.5, 11.5), (13.5, 0.4, 13.5)], s)
    assert not too_short(t4, 16.0, s)


def test_a_stretch_of_exactly_the_limit_is_judged_alike_whatever_its_last_bit():
    """The trusted path's p_m steps are multiples of its set-point grid (0.5 bar), and so are
    min_covered_bar and gap_max_bar (3 bar): a covered stretch of six steps came out 3.0 +- 1.5e-13
    bar in a replay (the p_m are weighted means of solved rows), and before stop 51 the sign of that
    rounding decided whether the window was confident — the note then said 'run over 14.22-17.22 bar(g)
    only (less than 3 bar)'. Both limits now compare with GRID_TOL_BAR."""
    from model.analysis.advice import GRID_TOL_BAR, AdviceSettings, stretch_from_path, too_short
    s = AdviceSettings()
    assert (s.min_covered_bar, s.gap_max_bar, s.path_step_bar) == (3.0, 3.0, 0.5)
    lo = 14.217713
    for err in (-1.5e-13, 0.0, 1.5e-13):
        hi = lo + 3.0 + err
        path = [(lo + 0.5 * k, 0.4, lo + 0.5 * k) for k in range(6)] + [(hi, 0.4, hi), (hi + 0.5, 1.6, hi + 0.5)]
        t = stretch_from_path(path, s)
        assert t.covered_hi - t.covered_lo == pytest.approx(3.0, abs=2e-13)
        assert not too_short(t, lo + 1.0, s), err
        # a hole of exactly gap_max_bar between two covered points is not wider than it
        t_gap = stretch_from_path([(lo, 0.4, lo)] + [(lo + 0.5 * k, 1.6, lo + 0.5 * k) for k in range(1, 6)]
                                  + [(hi, 0.4, hi)], s)
        assert t_gap.gaps == (), err
    # half a step shorter is short, and half a step wider is a gap, as before
    short = stretch_from_path([(lo + 0.5 * k, 0.4, lo + 0.5 * k) for k in range(6)], s)
    assert short.covered_hi - short.covered_lo == pytest.approx(2.5) and too_short(short, lo + 1.0, s)
    wide = stretch_from_path([(lo, 0.4, lo)] + [(lo + 0.5 * k, 1.6, lo + 0.5 * k) for k in range(1, 7)]
                             + [(lo + 3.5, 0.4, lo + 3.5)], s)
    assert wide.gaps == ((lo, lo + 3.5),)
    assert 0.0 < GRID_TOL_BAR <= 1e-6     # far below anything a plant could hold


def _refused_with_its_key(tmp_path, key: str, value, message: str) -> None:
    """advice.<key> = value is refused by AdviceSettings with ``message``, and by load_plant with the
    file's name before it (the line hp-edge prints when it exits 2)."""
    import yaml

    from edge.plantfile import PlantFileError, load_plant
    from model.analysis.advice import AdviceError, AdviceSettings
    with pytest.raises(AdviceError) as exc:
        AdviceSettings.from_dict({key: value})
    assert str(exc.value) == message
    doc = yaml.safe_load((Path(__file__).resolve().parent.parent / "config" / "plant.yaml").read_text())
    doc["advice"] = {key: value}
    f = tmp_path / "plant.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(PlantFileError) as exc:
        load_plant(f)
    assert str(exc.value) == f"{f}: {message}"


@pytest.mark.parametrize("value, message", [
    (0, "key 'advice.path_step_bar': must be >= 0.05, got 0"),
    (-1, "key 'advice.path_step_bar': expected a number >= 0, got -1"),
])
def test_a_bad_path_step_is_refused_with_its_key(tmp_path, value, message):
    """A zero step would make the trusted stretch's grid endless: refused when plant.yaml is read,
    naming the file and the key (hp-edge exits 2 with this line)."""
    _refused_with_its_key(tmp_path, "path_step_bar", value, message)


def test_the_shape_error_weighs_each_stage_by_its_share_of_the_work(plant):
    """advice._shape_at: per row and stage an eta_is error of shape_k x the learner's shape_sd
    (tests/test_compressors.py checks its definition), as a relative error of the stage's work
    weighted by the stage's share of the work; the stages in quadrature, the rows averaged; the
    search maximises COP x (1 - search_k x that / 100)."""
    from model.analysis.advice import AdviceSettings, _scorer, _shape_at
    from model.optimize import Point

    class Learner:                       # the parts of CompressorLearner the shape error reads
        class s:
            prior_sd = 0.03
        share = {"LS": np.array([0.1, 0.5]), "HS": np.array([0.0, 1.0])}

        def learned(self, stage, curve):
            return True

        def shape_sd(self, stage, pi, n):
            return self.s.prior_sd * self.share[stage]

    frame = pd.DataFrame({"p_e_bar": [3.0, 3.0], "p_m_bar": [9.0, 8.0], "p_c_bar": [40.0, 40.0],
                          "N_LS_rpm": [1000.0, 1100.0], "N_HS_rpm": [1200.0, 1500.0],
                          "W_LS_kW": [300.0, 320.0], "W_HS_kW": [500.0, 560.0],
                          "eta_is_LS": [0.75, 0.74], "eta_is_HS": [0.72, 0.70]})
    p = Point(9.0, 5.0, 4000.0, 800.0, False, frame)
    s = AdviceSettings(shape_k=2.0, search_k=1.5)
    u = {st: 2.0 * 0.03 * Learner.share[st] for st in ("LS", "HS")}
    per_row = [math.hypot(300 / 800 * u["LS"][0] / 0.75, 500 / 800 * u["HS"][0] / 0.72),
               math.hypot(320 / 880 * u["LS"][1] / 0.74, 560 / 880 * u["HS"][1] / 0.70)]
    expected = 100.0 * (per_row[0] + per_row[1]) / 2
    assert _shape_at(Learner(), plant, {}, s, p) == pytest.approx(expected, rel=1e-12)
    assert _scorer(Learner(), plant, {}, s)(p) == pytest.approx(5.0 * (1 - 0.015 * expected), rel=1e-12)
    # off: the plain COP
    assert _shape_at(Learner(), plant, {}, replace(s, shape_k=0.0), p) == 0.0
    assert _scorer(Learner(), plant, {}, replace(s, shape_k=0.0)) is None
    assert _scorer(Learner(), plant, {}, replace(s, search_k=0.0)) is None


# the window's samples placed around their representative points (advice.sample_spread), against
# every sample solved at the path's set points: the LS pressure ratio is exact at a common p_m, the
# HS ratio and the speeds are read at the actual set points (measured on this half day: HS ratio
# 2.2e-4 relative, speeds 0.004 of nominal, distances 0.003 margins)
SPREAD_PI_HS_REL_TOL = 1e-3
SPREAD_N_TOL = 0.01          # of the nominal speed
SPREAD_DIST_TOL = 0.01       # coverage distance [margins]


def test_the_trusted_path_judges_the_windows_samples_not_their_means(plant):
    """A path point's coverage distance is the largest over its rows, and a group's mean lies inside
    its group: on the 8 representative means alone the covered stretch came out wider than on the
    window's samples (0.5 bar, and confident, in 6 of 84 windows of the replay bench's confident
    reference before stop 52). The trusted path now places the samples around their means
    (advice.spread_at: the spread at one common set point, where the means are solved for the path
    anyway) and judges those: here as every sample solved at every path set point, in a window at
    one set point and in one across a set-point step (a sample's speed at its own set point is not
    its speed at the group's)."""
    from model.analysis.advice import (AdviceSettings, _distances, _operating_points, check_rows,
                                       sample_spread, spread_at)
    from model.analysis.compressors import CompressorLearner, observe
    from model.optimize import Evaluator
    from simulator.config import load_simulator_config
    from simulator.export import export_history
    cfg = load_simulator_config()
    cfg = replace(cfg, control=replace(cfg.control, p_m_sp_schedule=((0.0, 16.0), (0.25, 13.0))))
    hist = export_history(0.5, cfg=cfg).history
    data = hist.loc[process(hist, plant)["usable"].to_numpy()].reset_index(drop=True)
    ts = pd.to_datetime(data["timestamp"], utc=True)
    learner = CompressorLearner(plant)
    learner.update(observe(data.assign(timestamp=ts), plant))
    s = AdviceSettings()
    h = ((ts - ts.iloc[0]) / pd.Timedelta(hours=1)).to_numpy()
    seen_means_wrong = False
    for h0 in (0.0, 5.0):                  # two hours at 16 bar(g); the step to 13 bar(g) at 6 h
        c = check_rows(data.loc[(h >= h0) & (h < h0 + 2.0)], s)
        assert len(c.data) == s.check_rows and len(c.parts) == s.representative_points
        ev = Evaluator(c.rows, c.w, plant)
        full = Evaluator(c.data, np.ones(len(c.data)), plant, guess_from=ev)
        xs = [float(x) for x in np.arange(11.0, 19.01, s.path_step_bar)]
        reps, samples = ev.at_many(xs), full.at_many(xs)
        assert all(p.ok for p in reps + samples)
        spread = spread_at(ev, c.data, c.parts, plant, [None, *xs], c.actual)
        order = np.concatenate(c.parts)
        for st, pi_tol in (("LS", 1e-12), ("HS", SPREAD_PI_HS_REL_TOL)):
            g, r_pi, d_n, (n_lo, n_hi) = spread[st]
            assert np.array_equal(g, np.concatenate([np.full(len(p), k) for k, p in enumerate(c.parts)]))
            for p, f in zip(reps, samples):
                pi_g, n_g = _operating_points(p, plant)[st]
                pi_s, n_s = _operating_points(f, plant)[st]
                assert np.max(np.abs(pi_g[g] * r_pi / pi_s[order] - 1.0)) <= pi_tol, (h0, st, p.sp)
                n = np.clip(n_g[g] + d_n, n_lo, n_hi)
                assert np.max(np.abs(n - n_s[order])) <= SPREAD_N_TOL, (h0, st, p.sp)
        on_means = np.array(_distances(learner, plant, {}, reps))
        placed = np.array(_distances(learner, plant, {}, reps, spread))
        every = np.array(_distances(learner, plant, {}, samples))
        assert np.max(np.abs(placed - every)) <= SPREAD_DIST_TOL, h0
        assert np.array_equal(placed <= 1.0, every <= 1.0), h0
        seen_means_wrong |= bool(((on_means <= 1.0) & (every > 1.0)).any())
        # the trusted path's rule: covered where min_coverage_share of the samples lie inside
        share = s.min_coverage_share
        placed_q = np.array(_distances(learner, plant, {}, reps, spread, share=share, w=ev.w))
        every_q = np.array(_distances(learner, plant, {}, samples, share=share, w=full.w))
        assert np.max(np.abs(placed_q - every_q)) <= SPREAD_DIST_TOL, h0
        assert np.array_equal(placed_q <= 1.0, every_q <= 1.0), h0
        assert np.all(placed_q <= placed) and np.all(every_q <= every)
    # the case the spread is for: a set point the means call covered and the samples do not
    assert seen_means_wrong
    # every check row its own group: the path runs on the samples themselves
    one = [np.array([i]) for i in range(len(c.data))]
    assert sample_spread(full.at(16.0), full.at(16.0), one, plant) is None
    assert spread_at(full, c.data, one, plant, xs, c.actual) is None


def test_the_distance_within_a_share_of_the_rows_is_a_weighted_quantile():
    """advice.within_share: per point the smallest distance within which at least the share of the
    rows' weight lies (the trusted path's rule: covered where min_coverage_share of the window's
    samples lie in the covered region, so that one sample outside does not cut the stretch)."""
    from model.analysis.advice import within_share
    d = np.array([[0.5, 3.0, 0.2, 0.9, 1.5], [np.inf, 0.1, 0.2, 0.3, 0.4]])
    ones = np.ones(5)
    assert within_share(d, ones, 0.8).tolist() == [1.5, 0.4]       # 4 of 5 rows within
    assert within_share(d, ones, 0.6).tolist() == [0.9, 0.3]       # 3 of 5
    assert within_share(d, ones, 1.0).tolist() == [3.0, np.inf]    # all: the largest
    w = np.array([1.0, 1.0, 1.0, 1.0, 6.0])                        # the last row is 60 % of the weight
    assert within_share(d, w, 0.8).tolist() == [1.5, 0.4]
    assert within_share(d, w, 0.3).tolist() == [0.9, 0.3]
    assert within_share(d, np.array([1.0, 1.0, 1.0, 1.0, 1.0]), 0.8 - 1e-15).tolist() == [1.5, 0.4]


@pytest.mark.parametrize("value, message", [
    (1.5, "key 'advice.min_coverage_share': must be > 0 and <= 1, got 1.5"),
    (0, "key 'advice.min_coverage_share': must be > 0 and <= 1, got 0"),
])
def test_a_coverage_share_outside_zero_to_one_is_refused_with_its_key(tmp_path, value, message):
    """min_coverage_share is a share of the window's samples (the confidence rule and, since stop
    52, the trusted path's): a value above 1 would make both silently mean 'all of them'; refused
    when plant.yaml is read, naming the file and the key."""
    from model.analysis.advice import AdviceSettings
    _refused_with_its_key(tmp_path, "min_coverage_share", value, message)
    assert AdviceSettings.from_dict({"min_coverage_share": 1}).min_coverage_share == 1.0
