"""The advisory block: its layout (gateway.yaml's ``advisory`` section) and the conversion of
values and status bits <-> the register words the HMI reads (pure; no pymodbus).

Two fields are mandatory in the layout: ``heartbeat`` and ``status`` (both uint16), and so is the
``status_bits`` table; every other field is filled from ``values``. ``edge.config`` validates the
section with ``parse_advisory``. The block's register range (holding ``start``..``start+size-1``) is
the one range the gateway ever writes: ``edge.config`` checks it against every register the PLC
owns, and ``edge.plc`` refuses any other write before a byte is sent.
"""
from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from edge.codec import (BYTE_ORDERS, MAX_WRITE_COUNT, REGISTER_SPACES, TYPES, decode, encode,
                        raw_value, register_count)

NAME_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")  # tag, field and status bit names


@dataclass(frozen=True)
class AdvisoryField:
    name: str
    offset: int
    type: str
    unit: str = ""
    description: str = ""

    @property
    def count(self) -> int:
        return register_count(self.type)


@dataclass(frozen=True)
class AdvisoryConfig:
    register: str
    start: int
    size: int
    byte_order: str
    fields: tuple[AdvisoryField, ...]            # ordered by offset
    status_bits: tuple[tuple[int, str], ...]     # (bit, name), ordered by bit

    @property
    def end(self) -> int:
        """First address after the block."""
        return self.start + self.size

    def field(self, name: str) -> AdvisoryField:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(name)

    def contains(self, address: int, count: int) -> bool:
        return count >= 1 and self.start <= address and address + count <= self.end


HEARTBEAT = "heartbeat"
STATUS = "status"
STATUS_BITS_KEY = "status_bits"  # key of the decoded bit names in decode_advisory's result


# ------------------------------------------------------------------ layout validation

_ADV_KEYS = ("register", "start", "size", "byte_order", "fields", "status_bits")
_FIELD_KEYS = ("offset", "type", "unit", "description")


def parse_advisory(sec) -> AdvisoryConfig | None:
    """Validate gateway.yaml's advisory section (an ``edge.config`` section object); every
    problem is recorded on ``sec``. None when invalid."""
    if not sec.mapping():
        return None
    n0 = sec.count()   # a missing required key invalidates it too
    sec.keys(_ADV_KEYS, required=("register", "start", "size", "byte_order", "fields",
                                  "status_bits"))
    register = sec.choice("register", REGISTER_SPACES)
    if register == "input":
        sec.problem("register", "'input' registers cannot be written; the block must be holding")
    elif register is not None and register != "holding":
        sec.problem("register", f"{register!r}: the block is written with FC16; it must be "
                    "holding registers")
    start = sec.integer("start", lo=0, hi=65535)
    size = sec.integer("size", lo=1, hi=MAX_WRITE_COUNT)
    if start is not None and size is not None and start + size > 65536:
        sec.problem("size", f"block {start}..{start + size - 1} runs past register 65535")
    byte_order = sec.choice("byte_order", BYTE_ORDERS)
    fields = _fields(sec, size)
    bits = _status_bits(sec)
    if sec.count() != n0:
        return None
    return AdvisoryConfig(register=register, start=start, size=size, byte_order=byte_order,
                          fields=fields, status_bits=bits)


def _fields(sec, size: int | None) -> tuple[AdvisoryField, ...]:
    raw = sec.data.get("fields")
    if "fields" in sec.data and (not isinstance(raw, dict) or not raw):
        sec.problem("fields", "expected a non-empty mapping of field name -> keys")
        return ()
    fields: list[AdvisoryField] = []
    for name, body in (raw or {}).items():
        fsec = sec.child(f"advisory field '{name}'", body)
        if not isinstance(name, str) or not NAME_PATTERN.match(name) or name == "status_bits":
            fsec.problem(None, "field names must be identifiers (letters, digits, _), "
                         "not 'status_bits'")
            continue
        if not fsec.mapping():
            continue
        n0 = fsec.count()   # a missing required key invalidates it too
        fsec.keys(_FIELD_KEYS, required=("offset", "type"))
        offset = fsec.integer("offset", lo=0)
        type_ = fsec.choice("type", TYPES)
        unit = fsec.string("unit", default="")
        desc = fsec.string("description", default="", allow_empty=True)
        if offset is not None and type_ and size is not None:
            last = offset + register_count(type_) - 1
            if offset >= size:
                fsec.problem("offset", f"{offset} is outside the block (size {size})")
            elif last >= size:
                fsec.problem("offset", f"{type_} at offset {offset} crosses the block's end "
                             f"(needs offsets {offset}..{last}, size {size})")
        if fsec.count() == n0:
            fields.append(AdvisoryField(name, offset, type_, unit, desc))
    widest: AdvisoryField | None = None
    for f in sorted(fields, key=lambda f: f.offset):
        if widest is not None and f.offset < widest.offset + widest.count:
            sec.child(f"advisory field '{f.name}'").problem(
                "offset", f"offsets {f.offset}..{f.offset + f.count - 1} overlap field "
                f"'{widest.name}' ({widest.offset}..{widest.offset + widest.count - 1})")
        if widest is None or f.offset + f.count > widest.offset + widest.count:
            widest = f
    for required in ("heartbeat", "status"):
        f = next((f for f in fields if f.name == required), None)
        if raw and isinstance(raw, dict) and required not in raw:
            sec.problem("fields", f"field '{required}' (uint16) is required")
        elif f is not None and f.type != "uint16":
            sec.child(f"advisory field '{required}'").problem(
                "type", f"must be uint16, got {f.type}")
    return tuple(sorted(fields, key=lambda f: f.offset))


