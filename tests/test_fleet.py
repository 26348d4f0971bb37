"""Issue 12: replay through the Executor seam and ``hp-edge fleet replay`` on a Dask LocalCluster.

Everything runs on 127.0.0.1 with ports chosen at run time (the LocalCluster's scheduler port 0, no
dashboard); every test is bounded in time (subprocesses by ``timeout``, in-process work by an alarm).
Simulated histories are short (half a day to a day of one-minute samples): the point is that the
seam and the fleet give the same numbers as one process, not the analysis itself (test_replay.py).
"""
from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pandas as pd
import pytest

from edge.cli import main
from edge.commands.analysis_cmds import process_pool
from model.analysis.replay import ReplaySettings, replay
from simulator.export import export_history

ROOT = Path(__file__).resolve().parent.parent
PLANT_YAML = ROOT / "config" / "plant.yaml"
FLEET_TIMEOUT_S = 150      # the whole fleet command: cluster start, two half-day plants, shutdown
BROKEN_REASON = "{}: no such file"     # edge.io.history's message for a missing history file


@contextmanager
def time_limit(seconds: int):
    """Fail (not hang) when the block takes longer than ``seconds`` of wall time (SIGALRM: the
    main thread, Linux)."""
    def fire(signum, frame):
        raise TimeoutError(f"took longer than {seconds} s")
    old = signal.signal(signal.SIGALRM, fire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


# ---- (a) the Executor seam --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def day():
    """One simulated day (simulator.export, seed 5): ~11 windows of 2 h after the initial 90 min."""
    return export_history(1.0, seed=5).history


def test_replay_through_a_process_pool_equals_the_sequential_replay(plant, day):
    """Pass 2 of every window in a spawned process pool (CoolProp state and property tables built
    there) gives the same windows as one process with the surrogate off (a parallel replay always
    searches: the surrogate tracker is sequential). Compared exactly: the seam promises identical
    numbers (deterministic solver starts, tables built the same way in every process), and a
    tolerance would hide a window that depended on its predecessor's state."""
    s = ReplaySettings.from_config(plant.extra, surrogate=False)
    with time_limit(120):
        seq = replay(day, plant, s)
        with process_pool(2) as pool:           # replay --workers 2's pool: its workers pinned
            par = replay(day, plant, ReplaySettings.from_config(plant.extra), executor=pool)
    assert len(seq.windows) >= 8 and (seq.windows["status"] == "ok").sum() >= 8
    assert seq.windows["optimization_ok"].astype(bool).sum() >= 8      # the search ran: its numbers compared
    pd.testing.assert_frame_equal(seq.windows, par.windows, check_exact=True)
    pd.testing.assert_frame_equal(seq.samples, par.samples, check_exact=True)
    pd.testing.assert_frame_equal(seq.cips, par.cips, check_exact=True)
    assert seq.compressors == par.compressors
    assert any(n.startswith("parallel replay: the set-point search in every window") for n in par.notes)
    assert not any(n.startswith("parallel replay") for n in seq.notes)


def test_property_tables_agree_with_heos_row_by_row(plant, day):
    """The fast path's measured side (model.proptable) against the equation of state on every row
    (``use_tables(False)``: the switch ``hp-edge bench --only replay`` uses). Bounds: the tables'
    stated accuracy (~1e-3 J/kg in h) carried into an efficiency ratio of ~1e5 J/kg differences."""
    from model.measured import process
    from model.proptable import use_tables
    with time_limit(60):
        fast = process(day, plant)
        prev = use_tables(False)
        try:
            heos = process(day, plant)
        finally:
            use_tables(prev)
    assert prev is True
    assert (fast["usable"] == heos["usable"]).all() and (fast["reason"] == heos["reason"]).all()
    for col, tol in (("T_e_sat_C", 1e-9), ("eta_is_LS_meas", 1e-7), ("eta_is_HS_meas", 1e-7),
                     ("R_th_f_K_per_kW", 1e-12)):
        d = (fast[col] - heos[col]).abs()
        assert d.notna().sum() > 1000 and d.max() < tol, (col, d.max())


# ---- (b) hp-edge fleet replay ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    """PLANTS.yaml with two half-day plants (own plant.yaml and history each) and a third whose
    history file does not exist."""
    d = tmp_path_factory.mktemp("fleet")
    for name, seed in (("north-1", 11), ("south-2", 12)):
        (d / name).mkdir()
        shutil.copy(PLANT_YAML, d / name / "plant.yaml")
        export_history(0.5, d / name / "history.csv", seed=seed)
    (d / "broken-3").mkdir()
    shutil.copy(PLANT_YAML, d / "broken-3" / "plant.yaml")
    (d / "PLANTS.yaml").write_text(
        "plants:\n"
        "  - name: north-1\n    plant: north-1/plant.yaml\n    history: north-1/history.csv\n"
        "  - name: broken-3\n    plant: broken-3/plant.yaml\n    history: broken-3/history.csv\n"
        "  - name: south-2\n    plant: south-2/plant.yaml\n    history: south-2/history.csv\n"
        "    window_hours: 2\n", encoding="utf-8")
    return d


@pytest.fixture(scope="module")
def fleet_run(fleet_dir):
    out = fleet_dir / "out"
    proc = subprocess.run([sys.executable, "-m", "edge.cli", "fleet", "replay", str(fleet_dir / "PLANTS.yaml"),
                           "--out", str(out), "--workers", "2"], capture_output=True, text=True,
                          timeout=FLEET_TIMEOUT_S, cwd=fleet_dir, env=_env())
    return proc, out


def test_fleet_replay_reports_the_broken_plant_and_replays_the_others(fleet_run, fleet_dir):
    proc, out = fleet_run
    assert proc.returncode == 0, proc.stderr[-3000:]      # 1 only when every plant failed
    t = pd.read_csv(out / "fleet.csv", keep_default_na=False)
    assert list(t["name"]) == ["north-1", "broken-3", "south-2"]          # PLANTS.yaml's order
    assert list(t["status"]) == ["ok", "failed", "ok"]
    broken = t.set_index("name").loc["broken-3"]
    assert broken["reason"] == BROKEN_REASON.format(fleet_dir.resolve() / "broken-3" / "history.csv")
    assert broken["out_dir"] == ""
    assert not (out / "broken-3").exists()
    assert "3 plants, 2 replayed, 1 failed" in proc.stdout
    assert (out / "fleet.txt").read_text().splitlines()[-2] == "3 plants, 2 replayed, 1 failed"
    ok = t[t["status"] == "ok"].set_index("name")
    for name in ("north-1", "south-2"):
        row = ok.loc[name]
        assert row["period_start"] == "2024-03-01T00:00:00+00:00"
        assert row["reason"] == "" and Path(row["out_dir"]) == out / name
        assert int(row["windows_ok"]) >= 3 and float(row["days"]) == pytest.approx(0.5, abs=0.01)
        assert 0.0 < float(row["R_th_f_now_K_per_kW"]) < 2e-3
        for f in ("windows.csv", "cip.csv", "forecast.csv", "samples.csv", "summary.txt", "meta.json",
                  "compressors.json", "initial_calibration.json", "dp_clean.json"):
            assert (out / name / f).is_file(), f"{name}/{f}"


def test_a_fleet_plant_equals_a_single_process_replay(fleet_run, fleet_dir, tmp_path):
    """The plant replayed on a cluster worker and ``hp-edge replay`` of the same files in this
    process write the same tables, byte for byte."""
    proc, out = fleet_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    single = tmp_path / "single"
    with time_limit(90):
        assert main(["replay", str(fleet_dir / "south-2" / "history.csv"), "--out", str(single),
                     "--config", str(fleet_dir / "south-2" / "plant.yaml")]) == 0
    for f in ("windows.csv", "cip.csv", "forecast.csv", "samples.csv"):
        assert (out / "south-2" / f).read_bytes() == (single / f).read_bytes(), f
    for f in ("compressors.json", "initial_calibration.json", "dp_clean.json", "surrogate_tracker.json"):
        a, b = (json.loads((d / f).read_text()) for d in (out / "south-2", single))
        for k in ("saved_at", "run_time_s"):      # when the file was written, how long it took
            a.pop(k, None), b.pop(k, None)
        assert a == b, f


def test_a_plant_task_writes_its_directory_and_returns_its_line_only(fleet_run, fleet_dir, tmp_path):
    """Each task writes its plant's directory (the client would write them one after the other:
    ~6 s a plant-year) and hands the client its fleet-table line, not the result; a directory it
    cannot write fails the plant with the reason."""
    from edge.fleet import load_plants, replay_plant
    proc, out = fleet_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    e = load_plants(fleet_dir / "PLANTS.yaml")[0]
    assert e.name == "north-1"
    d = tmp_path / "north-1"
    with time_limit(90):
        o = replay_plant(e, str(d))
    assert o.ok and o.result is None and o.row["status"] == "ok" and o.row["out_dir"] == str(d)
    assert o.row["windows_ok"] >= 3
    assert (d / "windows.csv").read_bytes() == (out / "north-1" / "windows.csv").read_bytes()
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the plant's directory would go\n", encoding="utf-8")
    with time_limit(90):
        o = replay_plant(e, str(blocked))
    assert not o.ok and o.result is None
    assert o.reason == f"writing {blocked}: File exists"
    assert (o.row["status"], o.row["reason"], o.row["out_dir"]) == ("failed", o.reason, "")


# ---- (c) PLANTS.yaml errors ---------------------------------------------------------------------------
def _plants(tmp_path, text: str) -> Path:
    shutil.copy(PLANT_YAML, tmp_path / "plant.yaml")
    (tmp_path / "h.csv").write_text("timestamp\n", encoding="utf-8")
    p = tmp_path / "PLANTS.yaml"
    p.write_text(text, encoding="utf-8")
    return p


@pytest.mark.parametrize("text, message", [
    ("plants:\n  - name: a\n    plant: plant.yaml\n    histroy: h.csv\n",
     "PLANTS.yaml: line 4: plant 1 'a': key 'histroy': unknown key (did you mean 'history'?); allowed: "
     "name, plant, history, state, initial_window, window_hours"),
    ("plants:\n  - name: a\n    plant: plant.yaml\n    history: h.csv\n"
     "  - name: a\n    plant: plant.yaml\n    history: h.csv\n",
     "PLANTS.yaml: line 5: plant 2 'a': key 'name': 'a' is used twice (first by plant 1)"),
    ("plants:\n  - name: a\n    plant: plant.yaml\n    history: h.csv\nworkers: 4\n",
     "PLANTS.yaml: line 5: key 'workers': unknown key; allowed: plants"),
], ids=["unknown-key", "duplicate-name", "unknown-top-key"])
def test_plants_yaml_errors_exit_2_naming_file_plant_and_key(tmp_path, capsys, monkeypatch, text, message):
    p = _plants(tmp_path, text)
    monkeypatch.chdir(tmp_path)
    with time_limit(30):
        rc = main(["fleet", "replay", "PLANTS.yaml", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert f"hp-edge fleet replay: {message}" in err.splitlines(), err
    assert not (tmp_path / "out").exists()          # nothing ran, nothing written
    assert p.exists()


# ---- (c2) a running cluster (--scheduler tcp://...) and its faults ------------------------------------
LOST_REASON = "not replayed: the connection to the scheduler was lost before the plant's task ended"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(proc: subprocess.Popen) -> None:
    """Stop a process this test started and everything it started (its own session), by its PID."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=20)
        except ProcessLookupError:
            pass


