"""Simulator settings (config/simulator.yaml) and the register map it serves (tags.yaml, the
advisory block of gateway.yaml).

The simulator interprets these files independently of the gateway (it does not import
``edge.config`` or ``edge.codec``), so a bug in the gateway's config or codec cannot hide itself
in tests. Only the parsing of YAML text is shared: ``edge.yamlfile`` (PyYAML and nothing else of
hp-edge) is the one strict loader of every configuration file, refusing duplicate keys,
anchors/aliases, deep nesting and oversized files the same way everywhere. Errors name the file,
the entry, the key and, for unknown keys, the line.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

from edge.yamlfile import YamlFileError, fmt_value, key_line, load_yaml_or_raise
from model.units import CANONICAL_UNITS

REPO_CONFIG = Path(__file__).resolve().parent.parent / "config"
DEFAULT_CONFIG = REPO_CONFIG / "simulator.yaml"

TYPES = {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2}
TYPE_LIMITS = {"int16": (-32768, 32767), "uint16": (0, 65535), "int32": (-2**31, 2**31 - 1),
               "uint32": (0, 2**32 - 1)}
BYTE_ORDERS = ("ABCD", "CDAB", "BADC", "DCBA")
TAG_KEYS = {"register", "address", "type", "byte_order", "scale", "offset", "unit", "range",
            "max_age_s", "sentinel", "pressure"}


class SimConfigError(ValueError):
    """Invalid simulator configuration; the message names file, entry and key."""


# ------------------------------------------------------------------------------------ tag map --
@dataclass(frozen=True)
class TagSpec:
    """One served value: engineering = raw * scale + offset."""
    name: str
    register: str                  # "input" | "holding"
    address: int
    type: str                      # int16 | uint16 | int32 | uint32 | float32
    byte_order: str = "ABCD"
    scale: float = 1.0
    offset: float = 0.0
    unit: str = ""
    range: tuple[float, float] = (-math.inf, math.inf)
    sentinel: int | None = None
    pressure: str | None = None    # gauge | absolute | None

    @property
    def count(self) -> int:
        return TYPES[self.type]


def read_tags(path: str | Path) -> dict[str, TagSpec]:
    """Read tags.yaml -> {name: TagSpec}, checking what the simulator relies on."""
    path = Path(path)
    doc = load_yaml_file(path)
    tags = doc.get("tags") if isinstance(doc, dict) else None
    if not isinstance(tags, dict) or not tags:
        raise SimConfigError(f"{path}: expected a non-empty mapping 'tags'")
    out: dict[str, TagSpec] = {}
    used: dict[tuple[str, int], str] = {}
    for name, t in tags.items():
        where = f"{path}: tag '{name}'"
        if not isinstance(t, dict):
            raise SimConfigError(f"{where}: expected a mapping")
        unknown = sorted(set(t) - TAG_KEYS, key=str)
        if unknown:
            raise SimConfigError(f"{_at(where, t, unknown[0])}: unknown key '{unknown[0]}' (the "
                                 f"simulator serves keys {', '.join(sorted(TAG_KEYS))})")
        unit = t.get("unit", "")
        if unit not in CANONICAL_UNITS.values() or t.get("pressure") == "absolute":
            raise SimConfigError(f"{where}: key 'unit': the simulator serves values in the "
                                 f"canonical units ({', '.join(CANONICAL_UNITS.values())}, "
                                 f"pressures gauge), not {fmt_value(unit)}"
                                 + (" absolute" if t.get("pressure") == "absolute" else ""))
        for key in ("register", "address", "type"):
            if key not in t:
                raise SimConfigError(f"{where}: missing key '{key}'")
        if t["register"] not in ("input", "holding"):
            raise SimConfigError(f"{where}: key 'register' must be input or holding")
        if t["type"] not in TYPES:
            raise SimConfigError(f"{where}: key 'type' must be one of {', '.join(TYPES)}")
        addr = t["address"]
        if not isinstance(addr, int) or isinstance(addr, bool) or not 0 <= addr <= 65535 - 1:
            raise SimConfigError(f"{where}: key 'address' must be an integer 0..65534")
        bo = t.get("byte_order", "ABCD")
        if bo not in BYTE_ORDERS:
            raise SimConfigError(f"{where}: key 'byte_order' must be one of {', '.join(BYTE_ORDERS)}")
        scale = _number(t.get("scale", 1.0), f"{where}: key 'scale'")
        if scale == 0:
            raise SimConfigError(f"{where}: key 'scale' must not be 0")
        rng = t.get("range", [-math.inf, math.inf])
        if not (isinstance(rng, list) and len(rng) == 2):
            raise SimConfigError(f"{where}: key 'range' must be [low, high]")
        spec = TagSpec(
            name=str(name), register=t["register"], address=addr, type=t["type"], byte_order=bo,
            scale=scale, offset=_number(t.get("offset", 0.0), f"{where}: key 'offset'"),
            unit=str(t.get("unit", "")),
            range=(_number(rng[0], f"{where}: key 'range'"), _number(rng[1], f"{where}: key 'range'")),
            sentinel=t.get("sentinel"), pressure=t.get("pressure"))
        for i in range(spec.count):
            key = (spec.register, addr + i)
            if key in used:
                raise SimConfigError(f"{where}: key 'address' overlaps tag '{used[key]}'")
            used[key] = spec.name
        out[spec.name] = spec
    return out


@dataclass(frozen=True)
class AdvisoryBlock:
    register: str
    start: int
    size: int
    heartbeat_offset: int | None = None   # the heartbeat word the PLC's watchdog watches

    @property
    def heartbeat_address(self) -> int | None:
        return None if self.heartbeat_offset is None else self.start + self.heartbeat_offset

    def contains(self, address: int, count: int) -> bool:
        return self.start <= address and address + count <= self.start + self.size


def read_advisory(path: str | Path) -> AdvisoryBlock:
    """The writable advisory block of gateway.yaml (only register, start, size and the heartbeat
    field's offset are used here)."""
    path = Path(path)
    doc = load_yaml_file(path)
    adv = doc.get("advisory") if isinstance(doc, dict) else None
    if not isinstance(adv, dict):
        raise SimConfigError(f"{path}: missing mapping 'advisory'")
    for key in ("start", "size"):
        v = adv.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise SimConfigError(f"{path}: advisory: key '{key}' must be a non-negative integer")
    if adv.get("register", "holding") != "holding":
        raise SimConfigError(f"{path}: advisory: key 'register' must be holding (it is written)")
    if not 1 <= adv["size"] <= 123 or adv["start"] + adv["size"] > 65536:
        raise SimConfigError(f"{path}: advisory: key 'size' must be 1..123 inside the address space")
    hb = (adv.get("fields") or {}).get("heartbeat") if isinstance(adv.get("fields"), dict) else None
    offset = hb.get("offset") if isinstance(hb, dict) else None
    if offset is not None and (not isinstance(offset, int) or isinstance(offset, bool)
                               or not 0 <= offset < adv["size"]):
        raise SimConfigError(f"{path}: advisory: field 'heartbeat': key 'offset' must be an integer "
                             f"inside the block (0..{adv['size'] - 1})")
    return AdvisoryBlock("holding", adv["start"], adv["size"], offset)


# ---------------------------------------------------------------------------- simulator.yaml --
@dataclass(frozen=True)
class TimeCfg:
    tick_s: float = 5.0
    solve_interval_s: float = 60.0
    truth_interval_s: float = 60.0
    optimum_interval_s: float = 3600.0


@dataclass(frozen=True)
class CompressorTruth:
    eta_is_scale: float = 1.0
    eta_is_pi_tilt: float = 0.0
    eta_vol_scale: float = 1.0
    eta_vol_n_tilt: float = 0.0


PERTURBED = "perturbed"      # truth.compressors.family: plant.yaml's polynomials perturbed (LS/HS)
NOMINAL = "nominal"          # ... plant.yaml's polynomials exactly (the model's own curves)
RESERVED_FAMILIES = (PERTURBED, NOMINAL)


@dataclass(frozen=True)
class TruthCfg:
    CF_eva: float = 1.0
    CF_con: float = 1.0
    CF_DSH: float = 1.0
    CF_SC: float = 1.0
    motor_efficiency: float = 1.0
    compressors: dict = field(default_factory=dict)   # "LS"/"HS" -> CompressorTruth
    compressor_family: str = PERTURBED                # or a key of compressor_families


@dataclass(frozen=True)
class FlowCfg:
    exponent: float = 0.8
    water_side_share_eva: float = 0.5
    water_side_share_con: float = 0.4
    V_source_nom_m3h: float = 192.0
    V_sink_nom_m3h: float = 62.0


@dataclass(frozen=True)
class FoulingCfg:
    R_th_f_initial_K_per_kW: float = 2.5e-3
    R_th_f_inf_K_per_kW: float = 6.0e-3
    tau_days: float = 15.0
    CF_dp_f_initial: float = 1.08
    CF_dp_f_inf: float = 1.4
    tau_dp_days: float = 20.0


CIP_MODES = ("schedule", "on_request")


@dataclass(frozen=True)
class CipCfg:
    mode: str = "schedule"             # schedule | on_request (Plant.request_cip / request register)
    first_after_days: float = 9.0
    interval_days: float = 14.0
    jitter_days: float = 1.0
    duration_days: float = 2.5
    removal_share: float = 0.15
    dp_removal_share: float = 0.30
    request_register: int | None = None   # holding address a client writes 1 to (on_request mode)


@dataclass(frozen=True)
class ControlCfg:
    T_source_out_sp_C: float = 18.0
    p_m_sp_bar_g: float = 16.0
    p_m_sp_limits_bar_g: tuple = (4.0, 35.0)
    standstill_T_C: float = 20.0
    p_m_sp_schedule: tuple = ()        # ((from_day, bar_g), ...): the PLC's own set-point steps


@dataclass(frozen=True)
class RemoteSetpointCfg:
    """The PLC's program for a remote (supervisory) set point (simulator/remote.py,
    docs/closed_loop.md). enabled False: a PLC without it, where any client write to the set-point
    register is taken (clamped into control.p_m_sp_limits_bar_g)."""
    enabled: bool = False
    enable_tag: str = "closed_loop_enable"   # holding register of tags.yaml the operator sets (0/1)
    bounds_bar_g: tuple = (8.0, 22.0)        # a remote set point outside is refused (exception 3)
    heartbeat_timeout_s: float = 60.0        # wall seconds without a heartbeat change: fallback


T_C_LOCATIONS = ("condenser_outlet", "subcooler_outlet")


@dataclass(frozen=True)
class SensorsCfg:
    T_c: str = "condenser_outlet"      # where the "condenser outlet" T_c sensor sits


@dataclass(frozen=True)
class ProfileCfg:
    T_source_in_mean_C: float = 24.0
    T_source_in_daily_amp_K: float = 0.8
    T_source_in_peak_hour: float = 16.0
    T_sink_in_mean_C: float = 40.0
    T_sink_in_daily_amp_K: float = 0.6
    T_sink_in_peak_hour: float = 14.0
    V_sink_mean_m3h: float = 62.0
    V_sink_daily_amp: float = 0.10
    V_sink_peak_hour: float = 7.0
    V_source_mean_m3h: float = 192.0
    V_source_daily_amp: float = 0.03
    V_source_peak_hour: float = 11.0
    weather_sigma: float = 1.0
    weather_tau_h: float = 36.0
    weather_T_source_K: float = 0.5
    weather_V_sink: float = -0.06
    p_source_in_bar_g: float = 2.5
    limits_T_source_in_C: tuple = (22.5, 25.5)
    limits_V_sink_m3h: tuple = (45.0, 75.0)


@dataclass(frozen=True)
class LagCfg:
    temperature: float = 180.0
    pressure: float = 60.0
    flow: float = 20.0
    power: float = 20.0
    speed: float = 15.0


@dataclass(frozen=True)
class FaultSpec:
    """One fault. Tag faults: stuck, out_of_range, nan. Server faults: slow, drop, frozen, restart."""
    kind: str
    tag: str | None = None
    at_h: float | None = None          # scheduled start (plant hours after start_time); None = now
    duration_h: float | None = None    # None = until switched off / the end
    value: float | None = None         # out_of_range: engineering value served
    delay_s: float = 2.0               # slow
    probability: float = 1.0           # slow, drop
    down_s: float = 2.0                # restart


TAG_FAULTS = ("stuck", "out_of_range", "nan")
SERVER_FAULTS = ("slow", "drop", "frozen", "restart")
FAULT_KINDS = TAG_FAULTS + SERVER_FAULTS


@dataclass(frozen=True)
class SimulatorConfig:
    path: Path | None = None
    tags_file: Path = REPO_CONFIG / "tags.yaml"
    gateway_file: Path = REPO_CONFIG / "gateway.yaml"
    plant_file: Path = REPO_CONFIG / "plant.yaml"
    device_id: int = 1
    seed: int = 1
    start_time: str = "2024-03-01T00:00:00Z"
    ambient_pressure_bar: float = 1.01325
    time: TimeCfg = TimeCfg()
    truth: TruthCfg = TruthCfg()
    flow_dependence: FlowCfg = FlowCfg()
    fouling: FoulingCfg = FoulingCfg()
    cip: CipCfg = CipCfg()
    control: ControlCfg = ControlCfg()
    profiles: ProfileCfg = ProfileCfg()
    lags_s: LagCfg = LagCfg()
    sensors: SensorsCfg = SensorsCfg()
    remote_setpoint: RemoteSetpointCfg = RemoteSetpointCfg()
    noise: dict = field(default_factory=dict)       # tag -> sigma [engineering unit]
    faults: tuple = ()                              # FaultSpec
    compressor_families: dict = field(default_factory=dict)   # name -> {"LS": {...}, "HS": {...}}

    def replace(self, **kw) -> "SimulatorConfig":
        return dataclasses.replace(self, **kw)

    def with_compressor_family(self, name: str) -> "SimulatorConfig":
        """This config with the hidden compressors of family ``name``: a key of
        compressor_families, "perturbed" (plant.yaml's polynomials perturbed by truth.compressors.LS
        and HS, the default) or "nominal" (plant.yaml's polynomials exactly)."""
        check_family(name, self.compressor_families, f"{self.path or '<simulator config>'}: "
                                                      "truth.compressors")
        return self.replace(truth=dataclasses.replace(self.truth, compressor_family=name))

    def with_sections(self, **sections) -> "SimulatorConfig":
        """This config with some keys of some sections changed, checked like a loaded file:
        ``cfg.with_sections(cip={"mode": "on_request"}, sensors={"T_c": "subcooler_outlet"})``."""
        kw = {}
        for name, changes in sections.items():
            current = getattr(self, name)
            if not dataclasses.is_dataclass(current):
                raise SimConfigError(f"<simulator config>: '{name}' is not a section")
            doc = {f.name: getattr(current, f.name) for f in dataclasses.fields(current)}
            doc.update(changes)
            kw[name] = _section(name, doc, f"<simulator config>: {name}")
        cfg = self.replace(**kw)
        _check(cfg, "<simulator config>")
        return cfg

    @property
    def start_epoch(self) -> float:
        from datetime import datetime, timezone
        s = self.start_time.replace("Z", "+00:00")
        dt = datetime.fromisoformat(s)
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=timezone.utc)
        return dt.timestamp()


