"""The guarded closed loop (issue 13): each guard on its own, against a fake PLC that records every
set-point request and answers as told; the step planner by property; the gateway loop carries the
state in the advisory block and the audit trail goes to the history database."""
from __future__ import annotations

import asyncio
import math
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.advisory import decode_advisory
from edge.closed_loop import (BLOCKING_BITS, ClosedLoop, ClosedLoopConfig, Reason, State,
                              plan_step, raw_of, value_of)
from edge.codec import raw_to_registers, raw_value
from edge.config import load_config
from edge.loop import Advice, Gateway
from edge.plc import PlcCommError, PlcExceptionReply, ReadResult, TagValue
from edge.store import HistoryStore

ROOT = Path(__file__).resolve().parent.parent
BASE = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
SP = BASE.tag("p_m_sp")              # int16, scale 0.01, bar(g)
EN = BASE.tag("closed_loop_enable")
LOOP = ClosedLoopConfig(enabled=True, setpoint_tag="p_m_sp", enable_tag="closed_loop_enable",
                        bounds_bar_g=(12.0, 18.0), max_step_bar=0.5, min_interval_s=300.0,
                        heartbeat_timeout_s=60.0, shed_after_bad_scans=3, deadband_bar=0.05)
STEP_TOL = 1e-9                      # bar: round-off allowed on the step and the bounds
T0 = 1_709_251_200.0


def words(bar: float) -> tuple[int, ...]:
    """p_m_sp's register words for ``bar`` bar(g) (int16, 0.01 bar per count)."""
    return tuple(raw_to_registers(round(bar * 100), "int16", "AB"))


