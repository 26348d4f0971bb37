"""The simulated PLC's program for a remote (supervisory) set point: what docs/closed_loop.md gives
in IEC 61131-3 structured text (FB_RemoteSetpoint), in Python, pure (no I/O, times injected).

* Remote mode starts on a rising edge of the operator's enable while the heartbeat is alive and the
  fallback latch is clear; the remote set point starts at the active one (bumpless).
* Remote mode ends when the enable drops (reason ``enable_off``) or the heartbeat word has not
  changed for ``heartbeat_timeout_s`` (``heartbeat_timeout``; latched: only dropping the enable
  clears it, so a gateway that comes back does not take over by itself). The active set point then
  reverts to the operator's local one.
* A remote set-point write is accepted only in remote mode (else Modbus exception 4, server device
  failure: the program does not take remote set points now) and only inside the configured bounds
  (else exception 3, illegal data value).

Times are the PLC's own real-time clock (a TON timer): the server passes ``time.monotonic()``,
wall time, whatever the plant's speed - the gateway's scan interval is wall time too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

EXC_NOT_REMOTE = 4        # ExcCodes.DEVICE_FAILURE
EXC_OUT_OF_BOUNDS = 3     # ExcCodes.ILLEGAL_VALUE
BOUND_TOLERANCE = 1e-9    # bar: round-off of a decoded register value


@dataclass(frozen=True)
class Change:
    """A change of mode: ``mode`` 'remote' | 'local', ``reason`` 'enable_on' | 'enable_off' |
    'heartbeat_timeout', at PLC time ``t``; ``heartbeat_age_s`` when it happened."""
    mode: str
    reason: str
    t: float
    heartbeat_age_s: float


class RemoteSetpoint:
    """One instance of FB_RemoteSetpoint. ``heartbeat(word, now)`` when the heartbeat register is
    written; ``scan(enable, now)`` every PLC scan; ``check_write(bar_g)`` before a remote
    set-point write is taken."""

    def __init__(self, bounds_bar_g: tuple[float, float], heartbeat_timeout_s: float) -> None:
        lo, hi = bounds_bar_g
        if not (lo < hi and heartbeat_timeout_s > 0):
            raise ValueError("need bounds low < high and heartbeat_timeout_s > 0")
        self.bounds = (float(lo), float(hi))
        self.timeout_s = float(heartbeat_timeout_s)
        self.remote = False
        self.tripped = False            # fallback latch (heartbeat timeout), cleared by enable = 0
        self.enable_prev = False
        self.hb_last: int | None = None
        self.hb_changed_at = -math.inf  # PLC time of the last heartbeat change
        self.changes: list[Change] = []

    def heartbeat(self, word: int, now: float) -> None:
        """The heartbeat register now holds ``word`` (written at PLC time ``now``)."""
        if word != self.hb_last:
            self.hb_last = word
            self.hb_changed_at = now

    def heartbeat_age(self, now: float) -> float:
        return now - self.hb_changed_at

    def heartbeat_ok(self, now: float) -> bool:
        return self.heartbeat_age(now) <= self.timeout_s

    def scan(self, enable: bool, now: float) -> Change | None:
        """One PLC scan. Returns the change of mode, if any (also kept in ``changes``)."""
        ok = self.heartbeat_ok(now)
        change = None
        if not enable:
            self.tripped = False
        if self.remote and not enable:
            self.remote = False
            change = Change("local", "enable_off", now, self.heartbeat_age(now))
        elif self.remote and not ok:
            self.remote, self.tripped = False, True
            change = Change("local", "heartbeat_timeout", now, self.heartbeat_age(now))
        elif not self.remote and enable and not self.enable_prev and ok and not self.tripped:
            self.remote = True
            change = Change("remote", "enable_on", now, self.heartbeat_age(now))
        self.enable_prev = enable
        if change is not None:
            self.changes.append(change)
        return change

    def check_write(self, bar_g: float) -> int | None:
        """None when a remote set-point write of ``bar_g`` is taken, else the exception code."""
        if not self.remote:
            return EXC_NOT_REMOTE
        lo, hi = self.bounds
        if not (math.isfinite(bar_g) and lo - BOUND_TOLERANCE <= bar_g <= hi + BOUND_TOLERANCE):
            return EXC_OUT_OF_BOUNDS
        return None
