"""``edge.benchparts.PartTimer``: where a replay's CPU goes (the plant-year bench's ``parts``)."""
from __future__ import annotations

import time

import pytest

from edge.benchparts import TIMED, PartTimer, owner_of, split_rounds
from model import vtasks
from model.analysis.replay import replay
from simulator.synthetic import Noise, Operation, Truth, generate

# CPU clocks read in different threads are summed: a sum of parts may exceed its whole by the
# clocks' granularity per call (thread_time and process_time: well below a microsecond on Linux)
# and by the wrappers' own cost, which lands in the outer part only
CLOCK_SLACK_S = 0.05


def _originals():
    out = {}
    for mod, path, _, _ in TIMED:
        owner, name = owner_of(mod, path)
        out[(mod, path)] = owner.__dict__[name]
    return out


@pytest.fixture(scope="module")
def history(plant):
    """Commissioning, then 10 h of operation: 5 windows of 2 h after the first."""
    op = Operation(hours=12, commissioning_minutes=120, gap_after_commissioning_days=5)
    return generate(plant, op, Truth(), Noise(), seed=5).history


def test_the_part_timer_splits_a_replay_without_changing_it(plant, history):
    """Every part measured, each inside its whole (pass 2's solver and windows inside pass 2, the
    draft's steps inside the draft, the passes inside the replay), one pass-2 and one pass-3 call
    per analysed window, the windows the same as without the timer, the functions put back."""
    before = _originals()
    plain = replay(history, plant)
    with PartTimer() as pt:
        c = time.process_time()
        timed = replay(history, plant)
        cpu = time.process_time() - c
    assert _originals() == before
    assert timed.windows.equals(plain.windows), "the timer changed the replay's windows"
    n = len(timed.windows)
    assert n >= 4
    r = pt.report(cpu, n)
    s, calls = r["cpu_s"], r["calls"]
    assert all(v >= 0 for k, v in s.items() if k not in ("pass2_lockstep", "rest")), s
    assert s["pass2_solver"] > 0 and s["pass2_windows"] > 0 and s["pass3"] > 0 and s["pass1_prepare"] > 0
    assert s["pass2_solver"] + s["pass2_windows"] <= s["pass2"] + CLOCK_SLACK_S
    assert s["pass2_lockstep"] >= -CLOCK_SLACK_S
    draft_steps = (s["pass2_windows_advice_searches"] + s["pass2_windows_advice_trusted_stretch"]
                   + s["pass2_windows_advice_draws"])
    assert draft_steps <= s["pass2_windows_advice_draft"] + CLOCK_SLACK_S
    assert s["pass2_windows_advice_draft"] + s["pass2_windows_fouling_calibration"] \
        <= s["pass2_windows"] + CLOCK_SLACK_S
    assert s["pass3_forecast"] + s["pass3_dead_band"] + s["pass3_surrogate_tracker"] <= s["pass3"] + CLOCK_SLACK_S
    assert s["pass1_prepare"] + s["pass2"] + s["pass3"] <= cpu + CLOCK_SLACK_S
    assert s["rest"] == pytest.approx(cpu - s["pass1_prepare"] - s["pass2"] - s["pass3"])
    assert s["replay"] == cpu
    # every window prepared, analysed, drafted and its dead band decided once (all of them calibrate
    # here), one chunk through pass 2 and pass 3; the kept recommendations' runs once for the chunk
    assert set(timed.windows["status"]) == {"ok"}
    for part in ("pass1_prepare", "pass2_windows", "pass2_windows_advice_draft"):
        assert calls[part] == n, part
    kept = timed.windows["advice_note"].str.startswith("kept the previous recommendation").any()
    assert calls["pass3_dead_band"] == n + int(kept)
    assert calls["pass2"] == 1 and calls["pass2_solver"] >= 3     # one lockstep chunk, its rounds
    assert calls["pass3"] == 1
    assert r["ms_per_window"]["replay"] == pytest.approx(1e3 * cpu / n)
    assert r["share_of_replay"]["replay"] == pytest.approx(1.0)
    # the solver's rounds (the initial calibration's, passes 1-3's): main rounds in every run, all
    # of them inside the replay's CPU time, the observer taken away with the wrappers
    sr = r["solver_rounds"]
    assert vtasks.round_observer is None
    assert sr["runs"] > 0 and sr["main"]["rounds"] >= sr["runs"]
    assert sum(sr[k]["cpu_s"] for k in ("main", "tail", "head")) <= cpu + CLOCK_SLACK_S
    assert sr["main"]["row_rounds"] > sr["tail"]["row_rounds"] >= sr["tail"]["rounds"]
    assert sr["main"]["ms_per_window"] == pytest.approx(1e3 * sr["main"]["cpu_s"] / n)


