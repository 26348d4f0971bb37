"""Store-and-forward for the MQTT publisher, inside the gateway's own history database.

The rows to publish are already stored durably (``samples`` and ``advice`` of
``edge.store.HistoryStore``), so the outbox holds only references: SQLite triggers on those two
tables append ``(id, tbl, ts)`` to ``northbound_outbox`` in the same transaction that stores the
row. Nothing can be stored without being queued, a kill -9 loses nothing, and the store itself is
not changed. The publisher reads the outbox in ``id`` order (the order rows were stored), publishes
and deletes what the broker acknowledged; what is left after a restart is sent then.

* a row that the store does not insert (its time is taken: ``conflicts``) fires no trigger;
* rows the store keeps in memory while the database is locked or full are queued when they are
  written;
* bounded: a trigger keeps at most ``max_rows`` references (the oldest go first; the publisher
  counts the gap and logs it); a reference whose row retention has since pruned is skipped;
* the publisher's own state (the Sparkplug bdSeq) is in ``northbound_state``;
* ``detach(path)`` drops the triggers and the queue when the publisher is switched off, so a
  disabled publisher leaves nothing growing.

A second connection (WAL: readers never block the store's writer; writes wait ``busy_timeout_s``).
Used from the publisher's thread only.
"""
from __future__ import annotations

import json
import logging
import os
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

OUTBOX = "northbound_outbox"
STATE = "northbound_state"
SOURCES = {"samples": "sample", "advice": "advice"}     # history table -> metric source
TRIGGERS = tuple(f"northbound_{t}" for t in SOURCES) + ("northbound_cap",)
CAP_EVERY = 64            # the cap trigger runs on every 64th reference
BUSY_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class Entry:
    id: int                       # outbox id (insertion order)
    source: str                   # 'sample' | 'advice'
    ts: int                       # the row's time [epoch s, sample clock]
    row: dict[str, Any] | None    # the stored row (None: pruned by retention since)


class Outbox:
    """The queue of history rows not yet acknowledged by the broker.

    path : the history database (edge.store.HistoryStore's file)
    max_rows : references kept at most (oldest dropped first)
    """

    def __init__(self, path: str | Path, max_rows: int = 100_000,
                 busy_timeout_s: float = BUSY_TIMEOUT_S) -> None:
        if max_rows < CAP_EVERY:
            raise ValueError(f"max_rows must be >= {CAP_EVERY}, got {max_rows}")
        self.path = Path(path)
        self.max_rows = int(max_rows)
        self.busy_timeout_s = busy_timeout_s
        self._db: sqlite3.Connection | None = None
        self._inode: int | None = None

    # ------------------------------------------------------------------------- lifecycle

    def open(self) -> Outbox:
        """Connect, create the queue, the state table and the triggers (idempotent). Raises
        sqlite3.Error / OSError when the database cannot be opened or written (the publisher
        retries)."""
        db = sqlite3.connect(self.path, timeout=self.busy_timeout_s, isolation_level=None,
                             check_same_thread=False)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            db.execute("BEGIN IMMEDIATE")
            _attach(db, self.max_rows)
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            db.close()
            raise
        self._db = db
        self._inode = _inode(self.path)
        return self

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    @property
    def db(self) -> sqlite3.Connection:
        if self._db is None:
            raise sqlite3.OperationalError(f"outbox {self.path} is not open")
        return self._db

    def replaced(self) -> bool:
        """True when the database file was replaced (the store moved a corrupt file aside and
        started a new one): reopen to attach the triggers to the new file."""
        return _inode(self.path) != self._inode

    # --------------------------------------------------------------------------- queue

    def fetch(self, after_id: int, limit: int) -> list[Entry]:
        """Up to ``limit`` entries with id > ``after_id``, oldest first, with their rows."""
        refs = self.db.execute(f"SELECT id, tbl, ts FROM {OUTBOX} WHERE id > ? ORDER BY id "
                               "LIMIT ?", (after_id, limit)).fetchall()
        rows: dict[tuple[str, int], dict] = {}
        for tbl in SOURCES:
            want = sorted({ts for _, t, ts in refs if t == tbl})
            for i in range(0, len(want), 500):
                part = want[i:i + 500]
                cur = self.db.execute(f"SELECT * FROM {tbl} WHERE ts IN "
                                      f"({','.join('?' * len(part))})", part)
                cols = [c[0] for c in cur.description]
                for r in cur.fetchall():
                    d = dict(zip(cols, r))
                    rows[(tbl, d["ts"])] = d
        return [Entry(i, SOURCES[t], ts, rows.get((t, ts))) for i, t, ts in refs]

    def changed(self) -> bool:
        """True when another connection (the store) committed since the last call: only then can
        there be new entries (``PRAGMA data_version``, a read of the connection's own state)."""
        v = self.db.execute("PRAGMA data_version").fetchone()[0]
        seen, self._data_version = getattr(self, "_data_version", None), v
        return v != seen

    def ack(self, upto_id: int) -> int:
        """Forget every entry with id <= ``upto_id`` (delivered). Returns the entries removed."""
        return self.db.execute(f"DELETE FROM {OUTBOX} WHERE id <= ?", (upto_id,)).rowcount

    def depth(self) -> int:
        """Entries waiting."""
        return int(self.db.execute(f"SELECT COUNT(*) FROM {OUTBOX}").fetchone()[0])

    def first_id(self) -> int | None:
        return self.db.execute(f"SELECT MIN(id) FROM {OUTBOX}").fetchone()[0]

    def latest(self, source: str) -> dict | None:
        """The newest stored row of a source ('sample' | 'advice'), for a birth certificate."""
        tbl = next(t for t, s in SOURCES.items() if s == source)
        cur = self.db.execute(f"SELECT * FROM {tbl} ORDER BY ts DESC LIMIT 1")
        r = cur.fetchone()
        return dict(zip([c[0] for c in cur.description], r)) if r else None

    # --------------------------------------------------------------------------- state

    def get_state(self, key: str, default: Any = None) -> Any:
        r = self.db.execute(f"SELECT value FROM {STATE} WHERE key = ?", (key,)).fetchone()
        return json.loads(r[0]) if r else default

    def set_state(self, key: str, value: Any) -> None:
        self.db.execute(f"INSERT INTO {STATE} (key, value) VALUES (?, ?) ON CONFLICT(key) DO "
                        "UPDATE SET value = excluded.value", (key, json.dumps(value)))


