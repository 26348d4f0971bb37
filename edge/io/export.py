"""The gateway's history database as a canonical history CSV (SPEC §4): ``hp-edge export-history``.

The CSV is what ``replay``, ``calibrate`` and ``report`` read: a first column ``timestamp``
(ISO 8601 UTC, the start of each one-minute sample, as the gateway stores it), then the canonical
columns of SPEC §4 in their canonical units (°C, m³/h, bar(g), kW, rpm, 0/1) and in SPEC §4's order,
then ``quality`` (the gateway's mark on a suspect minute: frozen data, communication fault, a bad
tag; empty when the minute was good), so that a sample the gateway distrusted stays unusable after
the round trip. The gateway stores the tags as it decoded them (already in canonical units), so
the values are written unchanged, with 12 significant digits; a missing value is an empty cell.
Derived columns (p_e_bar, COP, usable, ...) are not exported: every reader recomputes them.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from model.measured import REQUIRED

from .historydb import read_table, utc_index

OPTIONAL = ("N_LS", "N_HS", "running", "cip")
CANONICAL_COLUMNS = tuple(REQUIRED) + OPTIONAL
QUALITY = "quality"
FLOAT_FORMAT = "%.12g"


@dataclass
class ExportResult:
    path: Path
    rows: int
    first: str | None                      # first and last timestamp written (ISO 8601 UTC)
    last: str | None
    columns: list[str]                     # canonical columns written (without timestamp)
    missing: list[str] = field(default_factory=list)   # required columns the database lacks
    empty_cells: dict[str, int] = field(default_factory=dict)   # per column, missing values


def history_frame(samples: pd.DataFrame) -> pd.DataFrame:
    """The ``samples`` table (as read by ``edge.io.historydb.read_table``) as a canonical history
    frame: ``timestamp`` (ISO 8601 UTC text), the canonical columns present, ``quality``."""
    out = pd.DataFrame({"timestamp": utc_index(samples["ts"]).strftime("%Y-%m-%dT%H:%M:%SZ")})
    for c in CANONICAL_COLUMNS:
        if c in samples.columns:
            out[c] = pd.to_numeric(samples[c], errors="coerce").to_numpy(dtype=float)
    if QUALITY in samples.columns:
        out[QUALITY] = samples[QUALITY].fillna("").astype(str).to_numpy()
    return out


def export_history(db_path: str | Path, out_path: str | Path, start=None, end=None) -> ExportResult:
    """Write the samples with start <= timestamp <= end (UTC; None: open) of the history database
    ``db_path`` to ``out_path`` (atomically: a temporary file renamed over it).

    Raises ``edge.io.historydb.HistoryDbError`` (unreadable database) and OSError (cannot write).
    """
    samples = read_table(db_path, "samples", start, end)
    frame = history_frame(samples)
    out_path = Path(out_path)
    if out_path.parent != Path(""):
        out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    try:
        frame.to_csv(tmp, index=False, float_format=FLOAT_FORMAT, na_rep="")
        os.replace(tmp, out_path)
    finally:
        if tmp.exists():
            tmp.unlink()
    cols = [c for c in CANONICAL_COLUMNS if c in frame.columns]
    empty = {c: int(np.isnan(frame[c].to_numpy(dtype=float)).sum()) for c in cols}
    return ExportResult(
        path=out_path, rows=len(frame),
        first=str(frame["timestamp"].iloc[0]) if len(frame) else None,
        last=str(frame["timestamp"].iloc[-1]) if len(frame) else None,
        columns=cols, missing=[c for c in REQUIRED if c not in frame.columns],
        empty_cells={c: n for c, n in empty.items() if n})


def describe(res: ExportResult) -> str:
    """A few lines for the command's output."""
    if not res.rows:
        return f"no samples in the period: wrote only the header to {res.path}"
    lines = [f"wrote {res.rows} one-minute samples {res.first} .. {res.last} to {res.path}"]
    if res.missing:
        lines.append("  the history has no column(s) " + ", ".join(res.missing)
                     + ": replay and calibrate will refuse the file")
    if res.empty_cells:
        worst = sorted(res.empty_cells.items(), key=lambda kv: -kv[1])[:6]
        lines.append("  missing values (empty cells): " + ", ".join(f"{k}: {v}" for k, v in worst)
                     + (" ..." if len(res.empty_cells) > 6 else ""))
    return "\n".join(lines)
