"""Modbus TCP client of the heat pump PLC. The only module of hp-edge that imports pymodbus.

Two failure channels are kept apart:

* the PLC answered with a Modbus exception reply (``rr.isError()``) -> ``PlcExceptionReply(code)``;
  the connection is fine;
* no usable answer at all (timeout, connection refused or lost, OSError, a garbled frame, a reply
  to another function than the one asked, a write echo that does not match the request)
  -> ``PlcCommError(reason)``; the connection is dropped and re-made by the next cycle, with
  exponential back-off (``reconnect_min_s`` doubling up to ``reconnect_max_s``) while it fails.

``read_all`` never raises for either: every tag comes back as a ``TagValue`` that is good or bad
with a reason, its value converted to the canonical unit (degC, bar(g), m3/h, kW, ...). Reads are
grouped per (device id, register space). A group the PLC refuses with exception 2 (illegal data
address: typically a read across a register it does not map) is read tag by tag, and the grouped
read is tried again after ``REGROUP_MIN_S``, doubling up to ``REGROUP_MAX_S`` while it keeps
failing; this is logged once per group.

Writes raise, and go only to the advisory block: ``write_registers`` refuses any address outside
it, or overlapping a register the PLC owns (gateway.yaml ``reserved``, any tag), before a byte is
sent (SPEC 7.3) - so the guard holds even when tags.yaml is incomplete. The one exception is the
opt-in closed loop (SPEC 7.4, edge/closed_loop.py): when gateway.yaml enables it, the client is
built with that set-point tag, and ``write_setpoint`` writes exactly that tag's registers - it
takes no address, builds the one FC16 request itself and refuses any other length; without the
closed loop it refuses to write at all.

Logging: the first failure of a run is a WARNING; while it goes on, one summary line ("still
failing: N failures in M s") at most every ``SUMMARY_INTERVAL_S``; the recovery once. A garbled
frame is one failure, never an asyncio traceback.
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, replace

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException

from edge.codec import (BIT_SPACES, MAX_READ_BITS, MAX_READ_COUNT, MAX_WRITE_COUNT, READ_FUNCTION,
                        ReadRequest, bit_of, format_number, plan_groups, raw_value)
from edge.config import AdvisoryConfig, GatewayConfig, PlcConfig, Reserved, TagConfig

log = logging.getLogger(__name__)

EXCEPTION_NAMES = {
    1: "illegal function", 2: "illegal data address", 3: "illegal data value",
    4: "server device failure", 5: "acknowledge", 6: "server device busy",
    8: "memory parity error", 10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}
CYCLE_BUDGET_FRACTION = 0.8  # of the scan interval: one poll cycle never takes longer
_PYMODBUS_SLACK_S = 1.0      # pymodbus' own timeout is a backstop behind ours
SUMMARY_INTERVAL_S = 300.0   # at most one loud log line per failure run in this time
REGROUP_MIN_S = 60.0         # a refused grouped read is tried again after this ...
REGROUP_MAX_S = 3600.0       # ... doubling up to this while it keeps being refused


def quiet_pymodbus_logging(level: int = logging.ERROR) -> None:
    """pymodbus logs every failed connect attempt as a warning of its own; PlcClient already
    reports the first failure loudly and summarises repeats. Commands call this once at start."""
    logging.getLogger("pymodbus").setLevel(level)


class PlcError(Exception):
    """Base of the errors of this module."""


class PlcCommError(PlcError):
    """No usable answer: ``reason`` is one of 'not connected', 'connect failed', 'timeout',
    'connection lost', 'protocol error'."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}" if detail else reason)


class PlcExceptionReply(PlcError):
    """The PLC answered with Modbus exception ``code`` (e.g. 2, illegal data address)."""

    def __init__(self, code: int, function_code: int, address: int, count: int) -> None:
        self.code, self.function_code, self.address, self.count = code, function_code, address, count
        name = EXCEPTION_NAMES.get(code, "unknown")
        super().__init__(f"modbus exception {code} ({name}) to function {function_code} "
                         f"at {address}..{address + count - 1}")


class WriteOutsideAdvisoryBlock(PlcError):
    """A write to registers outside the advisory block was refused; nothing was sent."""


