"""SQLite history: WAL, columns on demand, windows, retention, corrupt files, kill -9."""
from __future__ import annotations

import math
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap

import pytest

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


def test_same_timestamp_replaces(store):
    store.add_samples(rows(0, 1))
    store.add_samples([{"ts": 0, "T_source_in": 30.0, "usable": 1}])
    assert store.count() == 1
    assert store.window(0, 10)["T_source_in"].iloc[0] == 30.0


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
        assert s.count() == 1
    assert len(list(tmp_path.glob("h.sqlite.corrupt-*"))) == 1
    assert "moved aside" in caplog.text


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
