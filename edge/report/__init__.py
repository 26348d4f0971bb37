"""``hp-edge report``: one self-contained HTML file with the papers' figures for any plant, from a
replay directory or the gateway's history database with its state directory.

    data = load_replay(DIR, params, plant)          # or load_gateway(DB, STATE_DIR, params, plant)
    result = build_report(data, "report.html")      # -> ReportResult (figures with their data)

edge.report.data reads the sources (every column name in one place), edge.report.model computes
what the sources do not carry with model/, edge.report.figures draws (matplotlib, the optional
``report`` extra, imported only here), edge.report.html writes the page. The gateway never imports
this package.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from .data import ReportData, ReportSourceError, load_gateway, load_replay
from .model import DEFAULT_MAX_MODEL_SAMPLES, model_for_report

__all__ = ["ReportData", "ReportResult", "ReportSourceError", "build_report", "load_gateway",
           "load_replay", "model_for_report", "hp_edge_version", "MatplotlibMissing"]


class MatplotlibMissing(RuntimeError):
    """matplotlib is not installed (the optional ``report`` extra)."""


@dataclass
class ReportResult:
    path: Path
    figures: list                    # edge.report.figures.ReportFigure, in page order
    notes: list[str] = field(default_factory=list)
    run_time_s: float = 0.0
    size_bytes: int = 0

    def figure(self, key: str):
        return next(f for f in self.figures if f.key == key)


def hp_edge_version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("hp-edge")
    except PackageNotFoundError:
        return "unknown (not installed)"


def build_report(data: ReportData, out: str | os.PathLike,
                 max_model_samples: int = DEFAULT_MAX_MODEL_SAMPLES) -> ReportResult:
    """Compute what the source lacks, draw every figure and write the page to ``out``
    (atomically). Raises MatplotlibMissing without the ``report`` extra."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise MatplotlibMissing("the report needs matplotlib: pip install 'hp-edge[report]'") from None
    from . import figures as F
    from .html import render
    from .model import (ModelValues, add_eta_model, add_model_values, cop_curves, fouling_levels,
                        model_notes, representative_point, speeds_for_curves)

    t0 = time.perf_counter()
    notes = list(data.notes)
    fixed = model_for_report(data.params, data.state)
    notes += model_notes(data.state)
    mv = ModelValues()                      # nothing simulated: the source carries the values
    if data.samples is not None and data.recomputed_samples:
        mv = add_model_values(data, fixed, max_model_samples)
        notes += mv.notes
    add_eta_model(data, fixed)
    point = representative_point(data)
    curves, why = [], ""
    if point is None:
        why = "the source has no usable samples with boundary conditions (T_source, T_sink, flows)"
    else:
        curves = cop_curves(fixed, point, fouling_levels(data.windows))
    speeds = {st: speeds_for_curves(data, fixed, st) for st in ("LS", "HS")}
    with F.style():
        figs = [F.fig_timeseries(data, mv), F.fig_residuals(data, mv), F.fig_fouling(data),
                F.fig_pressure_drop(data), F.fig_setpoint(data),
                F.fig_cop_vs_setpoint(point, curves, why), F.fig_compressors(data, fixed, speeds)]
    generated = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    page = render(data, figs, hp_edge_version(), generated, notes)
    out = Path(out)
    if out.parent != Path(""):
        out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(page, encoding="utf-8")
    os.replace(tmp, out)
    return ReportResult(out, figs, notes, time.perf_counter() - t0, len(page.encode("utf-8")))
