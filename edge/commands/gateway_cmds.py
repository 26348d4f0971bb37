"""Gateway sub-commands: check-config, read, run and demo (one function each).

Heavy imports (pymodbus via edge.plc) happen inside the command functions.
"""
from __future__ import annotations

import argparse
import logging
import sys

CONFIG_HELP = ("gateway.yaml (default: config/gateway.yaml, else /etc/hp-edge/gateway.yaml, else "
               "the one shipped with the package)")

# What each status bit means (SPEC 7.3); docs/registers.md is rendered from the YAML plus this.
STATUS_BIT_NOTES = {   # what edge/loop.py does, word for word (the HMI map is generated from it)
    "data_stale": "no fresh data: a tag not read good for its max_age_s, a frozen life counter, "
                  "or the last poll failed",
    "heat_pump_off": "running flag reads 0 (without a good running flag: W_LS + W_HS < 20 kW)",
    "cip_detected": "CIP flag reads 1 (cleaning in place)",
    "calibration_failed": "no fouling calibration yet, or the last one failed",
    "model_infeasible": "the last set-point optimization found no feasible point in the window",
    "comm_fault": "the last poll got no usable answer, or one failed since the previous successful "
                  "advisory write (the first block after an outage carries it)",
    "advice_stale": "values are not a current advice: the last attempt failed, there are none "
                    "(NaN), they are older than 1.5 calibration intervals (see advice_age_s), or "
                    "their age is unknown (advice_age_s = 4294967295: no sample clock yet, or "
                    "the advice is from a later time than the sample clock shows)",
    "advice_low_confidence": "the model cannot tell where the optimum lies, so p_m_sp_rec is the "
                             "current set point: compressor curves not learned yet, operation or "
                             "the optimum outside the region the curves have data for, or an "
                             "expected gain not larger than its uncertainty (dCOP_sd_pct)",
    # issue 9 (runtime): storage, clock and sensor faults
    "storage_fault": "the history or the state directory is not writable (locked by another "
                     "process, disk full, read-only): the advice is still computed and written, "
                     "rows wait in memory, and the bit clears by itself once a write succeeds",
    "clock_fault": "the sample clock of the last scan was rejected as implausible (ahead of the "
                   "host clock by more than a day, back by more than 10 s, or a jump the elapsed "
                   "time cannot explain), or one was since the previous successful advisory "
                   "write; the scan is not aggregated. A jump that persists 5 min is accepted as "
                   "a clock correction",
    "sensor_fault": "while the heat pump runs and the PLC answers, a required tag has flat-lined "
                    "(no change beyond its resolution for its flatline_s; reason 'flatline') or "
                    "has not been read good for its max_age_s",
}


