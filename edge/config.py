"""Gateway configuration: gateway.yaml, the tags.yaml it names, and plant.yaml passed on as a dict.

``load_config(path)`` validates everything and either returns a frozen ``GatewayConfig`` or raises
one ``ConfigError`` listing every problem, one line each, naming the file, the tag (or section)
and the key (and the line for unknown and duplicate keys). Validation never rewrites the user's
config: defaults exist only for the optional keys documented in the YAML files. Paths in
gateway.yaml are relative to that file's folder; ``${STATE_DIRECTORY:-default}`` in state_dir and
history_db takes systemd's state directory when the service manager sets it.

Units: a tag's ``unit`` is the unit its engineering value (raw * scale + offset) is in, and its
``range`` is in that same unit (the unit the PLC engineer thinks in). ``TagConfig.to_canonical``
converts a value to the canonical unit of SPEC §4 (degC, bar(g), m3/h, kW, ...) with the table of
``model.units``; absolute pressures become gauge with plant.yaml's ``ambient_pressure_bar``.
"""
from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from typing import Any
from pathlib import Path

from edge.advisory import NAME_PATTERN as _NAME
from edge.advisory import AdvisoryConfig, AdvisoryField, parse_advisory
from edge.codec import (BIT_SPACES, BOOL, BYTE_ORDERS, BYTE_ORDERS_16, REGISTER_SPACES, TYPES,
                        raw_limits, register_count)
from edge.yamlfile import (MISSING, Problems, Section, display_path, finite_float, fmt_value,
                           key_line, load_yaml)
from model.columns import CANONICAL, REQUIRED as REQUIRED_TAGS
from model.units import (CANONICAL_UNITS, DEFAULT_AMBIENT_BAR, PRESSURE_KINDS, UNITS, UnitError,
                         canonical_linear)

DEFAULT_CONFIG = Path("config/gateway.yaml")
# Where commands look for gateway.yaml / plant.yaml when --config is not given, in this order:
# the working directory's config/, the system's /etc/hp-edge, a source checkout's config/ beside
# the package, and the copy a wheel installs under <prefix>/share/hp-edge/config.
CONFIG_DIRS = (Path("config"), Path("/etc/hp-edge"),
               Path(__file__).resolve().parent.parent / "config",
               Path(sys.prefix) / "share" / "hp-edge" / "config")
__all__ = ["AdvisoryConfig", "AdvisoryField", "ConfigError", "GatewayConfig", "PlcConfig",
           "Reserved", "TagConfig", "load_config", "load_read_config", "find_config",
           "DEFAULT_CONFIG"]
PRESSURE_UNITS = tuple(u for u, (q, _, _) in UNITS.items() if q == "pressure")
OPTIMIZERS = ("model", "auto", "surrogate")
DEVICE_IDS = (1, 255)   # 0 is the broadcast address: nobody answers it, everybody obeys it