_SECTIONS = {"time": TimeCfg, "flow_dependence": FlowCfg, "fouling": FoulingCfg, "cip": CipCfg,
             "control": ControlCfg, "profiles": ProfileCfg, "lags_s": LagCfg, "sensors": SensorsCfg,
             "remote_setpoint": RemoteSetpointCfg}
FAMILY_KEYS = ("eta_is_max", "eta_is_floor", "pi_opt", "w_ln_pi", "n_opt", "w_n",
               "vol_a", "vol_b", "vol_k", "vol_c")     # simulator.compressors.STAGE_KEYS


def load_simulator_config(path: str | Path | None = None) -> SimulatorConfig:
    """Read config/simulator.yaml (or ``path``); relative file names resolve against its folder."""
    path = Path(path) if path is not None else DEFAULT_CONFIG
    doc = load_yaml_file(path)
    if not isinstance(doc, dict):
        raise SimConfigError(f"{path}: expected a mapping at top level")
    return config_from_dict(doc, path)


def config_from_dict(doc: dict, path: Path | None = None) -> SimulatorConfig:
    where = str(path) if path else "<simulator config>"
    base = path.parent if path else REPO_CONFIG
    known = {f.name for f in dataclasses.fields(SimulatorConfig)} - {"path"}
    unknown = sorted(set(doc) - known, key=str)
    if unknown:
        raise SimConfigError(f"{_at(where, doc, unknown[0])}: unknown key '{unknown[0]}'")
    kw: dict = {"path": path}
    for key in ("tags_file", "gateway_file", "plant_file"):
        if key in doc:
            p = Path(str(doc[key]))
            kw[key] = p if p.is_absolute() else base / p
    for key in ("device_id", "seed"):
        if key in doc:
            v = doc[key]
            if not isinstance(v, int) or isinstance(v, bool) or v < 0:
                raise SimConfigError(f"{where}: key '{key}' must be a non-negative integer")
            kw[key] = v
    if "device_id" in kw and kw["device_id"] > 247:
        raise SimConfigError(f"{where}: key 'device_id' must be 0..247")
    if "start_time" in doc:
        kw["start_time"] = str(doc["start_time"])
    if "ambient_pressure_bar" in doc:
        kw["ambient_pressure_bar"] = _number(doc["ambient_pressure_bar"],
                                             f"{where}: key 'ambient_pressure_bar'")
    for key in _SECTIONS:
        if key in doc:
            kw[key] = _section(key, doc[key], f"{where}: {key}")
    if "compressor_families" in doc:
        kw["compressor_families"] = _families(doc["compressor_families"] or {}, where)
    if "truth" in doc:
        if not isinstance(doc["truth"] or {}, dict):
            raise SimConfigError(f"{where}: key 'truth' must be a mapping")
        t = dict(doc["truth"] or {})
        comps = t.pop("compressors", {}) or {}
        if "compressor_family" in t:
            raise SimConfigError(f"{where}: truth: unknown key 'compressor_family' "
                                 "(the family is truth.compressors.family)")
        truth = _dataclass_from(TruthCfg, t, f"{where}: truth")
        if not isinstance(comps, dict) or set(comps) - {"LS", "HS", "family"}:
            raise SimConfigError(f"{where}: truth: key 'compressors' takes family, LS and HS only")
        comps = dict(comps)
        family = comps.pop("family", PERTURBED)
        family = PERTURBED if family is None else family
        check_family(family, kw.get("compressor_families", {}), f"{where}: truth.compressors")
        kw["truth"] = dataclasses.replace(truth, compressor_family=str(family), compressors={
            k: _dataclass_from(CompressorTruth, v, f"{where}: truth.compressors.{k}")
            for k, v in comps.items()})
    if "noise" in doc:
        noise = doc["noise"] or {}
        if not isinstance(noise, dict):
            raise SimConfigError(f"{where}: key 'noise' must map tag -> sigma")
        kw["noise"] = {str(k): _number(v, f"{where}: noise: key '{k}'") for k, v in noise.items()}
    if "faults" in doc:
        items = doc["faults"] or []
        if not isinstance(items, list):
            raise SimConfigError(f"{where}: key 'faults' must be a list")
        kw["faults"] = tuple(fault_from_dict(f, f"{where}: faults[{i}]") for i, f in enumerate(items))
    cfg = SimulatorConfig(**kw)
    _check(cfg, where)
    return cfg


