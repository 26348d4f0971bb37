"""Northbound without a broker (issue 14): the configuration section, the metric table, the outbox
in the history database, the Sparkplug B payloads, the health endpoint's text, the loop's observer
hook, and that the daemon does not import the MQTT libraries unless the publisher is enabled.

The tests against a real broker are in test_northbound_broker.py.
"""
from __future__ import annotations

import re

import asyncio
import json
import math
import shutil
import sqlite3
import subprocess
import sys
import urllib.error
import urllib.request
from dataclasses import replace
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from prometheus_client.parser import text_string_to_metric_families

from edge.cli import main as cli_main
from edge.config import ConfigError, load_config
from edge.health import HealthServer, _kind
from edge.loop import Advice, CycleEvent, Gateway, Snapshot
from edge.northbound import sparkplug
from edge.northbound.config import HealthConfig, MqttConfig
from edge.northbound.metrics import (ADVICE_METRICS, DATATYPES, Catalog, MetricSpec,
                                     build_catalog, catalog_for, typed)
from edge.northbound.outbox import OUTBOX, TRIGGERS, Outbox, detach
from edge.plc import ReadResult, TagValue
from edge.store import HistoryStore
from test_loop import FakeAdvisor, FakePlc

ROOT = Path(__file__).resolve().parent.parent
CFG = load_config(ROOT / "config" / "gateway.yaml", load_plant=False)
T0 = 1_709_251_200


