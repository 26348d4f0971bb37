"""Register codec, read planner and advisory encoder: golden words, pymodbus cross-checks, properties."""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.client import ModbusTcpClient

from edge.advisory import decode_advisory, encode_advisory, status_word
from edge.codec import (
    BYTE_ORDERS,
    TYPES,
    bit_of,
    decode,
    encode,
    format_number,
    plan_reads,
    raw_limits,
    raw_to_registers,
    raw_value,
)
from edge.config import load_config

REPO = Path(__file__).resolve().parents[1]
DT = ModbusTcpClient.DATATYPE
PYMODBUS_TYPE = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32,
                 "uint32": DT.UINT32, "float32": DT.FLOAT32, "int64": DT.INT64,
                 "uint64": DT.UINT64, "float64": DT.FLOAT64}
# pymodbus' word_order covers two of our byte orders; BADC/DCBA are checked by golden tables
PYMODBUS_ORDER = {"ABCD": "big", "CDAB": "little"}

# (value, type, byte_order, scale, offset, registers) -- written out by hand from IEEE 754 / two's complement
GOLDEN = [
    (25.5, "float32", "ABCD", 1.0, 0.0, [0x41CC, 0x0000]),
    (25.5, "float32", "CDAB", 1.0, 0.0, [0x0000, 0x41CC]),
    (25.5, "float32", "BADC", 1.0, 0.0, [0xCC41, 0x0000]),
    (25.5, "float32", "DCBA", 1.0, 0.0, [0x0000, 0xCC41]),
    (-1.0, "float32", "ABCD", 1.0, 0.0, [0xBF80, 0x0000]),
    (0.1, "float32", "ABCD", 1.0, 0.0, [0x3DCC, 0xCCCD]),
    (0.1, "float32", "CDAB", 1.0, 0.0, [0xCCCD, 0x3DCC]),
    (0.1, "float32", "BADC", 1.0, 0.0, [0xCC3D, 0xCDCC]),
    (0.1, "float32", "DCBA", 1.0, 0.0, [0xCDCC, 0xCC3D]),
    (0x12345678, "int32", "ABCD", 1.0, 0.0, [0x1234, 0x5678]),
    (0x12345678, "int32", "CDAB", 1.0, 0.0, [0x5678, 0x1234]),
    (0x12345678, "int32", "BADC", 1.0, 0.0, [0x3412, 0x7856]),
    (0x12345678, "int32", "DCBA", 1.0, 0.0, [0x7856, 0x3412]),
    (-2, "int32", "ABCD", 1.0, 0.0, [0xFFFF, 0xFFFE]),
    (-2, "int32", "CDAB", 1.0, 0.0, [0xFFFE, 0xFFFF]),
    (-2, "int32", "BADC", 1.0, 0.0, [0xFFFF, 0xFEFF]),
    (-2147483648, "int32", "ABCD", 1.0, 0.0, [0x8000, 0x0000]),
    (4294967295, "uint32", "ABCD", 1.0, 0.0, [0xFFFF, 0xFFFF]),
    (65536, "uint32", "ABCD", 1.0, 0.0, [0x0001, 0x0000]),
    (65536, "uint32", "CDAB", 1.0, 0.0, [0x0000, 0x0001]),
    (-1, "int16", "ABCD", 1.0, 0.0, [0xFFFF]),
    (-32768, "int16", "ABCD", 1.0, 0.0, [0x8000]),
    (32767, "int16", "ABCD", 1.0, 0.0, [0x7FFF]),
    (65535, "uint16", "ABCD", 1.0, 0.0, [0xFFFF]),
    (25.5, "int16", "ABCD", 0.01, 0.0, [0x09F6]),       # raw 2550
    (-12.3, "int16", "ABCD", 0.1, 0.0, [0xFF85]),       # raw -123
    (373.15, "uint16", "ABCD", 0.01, 273.15, [0x2710]),  # raw 10000
    (1234.5, "uint16", "ABCD", 0.5, 0.0, [0x09A5]),     # raw 2469
    (0x1234, "uint16", "BA", 1.0, 0.0, [0x3412]),       # 16-bit byte swap
    (-2, "int16", "BA", 1.0, 0.0, [0xFEFF]),
    (0x0102030405060708, "uint64", "ABCD", 1.0, 0.0, [0x0102, 0x0304, 0x0506, 0x0708]),
    (0x0102030405060708, "uint64", "CDAB", 1.0, 0.0, [0x0708, 0x0506, 0x0304, 0x0102]),
    (0x0102030405060708, "uint64", "BADC", 1.0, 0.0, [0x0201, 0x0403, 0x0605, 0x0807]),
    (0x0102030405060708, "uint64", "DCBA", 1.0, 0.0, [0x0807, 0x0605, 0x0403, 0x0201]),
    (-2, "int64", "ABCD", 1.0, 0.0, [0xFFFF, 0xFFFF, 0xFFFF, 0xFFFE]),
    (1.0, "float64", "ABCD", 1.0, 0.0, [0x3FF0, 0x0000, 0x0000, 0x0000]),
    (25.5, "float64", "CDAB", 1.0, 0.0, [0x0000, 0x0000, 0x8000, 0x4039]),  # 0x4039800000000000
]


