"""The plain-JSON topic layout (``northbound.mqtt.mode: json``), for users without a Sparkplug host.

Under ``<topic_prefix>/<group_id>/<edge_node_id>/``:

* ``status`` (retained, QoS 1): ``{"online": true|false, "time": ...}``; ``false`` is the MQTT
  will, so a gateway that dies is shown offline by the broker;
* ``metrics`` (retained): every metric's name, datatype, unit and source (the birth certificate);
* ``sample`` (QoS of ``qos``): one message per one-minute sample, in the order stored;
* ``advice`` (QoS of ``qos``): one message per calibration cycle;
* ``state`` (retained): the status word and bits, when they change.

A sample or advice message is ``{"ts": <epoch s>, "time": "<ISO 8601 UTC>", "historical":
<bool>, "values": {<metric name>: <value or null>, ...}}``; ``historical`` is true for a message
sent from the store-and-forward backlog (the same rule as Sparkplug's ``is_historical``).
"""
from __future__ import annotations

import json
import time
from collections.abc import Iterable, Mapping
from typing import Any

from edge.northbound.metrics import Catalog, MetricSpec

KINDS = ("status", "metrics", "sample", "advice", "state")


def topic(prefix: str, group_id: str, edge_node_id: str, kind: str) -> str:
    if kind not in KINDS:
        raise ValueError(f"unknown JSON topic kind {kind!r}")
    return f"{prefix}/{group_id}/{edge_node_id}/{kind}"


def iso(ts: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ts))


def status(online: bool, now: float) -> bytes:
    return _dump({"online": online, "time": iso(now)})


def metrics(catalog: Catalog, now: float) -> bytes:
    return _dump({"time": iso(now), "metrics": [
        {"name": m.name, "datatype": m.datatype, "unit": m.unit, "source": m.source}
        for m in catalog.metrics]})


def record(values: Iterable[tuple[MetricSpec, Any]], ts: float, historical: bool) -> bytes:
    return _dump({"ts": int(ts), "time": iso(ts), "historical": bool(historical),
                  "values": {spec.name: v for spec, v in values}})


def state(values: Mapping[MetricSpec, Any], ts: float) -> bytes:
    return _dump({"ts": int(ts), "time": iso(ts),
                  "values": {spec.name: v for spec, v in values.items()}})


def _dump(doc: dict) -> bytes:
    # values are typed already (None for NaN): strict JSON, no NaN tokens
    return json.dumps(doc, allow_nan=False, separators=(",", ":")).encode("utf-8")
