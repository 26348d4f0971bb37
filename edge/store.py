"""Local history in SQLite: one-minute samples (tags, derived columns, usable/reason), the
advisory outputs of every calibration cycle, and the closed loop's audit trail (table
``closed_loop``: every set-point write - time, old, new, target, words, outcome - and every change
of the loop's state, in order; edge.closed_loop).

Durability: WAL journal with ``synchronous=FULL``; every write is one transaction, so a crash
(kill -9, power loss on a sane disk) at any moment loses no committed row - SQLite either has the
whole transaction or none of it. Size is bounded: rows older than the retention (counted back from
the newest sample, on the sample clock, never from more than ``PRUNE_MAX_AHEAD_S`` ahead of the
host clock) are deleted at most once per ``prune_every_s`` of sample time, with a row cap as a
backstop against clock jumps; SQLite reuses the freed pages, and the WAL file is truncated to
``journal_size_limit`` after checkpoints.

A stored row is never overwritten: a row whose ``ts`` is already stored (the sample clock went
back and the jump was accepted as a clock correction) keeps the stored one, and the new row goes,
whole, as JSON into the table ``conflicts`` (table, ts, wall, row), with a warning.

Faults, and what happens to the rows:

* the database is **locked** by another process (``SQLITE_BUSY``): ``open()`` retries with
  back-off for ``open_wait_s``, then runs without it and keeps retrying; the file is never moved;
* the disk is **full**, the file or its directory is **read-only** or cannot be created, an I/O
  error: the rows wait in memory (at most ``max_pending``; beyond that the oldest are dropped and
  counted) and are written when a retry succeeds (back-off ``retry_min_s`` .. ``retry_max_s``);
  reads (windows, latest advice) see the waiting rows too, so calibration goes on;
* **real corruption** only (``file is not a database``, ``malformed``, and ``PRAGMA quick_check``
  confirms it) moves the file aside to ``<name>.corrupt-<unix time>`` and starts a new one.

``fault`` says why the history is not writable right now (None when it is); the gateway shows it
as the ``storage_fault`` status bit. The first failure of a run is logged loudly, repeats are
summarised at a bounded rate, the recovery is logged once (edge.repeatlog).

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
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from edge.repeatlog import RepeatLog

log = logging.getLogger(__name__)

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
SAMPLE_TEXT = ("reason", "quality", "bad")
SAMPLE_INT = ("usable", "scans", "good_scans")
ADVICE_TEXT = ("status_bits", "detail", "message")
ADVICE_INT = ("ok", "calibration_ok", "optimization_ok", "low_confidence")
AUDIT_TEXT = ("event", "state", "reason", "words", "outcome", "message")
TABLES = {"samples": (SAMPLE_TEXT, SAMPLE_INT), "advice": (ADVICE_TEXT, ADVICE_INT),
          "closed_loop": (AUDIT_TEXT, ())}
APPEND_ONLY = ("closed_loop",)   # rows keyed by an id, not by ts (several may share a time)
BUSY_TIMEOUT_S = 2.0        # SQLite's own wait for a lock, per statement
OPEN_WAIT_S = 10.0          # open(): retry a locked database this long before running without it
RETRY_MIN_S, RETRY_MAX_S = 1.0, 60.0     # back-off between write retries while faulty
MAX_PENDING = 1440          # rows held in memory while the database is not writable (1 day)
PRUNE_MAX_AHEAD_S = 86400.0  # retention never counts back from further ahead of the host clock


class StoreError(Exception):
    """The history database failed in a way the gateway should log and survive."""


def _is_corruption(exc: BaseException) -> bool:
    """SQLITE_CORRUPT / SQLITE_NOTADB (DatabaseError itself), not an environment problem (lock,
    full, read-only, I/O: OperationalError) and not a bug (Interface/Programming/IntegrityError)."""
    return type(exc) is sqlite3.DatabaseError


def _errname(exc: BaseException) -> str:
    name = getattr(exc, "sqlite_errorname", None)
    return f"{exc} ({name})" if name else str(exc)


class HistoryStore:
    """SQLite history. ``open()`` before use (or use as a context manager).

    path : the database file
    retention_days : rows older than this before the newest sample are deleted
    aggregate_s : sample period [s] (sets the row cap)
    prune_every_s : prune at most once per this much sample time
    max_rows : row cap of ``samples`` (default: the retention's worth plus 10 %)
    busy_timeout_s : SQLite's wait for another process's lock, per statement
    open_wait_s : how long ``open()`` retries a locked database
    retry_min_s, retry_max_s : back-off between retries while the database is not writable
    max_pending : rows held in memory meanwhile
    (None: the module constants BUSY_TIMEOUT_S, OPEN_WAIT_S, RETRY_MIN_S, RETRY_MAX_S,
    MAX_PENDING)
    monotonic : clock of the back-off (injected in tests)
    """

    def __init__(self, path: str | Path, retention_days: float, *, aggregate_s: float = 60.0,
                 prune_every_s: float = 3600.0, max_rows: int | None = None,
                 busy_timeout_s: float | None = None, open_wait_s: float | None = None,
                 retry_min_s: float | None = None, retry_max_s: float | None = None,
                 max_pending: int | None = None,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        if retention_days <= 0:
            raise ValueError(f"retention_days must be > 0, got {retention_days}")
        self.path = Path(path)
        self.retention_s = float(retention_days) * 86400.0
        self.prune_every_s = float(prune_every_s)
        # backstop: retention's worth of samples plus 10 %
        self.max_rows = max_rows or int(self.retention_s / aggregate_s * 1.1) + 1000
        # None: the module's defaults, read now (tests may change them)
        self.busy_timeout_s = float(_given(busy_timeout_s, BUSY_TIMEOUT_S))
        self.open_wait_s = float(_given(open_wait_s, OPEN_WAIT_S))
        self.retry_min_s = float(_given(retry_min_s, RETRY_MIN_S))
        self.retry_max_s = float(_given(retry_max_s, RETRY_MAX_S))
        self.max_pending = int(_given(max_pending, MAX_PENDING))
        self._mono = monotonic
        self._db: sqlite3.Connection | None = None
        self._lock = threading.Lock()
        self._columns: dict[str, set[str]] = {}
        self._last_prune: float | None = None
        self._pending: dict[str, deque[dict]] = {t: deque() for t in TABLES}
        self._fault: str | None = None
        self._retry_at = -math.inf
        self._backoff = self.retry_min_s
        self._opened = False            # open() was called (and close() not yet)
        self._last_written: list[dict] = []
        self._write_log = RepeatLog(log, f"history {self.path}", monotonic=monotonic)
        self._read_log = RepeatLog(log, f"history {self.path} (reading)", level=logging.WARNING,
                                   monotonic=monotonic)
        self.dropped = 0                # rows dropped because max_pending was exceeded
        self.conflicts = 0              # rows not stored because their ts was taken

    # ------------------------------------------------------------------------- lifecycle

    def open(self) -> HistoryStore:
        """Open (or create) the database. Never raises for a lock, a full or read-only disk or
        a path that cannot be created: the store then runs without the database (``fault``
        says why), keeps rows in memory and retries."""
        self._opened = True
        deadline = self._mono() + self.open_wait_s
        delay = 0.05
        with self._lock:
            while True:
                err = self._try_connect()
                if err is None or "SQLITE_BUSY" not in err and "locked" not in err:
                    break
                if self._mono() + delay > deadline:
                    break
                time.sleep(delay)
                delay = min(2 * delay, 1.0)
            if err is not None:
                self._set_fault(err)
        return self

    def _try_connect(self) -> str | None:
        """Connect (moving a confirmed-corrupt file aside); None on success, else the reason."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            return f"cannot create the directory {self.path.parent}: {exc}"
        try:
            self._db = self._connect()
            return None
        except sqlite3.OperationalError as exc:
            return _errname(exc)
        except sqlite3.DatabaseError as exc:
            if not _is_corruption(exc):
                return _errname(exc)
            why = self._confirm_corrupt(exc)
            if why is None:
                return _errname(exc)
        try:
            self._move_aside(why)
            self._db = self._connect()
            return None
        except (OSError, sqlite3.Error) as exc:
            return _errname(exc)

    def _confirm_corrupt(self, exc: BaseException) -> str | None:
        """The reason when ``PRAGMA quick_check`` (or opening at all) shows real corruption;
        None when the file may be fine (e.g. it is merely locked)."""
        try:
            db = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None)
        except sqlite3.OperationalError:
            return None
        except sqlite3.DatabaseError as e:
            return _errname(e)
        try:
            rows = db.execute("PRAGMA quick_check").fetchall()
        except sqlite3.OperationalError:
            return None
        except sqlite3.DatabaseError as e:
            return _errname(e)
        finally:
            db.close()
        result = "; ".join(str(r[0]) for r in rows[:3])
        return None if result == "ok" else f"{_errname(exc)}; quick_check: {result}"

    def _move_aside(self, why: str) -> None:
        aside = self.path.with_name(f"{self.path.name}.corrupt-{int(time.time())}")
        log.error("history %s is corrupt (%s); moved aside to %s, starting a new one",
                  self.path, why, aside.name)
        self.path.rename(aside)
        for suffix in ("-wal", "-shm"):
            side = self.path.with_name(self.path.name + suffix)
            if side.exists():
                side.rename(aside.with_name(aside.name + suffix))

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None,
                             check_same_thread=False)
        try:
            mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if mode.lower() != "wal":
                log.warning("history %s: journal mode %s (WAL not available)", self.path, mode)
            db.execute("PRAGMA synchronous=FULL")
            db.execute("PRAGMA journal_size_limit=8388608")
            db.execute("CREATE TABLE IF NOT EXISTS samples (ts INTEGER PRIMARY KEY, wall REAL)")
            db.execute("CREATE TABLE IF NOT EXISTS advice (ts INTEGER PRIMARY KEY, wall REAL)")
            db.execute("CREATE TABLE IF NOT EXISTS conflicts (id INTEGER PRIMARY KEY, "
                       "tbl TEXT, ts INTEGER, wall REAL, row TEXT)")
            db.execute("CREATE TABLE IF NOT EXISTS closed_loop (id INTEGER PRIMARY KEY "
                       "AUTOINCREMENT, ts REAL, wall REAL)")
            self._columns = {t: {r[1] for r in db.execute(f"PRAGMA table_info({t})")}
                             for t in TABLES}
        except sqlite3.Error:
            db.close()
            raise
        return db

    def close(self) -> None:
        """Write what is waiting (one attempt), checkpoint and close."""
        if self._opened and any(self._pending.values()):
            self._retry_at = -math.inf
            self.flush()
        with self._lock:
            self._opened = False
            n = sum(len(q) for q in self._pending.values())
            if n:
                log.error("history %s: %d row(s) could not be written before closing (%s)",
                          self.path, n, self._fault)
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
            raise StoreError(f"history {self.path} is not open"
                             + (f": {self._fault}" if self._fault else ""))
        return self._db

    @property
    def fault(self) -> str | None:
        """Why the history is not writable right now (None: it is)."""
        return self._fault

    @property
    def pending(self) -> int:
        """Rows waiting in memory for the database to become writable."""
        return sum(len(q) for q in self._pending.values())

    # ---------------------------------------------------------------------------- writing

    def _check_names(self, row: Mapping[str, Any]) -> None:
        for name in row:
            if not _IDENT.match(name):
                raise ValueError(f"column name {name!r} is not an identifier")

    def _ensure_columns(self, table: str, row: Mapping[str, Any]) -> None:
        have = self._columns[table]
        text, ints = (set(x) for x in TABLES[table])
        for name in row:
            if name in have:
                continue
            kind = "TEXT" if name in text else "INTEGER" if name in ints else "REAL"
            self.db.execute(f'ALTER TABLE {table} ADD COLUMN "{name}" {kind}')
            have.add(name)

    def _insert(self, table: str, rows: list[dict]) -> tuple[int, list[dict]]:
        """Insert rows (caller holds the lock, inside a transaction); a row whose ts is stored
        already goes to ``conflicts``. Returns (rows written, rows displaced)."""
        db = self.db
        written, displaced = 0, []
        for row in rows:
            self._ensure_columns(table, row)
            cols = list(row)
            names = ",".join('"' + c + '"' for c in cols)
            marks = ",".join("?" * len(cols))
            if table in APPEND_ONLY:
                db.execute(f"INSERT INTO {table} ({names}) VALUES ({marks})",
                           [_sql_value(row[c]) for c in cols])
                written += 1
                continue
            cur = db.execute(f"INSERT INTO {table} ({names}) VALUES ({marks}) "
                             "ON CONFLICT(ts) DO NOTHING", [_sql_value(row[c]) for c in cols])
            if cur.rowcount == 1:
                written += 1
                continue
            displaced.append(row)
            db.execute("INSERT INTO conflicts (tbl, ts, wall, row) VALUES (?, ?, ?, ?)",
                       (table, row["ts"], row.get("wall"),
                        json.dumps({k: _sql_value(v) for k, v in row.items()},
                                   default=_json_default, sort_keys=True)))
        return written, displaced

    def _queue(self, table: str, rows: list[dict]) -> None:
        with self._lock:
            q = self._pending[table]
            q.extend(rows)
            over = self.pending - self.max_pending
            while over > 0:
                victim = max(self._pending.values(), key=len)   # the samples, in practice
                victim.popleft()
                self.dropped += 1
                over -= 1
                if self.dropped == 1 or self.dropped % 100 == 0:
                    log.error("history %s: %d row(s) dropped so far: more than %d waiting for "
                              "the database (%s)", self.path, self.dropped, self.max_pending,
                              self._fault)

    def flush(self) -> int:
        """Write the rows waiting in memory, when the back-off allows a try. Returns the rows
        written. Never raises for an unwritable database (``fault`` says why)."""
        with self._lock:
            if not self._opened or not any(self._pending.values()):
                return 0
            if self._fault is not None and self._mono() < self._retry_at:
                return 0
            if self._db is None:
                err = self._try_connect()
                if err is not None:
                    self._set_fault(err)
                    return 0
            try:
                written, displaced = self._write_pending()
            except sqlite3.Error as exc:
                if not _is_corruption(exc):
                    self._set_fault(_errname(exc))
                    return 0
                why = self._confirm_corrupt(exc)
                if why is None:
                    self._set_fault(_errname(exc))
                    return 0
                try:                      # corrupt under our feet: aside, fresh file, write
                    self._db.close()
                    self._db = None
                    self._move_aside(why)
                    self._db = self._connect()
                    written, displaced = self._write_pending()
                except (OSError, sqlite3.Error) as exc2:
                    self._set_fault(_errname(exc2))
                    return 0
            newest = max((r["ts"] for r in self._last_written), default=None)
        self._clear_fault(written)
        if displaced:
            self.conflicts += len(displaced)
            log.warning("history %s: %d row(s) at already stored times (%s) kept the stored "
                        "row; the new ones are in the table 'conflicts' (%d so far)", self.path,
                        len(displaced), ", ".join(_iso(r["ts"]) for r in displaced[:3]),
                        self.conflicts)
        if newest is not None:
            try:
                self._maybe_prune(newest)
            except sqlite3.OperationalError as exc:     # retried with the next write
                self._read_log.fail(f"pruning failed: {_errname(exc)}")
        return written

    def _write_pending(self) -> tuple[int, list[dict]]:
        db = self.db
        self._last_written = []
        try:
            db.execute("BEGIN IMMEDIATE")
            written, displaced = 0, []
            for table, q in self._pending.items():
                w, d = self._insert(table, list(q))
                written += w
                displaced += d
                if table == "samples":
                    self._last_written = list(q)
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                try:
                    db.execute("ROLLBACK")
                except sqlite3.Error:
                    pass
            try:
                self._columns = {t: {r[1] for r in db.execute(f"PRAGMA table_info({t})")}
                                 for t in TABLES}
            except sqlite3.Error:
                pass
            raise
        for q in self._pending.values():
            q.clear()
        return written, displaced

    def _set_fault(self, reason: str) -> None:
        first = self._fault is None
        self._fault = reason
        if first:
            self._backoff = self.retry_min_s
        else:
            self._backoff = min(2 * self._backoff, self.retry_max_s)
        self._retry_at = self._mono() + self._backoff
        n = sum(len(q) for q in self._pending.values())
        self._write_log.fail(f"not writable: {reason}; {n} row(s) wait in memory (at most "
                             f"{self.max_pending}), retrying by itself")

    def _clear_fault(self, written: int) -> None:
        if self._fault is not None:
            self._fault = None
            self._write_log.ok(f"wrote {written} waiting row(s)")

    def add_samples(self, rows: Iterable[Mapping[str, Any]]) -> int:
        """Store one-minute samples in ONE transaction (with any rows still waiting).

        Each row needs ``ts`` [epoch s, int]; other keys become columns (numbers REAL, the
        columns reason/quality/bad TEXT, usable/scans/good_scans INTEGER). A row whose ``ts`` is
        stored already is not written over (see the module doc). Returns the rows written now
        (0 while the database is not writable: the rows wait in memory). Raises ValueError for
        a column name that is not an identifier (nothing is stored then).
        """
        wall = time.time()
        out = []
        for r in rows:
            row = {"ts": int(r["ts"]), "wall": wall}
            row.update((k, v) for k, v in r.items() if k != "ts")
            self._check_names(row)
            out.append(row)
        if not out:
            return 0
        self._queue("samples", out)
        return self.flush()

    def add_advice(self, ts: float, record: Mapping[str, Any]) -> int:
        """One calibration cycle's outputs (advisory values, ok flag, status bits, detail).
        Returns the rows written now (0: waiting in memory, see ``fault``)."""
        row = {"ts": int(ts), "wall": time.time()}
        for k, v in record.items():
            row[k] = json.dumps(v, default=_json_default, sort_keys=True) if k == "detail" else v
        self._check_names(row)
        self._queue("advice", [row])
        return self.flush()

    def add_closed_loop_event(self, record: Mapping[str, Any]) -> int:
        """One row of the closed loop's audit trail (edge.closed_loop): ``ts`` [epoch s, sample
        clock], ``event`` ('write' | 'state') and its columns (old_bar_g, new_bar_g, target_bar_g,
        words, outcome, state, reason, message). Kept in order of arrival; waits in memory like
        every row while the database is not writable. Returns the rows written now."""
        row = {"ts": float(record["ts"]), "wall": time.time()}
        row.update((k, v) for k, v in record.items() if k != "ts")
        self._check_names(row)
        self._queue("closed_loop", [row])
        return self.flush()

    def closed_loop_events(self, since: float | None = None) -> list[dict]:
        """The audit trail (oldest first), rows still waiting in memory included."""
        with self._lock:
            got = self._read("SELECT * FROM closed_loop" + (" WHERE ts >= ?" if since is not None
                                                              else "") + " ORDER BY id",
                             (since,) if since is not None else ())
            out = [dict(zip(got[0], r)) for r in got[1]] if got else []
            out += [{k: _sql_value(v) for k, v in r.items()} for r in self._pending["closed_loop"]
                    if since is None or r["ts"] >= since]
        return out

    def _maybe_prune(self, newest: float) -> None:
        newest = min(newest, time.time() + PRUNE_MAX_AHEAD_S)
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
                n += db.execute("DELETE FROM conflicts WHERE ts < ?", (cutoff,)).rowcount
                n += db.execute("DELETE FROM closed_loop WHERE ts < ?", (cutoff,)).rowcount
                count = db.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
                if count > self.max_rows:
                    n += db.execute(
                        "DELETE FROM samples WHERE ts IN (SELECT ts FROM samples ORDER BY ts "
                        "LIMIT ?)", (count - self.max_rows,)).rowcount
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
        if n:
            log.info("history: pruned %d rows older than %s", n, _iso(cutoff))
        return n

    # ---------------------------------------------------------------------------- reading

    def _read(self, sql: str, args: tuple = ()) -> tuple[list[str], list[tuple]] | None:
        """Rows of a query on the database, or None when it cannot be read (not open, locked,
        I/O error: logged at a bounded rate). Caller holds the lock."""
        if self._db is None and self._opened:
            err = self._try_connect()
            if err is not None:
                self._read_log.fail(err)
                return None
        try:
            cur = self.db.execute(sql, args)
            cols = [d[0] for d in cur.description]
            rows = cur.fetchall()
        except (sqlite3.OperationalError, StoreError) as exc:
            self._read_log.fail(str(exc))
            return None
        self._read_log.ok()
        return cols, rows

    def window(self, end: float, seconds: float, usable_only: bool = True) -> pd.DataFrame:
        """Samples with end - seconds < ts <= end, oldest first, index ``timestamp`` (UTC).
        Rows still waiting in memory are included; while the database cannot be read, only
        they are."""
        lo, hi = int(end - seconds), int(end)
        where = "ts > ? AND ts <= ?" + (" AND usable = 1" if usable_only else "")
        with self._lock:
            got = self._read(f"SELECT * FROM samples WHERE {where} ORDER BY ts", (lo, hi))
            waiting = [r for r in self._pending["samples"] if lo < r["ts"] <= hi
                       and (not usable_only or bool(r.get("usable")))]
        df = pd.DataFrame.from_records(got[1], columns=got[0]) if got else pd.DataFrame()
        if waiting:
            extra = pd.DataFrame([{k: _sql_value(v) for k, v in r.items()} for r in waiting])
            df = extra if df.empty else pd.concat([df, extra[~extra["ts"].isin(df["ts"])]],
                                                  ignore_index=True)
            df = df.sort_values("ts", kind="stable").reset_index(drop=True)
        if "ts" not in df.columns:
            df = pd.DataFrame({"ts": pd.Series([], dtype="int64")})
        df.index = pd.to_datetime(df["ts"], unit="s", utc=True)
        df.index.name = "timestamp"
        return df

    def count(self, table: str = "samples") -> int:
        """Rows stored in the database (not those waiting in memory)."""
        if table not in ("samples", "advice", "conflicts", "closed_loop"):
            raise ValueError(f"unknown table {table!r}")
        with self._lock:
            return int(self.db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])

    def latest_sample_ts(self) -> int | None:
        with self._lock:
            got = self._read("SELECT MAX(ts) FROM samples")
            stored = got[1][0][0] if got else None
            waiting = max((r["ts"] for r in self._pending["samples"]), default=None)
        return max((t for t in (stored, waiting) if t is not None), default=None)

    def latest_advice(self, ok_only: bool = True) -> dict | None:
        """The newest advice row as a dict (``detail`` decoded), or None."""
        with self._lock:
            where = "WHERE ok = 1 " if ok_only and "ok" in self._columns.get("advice", ()) else ""
            got = self._read(f"SELECT * FROM advice {where}ORDER BY ts DESC LIMIT 1")
            out = dict(zip(got[0], got[1][0])) if got and got[1] else None
            for r in self._pending["advice"]:
                if (not ok_only or r.get("ok")) and (out is None or r["ts"] >= out["ts"]):
                    out = {k: _sql_value(v) for k, v in r.items()}
        if out is None:
            return None
        if isinstance(out.get("detail"), str):
            out["detail"] = json.loads(out["detail"])
        return out


def _given(v: Any, default: Any) -> Any:
    return default if v is None else v


def _iso(ts: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ts))


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
