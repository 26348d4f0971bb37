"""Benchmark of the guarded closed loop (issue 13): ``hp-edge bench --only closed_loop``.

One simulated day with the loop enabled, as deployed: the simulator (its PLC running the
remote-set-point program of docs/closed_loop.md) in this process, ``hp-edge run`` as its own
process against it (sample clock = the PLC's clock, plant time at ``speed`` x), killed with
SIGKILL by its PID at the end. Before the day, the gateway's state is what a site has after a
few days of advice it trusts: ``PRELEARN_DAYS`` of the same plant (compressor family
``FAMILY``, whose curves differ in shape from plant.yaml's) at the operators' set points
``PRELEARN_SCHEDULE``, exported and replayed (commissioning, learned compressor curves, the last
fouling calibration) into the state directory, and their last ``HISTORY_HOURS`` stored in the
gateway's history through its ingest path (a gateway that ran through those days has them; its
first calibration then needs no hour of new samples). The simulated plant then goes on from the
end of those days (the same seed, weather, fouling), served by the simulator at the set point the
operators copied by hand from the last confident advice of those days (the issue's operators, who
trust the advice and want to stop copying it; ``start_sp`` = a number starts at that set point
instead, e.g. 16 for SPEC §2's design value). The PLC's local set point (its fallback) is the same
value: the operators set it. The operator sets the enable right after the gateway starts; the day
starts there.

Targets (issue 13), all measured on the simulator's side:

* 0 set-point writes outside gateway.yaml's bounds or above its step limit (the PLC's log of
  every write with the value it replaced), and 0 refused;
* 0 set-point writes while a blocking status bit is set: the status word of the advisory block
  the gateway writes right after each set-point write (same scan);
* fallback within the configured heartbeat timeout after ``kill -9`` of the gateway: the time from
  the kill to the PLC's change to local mode, and the heartbeat's age then;
* realized COP within 0.2 % of the truth optimum over the run: per plant hour, the simulated
  plant's true COP at the set points it really ran (``simulator.truth.TruthModel.cop_actual``)
  against its optimum (``optimum``); the day's COP is sum Q / sum W over the hours. The same at
  SPEC §2's 16 bar(g) (``BASELINE_SP``) shows what the loop gained over the design set point.
"""
from __future__ import annotations

import asyncio
import math
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parent.parent
FAMILY = "speed_peak"
PRELEARN_DAYS = 3.0
PRELEARN_SCHEDULE = ((0.0, 13.0), (1.0, 10.0), (2.0, 16.0))
START_SP = "advice"           # the set point at the enable: the pre-learning days' last confident
#                               advice (copied by hand), or a number [bar(g)]
BASELINE_SP = 16.0            # SPEC §2's p_m,sp, held all day: what the loop gained
HOURS = 24.0
SPEED = 120.0                 # plant seconds per wall second
SCAN_PLANT_S = 15.0           # the gateway's scan in plant seconds (0.125 s of wall time at 120x)
HEARTBEAT_TIMEOUT_S = 5.0     # wall seconds (the PLC's TON), 40 scans at 120x
LOOP = {"enabled": True, "setpoint_tag": "p_m_sp", "enable_tag": "closed_loop_enable",
        "bounds_bar_g": [8.0, 18.0], "max_step_bar": 0.5, "min_interval_s": 300,
        "deadband_bar": 0.05, "heartbeat_timeout_s": HEARTBEAT_TIMEOUT_S,
        "shed_after_bad_scans": 3}
PLC_BOUNDS = (8.0, 22.0)
TOL_BAR = 1e-6                # decoded register values against bounds and step (resolution 0.01)
TARGET_COP_GAP_PCT = 0.2
HISTORY_HOURS = 12.0          # the last hours of the pre-learning days in the gateway's history, as
#                               a site's gateway has them (it has run through those days)


# ------------------------------------------------------------------------------ the pieces
# (tests/test_closed_loop_kill.py uses them too)

