"""PlcClient against in-test pymodbus servers on 127.0.0.1 (ports chosen at run time).

Server register images are encoded with pymodbus' own convert_to_registers, not with edge.codec,
so a codec bug cannot hide itself here. Every test is bounded by asyncio.wait_for and closes
its servers.
"""
from __future__ import annotations

import argparse
import asyncio
import dataclasses
import json
import logging
import socket
import subprocess
import sys
from contextlib import asynccontextmanager
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from edge.advisory import decode_advisory, encode_advisory
from edge.commands import gateway_cmds
from edge.config import TagConfig, load_config
from edge.plc import (
    PlcClient,
    PlcCommError,
    PlcExceptionReply,
    WriteOutsideAdvisoryBlock,
)

REPO = Path(__file__).resolve().parents[1]
CFG = load_config(REPO / "config" / "gateway.yaml", load_plant=False)
DT = ModbusTcpClient.DATATYPE
PM_TYPE = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32, "uint32": DT.UINT32,
           "float32": DT.FLOAT32}
PM_ORDER = {"AB": "big", "ABCD": "big", "CDAB": "little"}

PLANT = {  # a plausible operating point, engineering units
    "T_sink_in": 40.0, "T_sink_out": 68.0, "T_source_in": 25.0, "T_source_out": 18.0,
    "V_sink": 62.0, "V_source": 192.0, "p_source_in": 2.5, "p_source_out": 2.1,
    "T_suc_LS": 11.3, "T_dis_LS": 85.2, "T_suc_HS": 42.0, "T_dis_HS": 120.5, "T_c": 69.5,
    "T_e": 10.3, "p_suc_LS": 5.25, "p_dis_LS": 15.5, "p_suc_HS": 15.25, "p_dis_HS": 30.75,
    "W_LS": 260.0, "W_HS": 190.5, "N_LS": 1500, "N_HS": 1800, "running": 1, "cip": 0,
    "plc_clock": 1_718_000_000, "life_counter": 4711, "p_m_sp": 16.0, "closed_loop_enable": 0,
}


def run(coro, timeout: float = 15.0):
    """Run one test coroutine, bounded in time."""
    return asyncio.run(asyncio.wait_for(coro, timeout))


def pm_words(tag: TagConfig, value) -> list[int]:
    """Register words for ``value`` encoded by pymodbus (independent of edge.codec)."""
    raw = value if tag.type == "float32" else round((value - tag.offset) / tag.scale)
    return ModbusTcpClient.convert_to_registers(raw, PM_TYPE[tag.type], PM_ORDER[tag.byte_order])


def image(tags, values, space: str) -> dict[int, int]:
    regs: dict[int, int] = {}
    for tag in tags:
        if tag.register == space and tag.name in values:
            for i, w in enumerate(pm_words(tag, values[tag.name])):
                regs[tag.address + i] = w
    return regs


def _blocks(regs: dict[int, int]) -> list[SimData]:
    """Contiguous runs of defined registers; everything else answers exception 2."""
    blocks, run_ = [], []
    for addr in sorted(regs):
        if run_ and addr != run_[-1] + 1:
            blocks.append(run_)
            run_ = []
        run_.append(addr)
    if run_:
        blocks.append(run_)
    return [SimData(b[0], values=[regs[a] for a in b], datatype=DataType.REGISTERS) for b in blocks]


@asynccontextmanager
async def modbus_server(inputs: dict[int, int], holding: dict[int, int], *, port: int = 0,
                        delay_s: float = 0.0):
    """A pymodbus server on 127.0.0.1; ``server.requests`` records every request received."""
    requests: list[tuple] = []

    def trace_pdu(sending: bool, pdu):
        if not sending:
            requests.append((pdu.function_code, pdu.address, pdu.count, list(pdu.registers or [])))
        return pdu

    async def slow(*_args):
        await asyncio.sleep(delay_s)

    bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
    holding = {**holding, **{1000 + i: 0 for i in range(CFG.advisory.size)}}
    device = SimDevice(1, simdata=(bits, list(bits), _blocks(holding), _blocks(inputs)),
                       action=slow if delay_s else None)
    server = ModbusTcpServer(device, address=("127.0.0.1", port), trace_pdu=trace_pdu)
    await server.serve_forever(background=True)
    server.port = server.transport.sockets[0].getsockname()[1]
    server.requests = requests
    try:
        yield server
    finally:
        await server.shutdown()


