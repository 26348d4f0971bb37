"""``hp-edge demo``: the plant simulator at 60x plant speed and the gateway on 127.0.0.1, with a
live view of the advisory block as the HMI reads it, beside the simulator's hidden truth.

What the demo changes against config/gateway.yaml (so that advice shows within a minute or two):

* the gateway polls every 0.25 s of wall time (15 s of plant time at 60x) and time-stamps samples
  with the PLC's clock register (plant time), so one-minute samples are plant minutes;
* a calibration needs 30 usable samples instead of 60 (the first advice after ~45 s of wall time);
  the calibration interval (15 plant minutes = 15 s) and window (2 plant hours) stay as configured;
* history and state go to a fresh temporary directory (``--state-dir`` keeps them);
* at the end, a report of the run (``hp-edge report`` on the demo's history database and state
  directory) is written to ``--report`` (default: ``report.html`` in ``--state-dir``, else
  ``demo-report.html`` in the current directory, since the temporary directory goes away);
* commissioning first (a few seconds): the simulator's hidden truth differs from plant.yaml (e.g.
  its clean evaporator is 7 % worse than the data sheet), so, as on a real site, the initial
  calibration runs on 100 minutes of clean-evaporator operation (the simulator's plant with its
  fouling set to zero, exported by ``simulator.export``), through ``hp-edge calibrate initial``,
  into the demo's state directory. ``--no-commissioning`` skips it: the fouling estimate then
  carries the data sheet's error (about +0.3e-3 K/kW), which the view shows beside the truth.
"""
from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import io
import json
import logging
import math
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from edge.advisory import decode_advisory
from edge.config import GatewayConfig

log = logging.getLogger(__name__)

DEMO_SPEED = 60.0
DEMO_SCAN_S = 0.25
DEMO_MIN_WINDOW = 30
REFRESH_S = 2.0
DEMO_REPORT = "demo-report.html"


def demo_config(cfg: GatewayConfig, port: int, state_dir: Path, scan_s: float = DEMO_SCAN_S,
                min_window: int = DEMO_MIN_WINDOW) -> GatewayConfig:
    """The demo's changes to the gateway configuration (see the module docstring)."""
    plc = replace(cfg.plc, host="127.0.0.1", port=port, timeout_s=min(cfg.plc.timeout_s, 0.5 * scan_s),
                  reconnect_min_s=min(cfg.plc.reconnect_min_s, scan_s),
                  reconnect_max_s=min(cfg.plc.reconnect_max_s, 4 * scan_s))
    return replace(cfg, plc=plc, scan_interval_s=scan_s, min_window_samples=min_window,
                   state_dir=state_dir / "state", history_db=state_dir / "history.sqlite")


class CommissioningError(RuntimeError):
    """The commissioning calibration failed (the message says why)."""


def commission(state_dir: Path, plant_file: Path, sim_cfg=None, minutes: float = 100.0) -> dict:
    """Site acceptance test on the simulator: ``minutes`` of clean-evaporator operation exported
    to CSV, then ``hp-edge calibrate initial`` on it, writing initial_calibration.json and
    dp_clean.json into ``state_dir``. Returns that command's JSON report."""
    from edge.cli import main
    from simulator.config import load_simulator_config
    from simulator.export import export_history

    cfg = sim_cfg or load_simulator_config()
    clean = cfg.replace(fouling=dataclasses.replace(
        cfg.fouling, R_th_f_initial_K_per_kW=0.0, R_th_f_inf_K_per_kW=0.0, CF_dp_f_initial=1.0,
        CF_dp_f_inf=1.0), faults=())
    with tempfile.TemporaryDirectory(prefix="hp-edge-commissioning-") as tmp:
        csv = Path(tmp) / "commissioning.csv"
        export_history(minutes / 1440.0, csv, cfg=clean)
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(["calibrate", "initial", str(csv), "--config", str(plant_file),
                       "--state-dir", str(state_dir), "--json"])
    if rc != 0:
        raise CommissioningError(f"hp-edge calibrate initial failed ({rc}): {err.getvalue().strip()}")
    return json.loads(out.getvalue())


