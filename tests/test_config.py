"""Configuration loading and validation: exact messages, all problems at once, no rewriting."""
from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
import socket
from pathlib import Path

import pytest
import yaml

from edge.commands import gateway_cmds
from edge.config import ConfigError, load_config

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "config" / "gateway.yaml"
TOP_KEYS = ("plc, tags_file, plant_file, scan_interval_s, aggregate_s, "
            "calibration_interval_s, calibration_window_h, min_window_samples, optimizer, "
            "life_counter_tag, state_dir, history_db, history_retention_days, reserved, advisory, northbound, "
            "closed_loop")
TAG_KEYS = ("register, address, type, byte_order, scale, offset, unit, range, max_age_s, "
            "sentinel, pressure, device_id, bit, flatline_s")
TYPES = "int16, uint16, int32, uint32, float32, int64, uint64, float64, bool"


# -------------------------------------------------------------------------- default config

def test_default_config_loads():
    cfg = load_config(DEFAULT, load_plant=False)
    assert len(cfg.tags) == 28
    assert [t.name for t in cfg.tags][:3] == ["T_sink_in", "T_sink_out", "T_source_in"]
    p = cfg.tag("p_suc_LS")
    assert (p.register, p.address, p.type, p.byte_order, p.pressure) == ("input", 16, "float32", "CDAB", "gauge")
    t = cfg.tag("T_sink_in")
    assert (t.scale, t.offset, t.range, t.sentinel, t.byte_order) == (0.01, 0.0, (0.0, 90.0), -32768, "AB")
    assert cfg.plc.host == "127.0.0.1" and cfg.plc.port == 5020 and cfg.plc.device_id == 1
    adv = cfg.advisory
    assert (adv.register, adv.start, adv.size, adv.byte_order) == ("holding", 1000, 64, "ABCD")
    assert [f.offset for f in adv.fields] == [0, 1] + list(range(2, 46, 2)) + [48, 49, 50, 52, 54, 56]
    assert adv.field("last_update").type == "uint32"
    assert dict(adv.status_bits)[5] == "comm_fault"
    assert cfg.life_counter_tag == "life_counter" and cfg.optimizer == "auto"
    assert cfg.plant is None                       # not loaded when load_plant=False


def test_paths_resolve_relative_to_the_gateway_file(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)                    # nowhere near the config
    cfg = load_config(DEFAULT, load_plant=False)
    assert cfg.tags_file == REPO / "config" / "tags.yaml"
    assert cfg.state_dir == REPO / "var" / "state"
    assert cfg.history_db == REPO / "var" / "history.sqlite"


@pytest.mark.skipif(not (REPO / "config" / "plant.yaml").exists(), reason="plant.yaml not there yet")
def test_default_config_with_plant():
    cfg = load_config(DEFAULT)
    assert isinstance(cfg.plant, dict) and cfg.plant