@contextmanager
def dask_cluster(tmp_path: Path, workers: int):
    """A cluster as a user runs one: ``dask scheduler`` on 127.0.0.1 (a port chosen now, no
    dashboard) and ``workers`` single-threaded ``dask worker`` processes; yields (address, the
    scheduler's process); stops what it started."""
    from distributed import Client
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    procs = []
    try:
        with open(tmp_path / "scheduler.log", "wb") as log:
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port",
                 str(port), "--no-dashboard", "--dashboard-address", "127.0.0.1:0"],
                stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, env=_env(), start_new_session=True))
        for k in range(workers):
            with open(tmp_path / f"worker-{k}.log", "wb") as log:
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "distributed.cli.dask_worker", addr, "--host", "127.0.0.1",
                     "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                     "--local-directory", str(tmp_path / f"worker-{k}")],
                    stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, env=_env(), start_new_session=True))
        with Client(addr, timeout=60) as c:         # the scheduler answers (and the workers joined)
            if workers:
                c.wait_for_workers(workers, timeout=90)
        yield addr, procs[0]
    finally:
        for p in reversed(procs):
            _stop(p)


def _fleet_cmd(fleet_dir: Path, out: Path, *extra: str) -> list:
    return [sys.executable, "-m", "edge.cli", "fleet", "replay", str(fleet_dir / "PLANTS.yaml"),
            "--out", str(out), *extra]


