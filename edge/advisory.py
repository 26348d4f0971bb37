"""The advisory block: values and status bits <-> the register words the HMI reads (pure).

The layout (start, size, byte order, fields, status bits) comes from gateway.yaml's ``advisory``
section, parsed into ``edge.config.AdvisoryConfig``. Two fields are mandatory there: ``heartbeat``
and ``status`` (both uint16); every other field is filled from ``values``.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

from edge.codec import decode, encode, raw_value

if TYPE_CHECKING:  # pragma: no cover
    from edge.config import AdvisoryConfig

HEARTBEAT = "heartbeat"
STATUS = "status"
STATUS_BITS_KEY = "status_bits"  # key of the decoded bit names in decode_advisory's result


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