def write_gateway_yaml(path: Path, port: int, work: Path, *, scan_s: float, loop: dict,
                       **top) -> Path:
    """gateway.yaml for ``hp-edge run`` against a simulator on 127.0.0.1:``port``: the shipped
    file with the loop section, the scan, state and history under ``work``, and ``top`` keys."""
    doc = yaml.safe_load((ROOT / "config" / "gateway.yaml").read_text())
    doc["plc"].update(host="127.0.0.1", port=port, timeout_s=round(0.4 * scan_s, 4),
                      reconnect_min_s=scan_s, reconnect_max_s=2 * scan_s)
    doc.update(scan_interval_s=scan_s, state_dir=str(work / "state"),
               history_db=str(work / "history.sqlite"),
               tags_file=str(ROOT / "config" / "tags.yaml"),
               plant_file=str(ROOT / "config" / "plant.yaml"), **top)
    doc["closed_loop"] = dict(loop)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def start_gateway(cfg_path: Path, log_path: Path) -> subprocess.Popen:
    """``hp-edge run --time-source plc`` as its own process, its log to ``log_path``."""
    log = open(log_path, "w", encoding="utf-8")
    try:
        return subprocess.Popen([sys.executable, "-m", "edge.cli", "run", "--config", str(cfg_path),
                                 "--time-source", "plc"], cwd=ROOT,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                stdout=subprocess.DEVNULL, stderr=log)
    finally:
        log.close()       # the child holds its own descriptor


async def until(predicate, timeout: float, step: float = 0.02) -> None:
    async def poll():
        while not predicate():
            await asyncio.sleep(step)
    await asyncio.wait_for(poll(), timeout)


async def kill_and_fallback(sim, proc: subprocess.Popen, timeout: float) -> dict:
    """SIGKILL the gateway by its PID; wait for the PLC's fallback. The times are on this
    process's monotonic clock (the simulator's PLC runs here)."""
    n0 = len(sim.plc_events)
    t_kill = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    await asyncio.to_thread(proc.wait, 10)
    await until(lambda: len(sim.plc_events) > n0, timeout)
    ev = sim.plc_events[n0]
    await sim.wait_ticks(2)
    return {"returncode": proc.returncode, "reason": ev["reason"], "mode": ev["mode"],
            "kill_to_fallback_s": round(ev["mono"] - t_kill, 3),
            "heartbeat_age_at_fallback_s": round(ev["heartbeat_age_s"], 3),
            "set_point_before_bar_g": round(ev["p_m_sp_before"], 2),
            "set_point_after_bar_g": round(sim.plant.p_m_sp_bar_g, 2),
            "local_set_point_bar_g": ev["local_sp"]}


def judge_writes(sim, block_start: int, block_size: int, setpoint_address: int, status_bits: dict,
                 loop: dict) -> dict:
    """The simulator's logs against the loop's guards (see the module doc)."""
    from edge.closed_loop import BLOCKING_BITS

    lo, hi = loop["bounds_bar_g"]
    step = loop["max_step_bar"]
    sp = sim.setpoint_log
    outside = [r for r in sp if not lo - TOL_BAR <= r["new"] <= hi + TOL_BAR]
    too_big = [r for r in sp if abs(r["new"] - r["old"]) > step + TOL_BAR]
    refused = [r for r in sp if not r["accepted"]]
    names = {bit: name for bit, name in status_bits.items()}
    blocked, unjudged, expect_block = [], 0, False
    for w in sim.write_log:
        if w.address == setpoint_address:
            expect_block = True
        elif w.address == block_start and expect_block:
            status = w.values[1]
            on = {names[b] for b in names if status >> b & 1}
            if on & set(BLOCKING_BITS):
                blocked.append(sorted(on))
            expect_block = False
    if expect_block:
        unjudged += 1
    others = [w for w in sim.write_log if not (
        (w.address == setpoint_address and w.count == 1)
        or (w.address == block_start and w.count == block_size))]
    times = [r["plant_t"] for r in sp if r["accepted"]]
    return {"set_point_writes": len(sp), "accepted": len(sp) - len(refused),
            "refused": len(refused), "outside_bounds": len(outside), "above_step_limit": len(too_big),
            "while_blocking_bit_set": len(blocked), "not_judged": unjudged,
            "writes_elsewhere": len(others),
            "largest_step_bar": round(max((abs(r["new"] - r["old"]) for r in sp), default=0.0), 4),
            "shortest_interval_s": round(min((b - a for a, b in zip(times, times[1:])), default=math.nan), 1),
            "set_points_written_bar_g": [round(r["new"], 2) for r in sp][:60],
            "note": "intervals on the PLC's plant clock, which the simulator steps in 5-s ticks; the "
                    "gateway judges min_interval_s on its sample clock (audit.shortest_interval_s)"}


