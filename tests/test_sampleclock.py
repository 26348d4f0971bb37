"""Sample-clock plausibility (issue 9 item 6): corrupt reads, glitches and clocks going back never
reach the history; a lasting jump is accepted as a clock correction."""
from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.sampleclock import ClockPolicy, SampleClock

T0 = 1_709_251_200.0          # 2024-03-01T00:00:00Z: the simulator's plant clock at start
HOST = 1_790_000_000.0        # the host clock, later than the plant clock (as in the tests)
SPEED = 600.0                 # plant seconds per monotonic second (the accelerated simulator)
SCAN = 0.05                   # monotonic seconds between scans


def steady(clock: SampleClock, n: int, t0: float = T0, m0: float = 0.0, rate: float = SPEED,
           scan: float = SCAN) -> tuple[float, float]:
    """Feed n good readings; returns the last (t, m)."""
    t, m = t0, m0
    for k in range(n):
        t, m = t0 + k * rate * scan, m0 + k * scan
        v = clock.check(t, m, HOST)
        assert v.t == t and not v.rejected, v
    return t, m


def test_a_corrupt_read_0xffff_0xffff_is_rejected_and_never_accepted():
    c = SampleClock(ClockPolicy(confirm_s=1.0))
    t, m = steady(c, 10)
    for k in range(1, 100):                  # even when it persists far beyond confirm_s
        v = c.check(4294967295.0, m + k * SCAN, HOST)
        assert v.t is None
    assert v.rejected == ("sample clock 2106-02-07T06:28:15Z is 28992.7 days ahead of the host "
                          "clock 2026-09-21T14:13:20Z (limit 24.0 h)")
    assert c.jumps == 0 and c.rejected == 99
    good = c.check(t + SPEED * 100 * SCAN, m + 100 * SCAN, HOST)
    assert good.t == t + SPEED * 100 * SCAN       # the clock goes on where it was


def test_a_one_day_glitch_is_rejected_and_the_clock_goes_on():
    c = SampleClock()
    t, m = steady(c, 20)
    assert c.rate == pytest.approx(SPEED)
    v = c.check(t + 30 + 86400, m + SCAN, HOST)
    assert v.t is None
    assert v.rejected == ("sample clock jumped ahead by 24.0 h (from 2024-03-01T00:09:30Z to "
                          "2024-03-02T00:10:00Z) in 0.05 s; at most 111 min is plausible")
    assert c.check(t + 60, m + 2 * SCAN, HOST).t == t + 60


def test_a_long_outage_is_not_a_jump():
    """After 10 monotonic minutes without a reading the clock has legitimately moved on."""
    c = SampleClock()
    t, m = steady(c, 20)
    v = c.check(t + SPEED * 600, m + 600, HOST)
    assert v.t == t + SPEED * 600 and not v.rejected


def test_a_small_step_back_is_held_and_a_large_one_rejected():
    c = SampleClock(rate=1.0)
    t, m = steady(c, 5, t0=HOST - 100, rate=1.0, scan=5.0)
    held = c.check(t - 3, m + 1, HOST)             # within the 10-s tolerance
    assert held.t == t and not held.rejected       # the accepted clock never runs backwards
    back = c.check(t - 1800, m + 2, HOST)
    assert back.t is None
    assert back.rejected == ("sample clock went back by 30 min (from 2026-09-21T14:12:00Z to "
                             "2026-09-21T13:42:00Z; tolerance 10 s)")


def test_a_lasting_jump_back_is_accepted_after_confirm_s_as_a_correction():
    policy = ClockPolicy(confirm_s=2.0, confirm_reads=3)
    c = SampleClock(policy)
    t, m = steady(c, 20)
    new0 = t - 36000.0                               # the PLC clock was set back by 10 h
    out = []
    for k in range(1, 80):
        v = c.check(new0 + k * SPEED * SCAN, m + k * SCAN, HOST)
        out.append(v)
        if v.t is not None:
            break
    rejected = [v for v in out if v.t is None]
    # rejected until the new clock ran consistently for confirm_s (2 s = 40 scans)
    assert len(rejected) == 40 and all("sample clock went back by" in v.rejected for v in rejected)
    assert "went back by 10.0 h" in rejected[0].rejected
    last = out[-1]
    assert last.t == new0 + len(out) * SPEED * SCAN
    # the old clock, extrapolated at its rate, would show t + 41 scans: the jump is -10 h + that
    assert last.jump_s == pytest.approx(-36000.0, abs=1e-6)
    assert c.jumps == 1
    nxt = c.check(last.t + 30, m + (len(out) + 1) * SCAN, HOST)
    assert nxt.t == last.t + 30                     # and the new clock is the clock now


def test_glitches_that_disagree_with_each_other_are_never_accepted():
    c = SampleClock(ClockPolicy(confirm_s=0.5, confirm_reads=3))
    t, m = steady(c, 20)
    for k in range(1, 60):                          # random-looking garbage, alternating
        garbage = T0 + (86400.0 if k % 2 else -86400.0) + k
        assert c.check(garbage, m + k * SCAN, HOST).t is None
    assert c.jumps == 0


def test_non_numbers_are_rejected():
    c = SampleClock()
    steady(c, 3)
    assert c.check(math.nan, 1.0, HOST).rejected == "sample clock reads nan, not a time"
    assert c.check(-5.0, 1.0, HOST).rejected == "sample clock reads -5.0, not a time"
    assert c.check(None, 1.0, HOST).t is None and c.rejected == 2      # unreadable: not counted


def test_policy_and_rate_are_checked():
    with pytest.raises(ValueError, match=r"ClockPolicy.confirm_s must be a finite number >= 0"):
        ClockPolicy(confirm_s=-1)
    with pytest.raises(ValueError, match=r"rate_margin must be >= 1"):
        ClockPolicy(rate_margin=0.5)
    with pytest.raises(ValueError, match=r"rate must be > 0"):
        SampleClock(rate=0.0)


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(1.0, 3600.0), scan=st.floats(0.02, 10.0),
       jitter=st.lists(st.floats(0.5, 1.5), min_size=5, max_size=60))
def test_a_steady_clock_with_irregular_scans_is_never_rejected(rate, scan, jitter):
    """Scans late or early by up to 50 %, any speed the simulator supports: all accepted."""
    c = SampleClock(rate=None)
    t, m = T0, 0.0
    for j in jitter:
        m += scan * j
        t += rate * scan * j
        v = c.check(t, m, HOST)
        assert v.t == t, v.rejected


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e6, 1e6), st.floats(0.0, 10.0)), min_size=1, max_size=60))
def test_the_accepted_clock_never_runs_backwards_whatever_is_read(steps):
    """Arbitrary readings (within a day of the host clock): accepted times never decrease,
    except at an accepted jump (a clock correction, reported as such)."""
    c = SampleClock(ClockPolicy(confirm_s=1.0))
    m, last = 0.0, -math.inf
    for dt, dm in steps:
        m += dm
        v = c.check(HOST - 2e6 + dt, m, HOST)
        if v.t is None:
            continue
        if v.jump_s is None:
            assert v.t >= last
        last = v.t
