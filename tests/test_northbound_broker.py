"""Northbound against a real MQTT broker (issue 14): Debian's mosquitto, started by each test on a
loopback port chosen at run time and stopped by its PID (``edge.northbound.mosquitto``; `make
test` installs it, and a missing broker fails these tests rather than skipping them).

A subscriber with a persistent session (so it misses nothing the broker accepted while it was
reconnecting) decodes every Sparkplug B payload with the Sparkplug protobuf schema and resolves the
NDATA aliases with the NBIRTH that preceded them, as a Sparkplug host does. Rows are stored
through the gateway's own HistoryStore (the publisher reads them from there), at the test's pace:
no plant, no sleeps to wait for the plant; the last test runs the whole gateway against the
simulator. Every wait is bounded.
"""
from __future__ import annotations

import asyncio
import json
import math
import subprocess
import threading
import time
import urllib.request
from dataclasses import dataclass, field, replace
from pathlib import Path

import paho.mqtt.client as mqtt
import pytest
from prometheus_client.parser import text_string_to_metric_families

from edge.config import load_config
from edge.loop import CycleEvent, Snapshot
from edge.northbound import sparkplug
from edge.northbound.config import HealthConfig, MqttConfig, NorthboundConfig
from edge.northbound.metrics import DATATYPES
from edge.northbound.mosquitto import Mosquitto
from edge.northbound.publisher import MqttPublisher
from edge.plc import ReadResult
from edge.store import HistoryStore

ROOT = Path(__file__).resolve().parent.parent
CFG = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
T0 = 1_709_251_200
WAIT_S = 30.0              # every wait on the broker is bounded by this
TYPE_FIELD = {v: k for k, v in DATATYPES.items()}
VALUE_FIELD = {"Double": "double_value", "Boolean": "boolean_value", "String": "string_value",
               "UInt16": "int_value", "UInt32": "int_value", "Int64": "long_value",
               "UInt64": "long_value"}


@pytest.fixture
def broker(tmp_path):
    b = Mosquitto(tmp_path / "mosquitto").start()
    yield b
    b.stop()


class Subscriber:
    """A paho client with a persistent session that keeps every message it receives."""

    def __init__(self, port: int, topic: str, client_id: str = "test-host") -> None:
        self.messages: list[tuple[str, bytes, bool]] = []      # topic, payload, retained
        self.cond = threading.Condition()
        self.c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                             clean_session=False)
        self.c.reconnect_delay_set(0.05, 0.2)
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe(topic, qos=1)
        self.c.on_message = self._on_message
        self.c.connect("127.0.0.1", port, keepalive=10)
        self.c.loop_start()

    def _on_message(self, c, u, m) -> None:
        with self.cond:
            msg = (m.topic, bytes(m.payload), bool(m.retain))
            if m.dup and msg in self.messages:
                # the broker's redelivery (DUP set) of a message whose PUBACK from this session did
                # not reach it before it stopped: QoS 1 is at least once on this hop, and a reader
                # drops it. (A publisher's resend reaches subscribers without DUP: still counted.)
                return
            self.messages.append(msg)
            self.cond.notify_all()

    def wait_for(self, predicate, timeout: float = WAIT_S):
        deadline = time.monotonic() + timeout
        with self.cond:
            while not predicate(self.messages):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"not seen within {timeout:g} s; "
                                       f"{len(self.messages)} messages")
                self.cond.wait(min(left, 0.5))
            return list(self.messages)

    def publish(self, topic: str, payload: bytes) -> None:
        self.c.publish(topic, payload, qos=1).wait_for_publish(5)

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


@dataclass
class Msg:
    kind: str                     # NBIRTH, NDATA, NDEATH
    seq: int | None
    bd_seq: int | None = None
    metrics: dict = field(default_factory=dict)   # name -> (value, timestamp s, historical)
    units: dict = field(default_factory=dict)     # NBIRTH: name -> engUnit