def test_config_is_frozen():
    cfg = load_config(DEFAULT, load_plant=False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.tags[0].address = 5
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.plc.port = 1


# ---------------------------------------------------------------- edited copies in tmp_path

@pytest.fixture
def cfgdir(tmp_path, monkeypatch):
    """A copy of the default config in tmp_path/config, cwd = tmp_path (messages then read
    'config/tags.yaml: ...'), and a tiny plant.yaml so these tests do not depend on its content."""
    d = tmp_path / "config"
    d.mkdir()
    shutil.copy(REPO / "config" / "gateway.yaml", d)
    shutil.copy(REPO / "config" / "tags.yaml", d)
    shutil.copy(REPO / "config" / "plant.yaml", d)
    monkeypatch.chdir(tmp_path)
    return d


def edit(d: Path, name: str, change) -> None:
    path = d / name
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def problems(gateway: str = "config/gateway.yaml", lines: bool = False) -> list[str]:
    """The problems, by default without their 'line N: ' part (the edited files are re-dumped,
    so line numbers are checked by tests of their own)."""
    with pytest.raises(ConfigError) as info:
        load_config(gateway)
    assert str(info.value) == "\n".join(info.value.problems)
    if lines:
        return info.value.problems
    return [re.sub(r"^([^:]+): line \d+: ", r"\1: ", ln) for ln in info.value.problems]


def tag(name):
    return lambda data: data["tags"][name]


CASES = {
    "bad type": ("tags.yaml", lambda d: d["tags"]["T_sink_in"].update(type="int17"),
                 [f"config/tags.yaml: tag 'T_sink_in': key 'type': 'int17' is not one of {TYPES}"]),
    "unknown tag key": ("tags.yaml", lambda d: d["tags"]["p_source_in"].update(byteorder="ABCD"),
                        ["config/tags.yaml: tag 'p_source_in': key 'byteorder': unknown key "
                         f"(did you mean 'byte_order'?); allowed: {TAG_KEYS}"]),
    "missing key": ("tags.yaml", lambda d: d["tags"]["T_c"].pop("unit"),
                    ["config/tags.yaml: tag 'T_c': key 'unit': missing required key"]),
    "address as text": ("tags.yaml", lambda d: d["tags"]["T_suc_LS"].update(address="10"),
                        ["config/tags.yaml: tag 'T_suc_LS': key 'address': expected an integer, got '10'"]),
    "address as bool": ("tags.yaml", lambda d: d["tags"]["T_suc_LS"].update(address=True),
                        ["config/tags.yaml: tag 'T_suc_LS': key 'address': expected an integer, got True"]),
    "address too big": ("tags.yaml", lambda d: d["tags"]["W_HS"].update(address=65535),
                        ["config/tags.yaml: tag 'W_HS': key 'address': float32 at 65535 runs past register 65535"]),
    "bad byte order": ("tags.yaml", lambda d: d["tags"]["p_suc_LS"].update(byte_order="CDBA"),
                       ["config/tags.yaml: tag 'p_suc_LS': key 'byte_order': 'CDBA' is not one of "
                        "ABCD, CDAB, BADC, DCBA"]),
    "byte order on int16": ("tags.yaml", lambda d: d["tags"]["T_e"].update(byte_order="BADC"),
                            ["config/tags.yaml: tag 'T_e': key 'byte_order': 'BADC' is a 32/64-bit "
                             "byte order; a 16-bit int16 takes AB (default, high byte first) or BA "
                             "(bytes swapped)"]),
    "range reversed": ("tags.yaml", lambda d: d["tags"]["T_c"].update(range=[110, 0]),
                       ["config/tags.yaml: tag 'T_c': key 'range': low 110 must be below high 0"]),
    "range empty": ("tags.yaml", lambda d: d["tags"]["T_c"].update(range=[5, 5]),
                    ["config/tags.yaml: tag 'T_c': key 'range': low 5 must be below high 5"]),
    "range shape": ("tags.yaml", lambda d: d["tags"]["T_c"].update(range=[0, "x"]),
                    ["config/tags.yaml: tag 'T_c': key 'range': expected [low, high] (two numbers), "
                     "got [0, 'x']"]),
    "overlap 32-bit": ("tags.yaml", lambda d: d["tags"]["T_e"].update(address=17),
                       ["config/tags.yaml: tag 'T_e': key 'address': registers input 17..17 overlap "
                        "tag 'p_suc_LS' (input 16..17)"]),
    "overlap floats": ("tags.yaml", lambda d: d["tags"]["p_source_out"].update(address=7),
                       ["config/tags.yaml: tag 'p_source_out': key 'address': registers input 7..8 "
                        "overlap tag 'p_source_in' (input 6..7)"]),
    "sentinel too big": ("tags.yaml", lambda d: d["tags"]["V_sink"].update(sentinel=70000),
                         ["config/tags.yaml: tag 'V_sink': key 'sentinel': 70000 is not a raw uint16 "
                          "value (0..65535)"]),
    "pressure kind missing": ("tags.yaml", lambda d: d["tags"]["p_dis_HS"].pop("pressure"),
                              ["config/tags.yaml: tag 'p_dis_HS': key 'pressure': required for a "
                               "pressure tag (unit bar): gauge or absolute"]),
    "pressure on a temperature": ("tags.yaml", lambda d: d["tags"]["T_c"].update(pressure="gauge"),
                                  ["config/tags.yaml: tag 'T_c': key 'pressure': only for pressure "
                                   "units (bar, mbar, Pa, kPa, MPa, psi), unit is 'degC'"]),
    "scale zero": ("tags.yaml", lambda d: d["tags"]["N_LS"].update(scale=0),
                   ["config/tags.yaml: tag 'N_LS': key 'scale': must not be 0"]),
    "max age": ("tags.yaml", lambda d: d["tags"]["N_LS"].update(max_age_s=0),
                ["config/tags.yaml: tag 'N_LS': key 'max_age_s': must be > 0, got 0"]),
    "max age below scan": ("tags.yaml", lambda d: d["tags"]["N_HS"].update(max_age_s=4),
                           ["config/tags.yaml: tag 'N_HS': key 'max_age_s': 4 s is shorter than "
                            "scan_interval_s (5 s) of config/gateway.yaml; the value would always be stale"]),
    "tag name": ("tags.yaml", lambda d: d["tags"].update({"timestamp": d["tags"].pop("cip")}),
                 ["config/tags.yaml: tag 'timestamp': tag names must be identifiers (letters, "
                  "digits, _) and not 'timestamp'"]),
    "advisory field outside": ("gateway.yaml",
                               lambda d: d["advisory"]["fields"]["advice_age_s"].update(offset=64),
                               ["config/gateway.yaml: advisory field 'advice_age_s': key 'offset': "
                                "64 is outside the block (size 64)"]),
    "advisory 32-bit crossing end": ("gateway.yaml",
                                     lambda d: d["advisory"]["fields"]["advice_age_s"].update(offset=63),
                                     ["config/gateway.yaml: advisory field 'advice_age_s': key 'offset': "
                                      "uint32 at offset 63 crosses the block's end (needs offsets "
                                      "63..64, size 64)"]),
    "advisory fields overlap": ("gateway.yaml",
                                lambda d: d["advisory"]["fields"]["dCOP_pct"].update(offset=5),
                                ["config/gateway.yaml: advisory field 'dCOP_pct': key 'offset': "
                                 "offsets 5..6 overlap field 'p_m_sp_rec' (4..5)"]),
    "advisory unknown field key": ("gateway.yaml",
                                   lambda d: d["advisory"]["fields"]["R_th_f"].update(scale=1000),
                                   ["config/gateway.yaml: advisory field 'R_th_f': key 'scale': unknown "
                                    "key; allowed: offset, type, unit, description"]),
    "advisory heartbeat type": ("gateway.yaml",
                                lambda d: d["advisory"]["fields"]["heartbeat"].update(type="int16"),
                                ["config/gateway.yaml: advisory field 'heartbeat': key 'type': must be "
                                 "uint16, got int16"]),
    "advisory on input registers": ("gateway.yaml", lambda d: d["advisory"].update(register="input"),
                                    ["config/gateway.yaml: section 'advisory': key 'register': 'input' "
                                     "registers cannot be written; the block must be holding"]),
    "advisory too big for FC16": ("gateway.yaml", lambda d: d["advisory"].update(size=124),
                                  ["config/gateway.yaml: section 'advisory': key 'size': 124 is "
                                   "outside 1..123"]),
    "status bit 16": ("gateway.yaml", lambda d: d["advisory"]["status_bits"].update({16: "x"}),
                      ["config/gateway.yaml: section 'advisory': key 'status_bits': bit 16 is "
                       "outside 0..15"]),
    "status bit -1": ("gateway.yaml", lambda d: d["advisory"]["status_bits"].update({-1: "x"}),
                      ["config/gateway.yaml: section 'advisory': key 'status_bits': bit -1 is "
                       "outside 0..15"]),
    "status bit name twice": ("gateway.yaml",
                              lambda d: d["advisory"]["status_bits"].update({9: "comm_fault"}),
                              ["config/gateway.yaml: section 'advisory': key 'status_bits': bit 9: "
                               "name 'comm_fault' already used by bit 5"]),
    "scan interval zero": ("gateway.yaml", lambda d: d.update(scan_interval_s=0),
                           ["config/gateway.yaml: top level: key 'scan_interval_s': must be > 0, got 0"]),
    "scan interval text": ("gateway.yaml", lambda d: d.update(scan_interval_s="5 s"),
                           ["config/gateway.yaml: top level: key 'scan_interval_s': expected a finite "
                            "number, got '5 s'"]),
    "unknown top-level key": ("gateway.yaml", lambda d: d.update(scan_interval=5),
                              ["config/gateway.yaml: top level: key 'scan_interval': unknown key (did "
                               f"you mean 'scan_interval_s'?); allowed: {TOP_KEYS}"]),
    "missing section": ("gateway.yaml", lambda d: d.pop("advisory"),
                        ["config/gateway.yaml: top level: key 'advisory': missing required key"]),
    "plc typo": ("gateway.yaml", lambda d: d["plc"].update(hots=d["plc"].pop("host")),
                 ["config/gateway.yaml: section 'plc': key 'hots': unknown key (did you mean 'host'?); "
                  "allowed: host, port, device_id, timeout_s, reconnect_min_s, reconnect_max_s, "
                  "max_read_gap, close_after_poll, pause_between_requests_s",
                  "config/gateway.yaml: section 'plc': key 'host': missing required key"]),
    "plc port": ("gateway.yaml", lambda d: d["plc"].update(port=70000),
                 ["config/gateway.yaml: section 'plc': key 'port': 70000 is outside 1..65535"]),
    "timeout vs scan": ("gateway.yaml", lambda d: d["plc"].update(timeout_s=5.0),
                        ["config/gateway.yaml: section 'plc': key 'timeout_s': 5 s per request must be "
                         "shorter than scan_interval_s (5 s), or one poll cycle could overrun the "
                         "scan interval"]),
    "backoff": ("gateway.yaml", lambda d: d["plc"].update(reconnect_max_s=0.5),
                ["config/gateway.yaml: section 'plc': key 'reconnect_max_s': 0.5 is below "
                 "reconnect_min_s 1"]),
    "optimizer": ("gateway.yaml", lambda d: d.update(optimizer="surrogat"),
                  ["config/gateway.yaml: top level: key 'optimizer': 'surrogat' is not one of model, "
                   "auto, surrogate"]),
    "window too small": ("gateway.yaml", lambda d: d.update(min_window_samples=121),
                         ["config/gateway.yaml: top level: key 'min_window_samples': 121 exceeds the "
                          "120 samples a 2 h window of 60 s samples can hold; calibration would never run"]),
    "life counter": ("gateway.yaml", lambda d: d.update(life_counter_tag="life_cnt"),
                     ["config/gateway.yaml: top level: key 'life_counter_tag': 'life_cnt' is not a tag "
                      "of config/tags.yaml"]),
    "tags file missing": ("gateway.yaml", lambda d: d.update(tags_file="tagz.yaml"),
                          ["config/gateway.yaml: top level: key 'tags_file': file not found: "
                           "config/tagz.yaml"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_exact_error_messages(cfgdir, name):
    file, change, expected = CASES[name]
    edit(cfgdir, file, change)
    assert problems() == expected


def test_advisory_block_overlapping_a_tag(cfgdir):
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["life_counter"].update(address=1010))
    assert problems() == [
        "config/gateway.yaml: section 'advisory': key 'start': block holding 1000..1063 overlaps "
        "tag 'life_counter' (holding 1010..1010) of config/tags.yaml"]


def test_same_address_in_other_register_space_is_fine(cfgdir):
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["p_m_sp"].update(address=0))   # holding 0 vs input 0
    assert load_config("config/gateway.yaml").tag("p_m_sp").address == 0


def test_all_problems_of_all_files_at_once(cfgdir):
    def tags(d):
        d["tags"]["T_sink_in"]["type"] = "int17"
        d["tags"]["T_source_out"]["address"] = 2      # overlaps T_source_in ...
        d["tags"]["T_source_out"]["range"] = [50, -5]  # ... and has another problem
    edit(cfgdir, "tags.yaml", tags)
    edit(cfgdir, "gateway.yaml", lambda d: d.update(scan_interval_s=-1))
    assert problems() == [
        "config/gateway.yaml: top level: key 'scan_interval_s': must be > 0, got -1",
        f"config/tags.yaml: tag 'T_sink_in': key 'type': 'int17' is not one of {TYPES}",
        "config/tags.yaml: tag 'T_source_out': key 'range': low 50 must be below high -5",
        "config/tags.yaml: tag 'T_source_out': key 'address': registers input 2..2 overlap tag "
        "'T_source_in' (input 2..2)",
    ]


def test_duplicate_yaml_keys_are_reported(cfgdir):
    path = cfgdir / "tags.yaml"
    text = path.read_text()
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("T_c:"))
    path.write_text(text + line.replace("address: 14", "address: 40") + "\n")
    first = text.splitlines().index(line) + 1
    last = len(text.splitlines()) + 1
    assert problems(lines=True) == [f"config/tags.yaml: line {last}: duplicate key 'T_c' (first "
                                    f"at line {first}); YAML would silently keep the last"]


def test_yaml_syntax_error(cfgdir):
    (cfgdir / "tags.yaml").write_text("tags:\n  T_c: {register: input, address: 14\n")
    [line] = problems()
    assert line.startswith("config/tags.yaml: line 3 column 1: YAML syntax error:")


def test_missing_and_empty_files(cfgdir, tmp_path):
    (cfgdir / "plant.yaml").unlink()
    assert problems() == ["config/gateway.yaml: top level: key 'plant_file': file not found: "
                          "config/plant.yaml"]
    assert load_config("config/gateway.yaml", load_plant=False).plant is None
    (cfgdir / "plant.yaml").write_text("")
    assert problems() == ["config/plant.yaml: file is empty"]
    with pytest.raises(ConfigError, match="^nowhere.yaml: file not found$"):
        load_config("nowhere.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(ConfigError, match="^list.yaml: top level: expected a mapping of keys, got"):
        load_config("list.yaml")


def test_validation_never_rewrites_the_files(cfgdir):
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["T_c"].update(range=[110, 0]))
    before = {p.name: p.read_bytes() for p in cfgdir.iterdir()}
    problems()
    assert {p.name: p.read_bytes() for p in cfgdir.iterdir()} == before
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["T_c"].update(range=[0, 110]))
    before = {p.name: p.read_bytes() for p in cfgdir.iterdir()}
    load_config("config/gateway.yaml")
    assert {p.name: p.read_bytes() for p in cfgdir.iterdir()} == before