class SetpointWriteRefused(WriteOutsideAdvisoryBlock):
    """A set-point write was refused before anything was sent (no closed loop configured, or
    not exactly the set-point tag's registers)."""


@dataclass(frozen=True)
class TagValue:
    name: str
    value: float | None        # value in the canonical unit (degC, bar(g), m3/h, kW, ...); None when bad
    bad: str | None = None     # why the value is bad: 'sentinel', 'nan', 'inf',
    #                            'out of range [lo, hi]', 'modbus exception N', 'timeout', ...
    words: tuple[int, ...] = ()  # register words (or bits) as read (empty when not read)
    raw: int | float | None = None  # number before scale/offset (when the words were read)

    @property
    def ok(self) -> bool:
        return self.bad is None


@dataclass(frozen=True)
class ReadResult:
    values: Mapping[str, TagValue]
    timestamp: float             # wall clock (UTC epoch seconds) when the cycle started
    duration_s: float
    requests: int                # Modbus requests sent in this cycle
    comm_error: str | None = None  # set when a request got no usable answer (not for exception replies)

    def good(self) -> dict[str, float]:
        """Values of the good tags, in canonical units."""
        return {n: v.value for n, v in self.values.items() if v.bad is None}


def _check_tag(tag: TagConfig, words: list[int]) -> TagValue:
    """Decode, validate in the tag's own unit (range, sentinel, NaN), then convert to the
    canonical unit."""
    mark = dict(name=tag.name, words=tuple(words))
    if tag.register in BIT_SPACES:
        raw: int | float = int(words[0])
    elif tag.bit is not None:
        raw = bit_of(words[0], tag.bit)
    else:
        raw = raw_value(words, tag.type, tag.byte_order)
    mark["raw"] = raw
    if tag.sentinel is not None and raw == tag.sentinel:
        return TagValue(value=None, bad="sentinel", **mark)
    value = float(raw) * tag.scale + tag.offset
    if math.isnan(value):
        return TagValue(value=None, bad="nan", **mark)
    if math.isinf(value):
        return TagValue(value=None, bad="inf", **mark)
    lo, hi = tag.range
    if not lo <= value <= hi:
        return TagValue(value=None, bad=f"out of range [{format_number(lo)}, {format_number(hi)}]",
                        **mark)
    if tag.canonical is None:
        return TagValue(value=None, bad="no ambient pressure to convert an absolute pressure "
                        "(plant.yaml not loaded)", **mark)
    return TagValue(value=tag.to_canonical(value), **mark)


class FailureLog:
    """Logging policy of a run of failures: the first one loud, then at most one summary line
    per ``interval_s`` ("still failing: N failures in M s"), the recovery once. Failures that
    are not shown loudly go to debug and are counted in the next loud line."""

    def __init__(self, logger: logging.Logger, prefix: str, clock: Callable[[], float],
                 interval_s: float = SUMMARY_INTERVAL_S) -> None:
        self.log, self.prefix, self.clock, self.interval_s = logger, prefix, clock, interval_s
        self.failing = False
        self.run_start = 0.0
        self.run_failures = 0
        self.run_loud = False
        self.last_loud = -math.inf
        self.quiet = 0           # failures logged at debug since the last loud line

    def failed(self, message: str) -> None:
        now = self.clock()
        if not self.failing:
            self.failing, self.run_start, self.run_failures, self.run_loud = True, now, 0, False
        self.run_failures += 1
        if now - self.last_loud < self.interval_s:
            self.quiet += 1
            self.log.debug("%s: %s", self.prefix, message)
            return
        if self.run_failures == 1:
            extra = (f" ({self.quiet} more failure(s) in the last {now - self.last_loud:.0f} s "
                     "not shown)" if self.quiet else "")
            self.log.warning("%s: %s%s (repeats are summarised at most every %g s)",
                             self.prefix, message, extra, self.interval_s)
        else:
            self.log.warning("%s: still failing: %d failures in %.0f s; last: %s", self.prefix,
                             self.run_failures, now - self.run_start, message)
        self.last_loud, self.quiet, self.run_loud = now, 0, True

    def ok(self) -> None:
        if not self.failing:
            return
        self.failing = False
        how = (f"answering again after {self.run_failures} failure(s) in "
               f"{self.clock() - self.run_start:.0f} s")
        (self.log.warning if self.run_loud else self.log.debug)("%s: %s", self.prefix, how)


