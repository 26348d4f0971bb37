"""The model side of the gateway: measured-side processing, history, state, and one analysis
window (model.analysis.chain, the same chain replay runs) -> advisory values.

``ModelAdvisor`` is what ``edge.loop.Gateway`` calls from worker threads:

* ``ingest(samples)`` - closed one-minute samples -> ``model.measured.process`` (with the rows
  before them as context, so ramps after a start or a gap are recognised) -> the history store;
* ``advise(t_end)`` - the usable window ending at ``t_end`` -> ``AnalysisChain.window``: compressor
  learning, fouling calibration, the adaptive model, the set-point advice with its uncertainty and
  confidence -> the advisory values of SPEC 7.3, stored in the history; the chain's state (fouling
  calibration, learned compressors, what the next window needs) in the state directory;
* ``restored()`` - the last good advice after a restart.

CIPs (issue 10): ``ingest`` feeds every stored sample to a ``model.analysis.cip.CipWatch`` (replay's
rule: a stop with the CIP flag, or longer than plant.yaml's calibration.replay.cip_off_minutes; and a
hole in the samples that long) and calls ``AnalysisChain.cip`` when one ends: the fouling forecast and
the cumulated cost restart there. The forecast's memory (window estimates since the reset, the past
CIPs, earlier cycles' laws) and a stop in progress persist in chain_state.json.

The fixed model is plant.yaml plus the initial calibration and the clean pressure-drop fit from the
state directory when they exist; the adaptive model adds the learned compressor curves and the
latest fouling calibration.
"""
from __future__ import annotations

import json
import logging
import math
import os
import socket
import sqlite3
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from edge import statefiles
from edge.aggregate import Sample, sample_row
from edge.config import GatewayConfig
from edge.loop import Advice, Gateway, Notifier
from edge.repeatlog import RepeatLog
from edge.statefiles import StateError
from edge.store import HistoryStore
from model import measured
from model.analysis.chain import AnalysisChain, ChainSettings, WindowResult
from model.analysis.cip import CipWatch, ForecastState
from model.analysis.compressors import CompressorLearner, LearningError
from model.analysis.cost import CostError
from model.analysis.replay import ReplayError, ReplaySettings
from model.analysis.surrogate_tracker import SurrogateTracker, TrackerError
from model.heap import release_heap
from model.batch import INPUT_COLUMNS, simulate_batch, solved_mask
from model.calibration import CalibrationError, spec_from_config
from model.optimize import OptimizationError
from model.params import ParamError, PlantParams
from model.surrogate import Surrogate, SurrogateError

log = logging.getLogger(__name__)

CONTEXT_ROWS = measured.SETTLE_MIN + 2   # rows before new samples that processing needs to see
# A gap of more than this many periods between samples (gateway down, PLC clock unreadable) could
# hide a stop and a start: the samples after it count as a fresh start (ramping). Shorter gaps are
# scan jitter on an accelerated plant clock, or a brief outage the power-change check still covers.
GAP_PERIODS = 3


@dataclass
class ModelState:
    """Calibration state documents (dicts as stored in the state directory), None when absent."""
    initial: dict | None = None
    dp_clean: dict | None = None
    fouling: dict | None = None
    surrogate: dict | None = None
    compressors: dict | None = None
    chain: dict | None = None
    tracker: dict | None = None


class StartupError(Exception):
    """The gateway cannot start with this configuration or state (exit code 2, nothing
    connected); the message names the file."""