class ConfigError(Exception):
    """Invalid configuration; ``problems`` holds one line per problem."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


def find_config(name: str = "gateway.yaml", given: str | Path | None = None) -> Path:
    """The configuration file to use: ``given`` when the user named one, else the first
    ``name`` found in ./config, /etc/hp-edge and the config folder beside the package (a source
    checkout). When none exists, the first candidate (its 'file not found' names it)."""
    if given is not None:
        return Path(given)
    for d in CONFIG_DIRS:
        if (d / name).is_file():
            return d / name
    return CONFIG_DIRS[0] / name


@dataclass(frozen=True)
class TagConfig:
    name: str
    register: str            # holding | input | coil | discrete_input
    address: int             # 0-based PDU address (a bit address for coils / discrete inputs)
    type: str                # int16 | uint16 | int32 | uint32 | float32 | int64 | uint64 |
    #                          float64 | bool (coils and discrete inputs)
    byte_order: str          # AB | BA (16-bit), ABCD | CDAB | BADC | DCBA (32/64-bit)
    scale: float
    offset: float
    unit: str                # the engineering value's unit (model.units.UNITS)
    range: tuple[float, float]   # plausible range, in ``unit``
    max_age_s: float
    sentinel: int | float | None = None
    pressure: str | None = None  # gauge | absolute, for pressure units
    flatline_s: float | None = None  # stuck-sensor time; None: edge.aggregate's default, 0: off
    device_id: int | None = None  # Modbus unit id; None: the plc section's device_id
    bit: int | None = None        # one bit (0 = least significant) of a 16-bit register
    # engineering value in ``unit`` -> canonical unit: (factor, offset); None when it cannot be
    # known (an absolute pressure without plant.yaml's ambient pressure). Left out, it is
    # derived from ``unit`` and ``pressure`` (model.units), never assumed to be the identity.
    canonical: tuple[float, float] | None | str = "auto"

    def __post_init__(self) -> None:
        if self.canonical == "auto":
            try:
                conv = canonical_linear(self.unit, self.pressure)
            except UnitError:
                conv = None
            object.__setattr__(self, "canonical", conv)

    @property
    def count(self) -> int:
        return register_count(self.type)

    @property
    def end(self) -> int:
        """First address after this tag."""
        return self.address + self.count

    @property
    def canonical_unit(self) -> str:
        return CANONICAL_UNITS[UNITS[self.unit][0]] if self.unit in UNITS else self.unit

    def to_canonical(self, value: float) -> float:
        """``value`` in the tag's unit -> the canonical unit (bar(g) for pressures)."""
        if self.canonical is None:
            raise UnitError(f"tag {self.name!r}: an absolute pressure needs plant.yaml's "
                            "ambient_pressure_bar")
        factor, offset = self.canonical
        return value * factor + offset

    @property
    def canonical_range(self) -> tuple[float, float] | None:
        """``range`` in the canonical unit (None when the conversion is not known)."""
        if self.canonical is None:
            return None
        lo, hi = (self.to_canonical(v) for v in self.range)
        return (min(lo, hi), max(lo, hi))


@dataclass(frozen=True)
class PlcConfig:
    host: str
    port: int
    device_id: int = 1
    timeout_s: float = 1.0
    reconnect_min_s: float = 1.0
    reconnect_max_s: float = 2.5
    max_read_gap: int = 10               # unused addresses a grouped read may span
    close_after_poll: bool = False       # Telegraf's close_connection_after_gather
    pause_between_requests_s: float = 0.0  # Telegraf's pause_between_requests


@dataclass(frozen=True)
class Reserved:
    """Registers the PLC owns: the gateway never writes them (first..last inclusive)."""
    register: str
    first: int
    last: int

    def overlaps(self, register: str, start: int, count: int) -> bool:
        return register == self.register and start <= self.last and self.first < start + count


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
    reserved: tuple[Reserved, ...] = ()
    # optional section (issue 14): edge.northbound.config.NorthboundConfig, None when absent
    northbound: Any = None
    # optional section (issue 13): edge.closed_loop.ClosedLoopConfig, None when absent (= off)
    closed_loop: Any = None

    def tag(self, name: str) -> TagConfig:
        for t in self.tags:
            if t.name == name:
                return t
        raise KeyError(name)


# ------------------------------------------------------------------------------ loading

_display = display_path


