"""The metrics the gateway publishes northbound: name, data type, unit, and where each value
comes from. One table for both MQTT modes (Sparkplug B and JSON) and nothing else to change when a
metric is added: a new figure is ONE line in ``SAMPLE_METRICS`` or ``ADVICE_METRICS``.

Three sources:

* ``sample`` - a one-minute sample as stored in the history (``samples`` table): every tag of
  the tag map (``Sample/<tag>``, its unit from tags.yaml) plus the derived columns and the quality
  columns below; published store-and-forward, timestamped with the sample's time;
* ``advice`` - one calibration cycle as stored (``advice`` table): every value field of the
  advisory block (``Advisory/<field>``, its unit from gateway.yaml) plus the calibration results
  below; ``key`` may be a dotted path into the row's JSON ``detail`` (``detail.window.X``);
  published store-and-forward, timestamped with the window end;
* ``status`` - the status word of the advisory block, live (``Status/<bit name>`` and
  ``Status/word``), published when it changes (report by exception).

Data types are Sparkplug B's names (``DATATYPES``); units go into the Sparkplug metric's
property set as ``engUnit`` and into the JSON metric description.
"""
from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

# Sparkplug B data type codes (Sparkplug 3.0, Payload.DataType) of the types used here
DATATYPES = {"Int64": 4, "UInt16": 6, "UInt32": 7, "UInt64": 8, "Double": 10, "Boolean": 11,
             "String": 12}
SOURCES = ("sample", "advice", "status")
# advisory fields the loop fills per cycle: not results of a calibration (last_update is the
# advice row's own time stamp)
ADVISORY_LOOP_FIELDS = ("heartbeat", "status", "last_update", "advice_age_s")


@dataclass(frozen=True)
class MetricSpec:
    name: str        # metric name, '/' separates folders (Sparkplug hosts show them as such)
    datatype: str    # a key of DATATYPES
    unit: str        # engineering unit, '' when none
    source: str      # 'sample' | 'advice' | 'status'
    key: str         # row column, or 'detail.<path>' into the advice detail, or a status bit

    def __post_init__(self) -> None:
        if self.datatype not in DATATYPES:
            raise ValueError(f"metric {self.name}: unknown datatype {self.datatype!r}")
        if self.source not in SOURCES:
            raise ValueError(f"metric {self.name}: unknown source {self.source!r}")


# --- the table: one line per metric beyond the tag map and the advisory block -----------------
SAMPLE_METRICS = (
    MetricSpec("Sample/usable", "Boolean", "", "sample", "usable"),
    MetricSpec("Sample/reason", "String", "", "sample", "reason"),
    MetricSpec("Sample/quality", "String", "", "sample", "quality"),
    MetricSpec("Sample/bad_tags", "String", "", "sample", "bad"),
    MetricSpec("Sample/scans", "UInt32", "", "sample", "scans"),
    MetricSpec("Sample/good_scans", "UInt32", "", "sample", "good_scans"),
    MetricSpec("Sample/p_e", "Double", "bar(a)", "sample", "p_e_bar"),
    MetricSpec("Sample/p_m", "Double", "bar(a)", "sample", "p_m_bar"),
    MetricSpec("Sample/p_c", "Double", "bar(a)", "sample", "p_c_bar"),
    MetricSpec("Sample/dp_source", "Double", "bar", "sample", "dp_source_bar"),
    MetricSpec("Sample/Q_sink", "Double", "kW", "sample", "Q_sink_kW"),
    MetricSpec("Sample/Q_source", "Double", "kW", "sample", "Q_source_kW"),
    MetricSpec("Sample/W_total", "Double", "kW", "sample", "W_total_kW"),
    MetricSpec("Sample/COP", "Double", "1", "sample", "COP"),
    MetricSpec("Sample/heat_balance", "Double", "%", "sample", "heat_balance_pct"),
    MetricSpec("Sample/superheat", "Double", "K", "sample", "superheat_K"),
    MetricSpec("Sample/eta_is_LS", "Double", "1", "sample", "eta_is_LS_meas"),
    MetricSpec("Sample/eta_is_HS", "Double", "1", "sample", "eta_is_HS_meas"),
    MetricSpec("Sample/UA_eva", "Double", "kW/K", "sample", "UA_eva_kW_K"),
    MetricSpec("Sample/R_th_f", "Double", "K/kW", "sample", "R_th_f_K_per_kW"),
)
ADVICE_METRICS = (
    MetricSpec("Calibration/ok", "Boolean", "", "advice", "ok"),
    MetricSpec("Calibration/calibration_ok", "Boolean", "", "advice", "calibration_ok"),
    MetricSpec("Calibration/optimization_ok", "Boolean", "", "advice", "optimization_ok"),
    MetricSpec("Calibration/low_confidence", "Boolean", "", "advice", "low_confidence"),
    MetricSpec("Calibration/message", "String", "", "advice", "message"),
    MetricSpec("Calibration/run_time", "Double", "s", "advice", "detail.run_time_s"),
    MetricSpec("Calibration/iterations", "UInt32", "", "advice", "detail.calibration.iterations"),
    MetricSpec("Calibration/samples", "UInt32", "", "advice", "detail.calibration.n_samples"),
    MetricSpec("Calibration/R_th_f_se", "Double", "K/kW", "advice",
               "detail.window.R_th_f_se_K_per_kW"),
    MetricSpec("Calibration/CF_dp_f_se", "Double", "1", "advice", "detail.window.CF_dp_f_se"),
    MetricSpec("Calibration/coverage_share", "Double", "1", "advice",
               "detail.window.coverage_share"),
    MetricSpec("Calibration/p_m_sp_model_opt", "Double", "bar(g)", "advice",
               "detail.advice.p_m_sp_model_opt_barg"),
    # the forecast and CIP figures (issue 10) go here, one line each, once the chain stores
    # them in the advice detail, e.g.
    # MetricSpec("Forecast/days_to_clean", "Double", "d", "advice", "detail.cip.days_to_clean"),
)
STATUS_WORD = MetricSpec("Status/word", "UInt16", "bits", "status", "word")