def _section(key: str, d, where: str):
    """One section of simulator.yaml -> its dataclass, with the keys that need more than a
    number checked here (the CIP mode and request register, the set-point schedule, sensors)."""
    if key == "cip" and isinstance(d, dict):
        d = dict(d)
        reg = d.pop("request_register", None)
        mode = d.pop("mode", "schedule")
        cfg = _dataclass_from(CipCfg, d, where)
        if mode not in CIP_MODES:
            raise SimConfigError(f"{where}: key 'mode' must be one of {', '.join(CIP_MODES)}, got {mode!r}")
        if reg is not None and (not isinstance(reg, int) or isinstance(reg, bool) or not 0 <= reg <= 65535):
            raise SimConfigError(f"{where}: key 'request_register' must be a holding address 0..65535")
        return dataclasses.replace(cfg, mode=mode, request_register=reg)
    if key == "control" and isinstance(d, dict):
        d = dict(d)
        sched = d.pop("p_m_sp_schedule", ()) or ()
        cfg = _dataclass_from(ControlCfg, d, where)
        return dataclasses.replace(cfg, p_m_sp_schedule=_schedule(sched, cfg, where))
    if key == "remote_setpoint" and isinstance(d, dict):
        d = dict(d)
        enabled = d.pop("enabled", False)
        tag = d.pop("enable_tag", RemoteSetpointCfg.enable_tag)
        cfg = _dataclass_from(RemoteSetpointCfg, d, where)
        if not isinstance(enabled, bool):
            raise SimConfigError(f"{where}: key 'enabled' must be true or false, got {fmt_value(enabled)}")
        if not isinstance(tag, str) or not tag:
            raise SimConfigError(f"{where}: key 'enable_tag' must be a tag name, got {fmt_value(tag)}")
        lo, hi = cfg.bounds_bar_g
        if not lo < hi:
            raise SimConfigError(f"{where}: key 'bounds_bar_g' must be [low, high] with low < high")
        if not cfg.heartbeat_timeout_s > 0:
            raise SimConfigError(f"{where}: key 'heartbeat_timeout_s' must be > 0")
        return dataclasses.replace(cfg, enabled=enabled, enable_tag=tag)
    if key == "sensors" and isinstance(d, dict):
        cfg = _dataclass_from(SensorsCfg, d, where)
        if cfg.T_c not in T_C_LOCATIONS:
            raise SimConfigError(f"{where}: key 'T_c' must be one of {', '.join(T_C_LOCATIONS)}, "
                                 f"got {cfg.T_c!r}")
        return cfg
    return _dataclass_from(_SECTIONS[key], d, where)