class StateDir:
    """The state documents of one state directory (edge.statefiles: atomic JSON).

    initial_calibration.json, dp_clean.json and surrogate.json are put there by commissioning
    (``hp-edge calibrate``, ``hp-edge fit-surrogate``); an unreadable one stops the start, since
    running on defaults instead would be silently wrong. fouling_calibration.json is the gateway's
    own last result; an unreadable one is logged and recomputed. Without surrogate.json in the
    state directory, ``fallback_surrogate`` (config/surrogate.json as shipped) is used.
    """

    def __init__(self, state_dir: Path, fallback_surrogate: Path | None = None) -> None:
        self.dir = Path(state_dir)
        self.fallback_surrogate = fallback_surrogate

    def load_all(self) -> ModelState:
        st = ModelState()
        try:
            st.initial = statefiles.read_state(statefiles.INITIAL_CALIBRATION, self.dir)
            st.dp_clean = statefiles.read_state(statefiles.DP_CLEAN, self.dir)
            sur = statefiles.read_state(statefiles.SURROGATE, self.dir)
            if sur is not None:
                st.surrogate = Surrogate.from_dict(sur)
            elif self.fallback_surrogate is not None and self.fallback_surrogate.exists():
                st.surrogate = Surrogate.load(self.fallback_surrogate)
        except (StateError, SurrogateError) as exc:
            raise StartupError(str(exc)) from exc
        for attr, name, what in (("fouling", statefiles.FOULING_CALIBRATION, "a fouling calibration"),
                                 ("compressors", statefiles.COMPRESSORS, "learned compressor curves"),
                                 ("chain", statefiles.CHAIN, "the previous window's state"),
                                 ("tracker", statefiles.SURROGATE_TRACKER,
                                  "the surrogate tracker's rows")):
            try:     # the gateway's own results: an unreadable one is recomputed, not fatal
                setattr(st, attr, statefiles.read_state(name, self.dir))
            except StateError as exc:
                log.error("%s; starting without %s", exc, what)
        for name, doc in (("initial calibration", st.initial), ("dp_clean fit", st.dp_clean),
                          ("fouling calibration", st.fouling), ("compressor curves", st.compressors)):
            if doc is not None:
                log.info("state: %s of %s loaded", name, doc.get("saved_at", "?"))
        if st.initial is None:
            log.warning("state: no %s in %s: the fixed model is the data sheet (plant.yaml); "
                        "commission with 'hp-edge calibrate initial'",
                        statefiles.INITIAL_CALIBRATION, self.dir)
        return st

    def save_fouling(self, doc: dict) -> None:
        statefiles.write_state(statefiles.FOULING_CALIBRATION, doc, self.dir)

    def save(self, name: str, doc: dict) -> None:
        statefiles.write_state(name, doc, self.dir)