def decode(messages) -> list[Msg]:
    """Decode a Sparkplug stream as a host does: NDATA aliases through the last NBIRTH."""
    out, alias = [], {}
    for topic, raw, _ in messages:
        kind = topic.split("/")[2]
        if kind not in ("NBIRTH", "NDATA", "NDEATH"):
            continue                                     # our own NCMD
        p = sparkplug.Payload.FromString(raw)
        m = Msg(kind, p.seq if p.HasField("seq") else None)
        for x in p.metrics:
            if kind == "NBIRTH":
                dt = TYPE_FIELD[x.datatype]
                if x.HasField("alias"):
                    alias[x.alias] = (x.name, dt)
                if len(x.properties.keys):
                    m.units[x.name] = dict(zip(x.properties.keys,
                                               (v.string_value for v in x.properties.values)))
                name = x.name
            elif kind == "NDATA":
                assert not x.name and x.HasField("alias"), "NDATA uses aliases only"
                name, dt = alias[x.alias]
            else:
                name, dt = x.name, TYPE_FIELD[x.datatype]
            value = None if x.is_null else getattr(x, VALUE_FIELD[dt])
            if name == "bdSeq":
                m.bd_seq = value
            m.metrics[name] = (value, x.timestamp / 1000.0, x.is_historical)
        out.append(m)
    return out


def sample_ts(msgs: list[Msg]) -> list[tuple[int, bool]]:
    """(sample time, historical) of every sample NDATA, in the order received."""
    return [(int(m.metrics["Sample/usable"][1]), m.metrics["Sample/usable"][2])
            for m in msgs if m.kind == "NDATA" and "Sample/usable" in m.metrics]


def rows(start: int, n: int) -> list[dict]:
    return [{"ts": T0 + 60 * i, "T_source_in": 20.0 + 0.01 * i, "T_sink_in": float("nan"),
             "usable": 1, "reason": "", "quality": "", "COP": 4.5}
            for i in range(start, start + n)]


def event(bits=("data_stale",), t=float(T0)) -> CycleEvent:
    snap = Snapshot(status_bits=tuple(bits), sample_time=t)
    return CycleEvent(snap, ReadResult({}, t, 0.0, 0, None))


def publisher(port: int, history: Path, **kw) -> MqttPublisher:
    mq = MqttConfig(enabled=True, port=port, reconnect_min_s=0.05, reconnect_max_s=0.2,
                    group_id="plants", edge_node_id="hp1", **kw)
    return MqttPublisher(mq, replace(CFG, history_db=history), stop_timeout_s=10.0)


async def until(cond, timeout: float = WAIT_S, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what} not reached within {timeout:g} s")
        await asyncio.sleep(0.02)