def plant_server(values=PLANT, **kw):
    return modbus_server(image(CFG.tags, values, "input"), image(CFG.tags, values, "holding"), **kw)


def client(port: int, *, tags=CFG.tags, budget: float = 4.0, clock=None, **plc) -> PlcClient:
    cfg = dataclasses.replace(CFG.plc, host="127.0.0.1", port=port,
                              **{"timeout_s": 1.0, "max_read_gap": 10, **plc})
    kw = {"clock": clock} if clock else {}
    return PlcClient(cfg, tags, CFG.advisory, cycle_budget_s=budget, **kw)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def silent(reader, writer):
    """A TCP peer that swallows requests and never answers (a hung PLC gateway)."""
    try:
        while await reader.read(1000):
            pass
    finally:
        writer.close()


# ------------------------------------------------------------------------------- reading

def test_read_all_decodes_every_tag_and_falls_back_after_exception_2():
    async def scenario():
        # the server leaves holding 103..109 undefined: the grouped read 100..110 gets exception 2
        async with plant_server() as server:
            async with client(server.port) as plc:
                first = await plc.read_all()
                second = await plc.read_all()
            return first, second, server.requests

    first, second, requests = run(scenario())
    for result in (first, second):
        assert result.comm_error is None
        assert list(result.values) == [t.name for t in CFG.tags]
        bad = {n: v.bad for n, v in result.values.items() if not v.ok}
        assert bad == {}
        for name, expected in PLANT.items():
            assert result.values[name].value == pytest.approx(expected, rel=1e-6), name
    assert first.values["p_suc_LS"].words == tuple(pm_words(CFG.tag("p_suc_LS"), 5.25))
    assert first.values["T_sink_in"].raw == 4000
    reads = [(fc, a, n) for fc, a, n, _ in requests]
    # cycle 1: grouped input read, refused grouped holding read, then per-tag holding reads
    assert reads[:6] == [(4, 0, 32), (3, 100, 12), (3, 100, 2), (3, 102, 1), (3, 110, 1),
                         (3, 111, 1)]
    # cycle 2 remembers: no second attempt at the grouped holding read
    assert reads[6:] == [(4, 0, 32), (3, 100, 2), (3, 102, 1), (3, 110, 1), (3, 111, 1)]
    assert (first.requests, second.requests) == (6, 5)


def test_grouped_read_when_the_gap_is_readable():
    async def scenario():
        holding = image(CFG.tags, PLANT, "holding")
        holding.update({a: 0 for a in range(103, 110)})
        async with modbus_server(image(CFG.tags, PLANT, "input"), holding) as server:
            async with client(server.port) as plc:
                result = await plc.read_all()
            return result, server.requests

    result, requests = run(scenario())
    assert result.requests == 2 and all(v.ok for v in result.values.values())
    assert [(fc, a, n) for fc, a, n, _ in requests] == [(4, 0, 32), (3, 100, 12)]