def register(sub) -> None:
    """Add this module's sub-commands to the argparse sub-parsers."""
    p = sub.add_parser("check-config", help="validate the configuration and print the layout",
                       description="Validate gateway.yaml, tags.yaml and plant.yaml without "
                       "touching the network; print tags, planned reads and the advisory block.")
    p.add_argument("--config", default=None, help=CONFIG_HELP)
    p.add_argument("--markdown", action="store_true",
                   help="print the register map as Markdown (the source of docs/registers.md)")
    p.set_defaults(func=cmd_check_config)

    p = sub.add_parser("read", help="read the advisory block once, as the HMI sees it",
                       description="Connect to any Modbus TCP server, read the advisory block "
                       "once and print it decoded (status bits by name).")
    p.add_argument("--config", default=None, help=CONFIG_HELP)
    p.add_argument("--host", help="override plc.host")
    p.add_argument("--port", type=int, help="override plc.port")
    p.add_argument("--device-id", type=int, help="override plc.device_id")
    p.add_argument("--timeout", type=float, default=3.0,
                   help="give up after this many seconds in total (default: %(default)s)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_read)

    register_run_demo(sub)


def load_config_or_report(path, load_plant: bool = True):
    """The validated configuration, or None after printing every problem (file, tag, key) to
    stderr; callers then exit with code 2 before touching the network."""
    from edge.config import ConfigError, find_config, load_config
    from edge.yamlfile import format_problems

    try:
        return load_config(find_config("gateway.yaml", path), load_plant=load_plant)
    except ConfigError as exc:
        for line in format_problems(exc.problems):
            print(line, file=sys.stderr)
        print(f"{len(exc.problems)} problem(s); nothing was started.", file=sys.stderr)
        return None


# ------------------------------------------------------------------------------ check-config


def cmd_check_config(args: argparse.Namespace) -> int:
    cfg = load_config_or_report(args.config)
    if cfg is None:
        return 2
    print(render_markdown(cfg) if args.markdown else render_layout(cfg), end="")
    return 0


def _read_plan(cfg):
    """(device, space, request) exactly as the gateway will send them."""
    from edge.codec import plan_groups

    return plan_groups(cfg.tags, cfg.plc.device_id, cfg.plc.max_read_gap)


def _num(x) -> str:
    from edge.codec import format_number

    return "" if x is None else format_number(x)


def _range(t) -> str:
    return f"[{_num(t.range[0])}, {_num(t.range[1])}]"


def _order(type_: str, byte_order: str) -> str:
    from edge.codec import register_count

    if type_ == "bool":
        return ""
    if register_count(type_) == 1:
        return "BA" if byte_order == "BA" else "AB"
    return byte_order


def _ref(space: str, address: int) -> str:
    """Modicon-style 1-based reference (0xxxx coil, 1xxxx discrete input, 3xxxx input register,
    4xxxx holding register) that many HMIs use."""
    prefix = {"coil": 0, "discrete_input": 1, "input": 3, "holding": 4}[space]
    return f"{prefix}{address + 1:04d}" if address < 9999 else f"{prefix}{address + 1:05d}"


def _addr(t, sep: str = "–") -> str:
    """'6–7' for a two-register value, '30.2' for bit 2 of register 30."""
    if t.bit is not None:
        return f"{t.address}.{t.bit}"
    return f"{t.address}" + (f"{sep}{t.end - 1}" if t.count > 1 else "")


def _tag_ref(t) -> str:
    ref = _ref(t.register, t.address) + (f"–{_ref(t.register, t.end - 1)}" if t.count > 1 else "")
    return ref + (f".{t.bit}" if t.bit is not None else "")


def _unit(t) -> str:
    """The tag's unit, and the canonical one it is converted to when they differ."""
    text = t.unit + (" abs" if t.pressure == "absolute" else "")
    canon = "bar(g)" if t.pressure else t.canonical_unit
    return text if (t.unit == t.canonical_unit and t.pressure != "absolute") \
        else f"{text} -> {canon}"


def _devices(cfg) -> bool:
    return any(t.device_id not in (None, cfg.plc.device_id) for t in cfg.tags)


def _fc(space: str) -> int:
    from edge.codec import READ_FUNCTION

    return READ_FUNCTION[space]


def _table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h)
              for i, h in enumerate(header)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip()
             for row in [header, *rows]]
    return "\n".join("  " + ln for ln in lines) + "\n"