def default_report_path(state_dir: Path | None) -> Path:
    """Where the demo's report goes without ``--report``."""
    return Path(state_dir) / "report.html" if state_dir else Path(DEMO_REPORT)


async def run_demo(config: Path, minutes: float | None = None, speed: float = DEMO_SPEED,
                   state_dir: Path | None = None, refresh_s: float = REFRESH_S,
                   out: TextIO | None = None, commissioning: bool = True,
                   report: Path | None | bool = True) -> int:
    """Run simulator + gateway until Ctrl-C / SIGTERM, or ``minutes`` of wall time; then write a
    report of the run to ``report`` (True: ``default_report_path``; None/False: none)."""
    from edge.config import load_config

    out = out or sys.stdout
    if report is True:
        report = default_report_path(state_dir)

    cfg = load_config(config)
    with tempfile.TemporaryDirectory(prefix="hp-edge-demo-") as tmp:
        where = Path(state_dir) if state_dir else Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        with _demo_logging(where / "demo.log"):
            return await _demo(cfg, where, speed, minutes, refresh_s, out, commissioning,
                               Path(report) if report else None)


def write_report(cfg: GatewayConfig, path: Path, out: TextIO) -> bool:
    """The report of a gateway run (its history database and state directory) -> ``path``.
    Says why when it cannot be written (no matplotlib, no samples yet) and returns False."""
    from edge.plantfile import PlantFileError, load_plant
    from edge.report import MatplotlibMissing, ReportSourceError, build_report, load_gateway

    try:
        params = load_plant(cfg.plant_file)
        data = load_gateway(cfg.history_db, cfg.state_dir, params, str(cfg.plant_file),
                            window_hours=cfg.calibration_window_h)
        res = build_report(data, path)
    except (MatplotlibMissing, ReportSourceError, PlantFileError, OSError) as exc:
        _print(out, f"report not written: {exc}\n")
        return False
    drawn = sum(f.png is not None for f in res.figures)
    _print(out, f"report of this run ({drawn} of {len(res.figures)} figures): "
                f"{res.path.resolve()}\n")
    return True


async def _demo(cfg, where: Path, speed: float, minutes: float | None, refresh_s: float,
                out: TextIO, commissioning: bool, report: Path | None = None) -> int:
    from edge.service import GatewayService
    from simulator.server import PlantSimulator

    if commissioning:
        _print(out, "commissioning: initial calibration on 100 min of clean-evaporator plant "
                    "operation ...\n")
        rep = await asyncio.to_thread(commission, where / "state", cfg.plant_file)
        p = rep["initial"]["params"]
        _print(out, "commissioning: " + ", ".join(f"{k} {v:.3f}" for k, v in p.items())
               + f" (NRMSE {100 * rep['initial']['objective']:.2f} %)\n")
    sim = PlantSimulator(port=0, speed=speed)
    await sim.start()
    try:
        dcfg = demo_config(cfg, sim.port, where)
        service = GatewayService(dcfg, time_source="plc", install_signals=True)
        gw = service.gateway
        run = asyncio.create_task(service.run(), name="hp-edge-gateway")
        view = asyncio.create_task(_view(sim, gw, dcfg, refresh_s, out, where, speed, service.advisor))
        timer = None
        if minutes is not None:
            timer = asyncio.get_running_loop().call_later(minutes * 60.0, gw.request_stop)
        try:
            rc = await run
        finally:
            if timer is not None:
                timer.cancel()
            view.cancel()
            await asyncio.gather(view, return_exceptions=True)
        _print(out, _render(sim, gw, dcfg, await _read_block(sim, dcfg), where, speed,
                            final=True, advisor=service.advisor))
        writes_outside = sim.writes_outside(dcfg.advisory.start, dcfg.advisory.size)
        if writes_outside:
            log.error("writes outside the advisory block: %s", writes_outside)
            return 1
        if report is not None:
            _print(out, "writing the report of this run ...\n")
            await asyncio.to_thread(write_report, dcfg, report, out)
        return rc
    finally:
        await sim.stop()