def run(coro, timeout: float = 120.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


# ------------------------------------------------------------------------------------ tests


def test_birth_data_outage_rebirth_and_death_as_a_sparkplug_host_sees_them(broker, tmp_path):
    sub = Subscriber(broker.port, "spBv1.0/plants/#")
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    pub = publisher(broker.port, tmp_path / "h.sqlite")
    ncmd = sparkplug.topic("plants", "NCMD", "hp1")

    async def scenario():
        await pub.start(None)
        pub.cycle(event(("data_stale", "calibration_failed")))
        # 300 samples before the outage: the seq runs through 255 -> 0
        for i in range(0, 300, 30):
            store.add_samples(rows(i, 30))
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= 300)
        pub.cycle(event(("data_stale",)))                      # a status change, live
        await asyncio.to_thread(sub.wait_for, lambda ms: any(
            m.kind == "NDATA" and "Status/calibration_failed" in m.metrics for m in decode(ms)))
        await until(lambda: pub.queue_depth == 0, what="queue empty")
        pid = broker.pid
        broker.stop()                                           # the outage, by PID
        await until(lambda: not pub.connected, what="disconnect seen")
        for i in range(300, 340, 4):                            # stored during the outage
            store.add_samples(rows(i, 4))
        store.add_advice(T0 + 60 * 339, {"p_m_sp_rec": 15.25, "R_th_f": 2.5e-3, "ok": True,
                                         "calibration_ok": True, "optimization_ok": True,
                                         "low_confidence": False, "message": "fine",
                                         "detail": {"run_time_s": 0.5}})
        await until(lambda: pub.queue_depth == 41, what="41 rows waiting")
        broker.restart()
        assert broker.pid != pid
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= 340)
        store.add_samples(rows(340, 5))                         # live again
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= 345)
        # a host asks for a rebirth
        req = sparkplug.Payload(timestamp=1)
        req.metrics.add(name="Node Control/Rebirth", datatype=11, boolean_value=True)
        sub.publish(ncmd, req.SerializeToString())
        await asyncio.to_thread(sub.wait_for, lambda ms: sum(
            m.kind == "NBIRTH" for m in decode(ms)) >= 3)
        store.add_samples(rows(345, 1))
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= 346)
        await pub.stop()
        await asyncio.to_thread(sub.wait_for, lambda ms: decode(ms)[-1].kind == "NDEATH")
    try:
        run(scenario())
    finally:
        sub.close()
        store.close()
    msgs = decode(sub.messages)
    births = [m for m in msgs if m.kind == "NBIRTH"]
    # NBIRTH: every metric with its unit; bdSeq per connection; a rebirth keeps it
    assert [b.bd_seq for b in births] == [0, 1, 1]
    assert births[0].units["Sample/T_source_in"] == {"engUnit": "degC"}
    assert births[0].units["Advisory/p_m_sp_rec"] == {"engUnit": "bar(g)"}
    assert births[0].metrics["Status/calibration_failed"][0] is True
    assert births[0].metrics["Node Control/Rebirth"][0] is False
    assert births[1].metrics["Sample/T_source_in"][0] == pytest.approx(20.0 + 0.01 * 339)
    assert births[2].metrics["Advisory/p_m_sp_rec"][0] == 15.25     # current values
    # seq: 0 at each birth, +1 per message, 255 -> 0
    seqs = [m.seq for m in msgs if m.kind != "NDEATH"]
    session = []
    for s in seqs:
        session = [s] if s == 0 and (not session or session[-1] != 255) else session + [s]
        assert s == (session[0] + len(session) - 1) % 256
    assert 255 in seqs and seqs.count(0) >= 4
    # deaths: the will of the first connection (outage), then the clean one at stop
    deaths = [m.bd_seq for m in msgs if m.kind == "NDEATH"]
    assert set(deaths) == {0, 1} and deaths[-1] == 1
    # every sample accounted for, in order; stored during the outage -> historical; no live twice
    seen = sample_ts(msgs)
    first = list(dict.fromkeys(ts for ts, _ in seen))
    assert first == [T0 + 60 * i for i in range(346)]
    live = [ts for ts, hist in seen if not hist]
    assert len(live) == len(set(live))
    hist = {ts for ts, h in seen if h}
    assert {T0 + 60 * i for i in range(300, 340)} <= hist
    assert not hist & {T0 + 60 * i for i in range(340, 346)}
    s0 = next(m for m in msgs if m.kind == "NDATA" and "Sample/usable" in m.metrics)
    assert s0.metrics["Sample/T_sink_in"][0] is None             # NaN -> null
    assert s0.metrics["Sample/COP"][0] == 4.5
    adv = [m for m in msgs if m.kind == "NDATA" and "Advisory/p_m_sp_rec" in m.metrics]
    assert [a.metrics["Advisory/p_m_sp_rec"] for a in adv] == [(15.25, T0 + 60 * 339, True)]
    assert adv[0].metrics["Calibration/run_time"][0] == 0.5
    assert adv[0].metrics["Calibration/message"][0] == "fine"
    assert pub.published == 346 + 1 and pub.historical >= 41 and pub.error is None


def test_a_burst_larger_than_one_outbox_fetch_is_sent_without_waiting_for_the_next_row(
        broker, tmp_path):
    """More rows committed at once than one outbox read takes (FETCH), while the publisher is caught
    up (e.g. the rows a locked history kept in memory, written in one go): every one is sent now,
    not a batch per later commit. (It stalled after 256 when the whole suite loaded the machine.)"""
    from edge.northbound.publisher import FETCH

    n = FETCH + 44
    sub = Subscriber(broker.port, "spBv1.0/plants/#")
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    pub = publisher(broker.port, tmp_path / "h.sqlite")

    async def scenario():
        await pub.start(None)
        await asyncio.to_thread(sub.wait_for, lambda ms: any(m.kind == "NBIRTH" for m in decode(ms)))
        await until(lambda: pub.connected and pub.queue_depth == 0, what="caught up")
        await asyncio.sleep(0.3)                       # a few empty pumps: caught up for sure
        store.add_samples(rows(0, n))                  # one commit
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= n)
        await pub.stop()
    try:
        run(scenario())
    finally:
        sub.close()
        store.close()
    assert [ts for ts, _ in sample_ts(decode(sub.messages))] == [T0 + 60 * i for i in range(n)]
    assert pub.published == n and pub.error is None


