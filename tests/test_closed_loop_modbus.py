"""The closed loop over Modbus (issue 13): the one extra write path of edge/plc.py, the simulated
PLC's remote-set-point program (enable, bounds, heartbeat fallback), and the gateway against the
simulator, whose write log proves that nothing but the advisory block and the set point was
written. Servers on 127.0.0.1, ports chosen at run time; every test bounded by asyncio.wait_for
and synchronised on the simulator's events and the gateway's cycles."""
from __future__ import annotations

import asyncio
import time
from dataclasses import replace
from pathlib import Path

import pytest
from pymodbus.client import AsyncModbusTcpClient

from edge.closed_loop import ClosedLoopConfig
from edge.config import load_config
from edge.loop import Advice, Gateway
from edge.plc import PlcClient, SetpointWriteRefused, WriteOutsideAdvisoryBlock
from simulator.config import load_simulator_config
from simulator.remote import EXC_NOT_REMOTE, EXC_OUT_OF_BOUNDS, RemoteSetpoint
from simulator.server import PLC_SCAN_S, PlantSimulator

ROOT = Path(__file__).resolve().parent.parent
CFG = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
ADV = CFG.advisory
SIM = load_simulator_config()
SP_ADDR, EN_ADDR = CFG.tag("p_m_sp").address, CFG.tag("closed_loop_enable").address
LOOP = ClosedLoopConfig(enabled=True, setpoint_tag="p_m_sp", enable_tag="closed_loop_enable",
                        bounds_bar_g=(12.0, 18.0), max_step_bar=0.5, min_interval_s=120.0,
                        heartbeat_timeout_s=1.0, shed_after_bad_scans=3, deadband_bar=0.05)
STEP_TOL = 1e-9


