"""Gateway killed -> PLC fallback (issue 13): ``hp-edge run`` as its own process against the
simulator, the operator enables the loop, the operator's local set point moves while the PLC is in
remote mode (so the fallback is visible), then SIGKILL to the gateway's PID: the PLC's watchdog
reverts to the local set point once the heartbeat has not changed for its timeout - not before
the kill, not much after - and no write but the advisory block's ever reached the simulator."""
from __future__ import annotations

import asyncio
import time

import pytest

from edge.bench_closed_loop import kill_and_fallback, start_gateway, until, write_gateway_yaml
from edge.advisory import decode_advisory
from edge.closed_loop import State
from edge.config import load_read_config
from simulator.config import load_simulator_config
from simulator.server import PLC_SCAN_S, PlantSimulator

pytestmark = pytest.mark.slow

TIMEOUT_S = 1.0                  # the PLC's heartbeat timeout (wall seconds)
SCAN_S = 0.1                     # the gateway's scan (wall seconds)
LOOP = {"enabled": True, "setpoint_tag": "p_m_sp", "enable_tag": "closed_loop_enable",
        "bounds_bar_g": [12.0, 18.0], "max_step_bar": 0.5, "min_interval_s": 300,
        "heartbeat_timeout_s": TIMEOUT_S, "shed_after_bad_scans": 3}


def test_kill_9_of_the_gateway_makes_the_plc_fall_back_to_the_local_set_point(tmp_path):
    cfg = load_simulator_config().with_sections(
        remote_setpoint={"heartbeat_timeout_s": TIMEOUT_S})

    async def scenario():
        sim = PlantSimulator(cfg, port=0, speed=60.0)
        await sim.start()
        proc = None
        try:
            path = write_gateway_yaml(tmp_path / "gateway.yaml", sim.port, tmp_path, scan_s=SCAN_S,
                                      loop=LOOP)
            _, adv = load_read_config(path)
            proc = start_gateway(path, tmp_path / "gateway.log")
            await until(lambda: sim.program.hb_last is not None and sim.program.hb_last > 2, 60)
            await sim.set_operator_enable(True)
            await until(lambda: sim.remote_mode, 10)
            # the gateway has seen the enable (its block says armed): it acts on the enable once its
            # first calibration cycle has run, which may come after the PLC's remote mode
            t_arm = time.monotonic() + 20
            while (decode_advisory(adv, await sim.read_registers("holding", adv.start, adv.size))
                   ["closed_loop_state"] != State.ARMED):
                assert time.monotonic() < t_arm, "the gateway did not arm within 20 s"
                await asyncio.sleep(SCAN_S)
            sim.set_local_setpoint(14.0)          # the operator's own value moves meanwhile
            await sim.wait_ticks(3)
            remote_sp = sim.plant.p_m_sp_bar_g    # remote mode: the plant keeps the remote one
            t_before = time.monotonic()
            got = await kill_and_fallback(sim, proc, 10 * TIMEOUT_S)
            proc = None
            n_writes = len(sim.write_log)
            await asyncio.sleep(2 * SCAN_S)
            return sim, adv, remote_sp, got, t_before, n_writes
        finally:
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(10)
            await sim.stop()

    sim, adv, remote_sp, got, t_before, n_writes = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert remote_sp == 16.0
    assert got["returncode"] == -9 and (got["mode"], got["reason"]) == ("local", "heartbeat_timeout")
    # the watchdog's own figure: the heartbeat had not changed for its timeout, and the PLC
    # noticed within a few of its scans
    assert TIMEOUT_S <= got["heartbeat_age_at_fallback_s"] <= TIMEOUT_S + 10 * PLC_SCAN_S
    assert got["kill_to_fallback_s"] <= TIMEOUT_S + 10 * PLC_SCAN_S
    ev = sim.plc_events[-1]
    assert ev["mono"] > t_before                       # not before the kill
    assert got["set_point_after_bar_g"] == 14.0 and sim.plant.p_m_sp_bar_g == 14.0
    assert [(e["mode"], e["reason"]) for e in sim.plc_events] == [("remote", "enable_on"),
                                                                  ("local", "heartbeat_timeout")]
    # the write log: the advisory block only (no advice yet: no set-point write), nothing after
    assert n_writes > 0 and len(sim.write_log) == n_writes
    assert all(w.address == adv.start and w.count == adv.size and w.accepted for w in sim.write_log)
    assert sim.setpoint_log == []
    log = (tmp_path / "gateway.log").read_text()
    assert "closed loop armed" in log and "Traceback" not in log
