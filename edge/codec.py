"""Register words <-> engineering values, and the plan of grouped reads (pure; no pymodbus).

Conventions
-----------
* A register (word) is an int 0..65535 as it travels on the wire (big-endian inside the word).
* 16-bit types (int16, uint16) occupy one register, high byte first (``AB``, the default); ``BA``
  swaps the two bytes. The 32-bit orders below leave a 16-bit value as it is.
* 32-bit types (int32, uint32, float32) occupy two registers. Write the value's big-endian bytes
  as A B C D (A most significant); ``byte_order`` names the order the bytes travel in:
  ``ABCD`` -> [AB, CD] (Modbus default), ``CDAB`` -> [CD, AB] (word swap),
  ``BADC`` -> [BA, DC] (byte swap), ``DCBA`` -> [DC, BA] (both).
* 64-bit types (int64, uint64, float64) occupy four registers; the same four names apply word by
  word (Telegraf's convention): ``ABCD`` big-endian (ABCDEFGH), ``CDAB`` words in reverse order
  (GHEFCDAB), ``BADC`` bytes swapped in each word (BADCFEHG), ``DCBA`` little-endian (HGFEDCBA).
* ``bool`` is one coil or discrete input (a bit address, FC1/FC2); ``bit_of`` takes one bit of a
  16-bit register (bit 0 = least significant).
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
    "int64": ("q", 4),
    "uint64": ("Q", 4),
    "float64": ("d", 4),
}
BOOL = "bool"                       # a coil or discrete input: one bit address
BYTE_ORDERS: tuple[str, ...] = ("ABCD", "CDAB", "BADC", "DCBA")   # 32- and 64-bit
BYTE_ORDERS_16: tuple[str, ...] = ("AB", "BA")                    # 16-bit
WORD_SPACES: tuple[str, ...] = ("holding", "input")               # FC3/FC16 and FC4
BIT_SPACES: tuple[str, ...] = ("coil", "discrete_input")          # FC1 and FC2
REGISTER_SPACES: tuple[str, ...] = WORD_SPACES + BIT_SPACES
READ_FUNCTION = {"coil": 1, "discrete_input": 2, "holding": 3, "input": 4}
FLOAT32_MAX = struct.unpack(">f", bytes.fromhex("7f7fffff"))[0]
FLOAT64_MAX = struct.unpack(">d", bytes.fromhex("7fefffffffffffff"))[0]
MAX_READ_COUNT = 125   # registers per FC3/FC4 request (Modbus application protocol)
MAX_READ_BITS = 2000   # coils / discrete inputs per FC1/FC2 request
MAX_WRITE_COUNT = 123  # registers per FC16 request

_INT_LIMITS: dict[str, tuple[int, int]] = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
_FLOAT_TYPES = {"float32": FLOAT32_MAX, "float64": FLOAT64_MAX}


def _check_type(type_: str) -> None:
    if type_ not in TYPES:
        raise ValueError(f"unknown type {type_!r}; use one of {', '.join(TYPES)}")


def _check_byte_order(byte_order: str, count: int = 2) -> None:
    allowed = BYTE_ORDERS + (BYTE_ORDERS_16 if count == 1 else ())
    if byte_order not in allowed:
        raise ValueError(f"unknown byte order {byte_order!r}"
                         + (" for a 32/64-bit value" if byte_order in BYTE_ORDERS_16 else "")
                         + f"; use one of {', '.join(allowed)}")


def byte_orders_for(type_: str) -> tuple[str, ...]:
    """The byte orders a tag of ``type_`` may name (16-bit: AB, BA; wider: ABCD, CDAB, ...)."""
    return BYTE_ORDERS_16 if register_count(type_) == 1 else BYTE_ORDERS


def format_number(x: float | int) -> str:
    """Shortest exact-looking text for config numbers: 4294967295 stays 4294967295, 0.01 0.01."""
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e16:
        return str(int(x))
    return f"{x:.10g}" if isinstance(x, float) else str(x)


def register_count(type_: str) -> int:
    """Number of 16-bit registers a value of ``type_`` occupies (1, 2 or 4; ``bool``: one bit
    address)."""
    if type_ == BOOL:
        return 1
    _check_type(type_)
    return TYPES[type_][1]


def raw_limits(type_: str) -> tuple[float, float]:
    """Smallest and largest finite raw value of ``type_`` (floats: +-the largest finite)."""
    _check_type(type_)
    if type_ in _FLOAT_TYPES:
        return (-_FLOAT_TYPES[type_], _FLOAT_TYPES[type_])
    return _INT_LIMITS[type_]


def is_integer_type(type_: str) -> bool:
    _check_type(type_)
    return type_ not in _FLOAT_TYPES


def _swap_words(words: list[int], byte_order: str) -> list[int]:
    """Wire words <-> the value's words in big-endian order (the mapping is its own inverse)."""
    if len(words) == 1:
        return [((words[0] & 0xFF) << 8) | (words[0] >> 8)] if byte_order == "BA" else words
    if byte_order in ("CDAB", "DCBA"):
        words = words[::-1]
    if byte_order in ("BADC", "DCBA"):
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    return words


