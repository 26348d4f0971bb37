"""Engineering values -> Modbus registers for the simulator, with pymodbus's own
``convert_to_registers`` (never the gateway's codec), and the same quantization in bulk for export.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymodbus.client.mixin import ModbusClientMixin

from .config import TYPE_LIMITS, AdvisoryBlock, TagSpec

_DT = ModbusClientMixin.DATATYPE
_PYMODBUS_TYPE = {"int16": _DT.INT16, "uint16": _DT.UINT16, "int32": _DT.INT32,
                  "uint32": _DT.UINT32, "float32": _DT.FLOAT32}

SYSTEM_TAGS = ("plc_clock", "life_counter")
SETPOINT_TAG = "p_m_sp"


def _raw(spec: TagSpec, value: float) -> int | float:
    """Engineering value -> raw register value (rounded and saturated for integer types)."""
    if math.isnan(value):
        if spec.sentinel is not None:
            return int(spec.sentinel)
        if spec.type == "float32":
            return math.nan
        raise ValueError(f"tag {spec.name}: NaN cannot be represented (type {spec.type}, no sentinel)")
    raw = (value - spec.offset) / spec.scale
    if spec.type == "float32":
        return raw
    lo, hi = TYPE_LIMITS[spec.type]
    if spec.sentinel is not None:   # a saturated value must not read as "no value"
        lo, hi = (lo + 1, hi) if spec.sentinel == lo else (lo, hi - 1) if spec.sentinel == hi else (lo, hi)
    if math.isinf(raw):
        return hi if raw > 0 else lo
    return min(max(int(round(raw)), lo), hi)


def encode(spec: TagSpec, value: float) -> list[int]:
    """Engineering value -> the tag's registers in its byte order."""
    regs = ModbusClientMixin.convert_to_registers(
        _raw(spec, float(value)), _PYMODBUS_TYPE[spec.type],
        word_order="little" if spec.byte_order in ("CDAB", "DCBA") else "big")
    if spec.byte_order in ("BADC", "DCBA") and spec.count == 2:
        regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
    return regs


def quantize(spec: TagSpec, values: np.ndarray) -> np.ndarray:
    """What a reader decodes from ``encode(spec, v)``, vectorized (NaN stays NaN)."""
    v = np.asarray(values, dtype=float)
    raw = (v - spec.offset) / spec.scale
    if spec.type == "float32":
        q = raw.astype(np.float32).astype(float)
    else:
        lo, hi = TYPE_LIMITS[spec.type]
        if spec.sentinel is not None:
            lo, hi = (lo + 1, hi) if spec.sentinel == lo else (lo, hi - 1) if spec.sentinel == hi else (lo, hi)
        with np.errstate(invalid="ignore"):
            q = np.clip(np.round(raw), lo, hi)
    return q * spec.scale + spec.offset


@dataclass(frozen=True)
class Run:
    """A contiguous run of served registers: register type, first address, tags in address order."""
    register: str
    start: int
    count: int
    tags: tuple[TagSpec, ...]


def register_runs(tags: dict[str, TagSpec]) -> list[Run]:
    """Group tags into contiguous runs per register type (gaps stay undefined: exception 2)."""
    runs: list[Run] = []
    for register in ("input", "holding"):
        specs = sorted((t for t in tags.values() if t.register == register), key=lambda t: t.address)
        cur: list[TagSpec] = []
        for s in specs:
            if cur and s.address != cur[-1].address + cur[-1].count:
                runs.append(_run(register, cur))
                cur = []
            cur.append(s)
        if cur:
            runs.append(_run(register, cur))
    return runs


def _run(register: str, specs: list[TagSpec]) -> Run:
    return Run(register, specs[0].address, specs[-1].address + specs[-1].count - specs[0].address,
               tuple(specs))


def encode_run(run: Run, values: dict[str, float]) -> list[int]:
    regs: list[int] = []
    for spec in run.tags:
        regs.extend(encode(spec, values.get(spec.name, math.nan)))
    return regs


def writable_ranges(tags: dict[str, TagSpec], advisory: AdvisoryBlock,
                    extra: list[tuple[int, int]] = ()) -> list[tuple[int, int]]:
    """Holding-register ranges [start, end) a client may write: the set point, the advisory block
    and ``extra`` ranges (the CIP request register when configured)."""
    ranges = [(advisory.start, advisory.start + advisory.size)] + list(extra)
    sp = tags.get(SETPOINT_TAG)
    if sp is not None and sp.register == "holding":
        ranges.append((sp.address, sp.address + sp.count))
    return ranges