def _schedule(items, control: ControlCfg, where: str) -> tuple:
    """control.p_m_sp_schedule: [[from_day, bar_g], ...], from_day >= 0 and rising, set points
    inside p_m_sp_limits_bar_g (a schedule is not clamped like a client write: it is checked)."""
    what = f"{where}: key 'p_m_sp_schedule'"
    if not isinstance(items, (list, tuple)):
        raise SimConfigError(f"{what} must be a list of [from_day, bar_g] pairs")
    lo, hi = control.p_m_sp_limits_bar_g
    out, last = [], -math.inf
    for i, item in enumerate(items):
        if not (isinstance(item, (list, tuple)) and len(item) == 2):
            raise SimConfigError(f"{what}: entry {i} must be a [from_day, bar_g] pair, got {item!r}")
        day = _number(item[0], f"{what}: entry {i} from_day")
        bar = _number(item[1], f"{what}: entry {i} bar_g")
        if day < 0 or day <= last:
            raise SimConfigError(f"{what}: entry {i}: from_day must be >= 0 and rise from entry "
                                 f"to entry, got {day:g}")
        if not lo <= bar <= hi:
            raise SimConfigError(f"{what}: entry {i}: set point {bar:g} bar(g) is outside "
                                 f"p_m_sp_limits_bar_g [{lo:g}, {hi:g}]")
        out.append((day, bar))
        last = day
    return tuple(out)


