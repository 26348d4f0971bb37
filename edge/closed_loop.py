"""The guarded closed loop (SPEC 7.4, issue 13): the gateway writes the PLC's intermediate-pressure
set point p_m,sp itself, toward the advice, only while an operator enables it.

Off by default (gateway.yaml ``closed_loop: enabled: false``). When gateway.yaml enables it, the
loop still writes nothing until the operator sets the enable tag (a register or bit the PLC/HMI
owns; hp-edge only reads it) with a rising edge the gateway sees, and then only:

* at most one step of at most ``max_step_bar`` per ``min_interval_s`` (on the sample clock, like
  the calibration cadence), toward the latest advice's ``p_m_sp_rec`` clipped into
  ``bounds_bar_g``; every written value lies inside the bounds (checked on the register value the
  PLC will hold, after quantization), and is never written while a blocking status bit is set
  (``BLOCKING_BITS``: the issue's data_stale, comm_fault, calibration_failed, model_infeasible,
  advice_stale, advice_low_confidence, and also heat_pump_off, cip_detected, sensor_fault and
  clock_fault);
* to the set-point tag's registers only, through ``PlcClient.write_setpoint`` (edge/plc.py builds
  that one request and refuses every other address);
* read back right after the write: a PLC that does not hold the written words sheds the loop, and
  so does a set point that changed between two scans without the gateway (an operator at the HMI,
  the PLC's own fallback), a write the PLC refuses or does not answer, and ``shed_after_bad_scans``
  scans in a row without usable data (poll failed, data stale, the set point or the enable
  unreadable).

Shed is latched until the operator drops the enable. On disable, on shed and on shutdown the
gateway stops writing at once and leaves the PLC's value as it is: the PLC owns the fallback
(docs/closed_loop.md: it reverts to the operator's local set point when the enable drops or the
advisory heartbeat has not changed for ``heartbeat_timeout_s``).

States (advisory field ``closed_loop_state``) and reasons (``closed_loop_reason``) are the
enumerations ``State`` and ``Reason``; every write and every change of state is logged and goes
to the history database (table ``closed_loop``, edge.store) through the ``audit`` callable.
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from edge.codec import BIT_SPACES, BOOL, format_number, is_integer_type, raw_limits, \
    raw_to_registers, raw_value

log = logging.getLogger(__name__)

# the six, and the plant and input states in which a set-point change makes no sense
BLOCKING_BITS = ("data_stale", "comm_fault", "calibration_failed", "model_infeasible",
                 "advice_stale", "advice_low_confidence", "heat_pump_off", "cip_detected",
                 "sensor_fault", "clock_fault")
TOLERANCE_BAR = 1e-9      # round-off allowed on the step and bound checks [bar]


class State(IntEnum):
    """closed_loop_state: what the loop does now."""
    OFF = 0        # not enabled (gateway.yaml or the operator): the gateway writes no set point
    ARMED = 1      # enabled; holding: at the advice, or a guard holds it (the reason says which)
    WRITING = 2    # enabled; moving the set point toward the advice, one step per interval
    SHED = 3       # the loop stopped itself (the reason says why) until the operator drops the enable


class Reason(IntEnum):
    """closed_loop_reason: why the loop is in its state (0: none)."""
    NONE = 0
    DISABLED_IN_CONFIG = 1
    OPERATOR_OFF = 2
    ENABLE_EDGE_NEEDED = 3
    ENABLE_UNREADABLE = 4
    AT_TARGET = 10
    WAITING_INTERVAL = 11
    STEPPED = 12
    NO_ADVICE = 13
    SETPOINT_UNREADABLE = 14
    OUTSIDE_BOUNDS = 15
    CLOCK_UNKNOWN = 16
    BLOCKED_DATA_STALE = 20
    BLOCKED_COMM_FAULT = 21
    BLOCKED_CALIBRATION_FAILED = 22
    BLOCKED_MODEL_INFEASIBLE = 23
    BLOCKED_ADVICE_STALE = 24
    BLOCKED_ADVICE_LOW_CONFIDENCE = 25
    BLOCKED_HEAT_PUMP_OFF = 26
    BLOCKED_CIP_DETECTED = 27
    BLOCKED_SENSOR_FAULT = 28
    BLOCKED_CLOCK_FAULT = 29
    SHED_BAD_SCANS = 30
    SHED_READBACK_MISMATCH = 31
    SHED_READBACK_FAILED = 32
    SHED_WRITE_REFUSED = 33
    SHED_WRITE_FAILED = 34
    SHED_SETPOINT_CHANGED = 35
    SHED_INTERNAL_ERROR = 36
    SHUTDOWN = 40


REASON_NOTES = {   # docs/registers.md is rendered from this table
    Reason.NONE: "-",
    Reason.DISABLED_IN_CONFIG: "gateway.yaml closed_loop.enabled is false (as shipped)",
    Reason.OPERATOR_OFF: "the operator's enable tag reads 0",
    Reason.ENABLE_EDGE_NEEDED: "the enable was already 1 when the gateway started: drop it and set "
                               "it again to arm the loop",
    Reason.ENABLE_UNREADABLE: "the enable tag cannot be read (counts as a bad scan while enabled)",
    Reason.AT_TARGET: "the PLC's set point is within deadband_bar of the recommendation",
    Reason.WAITING_INTERVAL: "moving toward the recommendation; the next step is due after "
                             "min_interval_s",
    Reason.STEPPED: "a step was written (and read back) in this scan",
    Reason.NO_ADVICE: "no recommended set point yet",
    Reason.SETPOINT_UNREADABLE: "the set-point tag cannot be read (counts as a bad scan)",
    Reason.OUTSIDE_BOUNDS: "the PLC's set point lies so far outside bounds_bar_g that no step of "
                           "max_step_bar reaches them: nothing is written",
    Reason.CLOCK_UNKNOWN: "no sample clock yet: the write interval cannot be judged",
    Reason.BLOCKED_DATA_STALE: "holding: data_stale is set (counts as a bad scan)",
    Reason.BLOCKED_COMM_FAULT: "holding: comm_fault is set (a poll failed since the last block "
                               "write; the failed poll itself counts as a bad scan)",
    Reason.BLOCKED_CALIBRATION_FAILED: "holding: calibration_failed is set",
    Reason.BLOCKED_MODEL_INFEASIBLE: "holding: model_infeasible is set",
    Reason.BLOCKED_ADVICE_STALE: "holding: advice_stale is set",
    Reason.BLOCKED_ADVICE_LOW_CONFIDENCE: "holding: advice_low_confidence is set",
    Reason.BLOCKED_HEAT_PUMP_OFF: "holding: heat_pump_off is set",
    Reason.BLOCKED_CIP_DETECTED: "holding: cip_detected is set",
    Reason.BLOCKED_SENSOR_FAULT: "holding: sensor_fault is set",
    Reason.BLOCKED_CLOCK_FAULT: "holding: clock_fault is set",
    Reason.SHED_BAD_SCANS: "shed: shed_after_bad_scans scans in a row without usable data",
    Reason.SHED_READBACK_MISMATCH: "shed: the PLC did not hold the written value (read back "
                                   "right after the write)",
    Reason.SHED_READBACK_FAILED: "shed: the set point could not be read back after the write",
    Reason.SHED_WRITE_REFUSED: "shed: the PLC refused the write with a Modbus exception (outside "
                               "its bounds, or its remote mode is not active)",
    Reason.SHED_WRITE_FAILED: "shed: the PLC did not answer the write",
    Reason.SHED_SETPOINT_CHANGED: "shed: the PLC's set point changed without the gateway (the "
                                  "operator, or the PLC's fallback)",
    Reason.SHED_INTERNAL_ERROR: "shed: an unexpected error in the closed loop (logged)",
    Reason.SHUTDOWN: "the gateway stopped (history and log only)",
}
_BLOCKED = {b: Reason[f"BLOCKED_{b.upper()}"] for b in BLOCKING_BITS}


def state_name(code: int) -> str:
    try:
        return State(code).name.lower()
    except ValueError:
        return f"unknown ({code})"


def reason_name(code: int) -> str:
    try:
        return Reason(code).name.lower()
    except ValueError:
        return f"unknown ({code})"


# ------------------------------------------------------------------------------ configuration

KEYS = ("enabled", "setpoint_tag", "enable_tag", "bounds_bar_g", "max_step_bar", "min_interval_s",
        "deadband_bar", "heartbeat_timeout_s", "shed_after_bad_scans")
REQUIRED = ("enabled", "setpoint_tag", "enable_tag", "bounds_bar_g", "max_step_bar",
            "min_interval_s", "heartbeat_timeout_s", "shed_after_bad_scans")
DEFAULT_DEADBAND_BAR = 0.05
MIN_HEARTBEAT_SCANS = 2     # the PLC's heartbeat timeout spans at least this many scans


@dataclass(frozen=True)
class ClosedLoopConfig:
    """gateway.yaml ``closed_loop``; see config/gateway.yaml for every key."""
    enabled: bool
    setpoint_tag: str
    enable_tag: str
    bounds_bar_g: tuple[float, float]
    max_step_bar: float
    min_interval_s: float
    heartbeat_timeout_s: float
    shed_after_bad_scans: int
    deadband_bar: float = DEFAULT_DEADBAND_BAR


def parse_closed_loop(sec: Any, tags: Sequence[Any], tags_file: str, scan_interval_s: float | None,
                      tag_names: set | None = None) -> ClosedLoopConfig | None:
    """Validate gateway.yaml's ``closed_loop`` section (an ``edge.yamlfile.Section``); every
    problem is recorded on ``sec``. None when invalid. ``tags``: the valid tags of ``tags_file``;
    ``tag_names``: every tag name in that file (valid or not), so a broken tag is reported once."""
    if not sec.mapping():
        return None
    n0 = sec.count()
    sec.keys(KEYS, required=REQUIRED)
    enabled = sec.boolean("enabled", default=None)
    by_name = {t.name: t for t in tags}
    names = tag_names if tag_names is not None else set(by_name)
    sp_name = sec.string("setpoint_tag", default=None)
    en_name = sec.string("enable_tag", default=None)
    # the tags matter only to a loop that may write: a disabled one touches neither (its names
    # are checked when it is enabled, and the start then fails with exit code 2)
    sp = _tag(sec, "setpoint_tag", sp_name, by_name, names, tags_file) if enabled else None
    en = _tag(sec, "enable_tag", en_name, by_name, names, tags_file) if enabled else None
    if sp is not None:
        sp = _check_setpoint_tag(sec, sp)
    if en is not None:
        _check_enable_tag(sec, en)
    if enabled and sp_name is not None and sp_name == en_name:
        sec.problem("enable_tag", f"'{en_name}' is also setpoint_tag: the enable is the operator's "
                    "(read only), the set point the gateway's")
    bounds = sec.range("bounds_bar_g")
    if "bounds_bar_g" in sec.data and bounds is not None and sp is not None:
        rng = sp.canonical_range
        if rng is not None and not (rng[0] <= bounds[0] and bounds[1] <= rng[1]):
            sec.problem("bounds_bar_g", f"[{format_number(bounds[0])}, {format_number(bounds[1])}] "
                        f"bar(g) must lie within the plausible range [{format_number(rng[0])}, "
                        f"{format_number(rng[1])}] bar(g) of tag '{sp.name}' in {tags_file}")
    step = sec.number("max_step_bar", positive=True, default=None)
    if step is not None and sp is not None:
        res = resolution_bar(sp)
        if res is not None and step < res * (1 - 1e-9):
            sec.problem("max_step_bar", f"{format_number(step)} bar is below the resolution of tag "
                        f"'{sp.name}' ({format_number(res)} bar): no step could be written")
    interval = sec.number("min_interval_s", positive=True, default=None)
    if interval is not None and scan_interval_s is not None and interval < scan_interval_s:
        sec.problem("min_interval_s", f"{format_number(interval)} s is shorter than "
                    f"scan_interval_s ({format_number(scan_interval_s)} s)")
    deadband = sec.number("deadband_bar", lo=0.0, default=DEFAULT_DEADBAND_BAR)
    timeout = sec.number("heartbeat_timeout_s", positive=True, default=None)
    if timeout is not None and scan_interval_s is not None \
            and timeout < MIN_HEARTBEAT_SCANS * scan_interval_s:
        sec.problem("heartbeat_timeout_s", f"{format_number(timeout)} s is shorter than "
                    f"{MIN_HEARTBEAT_SCANS} scan intervals ({format_number(scan_interval_s)} s "
                    "each): the PLC would fall back while the gateway runs")
    bad = sec.integer("shed_after_bad_scans", lo=1, hi=1000, default=None)
    if sec.count() != n0:
        return None
    return ClosedLoopConfig(enabled=enabled, setpoint_tag=sp_name, enable_tag=en_name,
                            bounds_bar_g=bounds, max_step_bar=step, min_interval_s=interval,
                            heartbeat_timeout_s=timeout, shed_after_bad_scans=bad,
                            deadband_bar=deadband)


def _tag(sec, key: str, name: str | None, by_name: dict, names: set, tags_file: str):
    if name is None:
        return None
    if name not in names:
        sec.problem(key, f"'{name}' is not a tag of {tags_file}")
        return None
    return by_name.get(name)     # None: the tag itself is invalid (reported with the tag)


def _check_setpoint_tag(sec, t):
    where = f"tag '{t.name}'"
    if t.register != "holding":
        kind = f"{t.register} {'bit' if t.register in BIT_SPACES else 'register'}"
        sec.problem("setpoint_tag", f"{where} is {'an' if kind[0] in 'aeiou' else 'a'} {kind}: "
                    "the set point is written with FC16 and must be a holding register")
        return None
    if t.bit is not None or t.type == BOOL:
        sec.problem("setpoint_tag", f"{where} is one bit of a register: writing it would "
                    "overwrite the other bits; the set point must be a whole register value")
        return None
    if t.canonical_unit != "bar":
        sec.problem("setpoint_tag", f"{where} has unit {t.unit!r}: the set point must be a "
                    "pressure (bar(g) after conversion)")
        return None
    if t.canonical is None:
        sec.problem("setpoint_tag", f"{where} is an absolute pressure and plant.yaml's "
                    "ambient_pressure_bar is not loaded: its value cannot be converted")
        return None
    return t


def _check_enable_tag(sec, t) -> None:
    single = t.register in BIT_SPACES or t.bit is not None
    if not single and tuple(t.range) != (0.0, 1.0):
        sec.problem("enable_tag", f"tag '{t.name}' must be a 0/1 value: a coil, a discrete input, "
                    "one bit of a register, or a register with range [0, 1]")


def resolution_bar(tag) -> float | None:
    """Smallest set-point change the tag's register can carry [bar] (None for float types)."""
    if not is_integer_type(tag.type) or tag.canonical is None:
        return None
    return abs(tag.scale * tag.canonical[0])