def test_fleet_on_a_running_scheduler_and_worker_equals_the_embedded_cluster(fleet_run, fleet_dir, tmp_path):
    """``--scheduler tcp://host:port``: the plants go to a cluster started by ``dask scheduler`` and
    ``dask worker``; the same table and the same plant directories, byte for byte, as the embedded
    LocalCluster's run."""
    proc0, out0 = fleet_run
    assert proc0.returncode == 0, proc0.stderr[-3000:]
    out = tmp_path / "out"
    with dask_cluster(tmp_path, 1) as (addr, _):
        proc = subprocess.run(_fleet_cmd(fleet_dir, out, "--scheduler", addr), capture_output=True, text=True,
                              timeout=FLEET_TIMEOUT_S, cwd=fleet_dir, env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    a, b = (pd.read_csv(d / "fleet.csv", keep_default_na=False) for d in (out0, out))
    assert list(b["status"]) == ["ok", "failed", "ok"]
    assert b["reason"].iloc[1] == BROKEN_REASON.format(fleet_dir.resolve() / "broken-3" / "history.csv")
    pd.testing.assert_frame_equal(a.drop(columns=["replay_s", "out_dir"]), b.drop(columns=["replay_s", "out_dir"]))
    for name in ("north-1", "south-2"):
        for f in ("windows.csv", "cip.csv", "forecast.csv", "samples.csv"):
            assert (out / name / f).read_bytes() == (out0 / name / f).read_bytes(), f"{name}/{f}"


def test_fleet_gives_up_the_plants_when_the_scheduler_has_no_worker(fleet_dir, tmp_path):
    """A scheduler without workers (all died, or none started) would keep the tasks waiting for
    ever: after --no-workers-timeout every plant is reported as not replayed, with the reason, and
    the command ends (exit 1: no plant replayed), without a traceback."""
    out = tmp_path / "out"
    with dask_cluster(tmp_path, 0) as (addr, _):
        proc = subprocess.run(_fleet_cmd(fleet_dir, out, "--scheduler", addr, "--no-workers-timeout", "2"),
                              capture_output=True, text=True, timeout=FLEET_TIMEOUT_S, cwd=fleet_dir, env=_env())
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    t = pd.read_csv(out / "fleet.csv", keep_default_na=False)
    assert list(t["status"]) == ["failed"] * 3
    assert set(t["reason"]) == {f"not replayed: the scheduler {addr} has had no worker for 2 s"}
    assert "3 plants, 0 replayed, 3 failed" in proc.stdout.splitlines()
    assert not any((out / n).exists() for n in ("north-1", "broken-3", "south-2"))


@pytest.mark.parametrize("value", ["0", "-5", "inf", "nan"])
def test_fleet_no_workers_timeout_must_be_positive_seconds(fleet_dir, tmp_path, capsys, value):
    with time_limit(30):
        rc = main(["fleet", "replay", str(fleet_dir / "PLANTS.yaml"), "--out", str(tmp_path / "out"),
                   "--no-workers-timeout", value])
    assert rc == 2
    assert capsys.readouterr().err.splitlines() == [
        f"hp-edge fleet replay: --no-workers-timeout: expected seconds > 0, got {float(value):g}"]
    assert not (tmp_path / "out").exists()


def test_fleet_on_a_tls_scheduler_without_tls_settings_exits_2_with_the_reason(fleet_dir, tmp_path):
    """``--scheduler tls://...`` with no TLS files in Dask's configuration (an empty one here): one line
    naming what is missing, exit 2, nothing written (distributed raised a TypeError: a traceback)."""
    env = _env()
    env.update(HOME=str(tmp_path), DASK_CONFIG=str(tmp_path / "dask"))
    out = tmp_path / "out"
    proc = subprocess.run(_fleet_cmd(fleet_dir, out, "--scheduler", "tls://127.0.0.1:1"), capture_output=True,
                          text=True, timeout=FLEET_TIMEOUT_S, cwd=fleet_dir, env=env)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        "hp-edge fleet replay: scheduler tls://127.0.0.1:1: cannot connect (no TLS settings for the client: "
        "Dask's configuration needs distributed.comm.tls.ca-file, .client.cert and .client.key)"]
    assert not out.exists()