def render_layout(cfg) -> str:
    """Human-readable layout printed by check-config."""
    adv = cfg.advisory
    out = [f"OK: {cfg.path}\n",
           f"  tags: {cfg.tags_file}\n  plant: {cfg.plant_file}\n",
           f"  PLC {cfg.plc.host}:{cfg.plc.port} device {cfg.plc.device_id}; timeout "
           f"{cfg.plc.timeout_s:g} s per request; reconnect {cfg.plc.reconnect_min_s:g}.."
           f"{cfg.plc.reconnect_max_s:g} s; scan every {cfg.scan_interval_s:g} s\n",
           f"\nTags ({len(cfg.tags)})\n"]
    devices = _devices(cfg)
    rows = [[t.name, t.register, _addr(t, ".."), t.type, _order(t.type, t.byte_order),
             _num(t.scale), _num(t.offset), t.unit, _range(t), _num(t.sentinel),
             t.pressure or ""] + ([str(t.device_id or cfg.plc.device_id)] if devices else [])
            for t in cfg.tags]
    out.append(_table(["name", "space", "addr", "type", "order", "scale", "offset", "unit",
                       "range", "sentinel", "pressure"] + (["device"] if devices else []), rows))
    converted = [f"{t.name} ({_unit(t)})" for t in cfg.tags
                 if t.unit != t.canonical_unit or t.pressure == "absolute"]
    if converted:
        out.append("  converted to canonical units: " + ", ".join(converted) + "\n")
    plan = list(_read_plan(cfg))
    out.append(f"\nRead plan ({len(plan)} request(s) per scan"
               f"{', connection closed after each poll' if cfg.plc.close_after_poll else ''})\n")
    for dev, space, req in plan:
        what = ("bit" if space in ("coil", "discrete_input") else "register") \
            + ("s" if req.count != 1 else "")
        out.append(f"  FC{_fc(space)} {space} {req.start}..{req.start + req.count - 1} "
                   f"({req.count} {what})" + (f" device {dev}" if devices else "")
                   + f": {', '.join(t.name for t in req.tags)}\n")
    out.append(f"\nAdvisory block: {adv.register} {adv.start}..{adv.end - 1} ({adv.size} "
               f"registers, 32-bit order {adv.byte_order}), written in one FC16 request; "
               + _closed_loop_line(cfg) + "\n")
    if cfg.reserved:
        out.append("  reserved (PLC-owned, never written): " + ", ".join(
            f"{r.register} {r.first}..{r.last}" for r in cfg.reserved) + "\n")
    rows = [[f"{adv.start + f.offset}" + (f"..{adv.start + f.offset + 1}" if f.count == 2 else ""),
             str(f.offset), f.name, f.type, f.unit, f.description] for f in adv.fields]
    out.append(_table(["address", "offset", "field", "type", "unit", "description"], rows))
    status = adv.field("status")
    out.append(f"\nStatus bits (register {adv.start + status.offset})\n")
    out.append(_table(["bit", "mask", "name"],
                      [[str(b), f"0x{1 << b:04X}", n] for b, n in adv.status_bits]))
    return "".join(out)


def _closed_loop_line(cfg) -> str:
    """What else than the advisory block the gateway writes (check-config)."""
    cl = cfg.closed_loop
    if cl is None or not cl.enabled:
        return "the only registers the gateway writes (closed loop off)"
    t = cfg.tag(cl.setpoint_tag)
    return (f"the only registers the gateway writes besides the closed loop's set point "
            f"'{t.name}' ({t.register} {_addr(t, '..')}: ON, bounds {_num(cl.bounds_bar_g[0])}.."
            f"{_num(cl.bounds_bar_g[1])} bar(g), step {_num(cl.max_step_bar)} bar per "
            f"{_num(cl.min_interval_s)} s, while '{cl.enable_tag}' is 1)")


def _closed_loop_markdown(cfg) -> str:
    """The closed loop's paragraph and code tables of docs/registers.md."""
    from edge.closed_loop import REASON_NOTES, State

    cl = cfg.closed_loop
    adv = cfg.advisory
    fields = {f.name for f in adv.fields}
    if cl is not None and cl.enabled:
        t = cfg.tag(cl.setpoint_tag)
        head = (f"The opt-in closed loop (SPEC 7.4, docs/closed_loop.md) is **enabled** in "
                f"`{cfg.path.name}`: besides this block the gateway writes the set-point register "
                f"`{t.name}` ({t.register} {_addr(t)}) and nothing else, only while the operator's "
                f"`{cl.enable_tag}` is 1, inside {_num(cl.bounds_bar_g[0])}–"
                f"{_num(cl.bounds_bar_g[1])} bar(g), at most {_num(cl.max_step_bar)} bar per "
                f"{_num(cl.min_interval_s)} s; the PLC falls back when the heartbeat has not "
                f"changed for {_num(cl.heartbeat_timeout_s)} s.")
    else:
        head = (f"The opt-in closed loop (SPEC 7.4, docs/closed_loop.md) is **off** in "
                f"`{cfg.path.name}` (`closed_loop.enabled: false`): the gateway writes no "
                f"register but this block.")
    md = [f"\n### Closed loop\n\n{head}\n"]
    if "closed_loop_state" in fields:
        reg = adv.start + adv.field("closed_loop_state").offset
        md.append(f"\n`closed_loop_state` (register {reg}):\n\n| value | state | meaning |\n"
                  "|---|---|---|\n")
        meaning = {State.OFF: "not enabled (gateway.yaml or the operator): no set-point write",
                   State.ARMED: "enabled and holding: at the recommendation, or a guard holds it",
                   State.WRITING: "enabled and moving the set point toward the recommendation",
                   State.SHED: "stopped itself; writes nothing until the operator drops the enable"}
        for st in State:
            md.append(f"| {int(st)} | `{st.name.lower()}` | {meaning[st]} |\n")
    if "closed_loop_reason" in fields:
        reg = adv.start + adv.field("closed_loop_reason").offset
        md.append(f"\n`closed_loop_reason` (register {reg}):\n\n| value | reason | meaning |\n"
                  "|---|---|---|\n")
        for r, note in REASON_NOTES.items():
            md.append(f"| {int(r)} | `{r.name.lower()}` | {note} |\n")
    return "".join(md)