def test_rows_stored_while_the_gateway_is_down_are_sent_after_its_restart(broker, tmp_path):
    sub = Subscriber(broker.port, "spBv1.0/plants/#")
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()

    async def session(pub, n_samples):
        await pub.start(None)
        pub.cycle(event())
        await asyncio.to_thread(sub.wait_for,
                                lambda ms: len(sample_ts(decode(ms))) >= n_samples)
        await until(lambda: pub.queue_depth == 0, what="queue empty")
        await pub.stop()

    try:
        pub = publisher(broker.port, tmp_path / "h.sqlite")
        store.add_samples(rows(0, 5))
        run(session(pub, 5))
        store.add_samples(rows(5, 7))          # the publisher is not running: queued anyway
        pub2 = publisher(broker.port, tmp_path / "h.sqlite")
        run(session(pub2, 12))
    finally:
        sub.close()
        store.close()
    msgs = decode(sub.messages)
    seen = sample_ts(msgs)
    assert [ts for ts, _ in seen] == [T0 + 60 * i for i in range(12)]
    assert all(h for ts, h in seen[5:])        # stored while down: historical
    assert [m.bd_seq for m in msgs if m.kind == "NBIRTH"] == [0, 1]   # kept in the history db


def test_json_mode_topics_retained_status_and_historical_flag(broker, tmp_path):
    sub = Subscriber(broker.port, "hp-edge/plants/hp1/#", client_id="json-reader")
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    pub = publisher(broker.port, tmp_path / "h.sqlite", mode="json")

    def docs(ms, kind):
        return [json.loads(p) for t, p, _ in ms if t == f"hp-edge/plants/hp1/{kind}"]

    async def scenario():
        await pub.start(None)
        pub.cycle(event(("comm_fault",)))
        await until(lambda: pub.caught_up, what="connected and caught up")
        store.add_samples(rows(0, 3))
        await asyncio.to_thread(sub.wait_for, lambda ms: len(docs(ms, "sample")) >= 3)
        await until(lambda: pub.published == 3, what="3 acknowledged")
        broker.stop()
        await until(lambda: not pub.connected, what="disconnect seen")
        store.add_samples(rows(3, 2))
        broker.restart()
        await asyncio.to_thread(sub.wait_for, lambda ms: len(docs(ms, "sample")) >= 5)
        await pub.stop()
        await asyncio.to_thread(sub.wait_for, lambda ms: docs(ms, "status")[-1]["online"] is False)
    try:
        run(scenario())
    finally:
        sub.close()
        store.close()
    ms = sub.messages
    samples = docs(ms, "sample")
    assert [(d["ts"], d["historical"]) for d in samples] == [
        (T0, False), (T0 + 60, False), (T0 + 120, False), (T0 + 180, True), (T0 + 240, True)]
    assert samples[0]["time"] == "2024-03-01T00:00:00Z"
    assert samples[0]["values"]["Sample/T_source_in"] == 20.0
    assert samples[0]["values"]["Sample/T_sink_in"] is None
    meta = docs(ms, "metrics")[0]["metrics"]
    assert {"name": "Sample/T_source_in", "datatype": "Double", "unit": "degC",
            "source": "sample"} in meta
    assert docs(ms, "state")[0]["values"]["Status/comm_fault"] is True
    assert docs(ms, "state")[0]["values"]["Status/word"] == 0x20
    assert [d["online"] for d in docs(ms, "status")][0] is True
    # a new reader gets the retained status: offline after the clean stop
    late = Subscriber(broker.port, "hp-edge/plants/hp1/status", client_id="late-reader")
    try:
        got = late.wait_for(lambda m: len(m) >= 1)
    finally:
        late.close()
    assert got[0][2] is True and json.loads(got[0][1])["online"] is False