def judge_cop(truth_rows: list[dict], sim_cfg, t0: float, t1: float, baseline_sp: float) -> dict:
    """The true COP the plant realized between plant times t0 and t1, against the true optimum
    and against ``baseline_sp`` held all along, hour by hour (simulator.truth.TruthModel)."""
    import pandas as pd

    from simulator.truth import TruthModel

    tm = TruthModel(sim_cfg)
    df = pd.DataFrame([r for r in truth_rows if t0 <= r["t"] < t1])
    hours = []
    for h0 in range(int(t0), int(t1), 3600):
        sel = df[(df["t"] >= h0) & (df["t"] < h0 + 3600)]
        if (sel["running"] == 1).sum() < 30:
            continue
        w = tm.window(sel, max_rows=30)
        opt = w.optimum()
        cop_a, q_a, w_a = w.cop_actual()
        cop_b, q_b, w_b = w.cop_at(baseline_sp)
        cop_o, q_o, w_o = opt["COP_opt"], opt["Q_sink_opt_kW"], opt["W_opt_kW"]
        hours.append({"hour_start": h0, "COP_actual": cop_a, "COP_opt": cop_o, "COP_baseline": cop_b,
                      "Q_actual": q_a, "W_actual": w_a, "Q_opt": q_o, "W_opt": w_o,
                      "Q_baseline": q_b, "W_baseline": w_b,
                      "p_m_sp_actual_mean": float(sel["p_m_sp_solved_bar_g"].mean()),
                      "p_m_sp_opt": opt["p_m_sp_opt_barg"]})
    if not hours:
        return {"hours": 0}
    h = pd.DataFrame(hours)
    cop_run = h["Q_actual"].sum() / h["W_actual"].sum()
    cop_base = h["Q_baseline"].sum() / h["W_baseline"].sum()
    cop_opt = h["Q_opt"].sum() / h["W_opt"].sum()
    late = h.iloc[6:]
    late_gap = (100.0 * (1.0 - (late["Q_actual"].sum() / late["W_actual"].sum())
                         / (late["Q_opt"].sum() / late["W_opt"].sum()))) if len(late) else math.nan
    hourly = [{"hour": i, "set_point_bar_g": round(r.p_m_sp_actual_mean, 2),
               "optimum_bar_g": round(r.p_m_sp_opt, 2),
               "gap_pct": round(100 * (1 - r.COP_actual / r.COP_opt), 3),
               "baseline_gap_pct": round(100 * (1 - r.COP_baseline / r.COP_opt), 3)}
              for i, r in enumerate(h.itertuples())]
    return {"hours": int(len(h)), "gap_after_hour_6_pct": round(float(late_gap), 4),
            "hourly": hourly,
            "COP_realized": round(float(cop_run), 5), "COP_optimum": round(float(cop_opt), 5),
            "COP_at_baseline": round(float(cop_base), 5), "baseline_set_point_bar_g": baseline_sp,
            "gap_to_optimum_pct": round(100.0 * (1.0 - cop_run / cop_opt), 4),
            "baseline_gap_to_optimum_pct": round(100.0 * (1.0 - cop_base / cop_opt), 4),
            "gain_over_baseline_pct": round(100.0 * (cop_run / cop_base - 1.0), 4),
            "hourly_gap_pct_max": round(float((100 * (1 - h["COP_actual"] / h["COP_opt"])).max()), 4),
            "hourly_gap_pct_last_12h_mean": round(float((100 * (1 - h["COP_actual"] / h["COP_opt"]))
                                                        .tail(12).mean()), 4),
            "set_point_mean_bar_g": round(float(h["p_m_sp_actual_mean"].mean()), 3),
            "optimum_mean_bar_g": round(float(h["p_m_sp_opt"].mean()), 3)}


def prelearn_config(family: str = FAMILY, schedule=PRELEARN_SCHEDULE):
    """The simulator config of the pre-learning days (as edge.bench_advice.history builds it:
    commissioning with a clean evaporator, the operators' schedule)."""
    from simulator.config import load_simulator_config

    cfg = load_simulator_config().with_compressor_family(family)
    return replace(cfg, control=replace(cfg.control, p_m_sp_schedule=tuple(tuple(x) for x in schedule),
                                        p_m_sp_bar_g=schedule[0][1]),
                   fouling=replace(cfg.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0))


TAIL_CSV = "history_tail.csv"