def test_bad_values_are_marked_never_clamped():
    async def scenario():
        inputs = image(CFG.tags, PLANT, "input")
        inputs[0] = 0x8000                                      # T_sink_in sentinel -32768
        inputs[4] = 0xFFFF                                      # V_sink sentinel 65535
        inputs[6], inputs[7] = 0x7FC0, 0x0000                   # p_source_in NaN
        inputs[24], inputs[25] = 0x7F80, 0x0000                 # W_LS +inf
        inputs[14] = pm_words(CFG.tag("T_c"), 150.0)[0]         # T_c above [0, 110]
        inputs[16], inputs[17] = pm_words(CFG.tag("p_suc_LS"), -1.0)  # below [-0.9, 25]
        holding = image(CFG.tags, PLANT, "holding")
        del holding[100], holding[101]                          # plc_clock: illegal address
        async with modbus_server(inputs, holding) as server:
            async with client(server.port) as plc:
                return await plc.read_all()

    result = run(scenario())
    bad = {n: v.bad for n, v in result.values.items() if not v.ok}
    assert bad == {
        "T_sink_in": "sentinel", "V_sink": "sentinel", "p_source_in": "nan", "W_LS": "inf",
        "T_c": "out of range [0, 110]", "p_suc_LS": "out of range [-0.9, 25]",
        "plc_clock": "modbus exception 2",
    }
    assert result.comm_error is None                 # exception replies are answers
    assert result.values["T_c"].value is None and result.values["T_c"].raw == 1500
    assert result.values["T_sink_in"].words == (0x8000,)
    assert result.values["life_counter"].value == 4711   # neighbours of the bad tag still read
    assert result.good()["T_sink_out"] == pytest.approx(68.0)


def test_exception_reply_and_comm_error_are_distinct_channels():
    async def scenario():
        async with plant_server() as server:
            async with client(server.port) as plc:
                await plc.connect()
                with pytest.raises(PlcExceptionReply) as reply:
                    await plc.read_registers("holding", 500, 2)
                still_connected = plc.connected
        quiet = await asyncio.start_server(silent, "127.0.0.1", 0)
        try:
            async with client(quiet.sockets[0].getsockname()[1], timeout_s=0.2) as plc:
                await plc.connect()
                with pytest.raises(PlcCommError) as comm:
                    await plc.read_registers("input", 0, 2)
                after = plc.connected
        finally:
            quiet.close()
            await quiet.wait_closed()
        return reply.value, still_connected, comm.value, after

    reply, still_connected, comm, after = run(scenario())
    assert reply.code == 2 and "illegal data address" in str(reply)
    assert still_connected
    assert comm.reason == "timeout" and not after     # a timed-out link is dropped and re-made


def test_a_silent_plc_is_logged_loudly_once(caplog):
    async def scenario():
        srv = await asyncio.start_server(silent, "127.0.0.1", 0)
        try:
            async with client(srv.sockets[0].getsockname()[1], timeout_s=0.1, budget=0.3) as plc:
                return [await plc.read_all() for _ in range(3)]
        finally:
            srv.close()
            await srv.wait_closed()

    with caplog.at_level(logging.DEBUG, logger="edge.plc"):
        results = run(scenario())
    assert [r.comm_error for r in results] == ["timeout"] * 3
    mine = [r for r in caplog.records if r.name == "edge.plc" and "timeout" in r.message]
    assert [r.levelno for r in mine] == [logging.WARNING, logging.DEBUG, logging.DEBUG]


def test_connection_lost_mid_request():
    async def hang_up(reader, writer):
        await reader.read(1000)
        writer.close()

    async def scenario():
        srv = await asyncio.start_server(hang_up, "127.0.0.1", 0)
        try:
            async with client(srv.sockets[0].getsockname()[1], timeout_s=2.0) as plc:
                return await plc.read_all()
        finally:
            srv.close()
            await srv.wait_closed()

    result = run(scenario())
    assert result.comm_error == "connection lost"
    assert {v.bad for v in result.values.values()} == {"connection lost"}


