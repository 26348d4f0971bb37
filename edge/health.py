"""The health endpoint (issue 14): the gateway's own state in the Prometheus text exposition format
(version 0.0.4), served over HTTP on 127.0.0.1 by default (``northbound.health`` in gateway.yaml).

``GET /metrics`` answers the text below; anything else is 404. The server runs on the gateway's
event loop (asyncio), keeps no connection open (HTTP/1.0 style, one request per connection, 5 s
to send it) and renders from counters the loop updates after every cycle (``HealthServer.cycle``),
so a scrape never waits for the PLC, the disk or the broker. The text is written by hand: it is a
few dozen lines of a simple format, and the daemon stays free of a dependency (the tests parse it
with prometheus-client's own parser).

Metrics (all prefixed ``hp_edge_``):

=========================================  =======  ==========================================
name                                       type     what
=========================================  =======  ==========================================
up                                         gauge    1 while the gateway runs
scans_total                                counter  scan cycles
scan_duration_seconds                      summary  poll + aggregate + write per cycle
scan_duration_last_seconds                 gauge    the last cycle's duration
poll_errors_total{kind}                    counter  cycles whose poll failed, by reason
                                                    (timeout, connection_lost, not_connected,
                                                    connect_failed, protocol_error), and
                                                    cycles with a Modbus exception reply
tag_errors_total{reason}                   counter  tag values marked bad, by reason (out_of_range,
                                                    sentinel, nan, inf, modbus_exception, ...)
last_successful_poll_age_seconds           gauge    since the last poll without a comm error
                                                    (+Inf before the first)
samples_total                              counter  one-minute samples stored
calibrations_total{outcome}                counter  ok, calibration_failed, optimization_failed,
                                                    skipped
calibration_duration_seconds               summary  wall time of the calibration cycles
calibration_last_duration_seconds          gauge
advisory_writes_total{result}              counter  ok, failed
heartbeat                                  gauge    the heartbeat last written
advisory_value{field,unit}                 gauge    every value of the advisory block (NaN: none)
status_word                                gauge    the status register
status_bit{name,bit}                       gauge    each status bit, 0 or 1
errors_total                               counter  unexpected errors the loop survived
mqtt_connected                             gauge    1 while connected to the broker
mqtt_queue_depth                           gauge    rows waiting for the broker
mqtt_published_total{kind}                 counter  data messages acknowledged: live, historical
mqtt_dropped_total                         counter  rows lost to the backlog cap
mqtt_publisher_cpu_seconds_total           counter  CPU time of the publisher thread
=========================================  =======  ==========================================

(the ``mqtt_*`` lines appear only when the MQTT publisher is enabled.)
"""
from __future__ import annotations

import asyncio
import logging
import math
import re
from collections import Counter
from typing import Any

from edge.northbound.config import HealthConfig

log = logging.getLogger(__name__)

PREFIX = "hp_edge_"
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
REQUEST_TIMEOUT_S = 5.0
MAX_REQUEST_BYTES = 8192
LOOP_FIELDS = ("heartbeat", "status")     # shown as their own metrics, not as advisory values


def _kind(reason: str) -> str:
    """'out of range [0, 80]' -> 'out_of_range'; 'modbus exception 2' -> 'modbus_exception'."""
    reason = re.sub(r"\s*(\[.*\]|\d+)\s*$", "", reason.strip())
    return re.sub(r"[^a-z0-9]+", "_", reason.lower()).strip("_") or "unknown"


def _num(v: Any) -> str:
    if v is None:
        return "NaN"
    f = float(v)
    if math.isnan(f):
        return "NaN"
    if math.isinf(f):
        return "+Inf" if f > 0 else "-Inf"
    return repr(f) if not f.is_integer() or abs(f) >= 1e15 else str(int(f))


def _label(v: Any) -> str:
    return str(v).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


class _Text:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def family(self, name: str, kind: str, help_: str) -> None:
        self.lines.append(f"# HELP {PREFIX}{name} {help_}")
        self.lines.append(f"# TYPE {PREFIX}{name} {kind}")

    def sample(self, metric: str, value: Any, **labels: Any) -> None:
        lab = ",".join(f'{k}="{_label(v)}"' for k, v in labels.items())
        self.lines.append(f"{PREFIX}{metric}{{{lab}}} {_num(value)}" if lab
                          else f"{PREFIX}{metric} {_num(value)}")

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