def test_the_part_timer_puts_the_functions_back_when_the_block_raises():
    before = _originals()
    with pytest.raises(RuntimeError, match="^inside$"):
        with PartTimer():
            assert _originals() != before
            raise RuntimeError("inside")
    assert _originals() == before


def test_a_part_that_cannot_be_found_leaves_nothing_wrapped():
    """A misspelt entry fails at the start and unwraps the entries before it."""
    before = _originals()
    with pytest.raises(KeyError):
        with PartTimer(TIMED + (("model.analysis.chain", "AnalysisChain.no_such_step", "x", "process"),)):
            pass                                         # pragma: no cover - not reached
    assert _originals() == before


def test_the_dead_bands_draws_and_solver_calls_are_pass_threes_not_the_drafts():
    """``_draws_at`` and the merged solver calls run in pass 2 and in the dead band (pass 3):
    inside pass 3 the pass-2 parts are not counted (they are in pass 3's time)."""
    import sys
    import types
    mod = types.ModuleType("benchparts_probe")
    mod.draws = lambda: sum(range(1000))
    mod.solve = lambda: sum(range(1000))
    mod.finish = lambda: (mod.draws(), mod.solve())
    sys.modules[mod.__name__] = mod
    try:
        with PartTimer(((mod.__name__, "finish", "pass3", "process"),
                        (mod.__name__, "draws", "pass2_windows_advice_draws", "thread"),
                        (mod.__name__, "solve", "pass2_solver", "process"))) as pt:
            mod.draws()                 # the draft's
            mod.solve()                 # pass 2's
            mod.finish()                # the dead band's, inside pass 3
            mod.finish()
        calls = pt.report(1.0, 1)["calls"]
        assert calls == {"pass3": 2, "pass2_windows_advice_draws": 1, "pass2_solver": 1}
    finally:
        del sys.modules[mod.__name__]


def test_a_solver_runs_rounds_split_into_main_tail_and_head():
    """``split_rounds``: rounds with at least a tenth of the largest round's rows are the run's
    main rounds wherever they are; the smaller ones after the (first) largest its tail, before it
    its head."""
    got = split_rounds([(5, 0.5), (100, 2.0), (40, 1.0), (5, 0.25), (100, 2.0), (3, 0.125), (9, 0.0625)])
    assert got == {"main": (3, 240, 5.0), "tail": (3, 17, 0.4375), "head": (1, 5, 0.5)}
    assert split_rounds([]) == {"main": (0, 0, 0.0), "tail": (0, 0, 0.0), "head": (0, 0, 0.0)}


class _Sheet:
    """A flowsheet stand-in for ``vtasks.run``: an evaluation answers each row with its T_m."""

    def evaluate(self, idx, T_m, T_c, ms=None, full=False):
        return {"T_m": T_m}


def test_the_solver_hands_each_runs_rounds_to_the_observer_and_part_timer_sums_them():
    """``vtasks.round_observer`` gets a run's rounds (rows per round: every live task's request
    together) when the run ends; the part timer sets it for its block, sums the kinds and puts the
    one before it back."""
    import numpy as np
    fs = _Sheet()

    def task(rows: int, steps: int):
        for _ in range(steps):
            got = yield vtasks.Eval(fs, np.arange(rows), np.full(rows, 300.0), np.full(rows, 320.0))
            assert len(got["T_m"]) == rows

    seen = []
    vtasks.round_observer = seen.append
    try:
        vtasks.run(task(100, 1), task(5, 3))
    finally:
        vtasks.round_observer = None
    assert [r for r, _ in seen[0]] == [105, 5, 5] and all(c >= 0 for _, c in seen[0])
    before = lambda rounds: None                     # noqa: E731 - another observer, kept
    vtasks.round_observer = before
    try:
        with PartTimer(()) as pt:
            vtasks.run(task(100, 1), task(5, 3))
            vtasks.run(task(20, 2))
        assert vtasks.round_observer is before
    finally:
        vtasks.round_observer = None
    sr = pt.report(1.0, 1)["solver_rounds"]
    assert sr["runs"] == 2
    assert (sr["main"]["rounds"], sr["main"]["row_rounds"]) == (3, 145)
    assert (sr["tail"]["rounds"], sr["tail"]["row_rounds"]) == (2, 10)
    assert (sr["head"]["rounds"], sr["head"]["row_rounds"]) == (0, 0)