# ---------------------------------------------------------------- check-config and docs

def run_cli(*argv) -> int:
    parser = argparse.ArgumentParser(prog="hp-edge")
    sub = parser.add_subparsers(dest="command", required=True)
    gateway_cmds.register(sub)
    args = parser.parse_args(list(argv))
    return args.func(args)


@pytest.fixture
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("check-config must not touch the network")
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


def test_check_config_prints_the_layout(cfgdir, capsys, no_network):
    assert run_cli("check-config") == 0
    out = capsys.readouterr().out
    assert "FC4 input 0..31 (32 registers): T_sink_in, T_sink_out" in out
    assert "FC3 holding 100..102 (3 registers): plc_clock, life_counter" in out
    assert "FC3 holding 110..111 (2 registers): p_m_sp, closed_loop_enable" in out   # max_read_gap 0
    assert "  p_suc_LS            input    16..17    float32  CDAB   1      0       bar   [-0.9, 25]" in out
    assert "reserved (PLC-owned, never written): holding 0..999" in out
    assert "1028..1029  28      advice_age_s            uint32   s" in out
    assert "the only registers the gateway writes (closed loop off)" in out
    assert "5    0x0020  comm_fault" in out


def test_check_config_reports_problems_and_exits_2(cfgdir, capsys, no_network):
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["T_sink_in"].update(type="int17"))
    assert run_cli("check-config", "--config", "config/gateway.yaml") == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [
        f"config/tags.yaml: line 5: tag 'T_sink_in': key 'type': 'int17' is not one of {TYPES}",
        "1 problem(s); nothing was started."]