class ModelAdvisor:
    """Measured-side processing, calibration and optimization for the gateway loop.

    cfg : the gateway configuration (plant dict loaded)
    store : the opened history store
    state_io : loads and saves the state documents (edge.statefiles)
    """

    def __init__(self, cfg: GatewayConfig, store: HistoryStore, state_io: Any) -> None:
        if cfg.plant is None:
            raise ValueError("the gateway configuration was loaded without its plant file")
        if cfg.aggregate_s < 1.0:
            raise StartupError(f"{cfg.path}: aggregate_s {cfg.aggregate_s:g} s: the history keeps "
                               "whole seconds; use at least 1 s")
        self.cfg = cfg
        self.store = store
        self.state_io = state_io
        try:
            self.base = PlantParams.from_dict(cfg.plant)
        except ParamError as exc:
            raise StartupError(f"{cfg.plant_file}: {exc}") from exc
        self.state = state_io.load_all()
        from edge.io.prices import PriceFileError, price_for_plant
        try:
            price = price_for_plant(self.base.extra, cfg.plant_file)
        except PriceFileError as exc:
            raise StartupError(f"{cfg.plant_file}: key 'cip.electricity_price_csv': {exc}") from exc
        try:
            self.spec = spec_from_config(self.base.extra, "fouling")
            self.chain = AnalysisChain(self.base, self.spec, ChainSettings.from_config(
                self.base.extra, cip_price=price, min_samples=int(cfg.min_window_samples),
                optimize=cfg.optimizer in ("model", "auto"), use_surrogate=cfg.optimizer == "auto"))
            self._watch = CipWatch(ReplaySettings.from_config(self.base.extra).cip_off_minutes)
            learner = (CompressorLearner.from_dict(self.state.compressors, self.base,
                                                   self.chain.s.learning)
                       if self.state.compressors is not None else None)
            self.cstate = self.chain.new_state(self.state.initial, self.state.dp_clean, learner)
        except (CalibrationError, LearningError, ReplayError, KeyError, TypeError, ValueError) as exc:
            raise StartupError(f"calibration state in {getattr(state_io, 'dir', '?')} or "
                               f"{cfg.plant_file}: {exc}") from exc
        self.cip_text: list[str] = []      # the last window's "when to clean", for the demo screen
        self._restore_chain(self.state.chain)
        self.fixed = self.cstate.fixed
        self.surrogate = self.state.surrogate   # model.surrogate.Surrogate or None
        if cfg.optimizer == "surrogate" and self.surrogate is None:
            raise StartupError(f"{cfg.path}: optimizer 'surrogate' but no surrogate.json in "
                               f"{getattr(state_io, 'dir', '?')} nor beside the config")
        # plausible ranges in canonical units (tags.yaml states them in each tag's own unit)
        self.ranges = {t.name: t.canonical_range for t in cfg.tags
                       if t.canonical_range is not None}
        self.window_s = cfg.calibration_window_h * 3600.0
        self._context: deque[dict] = deque(maxlen=CONTEXT_ROWS)
        self._context_loaded = False
        self._lock = threading.Lock()     # ingest and advise may overlap (two worker threads)
        # issue 9 item 8: a state document that could not be saved is kept and retried
        self._unsaved: dict | None = None
        self._state_fault: str | None = None
        self._state_log = RepeatLog(log, f"state directory {getattr(state_io, 'dir', '?')}")

    @property
    def has_calibration(self) -> bool:
        return self.state.fouling is not None

    @property
    def storage_fault(self) -> str | None:
        """Why the history or the state directory is not writable right now (None: both are)."""
        return self.store.fault or self._state_fault

    def _save_state(self, docs: dict[str, dict]) -> None:
        """Persist the chain's state documents; on failure keep them for a retry and report it
        (storage_fault), never raise: the advice is still written to the block."""
        pending = {**(self._unsaved or {}), **docs}
        for name in list(pending):
            try:
                if name == statefiles.FOULING_CALIBRATION:
                    self.state_io.save_fouling(pending[name])
                else:
                    self.state_io.save(name, pending[name])
            except (StateError, OSError) as exc:      # read-only, full disk, cannot create
                self._unsaved, self._state_fault = pending, str(exc)
                self._state_log.fail(f"state not persisted (kept in memory, retried with every "
                                     f"sample): {exc}")
                return
            del pending[name]
        self._unsaved, self._state_fault = None, None
        self._state_log.ok("state saved")

    def _save_fouling(self, doc: dict) -> None:
        self._save_state({statefiles.FOULING_CALIBRATION: doc})

    def _retry_storage(self) -> None:
        if self._unsaved:
            self._save_state({})

    def _restore_chain(self, doc: dict | None) -> None:
        """The previous window's hand-over (previous recommendation, condenser factor, LS set
        point, change-penalty parameters) from chain_state.json, and the surrogate tracker."""
        st = self.cstate
        if self.state.tracker is not None and st.tracker is not None:
            try:
                st.tracker = SurrogateTracker.from_dict(self.state.tracker, self.chain.s.tracker)
            except TrackerError as exc:     # the gateway's own result: start over, not fatal
                log.error("%s in %s: the surrogate tracker starts over", exc,
                          getattr(self.state_io, "dir", "?"))
        if not doc:
            return
        for key in ("last_rec_barg", "cond_factor", "T_out_sp_C"):
            v = doc.get(key)
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                setattr(st, key, float(v))
        turn = doc.get("cost_turn")
        if isinstance(turn, int) and not isinstance(turn, bool) and turn >= 0:
            st.cost_turn = turn
        prev = doc.get("fouling_previous")
        if isinstance(prev, dict):
            st.fouling_previous = prev
        fc = doc.get("forecast")
        if isinstance(fc, dict):      # issue 10: the forecast's memory since the last reset
            try:
                st.forecast = ForecastState.from_dict(fc)
            except CostError as exc:  # the gateway's own result: start the forecast afresh
                log.error("chain_state.json: %s; the fouling forecast starts afresh", exc)
        self._watch.restore(doc.get("cip_watch"))

    def _chain_doc(self) -> dict:
        st = self.cstate
        return {"last_rec_barg": st.last_rec_barg, "cond_factor": st.cond_factor,
                "T_out_sp_C": st.T_out_sp_C, "fouling_previous": st.fouling_previous,
                "forecast": st.forecast.to_dict(), "cost_turn": st.cost_turn,
                "cip_watch": self._watch.to_dict()}

    def _watch_cips(self, stored: list[dict]) -> None:
        """Issue 10: CIPs in the stored samples (``CipWatch``) reset the chain's forecast; the
        state is saved when a stop begins or a CIP ends (a restart in between keeps it)."""
        changed = False
        for rec in stored:
            down = str(rec.get("reason") or "").split(":")[0] in ("off", "cip")
            flag = rec.get("cip")
            flagged = isinstance(flag, (int, float)) and not isinstance(flag, bool) \
                and math.isfinite(flag) and flag > 0.5
            was = self._watch.down_since
            found = self._watch.feed(float(rec["ts"]), down, flagged)
            changed |= was is None and self._watch.down_since is not None
            if found is not None:
                start, end, kind = found
                if self.chain.cip(self.cstate, start, end, kind):
                    log.info("CIP %s .. %s (%s): the fouling forecast restarts", _iso(start), _iso(end),
                             kind)
                changed = True
        if changed:
            self._save_state({statefiles.CHAIN: self._chain_doc()})

    # ------------------------------------------------------------------------- ingest

    def ingest(self, samples: Sequence[Sample]) -> list[dict]:
        """Process and store closed samples (one transaction). Returns the stored rows."""
        if not samples:
            return []
        with self._lock:
            self._retry_storage()
            self._load_context()
            agg = self.cfg.aggregate_s
            rows: list[dict] = []
            prev_ts = self._context[-1]["ts"] if self._context else None
            context = list(self._context)
            for s in sorted(samples, key=lambda s: s.timestamp):
                ts = int(s.timestamp)
                if prev_ts is not None and ts - prev_ts > agg * GAP_PERIODS:
                    # a gap (gateway down, no PLC clock): whatever happened, treat it as a stop
                    context.append({"ts": ts - int(agg), "quality": "gap"})
                row = {"ts": ts, **sample_row(s)}
                rows.append(row)
                context.append(row)
                prev_ts = ts
            frame = pd.DataFrame(context).set_index("ts")
            frame = frame[~frame.index.duplicated(keep="last")]   # a clock that went back
            processed = measured.process(frame.drop(columns=["ts"], errors="ignore"), self.fixed,
                                         self.ranges)
            out = []
            for row in rows:
                p = processed.loc[row["ts"]]
                s = next(x for x in samples if int(x.timestamp) == row["ts"])
                rec = dict(row)
                rec.update({k: _py(v) for k, v in p.items()})
                rec.update(scans=s.scans, good_scans=s.good_scans,
                           bad=json.dumps(s.bad, sort_keys=True) if s.bad else "")
                out.append(rec)
            self.store.add_samples(out)
            for row in rows:
                self._context.append(row)
            self._watch_cips(out)
        return out

    def _load_context(self) -> None:
        if self._context_loaded:
            return
        self._context_loaded = True
        last = self.store.latest_sample_ts()
        if last is None:
            return
        df = self.store.window(last, CONTEXT_ROWS * self.cfg.aggregate_s, usable_only=False)
        keep = [t.name for t in self.cfg.tags] + ["quality"]
        for ts, rec in zip(df["ts"], df.to_dict("records")):
            self._context.append({"ts": int(ts), **{k: rec.get(k) for k in keep if k in rec}})

    # ------------------------------------------------------------------------- advise

    def advise(self, t_end: float) -> Advice:
        """One analysis window (``AnalysisChain.window``) on the usable samples ending at
        ``t_end`` (sample clock); afterwards the heap the window freed is handed back to the OS."""
        try:
            return self._advise(t_end)
        finally:
            release_heap()

    def _advise(self, t_end: float) -> Advice:
        t0 = time.perf_counter()
        window = self.store.window(t_end, self.window_s, usable_only=True)
        n = len(window)
        if n < self.cfg.min_window_samples:
            return Advice(t_end, skipped=True,
                          message=f"{n} usable samples in the last {self.cfg.calibration_window_h:g}"
                                  f" h, {self.cfg.min_window_samples} needed")
        with self._lock:
            reset = self.cstate.forecast.reset_s
            if reset is not None and len(window):        # no window reaches back across a CIP
                window = window[window["ts"].to_numpy(dtype=float) >= reset]
                if len(window) < self.cfg.min_window_samples:
                    return Advice(t_end, skipped=True,
                                  message=f"{len(window)} usable samples since the last CIP, "
                                          f"{self.cfg.min_window_samples} needed")
            res = self.chain.window(window, self.cstate)
            if "cip" in res.detail:
                self.cip_text = list(res.detail["cip"]["text"])
        detail = self._detail(res)
        if not res.calibration_ok:
            return self._record(Advice(t_end, calibration_ok=False, optimization_ok=False,
                                       message=res.status.removeprefix("failed: "), detail=detail))
        docs = {statefiles.FOULING_CALIBRATION: res.detail["calibration"],
                statefiles.CHAIN: self._chain_doc()}
        if self.cstate.learner is not None:
            docs[statefiles.COMPRESSORS] = self.cstate.learner.to_dict()
        if self.cstate.tracker is not None:
            docs[statefiles.SURROGATE_TRACKER] = self.cstate.tracker.to_dict()
        self._save_state(docs)          # disk full, read-only: kept, retried, storage_fault
        self.state.fouling = res.detail["calibration"]
        values = res.advisory_values()
        if self.cfg.optimizer == "surrogate":
            try:
                opt = self._optimize_surrogate(window, res.detail["adaptive_params"],
                                               self.base.ambient_pressure / 1e5)
            except (ValueError, ArithmeticError) as exc:   # OptimizationError, SurrogateError
                return self._record(Advice(t_end, values, optimization_ok=False,
                                           message=f"set-point optimization failed: {exc}",
                                           detail=detail))
            values.update(opt["values"])
            detail["optimization"] = opt["detail"]
            detail["run_time_s"] = time.perf_counter() - t0
            return self._record(Advice(t_end, values, detail=detail))
        detail["run_time_s"] = time.perf_counter() - t0
        if not res.optimization_ok:
            return self._record(Advice(t_end, values, optimization_ok=False,
                                       message=res.status.removeprefix("failed: "), detail=detail))
        return self._record(Advice(t_end, values, detail=detail,
                                   low_confidence=not res.advice_confident,
                                   message=res.advice_note))

    @staticmethod
    def _detail(res: WindowResult) -> dict:
        """The window's figures for the advice table (JSON; no model objects)."""
        row = {k: v for k, v in res.row().items() if isinstance(v, (int, float, str, bool))}
        d = {"window": row}
        for k in ("calibration", "advice", "cip"):
            if k in res.detail:
                d[k] = res.detail[k]
        return d

    def _optimize_surrogate(self, window: pd.DataFrame, adaptive: PlantParams, amb: float) -> dict:
        sur = self.surrogate
        if sur is None:
            raise OptimizationError("optimizer 'surrogate' configured but no surrogate is "
                                    "available (state directory or config/surrogate.json)")
        inputs = window[list(INPUT_COLUMNS)]
        cols = ("Q_sink_kW", "W_total_kW", "p_e_bar", "p_c_bar", "eta_is_LS", "eta_is_HS")
        ref = simulate_batch(inputs, adaptive, p_m_sp=sur.reference_p_m_sp_barg, columns=cols)
        ok = solved_mask(ref)
        if not ok.any():
            raise OptimizationError("the adaptive model solves none of the window's samples at "
                                    "the surrogate's reference set point")
        r = ref[ok]
        eta = float((r["eta_is_LS"] * r["eta_is_HS"]).mean())
        p_e, p_c = float(r["p_e_bar"].mean()), float(r["p_c_bar"].mean())
        p_m_opt, dcop_ref, dq_ref = sur.evaluate(eta, p_e, p_c)
        rec = p_m_opt - amb
        act = simulate_batch(inputs, adaptive, columns=cols)
        new = simulate_batch(inputs, adaptive, p_m_sp=rec, columns=cols)
        both = solved_mask(act) & solved_mask(new)
        if not both.any():
            raise OptimizationError(f"the adaptive model solves no sample at the recommended "
                                    f"set point {rec:.2f} bar(g)")
        cop_act = _ratio(act["Q_sink_kW"][both], act["W_total_kW"][both])
        cop_new = _ratio(new["Q_sink_kW"][both], new["W_total_kW"][both])
        q_act = float(act["Q_sink_kW"][both].mean())
        q_new = float(new["Q_sink_kW"][both].mean())
        pe_a = float(act["p_e_bar"][both].mean())
        pc_a = float(act["p_c_bar"][both].mean())
        values = {"p_m_sp_rec": rec, "dCOP_pct": 100.0 * (cop_new / cop_act - 1.0),
                  "dQ_sink_pct": 100.0 * (q_new / q_act - 1.0),
                  "p_m_gm": math.sqrt(pe_a * pc_a) - amb}
        detail = {"optimizer": "surrogate", "inputs": [eta, p_e, p_c], "p_m_opt_bar_a": p_m_opt,
                  "dCOP_vs_reference_pct": dcop_ref, "dQ_sink_vs_reference_pct": dq_ref,
                  "reference_p_m_sp_barg": sur.reference_p_m_sp_barg,
                  "n_samples": int(both.sum())}
        return {"values": values, "detail": detail}

    def _record(self, adv: Advice) -> Advice:
        rec: dict[str, Any] = {k: v for k, v in adv.values.items()}
        rec.update(ok=adv.ok, calibration_ok=adv.calibration_ok,
                   optimization_ok=adv.optimization_ok, message=adv.message,
                   low_confidence=adv.low_confidence, detail=dict(adv.detail))
        self.store.add_advice(adv.t, rec)
        return adv

    # ------------------------------------------------------------------------ restore

    def restored(self) -> Advice | None:
        last = self.store.latest_advice(ok_only=True)
        if last is None:
            return None
        skip = {"ts", "wall", "ok", "calibration_ok", "optimization_ok", "message", "detail",
                "low_confidence"}
        values = {k: v for k, v in last.items()
                  if k not in skip and isinstance(v, (int, float)) and v is not None}
        return Advice(float(last["ts"]), values, message="restored after restart",
                      low_confidence=bool(last.get("low_confidence")))


