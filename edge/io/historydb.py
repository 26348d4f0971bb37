"""Read the gateway's history database (edge/store.py) outside the gateway: the report and
``hp-edge export-history`` read it, possibly while the gateway is running.

Only SELECTs, on a connection of its own (SQLite's WAL lets readers run beside the writer); a path
that does not exist is an error, never a new empty database. Times are epoch seconds on the sample
clock (``ts``, the start of each one-minute period), as stored.
"""
from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pandas as pd

BUSY_TIMEOUT_S = 5.0


class HistoryDbError(ValueError):
    """The history database cannot be read; the message names the file."""


def _connect(path: Path) -> sqlite3.Connection:
    if not path.is_file():
        raise HistoryDbError(f"{path}: no such history database")
    try:
        db = sqlite3.connect(path, timeout=BUSY_TIMEOUT_S)
        db.execute("SELECT name FROM sqlite_master LIMIT 1").fetchall()
    except sqlite3.DatabaseError as exc:
        raise HistoryDbError(f"{path}: not a readable history database ({exc})") from None
    return db


def _epoch(t) -> int | None:
    if t is None:
        return None
    ts = pd.Timestamp(t)
    ts = ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")
    return int(ts.timestamp())


def read_table(path: str | Path, table: str, start=None, end=None) -> pd.DataFrame:
    """Rows of ``samples`` or ``advice`` with start <= ts <= end (either may be None), oldest
    first, all columns as stored; an empty frame (with a ``ts`` column) when there are none.
    ``detail`` of advice rows is decoded from JSON ({} when absent or unreadable)."""
    if table not in ("samples", "advice"):
        raise ValueError(f"unknown table {table!r}")
    path = Path(path)
    db = _connect(path)
    try:
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if table not in tables:
            if table == "samples":
                raise HistoryDbError(f"{path}: has no table 'samples' (not a gateway history)")
            return pd.DataFrame({"ts": pd.Series(dtype="int64")})
        where, args = [], []
        if start is not None:
            where.append("ts >= ?")
            args.append(_epoch(start))
        if end is not None:
            where.append("ts <= ?")
            args.append(_epoch(end))
        sql = f"SELECT * FROM {table}" + (" WHERE " + " AND ".join(where) if where else "") \
            + " ORDER BY ts"
        try:
            cur = db.execute(sql, args)
            cols = [d[0] for d in cur.description]
            rows = cur.fetchall()
        except sqlite3.DatabaseError as exc:
            raise HistoryDbError(f"{path}: cannot read table {table}: {exc}") from None
    finally:
        db.close()
    df = pd.DataFrame.from_records(rows, columns=cols)
    if table == "advice" and "detail" in df.columns:
        df["detail"] = [_decode(v) for v in df["detail"]]
    return df


def _decode(v) -> dict:
    if isinstance(v, dict):
        return v
    if not isinstance(v, str) or not v:
        return {}
    try:
        d = json.loads(v)
    except json.JSONDecodeError:
        return {}
    return d if isinstance(d, dict) else {}


def utc_index(ts) -> pd.DatetimeIndex:
    """Epoch seconds -> a UTC DatetimeIndex."""
    return pd.DatetimeIndex(pd.to_datetime(pd.Series(ts, dtype="float64"), unit="s", utc=True))
