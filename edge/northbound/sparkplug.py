"""Sparkplug B payloads of the edge node (Sparkplug 3.0): NBIRTH, NDATA, NDEATH, and reading NCMD.

The protobuf schema is Eclipse Tahu's ``sparkplug_b.proto`` as compiled and packaged by the
``tahutils`` distribution (``tahutils.tahu.sparkplug_b_pb2``; the optional extra ``northbound``),
so no generated code lives in this repository. This module only fills messages:

* NBIRTH: ``bdSeq``, ``Node Control/Rebirth`` (false) and every metric of the catalog with its
  name, alias, datatype, ``engUnit`` property and current value (null when unknown); seq 0;
* NDATA: metrics by alias only (the birth told name and datatype), each with its own timestamp
  and ``is_historical`` for store-and-forward; seq 1..255, 0, 1, ...;
* NDEATH: ``bdSeq`` only (registered as the MQTT will; published before a clean disconnect).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from tahutils.tahu import sparkplug_b_pb2 as pb

from edge.northbound.metrics import DATATYPES, Catalog, MetricSpec

NAMESPACE = "spBv1.0"
BDSEQ = "bdSeq"
REBIRTH = "Node Control/Rebirth"
UNIT_PROPERTY = "engUnit"
_STRING = DATATYPES["String"]
_FIELD = {"Int64": "long_value", "UInt16": "int_value", "UInt32": "int_value",
          "UInt64": "long_value", "Double": "double_value", "Boolean": "boolean_value",
          "String": "string_value"}

Payload = pb.Payload     # for readers (tests, a subscriber): Payload.FromString(bytes)


def topic(group_id: str, message_type: str, edge_node_id: str) -> str:
    return f"{NAMESPACE}/{group_id}/{message_type}/{edge_node_id}"


def _set_value(m: Any, datatype: str, value: Any) -> None:
    if value is None:
        m.is_null = True
    else:
        setattr(m, _FIELD[datatype], value)


def encode_birth(catalog: Catalog, values: Mapping[str, Any], *, seq: int, bd_seq: int,
                 timestamp_ms: int, metric_ts_ms: Mapping[str, int] | None = None) -> bytes:
    """NBIRTH. ``values``: metric name -> current value (absent or None: null);
    ``metric_ts_ms``: metric name -> when that value was true (default: the payload's time)."""
    p = pb.Payload(timestamp=timestamp_ms, seq=seq)
    m = p.metrics.add(name=BDSEQ, timestamp=timestamp_ms, datatype=DATATYPES["Int64"])
    m.long_value = bd_seq
    m = p.metrics.add(name=REBIRTH, timestamp=timestamp_ms, datatype=DATATYPES["Boolean"])
    m.boolean_value = False
    ts = metric_ts_ms or {}
    for spec in catalog.metrics:
        m = p.metrics.add(name=spec.name, alias=catalog.alias(spec),
                          timestamp=ts.get(spec.name, timestamp_ms),
                          datatype=DATATYPES[spec.datatype])
        if spec.unit:
            m.properties.keys.append(UNIT_PROPERTY)
            m.properties.values.add(type=_STRING, string_value=spec.unit)
        _set_value(m, spec.datatype, values.get(spec.name))
    return p.SerializeToString()


def encode_data(catalog: Catalog, values: Iterable[tuple[MetricSpec, Any]], *, seq: int,
                timestamp_ms: int, metric_ts_ms: int, historical: bool) -> bytes:
    """NDATA with the given metric values, all true at ``metric_ts_ms``."""
    p = pb.Payload(timestamp=timestamp_ms, seq=seq)
    for spec, value in values:
        m = p.metrics.add(alias=catalog.alias(spec), timestamp=metric_ts_ms)
        if historical:
            m.is_historical = True
        _set_value(m, spec.datatype, value)
    return p.SerializeToString()


def encode_death(*, bd_seq: int, timestamp_ms: int) -> bytes:
    p = pb.Payload(timestamp=timestamp_ms)
    m = p.metrics.add(name=BDSEQ, timestamp=timestamp_ms, datatype=DATATYPES["Int64"])
    m.long_value = bd_seq
    return p.SerializeToString()


def wants_rebirth(payload: bytes) -> bool:
    """True when an NCMD payload asks for a rebirth (``Node Control/Rebirth`` = true). Raises
    ValueError for a payload that is not a Sparkplug B message."""
    try:
        p = pb.Payload.FromString(payload)
    except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
        raise ValueError(f"not a Sparkplug B payload: {exc}") from exc
    for m in p.metrics:
        if m.name == REBIRTH and m.WhichOneof("value") == "boolean_value" and m.boolean_value:
            return True
    return False