def test_cycle_is_bounded_by_the_budget():
    # 8 separate requests answered after 0.1 s each: 0.8 s unbounded, the budget is 0.35 s
    tags = [TagConfig(f"t{i}", "input", 40 * i, "uint16", "ABCD", 1.0, 0.0, "1", (0, 10), 30)
            for i in range(8)]

    async def scenario():
        async with modbus_server({40 * i: i for i in range(8)}, {}, delay_s=0.1) as server:
            async with client(server.port, tags=tags, budget=0.35, timeout_s=1.0) as plc:
                await plc.connect()
                return await plc.read_all()

    result = run(scenario())
    marks = [result.values[f"t{i}"].bad for i in range(8)]
    assert marks[0] is None and result.values["t0"].value == 0
    assert marks[-1] is not None
    assert set(marks) - {None} <= {"timeout", "cycle budget exhausted"}
    assert result.duration_s < 0.7     # stopped at the budget (+ slack), not after 8 x 0.1 s


def test_connection_refused_then_backoff_then_recovery(caplog):
    now = [1000.0]
    port = free_port()

    async def scenario():
        plc = client(port, clock=lambda: now[0], reconnect_min_s=1.0, reconnect_max_s=4.0)
        with pytest.raises(PlcCommError) as refused:
            await plc.connect()
        delays = [plc.retry_in_s]
        result = await plc.read_all()             # inside the back-off: no attempt at all
        attempts_during_backoff = sum("connect failed" in r.message for r in caplog.records)
        for _ in range(4):
            now[0] += plc.retry_in_s
            await plc.read_all()                  # attempt, fails, back-off doubles
            delays.append(plc.retry_in_s)
        async with plant_server(port=port):
            now[0] += plc.retry_in_s
            recovered = await plc.read_all()
            await plc.close()
        return refused.value, delays, result, attempts_during_backoff, recovered

    with caplog.at_level(logging.DEBUG, logger="edge.plc"):
        refused, delays, result, attempts, recovered = run(scenario())
    assert refused.reason == "connect failed"
    assert delays == [1.0, 2.0, 4.0, 4.0, 4.0]
    assert attempts == 1
    assert result.comm_error == "connect failed" and result.requests == 0
    assert {v.bad for v in result.values.values()} == {"connect failed"}
    assert recovered.comm_error is None and all(v.ok for v in recovered.values.values())
    failed = [r for r in caplog.records if "connect failed" in r.message]
    assert [r.levelno for r in failed] == [logging.WARNING] + [logging.DEBUG] * 4
    assert [r.message for r in caplog.records if r.levelno == logging.WARNING
            and "answering again" in r.message] == [
        f"PLC 127.0.0.1:{port}: answering again after 5 failure(s) in 15 s"]


# ------------------------------------------------------------------------------- writing

def test_write_advisory_is_one_fc16_of_the_whole_block():
    values = {"p_m_sp_rec": 17.5, "dCOP_pct": 1.25, "last_update": 1_718_000_000, "COP_measured": 4.4}
    words = encode_advisory(CFG.advisory, values, {"calibration_failed"}, heartbeat=3)

    async def scenario():
        async with plant_server() as server:
            async with client(server.port) as plc:
                await plc.connect()
                await plc.write_advisory(words)
                stored = await server.async_getValues(1, 3, 1000, 64)
                back = await plc.read_advisory()
            return server.requests, stored, back

    requests, stored, back = run(scenario())
    writes = [r for r in requests if r[0] == 16]
    assert writes == [(16, 1000, 64, words)]
    assert stored == words == back
    decoded = decode_advisory(CFG.advisory, back)
    assert decoded["p_m_sp_rec"] == 17.5 and decoded["status_bits"] == ["calibration_failed"]
    assert decoded["heartbeat"] == 3 and decoded["last_update"] == 1_718_000_000


@pytest.mark.parametrize("address, count", [(999, 2), (1063, 2), (110, 1), (0, 1), (1000, 65)])
def test_write_outside_the_advisory_block_is_refused_before_sending(address, count, monkeypatch):
    sent = []

    async def spy(self, *args, **kwargs):
        sent.append(args)
        raise AssertionError("nothing may be sent")

    monkeypatch.setattr("pymodbus.client.AsyncModbusTcpClient.write_registers", spy)

    async def scenario():
        async with plant_server() as server:
            async with client(server.port) as plc:
                await plc.connect()
                with pytest.raises(WriteOutsideAdvisoryBlock, match="refusing to write"):
                    await plc.write_registers(address, [0] * count)
            offline = client(free_port())           # not even connected: still refused first
            with pytest.raises(WriteOutsideAdvisoryBlock):
                await offline.write_registers(address, [0] * count)
            return server.requests

    requests = run(scenario())
    assert sent == [] and [r for r in requests if r[0] == 16] == []