def test_fleet_reports_a_lost_scheduler_for_each_plant_and_ends(fleet_dir, tmp_path):
    """The scheduler killed while the plants run: distributed cancels the client's tasks; each
    plant not finished is reported with the lost connection (not distributed's exception), the
    command ends at once (exit 1), and distributed's reconnect traceback is not printed."""
    out = tmp_path / "out"
    err_file = tmp_path / "stderr.txt"
    with dask_cluster(tmp_path, 1) as (addr, sched):
        with open(err_file, "w") as err:
            proc = subprocess.Popen(_fleet_cmd(fleet_dir, out, "--scheduler", addr), stdout=subprocess.PIPE,
                                    stderr=err, text=True, cwd=fleet_dir, env=_env(), start_new_session=True)
            try:
                deadline = time.monotonic() + 90
                while "plants [" not in err_file.read_text() and time.monotonic() < deadline \
                        and proc.poll() is None:
                    time.sleep(0.02)        # the tasks are submitted: a half-day plant takes seconds
                assert "plants [" in err_file.read_text()
                os.killpg(sched.pid, signal.SIGKILL)
                stdout, _ = proc.communicate(timeout=FLEET_TIMEOUT_S)
            finally:
                _stop(proc)
    stderr = err_file.read_text()
    assert proc.returncode == 1, stderr[-3000:]
    assert "Traceback" not in stderr
    t = pd.read_csv(out / "fleet.csv", keep_default_na=False).set_index("name")
    assert list(t.loc[["north-1", "south-2"], "reason"]) == [LOST_REASON] * 2
    assert t.loc["broken-3", "reason"] in (
        LOST_REASON, BROKEN_REASON.format(fleet_dir.resolve() / "broken-3" / "history.csv"))
    assert "3 plants, 0 replayed, 3 failed" in stdout.splitlines()