def test_docs_register_map_is_true_to_the_yaml():
    cfg = load_config(DEFAULT, load_plant=False)
    doc = (REPO / "docs" / "registers.md").read_text(encoding="utf-8")
    assert doc == gateway_cmds.render_markdown(cfg), (
        "docs/registers.md is out of date: hp-edge check-config --markdown > docs/registers.md")


def test_every_status_bit_is_documented():
    cfg = load_config(DEFAULT, load_plant=False)
    assert {name for _, name in cfg.advisory.status_bits} <= set(gateway_cmds.STATUS_BIT_NOTES)


# ------------------------------------------- issue 9: required tags, reserved, strict YAML

def test_every_missing_required_tag_is_named(cfgdir, capsys, no_network):
    edit(cfgdir, "tags.yaml", lambda d: [d["tags"].pop(n) for n in ("T_c", "W_HS", "p_m_sp",
                                                                     "N_LS", "cip")])
    assert problems() == [   # the optional N_LS and cip may go; the model needs the others
        "config/tags.yaml: tag 'T_c': missing: the model needs it (ammonia at the condenser "
        "outlet, a temperature); add it to the tag map (SPEC §4)",
        "config/tags.yaml: tag 'W_HS': missing: the model needs it (high-stage compressor "
        "electric power, a power); add it to the tag map (SPEC §4)",
        "config/tags.yaml: tag 'p_m_sp': missing: the model needs it (intermediate-pressure set "
        "point, a pressure); add it to the tag map (SPEC §4)",
    ]
    assert run_cli("check-config") == 2
    err = capsys.readouterr().err
    assert "tag 'T_c': missing" in err and "3 problem(s); nothing was started." in err


