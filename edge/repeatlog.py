"""Bounded logging of a failure that repeats (a locked database, a full disk, a rejected clock).

The first failure of a run is logged loudly, with its reason; repeats are counted and summarised at
most once per ``every_s`` ("still failing: N times in M s, last: ..."); the recovery is logged once,
with how long it lasted. So a fault that lasts a week writes a few hundred lines, not millions.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable


class RepeatLog:
    """One kind of failure, e.g. ``RepeatLog(log, "history write")``.

    logger : where the lines go
    what : the failing thing, as the start of each line
    every_s : at most one summary line per this many seconds of ``monotonic`` time
    level : level of the first line of a run of failures (summaries are WARNING, repeats DEBUG)
    """

    def __init__(self, logger: logging.Logger, what: str, *, every_s: float = 600.0,
                 level: int = logging.ERROR,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.log, self.what, self.every_s, self.level = logger, what, float(every_s), level
        self._mono = monotonic
        self.failing = False
        self.count = 0            # failures in the current run
        self.total = 0            # failures since construction
        self._since = 0.0
        self._last_line = 0.0
        self._since_line = 0      # failures since the last line

    def fail(self, reason: str) -> None:
        now = self._mono()
        self.count += 1
        self.total += 1
        if not self.failing:
            self.failing, self._since, self._last_line, self._since_line = True, now, now, 0
            self.log.log(self.level, "%s: %s (repeats are summarised every %g s)", self.what,
                         reason, self.every_s)
            return
        self._since_line += 1
        if now - self._last_line >= self.every_s:
            self.log.warning("%s: still failing: %d times in %.0f s (last: %s)", self.what,
                             self.count, now - self._since, reason)
            self._last_line, self._since_line = now, 0
        else:
            self.log.debug("%s: %s", self.what, reason)

    def ok(self, note: str = "") -> bool:
        """The thing works (again). Returns True when this ended a run of failures."""
        if not self.failing:
            return False
        now = self._mono()
        self.log.warning("%s: recovered after %d failure(s) in %.0f s%s", self.what, self.count,
                         now - self._since, f"; {note}" if note else "")
        self.failing, self.count = False, 0
        return True