def _attach(db: sqlite3.Connection, max_rows: int) -> None:
    db.execute(f"CREATE TABLE IF NOT EXISTS {OUTBOX} (id INTEGER PRIMARY KEY AUTOINCREMENT, "
               "tbl TEXT NOT NULL, ts INTEGER NOT NULL)")
    db.execute(f"CREATE TABLE IF NOT EXISTS {STATE} (key TEXT PRIMARY KEY, value TEXT)")
    for tbl in SOURCES:     # the store creates these on open; a fresh file may not have them
        db.execute(f"CREATE TABLE IF NOT EXISTS {tbl} (ts INTEGER PRIMARY KEY, wall REAL)")
        db.execute(f"CREATE TRIGGER IF NOT EXISTS northbound_{tbl} AFTER INSERT ON {tbl} "
                   f"BEGIN INSERT INTO {OUTBOX} (tbl, ts) VALUES ('{tbl}', NEW.ts); END")
    db.execute("DROP TRIGGER IF EXISTS northbound_cap")       # max_rows may have changed
    db.execute(f"CREATE TRIGGER northbound_cap AFTER INSERT ON {OUTBOX} "
               f"WHEN NEW.id % {CAP_EVERY} = 0 BEGIN "
               f"DELETE FROM {OUTBOX} WHERE id <= NEW.id - {int(max_rows)}; END")


def detach(path: str | Path, busy_timeout_s: float = BUSY_TIMEOUT_S) -> bool:
    """Drop the outbox triggers and queue from a history database (the publisher is off).
    Returns True when there was something to drop. Never raises for a missing, locked or
    unreadable database (logged): it is retried at the next start."""
    path = Path(path)
    if not path.exists():
        return False
    try:
        db = sqlite3.connect(path, timeout=busy_timeout_s, isolation_level=None)
    except sqlite3.Error as exc:
        log.warning("northbound outbox in %s not checked: %s", path, exc)
        return False
    try:
        names = {r[0] for r in db.execute(
            "SELECT name FROM sqlite_master WHERE type IN ('trigger', 'table') AND name LIKE "
            "'northbound_%'")}
        if not names & set(TRIGGERS + (OUTBOX,)):
            return False
        db.execute("BEGIN IMMEDIATE")
        for t in TRIGGERS:
            db.execute(f"DROP TRIGGER IF EXISTS {t}")
        db.execute(f"DROP TABLE IF EXISTS {OUTBOX}")
        db.execute("COMMIT")
        log.info("northbound publisher is off: its queue in %s was removed", path)
        return True
    except sqlite3.Error as exc:
        log.warning("northbound outbox in %s not removed (retried at the next start): %s",
                    path, exc)
        return False
    finally:
        db.close()


def _inode(path: Path) -> int | None:
    try:
        return os.stat(path).st_ino
    except OSError:
        return None