def test_block_moved_onto_a_plc_register_is_refused_even_without_its_tag(cfgdir):
    # the campaign's case: p_m_sp removed from tags.yaml and the block moved onto 110
    edit(cfgdir, "tags.yaml", lambda d: d["tags"].pop("p_m_sp"))
    edit(cfgdir, "gateway.yaml", lambda d: d["advisory"].update(start=110))
    got = problems()
    assert ("config/gateway.yaml: section 'advisory': key 'start': block holding 110..173 "
            "overlaps reserved holding 0..999 (registers the PLC owns; the gateway writes only "
            "the advisory block)") in got
    # and with the tag present but no reserved list, the tag itself is PLC-owned
    edit(cfgdir, "gateway.yaml", lambda d: d.update(reserved=[]))
    shutil.copy(REPO / "config" / "tags.yaml", cfgdir)
    assert problems() == [
        "config/gateway.yaml: section 'advisory': key 'start': block holding 110..173 overlaps "
        "tag 'p_m_sp' (holding 110..110) of config/tags.yaml",
        "config/gateway.yaml: section 'advisory': key 'start': block holding 110..173 overlaps "
        "tag 'closed_loop_enable' (holding 111..111) of config/tags.yaml"]


@pytest.mark.parametrize("change, expected", [
    (lambda d: d.pop("reserved"),
     "config/gateway.yaml: top level: key 'reserved': missing required key"),
    (lambda d: d.update(reserved=[{"register": "holding", "first": 5, "last": 2}]),
     "config/gateway.yaml: reserved[0]: key 'last': 2 is below first 5"),
    (lambda d: d["plc"].update(device_id=0),
     "config/gateway.yaml: section 'plc': key 'device_id': 0 is the broadcast address: devices "
     "do not answer it and all of them obey its writes; use 1..255"),
    (lambda d: d["advisory"].pop("status_bits"),
     "config/gateway.yaml: section 'advisory': key 'status_bits': missing required key"),
    (lambda d: d["advisory"].update(status_bits={}),
     "config/gateway.yaml: section 'advisory': key 'status_bits': expected a mapping of bit "
     "number (0..15) -> name; without it the status word would always read 0"),
    (lambda d: d["plc"].update(pause_between_requests_s=2),
     "config/gateway.yaml: section 'plc': key 'pause_between_requests_s': 2 s is not below a "
     "quarter of scan_interval_s (5 s); a poll cycle would not fit"),
])
def test_write_range_and_device_rules(cfgdir, change, expected):
    edit(cfgdir, "gateway.yaml", change)
    assert problems() == [expected]


