"""Analysis commands on SCADA history CSVs: calibrate, optimize, fit-surrogate, replay (SPEC §5-6).

History CSVs carry the canonical columns of SPEC §4 with a first column ``timestamp`` (ISO 8601, UTC
when naive); they are read by ``edge.io.history`` (separator and decimal mark detected, or given
with --sep/--decimal). Rows whose timestamp cannot be read, or that repeat one, are skipped and
counted (the first bad one named with its line); rows with bad values are marked unusable by the
measured-side processing and counted per reason. Heavy imports (CoolProp, SciPy, pandas) stay
inside the command functions.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time

DEFAULT_STATE_DIR = "var/state"
PLANT_HELP = ("plant file (default: config/plant.yaml, else /etc/hp-edge/plant.yaml, else the one "
              "shipped with the package)")


def register(sub) -> None:
    cal = sub.add_parser("calibrate", help="calibrate the model on a history CSV (initial or fouling)",
                         description="Calibrate the model on a window of a history CSV and save the "
                                     "result as state (SPEC §5).")
    csub = cal.add_subparsers(dest="kind", metavar="KIND")
    csub.required = True
    ini = csub.add_parser("initial", help="CF_DSH, CF_con, CF_SC, CF_eva and the clean pressure drop "
                                          "on commissioning data",
                          description="Initial calibration (CF_DSH, CF_con, CF_SC, CF_eva) and the clean "
                                      "pressure-drop fit on a clean window; default window: the first "
                                      "usable minutes (calibration.initial.window_minutes, 90). A result "
                                      "outside the plausibility limits (calibration.initial.limits: "
                                      "objective, parameters at a bound, dp_clean R^2) is not saved "
                                      "unless --force; exit code 2 names the limit.")
    _common(ini)
    ini.add_argument("--window", default=None, help="START/END (ISO 8601, UTC when naive)")
    ini.add_argument("--force", action="store_true",
                     help="save the result even when it fails the plausibility limits")
    ini.set_defaults(func=cmd_calibrate_initial)
    fou = csub.add_parser("fouling", help="R_th,f and CF_dp,f on a window of recent operation",
                          description="Fouling calibration (R_th,f, CF_dp,f) on the fixed model of the "
                                      "saved initial calibration.")
    _common(fou)
    fou.add_argument("--window", required=True, help="START/END (ISO 8601, UTC when naive)")
    fou.set_defaults(func=cmd_calibrate_fouling)

    opt = sub.add_parser("optimize", help="COP-optimal p_m set point for a window of a history CSV",
                         description="Optimal intermediate-pressure set point for a window, with the "
                                     "adaptive model of the saved calibrations (SPEC §6).")
    _common(opt)
    opt.add_argument("--window", required=True, help="START/END (ISO 8601, UTC when naive)")
    opt.set_defaults(func=cmd_optimize)

    fs = sub.add_parser("fit-surrogate", help="fit the 27-term set-point surrogate on model optima",
                        description="Fit the p_m,sp surrogate (SPEC §6) on optimization results of the "
                                    "model over fouling levels and operating points; prints R^2 on the "
                                    "held-out 30 % and saves the coefficients.")
    fs.add_argument("--config", default=None, help=PLANT_HELP)
    fs.add_argument("--state-dir", default=DEFAULT_STATE_DIR,
                    help=f"state directory; its initial calibration is used when present ({DEFAULT_STATE_DIR})")
    fs.add_argument("--out", default=None, help="coefficients file (default: STATE_DIR/surrogate.json)")
    fs.add_argument("--points-per-level", type=int, default=None,
                    help="operating points per fouling level (plant.yaml surrogate.points_per_level, 60)")
    fs.add_argument("--seed", type=int, default=None, help="sampling and split seed")
    fs.add_argument("--json", action="store_true", help="print JSON")
    fs.set_defaults(func=cmd_fit_surrogate)

    rp = sub.add_parser("replay", help="replay a history: calibrations, CIP effects, optimal set points",
                        description="Initial calibration and clean pressure-drop fit on the initial "
                                    "window, CIP detection, and per window the fouling calibration and "
                                    "the set-point optimization; the fouling forecast since the last "
                                    "CIP, the cost of fouling and the cost-optimal CIP (plant.yaml "
                                    "cip:). Writes DIR/windows.csv, DIR/cip.csv, DIR/forecast.csv, "
                                    "DIR/samples.csv, DIR/summary.txt and the calibration results.")
    rp.add_argument("history", help="history CSV (canonical columns, timestamp first)")
    _csv_format(rp)
    rp.add_argument("--out", required=True, help="output directory")
    rp.add_argument("--config", default=None, help=PLANT_HELP)
    rp.add_argument("--initial-window", default=None,
                    help="START/END of the clean initial window (default: the first 90 usable minutes)")
    rp.add_argument("--window-hours", type=float, default=None, help="calibration window length (2 h)")
    rp.add_argument("--cip-off-minutes", type=float, default=None,
                    help="a plant stop longer than this counts as a CIP (360)")
    rp.add_argument("--no-optimize", action="store_true", help="skip the set-point optimization")
    rp.add_argument("--forecast-horizon-days", type=float, default=None, metavar="DAYS",
                    help="R_th,f forecast this far after each window's end, in forecast.csv "
                         "(plant.yaml cip.horizon_days, 7)")
    rp.add_argument("--hindsight", action="store_true",
                    help="learn the compressor curves on the whole history first (default: causal, "
                         "each window uses only the data up to its end, as the gateway would)")
    rp.add_argument("--save-state", default=None, metavar="STATE_DIR",
                    help="also save the initial, dp_clean and last fouling results as state there")
    rp.add_argument("--workers", type=_workers, default=1, metavar="N",
                    help="processes for the windows' analysis: 1 (default) in this process, N > 1 a "
                         "process pool of N; the results equal a sequential replay with the surrogate "
                         "off (a parallel replay searches in every window)")
    rp.set_defaults(func=cmd_replay)


def _workers(text: str) -> int:
    import argparse
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of workers >= 1, got {text!r}") from None
    if not 1 <= n <= 256:
        raise argparse.ArgumentTypeError(f"expected a whole number of workers 1..256, got {n}")
    return n


def process_pool(workers: int):
    """The stdlib process pool of ``replay --workers N`` (spawned processes: each builds its own
    CoolProp state and property tables; nothing but the windows' tasks is shipped). Each worker
    pins itself to its own CPU, the i-th started to the i-th CPU this process may use, round robin
    (``edge.cpupin``: the lockstep's thread hand-overs otherwise wait on a busy core); this
    process, which runs the windows' passes 1 and 3, stays unpinned. Ctrl-C: the workers ignore
    SIGINT (a terminal sends it to all of them; each printed its traceback), this process gets it,
    and leaving the ``with`` block on an exception cancels the chunks not started and waits only
    for the running ones (until stop 41 it waited for every queued chunk: a Ctrl-C seemed to hang).
    The workers are started here, all of them, with SIGINT held back in this process meanwhile
    (``edge.procsignals``): they inherit the blocked signal and unblock it only once they ignore it
    (``pool_worker``), so a Ctrl-C while a worker still imports reaches this process alone (it gave
    a traceback from the worker); this process takes it as the block ends and stops the pool."""
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    from edge.procsignals import held

    class Pool(ProcessPoolExecutor):
        def __exit__(self, exc_type, exc, tb):
            self.shutdown(wait=True, cancel_futures=exc_type is not None)
            return False
    ctx = multiprocessing.get_context("spawn")
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    pool = Pool(max_workers=workers, mp_context=ctx, initializer=pool_worker, initargs=(ctx.Value("i", 0), cpus))
    try:
        with held():        # a Ctrl-C meanwhile is raised as it ends
            # one task a worker, none idle yet: submit starts a process for each, there and then
            # (os.getpid: nothing to import); they boot while this process goes on
            for _ in range(workers):
                pool.submit(os.getpid)
    except BaseException:       # Ctrl-C as they start: this process stops them before it goes
        pool.shutdown(wait=True, cancel_futures=True)
        raise
    return pool


def pool_worker(counter, cpus) -> None:
    """``process_pool``'s initializer in each worker: SIGINT ignored, then unblocked (the parent
    handles Ctrl-C and stops the pool), then pinned (``edge.cpupin.pin_next``) where the OS allows it. Never raises."""
    import signal
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except (OSError, ValueError):
        pass
    from edge.procsignals import block_sigint
    block_sigint(False)         # blocked since process_pool started it: a Ctrl-C held back is dropped
    if cpus is not None:
        from edge.cpupin import pin_next
        pin_next(counter, cpus)


def _csv_format(p) -> None:
    p.add_argument("--sep", choices=(",", ";", "tab"), default=None,
                   help="column separator of the CSV (default: detected from the header)")
    p.add_argument("--decimal", choices=(".", ","), default=None,
                   help="decimal mark of the CSV (default: detected from the numbers)")


def _common(p) -> None:
    p.add_argument("data", help="history CSV (canonical columns, timestamp first)")
    _csv_format(p)
    p.add_argument("--config", default=None, help=PLANT_HELP)
    p.add_argument("--state-dir", default=DEFAULT_STATE_DIR, help=f"state directory ({DEFAULT_STATE_DIR})")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------
class CommandError(Exception):
    """A user-facing error: printed as 'hp-edge <cmd>: message', exit code 2."""


def _fail(cmd: str, exc: Exception) -> int:
    from edge.yamlfile import format_problems
    for line in format_problems(str(exc).splitlines() or [type(exc).__name__]):
        print(f"hp-edge {cmd}: {line}", file=sys.stderr)
    return 2


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("hp-edge")
    except PackageNotFoundError:
        return "unknown"


def _params(path):
    from edge.config import find_config
    from edge.plantfile import load_plant
    return load_plant(find_config("plant.yaml", path))


def parse_window(text: str):
    """'START/END' -> (start, end) UTC Timestamps."""
    import pandas as pd
    parts = text.split("/")
    if len(parts) != 2 or not all(p.strip() for p in parts):
        raise CommandError(f"window {text!r}: expected START/END, e.g. 2024-03-01T00:00/2024-03-01T02:00")
    out = []
    for p in parts:
        try:
            t = pd.Timestamp(p.strip())
        except ValueError as exc:
            raise CommandError(f"window {text!r}: cannot read {p!r} as a time ({exc})") from None
        out.append(t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC"))
    if not out[0] < out[1]:
        raise CommandError(f"window {text!r}: START must be before END")
    return out[0], out[1]


def read_history_csv(path, sep=None, decimal=None):
    """(history DataFrame sorted by time with a UTC ``timestamp`` column, skipped rows per reason,
    non-numeric cells per column); edge.io.history does the reading (CommandError on failure)."""
    from edge.io.history import HistoryError
    from edge.io.history import read_history_csv as _read
    try:
        return _read(path, sep, decimal)
    except HistoryError as exc:
        raise CommandError(str(exc)) from None


def _read_history(path, args):
    """edge.io.history.History of ``path`` with the command's --sep/--decimal."""
    from edge.io.history import HistoryError, read_history
    sep = {"tab": "\t"}.get(args.sep, args.sep) if getattr(args, "sep", None) else None
    try:
        return read_history(path, sep, getattr(args, "decimal", None))
    except HistoryError as exc:
        raise CommandError(str(exc)) from None


def _report_reading(path, history, out=None) -> None:
    out = out or sys.stdout
    for line in history.report_lines(path):
        print(line, file=out)


def _load(args):
    """(plant params, history, window or None); reports what was read unless --json."""
    params = _params(args.config)
    h = _read_history(args.data, args)
    hist = h.frame
    if not args.json:
        _report_reading(args.data, h)
    window = parse_window(args.window) if getattr(args, "window", None) else None
    return params, hist, window


def _base_model(params, state_dir, adaptive: bool):
    """plant.yaml + saved initial calibration and dp_clean fit (+ fouling when adaptive)."""
    from edge.statefiles import DP_CLEAN, FOULING_CALIBRATION, INITIAL_CALIBRATION, read_state
    from model.calibration import apply_state
    initial = read_state(INITIAL_CALIBRATION, state_dir)
    dp = read_state(DP_CLEAN, state_dir)
    fouling = read_state(FOULING_CALIBRATION, state_dir) if adaptive else None
    notes = []
    if initial is None:
        notes.append(f"no initial calibration in {state_dir}: using plant.yaml's correction factors")
    if dp is None:
        notes.append(f"no clean pressure-drop fit in {state_dir}: using plant.yaml's dp_clean_coef")
    if adaptive and fouling is None:
        notes.append(f"no fouling calibration in {state_dir}: the model has no fouling")
    return apply_state(params, initial, dp, fouling), notes


def _window_mask(hist, processed, window):
    ts = hist["timestamp"]
    m = processed["usable"].to_numpy(dtype=bool).copy()
    if window is not None:
        m &= ((ts >= window[0]) & (ts <= window[1])).to_numpy()
    return m


class Progress:
    """A text progress bar on stderr (a line every 10 % when stderr is not a terminal)."""

    def __init__(self, label: str, stream=None):
        self.label = label
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = time.monotonic()
        self.last_decile = -1
        self._width = 0

    def __call__(self, done: int, total: int) -> None:
        if done == 0:
            self.t0 = time.monotonic()      # the clock starts with the first item
        total = max(total, 1)
        frac = min(done / total, 1.0)
        el = time.monotonic() - self.t0
        eta = el / frac - el if frac > 0 else math.nan
        txt = f"{self.label} [{'#' * int(30 * frac):<30}] {done}/{total}  {el:5.0f} s" + (
            f", ~{eta:.0f} s left" if frac < 1 and math.isfinite(eta) else "")
        if self.tty:
            pad = " " * max(0, self._width - len(txt))   # a shorter line must not leave "leftt"
            self._width = len(txt)
            print("\r" + txt + pad, end="\n" if done >= total else "", file=self.stream,
                  flush=True)
        else:
            dec = int(frac * 10)
            if dec > self.last_decile:
                self.last_decile = dec
                print(txt, file=self.stream, flush=True)


# --------------------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------------------
def cmd_calibrate_initial(args) -> int:
    import numpy as np
    from edge.commissioning import CommissioningLimits
    from edge.plantfile import PlantFileError
    from edge.statefiles import COMPRESSORS, DP_CLEAN, INITIAL_CALIBRATION, StateError, write_state
    from model.analysis.chain import AnalysisChain, ChainSettings
    from model.analysis.compressors import LearningError
    from model.calibration import CalibrationError, calibrate, calibration_frame, spec_from_config
    from model.dpfit import DpFitError, fit_dp_clean
    from model.measured import process
    from model.analysis.replay import ReplaySettings
    try:
        params, hist, window = _load(args)
        processed = process(hist, params)
        mask = _window_mask(hist, processed, window)
        if window is None:
            n0 = ReplaySettings.from_config(params.extra).initial_minutes
            idx = np.flatnonzero(mask)[:n0]
            mask = np.zeros(len(mask), dtype=bool)
            mask[idx] = True
        if not mask.any():
            raise CommandError("no usable samples in the window"
                               + _unusable_note(processed, window, hist))
        ts = hist["timestamp"][mask]
        win = (ts.iloc[0].isoformat(), ts.iloc[-1].isoformat())
        data = calibration_frame(hist, processed, mask)
        # the compressors' curves from the commissioning data first, then the initial calibration
        # with them applied (the condenser factors must not absorb the compressors' difference)
        chain = AnalysisChain(params, spec_from_config(params.extra, "fouling"),
                              ChainSettings.from_config(params.extra))
        learner = chain.commissioning_learner(hist.loc[mask])
        base = learner.apply(params) if learner is not None else params
        res = calibrate(data, base, spec_from_config(params.extra, "initial"), window=win)
        dp = fit_dp_clean(data["V_source"], data["dp_source_bar"], window=win)
        failed = CommissioningLimits.from_config(params.extra).failures(res, dp)
        if failed and not args.force:
            raise CommandError(
                "not saved: the result fails the plausibility limits of plant.yaml "
                "calibration.initial.limits (wrong input? e.g. swapped columns; --force saves "
                "it anyway):\n" + "\n".join(f"  {f}" for f in failed))
        p1 = write_state(INITIAL_CALIBRATION, res.to_dict(), args.state_dir)
        p2 = write_state(DP_CLEAN, dp.to_dict(), args.state_dir)
        if learner is not None:
            write_state(COMPRESSORS, learner.to_dict(), args.state_dir)
    except (CommandError, PlantFileError, CalibrationError, DpFitError, StateError,
            LearningError, ValueError) as exc:
        return _fail("calibrate initial", exc)
    if failed:
        for f in failed:
            print(f"hp-edge calibrate initial: WARNING (saved with --force): {f}", file=sys.stderr)
    if args.json:
        print(json.dumps({"initial": res.to_dict(), "dp_clean": dp.to_dict()}, indent=1))
    else:
        print(res.summary())
        print(f"clean pressure drop ({dp.form}): dp = {dp.coef_bar[0]:.5g} + {dp.coef_bar[1]:.5g}*V + "
              f"{dp.coef_bar[2]:.5g}*V^2 bar (V in m3/h), R^2 {dp.r2:.3f}, flows "
              f"{dp.V_range_m3h[0]:.0f}-{dp.V_range_m3h[1]:.0f} m3/h" + (f"; {dp.note}" if dp.note else ""))
        print(f"saved {p1} and {p2}")
    return 0


def _unusable_note(processed, window, hist) -> str:
    from model.measured import usable_counts
    if window is not None:
        ts = hist["timestamp"]
        sel = ((ts >= window[0]) & (ts <= window[1])).to_numpy()
        if not sel.any():
            return f" (the file has no rows between {window[0]} and {window[1]})"
        counts = usable_counts(processed.loc[sel])
    else:
        counts = usable_counts(processed)
    return " (unusable: " + ", ".join(f"{k}: {v}" for k, v in counts.items()) + ")" if counts else ""


def cmd_calibrate_fouling(args) -> int:
    from edge.plantfile import PlantFileError
    from edge.statefiles import FOULING_CALIBRATION, StateError, write_state
    from model.calibration import (CalibrationError, calibrate, calibration_frame, evaporator_share,
                                   spec_from_config)
    from model.measured import process
    try:
        params, hist, window = _load(args)
        fixed, notes = _base_model(params, args.state_dir, adaptive=False)
        processed = process(hist, fixed)
        mask = _window_mask(hist, processed, window)
        if not mask.any():
            raise CommandError("no usable samples in the window" + _unusable_note(processed, window, hist))
        ts = hist["timestamp"][mask]
        win = (ts.iloc[0].isoformat(), ts.iloc[-1].isoformat())
        res = calibrate(calibration_frame(hist, processed, mask), fixed,
                        spec_from_config(params.extra, "fouling"), window=win)
        doc = res.to_dict()
        adaptive = res.apply(fixed)
        doc["R_th_f_share"] = evaporator_share(adaptive)
        path = write_state(FOULING_CALIBRATION, doc, args.state_dir)
    except (CommandError, PlantFileError, CalibrationError, StateError) as exc:
        return _fail("calibrate fouling", exc)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        for n in notes:
            print(f"note: {n}")
        print(res.summary())
        print(f"  R_th,f share of the evaporator resistance: {100 * doc['R_th_f_share']:.1f} %")
        print(f"saved {path}")
    return 0


def cmd_optimize(args) -> int:
    from edge.plantfile import PlantFileError
    from edge.statefiles import StateError
    from model.measured import process
    from model.optimize import OptimizationError, optimize_setpoint
    try:
        params, hist, window = _load(args)
        adaptive, notes = _base_model(params, args.state_dir, adaptive=True)
        processed = process(hist, adaptive)
        mask = _window_mask(hist, processed, window)
        if not mask.any():
            raise CommandError("no usable samples in the window" + _unusable_note(processed, window, hist))
        res = optimize_setpoint(hist.loc[mask], adaptive)
    except (CommandError, PlantFileError, OptimizationError, StateError) as exc:
        return _fail("optimize", exc)
    if args.json:
        print(json.dumps(res.to_dict(), indent=1))
    else:
        for n in notes:
            print(f"note: {n}")
        print(res.summary())
    return 0


def cmd_fit_surrogate(args) -> int:
    from edge.plantfile import PlantFileError
    from edge.statefiles import INITIAL_CALIBRATION, SURROGATE, StateError, read_state, write_state
    from model.calibration import apply_state
    from model.surrogate import (INPUTS, OUTPUTS, SurrogateError, design_from_config, fit_surrogate,
                                 generate_samples)
    try:
        params = _params(args.config)
        initial = read_state(INITIAL_CALIBRATION, args.state_dir)
        base = apply_state(params, initial)
        design = design_from_config(params.extra)
        if args.points_per_level is not None:
            design["points_per_level"] = args.points_per_level
        if args.seed is not None:
            design["seed"] = args.seed
        t0 = time.perf_counter()
        samples, skipped = generate_samples(base, design, progress=Progress("optimizing"))
        sur = fit_surrogate(samples, seed=int(design["seed"]),
                            reference_p_m_sp_barg=float(design["reference_p_m_sp_barg"]),
                            meta={"design": design, "skipped_points": skipped,
                                  "model": "plant.yaml + initial calibration" if initial else "plant.yaml",
                                  "sampling_time_s": time.perf_counter() - t0})
        if args.out:
            sur.save(args.out)
            path = args.out
        else:
            path = str(write_state(SURROGATE, sur.to_dict(), args.state_dir))
    except (PlantFileError, SurrogateError, StateError) as exc:
        return _fail("fit-surrogate", exc)
    if args.json:
        print(json.dumps(sur.to_dict(), indent=1))
    else:
        print(f"surrogate fitted on {sur.n_train} optima, tested on {sur.n_test} held out "
              f"({sum(skipped.values())} design points skipped: "
              + (", ".join(f"{k}: {v}" for k, v in skipped.items()) or "none") + ")")
        for name, unit in OUTPUTS:
            print(f"  {name:<15} R^2 test {sur.r2_test[name]:.4f}, train {sur.r2_train[name]:.4f}")
        print("  fitted on: " + ", ".join(f"{n} {lo:.4g}..{hi:.4g} {u}" for (n, u), (lo, hi)
                                          in zip(INPUTS, sur.ranges)))
        print(f"saved {path}")
    return 0


def cmd_replay(args) -> int:
    from pathlib import Path
    from edge.plantfile import PlantFileError
    from edge.replaydir import write_replay_dir
    from edge.statefiles import (COMPRESSORS, DP_CLEAN, FOULING_CALIBRATION, INITIAL_CALIBRATION,
                                 SURROGATE_TRACKER, StateError, write_state)
    from model.calibration import CalibrationError
    from model.dpfit import DpFitError
    from model.analysis.chain import ChainSettings
    from model.analysis.cip import CipConfigError
    from model.analysis.replay import ReplayError, ReplaySettings, replay
    from edge.config import find_config
    from edge.io.prices import PriceFileError, price_for_plant
    from concurrent.futures import BrokenExecutor
    workers = getattr(args, "workers", 1)
    try:
        params = _params(args.config)
        h_days = args.forecast_horizon_days
        if h_days is not None and not (math.isfinite(h_days) and 0 <= h_days <= 365):
            raise CommandError(f"--forecast-horizon-days {h_days:g}: expected a number of days in 0..365")
        try:
            price = price_for_plant(params.extra, find_config("plant.yaml", args.config))
        except PriceFileError as exc:
            raise CommandError(f"key 'cip.electricity_price_csv': {exc}") from None
        h = _read_history(args.history, args)
        hist, skipped, nn = h.frame, h.skipped, h.non_numeric
        _report_reading(args.history, h)
        settings = ReplaySettings.from_config(params.extra, window_hours=args.window_hours,
                                              cip_off_minutes=args.cip_off_minutes,
                                              optimize=False if args.no_optimize else None,
                                              hindsight=True if args.hindsight else None)
        iw = parse_window(args.initial_window) if args.initial_window else None
        chain_settings = ChainSettings.from_config(params.extra, cip_price=price, optimize=settings.optimize,
                                                   min_samples=int(settings.min_samples),
                                                   use_surrogate=bool(settings.surrogate))
        if h_days is not None:
            chain_settings = dataclasses.replace(
                chain_settings, cip=dataclasses.replace(chain_settings.cip, horizon_days=float(h_days)))
        if price is not None:
            _check_price_cover(price, hist)
        if workers > 1:
            with process_pool(workers) as pool:
                res = replay(hist, params, settings, initial_window=iw, progress=Progress("windows"),
                             chain_settings=chain_settings, executor=pool)
        else:
            res = replay(hist, params, settings, initial_window=iw, progress=Progress("windows"),
                         chain_settings=chain_settings)
        out = Path(args.out)
        header = ""
        if skipped or nn:
            header = f"rows skipped while reading: {skipped or 'none'}; non-numeric values: {nn or 'none'}"
        text = write_replay_dir(res, out, {"plant": str(find_config("plant.yaml", args.config)),
                                           "history": str(args.history),
                                           "hp_edge_version": _version(), "workers": workers}, header)
        if args.save_state:
            write_state(INITIAL_CALIBRATION, res.initial.to_dict(), args.save_state)
            write_state(DP_CLEAN, res.dp_clean.to_dict(), args.save_state)
            if res.last_fouling is not None:
                write_state(FOULING_CALIBRATION, res.last_fouling.to_dict(), args.save_state)
            if res.compressors is not None:
                write_state(COMPRESSORS, res.compressors, args.save_state)
            if res.surrogate_tracker is not None:
                write_state(SURROGATE_TRACKER, res.surrogate_tracker, args.save_state)
    except (CommandError, PlantFileError, ReplayError, CalibrationError, DpFitError, StateError,
            CipConfigError, OSError) as exc:
        return _fail("replay", exc)
    except BrokenExecutor:
        # a pool worker died (SIGKILL, e.g. the out-of-memory killer): nothing is written (the
        # directory is written from the finished replay only); no traceback
        print(f"hp-edge replay: a worker process of the pool (--workers {workers}) ended abruptly (killed "
              f"by a signal, e.g. the out-of-memory killer): the replay did not finish and nothing was "
              f"written to {args.out}; run it again, with fewer workers or without --workers", file=sys.stderr)
        return 1
    print(text)
    print(f"wrote {out / 'windows.csv'}, {out / 'cip.csv'}, {out / 'forecast.csv'}, "
          f"{out / 'samples.csv'}, {out / 'summary.txt'}, {out / 'compressors.json'}, "
          f"{out / 'surrogate_tracker.json'}, "
          f"{out / 'meta.json'}")
    return 0


def _check_price_cover(price, hist) -> None:
    """A price series must cover the replayed history (else every window's cost would be missing)."""
    from datetime import datetime, timezone
    ts = hist["timestamp"]
    a, b = ts.iloc[0].timestamp(), ts.iloc[-1].timestamp()
    if a < price.t_s[0] or b > price.end_s:
        fmt = lambda t: datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%MZ")  # noqa: E731
        raise CommandError(f"key 'cip.electricity_price_csv': the price series covers {fmt(price.t_s[0])} .. "
                           f"{fmt(price.end_s)}, the history {fmt(a)} .. {fmt(b)}")
