"""Several analyses in lockstep: their ``model.vcycle.solve_many`` calls answered together.

A window's analysis makes ~20 solver calls one after the other, each of a few to a few hundred
rows; at that size a call costs its numpy operations, not its rows. ``run(fns)`` runs the callables
(e.g. the pass 2 of K replay windows) each in its own thread, but never two at once: the threads
take turns in a fixed order, each running until it calls ``solve_many`` (or ends). When every live
thread waits in ``solve_many``, the calls are answered together: the calls that can share one
solver call (``model.vcycle.merge_key``) by ``model.vcycle.solve_merged``, the others alone. Then
the threads take their turns again.

Because only one thread runs at a time, in an order fixed by the callables' order, the results do
not depend on the machine or on timing: a given list of callables always gives the same numbers
(the property tables and CoolProp states the threads share are never used by two at once). The
numbers of a callable can differ from what it gives run alone within the solver's tolerances
(``solve_merged``). A callable that raises has its exception returned in its place.
"""
from __future__ import annotations

import threading

_local = threading.local()


class Failed:
    """A callable's exception, in its place in ``run``'s results."""

    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def request(kwargs: dict):
    """``solve_many``'s hook: the answer to this call when the calling thread runs under ``run``
    (else None: ``solve_many`` answers it itself)."""
    ctx = getattr(_local, "ctx", None)
    if ctx is None:
        return None
    coord, slot = ctx
    return coord.ask(slot, kwargs)


class _Coordinator:
    """The turns, handed over like a baton: each slot waits on its own lock (held while it may not
    run) and the caller on one more, so a turn wakes exactly the thread it is given to. Only one
    thread runs at a time, so the shared dicts need no lock of their own (each hand-over orders
    the memory accesses before it)."""

    def __init__(self, k: int) -> None:
        self.go = [threading.Lock() for _ in range(k)]
        for g in self.go:
            g.acquire()
        self.back = threading.Lock()
        self.back.acquire()
        self.pending: dict[int, dict] = {}
        self.answers: dict[int, object] = {}
        self.live = set(range(k))

    # ---- in the threads -----------------------------------------------------------------------
    def ask(self, slot: int, kwargs: dict):
        self.pending[slot] = kwargs
        self.back.release()                 # the caller's turn
        self.go[slot].acquire()             # until the caller gives this slot its turn again
        ans = self.answers.pop(slot)
        if isinstance(ans, Failed):
            raise ans.exc
        return ans

    def start(self, slot: int) -> None:
        self.go[slot].acquire()

    def done(self, slot: int) -> None:
        self.live.discard(slot)
        self.back.release()

    # ---- in the caller ------------------------------------------------------------------------
    def give(self, slot: int) -> None:
        """Let ``slot`` run until it asks or ends."""
        self.go[slot].release()
        self.back.acquire()


def run(fns: list, answer=None) -> list:
    """Each callable's result (or ``Failed``) in order, the callables run in lockstep. ``answer``:
    the function that answers a round's requests ({slot: kwargs} -> {slot: result or Failed});
    default ``answer_requests``."""
    answer = answer or answer_requests
    k = len(fns)
    co = _Coordinator(k)
    results: list = [None] * k

    def body(slot: int) -> None:
        _local.ctx = (co, slot)
        co.start(slot)
        try:
            results[slot] = fns[slot]()
        except BaseException as exc:          # returned in its place; the others go on
            results[slot] = Failed(exc)
        finally:
            _local.ctx = None
            co.done(slot)

    threads = [threading.Thread(target=body, args=(i,), name=f"lockstep-{i}", daemon=True) for i in range(k)]
    for t in threads:
        t.start()
    first = list(range(k))
    while True:
        for slot in first:                    # each live thread runs until it asks or ends
            if slot in co.live:
                co.give(slot)
        if not co.pending:
            break
        batch = dict(sorted(co.pending.items()))
        co.pending.clear()
        try:
            got = answer(batch)
        except BaseException as exc:          # noqa: BLE001 - every waiting thread gets it
            got = {slot: Failed(exc) for slot in batch}
        co.answers.update(got)
        first = sorted(batch)
    for t in threads:
        t.join()
    return results


def answer_requests(batch: dict) -> dict:
    """The answers to a round's ``solve_many`` calls: those with one ``merge_key`` in one
    ``solve_merged`` call (alone: ``solve_many`` itself), in slot order. If a merged call raises,
    its calls are answered one by one, each with its own result or exception."""
    from .vcycle import merge_key, solve_direct, solve_merged
    groups: list[tuple[object, list[int]]] = []
    for slot, kw in batch.items():
        key = merge_key(kw)
        for gk, slots in groups:
            if key is not None and gk == key:
                slots.append(slot)
                break
        else:
            groups.append((key, [slot]))
    out: dict = {}
    for _, slots in groups:
        if len(slots) > 1:
            try:
                for slot, v in zip(slots, solve_merged([batch[s] for s in slots])):
                    out[slot] = v
                continue
            except Exception:                 # noqa: BLE001 - answered one by one below
                pass
        for slot in slots:
            try:
                out[slot] = solve_direct(batch[slot])
            except Exception as exc:          # noqa: BLE001 - the caller's own exception
                out[slot] = Failed(exc)
    return out