def _children(pid: int) -> list[int]:
    """The PIDs whose parent is ``pid`` (from /proc)."""
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(d.name))
    return kids


def test_replay_whose_pool_worker_is_killed_says_so_and_writes_nothing(day, tmp_path):
    """``replay --workers 2`` whose worker process dies (SIGKILL, as the out-of-memory killer sends):
    one clear line and exit 1, no traceback, no output directory (a replay is written only once it
    finished)."""
    hist = tmp_path / "day.csv"
    day.to_csv(hist, index=False)
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "edge.cli", "replay", str(hist), "--config", str(PLANT_YAML),
                             "--out", str(out), "--workers", "2"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=_env())
    try:
        deadline, victim = time.monotonic() + 90, None
        while victim is None and time.monotonic() < deadline and proc.poll() is None:
            victim = _pool_worker_of(proc.pid)    # a pool worker (spawned: it imports for seconds)
            time.sleep(0.02)
        assert victim is not None, "no pool worker seen"
        os.kill(victim, signal.SIGKILL)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=20)
    assert proc.returncode == 1, stderr[-3000:]
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == (
        f"hp-edge replay: a worker process of the pool (--workers 2) ended abruptly (killed by a signal, "
        f"e.g. the out-of-memory killer): the replay did not finish and nothing was written to {out}; run it "
        f"again, with fewer workers or without --workers")
    assert not out.exists()


# ---- (c3) Ctrl-C and SIGTERM ---------------------------------------------------------------------------
INTERRUPTED = "not replayed: the fleet command was stopped (Ctrl-C or SIGTERM) before the plant's task ended"


