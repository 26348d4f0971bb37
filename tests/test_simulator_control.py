"""Plant-side options for the advice and CIP benchmarks: where T_c is measured, the PLC's own
set-point schedule, CIP on request, and stepping the plant minute by minute from Python
(simulator.export.MinuteStepper) - on the plant, in the export and on the Modbus server."""
from __future__ import annotations

import asyncio
import math

import numpy as np
import pandas as pd
import pytest
from pymodbus.client import AsyncModbusTcpClient

from model.fluid import get_fluid
from model.units import BAR, T0
from simulator.config import SimConfigError, config_from_dict, load_simulator_config, read_tags
from simulator.export import MinuteStepper, export_history
from simulator.plant import Plant
from simulator.profiles import DAY
from simulator.server import PlantSimulator

CFG = load_simulator_config()
TAGS = read_tags(CFG.tags_file)
DEV = CFG.device_id
AMB = CFG.ambient_pressure_bar
TIMEOUT = 30.0
MIN_SUBCOOLING_K = 5.0     # the SC cools the condensate by ~20 K at the demo's operating points
SP_REG = TAGS["p_m_sp"].address
CIP_REG = 112              # free holding address (tags.yaml uses 100-102 and 110)


def run(coro, timeout: float = TIMEOUT):
    return asyncio.run(asyncio.wait_for(coro, timeout))


# ------------------------------------------------------------------------- T_c location ----
def test_T_c_at_the_condenser_or_the_subcooler_outlet():
    cond = Plant(CFG)
    sub = Plant(CFG.with_sections(sensors={"T_c": "subcooler_outlet"}))
    r = sub.steady.res
    assert cond.steady.values["T_c"] + T0 == pytest.approx(get_fluid().sat_p(r.p_c).T, abs=1e-6)
    assert sub.steady.values["T_c"] + T0 == pytest.approx(r.states["SC_out"].T, abs=1e-9)
    assert r.subcooling > MIN_SUBCOOLING_K
    assert sub.steady.values["T_c"] == pytest.approx(cond.steady.values["T_c"] - r.subcooling, abs=1e-6)
    # every other sensor is the same
    for k, v in cond.steady.values.items():
        if k != "T_c":
            assert sub.steady.values[k] == v, k
    with pytest.raises(SimConfigError, match=r"sensors: key 'T_c' must be one of condenser_outlet, "
                                             r"subcooler_outlet, got 'receiver'"):
        config_from_dict({"sensors": {"T_c": "receiver"}})


def test_T_c_location_reaches_the_export():
    a = export_history(0.02, cfg=CFG, with_truth=True)
    b = export_history(0.02, cfg=CFG.with_sections(sensors={"T_c": "subcooler_outlet"}), with_truth=True)
    run_rows = a.history["running"] == 1
    gap = (a.history["T_c"] - b.history["T_c"])[run_rows].iloc[5:]    # after the lag settles
    sub = a.truth["subcooling_K"][run_rows].iloc[5:]
    assert np.allclose(gap, sub, atol=0.3)        # noise 0.1 K each, lagged
    pd.testing.assert_series_equal(a.history["T_e"], b.history["T_e"])


def test_T_c_location_reaches_the_server():
    async def body():
        sim = PlantSimulator(CFG.with_sections(sensors={"T_c": "subcooler_outlet"}), port=0, speed=600.0)
        await sim.start()
        c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)
        try:
            assert await c.connect()
            sim.faults.enable("frozen")
            t = TAGS["T_c"]
            rr = await c.read_input_registers(t.address, count=1, device_id=DEV)
            got = (rr.registers[0] - (65536 if rr.registers[0] > 32767 else 0)) * t.scale + t.offset
            res = sim.plant.steady.res
            assert got == pytest.approx(res.states["SC_out"].T - T0, abs=0.6)   # noise 0.1 K, lag
            assert got < res.T_c - T0 - MIN_SUBCOOLING_K
        finally:
            c.close()
            await sim.stop()
    run(body())


# ------------------------------------------------------------------- set-point schedule ----
SCHED = [[0.0, 16.0], [0.01, 10.0], [0.02, 14.0]]       # plant days: 0, 14.4 min, 28.8 min


