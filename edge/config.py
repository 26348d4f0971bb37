"""Gateway configuration: gateway.yaml, the tags.yaml it names, and plant.yaml passed on as a dict.

``load_config(path)`` validates everything and either returns a frozen ``GatewayConfig`` or raises
one ``ConfigError`` listing every problem, one line each, naming the file, the tag (or section)
and the key. Validation never rewrites the user's config: defaults exist only for the optional
keys documented in the YAML files. Paths in gateway.yaml are relative to that file's folder.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from edge.advisory import NAME_PATTERN as _NAME
from edge.advisory import AdvisoryConfig, AdvisoryField, parse_advisory
from edge.codec import BYTE_ORDERS, REGISTER_SPACES, TYPES, raw_limits, register_count

DEFAULT_CONFIG = Path("config/gateway.yaml")
__all__ = ["AdvisoryConfig", "AdvisoryField", "ConfigError", "GatewayConfig", "PlcConfig",
           "TagConfig", "load_config", "DEFAULT_CONFIG"]
PRESSURE_KINDS = ("gauge", "absolute")
PRESSURE_UNITS = ("bar", "mbar", "Pa", "kPa", "MPa", "psi")
OPTIMIZERS = ("model", "surrogate")


class ConfigError(Exception):
    """Invalid configuration; ``problems`` holds one line per problem."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


@dataclass(frozen=True)
class TagConfig:
    name: str
    register: str            # holding | input
    address: int             # 0-based PDU address
    type: str                # int16 | uint16 | int32 | uint32 | float32
    byte_order: str          # ABCD | CDAB | BADC | DCBA (32-bit types only)
    scale: float
    offset: float
    unit: str
    range: tuple[float, float]
    max_age_s: float
    sentinel: int | float | None = None
    pressure: str | None = None  # gauge | absolute, for pressure units
    flatline_s: float | None = None  # stuck-sensor time; None: edge.aggregate's default, 0: off

    @property
    def count(self) -> int:
        return register_count(self.type)

    @property
    def end(self) -> int:
        """First address after this tag."""
        return self.address + self.count


@dataclass(frozen=True)
class PlcConfig:
    host: str
    port: int
    device_id: int = 1
    timeout_s: float = 1.0
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 2.5


@dataclass(frozen=True)
class GatewayConfig:
    path: Path
    plc: PlcConfig
    tags: tuple[TagConfig, ...]
    advisory: AdvisoryConfig
    tags_file: Path
    plant_file: Path
    scan_interval_s: float
    aggregate_s: float
    calibration_interval_s: float
    calibration_window_h: float
    min_window_samples: int
    optimizer: str
    life_counter_tag: str | None
    state_dir: Path
    history_db: Path
    history_retention_days: float
    plant: dict | None = field(default=None, compare=False, hash=False)  # None: not loaded
    # optional section (issue 14): edge.northbound.config.NorthboundConfig, None when absent
    northbound: Any = None

    def tag(self, name: str) -> TagConfig:
        for t in self.tags:
            if t.name == name:
                return t
        raise KeyError(name)


# ------------------------------------------------------------------------------ loading


