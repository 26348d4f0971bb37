"""Scan samples -> one-minute samples, with per-tag validity, max age and a frozen-data check.

Pure: no I/O, no clock of its own. The caller passes two times with every scan:

* ``t_sample`` - where the scan belongs on the *sample clock* [epoch s]: the wall clock in
  production, or the PLC's clock register when the gateway is told to use it (plant time in the
  accelerated demo and tests). Scans are grouped into periods of ``aggregate_s`` on this clock.
* ``t_mono`` - a monotonic clock [s] for freshness: a tag not read good for its ``max_age_s`` is
  stale, and a life counter that has not changed for its ``max_age_s`` means frozen data.

Validation rules (SPEC 4, 7.2):

* a scan value that is bad (sentinel, NaN/inf, out of its plausible range, not read) is excluded
  from the mean, never clamped; the minute value of a tag is the mean of its good scans when they
  are at least ``min_good_share`` of the period's scans, else NaN with the dominant reason;
* a scan is only *confirmed* when the PLC's life counter changes after it. Scans wait, pending,
  until then; when the counter has not changed for its ``max_age_s`` the PLC data is frozen and
  every pending scan is discarded (counted as ``frozen``), so frozen values never reach a
  one-minute sample, even those read before the freeze was detectable;
* flags: ``running`` takes the minimum over the period (running the whole minute) and ``cip`` the
  maximum (a CIP anywhere in the minute); every other tag the arithmetic mean;
* a **flat-lined** (stuck) sensor is bad with the reason ``flatline``: while the plant runs, a tag
  whose value has not moved by more than its resolution (half a raw step, ``0.5 * |scale|``, for
  integer registers; any change for float32) for its ``flatline_s`` of sample-clock time is
  excluded from the mean until it moves again. ``flatline_s`` comes from the tag map (0: off);
  without it the measurement tags of SPEC 4 (temperatures, pressures, flows, powers) default to
  ``FLATLINE_DEFAULT_S`` and the others (flags, speeds, set points, system registers) are off.
  Time counts only while the plant runs (``plant_running``), so a stop never looks like a stuck
  sensor, and a real one is found ``flatline_s`` after it stuck.

A period is closed, and its ``Sample`` returned by ``add``, when the first confirmed (or discarded)
scan of a later period arrives. A partial period at shutdown is dropped on purpose: it is not a
one-minute average.
"""
from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

FROZEN = "frozen"
FLATLINE = "flatline"
FLAGS_ALL = ("running",)   # min over the period
FLAGS_ANY = ("cip",)       # max over the period
MIN_POWER_KW = 20.0        # no running flag: below this compressor power the plant is off
                           # (the same threshold as model.measured.MIN_POWER_KW)
FLATLINE_DEFAULT_S = 1800.0
# the measurement tags of SPEC 4 that get FLATLINE_DEFAULT_S when the tag map says nothing
FLATLINE_DEFAULT_TAGS = (
    "T_sink_in", "T_sink_out", "T_source_in", "T_source_out", "V_sink", "V_source",
    "p_source_in", "p_source_out", "T_suc_LS", "T_dis_LS", "T_suc_HS", "T_dis_HS",
    "p_suc_LS", "p_dis_LS", "p_suc_HS", "p_dis_HS", "T_c", "T_e", "W_LS", "W_HS")


class TagLike(Protocol):
    name: str
    max_age_s: float


class ValueLike(Protocol):
    value: float | None
    bad: str | None


@dataclass(frozen=True)
class Sample:
    """One aggregation period (a one-minute sample)."""
    timestamp: float                 # start of the period on the sample clock [epoch s]
    values: dict[str, float]         # tag -> mean of the good scans [engineering unit]; NaN if bad
    bad: dict[str, str]              # tag -> reason, for every tag whose value is NaN
    scans: int                       # scans that fell into the period
    good_scans: int                  # of those: confirmed live (life counter moved), read OK
    frozen_scans: int                # of those: discarded as frozen
    comm_scans: int                  # of those: with a communication fault
    quality: str = ""                # '' or why the whole sample is suspect ('frozen', 'comm fault')


@dataclass(frozen=True)
class Freshness:
    """The data's state right now (drives the status word)."""
    stale: tuple[str, ...]           # tags not read good within their max_age_s
    frozen: bool                     # the life counter has stopped changing
    comm_fault: bool                 # the last scan had a communication fault
    last_good_sample_time: float | None   # sample clock of the newest confirmed good scan
    flat: tuple[str, ...] = ()       # tags flat-lined right now (reason 'flatline')

    @property
    def data_stale(self) -> bool:
        return self.frozen or bool(self.stale)


@dataclass
class _Scan:
    t_sample: float
    values: dict[str, float | None]   # good value or None
    reasons: dict[str, str]           # tag -> reason for the bad ones
    comm_error: str | None