def test_write_arguments_are_checked():
    async def scenario():
        plc = client(free_port())
        with pytest.raises(ValueError, match="64 words, got 31"):
            await plc.write_advisory([0] * 31)
        with pytest.raises(ValueError, match="not an integer 0..65535"):
            await plc.write_registers(1000, [70000])
        with pytest.raises(PlcCommError, match="not connected"):
            await plc.write_registers(1000, [1])

    run(scenario())


# ------------------------------------------------------------------------- read command

def cli(*argv) -> int:
    parser = argparse.ArgumentParser(prog="hp-edge")
    sub = parser.add_subparsers(dest="command", required=True)
    gateway_cmds.register(sub)
    args = parser.parse_args(list(argv))
    return args.func(args)


def test_read_command_prints_the_block_as_the_hmi_sees_it(capsys):
    words = encode_advisory(CFG.advisory, {"p_m_sp_rec": 16.5, "COP_adaptive": 4.25,
                                           "closed_loop_state": 3, "closed_loop_reason": 31},
                            {"data_stale", "advice_stale"}, heartbeat=42)

    async def scenario():
        async with plant_server() as server:
            await server.async_setValues(1, 16, 1000, words)
            base = ["read", "--config", str(REPO / "config" / "gateway.yaml"),
                    "--host", "127.0.0.1", "--port", str(server.port), "--device-id", "1"]
            text_rc = await asyncio.to_thread(cli, *base)
            text = capsys.readouterr().out
            json_rc = await asyncio.to_thread(cli, *base, "--json")
            return text_rc, text, json_rc, capsys.readouterr().out

    text_rc, text, json_rc, js = run(scenario())
    assert text_rc == 0 and json_rc == 0
    assert "1000     heartbeat               42" in text
    assert "1048     closed_loop_state       3  (shed)" in text
    assert "1049     closed_loop_reason      31  (shed_readback_mismatch)" in text
    assert text.endswith("closed loop: shed (shed_readback_mismatch)\n")
    assert "16.5" in text and "NaN (no value)" in text
    assert "[x]  0 data_stale" in text and "[ ]  5 comm_fault" in text and "[x]  6 advice_stale" in text
    doc = json.loads(js)
    assert doc["fields"]["heartbeat"] == 42 and doc["fields"]["dCOP_pct"] is None
    assert doc["status_bits"] == ["data_stale", "advice_stale"] and doc["words"] == words
    assert doc["closed_loop"] == {"state": "shed", "reason": "shed_readback_mismatch"}


def test_read_command_unreachable_exits_1(capsys):
    rc = cli("read", "--config", str(REPO / "config" / "gateway.yaml"), "--host", "127.0.0.1",
             "--port", str(free_port()), "--timeout", "1")
    err = capsys.readouterr().err
    assert rc == 1
    assert "cannot read the advisory block from 127.0.0.1:" in err and "connect failed" in err


# ------------------------------------------------------------------------ import hygiene

def test_only_plc_module_imports_pymodbus():
    offenders = [p.relative_to(REPO).as_posix() for p in (REPO / "edge").rglob("*.py")
                 if "pymodbus" in p.read_text(encoding="utf-8") and p.name != "plc.py"
                 and any(ln.lstrip().startswith(("import pymodbus", "from pymodbus"))
                         for ln in p.read_text(encoding="utf-8").splitlines())]
    assert offenders == []
    code = ("import sys, edge.config, edge.codec, edge.advisory, edge.commands.gateway_cmds; "
            "print('pymodbus' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