def _group_gone(pgid: int, seconds: float = 20.0) -> bool:
    """True once no process of the process group ``pgid`` (one this test started) is left."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False


def _signalled(cmd: list, cwd: Path, ready, sig: int, group: bool, tmp_path: Path):
    """Run ``cmd`` in its own session; once ``ready(stderr so far, pid)`` is true send ``sig`` (to
    the whole group, as a terminal's Ctrl-C does, or to the command's process only, as ``kill PID``
    does); returns (returncode, stdout, stderr, every process of the group gone)."""
    err_file = tmp_path / "stderr.txt"
    with open(err_file, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, cwd=cwd, env=_env(),
                                start_new_session=True)
        try:
            deadline = time.monotonic() + 120
            while not ready(err_file.read_text(), proc.pid) and time.monotonic() < deadline \
                    and proc.poll() is None:
                time.sleep(0.02)
            assert proc.poll() is None, "the command ended before the signal"
            (os.killpg if group else os.kill)(proc.pid, sig)
            stdout, _ = proc.communicate(timeout=FLEET_TIMEOUT_S)
            gone = _group_gone(proc.pid)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=20)
    return proc.returncode, stdout, err_file.read_text(), gone


@pytest.mark.parametrize("sig, group, rc, how", [(signal.SIGINT, True, 130, "interrupted"),
                                                 (signal.SIGTERM, False, 143, "stopped by SIGTERM")],
                         ids=["ctrl-c", "sigterm"])
def test_fleet_stopped_writes_the_table_and_leaves_no_process(fleet_dir, tmp_path, sig, group, rc, how):
    """Ctrl-C in a terminal (SIGINT to every process of the group: the cluster's workers too) or
    SIGTERM to the command while the plants run: the table is written with every plant not finished
    marked, the cluster is closed (no process of the group left), one line on stderr, no traceback."""
    out = tmp_path / "out"
    code, stdout, stderr, gone = _signalled(_fleet_cmd(fleet_dir, out, "--workers", "2"), fleet_dir,
                                            lambda err, pid: "plants [" in err, sig, group, tmp_path)
    assert code == rc, stderr[-3000:]
    assert gone
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == (f"hp-edge fleet replay: {how}; wrote {out / 'fleet.csv'} and "
                                       f"{out / 'fleet.txt'}: 0 of 3 plants replayed, the others marked not replayed")
    t = pd.read_csv(out / "fleet.csv", keep_default_na=False).set_index("name")
    assert list(t.loc[["north-1", "south-2"], "reason"]) == [INTERRUPTED] * 2
    assert t.loc["broken-3", "reason"] in (
        INTERRUPTED, BROKEN_REASON.format(fleet_dir.resolve() / "broken-3" / "history.csv"))


def _pool_worker_of(pid: int) -> int | None:
    for k in _children(pid):
        try:
            if "spawn_main" in Path(f"/proc/{k}/cmdline").read_text():
                return k
        except OSError:
            pass
    return None


@pytest.mark.parametrize("after_s", [0.0, 1.0], ids=["as-the-pool-starts", "while-it-replays"])
def test_replay_with_workers_ctrl_c_stops_at_once_without_tracebacks(day, tmp_path, after_s):
    """Ctrl-C in a terminal during ``replay --workers 2`` (as soon as a pool worker exists, and a
    second later, while the workers import and replay: a day takes them several seconds): the
    pool's workers ignore SIGINT (each printed a traceback), the command cancels the chunks not
    started and ends (it waited for every queued chunk: it seemed to hang), exit 130, nothing
    written, no process of the group left."""
    hist = tmp_path / "day.csv"
    day.to_csv(hist, index=False)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "edge.cli", "replay", str(hist), "--config", str(PLANT_YAML), "--out", str(out),
           "--workers", "2"]
    seen = []

    def ready(err, pid):
        if not seen and _pool_worker_of(pid) is not None:
            seen.append(time.monotonic())
        return bool(seen) and time.monotonic() - seen[0] >= after_s
    code, stdout, stderr, gone = _signalled(cmd, tmp_path, ready, signal.SIGINT, True, tmp_path)
    assert code == 130, stderr[-3000:]
    assert gone
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == "hp-edge replay: interrupted"
    assert not out.exists()


# ---- (d) the daemon does not import dask ---------------------------------------------------------------
def test_gateway_and_cli_do_not_import_dask():
    code = ("import sys, edge.service, edge.cli, edge.fleet, edge.commands.fleet_cmds\n"
            "from edge.cli import main\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed'))\n"
            "assert not bad, bad\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd=ROOT, env=_env())
    assert proc.returncode == 0, proc.stderr


# ---- (e) the embedded cluster's workers ----------------------------------------------------------------
def test_embedded_cluster_workers_run_without_dasks_memory_trimming():
    """distributed's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536 (4.6x the page faults of
    a replay); the embedded cluster's workers start without it and without the profiler, and
    starting the cluster leaves this process's environment as it was (the nanny writes the
    pre-spawn variables into it)."""
    code = ("import os, edge.fleet as F\n"
            "def probe():\n"
            "    import os, dask\n"
            "    return (os.environ.get('MALLOC_TRIM_THRESHOLD_'), dask.config.get('distributed.worker.profile.enabled'),\n"
            "            os.environ.get('OPENBLAS_NUM_THREADS'))\n"
            "if __name__ == '__main__':\n"
            "    with F.Cluster('local', 2) as c:\n"
            "        got = sorted(c.run(probe).values())\n"
            "    print(got, os.environ.get('MALLOC_TRIM_THRESHOLD_'))\n")
    env = _env()
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=FLEET_TIMEOUT_S,
                          cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "[(None, False, '1'), (None, False, '1')] None"


def test_embedded_cluster_pins_each_worker_to_its_own_cpu_and_its_tasks_threads_inherit_it():
    """Worker i of the embedded cluster runs on the i-th CPU of the client's (round robin): the
    task's thread, and a thread the task starts (a replay's lockstep threads), on that CPU alone."""
    code = ("import os, threading, edge.fleet as F\n"
            "def probe():\n"
            "    import os, threading\n"
            "    got = {}\n"
            "    t = threading.Thread(target=lambda: got.update(child=sorted(os.sched_getaffinity(0))))\n"
            "    t.start(); t.join()\n"
            "    return sorted(os.sched_getaffinity(0)), got['child']\n"
            "if __name__ == '__main__':\n"
            "    cpus = sorted(os.sched_getaffinity(0))\n"
            "    with F.Cluster('local', 3) as c:\n"
            "        ws = sorted(c.scheduler_info()['workers'].items(), key=lambda kv: kv[1]['name'])\n"
            "        got = [c.submit(probe, pure=False, workers=[a]).result() for a, _ in ws]\n"
            "    want = [([cpus[i % len(cpus)]], [cpus[i % len(cpus)]]) for i in range(3)]\n"
            "    print(got == want, got, want, sorted(os.sched_getaffinity(0)) == cpus)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=FLEET_TIMEOUT_S,
                          cwd=ROOT, env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split()[0] == "True", proc.stdout
    assert proc.stdout.split()[-1] == "True", proc.stdout        # the client's process is not pinned


def _pool_probe(delay_s: float):
    import time
    time.sleep(delay_s)                 # long enough that the pool starts every worker
    return os.getpid(), sorted(os.sched_getaffinity(0))


def test_replay_workers_pool_pins_each_worker_to_its_own_cpu_and_leaves_this_process_alone():
    """``replay --workers 3``'s pool: its workers on the CPUs of this process, one each in the
    order they start (round robin beyond the CPUs); this process (passes 1 and 3) not pinned."""
    cpus = sorted(os.sched_getaffinity(0))
    with time_limit(60):
        with process_pool(3) as pool:
            got = dict(pool.map(_pool_probe, [0.5] * 6))
    assert len(got) == 3, got
    assert sorted(got.values()) == sorted([[cpus[i % len(cpus)]] for i in range(3)]), (got, cpus)
    assert sorted(os.sched_getaffinity(0)) == cpus


def test_pin_next_numbers_the_workers_and_survives_a_refused_pin():
    from edge.cpupin import pin_next
    ctx = multiprocessing.get_context("spawn")
    counter = ctx.Value("i", 0)
    before = sorted(os.sched_getaffinity(0))
    pin_next(counter, [-1])             # a CPU that does not exist: refused, no exception
    assert counter.value == 1
    assert sorted(os.sched_getaffinity(0)) == before


def test_pin_threads_pins_every_thread_of_the_process():
    code = ("import os, threading, time\n"
            "from edge.cpupin import cpu_for, pin_threads\n"
            "ev = threading.Event()\n"
            "t = threading.Thread(target=ev.wait); t.start()\n"
            "cpu = cpu_for(1)\n"
            "ok = pin_threads(cpu)\n"
            "sets = {tid: sorted(os.sched_getaffinity(int(tid))) for tid in os.listdir('/proc/self/task')}\n"
            "ev.set(); t.join()\n"
            "print(ok, len(sets) >= 2 and all(v == [cpu] for v in sets.values()),\n"
            "      cpu_for(0, [3, 1]), cpu_for(1, [3, 1]), cpu_for(2, [3, 1]))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env=_env())
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "True True 1 3 1"


# ---- (f) the longest plants first ------------------------------------------------------------------------
def test_fleet_hands_the_longest_histories_to_the_executor_first_and_reports_in_plants_yaml_order(tmp_path):
    from concurrent.futures import Future

    from edge.fleet import PlantEntry, run_fleet, submission_order
    sizes = {"a": 1000, "b": 50_000, "c": 50_000, "d": 120_000, "e": 0}
    entries = []
    for name, size in sizes.items():
        h = tmp_path / f"{name}.csv"
        if name != "e":                                      # e: no history file (counts as empty)
            h.write_bytes(b"x" * size)
        entries.append(PlantEntry(name=name, plant=str(tmp_path / "plant.yaml"), history=str(h)))
    assert submission_order(entries) == [3, 1, 2, 0, 4]      # d, then b and c (equal) in PLANTS.yaml's order

    class Recording:
        """An executor that records what it is handed and fails every task at once."""
        def __init__(self):
            self.names = []

        def submit(self, fn, entry, *args):
            self.names.append(entry.name)
            f = Future()
            f.set_exception(RuntimeError("not run"))
            return f
    ex = Recording()
    table = run_fleet(entries, tmp_path / "out", executor=ex)
    assert ex.names == ["d", "b", "c", "a", "e"]
    assert list(table["name"]) == ["a", "b", "c", "d", "e"]
    assert list(table["reason"]) == ["task failed: RuntimeError: not run"] * 5


def test_fleet_progress_counts_plants_as_they_finish_in_any_order(tmp_path, monkeypatch):
    """The progress shows plants as they finish, not in PLANTS.yaml's order: here the first plant
    of PLANTS.yaml finishes only once the progress has counted the other three (it waits for
    that, at most 10 s); the table stays in PLANTS.yaml's order."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    import edge.fleet as fleet
    from edge.fleet import PlantEntry, PlantOutcome, run_fleet
    entries = [PlantEntry(name=n, plant=str(tmp_path / "plant.yaml"), history=str(tmp_path / f"{n}.csv"))
               for n in "abcd"]
    others_counted = threading.Event()
    waited: dict = {}

    def fake(entry, out_dir):
        if entry.name == "a":       # True: the progress counted b, c and d while a still ran
            waited["a"] = others_counted.wait(10.0)
        return PlantOutcome(entry.name, False, f"{entry.name} done")
    monkeypatch.setattr(fleet, "replay_plant", fake)
    monkeypatch.setattr(fleet, "AWAIT_POLL_S", 0.01, raising=False)
    calls = []

    def progress(done, total):
        calls.append((done, total))
        if done == 3:
            others_counted.set()
    with ThreadPoolExecutor(max_workers=4) as ex:
        table = run_fleet(entries, tmp_path / "out", executor=ex, progress=progress)
    assert waited == {"a": True}
    counts = [d for d, _ in calls]
    assert counts[0] == 0 and counts[-1] == 4 and counts == sorted(counts)
    assert all(t == 4 for _, t in calls)
    assert list(table["name"]) == ["a", "b", "c", "d"]
    assert list(table["reason"]) == ["a done", "b done", "c done", "d done"]


