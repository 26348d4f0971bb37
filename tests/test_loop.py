"""The gateway loop against a fake PLC and a fake advisor: one FC16 write per cycle, status bits,
last good advice kept on failure, calibration off the event loop, signals and shutdown."""
from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from edge.advisory import decode_advisory
from edge.config import load_config
from edge.loop import Advice, Gateway
from edge.plc import PlcCommError, ReadResult, TagValue
from edge.sampleclock import ClockPolicy

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def cfg():
    c = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
    return replace(c, scan_interval_s=0.02, calibration_interval_s=300.0)


GOOD = {"T_sink_in": 40.0, "T_sink_out": 68.0, "T_source_in": 24.0, "T_source_out": 18.0,
        "V_sink": 62.0, "V_source": 192.0, "p_source_in": 2.5, "p_source_out": 2.05,
        "T_suc_LS": 16.0, "T_dis_LS": 80.0, "T_suc_HS": 40.0, "T_dis_HS": 100.0, "T_c": 65.0,
        "T_e": 15.0, "p_suc_LS": 6.3, "p_dis_LS": 15.0, "p_suc_HS": 15.0, "p_dis_HS": 29.0,
        "W_LS": 170.0, "W_HS": 180.0, "N_LS": 1300.0, "N_HS": 1400.0, "running": 1.0,
        "cip": 0.0, "p_m_sp": 16.0}


FLAGS = ("running", "cip")
T0 = 1_709_251_200.0


class FakePlc:
    """Plays the PLC: every read advances a fake clock by one minute of plant time. Measured
    values move by a few resolution steps from read to read, as a live sensor does (so the
    flat-line check sees no stuck sensor); ``next_clock`` replaces the clock register of the
    next reads (a corrupt or glitched read)."""

    def __init__(self, cfg, t0: float = T0, step: float = 60.0):
        self.plc, self.advisory = cfg.plc, cfg.advisory
        self.step = step
        self.tags = cfg.tags
        self.t = t0
        self.life = 0
        self.connected = True
        self.fail_reads = 0          # the next n reads get no answer
        self.frozen = False
        self.override: dict[str, TagValue] = {}
        self.next_clock: list[float] = []
        self.writes: list[list[int]] = []
        self.closed = False

    async def read_all(self) -> ReadResult:
        self.t += self.step
        if self.fail_reads:
            self.fail_reads -= 1
            self.connected = False
            vals = {t.name: TagValue(t.name, None, "connection lost") for t in self.tags}
            return ReadResult(vals, self.t, 0.0, 1, "connection lost")
        self.connected = True
        if not self.frozen:
            self.life += 1
        jitter = 0.1 * (self.life % 3)
        vals = {n: TagValue(n, v if n in FLAGS else v + jitter) for n, v in GOOD.items()}
        vals["plc_clock"] = TagValue("plc_clock", self.next_clock.pop(0) if self.next_clock
                                     else self.t)
        vals["life_counter"] = TagValue("life_counter", float(self.life))
        vals.update(self.override)
        return ReadResult(vals, self.t, 0.0, 2, None)

    async def write_advisory(self, words):
        if not self.connected:
            raise PlcCommError("not connected")
        assert len(words) == self.advisory.size
        self.writes.append(list(words))

    async def close(self):
        self.closed = True

    def last(self) -> dict:
        return decode_advisory(self.advisory, self.writes[-1])


class FakeAdvisor:
    def __init__(self, outcomes=(), delay_s: float = 0.0, calibrated: bool = False):
        self.outcomes = list(outcomes)
        self.delay_s = delay_s
        self.ingested = []
        self.calls = []
        self.threads = set()
        self._calibrated = calibrated

    def ingest(self, samples):
        self.threads.add(threading.current_thread().name)
        self.ingested.extend(samples)
        return []

    def advise(self, t_end):
        self.threads.add(threading.current_thread().name)
        self.calls.append(t_end)
        if self.delay_s:
            time.sleep(self.delay_s)
        out = self.outcomes.pop(0) if self.outcomes else "skip"
        if out == "ok":
            self._calibrated = True
            return Advice(t_end, {"R_th_f": 3e-3, "p_m_sp_rec": 17.5, "CF_dp_f": 1.1})
        if out == "calibration":
            return Advice(t_end, calibration_ok=False, optimization_ok=False, message="boom")
        if out == "optimization":
            return Advice(t_end, {"R_th_f": 9e-3}, optimization_ok=False, message="no optimum")
        if out == "skip":
            return Advice(t_end, skipped=True, message="too few samples")
        raise RuntimeError("solver bug")

    def restored(self):
        return None

    @property
    def has_calibration(self):
        return self._calibrated


def gateway(cfg, advisor=None, **kw):
    plc = kw.pop("plc", None) or FakePlc(cfg)
    gw = Gateway(cfg, advisor or FakeAdvisor(), plc=plc, time_source="plc",
                 install_signals=False, **kw)
    return gw, plc


