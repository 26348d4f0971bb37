"""Simulator on loopback with a real pymodbus client: values, set point, write protection, faults.

Registers are decoded here with pymodbus's convert_from_registers and the tag map read by the test
(not the gateway's codec). Every test runs its own simulator on a port chosen at run time and is
bounded by asyncio.wait_for; synchronisation is on the simulator's tick/plant-time events.
"""
from __future__ import annotations

import asyncio
import math
import time

import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.exceptions import ModbusException

from simulator.config import read_advisory, read_tags, load_simulator_config
from simulator.server import PlantSimulator

CFG = load_simulator_config()
# a PLC without the remote-set-point program: any client write to the set point is taken (clamped)
LEGACY = CFG.with_sections(remote_setpoint={"enabled": False})
TAGS = read_tags(CFG.tags_file)
ADV = read_advisory(CFG.gateway_file)
DEV = CFG.device_id
TIMEOUT = 30.0
ILLEGAL_ADDRESS = 2


def run(coro, timeout: float = TIMEOUT):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def decode(name: str, regs: list[int]) -> float:
    """Independent decode: byte order by hand, then pymodbus convert_from_registers."""
    t = TAGS[name]
    regs = list(regs)
    if t.byte_order in ("BADC", "DCBA") and len(regs) == 2:
        regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
    raw = ModbusClientMixin.convert_from_registers(
        regs, getattr(ModbusClientMixin.DATATYPE, t.type.upper()),
        word_order="little" if t.byte_order in ("CDAB", "DCBA") else "big")
    if t.sentinel is not None and raw == t.sentinel:
        return math.nan
    return raw * t.scale + t.offset


async def read_all(client) -> dict[str, float]:
    inp = await client.read_input_registers(0, count=32, device_id=DEV)
    hold = await client.read_holding_registers(100, count=3, device_id=DEV)
    sp = await client.read_holding_registers(110, count=2, device_id=DEV)    # p_m_sp, enable
    assert not (inp.isError() or hold.isError() or sp.isError())
    out = {}
    for name, t in TAGS.items():
        if t.register == "input":
            out[name] = decode(name, inp.registers[t.address:t.address + t.count])
        elif t.address >= 110:
            out[name] = decode(name, sp.registers[t.address - 110:t.address - 110 + t.count])
        else:
            out[name] = decode(name, hold.registers[t.address - 100:t.address - 100 + t.count])
    return out


async def started(speed: float = 600.0, timeout: float = 2.0,
                  **kw) -> tuple[PlantSimulator, AsyncModbusTcpClient]:
    sim = PlantSimulator(port=0, speed=speed, **kw)
    await sim.start()
    client = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=timeout, retries=0)
    assert await client.connect()
    return sim, client


