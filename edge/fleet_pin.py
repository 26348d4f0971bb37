"""One CPU for each worker of the embedded LocalCluster (``hp-edge fleet replay --scheduler local``).

Why and how a process is pinned: ``edge.cpupin``. The embedded cluster's worker i is pinned to the
i-th CPU this process may use (round robin when there are more workers than CPUs), every thread of
the worker's process, so the threads its tasks start inherit it. Imported only by
``edge.fleet.Cluster`` for a local cluster (it imports distributed); a cluster at a scheduler's
address is the operator's to pin (e.g. ``taskset`` around ``dask worker``).
"""
from __future__ import annotations

from distributed import WorkerPlugin

from edge.cpupin import cpu_for, pin_threads


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