def load_config(path: str | Path = DEFAULT_CONFIG, *, load_plant: bool = True) -> GatewayConfig:
    """Load and validate gateway.yaml, its tags file and (unless ``load_plant`` is False) its
    plant file. Raises ConfigError listing every problem found."""
    path = Path(path)
    p = Problems()
    gw_file = _display(path)
    data = load_yaml(p, path, gw_file)
    if data is None:
        raise ConfigError(p.lines)
    top = Section(p, gw_file, "top level", data)
    if not top.mapping():
        raise ConfigError(p.lines)
    top.keys(_TOP_KEYS, required=_TOP_REQUIRED)
    base = path.parent

    plc = _plc(Section(p, gw_file, "section 'plc'", top.raw("plc")))
    scan = top.number("scan_interval_s", positive=True)
    aggregate = top.number("aggregate_s", positive=True)
    calib_every = top.number("calibration_interval_s", positive=True)
    window_h = top.number("calibration_window_h", positive=True)
    min_samples = top.integer("min_window_samples", lo=1)
    _cross_checks(top, plc, scan, aggregate, calib_every, window_h, min_samples)

    tags_path = top.path("tags_file", base, must_exist=True)
    plant_path = top.path("plant_file", base, must_exist=load_plant)
    plant = None
    ambient = None
    if load_plant and plant_path is not None and _exists(plant_path):
        from edge.plantfile import check_plant

        plant = check_plant(p, plant_path, _display(plant_path))
        if isinstance(plant, dict):
            a = finite_float(plant.get("ambient_pressure_bar", DEFAULT_AMBIENT_BAR))
            ambient = a if a is not None and a > 0 else None
    tags: tuple[TagConfig, ...] = ()
    names: set = set()
    if tags_path is not None:
        tags, names = _tags(p, tags_path, ambient)
    reserved = _reserved(top)
    advisory = parse_advisory(Section(p, gw_file, "section 'advisory'", top.raw("advisory")))
    if advisory is not None:
        _advisory_vs_plc_registers(p, gw_file, advisory, tags, tags_path, reserved)
    for t in tags:
        if scan is not None and t.max_age_s < scan:
            p.add(_display(tags_path), f"tag '{t.name}'", "max_age_s",
                  f"{t.max_age_s:g} s is shorter than scan_interval_s ({scan:g} s) of {gw_file}; "
                  "the value would always be stale")
    life_counter = top.string("life_counter_tag", nullable=True)
    if life_counter and names and life_counter not in names:
        top.problem("life_counter_tag", f"{life_counter!r} is not a tag of {_display(tags_path)}")
    cfg_kwargs = dict(
        optimizer=top.choice("optimizer", OPTIMIZERS),
        state_dir=_state_path(top, "state_dir", base),
        history_db=_state_path(top, "history_db", base),
        history_retention_days=top.number("history_retention_days", positive=True),
    )
    northbound = None
    if "northbound" in data:     # issue 14: parsed by its own module, problems land here
        from edge.northbound.config import parse_northbound
        northbound = parse_northbound(top.child("section 'northbound'", data["northbound"]), base)
    closed_loop = None
    if "closed_loop" in data:    # issue 13: the opt-in closed loop, its own module
        from edge.closed_loop import parse_closed_loop
        closed_loop = parse_closed_loop(top.child("section 'closed_loop'", data["closed_loop"]),
                                        tags, _display(tags_path) if tags_path else "tags_file",
                                        scan, names)
    if p.lines:
        raise ConfigError(p.lines)
    return GatewayConfig(
        path=path.resolve(), plc=plc, tags=tags, advisory=advisory, tags_file=tags_path,
        plant_file=plant_path, scan_interval_s=scan, aggregate_s=aggregate,
        calibration_interval_s=calib_every, calibration_window_h=window_h,
        min_window_samples=min_samples, life_counter_tag=life_counter, plant=plant,
        reserved=reserved, northbound=northbound, closed_loop=closed_loop, **cfg_kwargs,
    )


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except OSError:
        return False


def load_read_config(path: str | Path) -> tuple[PlcConfig | None, AdvisoryConfig]:
    """What ``hp-edge read`` needs of gateway.yaml: the plc section (None when it is invalid:
    the command line then names the server) and the advisory block's layout. Tags and plant
    files are not read. Raises ConfigError."""
    path = Path(path)
    p = Problems()
    gw_file = _display(path)
    data = load_yaml(p, path, gw_file)
    if data is None:
        raise ConfigError(p.lines)
    top = Section(p, gw_file, "top level", data)
    if not top.mapping():
        raise ConfigError(p.lines)
    n0 = top.count()
    plc = _plc(Section(p, gw_file, "section 'plc'", top.raw("plc")))
    if top.count() != n0:
        del p.lines[n0:]
        plc = None
    if "advisory" not in data:
        top.problem("advisory", "missing required key")
    advisory = parse_advisory(Section(p, gw_file, "section 'advisory'", top.raw("advisory")))
    if p.lines:
        raise ConfigError(p.lines)
    return plc, advisory