def _display(path: Path) -> str:
    """A path as the user should read it in messages: relative to cwd when inside it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def load_config(path: str | Path = DEFAULT_CONFIG, *, load_plant: bool = True) -> GatewayConfig:
    """Load and validate gateway.yaml, its tags file and (unless ``load_plant`` is False) its
    plant file. Raises ConfigError listing every problem found."""
    path = Path(path)
    p = _Problems()
    gw_file = _display(path)
    data = _load_yaml(p, path, gw_file)
    if data is None:
        raise ConfigError(p.lines)
    top = _Section(p, gw_file, "top level", data)
    if not top.mapping():
        raise ConfigError(p.lines)
    top.keys(_TOP_KEYS, required=_TOP_REQUIRED)
    base = path.parent

    plc = _plc(_Section(p, gw_file, "section 'plc'", top.raw("plc")))
    scan = top.number("scan_interval_s", positive=True)
    aggregate = top.number("aggregate_s", positive=True)
    calib_every = top.number("calibration_interval_s", positive=True)
    window_h = top.number("calibration_window_h", positive=True)
    min_samples = top.integer("min_window_samples", lo=1)
    _cross_checks(top, plc, scan, aggregate, calib_every, window_h, min_samples)

    tags_path = top.path("tags_file", base, must_exist=True)
    plant_path = top.path("plant_file", base, must_exist=load_plant)
    tags: tuple[TagConfig, ...] = ()
    names: set = set()
    if tags_path is not None:
        tags, names = _tags(p, tags_path)
    advisory = parse_advisory(_Section(p, gw_file, "section 'advisory'", top.raw("advisory")))
    if advisory is not None:
        _advisory_vs_tags(p, gw_file, advisory, tags, tags_path)
    for t in tags:
        if scan is not None and t.max_age_s < scan:
            p.add(_display(tags_path), f"tag '{t.name}'", "max_age_s",
                  f"{t.max_age_s:g} s is shorter than scan_interval_s ({scan:g} s) of {gw_file}; "
                  "the value would always be stale")
    life_counter = top.string("life_counter_tag", nullable=True)
    if life_counter and names and life_counter not in names:
        top.problem("life_counter_tag", f"{life_counter!r} is not a tag of {_display(tags_path)}")
    plant = None
    if load_plant and plant_path is not None and plant_path.exists():
        plant = _load_yaml(p, plant_path, _display(plant_path))
        if plant is not None and not isinstance(plant, dict):
            p.add(_display(plant_path), None, None, "expected a mapping at the top level")
    cfg_kwargs = dict(
        optimizer=top.choice("optimizer", OPTIMIZERS),
        state_dir=top.path("state_dir", base),
        history_db=top.path("history_db", base),
        history_retention_days=top.number("history_retention_days", positive=True),
    )
    northbound = None
    if "northbound" in data:     # issue 14: parsed by its own module, problems land here
        from edge.northbound.config import parse_northbound
        northbound = parse_northbound(top.child("section 'northbound'", data["northbound"]), base)
    if p.lines:
        raise ConfigError(p.lines)
    return GatewayConfig(
        path=path.resolve(), plc=plc, tags=tags, advisory=advisory, tags_file=tags_path,
        plant_file=plant_path, scan_interval_s=scan, aggregate_s=aggregate,
        calibration_interval_s=calib_every, calibration_window_h=window_h,
        min_window_samples=min_samples, life_counter_tag=life_counter, plant=plant,
        northbound=northbound, **cfg_kwargs,
    )


_TOP_REQUIRED = (
    "plc", "tags_file", "plant_file", "scan_interval_s", "aggregate_s",
    "calibration_interval_s", "calibration_window_h", "min_window_samples", "optimizer",
    "life_counter_tag", "state_dir", "history_db", "history_retention_days", "advisory",
)
_TOP_KEYS = _TOP_REQUIRED + ("northbound",)   # optional (issue 14, edge/northbound/config.py)


def _plc(sec: _Section) -> PlcConfig | None:
    if not sec.mapping():
        return None
    sec.keys(("host", "port", "device_id", "timeout_s", "reconnect_min_s", "reconnect_max_s"),
             required=("host", "port"))
    n0 = sec.count()
    kw = dict(
        host=sec.string("host"),
        port=sec.integer("port", lo=1, hi=65535),
        device_id=sec.integer("device_id", lo=0, hi=255, default=1),
        timeout_s=sec.number("timeout_s", positive=True, default=1.0),
        reconnect_min_s=sec.number("reconnect_min_s", positive=True, default=1.0),
        reconnect_max_s=sec.number("reconnect_max_s", positive=True, default=2.5),
    )
    if kw["reconnect_min_s"] is not None and kw["reconnect_max_s"] is not None \
            and kw["reconnect_max_s"] < kw["reconnect_min_s"]:
        sec.problem("reconnect_max_s", f"{kw['reconnect_max_s']:g} is below reconnect_min_s "
                    f"{kw['reconnect_min_s']:g}")
    return PlcConfig(**kw) if sec.count() == n0 else None


def _cross_checks(top, plc, scan, aggregate, calib_every, window_h, min_samples) -> None:
    if plc is not None and scan is not None and plc.timeout_s >= scan:
        top.child("section 'plc'").problem(
            "timeout_s", f"{plc.timeout_s:g} s per request must be shorter than scan_interval_s "
            f"({scan:g} s), or one poll cycle could overrun the scan interval")
    if scan is not None and aggregate is not None and aggregate < scan:
        top.problem("aggregate_s", f"{aggregate:g} s is shorter than scan_interval_s ({scan:g} s)")
    if aggregate is not None and calib_every is not None and calib_every < aggregate:
        top.problem("calibration_interval_s",
                    f"{calib_every:g} s is shorter than aggregate_s ({aggregate:g} s)")
    if None not in (window_h, aggregate, min_samples):
        capacity = int(window_h * 3600 // aggregate)
        if min_samples > capacity:
            top.problem("min_window_samples",
                        f"{min_samples} exceeds the {capacity} samples a {window_h:g} h window "
                        f"of {aggregate:g} s samples can hold; calibration would never run")


_TAG_KEYS = ("register", "address", "type", "byte_order", "scale", "offset", "unit", "range",
             "max_age_s", "sentinel", "pressure", "flatline_s")
_TAG_REQUIRED = ("register", "address", "type", "unit", "range", "max_age_s")


def _tags(p: _Problems, path: Path) -> tuple[tuple[TagConfig, ...], set]:
    """The valid tags, and the names of all tags in the file (valid or not)."""
    file = _display(path)
    data = _load_yaml(p, path, file)
    top = _Section(p, file, "top level", data)
    if data is None or not top.mapping():
        return (), set()
    top.keys(("tags",), required=("tags",))
    raw_tags = data.get("tags")
    if "tags" in data and (not isinstance(raw_tags, dict) or not raw_tags):
        top.problem("tags", "expected a non-empty mapping of tag name -> keys")
        return (), set()
    tags, placed = [], []
    for name, body in (raw_tags or {}).items():
        if not isinstance(name, str) or not _NAME.match(name) or name == "timestamp":
            p.add(file, f"tag {name!r}", None,
                  "tag names must be identifiers (letters, digits, _) and not 'timestamp'")
            continue
        tag, place = _tag(_Section(p, file, f"tag '{name}'", body), name)
        if tag is not None:
            tags.append(tag)
        if place is not None:
            placed.append(place)
    for space in REGISTER_SPACES:
        _overlaps(p, file, [t for t in placed if t[1] == space])
    return tuple(tags), set(raw_tags or ())


def _tag(sec: _Section, name: str) -> tuple[TagConfig | None, tuple | None]:
    """The tag (None if invalid) and its placement (name, space, start, end) for the overlap
    check, known whenever register, address and type are valid."""
    if not sec.mapping():
        return None, None
    sec.keys(_TAG_KEYS, required=_TAG_REQUIRED)
    n0 = sec.count()
    register = sec.choice("register", REGISTER_SPACES)
    type_ = sec.choice("type", TYPES)
    byte_order = sec.choice("byte_order", BYTE_ORDERS, default="ABCD")
    address = sec.integer("address", lo=0, hi=65535)
    if type_ and byte_order and register_count(type_) == 1 and byte_order != "ABCD":
        sec.problem("byte_order", f"{byte_order!r} has no effect on 16-bit type {type_} "
                    "(16-bit values are always big-endian AB); remove the key")
    if type_ and address is not None and address + register_count(type_) > 65536:
        sec.problem("address", f"{type_} at {address} runs past register 65535")
    scale = sec.number("scale", default=1.0)
    if scale == 0:
        sec.problem("scale", "must not be 0")
    offset = sec.number("offset", default=0.0)
    unit = sec.string("unit")
    rng = sec.range("range")
    max_age = sec.number("max_age_s", positive=True)
    sentinel = sec.sentinel("sentinel", type_)
    pressure = sec.choice("pressure", PRESSURE_KINDS, default=None)
    if unit in PRESSURE_UNITS and pressure is None and "pressure" not in sec.data:
        sec.problem("pressure", f"required for a pressure tag (unit {unit}): gauge or absolute")
    if unit is not None and unit not in PRESSURE_UNITS and "pressure" in sec.data:
        sec.problem("pressure", f"only for pressure units ({', '.join(PRESSURE_UNITS)}), "
                    f"unit is {unit!r}")
    # issue 9 item 17 (edge.aggregate's flat-line check): seconds >= 0, 0 = off
    flatline = sec.number("flatline_s", default=None)
    if flatline is not None and flatline < 0:
        sec.problem("flatline_s", f"must be >= 0 (0: no flat-line check), got {flatline:g}")
    place = None
    if register and type_ and address is not None:
        place = (name, register, address, address + register_count(type_))
    if sec.count() != n0:
        return None, place
    return TagConfig(name=name, register=register, address=address, type=type_,
                     byte_order=byte_order, scale=float(scale), offset=float(offset), unit=unit,
                     range=rng, max_age_s=max_age, sentinel=sentinel, pressure=pressure,
                     flatline_s=flatline), place


def _overlaps(p: _Problems, file: str, placed: list[tuple[str, str, int, int]]) -> None:
    widest = None
    for name, space, start, end in sorted(placed, key=lambda t: t[2]):
        if widest is not None and start < widest[3]:
            p.add(file, f"tag '{name}'", "address",
                  f"registers {space} {start}..{end - 1} overlap tag '{widest[0]}' "
                  f"({space} {widest[2]}..{widest[3] - 1})")
        if widest is None or end > widest[3]:
            widest = (name, space, start, end)


def _advisory_vs_tags(p, gw_file, adv: AdvisoryConfig, tags, tags_path) -> None:
    for tag in tags:
        if tag.register == adv.register and tag.address < adv.end and adv.start < tag.end:
            p.add(gw_file, "section 'advisory'", "start",
                  f"block {adv.register} {adv.start}..{adv.end - 1} overlaps tag '{tag.name}' "
                  f"({tag.register} {tag.address}..{tag.end - 1}) of {_display(tags_path)}")


# --------------------------------------------------------------------- validation helpers

_MISSING = object()  # key absent (its absence is reported once, by _Section.keys)
_REQUIRED = object()


class _Problems:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def add(self, file: str, where: str | None, key: Any, msg: str) -> None:
        parts = [file] + ([where] if where else []) + ([f"key '{key}'"] if key is not None else [])
        self.lines.append(": ".join(parts) + ": " + msg)


class _Loader(yaml.SafeLoader):
    """SafeLoader that records duplicate mapping keys (plain PyYAML keeps the last silently)."""

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self.duplicates: list[tuple[Any, int, int]] = []


def _construct_mapping(loader: _Loader, node, deep: bool = False):
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=True)
        try:
            first = seen.get(key)
        except TypeError:  # unhashable key: SafeLoader reports it below
            continue
        line = key_node.start_mark.line + 1
        if first is None:
            seen[key] = line
        else:
            loader.duplicates.append((key, line, first))
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _load_yaml(p: _Problems, path: Path, file: str) -> Any:
    """Parsed YAML, or None (with the reason recorded) when unreadable, invalid or empty."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        p.add(file, None, None, "file not found")
        return None
    except (OSError, UnicodeDecodeError) as exc:
        p.add(file, None, None, f"cannot read: {exc}")
        return None
    loader = _Loader(text)
    try:
        data = loader.get_single_data()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1} column {mark.column + 1}" if mark else None
        p.add(file, where, None, f"YAML syntax error: {getattr(exc, 'problem', None) or exc}")
        return None
    finally:
        loader.dispose()
    for key, line, first in loader.duplicates:
        p.add(file, f"line {line}", None,
              f"duplicate key {key!r} (first at line {first}); YAML would silently keep the last")
    if data is None:
        p.add(file, None, None, "file is empty")
    return data