def seed_history(cfg_path: Path, tail_csv: Path) -> int:
    """Store the pre-learning days' last ``HISTORY_HOURS`` in the gateway's history through its
    own ingest path (``ModelAdvisor.ingest``: processed, flagged, stored as the scan loop stores
    one-minute samples), as the history of a gateway that ran through those days. Returns the
    samples stored."""
    from edge import statefiles
    from edge.aggregate import Sample
    from edge.config import load_config
    from edge.service import ModelAdvisor, StateDir
    from edge.store import HistoryStore

    cfg = load_config(cfg_path)
    hist = pd.read_csv(tail_csv)
    samples = []
    for rec in hist.to_dict("records"):
        ts = pd.Timestamp(rec.pop("timestamp")).timestamp()
        vals = {k: float(v) for k, v in rec.items()}
        bad = {k: "nan" for k, v in vals.items() if not math.isfinite(v)}
        samples.append(Sample(ts, vals, bad, 1, 1, 0, 0, ""))
    store = HistoryStore(cfg.history_db, cfg.history_retention_days, aggregate_s=cfg.aggregate_s)
    store.open()
    try:
        advisor = ModelAdvisor(cfg, store, StateDir(cfg.state_dir, cfg.path.parent / statefiles.SURROGATE))
        n = 0
        for k in range(0, len(samples), 60):
            n += len(advisor.ingest(samples[k:k + 60]))
    finally:
        store.close()
    return n


def prelearned_state(state: Path, family: str = FAMILY, days: float = PRELEARN_DAYS,
                     schedule=PRELEARN_SCHEDULE):
    """Export and replay the pre-learning days; write the state documents the gateway starts
    from (kept: a state directory that holds them for the same family, days and schedule is
    used as it is). Returns (simulator config of the export, truth at its end, seconds, the
    replay's windows in brief)."""
    import json

    from edge import statefiles
    from edge.plantfile import load_plant
    from model.analysis.replay import replay
    from simulator.export import export_history

    t0 = time.perf_counter()
    cfg = prelearn_config(family, schedule)
    key = {"v": 2, "family": family, "days": days, "schedule": [list(x) for x in schedule],
           "history_hours": HISTORY_HOURS}
    done = state / "prelearn.json"
    if done.exists() and (state / TAIL_CSV).exists():
        doc = json.loads(done.read_text())
        if doc.get("key") == key:
            return cfg, doc["last"], time.perf_counter() - t0, {**doc["learned"], "cached": True}
    res_export = export_history(days, cfg=cfg, with_truth=True)
    hist, truth = res_export.history, res_export.truth
    res = replay(hist, load_plant())
    state.mkdir(parents=True, exist_ok=True)
    ts = pd.to_datetime(hist["timestamp"], utc=True)
    hist.loc[(ts > ts.iloc[-1] - pd.Timedelta(hours=HISTORY_HOURS)).to_numpy()].to_csv(
        state / TAIL_CSV, index=False)
    statefiles.write_state(statefiles.INITIAL_CALIBRATION, res.initial.to_dict(), state)
    statefiles.write_state(statefiles.DP_CLEAN, res.dp_clean.to_dict(), state)
    if res.compressors is not None:
        statefiles.write_state(statefiles.COMPRESSORS, res.compressors, state)
    if res.last_fouling is not None:
        statefiles.write_state(statefiles.FOULING_CALIBRATION, res.last_fouling.to_dict(), state)
    w = res.windows
    ok = w[w["status"] == "ok"]
    end = truth.iloc[-1]
    last = {k: float(end[k]) for k in ("t", "R_th_f_K_per_kW", "CF_dp_f")}
    conf = ok[ok["advice_confident"].astype(bool)]
    learned = {"windows": int(len(w)), "confident_last_12": int(ok["advice_confident"].tail(12).sum()),
               "last_recommendations_bar_g": [round(float(x), 2) for x in ok["p_m_sp_opt_barg"].tail(6)],
               "last_confident_recommendation_bar_g": (round(float(conf["p_m_sp_opt_barg"].iloc[-1]), 2)
                                                       if len(conf) else None)}
    done.write_text(json.dumps({"key": key, "last": last, "learned": learned}))
    return cfg, last, time.perf_counter() - t0, learned


# ------------------------------------------------------------------------------ the run