_TOP_REQUIRED = (
    "plc", "tags_file", "plant_file", "scan_interval_s", "aggregate_s",
    "calibration_interval_s", "calibration_window_h", "min_window_samples", "optimizer",
    "life_counter_tag", "state_dir", "history_db", "history_retention_days", "reserved",
    "advisory",
)
_TOP_KEYS = _TOP_REQUIRED + ("northbound",    # optional (issue 14, edge/northbound/config.py)
                              "closed_loop")   # optional (issue 13, edge/closed_loop.py)
_PLC_KEYS = ("host", "port", "device_id", "timeout_s", "reconnect_min_s", "reconnect_max_s",
             "max_read_gap", "close_after_poll", "pause_between_requests_s")


def _plc(sec: Section) -> PlcConfig | None:
    if not sec.mapping():
        return None
    n0 = sec.count()   # a missing required key invalidates it too
    sec.keys(_PLC_KEYS, required=("host", "port"))
    kw = dict(
        host=sec.string("host"),
        port=sec.integer("port", lo=1, hi=65535),
        device_id=_device_id(sec, "device_id", default=1),
        timeout_s=sec.number("timeout_s", positive=True, default=1.0),
        reconnect_min_s=sec.number("reconnect_min_s", positive=True, default=1.0),
        reconnect_max_s=sec.number("reconnect_max_s", positive=True, default=2.5),
        max_read_gap=sec.integer("max_read_gap", lo=0, hi=124, default=10),
        close_after_poll=sec.boolean("close_after_poll", default=False),
        pause_between_requests_s=sec.number("pause_between_requests_s", lo=0.0, hi=10.0,
                                            default=0.0),
    )
    if kw["reconnect_min_s"] is not None and kw["reconnect_max_s"] is not None \
            and kw["reconnect_max_s"] < kw["reconnect_min_s"]:
        sec.problem("reconnect_max_s", f"{kw['reconnect_max_s']:g} is below reconnect_min_s "
                    f"{kw['reconnect_min_s']:g}")
    return PlcConfig(**kw) if sec.count() == n0 else None


def _device_id(sec: Section, key: str, default):
    if key in sec.data and sec.data[key] == 0 and not isinstance(sec.data[key], bool):
        sec.problem(key, "0 is the broadcast address: devices do not answer it and all of them "
                    f"obey its writes; use {DEVICE_IDS[0]}..{DEVICE_IDS[1]}")
        return None
    return sec.integer(key, lo=DEVICE_IDS[0], hi=DEVICE_IDS[1], default=default)


def _cross_checks(top, plc, scan, aggregate, calib_every, window_h, min_samples) -> None:
    if plc is not None and scan is not None and plc.timeout_s >= scan:
        top.child("section 'plc'").problem(
            "timeout_s", f"{plc.timeout_s:g} s per request must be shorter than scan_interval_s "
            f"({scan:g} s), or one poll cycle could overrun the scan interval")
    if plc is not None and scan is not None and plc.pause_between_requests_s >= scan / 4:
        top.child("section 'plc'").problem(
            "pause_between_requests_s", f"{plc.pause_between_requests_s:g} s is not below a "
            f"quarter of scan_interval_s ({scan:g} s); a poll cycle would not fit")
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


_ENV = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