def run(coro, timeout=30.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


# --------------------------------------------------------------------------- edge/plc.py

def plc_client(port: int, cfg) -> PlcClient:
    return PlcClient.from_config(replace(cfg, plc=replace(cfg.plc, port=port, timeout_s=1.0)))


def test_without_the_closed_loop_no_set_point_request_is_ever_built(monkeypatch):
    sent = []

    async def spy(self, *args, **kwargs):
        sent.append(args)
        raise AssertionError("nothing may be sent")

    monkeypatch.setattr("pymodbus.client.AsyncModbusTcpClient.write_registers", spy)

    async def go():
        plc = plc_client(1, CFG)                      # shipped: closed_loop.enabled false
        with pytest.raises(SetpointWriteRefused, match="the closed loop is not enabled in "
                                                       "gateway.yaml"):
            await plc.write_setpoint([1550])
        with pytest.raises(WriteOutsideAdvisoryBlock, match="writes are allowed only inside "
                                                           "the advisory block"):
            await plc.write_registers(SP_ADDR, [1550])
    run(go())
    assert sent == []


def test_with_the_closed_loop_exactly_the_set_point_registers_and_nothing_else(monkeypatch):
    cfg = replace(CFG, closed_loop=LOOP)

    async def go():
        sim = PlantSimulator(SIM.with_sections(remote_setpoint={"enabled": False}), port=0,
                             speed=60.0)
        await sim.start()
        try:
            plc = plc_client(sim.port, cfg)
            await plc.connect()
            with pytest.raises(SetpointWriteRefused, match=r"refusing to write 2 register\(s\) to "
                               r"set-point tag 'p_m_sp' \(holding 110..110\): it has exactly 1"):
                await plc.write_setpoint([1550, 0])
            for address in (SP_ADDR, EN_ADDR, 100):   # the generic path still refuses them
                with pytest.raises(WriteOutsideAdvisoryBlock):
                    await plc.write_registers(address, [1])
            await plc.write_setpoint([1550])
            back = await plc.read_setpoint()
            await plc.close()
            return sim.write_log, back
        finally:
            await sim.stop()

    log, back = run(go())
    assert back == [1550]
    assert [(w.function_code, w.address, w.count, w.values, w.accepted) for w in log] == [
        (16, SP_ADDR, 1, (1550,), True)]


# --------------------------------------------------------------------------- the PLC program

def test_program_enable_edge_bounds_and_latched_heartbeat_fallback():
    p = RemoteSetpoint((8.0, 22.0), heartbeat_timeout_s=2.0)
    assert p.check_write(15.0) == EXC_NOT_REMOTE
    assert p.scan(True, 0.0) is None                 # enable on, but no heartbeat ever seen
    p.heartbeat(1, 1.0)
    assert p.scan(True, 1.0) is None                 # still on: a rising edge is needed
    assert p.scan(False, 1.1) is None
    ch = p.scan(True, 1.2)
    assert (ch.mode, ch.reason) == ("remote", "enable_on") and p.remote
    assert p.check_write(15.0) is None
    assert p.check_write(22.5) == EXC_OUT_OF_BOUNDS and p.check_write(7.99) == EXC_OUT_OF_BOUNDS
    assert p.check_write(float("nan")) == EXC_OUT_OF_BOUNDS
    p.heartbeat(1, 2.0)                              # the same word: not a change
    assert p.scan(True, 2.9) is None                 # 1.9 s since the change
    ch = p.scan(True, 3.1)
    assert (ch.mode, ch.reason) == ("local", "heartbeat_timeout")
    assert ch.heartbeat_age_s == pytest.approx(2.1) and p.tripped
    p.heartbeat(2, 3.4)                              # the gateway is back ...
    assert p.scan(True, 3.5) is None and not p.remote          # ... and does not take over
    assert p.scan(False, 3.6) is None and not p.tripped        # the operator drops the enable
    assert p.scan(True, 3.7).mode == "remote"
    ch = p.scan(False, 3.8)
    assert (ch.mode, ch.reason) == ("local", "enable_off")
    assert [c.reason for c in p.changes] == ["enable_on", "heartbeat_timeout", "enable_on",
                                             "enable_off"]


def test_simulated_plc_refuses_set_points_unless_remote_and_inside_its_bounds():
    async def go():
        cfg = SIM.with_sections(remote_setpoint={"heartbeat_timeout_s": 30.0})
        sim = PlantSimulator(cfg, port=0, speed=600.0)
        await sim.start()
        c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)
        try:
            assert await c.connect()
            local = await c.write_register(SP_ADDR, 1500, device_id=1)
            await c.write_registers(ADV.start, [1], device_id=1)          # a heartbeat
            assert not (await c.write_register(EN_ADDR, 1, device_id=1)).isError()   # the HMI
            await asyncio.wait_for(_until(lambda: sim.remote_mode), 5)
            inside = await c.write_register(SP_ADDR, 1500, device_id=1)
            above = await c.write_register(SP_ADDR, 2250, device_id=1)
            await sim.wait_ticks(2)
            plant_sp = sim.plant.p_m_sp_bar_g
            return local, inside, above, plant_sp, sim.setpoint_log, sim.plc_events
        finally:
            c.close()
            await sim.stop()

    local, inside, above, plant_sp, splog, events = run(go())
    assert local.isError() and local.exception_code == 4
    assert not inside.isError()
    assert above.isError() and above.exception_code == 3
    assert plant_sp == 15.0
    assert [(r["old"], r["new"], r["accepted"], r["exception"]) for r in splog] == [
        (16.0, 15.0, False, 4), (16.0, 15.0, True, None), (15.0, 22.5, False, 3)]
    assert [(e["mode"], e["reason"]) for e in events] == [("remote", "enable_on")]


async def _until(predicate, step=0.01):
    while not predicate():
        await asyncio.sleep(step)


# --------------------------------------------------------------------------- gateway + simulator

class Confident:
    """A model side that learned everything: every calibration recommends ``rec``."""

    def __init__(self, rec: float):
        self.rec = rec

    def ingest(self, samples):
        return []

    def advise(self, t_end):
        return Advice(t_end, {"p_m_sp_rec": self.rec, "R_th_f": 3e-3})

    def restored(self):
        return None

    has_calibration = True


