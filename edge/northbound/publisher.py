"""The MQTT publisher: a Sparkplug B edge node (or the plain-JSON layout) in its own thread.

The gateway loop only hands it the status of each cycle (``cycle``: a dict swap and an event,
microseconds); samples and advice reach it through the history database (``edge.northbound.outbox``:
triggers queue every stored row), so the scan loop and the Modbus side never wait for a broker.

One thread (``hp-edge-northbound``) owns the paho-mqtt client (``Client.loop`` is called from it,
so every paho callback runs in it too, and nothing needs a lock but the status hand-over):

1. connect (TLS, username/password when configured) with the NDEATH as the MQTT will; a new
   client for every connection, so nothing of an old session is ever re-sent into a new one;
   reconnect with back-off ``reconnect_min_s`` .. ``reconnect_max_s`` while the broker is away;
2. on CONNACK: subscribe to NCMD, publish NBIRTH (seq 0; bdSeq, incremented per connection and
   kept in the history database, matches the will's), then the backlog;
3. publish the outbox in the order rows were stored, as NDATA with each row's time stamp;
   ``is_historical`` is set on everything sent before the backlog was first found empty in this
   session (rows stored while the broker was away, before a restart, or re-sent after a
   connection dropped before the broker acknowledged them), and on a row older than one already
   sent live; delete from the outbox what the broker acknowledged (QoS 1: PUBACK);
4. publish changed status bits as live NDATA (report by exception);
5. NCMD ``Node Control/Rebirth`` = true: publish NBIRTH again (same bdSeq, seq 0);
6. on stop: wait (bounded) for outstanding acknowledgements, publish NDEATH, disconnect.

Delivery is at least once: a row whose acknowledgement was lost with the connection is sent again
after the reconnect, marked historical, so a host may see it twice but never twice as live.
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt

from edge.northbound import jsonmode, sparkplug
from edge.northbound.config import MqttConfig
from edge.northbound.metrics import Catalog, catalog_for, status_values
from edge.northbound.outbox import Entry, Outbox
from edge.repeatlog import RepeatLog

log = logging.getLogger(__name__)

WINDOW = 64               # data messages in flight (sent, not yet acknowledged) at most
FETCH = 256               # outbox entries read per query
ACK_EVERY_S = 0.5         # delete acknowledged entries at most this often (one transaction)
IDLE_LOOP_S = 0.5         # network loop timeout when there is nothing to send
BUSY_LOOP_S = 0.005       # ... and while sending a backlog
CONNACK_TIMEOUT_S = 10.0  # a connection without CONNACK by then is dropped
STOP_FLUSH_S = 2.0        # on stop: wait this long at most for outstanding acknowledgements
DEPTH_EVERY_S = 1.0       # recount the outbox at most this often


class MqttPublisher:
    """Observer of ``edge.loop.Gateway`` that publishes northbound.

    cfg : ``northbound.mqtt`` (edge.northbound.config.MqttConfig)
    gateway_cfg : the gateway's configuration (tags, advisory block, history path)
    history_path : the history database (default: gateway_cfg.history_db)

    Counters (read by the health endpoint from another thread; plain numbers):
    ``connected``, ``queue_depth`` (rows waiting: outbox + in flight), ``published`` (data
    messages acknowledged), ``historical`` (of those, sent as historical), ``dropped`` (rows lost
    to the backlog cap), ``expired`` (rows pruned by retention before they could be sent),
    ``births``, ``connects``, ``cpu_s`` (this thread's CPU time).
    """

    def __init__(self, cfg: MqttConfig, gateway_cfg: Any, *, history_path: str | Path | None = None,
                 stop_timeout_s: float = 10.0) -> None:
        self.cfg = cfg
        self.catalog: Catalog = catalog_for(gateway_cfg)
        self.history = Path(history_path or gateway_cfg.history_db)
        self.bits = tuple(sorted(gateway_cfg.advisory.status_bits))
        self.stop_timeout_s = stop_timeout_s
        self.sparkplug = cfg.mode == "sparkplug"
        g, n = cfg.group_id, cfg.edge_node_id
        if self.sparkplug:
            self.t_birth = sparkplug.topic(g, "NBIRTH", n)
            self.t_data = sparkplug.topic(g, "NDATA", n)
            self.t_death = sparkplug.topic(g, "NDEATH", n)
            self.t_cmd = sparkplug.topic(g, "NCMD", n)
        else:
            self.t_status, self.t_metrics, self.t_state = (
                jsonmode.topic(cfg.topic_prefix, g, n, k) for k in ("status", "metrics", "state"))
            self.t_rows = {s: jsonmode.topic(cfg.topic_prefix, g, n, s)
                           for s in ("sample", "advice")}
        self._stop = threading.Event()
        self._live_lock = threading.Lock()
        self._live: tuple[dict, float] | None = None       # (status row, time) from the loop
        self._thread: threading.Thread | None = None
        self._client: mqtt.Client | None = None
        self._outbox: Outbox | None = None
        self._reset_session()
        self._acked_upto = 0          # every outbox id <= this was acknowledged
        self._deleted_upto = 0        # ... and deleted from the outbox
        self._expect: int | None = None
        self._last_ack_write = 0.0
        self._last_depth = -1e9
        self._newest_live = {"sample": -1, "advice": -1}
        self._bd_seq = 0
        self._conn_log = RepeatLog(log, f"MQTT broker {cfg.host}:{cfg.port}", level=logging.WARNING)
        self._db_log = RepeatLog(log, f"northbound outbox {self.history}")
        # counters
        self.connected = False
        self.queue_depth = 0
        self.published = 0
        self.historical = 0
        self.dropped = 0
        self.expired = 0
        self.births = 0
        self.connects = 0
        self.cpu_s = 0.0
        self.error: str | None = None      # the thread died (a bug): why
        # attach the outbox triggers now, before the gateway stores its first row, so that every
        # row stored from here on is queued (when the database is locked, the thread retries)
        self._ensure_outbox()

    @property
    def caught_up(self) -> bool:
        """Connected, born, and the backlog was found empty: rows stored now go out live."""
        return self.connected and self._session and self._caught_up and not self._need_birth

    # ---------------------------------------------------------------- observer interface

    async def start(self, gateway: Any) -> None:
        self._thread = threading.Thread(target=self._run, name="hp-edge-northbound", daemon=True)
        self._thread.start()
        log.info("northbound: MQTT %s publisher for %s:%s as %s/%s (client id %s)",
                 self.cfg.mode, self.cfg.host, self.cfg.port, self.cfg.group_id,
                 self.cfg.edge_node_id, self.cfg.effective_client_id)

    def cycle(self, event: Any) -> None:
        """Called on the event loop after every scan: hand over the status (never blocks)."""
        snap = event.snapshot
        on = set(snap.status_bits)
        word = sum(1 << b for b, name in self.bits if name in on)
        row = status_values(on, word, (name for _, name in self.bits))
        t = snap.sample_time if snap.sample_time is not None else time.time()
        with self._live_lock:
            self._live = (row, t)

    async def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, self.stop_timeout_s)
            if self._thread.is_alive():
                log.warning("northbound publisher did not stop within %g s", self.stop_timeout_s)

    # --------------------------------------------------------------------------- thread

    def _run(self) -> None:
        try:
            self._main()
        except Exception as exc:  # noqa: BLE001 - a bug here must not take the gateway down
            self.error = f"{type(exc).__name__}: {exc}"
            log.exception("northbound publisher stopped by an error: %s", exc)
        finally:
            self._shutdown()
            self.cpu_s = time.thread_time()

    def _main(self) -> None:
        backoff = self.cfg.reconnect_min_s
        next_try = 0.0
        while not self._stop.is_set():
            self.cpu_s = time.thread_time()
            if not self._ensure_outbox():
                self._stop.wait(min(backoff, 5.0))
                continue
            try:
                self._count_depth()
            except Exception as exc:  # noqa: BLE001 - sqlite: locked, I/O (counted again later)
                log.debug("northbound: outbox not counted: %s", exc)
            if self._client is None:
                now = time.monotonic()
                if now < next_try:
                    self._stop.wait(min(next_try - now, 1.0))
                    continue
                if not self._connect():
                    next_try = time.monotonic() + backoff
                    backoff = min(2 * backoff, self.cfg.reconnect_max_s)
                continue
            busy = bool(self._inflight or self._buffer) or not self._caught_up or self._more
            rc = self._client.loop(timeout=BUSY_LOOP_S if busy else IDLE_LOOP_S)
            if rc != mqtt.MQTT_ERR_SUCCESS or self._lost is not None:
                self._drop(self._lost or mqtt.error_string(rc))
                next_try = time.monotonic() + backoff
                backoff = min(2 * backoff, self.cfg.reconnect_max_s)
                continue
            if not self._session:
                if self._refused is not None:
                    self._drop(f"connection refused: {self._refused}")
                    next_try = time.monotonic() + backoff
                    backoff = min(2 * backoff, self.cfg.reconnect_max_s)
                elif time.monotonic() > self._connack_by:
                    self._drop(f"no CONNACK within {CONNACK_TIMEOUT_S:g} s")
                    next_try = time.monotonic() + backoff
                continue
            backoff = self.cfg.reconnect_min_s
            try:
                if self._need_birth:
                    self._birth()
                self._publish_status()
                self._pump()
                self._write_acks()
            except Exception as exc:  # noqa: BLE001 - sqlite (locked, I/O) or an encoding bug
                self._db_log.fail(f"{type(exc).__name__}: {exc}")
                log.debug("northbound step failed", exc_info=True)
                self._stop.wait(1.0)
            else:
                self._db_log.ok()

    # ------------------------------------------------------------------------ connection

    def _ensure_outbox(self) -> bool:
        ob = self._outbox
        if ob is not None and not ob.replaced():
            return True
        if ob is not None:
            log.warning("northbound: the history database %s was replaced; re-attaching the "
                        "outbox", self.history)
            ob.close()
            self._outbox = None
            self._acked_upto = self._deleted_upto = 0
            self._expect = None
            self._drop("history database replaced")
        try:
            self._outbox = Outbox(self.history, self.cfg.max_backlog_rows).open()
        except Exception as exc:  # noqa: BLE001 - sqlite3.Error, OSError: retried
            self._db_log.fail(f"cannot open: {exc}")
            return False
        self._db_log.ok()
        self._bd_seq = int(self._outbox.get_state("bdSeq", -1))
        return True

    def _reset_session(self) -> None:
        self._session = False         # CONNACK received (success)
        self._lost: str | None = None
        self._refused: str | None = None
        self._connack_by = 0.0
        self._need_birth = False
        self._caught_up = False
        self._more = False            # the last outbox fetch was full: more may wait
        self._seq = 0
        self._inflight: dict[int, int] = {}       # mid -> outbox id
        self._order: deque[list] = deque()        # [outbox id, acked?, historical?] in send
        #                                           order (historical None: nothing was sent)
        self._buffer: deque[Entry] = deque()
        self._last_status: dict | None = None

    def _connect(self) -> bool:
        cfg = self.cfg
        self._reset_session()
        bd_seq = (self._bd_seq + 1) % 256      # counts CONNECT packets sent (Sparkplug bdSeq)
        c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=cfg.effective_client_id,
                        clean_session=True, protocol=mqtt.MQTTv311)
        c.connect_timeout = min(5.0, cfg.keepalive_s)
        c.max_inflight_messages_set(WINDOW)
        if cfg.username:
            c.username_pw_set(cfg.username, cfg.password)
        if cfg.tls is not None:
            t = cfg.tls
            c.tls_set(ca_certs=str(t.ca_file) if t.ca_file else None,
                      certfile=str(t.cert_file) if t.cert_file else None,
                      keyfile=str(t.key_file) if t.key_file else None)
            if t.insecure:
                c.tls_insecure_set(True)
        now_ms = int(time.time() * 1000)
        if self.sparkplug:
            c.will_set(self.t_death, sparkplug.encode_death(bd_seq=bd_seq,
                                                            timestamp_ms=now_ms), qos=1)
        else:
            c.will_set(self.t_status, jsonmode.status(False, time.time()), qos=1, retain=True)
        c.on_connect = self._on_connect
        c.on_disconnect = self._on_disconnect
        c.on_publish = self._on_publish
        c.on_message = self._on_message
        try:
            c.connect(cfg.host, cfg.port, keepalive=int(cfg.keepalive_s))
        except (OSError, ValueError) as exc:      # refused, unreachable, TLS, timeout
            self._conn_log.fail(f"cannot connect: {exc}")
            return False
        self._bd_seq = bd_seq
        assert self._outbox is not None
        self._outbox.set_state("bdSeq", bd_seq)
        self.connects += 1
        self._client = c
        self._connack_by = time.monotonic() + CONNACK_TIMEOUT_S
        return True

    def _drop(self, why: str) -> None:
        c, self._client = self._client, None
        was = self.connected
        self.connected = False
        if c is not None:
            try:
                c.disconnect()
            except Exception:  # noqa: BLE001 - the socket is gone already
                pass
            try:
                c.loop(timeout=0.01)     # writes the DISCONNECT, and paho closes the socket
            except Exception:  # noqa: BLE001
                pass
        if self._expect is not None:
            self._expect = self._acked_upto + 1
        self._reset_session()
        if was or c is not None:
            self._conn_log.fail(f"{why}; rows wait in the history database and are sent, "
                                "marked historical, after the reconnect")

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            self._refused = str(reason_code)
            return
        self._session = True
        self.connected = True
        self._need_birth = True
        if self.sparkplug:
            client.subscribe(self.t_cmd, qos=1)
        self._conn_log.ok(f"connected, bdSeq {self._bd_seq}")
        if not self._conn_log.total:
            log.info("northbound: connected to %s:%s", self.cfg.host, self.cfg.port)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        if client is self._client:
            self._lost = f"disconnected ({reason_code})"

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        oid = self._inflight.pop(mid, None)
        if oid is None:
            return
        for item in self._order:
            if item[0] == oid:
                item[1] = True
                break

    def _on_message(self, client, userdata, msg) -> None:
        if not self.sparkplug or msg.topic != self.t_cmd:
            return
        try:
            if sparkplug.wants_rebirth(msg.payload):
                log.info("northbound: rebirth requested (NCMD)")
                self._need_birth = True
        except ValueError as exc:
            log.warning("northbound: NCMD ignored: %s", exc)

    # -------------------------------------------------------------------------- publish

    def _status(self) -> tuple[dict, float] | None:
        with self._live_lock:
            return self._live

    def _birth(self) -> None:
        assert self._client is not None and self._outbox is not None
        now = time.time()
        cat = self.catalog
        live = self._status()
        if self.sparkplug:
            values: dict[str, Any] = {}
            stamps: dict[str, int] = {}
            for source in ("sample", "advice"):
                row = self._outbox.latest(source)
                if row is not None:
                    for spec, v in cat.values(source, row).items():
                        values[spec.name] = v
                        stamps[spec.name] = int(row["ts"]) * 1000
            if live is not None:
                for spec, v in cat.values("status", live[0]).items():
                    values[spec.name] = v
                    stamps[spec.name] = int(live[1] * 1000)
            self._seq = 0
            self._client.publish(self.t_birth, sparkplug.encode_birth(
                cat, values, seq=0, bd_seq=self._bd_seq, timestamp_ms=int(now * 1000),
                metric_ts_ms=stamps), qos=0)
        else:
            self._client.publish(self.t_status, jsonmode.status(True, now), qos=1, retain=True)
            self._client.publish(self.t_metrics, jsonmode.metrics(cat, now), qos=1, retain=True)
        self._last_status = dict(live[0]) if live is not None and self.sparkplug else None
        self._need_birth = False
        self.births += 1

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) % 256
        return self._seq

    def _publish_status(self) -> None:
        live = self._status()
        if live is None or self._client is None:
            return
        row, t = live
        last = self._last_status
        changed = {k: v for k, v in row.items() if last is None or last.get(k) != v}
        if not changed:
            return
        values = {spec: v for spec, v in self.catalog.values("status", row).items()
                  if spec.key in changed}
        if self.sparkplug:
            payload = sparkplug.encode_data(self.catalog, values.items(), seq=self._next_seq(),
                                            timestamp_ms=int(time.time() * 1000),
                                            metric_ts_ms=int(t * 1000), historical=False)
            self._client.publish(self.t_data, payload, qos=0)
        else:
            self._client.publish(self.t_state, jsonmode.state(
                self.catalog.values("status", row), t), qos=1, retain=True)
        self._last_status = dict(row)

    def _pump(self) -> None:
        """Send outbox rows in order while fewer than WINDOW are unacknowledged."""
        assert self._client is not None and self._outbox is not None
        budget = WINDOW          # per call, so the network loop runs between batches (QoS 0)
        while len(self._inflight) < WINDOW and not self._need_birth and budget > 0:
            if not self._buffer:
                if self._caught_up and not self._more and not self._outbox.changed():
                    return                   # nothing was stored since the last empty fetch
                after = self._order[-1][0] if self._order else self._acked_upto
                got = self._outbox.fetch(after, FETCH)
                # a full fetch may have left entries of the same commit behind: read on without
                # waiting for another commit (changed() has already seen this one)
                self._more = len(got) == FETCH
                if not got:
                    self._caught_up = True
                    return
                self._buffer.extend(got)
            e = self._buffer.popleft()
            if self._expect is not None and e.id > self._expect:
                gap = e.id - self._expect
                self.dropped += gap
                log.error("northbound: %d row(s) dropped from the backlog (more than "
                          "max_backlog_rows %d waited for the broker)", gap,
                          self.cfg.max_backlog_rows)
            self._expect = e.id + 1
            if e.row is None:            # pruned by retention before it could be sent
                self.expired += 1
                self._order.append([e.id, True, None])
                continue
            historical = not self._caught_up or e.ts < self._newest_live[e.source]
            values = self.catalog.values(e.source, e.row).items()
            if self.sparkplug:
                info = self._client.publish(self.t_data, sparkplug.encode_data(
                    self.catalog, values, seq=self._next_seq(),
                    timestamp_ms=int(time.time() * 1000), metric_ts_ms=e.ts * 1000,
                    historical=historical), qos=self.cfg.qos)
            else:
                info = self._client.publish(self.t_rows[e.source],
                                            jsonmode.record(values, e.ts, historical),
                                            qos=self.cfg.qos)
            if info.rc != mqtt.MQTT_ERR_SUCCESS:
                self._buffer.appendleft(e)        # the connection is going: resent later
                self._expect = e.id
                return
            budget -= 1
            self._inflight[info.mid] = e.id
            self._order.append([e.id, False, historical])
            if not historical:
                self._newest_live[e.source] = max(self._newest_live[e.source], e.ts)
            if info.is_published():          # QoS 0: written at once, no acknowledgement
                self._on_publish(self._client, None, info.mid, None, None)

    def _write_acks(self, force: bool = False) -> None:
        while self._order and self._order[0][1]:
            oid, _, historical = self._order.popleft()
            self._acked_upto = oid
            if historical is not None:
                self.published += 1
                self.historical += bool(historical)
        now = time.monotonic()
        if self._acked_upto > self._deleted_upto and (force or now - self._last_ack_write
                                                      >= ACK_EVERY_S):
            assert self._outbox is not None
            self._outbox.ack(self._acked_upto)
            self._deleted_upto = self._acked_upto
            self._last_ack_write = now

    def _count_depth(self) -> None:
        now = time.monotonic()
        if now - self._last_depth >= DEPTH_EVERY_S and self._outbox is not None:
            self._last_depth = now
            waiting = self._outbox.depth() - (self._acked_upto - self._deleted_upto)
            self.queue_depth = max(0, waiting)

    # ------------------------------------------------------------------------- shutdown

    def _shutdown(self) -> None:
        c = self._client
        try:
            if c is not None and self._session:
                deadline = time.monotonic() + STOP_FLUSH_S
                while self._inflight and time.monotonic() < deadline and self._lost is None:
                    c.loop(timeout=0.05)
                self._write_acks(force=True)
                if self.sparkplug:
                    info = c.publish(self.t_death, sparkplug.encode_death(
                        bd_seq=self._bd_seq, timestamp_ms=int(time.time() * 1000)), qos=1)
                else:
                    info = c.publish(self.t_status, jsonmode.status(False, time.time()), qos=1,
                                     retain=True)
                deadline = time.monotonic() + 1.0
                while not info.is_published() and time.monotonic() < deadline \
                        and self._lost is None:
                    c.loop(timeout=0.05)
                c.disconnect()
                c.loop(timeout=0.05)
        except Exception as exc:  # noqa: BLE001 - best effort: the will covers the rest
            log.warning("northbound: clean disconnect failed: %s", exc)
        finally:
            self._client = None
            self.connected = False
            if self._outbox is not None:
                try:
                    self._write_acks(force=True)
                except Exception as exc:  # noqa: BLE001 - re-sent after the restart instead
                    log.warning("northbound: acknowledged rows not removed from the outbox "
                                "(they are re-sent as historical): %s", exc)
                self._outbox.close()
                self._outbox = None