def render_markdown(cfg) -> str:
    """The register map for the HMI engineer (docs/registers.md is this output, verbatim)."""
    adv = cfg.advisory
    md = ["# hp-edge register map\n\n",
          f"Generated by `hp-edge check-config --markdown` from `{cfg.path.name}` and "
          f"`{cfg.tags_file.name}`; do not edit by hand (a test compares this file with the "
          f"YAML).\n\n",
          "Addresses are 0-based PDU addresses as sent on the wire. *Ref* is the 1-based "
          "Modicon reference (0xxxx coil, 1xxxx discrete input, 3xxxx input register, 4xxxx "
          "holding register) many HMIs use; `30.2` is bit 2 (0 = least significant) of register "
          "30. 16-bit values are big-endian (AB) unless marked BA (bytes swapped). 32-bit values "
          "take two registers; the byte order names the order in which the value's big-endian "
          "bytes A B C D travel: ABCD = high word first, CDAB = low word first, BADC / DCBA = the "
          "same with the bytes of each word swapped (64-bit values: the same rule word by word). "
          "Engineering value = raw × scale + offset, in the tag's unit; the range is in that "
          "unit too, and the gateway converts the value to the canonical unit (°C, bar(g), m³/h, "
          "kW) before it is used.\n\n",
          "## Tags read from the PLC\n\n",
          "A value outside its plausible range, NaN/inf or equal to its sentinel is marked bad "
          "(never clamped); a tag not read successfully for `max_age_s` is stale.\n\n"]
    devices = _devices(cfg)
    names = {"input": "Input registers", "holding": "Holding registers",
             "discrete_input": "Discrete inputs", "coil": "Coils"}
    for space in ("input", "holding", "discrete_input", "coil"):
        tags = [t for t in cfg.tags if t.register == space]
        if not tags:
            continue
        md.append(f"### {names[space]} (FC{_fc(space)})\n\n")
        md.append("| address | ref | tag | type | order | scale | offset | unit | range | "
                  "max age s | sentinel | pressure |" + (" device |" if devices else "")
                  + "\n|---|---|---|---|---|---|---|---|---|---|---|---|"
                  + ("---|" if devices else "") + "\n")
        for t in tags:
            md.append(f"| {_addr(t)} | {_tag_ref(t)} | `{t.name}` | {t.type} | "
                      f"{_order(t.type, t.byte_order)} | {_num(t.scale)} | {_num(t.offset)} | "
                      f"{_unit(t)} | {_range(t)} | {_num(t.max_age_s)} | {_num(t.sentinel)} | "
                      f"{t.pressure or ''} |"
                      + (f" {t.device_id or cfg.plc.device_id} |" if devices else "") + "\n")
        md.append("\n")
    md.append("### Grouped reads per scan\n\n| function | registers | tags |\n|---|---|---|\n")
    for dev, space, req in _read_plan(cfg):
        md.append(f"| FC{_fc(space)} {space}" + (f" device {dev}" if devices else "")
                  + f" | {req.start}–{req.start + req.count - 1} | "
                  f"{', '.join(t.name for t in req.tags)} |\n")
    md.append(f"\nA grouped read spans at most {cfg.plc.max_read_gap} unused register(s) "
              f"(`plc.max_read_gap`). If the PLC refuses a grouped read with exception 2, the "
              f"gateway reads that group tag by tag and tries the grouped read again after 60 s, "
              f"then less often (at most hourly).\n\n")
    md.append(f"## Advisory block (written by the gateway, read by the HMI)\n\n"
              f"{adv.register.capitalize()} registers {adv.start}–{adv.end - 1} "
              f"({adv.size} registers), written as a whole in one FC16 request per cycle. "
              f"32-bit fields use byte order {adv.byte_order}. The gateway writes no other "
              f"register, except the set point of the opt-in closed loop (below). Words not "
              f"listed are written as 0. A float32 field without a value holds NaN.\n\n")
    md.append("| address | ref | offset | field | type | unit | description |\n"
              "|---|---|---|---|---|---|---|\n")
    for f in adv.fields:
        a = adv.start + f.offset
        addr = f"{a}" + (f"–{a + 1}" if f.count == 2 else "")
        ref = _ref(adv.register, a) + (f"–{_ref(adv.register, a + 1)}" if f.count == 2 else "")
        md.append(f"| {addr} | {ref} | {f.offset} | `{f.name}` | {f.type} | "
                  f"{f.unit} | {f.description} |\n")
    used = {f.offset + i for f in adv.fields for i in range(f.count)}
    unused = [adv.start + o for o in range(adv.size) if o not in used]
    if unused:
        md.append(f"\nUnused (written as 0): {', '.join(map(str, unused))}.\n")
    status = adv.field("status")
    md.append(f"\n### Status bits (register {adv.start + status.offset}, `status`; bit 0 = least "
              f"significant)\n\n| bit | mask | name | meaning |\n|---|---|---|---|\n")
    for bit, name in adv.status_bits:
        md.append(f"| {bit} | 0x{1 << bit:04X} | `{name}` | {STATUS_BIT_NOTES.get(name, '')} |\n")
    md.append(_closed_loop_markdown(cfg))
    return "".join(md)