def _status_bits(sec) -> tuple[tuple[int, str], ...]:
    if "status_bits" not in sec.data:
        return ()      # reported as a missing required key
    raw = sec.data["status_bits"]
    if not isinstance(raw, dict) or not raw:
        sec.problem("status_bits", "expected a mapping of bit number (0..15) -> name; without "
                    "it the status word would always read 0")
        return ()
    bits, seen = [], {}
    for bit, name in raw.items():
        if isinstance(bit, bool) or not isinstance(bit, int) or not 0 <= bit <= 15:
            sec.problem("status_bits", f"bit {bit!r} is outside 0..15")
            continue
        if not isinstance(name, str) or not NAME_PATTERN.match(name):
            sec.problem("status_bits", f"bit {bit}: name {name!r} is not an identifier")
            continue
        if name in seen:
            sec.problem("status_bits", f"bit {bit}: name {name!r} already used by bit {seen[name]}")
            continue
        seen[name] = bit
        bits.append((bit, name))
    return tuple(sorted(bits))


# ------------------------------------------------------------------ words

def status_word(adv: AdvisoryConfig, status_bits: Iterable[str]) -> int:
    """The status word with the named bits set. Unknown names raise ValueError."""
    by_name = {name: bit for bit, name in adv.status_bits}
    word = 0
    for name in status_bits:
        if name not in by_name:
            raise ValueError(
                f"unknown status bit {name!r}; configured bits: {', '.join(by_name) or 'none'}"
            )
        word |= 1 << by_name[name]
    return word


def encode_advisory(
    adv: AdvisoryConfig,
    values: Mapping[str, float | int | None],
    status_bits: Iterable[str],
    heartbeat: int,
) -> list[int]:
    """Exactly ``adv.size`` words for one FC16 write of the whole block.

    ``values`` maps field names (other than heartbeat and status) to numbers. A float32 field
    that is missing, None or NaN is written as float32 NaN ("no value"); a missing integer field
    is written as 0. Words not covered by any field are 0. ``heartbeat`` wraps modulo 65536.
    Raises ValueError for an unknown field or bit name, a negative heartbeat, NaN in an integer
    field, or a value that does not fit its type (nothing is clamped).
    """
    fields = {f.name: f for f in adv.fields}
    unknown = sorted(set(values) - (set(fields) - {HEARTBEAT, STATUS}))
    if unknown:
        raise ValueError(
            f"unknown advisory field(s) {', '.join(map(repr, unknown))}; "
            f"fields: {', '.join(n for n in fields if n not in (HEARTBEAT, STATUS))}"
        )
    if isinstance(heartbeat, bool) or not isinstance(heartbeat, int) or heartbeat < 0:
        raise ValueError(f"heartbeat must be a non-negative integer, got {heartbeat!r}")
    words = [0] * adv.size
    for f in adv.fields:
        if f.name == HEARTBEAT:
            value: float | int | None = heartbeat % 65536
        elif f.name == STATUS:
            value = status_word(adv, status_bits)
        else:
            value = values.get(f.name)
        if value is None:
            value = math.nan if f.type == "float32" else 0
        try:
            encoded = encode(value, f.type, adv.byte_order)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"advisory field {f.name!r}: {exc}") from None
        words[f.offset : f.offset + len(encoded)] = encoded
    return words


def decode_advisory(adv: AdvisoryConfig, words: Sequence[int]) -> dict:
    """Field name -> value (int for integer types, float for float32, NaN kept), plus
    ``"status_bits"``: the names of the set status bits in bit order (an unnamed set bit
    appears as ``"bit N"``)."""
    if len(words) != adv.size:
        raise ValueError(f"advisory block has {adv.size} words, got {len(words)}")
    out: dict = {}
    for f in adv.fields:
        regs = list(words[f.offset : f.offset + f.count])
        if f.type == "float32":
            out[f.name] = decode(regs, f.type, adv.byte_order)
        else:
            out[f.name] = int(raw_value(regs, f.type, adv.byte_order))
    names = dict(adv.status_bits)
    status = out.get(STATUS, 0)
    out[STATUS_BITS_KEY] = [names.get(bit, f"bit {bit}") for bit in range(16) if status >> bit & 1]
    return out