@pytest.mark.parametrize("value, type_, order, scale, offset, words", GOLDEN)
def test_golden_encode(value, type_, order, scale, offset, words):
    assert encode(value, type_, order, scale, offset) == words


@pytest.mark.parametrize("value, type_, order, scale, offset, words", GOLDEN)
def test_golden_decode(value, type_, order, scale, offset, words):
    got = decode(words, type_, order, scale, offset)
    tol = 1e-7 * abs(value) if type_ == "float32" else 1e-9 * max(1.0, abs(value))
    assert abs(got - value) <= tol


def test_16_bit_types_ignore_the_32_bit_orders_and_swap_with_BA():
    for order in BYTE_ORDERS + ("AB",):
        assert encode(-2, "int16", order) == [0xFFFE]
        assert raw_value([0x1234], "uint16", order) == 0x1234
    assert raw_value([0x1234], "uint16", "BA") == 0x3412
    with pytest.raises(ValueError, match="unknown byte order 'BA' for a 32/64-bit value"):
        raw_value([0, 0], "float32", "BA")


def test_bit_of_a_word():
    word = 0b1000_0000_0000_0101
    assert [bit_of(word, b) for b in range(16)] == [1, 0, 1] + [0] * 12 + [1]
    with pytest.raises(ValueError, match="bit 16 is not 0..15"):
        bit_of(word, 16)
    with pytest.raises(ValueError, match="not an integer 0..65535"):
        bit_of(-1, 0)


def test_float32_nan_and_infinity():
    assert encode(math.nan, "float32") == [0x7FC0, 0x0000]
    assert encode(math.nan, "float32", "CDAB") == [0x0000, 0x7FC0]
    assert math.isnan(decode([0x7FC0, 0x0000], "float32"))
    assert decode([0x7F80, 0x0000], "float32") == math.inf
    assert decode([0xFF80, 0x0000], "float32", scale=2.0) == -math.inf


def test_raw_value_is_the_unscaled_integer_for_sentinels():
    assert raw_value([0x8000], "int16") == -32768
    assert raw_value([0xFFFF], "uint16") == 65535
    assert decode([0x8000], "int16", scale=0.01) == pytest.approx(-327.68)
    assert raw_value([0x0000, 0x41CC], "float32", "CDAB") == 25.5


