"""Export a simulated history without a server: one-minute samples with the canonical columns of
SPEC §4 (and the hidden truth beside them, in a separate file), for replay and calibration tests.

Each one-minute row is the mean of the plant's ticks in that minute, every tick quantized by its
register type exactly as a client would decode it (so the history carries the same resolution as a
gateway poll); running is the minute's minimum, cip its maximum, p_m_sp its last value. Timestamps
are the start of each minute, ISO 8601 UTC (the gateway's aggregation convention). Tag faults
scheduled in the config apply (stuck, out_of_range, nan); frozen repeats the last row; the
Modbus-side faults (slow, drop, restart) have no meaning here and are ignored.
The truth row of a minute is the plant's hidden state at the start of that minute.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .config import TAG_FAULTS, SimulatorConfig, load_simulator_config, read_tags
from .faults import Faults
from .plant import NAMES, Plant
from .profiles import DAY
from .registers import SYSTEM_TAGS, quantize

MINUTE = 60.0


@dataclass
class ExportResult:
    history: pd.DataFrame          # timestamp + canonical columns
    truth: pd.DataFrame | None     # timestamp + hidden truth (when asked for)
    seconds: float                 # wall time spent
    rows: int


def export_history(days: float, path: str | Path | None = None, *, cfg: SimulatorConfig | None = None,
                   seed: int | None = None, truth_path: str | Path | None = None,
                   with_truth: bool | None = None, progress=None) -> ExportResult:
    """Simulate ``days`` of plant time from cfg.start_time and return (and write) the history.

    path / truth_path: CSV files to write (None: only return the frames).
    with_truth: compute the truth frame (default: when truth_path is given).
    progress: optional callable(day_done, days_total).
    """
    t_wall = time.perf_counter()
    cfg = cfg or load_simulator_config()
    if seed is not None:
        cfg = cfg.replace(seed=seed)
    if with_truth is None:
        with_truth = truth_path is not None
    tags = read_tags(cfg.tags_file)
    columns = [n for n in tags if n not in SYSTEM_TAGS]
    plant = Plant(cfg)
    plant.record_truth = False
    tpm = MINUTE / plant.dt
    if abs(tpm - round(tpm)) > 1e-9 or round(tpm) < 1:
        raise ValueError(f"time.tick_s={plant.dt} must divide one minute for the export")
    tpm = int(round(tpm))
    n_min = int(round(days * DAY / MINUTE))
    # tick matrix columns: the plant's sensors, then running, cip, p_m_sp
    extra = ("running", "cip", "p_m_sp")
    names = list(NAMES) + list(extra)
    col_of = {n: i for i, n in enumerate(names)}
    n_cols = len(names)
    faults = Faults(tags, seed=cfg.seed)
    schedule = [f for f in cfg.faults if f.kind in TAG_FAULTS + ("frozen",)]
    minutes_per_chunk = 1440
    hist_parts, truth_rows = [], []
    last_row: np.ndarray | None = None
    for m0 in range(0, n_min, minutes_per_chunk):
        nm = min(minutes_per_chunk, n_min - m0)
        block = np.empty((nm * tpm, n_cols))
        frozen_rows = np.zeros(nm, dtype=bool)
        for m in range(nm):
            if with_truth:
                truth_rows.append(plant.truth())
            h = (plant.t - plant.t0) / 3600.0
            active = _schedule(faults, schedule, h)
            frozen_rows[m] = faults.frozen
            for j in range(tpm):
                plant.tick()
                row = block[m * tpm + j]
                row[: len(NAMES)] = plant.noisy
                row[col_of["running"]] = plant.running
                row[col_of["cip"]] = plant.cip_window is not None
                row[col_of["p_m_sp"]] = plant.p_m_sp_bar_g
                if active:
                    vals = faults.apply(dict(zip(names, row.tolist())))
                    row[:] = [vals[n] for n in names]
        # quantize every tick as the register type would, then average per minute
        cube = block.reshape(nm, tpm, n_cols)
        out = {}
        for name in columns:
            if name not in col_of:
                out[name] = np.full(nm, np.nan)   # a tag the plant does not know: no value
                continue
            q = quantize(tags[name], cube[:, :, col_of[name]])
            if name == "running":
                out[name] = q.min(axis=1)
            elif name == "cip":
                out[name] = q.max(axis=1)
            elif name == "p_m_sp":
                out[name] = q[:, -1]
            else:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN minute -> NaN
                    out[name] = np.nanmean(q, axis=1)
        part = pd.DataFrame(out, columns=columns)
        if frozen_rows.any():
            arr = part.to_numpy()
            for i in range(nm):
                if frozen_rows[i] and (last_row is not None or i > 0):
                    arr[i] = arr[i - 1] if i > 0 else last_row
            part = pd.DataFrame(arr, columns=columns)
        last_row = part.to_numpy()[-1].copy()
        stamps = pd.to_datetime(plant.t0 + (m0 + np.arange(nm)) * MINUTE, unit="s", utc=True)
        part.insert(0, "timestamp", stamps.strftime("%Y-%m-%dT%H:%M:%SZ"))
        hist_parts.append(part)
        if progress is not None:
            progress((m0 + nm) / 1440.0, days)
    history = pd.concat(hist_parts, ignore_index=True) if hist_parts else pd.DataFrame(
        columns=["timestamp"] + columns)
    truth = None
    if with_truth:
        truth = pd.DataFrame(truth_rows)
        truth.insert(0, "timestamp", history["timestamp"].to_numpy())
        truth = truth.drop(columns=["time"])
    if path is not None:
        _write_csv(history, Path(path))
    if truth_path is not None and truth is not None:
        _write_csv(truth, Path(truth_path))
    return ExportResult(history, truth, time.perf_counter() - t_wall, len(history))


def _schedule(faults: Faults, schedule, h: float) -> bool:
    """Switch scheduled faults for plant hour h; return whether a tag fault is active."""
    for spec in schedule:
        start = spec.at_h if spec.at_h is not None else 0.0
        end = start + spec.duration_h if spec.duration_h is not None else math.inf
        want = start <= h < end
        if want and not faults.is_on(spec.kind, spec.tag):
            faults.enable_spec(spec)
        elif not want and faults.is_on(spec.kind, spec.tag):
            faults.disable(spec.kind, spec.tag)
    return any(f.kind in TAG_FAULTS for f in faults.active())


def _write_csv(df: pd.DataFrame, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    df.to_csv(tmp, index=False, float_format="%.7g")
    tmp.replace(path)


def read_history(path: str | Path) -> pd.DataFrame:
    """Read an exported history CSV back: DatetimeIndex (UTC) named timestamp, float columns."""
    df = pd.read_csv(path)
    df["timestamp"] = pd.to_datetime(df["timestamp"], utc=True)
    return df.set_index("timestamp")