def _families(d, where: str) -> dict:
    """compressor_families: NAME -> {LS: {...}, HS: {...}} with the keys of FAMILY_KEYS."""
    if not isinstance(d, dict):
        raise SimConfigError(f"{where}: key 'compressor_families' must map a family name to LS and HS")
    out = {}
    for name, fam in d.items():
        w = f"{where}: compressor_families.{name}"
        if str(name) in RESERVED_FAMILIES:
            raise SimConfigError(f"{w}: the name '{name}' is reserved ({PERTURBED}: plant.yaml's curves "
                                 f"perturbed by truth.compressors.LS/HS; {NOMINAL}: plant.yaml's curves)")
        if not isinstance(fam, dict) or set(fam) != {"LS", "HS"}:
            raise SimConfigError(f"{w}: expected the keys LS and HS")
        stages = {}
        for stage in ("LS", "HS"):
            s = fam[stage]
            ws = f"{w}.{stage}"
            if not isinstance(s, dict):
                raise SimConfigError(f"{ws}: expected a mapping")
            unknown = set(s) - set(FAMILY_KEYS)
            if unknown:
                raise SimConfigError(f"{ws}: unknown key '{sorted(unknown)[0]}'")
            vals = {}
            for k, v in s.items():
                if k == "n_opt" and v is None:
                    vals[k] = None
                    continue
                vals[k] = _number(v, f"{ws}: key '{k}'")
            for k in ("w_ln_pi", "w_n", "vol_k", "pi_opt"):
                if k in vals and not vals[k] > 0:
                    raise SimConfigError(f"{ws}: key '{k}' must be > 0")
            for k in ("eta_is_max", "eta_is_floor"):
                if k in vals and not 0.05 < vals[k] <= 1.0:
                    raise SimConfigError(f"{ws}: key '{k}' must be within (0.05, 1]")
            stages[stage] = vals
        out[str(name)] = stages
    return out