# ------------------------------------------------------------------------------ one step, pure


def value_of(tag, raw: float) -> float:
    """Canonical value [bar(g)] of a raw register number of the set-point tag."""
    factor, offset = tag.canonical
    return (float(raw) * tag.scale + tag.offset) * factor + offset


def raw_of(tag, value: float) -> float:
    """Raw register number (unrounded) for a canonical value [bar(g)]."""
    factor, offset = tag.canonical
    return ((value - offset) / factor - tag.offset) / tag.scale


@dataclass(frozen=True)
class Step:
    """What to write: the register words and the value the PLC will hold [bar(g)]."""
    words: tuple[int, ...]
    value: float
    old: float


def plan_step(tag, current_words: Sequence[int], target: float, max_step: float,
              bounds: tuple[float, float]) -> Step | None:
    """The one write that moves the set point from ``current_words`` toward ``target`` (already
    inside ``bounds``) by at most ``max_step`` [bar] and lands inside ``bounds`` after the register's
    quantization; the candidate nearest to the ideal step. None when no register value satisfies
    all of that (the current value lies too far outside the bounds)."""
    lo, hi = bounds
    old = value_of(tag, raw_value(list(current_words), tag.type, tag.byte_order))
    if not math.isfinite(old):
        return None
    delta = target - old
    if delta == 0:
        return None
    ideal = old + max(-max_step, min(max_step, delta))
    r = raw_of(tag, ideal)
    if is_integer_type(tag.type):
        rlo, rhi = raw_limits(tag.type)
        candidates = [int(math.floor(r)), int(math.ceil(r))]
        candidates = [c for c in candidates if rlo <= c <= rhi]
    else:
        f = np.float32(r)
        candidates = [float(f), float(np.nextafter(f, np.float32(np.inf))),
                      float(np.nextafter(f, np.float32(-np.inf)))]
    best: Step | None = None
    for c in candidates:
        try:
            words = tuple(raw_to_registers(c, tag.type, tag.byte_order))
        except ValueError:
            continue
        v = value_of(tag, raw_value(list(words), tag.type, tag.byte_order))
        if not (lo - TOLERANCE_BAR <= v <= hi + TOLERANCE_BAR):
            continue
        if abs(v - old) > max_step + TOLERANCE_BAR or (v - old) * delta <= 0:
            continue
        if best is None or abs(v - ideal) < abs(best.value - ideal):
            best = Step(words, v, old)
    return best


