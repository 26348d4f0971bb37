"""The Modbus side of issue 9 (items 10-14): per-group fallback with retries, reply function
codes, bounded logging, the write guard without a complete tag map, and tag-map coverage
(coils, discrete inputs, bits of a word, BA, 64-bit, several device ids, one connection per poll,
pauses between requests).

Servers listen on 127.0.0.1 on ports chosen at run time: the raw server of tests/modbus_raw.py
(frames built by hand) or a pymodbus server (words encoded by pymodbus). Every scenario is bounded
by asyncio.wait_for; monotonic time for back-off and log summaries is an injected clock.
"""
from __future__ import annotations

import asyncio
import dataclasses
import logging
import struct

import pytest
from modbus_raw import CLOSE, RawServer
from pymodbus.client import ModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from test_plc import CFG, PLANT, image, pm_words

from edge.advisory import encode_advisory
from edge.config import Reserved, TagConfig
from edge.plc import PlcClient, PlcCommError, WriteOutsideAdvisoryBlock

DT = ModbusTcpClient.DATATYPE


def run(coro, timeout: float = 30.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def raw_image(values=PLANT, tags=CFG.tags) -> dict:
    img = {("input", a): w for a, w in image(tags, values, "input").items()}
    img.update({("holding", a): w for a, w in image(tags, values, "holding").items()})
    img.update({("holding", 1000 + i): 0 for i in range(CFG.advisory.size)})
    return img


def client(port, tags=CFG.tags, clock=None, advisory=CFG.advisory, **plc) -> PlcClient:
    cfg = dataclasses.replace(CFG.plc, host="127.0.0.1", port=port,
                              **{"timeout_s": 1.0, "max_read_gap": 10, **plc})
    kw = {"clock": clock} if clock else {}
    return PlcClient(cfg, tags, advisory, reserved=CFG.reserved, cycle_budget_s=4.0, **kw)


def tag(name, register, address, type_="uint16", **kw) -> TagConfig:
    base = dict(byte_order="AB" if type_ in ("int16", "uint16") else "ABCD", scale=1.0,
                offset=0.0, unit="1", range=(-1e30, 1e30), max_age_s=30.0)
    base.update(kw)
    return TagConfig(name, register, address, type_, **base)


# -------------------------------------------------------------------- item 10: per group


def test_a_refused_group_falls_back_alone_and_is_retried_with_backoff(caplog):
    now = [0.0]
    extra = (tag("extra_a", "holding", 200), tag("extra_b", "holding", 205))
    tags = CFG.tags + extra
    img = raw_image()
    img.update({("holding", a): 7 for a in range(200, 206)})   # this group's gap is readable

    async def scenario():
        async with RawServer(img) as srv:
            plc = client(srv.port, tags=tags, clock=lambda: now[0])
            polls = []
            for step, gap_mapped in ((0, False), (30, False), (31, False), (119, False),
                                     (2, True), (1, True)):
                now[0] += step
                if gap_mapped:
                    srv.image.update({("holding", a): 0 for a in range(103, 110)})
                n0 = len(srv.requests)
                result = await plc.read_all()
                polls.append((result, [r[1:] for r in srv.requests[n0:]], plc.split_groups))
            await plc.close()
            return polls

    with caplog.at_level(logging.DEBUG, logger="edge.plc"):
        polls = run(scenario())
    # holding 100..111: plc_clock, life_counter, p_m_sp, closed_loop_enable (the gap 103..109)
    grouped = [(4, 0, 32), (3, 100, 12), (3, 200, 6)]
    per_tag = [(4, 0, 32), (3, 100, 2), (3, 102, 1), (3, 110, 1), (3, 111, 1), (3, 200, 6)]
    refused = [(4, 0, 32), (3, 100, 12), (3, 100, 2), (3, 102, 1), (3, 110, 1), (3, 111, 1), (3, 200, 6)]
    assert [p[1] for p in polls] == [
        refused,            # t=0: exception 2 -> this group tag by tag, the others stay grouped
        per_tag,            # t=30: no retry yet
        refused,            # t=61: retried after 60 s, refused again -> next retry in 120 s
        per_tag,            # t=180: still waiting (retry due at 181)
        grouped[:2] + [(3, 200, 6)],   # t=182: retried and accepted: grouped again
        grouped,            # t=183
    ]
    assert [p[2] for p in polls] == [[(1, "holding", 100)]] * 4 + [[], []]
    for result, _, _ in polls:
        assert result.comm_error is None and all(v.ok for v in result.values.values())
    warnings = [r.message for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "reading tags plc_clock, life_counter, p_m_sp, closed_loop_enable one by one; " \
        "the grouped read is tried again in 60 s" in warnings[0]
    assert sum("is accepted again" in r.message for r in caplog.records) == 1


# -------------------------------------------------------------- item 11: function codes


@pytest.mark.parametrize("reply, fragment", [
    (bytes([3, 4, 0, 1, 0, 2]), "the reply is for function 3, not 4"),   # FC3 data for FC4
    (bytes([0x83, 2]), "exception reply for function 3"),                 # FC3's exception
    (bytes([4, 2, 0, 1]), "asked 2 registers, got 1"),                    # short reply
])
def test_a_reply_to_another_function_is_not_data(reply, fragment):
    async def scenario():
        async with RawServer(raw_image()) as srv:
            srv.misbehave = lambda dev, fc, a, n, pdu: reply if fc == 4 else None
            plc = client(srv.port)
            await plc.connect()
            with pytest.raises(PlcCommError) as info:
                await plc.read_registers("input", 0, 2)
            dropped = not plc.connected
            result = await plc.read_all()
            await plc.close()
            return info.value, dropped, result

    err, dropped, result = run(scenario())
    assert err.reason == "protocol error" and fragment in str(err)
    assert dropped                                    # the stream is not trusted any more
    assert result.comm_error == "protocol error"
    assert result.values["T_sink_in"].value is None   # never decoded as data


@pytest.mark.parametrize("reply, fragment", [
    (lambda a, n, pdu: struct.pack(">BHH", 6, a, struct.unpack(">H", pdu[6:8])[0]),
     "the reply is for function 6, not 16"),
    (lambda a, n, pdu: struct.pack(">BHH", 16, a, n - 1),
     "the reply confirms 63 registers at 1000"),
    (lambda a, n, pdu: struct.pack(">BHH", 16, a + 1, n),
     "the reply confirms 64 registers at 1001"),
])
def test_a_write_is_confirmed_only_by_its_own_echo(reply, fragment):
    words = encode_advisory(CFG.advisory, {}, set(), heartbeat=1)

    async def scenario():
        async with RawServer(raw_image()) as srv:
            srv.misbehave = lambda dev, fc, a, n, pdu: reply(a, n, pdu) if fc == 16 else None
            plc = client(srv.port)
            await plc.connect()
            with pytest.raises(PlcCommError) as info:
                await plc.write_advisory(words)
            await plc.close()
            return info.value

    err = run(scenario())
    assert err.reason == "protocol error" and fragment in str(err)


# -------------------------------------------------------------- item 12: log flooding


def test_garbled_frames_are_one_failure_each_and_the_log_stays_short(caplog):
    now = [0.0]

    def garble(dev, fc, a, n, pdu):
        return bytes([3, 16, 0]) if fc == 3 else None    # byte count 16, one byte follows

    async def scenario():
        async with RawServer(raw_image()) as srv:
            srv.misbehave = garble
            plc = client(srv.port, clock=lambda: now[0], max_read_gap=0)
            results = []
            for _ in range(61):                  # t = 0, 5, ..., 300 s
                results.append(await plc.read_all())
                now[0] += 5.0
            srv.misbehave = None
            recovered = await plc.read_all()
            await plc.close()
            return results, recovered

    with caplog.at_level(logging.DEBUG), caplog.at_level(logging.DEBUG, logger="edge.plc"):
        results, recovered = run(scenario())
    assert {r.comm_error for r in results} == {"protocol error"}
    assert results[0].values["T_sink_in"].ok          # the FC4 group was fine
    assert results[0].values["plc_clock"].bad == "protocol error"
    assert recovered.comm_error is None
    mine = [r.getMessage() for r in caplog.records
            if r.name == "edge.plc" and r.levelno >= logging.WARNING]
    assert len(mine) == 3, mine
    assert "malformed reply" in mine[0] and "repeats are summarised at most every 300 s" in mine[0]
    assert "still failing: 61 failures in 300 s; last: protocol error: function 3 at 100..102: " \
        "malformed reply" in mine[1]
    assert mine[2] == "PLC 127.0.0.1:%d: answering again after 61 failure(s) in 305 s" % \
        int(mine[2].split(":")[1].split()[0])
    asyncio_errors = [r for r in caplog.records
                      if r.name.startswith("asyncio") and r.levelno >= logging.WARNING]
    assert asyncio_errors == []       # no "Fatal error: protocol.data_received()" tracebacks


def test_flapping_is_summarised_not_repeated(caplog):
    """A PLC that answers one poll and fails the next: two loud lines per summary interval."""
    now = [0.0]
    count = [0]

    def every_other(dev, fc, a, n, pdu):
        if fc == 4:
            count[0] += 1
            return CLOSE if count[0] % 2 == 0 else None
        return None

    async def scenario():
        async with RawServer(raw_image()) as srv:
            srv.misbehave = every_other
            plc = client(srv.port, clock=lambda: now[0], max_read_gap=0)
            for _ in range(40):                  # 200 s of 5-s polls
                await plc.read_all()
                now[0] += 5.0
            await plc.close()

    with caplog.at_level(logging.DEBUG, logger="edge.plc"):
        run(scenario())
    loud = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(loud) == 2, loud     # the first failure and its recovery; the rest summarised
    assert "connection lost" in loud[0] and "answering again after 1 failure(s)" in loud[1]


# ------------------------------------------------------ item 13: the write guard alone


def test_write_guard_holds_when_the_tag_map_is_incomplete():
    """The campaign's case: p_m_sp missing from tags.yaml and the block moved onto 110. Even if
    such a configuration reached the client, nothing is sent."""
    tags = tuple(t for t in CFG.tags if t.name != "p_m_sp")
    moved = dataclasses.replace(CFG.advisory, start=110)
    words = [0] * CFG.advisory.size

    async def scenario():
        async with RawServer(raw_image()) as srv:
            plc = client(srv.port, tags=tags, advisory=moved)
            await plc.connect()
            with pytest.raises(WriteOutsideAdvisoryBlock) as moved_block:
                await plc.write_advisory(words)
            plain = client(srv.port, tags=tags)
            await plain.connect()
            with pytest.raises(WriteOutsideAdvisoryBlock) as direct:
                await plain.write_registers(110, [1600])     # the set point, directly
            inside = client(srv.port, tags=tags + (tag("pm", "holding", 1005),))
            await inside.connect()
            with pytest.raises(WriteOutsideAdvisoryBlock) as over_tag:
                await inside.write_advisory(words)
            for p in (plc, plain, inside):
                await p.close()
            return srv.requests, moved_block.value, direct.value, over_tag.value

    requests, moved_block, direct, over_tag = run(scenario())
    assert [r for r in requests if r[1] in (6, 16)] == []           # nothing written, ever
    assert str(moved_block) == ("refusing to write holding registers 110..173: they overlap "
                                "reserved holding 0..999 (PLC-owned)")
    assert str(direct) == ("refusing to write holding registers 110..110: writes are allowed "
                           "only inside the advisory block holding 1000..1063")
    assert str(over_tag) == ("refusing to write holding registers 1000..1063: they overlap tag "
                             "'pm' (holding 1005..1005, PLC-owned)")
    assert CFG.reserved == (Reserved("holding", 0, 999),)


# ------------------------------------------------------------ item 14: tag-map coverage


def _swap(words):
    return [((w & 0xFF) << 8) | (w >> 8) for w in words]


COVERAGE_TAGS = (
    tag("running", "holding", 30, bit=0),
    tag("cip", "holding", 30, bit=3),
    tag("valve_open", "coil", 5, "bool", byte_order="AB", range=(0.0, 1.0)),
    tag("pump_fault", "discrete_input", 2, "bool", byte_order="AB", range=(0.0, 1.0)),
    tag("T_ba", "input", 10, "uint16", byte_order="BA", scale=0.1, unit="degC"),
    tag("count64", "input", 20, "int64"),
    tag("energy64", "input", 24, "uint64", byte_order="DCBA"),
    tag("ratio64", "input", 28, "float64", byte_order="CDAB"),
    tag("W_meter", "input", 0, "float32", unit="W", device_id=2, range=(0, 2e6)),
)
EXPECTED = {"running": 1.0, "cip": 1.0, "valve_open": 1.0, "pump_fault": 0.0, "T_ba": 42.5,
            "count64": -1_234_567_890_123.0, "energy64": 9_876_543_210_987.0,
            "ratio64": 0.123456789012345, "W_meter": 263.5}     # W -> kW


def _coverage_server():
    i64 = ModbusTcpClient.convert_to_registers(-1_234_567_890_123, DT.INT64, "big")
    u64 = _swap(ModbusTcpClient.convert_to_registers(9_876_543_210_987, DT.UINT64, "little"))
    f64 = ModbusTcpClient.convert_to_registers(0.123456789012345, DT.FLOAT64, "little")
    inputs = [0] * 32
    inputs[10] = _swap([425])[0]
    inputs[20:24], inputs[24:28], inputs[28:32] = i64, u64, f64
    holding = [0] * 40
    holding[30] = 0b1001                                  # bits 0 and 3
    coils = [False] * 16
    coils[5] = True
    discrete = [True, True, False] + [False] * 13
    meter = ModbusTcpClient.convert_to_registers(263_500.0, DT.FLOAT32, "big")
    requests = []

    def trace(sending, pdu):
        if not sending:
            requests.append((pdu.dev_id, pdu.function_code, pdu.address, pdu.count))
        return pdu

    bits = lambda values: [SimData(0, values=values, datatype=DataType.BITS)]   # noqa: E731
    regs = lambda values: [SimData(0, values=values, datatype=DataType.REGISTERS)]   # noqa: E731
    plc = SimDevice(1, simdata=(bits(coils), bits(discrete), regs(holding), regs(inputs)))
    meter_dev = SimDevice(2, simdata=(bits([False] * 16), bits([False] * 16), regs([0] * 4),
                                      regs(meter + [0, 0])))
    server = ModbusTcpServer([plc, meter_dev], address=("127.0.0.1", 0), trace_pdu=trace)
    return server, requests


def test_coils_discrete_inputs_bits_ba_64_bit_and_a_second_device():
    async def scenario():
        server, requests = _coverage_server()
        await server.serve_forever(background=True)
        port = server.transport.sockets[0].getsockname()[1]
        try:
            async with client(port, tags=COVERAGE_TAGS) as plc:
                result = await plc.read_all()
        finally:
            await server.shutdown()
        return result, requests

    result, requests = run(scenario())
    assert result.comm_error is None
    for name, expected in EXPECTED.items():
        v = result.values[name]
        assert v.ok, (name, v.bad)
        assert v.value == pytest.approx(expected, rel=1e-12), name
    assert result.values["T_ba"].raw == 425 and result.values["T_ba"].words == (0xA901,)
    # grouped per (device, space): device 1 input, holding (both bits in one read), discrete,
    # coil; then device 2
    assert requests == [(1, 4, 10, 22), (1, 3, 30, 1), (1, 2, 2, 1), (1, 1, 5, 1), (2, 4, 0, 2)]


def test_one_connection_per_poll_and_pauses_between_requests():
    words = encode_advisory(CFG.advisory, {}, set(), heartbeat=1)

    async def cycles(**plc_kw):
        async with RawServer(raw_image()) as srv:
            plc = client(srv.port, max_read_gap=0, **plc_kw)
            for _ in range(3):
                result = await plc.read_all()
                assert result.comm_error is None
                await plc.write_advisory(words)
                connected_after_write = plc.connected
            await plc.close()
            return srv.connections, connected_after_write, srv.requests, srv.times

    conns, after, _, _ = run(cycles(close_after_poll=True))
    assert conns == 3 and not after              # Telegraf's close_connection_after_gather
    conns, after, _, _ = run(cycles())
    assert conns == 1 and after
    _, _, requests, times = run(cycles(pause_between_requests_s=0.05))
    assert [r[1] for r in requests[:4]] == [4, 3, 3, 16]   # three reads and the write
    gaps = [b - a for a, b in zip(times, times[1:])]
    assert min(gaps) >= 0.045                    # Telegraf's pause_between_requests


def test_device_id_of_a_tag_goes_on_the_wire():
    async def scenario():
        async with RawServer({("input", 0): 1, ("input", 1): 2}) as srv:
            tags = (tag("a", "input", 0), tag("b", "input", 1, device_id=7))
            async with client(srv.port, tags=tags) as plc:
                result = await plc.read_all()
            return result, srv.requests

    result, requests = run(scenario())
    assert requests == [(1, 4, 0, 1), (7, 4, 1, 1)]
    assert result.values["b"].value == 2.0


def test_pm_words_helper_is_independent():
    # the helper used above encodes with pymodbus, not with edge.codec
    assert pm_words(CFG.tag("p_suc_LS"), 2.5) == [0x0000, 0x4020]