async def _day(work: Path, hours: float, speed: float, family: str, start_sp) -> dict:
    from datetime import datetime, timezone

    from edge.advisory import decode_advisory
    from edge.config import load_read_config
    from simulator.server import PlantSimulator

    out: dict = {"family": family, "hours": hours, "speed": speed, "loop": LOOP,
                 "plc_bounds_bar_g": list(PLC_BOUNDS)}
    import shutil

    cfg, last, secs, learned = await asyncio.to_thread(prelearned_state, work / "prelearn", family)
    shutil.rmtree(work / "state", ignore_errors=True)       # each run from the pre-learned state
    for old in work.glob("history.sqlite*"):
        old.unlink()
    (work / "state").mkdir()
    for doc in (work / "prelearn").glob("*.json"):
        if doc.name != "prelearn.json":
            shutil.copy(doc, work / "state" / doc.name)
    if start_sp == "advice":
        local_sp = learned["last_confident_recommendation_bar_g"]
        if local_sp is None:
            raise RuntimeError("the pre-learning days gave no confident advice to start from")
    else:
        local_sp = float(start_sp)
    out["start_set_point"] = {"rule": start_sp if start_sp == "advice" else "given",
                              "bar_g": local_sp}
    out["local_set_point_bar_g"] = local_sp
    out["prelearn"] = {"days": PRELEARN_DAYS, "schedule_days_barg": [list(x) for x in PRELEARN_SCHEDULE],
                       "seconds": round(secs, 1), **learned}
    # the plant of the pre-learning days goes on where they end (same seed: the same plant)
    from simulator.plant import Plant

    sim_cfg = replace(cfg, faults=()).with_sections(
        remote_setpoint={"enabled": True, "bounds_bar_g": list(PLC_BOUNDS),
                         "heartbeat_timeout_s": HEARTBEAT_TIMEOUT_S})
    plant = Plant(sim_cfg)
    plant.record_truth = False
    await asyncio.to_thread(plant.advance_to, plant.t0 + PRELEARN_DAYS * 86400.0)
    plant.record_truth = True
    plant.local_sp_bar_g = local_sp
    plant.set_p_m_sp(local_sp)
    out["start"] = {"plant_time": datetime.fromtimestamp(plant.t, timezone.utc).isoformat(),
                    "R_th_f_K_per_kW": round(plant.fouling.R, 6),
                    "prelearn_end_R_th_f_K_per_kW": round(float(last["R_th_f_K_per_kW"]), 6)}
    sim = PlantSimulator(sim_cfg, port=0, speed=speed, plant=plant)
    await sim.start()
    proc = None
    try:
        cfg_path = write_gateway_yaml(work / "gateway.yaml", sim.port, work,
                                      scan_s=SCAN_PLANT_S / speed, loop=LOOP)
        _, adv = load_read_config(cfg_path)
        out["prelearn"]["history_samples_stored"] = await asyncio.to_thread(
            seed_history, cfg_path, work / "prelearn" / TAIL_CSV)
        proc = start_gateway(cfg_path, work / "gateway.log")
        await until(lambda: sim.program.hb_last is not None, 60)     # the gateway runs
        await sim.set_operator_enable(False)
        await asyncio.sleep(4 * SCAN_PLANT_S / speed)
        await sim.set_operator_enable(True)
        await until(lambda: sim.remote_mode, 10)
        t_start = sim.plant.t
        t_end = t_start + hours * 3600.0
        wall0 = time.perf_counter()
        while sim.plant.t < t_end:
            if proc.poll() is not None:
                raise RuntimeError(f"the gateway exited with {proc.returncode}; see {work / 'gateway.log'}")
            await asyncio.sleep(0.5)
        out["wall_s"] = round(time.perf_counter() - wall0, 1)
        block = decode_advisory(adv, await sim.read_registers("holding", adv.start, adv.size))
        out["closed_loop_at_end"] = {k: block[k] for k in ("closed_loop_state", "closed_loop_reason",
                                                           "closed_loop_writes", "closed_loop_sp_written",
                                                           "closed_loop_target")}
        out["guards"] = judge_writes(sim, adv.start, adv.size, 110, dict(adv.status_bits), LOOP)
        # how long the advice was confident: the advisory blocks of the day
        low = total = 0
        bit = {n: b for b, n in adv.status_bits}["advice_low_confidence"]
        for w in sim.write_log:
            if w.address == adv.start and w.count == adv.size:
                total += 1
                low += (w.values[1] >> bit) & 1
        out["blocks_with_low_confidence_share"] = round(low / total, 4) if total else math.nan
        beats = [w.wall_time for w in sim.write_log if w.address == adv.start and w.accepted]
        gaps = sorted(b - a for a, b in zip(beats, beats[1:]))
        out["heartbeat"] = {"blocks": len(beats), "scan_s": round(SCAN_PLANT_S / speed, 4),
                            "gap_max_s": round(gaps[-1], 3) if gaps else math.nan,
                            "gap_p99_s": round(gaps[int(0.99 * (len(gaps) - 1))], 3) if gaps else math.nan,
                            "spurious_fallbacks": sum(e["mode"] == "local" for e in sim.plc_events)}
        if sim.remote_mode:
            out["fallback"] = await kill_and_fallback(sim, proc, 5 * HEARTBEAT_TIMEOUT_S + 5)
        else:      # the PLC left remote mode before (see plc_events): kill all the same
            os.kill(proc.pid, signal.SIGKILL)
            await asyncio.to_thread(proc.wait, 10)
            out["fallback"] = {"returncode": proc.returncode, "kill_to_fallback_s": None,
                               "note": "the PLC was not in remote mode at the kill"}
        out["fallback"]["heartbeat_timeout_s"] = HEARTBEAT_TIMEOUT_S
        proc = None
        out["plc_events"] = [{k: e[k] for k in ("mode", "reason", "heartbeat_age_s")}
                             for e in sim.plc_events]
        truth = list(sim.truth_history)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        await sim.stop()
    out["cop"] = await asyncio.to_thread(judge_cop, truth, sim_cfg, t_start, t_end, BASELINE_SP)
    from edge.store import HistoryStore
    with HistoryStore(work / "history.sqlite", 400) as store:
        events = store.closed_loop_events()
    wts = [e["ts"] for e in events if e["event"] == "write"]
    out["audit"] = {"writes": len(wts),
                    "shortest_interval_s": min((b - a for a, b in zip(wts, wts[1:])), default=None),
                    "state_changes": [f"{e['state']}:{e['reason']}" for e in events
                                      if e["event"] == "state"][:20]}
    g, c, f = out["guards"], out["cop"], out["fallback"]
    out["targets"] = {
        "writes_outside_bounds_or_above_step": {"measured": g["outside_bounds"] + g["above_step_limit"],
                                                "target": 0},
        "writes_while_blocking_bit_set": {"measured": g["while_blocking_bit_set"], "target": 0},
        "fallback_after_kill_s": {"measured": f["kill_to_fallback_s"],
                                  "target": f"<= {HEARTBEAT_TIMEOUT_S} (heartbeat timeout)"},
        "realized_cop_gap_to_optimum_pct": {"measured": c.get("gap_to_optimum_pct"),
                                            "target": TARGET_COP_GAP_PCT},
    }
    return out


