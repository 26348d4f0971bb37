"""Local history in SQLite: one-minute samples (tags, derived columns, usable/reason) and the
advisory outputs of every calibration cycle.

Durability: WAL journal with ``synchronous=FULL``; every ``add_*`` call is one transaction, so a
crash (kill -9, power loss on a sane disk) at any moment loses no committed row - SQLite either
has the whole transaction or none of it. Size is bounded: rows older than the retention (counted
back from the newest sample, on the sample clock) are deleted at most once per ``prune_every_s``
of sample time, with a row cap as a backstop against clock jumps; SQLite reuses the freed pages,
and the WAL file is truncated to ``journal_size_limit`` after checkpoints.

A database that cannot be opened (not a database, malformed) is moved aside to
``<name>.corrupt-<unix time>`` and a fresh one is started: the gateway must keep running; the
history is a convenience, the state that matters (calibrations) lives in the state directory.

Columns are created on demand: a new tag or derived quantity adds a column (``ALTER TABLE ADD
COLUMN``). Names must be identifiers. The connection is used from worker threads
(``asyncio.to_thread``), one call at a time (a lock).
"""
from __future__ import annotations

import json
import logging
import math
import re
import sqlite3
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import pandas as pd

log = logging.getLogger(__name__)

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
SAMPLE_TEXT = ("reason", "quality", "bad")
SAMPLE_INT = ("usable", "scans", "good_scans")
ADVICE_TEXT = ("status_bits", "detail", "message")
ADVICE_INT = ("ok", "calibration_ok", "optimization_ok")
BUSY_TIMEOUT_S = 5.0


class StoreError(Exception):
    """The history database failed in a way the gateway should log and survive."""