def _fmt(v: Any) -> str:
    return "null" if v is None else repr(v)


class _Section:
    """One mapping of a YAML file being validated: typed getters that record problems."""

    def __init__(self, p: _Problems, file: str, where: str, data: Any) -> None:
        self.p, self.file, self.where, self.data = p, file, where, data

    def problem(self, key: Any, msg: str) -> None:
        self.p.add(self.file, self.where, key, msg)

    def child(self, where: str, data: Any = _MISSING) -> _Section:
        """A section of the same file (e.g. one advisory field)."""
        return _Section(self.p, self.file, where, data)

    def count(self) -> int:
        return len(self.p.lines)

    def mapping(self) -> bool:
        if self.data is _MISSING:
            return False
        if not isinstance(self.data, dict):
            self.problem(None, f"expected a mapping of keys, got {_fmt(self.data)}")
            return False
        return True

    def keys(self, allowed, required=()) -> None:
        for key in self.data:
            if key not in allowed:
                hint = ""
                if isinstance(key, str) and (close := difflib.get_close_matches(key, allowed, 1)):
                    hint = f" (did you mean '{close[0]}'?)"
                self.problem(key, f"unknown key{hint}; allowed: {', '.join(allowed)}")
        for key in required:
            if key not in self.data:
                self.problem(key, "missing required key")

    def raw(self, key: str) -> Any:
        return self.data.get(key, _MISSING) if isinstance(self.data, dict) else _MISSING

    def _get(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        return None if default is _REQUIRED else default

    def string(self, key, default=_REQUIRED, nullable=False, allow_empty=False):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if v is None and nullable:
            return None
        if not isinstance(v, str) or (not v and not allow_empty):
            self.problem(key, f"expected a {'non-empty ' if not allow_empty else ''}string, "
                         f"got {_fmt(v)}")
            return None
        return v

    def number(self, key, positive=False, default=_REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v or v in (
                float("inf"), float("-inf")):
            self.problem(key, f"expected a finite number, got {_fmt(v)}")
            return None
        if positive and v <= 0:
            self.problem(key, f"must be > 0, got {v!r}")
            return None
        return float(v)

    def integer(self, key, lo=None, hi=None, default=_REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if isinstance(v, bool) or not isinstance(v, int):
            self.problem(key, f"expected an integer, got {_fmt(v)}")
            return None
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            bounds = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            self.problem(key, f"{v} is outside {bounds}")
            return None
        return v

    def choice(self, key, options, default=_REQUIRED):
        if key not in self.data:
            return self._get(key, default)
        v = self.data[key]
        if not isinstance(v, str) or v not in options:
            self.problem(key, f"{_fmt(v)} is not one of {', '.join(options)}")
            return None
        return v

    def range(self, key):
        if key not in self.data:
            return None
        v = self.data[key]
        ok = isinstance(v, list) and len(v) == 2 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and x == x for x in v)
        if not ok:
            self.problem(key, f"expected [low, high] (two numbers), got {_fmt(v)}")
            return None
        if not v[0] < v[1]:
            self.problem(key, f"low {v[0]!r} must be below high {v[1]!r}")
            return None
        return (float(v[0]), float(v[1]))

    def sentinel(self, key, type_):
        if key not in self.data or self.data[key] is None:
            return None
        v = self.data[key]
        if type_ is None:
            return None  # the type's own problem is reported already
        if type_ == "float32":
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                self.problem(key, f"expected a number (raw float32 value), got {_fmt(v)}")
                return None
            return float(v)
        lo, hi = raw_limits(type_)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            self.problem(key, f"{_fmt(v)} is not a raw {type_} value ({lo}..{hi})")
            return None
        return v

    def path(self, key, base: Path, must_exist=False):
        v = self.string(key)
        if v is None:
            return None
        resolved = (base / Path(v).expanduser()).resolve()
        if must_exist and not resolved.is_file():
            what = "is not a file" if resolved.exists() else "file not found"
            self.problem(key, f"{what}: {_display(resolved)}")
            return None
        return resolved
