"""The small things a new user hit (issue 9 item 16): --version, a clear error for an unknown
fault tag, the progress line, finding config/ away from the repository, `read` without a
config file, the demo's exception-2 warning, $STATE_DIRECTORY, journald priorities, the unit."""
from __future__ import annotations

import asyncio
import io
import logging
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from edge import config as edge_config
from edge.cli import main
from edge.commands.analysis_cmds import Progress
from edge.commands.gateway_cmds import JournalFormatter, stderr_is_journal
from edge.config import load_config

REPO = Path(__file__).resolve().parents[1]


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    version = re.search(r'^version = "([^"]+)"', (REPO / "pyproject.toml").read_text(), re.M)
    assert capsys.readouterr().out == f"hp-edge {version.group(1)}\n"


@pytest.mark.parametrize("extra", [["--port", "0", "--duration", "0.1"],
                                   ["--export", "never-written.csv", "--days", "0.001"]])
def test_simulate_with_an_unknown_fault_tag_is_a_clear_error(extra, capsys, tmp_path,
                                                             monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--fault", "stuck:T_ee", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hp-edge simulate: --fault stuck:T_ee: unknown tag 'T_ee' (did you "
                          "mean 'T_e'?); the simulator serves T_sink_in, ")
    assert "Traceback" not in err and not (tmp_path / "never-written.csv").exists()


class Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def screen(text: str) -> str:
    """What a terminal shows for the last line after carriage returns overwrite it."""
    line = ""
    for part in text.split("\n")[-1].split("\r"):
        line = part + line[len(part):]
    return line


def test_progress_line_leaves_nothing_behind():
    out = Tty()
    p = Progress("windows", stream=out)
    p(0, 100)
    p(1, 100)         # "~N s left" appears ...
    out.seek(0)
    out.truncate()
    p.t0 -= 1e6       # ... and the next line is shorter than the one before
    p(2, 100)
    p(3, 100)
    shown = screen(out.getvalue())
    assert shown.rstrip().endswith("s left") and not shown.rstrip().endswith("leftt")
    p(100, 100)
    assert out.getvalue().endswith("\n")


def test_commands_find_config_away_from_the_repository(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)                       # no config/ here
    assert main(["check-config"]) == 0                # the package's config/ is found
    assert capsys.readouterr().out.startswith(f"OK: {REPO / 'config' / 'gateway.yaml'}")
    etc = tmp_path / "etc-hp-edge"
    shutil.copytree(REPO / "config", etc)
    monkeypatch.setattr(edge_config, "CONFIG_DIRS", (tmp_path / "config", etc,
                                                     REPO / "config"))
    assert main(["check-config"]) == 0                # /etc/hp-edge before the package's
    assert capsys.readouterr().out.startswith(f"OK: {etc / 'gateway.yaml'}")
    assert edge_config.find_config("plant.yaml") == etc / "plant.yaml"


def test_read_needs_neither_tags_nor_plant_file(tmp_path, monkeypatch, capsys):
    from test_plc import encode_advisory, plant_server, CFG

    doc = yaml.safe_load((REPO / "config" / "gateway.yaml").read_text())
    doc.update(tags_file="missing-tags.yaml", plant_file="missing-plant.yaml")
    doc["plc"].pop("host")                            # and no usable plc section either
    gw = tmp_path / "gateway.yaml"
    gw.write_text(yaml.safe_dump(doc))
    words = encode_advisory(CFG.advisory, {"p_m_sp_rec": 15.25}, {"comm_fault"}, heartbeat=7)

    async def scenario():
        async with plant_server() as server:
            await server.async_setValues(1, 16, 1000, words)
            rc = await asyncio.to_thread(main, ["read", "--config", str(gw), "--host",
                                                "127.0.0.1", "--port", str(server.port)])
            no_host = await asyncio.to_thread(main, ["read", "--config", str(gw)])
            monkeypatch.chdir(tmp_path)               # no --config at all: the package's layout
            plain = await asyncio.to_thread(main, ["read", "--host", "127.0.0.1", "--port",
                                                   str(server.port), "--json"])
            return rc, no_host, plain

    rc, no_host, plain = asyncio.run(asyncio.wait_for(scenario(), 30))
    captured = capsys.readouterr()
    assert (rc, no_host, plain) == (0, 2, 0)
    assert "1000     heartbeat               7" in captured.out and '"heartbeat": 7' in captured.out
    assert f"the plc section of {gw} is not valid; name the server with --host and --port" \
        in captured.err


