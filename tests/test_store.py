"""SQLite history: WAL, columns on demand, windows, retention, corrupt files, kill -9; and issue 9:
a stored row is never overwritten, a lock is not corruption, a full or unwritable disk keeps the
rows in memory until it recovers, a clock far in the future never prunes the history."""
from __future__ import annotations

import errno
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

import pytest

from edge import statefiles
from edge.statefiles import StateError, write_state
from edge.store import HistoryStore

DAY = 86400.0


def rows(t0: int, n: int, step: int = 60, **extra):
    return [{"ts": t0 + k * step, "T_source_in": 24.0 + 0.01 * k, "p_e_bar": 7.3,
             "usable": k % 2 == 0, "reason": "" if k % 2 == 0 else "ramping",
             "quality": "", **extra} for k in range(n)]


@pytest.fixture
def store(tmp_path):
    with HistoryStore(tmp_path / "h.sqlite", retention_days=1.0) as s:
        yield s


def test_wal_mode_and_full_sync(store):
    assert store.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert store.db.execute("PRAGMA synchronous").fetchone()[0] == 2   # FULL


def test_samples_roundtrip_and_usable_window(store):
    store.add_samples(rows(1_700_000_040, 10))
    w = store.window(1_700_000_040 + 9 * 60, 600)
    assert list(w["ts"]) == [1_700_000_040 + k * 60 for k in (0, 2, 4, 6, 8)]
    assert w.index.tz is not None and w.index.name == "timestamp"
    assert w["T_source_in"].iloc[1] == pytest.approx(24.02)
    everything = store.window(1_700_000_040 + 9 * 60, 600, usable_only=False)
    assert len(everything) == 10 and set(everything["reason"]) == {"", "ramping"}


def test_new_columns_are_added_and_nan_is_null(store):
    store.add_samples(rows(0, 1))
    store.add_samples([{"ts": 60, "new_tag": math.nan, "usable": 1, "bad": {"T": "nan"}}])
    got = store.db.execute("SELECT new_tag, bad, T_source_in FROM samples WHERE ts=60").fetchone()
    assert got == (None, '{"T": "nan"}', None)
    with pytest.raises(ValueError):
        store.add_samples([{"ts": 120, "bad name;": 1.0}])
    assert store.count() == 2       # the failed transaction left nothing behind


def test_a_stored_sample_is_never_overwritten(store, caplog):
    """A clock that went back (and was accepted as a correction) brings rows at stored times:
    the stored row stays, the new one is kept whole in 'conflicts', and a warning says so."""
    store.add_samples(rows(0, 2))
    assert store.add_samples([{"ts": 0, "T_source_in": 30.0, "usable": 1},
                              {"ts": 120, "T_source_in": 31.0, "usable": 1}]) == 1
    assert store.count() == 3 and store.conflicts == 1
    assert store.window(0, 10)["T_source_in"].iloc[0] == 24.0
    (tbl, ts, row), = store.db.execute("SELECT tbl, ts, row FROM conflicts").fetchall()
    assert (tbl, ts) == ("samples", 0)
    assert json.loads(row)["T_source_in"] == 30.0
    assert ("1 row(s) at already stored times (1970-01-01T00:00:00Z) kept the stored row; the new "
            "ones are in the table 'conflicts' (1 so far)") in caplog.text
    store.add_advice(600, {"ok": True, "R_th_f": 3e-3})
    store.add_advice(600, {"ok": True, "R_th_f": 9e-3})
    assert store.latest_advice()["R_th_f"] == 3e-3 and store.count("conflicts") == 2


def test_retention_counts_back_from_the_newest_sample(tmp_path):
    with HistoryStore(tmp_path / "h.sqlite", retention_days=1.0, prune_every_s=0) as s:
        s.add_samples(rows(0, 3, step=int(DAY / 2)))         # 0, 0.5 d, 1 d
        s.add_advice(0, {"ok": True, "R_th_f": 3e-3})
        s.add_samples(rows(int(2 * DAY), 1))                 # 2 d: 0 and 0.5 d go
        assert [r[0] for r in s.db.execute("SELECT ts FROM samples ORDER BY ts")] == \
            [int(DAY), int(2 * DAY)]
        assert s.count("advice") == 0


def test_row_cap_is_a_backstop(tmp_path):
    with HistoryStore(tmp_path / "h.sqlite", retention_days=10.0, max_rows=5,
                      prune_every_s=0) as s:
        s.add_samples(rows(0, 8))
        assert s.count() == 5 and s.latest_sample_ts() == 7 * 60


