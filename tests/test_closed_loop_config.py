"""gateway.yaml's closed_loop section (issue 13): shipped off, every bad key named with file,
section and key, exit 2 from check-config and run; the set-point write path follows the config."""
from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
import yaml

from edge.cli import main as cli_main
from edge.closed_loop import ClosedLoopConfig
from edge.config import ConfigError, load_config

REPO = Path(__file__).resolve().parents[1]
SEC = "config/gateway.yaml: section 'closed_loop'"


@pytest.fixture
def cfgdir(tmp_path, monkeypatch):
    d = tmp_path / "config"
    d.mkdir()
    for name in ("gateway.yaml", "tags.yaml", "plant.yaml"):
        shutil.copy(REPO / "config" / name, d)
    monkeypatch.chdir(tmp_path)
    return d


def edit(d: Path, name: str, change) -> None:
    path = d / name
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def problems() -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config("config/gateway.yaml")
    return [re.sub(r"^([^:]+): line \d+: ", r"\1: ", ln) for ln in info.value.problems]


def loop(**kw):
    def change(d):
        d["closed_loop"].update(kw)
    return change


def test_shipped_off_with_every_key():
    cfg = load_config(REPO / "config" / "gateway.yaml", load_plant=False)
    assert cfg.closed_loop == ClosedLoopConfig(
        enabled=False, setpoint_tag="p_m_sp", enable_tag="closed_loop_enable",
        bounds_bar_g=(12.0, 18.0), max_step_bar=0.5, min_interval_s=300.0,
        heartbeat_timeout_s=60.0, shed_after_bad_scans=3, deadband_bar=0.05)


def test_an_absent_section_is_off(cfgdir):
    edit(cfgdir, "gateway.yaml", lambda d: d.pop("closed_loop"))
    assert load_config("config/gateway.yaml").closed_loop is None


def test_enabled_config_loads(cfgdir):
    edit(cfgdir, "gateway.yaml", loop(enabled=True))
    cfg = load_config("config/gateway.yaml")
    assert cfg.closed_loop.enabled and cfg.closed_loop.setpoint_tag == "p_m_sp"


