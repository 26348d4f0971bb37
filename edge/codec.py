"""Register words <-> engineering values, and the plan of grouped reads (pure; no pymodbus).

Conventions
-----------
* A register (word) is an int 0..65535 as it travels on the wire (big-endian inside the word).
* 16-bit types (int16, uint16) occupy one register, high byte first; ``byte_order`` is ignored.
* 32-bit types (int32, uint32, float32) occupy two registers. Write the value's big-endian bytes
  as A B C D (A most significant); ``byte_order`` names the order the bytes travel in:
  ``ABCD`` -> [AB, CD] (Modbus default), ``CDAB`` -> [CD, AB] (word swap),
  ``BADC`` -> [BA, DC] (byte swap), ``DCBA`` -> [DC, BA] (both).
* engineering value = raw * scale + offset, and back: raw = (value - offset) / scale.
* Encoding a value that does not fit the type raises ``ValueError``; nothing is clamped.
  Integer types round the raw value half away from zero (quantisation, not clamping).
"""
from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Sequence
from typing import NamedTuple, Protocol

# type name -> (struct format char, number of registers)
TYPES: dict[str, tuple[str, int]] = {
    "int16": ("h", 1),
    "uint16": ("H", 1),
    "int32": ("i", 2),
    "uint32": ("I", 2),
    "float32": ("f", 2),
}
BYTE_ORDERS: tuple[str, ...] = ("ABCD", "CDAB", "BADC", "DCBA")
REGISTER_SPACES: tuple[str, ...] = ("holding", "input")  # FC3/FC16 and FC4
FLOAT32_MAX = struct.unpack(">f", bytes.fromhex("7f7fffff"))[0]
MAX_READ_COUNT = 125   # registers per FC3/FC4 request (Modbus application protocol)
MAX_WRITE_COUNT = 123  # registers per FC16 request

_INT_LIMITS: dict[str, tuple[int, int]] = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


def _check_type(type_: str) -> None:
    if type_ not in TYPES:
        raise ValueError(f"unknown type {type_!r}; use one of {', '.join(TYPES)}")


def _check_byte_order(byte_order: str) -> None:
    if byte_order not in BYTE_ORDERS:
        raise ValueError(f"unknown byte order {byte_order!r}; use one of {', '.join(BYTE_ORDERS)}")


def format_number(x: float | int) -> str:
    """Shortest exact-looking text for config numbers: 4294967295 stays 4294967295, 0.01 0.01."""
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e16:
        return str(int(x))
    return f"{x:.10g}" if isinstance(x, float) else str(x)


def register_count(type_: str) -> int:
    """Number of 16-bit registers a value of ``type_`` occupies (1 or 2)."""
    _check_type(type_)
    return TYPES[type_][1]


def raw_limits(type_: str) -> tuple[float, float]:
    """Smallest and largest finite raw value of ``type_`` (float32: +-FLT_MAX)."""
    _check_type(type_)
    if type_ == "float32":
        return (-FLOAT32_MAX, FLOAT32_MAX)
    return _INT_LIMITS[type_]


def is_integer_type(type_: str) -> bool:
    _check_type(type_)
    return type_ != "float32"


def _words_to_bytes(registers: Sequence[int], type_: str, byte_order: str) -> bytes:
    _check_type(type_)
    _check_byte_order(byte_order)
    count = TYPES[type_][1]
    if len(registers) != count:
        raise ValueError(f"{type_} needs {count} register(s), got {len(registers)}")
    for word in registers:
        if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFFFF:
            raise ValueError(f"register word {word!r} is not an integer 0..65535")
    wire = b"".join(word.to_bytes(2, "big") for word in registers)
    if count == 1:
        return wire
    # wire[i] carries byte byte_order[i]; put the bytes back in A B C D order
    return bytes(wire[byte_order.index(letter)] for letter in "ABCD")


def _bytes_to_words(data: bytes, byte_order: str) -> list[int]:
    if len(data) == 4:
        data = bytes(data["ABCD".index(letter)] for letter in byte_order)
    return [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]


def raw_value(registers: Sequence[int], type_: str, byte_order: str = "ABCD") -> int | float:
    """The raw number in ``registers`` before scale and offset (int, or float for float32).

    This is what a tag's ``sentinel`` is compared with.
    """
    data = _words_to_bytes(registers, type_, byte_order)
    return struct.unpack(">" + TYPES[type_][0], data)[0]