def _state_path(top: Section, key: str, base: Path) -> Path | None:
    """A path that may start from the service manager's state directory:
    ``${STATE_DIRECTORY:-../var}/state`` is $STATE_DIRECTORY/state under systemd (its first entry
    when it lists several) and ../var/state (relative to gateway.yaml) otherwise."""
    v = top.string(key)
    if v is None:
        return None
    missing = []

    def sub(m: re.Match) -> str:
        value = os.environ.get(m.group(1))
        if value and m.group(1) == "STATE_DIRECTORY":
            value = value.split(":")[0]
        if value:
            return value
        if m.group(2) is None:
            missing.append(m.group(1))
            return ""
        return m.group(2)

    expanded = _ENV.sub(sub, v)
    if missing:
        top.problem(key, f"environment variable {missing[0]} is not set and {fmt_value(v)} "
                    "gives no default (write ${NAME:-default})")
        return None
    if "$" in expanded:
        top.problem(key, f"{fmt_value(v)}: only ${{NAME}} and ${{NAME:-default}} are expanded")
        return None
    return Section(top.p, top.file, top.where, {key: expanded}).path(key, base)


def _reserved(top: Section) -> tuple[Reserved, ...]:
    raw = top.raw("reserved")
    if raw is MISSING or raw is None:
        return ()
    if not isinstance(raw, list):
        top.problem("reserved", "expected a list of {register: holding, first: N, last: M} "
                    "(registers the PLC owns), or [] for none")
        return ()
    out = []
    for i, item in enumerate(raw):
        sec = top.child(f"reserved[{i}]", item)
        if not sec.mapping():
            continue
        n0 = sec.count()   # a missing required key invalidates it too
        sec.keys(("register", "first", "last", "note"), required=("register", "first", "last"))
        register = sec.choice("register", REGISTER_SPACES)
        first = sec.integer("first", lo=0, hi=65535)
        last = sec.integer("last", lo=0, hi=65535)
        sec.string("note", default="", allow_empty=True)
        if first is not None and last is not None and last < first:
            sec.problem("last", f"{last} is below first {first}")
        if sec.count() == n0:
            out.append(Reserved(register, first, last))
    return tuple(out)


_TAG_KEYS = ("register", "address", "type", "byte_order", "scale", "offset", "unit", "range",
             "max_age_s", "sentinel", "pressure", "device_id", "bit", "flatline_s")
_TAG_REQUIRED = ("register", "address", "type", "unit", "max_age_s")


def _tags(p: Problems, path: Path, ambient: float | None) -> tuple[tuple[TagConfig, ...], set]:
    """The valid tags, and the names of all tags in the file (valid or not)."""
    file = _display(path)
    data = load_yaml(p, path, file)
    top = Section(p, file, "top level", data)
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
            p.add(file, f"tag {fmt_value(name)}", None,
                  "tag names must be identifiers (letters, digits, _) and not 'timestamp'")
            continue
        tag, place = _tag(Section(p, file, f"tag '{name}'", body), name, ambient)
        if tag is not None:
            tags.append(tag)
        if place is not None:
            placed.append(place)
    groups: dict[tuple, list] = {}
    for place in placed:
        groups.setdefault((place[1], place[2]), []).append(place)
    for key in sorted(groups, key=lambda k: (str(k[0]), k[1])):
        _overlaps(p, file, groups[key])
    names = {n for n in raw_tags if isinstance(n, str)} if raw_tags else set()
    for name in REQUIRED_TAGS:
        if name not in names:
            quantity, what = CANONICAL[name]
            p.add(file, f"tag '{name}'", None,
                  f"missing: the model needs it ({what}, a {quantity.replace('_', ' ')}); "
                  "add it to the tag map (SPEC §4)")
    return tuple(tags), names