def plant_running(values: Mapping[str, float | None]) -> bool | None:
    """Is the heat pump running, from one scan's good values (tag -> value, None when bad)?
    The running flag when it was read good, else W_LS + W_HS >= MIN_POWER_KW, else None
    (unknown). A CIP in progress counts as not running."""
    cip = values.get("cip")
    if cip is not None and cip > 0.5:
        return False
    flag = values.get("running")
    if flag is not None:
        return flag >= 0.5
    power = [values.get("W_LS"), values.get("W_HS")]
    if all(p is not None for p in power):
        return sum(power) >= MIN_POWER_KW
    return None


@dataclass
class _Flat:
    """Flat-line tracking of one tag."""
    limit_s: float                   # flat for this long while running: bad
    tol: float                       # a change larger than this is movement
    ref: float | None = None         # value the tag has stayed at
    since: float = 0.0               # sample clock when it started staying (while running)
    flat: bool = False


@dataclass
class _Bucket:
    start: float
    scans: int = 0
    frozen: int = 0
    comm: int = 0
    good: dict[str, list[float]] = field(default_factory=dict)
    reasons: dict[str, Counter] = field(default_factory=dict)


class Aggregator:
    """Groups scans into periods of ``aggregate_s`` seconds of the sample clock.

    tags : the tag configuration (``name`` and ``max_age_s`` are used)
    aggregate_s : period length [s] on the sample clock
    life_counter : name of the PLC life-counter tag, or None (no frozen-data check)
    exclude : tags not aggregated (e.g. the PLC clock); the life counter never is
    min_good_share : share of a period's scans that must be good for a tag to get a value
    t_start : monotonic time of the start (ages count from here before the first good read)

    A tag's ``flatline_s`` (0 or None: see the module doc), ``scale`` and ``type`` are read when
    the tag has them.
    """

    def __init__(self, tags: Sequence[TagLike], aggregate_s: float, *,
                 life_counter: str | None = None, exclude: Iterable[str] = (),
                 min_good_share: float = 0.5, t_start: float = 0.0) -> None:
        if aggregate_s <= 0:
            raise ValueError(f"aggregate_s must be > 0, got {aggregate_s}")
        if not 0 < min_good_share <= 1:
            raise ValueError(f"min_good_share must be in (0, 1], got {min_good_share}")
        names = {t.name for t in tags}
        if life_counter is not None and life_counter not in names:
            raise ValueError(f"life counter {life_counter!r} is not a tag")
        self.aggregate_s = float(aggregate_s)
        self.max_age = {t.name: float(t.max_age_s) for t in tags}
        skip = set(exclude) | ({life_counter} if life_counter else set())
        self.data_tags = tuple(t.name for t in tags if t.name not in skip)
        self.life_counter = life_counter
        self.frozen_after_s = self.max_age[life_counter] if life_counter else math.inf
        self.min_good_share = float(min_good_share)
        self._last_good = {n: float(t_start) for n in self.max_age}
        self._lc_value: float | None = None
        self._lc_changed = float(t_start)
        self._frozen = False
        self._comm_fault = False
        self._pending: list[_Scan] = []
        self._bucket: _Bucket | None = None
        self._last_good_sample_time: float | None = None
        self.frozen_events = 0       # how many times data froze (for logs and tests)
        self._flat: dict[str, _Flat] = {}
        for t in tags:
            limit = flatline_limit(t)
            if limit is not None and t.name in self.data_tags:
                self._flat[t.name] = _Flat(limit, _resolution(t))
        self.flatline_events = 0     # how many times a tag flat-lined

    # ------------------------------------------------------------------------------ input

    def add(self, t_sample: float | None, t_mono: float, values: Mapping[str, ValueLike],
            comm_error: str | None = None) -> list[Sample]:
        """Take one scan; return the periods it closed (usually none, at most a few).

        ``t_sample`` None means the scan cannot be placed in time (e.g. the PLC clock register
        was bad): it still counts for freshness and the life counter, but is not aggregated.
        """
        good: dict[str, float | None] = {}
        reasons: dict[str, str] = {}
        for name in self.max_age:
            v = values.get(name)
            if v is None:
                good[name], reasons[name] = None, comm_error or "not read"
            elif v.bad is not None or v.value is None or not math.isfinite(v.value):
                good[name], reasons[name] = None, v.bad or "nan"
            else:
                good[name] = float(v.value)
                self._last_good[name] = t_mono
        self._comm_fault = comm_error is not None
        scan = _Scan(t_sample, good, reasons, comm_error) if t_sample is not None else None
        out: list[Sample] = []
        if self.life_counter is None:
            if scan is not None:
                out += self._place(scan, discard=None)
            return out
        lc = good.get(self.life_counter)
        if scan is not None:
            self._pending.append(scan)
        if lc is not None and self._lc_value is None:
            self._lc_value, self._lc_changed = lc, t_mono   # first sight: wait for a change
        elif lc is not None and lc != self._lc_value:
            self._lc_value, self._lc_changed = lc, t_mono
            self._frozen = False
            for s in self._pending:          # the PLC was alive after these scans
                out += self._place(s, discard=None)
            self._pending.clear()
        if t_mono - self._lc_changed > self.frozen_after_s:
            # no sign of life for too long: frozen if we read the counter and it stood still,
            # otherwise we could not read it (the scans carry that reason)
            cause = FROZEN if lc is not None else (comm_error or "life counter not read")
            if cause == FROZEN and not self._frozen:
                self.frozen_events += 1
                self._frozen = True
            for s in self._pending:
                out += self._place(s, discard=cause)
            self._pending.clear()
        return out

    def freshness(self, t_mono: float) -> Freshness:
        stale = tuple(n for n, age in self.max_age.items()
                      if n != self.life_counter and t_mono - self._last_good[n] > age)
        flat = tuple(n for n, f in self._flat.items() if f.flat)
        return Freshness(stale, self._frozen, self._comm_fault, self._last_good_sample_time,
                         flat)

    @property
    def flatline_limits(self) -> dict[str, float]:
        """Tag -> flatline_s, for the tags checked for a flat line."""
        return {n: f.limit_s for n, f in self._flat.items()}

    @property
    def pending(self) -> int:
        """Scans waiting for the life counter to move."""
        return len(self._pending)

    # ---------------------------------------------------------------------------- periods

    def _period(self, t: float) -> float:
        return math.floor(t / self.aggregate_s) * self.aggregate_s

    def _place(self, scan: _Scan, discard: str | None) -> list[Sample]:
        """Add a scan to its period; ``discard`` (a reason) drops its values."""
        start = self._period(scan.t_sample)
        out: list[Sample] = []
        b = self._bucket
        if b is not None and start != b.start:
            out.append(self._close(b))    # a later period (or the clock went back): close
            b = None
        if b is None:
            b = self._bucket = _Bucket(start)
        b.scans += 1
        if discard is not None:
            if discard == FROZEN:
                b.frozen += 1
            else:
                b.comm += 1
            for n in self.data_tags:
                b.reasons.setdefault(n, Counter())[discard] += 1
            return out
        if scan.comm_error is not None:
            b.comm += 1
        if self._flat:
            self._flatline(scan)
        any_good = False
        for n in self.data_tags:
            v = scan.values.get(n)
            if v is None:
                b.reasons.setdefault(n, Counter())[scan.reasons.get(n, "not read")] += 1
            else:
                b.good.setdefault(n, []).append(v)
                any_good = True
        if any_good:
            self._last_good_sample_time = scan.t_sample
        return out

    def _flatline(self, scan: _Scan) -> None:
        """Track each tag's flat line on this (confirmed) scan; a flat value is made bad."""
        running = plant_running(scan.values)
        t = scan.t_sample
        for name, f in self._flat.items():
            v = scan.values.get(name)
            if v is None:
                continue                     # bad anyway; the flat line goes on from ref
            if f.ref is None or abs(v - f.ref) > f.tol:
                f.ref, f.since, f.flat = v, t, False      # it moves: alive
                continue
            if not running:
                f.since = t                  # time counts only while the plant runs
            elif not f.flat and t - f.since >= f.limit_s:
                f.flat = True
                self.flatline_events += 1
            if f.flat:                       # stuck stays stuck (also through a stop)
                scan.values[name] = None
                scan.reasons[name] = FLATLINE

    def _close(self, b: _Bucket) -> Sample:
        values: dict[str, float] = {}
        bad: dict[str, str] = {}
        need = max(1, math.ceil(self.min_good_share * b.scans - 1e-9))
        for n in self.data_tags:
            goods = b.good.get(n, [])
            if len(goods) >= need:
                values[n] = _reduce(n, goods)
            else:
                values[n] = math.nan
                reasons = b.reasons.get(n)
                bad[n] = reasons.most_common(1)[0][0] if reasons else "no good value"
        good_scans = b.scans - b.frozen - b.comm
        quality = ""
        if b.frozen * 2 >= b.scans:
            quality = FROZEN
        elif b.comm * 2 >= b.scans:
            quality = "comm fault"
        return Sample(b.start, values, bad, b.scans, good_scans, b.frozen, b.comm, quality)


