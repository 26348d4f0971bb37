"""The model side of the gateway: measured-side processing, history, state, and one calibration
cycle (fouling calibration -> set-point optimization -> advisory values).

``ModelAdvisor`` is what ``edge.loop.Gateway`` calls from worker threads:

* ``ingest(samples)`` - closed one-minute samples -> ``model.measured.process`` (with the rows
  before them as context, so ramps after a start or a gap are recognised) -> the history store;
* ``advise(t_end)`` - the usable window ending at ``t_end`` -> fouling calibration of the fixed
  model (``model.calibration``) -> the adaptive model -> set-point optimization (adaptive model or
  surrogate) -> the advisory values of SPEC 7.3, stored in the history and the fouling state file;
* ``restored()`` - the last good advice after a restart.

The fixed model is plant.yaml plus the initial calibration and the clean pressure-drop fit from the
state directory when they exist; the adaptive model adds the latest fouling calibration.
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
from edge.statefiles import StateError
from edge.store import HistoryStore
from model import measured
from model.batch import INPUT_COLUMNS, simulate_batch, solved_mask
from model.calibration import (CalibrationError, CalibrationResult, apply_state, calibrate,
                               evaporator_share, spec_from_config)
from model.optimize import OptimizationError, optimize_setpoint
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
        try:
            st.fouling = statefiles.read_state(statefiles.FOULING_CALIBRATION, self.dir)
        except StateError as exc:
            log.error("%s; starting without a fouling calibration", exc)
        for name, doc in (("initial calibration", st.initial), ("dp_clean fit", st.dp_clean),
                          ("fouling calibration", st.fouling)):
            if doc is not None:
                log.info("state: %s of %s loaded", name, doc.get("saved_at", "?"))
        if st.initial is None:
            log.warning("state: no %s in %s: the fixed model is the data sheet (plant.yaml); "
                        "commission with 'hp-edge calibrate initial'",
                        statefiles.INITIAL_CALIBRATION, self.dir)
        return st

    def save_fouling(self, doc: dict) -> None:
        statefiles.write_state(statefiles.FOULING_CALIBRATION, doc, self.dir)


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
        try:
            self.fixed = apply_state(self.base, self.state.initial, self.state.dp_clean)
            self.spec = spec_from_config(self.base.extra, "fouling")
        except (CalibrationError, KeyError, TypeError, ValueError) as exc:
            raise StartupError(f"calibration state in {getattr(state_io, 'dir', '?')} or "
                               f"{cfg.plant_file}: {exc}") from exc
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

    @property
    def has_calibration(self) -> bool:
        return self.state.fouling is not None

    # ------------------------------------------------------------------------- ingest

    def ingest(self, samples: Sequence[Sample]) -> list[dict]:
        """Process and store closed samples (one transaction). Returns the stored rows."""
        if not samples:
            return []
        with self._lock:
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
        """One calibration cycle on the usable window ending at ``t_end`` (sample clock)."""
        t0 = time.perf_counter()
        window = self.store.window(t_end, self.window_s, usable_only=True)
        n = len(window)
        if n < self.cfg.min_window_samples:
            return Advice(t_end, skipped=True,
                          message=f"{n} usable samples in the last {self.cfg.calibration_window_h:g}"
                                  f" h, {self.cfg.min_window_samples} needed")
        previous = self.state.fouling["params"] if self.state.fouling else None
        span = (_iso(window["ts"].iloc[0]), _iso(window["ts"].iloc[-1]))
        try:
            result = calibrate(window, self.fixed, self.spec, previous=previous, window=span)
        except (CalibrationError, ValueError, ArithmeticError) as exc:
            return self._record(Advice(t_end, calibration_ok=False, optimization_ok=False,
                                       message=f"fouling calibration failed: {exc}"))
        if not result.success or not all(math.isfinite(v) for v in result.params.values()):
            return self._record(Advice(t_end, calibration_ok=False, optimization_ok=False,
                                       message=f"fouling calibration failed: {result.message}",
                                       detail={"calibration": result.to_dict()}))
        doc = result.to_dict()
        try:
            self.state_io.save_fouling(doc)
        except StateError as exc:      # disk full, read-only: keep going, say so
            log.error("fouling calibration not persisted: %s", exc)
        self.state.fouling = doc
        adaptive = result.apply(self.fixed)
        values, detail = self._fouling_values(window, result, adaptive)
        detail["calibration"] = doc
        try:
            opt = self._optimize(window, adaptive)
        except (ValueError, ArithmeticError) as exc:   # OptimizationError, SurrogateError
            return self._record(Advice(t_end, values, optimization_ok=False,
                                       message=f"set-point optimization failed: {exc}",
                                       detail=detail))
        values.update(opt["values"])
        detail["optimization"] = opt["detail"]
        detail["run_time_s"] = time.perf_counter() - t0
        return self._record(Advice(t_end, values, detail=detail))

    def _fouling_values(self, window: pd.DataFrame, result: CalibrationResult,
                        adaptive: PlantParams) -> tuple[dict, dict]:
        V = float(np.nanmean(window["V_source"].to_numpy(dtype=float)))
        dp_clean_bar = float(adaptive.dp_clean(V / 3600.0)) / 1e5
        cop_meas = _ratio(window["Q_sink_kW"], window["W_total_kW"])
        inputs = window[list(INPUT_COLUMNS)]
        sim_a = simulate_batch(inputs, adaptive, columns=("Q_sink_kW", "W_total_kW", "COP"))
        sim_f = simulate_batch(inputs, self.fixed, columns=("Q_sink_kW", "W_total_kW", "COP"))
        both = solved_mask(sim_a) & solved_mask(sim_f)
        values = {
            "R_th_f": result.params["R_th_f_K_per_kW"],
            "R_th_f_share": 100.0 * evaporator_share(adaptive),
            "CF_dp_f": result.params["CF_dp_f"],
            "dp_fouling": (result.params["CF_dp_f"] - 1.0) * dp_clean_bar,
            "nrmse_pct": 100.0 * result.objective,
            "COP_measured": cop_meas,
            "COP_adaptive": _ratio(sim_a["Q_sink_kW"][both], sim_a["W_total_kW"][both]),
            "COP_fixed": _ratio(sim_f["Q_sink_kW"][both], sim_f["W_total_kW"][both]),
        }
        detail = {"n_samples": int(len(window)), "n_solved_both": int(both.sum()),
                  "V_source_mean_m3h": V}
        return values, detail

    def _optimize(self, window: pd.DataFrame, adaptive: PlantParams) -> dict:
        """Recommended set point and its expected effect against the window's actual set point.

        ``optimizer: model`` - ``model.optimize.optimize_setpoint`` on the adaptive model.
        ``optimizer: surrogate`` - the 27-term polynomial gives the optimal p_m from the adaptive
        model's state at the surrogate's reference set point (window means); the expected COP and
        heat-output changes are then those of the adaptive model at that set point against the
        actual one (two window simulations), so both optimizers report the same quantity.
        Raises OptimizationError / SurrogateError (ValueError) when there is no answer.
        """
        amb = adaptive.ambient_pressure / 1e5
        if self.cfg.optimizer == "surrogate":
            return self._optimize_surrogate(window, adaptive, amb)
        r = optimize_setpoint(window, adaptive)
        values = {"p_m_sp_rec": r.p_m_sp_opt_barg, "dCOP_pct": r.dCOP_opt_pct,
                  "dQ_sink_pct": r.dQ_sink_opt_pct, "p_m_gm": r.p_m_gm_bar_a - amb}
        return {"values": values, "detail": {"optimizer": "model", **r.to_dict()}}

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
                   detail=dict(adv.detail))
        self.store.add_advice(adv.t, rec)
        return adv

    # ------------------------------------------------------------------------ restore

    def restored(self) -> Advice | None:
        last = self.store.latest_advice(ok_only=True)
        if last is None:
            return None
        skip = {"ts", "wall", "ok", "calibration_ok", "optimization_ok", "message", "detail"}
        values = {k: v for k, v in last.items()
                  if k not in skip and isinstance(v, (int, float)) and v is not None}
        return Advice(float(last["ts"]), values, message="restored after restart")


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
    connected). ``await run()`` runs the gateway until stopped and closes the store.
    """

    def __init__(self, cfg: GatewayConfig, *, time_source: str = "wall",
                 install_signals: bool = True, plc=None, shutdown_timeout_s: float = 10.0) -> None:
        state = StateDir(cfg.state_dir, cfg.path.parent / statefiles.SURROGATE)
        self.store = HistoryStore(cfg.history_db, cfg.history_retention_days,
                                  aggregate_s=cfg.aggregate_s)
        try:
            try:
                self.store.open()
            except (OSError, sqlite3.Error) as exc:
                raise StartupError(f"history {cfg.history_db}: {exc}") from exc
            self.advisor = ModelAdvisor(cfg, self.store, state)
            self.gateway = Gateway(cfg, self.advisor, plc=plc, time_source=time_source,
                                   install_signals=install_signals,
                                   shutdown_timeout_s=shutdown_timeout_s, notifier=SdNotify())
        except BaseException:
            self.store.close()
            raise

    async def run(self) -> int:
        try:
            return await self.gateway.run()
        finally:
            self.store.close()