def _tag(sec: Section, name: str, ambient: float | None) -> tuple[TagConfig | None, tuple | None]:
    """The tag (None if invalid) and its placement (name, device, space, start, end, bit) for
    the overlap check, known whenever register, address and type are valid."""
    if not sec.mapping():
        return None, None
    n0 = sec.count()   # a missing required key invalidates it too
    sec.keys(_TAG_KEYS, required=_TAG_REQUIRED)
    register = sec.choice("register", REGISTER_SPACES)
    type_ = sec.choice("type", tuple(TYPES) + (BOOL,))
    bits = register in BIT_SPACES
    bit = sec.integer("bit", lo=0, hi=15, default=None)
    single = bits or bit is not None     # a 0/1 value: a coil, discrete input or bit of a word
    if register and type_:
        if bits and type_ != BOOL:
            sec.problem("type", f"{register} values are single bits: type must be bool")
            type_ = None
        elif not bits and type_ == BOOL:
            sec.problem("type", "bool is for coils and discrete inputs; for one bit of a "
                        "register use type uint16 and bit: 0..15")
            type_ = None
    if bit is not None and register in BIT_SPACES:
        sec.problem("bit", f"only for holding or input registers, not {register}")
    elif bit is not None and type_ and type_ not in ("int16", "uint16"):
        sec.problem("bit", f"takes one bit of a 16-bit register; type must be uint16 or int16, "
                    f"not {type_}")
    byte_order = None
    if single:
        for key in ("byte_order", "sentinel", "pressure"):
            if key in sec.data:
                sec.problem(key, "not used by a single-bit value (coil, discrete input or "
                            "bit of a register); remove the key")
        byte_order = "AB"
    elif type_:
        allowed = BYTE_ORDERS_16 if register_count(type_) == 1 else BYTE_ORDERS
        default = allowed[0]
        if register_count(type_) == 1 and sec.data.get("byte_order") == "ABCD":
            byte_order = "ABCD"     # the pre-0.2 default spelling of AB, still accepted
        elif register_count(type_) == 1 and sec.data.get("byte_order") in BYTE_ORDERS:
            sec.problem("byte_order", f"{sec.data['byte_order']!r} is a 32/64-bit byte order; "
                        f"a 16-bit {type_} takes AB (default, high byte first) or BA (bytes "
                        "swapped)")
        else:
            byte_order = sec.choice("byte_order", allowed, default=default)
    address = sec.integer("address", lo=0, hi=65535)
    if type_ and address is not None and address + register_count(type_) > 65536:
        sec.problem("address", f"{type_} at {address} runs past register 65535")
    scale = sec.number("scale", default=1.0)
    if scale == 0:
        sec.problem("scale", "must not be 0")
    offset = sec.number("offset", default=0.0)
    if single and (scale not in (1.0, None) or offset not in (0.0, None)):
        sec.problem("scale" if scale != 1.0 else "offset",
                    "a single-bit value is 0 or 1: scale 1 and offset 0 only")
    unit = sec.string("unit")
    quantity = None
    if unit is not None:
        if unit not in UNITS:
            sec.problem("unit", f"{fmt_value(unit)} is not a supported unit; supported: "
                        f"{', '.join(UNITS)}")
            unit = None
        else:
            quantity = UNITS[unit][0]
    if unit is not None and single and unit != "1":
        sec.problem("unit", f"a single-bit value is 0 or 1: unit must be \"1\", not {unit!r}")
    if unit is not None and name in CANONICAL and CANONICAL[name][0] != quantity:
        want, what = CANONICAL[name]
        sec.problem("unit", f"{unit!r} measures {quantity.replace('_', ' ')}, but {name} is "
                    f"{what}: a {want.replace('_', ' ')} ({', '.join(_units_of(want))})")
    if "range" in sec.data or not single:
        if "range" not in sec.data:
            sec.p.add(sec.file, sec.where, "range", "missing required key")
        rng = sec.range("range")
    else:
        rng = (0.0, 1.0)
    max_age = sec.number("max_age_s", positive=True)
    sentinel = _sentinel(sec, "sentinel", type_) if not single else None
    pressure = None if single else sec.choice("pressure", PRESSURE_KINDS, default=None)
    if quantity == "pressure" and pressure is None and "pressure" not in sec.data:
        sec.p.add(sec.file, sec.where, "pressure",
                  f"required for a pressure tag (unit {unit}): gauge or absolute")
    if unit is not None and quantity != "pressure" and "pressure" in sec.data and not single:
        sec.problem("pressure", f"only for pressure units ({', '.join(PRESSURE_UNITS)}), "
                    f"unit is {unit!r}")
    # issue 9 item 17 (edge.aggregate's flat-line check): seconds >= 0, 0 = off
    flatline = sec.number("flatline_s", default=None)
    if flatline is not None and flatline < 0:
        sec.problem("flatline_s", f"must be >= 0 (0: no flat-line check), got {flatline:g}")
    device_id = _device_id(sec, "device_id", default=None)
    place = None
    if register and type_ and address is not None:
        place = (name, device_id, register, address, address + register_count(type_), bit,
                 key_line(sec.data, "address"))
    if sec.count() != n0:
        return None, place
    try:
        canonical = canonical_linear(unit, pressure, ambient)
    except UnitError:
        canonical = None    # absolute pressure, plant.yaml not loaded: read values are bad
    return TagConfig(name=name, register=register, address=address, type=type_,
                     byte_order=byte_order, scale=float(scale), offset=float(offset), unit=unit,
                     range=rng, max_age_s=max_age, sentinel=sentinel, pressure=pressure,
                     device_id=device_id, bit=bit, canonical=canonical, flatline_s=flatline), place