# ---- (g) a worker started with Dask's trim threshold ----------------------------------------------------
def test_replay_memory_keeps_freed_arrays_in_a_process_started_with_a_small_trim_threshold():
    """In a process started with MALLOC_TRIM_THRESHOLD_=65536 (a Dask worker's default), arrays of
    24 MB freed and allocated again cost fresh pages every time (each is mmapped; 24 MB: more than
    a free block the imports may have left in the heap, which would serve it without a fault);
    inside ``replay_memory`` they are reused, and afterwards the process's own setting holds again."""
    code = ("import resource, numpy as np, model.analysis.replay as F\n"
            "def faults():\n"
            "    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "    for _ in range(20):\n"
            "        a = np.ones(3_000_000); del a\n"
            "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0\n"
            "before = faults()\n"
            "with F.replay_memory():\n"
            "    faults(); inside = faults()\n"
            "after = faults()\n"
            "print(before, inside, after)\n")
    env = _env()
    env["MALLOC_TRIM_THRESHOLD_"] = "65536"
    env.pop("MALLOC_MMAP_THRESHOLD_", None)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    before, inside, after = map(int, proc.stdout.split())
    # fresh pages for every array: 5,860 faults each with 4-kB pages, 12 where the kernel backs it
    # with 2-MB pages (transparent huge pages); at least 10 an array either way
    assert before >= 20 * 10 and after >= before / 2, (before, after)
    assert inside <= before / 20, (before, inside)