# ------------------------------------------------------------------------------------- read


def cmd_read(args: argparse.Namespace) -> int:
    """Only gateway.yaml's advisory layout (and its plc section, unless --host and --port name
    the server) is read: no tags.yaml, no plant.yaml."""
    import asyncio
    import dataclasses
    import logging

    from edge.config import ConfigError, PlcConfig, find_config, load_read_config
    from edge.yamlfile import format_problems

    path = find_config("gateway.yaml", args.config)
    try:
        plc, adv = load_read_config(path)
    except ConfigError as exc:
        for line in format_problems(exc.problems):
            print(line, file=sys.stderr)
        return 2
    if args.timeout <= 0:
        print("hp-edge read: --timeout must be > 0", file=sys.stderr)
        return 2
    if args.device_id is not None and not 1 <= args.device_id <= 255:
        print("hp-edge read: --device-id must be 1..255 (0 is the broadcast address)",
              file=sys.stderr)
        return 2
    if plc is None:
        if args.host is None or args.port is None:
            print(f"hp-edge read: the plc section of {path} is not valid; name the server with "
                  "--host and --port", file=sys.stderr)
            return 2
        plc = PlcConfig(host=args.host, port=args.port)
    overrides = {k: v for k, v in (("host", args.host), ("port", args.port),
                                   ("device_id", args.device_id)) if v is not None}
    plc = dataclasses.replace(plc, **overrides)
    # one attempt, its outcome is reported below: quiet the PLC loggers meanwhile
    loggers = [logging.getLogger(n) for n in ("pymodbus", "edge.plc")]
    saved = [lg.level for lg in loggers]
    for lg, level in zip(loggers, (logging.CRITICAL, logging.ERROR)):
        lg.setLevel(level)
    try:
        return asyncio.run(_read(plc, adv, args.timeout, args.json))
    finally:
        for lg, level in zip(loggers, saved):
            lg.setLevel(level)


async def _read(plc_cfg, adv, timeout: float, as_json: bool) -> int:
    import asyncio

    from edge.advisory import decode_advisory
    from edge.plc import PlcClient, PlcError

    plc = PlcClient(plc_cfg, (), adv, cycle_budget_s=timeout)
    target = f"{plc.plc.host}:{plc.plc.port} device {plc.plc.device_id}"
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    try:
        await plc.connect(timeout)
        words = await plc.read_advisory(max(0.05, deadline - loop.time()))
    except PlcError as exc:
        print(f"hp-edge read: cannot read the advisory block from {target}: {exc}",
              file=sys.stderr)
        return 1
    finally:
        await plc.close()
    decoded = decode_advisory(adv, words)
    print(_format_json(adv, target, words, decoded) if as_json
          else _format_text(adv, target, decoded), end="")
    return 0