def test_wrong_password_keeps_rows_waiting_and_the_right_one_delivers(tmp_path):
    pw = tmp_path / "passwd"
    subprocess.run(["mosquitto_passwd", "-c", "-b", str(pw), "hp", "right"], check=True,
                   capture_output=True, timeout=30)
    b = Mosquitto(tmp_path / "mq", extra=f"password_file {pw}\n", anonymous=False).start()
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    try:
        sub = Subscriber(b.port, "spBv1.0/#")    # anonymous: refused, receives nothing
        bad = publisher(b.port, tmp_path / "h.sqlite", username="hp", password="wrong")

        async def refused():
            await bad.start(None)
            store.add_samples(rows(0, 3))
            await until(lambda: bad.connects >= 2 and bad.queue_depth == 3, what="retries")
            await bad.stop()
        run(refused())
        assert not bad.connected and bad.published == 0 and sub.messages == []
        sub.close()

        good = publisher(b.port, tmp_path / "h.sqlite", username="hp", password="right")

        async def accepted():
            await good.start(None)
            await until(lambda: good.published == 3 and good.queue_depth == 0, what="sent")
            await good.stop()
        run(accepted())
        assert good.historical == 3
    finally:
        store.close()
        b.stop()


def test_the_gateway_publishes_and_serves_its_health_against_the_simulator(broker, tmp_path):
    """The whole chain: simulator -> gateway (GatewayService) -> mosquitto -> a host; and the
    health endpoint scraped while it runs."""
    from edge.service import GatewayService
    from simulator.server import PlantSimulator

    sub = Subscriber(broker.port, "spBv1.0/#")
    nb = NorthboundConfig(
        mqtt=MqttConfig(enabled=True, port=broker.port, group_id="plants", edge_node_id="hp1",
                        reconnect_min_s=0.05, reconnect_max_s=0.2),
        health=HealthConfig(enabled=True, port=0))

    async def scenario():
        sim = PlantSimulator(port=0, speed=300.0)
        await sim.start()
        full = load_config(ROOT / "config" / "gateway.yaml")
        scan = 5.0 / 300.0
        cfg = replace(full, plc=replace(full.plc, port=sim.port, timeout_s=0.8 * scan,
                                        reconnect_min_s=0.5 * scan, reconnect_max_s=0.5 * scan),
                      scan_interval_s=scan, state_dir=tmp_path / "state",
                      history_db=tmp_path / "history.sqlite", min_window_samples=10,
                      calibration_window_h=0.5, northbound=nb)
        svc = GatewayService(cfg, time_source="plc", install_signals=False,
                             shutdown_timeout_s=10.0)
        task = asyncio.create_task(svc.run())
        try:
            await asyncio.to_thread(sub.wait_for, lambda ms: any(
                m.kind == "NDATA" and "Advisory/p_m_sp_rec" in m.metrics for m in decode(ms))
                and len(sample_ts(decode(ms))) >= 15, 60.0)
            url = f"http://127.0.0.1:{svc.health.port}/metrics"
            text = await asyncio.to_thread(
                lambda: urllib.request.urlopen(url, timeout=5).read().decode())
        finally:
            svc.gateway.request_stop()
            rc = await asyncio.wait_for(task, 30.0)
            await sim.stop()
        return svc, rc, text
    try:
        svc, rc, text = run(scenario(), 150.0)
    finally:
        sub.close()
    assert rc == 0 and svc.gateway.snapshot.errors == 0
    msgs = decode(sub.messages)
    births = [m for m in msgs if m.kind == "NBIRTH"]
    assert births and births[0].units["Sample/T_source_in"] == {"engUnit": "degC"}
    ts = [t for t, _ in sample_ts(msgs)]
    assert ts == sorted(ts) and len(ts) == len(set(ts))
    stored = [r[0] for r in _query(tmp_path / "history.sqlite", "SELECT ts FROM samples "
                                   "ORDER BY ts")]
    queued = [r[0] for r in _query(tmp_path / "history.sqlite", "SELECT ts FROM "
                                   "northbound_outbox WHERE tbl = 'samples'")]
    assert set(ts) | set(queued) == set(stored)      # delivered, or still queued for next time
    assert len(ts) >= 15
    s = next(m for m in msgs if m.kind == "NDATA" and "Sample/COP" in m.metrics)
    assert 2.0 < s.metrics["Sample/COP"][0] < 8.0                    # a heat pump's COP
    adv = next(m for m in msgs if m.kind == "NDATA" and "Advisory/R_th_f" in m.metrics)
    assert adv.metrics["Calibration/ok"][0] in (True, False)
    assert math.isfinite(adv.metrics["Advisory/R_th_f"][0] or math.nan) or \
        adv.metrics["Calibration/ok"][0] is False
    assert msgs[-1].kind == "NDEATH"
    fams = {(s.name, tuple(sorted(s.labels.items()))): s.value
            for f in text_string_to_metric_families(text) for s in f.samples}
    assert fams[("hp_edge_mqtt_connected", ())] == 1
    assert fams[("hp_edge_samples_total", ())] >= 15
    assert fams[("hp_edge_scans_total", ())] > 100
    assert fams[("hp_edge_last_successful_poll_age_seconds", ())] < 5.0
    assert fams[("hp_edge_advisory_writes_total", (("result", "ok"),))] > 100