@pytest.mark.parametrize("value, type_, scale, offset, fragment", [
    (400.0, "int16", 0.01, 0.0, "raw 40000) does not fit int16 [-32768, 32767]"),
    (-0.01, "uint16", 0.01, 0.0, "raw -1) does not fit uint16 [0, 65535]"),
    (4294967296, "uint32", 1.0, 0.0, "does not fit uint32 [0, 4294967295]"),
    (-2147483649, "int32", 1.0, 0.0, "does not fit int32"),
    (math.nan, "int16", 1.0, 0.0, "cannot be encoded as int16 (not finite)"),
    (math.inf, "uint32", 1.0, 0.0, "not finite"),
    (1e39, "float32", 1.0, 0.0, "does not fit float32"),
    (1.0, "float32", 1e-39, 0.0, "does not fit float32"),
    (1.0, "int16", 0.0, 0.0, "scale must not be 0"),
])
def test_encode_refuses_what_does_not_fit(value, type_, scale, offset, fragment):
    with pytest.raises(ValueError) as info:
        encode(value, type_, "ABCD", scale, offset)
    assert fragment in str(info.value)


def test_encode_boundaries_fit_exactly():
    assert encode(327.67, "int16", scale=0.01) == [0x7FFF]
    assert encode(-327.68, "int16", scale=0.01) == [0x8000]
    assert encode(655.35, "uint16", scale=0.01) == [0xFFFF]


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError, match="needs 2 register"):
        decode([1], "float32")
    with pytest.raises(ValueError, match="not an integer 0..65535"):
        decode([70000], "uint16")
    with pytest.raises(ValueError, match="unknown type 'int17'"):
        encode(1, "int17")
    with pytest.raises(ValueError, match="unknown byte order 'ABDC'"):
        decode([0, 0], "int32", "ABDC")
    with pytest.raises(TypeError):
        encode("1", "int16")
    with pytest.raises(ValueError, match="must be an integer"):
        raw_to_registers(1.5, "int16")


def test_format_number_keeps_config_numbers_exact():
    assert format_number(4294967295.0) == "4294967295"
    assert format_number(0.01) == "0.01"
    assert format_number(-0.9) == "-0.9"
    assert format_number(-32768) == "-32768"


# ---------------------------------------------------------------- pymodbus cross-checks

def _values_of(type_):
    if type_ == "float32":
        return st.floats(width=32, allow_nan=False)
    if type_ == "float64":
        return st.floats(allow_nan=False)
    lo, hi = raw_limits(type_)
    return st.integers(int(lo), int(hi))


@pytest.mark.parametrize("type_", list(TYPES))
@pytest.mark.parametrize("order", list(PYMODBUS_ORDER))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_matches_pymodbus_convert(type_, order, data):
    raw = data.draw(_values_of(type_))
    ours = raw_to_registers(raw, type_, order)
    theirs = ModbusTcpClient.convert_to_registers(raw, PYMODBUS_TYPE[type_], PYMODBUS_ORDER[order])
    assert ours == theirs
    back = ModbusTcpClient.convert_from_registers(ours, PYMODBUS_TYPE[type_], PYMODBUS_ORDER[order])
    assert raw_value(ours, type_, order) == back


# ---------------------------------------------------------------- round-trip properties

words = st.integers(0, 0xFFFF)


@pytest.mark.parametrize("type_", list(TYPES))
@pytest.mark.parametrize("order", BYTE_ORDERS)
@settings(max_examples=60, deadline=None)
@given(regs=st.lists(words, min_size=4, max_size=4))
def test_registers_survive_raw_round_trip(type_, order, regs):
    regs = regs[: TYPES[type_][1]]
    raw = raw_value(regs, type_, order)
    if isinstance(raw, float) and math.isnan(raw):
        assert math.isnan(raw_value(raw_to_registers(raw, type_, order), type_, order))
    else:
        assert raw_to_registers(raw, type_, order) == regs


@settings(max_examples=100, deadline=None)
@given(regs=st.lists(words, min_size=2, max_size=2))
def test_byte_orders_are_swaps_of_abcd(regs):
    swap = [((w & 0xFF) << 8) | (w >> 8) for w in regs]
    v = raw_value(regs, "uint32", "ABCD")
    assert raw_value(regs[::-1], "uint32", "CDAB") == v
    assert raw_value(swap, "uint32", "BADC") == v
    assert raw_value(swap[::-1], "uint32", "DCBA") == v