def test_shipped_config_reads_the_shipped_simulator_without_exception_2(caplog):
    """The demo began with an exception-2 WARNING: the shipped plan read holding 100..110
    across registers the shipped simulator does not serve. max_read_gap 0 reads what the tag
    map declares."""
    from edge.plc import PlcClient
    from simulator.server import PlantSimulator

    cfg = load_config(REPO / "config" / "gateway.yaml")

    async def scenario():
        sim = PlantSimulator(port=0, speed=60)
        await sim.start()
        try:
            plc = PlcClient.from_config(cfg, host="127.0.0.1", port=sim.port)
            results = [await plc.read_all() for _ in range(2)]
            split = plc.split_groups
            await plc.close()
        finally:
            await sim.stop()
        return results, split

    with caplog.at_level(logging.INFO, logger="edge.plc"):
        results, split = asyncio.run(asyncio.wait_for(scenario(), 60))
    for r in results:
        assert r.comm_error is None and r.requests == 3
        assert {n: v.bad for n, v in r.values.items() if v.bad} == {}
    assert split == []
    assert [r.message for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_state_paths_follow_systemds_state_directory(monkeypatch):
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    cfg = load_config(REPO / "config" / "gateway.yaml", load_plant=False)
    assert cfg.state_dir == REPO / "var" / "state"
    monkeypatch.setenv("STATE_DIRECTORY", "/var/lib/hp-edge:/var/lib/other")
    cfg = load_config(REPO / "config" / "gateway.yaml", load_plant=False)
    assert cfg.state_dir == Path("/var/lib/hp-edge/state")
    assert cfg.history_db == Path("/var/lib/hp-edge/history.sqlite")


def test_state_path_without_default_needs_the_variable(tmp_path, monkeypatch):
    shutil.copytree(REPO / "config", tmp_path / "config")
    path = tmp_path / "config" / "gateway.yaml"
    path.write_text(path.read_text().replace("${STATE_DIRECTORY:-../var}/state",
                                             "${STATE_DIRECTORY}/state"))
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(edge_config.ConfigError) as info:
        load_config(path, load_plant=False)
    assert info.value.problems[0].endswith(
        "top level: key 'state_dir': environment variable STATE_DIRECTORY is not set and "
        "'${STATE_DIRECTORY}/state' gives no default (write ${NAME:-default})")


def test_log_lines_carry_a_journald_priority(tmp_path):
    fmt = JournalFormatter("%(levelname)s %(name)s: %(message)s")
    rec = logging.LogRecord("edge.plc", logging.WARNING, __file__, 1, "PLC down", (), None)
    assert fmt.format(rec) == "<4>WARNING edge.plc: PLC down"
    rec = logging.LogRecord("edge.loop", logging.ERROR, __file__, 1, "a\nb", (), None)
    assert fmt.format(rec) == "<3>ERROR edge.loop: a\n<3>b"
    # a real process whose stderr is "the journal" (JOURNAL_STREAM names its device:inode)
    err = tmp_path / "journal"
    with open(err, "wb") as fh:
        st = os.fstat(fh.fileno())
        code = ("from edge.commands.gateway_cmds import _setup_logging; _setup_logging('INFO'); "
                "import logging; logging.getLogger('edge.plc').warning('connect failed'); "
                "logging.getLogger('edge.loop').info('started')")
        env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        subprocess.run([sys.executable, "-c", code], stderr=fh, env=env, cwd=REPO, timeout=60,
                       check=True)
    assert err.read_text().splitlines() == ["<4>WARNING edge.plc: connect failed",
                                            "<6>INFO edge.loop: started"]
    with open(err, "rb") as fh:
        assert not stderr_is_journal(fh)          # JOURNAL_STREAM not set here


UNIT = (REPO / "deploy" / "hp-edge.service").read_text()


def test_the_unit_file_is_hardened():
    directives = {ln.split("=", 1)[0]: ln.split("=", 1)[1] for ln in UNIT.splitlines()
                  if "=" in ln and not ln.startswith("#")}
    for key, value in {"SystemCallFilter": "@system-service", "MemoryDenyWriteExecute": "yes",
                       "RestrictSUIDSGID": "yes", "ProtectProc": "invisible",
                       "ProcSubset": "pid", "RemoveIPC": "yes", "StateDirectory": "hp-edge",
                       "RestartPreventExitStatus": "2"}.items():
        assert directives.get(key) == value, key
    # the one writable place besides the state: the tables' cache (model.cycletables.cache_file)
    assert directives.get("CacheDirectory") == "hp-edge"
    assert "Environment=HP_EDGE_CACHE_DIR=/var/cache/hp-edge" in UNIT.splitlines()


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_security_of_the_unit():
    out = subprocess.run(["systemd-analyze", "security", "--offline=true",
                          str(REPO / "deploy" / "hp-edge.service")],
                         capture_output=True, text=True, timeout=60)
    match = re.search(r"Overall exposure level for hp-edge.service: ([\d.]+) (\w+)", out.stdout)
    assert match, out.stdout + out.stderr
    assert float(match.group(1)) <= 2.0 and match.group(2) == "OK"


def test_simulate_checks_plant_yaml_like_every_command(tmp_path, capsys):
    shutil.copytree(REPO / "config", tmp_path / "config")
    plant = tmp_path / "config" / "plant.yaml"
    plant.write_text(plant.read_text().replace("R_th_f_K_per_kW: 0.0", "R_th_f_K_per_kw: 0.0", 1))
    rc = main(["simulate", "--config", str(tmp_path / "config" / "simulator.yaml"), "--export",
               str(tmp_path / "h.csv"), "--days", "0.001"])
    err = capsys.readouterr().err
    assert rc == 2 and not (tmp_path / "h.csv").exists()
    assert "section 'calibrated': key 'R_th_f_K_per_kw': unknown key (did you mean " \
           "'R_th_f_K_per_kW'?)" in err


def test_report_and_export_history_find_config_away_from_the_repository(tmp_path, monkeypatch, capsys):
    """Like the other commands, report and export-history without --config use the source
    checkout's config/ when the working directory has none (the README's service session)."""
    monkeypatch.chdir(tmp_path)
    assert main(["export-history", "--out", "h.csv"]) == 2
    err = capsys.readouterr().err
    assert "file not found" not in err
    db = load_config(str(REPO / "config" / "gateway.yaml"), load_plant=False).history_db
    assert err == f"hp-edge export-history: {db}: no such history database\n"
    assert main(["report", "missing-dir", "--out", "r.html"]) == 2
    assert capsys.readouterr().err == ("hp-edge report: missing-dir: not a directory (expected the output "
                                       "of hp-edge replay)\n")


def test_demo_clips_the_advice_reason_at_a_word():
    from edge.demo import _clip
    text = ("in conditions like this window's the plant has run over p_m 14.60-16.60 bar(g) only "
            "(less than 2 bar): the data do not show where the optimum lies")
    assert _clip(text, 90) == ("in conditions like this window's the plant has run over p_m 14.60-16.60 "
                               "bar(g) only…")
    assert _clip("short", 90) == "short"
    assert len(_clip("x" * 200, 90)) == 90


def test_hp_edge_runs_numpy_on_one_blas_thread_unless_told_otherwise():
    """edge.cli sets one BLAS/OpenMP thread before numpy loads (the gateway on one core; a replay
    here gives a Dask worker's numbers); a value in the environment wins."""
    import subprocess
    import sys
    code = ("import os, sys, edge.cli; assert 'numpy' not in sys.modules; "
            "print(' '.join(os.environ[k] for k in edge.cli.BLAS_THREADS_ENV))")
    env = {k: v for k, v in __import__("os").environ.items() if k not in
           ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "1", "1"]
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "2"},
                         capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["2", "1", "1"]
