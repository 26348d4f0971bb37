"""Cooperative tasks whose flowsheet evaluations run batched: one ``Flowsheet.evaluate`` per round.

At a few hundred rows the cost of an evaluation is its fixed numpy overhead, not its rows, so what
counts is the number of sequential evaluation rounds. The solver's phases are written as generators
that ``yield Eval(...)`` where the scalar solver calls its flowsheet, and receive the result; phases
of different rows run as concurrent tasks (``yield Spawn(task)`` starts one), and ``run`` gathers the
pending requests of all live tasks into one evaluation per flowsheet and round. A row's own sequence
of evaluations is unchanged by the batching: the tasks only overlap where their rows are disjoint.
"""
from __future__ import annotations

import time

import numpy as np

from .vflowsheet import MSide


class Eval:
    """A request: the flowsheet ``fs`` at (T_m, T_c) [K] for its rows idx (``ms``: their
    ``m_side`` at T_m when known; ``full``: every state)."""
    __slots__ = ("fs", "idx", "T_m", "T_c", "ms", "full")

    def __init__(self, fs, idx, T_m, T_c, ms=None, full: bool = False) -> None:
        self.fs, self.idx, self.T_m, self.T_c, self.ms, self.full = fs, idx, T_m, T_c, ms, full


class LSReq:
    """A request: the LS speed ratio of the rows idx at T_source,out T_so and T_m [K] (the LS side
    alone; a row may appear several times)."""
    __slots__ = ("fs", "idx", "T_so", "T_m")

    def __init__(self, fs, idx, T_so, T_m) -> None:
        self.fs, self.idx, self.T_so, self.T_m = fs, idx, T_so, T_m


class Spawn:
    """A request: start ``task`` (a generator) beside the current one, which resumes at once."""
    __slots__ = ("task",)

    def __init__(self, task) -> None:
        self.task = task


#: None, or a callable handed each ``run``'s rounds when it ends: [(rows, process CPU s)] per round,
#: rows the requests' rows summed (``edge.benchparts.PartTimer`` sets it for the plant-year bench)
round_observer = None


def run(*tasks) -> None:
    """Drive the tasks (generators yielding Eval and Spawn) to their end, batching their Eval
    requests per flowsheet into one evaluation per round."""
    live: list = []
    observer = round_observer
    rounds: list | None = [] if observer is not None else None

    def advance(gen, value) -> None:
        while True:
            try:
                req = gen.send(value)
            except StopIteration:
                return
            if isinstance(req, Spawn):
                advance(req.task, None)
                value = None
                continue
            live.append((gen, req))
            return

    for t in tasks:
        advance(t, None)
    while live:
        if rounds is not None:
            c = time.process_time()
        batch, live[:] = list(live), []
        groups: dict = {}
        for item in batch:
            groups.setdefault((type(item[1]), id(item[1].fs)), []).append(item)
        for (kind, _), items in groups.items():
            reqs = [req for _, req in items]
            results = _evaluate(reqs) if kind is Eval else _ls(reqs)
            for (gen, _), res in zip(items, results):
                advance(gen, res)
        if rounds is not None:
            rounds.append((sum(len(req.idx) for _, req in batch), time.process_time() - c))
    if rounds is not None:
        observer(rounds)


def _cuts(reqs) -> list:
    ends = np.cumsum([len(r.idx) for r in reqs])
    return [(e - len(r.idx), e) for r, e in zip(reqs, ends)]


def _ls(reqs: list) -> list:
    fs = reqs[0].fs
    n = fs.ls_speed_at(np.concatenate([r.idx for r in reqs]), np.concatenate([r.T_so for r in reqs]),
                       np.concatenate([r.T_m for r in reqs]))
    return [n[a:b] for a, b in _cuts(reqs)]


def _evaluate(reqs: list) -> list:
    """One flowsheet evaluation for the requests (same flowsheet), split back per request."""
    fs = reqs[0].fs
    if len(reqs) == 1:
        r = reqs[0]
        return [fs.evaluate(r.idx, r.T_m, r.T_c, ms=r.ms, full=r.full)]
    idx = np.concatenate([r.idx for r in reqs])
    T_m = np.concatenate([r.T_m for r in reqs])
    T_c = np.concatenate([r.T_c for r in reqs])
    if all(r.ms is None for r in reqs):
        ms = None
    else:
        ms = MSide.concat([r.ms if r.ms is not None else fs.m_side(r.idx, r.T_m) for r in reqs])
    ev = fs.evaluate(idx, T_m, T_c, ms=ms, full=any(r.full for r in reqs))
    return [_Part(ev, a, b) for a, b in _cuts(reqs)]


class _Part:
    """The rows [a, b) of a batched evaluation's result, sliced on access."""
    __slots__ = ("ev", "a", "b")

    def __init__(self, ev: dict, a: int, b: int) -> None:
        self.ev, self.a, self.b = ev, a, b

    def __getitem__(self, key: str):
        if key == "ms":
            return self.ev["ms"].take(slice(self.a, self.b))
        return self.ev[key][self.a:self.b]

    def __contains__(self, key: str) -> bool:
        return key in self.ev

    def keys(self):
        return [k for k in self.ev.keys() if k != "ms"]