def _units_of(quantity: str) -> list[str]:
    return [u for u, (q, _, _) in UNITS.items() if q == quantity]


def _sentinel(sec: Section, key, type_):
    if key not in sec.data or sec.data[key] is None:
        return None
    v = sec.data[key]
    if type_ is None:
        return None  # the type's own problem is reported already
    if type_ in ("float32", "float64"):
        f = finite_float(v)
        if f is None:
            sec.problem(key, f"expected a number (raw {type_} value), got {fmt_value(v)}")
            return None
        return f
    lo, hi = raw_limits(type_)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        sec.problem(key, f"{fmt_value(v)} is not a raw {type_} value ({lo}..{hi})")
        return None
    return v


def _overlaps(p: Problems, file: str, placed: list[tuple]) -> None:
    """Overlapping registers of one device and space; bits of one register may share it."""
    widest = None
    bits_at: dict[int, dict[int, str]] = {}
    for name, _dev, space, start, end, bit, line in sorted(placed, key=lambda t: (t[3], t[0])):
        if bit is not None and widest is not None and widest[5] is not None \
                and widest[3] == start and end == widest[4]:
            other = bits_at.setdefault(start, {widest[5]: widest[0]})
            if bit in other:
                p.add(file, f"tag '{name}'", "bit", f"bit {bit} of {space} {start} is also "
                      f"tag '{other[bit]}'", line=line)
            other[bit] = name
            continue
        if widest is not None and start < widest[4]:
            p.add(file, f"tag '{name}'", "address",
                  f"registers {space} {start}..{end - 1} overlap tag '{widest[0]}' "
                  f"({space} {widest[3]}..{widest[4] - 1})", line=line)
        if widest is None or end > widest[4]:
            widest = (name, _dev, space, start, end, bit, line)


def _advisory_vs_plc_registers(p, gw_file, adv: AdvisoryConfig, tags, tags_path,
                               reserved) -> None:
    """The advisory block is the one writable range: it must not touch a register the PLC owns
    (a ``reserved`` range, or any tag of any device)."""
    for tag in tags:
        if tag.register == adv.register and tag.address < adv.end and adv.start < tag.end:
            p.add(gw_file, "section 'advisory'", "start",
                  f"block {adv.register} {adv.start}..{adv.end - 1} overlaps tag '{tag.name}' "
                  f"({tag.register} {tag.address}..{tag.end - 1}) of {_display(tags_path)}")
    for r in reserved:
        if r.overlaps(adv.register, adv.start, adv.size):
            p.add(gw_file, "section 'advisory'", "start",
                  f"block {adv.register} {adv.start}..{adv.end - 1} overlaps reserved "
                  f"{r.register} {r.first}..{r.last} (registers the PLC owns; the gateway "
                  "writes only the advisory block)")
