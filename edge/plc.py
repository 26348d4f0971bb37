"""Modbus TCP client of the heat pump PLC. The only module of hp-edge that imports pymodbus.

Two failure channels are kept apart:

* the PLC answered with a Modbus exception reply (``rr.isError()``) -> ``PlcExceptionReply(code)``;
  the connection is fine;
* no usable answer at all (timeout, connection refused or lost, OSError, garbled frame)
  -> ``PlcCommError(reason)``; the connection is dropped and re-made by the next cycle, with
  exponential back-off (``reconnect_min_s`` doubling up to ``reconnect_max_s``) while it fails.

``read_all`` never raises for either: every tag comes back as a ``TagValue`` that is good or bad
with a reason. Writes raise, and go only to the advisory block: ``write_registers`` refuses any
address outside it before a byte is sent (SPEC 7.3).
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

from edge.codec import (MAX_READ_COUNT, MAX_WRITE_COUNT, ReadRequest, format_number, plan_reads,
                        raw_value)
from edge.config import AdvisoryConfig, GatewayConfig, PlcConfig, TagConfig

log = logging.getLogger(__name__)

EXCEPTION_NAMES = {
    1: "illegal function", 2: "illegal data address", 3: "illegal data value",
    4: "server device failure", 5: "acknowledge", 6: "server device busy",
    8: "memory parity error", 10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}
CYCLE_BUDGET_FRACTION = 0.8  # of the scan interval: one poll cycle never takes longer
_PYMODBUS_SLACK_S = 1.0      # pymodbus' own timeout is a backstop behind ours
_FC_READ = {"holding": 3, "input": 4}


def quiet_pymodbus_logging(level: int = logging.ERROR) -> None:
    """pymodbus logs every failed connect attempt as a warning of its own; PlcClient already
    reports the first failure loudly and repeats at debug. Commands call this once at start."""
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


@dataclass(frozen=True)
class TagValue:
    name: str
    value: float | None        # engineering value; None when bad
    bad: str | None = None     # why the value is bad: 'sentinel', 'nan', 'inf',
    #                            'out of range [lo, hi]', 'modbus exception N', 'timeout', ...
    words: tuple[int, ...] = ()  # register words as read (empty when not read)
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
        """Engineering values of the good tags."""
        return {n: v.value for n, v in self.values.items() if v.bad is None}


def _check_tag(tag: TagConfig, words: list[int]) -> TagValue:
    raw = raw_value(words, tag.type, tag.byte_order)
    mark = dict(name=tag.name, words=tuple(words), raw=raw)
    if tag.sentinel is not None and raw == tag.sentinel:
        return TagValue(value=None, bad="sentinel", **mark)
    value = float(raw) * tag.scale + tag.offset
    if math.isnan(value):
        return TagValue(value=None, bad="nan", **mark)
    if math.isinf(value):
        return TagValue(value=None, bad="inf", **mark)
    lo, hi = tag.range
    if not lo <= value <= hi:
        return TagValue(value=None, bad=f"out of range [{format_number(lo)}, {format_number(hi)}]", **mark)
    return TagValue(value=value, **mark)


class PlcClient:
    """Reads the tags of the PLC in grouped requests and writes the advisory block.

    The connection is made by ``connect()`` or lazily by ``read_all()``; after a failure the next
    attempt waits ``reconnect_min_s``, doubling up to ``reconnect_max_s``. The first failure of a
    run of failures is logged as a warning, the repeats at debug until the next success.
    """

    def __init__(
        self,
        plc: PlcConfig,
        tags: Sequence[TagConfig],
        advisory: AdvisoryConfig,
        *,
        cycle_budget_s: float,
        max_gap: int = 10,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if cycle_budget_s <= 0:
            raise ValueError(f"cycle_budget_s must be > 0, got {cycle_budget_s}")
        self.plc, self.tags, self.advisory = plc, tuple(tags), advisory
        self.cycle_budget_s = cycle_budget_s
        self._clock = clock
        self.plan: list[tuple[str, ReadRequest]] = [
            (space, req)
            for space in ("input", "holding")
            if (in_space := [t for t in self.tags if t.register == space])
            for req in plan_reads(in_space, max_gap=max_gap)
        ]
        self._per_tag: set[tuple[str, int]] = set()  # groups read tag by tag after exception 2
        self._client: AsyncModbusTcpClient | None = None
        self._lost: asyncio.Event | None = None
        self._failures = 0              # consecutive failed connect attempts
        self._next_attempt = -math.inf  # clock time before which no connect is attempted
        self._failing = False           # in a run of failures (logging policy)
        self._last_error = "not connected"

    @classmethod
    def from_config(cls, cfg: GatewayConfig, **overrides) -> PlcClient:
        """Client for ``cfg``; ``overrides`` replace PlcConfig fields (host, port, device_id...)."""
        plc = replace(cfg.plc, **overrides) if overrides else cfg.plc
        return cls(plc, cfg.tags, cfg.advisory,
                   cycle_budget_s=CYCLE_BUDGET_FRACTION * cfg.scan_interval_s)

    # ------------------------------------------------------------------ connection handling

    @property
    def connected(self) -> bool:
        return (self._client is not None and self._client.connected
                and self._lost is not None and not self._lost.is_set())

    @property
    def retry_in_s(self) -> float:
        """Seconds until the next connect attempt is allowed (0 when allowed now)."""
        return max(0.0, self._next_attempt - self._clock())

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
        try:
            ok = await asyncio.wait_for(client.connect(), timeout)
            why = "refused or unreachable"
        except asyncio.TimeoutError:
            ok, why = False, f"no answer within {timeout:g} s"
        if not ok:
            client.close()
            self._failures += 1
            delay = min(self.plc.reconnect_max_s,
                        self.plc.reconnect_min_s * 2 ** min(self._failures - 1, 30))
            self._next_attempt = self._clock() + delay
            err = PlcCommError("connect failed", f"{self.plc.host}:{self.plc.port} {why}")
            self._last_error = err.reason
            self._failed(f"{err}; next attempt in {delay:g} s")
            raise err
        self._client, self._lost = client, lost
        self._failures, self._next_attempt = 0, -math.inf
        # recovery is declared when the PLC answers, not when TCP connects (see _execute)
        (log.debug if self._failing else log.info)(
            "PLC %s:%s: connected", self.plc.host, self.plc.port)

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
        self._failed(f"{reason}: {detail}")

    def _failed(self, message: str) -> None:
        if self._failing:
            log.debug("PLC %s:%s: %s", self.plc.host, self.plc.port, message)
        else:
            log.warning("PLC %s:%s: %s (repeats are logged at debug level until it recovers)",
                        self.plc.host, self.plc.port, message)
            self._failing = True

    async def _execute(self, call: Callable[[AsyncModbusTcpClient], Awaitable],
                       timeout: float, fc: int, address: int, count: int):
        """Run one request; map every outcome to a reply, PlcExceptionReply or PlcCommError."""
        if not self.connected:
            if self._client is not None:
                self._lose("connection lost", "the PLC closed the connection")
            raise PlcCommError("not connected")
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
        if self._failing:  # any answer, an exception reply too, ends a run of failures
            log.warning("PLC %s:%s: answering again", self.plc.host, self.plc.port)
            self._failing = False
        if reply.isError():
            raise PlcExceptionReply(getattr(reply, "exception_code", 0), fc, address, count)
        return reply

    # ------------------------------------------------------------------------------ reading

    async def read_registers(self, register: str, address: int, count: int,
                             timeout: float | None = None) -> list[int]:
        """Words of one FC3 (holding) or FC4 (input) request. Raises PlcExceptionReply or
        PlcCommError."""
        if register not in _FC_READ:
            raise ValueError(f"register must be holding or input, got {register!r}")
        if not 1 <= count <= MAX_READ_COUNT:
            raise ValueError(f"count must be 1..{MAX_READ_COUNT}, got {count}")
        fc, dev = _FC_READ[register], self.plc.device_id
        if register == "holding":
            def call(c): return c.read_holding_registers(address, count=count, device_id=dev)
        else:
            def call(c): return c.read_input_registers(address, count=count, device_id=dev)
        reply = await self._execute(call, timeout or self.plc.timeout_s, fc, address, count)
        words = list(reply.registers)
        if len(words) != count:
            self._lose("protocol error", f"asked {count} registers at {address}, got {len(words)}")
            raise PlcCommError("protocol error", f"asked {count} registers, got {len(words)}")
        return words

    async def read_advisory(self, timeout: float | None = None) -> list[int]:
        """The whole advisory block (what the HMI sees), in one request."""
        return await self.read_registers(self.advisory.register, self.advisory.start,
                                         self.advisory.size, timeout)

    async def read_all(self) -> ReadResult:
        """Read every tag once, in the planned grouped requests, within the cycle budget."""
        wall, t0 = time.time(), self._clock()
        deadline = t0 + self.cycle_budget_s
        values: dict[str, TagValue] = {}
        sent = 0
        comm_error: str | None = None
        if not await self.ensure_connected(min(self.plc.timeout_s, self.cycle_budget_s)):
            comm_error = self._last_error
        queue = [] if comm_error else [(sp, r, False) for sp, r in self.plan]
        while queue:
            space, req, single = queue.pop(0)
            if not single and (space, req.start) in self._per_tag:
                queue[:0] = [(space, ReadRequest(t.address, t.count, (t,)), True) for t in req.tags]
                continue
            remaining = deadline - self._clock()
            if remaining <= 0:
                values.update((t.name, TagValue(t.name, None, "cycle budget exhausted"))
                              for t in req.tags)
                continue
            sent += 1
            try:
                words = await self.read_registers(space, req.start, req.count,
                                                  min(self.plc.timeout_s, remaining))
            except PlcExceptionReply as exc:
                if exc.code == 2 and len(req.tags) > 1 and not single:
                    log.warning("PLC: %s; reading tags %s one by one from now on",
                                exc, ", ".join(t.name for t in req.tags))
                    self._per_tag.add((space, req.start))
                    queue.insert(0, (space, req, False))
                    continue
                values.update((t.name, TagValue(t.name, None, f"modbus exception {exc.code}"))
                              for t in req.tags)
                continue
            except PlcCommError as exc:
                comm_error = exc.reason
                values.update((t.name, TagValue(t.name, None, exc.reason)) for t in req.tags)
                break
            for tag in req.tags:
                at = tag.address - req.start
                values[tag.name] = _check_tag(tag, words[at : at + tag.count])
        for tag in self.tags:  # not read: no connection, or an earlier request failed
            values.setdefault(tag.name, TagValue(tag.name, None, comm_error or "not read"))
        ordered = {t.name: values[t.name] for t in self.tags}
        return ReadResult(ordered, wall, self._clock() - t0, sent, comm_error)

    # ------------------------------------------------------------------------------ writing

    def check_write_allowed(self, address: int, count: int) -> None:
        """Raise WriteOutsideAdvisoryBlock unless [address, address+count) is inside the block."""
        adv = self.advisory
        if adv.register != "holding" or not adv.contains(address, count):
            raise WriteOutsideAdvisoryBlock(
                f"refusing to write holding registers {address}..{address + count - 1}: "
                f"writes are allowed only inside the advisory block "
                f"{adv.register} {adv.start}..{adv.end - 1}")

    async def write_registers(self, address: int, words: Sequence[int],
                              timeout: float | None = None) -> None:
        """One FC16 request. The allow-list is checked before anything is sent."""
        words = list(words)
        self.check_write_allowed(address, len(words))
        if len(words) > MAX_WRITE_COUNT:
            raise ValueError(f"one FC16 request writes at most {MAX_WRITE_COUNT} registers")
        for w in words:
            if isinstance(w, bool) or not isinstance(w, int) or not 0 <= w <= 0xFFFF:
                raise ValueError(f"register word {w!r} is not an integer 0..65535")
        dev = self.plc.device_id
        await self._execute(lambda c: c.write_registers(address, words, device_id=dev),
                            timeout or self.plc.timeout_s, 16, address, len(words))

    async def write_advisory(self, words: Sequence[int], timeout: float | None = None) -> None:
        """Write the whole advisory block (exactly ``size`` words) in ONE FC16 request."""
        if len(words) != self.advisory.size:
            raise ValueError(f"the advisory block is {self.advisory.size} words, got {len(words)}")
        await self.write_registers(self.advisory.start, words, timeout)