def _ratio(num, den) -> float:
    n = np.asarray(num, dtype=float)
    d = np.asarray(den, dtype=float)
    ok = np.isfinite(n) & np.isfinite(d)
    s = d[ok].sum()
    return float(n[ok].sum() / s) if s > 0 else math.nan


def _py(v: Any) -> Any:
    if isinstance(v, (np.bool_,)):
        return bool(v)
    if hasattr(v, "item"):
        return v.item()
    return v


def _iso(ts: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(float(ts)))


class SdNotify(Notifier):
    """systemd's notify protocol (``Type=notify``, ``WatchdogSec=``) without a dependency: one
    datagram per message to $NOTIFY_SOCKET. WATCHDOG=1 is sent at most every half watchdog
    interval, from the event loop after each completed cycle, so a hung loop gets the service
    restarted. Outside systemd (no NOTIFY_SOCKET) it does nothing."""

    def __init__(self, environ: dict | None = None) -> None:
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET")
        self._addr = ("\0" + addr[1:]) if addr and addr.startswith("@") else addr
        usec = env.get("WATCHDOG_USEC", "")
        self._every = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else None
        self._last = -math.inf

    def _send(self, msg: str) -> None:
        if not self._addr:
            return
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
                s.sendto(msg.encode(), self._addr)
        except OSError as exc:
            log.warning("systemd notification %r failed: %s", msg, exc)

    def ready(self) -> None:
        self._send("READY=1")

    def alive(self) -> None:
        if self._every is None:
            return
        now = time.monotonic()
        if now - self._last >= self._every:
            self._last = now
            self._send("WATCHDOG=1")

    def stopping(self) -> None:
        self._send("STOPPING=1")