def bench_closed_loop(hours: float = HOURS, speed: float = SPEED, family: str = FAMILY,
                      work: Path | None = None, start_sp: float | str = START_SP) -> dict:
    """``hp-edge bench --only closed_loop``: the figures as a dict (JSON-ready). ``work``: keep
    the run's files there (gateway.yaml, its log, history, state; the pre-learned state is
    reused by the next run in the same directory)."""
    if work is not None:
        work.mkdir(parents=True, exist_ok=True)
        return asyncio.run(_day(work, hours, speed, family, start_sp))
    with tempfile.TemporaryDirectory(prefix="hp-edge-bench-closed-loop-") as tmp:
        return asyncio.run(_day(Path(tmp), hours, speed, family, start_sp))


if __name__ == "__main__":
    # python -m edge.bench_closed_loop [HOURS [SPEED [WORKDIR [START_SP [FAMILY]]]]]
    # (START_SP: "advice" or a set point in bar(g), e.g. 16)
    import json
    a = sys.argv[1:]
    res = bench_closed_loop(float(a[0]) if a else HOURS, float(a[1]) if len(a) > 1 else SPEED,
                            work=Path(a[2]) if len(a) > 2 and a[2] != "-" else None,
                            start_sp=(a[3] if a[3] == "advice" else float(a[3])) if len(a) > 3 else START_SP,
                            family=a[4] if len(a) > 4 else FAMILY)
    print(json.dumps(res, indent=2, default=float))