def test_tag_device_id_zero_is_refused(cfgdir):
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["W_LS"].update(device_id=0))
    assert problems() == [
        "config/tags.yaml: tag 'W_LS': key 'device_id': 0 is the broadcast address: devices do "
        "not answer it and all of them obey its writes; use 1..255"]


def test_unknown_keys_name_their_line(cfgdir):
    path = cfgdir / "tags.yaml"
    lines = path.read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.lstrip().startswith("T_c:"))
    lines[at] = lines[at].replace("unit: degC", "unit: degC, colour: red")
    path.write_text("\n".join(lines) + "\n")
    assert problems(lines=True) == [
        f"config/tags.yaml: line {at + 1}: tag 'T_c': key 'colour': unknown key; allowed: "
        f"{TAG_KEYS}"]


# ------------------------------------------------------------------- plant.yaml, strictly

def test_plant_yaml_unknown_keys_are_refused_everywhere(cfgdir, capsys):
    path = cfgdir / "plant.yaml"
    text = path.read_text().replace("R_th_f_K_per_kW: 0.0", "R_th_f_K_per_kw: 0.0", 1)
    path.write_text(text)
    line = next(i + 1 for i, ln in enumerate(text.splitlines()) if "R_th_f_K_per_kw" in ln)
    expected = (f"config/plant.yaml: line {line}: section 'calibrated': key 'R_th_f_K_per_kw': "
                "unknown key (did you mean 'R_th_f_K_per_kW'?); allowed: CF_DSH, CF_con, CF_SC, "
                "CF_eva, R_th_f_K_per_kW, CF_dp_f")
    assert problems(lines=True) == [expected]
    from edge.cli import main
    with pytest.raises(SystemExit) as info:      # the model commands use the same checker
        main(["point", "--config", str(path)])
    assert info.value.code == 2
    assert capsys.readouterr().err.splitlines() == [f"hp-edge: {expected}"]


def test_point_with_duplicate_plant_keys_exits_2(cfgdir, capsys):
    """The campaign's case: a duplicated key took the last value and printed T_e -497.65 degC."""
    path = cfgdir / "plant.yaml"
    text = path.read_text()
    text = text.replace("  A_m2: 91.96", "  A_m2: 91.96\n  A_m2: 0.0001", 1)
    path.write_text(text)
    line = next(i + 1 for i, ln in enumerate(text.splitlines()) if "A_m2: 0.0001" in ln)
    from edge.cli import main
    with pytest.raises(SystemExit) as info:
        main(["point", "--config", str(path)])
    assert info.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [
        f"hp-edge: config/plant.yaml: line {line}: duplicate key 'A_m2' (first at line "
        f"{line - 1}); YAML would silently keep the last"]