class HistoryStore:
    """SQLite history. ``open()`` before use (or use as a context manager)."""

    def __init__(self, path: str | Path, retention_days: float, *, aggregate_s: float = 60.0,
                 prune_every_s: float = 3600.0, max_rows: int | None = None) -> None:
        if retention_days <= 0:
            raise ValueError(f"retention_days must be > 0, got {retention_days}")
        self.path = Path(path)
        self.retention_s = float(retention_days) * 86400.0
        self.prune_every_s = float(prune_every_s)
        # backstop: retention's worth of samples plus 10 %
        self.max_rows = max_rows or int(self.retention_s / aggregate_s * 1.1) + 1000
        self._db: sqlite3.Connection | None = None
        self._lock = threading.Lock()
        self._columns: dict[str, set[str]] = {}
        self._last_prune: float | None = None

    # ------------------------------------------------------------------------- lifecycle

    def open(self) -> HistoryStore:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = self._connect()
        except sqlite3.DatabaseError as exc:
            aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
            log.error("history %s cannot be opened (%s); moved aside to %s, starting a new one",
                      self.path, exc, aside.name)
            self.path.rename(aside)
            for suffix in ("-wal", "-shm"):
                side = self.path.with_name(self.path.name + suffix)
                if side.exists():
                    side.rename(aside.with_name(aside.name + suffix))
            self._db = self._connect()
        return self

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None,
                             check_same_thread=False)
        try:
            mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if mode.lower() != "wal":
                log.warning("history %s: journal mode %s (WAL not available)", self.path, mode)
            db.execute("PRAGMA synchronous=FULL")
            db.execute("PRAGMA journal_size_limit=8388608")
            db.execute("CREATE TABLE IF NOT EXISTS samples (ts INTEGER PRIMARY KEY, wall REAL)")
            db.execute("CREATE TABLE IF NOT EXISTS advice (ts INTEGER PRIMARY KEY, wall REAL)")
            self._columns = {t: {r[1] for r in db.execute(f"PRAGMA table_info({t})")}
                             for t in ("samples", "advice")}
        except sqlite3.DatabaseError:
            db.close()
            raise
        return db

    def close(self) -> None:
        with self._lock:
            if self._db is not None:
                try:
                    self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                except sqlite3.Error as exc:
                    log.warning("history %s: checkpoint at close failed: %s", self.path, exc)
                self._db.close()
                self._db = None

    def __enter__(self) -> HistoryStore:
        return self.open()

    def __exit__(self, *exc_info) -> None:
        self.close()

    @property
    def db(self) -> sqlite3.Connection:
        if self._db is None:
            raise StoreError(f"history {self.path} is not open")
        return self._db

    # ---------------------------------------------------------------------------- writing

    def _ensure_columns(self, table: str, row: Mapping[str, Any], text: Iterable[str],
                        ints: Iterable[str]) -> None:
        have = self._columns[table]
        text, ints = set(text), set(ints)
        for name in row:
            if name in have:
                continue
            if not _IDENT.match(name):
                raise ValueError(f"column name {name!r} is not an identifier")
            kind = "TEXT" if name in text else "INTEGER" if name in ints else "REAL"
            self.db.execute(f'ALTER TABLE {table} ADD COLUMN "{name}" {kind}')
            have.add(name)

    def _upsert(self, table: str, rows: list[dict], text, ints) -> None:
        with self._lock:
            db = self.db
            try:
                db.execute("BEGIN IMMEDIATE")
                for row in rows:
                    self._ensure_columns(table, row, text, ints)
                    cols = list(row)
                    names = ",".join('"' + c + '"' for c in cols)
                    marks = ",".join("?" * len(cols))
                    sql = f"INSERT OR REPLACE INTO {table} ({names}) VALUES ({marks})"
                    db.execute(sql, [_sql_value(row[c]) for c in cols])
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                self._columns = {t: {r[1] for r in db.execute(f"PRAGMA table_info({t})")}
                                 for t in ("samples", "advice")}
                raise

    def add_samples(self, rows: Iterable[Mapping[str, Any]]) -> int:
        """Insert (or replace, same ``ts``) one-minute samples in ONE transaction.

        Each row needs ``ts`` [epoch s, int]; other keys become columns (numbers REAL, the
        columns reason/quality/bad TEXT, usable/scans/good_scans INTEGER). Returns rows written.
        """
        wall = time.time()
        out = []
        for r in rows:
            row = {"ts": int(r["ts"]), "wall": wall}
            row.update((k, v) for k, v in r.items() if k != "ts")
            out.append(row)
        if out:
            self._upsert("samples", out, SAMPLE_TEXT, SAMPLE_INT)
            self._maybe_prune(max(r["ts"] for r in out))
        return len(out)

    def add_advice(self, ts: float, record: Mapping[str, Any]) -> None:
        """One calibration cycle's outputs (advisory values, ok flag, status bits, detail)."""
        row = {"ts": int(ts), "wall": time.time()}
        for k, v in record.items():
            row[k] = json.dumps(v, default=_json_default, sort_keys=True) if k == "detail" else v
        self._upsert("advice", [row], ADVICE_TEXT, ADVICE_INT)

    def _maybe_prune(self, newest: float) -> None:
        if self._last_prune is not None and newest - self._last_prune < self.prune_every_s \
                and newest >= self._last_prune:
            return
        self._last_prune = newest
        self.prune(newest)

    def prune(self, newest: float) -> int:
        """Delete samples and advice older than the retention before ``newest``, then cap the
        sample rows. Returns the rows deleted."""
        cutoff = int(newest - self.retention_s)
        with self._lock:
            db = self.db
            db.execute("BEGIN IMMEDIATE")
            try:
                n = db.execute("DELETE FROM samples WHERE ts < ?", (cutoff,)).rowcount
                n += db.execute("DELETE FROM advice WHERE ts < ?", (cutoff,)).rowcount
                count = db.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
                if count > self.max_rows:
                    n += db.execute(
                        "DELETE FROM samples WHERE ts IN (SELECT ts FROM samples ORDER BY ts "
                        "LIMIT ?)", (count - self.max_rows,)).rowcount
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
        if n:
            log.info("history: pruned %d rows older than %s", n, cutoff)
        return n

    # ---------------------------------------------------------------------------- reading

    def window(self, end: float, seconds: float, usable_only: bool = True) -> pd.DataFrame:
        """Samples with end - seconds < ts <= end, oldest first, index ``timestamp`` (UTC)."""
        where = "ts > ? AND ts <= ?" + (" AND usable = 1" if usable_only else "")
        with self._lock:
            cur = self.db.execute(f"SELECT * FROM samples WHERE {where} ORDER BY ts",
                                  (int(end - seconds), int(end)))
            cols = [d[0] for d in cur.description]
            rows = cur.fetchall()
        df = pd.DataFrame.from_records(rows, columns=cols)
        df.index = pd.to_datetime(df["ts"], unit="s", utc=True)
        df.index.name = "timestamp"
        return df

    def count(self, table: str = "samples") -> int:
        if table not in ("samples", "advice"):
            raise ValueError(f"unknown table {table!r}")
        with self._lock:
            return int(self.db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])

    def latest_sample_ts(self) -> int | None:
        with self._lock:
            return self.db.execute("SELECT MAX(ts) FROM samples").fetchone()[0]

    def latest_advice(self, ok_only: bool = True) -> dict | None:
        """The newest advice row as a dict (``detail`` decoded), or None."""
        where = "WHERE ok = 1 " if ok_only and "ok" in self._columns["advice"] else ""
        with self._lock:
            cur = self.db.execute(f"SELECT * FROM advice {where}ORDER BY ts DESC LIMIT 1")
            cols = [d[0] for d in cur.description]
            row = cur.fetchone()
        if row is None:
            return None
        out = dict(zip(cols, row))
        if isinstance(out.get("detail"), str):
            out["detail"] = json.loads(out["detail"])
        return out


def _sql_value(v: Any) -> Any:
    """Python/numpy value -> what sqlite3 stores (NaN -> NULL, numpy scalars -> Python)."""
    if v is None or isinstance(v, (str, bytes)):
        return v
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (dict, list, tuple)):
        return json.dumps(v, default=_json_default, sort_keys=True)
    if hasattr(v, "item"):   # numpy scalar
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _json_default(o: Any) -> Any:
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