def test_schedule_config_is_checked():
    with pytest.raises(SimConfigError, match=r"control: key 'p_m_sp_schedule': entry 1: from_day "
                                             r"must be >= 0 and rise from entry to entry, got 1"):
        config_from_dict({"control": {"p_m_sp_schedule": [[2, 10.0], [1, 16.0]]}})
    with pytest.raises(SimConfigError, match=r"entry 0: set point 50 bar\(g\) is outside "
                                             r"p_m_sp_limits_bar_g \[4, 35\]"):
        config_from_dict({"control": {"p_m_sp_schedule": [[0, 50.0]]}})
    with pytest.raises(SimConfigError, match=r"entry 0 must be a \[from_day, bar_g\] pair"):
        config_from_dict({"control": {"p_m_sp_schedule": [10.0]}})
    cfg = config_from_dict({"control": {"p_m_sp_schedule": SCHED}})
    assert cfg.control.p_m_sp_schedule == ((0.0, 16.0), (0.01, 10.0), (0.02, 14.0))


def test_schedule_steps_and_a_client_write_holds_until_the_next_step():
    p = Plant(CFG.with_sections(control={"p_m_sp_schedule": [[0.0, 12.0], [0.01, 10.0], [0.02, 14.0]]}))
    assert p.p_m_sp_bar_g == 12.0 and p.steady.p_m_sp_bar_g == 12.0
    # a step applies at the first tick at or after its time (864 s and 1728 s; ticks of 5 s)
    p.advance_to(p.t0 + 0.01 * DAY)
    assert p.t == p.t0 + 860 and p.p_m_sp_bar_g == 12.0
    p.tick()
    assert p.p_m_sp_bar_g == 10.0
    p.advance_to(p.t0 + 0.015 * DAY)
    p.set_p_m_sp(11.0)                                        # a client write
    p.advance_to(p.t0 + 0.02 * DAY)
    assert p.p_m_sp_bar_g == 11.0
    p.tick()
    assert p.p_m_sp_bar_g == 14.0 and p.sp_steps == 3
    p.advance_to(p.t0 + 0.02 * DAY + 120)
    r = p.steady.res
    assert p.steady.p_m_sp_bar_g == 14.0 and r.p_m / BAR - AMB == pytest.approx(14.0, abs=1e-6)


def test_schedule_in_the_export():
    h = export_history(0.03, cfg=CFG.with_sections(control={"p_m_sp_schedule": SCHED})).history
    sp = h["p_m_sp"].to_numpy()
    assert (sp[:14] == 16.0).all() and (sp[15:28] == 10.0).all() and (sp[29:] == 14.0).all()


def test_schedule_on_the_server_and_client_override():
    async def body():
        # a PLC without the remote-set-point program: a client write is taken at once
        cfg = CFG.with_sections(control={"p_m_sp_schedule": SCHED}, remote_setpoint={"enabled": False})
        sim = PlantSimulator(cfg, port=0, speed=1200.0)
        await sim.start()
        c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)

        async def register() -> float:
            return (await c.read_holding_registers(SP_REG, count=1, device_id=DEV)).registers[0] / 100.0
        try:
            assert await c.connect()
            assert await register() == 16.0
            await sim.wait_plant_time(sim.plant.t0 + 0.01 * DAY + 30)
            await sim.wait_ticks(2)
            assert await register() == 10.0 and sim.plant.p_m_sp_bar_g == 10.0
            assert not (await c.write_register(SP_REG, 1250, device_id=DEV)).isError()
            await sim.wait_ticks(3)
            assert sim.plant.p_m_sp_bar_g == 12.5 and await register() == 12.5
            await sim.wait_plant_time(sim.plant.t0 + 0.02 * DAY + 30)
            await sim.wait_ticks(2)
            assert sim.plant.p_m_sp_bar_g == 14.0 and await register() == 14.0
        finally:
            c.close()
            await sim.stop()
    run(body())


# -------------------------------------------------------------------------- CIP on request --
ON_REQUEST = dict(mode="on_request", first_after_days=0.01, jitter_days=0.0, duration_days=0.02)