# ------------------------------------------------------------------------------ the state machine


@dataclass
class Status:
    """The loop's state for the advisory block, the snapshot and the health of the gateway."""
    state: State = State.OFF
    reason: Reason = Reason.DISABLED_IN_CONFIG
    detail: str = ""
    written: float = math.nan          # last value written [bar(g)]
    target: float = math.nan           # the recommendation within the bounds [bar(g)]
    last_write_t: float | None = None  # sample clock of the last write [epoch s]
    writes: int = 0                    # writes since start
    bad_scans: int = 0                 # consecutive bad scans while enabled


class ClosedLoop:
    """The state machine; ``await step(...)`` once per scan cycle, after the status bits are known
    and before the advisory block is written (so the block carries this scan's state).

    cfg : the ``closed_loop`` section (None: absent, the loop is off)
    setpoint, enable : the TagConfig of the set-point and enable tags (None when off)
    plc : the PlcClient (``write_setpoint``, ``read_setpoint``)
    audit : called with one dict per write or change of state (a worker thread; the gateway
        passes the history store's ``add_closed_loop_event``)
    """

    def __init__(self, cfg: ClosedLoopConfig | None, setpoint=None, enable=None, plc=None,
                 audit: Callable[[dict], Any] | None = None) -> None:
        self.cfg = cfg
        self.on = bool(cfg is not None and cfg.enabled)
        self.setpoint, self.enable, self.plc, self.audit = setpoint, enable, plc, audit
        self.status = Status()
        self._seen_off = False          # the enable read 0 since start (a rising edge arms)
        self._written_words: tuple[int, ...] | None = None   # what the PLC should hold now
        self._t: float | None = None    # sample clock of the scan being handled

    @classmethod
    def from_config(cls, cfg, plc, audit=None) -> ClosedLoop:
        cl = getattr(cfg, "closed_loop", None)
        if cl is None or not cl.enabled:
            return cls(cl, plc=plc, audit=audit)
        return cls(cl, cfg.tag(cl.setpoint_tag), cfg.tag(cl.enable_tag), plc, audit)

    # ------------------------------------------------------------------ advisory fields

    def values(self) -> dict[str, float]:
        s = self.status
        return {"closed_loop_state": int(s.state), "closed_loop_reason": int(s.reason),
                "closed_loop_sp_written": s.written, "closed_loop_target": s.target,
                "closed_loop_last_write": int(max(0.0, s.last_write_t or 0.0)),
                "closed_loop_writes": s.writes % 65536}

    # ------------------------------------------------------------------ transitions

    async def _set(self, state: State, reason: Reason, detail: str = "") -> None:
        s = self.status
        changed = state != s.state
        s.state, s.reason, s.detail = state, reason, detail
        if not changed:
            return
        text = f"closed loop {state.name.lower()}: {reason.name.lower()}" + (f" ({detail})" if detail else "")
        if state == State.SHED:
            log.error("%s; the gateway writes no set point until the operator drops the enable; the "
                      "PLC keeps its value and owns the fallback", text)
        else:
            log.info("%s", text)
        await self._audit({"event": "state", "state": state.name.lower(),
                           "reason": reason.name.lower(), "message": detail})

    async def _audit(self, row: dict) -> None:
        if self.audit is None:
            return
        row = {"ts": self._t if self._t is not None else time.time(), **row}
        try:
            await asyncio.to_thread(self.audit, row)
        except Exception as exc:  # noqa: BLE001 - the store reports its own faults; never stop here
            log.error("closed loop: the audit row could not be stored: %s", exc)

    async def _shed(self, reason: Reason, detail: str) -> None:
        self._written_words = None
        await self._set(State.SHED, reason, detail)

    async def shutdown(self) -> None:
        """The gateway stops: no more writes; the PLC's value stays (it owns the fallback)."""
        if self.status.state in (State.ARMED, State.WRITING):
            log.info("closed loop: gateway stopping, no more set-point writes; the PLC keeps "
                     "%s and falls back after its heartbeat timeout (%g s)",
                     _fmt(self.status.written), self.cfg.heartbeat_timeout_s)
            await self._audit({"event": "state", "state": "off", "reason": "shutdown",
                               "message": "gateway stopping"})
        self.status.state, self.status.reason = State.OFF, Reason.SHUTDOWN

    async def fault(self, exc: BaseException) -> None:
        """An unexpected error inside ``step``: shed (the gateway logs the traceback)."""
        if self.on and self.status.state in (State.ARMED, State.WRITING):
            await self._shed(Reason.SHED_INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")

    # ------------------------------------------------------------------ one scan

    async def step(self, result, bits: set[str] | frozenset[str], advice_values: Mapping[str, float] | None,
                   t_sample: float | None) -> Status:
        """Decide and, when due, write one step. ``result``: this scan's ReadResult; ``bits``:
        every status bit the gateway computed this scan (configured in the block or not);
        ``advice_values``: the current advice's values (``p_m_sp_rec``), None when there is none;
        ``t_sample``: this scan's sample clock [epoch s] (None when unknown)."""
        self._t = t_sample
        s = self.status
        if not self.on:
            s.state, s.reason = State.OFF, Reason.DISABLED_IN_CONFIG
            return s
        en = result.values.get(self.enable.name)
        sp = result.values.get(self.setpoint.name)
        if en is None or en.bad is not None:
            if s.state in (State.ARMED, State.WRITING):
                await self._bad_scan(Reason.ENABLE_UNREADABLE,
                                     f"enable tag '{self.enable.name}': "
                                     f"{en.bad if en is not None else 'not read'}")
            elif s.state == State.OFF:
                s.reason = Reason.ENABLE_UNREADABLE
            return s
        if en.value < 0.5:
            self._seen_off = True
            if s.state != State.OFF or s.reason != Reason.OPERATOR_OFF:
                self._written_words = None
                await self._set(State.OFF, Reason.OPERATOR_OFF)
            return s
        if s.state == State.SHED:
            return s
        if s.state == State.OFF:
            if not self._seen_off:
                s.reason = Reason.ENABLE_EDGE_NEEDED
                return s
            s.bad_scans = 0
            self._written_words = None
            # the first write waits for the next scan: the PLC's program sees the same edge in
            # its own scan, and a write racing it would be refused (and shed the loop)
            await self._set(State.ARMED, Reason.NONE, "operator enabled")
            return s
        # ---- armed or writing: are this scan's inputs usable?
        if result.comm_error is not None:
            return await self._bad_scan(Reason.BLOCKED_COMM_FAULT, f"poll failed: {result.comm_error}")
        if "data_stale" in bits:
            return await self._bad_scan(Reason.BLOCKED_DATA_STALE, "data_stale")
        if sp is None or sp.bad is not None or not sp.words:
            return await self._bad_scan(Reason.SETPOINT_UNREADABLE,
                                        f"set-point tag '{self.setpoint.name}': "
                                        f"{sp.bad if sp is not None else 'not read'}")
        s.bad_scans = 0
        if self._written_words is not None and tuple(sp.words) != self._written_words:
            await self._shed(Reason.SHED_SETPOINT_CHANGED,
                             f"the PLC holds {_fmt(sp.value)} bar(g), the gateway wrote "
                             f"{_fmt(s.written)}")
            return s
        for bit in BLOCKING_BITS:
            if bit in bits:
                await self._set(State.ARMED, _BLOCKED[bit])
                return s
        rec = None if advice_values is None else advice_values.get("p_m_sp_rec")
        if rec is None or not math.isfinite(rec):
            await self._set(State.ARMED, Reason.NO_ADVICE)
            return s
        lo, hi = self.cfg.bounds_bar_g
        target = min(max(float(rec), lo), hi)
        s.target = target
        if abs(target - sp.value) < self.cfg.deadband_bar:
            await self._set(State.ARMED, Reason.AT_TARGET)
            return s
        if t_sample is None:
            await self._set(State.ARMED, Reason.CLOCK_UNKNOWN)
            return s
        if s.last_write_t is not None:
            if t_sample < s.last_write_t:      # the clock went back: wait a whole interval anew
                s.last_write_t = t_sample
            if t_sample - s.last_write_t < self.cfg.min_interval_s:
                await self._set(State.WRITING, Reason.WAITING_INTERVAL)
                return s
        plan = plan_step(self.setpoint, sp.words, target, self.cfg.max_step_bar, (lo, hi))
        if plan is None:
            await self._set(State.ARMED, Reason.OUTSIDE_BOUNDS,
                            f"the PLC holds {_fmt(sp.value)} bar(g), bounds {_fmt(lo)}..{_fmt(hi)}")
            return s
        await self._write(plan, target)
        return s

    async def _bad_scan(self, reason: Reason, detail: str) -> Status:
        s = self.status
        s.bad_scans += 1
        if s.bad_scans >= self.cfg.shed_after_bad_scans:
            await self._shed(Reason.SHED_BAD_SCANS, f"{s.bad_scans} bad scans in a row, the last: "
                             f"{detail}")
        else:
            await self._set(State.ARMED, reason, detail)
        return s

    async def _write(self, plan: Step, target: float) -> None:
        from edge.plc import PlcError, PlcExceptionReply

        s = self.status
        try:
            await self.plc.write_setpoint(list(plan.words))
        except PlcExceptionReply as exc:
            await self._audit(_write_row(plan, target, "refused", str(exc)))
            await self._shed(Reason.SHED_WRITE_REFUSED, str(exc))
            return
        except PlcError as exc:
            await self._audit(_write_row(plan, target, "no answer", str(exc)))
            await self._shed(Reason.SHED_WRITE_FAILED, str(exc))
            return
        s.writes += 1
        s.written = plan.value
        s.last_write_t = self._t
        try:
            back = tuple(await self.plc.read_setpoint())
        except PlcError as exc:
            await self._audit(_write_row(plan, target, "written, read-back failed", str(exc)))
            await self._shed(Reason.SHED_READBACK_FAILED, str(exc))
            return
        if back != plan.words:
            got = value_of(self.setpoint, raw_value(list(back), self.setpoint.type,
                                                    self.setpoint.byte_order))
            msg = (f"wrote {_fmt(plan.value)} bar(g) (words {list(plan.words)}), read back "
                   f"{_fmt(got)} (words {list(back)})")
            await self._audit(_write_row(plan, target, "read-back mismatch", msg))
            await self._shed(Reason.SHED_READBACK_MISMATCH, msg)
            return
        self._written_words = plan.words
        log.info("closed loop: %s %s -> %s bar(g) (recommendation %s within bounds, step limit %g "
                 "bar)", self.setpoint.name, _fmt(plan.old), _fmt(plan.value), _fmt(target),
                 self.cfg.max_step_bar)
        await self._audit(_write_row(plan, target, "ok", "toward the recommendation"))
        await self._set(State.WRITING, Reason.STEPPED)


def _write_row(plan: Step, target: float, outcome: str, message: str) -> dict:
    return {"event": "write", "old_bar_g": plan.old, "new_bar_g": plan.value,
            "target_bar_g": target, "words": " ".join(str(w) for w in plan.words),
            "outcome": outcome, "message": message}


def _fmt(v: float | None) -> str:
    return "nan" if v is None or not math.isfinite(v) else f"{v:.2f}"