@dataclass(frozen=True)
class Catalog:
    """Every published metric in a fixed order; a metric's alias is its position + 1 (alias 0
    is left out; ``bdSeq`` and ``Node Control/Rebirth`` carry no alias)."""
    metrics: tuple[MetricSpec, ...]

    def __post_init__(self) -> None:
        names = [m.name for m in self.metrics]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"metric names used twice: {', '.join(dup)}")

    def alias(self, spec: MetricSpec) -> int:
        return self._index()[spec.name] + 1

    def by_source(self, source: str) -> tuple[MetricSpec, ...]:
        return tuple(m for m in self.metrics if m.source == source)

    def by_name(self, name: str) -> MetricSpec:
        return self.metrics[self._index()[name]]

    def _index(self) -> dict[str, int]:
        idx = self.__dict__.get("_idx")
        if idx is None:
            idx = {m.name: i for i, m in enumerate(self.metrics)}
            object.__setattr__(self, "_idx", idx)
        return idx

    def values(self, source: str, row: Mapping[str, Any]) -> dict[MetricSpec, Any]:
        """Each metric of ``source`` -> its value in ``row`` (a stored sample or advice row, or
        the status dict), typed for its data type; None when the row has no value (absent,
        NULL, NaN). Metrics whose key the row does not have at all are left out, so an older
        row without a newer column publishes nothing for it."""
        detail = None
        out: dict[MetricSpec, Any] = {}
        for spec in self.by_source(source):
            if spec.key.startswith("detail."):
                if detail is None:
                    detail = _detail(row.get("detail"))
                found, v = _path(detail, spec.key.split(".")[1:])
                if not found:
                    continue
            elif spec.key in row:
                v = row[spec.key]
            else:
                continue
            out[spec] = typed(spec.datatype, v)
        return out


def build_catalog(tags: Iterable[Any], advisory_fields: Iterable[Any],
                  status_bits: Iterable[tuple[int, str]]) -> Catalog:
    """The catalog of a configuration: ``tags`` (name, unit) of tags.yaml, the advisory block's
    fields (name, unit) and its status bits ((bit, name)) from gateway.yaml, and the tables
    above."""
    metrics: list[MetricSpec] = [MetricSpec(f"Sample/{t.name}", "Double", t.unit, "sample",
                                            t.name) for t in tags]
    metrics += SAMPLE_METRICS
    metrics += [MetricSpec(f"Advisory/{f.name}", "Double", f.unit, "advice", f.name)
                for f in advisory_fields if f.name not in ADVISORY_LOOP_FIELDS]
    metrics += ADVICE_METRICS
    metrics += [MetricSpec(f"Status/{name}", "Boolean", "", "status", name)
                for _, name in sorted(status_bits)]
    metrics.append(STATUS_WORD)
    return Catalog(tuple(metrics))


def catalog_for(cfg: Any) -> Catalog:
    """The catalog of a loaded ``edge.config.GatewayConfig``."""
    return build_catalog(cfg.tags, cfg.advisory.fields, cfg.advisory.status_bits)


def status_values(bits: Iterable[str], word: int, names: Iterable[str]) -> dict[str, Any]:
    """The status source's row: each configured bit name -> set?, and 'word'."""
    on = set(bits)
    row: dict[str, Any] = {n: n in on for n in names}
    row["word"] = int(word)
    return row


def typed(datatype: str, v: Any) -> Any:
    """A stored value as the data type wants it; None for no value (NULL, NaN, inf, '')."""
    if v is None:
        return None
    if datatype == "String":
        return str(v)
    if isinstance(v, str):
        try:
            v = float(v)
        except ValueError:
            return None
    if hasattr(v, "item"):
        v = v.item()
    if datatype == "Boolean":
        return bool(v)
    f = float(v)
    if not math.isfinite(f):
        return None
    if datatype == "Double":
        return f
    return int(round(f))


def _detail(v: Any) -> Any:
    if isinstance(v, str):
        try:
            return json.loads(v)
        except ValueError:
            return {}
    return v if isinstance(v, Mapping) else {}


def _path(d: Any, parts: list[str]) -> tuple[bool, Any]:
    for p in parts:
        if not isinstance(d, Mapping) or p not in d:
            return False, None
        d = d[p]
    return True, d
