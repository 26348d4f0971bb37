"""Benchmark of store-and-forward (issue 14 target): the gateway (``hp-edge run`` as its own
process) against the plant simulator at 60x plant speed, publishing Sparkplug B to a local
mosquitto; the broker is stopped by its PID for 30 minutes of plant time and started again. A
Sparkplug host (a paho subscriber with a persistent session, resolving aliases through the NBIRTH)
records every sample NDATA. Afterwards every sample in the gateway's history is looked up among
those received: delivered, in order, how many as historical, none twice as live.

``python -m edge.northbound.bench [outage_minutes speed]`` prints the JSON;
``hp-edge bench --only gateway`` includes it as ``northbound_outage``.
"""
from __future__ import annotations

import asyncio
import json
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as mqtt

from edge.northbound import sparkplug
from edge.northbound.mosquitto import Mosquitto

ROOT = Path(__file__).resolve().parents[2]
SCAN_PLANT_S = 5.0


def mqtt_section(port: int, health_port: int | None = None, **mqtt_kw) -> dict:
    """A ``northbound:`` section for gateway.yaml that publishes to 127.0.0.1:port."""
    sec = {"mqtt": {"enabled": True, "mode": "sparkplug", "host": "127.0.0.1", "port": port,
                    "group_id": "bench", "edge_node_id": "hp1", **mqtt_kw}}
    if health_port is not None:
        sec["health"] = {"enabled": True, "bind": "127.0.0.1", "port": health_port}
    return sec


class _Host:
    """Subscriber that decodes sample NDATA: (sample ts, historical, wall time received)."""

    def __init__(self, port: int) -> None:
        self.samples: list[tuple[int, bool, float]] = []
        self.births = 0
        self._usable_alias: int | None = None
        self._lock = threading.Lock()
        self.c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id="bench-host",
                             clean_session=False)
        self.c.reconnect_delay_set(0.05, 0.2)
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe("spBv1.0/bench/#", qos=1)
        self.c.on_message = self._on_message
        self.c.connect("127.0.0.1", port, keepalive=10)
        self.c.loop_start()

    def _on_message(self, c, u, msg) -> None:
        kind = msg.topic.split("/")[2]
        p = sparkplug.Payload.FromString(msg.payload)
        with self._lock:
            if kind == "NBIRTH":
                self.births += 1
                self._usable_alias = next(m.alias for m in p.metrics
                                          if m.name == "Sample/usable")
            elif kind == "NDATA" and self._usable_alias is not None:
                for m in p.metrics:
                    if m.alias == self._usable_alias:
                        self.samples.append((m.timestamp // 1000, m.is_historical,
                                             time.monotonic()))

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def bench_outage(outage_minutes: float = 30.0, speed: float = 60.0, warmup_minutes: float = 10.0,
                 after_minutes: float = 5.0, config: str | Path | None = None) -> dict:
    """Run the outage benchmark (about (warmup + outage + after) * 60 / speed s of wall time
    plus start-up) and return its figures."""
    return asyncio.run(_outage(outage_minutes, speed, warmup_minutes, after_minutes,
                               Path(config) if config else ROOT / "config" / "gateway.yaml"))


