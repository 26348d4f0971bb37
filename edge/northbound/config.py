"""The optional ``northbound:`` section of gateway.yaml (issue 14).

``parse_northbound(section, base)`` is called by ``edge.config.load_config`` with the section's
validator (``edge.config._Section``); every problem is recorded there, one line each, naming the
file, the section and the key, so a bad northbound section fails the start with exit code 2 like
any other configuration error. Nothing here imports paho-mqtt or a protobuf library.

Secrets: the MQTT password comes from a file (``password_file``, first line, trailing newline
stripped) or an environment variable (``password_env``), never from gateway.yaml itself. It is
read when the configuration is loaded, and only when the publisher is enabled; it is kept out of
every ``repr``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MODES = ("sparkplug", "json")
QOS_LEVELS = (0, 1)
# Sparkplug B forbids these in group and edge-node ids (MQTT wildcards and the level separator)
_FORBIDDEN = ("/", "+", "#")

MQTT_KEYS = ("enabled", "mode", "host", "port", "group_id", "edge_node_id", "client_id",
             "topic_prefix", "qos", "keepalive_s", "reconnect_min_s", "reconnect_max_s",
             "max_backlog_rows", "username", "password_file", "password_env", "tls")
TLS_KEYS = ("ca_file", "cert_file", "key_file", "insecure")
HEALTH_KEYS = ("enabled", "bind", "port")


@dataclass(frozen=True)
class TlsConfig:
    ca_file: Path | None = None      # CA bundle that signed the broker's certificate (None: system)
    cert_file: Path | None = None    # client certificate (mutual TLS), with key_file
    key_file: Path | None = None
    insecure: bool = False           # skip the host-name check (testing only)


@dataclass(frozen=True)
class MqttConfig:
    """``northbound.mqtt``. Defaults are those documented in config/gateway.yaml."""
    enabled: bool = False
    mode: str = "sparkplug"          # sparkplug | json
    host: str = "127.0.0.1"
    port: int = 1883
    group_id: str = "hp-edge"
    edge_node_id: str = "heat-pump"
    client_id: str = ""              # '' -> hp-edge-<group_id>-<edge_node_id>
    topic_prefix: str = "hp-edge"    # json mode: <prefix>/<group_id>/<edge_node_id>/...
    qos: int = 1                     # QoS of data messages (NDATA / JSON samples and advice)
    keepalive_s: float = 30.0
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 60.0
    max_backlog_rows: int = 100_000  # rows waiting for the broker at most (oldest dropped first)
    username: str | None = None
    password: str | None = field(default=None, repr=False, compare=False)
    password_source: str | None = None   # 'file PATH' | 'environment NAME' (for messages)
    tls: TlsConfig | None = None

    @property
    def effective_client_id(self) -> str:
        return self.client_id or f"hp-edge-{self.group_id}-{self.edge_node_id}"


@dataclass(frozen=True)
class HealthConfig:
    """``northbound.health``: the Prometheus endpoint (GET /metrics)."""
    enabled: bool = False
    bind: str = "127.0.0.1"
    port: int = 9108                 # 0: any free port (logged at start)


@dataclass(frozen=True)
class NorthboundConfig:
    mqtt: MqttConfig | None = None
    health: HealthConfig | None = None

    @property
    def mqtt_enabled(self) -> bool:
        return self.mqtt is not None and self.mqtt.enabled

    @property
    def health_enabled(self) -> bool:
        return self.health is not None and self.health.enabled


def parse_northbound(sec: Any, base: Path) -> NorthboundConfig | None:
    """The validated section (``sec`` is an ``edge.config._Section``; problems are recorded on
    it), or None when it is invalid. ``base``: the folder relative paths start from."""
    if sec.data is None:         # `northbound:` with nothing under it: everything off
        return NorthboundConfig()
    if not sec.mapping():
        return None
    sec.keys(("mqtt", "health"))
    n0 = sec.count()
    mqtt = _mqtt(sec.child("section 'northbound.mqtt'", sec.raw("mqtt")), base) \
        if "mqtt" in sec.data else None
    health = _health(sec.child("section 'northbound.health'", sec.raw("health"))) \
        if "health" in sec.data else None
    if sec.count() != n0:
        return None
    return NorthboundConfig(mqtt=mqtt, health=health)


def _flag(sec: Any, key: str, default: bool) -> bool | None:
    if key not in sec.data:
        return default
    v = sec.data[key]
    if not isinstance(v, bool):
        sec.problem(key, f"expected true or false, got {v!r}")
        return None
    return v


def _ident(sec: Any, key: str, default: str) -> str | None:
    v = sec.string(key, default=default)
    if v is not None and any(c in v for c in _FORBIDDEN):
        sec.problem(key, f"{v!r} must not contain {' '.join(_FORBIDDEN)} (MQTT topic levels "
                    "and wildcards)")
        return None
    return v


def _mqtt(sec: Any, base: Path) -> MqttConfig | None:
    if sec.data is None:
        return MqttConfig()
    if not sec.mapping():
        return None
    sec.keys(MQTT_KEYS)
    n0 = sec.count()
    d = MqttConfig()
    kw: dict[str, Any] = dict(
        enabled=_flag(sec, "enabled", d.enabled),
        mode=sec.choice("mode", MODES, default=d.mode),
        host=sec.string("host", default=d.host),
        port=sec.integer("port", lo=1, hi=65535, default=d.port),
        group_id=_ident(sec, "group_id", d.group_id),
        edge_node_id=_ident(sec, "edge_node_id", d.edge_node_id),
        client_id=sec.string("client_id", default=d.client_id),
        topic_prefix=_ident(sec, "topic_prefix", d.topic_prefix),
        keepalive_s=sec.number("keepalive_s", positive=True, default=d.keepalive_s),
        reconnect_min_s=sec.number("reconnect_min_s", positive=True, default=d.reconnect_min_s),
        reconnect_max_s=sec.number("reconnect_max_s", positive=True, default=d.reconnect_max_s),
        max_backlog_rows=sec.integer("max_backlog_rows", lo=100, default=d.max_backlog_rows),
        username=sec.string("username", default=None),
        password=None, password_source=None,
    )
    qos = sec.integer("qos", lo=0, hi=1, default=d.qos)
    kw["qos"] = qos
    if kw["keepalive_s"] is not None and kw["keepalive_s"] < 5:
        sec.problem("keepalive_s", f"{kw['keepalive_s']:g} s is too short; use 5 s or more")
    lo, hi = kw["reconnect_min_s"], kw["reconnect_max_s"]
    if lo is not None and hi is not None and hi < lo:
        sec.problem("reconnect_max_s", f"{hi:g} is below reconnect_min_s {lo:g}")
    if "password_file" in sec.data and "password_env" in sec.data:
        sec.problem("password_env", "give password_file or password_env, not both")
    elif kw["enabled"]:
        kw["password"], kw["password_source"] = _password(sec, base)
    if (kw["password"] is not None or "password_file" in sec.data
            or "password_env" in sec.data) and not kw["username"]:
        sec.problem("username", "a password is configured but no username")
    if "tls" in sec.data:
        kw["tls"] = _tls(sec.child("section 'northbound.mqtt.tls'", sec.raw("tls")), base)
    if sec.count() != n0:
        return None
    return MqttConfig(**kw)


def _password(sec: Any, base: Path) -> tuple[str | None, str | None]:
    if "password_file" in sec.data:
        path = sec.path("password_file", base, must_exist=True)
        if path is None:
            return None, None
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            sec.problem("password_file", f"cannot read {path}: {exc}")
            return None, None
        lines = text.splitlines()
        if not lines or not lines[0]:
            sec.problem("password_file", f"{path} is empty (the password is its first line)")
            return None, None
        return lines[0], f"file {path}"
    if "password_env" in sec.data:
        name = sec.string("password_env")
        if name is None:
            return None, None
        value = os.environ.get(name)
        if not value:
            sec.problem("password_env", f"the environment variable {name} is not set (or empty)")
            return None, None
        return value, f"environment {name}"
    return None, None


def _tls(sec: Any, base: Path) -> TlsConfig | None:
    if sec.data is None:
        return TlsConfig()
    if not sec.mapping():
        return None
    sec.keys(TLS_KEYS)
    n0 = sec.count()
    kw = {k: sec.path(k, base, must_exist=True) if k in sec.data else None
          for k in ("ca_file", "cert_file", "key_file")}
    insecure = _flag(sec, "insecure", False)
    if ("cert_file" in sec.data) != ("key_file" in sec.data):
        sec.problem("key_file" if "cert_file" in sec.data else "cert_file",
                    "a client certificate needs both cert_file and key_file")
    if sec.count() != n0:
        return None
    return TlsConfig(insecure=bool(insecure), **kw)


def _health(sec: Any) -> HealthConfig | None:
    if sec.data is None:
        return HealthConfig()
    if not sec.mapping():
        return None
    sec.keys(HEALTH_KEYS)
    n0 = sec.count()
    d = HealthConfig()
    kw = dict(enabled=_flag(sec, "enabled", d.enabled),
              bind=sec.string("bind", default=d.bind),
              port=sec.integer("port", lo=0, hi=65535, default=d.port))
    if sec.count() != n0:
        return None
    return HealthConfig(**kw)