async def cycles(gw, n):
    for _ in range(n):
        await gw.cycle()
        await asyncio.sleep(0)


def run(coro, timeout=20.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def test_one_whole_block_write_per_cycle_and_heartbeat(cfg):
    async def go():
        gw, plc = gateway(cfg)
        await gw.startup()
        await cycles(gw, 5)
        await gw.shutdown()
        return gw, plc
    gw, plc = run(go())
    assert len(plc.writes) == 5 and all(len(w) == cfg.advisory.size for w in plc.writes)
    beats = [decode_advisory(cfg.advisory, w)["heartbeat"] for w in plc.writes]
    assert beats == [1, 2, 3, 4, 5]
    assert plc.closed
    first = plc.last()
    assert "calibration_failed" in first["status_bits"]      # none yet
    assert first["R_th_f"] != first["R_th_f"]                 # NaN: no value yet


def test_advice_written_in_the_cycle_it_arrives_and_age_counts(cfg):
    async def go():
        adv = FakeAdvisor(["ok"])
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        for _ in range(30):
            await cycles(gw, 1)
            if adv.calls:
                break
        await asyncio.sleep(0.05)          # the worker thread returns
        await cycles(gw, 1)
        got = plc.last()
        await cycles(gw, 2)
        later = plc.last()
        await gw.shutdown()
        return adv, got, later
    adv, got, later = run(go())
    assert got["R_th_f"] == pytest.approx(3e-3) and got["p_m_sp_rec"] == pytest.approx(17.5)
    assert got["last_update"] == int(adv.calls[0])
    assert "calibration_failed" not in got["status_bits"]
    assert later["advice_age_s"] - got["advice_age_s"] == 120       # two plant minutes later
    assert "hp-edge-calibration_0" in adv.threads


async def _advise_until(gw, plc, adv, n_calls):
    for _ in range(2000):
        await cycles(gw, 1)
        if len(adv.calls) >= n_calls and gw._calibration is None:
            return
        await asyncio.sleep(0.001)
    raise AssertionError("calibration did not run")


def test_failed_calibration_keeps_last_good_advice_and_sets_bits(cfg):
    async def go():
        adv = FakeAdvisor(["ok", "calibration", "optimization", "crash"])
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        out = []
        for k in range(1, 5):
            await _advise_until(gw, plc, adv, k)
            out.append(plc.last())
        await gw.shutdown()
        return gw, out
    gw, (ok, cal, opt, crash) = run(go())
    assert ok["R_th_f"] == pytest.approx(3e-3) and ok["status_bits"] == []
    assert cal["R_th_f"] == pytest.approx(3e-3)          # kept
    assert {"calibration_failed", "advice_stale"} <= set(cal["status_bits"])
    assert cal["advice_age_s"] > 0
    assert opt["R_th_f"] == pytest.approx(3e-3)          # all or nothing: the 9e-3 is not shown
    assert {"model_infeasible", "advice_stale"} <= set(opt["status_bits"])
    assert "calibration_failed" not in opt["status_bits"]
    assert {"calibration_failed", "advice_stale"} <= set(crash["status_bits"])
    assert gw.snapshot.errors == 1


def test_skipped_calibration_is_not_a_failure_and_retries_next_sample(cfg):
    async def go():
        adv = FakeAdvisor(["skip", "skip", "ok"])
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        await _advise_until(gw, plc, adv, 3)
        await gw.shutdown()
        return adv, plc
    adv, plc = run(go())
    assert adv.calls[1] - adv.calls[0] <= 120      # retried on the next samples, not an interval
    assert plc.last()["R_th_f"] == pytest.approx(3e-3)


def test_comm_fault_is_shown_after_the_link_is_back(cfg):
    async def go():
        gw, plc = gateway(cfg)
        await gw.startup()
        await cycles(gw, 2)
        plc.fail_reads = 3
        await cycles(gw, 3)
        n_during = len(plc.writes)
        await cycles(gw, 1)
        back = plc.last()
        await cycles(gw, 1)
        after = plc.last()
        await gw.shutdown()
        return n_during, back, after
    n_during, back, after = run(go())
    assert n_during == 2                                  # nothing written while down
    assert "comm_fault" in back["status_bits"] and back["heartbeat"] == 6
    assert "comm_fault" not in after["status_bits"]


def test_frozen_life_counter_sets_stale_and_no_samples_come_from_it(cfg):
    fast = replace(cfg, tags=tuple(replace(t, max_age_s=0.05) for t in cfg.tags))

    async def go():
        adv = FakeAdvisor()
        gw, plc = gateway(fast, adv)
        await gw.startup()
        await cycles(gw, 3)
        n0 = len(adv.ingested)
        plc.frozen = True
        plc.override = {"T_source_in": TagValue("T_source_in", 49.0)}   # frozen garbage
        for _ in range(10):
            await cycles(gw, 1)
            await asyncio.sleep(0.01)
        frozen = plc.last()
        got = adv.ingested[n0:]
        plc.frozen, plc.override = False, {}
        await cycles(gw, 3)
        await gw.shutdown()
        return frozen, got, plc.last()
    frozen, got, after = run(go())
    assert "data_stale" in frozen["status_bits"]
    assert all(s.values["T_source_in"] != 49.0 for s in got)
    assert all(s.quality == "frozen" for s in got[1:])
    assert "data_stale" not in after["status_bits"]


def test_bad_values_flags_off_and_cip(cfg):
    async def go():
        gw, plc = gateway(cfg)
        await gw.startup()
        plc.override = {"running": TagValue("running", 0.0), "cip": TagValue("cip", 1.0),
                        "T_e": TagValue("T_e", None, "nan")}
        await cycles(gw, 2)
        await gw.shutdown()
        return plc.last()
    last = run(go())
    assert {"heat_pump_off", "cip_detected"} <= set(last["status_bits"])


def test_heat_pump_off_is_inferred_from_power_without_a_running_flag(cfg):
    async def go():
        gw, plc = gateway(cfg)
        await gw.startup()
        plc.override = {"running": TagValue("running", None, "timeout"),
                        "W_LS": TagValue("W_LS", 0.0), "W_HS": TagValue("W_HS", 3.0)}
        await cycles(gw, 1)
        off = plc.last()
        plc.override = {"running": TagValue("running", None, "timeout")}
        await cycles(gw, 1)
        await gw.shutdown()
        return off, plc.last()
    off, on = run(go())
    assert "heat_pump_off" in off["status_bits"] and "heat_pump_off" not in on["status_bits"]


def test_calibration_never_blocks_the_event_loop(cfg):
    async def go():
        adv = FakeAdvisor(["ok"], delay_s=0.5)
        gw, plc = gateway(cfg, adv)
        task = asyncio.create_task(gw.run())
        await gw.wait_until(lambda s: bool(adv.calls), 5.0)
        hb0 = gw.snapshot.heartbeat
        await gw.wait_until(lambda s: s.heartbeat >= hb0 + 5, 0.45)   # while the solver runs
        assert gw._calibration is not None and not gw._calibration.done()
        await gw.wait_until(lambda s: s.calibrations == 1, 5.0)
        gw.request_stop()
        return await task
    assert run(go()) == 0


def test_finished_calibration_is_written_without_waiting_for_the_next_slot(cfg):
    slow = replace(cfg, scan_interval_s=2.0)

    async def go():
        adv = FakeAdvisor(["ok"])
        gw, plc = gateway(slow, adv)
        task = asyncio.create_task(gw.run())
        # cycle 1 at 0 s (scan pending), cycle 2 at 2 s closes a sample and starts the
        # calibration; its advice is written by a woken cycle long before the 4-s slot
        snap = await gw.wait_until(lambda s: s.advice_time is not None and s.writes_ok >= 3, 3.5)
        gw.request_stop()
        await task
        return snap.writes_ok, plc.writes
    n, writes = run(go())
    assert decode_advisory(cfg.advisory, writes[2])["R_th_f"] == pytest.approx(3e-3)


def test_sigterm_stops_gracefully_and_restores_the_previous_handler(cfg):
    seen = []

    def previous(signum, frame):
        seen.append(signum)

    async def go():
        gw, plc = gateway(cfg)
        gw.install_signals = True
        task = asyncio.create_task(gw.run())
        await gw.wait_until(lambda s: s.heartbeat >= 3, 5.0)
        os.kill(os.getpid(), signal.SIGTERM)
        return await task, plc

    old = signal.signal(signal.SIGTERM, previous)
    try:
        rc, plc = run(go())
        assert rc == 0 and plc.closed
        assert signal.getsignal(signal.SIGTERM) is previous
        assert seen == []          # our handler took it, not the previous one
    finally:
        signal.signal(signal.SIGTERM, old)


def test_shutdown_does_not_wait_forever_for_a_stuck_solver(cfg):
    async def go():
        adv = FakeAdvisor(["ok"], delay_s=1.0)
        gw, plc = gateway(cfg, adv, shutdown_timeout_s=0.05)
        task = asyncio.create_task(gw.run())
        await gw.wait_until(lambda s: bool(adv.calls), 5.0)
        gw.request_stop()
        return await asyncio.wait_for(task, 0.8), plc
    rc, plc = run(go())
    assert rc == 0 and plc.closed


def test_arguments_are_checked(cfg):
    with pytest.raises(ValueError):
        Gateway(cfg, FakeAdvisor(), plc=FakePlc(cfg), time_source="sundial")


def test_systemd_notifications_ready_watchdog_stopping(cfg, tmp_path):
    import socket

    from edge.service import SdNotify

    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    try:
        notifier = SdNotify({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1"})

        async def go():
            gw, plc = gateway(cfg, notifier=notifier)
            await gw.startup()
            await cycles(gw, 2)
            await gw.shutdown()
        run(go())
        got = [sock.recv(64).decode() for _ in range(4)]
    finally:
        sock.close()
    assert got == ["READY=1", "WATCHDOG=1", "WATCHDOG=1", "STOPPING=1"]
    SdNotify({}).ready()          # outside systemd: nothing, no error


# ------------------------------------------------------------------ the model side (ModelAdvisor)

ADVICE_FIELDS = {"p_m_sp_rec", "dCOP_pct", "dQ_sink_pct", "p_m_gm", "R_th_f", "R_th_f_share",
                 "CF_dp_f", "dp_fouling", "COP_measured", "COP_adaptive", "COP_fixed", "nrmse_pct"}


@pytest.fixture(scope="module")
def plant_minutes():
    """2.2 h of the simulator's plant as one-minute samples (what the aggregator would emit)."""
    import math as _m

    from edge.aggregate import Sample
    from simulator.export import export_history

    hist = export_history(2.2 / 24).history
    out = []
    for rec in hist.to_dict("records"):
        ts = pd_ts(rec.pop("timestamp"))
        vals = {k: float(v) for k, v in rec.items()}
        bad = {k: "nan" for k, v in vals.items() if not _m.isfinite(v)}
        out.append(Sample(ts, vals, bad, 12, 12, 0, 0, ""))
    return out


def pd_ts(text: str) -> float:
    from datetime import datetime
    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def advisor_for(tmp_path, **kw):
    from edge.service import ModelAdvisor, StateDir
    from edge.store import HistoryStore

    full = load_config(ROOT / "config" / "gateway.yaml")
    c = replace(full, state_dir=tmp_path / "state", history_db=tmp_path / "h.sqlite", **kw)
    store = HistoryStore(c.history_db, c.history_retention_days).open()
    try:
        return ModelAdvisor(c, store, StateDir(c.state_dir, ROOT / "config" / "surrogate.json")), store
    except BaseException:
        store.close()
        raise


@pytest.mark.parametrize("optimizer", ["model", "auto", "surrogate"])
def test_model_advisor_ingests_calibrates_optimizes_and_restores(plant_minutes, tmp_path,
                                                                 optimizer):
    adv, store = advisor_for(tmp_path, optimizer=optimizer)
    try:
        assert not adv.has_calibration
        for k in range(0, len(plant_minutes), 7):        # the loop hands over a few at a time
            adv.ingest(plant_minutes[k:k + 7])
        assert store.count() == len(plant_minutes)
        t_end = plant_minutes[-1].timestamp + 60
        few = adv.advise(plant_minutes[20].timestamp)
        assert few.skipped and "usable samples" in few.message
        a = adv.advise(t_end)
        assert a.ok, a.message
        assert ADVICE_FIELDS <= set(a.values)
        assert all(math.isfinite(a.values[k]) for k in ADVICE_FIELDS)
        assert 1.5e-3 < a.values["R_th_f"] < 4e-3 and a.values["CF_dp_f"] >= 1.0
        if optimizer == "surrogate":
            assert a.detail["optimization"]["optimizer"] == "surrogate"
        else:    # the chain's advice: uncertainty, confidence and the window's figures
            assert set(a.values) == ADVICE_FIELDS | {"dCOP_sd_pct", "eta_is_LS_drift", "eta_is_HS_drift",
                                                     "fouling_rate", "R_th_f_forecast", "days_to_cip",
                                                     "fouling_cost", "fouling_cost_cum"}
            # one window since the reset: a cost of fouling, but no forecast and no plan yet
            assert a.values["fouling_cost"] > 0 and a.values["fouling_cost_cum"] > 0
            assert all(math.isnan(a.values[k]) for k in ("fouling_rate", "R_th_f_forecast", "days_to_cip"))
            assert a.detail["cip"]["text"][0].startswith("no fouling forecast yet (R_th_f: not enough data")
            assert a.detail["advice"]["p_m_sp_rec_barg"] == a.values["p_m_sp_rec"]
            assert a.low_confidence == (not a.detail["advice"]["confident"])
            assert a.detail["window"]["status"] == "ok"
            # 2 h of data at one set point: the curves cannot show where the optimum lies yet
            assert a.low_confidence and a.values["p_m_sp_rec"] == pytest.approx(16.0, abs=0.01)
            assert (tmp_path / "state" / "compressors.json").exists()
            assert (tmp_path / "state" / "chain_state.json").exists()
            assert a.detail["window"]["optimizer"] == "search"
            # the tracker runs (and is saved) with optimizer: auto only
            assert (tmp_path / "state" / "surrogate_tracker.json").exists() == (optimizer == "auto")
        assert adv.has_calibration and (tmp_path / "state" / "fouling_calibration.json").exists()
    finally:
        store.close()
    again, store = advisor_for(tmp_path, optimizer=optimizer)
    try:
        r = again.restored()
        assert again.has_calibration
        assert r.t == t_end and r.values["R_th_f"] == pytest.approx(a.values["R_th_f"])
    finally:
        store.close()


def _qualified_tracker_doc(p_m_opt_bar_a: float) -> dict:
    """A tracker whose forms qualified on rows spanning any plausible operation, with the optimum
    at p_m_opt_bar_a +- 0.03 bar (what the gateway then must take in place of its search)."""
    from model.analysis.surrogate_tracker import SurrogateTracker, TrackerSettings
    rng = np.random.default_rng(11)
    rows = []
    for i in range(100):
        p_c = rng.uniform(10.0, 70.0)
        rows.append({"eta_is_product": rng.uniform(0.2, 0.95), "p_e_bar_a": rng.uniform(1.0, 12.0),
                     "p_c_bar_a": p_c, "V_sink_m3h": rng.uniform(5.0, 400.0),
                     "T_sink_in_C": rng.uniform(5.0, 95.0), "p_m_opt_bar_a": p_m_opt_bar_a + 1e-3 * (p_c - 40.0),
                     "dCOP_pct": 1.0 + 0.01 * p_c, "t": 3600.0 * i})
    tr = SurrogateTracker(TrackerSettings())
    tr.add(rows)
    tr.refit()
    assert tr.qualified is not None
    return tr.to_dict()


def test_auto_optimizer_takes_the_qualified_surrogate_and_keeps_learning(plant_minutes, tmp_path):
    """optimizer: auto: with a qualified tracker in the state directory the window's optimum is the
    surrogate's (here a constant 14 bar a, 12.99 bar(g)), the rest of the advice is the chain's,
    and the tracker (with this window's row) is saved for the next start."""
    from edge import statefiles
    statefiles.write_state(statefiles.SURROGATE_TRACKER, _qualified_tracker_doc(14.0), tmp_path / "state")
    adv, store = advisor_for(tmp_path, optimizer="auto")
    try:
        adv.ingest(plant_minutes)
        a = adv.advise(plant_minutes[-1].timestamp + 60)
        assert a.ok, a.message
        w = a.detail["window"]
        assert w["optimizer"] == "surrogate:extended"
        amb = adv.base.ambient_pressure / 1e5
        assert a.detail["advice"]["p_m_sp_model_opt_barg"] == pytest.approx(14.0 - amb, abs=0.03) \
            or a.detail["advice"]["hs_saturated"]
        assert a.low_confidence == (not a.detail["advice"]["confident"])
        doc = json.loads((tmp_path / "state" / "surrogate_tracker.json").read_text())
        assert len(doc["rows"]) == 100         # qualified: rows only every qualified_every-th window
        assert doc["windows"] == 1
    finally:
        store.close()


def test_unreadable_commissioning_state_stops_the_start(tmp_path):
    from edge.service import StartupError

    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "initial_calibration.json").write_text("{ torn")
    with pytest.raises(StartupError, match="initial_calibration.json"):
        advisor_for(tmp_path)


def test_a_failing_cycle_is_logged_and_ten_in_a_row_exit_1(cfg):
    class Broken(FakePlc):
        async def read_all(self):
            raise KeyError("bug")

    async def go():
        gw, plc = gateway(cfg, plc=Broken(cfg))
        return await gw.run(), gw
    rc, gw = run(go())
    assert rc == 1 and gw.snapshot.errors == 10


def test_a_clock_set_back_is_rejected_then_accepted_as_a_correction(cfg):
    """Going back 10 h: rejected (clock_fault) until the new clock persisted (here 3 reads),
    then accepted; the advice is then from the "future": advice_stale and an unknown age
    (4294967295), never age 0; calibration restarts on the new clock."""
    async def go():
        adv = FakeAdvisor(["ok", "ok"])
        gw, plc = gateway(cfg, adv, clock=ClockPolicy(confirm_s=0.0, confirm_reads=3))
        await gw.startup()
        await _advise_until(gw, plc, adv, 1)
        await cycles(gw, 1)
        plc.t -= 10 * 3600.0                 # PLC clock reset / a fresh simulator
        await cycles(gw, 3)
        blocks = [list(w) for w in plc.writes[-3:]]
        await _advise_until(gw, plc, adv, 2)
        await gw.shutdown()
        return adv.calls, blocks, gw.snapshot
    calls, (rej1, rej2, accepted), snap = run(go())
    assert rej1[1] == rej2[1] == 0x0200                      # clock_fault, the advice is fine
    assert accepted[1] == 0x0040                             # advice_stale: from the "future"
    assert accepted[28:30] == [0xFFFF, 0xFFFF]               # its age is unknown, not 0
    assert calls[1] < calls[0] - 9 * 3600.0                   # calibrated on the new clock
    assert snap.clock_rejected == 2 and snap.clock_jumps == 1


def test_rejected_clock_readings_are_counted_and_logged_at_a_bounded_rate(cfg, caplog):
    async def go():
        gw, plc = gateway(cfg)
        await gw.startup()
        await cycles(gw, 3)
        plc.next_clock = [4294967295.0] * 50
        await cycles(gw, 52)
        await gw.shutdown()
        return gw.snapshot
    snap = run(go())
    assert snap.clock_rejected == 50
    lines = [r.getMessage() for r in caplog.records if r.name == "edge.loop"
             and r.levelno >= logging.WARNING and r.getMessage().startswith("clock check")]
    assert len(lines) == 2
    assert lines[0].startswith("clock check: sample clock 2106-02-07T06:28:15Z is ")
    assert lines[0].endswith("the scan is not aggregated (1 rejected since start) (repeats are "
                             "summarised every 600 s)")
    assert lines[1].startswith("clock check: recovered after 50 failure(s) in ")


def test_a_corrupt_clock_read_and_a_one_day_glitch_are_neither_stored_nor_scheduled(cfg):
    """0xFFFF 0xFFFF and +1 day in the PLC clock register: clock_fault in that cycle's block,
    no sample at that time, the calibration cadence goes on (it was blocked for 90 min)."""
    mono = FakeMono()

    async def go():
        adv = FakeAdvisor(["ok", "ok", "ok"])
        gw, plc = gateway(cfg, adv, monotonic=mono)
        await gw.startup()
        words = []
        for k in range(20):
            if k == 8:
                plc.next_clock = [4294967295.0]
            if k == 12:
                plc.next_clock = [plc.t + plc.step + 86400.0]
            mono.t += 1.0                       # a scan per second: the PLC clock runs at 60x
            await cycles(gw, 1)
            await asyncio.sleep(0.01)           # let the calibration thread finish
            words.append(plc.writes[-1][1])
        await gw.shutdown()
        return adv, words, gw.snapshot
    adv, words, snap = run(go())
    assert words[8] & 0x0200 and words[12] & 0x0200          # clock_fault on the glitch cycles
    assert not words[9] & 0x0200 and not words[13] & 0x0200 and not words[19] & 0x0200
    assert snap.clock_rejected == 2
    stamps = [s.timestamp for s in adv.ingested]
    assert max(stamps) < T0 + 3600 and stamps == sorted(stamps)
    assert len(adv.calls) >= 3 and max(adv.calls) < T0 + 3600
    ok = adv.calls[:3]                          # then the fake skips (retried every sample)
    assert [b - a for a, b in zip(ok, ok[1:])] == [cfg.calibration_interval_s] * 2


class FakeMono:
    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_first_block_after_a_restart_carries_advice_stale(cfg):
    """Restored advice 3,990 s old: the very first block says advice_stale (exact words)."""
    class Restoring(FakeAdvisor):
        def restored(self):
            return Advice(T0 + 60 - 3990, {"R_th_f": 3e-3, "p_m_sp_rec": 17.5})

    async def go():
        gw, plc = gateway(cfg, Restoring(calibrated=True))
        await gw.startup()
        await cycles(gw, 1)
        await gw.shutdown()
        return plc.writes[0]
    w = run(go())
    assert w[0:4] == [1, 0x0040, 26081, 2854]        # heartbeat, advice_stale, last_update
    assert w[28:30] == [0, 3990]                      # advice_age_s
    assert w[4:6] == [0x418C, 0x0000]                 # p_m_sp_rec 17.5 (float32 ABCD)


def test_blocks_while_the_first_calibration_runs_say_calibration_failed(cfg):
    """The advisor has saved its first fouling state but is still optimizing: the blocks of
    those cycles used to carry status 0 with last_update 0 and NaN values."""
    class Slow(FakeAdvisor):
        def __init__(self):
            super().__init__()
            self.started, self.go = threading.Event(), threading.Event()

        def advise(self, t_end):
            self.calls.append(t_end)
            self._calibrated = True            # state saved; the optimization still runs
            self.started.set()
            self.go.wait(5.0)
            return Advice(t_end, {"R_th_f": 3e-3, "p_m_sp_rec": 17.5, "CF_dp_f": 1.1})

    async def go():
        adv = Slow()
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        for _ in range(50):
            await cycles(gw, 1)
            if adv.started.is_set():
                break
        n0 = len(plc.writes)
        await cycles(gw, 3)
        during = plc.writes[n0:]
        adv.go.set()
        await asyncio.wait_for(asyncio.shield(gw._calibration), 5.0)
        await cycles(gw, 1)
        after = plc.writes[-1]
        await gw.shutdown()
        return during, after
    during, after = run(go())
    assert len(during) == 3
    for w in during:
        assert w[1] == 0x0048                          # calibration_failed + advice_stale
        assert w[2:4] == [0, 0] and w[12:14] == [0x7FC0, 0x0000]      # no time, R_th_f NaN
    assert after[1] == 0x0000 and after[12:14] != [0x7FC0, 0x0000]


def test_storage_fault_bit_with_the_advice_still_written(cfg):
    class Storing(FakeAdvisor):
        storage_fault = None

    async def go():
        adv = Storing(["ok"])
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        await _advise_until(gw, plc, adv, 1)
        await cycles(gw, 1)
        adv.storage_fault = "database or disk is full (SQLITE_FULL)"
        await cycles(gw, 1)
        faulty = plc.writes[-1]
        adv.storage_fault = None
        await cycles(gw, 1)
        await gw.shutdown()
        return faulty, plc.writes[-1]
    faulty, fine = run(go())
    assert faulty[1] == 0x0100 and fine[1] == 0x0000
    assert faulty[4:6] == fine[4:6] == [0x418C, 0x0000]      # p_m_sp_rec 17.5 in both


def test_a_stuck_sensor_is_flagged_flatline_and_sets_sensor_fault(cfg):
    """T_source_out frozen at one value while the plant runs: after its flatline_s (default 1800
    s of sample clock = 30 reads here) it is bad ('flatline') and sensor_fault is set; it clears
    when the value moves. While the plant is off a flat value is no fault."""
    stuck = {"T_source_out": TagValue("T_source_out", 18.0)}

    async def go():
        adv = FakeAdvisor()
        gw, plc = gateway(cfg, adv)
        await gw.startup()
        plc.override = {**stuck, "running": TagValue("running", 0.0)}
        await cycles(gw, 40)                                  # off: flat is normal
        off = plc.writes[-1][1]
        plc.override = dict(stuck)
        await cycles(gw, 29)
        not_yet = plc.writes[-1][1]
        await cycles(gw, 3)
        flat = plc.writes[-1][1]
        n = len(adv.ingested)
        await cycles(gw, 3)
        flagged = adv.ingested[n:]
        plc.override = {}
        await cycles(gw, 3)
        await gw.shutdown()
        return off, not_yet, flat, flagged, plc.writes[-1][1]
    off, not_yet, flat, flagged, moving = run(go())
    assert off == 0x004A                           # heat_pump_off + calibration_failed + stale
    assert not_yet == 0x0048
    assert flat == 0x0448                          # + sensor_fault
    assert flagged and all(s.bad.get("T_source_out") == "flatline"
                           and math.isnan(s.values["T_source_out"]) for s in flagged)
    assert all(math.isfinite(s.values["T_source_in"]) for s in flagged)
    assert moving == 0x0048


def test_a_required_tag_bad_longer_than_its_max_age_sets_sensor_fault(cfg):
    fast = replace(cfg, tags=tuple(replace(t, max_age_s=0.05) for t in cfg.tags))

    async def go():
        gw, plc = gateway(fast)
        await gw.startup()
        plc.override = {"T_e": TagValue("T_e", None, "nan")}
        await cycles(gw, 1)
        first = plc.writes[-1][1]
        await asyncio.sleep(0.1)
        await cycles(gw, 1)
        await gw.shutdown()
        return first, plc.writes[-1][1]
    first, later = run(go())
    assert first == 0x0048                  # bad, but not yet for its max age
    assert later == 0x0449                  # data_stale + sensor_fault (+ no advice yet)


def test_a_skipped_calibration_waits_for_the_next_sample(cfg):
    # plant clock 10 s per scan: a sample closes every 6 cycles; a skip must not be retried
    # (or wake the loop) before the next one
    async def go():
        adv = FakeAdvisor()                     # always "skip"
        gw, plc = gateway(cfg, adv, plc=FakePlc(cfg, step=10.0))
        task = asyncio.create_task(gw.run())
        await gw.wait_until(lambda s: s.cycles >= 60, 10)
        gw.request_stop()
        await task
        return adv.calls, gw.snapshot
    calls, snap = run(go())
    assert 5 <= len(calls) <= snap.samples
    assert len(set(calls)) == len(calls)


def test_a_refused_block_write_is_logged_once_and_counted(cfg, caplog):
    from edge.plc import PlcExceptionReply

    class Refusing(FakePlc):
        async def write_advisory(self, words):
            raise PlcExceptionReply(2, 16, 1000, len(words))

    async def go():
        gw, plc = gateway(cfg, plc=Refusing(cfg))
        await gw.startup()
        await cycles(gw, 3)
        await gw.shutdown()
        return gw
    gw = run(go())
    assert gw.snapshot.writes_failed == 3 and gw.snapshot.writes_ok == 0
    assert caplog.text.count("refuses the advisory block") == 1


def test_unwritable_state_and_full_history_keep_the_advice_and_recover(plant_minutes, tmp_path,
                                                                       monkeypatch):
    """Issue 9 item 8: a read-only state directory (mkstemp fails with EROFS, injected: this
    runs as root, where chmod does not stop writes) and a full history (SQLITE_FULL from a capped
    database) used to make the calibration fail or discard its advice. Now the advice comes back
    whole, storage_fault says why, and both recover by themselves with the next sample."""
    import errno

    from edge import statefiles

    adv, store = advisor_for(tmp_path)
    try:
        adv.ingest(plant_minutes[:-1])
        t_end = plant_minutes[-2].timestamp + 60

        def read_only(*a, **kw):
            raise OSError(errno.EROFS, "Read-only file system")
        monkeypatch.setattr(statefiles.tempfile, "mkstemp", read_only)
        store.add_advice(0, {"message": "x" * 4000})   # fills the advice table's first page
        pages = store.db.execute("PRAGMA page_count").fetchone()[0]
        store.db.execute(f"PRAGMA max_page_count={pages}")   # no page more: a full disk
        a = adv.advise(t_end)
        assert a.ok, a.message
        assert ADVICE_FIELDS <= set(a.values) and all(math.isfinite(a.values[k]) for k in ADVICE_FIELDS)
        assert store.fault == "database or disk is full (SQLITE_FULL)"
        assert adv.storage_fault == store.fault
        assert not (tmp_path / "state" / "fouling_calibration.json").exists()
        store.db.execute("PRAGMA max_page_count=1000000")
        store._retry_at = -math.inf                   # the back-off would wait 1 s
        assert store.flush() == 1 and store.fault is None
        assert adv.storage_fault.startswith("cannot write state file ")
        assert adv.storage_fault.endswith("fouling_calibration.json: [Errno 30] Read-only file "
                                          "system")
        monkeypatch.undo()                            # the directory is writable again
        adv.ingest(plant_minutes[-1:])
        assert adv.storage_fault is None
        assert store.latest_advice(ok_only=True)["ts"] == int(t_end)
        assert store.count("advice") == 2 and store.count() == len(plant_minutes)
        saved = json.loads((tmp_path / "state" / "fouling_calibration.json").read_text())
        assert saved["params"]["R_th_f_K_per_kW"] == pytest.approx(a.values["R_th_f"])
    finally:
        store.close()


def test_a_locked_history_does_not_stop_the_gateway(tmp_path, monkeypatch):
    """Issue 9 item 7: the history locked by another process at start: no '.corrupt-*' file, the
    gateway runs and writes its block with storage_fault; when the lock goes, the waiting samples
    are written and the bit clears."""
    import sqlite3

    from edge import store as store_mod
    from edge.service import GatewayService

    monkeypatch.setattr(store_mod, "OPEN_WAIT_S", 0.2)
    monkeypatch.setattr(store_mod, "BUSY_TIMEOUT_S", 0.02)
    monkeypatch.setattr(store_mod, "RETRY_MIN_S", 0.0)
    full = load_config(ROOT / "config" / "gateway.yaml")
    c = replace(full, state_dir=tmp_path / "state", history_db=tmp_path / "h.sqlite",
                scan_interval_s=0.02)
    with store_mod.HistoryStore(c.history_db, 1.0) as s:
        s.add_samples([{"ts": 0, "usable": 0}])
    other = sqlite3.connect(c.history_db, isolation_level=None)
    other.execute("PRAGMA locking_mode=EXCLUSIVE")
    other.execute("BEGIN EXCLUSIVE")
    other.execute("CREATE TABLE lock_holder (x)")
    locked = True

    async def go():
        nonlocal locked
        svc = GatewayService(c, time_source="plc", install_signals=False, plc=FakePlc(c))
        gw, plc = svc.gateway, svc.gateway.plc
        try:
            await gw.startup()
            await cycles(gw, 4)
            during = list(plc.writes[-1])
            other.execute("ROLLBACK")
            other.close()
            locked = False
            await cycles(gw, 2)
            await gw.shutdown()
        finally:
            svc.store.close()
        return during, plc.writes[-1], gw.snapshot
    try:
        during, after, snap = run(go())
    finally:
        if locked:
            other.close()
    assert during[1] == 0x0148           # storage_fault + calibration_failed + advice_stale
    assert after[1] == 0x0048
    assert list(tmp_path.glob("*.corrupt-*")) == []
    db = sqlite3.connect(c.history_db)
    try:
        n = db.execute("SELECT COUNT(*) FROM samples WHERE ts > 0").fetchone()[0]
    finally:
        db.close()
    assert n == snap.samples >= 4        # every sample of the locked time reached the disk