def check_family(name, families: dict, where: str) -> None:
    if name not in RESERVED_FAMILIES and name not in families:
        known = ", ".join(list(RESERVED_FAMILIES) + sorted(families))
        raise SimConfigError(f"{where}: key 'family': unknown compressor family {name!r} "
                             f"(known: {known})")


def fault_from_dict(d: dict, where: str = "fault") -> FaultSpec:
    spec = _dataclass_from(FaultSpec, d, where, required=("kind",))
    if spec.kind not in FAULT_KINDS:
        raise SimConfigError(f"{where}: key 'kind' must be one of {', '.join(FAULT_KINDS)}")
    if spec.kind in TAG_FAULTS and not spec.tag:
        raise SimConfigError(f"{where}: key 'tag' is required for kind {spec.kind}")
    if spec.kind in SERVER_FAULTS and spec.tag:
        raise SimConfigError(f"{where}: key 'tag' does not apply to kind {spec.kind}")
    if not 0.0 <= spec.probability <= 1.0:
        raise SimConfigError(f"{where}: key 'probability' must be within 0..1")
    if spec.delay_s < 0 or spec.down_s < 0:
        raise SimConfigError(f"{where}: delay_s and down_s must be >= 0")
    return spec


def _check(cfg: SimulatorConfig, where: str) -> None:
    try:
        cfg.start_epoch
    except ValueError as exc:
        raise SimConfigError(f"{where}: key 'start_time' is not ISO 8601: {exc}") from None
    t = cfg.time
    if not (t.tick_s > 0 and t.solve_interval_s >= t.tick_s and t.truth_interval_s > 0
            and t.optimum_interval_s > 0):
        raise SimConfigError(f"{where}: time: need tick_s > 0 and solve_interval_s >= tick_s")
    for name in ("removal_share", "dp_removal_share"):
        if not 0.0 <= getattr(cfg.cip, name) <= 1.0:
            raise SimConfigError(f"{where}: cip: key '{name}' must be within 0..1")
    if cfg.cip.mode == "schedule" and cfg.cip.interval_days <= cfg.cip.duration_days + 2 * cfg.cip.jitter_days:
        raise SimConfigError(f"{where}: cip: key 'interval_days' must exceed duration + 2 jitter")
    if cfg.cip.mode != "on_request" and cfg.cip.request_register is not None:
        raise SimConfigError(f"{where}: cip: key 'request_register' applies to mode on_request only")
    if not cfg.cip.duration_days > 0:
        raise SimConfigError(f"{where}: cip: key 'duration_days' must be > 0")
    lo, hi = cfg.control.p_m_sp_limits_bar_g
    if not lo < hi:
        raise SimConfigError(f"{where}: control: key 'p_m_sp_limits_bar_g' must be [low, high]")
    blo, bhi = cfg.remote_setpoint.bounds_bar_g
    if not lo <= blo < bhi <= hi:
        raise SimConfigError(f"{where}: remote_setpoint: key 'bounds_bar_g' [{blo:g}, {bhi:g}] must lie "
                             f"within control.p_m_sp_limits_bar_g [{lo:g}, {hi:g}]")
    for name in ("water_side_share_eva", "water_side_share_con"):
        if not 0.0 <= getattr(cfg.flow_dependence, name) < 1.0:
            raise SimConfigError(f"{where}: flow_dependence: key '{name}' must be within 0..1")
    for f in dataclasses.fields(LagCfg):
        if getattr(cfg.lags_s, f.name) < 0:
            raise SimConfigError(f"{where}: lags_s: key '{f.name}' must be >= 0")
    if any(v < 0 for v in cfg.noise.values()):
        raise SimConfigError(f"{where}: noise: sigmas must be >= 0")