def run(coro, timeout: float = 20.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


# ------------------------------------------------------------------------------ configuration


@pytest.fixture
def confdir(tmp_path, monkeypatch) -> Path:
    """A copy of config/ whose gateway.yaml the test extends (messages name it relative to
    the working directory, tmp_path)."""
    monkeypatch.chdir(tmp_path)
    d = tmp_path / "config"
    shutil.copytree(ROOT / "config", d)
    return d


def write_northbound(confdir: Path, section) -> Path:
    path = confdir / "gateway.yaml"
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    doc["northbound"] = section
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def problems(path: Path) -> list[str]:
    """The problems without their YAML line numbers (edge.yamlfile adds 'line N: ' after the file
    name; the lines of this generated file are not what these tests are about)."""
    with pytest.raises(ConfigError) as exc:
        load_config(path, load_plant=False)
    return [re.sub(r"^(config/gateway\.yaml: )line \d+: ", r"\1", p) for p in exc.value.problems]


def test_shipped_config_has_no_northbound_and_everything_is_off():
    assert CFG.northbound is None


def test_a_full_northbound_section_is_parsed_with_the_password_from_a_file(confdir):
    (confdir / "mqtt.pass").write_text("s3cret\nignored\n", encoding="utf-8")
    (confdir / "ca.pem").write_text("not checked here\n", encoding="utf-8")
    path = write_northbound(confdir, {
        "mqtt": {"enabled": True, "mode": "json", "host": "broker.local", "port": 8883,
                 "group_id": "plants", "edge_node_id": "copenhagen-1", "qos": 0,
                 "username": "hp", "password_file": "mqtt.pass", "tls": {"ca_file": "ca.pem"}},
        "health": {"enabled": True, "bind": "0.0.0.0", "port": 9200}})
    nb = load_config(path, load_plant=False).northbound
    m = nb.mqtt
    assert (m.enabled, m.mode, m.host, m.port, m.qos) == (True, "json", "broker.local", 8883, 0)
    assert (m.group_id, m.edge_node_id, m.effective_client_id) == (
        "plants", "copenhagen-1", "hp-edge-plants-copenhagen-1")
    assert m.username == "hp" and m.password == "s3cret"
    assert m.password_source == f"file {(confdir / 'mqtt.pass').resolve()}"
    assert "s3cret" not in repr(nb)
    assert m.tls.ca_file == (confdir / "ca.pem").resolve() and m.tls.cert_file is None
    assert nb.health == HealthConfig(enabled=True, bind="0.0.0.0", port=9200)
    assert nb.mqtt_enabled and nb.health_enabled


def test_password_from_the_environment_and_a_missing_variable_is_named(confdir, monkeypatch):
    path = write_northbound(confdir, {"mqtt": {"enabled": True, "username": "hp",
                                               "password_env": "HP_EDGE_TEST_MQTT_PW"}})
    monkeypatch.setenv("HP_EDGE_TEST_MQTT_PW", "from-env")
    assert load_config(path, load_plant=False).northbound.mqtt.password == "from-env"
    monkeypatch.delenv("HP_EDGE_TEST_MQTT_PW")
    assert problems(path) == [
        "config/gateway.yaml: section 'northbound.mqtt': key 'password_env': the environment "
        "variable HP_EDGE_TEST_MQTT_PW is not set (or empty)"]


def test_a_disabled_publisher_does_not_need_its_secret(confdir, monkeypatch):
    monkeypatch.delenv("HP_EDGE_TEST_MQTT_PW", raising=False)
    path = write_northbound(confdir, {"mqtt": {"enabled": False, "username": "hp",
                                               "password_env": "HP_EDGE_TEST_MQTT_PW"}})
    nb = load_config(path, load_plant=False).northbound
    assert not nb.mqtt_enabled and nb.mqtt.password is None


def test_bad_northbound_keys_are_named_one_line_each(confdir):
    path = write_northbound(confdir, {
        "mqtt": {"enabled": "yes", "mode": "mqtt", "port": 70000, "group_id": "a/b", "qos": 2,
                 "reconnect_min_s": 10, "reconnect_max_s": 1, "tls": {"cert_file": "nope.pem"},
                 "pasword_file": "x"},
        "health": {"enabled": True, "port": -1}, "prometheus": {}})
    assert problems(path) == [
        "config/gateway.yaml: section 'northbound': key 'prometheus': unknown key; allowed: "
        "mqtt, health",
        "config/gateway.yaml: section 'northbound.mqtt': key 'pasword_file': unknown key (did "
        "you mean 'password_file'?); allowed: enabled, mode, host, port, group_id, "
        "edge_node_id, client_id, topic_prefix, qos, keepalive_s, reconnect_min_s, "
        "reconnect_max_s, max_backlog_rows, username, password_file, password_env, tls",
        "config/gateway.yaml: section 'northbound.mqtt': key 'enabled': expected true or false, "
        "got 'yes'",
        "config/gateway.yaml: section 'northbound.mqtt': key 'mode': 'mqtt' is not one of "
        "sparkplug, json",
        "config/gateway.yaml: section 'northbound.mqtt': key 'port': 70000 is outside 1..65535",
        "config/gateway.yaml: section 'northbound.mqtt': key 'group_id': 'a/b' must not contain "
        "/ + # (MQTT topic levels and wildcards)",
        "config/gateway.yaml: section 'northbound.mqtt': key 'qos': 2 is outside 0..1",
        "config/gateway.yaml: section 'northbound.mqtt': key 'reconnect_max_s': 1 is below "
        "reconnect_min_s 10",
        "config/gateway.yaml: section 'northbound.mqtt.tls': key 'cert_file': file not found: "
        "config/nope.pem",
        "config/gateway.yaml: section 'northbound.mqtt.tls': key 'key_file': a client "
        "certificate needs both cert_file and key_file",
        "config/gateway.yaml: section 'northbound.health': key 'port': -1 is outside 0..65535"]


def test_check_config_exits_2_on_a_bad_northbound_section(confdir, capsys):
    path = write_northbound(confdir, {"health": {"enabled": True, "bind": 127}})
    assert cli_main(["check-config", "--config", str(path)]) == 2
    err = re.sub(r"line \d+: ", "", capsys.readouterr().err)
    assert ("config/gateway.yaml: section 'northbound.health': key 'bind': expected a "
            "non-empty string, got 127") in err


def test_an_empty_northbound_section_means_everything_off(confdir):
    path = write_northbound(confdir, None)
    nb = load_config(path, load_plant=False).northbound
    assert nb is not None and not nb.mqtt_enabled and not nb.health_enabled


# ------------------------------------------------------------------------------ metric table


def test_catalog_takes_names_and_units_from_the_tag_map_and_the_advisory_block():
    cat = catalog_for(CFG)
    names = [m.name for m in cat.metrics]
    assert len(set(names)) == len(names)
    assert [cat.alias(m) for m in cat.metrics] == list(range(1, len(names) + 1))
    tin = cat.by_name("Sample/T_source_in")
    assert (tin.datatype, tin.unit, tin.source, tin.key) == ("Double", "degC", "sample",
                                                             "T_source_in")
    assert cat.by_name("Sample/p_suc_LS").unit == CFG.tag("p_suc_LS").unit
    rec = cat.by_name("Advisory/p_m_sp_rec")
    assert (rec.unit, rec.source) == ("bar(g)", "advice")
    assert "Advisory/heartbeat" not in names and "Advisory/advice_age_s" not in names
    assert [m.name for m in cat.by_source("status")] == (
        [f"Status/{n}" for _, n in sorted(CFG.advisory.status_bits)] + ["Status/word"])


def test_adding_a_metric_is_one_line_of_the_table():
    extra = MetricSpec("Forecast/days_to_clean", "Double", "d", "advice",
                       "detail.cip.days_to_clean")
    base = catalog_for(CFG)
    cat = Catalog(base.metrics + (extra,))
    row = {"ts": T0, "detail": json.dumps({"cip": {"days_to_clean": 12.5}})}
    assert cat.values("advice", row)[extra] == 12.5
    assert cat.alias(extra) == len(base.metrics) + 1


def test_values_are_typed_and_nan_or_absent_give_null_or_nothing():
    cat = catalog_for(CFG)
    row = {"ts": T0, "T_source_in": 24.5, "T_sink_in": float("nan"), "usable": 1,
           "reason": "", "scans": 12.0, "detail": "{}"}
    vals = {m.name: v for m, v in cat.values("sample", row).items()}
    assert vals["Sample/T_source_in"] == 24.5
    assert vals["Sample/T_sink_in"] is None                 # NaN -> null
    assert vals["Sample/usable"] is True and vals["Sample/reason"] == ""
    assert vals["Sample/scans"] == 12 and isinstance(vals["Sample/scans"], int)
    assert "Sample/T_source_out" not in vals                 # not in the row: not published
    adv = {"ts": T0, "p_m_sp_rec": 15.5, "ok": 1, "message": "fine",
           "detail": json.dumps({"run_time_s": 0.25, "window": {"R_th_f_se_K_per_kW": 1e-5}})}
    vals = {m.name: v for m, v in cat.values("advice", adv).items()}
    assert vals["Advisory/p_m_sp_rec"] == 15.5 and vals["Calibration/ok"] is True
    assert vals["Calibration/run_time"] == 0.25 and vals["Calibration/R_th_f_se"] == 1e-5
    assert "Calibration/iterations" not in vals              # path absent in this detail
    assert typed("Double", float("inf")) is None and typed("UInt16", 5.0) == 5


def test_every_table_entry_names_a_known_datatype_and_a_detail_path_or_column():
    for spec in ADVICE_METRICS:
        assert spec.datatype in DATATYPES and spec.source == "advice"
    with pytest.raises(ValueError, match="unknown datatype 'Float64'"):
        MetricSpec("X/y", "Float64", "", "sample", "y")
    with pytest.raises(ValueError, match="^metric names used twice: Sample/T_c$"):
        build_catalog(CFG.tags + (CFG.tag("T_c"),), (), ())


# ------------------------------------------------------------------------------------ outbox


def store_with_outbox(path: Path, **kw) -> tuple[HistoryStore, Outbox]:
    store = HistoryStore(path, 400).open()
    return store, Outbox(path, **kw).open()


def test_every_stored_row_is_queued_in_store_order_and_a_conflict_is_not(tmp_path):
    store, ob = store_with_outbox(tmp_path / "h.sqlite")
    store.add_samples([{"ts": T0 + 60, "T_c": 60.0}, {"ts": T0 + 120, "T_c": 61.0}])
    store.add_advice(T0 + 120, {"p_m_sp_rec": 15.0, "ok": True, "detail": {"a": 1}})
    store.add_samples([{"ts": T0 + 60, "T_c": 99.0}])            # taken: goes to conflicts
    store.add_samples([{"ts": T0, "T_c": 59.0}])                 # clock set back: queued last
    got = ob.fetch(0, 100)
    assert [(e.source, e.ts) for e in got] == [("sample", T0 + 60), ("sample", T0 + 120),
                                               ("advice", T0 + 120), ("sample", T0)]
    assert [e.row["T_c"] for e in got if e.source == "sample"] == [60.0, 61.0, 59.0]
    assert json.loads(got[2].row["detail"]) == {"a": 1}
    assert ob.ack(got[1].id) == 2
    assert [e.ts for e in ob.fetch(0, 100)] == [T0 + 120, T0]
    assert ob.depth() == 2
    store.close()
    ob.close()
    # a restart: the queue is still there, and the triggers still queue
    store, ob = store_with_outbox(tmp_path / "h.sqlite")
    store.add_samples([{"ts": T0 + 180, "T_c": 62.0}])
    assert [e.ts for e in ob.fetch(0, 100)] == [T0 + 120, T0, T0 + 180]
    store.close()
    ob.close()


def test_rows_waiting_in_memory_while_the_history_is_locked_are_queued_when_written(tmp_path):
    path = tmp_path / "h.sqlite"
    store, ob = store_with_outbox(path)
    blocker = sqlite3.connect(path, isolation_level=None)
    blocker.execute("BEGIN IMMEDIATE")                           # another process holds the lock
    store.busy_timeout_s = 0.05
    store.db.execute("PRAGMA busy_timeout = 50")
    assert store.add_samples([{"ts": T0, "T_c": 60.0}]) == 0
    assert store.fault is not None and store.pending == 1
    blocker.execute("ROLLBACK")
    blocker.close()
    store._retry_at = -math.inf
    assert store.add_samples([{"ts": T0 + 60, "T_c": 61.0}]) == 2
    assert [e.ts for e in ob.fetch(0, 10)] == [T0, T0 + 60]
    store.close()
    ob.close()


def test_the_backlog_is_bounded_oldest_first(tmp_path):
    store, ob = store_with_outbox(tmp_path / "h.sqlite", max_rows=100)
    store.add_samples([{"ts": T0 + 60 * i, "T_c": 60.0} for i in range(300)])
    got = ob.fetch(0, 1000)
    assert 100 <= len(got) < 100 + 64
    assert got[-1].ts == T0 + 60 * 299
    assert [e.ts for e in got] == sorted(e.ts for e in got)
    store.close()
    ob.close()


def test_a_pruned_row_comes_back_as_none_and_detach_removes_everything(tmp_path):
    path = tmp_path / "h.sqlite"
    store, ob = store_with_outbox(path)
    store.add_samples([{"ts": T0, "T_c": 60.0}])
    store.db.execute("DELETE FROM samples")
    assert [(e.ts, e.row) for e in ob.fetch(0, 10)] == [(T0, None)]
    ob.close()
    assert detach(path) is True
    names = {r[0] for r in store.db.execute("SELECT name FROM sqlite_master")}
    assert not names & set(TRIGGERS + (OUTBOX,))
    store.add_samples([{"ts": T0 + 60, "T_c": 60.0}])             # no trigger, no error
    assert store.count() == 1
    assert detach(path) is False                                  # nothing left to drop
    store.close()


@settings(max_examples=40, deadline=None)
@given(st.lists(st.one_of(st.tuples(st.just("add"), st.integers(1, 5)),
                          st.tuples(st.just("ack"), st.integers(0, 6))), max_size=25))
def test_outbox_returns_exactly_the_unacknowledged_rows_in_order(tmp_path_factory, ops):
    path = tmp_path_factory.mktemp("ob") / "h.sqlite"
    store, ob = store_with_outbox(path)
    ts, waiting = T0, []
    for op, n in ops:
        if op == "add":
            rows = [{"ts": ts + 60 * i, "T_c": 1.0} for i in range(n)]
            ts += 60 * n
            store.add_samples(rows)
            waiting += [r["ts"] for r in rows]
        else:
            got = ob.fetch(0, n)
            if got:
                ob.ack(got[-1].id)
            waiting = waiting[len(got):]
    assert [e.ts for e in ob.fetch(0, 10_000)] == waiting
    assert ob.depth() == len(waiting)
    store.close()
    ob.close()


# --------------------------------------------------------------------------------- sparkplug


def test_birth_carries_every_metric_with_alias_datatype_unit_and_value():
    cat = catalog_for(CFG)
    raw = sparkplug.encode_birth(cat, {"Sample/T_source_in": 24.5, "Status/data_stale": True,
                                       "Sample/reason": "ramp"},
                                 seq=0, bd_seq=7, timestamp_ms=1000,
                                 metric_ts_ms={"Sample/T_source_in": 500})
    p = sparkplug.Payload.FromString(raw)
    assert p.seq == 0 and p.timestamp == 1000
    assert (p.metrics[0].name, p.metrics[0].long_value, p.metrics[0].datatype) == ("bdSeq", 7, 4)
    assert (p.metrics[1].name, p.metrics[1].boolean_value) == ("Node Control/Rebirth", False)
    by = {m.name: m for m in p.metrics[2:]}
    assert list(by) == [m.name for m in cat.metrics]
    t = by["Sample/T_source_in"]
    assert (t.alias, t.datatype, t.double_value, t.timestamp) == (
        cat.alias(cat.by_name("Sample/T_source_in")), 10, 24.5, 500)
    assert list(t.properties.keys) == ["engUnit"]
    assert t.properties.values[0].string_value == "degC" and t.properties.values[0].type == 12
    assert by["Status/data_stale"].boolean_value is True
    assert by["Sample/reason"].string_value == "ramp"
    assert by["Sample/T_sink_in"].is_null and by["Sample/T_sink_in"].timestamp == 1000
    assert len(by["Status/heat_pump_off"].properties.keys) == 0     # no unit, no property


def test_data_uses_aliases_only_with_is_historical_and_death_carries_bdseq():
    cat = catalog_for(CFG)
    spec = cat.by_name("Advisory/R_th_f")
    p = sparkplug.Payload.FromString(sparkplug.encode_data(
        cat, [(spec, 2.5e-3), (cat.by_name("Calibration/message"), None)], seq=255,
        timestamp_ms=9, metric_ts_ms=T0 * 1000, historical=True))
    assert p.seq == 255 and len(p.metrics) == 2
    m = p.metrics[0]
    assert (m.name, m.alias, m.datatype, m.double_value, m.is_historical, m.timestamp) == (
        "", cat.alias(spec), 0, 2.5e-3, True, T0 * 1000)
    assert p.metrics[1].is_null
    d = sparkplug.Payload.FromString(sparkplug.encode_death(bd_seq=3, timestamp_ms=5))
    assert [(x.name, x.long_value) for x in d.metrics] == [("bdSeq", 3)]
    assert sparkplug.topic("g", "NDATA", "n") == "spBv1.0/g/NDATA/n"


def test_rebirth_request_is_recognised_and_garbage_is_refused():
    p = sparkplug.Payload(timestamp=1)
    p.metrics.add(name="Node Control/Rebirth", datatype=11, boolean_value=True)
    assert sparkplug.wants_rebirth(p.SerializeToString())
    p.metrics[0].boolean_value = False
    assert not sparkplug.wants_rebirth(p.SerializeToString())
    with pytest.raises(ValueError, match="not a Sparkplug B payload"):
        sparkplug.wants_rebirth(b"\xff\xff\xff")


# ------------------------------------------------------------------------------------ health


def result(comm_error=None, bad=None) -> ReadResult:
    vals = {t.name: TagValue(t.name, 1.0) for t in CFG.tags}
    for name, reason in (bad or {}).items():
        vals[name] = TagValue(name, None, reason)
    if comm_error:
        vals = {t.name: TagValue(t.name, None, comm_error) for t in CFG.tags}
    return ReadResult(vals, 0.0, 0.01, 2, comm_error)


class _Gw:
    """What the health server reads of a gateway."""
    def __init__(self):
        self.cfg, self.snapshot, self.now = CFG, Snapshot(), 100.0

    def monotonic(self):
        return self.now


def families(text: str) -> dict:
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def test_health_text_parses_and_counts_what_the_cycles_did():
    h = HealthServer(HealthConfig(enabled=True, port=0))
    gw = _Gw()
    h._gw = gw
    f = families(h.render())
    assert f[("hp_edge_last_successful_poll_age_seconds", ())] == math.inf
    snap = gw.snapshot
    snap.writes_ok, snap.writes_failed, snap.heartbeat = 7, 2, 9
    snap.values = {"p_m_sp_rec": 15.5, "R_th_f": 2.5e-3}
    snap.status_bits = ("data_stale", "comm_fault")
    h.cycle(CycleEvent(snap, result(bad={"T_c": "out of range [0, 80]",
                                         "T_e": "modbus exception 2"}),
                       rows=({"ts": T0},), duration_s=0.25, t_mono=90.0))
    h.cycle(CycleEvent(snap, result(comm_error="timeout"), duration_s=0.75, t_mono=95.0,
                       advice=Advice(T0, {"R_th_f": 1e-3}), calibration_s=1.5))
    h.cycle(CycleEvent(snap, result(), duration_s=0.5, t_mono=96.0,
                       advice=Advice(T0, skipped=True), calibration_s=0.01))
    f = families(h.render())
    assert f[("hp_edge_scans_total", ())] == 3
    assert f[("hp_edge_scan_duration_seconds_sum", ())] == 1.5
    assert f[("hp_edge_scan_duration_seconds_count", ())] == 3
    assert f[("hp_edge_scan_duration_last_seconds", ())] == 0.5
    assert f[("hp_edge_poll_errors_total", (("kind", "timeout"),))] == 1
    assert f[("hp_edge_poll_errors_total", (("kind", "modbus_exception"),))] == 1
    assert f[("hp_edge_tag_errors_total", (("reason", "out_of_range"),))] == 1
    assert f[("hp_edge_tag_errors_total", (("reason", "modbus_exception"),))] == 1
    assert ("hp_edge_tag_errors_total", (("reason", "timeout"),)) not in f   # a comm error
    assert f[("hp_edge_last_successful_poll_age_seconds", ())] == 4.0         # 100 - 96
    assert f[("hp_edge_samples_total", ())] == 1
    assert f[("hp_edge_calibrations_total", (("outcome", "ok"),))] == 1
    assert f[("hp_edge_calibrations_total", (("outcome", "skipped"),))] == 1
    assert f[("hp_edge_calibration_duration_seconds_sum", ())] == 1.5
    assert f[("hp_edge_calibration_duration_seconds_count", ())] == 1
    assert f[("hp_edge_advisory_writes_total", (("result", "ok"),))] == 7
    assert f[("hp_edge_advisory_writes_total", (("result", "failed"),))] == 2
    assert f[("hp_edge_advisory_value", (("field", "p_m_sp_rec"), ("unit", "bar(g)")))] == 15.5
    assert math.isnan(f[("hp_edge_advisory_value", (("field", "dCOP_pct"), ("unit", "%")))])
    assert f[("hp_edge_status_word", ())] == 0x0021
    assert f[("hp_edge_status_bit", (("bit", "5"), ("name", "comm_fault")))] == 1
    assert f[("hp_edge_status_bit", (("bit", "1"), ("name", "heat_pump_off")))] == 0
    assert ("hp_edge_mqtt_connected", ()) not in f                  # no publisher


def test_health_shows_the_publisher_and_escapes_labels():
    class Pub:
        connected, queue_depth, published, historical, dropped, cpu_s = True, 12, 30, 10, 0, 0.5
    h = HealthServer(HealthConfig(enabled=True), publisher=Pub())
    f = families(h.render())
    assert f[("hp_edge_mqtt_connected", ())] == 1 and f[("hp_edge_mqtt_queue_depth", ())] == 12
    assert f[("hp_edge_mqtt_published_total", (("kind", "live"),))] == 20
    assert f[("hp_edge_mqtt_published_total", (("kind", "historical"),))] == 10
    assert _kind('out of range [0, 80]') == "out_of_range"
    assert _kind("cycle budget exhausted") == "cycle_budget_exhausted"


def test_health_endpoint_serves_http_on_loopback_and_404_elsewhere():
    async def go():
        h = HealthServer(HealthConfig(enabled=True, port=0))
        await h.start(_Gw())
        url = f"http://127.0.0.1:{h.port}"

        def get(path):
            try:
                with urllib.request.urlopen(url + path, timeout=5) as r:
                    return r.status, r.headers["Content-Type"], r.read().decode()
            except urllib.error.HTTPError as e:
                return e.code, None, ""
        ok = await asyncio.to_thread(get, "/metrics")
        missing = await asyncio.to_thread(get, "/")
        await h.stop()
        return ok, missing, h
    (code, ctype, body), (code404, _, _), h = run(go())
    assert code == 200 and ctype == "text/plain; version=0.0.4; charset=utf-8"
    assert ("hp_edge_up", ()) in families(body) and h.scrapes == 1
    assert code404 == 404


# --------------------------------------------------------------------------- observer hook


class Recorder:
    def __init__(self, fail_cycle=False, fail_start=False):
        self.events, self.started, self.stopped = [], False, False
        self.fail_cycle, self.fail_start = fail_cycle, fail_start

    async def start(self, gateway):
        if self.fail_start:
            raise OSError("address already in use")
        self.started = True

    def cycle(self, event):
        self.events.append(event)
        if self.fail_cycle:
            raise RuntimeError("observer bug")

    async def stop(self):
        self.stopped = True


class RowsAdvisor(FakeAdvisor):
    def ingest(self, samples):
        super().ingest(samples)
        return [{"ts": int(s.timestamp)} for s in samples]


def test_observers_see_every_cycle_with_its_rows_and_advice_and_cannot_break_the_loop():
    cfg = replace(CFG, scan_interval_s=0.02, calibration_interval_s=300.0)

    async def go():
        good, bad, dead = Recorder(), Recorder(fail_cycle=True), Recorder(fail_start=True)
        gw = Gateway(cfg, RowsAdvisor(["ok"]), plc=FakePlc(cfg), time_source="plc",
                     install_signals=False, observers=[good, bad, dead])
        await gw.startup()
        for _ in range(12):
            await gw.cycle()
            await asyncio.sleep(0.01)
        await gw.shutdown()
        return gw, good, bad, dead
    gw, good, bad, dead = run(go())
    assert good.started and good.stopped and dead not in gw.observers and not dead.stopped
    assert len(good.events) == len(bad.events) == 12 == gw.snapshot.cycles
    assert gw.snapshot.errors == 0 and gw.snapshot.writes_ok == 12
    rows = [r["ts"] for e in good.events for r in e.rows]
    assert len(rows) == gw.snapshot.samples > 0 and rows == sorted(rows)
    advised = [e for e in good.events if e.advice is not None]
    assert advised[0].advice.values["p_m_sp_rec"] == 17.5
    assert all(e.advice.skipped for e in advised[1:])           # the fake's later outcomes
    assert advised[0].calibration_s is not None and advised[0].calibration_s >= 0
    assert all(e.duration_s >= 0 and e.snapshot is gw.snapshot for e in good.events)


# ------------------------------------------------------------------------ the daemon stays lean


def test_the_gateway_without_northbound_does_not_import_mqtt_libraries(tmp_path):
    code = ("import sys\n"
            "from edge.config import load_config\n"
            "from edge.service import GatewayService\n"
            f"cfg = load_config({str(ROOT / 'config' / 'gateway.yaml')!r})\n"
            "from dataclasses import replace\n"
            f"cfg = replace(cfg, state_dir=__import__('pathlib').Path({str(tmp_path)!r}),\n"
            f"              history_db=__import__('pathlib').Path({str(tmp_path / 'h.sqlite')!r}))\n"
            "svc = GatewayService(cfg, install_signals=False)\n"
            "svc.store.close()\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('paho', 'tahutils',\n"
            "             'google', 'prometheus_client') or m in ('edge.northbound.publisher',\n"
            "             'edge.northbound.sparkplug', 'edge.health'))\n"
            "print('IMPORTED:' + ','.join(bad))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "IMPORTED:"


def test_an_enabled_publisher_without_its_libraries_stops_the_start_with_exit_2(tmp_path):
    code = ("import sys\n"
            "sys.modules['paho'] = None\n"         # as if the extra were not installed
            "from dataclasses import replace\n"
            "from pathlib import Path\n"
            "from edge.config import load_config\n"
            "from edge.northbound.config import MqttConfig, NorthboundConfig\n"
            "from edge.service import GatewayService, StartupError\n"
            f"cfg = load_config({str(ROOT / 'config' / 'gateway.yaml')!r})\n"
            f"cfg = replace(cfg, state_dir=Path({str(tmp_path)!r}), history_db=Path("
            f"{str(tmp_path / 'h.sqlite')!r}), northbound=NorthboundConfig(mqtt=MqttConfig("
            "enabled=True)))\n"
            "try:\n"
            "    GatewayService(cfg, install_signals=False)\n"
            "except StartupError as exc:\n"
            "    print('STARTUP:', exc)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "northbound.mqtt is enabled but its libraries are missing" in r.stdout
    assert "pip install 'hp-edge[northbound]'" in r.stdout


def test_the_commented_example_in_gateway_yaml_is_valid_when_uncommented(confdir, monkeypatch):
    monkeypatch.setenv("HP_EDGE_MQTT_PASSWORD", "x")
    path = confdir / "gateway.yaml"
    lines = path.read_text(encoding="utf-8").splitlines()
    start = lines.index("# northbound:")
    block = []
    for ln in lines[start:]:
        if not ln.startswith("#"):
            break
        block.append(ln[2:])
    path.write_text("\n".join(lines[:start] + block) + "\n", encoding="utf-8")
    nb = load_config(path, load_plant=False).northbound
    assert nb.mqtt == MqttConfig(enabled=True)           # the example shows the defaults
    assert nb.health == HealthConfig(enabled=True)