def test_replay_memory_leaves_other_processes_alone(monkeypatch):
    import model.analysis.replay as F
    calls = []

    class Libc:
        def mallopt(self, *a):
            calls.append(("mallopt",) + a)

        def malloc_trim(self, *a):
            calls.append(("malloc_trim",) + a)
    monkeypatch.setattr(F, "_glibc", lambda: Libc())
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    with F.replay_memory():
        pass
    assert calls == []                                    # no trim setting: glibc's own behaviour
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", str(F.TASK_TRIM_THRESHOLD))
    with F.replay_memory():
        pass
    assert calls == []                                    # a threshold as large as the task's: left as is
    for bad in ("-1", "64k", ""):
        monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", bad)
        with F.replay_memory():
            pass
    assert calls == []                                    # not a size: left as is
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "65536")
    with pytest.raises(RuntimeError):
        with F.replay_memory():
            raise RuntimeError("the task failed")
    assert calls == [("mallopt", F.M_MMAP_THRESHOLD, F.TASK_MMAP_THRESHOLD),
                     ("mallopt", F.M_TRIM_THRESHOLD, F.TASK_TRIM_THRESHOLD),
                     ("mallopt", F.M_TRIM_THRESHOLD, 65536),
                     ("mallopt", F.M_MMAP_THRESHOLD, F.DEFAULT_MMAP_THRESHOLD),
                     ("malloc_trim", 0)]                  # set back even when the task raised
    calls.clear()
    with F.replay_memory():
        with F.replay_memory():                           # nested (replay_plant -> replay): the outer one
            pass
        assert len(calls) == 2
    assert len(calls) == 5