CASES = {
    "enabled as text": (loop(enabled="yes"),
                        [f"{SEC}: key 'enabled': expected true or false, got 'yes'"]),
    "unknown key": (loop(max_step=0.5), [
        f"{SEC}: key 'max_step': unknown key (did you mean 'max_step_bar'?); allowed: enabled, "
        "setpoint_tag, enable_tag, bounds_bar_g, max_step_bar, min_interval_s, deadband_bar, "
        "heartbeat_timeout_s, shed_after_bad_scans"]),
    "missing key": (lambda d: d["closed_loop"].pop("bounds_bar_g"),
                    [f"{SEC}: key 'bounds_bar_g': missing required key"]),
    "set point not a tag": (loop(enabled=True, setpoint_tag="p_m_setpoint"),
                            [f"{SEC}: key 'setpoint_tag': 'p_m_setpoint' is not a tag of "
                             "config/tags.yaml"]),
    "set point an input register": (loop(enabled=True, setpoint_tag="p_dis_LS"), [
        f"{SEC}: key 'setpoint_tag': tag 'p_dis_LS' is an input register: the set point is "
        "written with FC16 and must be a holding register"]),
    "set point not a pressure": (loop(enabled=True, setpoint_tag="life_counter",
                                      enable_tag="closed_loop_enable"), [
        f"{SEC}: key 'setpoint_tag': tag 'life_counter' has unit '1': the set point must be a "
        "pressure (bar(g) after conversion)"]),
    "enable not 0/1": (loop(enabled=True, enable_tag="life_counter"), [
        f"{SEC}: key 'enable_tag': tag 'life_counter' must be a 0/1 value: a coil, a discrete "
        "input, one bit of a register, or a register with range [0, 1]"]),
    "enable is the set point": (loop(enabled=True, enable_tag="p_m_sp"), [
        f"{SEC}: key 'enable_tag': tag 'p_m_sp' must be a 0/1 value: a coil, a discrete input, "
        "one bit of a register, or a register with range [0, 1]",
        f"{SEC}: key 'enable_tag': 'p_m_sp' is also setpoint_tag: the enable is the operator's "
        "(read only), the set point the gateway's"]),
    "bounds reversed": (loop(bounds_bar_g=[18.0, 12.0]),
                        [f"{SEC}: key 'bounds_bar_g': low 18.0 must be below high 12.0"]),
    "bounds beyond the tag's range": (loop(enabled=True, bounds_bar_g=[12.0, 45.0]), [
        f"{SEC}: key 'bounds_bar_g': [12, 45] bar(g) must lie within the plausible range "
        "[0, 40] bar(g) of tag 'p_m_sp' in config/tags.yaml"]),
    "step below the resolution": (loop(enabled=True, max_step_bar=0.004), [
        f"{SEC}: key 'max_step_bar': 0.004 bar is below the resolution of tag 'p_m_sp' (0.01 "
        "bar): no step could be written"]),
    "step zero": (loop(max_step_bar=0), [f"{SEC}: key 'max_step_bar': must be > 0, got 0"]),
    "interval shorter than a scan": (loop(min_interval_s=2), [
        f"{SEC}: key 'min_interval_s': 2 s is shorter than scan_interval_s (5 s)"]),
    "heartbeat timeout too short": (loop(heartbeat_timeout_s=8), [
        f"{SEC}: key 'heartbeat_timeout_s': 8 s is shorter than 2 scan intervals (5 s each): "
        "the PLC would fall back while the gateway runs"]),
    "shed after zero scans": (loop(shed_after_bad_scans=0),
                              [f"{SEC}: key 'shed_after_bad_scans': 0 is outside 1..1000"]),
    "negative deadband": (loop(deadband_bar=-0.1),
                          [f"{SEC}: key 'deadband_bar': must be >= 0, got -0.1"]),
}


@pytest.mark.parametrize("case", list(CASES))
def test_exact_error_messages(cfgdir, case):
    change, expected = CASES[case]
    edit(cfgdir, "gateway.yaml", change)
    assert problems() == expected


def test_a_disabled_loop_does_not_need_its_tags(cfgdir):
    """Off, the loop touches no tag: a tags.yaml without the enable tag is fine ..."""
    edit(cfgdir, "tags.yaml", lambda d: d["tags"].pop("closed_loop_enable"))
    assert load_config("config/gateway.yaml").closed_loop.enabled is False
    # ... and enabling it then names the missing tag
    edit(cfgdir, "gateway.yaml", loop(enabled=True))
    assert problems() == [f"{SEC}: key 'enable_tag': 'closed_loop_enable' is not a tag of "
                          "config/tags.yaml"]


def test_check_config_and_run_exit_2_naming_the_key(cfgdir, capsys):
    edit(cfgdir, "gateway.yaml", loop(enabled=True, bounds_bar_g=[12.0, 45.0]))
    for cmd in (["check-config"], ["run"]):
        assert cli_main([*cmd, "--config", "config/gateway.yaml"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert re.fullmatch(r"config/gateway\.yaml: line \d+: section 'closed_loop': key "
                            r"'bounds_bar_g': \[12, 45\] bar\(g\) must lie within the plausible "
                            r"range \[0, 40\] bar\(g\) of tag 'p_m_sp' in config/tags\.yaml",
                            err[0]), err
        assert err[-1] == "1 problem(s); nothing was started."


def test_check_config_says_what_the_gateway_writes(cfgdir, capsys):
    edit(cfgdir, "gateway.yaml", loop(enabled=True))
    assert cli_main(["check-config", "--config", "config/gateway.yaml"]) == 0
    out = capsys.readouterr().out
    assert ("the only registers the gateway writes besides the closed loop's set point 'p_m_sp' "
            "(holding 110: ON, bounds 12..18 bar(g), step 0.5 bar per 300 s, while "
            "'closed_loop_enable' is 1)") in out
