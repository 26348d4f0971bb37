"""The simulated PLC: a pymodbus 3.16 Modbus TCP server in front of the simulated plant.

Register memory is a pymodbus ``SimDevice`` (separate coil / discrete / holding / input blocks):
  input 0..       every plant tag of tags.yaml at its address (gaps stay undefined -> exception 2)
  holding 100..   PLC clock (plant time, uint32 epoch s), life counter; 110 p_m,sp (writable);
                  111 the operator's closed-loop enable (written by the HMI / ``set_operator_enable``)
  holding 1000..  the advisory block of gateway.yaml (writable, readable)
  holding cip.request_register (only when configured, cip.mode on_request): write non-zero to ask
                  for a CIP; reads 1 while a request is pending or the CIP runs, else 0
The set-point register follows the plant when the PLC's own schedule (control.p_m_sp_schedule)
steps it; a client write is applied from the next plant step and holds until the next step.
A client write anywhere but those registers and the advisory block gets exception 2 (ILLEGAL DATA
ADDRESS) and changes nothing: undefined addresses by SimDevice itself, defined read-only registers
by the SimDevice action hook.

With ``remote_setpoint.enabled`` (config/simulator.yaml, as shipped) the PLC runs the program of
docs/closed_loop.md for a remote (supervisory) set point (simulator/remote.py): a set-point write
is taken only in remote mode (else exception 4) and inside its bounds (else exception 3); remote
mode starts on a rising edge of the enable register while the advisory heartbeat is alive, and
ends - the set point reverting to the operator's local one (the schedule's) - when the enable
drops or the heartbeat word has not changed for ``heartbeat_timeout_s`` of wall time (latched
until the enable drops). The program scans every ``PLC_SCAN_S``; ``plc_events`` lists every change
of mode, ``setpoint_log`` every set-point write with the value it replaced. The plant task pushes values with ``server.async_setValues`` using
read function codes (3 / 4), which never carry values on the wire, so the hook can tell the two
apart. Every write request received is recorded in ``write_log`` (accepted or not).

Slow responses, dropped connections and every write's outcome need the request and its response
together, which SimDevice's hook does not see; the server therefore uses a small subclass of
pymodbus's ServerRequestHandler (pymodbus is pinned <3.17).

Usage (tests, demo)::

    sim = PlantSimulator(port=0, speed=600)
    await sim.start()            # listening on 127.0.0.1, plant stepping
    sim.port                     # the bound port
    sim.faults.enable("stuck", tag="T_e"); sim.faults.disable("stuck", tag="T_e")
    await sim.wait_ticks(2)      # synchronise on register updates, not sleeps (while the frozen
                                 # fault is on nothing is pushed: use wait_plant_time(t) instead)
    sim.truth                    # latest hidden truth; sim.writes_rejected(); sim.write_log
    await sim.stop()
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from .config import SimulatorConfig, load_simulator_config, read_advisory, read_tags
from .faults import Faults
from .plant import Plant
from .registers import SETPOINT_TAG, encode, encode_run, quantize, register_runs, writable_ranges
from .remote import RemoteSetpoint

log = logging.getLogger("hp_edge.simulator")

WRITE_FCS = (5, 6, 15, 16, 22, 23)
INTERNAL_FC = {"input": 4, "holding": 3}     # plant pushes: read FCs never carry values on the wire
UNUSED_BITS_ADDRESS = 65520                  # SimDevice needs coil/discrete blocks; park them here
MAX_LOOP_HZ = 20.0                           # register pushes per wall second at most
MAX_PERIOD_S = 0.5                           # ... and at least one push per this (life counter)
PLC_SCAN_S = 0.02                            # the remote-set-point program's scan (wall seconds)


@dataclass(frozen=True)
class WriteRecord:
    """One write request as received and answered."""
    wall_time: float
    plant_time: float
    function_code: int
    address: int
    count: int
    values: tuple
    accepted: bool
    exception_code: int | None


@dataclass
class _Stats:
    requests: int = 0
    dropped: int = 0
    delayed: int = 0
    pushes: int = 0
    catchups: int = 0            # the plant fell behind wall time and was re-anchored
    restarts: int = 0
    fc: dict = field(default_factory=dict)


class _Handler(ServerRequestHandler):
    """pymodbus's request handler with fault hooks and the write log (same reply logic)."""

    async def handle_request(self):
        pdu, addr = self.last_pdu, self.last_addr
        if not pdu:
            return
        sim: PlantSimulator = self.server.sim
        sim.stats.requests += 1
        delay = sim.faults.response_delay()
        if delay > 0:
            sim.stats.delayed += 1
            await asyncio.sleep(delay)
        if sim.faults.should_drop() or not self.transport:
            sim.stats.dropped += 1
            sim._record(pdu, None)
            self.close()
            return
        try:
            response = await pdu.datastore_update(self.server.context, pdu.dev_id)
        except NoSuchIdException:
            response = ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            log.error("request fc=%s could not be served: %s", pdu.function_code, exc)
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        sim._record(pdu, response)
        response.transaction_id = pdu.transaction_id
        response.dev_id = pdu.dev_id
        if self.transport:
            self.server_send(response, addr)