# ----------------------------------------------------------------------------------- helpers --
def load_yaml_file(path: Path):
    """The strict loader of every hp-edge configuration file (edge.yamlfile); SimConfigError
    with every problem."""
    try:
        return load_yaml_or_raise(path, str(path))
    except YamlFileError as exc:
        raise SimConfigError(str(exc)) from None


def _at(where: str, data, key) -> str:
    """``where`` with the line of ``key`` when known: 'file: line 12: truth'."""
    line = key_line(data, key)
    if line is None:
        return where
    file, _, rest = where.partition(": ")
    return f"{file}: line {line}" + (f": {rest}" if rest else "")


def _number(v, where: str) -> float:
    ok = not isinstance(v, bool) and isinstance(v, (int, float))
    try:
        ok = ok and math.isfinite(float(v))
    except OverflowError:       # an integer too large for a float
        ok = False
    if not ok:
        raise SimConfigError(f"{where} must be a finite number, got {fmt_value(v)}")
    return float(v)


def _dataclass_from(cls, d, where: str, required: tuple = ()):
    if not isinstance(d, dict):
        raise SimConfigError(f"{where}: expected a mapping")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - set(fields), key=str)
    if unknown:
        raise SimConfigError(f"{_at(where, d, unknown[0])}: unknown key '{unknown[0]}'")
    for key in required:
        if key not in d:
            raise SimConfigError(f"{where}: missing key '{key}'")
    kw = {}
    for key, v in d.items():
        default = fields[key].default
        if isinstance(default, tuple):
            if not (isinstance(v, (list, tuple)) and len(v) == len(default)):
                raise SimConfigError(f"{where}: key '{key}' must be a list of {len(default)} numbers")
            kw[key] = tuple(_number(x, f"{where}: key '{key}'") for x in v)
        elif isinstance(default, float) or (default is None and key not in ("tag", "kind")):
            if v is None and default is not None:    # only optional values may be left empty
                raise SimConfigError(f"{where}: key '{key}' must be a finite number, got null")
            kw[key] = None if v is None else _number(v, f"{where}: key '{key}'")
        else:
            kw[key] = v if v is None else str(v)
    return cls(**kw)