@contextlib.contextmanager
def _demo_logging(path: Path):
    """Everything to the log file; the console shows problems only (restored afterwards)."""
    root = logging.getLogger()
    fh = logging.FileHandler(path, encoding="utf-8")
    fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    saved = [(root, root.level)] + [(h, h.level) for h in root.handlers
                                    if type(h) is logging.StreamHandler]
    pymodbus = logging.getLogger("pymodbus")
    saved.append((pymodbus, pymodbus.level))
    root.setLevel(logging.INFO)
    for h, _ in saved[1:-1]:
        h.setLevel(logging.WARNING)
    pymodbus.setLevel(logging.ERROR)
    root.addHandler(fh)
    try:
        yield
    finally:
        root.removeHandler(fh)
        fh.close()
        for obj, level in saved:
            obj.setLevel(level)


async def _read_block(sim, cfg: GatewayConfig) -> dict:
    words = await sim.read_registers("holding", cfg.advisory.start, cfg.advisory.size)
    return decode_advisory(cfg.advisory, words)


async def _view(sim, gw, cfg, refresh_s, out, where, speed, advisor=None) -> None:
    while True:
        await asyncio.sleep(refresh_s)
        _print(out, _render(sim, gw, cfg, await _read_block(sim, cfg), where, speed, advisor=advisor),
               clear=True)


def _print(out: TextIO, text: str, clear: bool = False) -> None:
    if clear and out.isatty():
        out.write("\x1b[H\x1b[2J")
    elif clear:
        out.write("-" * 78 + "\n")
    out.write(text)
    out.flush()


def _clip(text: str, n: int) -> str:
    """``text`` cut to at most n characters at a word's end, "…" where it was cut."""
    if len(text) <= n:
        return text
    cut = text[:n - 1]
    return (cut.rsplit(" ", 1)[0] if " " in cut else cut).rstrip(" ,;:(") + "…"


def _f(v, fmt: str, unit: str = "", none: str = "-") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return f"{v:{fmt}}{(' ' + unit) if unit else ''}"