def test_plant_values_are_checked_at_load(cfgdir):
    edit(cfgdir, "plant.yaml", lambda d: (d["evaporator"].update(U_W_per_m2K="3000"),
                                         d["calibration"]["initial"]["limits"].update(
                                             max_objective_pct=-1)))
    assert problems() == [
        "config/plant.yaml: key 'evaporator.U_W_per_m2K': expected a number, got '3000'"]
    edit(cfgdir, "plant.yaml", lambda d: d["evaporator"].update(U_W_per_m2K=3000))
    assert problems() == ["config/plant.yaml: key 'calibration.initial.limits.max_objective_pct': "
                          "expected a number > 0, got -1"]


def test_plant_schema_matches_its_readers():
    """PLANT_SCHEMA is the one list of plant.yaml's keys; it must agree with what the readers
    accept, or a valid key would be refused (or an invalid one slip through)."""
    from edge.plantfile import PLANT_SCHEMA
    from model.calibration import CalibrationError, spec_from_config
    from model.analysis.replay import ReplaySettings
    from model.surrogate import DEFAULT_DESIGN

    assert set(PLANT_SCHEMA["surrogate"]) == set(DEFAULT_DESIGN)
    assert set(PLANT_SCHEMA["calibration"]["replay"]) == set(ReplaySettings.__dataclass_fields__)
    for kind in ("initial", "fouling"):
        for key in PLANT_SCHEMA["calibration"][kind]:
            try:
                spec_from_config({"calibration": {kind: {key: None}}}, kind)
            except CalibrationError as exc:
                assert "unknown" not in str(exc), (kind, key, exc)
            except (TypeError, ValueError):
                pass   # known key, bad value: what matters is that it is known
    shipped = yaml.safe_load((REPO / "config" / "plant.yaml").read_text())

    def walk(doc, schema, path=""):
        for k, v in doc.items():
            assert k in schema, f"{path}{k} is in plant.yaml but not in PLANT_SCHEMA"
            if isinstance(schema[k], dict) and isinstance(v, dict):
                walk(v, schema[k], f"{path}{k}.")
    walk(shipped, PLANT_SCHEMA)


# ------------------------------------------------ hostile YAML: bounded in memory and time