@dataclass
class _Split:
    """A group read tag by tag after exception 2, and when to try the grouped read again."""
    retry_at: float
    backoff_s: float


class PlcClient:
    """Reads the tags of the PLC in grouped requests and writes the advisory block.

    The connection is made by ``connect()`` or lazily by ``read_all()``; after a failure the next
    attempt waits ``reconnect_min_s``, doubling up to ``reconnect_max_s``.
    """

    def __init__(
        self,
        plc: PlcConfig,
        tags: Sequence[TagConfig],
        advisory: AdvisoryConfig,
        *,
        cycle_budget_s: float,
        max_gap: int | None = None,
        clock: Callable[[], float] = time.monotonic,
        reserved: Sequence[Reserved] = (),
        summary_interval_s: float = SUMMARY_INTERVAL_S,
        setpoint: TagConfig | None = None,
    ) -> None:
        if cycle_budget_s <= 0:
            raise ValueError(f"cycle_budget_s must be > 0, got {cycle_budget_s}")
        self.plc, self.tags, self.advisory = plc, tuple(tags), advisory
        self.reserved = tuple(reserved)
        if setpoint is not None and (setpoint.register != "holding" or setpoint.bit is not None
                                     or advisory.contains(setpoint.address, setpoint.count)):
            raise ValueError(f"set-point tag {setpoint.name!r} must be a whole holding register "
                             "value outside the advisory block")
        self.setpoint = setpoint    # the closed loop's one extra writable tag (None: no closed loop)
        self.cycle_budget_s = cycle_budget_s
        self._clock = clock
        gap = plc.max_read_gap if max_gap is None else max_gap
        # (device id, register space, request), devices in order, spaces input, holding, bits
        self.plan: list[tuple[int, str, ReadRequest]] = plan_groups(self.tags, plc.device_id, gap)
        self._split: dict[tuple[int, str, int], _Split] = {}
        self._client: AsyncModbusTcpClient | None = None
        self._lost: asyncio.Event | None = None
        self._malformed: str | None = None    # why the connection was dropped mid-frame
        self._failures = 0              # consecutive failed connect attempts
        self._next_attempt = -math.inf  # clock time before which no connect is attempted
        self._last_error = "not connected"
        self._connected_once = False
        self._last_request = -math.inf  # event-loop time of the last request (pauses)
        self.failures = FailureLog(log, f"PLC {plc.host}:{plc.port}", clock, summary_interval_s)

    @classmethod
    def from_config(cls, cfg: GatewayConfig, **overrides) -> PlcClient:
        """Client for ``cfg``; ``overrides`` replace PlcConfig fields (host, port, device_id...)."""
        plc = replace(cfg.plc, **overrides) if overrides else cfg.plc
        loop = getattr(cfg, "closed_loop", None)
        setpoint = cfg.tag(loop.setpoint_tag) if loop is not None and loop.enabled else None
        return cls(plc, cfg.tags, cfg.advisory, reserved=cfg.reserved,
                   cycle_budget_s=CYCLE_BUDGET_FRACTION * cfg.scan_interval_s, setpoint=setpoint)

    # ------------------------------------------------------------------ connection handling

    @property
    def connected(self) -> bool:
        return (self._client is not None and self._client.connected
                and self._lost is not None and not self._lost.is_set())

    @property
    def retry_in_s(self) -> float:
        """Seconds until the next connect attempt is allowed (0 when allowed now)."""
        return max(0.0, self._next_attempt - self._clock())

    @property
    def split_groups(self) -> list[tuple[int, str, int]]:
        """(device, space, start) of the groups currently read tag by tag."""
        return sorted(self._split)

    async def connect(self, timeout: float | None = None) -> None:
        """One connect attempt now. Raises PlcCommError('connect failed') and schedules the
        next attempt with back-off."""
        self._drop()
        timeout = self.plc.timeout_s if timeout is None else timeout
        lost = asyncio.Event()
        client = AsyncModbusTcpClient(
            self.plc.host, port=self.plc.port, name="hp-edge-plc",
            timeout=self.plc.timeout_s + _PYMODBUS_SLACK_S, retries=0,
            reconnect_delay=0,  # reconnecting is ours (back-off, logging)
            trace_connect=lambda up: None if up else lost.set(),
        )
        self._guard_frames(client, lost)
        try:
            ok = await asyncio.wait_for(client.connect(), timeout)
            why = "refused or unreachable"
        except asyncio.TimeoutError:
            ok, why = False, f"no answer within {timeout:g} s"
        except (OSError, ModbusException) as exc:
            ok, why = False, str(exc) or type(exc).__name__
        if not ok:
            client.close()
            self._failures += 1
            delay = min(self.plc.reconnect_max_s,
                        self.plc.reconnect_min_s * 2 ** min(self._failures - 1, 30))
            self._next_attempt = self._clock() + delay
            err = PlcCommError("connect failed", f"{self.plc.host}:{self.plc.port} {why}")
            self._last_error = err.reason
            self.failures.failed(f"{err}; next attempt in {delay:g} s")
            raise err
        self._client, self._lost, self._malformed = client, lost, None
        self._failures, self._next_attempt = 0, -math.inf
        # recovery is declared when the PLC answers, not when TCP connects
        (log.debug if self._connected_once or self.failures.failing else log.info)(
            "PLC %s:%s: connected", self.plc.host, self.plc.port)
        self._connected_once = True

    def _guard_frames(self, client: AsyncModbusTcpClient, lost: asyncio.Event) -> None:
        """A frame pymodbus cannot decode raises inside the transport's data_received, which
        asyncio reports with a traceback and a closed transport. Catch it here instead: drop the
        connection, remember why; the waiting request ends as a protocol error."""
        ctx = getattr(client, "ctx", None)
        original = getattr(ctx, "callback_data", None)
        if original is None:   # pragma: no cover - pymodbus layout changed (pinned <3.17)
            return

        def guarded(data: bytes, addr=None) -> int:
            try:
                return original(data, addr)
            except Exception as exc:  # noqa: BLE001 - any decoder failure is a garbled frame
                self._malformed = f"malformed reply ({exc})"
                lost.set()
                transport = getattr(ctx, "transport", None)
                if transport is not None:
                    transport.close()
                return len(data)

        ctx.callback_data = guarded

    async def ensure_connected(self, timeout: float | None = None) -> bool:
        """True when connected, connecting first if the back-off allows it."""
        if self.connected:
            return True
        if self._client is not None:
            self._lose("connection lost", "the PLC closed the connection")
        if self._clock() < self._next_attempt:
            return False
        try:
            await self.connect(timeout)
        except PlcCommError:
            return False
        return True

    async def close(self) -> None:
        self._drop()

    async def __aenter__(self) -> PlcClient:
        return self

    async def __aexit__(self, *exc_info) -> None:
        await self.close()

    def _drop(self) -> None:
        if self._client is not None:
            self._client.close()
        self._client = self._lost = None

    def _lose(self, reason: str, detail: str) -> None:
        """A working connection failed: drop it; the next cycle reconnects at once."""
        self._drop()
        self._last_error = reason
        self._next_attempt = -math.inf
        self.failures.failed(f"{reason}: {detail}")

    async def _pause(self) -> None:
        pause = self.plc.pause_between_requests_s
        if pause > 0:
            loop = asyncio.get_running_loop()
            wait = self._last_request + pause - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)

    async def _fc16(self, dev: int, address: int, words: list[int], timeout: float | None) -> None:
        """One FC16 request and the check of its echo (the advisory block and the set point)."""
        reply = await self._execute(lambda c: c.write_registers(address, words, device_id=dev),
                                    timeout or self.plc.timeout_s, 16, address, len(words))
        echo = (getattr(reply, "address", None), getattr(reply, "count", None))
        if echo != (address, len(words)):
            detail = (f"function 16 at {address}..{address + len(words) - 1}: the reply confirms "
                      f"{echo[1]} registers at {echo[0]}")
            self._lose("protocol error", detail)
            raise PlcCommError("protocol error", detail)
        self.failures.ok()

    async def _execute(self, call: Callable[[AsyncModbusTcpClient], Awaitable],
                       timeout: float, fc: int, address: int, count: int):
        """Run one request; map every outcome to a reply of function ``fc``, PlcExceptionReply
        or PlcCommError."""
        if not self.connected:
            if self._client is not None:
                self._lose("connection lost", "the PLC closed the connection")
            raise PlcCommError("not connected")
        await self._pause()
        self._last_request = asyncio.get_running_loop().time()
        request = asyncio.ensure_future(call(self._client))
        lost = asyncio.ensure_future(self._lost.wait())
        try:
            done, _ = await asyncio.wait({request, lost}, timeout=timeout,
                                         return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (request, lost):
                task.cancel()
            await asyncio.gather(request, lost, return_exceptions=True)
        where = f"function {fc} at {address}..{address + count - 1}"
        if request not in done:
            if lost in done and self._malformed:
                detail = f"{where}: {self._malformed}"
                self._lose("protocol error", detail)
                raise PlcCommError("protocol error", detail)
            reason = "connection lost" if lost in done else "timeout"
            detail = f"{where}: no reply within {timeout:.3g} s" if reason == "timeout" else where
            self._lose(reason, detail)
            raise PlcCommError(reason, detail)
        try:
            reply = request.result()
        except (ConnectionException, OSError) as exc:
            self._lose("connection lost", f"{where}: {exc}")
            raise PlcCommError("connection lost", f"{where}: {exc}") from exc
        except (ModbusException, asyncio.TimeoutError) as exc:
            self._lose("protocol error", f"{where}: {exc}")
            raise PlcCommError("protocol error", f"{where}: {exc}") from exc
        got = getattr(reply, "function_code", None)
        if reply.isError():
            if got != fc | 0x80:
                detail = f"{where}: exception reply for function {_fc(got, 0x7F)}"
                self._lose("protocol error", detail)
                raise PlcCommError("protocol error", detail)
            raise PlcExceptionReply(getattr(reply, "exception_code", 0), fc, address, count)
        if got != fc:
            detail = f"{where}: the reply is for function {_fc(got)}, not {fc}"
            self._lose("protocol error", detail)
            raise PlcCommError("protocol error", detail)
        return reply

    # ------------------------------------------------------------------------------ reading

    async def read_registers(self, register: str, address: int, count: int,
                             timeout: float | None = None, device_id: int | None = None) -> list[int]:
        """Words of one FC3 (holding) or FC4 (input) request, or the bits (0/1) of one FC1
        (coil) or FC2 (discrete_input) request. Raises PlcExceptionReply or PlcCommError."""
        if register not in READ_FUNCTION:
            raise ValueError(f"register must be one of {', '.join(READ_FUNCTION)}, got {register!r}")
        limit = MAX_READ_BITS if register in BIT_SPACES else MAX_READ_COUNT
        if not 1 <= count <= limit:
            raise ValueError(f"count must be 1..{limit}, got {count}")
        fc = READ_FUNCTION[register]
        dev = self.plc.device_id if device_id is None else device_id
        method = {1: "read_coils", 2: "read_discrete_inputs", 3: "read_holding_registers",
                  4: "read_input_registers"}[fc]

        def call(c):
            return getattr(c, method)(address, count=count, device_id=dev)

        reply = await self._execute(call, timeout or self.plc.timeout_s, fc, address, count)
        if register in BIT_SPACES:
            bits = list(getattr(reply, "bits", None) or [])
            if not count <= len(bits) < count + 8:
                detail = f"asked {count} bits at {address}, got {len(bits)}"
                self._lose("protocol error", detail)
                raise PlcCommError("protocol error", detail)
            return [int(bool(b)) for b in bits[:count]]
        words = list(reply.registers)
        if len(words) != count:
            self._lose("protocol error", f"asked {count} registers at {address}, got {len(words)}")
            raise PlcCommError("protocol error", f"asked {count} registers, got {len(words)}")
        return words

    async def read_advisory(self, timeout: float | None = None) -> list[int]:
        """The whole advisory block (what the HMI sees), in one request."""
        return await self.read_registers(self.advisory.register, self.advisory.start,
                                         self.advisory.size, timeout)

    def _per_tag(self, req: ReadRequest) -> list[ReadRequest]:
        """The requests of a group read one by one (bits of one register share a request)."""
        out: dict[tuple[int, int], list] = {}
        for t in req.tags:
            out.setdefault((t.address, t.count), []).append(t)
        return [ReadRequest(a, n, tuple(ts)) for (a, n), ts in out.items()]

    async def read_all(self) -> ReadResult:
        """Read every tag once, in the planned grouped requests, within the cycle budget."""
        wall, t0 = time.time(), self._clock()
        deadline = t0 + self.cycle_budget_s
        values: dict[str, TagValue] = {}
        sent = 0
        comm_error: str | None = None
        if self.plc.close_after_poll and self._client is not None:
            self._drop()        # one connection per poll (single-master gateways)
        if not await self.ensure_connected(min(self.plc.timeout_s, self.cycle_budget_s)):
            comm_error = self._last_error
        queue = [] if comm_error else [(dev, sp, r, False) for dev, sp, r in self.plan]
        while queue:
            dev, space, req, single = queue.pop(0)
            key = (dev, space, req.start)
            split = self._split.get(key)
            if not single and split is not None and self._clock() < split.retry_at:
                queue[:0] = [(dev, space, r, True) for r in self._per_tag(req)]
                continue
            remaining = deadline - self._clock()
            if remaining <= 0:
                values.update((t.name, TagValue(t.name, None, "cycle budget exhausted"))
                              for t in req.tags)
                continue
            sent += 1
            try:
                words = await self.read_registers(space, req.start, req.count,
                                                  min(self.plc.timeout_s, remaining), dev)
            except PlcExceptionReply as exc:
                if exc.code == 2 and not single and len(self._per_tag(req)) > 1:
                    self._refused_group(key, req, exc, split)
                    queue[:0] = [(dev, space, r, True) for r in self._per_tag(req)]
                    continue
                values.update((t.name, TagValue(t.name, None, f"modbus exception {exc.code}"))
                              for t in req.tags)
                continue
            except PlcCommError as exc:
                comm_error = exc.reason
                values.update((t.name, TagValue(t.name, None, exc.reason)) for t in req.tags)
                break
            if split is not None and not single:
                del self._split[key]
                log.info("PLC: the grouped read of %s %s..%s (device %s) is accepted again",
                         space, req.start, req.start + req.count - 1, dev)
            for tag in req.tags:
                at = tag.address - req.start
                values[tag.name] = _check_tag(tag, words[at : at + tag.count])
        for tag in self.tags:  # not read: no connection, or an earlier request failed
            values.setdefault(tag.name, TagValue(tag.name, None, comm_error or "not read"))
        if comm_error is None:
            self.failures.ok()
        ordered = {t.name: values[t.name] for t in self.tags}
        return ReadResult(ordered, wall, self._clock() - t0, sent, comm_error)

    def _refused_group(self, key, req: ReadRequest, exc: PlcExceptionReply,
                       split: _Split | None) -> None:
        now = self._clock()
        if split is None:
            self._split[key] = _Split(now + REGROUP_MIN_S, REGROUP_MIN_S)
            log.warning("PLC: %s; reading tags %s one by one; the grouped read is tried again "
                        "in %g s (then less often, at most every %g s)", exc,
                        ", ".join(t.name for t in req.tags), REGROUP_MIN_S, REGROUP_MAX_S)
        else:
            split.backoff_s = min(2 * split.backoff_s, REGROUP_MAX_S)
            split.retry_at = now + split.backoff_s
            log.debug("PLC: %s again; next grouped attempt in %g s", exc, split.backoff_s)

    # ------------------------------------------------------------------------------ writing

    def check_write_allowed(self, address: int, count: int) -> None:
        """Raise WriteOutsideAdvisoryBlock unless [address, address+count) is inside the
        advisory block and touches no register the PLC owns (``reserved``, any holding tag)."""
        adv = self.advisory
        what = f"refusing to write holding registers {address}..{address + count - 1}"
        if adv.register != "holding" or not adv.contains(address, count):
            raise WriteOutsideAdvisoryBlock(
                f"{what}: writes are allowed only inside the advisory block "
                f"{adv.register} {adv.start}..{adv.end - 1}")
        for r in self.reserved:
            if r.overlaps("holding", address, count):
                raise WriteOutsideAdvisoryBlock(
                    f"{what}: they overlap reserved holding {r.first}..{r.last} (PLC-owned)")
        for t in self.tags:
            if t.register == "holding" and t.address < address + count and address < t.end:
                raise WriteOutsideAdvisoryBlock(
                    f"{what}: they overlap tag '{t.name}' (holding {t.address}..{t.end - 1}, "
                    "PLC-owned)")

    async def write_registers(self, address: int, words: Sequence[int],
                              timeout: float | None = None) -> None:
        """One FC16 request. The allow-list is checked before anything is sent; the reply must
        echo the address and count."""
        words = list(words)
        self.check_write_allowed(address, len(words))
        if len(words) > MAX_WRITE_COUNT:
            raise ValueError(f"one FC16 request writes at most {MAX_WRITE_COUNT} registers")
        for w in words:
            if isinstance(w, bool) or not isinstance(w, int) or not 0 <= w <= 0xFFFF:
                raise ValueError(f"register word {w!r} is not an integer 0..65535")
        dev = self.plc.device_id
        await self._fc16(dev, address, words, timeout)

    async def write_advisory(self, words: Sequence[int], timeout: float | None = None) -> None:
        """Write the whole advisory block (exactly ``size`` words) in ONE FC16 request; with
        ``close_after_poll`` the connection is closed afterwards (one connection per cycle)."""
        if len(words) != self.advisory.size:
            raise ValueError(f"the advisory block is {self.advisory.size} words, got {len(words)}")
        try:
            await self.write_registers(self.advisory.start, words, timeout)
        finally:
            if self.plc.close_after_poll:
                self._drop()


    # ------------------------------------------------------------ the closed loop's set point

    async def write_setpoint(self, words: Sequence[int], timeout: float | None = None) -> None:
        """Write the closed loop's set-point tag: ONE FC16 request to exactly that tag's registers
        (address, count and device from the tag map; the caller gives only the words). Refused
        before anything is sent when gateway.yaml does not enable the closed loop, or when
        ``words`` is not exactly the tag's register count. The reply must echo address and count."""
        tag = self.setpoint
        words = list(words)
        if tag is None:
            raise SetpointWriteRefused(
                "refusing to write a set point: the closed loop is not enabled in gateway.yaml "
                "(closed_loop.enabled); the gateway writes only the advisory block")
        what = f"set-point tag '{tag.name}' (holding {tag.address}..{tag.end - 1})"
        if len(words) != tag.count:
            raise SetpointWriteRefused(f"refusing to write {len(words)} register(s) to {what}: "
                                       f"it has exactly {tag.count}")
        for w in words:
            if isinstance(w, bool) or not isinstance(w, int) or not 0 <= w <= 0xFFFF:
                raise ValueError(f"register word {w!r} is not an integer 0..65535")
        if tag.register != "holding" or self.advisory.contains(tag.address, tag.count):
            raise SetpointWriteRefused(f"refusing to write {what}: not a holding register "
                                       "outside the advisory block")
        dev = self.plc.device_id if tag.device_id is None else tag.device_id
        address = tag.address
        await self._fc16(dev, address, words, timeout)

    async def read_setpoint(self, timeout: float | None = None) -> list[int]:
        """The set-point tag's registers as the PLC holds them now (one FC3 request)."""
        tag = self.setpoint
        if tag is None:
            raise SetpointWriteRefused("no set-point tag: the closed loop is not enabled")
        dev = self.plc.device_id if tag.device_id is None else tag.device_id
        return await self.read_registers("holding", tag.address, tag.count, timeout, dev)


def _fc(code, mask: int = 0xFF) -> str:
    return str(code & mask) if isinstance(code, int) else repr(code)