class GatewayService:
    """Everything ``hp-edge run`` starts: history store, state, model advisor, gateway loop.

    Construction loads and checks state and plant (``StartupError``: exit code 2, nothing
    connected). A history that is locked, full or not writable does not stop the start: the
    store runs without it and retries (``storage_fault``). ``await run()`` runs the gateway until
    stopped and closes the store. ``clock``: the sample-clock limits
    (``edge.sampleclock.ClockPolicy``; default limits when None).
    """

    def __init__(self, cfg: GatewayConfig, *, time_source: str = "wall",
                 install_signals: bool = True, plc=None, shutdown_timeout_s: float = 10.0,
                 clock=None) -> None:
        state = StateDir(cfg.state_dir, cfg.path.parent / statefiles.SURROGATE)
        self.store = HistoryStore(cfg.history_db, cfg.history_retention_days,
                                  aggregate_s=cfg.aggregate_s)
        try:
            try:
                self.store.open()
            except (OSError, sqlite3.Error) as exc:
                raise StartupError(f"history {cfg.history_db}: {exc}") from exc
            self.advisor = ModelAdvisor(cfg, self.store, state)
            self.publisher, self.health = _northbound(cfg)
            self.gateway = Gateway(cfg, self.advisor, plc=plc, time_source=time_source,
                                   install_signals=install_signals,
                                   shutdown_timeout_s=shutdown_timeout_s, notifier=SdNotify(),
                                   required_tags=measured.REQUIRED, clock=clock,
                                   observers=[o for o in (self.health, self.publisher) if o],
                                   audit=self.store.add_closed_loop_event)
        except BaseException:
            self.store.close()
            raise

    async def run(self) -> int:
        try:
            return await self.gateway.run()
        finally:
            self.store.close()


def _northbound(cfg: GatewayConfig) -> tuple[Any, Any]:
    """The MQTT publisher and the health endpoint when gateway.yaml enables them (issue 14),
    else None. paho-mqtt and the Sparkplug codec are imported only here, and only when the
    publisher is enabled (the optional extra 'northbound')."""
    nb = cfg.northbound
    publisher = health = None
    if nb is not None and nb.mqtt_enabled:
        try:
            from edge.northbound.publisher import MqttPublisher
        except ImportError as exc:
            raise StartupError(f"{cfg.path}: northbound.mqtt is enabled but its libraries are "
                               f"missing ({exc}); install them with pip install "
                               "'hp-edge[northbound]'") from exc
        publisher = MqttPublisher(nb.mqtt, cfg)
    else:   # a publisher switched off leaves no queue growing in the history
        from edge.northbound.outbox import detach
        detach(cfg.history_db)
    if nb is not None and nb.health_enabled:
        from edge.health import HealthServer
        health = HealthServer(nb.health, publisher=publisher)
    return publisher, health