def decode(
    registers: Sequence[int],
    type_: str,
    byte_order: str = "ABCD",
    scale: float = 1.0,
    offset: float = 0.0,
) -> float:
    """Engineering value = raw * scale + offset. NaN/inf of a float32 come back as NaN/inf."""
    return float(raw_value(registers, type_, byte_order)) * scale + offset


def raw_to_registers(raw: int | float, type_: str, byte_order: str = "ABCD") -> list[int]:
    """Registers holding ``raw`` (already unscaled). Raises ValueError if it does not fit."""
    _check_type(type_)
    _check_byte_order(byte_order)
    fmt = TYPES[type_][0]
    if type_ == "float32":
        try:
            data = struct.pack(">f", float(raw))
        except OverflowError:
            raise ValueError(
                f"raw value {raw!r} does not fit float32 (|x| <= {FLOAT32_MAX:.6g})"
            ) from None
    else:
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise ValueError(f"raw value {raw!r} of {type_} must be an integer")
        lo, hi = _INT_LIMITS[type_]
        if not lo <= raw <= hi:
            raise ValueError(f"raw value {raw} does not fit {type_} [{lo}, {hi}]")
        data = struct.pack(">" + fmt, raw)
    return _bytes_to_words(data, byte_order)


def _round_half_away(x: float) -> int:
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def encode(
    value: float,
    type_: str,
    byte_order: str = "ABCD",
    scale: float = 1.0,
    offset: float = 0.0,
) -> list[int]:
    """Registers for engineering ``value``: raw = (value - offset) / scale.

    Raises ValueError when the raw value does not fit the type (never clamps), when an integer
    type gets NaN or infinity, or when scale is 0. float32 accepts NaN and infinities.
    """
    _check_type(type_)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"value must be a number, got {value!r}")
    if scale == 0:
        raise ValueError("scale must not be 0")
    if isinstance(value, int) and scale == 1 and offset == 0:
        raw: int | float = value
    else:
        raw = (value - offset) / scale
    if type_ == "float32":
        try:
            return raw_to_registers(raw, type_, byte_order)
        except ValueError:
            raise ValueError(
                f"value {value!r} (raw {raw!r}) does not fit float32 "
                f"with scale {scale:g} and offset {offset:g}"
            ) from None
    if not math.isfinite(raw):
        raise ValueError(f"value {value!r} cannot be encoded as {type_} (not finite)")
    raw_int = raw if isinstance(raw, int) else _round_half_away(raw)
    lo, hi = _INT_LIMITS[type_]
    if not lo <= raw_int <= hi:
        raise ValueError(
            f"value {value!r} (raw {raw_int}) does not fit {type_} [{lo}, {hi}] "
            f"with scale {scale:g} and offset {offset:g}"
        )
    return raw_to_registers(raw_int, type_, byte_order)


# ---------------------------------------------------------------------------- read planning


class Addressed(Protocol):
    """Anything with a register space, an address and a type (e.g. config.TagConfig)."""

    register: str
    address: int
    type: str


class ReadRequest(NamedTuple):
    """One FC3/FC4 request: ``count`` registers from ``start``, decoding ``tags``."""

    start: int
    count: int
    tags: tuple


def plan_reads(
    tags: Iterable[Addressed], max_gap: int = 10, max_count: int = MAX_READ_COUNT
) -> list[ReadRequest]:
    """Group the tags of ONE register space into as few read requests as the addresses allow.

    A request covers at most ``max_count`` registers, never splits a 32-bit value, and spans a
    gap of unused registers between two tags only when the gap is at most ``max_gap`` registers.
    Greedy packing in address order is optimal here: every request ends as late as possible.
    """
    if not 2 <= max_count <= MAX_READ_COUNT:
        raise ValueError(f"max_count must be 2..{MAX_READ_COUNT}, got {max_count}")
    if max_gap < 0:
        raise ValueError(f"max_gap must be >= 0, got {max_gap}")
    ordered = sorted(tags, key=lambda t: t.address)
    spaces = {t.register for t in ordered}
    if len(spaces) > 1:
        raise ValueError(f"plan_reads takes tags of one register space, got {sorted(spaces)}")
    requests: list[ReadRequest] = []
    start = end = 0
    group: list = []
    for tag in ordered:
        tag_end = tag.address + register_count(tag.type)
        if group and tag.address - end <= max_gap and max(end, tag_end) - start <= max_count:
            group.append(tag)
            end = max(end, tag_end)
            continue
        if group:
            requests.append(ReadRequest(start, end - start, tuple(group)))
        start, end, group = tag.address, tag_end, [tag]
    if group:
        requests.append(ReadRequest(start, end - start, tuple(group)))
    return requests