class Rig:
    """The simulator (remote-set-point program on) and the real Gateway + PlcClient against it,
    in this event loop; the plant runs at ``speed``, the gateway scans every ``scan`` s."""

    def __init__(self, loop_cfg, rec, *, speed=600.0, scan=0.05, sim_bounds=(8.0, 22.0),
                 hb_timeout=1.0):
        self.loop_cfg, self.rec, self.speed, self.scan = loop_cfg, rec, speed, scan
        self.sim_cfg = SIM.with_sections(remote_setpoint={"bounds_bar_g": list(sim_bounds),
                                                          "heartbeat_timeout_s": hb_timeout})

    async def __aenter__(self):
        self.sim = PlantSimulator(self.sim_cfg, port=0, speed=self.speed)
        await self.sim.start()
        plc = replace(CFG.plc, port=self.sim.port, timeout_s=0.5 * self.scan * 10,
                      reconnect_min_s=self.scan, reconnect_max_s=self.scan)
        self.cfg = replace(CFG, plc=plc, scan_interval_s=self.scan, calibration_interval_s=300.0,
                           closed_loop=self.loop_cfg,
                           tags=tuple(replace(t, max_age_s=30.0) for t in CFG.tags))
        self.audit: list[dict] = []          # the closed loop's audit rows (``ts``: the sample time)
        self.gw = Gateway(self.cfg, Confident(self.rec), time_source="plc", install_signals=False,
                          audit=self.audit.append)
        self.task = asyncio.create_task(self.gw.run())
        return self

    async def cycles(self, n):
        target = self.gw.snapshot.cycles + n
        await self.gw.wait_until(lambda s: s.cycles >= target, 20)

    async def __aexit__(self, *exc):
        self.gw.request_stop()
        await asyncio.wait_for(self.task, 10)
        await self.sim.stop()


def setpoint_writes(sim):
    return [w for w in sim.write_log if w.address == SP_ADDR]


def only_block_and_set_point(sim):
    """The simulator's write log: every request went to the advisory block or to the set point."""
    return all((w.address == SP_ADDR and w.count == 1 and w.function_code == 16)
               or (w.address == ADV.start and w.count == ADV.size and w.function_code == 16)
               for w in sim.write_log)


def test_gateway_steps_the_simulated_plc_within_bounds_and_step_limit():
    async def go():
        async with Rig(LOOP, rec=13.6) as rig:
            await rig.cycles(5)
            before = len(setpoint_writes(rig.sim))
            await rig.sim.set_operator_enable(True)
            await rig.gw.wait_until(lambda s: s.closed_loop == ("armed", "at_target"), 25)
            await rig.cycles(3)
            return rig.sim, before, rig.gw.snapshot, rig.audit
    sim, before, snap, audit = run(go(), 40)
    assert before == 0                                   # nothing before the operator's enable
    sps = sim.setpoint_log
    assert [round(r["new"], 2) for r in sps] == [15.5, 15.0, 14.5, 14.0, 13.6]
    assert all(r["accepted"] and r["remote"] for r in sps)
    assert all(abs(r["new"] - r["old"]) <= LOOP.max_step_bar + STEP_TOL for r in sps)
    assert all(12.0 <= r["new"] <= 18.0 for r in sps)
    # one step per min_interval_s on the sample clock, the clock the gateway decides on (the plant's
    # own clock at the write runs on while a scan is under way: at 600x a loaded machine's
    # 40 ms between the read and the write are 24 s of plant time, so its gaps are no test)
    writes = [r for r in audit if r.get("event") == "write"]
    assert [(round(r["new_bar_g"], 2), r["outcome"]) for r in writes] == \
        [(15.5, "ok"), (15.0, "ok"), (14.5, "ok"), (14.0, "ok"), (13.6, "ok")]
    ts = [r["ts"] for r in writes]
    assert min(b - a for a, b in zip(ts, ts[1:])) >= LOOP.min_interval_s
    assert [w.values for w in setpoint_writes(sim)] == [(1550,), (1500,), (1450,), (1400,), (1360,)]
    assert sim.plant.p_m_sp_bar_g == pytest.approx(13.6)
    assert only_block_and_set_point(sim) and sim.writes_rejected() == []
    assert snap.values["closed_loop_writes"] == 5