def flatline_limit(tag: Any) -> float | None:
    """The tag's flat-line time [s of sample clock], or None when it is not checked."""
    limit = getattr(tag, "flatline_s", None)
    if limit is None:
        return FLATLINE_DEFAULT_S if tag.name in FLATLINE_DEFAULT_TAGS else None
    return float(limit) if limit > 0 else None


def _resolution(tag: Any) -> float:
    """A change of the tag's value larger than this is movement: half a raw step for integer
    registers (the value is raw * scale + offset), 0 (any change) for floating-point ones."""
    type_ = getattr(tag, "type", "float32")
    if type_.startswith("float"):
        return 0.0
    return 0.5 * abs(float(getattr(tag, "scale", 1.0)))


def _reduce(name: str, goods: list[float]) -> float:
    if name in FLAGS_ALL:
        return min(goods)
    if name in FLAGS_ANY:
        return max(goods)
    return math.fsum(goods) / len(goods)


def sample_row(sample: Sample) -> dict[str, Any]:
    """The sample as a flat row (tag columns, ``quality``) for measured-side processing."""
    row: dict[str, Any] = dict(sample.values)
    q = sample.quality
    if not q and sample.bad:
        name, why = next(iter(sample.bad.items()))
        q = f"bad: {name} {why}"
    row["quality"] = q
    return row