@pytest.mark.parametrize("type_", ["int16", "uint16", "int32", "uint32"])
@settings(max_examples=80, deadline=None)
@given(data=st.data(), scale=st.sampled_from([1.0, 0.1, 0.01, 0.001, 2.5, -0.5]),
       offset=st.sampled_from([0.0, -273.15, 100.0]), order=st.sampled_from(BYTE_ORDERS))
def test_integer_engineering_round_trip(type_, data, scale, offset, order):
    lo, hi = raw_limits(type_)
    raw = data.draw(st.integers(int(lo), int(hi)))
    value = raw * scale + offset
    regs = encode(value, type_, order, scale, offset)
    assert raw_value(regs, type_, order) == raw
    assert decode(regs, type_, order, scale, offset) == pytest.approx(value, rel=1e-12, abs=1e-9)


@settings(max_examples=100, deadline=None)
@given(value=st.floats(-1e30, 1e30, allow_nan=False), order=st.sampled_from(BYTE_ORDERS))
def test_float32_engineering_round_trip(value, order):
    regs = encode(value, "float32", order)
    assert decode(regs, "float32", order) == struct.unpack(">f", struct.pack(">f", value))[0]


# ---------------------------------------------------------------------------- read planner

@dataclass(frozen=True)
class T:
    name: str
    address: int
    type: str = "uint16"
    register: str = "input"


def _spans(plan):
    return [(r.start, r.count, [t.name for t in r.tags]) for r in plan]


def test_plan_for_default_tags():
    cfg = load_config(REPO / "config" / "gateway.yaml", load_plant=False)
    inputs = [t for t in cfg.tags if t.register == "input"]
    holding = [t for t in cfg.tags if t.register == "holding"]
    assert _spans(plan_reads(inputs)) == [(0, 32, [t.name for t in inputs])]
    assert _spans(plan_reads(holding)) == [
        (100, 12, ["plc_clock", "life_counter", "p_m_sp", "closed_loop_enable"])]
    assert _spans(plan_reads(holding, max_gap=cfg.plc.max_read_gap)) == [   # as shipped: 0
        (100, 3, ["plc_clock", "life_counter"]), (110, 2, ["p_m_sp", "closed_loop_enable"])]
    assert _spans(plan_reads(holding, max_gap=6)) == [
        (100, 3, ["plc_clock", "life_counter"]), (110, 2, ["p_m_sp", "closed_loop_enable"])]


def test_plan_respects_125_registers():
    tags = [T(f"t{i}", i) for i in range(130)]
    plan = plan_reads(tags)
    assert [(r.start, r.count) for r in plan] == [(0, 125), (125, 5)]
    assert [len(r.tags) for r in plan] == [125, 5]


def test_plan_never_splits_a_32_bit_value():
    tags = [T(f"t{i}", i) for i in range(124)] + [T("f", 124, "float32")]
    plan = plan_reads(tags)
    assert [(r.start, r.count) for r in plan] == [(0, 124), (124, 2)]
    assert plan[1].tags[0].name == "f"


def test_plan_gap_rule():
    assert _spans(plan_reads([T("a", 0), T("b", 11)])) == [(0, 12, ["a", "b"])]      # gap 10
    assert _spans(plan_reads([T("a", 0), T("b", 12)])) == [(0, 1, ["a"]), (12, 1, ["b"])]
    assert _spans(plan_reads([T("a", 0, "float32"), T("b", 12)])) == [(0, 13, ["a", "b"])]
    assert _spans(plan_reads([T("a", 0), T("b", 3)], max_gap=1)) == [(0, 1, ["a"]), (3, 1, ["b"])]
    assert _spans(plan_reads([T("b", 5), T("a", 0)], max_gap=0)) == [(0, 1, ["a"]), (5, 1, ["b"])]
    assert plan_reads([]) == []