def test_advice_latest_ok(store):
    store.add_advice(100, {"ok": True, "R_th_f": 3e-3, "detail": {"nrmse": [0.1, math.nan]}})
    store.add_advice(200, {"ok": False, "R_th_f": math.nan, "status_bits": "calibration_failed"})
    last = store.latest_advice()
    assert last["ts"] == 100 and last["R_th_f"] == 3e-3 and last["detail"]["nrmse"][0] == 0.1
    assert store.latest_advice(ok_only=False)["ts"] == 200


def test_corrupt_database_is_moved_aside(tmp_path, caplog):
    path = tmp_path / "h.sqlite"
    path.write_bytes(b"this is not a database" * 100)
    with HistoryStore(path, retention_days=1.0) as s:
        s.add_samples(rows(0, 1))
        assert s.count() == 1 and s.fault is None
    assert len(list(tmp_path.glob("h.sqlite.corrupt-*"))) == 1
    assert "is corrupt (file is not a database (SQLITE_NOTADB))" in caplog.text
    assert "moved aside" in caplog.text


class FakeMono:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _lock(path):
    """Another process's exclusive lock (the sqlite3 shell in a transaction, a backup tool)."""
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("PRAGMA locking_mode=EXCLUSIVE")
    other.execute("BEGIN EXCLUSIVE")
    other.execute("CREATE TABLE IF NOT EXISTS other (x)")
    return other


def test_a_locked_database_is_retried_not_moved_aside_and_catches_up(tmp_path, caplog):
    path = tmp_path / "h.sqlite"
    with HistoryStore(path, retention_days=10.0) as s:
        s.add_samples(rows(0, 3))
    other = _lock(path)
    mono = FakeMono()
    t0 = time.monotonic()
    s = HistoryStore(path, retention_days=10.0, busy_timeout_s=0.02, open_wait_s=0.3,
                     monotonic=mono)
    try:
        mono.t = 1.0          # open() retries on the injected clock: it gives up at once
        s.open()
        assert time.monotonic() - t0 < 5.0
        assert s.fault == "database is locked (SQLITE_BUSY)"
        assert list(tmp_path.glob("*.corrupt-*")) == []            # a lock is not corruption
        assert s.add_samples(rows(180, 2)) == 0 and s.pending == 2
        s.add_advice(300, {"ok": True, "R_th_f": 2e-3})
        # the waiting rows are seen by readers: calibration goes on
        assert list(s.window(300, 600, usable_only=False)["ts"]) == [180, 240]
        assert s.latest_sample_ts() == 240 and s.latest_advice()["R_th_f"] == 2e-3
        other.execute("ROLLBACK")
        other.close()
        assert s.add_samples(rows(300, 1)) == 0          # still in back-off: not even tried
        mono.t += 1.5
        assert s.add_samples(rows(360, 1)) == 5          # 2 + advice + 2 new, one transaction
        assert s.fault is None and s.pending == 0
        assert s.count() == 7 and s.count("advice") == 1
    finally:
        s.close()
    assert "history %s: not writable: database is locked (SQLITE_BUSY)" % path in caplog.text
    assert "recovered after" in caplog.text and "wrote 5 waiting row(s)" in caplog.text
    assert caplog.text.count("not writable") == 1      # one line, not one per attempt


def test_a_full_disk_keeps_the_rows_in_memory_until_there_is_room(tmp_path):
    """SQLITE_FULL from a capped database (PRAGMA max_page_count): what a full disk returns."""
    mono = FakeMono()
    with HistoryStore(tmp_path / "h.sqlite", retention_days=10.0, monotonic=mono) as s:
        s.add_samples(rows(0, 1))
        pages = s.db.execute("PRAGMA page_count").fetchone()[0]
        s.db.execute(f"PRAGMA max_page_count={pages}")
        big = [{**r, "reason": "x" * 3000} for r in rows(60, 3)]
        assert s.add_samples(big) == 0
        assert s.fault == "database or disk is full (SQLITE_FULL)" and s.pending == 3
        s.db.execute("PRAGMA max_page_count=1000000")
        mono.t += 1.0
        assert s.add_samples(rows(240, 1)) == 4 and s.fault is None
        assert s.count() == 5