class _Server(ModbusTcpServer):
    def __init__(self, sim: "PlantSimulator", context, address: tuple[str, int]):
        super().__init__(context, address=address)
        self.sim = sim

    def callback_new_connection(self):
        return _Handler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class PlantSimulator:
    """The simulator as an in-process object: ``await start()`` ... ``await stop()``.

    cfg: SimulatorConfig (default config/simulator.yaml); seed overrides cfg.seed.
    speed: plant seconds per wall second (1..3600 for the CLI; any positive value here).
    truth_log: path of a JSONL file that gets one hidden-truth record per truth interval.
    """

    def __init__(self, cfg: SimulatorConfig | None = None, *, host: str = "127.0.0.1",
                 port: int = 5020, speed: float = 60.0, seed: int | None = None,
                 truth_log: str | Path | None = None, plant: Plant | None = None):
        cfg = cfg or load_simulator_config()
        if seed is not None:
            cfg = cfg.replace(seed=seed)
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.cfg = cfg
        self.host, self._port_req, self.speed = host, port, float(speed)
        self.tags = read_tags(cfg.tags_file)
        self.advisory = read_advisory(cfg.gateway_file)
        self.runs = register_runs(self.tags)
        self.cip_register = cfg.cip.request_register if cfg.cip.mode == "on_request" else None
        extra = [] if self.cip_register is None else [(self.cip_register, self.cip_register + 1)]
        self.enable_spec = self.tags.get(cfg.remote_setpoint.enable_tag)
        if self.enable_spec is not None and self.enable_spec.register == "holding":
            extra.append((self.enable_spec.address, self.enable_spec.address + self.enable_spec.count))
        self.writable = writable_ranges(self.tags, self.advisory, extra)
        self._check_layout()
        # tags the clients own (the plant never pushes them): the set point and the enable
        self.client_tags = {SETPOINT_TAG, cfg.remote_setpoint.enable_tag}
        self.program = self._remote_program()
        self.plc_events: list[dict] = []         # changes of the program's mode
        self.setpoint_log: list[dict] = []       # every set-point write: old, new, accepted
        self.plant = plant or Plant(cfg)
        self.faults = Faults(self.tags, seed=cfg.seed)
        self.faults.listeners.append(self._on_fault)
        self.truth_log_path = Path(truth_log) if truth_log else None
        self.truth: dict = {}
        self.truth_history: list[dict] = []
        self.truth_history_max = 100_000
        self.write_log: list[WriteRecord] = []
        self.stats = _Stats()
        self.served: dict[str, float] = {}       # engineering values last pushed
        self.life_counter = 0
        self.clock = self.plant.t                # PLC clock: plant time, continuous between ticks
        self.port: int | None = None
        self._server: _Server | None = None
        self._context = None
        self._task: asyncio.Task | None = None
        self._executor: ThreadPoolExecutor | None = None
        self._truth_fh = None
        self._update: asyncio.Condition | None = None     # created in start (needs a loop)
        self._pushes = 0
        self._stopping = False
        self._restart_task: asyncio.Task | None = None
        self._down: asyncio.Event | None = None
        self._sp_last: float | None = None
        self._sp_steps_seen = 0
        self._cip_reg_last = 0
        self._listening: asyncio.Event | None = None
        self._plc_task: asyncio.Task | None = None
        self._schedule = [(f, False) for f in cfg.faults]
        self._errors: list[BaseException] = []

    # --------------------------------------------------------------------------- layout ----
    def _check_layout(self) -> None:
        adv = self.advisory
        for run in self.runs:
            if run.register == "holding" and run.start < adv.start + adv.size and adv.start < run.start + run.count:
                raise ValueError(f"{self.cfg.tags_file}: tags at holding {run.start}..{run.start + run.count - 1} "
                                 f"overlap the advisory block of {self.cfg.gateway_file}")
        reg = self.cip_register
        if reg is not None:
            where = f"{self.cfg.path or '<simulator config>'}: cip: key 'request_register'"
            if adv.contains(reg, 1):
                raise ValueError(f"{where}: holding {reg} is inside the advisory block of {self.cfg.gateway_file}")
            for run in self.runs:
                if run.register == "holding" and run.start <= reg < run.start + run.count:
                    raise ValueError(f"{where}: holding {reg} is already a tag of {self.cfg.tags_file}")

    def _remote_program(self) -> RemoteSetpoint | None:
        rs = self.cfg.remote_setpoint
        if not rs.enabled:
            return None
        where = f"{self.cfg.path or '<simulator config>'}: remote_setpoint"
        sp, en = self.tags.get(SETPOINT_TAG), self.enable_spec
        if sp is None or sp.register != "holding":
            raise ValueError(f"{where}: needs the set-point tag '{SETPOINT_TAG}' as a holding register "
                             f"in {self.cfg.tags_file}")
        if en is None or en.register != "holding" or en.count != 1:
            raise ValueError(f"{where}: key 'enable_tag': '{rs.enable_tag}' must be a 16-bit holding "
                             f"register of {self.cfg.tags_file}")
        if self.advisory.heartbeat_address is None:
            raise ValueError(f"{where}: the advisory block of {self.cfg.gateway_file} has no heartbeat "
                             "field for the watchdog")
        return RemoteSetpoint(rs.bounds_bar_g, rs.heartbeat_timeout_s)

    def _device(self) -> SimDevice:
        holding = [SimData(r.start, count=r.count, values=0, datatype=DataType.REGISTERS)
                   for r in self.runs if r.register == "holding"]
        holding.append(SimData(self.advisory.start, count=self.advisory.size, values=0,
                               datatype=DataType.REGISTERS))
        if self.cip_register is not None:
            holding.append(SimData(self.cip_register, count=1, values=0, datatype=DataType.REGISTERS))
        inputs = [SimData(r.start, count=r.count, values=0, datatype=DataType.REGISTERS)
                  for r in self.runs if r.register == "input"]
        if not inputs:   # SimDevice needs every block non-empty
            inputs = [SimData(UNUSED_BITS_ADDRESS, values=0, datatype=DataType.REGISTERS)]
        bits = [SimData(UNUSED_BITS_ADDRESS, count=1, values=0, datatype=DataType.BITS)]
        return SimDevice(id=self.cfg.device_id,
                         simdata=(bits, [SimData(UNUSED_BITS_ADDRESS, values=0, datatype=DataType.BITS)],
                                  holding, inputs),
                         action=self._action)

    def is_writable(self, address: int, count: int) -> bool:
        return any(lo <= address and address + count <= hi for lo, hi in self.writable)

    async def _action(self, function_code, start_address, address, count, registers, set_values):
        """SimDevice hook: reads pass; client writes only into the set point / advisory block
        (and the enable / CIP request registers); the remote-set-point program judges set-point
        writes and watches the heartbeat."""
        if set_values is None or function_code in (3, 4):
            return None
        if not (function_code in (6, 16, 22, 23) and self.is_writable(address, count)):
            return ExcCodes.ILLEGAL_ADDRESS
        sp = self.tags.get(SETPOINT_TAG)
        if sp is not None and address < sp.address + sp.count and sp.address < address + count:
            code = self._setpoint_write(function_code, start_address, address, count, registers,
                                        set_values, sp)
            if code is not None:
                return code
        hb = self.advisory.heartbeat_address
        if (self.program is not None and hb is not None and address <= hb < address + count
                and function_code in (6, 16, 23) and not self.faults.frozen):
            self.program.heartbeat(int(set_values[hb - address]), time.monotonic())
        return None

    def _setpoint_write(self, fc, start_address, address, count, registers, set_values, sp):
        """The program's check of a client write to the set point; logs it in ``setpoint_log``."""
        def value(words):
            raw = ModbusClientMixin.convert_from_registers(
                list(words), getattr(ModbusClientMixin.DATATYPE, sp.type.upper()),
                word_order="little" if sp.byte_order in ("CDAB", "DCBA") else "big")
            return raw * sp.scale + sp.offset
        code = None
        if fc not in (6, 16, 23) or address > sp.address or address + count < sp.address + sp.count:
            new = math.nan        # a mask write, or part of a two-register value
            code = ExcCodes.ILLEGAL_VALUE if self.program is not None else None
        else:
            new = value(set_values[sp.address - address: sp.address - address + sp.count])
            if self.program is not None:
                c = self.program.check_write(new)
                code = None if c is None else ExcCodes(c)
        old = value(registers[sp.address - start_address: sp.address - start_address + sp.count])
        self.setpoint_log.append({"wall": time.time(), "mono": time.monotonic(), "plant_t": self.plant.t,
                                  "old": old, "new": new, "accepted": code is None,
                                  "exception": None if code is None else int(code),
                                  "remote": None if self.program is None else self.program.remote})
        return code

    def _record(self, pdu, response) -> None:
        """Count the request; log writes (response None: dropped unanswered)."""
        fc = pdu.function_code
        self.stats.fc[fc] = self.stats.fc.get(fc, 0) + 1
        if fc not in WRITE_FCS:
            return
        if fc == 23:
            address, values = pdu.write_address, tuple(pdu.write_registers)
        elif fc == 22:
            address, values = pdu.address, (pdu.and_mask, pdu.or_mask)
        elif fc in (5, 15):
            address, values = pdu.address, tuple(bool(b) for b in pdu.bits)
        else:
            address, values = pdu.address, tuple(pdu.registers)
        count = 1 if fc == 22 else len(values)
        accepted = response is not None and not isinstance(response, ExceptionResponse)
        exc = int(response.exception_code) if isinstance(response, ExceptionResponse) else None
        self.write_log.append(WriteRecord(time.time(), self.plant.t, fc, address, count, values,
                                          accepted, exc))

    def writes_rejected(self) -> list[WriteRecord]:
        return [w for w in self.write_log if not w.accepted]

    def writes_outside(self, start: int, size: int) -> list[WriteRecord]:
        """Write requests (accepted or not) that touched anything outside [start, start+size)."""
        return [w for w in self.write_log
                if not (start <= w.address and w.address + w.count <= start + size)]

    # ----------------------------------------------------------------------- lifecycle ----
    async def start(self) -> None:
        """Listen, push the first register image and start stepping the plant."""
        self._update = asyncio.Condition()
        self._down = asyncio.Event()
        self._listening = asyncio.Event()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hp-sim-plant")
        if self.truth_log_path:
            self.truth_log_path.parent.mkdir(parents=True, exist_ok=True)
            self._truth_fh = open(self.truth_log_path, "a", encoding="utf-8")
        await self._listen(self._port_req)
        await self._push()
        self._stopping = False
        self._task = asyncio.create_task(self._run(), name="hp-sim-plant-loop")
        if self.program is not None:
            self._plc_task = asyncio.create_task(self._plc_loop(), name="hp-sim-plc-program")

    async def _listen(self, port: int) -> None:
        server = _Server(self, self._device(), (self.host, port))
        if self._context is not None:
            server.context = self._context     # a restart keeps the PLC's register memory
        self._context = server.context
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:
            raise RuntimeError(f"simulator could not listen on {self.host}:{port} "
                               f"(address in use or not local?): {exc}") from None
        sockets = getattr(server.transport, "sockets", None) or []
        if not sockets:
            raise RuntimeError(f"simulator could not listen on {self.host}:{port}")
        self.port = sockets[0].getsockname()[1]
        self._server = server
        self._listening.set()
        log.info("simulator listening on %s:%s", self.host, self.port)

    async def stop(self) -> None:
        self._stopping = True
        for task in (self._task, self._restart_task, self._plc_task):
            if task is not None and not task.done():
                task.cancel()
                try:
                    await task
                except asyncio.CancelledError:
                    pass
        if self._server is not None:
            await self._server.shutdown()
            self._server = None
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None
        if self._truth_fh is not None:
            self._truth_fh.close()
            self._truth_fh = None
        async with self._update:
            self._update.notify_all()

    async def __aenter__(self) -> "PlantSimulator":
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.stop()

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    @property
    def is_listening(self) -> bool:
        return self._server is not None

    async def drop_connections(self) -> int:
        """Close every open client connection now (the listener stays); returns how many."""
        if self._server is None:
            return 0
        conns = list(self._server.active_connections.values())
        for c in conns:
            c.close()
        self.stats.dropped += len(conns)
        return len(conns)

    async def restart(self, down_s: float = 1.0) -> None:
        """Server restart: listener and connections closed for down_s wall seconds, then back on
        the same port with the same register memory. Returns when it listens again."""
        self._listening.clear()
        if self._server is not None:
            await self._server.shutdown()
            self._server = None
        self.stats.restarts += 1
        self._down.clear()
        try:
            await asyncio.wait_for(self._down.wait(), timeout=down_s)
        except asyncio.TimeoutError:
            pass
        if not self._stopping:
            await self._listen(self.port)

    def add_fault(self, spec) -> None:
        """A FaultSpec from config/CLI: switched on now, or scheduled when it has at_h."""
        if spec.at_h is None:
            self.faults.enable_spec(spec)
        else:
            self._schedule.append((spec, False))

    @property
    def loop_task(self) -> asyncio.Task | None:
        """The plant loop task (done only after stop() or a failure)."""
        return self._task

    async def wait_listening(self, timeout: float = 10.0) -> None:
        """Wait until the server listens (after start or a restart)."""
        await asyncio.wait_for(self._listening.wait(), timeout)

    def _on_fault(self, kind: str, tag: str | None, on: bool) -> None:
        if kind != "restart":
            return
        if on:
            spec = next(f for f in self.faults.active() if f.kind == "restart")
            if self._restart_task is None or self._restart_task.done():
                self._restart_task = asyncio.get_running_loop().create_task(self._restart_then_clear(spec.down_s))
        elif self._down is not None:
            self._down.set()

    async def _restart_then_clear(self, down_s: float) -> None:
        await self.restart(down_s)
        if self.faults.is_on("restart"):
            self.faults.disable("restart")

    # ---------------------------------------------------------------------------- loop ----
    @property
    def plant_time(self) -> float:
        return self.plant.t

    async def wait_ticks(self, n: int = 1, timeout: float = 10.0) -> None:
        """Wait until the registers have been pushed n more times (TimeoutError otherwise)."""
        target = self._pushes + n
        async with self._update:
            await asyncio.wait_for(self._update.wait_for(
                lambda: self._pushes >= target or self._stopping), timeout)
        self._raise_errors()

    async def wait_plant_time(self, t: float, timeout: float = 10.0) -> None:
        """Wait until plant time has reached t [epoch s] (registers show it unless frozen)."""
        async with self._update:
            await asyncio.wait_for(self._update.wait_for(
                lambda: self.plant.t >= t or self._stopping),
                timeout)
        self._raise_errors()

    def _raise_errors(self) -> None:
        if self._errors:
            raise RuntimeError("simulator plant loop failed") from self._errors[0]

    async def _run(self) -> None:
        """Step the plant to wall-clock plant time and push the registers, every `period`:
        one tick's worth of wall time, but at least MAX_PERIOD_S (the life counter and the PLC
        clock move like a PLC's even at 1x) and at most MAX_LOOP_HZ pushes per second."""
        loop = asyncio.get_running_loop()
        wall0, plant0 = loop.time(), self.plant.t
        period = min(max(self.plant.dt / self.speed, 1.0 / MAX_LOOP_HZ), MAX_PERIOD_S)
        max_ticks = max(1, int(math.ceil(2.0 * self.speed / self.plant.dt)))   # <= 2 s of plant time
        next_wake = loop.time()
        try:
            while not self._stopping:
                await self._sync_setpoint()
                await self._sync_cip_request()
                target = plant0 + self.speed * (loop.time() - wall0)
                await loop.run_in_executor(self._executor, self.plant.advance_to, target, max_ticks)
                await self._sync_setpoint()
                await self._sync_cip_request()
                if target - self.plant.t > 4.0 * self.speed + self.plant.dt:
                    # cannot keep up (slow machine, huge speed): re-anchor instead of bursting
                    self.stats.catchups += 1
                    wall0, plant0 = loop.time(), self.plant.t
                    target = self.plant.t
                self.clock = min(target, self.plant.t + self.plant.dt)
                self._apply_schedule()
                self._drain_truth()
                if not self.faults.frozen:
                    await self._push()
                async with self._update:
                    self._update.notify_all()
                next_wake = max(next_wake + period, loop.time() + 0.001)
                await asyncio.sleep(next_wake - loop.time())
        except asyncio.CancelledError:
            raise
        except Exception as exc:   # surfaced to waiters and re-raised: a dead plant must be loud
            log.exception("simulator plant loop failed")
            self._errors.append(exc)
            async with self._update:
                self._update.notify_all()
            raise

    # ------------------------------------------------------------- remote set point ----
    async def _plc_loop(self) -> None:
        """The remote-set-point program, one scan every PLC_SCAN_S of wall time."""
        while not self._stopping:
            await self._plc_scan()
            await asyncio.sleep(PLC_SCAN_S)

    async def _plc_scan(self) -> None:
        if self._context is None or self.program is None:
            return
        dev, en = self.cfg.device_id, self.enable_spec
        words = await self._context.async_getValues(dev, 3, en.address, 1)
        enable = not isinstance(words, ExcCodes) and words[0] != 0
        change = self.program.scan(enable, time.monotonic())
        if change is None:
            return
        sp = self.tags[SETPOINT_TAG]
        before = self.plant.p_m_sp_bar_g
        if change.mode == "local":     # revert to the operator's local set point, at once
            await self._context.async_setValues(dev, 3, sp.address, encode(sp, self.plant.local_sp_bar_g))
        rec = {"wall": time.time(), "mono": change.t, "plant_t": self.plant.t, "mode": change.mode,
               "reason": change.reason, "heartbeat_age_s": change.heartbeat_age_s,
               "p_m_sp_before": before, "local_sp": self.plant.local_sp_bar_g}
        self.plc_events.append(rec)
        log.info("PLC: %s mode (%s); heartbeat age %.2f s", change.mode, change.reason,
                 change.heartbeat_age_s)

    async def set_operator_enable(self, on: bool) -> None:
        """The operator's switch at the HMI (the enable register), without a Modbus write (so the
        write log shows the gateway's writes only)."""
        if self.enable_spec is None or self._context is None:
            raise RuntimeError("no enable register (remote_setpoint.enable_tag) or not started")
        await self._context.async_setValues(self.cfg.device_id, 3, self.enable_spec.address, [int(bool(on))])

    def set_local_setpoint(self, bar_g: float) -> None:
        """The operator's local set point at the panel (clamped into control.p_m_sp_limits_bar_g):
        the plant takes it in local mode; in remote mode it waits for the fallback. Without the
        remote-set-point program the set-point register rules and this has no effect."""
        lo, hi = self.cfg.control.p_m_sp_limits_bar_g
        self.plant.local_sp_bar_g = min(max(float(bar_g), lo), hi)

    @property
    def remote_mode(self) -> bool:
        """The remote-set-point program's mode (False without the program)."""
        return self.program is not None and self.program.remote

    async def _sync_setpoint(self) -> None:
        """Keep the set-point register and the plant's set point together (unless frozen: a
        write then never reaches the PLC). A client write (the register differs from what was
        last applied) moves the plant; a step of the PLC's own schedule moves the register.
        With the remote-set-point program: in local mode the register and the plant hold the
        operator's local set point; in remote mode the register (the remote set point) moves the plant."""
        spec = self.tags.get(SETPOINT_TAG)
        if spec is None or self.faults.frozen or self._server is None:
            return
        if self.program is not None:
            self.plant.remote = self.program.remote
            if not self.program.remote:
                await self._hold_local(spec)
                return
        regs = await self._server.async_getValues(self.cfg.device_id, 3, spec.address, spec.count)
        raw = ModbusClientMixin.convert_from_registers(
            list(regs), getattr(ModbusClientMixin.DATATYPE, spec.type.upper()),
            word_order="little" if spec.byte_order in ("CDAB", "DCBA") else "big")
        if not (spec.sentinel is not None and raw == spec.sentinel):
            value = raw * spec.scale + spec.offset
            if self._sp_last is None or abs(value - self._sp_last) >= 1e-9:
                used = self.plant.set_p_m_sp(value)
                self._sp_last = used
                self._sp_steps_seen = self.plant.sp_steps
                if abs(used - value) > spec.scale / 2:      # clamped: the PLC shows what it uses
                    await self._server.async_setValues(self.cfg.device_id, 3, spec.address, encode(spec, used))
                return
        if self.plant.sp_steps != self._sp_steps_seen:
            sp = self.plant.p_m_sp_bar_g
            await self._server.async_setValues(self.cfg.device_id, 3, spec.address, encode(spec, sp))
            self._sp_last = float(quantize(spec, np.array([sp]))[0])
            self._sp_steps_seen = self.plant.sp_steps

    async def _hold_local(self, spec) -> None:
        """Local mode: the register and the plant show the operator's local set point."""
        local = self.plant.local_sp_bar_g
        want = encode(spec, local)
        regs = await self._server.async_getValues(self.cfg.device_id, 3, spec.address, spec.count)
        if list(regs) != want:
            await self._server.async_setValues(self.cfg.device_id, 3, spec.address, want)
        if self.plant.p_m_sp_bar_g != local:
            self.plant.set_p_m_sp(local)
        self._sp_last = float(quantize(spec, np.array([local]))[0])
        self._sp_steps_seen = self.plant.sp_steps

    async def _sync_cip_request(self) -> None:
        """The CIP request register (cip.mode on_request): a non-zero client write asks the plant
        for a CIP; the register then reads 1 while the request is pending or the CIP runs."""
        reg = self.cip_register
        if reg is None or self.faults.frozen or self._server is None:
            return
        dev = self.cfg.device_id
        value = (await self._server.async_getValues(dev, 3, reg, 1))[0]
        plant = self.plant
        want = int(plant.cip_pending or plant.cip_window is not None)
        if value != 0 and want == 0 and value != self._cip_reg_last:
            plant.request_cip()
            want = 1
        if value != want:
            await self._server.async_setValues(dev, 3, reg, [want])
        self._cip_reg_last = want

    async def request_cip(self) -> bool:
        """Ask the plant for a CIP (cip.mode on_request), serialised with its stepping thread;
        returns Plant.request_cip()'s answer."""
        if self._executor is None:
            return self.plant.request_cip()
        return await asyncio.get_running_loop().run_in_executor(self._executor, self.plant.request_cip)

    def _apply_schedule(self) -> None:
        if not self._schedule:
            return
        h = (self.plant.t - self.plant.t0) / 3600.0
        new = []
        for spec, on in self._schedule:
            start = spec.at_h if spec.at_h is not None else 0.0
            end = start + spec.duration_h if spec.duration_h is not None else math.inf
            want = start <= h < end
            if want and not on:
                self.faults.enable_spec(spec)
            elif on and not want and spec.kind != "restart":
                self.faults.disable(spec.kind, spec.tag)
            new.append((spec, want or (on and spec.kind == "restart")))
        self._schedule = new

    def _drain_truth(self) -> None:
        recs = self.plant.drain_truth()
        if not recs:
            return
        self.truth = recs[-1]
        self.truth_history.extend(recs)
        if len(self.truth_history) > self.truth_history_max:
            del self.truth_history[: len(self.truth_history) - self.truth_history_max]
        if self._truth_fh is not None:
            for r in recs:
                self._truth_fh.write(json.dumps(_jsonable(r)) + "\n")
            self._truth_fh.flush()

    def current_values(self) -> dict[str, float]:
        """Engineering values the plant shows now, with faults applied, before quantization."""
        values = dict(self.plant.measured)
        values.update({k: float(v) for k, v in self.plant.flags.items()})
        values = self.faults.apply(values)
        values["plc_clock"] = float(int(max(self.clock, self.plant.t)))
        values["life_counter"] = float(self.life_counter)
        values["p_m_sp"] = self.plant.p_m_sp_bar_g
        return values

    async def _push(self) -> None:
        if self._server is None:      # restarting: the PLC keeps running, nobody can read
            return
        self.life_counter = (self.life_counter + 1) % 65536
        values = self.current_values()
        dev = self.cfg.device_id
        for run in self.runs:
            owned = [t for t in run.tags if t.name in self.client_tags]
            if not owned:
                await self._server.async_setValues(dev, INTERNAL_FC[run.register], run.start,
                                                   encode_run(run, values))
                continue
            # the set point and the enable are the clients' (the plant writes the set point back
            # only when clamping): push the run's other tags one by one
            for t in run.tags:
                if t.name not in self.client_tags:
                    await self._server.async_setValues(dev, INTERNAL_FC[run.register], t.address,
                                                       encode(t, values.get(t.name, math.nan)))
        if self._sp_last is None:
            spec = self.tags.get(SETPOINT_TAG)
            if spec is not None:
                await self._server.async_setValues(dev, 3, spec.address, encode(spec, values["p_m_sp"]))
                self._sp_last = values["p_m_sp"]
        values["_t"] = self.plant.t
        self.served = values
        self.stats.pushes += 1
        self._pushes += 1

    # ----------------------------------------------------------------- direct access ----
    async def read_registers(self, register: str, address: int, count: int) -> list[int]:
        """Read the register memory directly (no Modbus round trip), e.g. the advisory block."""
        if self._context is None:
            raise RuntimeError("simulator not started")
        res = await self._context.async_getValues(self.cfg.device_id, INTERNAL_FC[register], address, count)
        if isinstance(res, ExcCodes):
            raise ValueError(f"{register} {address}+{count}: {res.name}")
        return list(res)


def _jsonable(rec: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in rec.items()}