def test_plan_rejects_mixed_spaces_and_bad_limits():
    with pytest.raises(ValueError, match="one register space"):
        plan_reads([T("a", 0), T("b", 1, register="holding")])
    with pytest.raises(ValueError, match="max_count"):
        plan_reads([T("a", 0)], max_count=126)
    with pytest.raises(ValueError, match="one device"):
        plan_reads([D("a", 0, device_id=1), D("b", 1, device_id=2)])


@dataclass(frozen=True)
class D:
    name: str
    address: int
    type: str = "uint16"
    register: str = "input"
    device_id: int | None = None


def test_plan_of_coils_and_64_bit_values():
    coils = [D(f"c{i}", 10 * i, "bool", "coil") for i in range(300)]
    plan = plan_reads(coils)                     # bits: up to 2000 per request
    assert [(r.start, r.count) for r in plan] == [(0, 1991), (2000, 991)]
    with pytest.raises(ValueError, match="max_count must be 2..2000"):
        plan_reads(coils, max_count=2001)
    wide = [D("a", 0, "float64"), D("b", 4, "int64"), D("c", 8, "uint16")]
    assert _spans(plan_reads(wide, max_gap=0)) == [(0, 9, ["a", "b", "c"])]
    shared = [D("run", 30), D("cip", 30), D("x", 31)]   # two bits of one register
    assert _spans(plan_reads(shared, max_gap=0)) == [(30, 2, ["run", "cip", "x"])]


def _min_requests(tags, max_gap, max_count):
    """Brute-force dynamic programme: fewest requests covering consecutive runs of tags."""
    tags = sorted(tags, key=lambda t: t.address)
    end = [t.address + TYPES[t.type][1] for t in tags]
    best = [0] + [math.inf] * len(tags)
    for i in range(1, len(tags) + 1):
        for j in range(i):
            run_ok = end[i - 1] - tags[j].address <= max_count and all(
                tags[k + 1].address - end[k] <= max_gap for k in range(j, i - 1))
            if run_ok:
                best[i] = min(best[i], best[j] + 1)
    return best[-1]


@st.composite
def tag_layouts(draw):
    n = draw(st.integers(0, 40))
    address, tags = 0, []
    for i in range(n):
        address += draw(st.integers(0, 30))
        type_ = draw(st.sampled_from(["uint16", "float32"]))
        tags.append(T(f"t{i}", address, type_))
        address += TYPES[type_][1]
    return tags


@settings(max_examples=150, deadline=None)
@given(tags=tag_layouts(), max_gap=st.integers(0, 12), max_count=st.integers(2, 125))
def test_plan_properties(tags, max_gap, max_count):
    plan = plan_reads(tags, max_gap=max_gap, max_count=max_count)
    assert sorted(t.name for r in plan for t in r.tags) == sorted(t.name for t in tags)
    for r in plan:
        assert 1 <= r.count <= max_count
        ordered = sorted(r.tags, key=lambda t: t.address)
        for t in ordered:   # every value entirely inside its request
            assert r.start <= t.address and t.address + TYPES[t.type][1] <= r.start + r.count
        assert ordered[0].address == r.start
        assert ordered[-1].address + TYPES[ordered[-1].type][1] == r.start + r.count
        for a, b in zip(ordered, ordered[1:]):
            assert b.address - (a.address + TYPES[a.type][1]) <= max_gap
    assert len(plan) == _min_requests(tags, max_gap, max_count)


# ------------------------------------------------------------------------- advisory block

@pytest.fixture(scope="module")
def adv():
    return load_config(REPO / "config" / "gateway.yaml", load_plant=False).advisory