def test_a_history_that_cannot_be_created_runs_in_memory(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the history's directory should be")
    s = HistoryStore(blocker / "var" / "h.sqlite", retention_days=1.0, max_pending=3).open()
    try:
        assert s.fault.startswith(f"cannot create the directory {blocker / 'var'}: ")
        s.add_samples(rows(0, 5))
        assert s.pending == 3 and s.dropped == 2          # bounded memory, drops counted
        assert list(s.window(600, 600, usable_only=False)["ts"]) == [120, 180, 240]
    finally:
        s.close()


def test_a_clock_far_ahead_never_prunes_the_history(tmp_path):
    """One PLC-clock read of 0xFFFF 0xFFFF used to prune every row ('older than 4260407280')."""
    now = int(time.time())
    with HistoryStore(tmp_path / "h.sqlite", retention_days=2.0, prune_every_s=0) as s:
        s.add_samples(rows(now - 43200, 10))
        s.add_samples([{"ts": 4294967295, "T_source_in": 1.0, "usable": 0}])
        assert s.count() == 11


# ------------------------------------------------------------------------------ state files

def test_state_write_failures_are_state_errors_and_leave_the_old_document(tmp_path, monkeypatch):
    """A read-only state directory (mkstemp fails with EROFS: what a read-only mount or a
    directory without write permission gives) and a full disk (fsync fails with ENOSPC) are both
    StateError naming the file; the old document stays, no temporary file is left."""
    write_state("fouling_calibration.json", {"v": 1}, tmp_path)

    def read_only(*a, **kw):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(statefiles.tempfile, "mkstemp", read_only)
    with pytest.raises(StateError, match=r"cannot write state file .*fouling_calibration.json: "
                                         r"\[Errno 30\] Read-only file system"):
        write_state("fouling_calibration.json", {"v": 2}, tmp_path)
    monkeypatch.undo()

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(statefiles.os, "fsync", full)
    with pytest.raises(StateError, match=r"\[Errno 28\] No space left on device"):
        write_state("fouling_calibration.json", {"v": 3}, tmp_path)
    monkeypatch.undo()
    assert statefiles.read_state("fouling_calibration.json", tmp_path)["v"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fouling_calibration.json"]


def test_state_directory_that_cannot_be_created(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(StateError, match=r"cannot create state directory .*file/state"):
        write_state("fouling_calibration.json", {"v": 1}, blocker / "state")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a chmod 0500 directory anyway; "
                    "test_state_write_failures_are_state_errors_and_leave_the_old_document "
                    "injects the same EROFS/EACCES failure")
def test_state_in_a_chmod_read_only_directory(tmp_path):
    d = tmp_path / "state"
    d.mkdir()
    d.chmod(0o500)
    try:
        with pytest.raises(StateError, match="Permission denied"):
            write_state("fouling_calibration.json", {"v": 1}, d)
    finally:
        d.chmod(0o700)


_WRITER = textwrap.dedent("""
    import os, sys
    from edge.store import HistoryStore
    s = HistoryStore(sys.argv[1], retention_days=1000.0).open()
    k = 0
    while True:
        s.add_samples([{"ts": k * 60, "T_source_in": float(k), "usable": 1}])
        os.write(1, f"{k}\\n".encode())     # printed only after the commit returned
        k += 1
""")


def test_kill_9_loses_no_committed_row(tmp_path):
    path = tmp_path / "h.sqlite"
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(path)], stdout=subprocess.PIPE,
                            cwd=os.getcwd())
    committed = -1
    try:
        while committed < 40:
            line = proc.stdout.readline()
            assert line, "writer died"
            committed = int(line)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()
    db = sqlite3.connect(path)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    n = db.execute("SELECT COUNT(*), MAX(ts) FROM samples").fetchone()
    db.close()
    assert n[0] >= committed + 1 and n[1] >= committed * 60


def test_a_lock_taken_while_running_is_waited_out(tmp_path):
    """The database opened fine; another process then holds a write lock for a while."""
    mono = FakeMono()
    path = tmp_path / "h.sqlite"
    with HistoryStore(path, retention_days=10.0, busy_timeout_s=0.02, monotonic=mono) as s:
        s.add_samples(rows(0, 1))
        other = sqlite3.connect(path, isolation_level=None, timeout=0.02)
        other.execute("BEGIN IMMEDIATE")            # a writer that does not finish
        try:
            assert s.add_samples(rows(60, 1)) == 0
            assert s.fault == "database is locked (SQLITE_BUSY)" and s.pending == 1
            mono.t += 1.0
            assert s.add_samples(rows(120, 1)) == 0          # still locked: back-off doubles
        finally:
            other.execute("ROLLBACK")
            other.close()
        mono.t += 1.5
        assert s.add_samples(rows(180, 1)) == 0              # free, but 2 s are not over yet
        assert s.fault is not None and s.pending == 3
        mono.t += 1.0
        assert s.add_samples(rows(240, 1)) == 4 and s.fault is None
        assert [r[0] for r in s.db.execute("SELECT ts FROM samples ORDER BY ts")] == \
            [0, 60, 120, 180, 240]
    assert list(tmp_path.glob("*.corrupt-*")) == []
