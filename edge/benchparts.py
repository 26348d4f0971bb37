"""Where a replay's CPU goes, part by part: ``hp-edge bench --only plant_year``'s ``parts`` block.

Stop 53 asked what closes the last factor of two to the 100-plant-year target, and found the answer
in how a window's time divides: the merged solver is a quarter of it, the windows' own Python (the
advice's search and trusted stretch, the forecast, the dead band) most of the rest. ``PartTimer``
measures that split in the bench's own replay, so that the next change is judged against it
without a profiler:

- the main thread's parts (pass 1's ``prepare``, pass 2 as a whole, its merged solver calls, pass 3
  and its forecast, dead band and surrogate tracker) in process CPU time: while the main thread
  runs them, no other thread computes (pass 2's lockstep runs one thread at a time);
- pass 2's parts inside the windows' threads (``AnalysisChain.analyse`` and the advice's draft, its
  searches, trusted stretch and uncertainty draws, and the fouling calibration) in each thread's
  own CPU time (``time.thread_time``): the solver answers their requests in the main thread, so
  these are the windows' own Python and numpy work (the dead band's ``_draws_at`` and solver
  calls in pass 3, whose kept recommendations run in a lockstep of their own since stop 54, are
  pass 3's and not counted here);
- derived: pass 2's lockstep (threads started, batons handed: pass 2 less its solver and its
  threads), and the rest of the replay (the measured side, the initial calibration, the results'
  tables: the replay less passes 1–3).

The timer wraps the named functions for the duration of a ``with`` block and puts the originals
back when it ends (also when the block raises). A wrapped call costs ~1 µs more; a plant-year makes
~110,000 of them (~0.1 s of ~200). A replay whose pass 2 runs in other processes (``--workers``)
records its pass 2 parts there, not here: the bench's plant-year runs in this process.
"""
from __future__ import annotations

import functools
import threading
import time
from collections import Counter

# (module, attribute path, part, clock): the function ``attribute path`` of ``module`` is timed as
# ``part`` with the process's ("process") or the calling thread's ("thread") CPU clock. The module
# attribute is the one the caller looks up (chain.py imports draft_advice by name and calls its own
# settle_now and settle_kept, advice.py searches), so that the wrapper is the function called.
TIMED = (
    ("model.analysis.chain", "AnalysisChain.prepare", "pass1_prepare", "process"),
    ("model.analysis.replay", "_analyse_tasks", "pass2", "process"),
    ("model.lockstep", "answer_requests", "pass2_solver", "process"),
    ("model.analysis.chain", "AnalysisChain.analyse", "pass2_windows", "thread"),
    ("model.analysis.chain", "AnalysisChain._calibrate", "pass2_windows_fouling_calibration", "thread"),
    ("model.analysis.chain", "draft_advice", "pass2_windows_advice_draft", "thread"),
    ("model.analysis.advice", "searches", "pass2_windows_advice_searches", "thread"),
    ("model.analysis.advice", "trusted_stretch", "pass2_windows_advice_trusted_stretch", "thread"),
    ("model.analysis.advice", "_draws_at", "pass2_windows_advice_draws", "thread"),
    ("model.analysis.chain", "AnalysisChain.finish_chunk", "pass3", "process"),
    ("model.analysis.chain", "AnalysisChain._forecast", "pass3_forecast", "process"),
    ("model.analysis.chain", "settle_now", "pass3_dead_band", "process"),
    ("model.analysis.chain", "settle_kept", "pass3_dead_band", "process"),
    ("model.analysis.surrogate_tracker", "SurrogateTracker.window", "pass3_surrogate_tracker", "process"),
)
CLOCKS = {"process": time.process_time, "thread": time.thread_time}


def owner_of(mod_name: str, path: str) -> tuple:
    """(the object holding the attribute, its name) of a ``TIMED`` entry's function."""
    import importlib
    owner = importlib.import_module(mod_name)
    *outer, name = path.split(".")
    for a in outer:
        owner = getattr(owner, a)
    return owner, name


class PartTimer:
    """``with PartTimer() as pt: replay(...)`` then ``pt.report(cpu_s, windows)``."""

    def __init__(self, timed=TIMED) -> None:
        self.timed = timed
        self.cpu: Counter = Counter()
        self.calls: Counter = Counter()
        self._saved: list = []
        self._lock = threading.Lock()
        self._in_pass3 = 0      # pass 3 calls _draws_at too (the dead band): not pass 2's

    def __enter__(self) -> "PartTimer":
        try:
            for mod_name, path, part, clock in self.timed:
                owner, name = owner_of(mod_name, path)
                original = owner.__dict__[name]
                self._saved.append((owner, name, original))
                setattr(owner, name, self._wrap(original, part, CLOCKS[clock]))
        except BaseException:
            self._restore()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self._restore()

    def _restore(self) -> None:
        while self._saved:
            owner, name, original = self._saved.pop()
            setattr(owner, name, original)

    def _wrap(self, f, part: str, clock):
        cpu, calls, lock = self.cpu, self.calls, self._lock
        is_pass3, pass2 = part == "pass3", part.startswith("pass2_")

        @functools.wraps(f)
        def timed(*a, **k):
            if pass2 and self._in_pass3:
                return f(*a, **k)
            c = clock()
            self._in_pass3 += is_pass3
            try:
                return f(*a, **k)
            finally:
                self._in_pass3 -= is_pass3
                d = clock() - c
                with lock:
                    cpu[part] += d
                    calls[part] += 1
        return timed

    def report(self, total_cpu_s: float, windows: int) -> dict:
        """{"cpu_s": {part: s}, "ms_per_window": {part: ms}, "share_of_replay": {part: share},
        "calls": {part: n}} with the derived parts (``pass2_lockstep``, ``rest``) and the replay's
        total (``replay``) among the parts."""
        cpu = {part: float(self.cpu.get(part, 0.0)) for _, _, part, _ in self.timed}
        g = lambda k: cpu.get(k, 0.0)                      # noqa: E731 - a timer of other parts
        cpu["pass2_lockstep"] = g("pass2") - g("pass2_solver") - g("pass2_windows")
        cpu["rest"] = total_cpu_s - g("pass1_prepare") - g("pass2") - g("pass3")
        cpu["replay"] = float(total_cpu_s)
        n = max(int(windows), 1)
        return {"cpu_s": cpu,
                "ms_per_window": {k: 1e3 * v / n for k, v in cpu.items()},
                "share_of_replay": {k: (v / total_cpu_s if total_cpu_s > 0 else float("nan"))
                                    for k, v in cpu.items()},
                "calls": {part: int(self.calls.get(part, 0)) for _, _, part, _ in self.timed},
                "how": "main-thread parts in process CPU time, pass 2's window parts in each thread's "
                       "CPU time (edge.benchparts); pass2_lockstep = pass2 - pass2_solver - "
                       "pass2_windows; rest = replay - pass1_prepare - pass2 - pass3"}
