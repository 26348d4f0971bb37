"""Processes pinned to CPUs: the workers of ``hp-edge replay --workers N`` and of the embedded
LocalCluster (``edge.fleet_pin``).

A replay runs its windows in lockstep: 64 threads hand one turn around (``model.lockstep``), each
hand-over a thread woken by another. On a machine whose every core is busy the kernel wakes the
next thread on whichever core it chooses; on another core it waits behind that core's process
while its own core idles. Stop 39 measured it with two 30-day replays side by side on 2 cores
(27.8 and 33.4 s of wall time, 26 % of both cores idle; each pinned to its own core, 23.8 and
29.9 s), stop 40 with ``replay --workers 2`` (a 60-day replay 33.1 and 33.4 s unpinned, 29.1 and
29.7 s with the pool's workers pinned). Pinning a process means every thread it has
(``/proc/self/task``); the threads they start later inherit it. Where the OS cannot pin, nothing
is done. Standard library only: the gateway's runtime imports nothing of the extras.
"""
from __future__ import annotations

import os


def pin_threads(cpu: int) -> bool:
    """Every thread of this process on CPU ``cpu`` (threads started later by them inherit it).
    False where the OS cannot (no sched_setaffinity or /proc/self/task) or refuses."""
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return False
    for tid in tids:
        try:
            os.sched_setaffinity(int(tid), {cpu})
        except ProcessLookupError:      # the thread ended meanwhile
            continue
        except (AttributeError, OSError, ValueError):
            return False
    return True


def cpu_for(index: int, cpus=None) -> int:
    """The CPU of worker ``index``: the index-th of the CPUs this process may use, round robin."""
    cpus = sorted(os.sched_getaffinity(0) if cpus is None else cpus)
    return cpus[index % len(cpus)]


def pin_next(counter, cpus: list[int]) -> None:
    """A process pool's initializer: the worker takes the next number from ``counter`` (a
    ``multiprocessing.Value('i')`` shared by the pool's workers) and pins itself to ``cpu_for``
    it. Never raises (a raising initializer breaks the pool): where pinning fails the worker runs
    unpinned."""
    try:
        with counter.get_lock():
            index = counter.value
            counter.value += 1
        pin_threads(cpu_for(index, cpus))
    except Exception:                   # noqa: BLE001 - pinning is for speed only
        pass