def _load_problems(path: Path) -> list[str]:
    import tracemalloc
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError) as info:
            load_config(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, f"loading took {peak / 1e6:.1f} MB"
    return info.value.problems


def test_alias_bomb_is_refused_without_expanding(cfgdir):
    bomb = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    bomb += [f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
             f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
             f"*{chr(97 + i)}]" for i in range(8)]      # 9^9 = 387 million leaves if expanded
    (cfgdir / "gateway.yaml").write_text("\n".join(bomb) + "\n")
    assert _load_problems(cfgdir / "gateway.yaml") == [
        "config/gateway.yaml: line 1 column 4: anchor '&a': anchors and aliases are not allowed "
        "in hp-edge configuration files; write the value out"]


@pytest.mark.parametrize("text, expected", [
    ("plc:" + " [" * 500 + " ]" * 500 + "\n",
     "config/gateway.yaml: line 1 column 44: nested deeper than 20 levels"),
    ("plc: {host: a\x00b}\n",
     "config/gateway.yaml: line 1: unacceptable character #x0000: special characters are not "
     "allowed"),
    ("scan_interval_s: " + "9" * 5000 + "\n",
     "config/gateway.yaml: line 1 column 18: cannot read the value: Exceeds the limit (4300 "
     "digits) for integer string conversion: value has 5000 digits; use "
     "sys.set_int_max_str_digits() to increase the limit"),
    ("start: 2024-02-30\n", "config/gateway.yaml: line 1 column 8: cannot read the value: day "
     "is out of range for month"),
    ("? [a, b]\n: 1\n", "config/gateway.yaml: line 1 column 3: a mapping key must be a plain "
     "value, not a list or mapping"),
])
def test_hostile_yaml_gets_one_line(cfgdir, text, expected):
    (cfgdir / "gateway.yaml").write_text(text)
    assert _load_problems(cfgdir / "gateway.yaml") == [expected]


def test_binary_and_huge_files(cfgdir):
    (cfgdir / "gateway.yaml").write_bytes(b"plc: \xff\xfe\n")
    assert _load_problems(cfgdir / "gateway.yaml") == [
        "config/gateway.yaml: not UTF-8 text (byte 0xff at offset 5)"]
    (cfgdir / "gateway.yaml").write_text("# " + "x" * 1_000_001 + "\n")
    assert _load_problems(cfgdir / "gateway.yaml") == [
        "config/gateway.yaml: file is larger than 1000000 bytes; configuration files are a few KB"]


def test_huge_numbers_are_problems_not_tracebacks(cfgdir):
    edit(cfgdir, "gateway.yaml", lambda d: d.update(scan_interval_s=10**400))
    [line] = problems()
    assert line.startswith("config/gateway.yaml: top level: key 'scan_interval_s': expected a "
                           "finite number, got 1000000000000")
    assert len(line) < 200


def test_problem_output_is_bounded(cfgdir, capsys, no_network):
    edit(cfgdir, "gateway.yaml", lambda d: d.update({f"junk{i}": "y" * 1000 for i in range(400)}))
    assert run_cli("check-config") == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 52 and err[-2] == "... and 350 more problem(s)"
    assert err[-1] == "400 problem(s); nothing was started."
    assert max(len(ln) for ln in err) <= 300


@pytest.mark.parametrize("file, change, expected", [
    ("gateway.yaml", lambda d: d["advisory"]["fields"]["p_m_gm"].pop("offset"),
     "config/gateway.yaml: advisory field 'p_m_gm': key 'offset': missing required key"),
    ("gateway.yaml", lambda d: d["advisory"]["fields"]["p_m_gm"].pop("type"),
     "config/gateway.yaml: advisory field 'p_m_gm': key 'type': missing required key"),
    ("gateway.yaml", lambda d: d["advisory"].pop("start"),
     "config/gateway.yaml: section 'advisory': key 'start': missing required key"),
    ("gateway.yaml", lambda d: d["advisory"].pop("size"),
     "config/gateway.yaml: section 'advisory': key 'size': missing required key"),
    ("tags.yaml", lambda d: d["tags"]["T_c"].pop("max_age_s"),
     "config/tags.yaml: tag 'T_c': key 'max_age_s': missing required key"),
    ("gateway.yaml", lambda d: d["plc"].pop("host"),
     "config/gateway.yaml: section 'plc': key 'host': missing required key"),
])
def test_campaign_tracebacks_are_one_line_and_exit_2(cfgdir, capsys, no_network, file, change,
                                                      expected):
    """The campaign's 26 tracebacks: a missing key left a half-built object behind."""
    edit(cfgdir, file, change)
    assert run_cli("check-config") == 2
    err = capsys.readouterr().err.splitlines()
    assert [re.sub(r"^([^:]+): line \d+: ", r"\1: ", ln) for ln in err] == [
        expected, "1 problem(s); nothing was started."]


def test_a_path_too_long_for_the_file_system_is_a_problem(cfgdir):
    edit(cfgdir, "gateway.yaml", lambda d: d.update(tags_file="y" * 5000))
    assert problems() == ["config/gateway.yaml: top level: key 'tags_file': not a usable path: "
                          "File name too long"]


def test_plant_schema_knows_every_setting_of_the_analysis_sections():
    """Every key the analysis settings accept is a key plant.yaml's schema accepts (a key missing
    from the schema would be refused as unknown before the settings see it)."""
    from dataclasses import fields

    from edge.plantfile import PLANT_SCHEMA
    from model.analysis.advice import AdviceSettings
    from model.analysis.compressors import LearningSettings
    from model.analysis.replay import ReplaySettings
    from model.analysis.surrogate_tracker import TrackerSettings
    for section, cls in (("advice", AdviceSettings), ("compressor_learning", LearningSettings),
                         ("surrogate_tracker", TrackerSettings)):
        assert set(PLANT_SCHEMA[section]) == {f.name for f in fields(cls)}, section
    assert set(PLANT_SCHEMA["calibration"]["replay"]) == {f.name for f in fields(ReplaySettings)}


def test_overlapping_tags_name_the_line_of_the_address(cfgdir):
    """An overlap names the line of the overlapping tag's address key, as every other problem."""
    edit(cfgdir, "tags.yaml", lambda d: d["tags"]["T_sink_out"].update(address=d["tags"]["T_sink_in"]["address"]))
    text = (cfgdir / "tags.yaml").read_text().splitlines()
    start = text.index("  T_sink_out:")
    line = next(i for i in range(start, len(text)) if text[i].strip().startswith("address:")) + 1
    assert problems(lines=True) == [
        f"config/tags.yaml: line {line}: tag 'T_sink_out': key 'address': registers input 0..0 overlap "
        "tag 'T_sink_in' (input 0..0)"]