def run(coro, timeout=20.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


class FakeSetpointPlc:
    """The PLC side of the set-point write path: holds the set point's words; ``hold`` False
    makes it ignore writes (a PLC program that overrides them); ``refuse`` answers with a Modbus
    exception; ``silent`` does not answer."""

    def __init__(self, bar: float = 16.0):
        self.words = words(bar)
        self.requests: list[tuple[int, ...]] = []
        self.hold = True
        self.refuse: int | None = None
        self.silent = False
        self.readback_fails = False

    async def write_setpoint(self, ws):
        self.requests.append(tuple(ws))
        if self.silent:
            raise PlcCommError("timeout", "no reply")
        if self.refuse is not None:
            raise PlcExceptionReply(self.refuse, 16, SP.address, 1)
        if self.hold:
            self.words = tuple(ws)

    async def read_setpoint(self):
        if self.readback_fails:
            raise PlcCommError("timeout", "no reply")
        return list(self.words)

    @property
    def bar(self) -> float:
        return raw_value(list(self.words), "int16", "AB") / 100.0


def scan(plc: FakeSetpointPlc, enable: float | None = 1.0, comm_error: str | None = None,
         sp_bad: str | None = None) -> ReadResult:
    """This scan's values of the two tags the loop reads (the PLC's words as they are)."""
    vals = {"p_m_sp": TagValue("p_m_sp", None, sp_bad) if sp_bad else
            TagValue("p_m_sp", plc.bar, None, plc.words),
            "closed_loop_enable": TagValue("closed_loop_enable", None, "timeout") if enable is None
            else TagValue("closed_loop_enable", enable, None, (int(enable),))}
    return ReadResult(vals, T0, 0.0, 1, comm_error)


class Audit(list):
    def __call__(self, row):
        self.append(dict(row))


def loop(cfg=LOOP, bar=16.0):
    plc = FakeSetpointPlc(bar)
    audit = Audit()
    return ClosedLoop(cfg, SP, EN, plc, audit), plc, audit


REC = {"p_m_sp_rec": 14.2}


async def arm(cl, plc, t=T0, advice=REC):
    """Operator: enable 0 then 1 (the rising edge the loop needs), and one more scan, in which
    the loop writes its first step when there is ``advice``."""
    await cl.step(scan(plc, 0.0), set(), advice, t)
    armed = await cl.step(scan(plc, 1.0), set(), advice, t)
    assert (armed.state, armed.reason) == (State.ARMED, Reason.NONE)
    await cl.step(scan(plc, 1.0), set(), advice, t)


# --------------------------------------------------------------------------- enable / config

def test_disabled_in_config_writes_nothing_and_says_so():
    async def go():
        off = replace(LOOP, enabled=False)
        cl, plc, audit = loop(off)
        for k in range(5):
            st_ = await cl.step(scan(plc, 1.0), set(), REC, T0 + 600 * k)
        return cl, plc, audit, st_
    cl, plc, audit, st_ = run(go())
    assert plc.requests == [] and audit == []
    assert (st_.state, st_.reason) == (State.OFF, Reason.DISABLED_IN_CONFIG)
    assert cl.values()["closed_loop_state"] == 0 and cl.values()["closed_loop_reason"] == 1


def test_enable_off_writes_nothing_and_enable_already_on_at_start_needs_an_edge():
    async def go():
        cl, plc, audit = loop()
        out = []
        for k in range(3):      # enable already on when the gateway starts
            out.append((await cl.step(scan(plc, 1.0), set(), REC, T0 + 600 * k)).reason)
        n_before = len(plc.requests)
        for k in range(3, 5):   # operator drops it
            out.append((await cl.step(scan(plc, 0.0), set(), REC, T0 + 600 * k)).reason)
        n_off = len(plc.requests)
        armed = await cl.step(scan(plc, 1.0), set(), REC, T0 + 600 * 5)   # ... and sets it
        n_armed = len(plc.requests)
        st_ = await cl.step(scan(plc, 1.0), set(), REC, T0 + 600 * 6)      # the scan after
        return out, n_before, n_off + n_armed, st_, plc, audit
    reasons, n_before, n_off, st_, plc, audit = run(go())
    assert reasons == [Reason.ENABLE_EDGE_NEEDED] * 3 + [Reason.OPERATOR_OFF] * 2
    assert n_before == 0 and n_off == 0
    assert (st_.state, st_.reason) == (State.WRITING, Reason.STEPPED)
    assert plc.requests == [words(15.5)] and plc.requests[0] == (0x060E,)
    assert [(r["event"], r.get("state"), r.get("reason")) for r in audit] == [
        ("state", "armed", "none"), ("write", None, None), ("state", "writing", "stepped")]


def test_enable_dropping_stops_writes_at_once_and_leaves_the_value():
    async def go():
        cl, plc, audit = loop()
        await arm(cl, plc)                               # wrote 15.50
        held = plc.words
        st_ = await cl.step(scan(plc, 0.0), set(), REC, T0 + 600)
        for k in range(2, 6):
            await cl.step(scan(plc, 0.0), set(), REC, T0 + 600 * k)
        return st_, plc, held
    st_, plc, held = run(go())
    assert (st_.state, st_.reason) == (State.OFF, Reason.OPERATOR_OFF)
    assert plc.requests == [words(15.5)] and plc.words == held      # nothing written back


def test_unreadable_enable_holds_and_counts_as_a_bad_scan():
    async def go():
        cl, plc, _ = loop()
        await arm(cl, plc)
        a = await cl.step(scan(plc, None), set(), REC, T0 + 600)
        return (a.state, a.reason, a.bad_scans), plc.requests
    got, requests = run(go())
    assert got == (State.ARMED, Reason.ENABLE_UNREADABLE, 1)
    assert requests == [words(15.5)]


# --------------------------------------------------------------------------- bounds and steps

def test_step_limit_interval_and_exact_words_on_the_way_down():
    async def go():
        cl, plc, audit = loop()
        await arm(cl, plc)
        seen = []
        t = T0
        for k in range(1, 40):                         # scans every 60 s of sample clock
            t = T0 + 60 * k
            st_ = await cl.step(scan(plc), set(), REC, t)
            seen.append((t, st_.state, st_.reason))
        return plc.requests, audit, seen
    requests, audit, seen = run(go())
    bars = [raw_value(list(w), "int16", "AB") / 100.0 for w in requests]
    assert bars == [15.5, 15.0, 14.5, 14.2]          # 0.5 bar per write, then the rest
    assert requests == [(1550,), (1500,), (1450,), (1420,)]
    writes = [r for r in audit if r["event"] == "write"]
    assert [(r["old_bar_g"], r["new_bar_g"], r["target_bar_g"], r["words"], r["outcome"])
            for r in writes] == [(16.0, 15.5, 14.2, "1550", "ok"), (15.5, 15.0, 14.2, "1500", "ok"),
                                 (15.0, 14.5, 14.2, "1450", "ok"),
                                 (14.5, pytest.approx(14.2, abs=1e-12), 14.2, "1420", "ok")]
    times = [r["ts"] for r in writes]
    assert min(b - a for a, b in zip(times, times[1:])) >= LOOP.min_interval_s
    assert seen[-1][1:] == (State.ARMED, Reason.AT_TARGET)
    assert (State.WRITING, Reason.WAITING_INTERVAL) in {s[1:] for s in seen}


@pytest.mark.parametrize("rec, end", [(25.0, 18.0), (3.0, 12.0)])
def test_recommendations_outside_the_bounds_stop_at_the_bound(rec, end):
    async def go():
        cl, plc, _ = loop()
        await arm(cl, plc)
        for k in range(1, 30):
            await cl.step(scan(plc), set(), {"p_m_sp_rec": rec}, T0 + 300 * k)
        return plc.requests, cl.status
    requests, status = run(go())
    bars = [raw_value(list(w), "int16", "AB") / 100.0 for w in requests]
    assert bars[-1] == end and all(12.0 <= b <= 18.0 for b in bars)
    steps = [abs(b - a) for a, b in zip([16.0] + bars, bars)]
    assert max(steps) <= LOOP.max_step_bar + STEP_TOL
    assert status.target == end and (status.state, status.reason) == (State.ARMED, Reason.AT_TARGET)


def test_a_plc_value_too_far_outside_the_bounds_is_left_alone():
    async def go():
        cl, plc, _ = loop(bar=10.0)                 # 2 bar below the lower bound
        await arm(cl, plc)
        far = cl.status.reason
        plc.words = words(11.8)                     # within one step of the bound: allowed
        cl._written_words = None                    # (as if the operator had set it before arming)
        await cl.step(scan(plc), set(), REC, T0 + 600)
        return far, plc.requests
    far, requests = run(go())
    assert far == Reason.OUTSIDE_BOUNDS
    assert requests == [words(12.3)]


# --------------------------------------------------------------------------- blocking bits

@pytest.mark.parametrize("bit", BLOCKING_BITS)
def test_every_blocking_bit_alone_holds_the_set_point(bit):
    async def go():
        cl, plc, _ = loop()
        await cl.step(scan(plc, 0.0), {bit}, REC, T0)
        await cl.step(scan(plc, 1.0), {bit}, REC, T0)       # armed
        reasons = []
        for k in range(1, 6):
            st_ = await cl.step(scan(plc, 1.0), {bit}, REC, T0 + 600 * k)
            reasons.append((st_.state, st_.reason))
        held = list(plc.requests)
        cleared = await cl.step(scan(plc, 1.0), set(), REC, T0 + 600 * 6)
        return reasons, held, cleared.reason
    reasons, requests, cleared = run(go())
    blocked = Reason[f"BLOCKED_{bit.upper()}"]
    if bit == "data_stale":          # no usable data: counts toward shedding
        assert reasons[:2] == [(State.ARMED, blocked)] * 2
        assert reasons[2] == (State.SHED, Reason.SHED_BAD_SCANS)
        assert requests == [] and cleared == Reason.SHED_BAD_SCANS
    else:
        assert reasons == [(State.ARMED, blocked)] * 5
        assert requests == [] and cleared == Reason.STEPPED


def test_storage_fault_does_not_block():
    async def go():
        cl, plc, _ = loop()
        await cl.step(scan(plc, 0.0), set(), REC, T0)
        await cl.step(scan(plc, 1.0), set(), REC, T0)        # armed
        await cl.step(scan(plc, 1.0), {"storage_fault"}, REC, T0 + 60)
        return plc.requests
    assert run(go()) == [words(15.5)]


def test_no_advice_and_unknown_clock_hold():
    async def go():
        cl, plc, _ = loop()
        await arm(cl, plc, advice=None)       # no advice: nothing to do
        a = cl.status.reason
        await cl.step(scan(plc), set(), {"p_m_sp_rec": math.nan}, T0 + 60)
        b = cl.status.reason
        await cl.step(scan(plc), set(), REC, None)
        return a, b, cl.status.reason, plc.requests
    a, b, c, requests = run(go())
    assert (a, b, c) == (Reason.NO_ADVICE, Reason.NO_ADVICE, Reason.CLOCK_UNKNOWN)
    assert requests == []


# --------------------------------------------------------------------------- shedding

def test_readback_mismatch_sheds_and_only_the_operator_rearms():
    async def go():
        cl, plc, audit = loop()
        plc.hold = False                          # the PLC program ignores the write
        await arm(cl, plc)
        shed = (cl.status.state, cl.status.reason, cl.status.detail)
        for k in range(1, 5):
            await cl.step(scan(plc), set(), REC, T0 + 600 * k)
        n_shed = len(plc.requests)
        plc.hold = True
        await cl.step(scan(plc, 0.0), set(), REC, T0 + 3000)
        await cl.step(scan(plc, 1.0), set(), REC, T0 + 3060)
        await cl.step(scan(plc, 1.0), set(), REC, T0 + 3120)
        return shed, n_shed, plc.requests, audit
    shed, n_shed, requests, audit = run(go())
    assert shed[:2] == (State.SHED, Reason.SHED_READBACK_MISMATCH)
    assert shed[2] == "wrote 15.50 bar(g) (words [1550]), read back 16.00 (words [1600])"
    assert n_shed == 1                             # one attempt, then nothing while shed
    assert requests == [words(15.5), words(15.5)]  # re-armed by the operator: writes again
    row = next(r for r in audit if r["event"] == "write")
    assert row["outcome"] == "read-back mismatch"


@pytest.mark.parametrize("fault, reason", [("refuse", Reason.SHED_WRITE_REFUSED),
                                           ("silent", Reason.SHED_WRITE_FAILED),
                                           ("readback_fails", Reason.SHED_READBACK_FAILED)])
def test_a_refused_unanswered_or_unconfirmed_write_sheds(fault, reason):
    async def go():
        cl, plc, _ = loop()
        setattr(plc, fault, 3 if fault == "refuse" else True)
        await arm(cl, plc)
        for k in range(1, 4):
            await cl.step(scan(plc), set(), REC, T0 + 600 * k)
        return cl.status, plc.requests
    status, requests = run(go())
    assert (status.state, status.reason) == (State.SHED, reason)
    assert len(requests) == 1
    if fault == "refuse":
        assert status.detail == ("modbus exception 3 (illegal data value) to function 16 at "
                                 "110..110")


def test_shed_after_n_bad_scans_and_not_before():
    async def go():
        cl, plc, _ = loop()
        await arm(cl, plc)                                   # one write
        out = []
        for k in range(1, 3):                                # N - 1 bad scans ...
            out.append((await cl.step(scan(plc, comm_error="timeout"), {"comm_fault"}, REC,
                                      T0 + 600 * k)).state)
        out.append((await cl.step(scan(plc), set(), REC, T0 + 1800)).state)   # ... a good one
        for k in range(4, 6):
            out.append((await cl.step(scan(plc, sp_bad="sentinel"), set(), REC, T0 + 600 * k)).state)
        out.append((await cl.step(scan(plc, comm_error="timeout"), {"comm_fault"}, REC,
                                  T0 + 3600)).state)         # the third in a row
        return out, cl.status, plc.requests
    states, status, requests = run(go())
    assert states[:2] == [State.ARMED, State.ARMED]
    assert states[2] == State.WRITING                        # the count starts again
    assert states[3:5] == [State.ARMED, State.ARMED] and states[5] == State.SHED
    assert status.reason == Reason.SHED_BAD_SCANS
    assert status.detail == "3 bad scans in a row, the last: poll failed: timeout"
    assert requests == [words(15.5), words(15.0)]


def test_a_set_point_changed_behind_the_gateway_sheds():
    async def go():
        cl, plc, _ = loop()
        await arm(cl, plc)                 # wrote 15.50
        plc.words = words(16.0)            # the PLC fell back / the operator typed 16
        await cl.step(scan(plc), set(), REC, T0 + 600)
        return cl.status, plc.requests
    status, requests = run(go())
    assert (status.state, status.reason) == (State.SHED, Reason.SHED_SETPOINT_CHANGED)
    assert status.detail == "the PLC holds 16.00 bar(g), the gateway wrote 15.50"
    assert requests == [words(15.5)]


def test_shutdown_stops_writing_and_is_audited():
    async def go():
        cl, plc, audit = loop()
        await arm(cl, plc)
        await cl.shutdown()
        return cl.status, audit[-1], plc
    status, last, plc = run(go())
    assert (status.state, status.reason) == (State.OFF, Reason.SHUTDOWN)
    assert (last["event"], last["state"], last["reason"]) == ("state", "off", "shutdown")
    assert plc.words == words(15.5)         # left as it is: the PLC owns the fallback


# --------------------------------------------------------------------------- the planner

@settings(max_examples=300, deadline=None)
@given(current=st.integers(-3000, 4000), target=st.floats(0.0, 40.0), lo=st.floats(1.0, 20.0),
       width=st.floats(0.5, 15.0), step=st.floats(0.01, 3.0))
def test_plan_step_respects_bounds_and_step_and_moves_toward_the_target(current, target, lo, width,
                                                                        step):
    hi = lo + width
    tgt = min(max(target, lo), hi)
    ws = raw_to_registers(current, "int16", "AB")
    old = current / 100.0
    plan = plan_step(SP, ws, tgt, step, (lo, hi))
    if plan is None:
        # nothing fits: no register value is both within one step and inside the bounds
        # (the bounds are out of reach), or the target is the current value
        reachable = [r / 100.0 for r in range(current - 400, current + 401)
                     if abs(r / 100.0 - old) <= step + STEP_TOL and lo - STEP_TOL <= r / 100.0 <= hi + STEP_TOL
                     and (r / 100.0 - old) * (tgt - old) > 0]
        assert reachable == [] or abs(tgt - old) < 0.01
        return
    assert lo - STEP_TOL <= plan.value <= hi + STEP_TOL
    assert abs(plan.value - old) <= step + STEP_TOL
    assert (plan.value - old) * (tgt - old) > 0
    assert plan.value == pytest.approx(raw_value(list(plan.words), "int16", "AB") / 100.0, abs=1e-12)
    ideal = old + max(-step, min(step, tgt - old))
    assert abs(plan.value - ideal) <= 0.01 + STEP_TOL       # the nearest register value


def test_plan_step_on_a_float32_set_point_in_kpa_absolute():
    tag = replace(SP, type="float32", byte_order="CDAB", scale=1.0, unit="kPa", pressure="absolute",
                  sentinel=None, canonical=(0.01, -1.01325))
    ws = raw_to_registers(raw_of(tag, 16.0), "float32", "CDAB")
    plan = plan_step(tag, ws, 14.2, 0.5, (12.0, 18.0))
    assert plan.old == pytest.approx(16.0, abs=1e-4)       # float32 of 1701.325 kPa
    assert plan.value == pytest.approx(15.5, abs=1e-4)
    assert abs(plan.value - plan.old) <= 0.5 + STEP_TOL
    assert value_of(tag, raw_value(list(plan.words), "float32", "CDAB")) == plan.value


# --------------------------------------------------------------------------- the gateway loop

GOOD = {"T_sink_in": 40.0, "T_sink_out": 68.0, "T_source_in": 24.0, "T_source_out": 18.0,
        "V_sink": 62.0, "V_source": 192.0, "p_source_in": 2.5, "p_source_out": 2.05,
        "T_suc_LS": 16.0, "T_dis_LS": 80.0, "T_suc_HS": 40.0, "T_dis_HS": 100.0, "T_c": 65.0,
        "T_e": 15.0, "p_suc_LS": 6.3, "p_dis_LS": 15.0, "p_suc_HS": 15.0, "p_dis_HS": 29.0,
        "W_LS": 170.0, "W_HS": 180.0, "N_LS": 1300.0, "N_HS": 1400.0, "running": 1.0,
        "cip": 0.0}


class GatewayPlc(FakeSetpointPlc):
    """The whole fake PLC for the gateway loop: every tag, one minute of plant time per read,
    the advisory block and the set point."""

    def __init__(self, cfg):
        super().__init__(16.0)
        self.plc, self.advisory, self.tags = cfg.plc, cfg.advisory, cfg.tags
        self.t, self.life, self.enable = T0, 0, 0.0
        self.blocks: list[list[int]] = []
        self.connected = True
        self.order: list[str] = []
        self.write_times: list[float] = []

    async def read_all(self):
        self.t += 60.0
        self.life += 1
        j = 0.1 * (self.life % 3)
        vals = {n: TagValue(n, v if n in ("running", "cip") else v + j) for n, v in GOOD.items()}
        vals.update(plc_clock=TagValue("plc_clock", self.t),
                    life_counter=TagValue("life_counter", float(self.life)),
                    p_m_sp=TagValue("p_m_sp", self.bar, None, self.words),
                    closed_loop_enable=TagValue("closed_loop_enable", self.enable, None,
                                                (int(self.enable),)))
        return ReadResult(vals, self.t, 0.0, 2, None)

    async def write_advisory(self, ws):
        self.order.append("block")
        self.blocks.append(list(ws))

    async def write_setpoint(self, ws):
        self.order.append("setpoint")
        self.write_times.append(self.t)
        await super().write_setpoint(ws)

    async def close(self):
        pass


class ConfidentAdvisor:
    def __init__(self, low_confidence=False):
        self.low = low_confidence

    def ingest(self, samples):
        return []

    def advise(self, t_end):
        return Advice(t_end, {"p_m_sp_rec": 14.2, "R_th_f": 3e-3}, low_confidence=self.low)

    def restored(self):
        return None

    has_calibration = True


def gw_cfg():
    return replace(BASE, scan_interval_s=0.02, calibration_interval_s=600.0, min_window_samples=1,
                   closed_loop=replace(LOOP, min_interval_s=120.0))


@pytest.mark.parametrize("low_confidence", [False, True])
def test_the_gateway_writes_steps_and_shows_the_state_in_the_block(low_confidence, tmp_path):
    cfg = gw_cfg()
    store = HistoryStore(tmp_path / "h.sqlite", 30).open()

    async def go():
        plc = GatewayPlc(cfg)
        gw = Gateway(cfg, ConfidentAdvisor(low_confidence), plc=plc, time_source="plc",
                     install_signals=False, audit=store.add_closed_loop_event)
        await gw.startup()
        for _ in range(3):
            await gw.cycle()
        plc.enable = 1.0
        for _ in range(30):
            await gw.cycle()
            await asyncio.sleep(0.005)
        await gw.shutdown()
        return plc, gw

    try:
        plc, gw = run(go())
        events = store.closed_loop_events()
    finally:
        store.close()
    last = decode_advisory(cfg.advisory, plc.blocks[-1])
    if low_confidence:
        assert plc.requests == []
        assert "advice_low_confidence" in last["status_bits"]
        assert (last["closed_loop_state"], last["closed_loop_reason"]) == (1, 25)
        assert [(e["state"], e["reason"]) for e in events] == [("armed", "none"), ("off", "shutdown")]
        return
    assert plc.requests == [(1550,), (1500,), (1450,), (1420,)]
    # the set point is written before the block of the same scan, which reports it
    i = plc.order.index("setpoint")
    first = decode_advisory(cfg.advisory, plc.blocks[plc.order[:i].count("block")])
    assert first["closed_loop_state"] == 2 and first["closed_loop_reason"] == 12
    assert first["closed_loop_sp_written"] == pytest.approx(15.5)
    assert first["closed_loop_target"] == pytest.approx(14.2, abs=1e-6)
    assert first["closed_loop_writes"] == 1
    assert first["closed_loop_last_write"] == plc.write_times[0]     # the scan's sample clock
    assert (last["closed_loop_state"], last["closed_loop_reason"]) == (1, 10)
    assert last["closed_loop_writes"] == 4
    assert plc.blocks[-1][48:50] == [1, 10]
    writes = [e for e in events if e["event"] == "write"]
    assert [x for w in writes for x in (w["old_bar_g"], w["new_bar_g"])] == pytest.approx(
        [16.0, 15.5, 15.5, 15.0, 15.0, 14.5, 14.5, 14.2], abs=1e-12)
    assert all(b - a >= 120.0 for a, b in zip([w["ts"] for w in writes], [w["ts"] for w in writes][1:]))
    assert events[-1]["reason"] == "shutdown"


# --------------------------------------------------------------------------- the audit table

def test_audit_rows_keep_their_order_share_a_time_and_survive_a_reopen(tmp_path):
    path = tmp_path / "h.sqlite"
    rows = [{"ts": T0, "event": "state", "state": "armed", "reason": "none", "message": "operator enabled"},
            {"ts": T0, "event": "write", "old_bar_g": 16.0, "new_bar_g": 15.5, "target_bar_g": 14.2,
             "words": "1550", "outcome": "ok", "message": "toward the recommendation"},
            {"ts": T0, "event": "state", "state": "writing", "reason": "stepped", "message": ""}]
    with HistoryStore(path, 30) as store:
        for r in rows:
            assert store.add_closed_loop_event(r) == 1
    with HistoryStore(path, 30) as store:
        got = store.closed_loop_events()
        assert store.count("closed_loop") == 3
    assert [(g["event"], g["state"], g["reason"]) for g in got] == [
        ("state", "armed", "none"), ("write", None, None), ("state", "writing", "stepped")]
    w = got[1]
    assert (w["ts"], w["old_bar_g"], w["new_bar_g"], w["words"], w["outcome"]) == \
        (T0, 16.0, 15.5, "1550", "ok")


def test_audit_rows_wait_in_memory_while_the_history_is_not_writable(tmp_path):
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the history's directory should be")
    store = HistoryStore(blocker / "h.sqlite", 30, open_wait_s=0.0).open()
    try:
        assert "cannot create the directory" in store.fault
        assert store.add_closed_loop_event({"ts": T0, "event": "write", "new_bar_g": 15.5}) == 0
        assert [(e["event"], e["new_bar_g"]) for e in store.closed_loop_events()] == [("write", 15.5)]
        assert store.pending == 1
    finally:
        store.close()


# --------------------------------------------------------------------------- the bench's judge

def test_the_benchs_judge_finds_every_kind_of_violation():
    """edge.bench_closed_loop.judge_writes on a made-up simulator log: one write outside the
    bounds, one above the step limit, one followed by a block with a blocking bit, one refused."""
    from types import SimpleNamespace as NS

    from edge.bench_closed_loop import LOOP as BENCH_LOOP, judge_writes

    adv = BASE.advisory
    bits = dict(adv.status_bits)
    stale = 1 << {n: b for b, n in adv.status_bits}["data_stale"]
    off = 1 << {n: b for b, n in adv.status_bits}["storage_fault"]     # not a blocking bit

    def block(status):
        return NS(address=adv.start, count=adv.size, values=(1, status), function_code=16)

    def sp():
        return NS(address=110, count=1, values=(0,), function_code=16)

    lo = BENCH_LOOP["bounds_bar_g"][0]
    sim = NS(setpoint_log=[
        {"old": 16.0, "new": 15.5, "accepted": True, "plant_t": 0.0},
        {"old": 15.5, "new": 14.8, "accepted": True, "plant_t": 300.0},     # step 0.7
        {"old": lo + 0.2, "new": lo - 0.3, "accepted": True, "plant_t": 600.0},   # below the bounds
        {"old": lo - 0.3, "new": lo + 0.2, "accepted": False, "plant_t": 900.0}],
        write_log=[block(0), sp(), block(off), sp(), block(0), sp(), block(stale), sp(), block(0),
                   NS(address=111, count=1, values=(1,), function_code=6)])
    got = judge_writes(sim, adv.start, adv.size, 110, bits, BENCH_LOOP)
    assert (got["outside_bounds"], got["above_step_limit"], got["while_blocking_bit_set"],
            got["refused"], got["writes_elsewhere"], got["accepted"]) == (1, 1, 1, 1, 1, 3)
    assert got["largest_step_bar"] == 0.7 and got["shortest_interval_s"] == 300.0


def test_the_benchs_cop_judge_on_a_plant_that_held_its_set_point():
    """edge.bench_closed_loop.judge_cop: a plant that ran at 16 bar(g) all along realized exactly
    the 16-bar baseline; the optimum is at least as good; the gap is the baseline's."""
    from edge.bench_closed_loop import judge_cop
    from simulator.config import load_simulator_config
    from simulator.export import MinuteStepper

    cfg = load_simulator_config()
    st_ = MinuteStepper(cfg)
    rows = [st_.step()[1] for _ in range(120)]
    t0 = rows[0]["t"]
    got = judge_cop(rows, cfg, t0, t0 + 7200, 16.0)
    assert got["hours"] == 2 and len(got["hourly"]) == 2
    assert got["COP_realized"] == pytest.approx(got["COP_at_baseline"], rel=1e-9)
    assert got["gain_over_baseline_pct"] == pytest.approx(0.0, abs=1e-6)
    assert got["COP_optimum"] >= got["COP_realized"] - 1e-9
    assert got["gap_to_optimum_pct"] == pytest.approx(got["baseline_gap_to_optimum_pct"], abs=1e-6)
    assert [h["set_point_bar_g"] for h in got["hourly"]] == [16.0, 16.0]