def _render(sim, gw, cfg, blk: dict, where: Path, speed: float, final: bool = False,
            advisor=None) -> str:
    truth = sim.truth or {}
    t = sim.plant_time
    snap = gw.snapshot
    bits = blk["status_bits"]
    names = [n for _, n in cfg.advisory.status_bits]
    age = blk.get("advice_age_s", 0)
    has = blk.get("last_update", 0) > 0
    lines = [
        f"hp-edge demo: simulator 127.0.0.1:{sim.port} at {speed:g}x plant speed, gateway scan "
        f"{cfg.scan_interval_s:g} s" + ("" if final else "   (Ctrl-C stops)"),
        f"plant time {time.strftime('%Y-%m-%d %H:%M', time.gmtime(t))} UTC   heartbeat "
        f"{blk['heartbeat']}   one-minute samples {snap.samples}   calibrations "
        f"{snap.calibrations}",
        "status   " + ("  ".join(f"[{'x' if n in bits else ' '}] {n}" for n in names[:4])),
        "         " + ("  ".join(f"[{'x' if n in bits else ' '}] {n}" for n in names[4:])),
    ]
    if not has:
        lines.append(f"advice   waiting for the first calibration: {snap.advice_message or 'collecting usable samples'}")
    else:
        lines.append(f"advice   of {time.strftime('%H:%M', time.gmtime(blk['last_update']))} plant time,"
                     f" age {age // 60} min")
    sp_now = sim.served.get("p_m_sp") if sim.served else None
    lines += [
        f"  recommended p_m,sp  {_f(blk.get('p_m_sp_rec'), '7.2f', 'bar(g)')}   set point now "
        f"{_f(sp_now, '.2f', 'bar(g)')}   truth optimum {_f(truth.get('p_m_sp_opt_bar_g'), '.2f', 'bar(g)')}",
        f"  expected change     COP {_f(blk.get('dCOP_pct'), '+.2f', '%')} (sd "
        f"{_f(blk.get('dCOP_sd_pct'), '.2f', '%')})   heat output {_f(blk.get('dQ_sink_pct'), '+.2f', '%')}",
        "  confidence          " + (("low: keep the current set point" + (
            f" ({_clip(snap.advice_message, 90)})" if snap.advice_message else ""))
            if "advice_low_confidence" in bits else ("confident" if has else "-")),
        f"  geometric-mean p_m  {_f(blk.get('p_m_gm'), '7.2f', 'bar(g)')}",
        f"  fouling R_th,f      {_f(_milli(blk.get('R_th_f')), '7.3f', 'e-3 K/kW')}   simulator truth "
        f"{_f(_milli(truth.get('R_th_f_K_per_kW')), '.3f', 'e-3 K/kW')}",
        f"  share of evaporator {_f(blk.get('R_th_f_share'), '7.1f', '%')}        truth "
        f"{_f(truth.get('R_th_f_share_pct'), '.1f', '%')}",
        f"  CF_dp,f             {_f(blk.get('CF_dp_f'), '7.3f')}          truth "
        f"{_f(truth.get('CF_dp_f'), '.3f')}   fouling dp {_f(blk.get('dp_fouling'), '.3f', 'bar')}",
        f"  COP                 measured {_f(blk.get('COP_measured'), '.2f')}   adaptive model "
        f"{_f(blk.get('COP_adaptive'), '.2f')}   fixed model {_f(blk.get('COP_fixed'), '.2f')}",
        f"  calibration NRMSE   {_f(blk.get('nrmse_pct'), '7.2f', '%')}   compressor eta_is vs "
        f"commissioning LS {_f(blk.get('eta_is_LS_drift'), '+.2f')} HS "
        f"{_f(blk.get('eta_is_HS_drift'), '+.2f')} points",
        *_cip_lines(blk, advisor),
        f"history and log in {where}" + ("  (temporary)" if "hp-edge-demo-" in str(where) else ""),
    ]
    if final:
        lines.append(f"stopped: {snap.cycles} cycles, {snap.writes_ok} advisory writes, "
                     f"{len(sim.write_log)} write requests seen by the simulator, all inside the "
                     f"advisory block" if not sim.writes_outside(cfg.advisory.start, cfg.advisory.size)
                     else "stopped: WRITES OUTSIDE THE ADVISORY BLOCK (see the log)")
    return "\n".join(lines) + "\n"


def _milli(v):
    return None if v is None else v * 1e3


def _cip_lines(blk: dict, advisor=None, width: int = 100, max_lines: int = 6) -> list[str]:
    """Issue 10: the forecast and cost registers, and the last window's "when to clean" in words
    (the lines replay's summary.txt has)."""
    import textwrap
    horizon = getattr(getattr(getattr(getattr(advisor, "chain", None), "s", None), "cip", None),
                      "horizon_days", None)
    h = f"{horizon:g} d" if horizon is not None else "the horizon"
    out = [f"  fouling forecast    rate {_f(_milli(blk.get('fouling_rate')), '.3f', 'e-3 K/kW per day')}   "
           f"R_th,f in {h} {_f(_milli(blk.get('R_th_f_forecast')), '.3f', 'e-3 K/kW')}",
           f"  cost of fouling     {_f(blk.get('fouling_cost'), '.0f', 'EUR/d')}   since the last CIP "
           f"{_f(blk.get('fouling_cost_cum'), '.0f', 'EUR')}   recommended CIP in "
           f"{_f(blk.get('days_to_cip'), '.1f', 'days')}"]
    text = list(getattr(advisor, "cip_text", None) or [])
    if text:
        wrapped = []
        for line in text:
            wrapped += textwrap.wrap(line, width - 20, subsequent_indent="  ")
        out += [("  when to clean       " if i == 0 else " " * 22) + w
                for i, w in enumerate(wrapped[:max_lines])]
    return out
