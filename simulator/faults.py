"""Fault injection: field-device misbehaviour the gateway must survive.

Tag faults act on the engineering values before encoding:
  stuck         the tag keeps the value it had when the fault came on
  out_of_range  the tag reads `value` (default: the range's high end plus its width, saturated by
                the register type)
  nan           the tag reads "no value": its sentinel, or an IEEE NaN for float32
Server faults act on the Modbus side:
  slow          each response is delayed by delay_s (with the given probability)
  drop          the connection is closed instead of answering (with the given probability)
  frozen        registers stop updating and the life counter stops, as a Profibus-to-Modbus gateway
                does when its Profibus link drops; writes reach the gateway's memory, not the plant
  restart       the server goes down (listener and connections closed) and comes back after
                down_s wall seconds, or when the fault is switched off

Every fault is switched with ``enable`` / ``disable`` (tests, CLI ``--fault``) or scheduled in plant
time by config (``faults:`` list of simulator.yaml, FaultSpec.at_h / duration_h).
"""
from __future__ import annotations

import dataclasses
import math
import random

from .config import SERVER_FAULTS, TAG_FAULTS, FaultSpec, SimConfigError, TagSpec, fault_from_dict

FAULTABLE_EXCLUDED = ("plc_clock", "life_counter", "p_m_sp")   # frozen covers the system registers


class Faults:
    """The set of active faults. Used from the event-loop thread only."""

    def __init__(self, tags: dict[str, TagSpec], seed: int = 0):
        self.tags = tags
        self._rng = random.Random(seed)
        self._tag: dict[tuple[str, str], FaultSpec] = {}
        self._server: dict[str, FaultSpec] = {}
        self._stuck_values: dict[str, float] = {}
        self.listeners: list = []      # callables(kind, tag, on) - the server reacts to restart
        self.history: list[tuple[str, str | None, bool]] = []

    # --------------------------------------------------------------------------- switching --
    def enable(self, kind: str, tag: str | None = None, **params) -> FaultSpec:
        """Switch a fault on (replacing the same kind/tag). Parameters: see FaultSpec."""
        spec = fault_from_dict({"kind": kind, "tag": tag, **params}, f"fault {kind}")
        return self.enable_spec(spec)

    def enable_spec(self, spec: FaultSpec) -> FaultSpec:
        spec = dataclasses.replace(spec, at_h=None, duration_h=None) if spec.at_h is not None else spec
        if spec.kind in TAG_FAULTS:
            self._check_tag(spec)
            self._tag[(spec.kind, spec.tag)] = spec
            self._stuck_values.pop(spec.tag, None)
        else:
            self._server[spec.kind] = spec
        self.history.append((spec.kind, spec.tag, True))
        for cb in list(self.listeners):
            cb(spec.kind, spec.tag, True)
        return spec

    def disable(self, kind: str, tag: str | None = None) -> bool:
        """Switch a fault off; returns whether it was on."""
        if kind in TAG_FAULTS:
            was = self._tag.pop((kind, tag), None) is not None
            if kind == "stuck":
                self._stuck_values.pop(tag, None)
        elif kind in SERVER_FAULTS:
            was = self._server.pop(kind, None) is not None
        else:
            raise SimConfigError(f"unknown fault kind {kind!r}")
        if was:
            self.history.append((kind, tag, False))
            for cb in list(self.listeners):
                cb(kind, tag, False)
        return was

    def clear(self) -> None:
        for kind, tag in list(self._tag):
            self.disable(kind, tag)
        for kind in list(self._server):
            self.disable(kind)

    def active(self) -> list[FaultSpec]:
        return list(self._tag.values()) + list(self._server.values())

    def is_on(self, kind: str, tag: str | None = None) -> bool:
        return (kind, tag) in self._tag if kind in TAG_FAULTS else kind in self._server

    def _check_tag(self, spec: FaultSpec) -> None:
        t = self.tags.get(spec.tag)
        if t is None:
            raise SimConfigError(f"fault {spec.kind}: unknown tag {spec.tag!r}")
        if spec.tag in FAULTABLE_EXCLUDED:
            raise SimConfigError(f"fault {spec.kind}: tag {spec.tag} is a system/set-point register "
                                 f"(use the frozen fault for the PLC's system registers)")
        if spec.kind == "nan" and t.sentinel is None and t.type != "float32":
            raise SimConfigError(f"fault nan: tag {spec.tag} ({t.type}) has no sentinel, so it "
                                 f"cannot carry 'no value'")

    # ---------------------------------------------------------------------------- applying --
    def apply(self, values: dict[str, float]) -> dict[str, float]:
        """Tag faults applied to a {tag: engineering value} dict (a new dict)."""
        if not self._tag:
            return values
        out = dict(values)
        for (kind, tag), spec in self._tag.items():
            if kind == "stuck":
                if tag not in self._stuck_values:
                    self._stuck_values[tag] = out.get(tag, math.nan)
                out[tag] = self._stuck_values[tag]
        for (kind, tag), spec in self._tag.items():
            if kind == "out_of_range":
                lo, hi = self.tags[tag].range
                out[tag] = spec.value if spec.value is not None else (
                    hi + (hi - lo) if math.isfinite(hi - lo) else 1e9)
            elif kind == "nan":
                out[tag] = math.nan
        return out

    @property
    def frozen(self) -> bool:
        return "frozen" in self._server

    def response_delay(self) -> float:
        spec = self._server.get("slow")
        if spec is None or self._rng.random() >= spec.probability:
            return 0.0
        return spec.delay_s

    def should_drop(self) -> bool:
        spec = self._server.get("drop")
        return spec is not None and self._rng.random() < spec.probability


def parse_cli_fault(text: str) -> FaultSpec:
    """``KIND[:TAG][:key=value,...]`` -> FaultSpec, e.g. ``stuck:T_e``, ``slow:delay_s=3``,
    ``out_of_range:T_c:value=150``, ``frozen:at_h=2,duration_h=0.5``."""
    parts = text.split(":")
    d: dict = {"kind": parts[0]}
    for part in parts[1:]:
        if "=" in part:
            for kv in part.split(","):
                k, _, v = kv.partition("=")
                try:
                    d[k.strip()] = float(v)
                except ValueError:
                    raise SimConfigError(f"--fault {text}: {k} needs a number, got {v!r}") from None
        elif part:
            d["tag"] = part
    return fault_from_dict(d, f"--fault {text}")
