"""One CPU for each worker of the embedded LocalCluster (``hp-edge fleet replay --scheduler local``).

A replay runs its windows in lockstep: 64 threads hand one turn around (``model.lockstep``), each
hand-over a thread woken by another. On a machine whose every core is busy (a cluster with a worker
per core) the kernel wakes the next thread on whichever core it chooses; on the other core it waits
behind that core's worker while its own core idles. Stop 39 measured it on 2 cores: two 30-day
replays side by side took 27.8 and 33.4 s of wall time for 24.9 and 30.5 CPU-s, 26 % of both cores
idle; each pinned to its own core, 23.8 and 29.9 s for 23.8 and 29.7 CPU-s (alone: 24.6 s). The
embedded cluster's workers are therefore pinned, worker i to the i-th CPU this process may use
(round robin when there are more workers than CPUs), every thread of the worker's process, so the
threads its tasks start inherit it. Imported only by ``edge.fleet.Cluster`` for a local cluster
(it imports distributed); a cluster at a scheduler's address is the operator's to pin (e.g.
``taskset`` around ``dask worker``). Where the OS cannot pin (no ``sched_setaffinity``), nothing is
done.
"""
from __future__ import annotations

from distributed import WorkerPlugin

from edge.cpupin import cpu_for, pin_threads

__all__ = ["PinWorkerToCPU", "cpu_for", "pin_threads"]


class PinWorkerToCPU(WorkerPlugin):
    """Pins a LocalCluster worker (named 0, 1, ... by LocalCluster) to ``cpu_for(its name)`` when it
    starts; a worker with another name is left alone."""

    name = "hp-edge-pin-to-cpu"

    def __init__(self, cpus: list[int]) -> None:
        self.cpus = list(cpus)        # the client's CPUs: the workers run on the same machine

    def setup(self, worker) -> None:
        try:
            index = int(worker.name)
        except (TypeError, ValueError):
            return
        pin_threads(cpu_for(index, self.cpus))