async def _outage(outage_min: float, speed: float, warmup_min: float, after_min: float,
                  config: Path) -> dict:
    import logging

    from edge.bench_gateway import _fc16, _gateway_yaml, _wait_first_write
    from simulator.server import PlantSimulator

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    with tempfile.TemporaryDirectory(prefix="hp-edge-bench-outage-") as tmp:
        tmp = Path(tmp)
        broker = Mosquitto(tmp / "mosquitto").start()
        host = _Host(broker.port)
        sim = PlantSimulator(port=0, speed=speed)
        await sim.start()
        # reconnect within about a plant minute at this speed (a real plant keeps the defaults)
        nb = mqtt_section(broker.port, reconnect_min_s=0.2, reconnect_max_s=1.0)
        gw_yaml = _gateway_yaml(tmp, sim.port, speed, config, nb)
        log = open(tmp / "gateway.log", "w", encoding="utf-8")
        proc = subprocess.Popen([sys.executable, "-m", "edge.cli", "run", "--config",
                                 str(gw_yaml), "--time-source", "plc"], cwd=ROOT,
                                stdout=log, stderr=subprocess.STDOUT)
        budget = (warmup_min + outage_min + after_min) * 60.0 / speed * 3 + 60.0
        try:
            await _wait_first_write(sim, proc, 60.0)
            t0 = sim.plant_time
            await sim.wait_plant_time(t0 + warmup_min * 60.0, timeout=budget)
            out_from = sim.plant_time
            broker.stop()                                     # by its PID
            await sim.wait_plant_time(out_from + outage_min * 60.0, timeout=budget)
            out_to = sim.plant_time
            broker.restart()
            restarted = time.monotonic()
            await sim.wait_plant_time(out_to + after_min * 60.0, timeout=budget)
            writes = _fc16(sim)
            # let the publisher finish what the gateway stored (bounded), then stop it
            deadline = time.monotonic() + 30.0
            stored = _stored(tmp / "history.sqlite")
            while time.monotonic() < deadline and not set(stored) <= {s[0] for s in
                                                                        host.samples}:
                await asyncio.sleep(0.1)
        finally:
            proc.terminate()
            try:
                rc = await asyncio.to_thread(proc.wait, 20)
            except subprocess.TimeoutExpired:
                proc.kill()
                rc = await asyncio.to_thread(proc.wait, 10)
            log.close()
            await sim.stop()
            await asyncio.sleep(0.5)
            host.close()
            broker.stop()
        stored = _stored(tmp / "history.sqlite")
        left = _outbox_left(tmp / "history.sqlite")
    got = list(host.samples)
    first = list(dict.fromkeys(ts for ts, _, _ in got))
    live = [ts for ts, hist, _ in got if not hist]
    in_outage = [s for s in stored if out_from <= s < out_to]
    delivered = set(first)
    outage_recv = [w for ts, _, w in got if out_from <= ts < out_to]
    return {
        "speed": speed,
        "outage_plant_minutes": round((out_to - out_from) / 60.0, 2),
        "samples_stored": len(stored),
        "samples_stored_during_outage": len(in_outage),
        "samples_delivered": len(set(stored) & delivered),
        "delivered_pct": round(100.0 * len(set(stored) & delivered) / len(stored), 3)
        if stored else None,
        "in_order": first == sorted(first),
        "duplicated_as_live": len(live) - len(set(live)),
        "delivered_as_historical": len({ts for ts, h, _ in got if h}),
        "outage_samples_historical": sum(1 for s in in_outage
                                         if any(ts == s and h for ts, h, _ in got)),
        "messages_received": len(got),
        "catch_up_s_after_broker_restart": round(max(outage_recv) - restarted, 3)
        if outage_recv else None,
        "births": host.births,
        "outbox_left_at_stop": left,
        "advisory_writes": writes,
        "gateway_exit_code_on_sigterm": rc,
        "targets": {"delivered_pct": 100.0, "in_order": True, "duplicated_as_live": 0},
        "method": "hp-edge run (own process, --time-source plc) against the simulator; "
                  "mosquitto stopped by PID for outage_plant_minutes, restarted; a persistent-"
                  "session Sparkplug subscriber; see edge/northbound/bench.py",
    }


def idle_cpu(seconds: float = 10.0, port: int | None = None) -> dict:
    """CPU share of the publisher thread while connected with nothing to send, at real time
    (its network loop wakes every IDLE_LOOP_S; an accelerated run compresses those wake-ups
    away, so this part is measured on the wall clock)."""
    from edge.config import load_config
    from edge.northbound.config import MqttConfig
    from edge.northbound.publisher import MqttPublisher
    from edge.store import HistoryStore

    async def run(db: Path, port: int) -> float:
        cfg = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
        store = HistoryStore(db, 400).open()
        pub = MqttPublisher(MqttConfig(enabled=True, port=port), cfg.__class__(
            **{**cfg.__dict__, "history_db": db}))
        try:
            await pub.start(None)
            deadline = time.monotonic() + 20.0
            while not pub.caught_up and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            await asyncio.sleep(1.0)
            c0 = pub.cpu_s
            await asyncio.sleep(seconds)
            return (pub.cpu_s - c0) / seconds
        finally:
            await pub.stop()
            store.close()

    with tempfile.TemporaryDirectory(prefix="hp-edge-bench-idle-") as tmp:
        tmp = Path(tmp)
        broker = None
        if port is None:
            broker = Mosquitto(tmp / "mosquitto").start()
            port = broker.port
        try:
            share = asyncio.run(run(tmp / "h.sqlite", port))
        finally:
            if broker is not None:
                broker.stop()
    return {"publisher_idle_cpu_pct_of_one_core": round(100.0 * share, 4),
            "idle_seconds_measured": seconds}


def _stored(db: Path) -> list[int]:
    c = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return [r[0] for r in c.execute("SELECT ts FROM samples ORDER BY ts")]
    finally:
        c.close()


def _outbox_left(db: Path) -> int | None:
    c = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    try:
        return int(c.execute("SELECT COUNT(*) FROM northbound_outbox").fetchone()[0])
    except sqlite3.Error:
        return None
    finally:
        c.close()


def main() -> None:   # python -m edge.northbound.bench [outage_minutes speed]
    args = [float(a) for a in sys.argv[1:3]]
    print(json.dumps(bench_outage(*args), indent=1))


if __name__ == "__main__":
    main()