def _format_json(adv, target: str, words: list[int], decoded: dict) -> str:
    import json
    import math

    def clean(v):
        return None if isinstance(v, float) and not math.isfinite(v) else v

    doc = {"server": target, "register": adv.register, "start": adv.start, "size": adv.size,
           "words": words, "fields": {f.name: clean(decoded[f.name]) for f in adv.fields},
           "status_bits": decoded["status_bits"]}
    names = _closed_loop_names(decoded)
    if names:
        doc["closed_loop"] = names
    return json.dumps(doc, indent=2) + "\n"


def _format_text(adv, target: str, decoded: dict) -> str:
    import math
    from datetime import datetime, timezone

    rows = []
    for f in adv.fields:
        v = decoded[f.name]
        if f.name == "status":
            shown = f"0x{v:04X}"
        elif isinstance(v, float):
            shown = "NaN (no value)" if math.isnan(v) else f"{v:.6g}"
        else:
            shown = str(v)
        if f.name in ("last_update", "closed_loop_last_write") and v:
            shown += "  (" + datetime.fromtimestamp(v, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ") + ")"
        elif f.name in ("closed_loop_state", "closed_loop_reason"):
            shown += f"  ({_closed_loop_names(decoded)[f.name.removeprefix('closed_loop_')]})"
        rows.append([str(adv.start + f.offset), f.name, shown, f.unit])
    out = [f"advisory block {adv.register} {adv.start}..{adv.end - 1} from {target}\n",
           _table(["address", "field", "value", "unit"], rows), "status bits:\n"]
    set_bits = set(decoded["status_bits"])
    for bit, name in adv.status_bits:
        out.append(f"  [{'x' if name in set_bits else ' '}] {bit:2d} {name}\n")
    for extra in sorted(set_bits - {n for _, n in adv.status_bits}):
        out.append(f"  [x]    {extra} (not configured)\n")
    names = _closed_loop_names(decoded)
    if names:
        out.append(f"closed loop: {names['state']}" + (f" ({names['reason']})"
                                                         if names["reason"] != "none" else "")
                   + "\n")
    return "".join(out)


def _closed_loop_names(decoded: dict) -> dict:
    """{'state': name, 'reason': name} from the decoded block ({} without those fields)."""
    from edge.closed_loop import reason_name, state_name

    if "closed_loop_state" not in decoded:
        return {}
    return {"state": state_name(decoded["closed_loop_state"]),
            "reason": reason_name(decoded.get("closed_loop_reason", 0))}


# ----------------------------------------------------------------------------- run, demo


def register_run_demo(sub) -> None:
    """Parser entries of ``run`` and ``demo`` (the gateway daemon; edge/loop.py, edge/demo.py)."""
    p = sub.add_parser("run", help="run the gateway daemon (poll, model, advisory block)",
                       description="Run the gateway until SIGTERM/SIGINT: poll the PLC, keep the "
                       "history, calibrate and optimize on the configured cadence and write the "
                       "advisory block once per scan. Exit codes: 0 stopped on request, 2 invalid "
                       "configuration or state (nothing was connected), 1 unexpected error.")
    p.add_argument("--config", default=None, help=CONFIG_HELP)
    p.add_argument("--time-source", choices=("wall", "plc"), default="wall",
                   help="time-stamp samples with the wall clock (default) or the PLC's clock "
                   "register plc_clock (plant time, e.g. an accelerated simulator)")
    p.add_argument("--log-level", default="INFO",
                   choices=("DEBUG", "INFO", "WARNING", "ERROR"), help="(default: %(default)s)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("demo", help="simulator at 60x plant speed + gateway, with a live view",
                       description="Start the plant simulator on 127.0.0.1 (free port) at 60x "
                       "plant speed and the gateway against it; show the advisory block as the "
                       "HMI reads it, beside the simulator's hidden truth. Ctrl-C stops both.")
    p.add_argument("--config", default=None, help=CONFIG_HELP)
    p.add_argument("--minutes", type=float, help="stop by itself after this many wall minutes")
    p.add_argument("--speed", type=float, default=60.0,
                   help="plant seconds per wall second (default: %(default)s)")
    p.add_argument("--state-dir", help="keep history, state and log here (default: a temporary "
                   "directory removed at the end)")
    p.add_argument("--refresh", type=float, default=2.0,
                   help="seconds between view updates (default: %(default)s)")
    p.add_argument("--no-commissioning", action="store_true",
                   help="skip the initial calibration on clean simulated operation (the fouling "
                   "estimate then carries the data sheet's error)")
    rep = p.add_mutually_exclusive_group()
    rep.add_argument("--report", help="write the report of the run here (default: report.html in "
                     "--state-dir, else demo-report.html in the current directory)")
    rep.add_argument("--no-report", action="store_true", help="write no report at the end")
    p.set_defaults(func=cmd_demo)


