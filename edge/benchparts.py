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

- the vectorised solver's rounds (``model.vtasks.run``: one batched flowsheet evaluation and its
  tasks' steps per round), wherever the replay calls the solver, in process CPU time, split per
  ``run`` into its *main* rounds (at least ``TAIL_SHARE`` of the run's largest round's rows), its
  *tail* (the smaller rounds after the largest: the few rows still on the cold path or the LS
  float's search while the others are done; a round then costs its fixed overhead, not its rows)
  and its *head* (smaller rounds before the largest).

The timer wraps the named functions for the duration of a ``with`` block and puts the originals
back when it ends (also when the block raises). A wrapped call costs ~1 µs more; a plant-year makes
~110,000 of them (~0.1 s of ~200), and ~18,000 solver rounds of two clock readings each. A replay
whose pass 2 runs in other processes (``--workers``) records its pass 2 parts there, not here: the
bench's plant-year runs in this process.
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
TAIL_SHARE = 0.1        # a solver run's rounds with fewer rows than this share of its largest: tail or head
KINDS = ("main", "tail", "head")


def split_rounds(rounds: list) -> dict:
    """A solver run's rounds [(rows, CPU s)] by kind: {kind: (rounds, row-rounds, CPU s)}, kinds
    ``KINDS``: main (rows >= TAIL_SHARE x the largest round's), tail (fewer, after the first
    largest round), head (fewer, before it)."""
    out = {k: [0, 0, 0.0] for k in KINDS}
    if not rounds:
        return {k: tuple(v) for k, v in out.items()}
    big = max(r for r, _ in rounds)
    first = next(i for i, (r, _) in enumerate(rounds) if r == big)
    for i, (r, c) in enumerate(rounds):
        kind = "main" if r >= TAIL_SHARE * big else ("tail" if i > first else "head")
        o = out[kind]
        o[0] += 1
        o[1] += r
        o[2] += c
    return {k: tuple(v) for k, v in out.items()}


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
        self.rounds = {k: [0, 0, 0.0] for k in KINDS}
        self.runs = 0
        self._observer = None   # model.vtasks.round_observer before the block (restored after it)

    def _observe(self, rounds: list) -> None:
        """``model.vtasks.round_observer``: a solver run's rounds, split and summed."""
        with self._lock:
            self.runs += 1
            for k, (n, rr, c) in split_rounds(rounds).items():
                o = self.rounds[k]
                o[0] += n
                o[1] += rr
                o[2] += c

    def __enter__(self) -> "PartTimer":
        from model import vtasks
        self._observer = vtasks.round_observer
        vtasks.round_observer = self._observe
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
        from model import vtasks
        vtasks.round_observer = self._observer
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
        "calls": {part: n}, "solver_rounds": {"runs": n, kind: {"rounds", "row_rounds", "cpu_s",
        "ms_per_window", "share_of_replay"}}} with the derived parts (``pass2_lockstep``, ``rest``)
        and the replay's total (``replay``) among the parts."""
        cpu = {part: float(self.cpu.get(part, 0.0)) for _, _, part, _ in self.timed}
        g = lambda k: cpu.get(k, 0.0)                      # noqa: E731 - a timer of other parts
        cpu["pass2_lockstep"] = g("pass2") - g("pass2_solver") - g("pass2_windows")
        cpu["rest"] = total_cpu_s - g("pass1_prepare") - g("pass2") - g("pass3")
        cpu["replay"] = float(total_cpu_s)
        n = max(int(windows), 1)
        rounds = {"runs": self.runs,
                  **{k: {"rounds": v[0], "row_rounds": v[1], "cpu_s": v[2], "ms_per_window": 1e3 * v[2] / n,
                         "share_of_replay": v[2] / total_cpu_s if total_cpu_s > 0 else float("nan")}
                     for k, v in self.rounds.items()},
                  "how": f"model.vtasks.run's rounds over the whole replay in process CPU time; per run, "
                         f"main: rows >= {TAIL_SHARE:g} x its largest round's, tail: fewer after the "
                         f"largest, head: fewer before it (edge.benchparts.split_rounds)"}
        return {"cpu_s": cpu,
                "ms_per_window": {k: 1e3 * v / n for k, v in cpu.items()},
                "share_of_replay": {k: (v / total_cpu_s if total_cpu_s > 0 else float("nan"))
                                    for k, v in cpu.items()},
                "calls": {part: int(self.calls.get(part, 0)) for _, _, part, _ in self.timed},
                "solver_rounds": rounds,
                "how": "main-thread parts in process CPU time, pass 2's window parts in each thread's "
                       "CPU time (edge.benchparts); pass2_lockstep = pass2 - pass2_solver - "
                       "pass2_windows; rest = replay - pass1_prepare - pass2 - pass3"}
