"""Plausibility of the sample clock, checked before a scan is aggregated, stored, pruned by or
scheduled on (issue 9 item 6).

The sample clock is the host's wall clock, or the PLC's clock register (plant time). One corrupted
read (0xFFFF 0xFFFF = year 2106), a +1-day glitch or a clock stepping back must not reach the
history: a retention counted back from 2106 deletes everything, a calibration scheduled a day ahead
waits a day, and a sample at a time already stored would take its place.

A reading ``t`` at monotonic time ``m`` (host clock ``h``) is **rejected** when

* it is not a finite positive number;
* it is ahead of the host clock by more than ``max_ahead_of_host_s`` (default one day: a PLC kept
  in local time passes, 0xFFFFFFFF does not). Such readings are never accepted;
* it went back from the last accepted reading by more than ``back_tolerance_s``; a smaller step
  back is held at the last accepted time (the accepted clock never runs backwards);
* it jumped forward further than the elapsed monotonic time explains:
  ``t - t_ref > rate_margin * rate * (m - m_ref + lag_s) + slack_s``, where ``(t_ref, m_ref)`` is
  the last accepted reading at which the clock advanced and ``rate`` the sample clock's speed
  against the monotonic clock: 1 for the wall clock, and for a PLC clock measured over the last
  accepted readings (an accelerated simulator runs at 60x or 600x). Until a rate is known, only
  the host check applies.

A **lasting jump** - the rejected readings agree with each other (each consistent with the one
before by the same rules) for ``confirm_s`` of monotonic time and at least ``confirm_reads``
readings - is a real clock correction: it is accepted, the rate is measured afresh, and the caller
is told (``Verdict.jump_s``) so that it can say so and re-plan what it scheduled on the old clock.

Pure: no I/O, no clock of its own (the caller passes all three times).
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ClockPolicy:
    """Limits of the sample-clock check (module doc). Times in seconds; ``confirm_s`` is
    monotonic (wall) time, the others are sample-clock time."""
    max_ahead_of_host_s: float = 86400.0
    back_tolerance_s: float = 10.0
    rate_margin: float = 2.0
    lag_s: float = 5.0
    slack_s: float = 600.0
    confirm_s: float = 300.0
    confirm_reads: int = 3
    rate_points: int = 32          # accepted readings the rate is measured over

    def __post_init__(self) -> None:
        for name in ("max_ahead_of_host_s", "back_tolerance_s", "lag_s", "slack_s", "confirm_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"ClockPolicy.{name} must be a finite number >= 0, got {v!r}")
        if not self.rate_margin >= 1.0:
            raise ValueError(f"ClockPolicy.rate_margin must be >= 1, got {self.rate_margin!r}")
        if self.confirm_reads < 2 or self.rate_points < 2:
            raise ValueError("ClockPolicy.confirm_reads and rate_points must be >= 2")


@dataclass(frozen=True)
class Verdict:
    """The outcome of one reading.

    t : the accepted sample time [epoch s], or None when rejected (or unreadable)
    rejected : why the reading was rejected ('' when accepted)
    jump_s : a lasting jump was accepted with this reading: its size [s] against the old clock
        (extrapolated at its rate), else None
    """
    t: float | None
    rejected: str = ""
    jump_s: float | None = None


class SampleClock:
    """Checks each sample-clock reading (module doc).

    policy : the limits
    rate : the clock's known speed against the monotonic clock (1.0 for the host's wall clock),
        or None to measure it (a PLC clock, possibly accelerated)
    """

    def __init__(self, policy: ClockPolicy | None = None, *, rate: float | None = None) -> None:
        if rate is not None and not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"rate must be > 0, got {rate!r}")
        self.policy = policy or ClockPolicy()
        self.known_rate = rate
        self._points: deque[tuple[float, float]] = deque(maxlen=self.policy.rate_points)
        self._last: float | None = None               # last accepted (held) time
        self._candidate: list[tuple[float, float]] = []
        self.accepted = 0
        self.rejected = 0
        self.jumps = 0

    # --------------------------------------------------------------------------------- state

    @property
    def rate(self) -> float | None:
        """The sample clock's speed against the monotonic clock, when known."""
        if self.known_rate is not None:
            return self.known_rate
        return _rate(self._points)

    @property
    def last(self) -> float | None:
        """The last accepted sample time."""
        return self._last

    # --------------------------------------------------------------------------------- check

    def check(self, t: float | None, t_mono: float, t_host: float) -> Verdict:
        """Judge one reading; None (unreadable) is neither accepted nor rejected."""
        if t is None:
            return Verdict(None)
        p = self.policy
        if not isinstance(t, (int, float)) or not math.isfinite(t) or t <= 0:
            return self._reject(f"sample clock reads {t!r}, not a time")
        t = float(t)
        if t - t_host > p.max_ahead_of_host_s:
            return self._reject(f"sample clock {_fmt(t)} is {_dur(t - t_host)} ahead of the "
                                f"host clock {_fmt(t_host)} (limit {_dur(p.max_ahead_of_host_s)})")
        if not self._points:                              # the first reading: nothing to compare
            return self._accept(t, t_mono)
        why = self._implausible(t, t_mono, self._points[-1], self._last, self.rate)
        if why is None:
            self._candidate.clear()                       # a glitch (if any) has ended
            return self._accept(t, t_mono)
        # a jump: a glitch, or a real clock correction if the new clock persists
        cand = self._candidate
        if cand and self._implausible(t, t_mono, cand[-1], cand[-1][1], self.rate) is None:
            cand.append((t_mono, t))
        else:
            cand[:] = [(t_mono, t)]
        if t_mono - cand[0][0] >= p.confirm_s and len(cand) >= p.confirm_reads:
            m_ref, t_ref = self._points[-1]
            r = self.rate or 0.0
            jump = t - (t_ref + r * (t_mono - m_ref))
            self._points.clear()
            self._points.extend(cand[-p.rate_points:])
            self._candidate = []
            self._last = None
            self.jumps += 1
            v = self._accept(t, t_mono)
            return Verdict(v.t, jump_s=jump)
        return self._reject(why)

    def _implausible(self, t: float, m: float, ref: tuple[float, float], last: float | None,
                     rate: float | None) -> str | None:
        p = self.policy
        m_ref, t_ref = ref
        back_from = last if last is not None else t_ref
        if t < back_from - p.back_tolerance_s:
            return (f"sample clock went back by {_dur(back_from - t)} (from {_fmt(back_from)} to "
                    f"{_fmt(t)}; tolerance {_dur(p.back_tolerance_s)})")
        if rate is None:
            return None
        elapsed = max(0.0, m - m_ref)
        allowed = p.rate_margin * rate * (elapsed + p.lag_s) + p.slack_s
        if t - t_ref > allowed:
            return (f"sample clock jumped ahead by {_dur(t - t_ref)} (from {_fmt(t_ref)} to "
                    f"{_fmt(t)}) in {elapsed:.3g} s; at most {_dur(allowed)} is plausible")
        return None

    def _accept(self, t: float, m: float) -> Verdict:
        held = t if self._last is None else max(t, self._last)
        if not self._points or t > self._points[-1][1]:
            self._points.append((m, t))                   # the clock advanced: a rate point
        self._last = held
        self.accepted += 1
        return Verdict(held)

    def _reject(self, why: str) -> Verdict:
        self.rejected += 1
        return Verdict(None, rejected=why)


def _rate(points: deque[tuple[float, float]]) -> float | None:
    if len(points) < 2:
        return None
    (m0, t0), (m1, t1) = points[0], points[-1]
    if m1 - m0 <= 0 or t1 <= t0:
        return None
    return (t1 - t0) / (m1 - m0)


def _fmt(t: float) -> str:
    try:
        return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))
    except (OverflowError, OSError, ValueError):
        return f"{t:.0f}"


def _dur(s: float) -> str:
    s = abs(s)
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 172800:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} days"
