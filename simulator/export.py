"""Export a simulated history without a server: one-minute samples with the canonical columns of
SPEC §4 (and the hidden truth beside them, in a separate file), for replay and calibration tests.

Each one-minute row is the mean of the plant's ticks in that minute, every tick quantized by its
register type exactly as a client would decode it (so the history carries the same resolution as a
gateway poll); running is the minute's minimum, cip its maximum, p_m_sp its last value. Timestamps
are the start of each minute, ISO 8601 UTC (the gateway's aggregation convention). Tag faults
scheduled in the config apply (stuck, out_of_range, nan); frozen repeats the last row; the
Modbus-side faults (slow, drop, restart) have no meaning here and are ignored.
The truth row of a minute is the plant's hidden state at the start of that minute.

``MinuteStepper`` produces the same rows one minute at a time, for benchmarks that close a loop
through the plant (set point, CIP on request) without a server.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from .config import TAG_FAULTS, TYPE_LIMITS, SimulatorConfig, load_simulator_config, read_tags
from .faults import Faults
from .plant import NAMES, Plant
from .profiles import DAY
from .registers import SYSTEM_TAGS

MINUTE = 60.0
AGGREGATE = {"running": "min", "cip": "max", "p_m_sp": "last"}   # every other column: mean
TIME_FORMAT = "%Y-%m-%dT%H:%M:%SZ"


@dataclass
class ExportResult:
    history: pd.DataFrame          # timestamp + canonical columns
    truth: pd.DataFrame | None     # timestamp + hidden truth (when asked for)
    seconds: float                 # wall time spent
    rows: int


class _MinuteAggregate:
    """Quantize a minute of ticks (ticks x plant columns) as each tag's register type would and
    reduce it to the one-minute row of the history's columns, all columns at once (the same
    arithmetic as registers.quantize, per element)."""

    def __init__(self, tags: dict, columns: list[str], col_of: dict[str, int]):
        self.src = np.array([col_of.get(c, 0) for c in columns])
        self.known = np.array([c in col_of for c in columns])
        specs = [tags[c] for c in columns]
        self.scale = np.array([t.scale for t in specs])
        self.offset = np.array([t.offset for t in specs])
        self.is_float = np.array([t.type == "float32" for t in specs])
        lo, hi = [], []
        for t in specs:
            a, b = TYPE_LIMITS.get(t.type, (-np.inf, np.inf))
            if t.sentinel is not None:
                a, b = (a + 1, b) if t.sentinel == a else (a, b - 1) if t.sentinel == b else (a, b)
            lo.append(a)
            hi.append(b)
        self.lo, self.hi = np.array(lo, dtype=float), np.array(hi, dtype=float)
        how = [AGGREGATE.get(c, "mean") for c in columns]
        self.i_min = np.array([h == "min" for h in how])
        self.i_max = np.array([h == "max" for h in how])
        self.i_last = np.array([h == "last" for h in how])
        self.i_mean = ~(self.i_min | self.i_max | self.i_last)

    def __call__(self, block: np.ndarray) -> np.ndarray:
        raw = (block[:, self.src] - self.offset) / self.scale
        with np.errstate(over="ignore", invalid="ignore"):
            f32 = raw.astype(np.float32).astype(float)
            q = np.where(self.is_float, f32, np.clip(np.round(raw), self.lo, self.hi))
        q = q * self.scale + self.offset
        row = np.empty(q.shape[1])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN minute -> NaN
            row[self.i_mean] = np.nanmean(q[:, self.i_mean], axis=0)
        row[self.i_min] = q[:, self.i_min].min(axis=0)
        row[self.i_max] = q[:, self.i_max].max(axis=0)
        row[self.i_last] = q[-1, self.i_last]
        row[~self.known] = np.nan            # a tag the plant does not know: no value
        return row


class MinuteStepper:
    """The plant advanced minute by minute, giving the one-minute history row and the truth row
    that export_history writes, so a benchmark can drive the plant from Python without a server::

        st = MinuteStepper(cfg.with_sections(cip={"mode": "on_request"}))
        for _ in range(120):
            row, truth = st.step()          # dicts: timestamp + canonical columns; hidden truth
            ...                             # decide on the rows so far
        st.plant.set_p_m_sp(14.0)           # what a client write does
        st.plant.request_cip()              # starts a CIP at the next tick

    ``step()`` returns the minute that starts at ``time`` (plant time, epoch s) and ends one minute
    later: its truth row is the plant's hidden state at the start of the minute, its history row
    the mean of the minute's ticks quantized by each tag's register type (running: the minute's
    minimum, cip: maximum, p_m_sp: last value). Scheduled tag faults (stuck, out_of_range, nan)
    and frozen apply as in the export; Modbus-side faults have no meaning here.
    """

    def __init__(self, cfg: SimulatorConfig | None = None, *, with_truth: bool = True,
                 plant: Plant | None = None):
        self.cfg = cfg = cfg or load_simulator_config()
        self.tags = read_tags(cfg.tags_file)
        # the history's columns: the plant's values (not the PLC's system registers, and not the
        # operator's closed-loop enable, which is no measurement)
        skip = set(SYSTEM_TAGS) | {cfg.remote_setpoint.enable_tag}
        self.columns = [n for n in self.tags if n not in skip]
        self.plant = plant or Plant(cfg)
        self.plant.record_truth = False
        self.with_truth = with_truth
        tpm = MINUTE / self.plant.dt
        if abs(tpm - round(tpm)) > 1e-9 or round(tpm) < 1:
            raise ValueError(f"time.tick_s={self.plant.dt} must divide one minute for the export")
        self.ticks_per_minute = int(round(tpm))
        # tick matrix columns: the plant's sensors, then running, cip, p_m_sp
        self._names = list(NAMES) + ["running", "cip", "p_m_sp"]
        self._col_of = {n: i for i, n in enumerate(self._names)}
        self._aggregate = _MinuteAggregate(self.tags, self.columns, self._col_of)
        self.faults = Faults(self.tags, seed=cfg.seed)
        self._fault_schedule = [f for f in cfg.faults if f.kind in TAG_FAULTS + ("frozen",)]
        self._block = np.empty((self.ticks_per_minute, len(self._names)))
        self._last_row: np.ndarray | None = None
        self.minutes = 0

    @property
    def time(self) -> float:
        """Plant time [epoch s] at the start of the next minute."""
        return self.plant.t

    def step_array(self) -> tuple[np.ndarray, dict | None]:
        """One minute: (history values in the order of ``columns``, truth dict or None). The
        truth dict has no timestamp; ``step()`` adds it."""
        plant = self.plant
        truth = plant.truth() if self.with_truth else None
        h = (plant.t - plant.t0) / 3600.0
        active = _schedule(self.faults, self._fault_schedule, h)
        frozen = self.faults.frozen
        block, names, col = self._block, self._names, self._col_of
        n_sensors = len(NAMES)
        i_run, i_cip, i_sp = col["running"], col["cip"], col["p_m_sp"]
        for j in range(self.ticks_per_minute):
            plant.tick()
            row = block[j]
            row[:n_sensors] = plant.noisy
            row[i_run] = plant.running
            row[i_cip] = plant.cip_window is not None
            row[i_sp] = plant.p_m_sp_bar_g
            if active:
                vals = self.faults.apply(dict(zip(names, row.tolist())))
                row[:] = [vals[n] for n in names]
        out = self._aggregate(block)
        if frozen and self._last_row is not None:
            out = self._last_row.copy()
        self._last_row = out
        self.minutes += 1
        if truth is not None:
            truth.pop("time", None)
        return out, truth

    def step(self) -> tuple[dict, dict | None]:
        """One minute: (history row {timestamp, canonical columns...}, truth row or None), the
        rows export_history writes for that minute (before the CSV's number formatting)."""
        t = self.plant.t
        values, truth = self.step_array()
        stamp = datetime.fromtimestamp(t, timezone.utc).strftime(TIME_FORMAT)
        row = {"timestamp": stamp, **dict(zip(self.columns, values.tolist()))}
        if truth is not None:
            truth = {"timestamp": stamp, **truth}
        return row, truth


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
    stepper = MinuteStepper(cfg, with_truth=with_truth)
    columns = stepper.columns
    t0 = stepper.plant.t0
    n_min = int(round(days * DAY / MINUTE))
    values = np.empty((n_min, len(columns)))
    truth_rows = []
    for m in range(n_min):
        values[m], tr = stepper.step_array()
        if with_truth:
            truth_rows.append(tr)
        if progress is not None and ((m + 1) % 1440 == 0 or m + 1 == n_min):
            progress((m + 1) / 1440.0, days)
    history = pd.DataFrame(values, columns=columns)
    stamps = pd.to_datetime(t0 + np.arange(n_min) * MINUTE, unit="s", utc=True)
    history.insert(0, "timestamp", stamps.strftime(TIME_FORMAT))
    truth = None
    if with_truth:
        truth = pd.DataFrame(truth_rows)
        truth.insert(0, "timestamp", history["timestamp"].to_numpy())
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