def _words_to_bytes(registers: Sequence[int], type_: str, byte_order: str) -> bytes:
    _check_type(type_)
    count = TYPES[type_][1]
    _check_byte_order(byte_order, count)
    if len(registers) != count:
        raise ValueError(f"{type_} needs {count} register(s), got {len(registers)}")
    for word in registers:
        if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFFFF:
            raise ValueError(f"register word {word!r} is not an integer 0..65535")
    return b"".join(w.to_bytes(2, "big") for w in _swap_words(list(registers), byte_order))


def _bytes_to_words(data: bytes, byte_order: str) -> list[int]:
    words = [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]
    return _swap_words(words, byte_order)


def bit_of(word: int, bit: int) -> int:
    """Bit ``bit`` (0 = least significant) of a 16-bit register word: 0 or 1."""
    if isinstance(word, bool) or not isinstance(word, int) or not 0 <= word <= 0xFFFF:
        raise ValueError(f"register word {word!r} is not an integer 0..65535")
    if isinstance(bit, bool) or not isinstance(bit, int) or not 0 <= bit <= 15:
        raise ValueError(f"bit {bit!r} is not 0..15")
    return (word >> bit) & 1


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
    _check_byte_order(byte_order, TYPES[type_][1])
    fmt = TYPES[type_][0]
    if type_ in _FLOAT_TYPES:
        try:
            data = struct.pack(">" + fmt, float(raw))
        except OverflowError:
            raise ValueError(
                f"raw value {raw!r} does not fit {type_} (|x| <= {_FLOAT_TYPES[type_]:.6g})"
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
    type gets NaN or infinity, or when scale is 0. float32/float64 accept NaN and infinities.
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
    if type_ in _FLOAT_TYPES:
        try:
            return raw_to_registers(raw, type_, byte_order)
        except (ValueError, OverflowError):
            raise ValueError(
                f"value {value!r} (raw {raw!r}) does not fit {type_} "
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
    """Anything with a register space, an address and a type (e.g. config.TagConfig); an
    optional ``device_id`` too."""

    register: str
    address: int
    type: str


class ReadRequest(NamedTuple):
    """One FC1-FC4 request: ``count`` registers (or bits) from ``start``, decoding ``tags``."""

    start: int
    count: int
    tags: tuple


def plan_reads(
    tags: Iterable[Addressed], max_gap: int = 10, max_count: int | None = None
) -> list[ReadRequest]:
    """Group the tags of ONE register space of ONE device into as few read requests as the
    addresses allow.

    A request covers at most ``max_count`` registers (default and upper limit: 125 registers,
    2000 coils or discrete inputs), never splits a multi-register value, and spans a gap of
    unused addresses between two tags only when the gap is at most ``max_gap``. Several bits of
    one register (``bit`` tags) share it. Greedy packing in address order is optimal here: every
    request ends as late as possible.
    """
    ordered = sorted(tags, key=lambda t: t.address)
    spaces = {t.register for t in ordered}
    if len(spaces) > 1:
        raise ValueError(f"plan_reads takes tags of one register space, got {sorted(spaces)}")
    devices = {d for t in ordered if (d := getattr(t, "device_id", None)) is not None}
    if len(devices) > 1:
        raise ValueError(f"plan_reads takes tags of one device, got {sorted(devices)}")
    limit = MAX_READ_BITS if spaces and next(iter(spaces)) in BIT_SPACES else MAX_READ_COUNT
    max_count = limit if max_count is None else max_count
    if not 2 <= max_count <= limit:
        raise ValueError(f"max_count must be 2..{limit}, got {max_count}")
    if max_gap < 0:
        raise ValueError(f"max_gap must be >= 0, got {max_gap}")
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


SPACE_ORDER: tuple[str, ...] = ("input", "holding", "discrete_input", "coil")


def plan_groups(tags: Iterable[Addressed], default_device: int,
                max_gap: int = 10) -> list[tuple[int, str, ReadRequest]]:
    """The read plan of a whole tag map: ``(device id, register space, request)`` for every
    group of one device and one space (``plan_reads``), devices in order, input registers first.
    A tag without a ``device_id`` (or with None) belongs to ``default_device``."""
    groups: dict[tuple[int, str], list] = {}
    for t in tags:
        dev = getattr(t, "device_id", None)
        groups.setdefault((default_device if dev is None else dev, t.register), []).append(t)
    return [(dev, space, req)
            for dev, space in sorted(groups, key=lambda k: (k[0], SPACE_ORDER.index(k[1])))
            for req in plan_reads(groups[(dev, space)], max_gap=max_gap)]
