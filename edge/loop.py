"""The gateway daemon: startup -> main loop -> shutdown (SPEC 7.2, issue #5 item 3).

One scan cycle, every ``scan_interval_s`` on the monotonic clock:

1. read every tag in the planned grouped requests (``PlcClient.read_all``; never raises);
2. feed the scan to the ``Aggregator`` (validity, max age, frozen life counter); every period it
   closes becomes a one-minute sample, processed on the measured side and stored (worker thread);
3. when a calibration is due on the sample clock and none is running, start one in a worker
   thread (fouling calibration on the latest usable window, then the set-point optimization);
   it never blocks the event loop, and the cycle goes on while it runs;
4. when a calibration has finished, take its advice (or keep the last good advice, with its age,
   and set the failure bit);
5. the opt-in closed loop (edge.closed_loop, SPEC 7.4): with this scan's values, status bits and
   advice, write at most one set-point step (off as shipped; then it only reports its state);
6. write the whole advisory block - heartbeat, status word, values, closed-loop state - in ONE FC16
   request.

The sample clock is the wall clock, or with ``time_source="plc"`` the PLC's clock register (plant
time: the accelerated simulator, or a PLC whose clock the plant's history should follow). Every
reading is checked for plausibility (``edge.sampleclock``: against the host clock and the last
accepted reading) before the scan is aggregated, stored, pruned by or scheduled on; a rejected
reading's scan still counts for freshness but is not aggregated. A lasting jump (a real clock
correction) is accepted after it persisted for ``ClockPolicy.confirm_s``, logged, and the
calibration schedule starts afresh on the new clock.
Freshness (max age, frozen life counter) is always judged on the monotonic clock.

Status bits (gateway.yaml ``advisory.status_bits``; names are what matters, numbers are config):

- ``data_stale``: a tag has not been read good for its ``max_age_s``, or the life counter froze;
- ``heat_pump_off``: the running flag reads 0 (without a good running flag: W_LS + W_HS < 20 kW);
- ``cip_detected``: the CIP flag reads 1;
- ``calibration_failed``: no fouling calibration yet (none restored from the state directory),
  or the last one failed;
- ``model_infeasible``: the last set-point optimization failed (no feasible point in the window);
- ``comm_fault``: the last poll got no usable answer, or one did since the previous successful
  advisory write (so an HMI sees the bit after a PLC restart, for one cycle at least);
- ``advice_stale``: the values are not a current advice: the last attempt failed, there are no
  values at all, or they are older than 1.5 calibration intervals (e.g. not enough usable data:
  plant off, CIP), or their age is unknown (no sample clock yet, or the advice is from a later
  time than the sample clock now shows: ``advice_age_s`` then holds its type's maximum);
- ``storage_fault``: the history or the state directory is not writable (locked, full,
  read-only); the advice is still computed and written, rows wait in memory and storage recovers
  by itself (the advisor's ``storage_fault``);
- ``clock_fault``: the sample clock of this scan was rejected as implausible, or one was since the
  previous successful advisory write;
- ``sensor_fault``: while the plant runs and the PLC answers, a required tag has flat-lined
  (``edge.aggregate``, reason ``flatline``) or has not been read good for its ``max_age_s``.

The first block already carries the right bits: ``calibration_failed`` follows the calibrations
this loop has seen (restored at start, collected since), never a calibration still running, and
the advice's age is judged on the sample clock of the scan being written.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from edge.advisory import encode_advisory
from edge.aggregate import MIN_POWER_KW, Aggregator, Freshness, Sample, plant_running
from edge.closed_loop import ClosedLoop
from edge.codec import raw_limits
from edge.config import GatewayConfig
from edge.plc import PlcClient, PlcError, PlcExceptionReply, ReadResult
from edge.repeatlog import RepeatLog
from edge.sampleclock import ClockPolicy, SampleClock

log = logging.getLogger(__name__)

TIME_SOURCES = ("wall", "plc")
ADVICE_STALE_INTERVALS = 1.5
MAX_FAILED_CYCLES = 10      # consecutive cycles raising an unexpected error: exit code 1
STATUS_NAMES = ("data_stale", "heat_pump_off", "cip_detected", "calibration_failed",
                "model_infeasible", "comm_fault", "advice_stale", "advice_low_confidence",
                "storage_fault", "clock_fault", "sensor_fault")
# advisory fields the loop fills itself; an advisor provides the others
LOOP_FIELDS = ("heartbeat", "status", "last_update", "advice_age_s", "closed_loop_state",
               "closed_loop_reason", "closed_loop_sp_written", "closed_loop_target",
               "closed_loop_last_write", "closed_loop_writes")


@dataclass(frozen=True)
class Advice:
    """The outcome of one calibration cycle.

    t : end of the window the advice was computed on [epoch s, sample clock]
    values : advisory field name -> value in the block's unit (empty when nothing new)
    calibration_ok, optimization_ok : outcome of the two steps (False: the step failed)
    message : why a step failed or was skipped ('' when all went well)
    detail : report for the history (NRMSE per target, iterations, run time, ...)
    skipped : nothing was attempted (e.g. too few usable samples): no failure bit
    low_confidence : the recommendation is the current set point because the model cannot tell
        where the optimum lies (status bit advice_low_confidence; the reason is in ``message``)
    """
    t: float
    values: Mapping[str, float] = field(default_factory=dict)
    calibration_ok: bool = True
    optimization_ok: bool = True
    message: str = ""
    detail: Mapping[str, Any] = field(default_factory=dict)
    skipped: bool = False
    low_confidence: bool = False

    @property
    def ok(self) -> bool:
        return self.calibration_ok and self.optimization_ok and not self.skipped


class Notifier:
    """Life-cycle notifications for a supervisor; this one does nothing (edge.service.SdNotify
    tells systemd: READY=1, WATCHDOG=1 every cycle, STOPPING=1)."""

    def ready(self) -> None:
        """Start-up done; the main loop begins."""

    def alive(self) -> None:
        """A scan cycle completed (the event loop is not stuck)."""

    def stopping(self) -> None:
        """Shutdown has begun."""


class Advisor(Protocol):
    """What the loop needs from the model side (edge.service.ModelAdvisor is the real one)."""

    def ingest(self, samples: list[Sample]) -> list[dict]:
        """Measured-side processing and storage of closed one-minute samples (worker thread).
        Returns the stored rows (tags, derived columns, usable, reason)."""

    def advise(self, t_end: float) -> Advice:
        """Fouling calibration on the usable window ending at ``t_end``, then the set-point
        optimization (worker thread). Never raises for model failures: reports them."""

    def restored(self) -> Advice | None:
        """The last good advice from persisted state, or None (called once at startup)."""

    @property
    def has_calibration(self) -> bool:
        """True when a fouling calibration exists (restored or computed). The loop reads it
        once, at startup; afterwards it follows the calibrations it collects."""

    @property
    def storage_fault(self) -> str | None:
        """Why the history or the state directory is not writable right now, None when they
        are (optional: an advisor without it never sets the storage_fault bit)."""


class Observer(Protocol):
    """Told about the gateway's life and every scan cycle (edge.health, edge.northbound).

    All three are called on the event loop. ``cycle`` must return at once: an observer that
    has real work (a network, a disk) hands it to its own thread or task. An observer that
    raises is logged and never stops the loop or the advisory writes."""

    async def start(self, gateway: Gateway) -> None:
        """The gateway has started (before the first cycle)."""

    def cycle(self, event: CycleEvent) -> None:
        """One scan cycle has ended (its advisory write done or failed)."""

    async def stop(self) -> None:
        """The gateway is stopping (bounded: each observer gets ``shutdown_timeout_s``)."""


@dataclass
class Snapshot:
    """What the gateway shows right now (tests and the demo read it)."""
    cycles: int = 0
    heartbeat: int = 0
    writes_ok: int = 0
    writes_failed: int = 0
    status_bits: tuple[str, ...] = ()
    values: dict[str, float] = field(default_factory=dict)
    sample_time: float | None = None     # sample clock of the last scan
    samples: int = 0                     # one-minute samples closed since start
    calibrations: int = 0                # calibration cycles finished (any outcome)
    advice_time: float | None = None
    advice_message: str = ""
    last_scan: dict[str, float | None] = field(default_factory=dict)
    comm_error: str | None = None
    errors: int = 0                      # unexpected errors survived (logged with traceback)
    clock_rejected: int = 0              # scans whose sample clock was rejected
    clock_jumps: int = 0                 # lasting clock jumps accepted as corrections
    storage_fault: str | None = None     # the advisor's, as of the last cycle
    closed_loop: tuple[str, str] = ("off", "disabled_in_config")   # (state, reason) of edge.closed_loop


@dataclass(frozen=True)
class CycleEvent:
    """What one scan cycle did, for observers (read-only; ``snapshot`` is the live object).

    result : this cycle's poll (values, comm_error, duration)
    rows : one-minute samples stored in this cycle, as ``Advisor.ingest`` returned them
    advice : the calibration cycle collected in this cycle (any outcome, skipped ones too)
    calibration_s : how long that calibration ran [s, on the gateway's monotonic clock]
    duration_s : this cycle from the start of the poll to the end of the advisory write [s]
    t_mono : end of the cycle on the gateway's monotonic clock [s]
    """
    snapshot: Snapshot
    result: ReadResult
    rows: tuple[dict, ...] = ()
    advice: Advice | None = None
    calibration_s: float | None = None
    duration_s: float = 0.0
    t_mono: float = 0.0


class Gateway:
    """The daemon. ``await Gateway(cfg, ...).run()`` runs until ``request_stop()`` or a signal.

    cfg : the loaded configuration (loaded once; nothing re-reads files while running)
    advisor : the model side (ingest, advise, restored); built by edge.service for production
    plc : a PlcClient (default: from cfg)
    time_source : 'wall' (production) or 'plc' (sample clock = the PLC's clock register)
    clock_tag : the tag that holds the PLC clock (uint32 epoch seconds)
    monotonic : the clock of the scan cadence and of freshness (injected in tests); the sample
        clock comes from the scans (ReadResult.timestamp or the PLC clock register)
    install_signals : handle SIGTERM/SIGINT (only in the main thread)
    shutdown_timeout_s : how long shutdown waits for a running calibration
    notifier : told when the gateway is ready, alive (every cycle) and stopping (systemd)
    clock : limits of the sample-clock check (edge.sampleclock.ClockPolicy; default limits)
    host_clock : the host's wall clock [epoch s] the sample clock is checked against (injected
        in tests)
    required_tags : tags whose flat line or staleness sets sensor_fault (default: every
        aggregated tag; the service passes the model's required inputs)
    observers : told after every cycle (``Observer``: the health endpoint, the MQTT publisher)
    audit : called (in a worker thread) with one dict per closed-loop write or change of state
        (edge.service passes the history store's ``add_closed_loop_event``)
    """

    def __init__(self, cfg: GatewayConfig, advisor: Advisor, *, plc: PlcClient | None = None,
                 time_source: str = "wall", clock_tag: str = "plc_clock",
                 monotonic: Callable[[], float] = time.monotonic, install_signals: bool = True,
                 shutdown_timeout_s: float = 10.0, notifier: Notifier | None = None,
                 clock: ClockPolicy | None = None, host_clock: Callable[[], float] = time.time,
                 required_tags: Iterable[str] | None = None,
                 observers: Iterable[Observer] = (),
                 audit: Callable[[dict], Any] | None = None) -> None:
        if time_source not in TIME_SOURCES:
            raise ValueError(f"time_source must be one of {', '.join(TIME_SOURCES)}")
        tag_names = {t.name for t in cfg.tags}
        if time_source == "plc" and clock_tag not in tag_names:
            raise ValueError(f"time_source 'plc' needs the clock tag {clock_tag!r} in the tag map")
        self.cfg = cfg
        self.advisor = advisor
        self.plc = plc or PlcClient.from_config(cfg)
        self.time_source, self.clock_tag = time_source, clock_tag
        self._mono = monotonic
        self.install_signals = install_signals
        self.shutdown_timeout_s = shutdown_timeout_s
        configured = {name for _, name in cfg.advisory.status_bits}
        self._bits = tuple(n for n in STATUS_NAMES if n in configured)
        self._fields = {f.name for f in cfg.advisory.fields}
        # the operator's closed-loop enable is a switch, not a measurement: not aggregated and
        # never data_stale (the closed loop judges it itself); the PLC clock is not aggregated
        loop_cfg = getattr(cfg, "closed_loop", None)
        enable = loop_cfg.enable_tag if loop_cfg is not None else None
        self.aggregator = Aggregator(
            tuple(t for t in cfg.tags if t.name != enable), cfg.aggregate_s,
            life_counter=cfg.life_counter_tag,
            exclude=(clock_tag,) if clock_tag in tag_names else (), t_start=monotonic())
        self.clock = SampleClock(clock, rate=1.0 if time_source == "wall" else None)
        self._host = host_clock
        self._clock_log = RepeatLog(log, "clock check", level=logging.WARNING,
                                    monotonic=monotonic)
        self._clock_since_write = False
        data = set(self.aggregator.data_tags)
        self.required = tuple(n for n in (required_tags if required_tags is not None else data)
                              if n in data)
        self._has_calibration = False      # as far as this loop knows (startup, collected)
        self.snapshot = Snapshot()
        self.changed = asyncio.Event()   # set after every cycle (tests and the demo wait on it)
        self._stop = asyncio.Event()
        self._wake = asyncio.Event()   # stop requested, or a calibration finished
        self._advice: Advice | None = None            # last good advice
        self._last_attempt: Advice | None = None      # last finished calibration cycle
        self._calibration: asyncio.Future | None = None
        self._calibration_t = math.nan                # window end of the running calibration
        self._calibration_due = -math.inf             # sample clock
        self._skipped_at: float | None = None         # window end of the last skipped attempt
        self._skipping = False                        # in a run of skipped attempts (logging)
        self._comm_since_write = False
        self._write_refused = False                   # the PLC answered a write with an exception
        self._last_sample_end: float | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._saved_signals: dict[int, Any] = {}
        self.exit_code = 0
        self.notifier = notifier or Notifier()
        self.observers: list[Observer] = list(observers)
        self._observer_log = RepeatLog(log, "observer", level=logging.ERROR, monotonic=monotonic)
        self._calibration_started = math.nan          # monotonic start of the running one
        self._calibration_s: float | None = None      # duration of the last finished one
        self._all_bits: set[str] = set()              # this scan's bits, configured or not
        self.closed_loop = ClosedLoop.from_config(cfg, self.plc, audit)

    # ------------------------------------------------------------------------- lifecycle

    async def run(self) -> int:
        """startup -> main loop -> shutdown. Returns the exit code (0: stopped on request)."""
        await self.startup()
        try:
            await self.main_loop()
        finally:
            await self.shutdown()
        return self.exit_code

    def request_stop(self) -> None:
        """Ask the loop to stop after the current cycle (safe from signal handlers)."""
        if not self._stop.is_set():
            log.info("stop requested")
        self._stop.set()
        self._wake.set()

    async def startup(self) -> None:
        self._executor = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="hp-edge-calibration")
        if self.install_signals:
            self._install_signal_handlers()
        restored = await asyncio.to_thread(self.advisor.restored)
        self._has_calibration = bool(self.advisor.has_calibration)
        if restored is not None:
            self._advice = restored
            self._calibration_due = restored.t + self.cfg.calibration_interval_s
            log.info("restored advice of %s", _fmt_time(restored.t))
        for obs in list(self.observers):
            try:
                await obs.start(self)
            except Exception as exc:  # noqa: BLE001 - a port in use must not stop the advisory
                log.error("%s did not start, the gateway runs without it: %s",
                          type(obs).__name__, exc)
                self.observers.remove(obs)
        self.notifier.ready()
        log.info("gateway started: PLC %s:%s, scan %g s, sample clock %s, optimizer %s",
                 self.plc.plc.host, self.plc.plc.port, self.cfg.scan_interval_s,
                 self.time_source, self.cfg.optimizer)

    async def shutdown(self) -> None:
        """Wait (bounded) for a running calibration, close the PLC connection, restore signals."""
        self.notifier.stopping()
        if self._calibration is not None and not self._calibration.done():
            log.info("waiting up to %g s for the running calibration", self.shutdown_timeout_s)
            try:
                await asyncio.wait_for(asyncio.shield(self._calibration), self.shutdown_timeout_s)
                self._collect_calibration()
            except asyncio.TimeoutError:
                log.warning("calibration still running after %g s: abandoned (its state is "
                            "written atomically, nothing half-written remains)",
                            self.shutdown_timeout_s)
        await self.closed_loop.shutdown()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
        await self.plc.close()
        for obs in self.observers:
            try:
                await asyncio.wait_for(obs.stop(), self.shutdown_timeout_s)
            except Exception as exc:  # noqa: BLE001 - stopping goes on for the others
                log.error("%s did not stop cleanly: %s", type(obs).__name__, exc or
                          type(exc).__name__)
        self._restore_signal_handlers()
        log.info("gateway stopped after %d cycles", self.snapshot.cycles)

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            self._saved_signals[sig] = signal.getsignal(sig)
            loop.add_signal_handler(sig, self.request_stop)

    def _restore_signal_handlers(self) -> None:
        if not self._saved_signals:
            return
        loop = asyncio.get_running_loop()
        for sig, previous in self._saved_signals.items():
            loop.remove_signal_handler(sig)
            signal.signal(sig, previous)
        self._saved_signals.clear()

    # ------------------------------------------------------------------------- main loop

    async def main_loop(self) -> None:
        """Cycles every scan interval on the monotonic clock. A finished calibration wakes the
        loop at once, so its advice is written within milliseconds (the cadence restarts from
        that cycle); a stop request wakes it too."""
        period = self.cfg.scan_interval_s
        next_at = self._mono()
        failures = 0
        while not self._stop.is_set():
            try:
                await self.cycle()
                failures = 0
            except Exception as exc:  # noqa: BLE001 - a bug must not stop the advisory at once
                failures += 1
                self.snapshot.errors += 1
                log.exception("scan cycle failed (%d in a row): %s", failures, exc)
                if failures >= MAX_FAILED_CYCLES:
                    log.critical("%d scan cycles failed in a row: exiting so that the service "
                                 "manager restarts a fresh process", failures)
                    self.exit_code = 1
                    break
            next_at += period
            now = self._mono()
            if now > next_at:   # overran (slow PLC, slow disk): skip the missed slots
                missed = math.floor((now - next_at) / period) + 1
                log.debug("cycle overran by %.3f s; skipping %d slot(s)", now - next_at + period,
                          missed)
                next_at += missed * period
            try:
                await asyncio.wait_for(self._wake.wait(), max(0.0, next_at - self._mono()))
                next_at = self._mono()          # woken: a calibration finished (or stop)
            except asyncio.TimeoutError:
                pass

    async def cycle(self) -> None:
        """One scan cycle: read, aggregate, store, calibrate (in the background), write."""
        if not self._stop.is_set():
            self._wake.clear()  # before collecting: a calibration finishing later wakes us again
        t_begin = self._mono()
        result = await self.plc.read_all()
        t_mono = self._mono()
        t_sample = self._check_clock(self._sample_time(result), t_mono)
        if t_sample is not None:
            self.snapshot.sample_time = t_sample
        if result.comm_error is not None:
            self._comm_since_write = True
        samples = self.aggregator.add(t_sample, t_mono, result.values, result.comm_error)
        rows: list[dict] = []
        if samples:
            rows = await self._ingest(samples)
        advice, calibration_s = self._collect_calibration(), self._calibration_s
        self._maybe_start_calibration()
        fresh = self.aggregator.freshness(t_mono)
        bits = self._status_bits(result, fresh)
        await self._closed_loop(result, t_sample)
        await self._write(bits, t_sample)
        snap = self.snapshot
        snap.cycles += 1
        self.notifier.alive()
        snap.comm_error = result.comm_error
        snap.last_scan = {n: v.value for n, v in result.values.items()}
        if self.observers:
            t_end = self._mono()
            self._notify(CycleEvent(snap, result, tuple(rows), advice,
                                    calibration_s if advice is not None else None,
                                    t_end - t_begin, t_end))
        self.changed.set()
        self.changed = asyncio.Event()

    async def _closed_loop(self, result: ReadResult, t_sample: float | None) -> None:
        """One step of the opt-in closed loop; an unexpected error in it sheds it, never the scan."""
        adv = self._advice
        try:
            st = await self.closed_loop.step(result, self._all_bits,
                                             adv.values if adv is not None else None, t_sample)
        except Exception as exc:  # noqa: BLE001 - a bug here must stop the writes, not the advisory
            self.snapshot.errors += 1
            log.exception("closed loop step failed: %s", exc)
            await self.closed_loop.fault(exc)
            st = self.closed_loop.status
        self.snapshot.closed_loop = (st.state.name.lower(), st.reason.name.lower())

    def _notify(self, event: CycleEvent) -> None:
        failed = None
        for obs in self.observers:
            try:
                obs.cycle(event)
            except Exception as exc:  # noqa: BLE001 - an observer's bug never stops the loop
                failed = f"{type(obs).__name__}.cycle raised {type(exc).__name__}: {exc}"
                log.debug("observer failed", exc_info=True)
        if failed:
            self._observer_log.fail(failed)
        else:
            self._observer_log.ok()

    @property
    def monotonic(self) -> Callable[[], float]:
        """The clock of the scan cadence and of freshness (observers measure ages on it)."""
        return self._mono

    def _sample_time(self, result: ReadResult) -> float | None:
        if self.time_source == "wall":
            return result.timestamp
        v = result.values.get(self.clock_tag)
        return v.value if v is not None and v.bad is None else None

    def _check_clock(self, t: float | None, t_mono: float) -> float | None:
        """The scan's sample time if plausible (edge.sampleclock), else None (and counted)."""
        if t is None:
            return None
        v = self.clock.check(t, t_mono, self._host())
        if v.t is None:
            self.snapshot.clock_rejected += 1
            self._clock_since_write = True
            self._clock_log.fail(f"{v.rejected}; the scan is not aggregated "
                                 f"({self.snapshot.clock_rejected} rejected since start)")
            return None
        self._clock_log.ok()
        if v.jump_s is not None:
            self.snapshot.clock_jumps += 1
            log.warning("sample clock: a jump of %+.0f s persisted for %g s: accepted as a "
                        "clock correction (now %s); calibration is planned afresh on the new "
                        "clock", v.jump_s, self.clock.policy.confirm_s, _fmt_time(v.t))
            self._calibration_due = -math.inf
            self._skipped_at = None
            self._last_sample_end = None    # samples of the old clock schedule nothing now
        return v.t

    async def _ingest(self, samples: list[Sample]) -> list[dict]:
        rows: list[dict] = []
        try:
            rows = list(await asyncio.to_thread(self.advisor.ingest, samples) or ())
        except Exception as exc:  # noqa: BLE001 - disk full, sqlite, a bad sample: log, go on
            self.snapshot.errors += 1
            log.exception("processing or storing %d sample(s) failed: %s", len(samples), exc)
        self.snapshot.samples += len(samples)
        # schedule on samples up to the clock now: after the clock was set back (an accepted
        # correction), the old clock's last period is stored but calibrates nothing
        now = self.clock.last
        ends = [s.timestamp + self.cfg.aggregate_s for s in samples
                if now is None or s.timestamp <= now]
        if ends:
            self._last_sample_end = max(ends)
        return rows

    # ----------------------------------------------------------------------- calibration

    def _maybe_start_calibration(self) -> None:
        t_end = self._last_sample_end
        if t_end is None or (self._calibration is not None and not self._calibration.done()):
            return
        if t_end < self._calibration_due - self.cfg.calibration_interval_s:
            # the sample clock went back behind the last calibration (PLC clock reset, replaced
            # simulator): calibrate on the new clock instead of waiting for the old one
            log.warning("sample clock %s is before the last calibration's window end; "
                        "calibrating on the new clock", _fmt_time(t_end))
            self._calibration_due = -math.inf
        if t_end < self._calibration_due:
            return
        if self._skipped_at is not None and t_end <= self._skipped_at:
            return      # skipped for too few samples: try again with the next sample
        loop = asyncio.get_running_loop()
        self._calibration = loop.run_in_executor(self._executor, self.advisor.advise, t_end)
        self._calibration.add_done_callback(self._calibration_done)
        self._calibration_t = t_end
        self._calibration_started = self._mono()

    def _calibration_done(self, fut: asyncio.Future) -> None:
        """Wake the loop to write new advice (or a failure) at once; a skip has nothing to show."""
        self._calibration_s = self._mono() - self._calibration_started
        if fut.cancelled() or fut.exception() is not None or not fut.result().skipped:
            self._wake.set()

    def _collect_calibration(self) -> Advice | None:
        """The finished calibration cycle's outcome (None when none finished)."""
        fut = self._calibration
        if fut is None or not fut.done():
            return None
        self._calibration = None
        t_end = self._calibration_t
        try:
            adv: Advice = fut.result()
        except Exception as exc:  # noqa: BLE001 - a bug in a solver must not stop the daemon
            self.snapshot.errors += 1
            log.exception("calibration cycle raised: %s", exc)
            adv = Advice(t_end, calibration_ok=False, optimization_ok=False,
                         message=f"{type(exc).__name__}: {exc}")
        if adv.skipped:
            # nothing attempted (too few usable samples): look again at the next sample
            self._skipped_at = t_end
            # the first skip of a run is news; the repeats (a CIP lasts days) go to debug
            log.log(logging.DEBUG if self._skipping else logging.INFO,
                    "calibration at %s skipped: %s", _fmt_time(t_end), adv.message)
            self._skipping = True
            self.snapshot.advice_message = adv.message
            return adv
        self._skipping = False
        self._calibration_due = t_end + self.cfg.calibration_interval_s
        self._last_attempt = adv
        if adv.calibration_ok:
            self._has_calibration = True
        self.snapshot.calibrations += 1
        self.snapshot.advice_message = adv.message
        if adv.ok:
            self._advice = adv
            log.info("advice of %s: %s", _fmt_time(adv.t), _fmt_values(adv.values))
        else:
            log.warning("calibration cycle of %s failed, keeping the last good advice: %s",
                        _fmt_time(t_end), adv.message)
        return adv

    # ----------------------------------------------------------------------------- output

    def _status_bits(self, result: ReadResult, fresh: Freshness) -> set[str]:
        bits: set[str] = set()
        if fresh.data_stale or result.comm_error is not None:
            bits.add("data_stale")
        good = {n: v.value for n, v in result.values.items() if v.bad is None}
        running = good.get("running")
        if running is not None:
            if running < 0.5:
                bits.add("heat_pump_off")
        else:   # no running flag: infer it from the compressor power, as the model side does
            power = [good.get(n) for n in ("W_LS", "W_HS")]
            if None not in power and sum(power) < MIN_POWER_KW:
                bits.add("heat_pump_off")
        cip = good.get("cip")
        if cip is not None and cip > 0.5:
            bits.add("cip_detected")
        last = self._last_attempt
        if not self._has_calibration or (last is not None and not last.calibration_ok):
            bits.add("calibration_failed")
        if last is not None and last.calibration_ok and not last.optimization_ok:
            bits.add("model_infeasible")
        if result.comm_error is not None or self._comm_since_write:
            bits.add("comm_fault")
        adv = self._advice
        if adv is None or (last is not None and not last.ok):
            bits.add("advice_stale")
        else:
            age = self._advice_age()
            if age is None or age > ADVICE_STALE_INTERVALS * self.cfg.calibration_interval_s:
                bits.add("advice_stale")
        if adv is not None and adv.low_confidence:
            bits.add("advice_low_confidence")
        fault = getattr(self.advisor, "storage_fault", None)
        self.snapshot.storage_fault = fault
        if fault is not None:
            bits.add("storage_fault")
        if self._clock_since_write:
            bits.add("clock_fault")
        if (plant_running(good) and result.comm_error is None and not fresh.frozen
                and set(self.required) & (set(fresh.stale) | set(fresh.flat))):
            bits.add("sensor_fault")
        self._all_bits = bits       # the closed loop judges every bit, configured in the block or not
        return {b for b in bits if b in self._bits}

    def _advice_age(self) -> float | None:
        """Age of the advice on the sample clock [s]; None when unknown: no sample clock yet, or
        the advice is from a later time than the clock now shows (it was set back)."""
        adv, now = self._advice, self.snapshot.sample_time
        if adv is None or now is None:
            return None
        age = now - adv.t
        if age < -(self.cfg.aggregate_s + self.clock.policy.back_tolerance_s):
            return None
        return max(0.0, age)

    def _values(self, t_sample: float | None) -> dict[str, float]:
        adv = self._advice
        values: dict[str, float] = {}
        if adv is not None:
            values.update((k, float(v)) for k, v in adv.values.items()
                          if k in self._fields and k not in LOOP_FIELDS)
            if "last_update" in self._fields:
                values["last_update"] = int(max(0.0, adv.t))
            if "advice_age_s" in self._fields:
                top = int(raw_limits(self.cfg.advisory.field("advice_age_s").type)[1])
                age = self._advice_age()
                values["advice_age_s"] = top if age is None else int(min(age, top))
        values.update((k, v) for k, v in self.closed_loop.values().items() if k in self._fields)
        return values

    async def _write(self, bits: set[str], t_sample: float | None) -> None:
        snap = self.snapshot
        snap.heartbeat = (snap.heartbeat + 1) % 65536
        values = self._values(t_sample)
        snap.values, snap.status_bits = values, tuple(sorted(bits, key=STATUS_NAMES.index))
        snap.advice_time = self._advice.t if self._advice is not None else None
        try:
            words = encode_advisory(self.cfg.advisory, values, bits, snap.heartbeat)
        except ValueError as exc:   # a value that does not fit its register: a bug, say so
            log.error("advisory block not encodable, writing status only: %s", exc)
            words = encode_advisory(self.cfg.advisory, {}, bits, snap.heartbeat)
        if not self.plc.connected:
            snap.writes_failed += 1
            return
        try:
            await self.plc.write_advisory(words)
        except PlcExceptionReply as exc:
            # the PLC refuses the block (not mapped, write-protected): say so once per run
            snap.writes_failed += 1
            self._comm_since_write = True
            if not self._write_refused:
                log.error("the PLC refuses the advisory block write: %s (repeats at debug "
                          "level)", exc)
            else:
                log.debug("advisory write refused: %s", exc)
            self._write_refused = True
            return
        except PlcError as exc:   # no answer: edge.plc logs the connection trouble
            snap.writes_failed += 1
            self._comm_since_write = True
            log.debug("advisory write failed: %s", exc)
            return
        if self._write_refused:
            log.warning("the PLC accepts the advisory block again")
            self._write_refused = False
        snap.writes_ok += 1
        self._comm_since_write = False   # this write carried the comm_fault bit, if it was due
        self._clock_since_write = False  # ... and the clock_fault bit

    # ------------------------------------------------------------------------ for callers

    async def wait_until(self, predicate: Callable[[Snapshot], bool], timeout: float) -> Snapshot:
        """Wait (bounded) until ``predicate(snapshot)`` holds after a cycle."""
        async def _wait() -> Snapshot:
            while not predicate(self.snapshot):
                await self.changed.wait()
            return self.snapshot
        return await asyncio.wait_for(_wait(), timeout)


def with_overrides(cfg: GatewayConfig, **kw) -> GatewayConfig:
    """A copy of ``cfg`` with fields replaced (the demo and tests shorten the cadence)."""
    return replace(cfg, **kw)


def _fmt_time(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def _fmt_values(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in values.items() if isinstance(v, (int, float)))