def test_advisory_encode_layout(adv):
    words = encode_advisory(adv, {"p_m_sp_rec": 16.0, "last_update": 0x12345678,
                                  "COP_measured": 4.5, "advice_age_s": 60},
                            {"data_stale", "comm_fault"}, heartbeat=7)
    assert len(words) == adv.size == 64
    assert words[0] == 7
    assert words[1] == 0b100001
    assert words[2:4] == [0x1234, 0x5678]
    assert words[4:6] == [0x4180, 0x0000]        # 16.0 as float32 ABCD
    assert words[20:22] == [0x4090, 0x0000]      # 4.5
    assert words[28:30] == [0x0000, 60]
    assert words[6:8] == [0x7FC0, 0x0000]        # dCOP_pct not given -> NaN
    assert words[30:32] == [0x7FC0, 0x0000]      # dCOP_sd_pct not given -> NaN
    assert words[36:46] == [0x7FC0, 0x0000] * 5  # the CIP fields (issue 10) not given -> NaN
    assert words[46:48] == [0] * 2               # not covered by any field
    assert words[48:50] == [0, 0]                # closed_loop_state, _reason not given -> 0
    assert words[50:54] == [0x7FC0, 0, 0x7FC0, 0]  # closed_loop_sp_written, _target -> NaN
    assert words[54:] == [0] * 10                # last write, writes; 57..63 not covered


def test_advisory_matches_pymodbus_words(adv):
    values = {"dCOP_pct": 2.75, "R_th_f": 4.2e-3, "nrmse_pct": 1.5}
    words = encode_advisory(adv, values, set(), 0)
    for name, value in values.items():
        off = adv.field(name).offset
        assert words[off:off + 2] == ModbusTcpClient.convert_to_registers(value, DT.FLOAT32, "big")


def test_advisory_round_trip(adv):
    values = {"p_m_sp_rec": 17.25, "dQ_sink_pct": -1.5, "last_update": 1_718_000_000,
              "advice_age_s": 4294967295, "CF_dp_f": math.nan}
    out = decode_advisory(adv, encode_advisory(adv, values, {"cip_detected"}, 65537))
    assert out["heartbeat"] == 1                 # wraps modulo 65536
    assert out["status"] == 0b100
    assert out["status_bits"] == ["cip_detected"]
    assert out["p_m_sp_rec"] == 17.25 and out["dQ_sink_pct"] == -1.5
    assert out["last_update"] == 1_718_000_000 and out["advice_age_s"] == 4294967295
    assert math.isnan(out["CF_dp_f"]) and math.isnan(out["COP_fixed"])


def test_advisory_decode_names_unconfigured_bits(adv):
    words = [0] * 64
    words[1] = (1 << 15) | 1
    assert decode_advisory(adv, words)["status_bits"] == ["data_stale", "bit 15"]


@pytest.mark.parametrize("values, bits, heartbeat, fragment", [
    ({"p_m_sp_recc": 1.0}, set(), 0, "unknown advisory field(s) 'p_m_sp_recc'"),
    ({"heartbeat": 1}, set(), 0, "unknown advisory field(s) 'heartbeat'"),
    ({}, {"data_stail"}, 0, "unknown status bit 'data_stail'"),
    ({}, set(), -1, "heartbeat must be a non-negative integer"),
    ({"last_update": -5}, set(), 0, "advisory field 'last_update': value -5"),
    ({"advice_age_s": math.nan}, set(), 0, "advisory field 'advice_age_s'"),
    ({"dCOP_pct": 1e40}, set(), 0, "advisory field 'dCOP_pct': value 1e+40"),
])
def test_advisory_encode_refuses(adv, values, bits, heartbeat, fragment):
    with pytest.raises(ValueError) as info:
        encode_advisory(adv, values, bits, heartbeat)
    assert fragment in str(info.value)


def test_status_word(adv):
    assert status_word(adv, []) == 0
    assert status_word(adv, ["advice_stale", "data_stale"]) == 0x41
    with pytest.raises(ValueError, match="wrong size|has 64 words"):
        decode_advisory(adv, [0] * 31)