def test_a_plc_with_narrower_bounds_refuses_and_the_gateway_sheds():
    """The gateway's bounds reach 20 bar(g), the PLC's end at 17: its exception 3 sheds the loop."""
    async def go():
        async with Rig(replace(LOOP, bounds_bar_g=(12.0, 20.0)), rec=19.5,
                       sim_bounds=(8.0, 17.0)) as rig:
            await rig.cycles(3)
            await rig.sim.set_operator_enable(True)
            await rig.gw.wait_until(lambda s: s.closed_loop[0] == "shed", 25)
            n = len(setpoint_writes(rig.sim))
            await rig.cycles(10)
            return rig.sim, n, rig.gw.snapshot
    sim, n, snap = run(go(), 40)
    assert snap.closed_loop == ("shed", "shed_write_refused")
    assert snap.values["closed_loop_state"] == 3 and snap.values["closed_loop_reason"] == 33
    log = [(round(r["new"], 2), r["accepted"], r["exception"]) for r in sim.setpoint_log]
    assert log == [(16.5, True, None), (17.0, True, None), (17.5, False, 3)]
    assert len(setpoint_writes(sim)) == n == 3          # nothing more while shed
    assert sim.plant.p_m_sp_bar_g == pytest.approx(17.0)   # the PLC kept its value
    assert only_block_and_set_point(sim)


def test_disabling_at_the_hmi_reverts_the_plc_and_the_gateway_stops_at_once():
    async def go():
        async with Rig(LOOP, rec=13.0) as rig:
            await rig.cycles(3)
            await rig.sim.set_operator_enable(True)
            await rig.gw.wait_until(lambda s: s.values.get("closed_loop_writes", 0) >= 2, 25)
            await rig.sim.set_operator_enable(False)
            await rig.gw.wait_until(lambda s: s.closed_loop == ("off", "operator_off"), 10)
            n = len(setpoint_writes(rig.sim))
            await rig.cycles(10)
            await rig.sim.wait_ticks(2)
            return rig.sim, n
    sim, n = run(go(), 40)
    assert len(setpoint_writes(sim)) == n
    assert [(e["mode"], e["reason"]) for e in sim.plc_events] == [("remote", "enable_on"),
                                                                  ("local", "enable_off")]
    assert sim.plant.p_m_sp_bar_g == SIM.control.p_m_sp_bar_g     # the operator's local set point
    assert only_block_and_set_point(sim)


def test_a_stalled_gateway_lets_the_plc_fall_back_within_its_timeout():
    """In-process: the gateway's loop stops (as if hung); the PLC's watchdog falls back. The
    process-level kill -9 is in test_closed_loop_kill.py."""
    async def go():
        async with Rig(LOOP, rec=13.0, hb_timeout=0.5) as rig:
            await rig.cycles(3)
            await rig.sim.set_operator_enable(True)
            await rig.gw.wait_until(lambda s: s.values.get("closed_loop_writes", 0) >= 1, 25)
            rig.gw.request_stop()
            await asyncio.wait_for(rig.task, 10)
            t_stop = time.monotonic()
            await asyncio.wait_for(_until(lambda: not rig.sim.remote_mode), 5)
            await rig.sim.wait_ticks(2)
            rig.task = asyncio.create_task(asyncio.sleep(0))
            return rig.sim, t_stop
    sim, t_stop = run(go(), 40)
    ev = sim.plc_events[-1]
    assert (ev["mode"], ev["reason"]) == ("local", "heartbeat_timeout")
    assert 0.5 <= ev["heartbeat_age_s"] <= 0.5 + 10 * PLC_SCAN_S
    assert ev["mono"] >= t_stop            # not before the gateway stopped
    assert sim.plant.p_m_sp_bar_g == SIM.control.p_m_sp_bar_g