def test_reads_match_plant_state():
    async def body():
        sim, c = await started(speed=60.0)
        try:
            assert sim.port and sim.port != 0
            sim.faults.enable("frozen")          # hold the image still while reading it
            served = sim.served
            got = await read_all(c)
            assert got["closed_loop_enable"] == 0     # the operator's, never pushed by the plant
            for name, t in TAGS.items():
                if name == "closed_loop_enable":
                    continue
                want = served[name]
                tol = 1e-5 * max(1.0, abs(want)) if t.type == "float32" else t.scale / 2 + 1e-9
                assert got[name] == pytest.approx(want, abs=tol), name
            assert int(sim.plant_time) <= got["plc_clock"] <= sim.plant_time + sim.plant.dt
            assert got["running"] == 1 and got["cip"] == 0
            # consistent with the hidden steady state (within lags + noise)
            tr = sim.plant.steady.res
            assert got["p_dis_LS"] == pytest.approx(tr.p_m / 1e5 - CFG.ambient_pressure_bar, abs=0.15)
            assert got["N_LS"] == pytest.approx(tr.N_LS, abs=10)
            sim.faults.disable("frozen")
            await sim.wait_ticks(1)
            later = await read_all(c)
            assert later["life_counter"] != got["life_counter"]
            assert later["plc_clock"] >= got["plc_clock"]
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_real_time_life_counter_and_clock_move_like_a_plc():
    async def body():
        sim, c = await started(speed=1.0)
        try:
            a = await read_all(c)
            await sim.wait_ticks(2, timeout=3.0)      # pushes at least every 0.5 s at 1x
            b = await read_all(c)
            assert b["life_counter"] != a["life_counter"]
            assert 0 <= b["plc_clock"] - a["plc_clock"] <= 3
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_setpoint_write_moves_p_m_and_is_clamped():
    async def body():
        sim, c = await started(speed=1200.0, cfg=LEGACY)
        try:
            await sim.wait_ticks(1)
            sp = TAGS["p_m_sp"]
            rr = await c.write_register(sp.address, 1300, device_id=DEV)       # 13.00 bar(g)
            assert not rr.isError()
            await sim.wait_plant_time(sim.plant_time + 900)                   # 15 plant minutes
            assert sim.plant.p_m_sp_bar_g == pytest.approx(13.0)
            vals = await read_all(c)
            assert vals["p_m_sp"] == pytest.approx(13.0)
            res = sim.plant.steady.res
            p_m = res.p_m / 1e5 - CFG.ambient_pressure_bar
            if res.hs_saturated:
                assert p_m >= 13.0 - 1e-6
            else:
                assert p_m == pytest.approx(13.0, abs=1e-6)
            assert vals["p_dis_LS"] == pytest.approx(p_m, abs=0.2)
            # a set point beyond the PLC's limits is clamped and written back
            await c.write_register(sp.address, 9000, device_id=DEV)             # 90 bar(g)
            await sim.wait_ticks(2)
            hi = CFG.control.p_m_sp_limits_bar_g[1]
            assert sim.plant.p_m_sp_bar_g == hi
            assert (await read_all(c))["p_m_sp"] == pytest.approx(hi)
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_writes_outside_allowed_blocks_get_exception_2_and_change_nothing():
    async def body():
        sim, c = await started()
        try:
            sim.faults.enable("frozen")          # registers stand still: any change is a write
            await sim.wait_plant_time(sim.plant_time + 60)
            before_h = (await c.read_holding_registers(100, count=3, device_id=DEV)).registers
            before_i = (await c.read_input_registers(0, count=32, device_id=DEV)).registers
            before_a = (await c.read_holding_registers(ADV.start, count=ADV.size, device_id=DEV)).registers
            attempts = [
                lambda: c.write_register(100, 1, device_id=DEV),            # PLC clock
                lambda: c.write_register(102, 1, device_id=DEV),            # life counter
                lambda: c.write_registers(100, [1, 2, 3], device_id=DEV),
                lambda: c.write_register(0, 1, device_id=DEV),              # undefined holding 0
                lambda: c.write_register(112, 1, device_id=DEV),            # next to the enable
                lambda: c.write_registers(109, [1, 2], device_id=DEV),      # straddles the set point
                lambda: c.write_registers(ADV.start + ADV.size - 2, [1, 2, 3], device_id=DEV),
                lambda: c.write_registers(ADV.start - 1, [1, 2], device_id=DEV),
                lambda: c.write_coil(0, True, device_id=DEV),
                lambda: c.write_coils(65520, [True] * 3, device_id=DEV),
                lambda: c.mask_write_register(address=102, and_mask=0, or_mask=0xFFFF, device_id=DEV),
                lambda: c.readwrite_registers(read_address=0, read_count=1, write_address=101,
                                              values=[7], device_id=DEV),
            ]
            for attempt in attempts:
                rr = await attempt()
                assert rr.isError(), rr
                assert rr.exception_code == ILLEGAL_ADDRESS, rr
            assert (await c.read_holding_registers(100, count=3, device_id=DEV)).registers == before_h
            assert (await c.read_input_registers(0, count=32, device_id=DEV)).registers == before_i
            assert (await c.read_holding_registers(ADV.start, count=ADV.size, device_id=DEV)).registers == before_a
            rejected = sim.writes_rejected()
            assert len(rejected) == len(attempts)
            assert all(w.exception_code == ILLEGAL_ADDRESS for w in rejected)
            # the allowed blocks take writes, and the log says so
            ok = await c.write_registers(ADV.start, list(range(1, ADV.size + 1)), device_id=DEV)
            assert not ok.isError()
            rr = await c.read_holding_registers(ADV.start, count=ADV.size, device_id=DEV)
            assert rr.registers == list(range(1, ADV.size + 1))
            assert await sim.read_registers("holding", ADV.start, 2) == [1, 2]
            assert sim.write_log[-1].accepted and sim.write_log[-1].count == ADV.size
            assert sim.writes_outside(ADV.start, ADV.size) == rejected
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_tag_faults_switch_on_and_off():
    async def body():
        sim, c = await started()
        try:
            await sim.wait_ticks(1)
            sim.faults.enable("stuck", tag="T_dis_HS")
            await sim.wait_ticks(1)
            first = (await read_all(c))["T_dis_HS"]
            seen = set()
            for _ in range(4):
                await sim.wait_ticks(1)
                v = await read_all(c)
                assert v["T_dis_HS"] == first
                seen.add(v["W_LS"])
            assert len(seen) > 1                      # the rest of the plant moves on
            sim.faults.disable("stuck", tag="T_dis_HS")
            changes = set()
            for _ in range(4):
                await sim.wait_ticks(1)
                changes.add((await read_all(c))["T_dis_HS"])
            assert len(changes) > 1

            sim.faults.enable("out_of_range", tag="T_c")
            sim.faults.enable("nan", tag="T_e")                 # int16 with sentinel
            sim.faults.enable("nan", tag="p_source_in")         # float32: IEEE NaN
            await sim.wait_ticks(1)
            v = await read_all(c)
            assert v["T_c"] > TAGS["T_c"].range[1]
            assert math.isnan(v["T_e"]) and math.isnan(v["p_source_in"])
            sim.faults.enable("out_of_range", tag="T_source_in", value=-30.0)
            await sim.wait_ticks(1)
            assert (await read_all(c))["T_source_in"] == pytest.approx(-30.0)
            sim.faults.clear()
            await sim.wait_ticks(1)
            v = await read_all(c)
            lo, hi = TAGS["T_c"].range
            assert lo <= v["T_c"] <= hi and lo <= v["T_source_in"] <= hi
            assert math.isfinite(v["T_e"]) and math.isfinite(v["p_source_in"])
            assert not sim.faults.active()
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_frozen_registers_stop_life_counter_and_setpoint_waits():
    async def body():
        sim, c = await started(cfg=LEGACY)
        try:
            await sim.wait_ticks(1)
            sim.faults.enable("frozen")
            a = await read_all(c)
            await c.write_register(TAGS["p_m_sp"].address, 1400, device_id=DEV)
            await sim.wait_plant_time(sim.plant_time + 120)
            b = await read_all(c)
            for name in TAGS:
                if name != "p_m_sp":
                    assert a[name] == b[name] or (math.isnan(a[name]) and math.isnan(b[name])), name
            assert sim.plant.p_m_sp_bar_g == CFG.control.p_m_sp_bar_g   # link down: PLC not reached
            sim.faults.disable("frozen")
            await sim.wait_ticks(2)
            d = await read_all(c)
            assert d["life_counter"] != b["life_counter"] and d["plc_clock"] > b["plc_clock"]
            assert sim.plant.p_m_sp_bar_g == pytest.approx(14.0)
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_slow_responses_on_and_off():
    async def body():
        sim, c = await started()
        try:
            sim.faults.enable("slow", delay_s=0.4)
            t0 = time.perf_counter()
            rr = await c.read_input_registers(0, count=32, device_id=DEV)
            assert not rr.isError() and time.perf_counter() - t0 >= 0.4
            sim.faults.disable("slow")
            t0 = time.perf_counter()
            rr = await c.read_input_registers(0, count=32, device_id=DEV)
            assert not rr.isError() and time.perf_counter() - t0 < 0.35
            assert sim.stats.delayed == 1
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_dropped_connections_on_and_off():
    async def body():
        sim, c = await started(timeout=0.5)
        try:
            sim.faults.enable("drop")
            with pytest.raises(ModbusException):
                await c.read_input_registers(0, count=32, device_id=DEV)
            assert sim.stats.dropped >= 1
            sim.faults.disable("drop")
            c.close()
            c2 = AsyncModbusTcpClient("127.0.0.1", port=sim.port, timeout=0.5, retries=0)
            assert await c2.connect()
            assert not (await c2.read_input_registers(0, count=32, device_id=DEV)).isError()
            # one-shot: close every open connection now
            assert await sim.drop_connections() == 1
            with pytest.raises(ModbusException):
                await c2.read_input_registers(0, count=32, device_id=DEV)
            c2.close()
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_server_restart_keeps_port_and_register_memory():
    async def body():
        sim, c = await started()
        try:
            port = sim.port
            await c.write_registers(ADV.start, [11, 22], device_id=DEV)
            sim.faults.enable("restart", down_s=30.0)      # down until switched off
            await asyncio.sleep(0)                         # let the restart task close the listener
            while sim.is_listening:
                await asyncio.sleep(0.01)
            c.close()
            c2 = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=0.5, retries=0)
            assert not await c2.connect()
            sim.faults.disable("restart")
            await sim.wait_listening(5.0)
            assert sim.port == port and sim.stats.restarts == 1
            c3 = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2.0, retries=0)
            assert await c3.connect()
            rr = await c3.read_holding_registers(ADV.start, count=2, device_id=DEV)
            assert rr.registers == [11, 22]
            await sim.wait_ticks(1)
            assert not (await c3.read_input_registers(0, count=32, device_id=DEV)).isError()
            c3.close()
            # timed restart switches itself off
            sim.faults.enable("restart", down_s=0.2)
            await asyncio.sleep(0)
            await sim.wait_listening(5.0)
            for _ in range(100):
                if not sim.faults.is_on("restart"):
                    break
                await asyncio.sleep(0.02)
            assert not sim.faults.is_on("restart") and sim.stats.restarts == 2
        finally:
            c.close()
            await sim.stop()
    run(body())


def test_truth_log_written_per_plant_minute(tmp_path):
    path = tmp_path / "truth.jsonl"

    async def body():
        sim = PlantSimulator(port=0, speed=1200.0, truth_log=path)
        await sim.start()
        try:
            await sim.wait_plant_time(sim.plant_time + 300)
        finally:
            await sim.stop()
        return sim

    sim = run(body())
    import json
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    assert len(lines) >= 5
    ts = [x["t"] for x in lines]
    assert all(b - a == pytest.approx(60.0) for a, b in zip(ts, ts[1:]))
    rec = lines[-1]
    for key in ("R_th_f_K_per_kW", "CF_dp_f", "CF_eva", "CF_con", "CF_DSH", "CF_SC", "COP",
                "p_m_opt_bar_g"):
        assert key in rec
    assert rec["COP"] > 2 and 0 < rec["p_m_opt_bar_g"] < 40
    assert sim.truth["t"] == rec["t"]