JOURNAL_PRIORITY = {"CRITICAL": 2, "ERROR": 3, "WARNING": 4, "INFO": 6, "DEBUG": 7}


def stderr_is_journal(stream=None) -> bool:
    """True when ``stream`` (default stderr) is the journal's stream socket: systemd sets
    JOURNAL_STREAM=<device>:<inode> of it for the service's stdout/stderr."""
    import os

    stream = stream or sys.stderr
    want = os.environ.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in want.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


class JournalFormatter(logging.Formatter):
    """'<4>WARNING edge.plc: ...': journald reads the <N> prefix as the syslog priority
    (SyslogLevelPrefix=, on by default), so `journalctl -p warning` finds the warnings."""

    def format(self, record) -> str:
        prio = JOURNAL_PRIORITY.get(record.levelname, 6)
        return "\n".join(f"<{prio}>{line}" for line in super().format(record).splitlines())


def _setup_logging(level: str, stream=None) -> None:
    import logging

    stream = stream or sys.stderr
    handler = logging.StreamHandler(stream)
    if stderr_is_journal(stream):
        # journald adds the time stamp and the unit name; the prefix carries the priority
        handler.setFormatter(JournalFormatter("%(levelname)s %(name)s: %(message)s"))
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=getattr(logging, level), handlers=[handler])
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)   # edge.plc reports PLC problems


def cmd_run(args: argparse.Namespace) -> int:
    import asyncio

    cfg = load_config_or_report(args.config)
    if cfg is None:
        return 2
    _setup_logging(args.log_level)
    if args.time_source == "plc" and "plc_clock" not in {t.name for t in cfg.tags}:
        print(f"{cfg.tags_file}: --time-source plc needs a tag 'plc_clock'; nothing was started.",
              file=sys.stderr)
        return 2
    from edge.service import GatewayService, StartupError

    try:
        service = GatewayService(cfg, time_source=args.time_source)
    except StartupError as exc:
        print(f"{exc}; nothing was started.", file=sys.stderr)
        return 2
    try:
        return asyncio.run(service.run())
    except KeyboardInterrupt:   # Ctrl-C before the gateway's own handler was installed
        return 130


def cmd_demo(args: argparse.Namespace) -> int:
    import asyncio
    import logging
    from pathlib import Path

    if load_config_or_report(args.config) is None:
        return 2
    if not 1.0 <= args.speed <= 3600.0 or args.refresh <= 0 or (args.minutes is not None
                                                                and args.minutes <= 0):
        print("--speed must be 1..3600, --refresh and --minutes > 0", file=sys.stderr)
        return 2
    _setup_logging("WARNING")
    from edge.demo import CommissioningError, run_demo
    from edge.service import StartupError

    try:
        from edge.config import find_config
        return asyncio.run(run_demo(find_config("gateway.yaml", args.config), args.minutes,
                                    args.speed,
                                    Path(args.state_dir) if args.state_dir else None,
                                    args.refresh, commissioning=not args.no_commissioning,
                                    report=False if args.no_report else
                                    (Path(args.report) if args.report else True)))
    except (StartupError, CommissioningError) as exc:
        print(f"{exc}; nothing was started.", file=sys.stderr)
        return 2
    except KeyboardInterrupt:   # Ctrl-C before the gateway's own handler was installed
        logging.getLogger(__name__).warning("interrupted during start-up")
        return 130