def test_cip_on_request_on_the_plant():
    cfg = CFG.with_sections(cip=ON_REQUEST)
    p = Plant(cfg)
    assert p.cip_schedule is None
    p.advance_to(p.t0 + 0.05 * DAY)                # past first_after_days: nothing scheduled
    assert p.running and p.cip_count == 0 and not p.cip_log
    R_before, CF_before = p.fouling.R, p.fouling.CF_dp
    assert p.request_cip() is True
    assert p.request_cip() is False                # already pending
    assert p.truth()["cip_pending"] == 1
    p.tick()
    t_start = p.t
    assert not p.running and p.flags == {"running": 0, "cip": 1} and p.cip_window[0] == t_start
    assert p.request_cip() is False                # in progress
    assert math.isnan(p.truth()["COP"]) and p.truth()["cip"] == 1
    p.advance_to(t_start + 0.02 * DAY - p.dt)
    assert not p.running
    p.advance_to(t_start + 0.02 * DAY + p.dt)
    assert p.running and p.cip_count == 1
    log = p.cip_log[0]
    assert log["requested"] is True and log["end"] - log["start"] == pytest.approx(0.02 * DAY)
    assert p.truth()["cip_requests"] == 1
    assert log["R_th_f_before_K_per_kW"] == R_before and log["CF_dp_f_before"] == CF_before
    assert log["R_th_f_after_K_per_kW"] == pytest.approx(R_before * (1 - cfg.cip.removal_share), rel=1e-12)
    assert log["CF_dp_f_after"] - 1 == pytest.approx((CF_before - 1) * (1 - cfg.cip.dp_removal_share), rel=1e-12)
    with pytest.raises(RuntimeError, match="CIP on request needs cip.mode: on_request"):
        Plant(CFG).request_cip()


def test_cip_request_config_errors():
    with pytest.raises(SimConfigError, match=r"cip: key 'mode' must be one of schedule, on_request, got 'manual'"):
        config_from_dict({"cip": {"mode": "manual"}})
    with pytest.raises(SimConfigError, match=r"cip: key 'request_register' applies to mode on_request only"):
        config_from_dict({"cip": {"request_register": 112}})
    bad = CFG.with_sections(cip={**ON_REQUEST, "request_register": 110})
    with pytest.raises(ValueError, match=r"cip: key 'request_register': holding 110 is already a tag"):
        PlantSimulator(bad, port=0)


def test_minute_stepper_closes_a_loop_and_matches_the_export():
    """A benchmark's loop: step minute by minute, request a CIP, change the set point."""
    cfg = CFG.with_sections(cip=ON_REQUEST)
    ref = export_history(0.01, cfg=cfg, with_truth=True)
    st = MinuteStepper(cfg)
    rows = [st.step() for _ in range(14)]
    hist = pd.DataFrame([r for r, _ in rows])
    truth = pd.DataFrame([t for _, t in rows])
    pd.testing.assert_frame_equal(hist, ref.history)          # the same rows the export writes
    pd.testing.assert_frame_equal(truth, ref.truth)
    assert st.plant.request_cip()
    st.plant.set_p_m_sp(12.0)
    row, tr = st.step()
    assert row["cip"] == 1 and row["running"] == 0 and row["p_m_sp"] == 12.0
    assert tr["cip_pending"] == 1 and tr["running"] == 1        # truth at the start of the minute
    row, tr = st.step()
    assert tr["cip"] == 1 and tr["running"] == 0 and math.isnan(tr["COP"])
    assert row["timestamp"] == "2024-03-01T00:15:00Z" and tr["timestamp"] == row["timestamp"]


def test_cip_request_register_on_the_server():
    async def body():
        cfg = CFG.with_sections(cip={**ON_REQUEST, "request_register": CIP_REG})
        sim = PlantSimulator(cfg, port=0, speed=1200.0)
        await sim.start()
        c = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=2.0, retries=0)

        async def reg() -> int:
            return (await c.read_holding_registers(CIP_REG, count=1, device_id=DEV)).registers[0]
        try:
            assert await c.connect()
            await sim.wait_ticks(2)
            assert await reg() == 0 and sim.plant.running
            assert not (await c.write_register(CIP_REG, 1, device_id=DEV)).isError()
            await sim.wait_ticks(3)
            assert sim.plant.cip_window is not None and not sim.plant.running
            assert await reg() == 1
            end = sim.plant.cip_window[1]
            await sim.wait_plant_time(end + 60)
            await sim.wait_ticks(2)
            assert sim.plant.running and sim.plant.cip_count == 1 and await reg() == 0
            assert sim.plant.cip_log[0]["requested"] is True
            assert await sim.request_cip() is True               # the in-process way
            await sim.wait_ticks(2)
            assert sim.plant.cip_window is not None
        finally:
            c.close()
            await sim.stop()
    run(body())