def _query(db: Path, sql: str):
    import sqlite3
    c = sqlite3.connect(db)
    try:
        return c.execute(sql).fetchall()
    finally:
        c.close()


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def test_tls_to_a_broker_whose_certificate_a_private_ca_signed(tmp_path):
    pki = tmp_path / "pki"
    pki.mkdir()
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj",
             "/CN=hp-edge test CA", "-keyout", "ca.key", "-out", "ca.pem", cwd=pki)
    _openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=127.0.0.1", "-keyout",
             "server.key", "-out", "server.csr", cwd=pki)
    (pki / "san.ext").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n", encoding="utf-8")
    _openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
             "-CAcreateserial", "-days", "2", "-extfile", "san.ext", "-out", "server.pem",
             cwd=pki)
    b = Mosquitto(tmp_path / "mq", extra=f"cafile {pki / 'ca.pem'}\ncertfile {pki / 'server.pem'}"
                                          f"\nkeyfile {pki / 'server.key'}\n").start()
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    try:
        from edge.northbound.config import TlsConfig
        pub = publisher(b.port, tmp_path / "h.sqlite", tls=TlsConfig(ca_file=pki / "ca.pem"))

        async def go():
            await pub.start(None)
            store.add_samples(rows(0, 2))
            await until(lambda: pub.published == 2, what="sent over TLS")
            await pub.stop()
        run(go())
        assert pub.connects == 1 and pub.error is None
        # a CA that did not sign the broker's certificate: no connection, rows wait
        _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj",
                 "/CN=another CA", "-keyout", "other.key", "-out", "other.pem", cwd=pki)
        stranger = publisher(b.port, tmp_path / "h.sqlite",
                             tls=TlsConfig(ca_file=pki / "other.pem"))

        async def refused():
            await stranger.start(None)
            store.add_samples(rows(2, 1))
            await until(lambda: stranger.queue_depth == 1 and stranger._conn_log.total >= 2,
                        what="refused twice")
            await stranger.stop()
        run(refused())
        assert stranger.published == 0 and not stranger.connected
    finally:
        store.close()
        b.stop()


def test_qos_0_as_sparkplug_asks_sends_and_forgets_in_order(broker, tmp_path):
    sub = Subscriber(broker.port, "spBv1.0/plants/#")
    store = HistoryStore(tmp_path / "h.sqlite", 400).open()
    pub = publisher(broker.port, tmp_path / "h.sqlite", qos=0)

    async def go():
        await pub.start(None)
        store.add_samples(rows(0, 150))
        await asyncio.to_thread(sub.wait_for, lambda ms: len(sample_ts(decode(ms))) >= 150)
        await until(lambda: pub.published == 150, what="150 written")
        await until(lambda: pub.queue_depth == 0, what="queue empty")
        await pub.stop()
    try:
        run(go())
    finally:
        sub.close()
        store.close()
    assert [ts for ts, _ in sample_ts(decode(sub.messages))] == [T0 + 60 * i for i in range(150)]
