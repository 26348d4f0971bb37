"""Simulator benchmarks for ``hp-edge bench`` (targets of issue #3):
plant step <= 5 ms; >= 500 register-read requests/s on loopback while the plant steps at 60x;
30 days exported in <= 2 min. Returns plain numbers; the caller prints JSON.
"""
from __future__ import annotations

import asyncio
import time

import numpy as np

TARGETS = {"plant_step_ms": 5.0, "reads_per_s": 500.0, "export_30d_s": 120.0}


def bench_plant_step(plant_hours: float = 12.0, warm_days: float = 3.0) -> dict:
    """Wall time per plant tick (5 plant seconds; a model solve every 12th tick, the hidden-truth
    record every 12th and a COP-optimum scan every 720th included), on a plant warmed up for
    warm_days so that fouling puts the LS compressor at its speed limit part of the time."""
    from .plant import Plant
    plant = Plant()
    plant.advance_to(plant.t + warm_days * 86400.0)
    plant.drain_truth()
    n = int(plant_hours * 3600.0 / plant.dt)
    times = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        plant.tick()
        times[i] = time.perf_counter() - t0
    plant.drain_truth()
    solve_ticks = times[np.arange(1, n + 1) % plant._solve_every == 0]
    return {"plant_step_ms": float(times.mean() * 1e3),
            "plant_step_p99_ms": float(np.percentile(times, 99) * 1e3),
            "plant_step_with_solve_ms": float(np.median(solve_ticks) * 1e3),
            "plant_step_max_ms": float(times.max() * 1e3),
            "plant_ticks": n}


async def _reads(speed: float, seconds: float, clients: int) -> dict:
    from pymodbus.client import AsyncModbusTcpClient

    from .server import PlantSimulator
    sim = PlantSimulator(port=0, speed=speed)
    await sim.start()
    counts = [0] * clients
    errors = [0] * clients
    try:
        await sim.wait_ticks(1)
        t_plant0 = sim.plant_time

        async def worker(i: int, deadline: float) -> None:
            c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)
            await c.connect()
            try:
                while time.perf_counter() < deadline:
                    r = await c.read_input_registers(0, count=32, device_id=sim.cfg.device_id)
                    if r.isError():
                        errors[i] += 1
                    counts[i] += 1
            finally:
                c.close()

        t0 = time.perf_counter()
        await asyncio.gather(*(worker(i, t0 + seconds) for i in range(clients)))
        el = time.perf_counter() - t0
        plant_rate = (sim.plant_time - t_plant0) / el
    finally:
        await sim.stop()
    return {"reads_per_s": sum(counts) / el, "read_errors": sum(errors), "read_clients": clients,
            "plant_speed_achieved": plant_rate}


def bench_reads(speed: float = 60.0, seconds: float = 3.0, clients: int = 1) -> dict:
    """Register-read requests per second (32 input registers each) from `clients` pymodbus clients
    on loopback while the plant steps at `speed` x wall time."""
    return asyncio.run(_reads(speed, seconds, clients))


def bench_export(days: float = 30.0) -> dict:
    from .export import export_history
    res = export_history(days)
    return {"export_days": days, "export_s": res.seconds,
            "export_30d_s": res.seconds * 30.0 / days, "export_rows": res.rows}


def bench_simulator(export_days: float = 30.0, read_seconds: float = 3.0) -> dict:
    """All simulator figures in one dict (keys: plant_step_ms, reads_per_s, export_30d_s, ...),
    with the issue's targets and whether each is met."""
    out: dict = {}
    out.update(bench_plant_step())
    out.update(bench_reads(seconds=read_seconds))
    out.update(bench_export(export_days))
    out["targets"] = TARGETS
    out["targets_met"] = {
        "plant_step_ms": out["plant_step_ms"] <= TARGETS["plant_step_ms"],
        "reads_per_s": out["reads_per_s"] >= TARGETS["reads_per_s"],
        "export_30d_s": out["export_30d_s"] <= TARGETS["export_30d_s"],
    }
    return out


if __name__ == "__main__":   # python -m simulator.bench
    import json
    print(json.dumps(bench_simulator(), indent=2))