class HealthServer:
    """Observer of ``edge.loop.Gateway``: counts what each cycle did and serves it.

    cfg : ``northbound.health`` (bind address, port; port 0 picks a free one: ``port`` after
        ``start`` is the one bound)
    publisher : the MQTT publisher whose counters to show (edge.northbound.publisher), or None
    """

    def __init__(self, cfg: HealthConfig, *, publisher: Any = None) -> None:
        self.cfg = cfg
        self.publisher = publisher
        self.port: int | None = None
        self._server: asyncio.base_events.Server | None = None
        self._gw: Any = None
        self.scans = 0
        self.scan_sum = 0.0
        self.scan_last = math.nan
        self.poll_errors: Counter[str] = Counter()
        self.tag_errors: Counter[str] = Counter()
        self.last_ok_poll: float | None = None       # gateway monotonic time
        self.samples = 0
        self.calibrations: Counter[str] = Counter({k: 0 for k in (
            "ok", "calibration_failed", "optimization_failed", "skipped")})
        self.calibration_sum = 0.0
        self.calibration_count = 0
        self.calibration_last = math.nan
        self.scrapes = 0

    # ---------------------------------------------------------------- observer interface

    async def start(self, gateway: Any) -> None:
        self._gw = gateway
        self._server = await asyncio.start_server(self._handle, self.cfg.bind, self.cfg.port,
                                                  reuse_address=True, limit=MAX_REQUEST_BYTES)
        self.port = self._server.sockets[0].getsockname()[1]
        log.info("health endpoint: http://%s:%d/metrics", self.cfg.bind, self.port)

    def cycle(self, event: Any) -> None:
        self.scans += 1
        self.scan_sum += event.duration_s
        self.scan_last = event.duration_s
        res = event.result
        if res.comm_error is None:
            self.last_ok_poll = event.t_mono
        else:
            self.poll_errors[_kind(res.comm_error)] += 1
        exception = False
        for v in res.values.values():
            if v.bad is not None and (res.comm_error is None or v.bad != res.comm_error):
                kind = _kind(v.bad)
                self.tag_errors[kind] += 1
                exception |= kind == "modbus_exception"
        if exception:
            self.poll_errors["modbus_exception"] += 1
        self.samples += len(event.rows)
        adv = event.advice
        if adv is not None:
            outcome = ("skipped" if adv.skipped else "calibration_failed"
                       if not adv.calibration_ok else "optimization_failed"
                       if not adv.optimization_ok else "ok")
            self.calibrations[outcome] += 1
            if event.calibration_s is not None and not adv.skipped:
                self.calibration_sum += event.calibration_s
                self.calibration_count += 1
                self.calibration_last = event.calibration_s

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None

    # ------------------------------------------------------------------------- rendering

    def render(self) -> str:
        """The exposition text as of now."""
        t = _Text()
        gw = self._gw
        snap = gw.snapshot if gw is not None else None
        t.family("up", "gauge", "1 while the gateway runs")
        t.sample("up", 1)
        t.family("scans_total", "counter", "scan cycles completed")
        t.sample("scans_total", self.scans)
        t.family("scan_duration_seconds", "summary", "duration of a scan cycle (poll to write)")
        t.sample("scan_duration_seconds_sum", self.scan_sum)
        t.sample("scan_duration_seconds_count", self.scans)
        t.family("scan_duration_last_seconds", "gauge", "duration of the last scan cycle")
        t.sample("scan_duration_last_seconds", self.scan_last)
        t.family("poll_errors_total", "counter", "scan cycles whose poll failed, by kind")
        for kind, n in sorted(self.poll_errors.items()):
            t.sample("poll_errors_total", n, kind=kind)
        t.family("tag_errors_total", "counter", "tag values marked bad, by reason")
        for kind, n in sorted(self.tag_errors.items()):
            t.sample("tag_errors_total", n, reason=kind)
        t.family("last_successful_poll_age_seconds", "gauge",
                 "seconds since the last poll without a communication error")
        now = gw.monotonic() if gw is not None else None
        t.sample("last_successful_poll_age_seconds",
                 math.inf if self.last_ok_poll is None or now is None
                 else max(0.0, now - self.last_ok_poll))
        t.family("samples_total", "counter", "one-minute samples stored")
        t.sample("samples_total", self.samples)
        t.family("calibrations_total", "counter", "calibration cycles, by outcome")
        for outcome, n in sorted(self.calibrations.items()):
            t.sample("calibrations_total", n, outcome=outcome)
        t.family("calibration_duration_seconds", "summary", "wall time of a calibration cycle")
        t.sample("calibration_duration_seconds_sum", self.calibration_sum)
        t.sample("calibration_duration_seconds_count", self.calibration_count)
        t.family("calibration_last_duration_seconds", "gauge",
                 "wall time of the last calibration cycle")
        t.sample("calibration_last_duration_seconds", self.calibration_last)
        if snap is not None:
            t.family("advisory_writes_total", "counter", "advisory block writes, by result")
            t.sample("advisory_writes_total", snap.writes_ok, result="ok")
            t.sample("advisory_writes_total", snap.writes_failed, result="failed")
            t.family("heartbeat", "gauge", "the heartbeat register last written")
            t.sample("heartbeat", snap.heartbeat)
            adv = gw.cfg.advisory
            t.family("advisory_value", "gauge", "the advisory block's values (NaN: no value)")
            for f in adv.fields:
                if f.name in LOOP_FIELDS:
                    continue
                t.sample("advisory_value", snap.values.get(f.name), field=f.name, unit=f.unit)
            on = set(snap.status_bits)
            t.family("status_word", "gauge", "the status register")
            t.sample("status_word", sum(1 << b for b, n in adv.status_bits if n in on))
            t.family("status_bit", "gauge", "each status bit (1: set)")
            for b, n in sorted(adv.status_bits):
                t.sample("status_bit", int(n in on), name=n, bit=b)
            t.family("errors_total", "counter", "unexpected errors the loop survived")
            t.sample("errors_total", snap.errors)
        pub = self.publisher
        if pub is not None:
            t.family("mqtt_connected", "gauge", "1 while connected to the MQTT broker")
            t.sample("mqtt_connected", int(bool(pub.connected)))
            t.family("mqtt_queue_depth", "gauge", "rows waiting to be acknowledged by the broker")
            t.sample("mqtt_queue_depth", pub.queue_depth)
            t.family("mqtt_published_total", "counter", "data messages acknowledged, by kind")
            t.sample("mqtt_published_total", pub.published - pub.historical, kind="live")
            t.sample("mqtt_published_total", pub.historical, kind="historical")
            t.family("mqtt_dropped_total", "counter", "rows dropped from a full backlog")
            t.sample("mqtt_dropped_total", pub.dropped)
            t.family("mqtt_publisher_cpu_seconds_total", "counter",
                     "CPU time of the publisher thread")
            t.sample("mqtt_publisher_cpu_seconds_total", pub.cpu_s)
        return t.text()

    # ---------------------------------------------------------------------------- HTTP

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
        except (asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError,
                ConnectionError):
            writer.close()
            return
        line = head.split(b"\r\n", 1)[0].decode("latin-1")
        parts = line.split()
        if len(parts) < 2 or parts[0] not in ("GET", "HEAD"):
            status, body, ctype = "405 Method Not Allowed", "GET /metrics\n", "text/plain"
        elif parts[1].split("?", 1)[0] == "/metrics":
            self.scrapes += 1
            status, body, ctype = "200 OK", self.render(), CONTENT_TYPE
        else:
            status, body, ctype = "404 Not Found", "see /metrics\n", "text/plain"
        data = body.encode("utf-8")
        writer.write((f"HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: "
                      f"{len(data)}\r\nConnection: close\r\n\r\n").encode("latin-1"))
        if parts and parts[0] != "HEAD":
            writer.write(data)
        try:
            await asyncio.wait_for(writer.drain(), REQUEST_TIMEOUT_S)
        except (asyncio.TimeoutError, ConnectionError):
            pass
        finally:
            writer.close()
