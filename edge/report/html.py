"""One self-contained HTML page: inline CSS, figures as base64 PNG, no scripts, no fonts, no
external reference of any kind (it opens from a USB stick on a laptop without network)."""
from __future__ import annotations

import base64
import math
from html import escape

import pandas as pd

from .data import ReportData
from .figures import ReportFigure

CSS = """
@page { size: A4; margin: 12mm; }
body { font-family: Helvetica, Arial, sans-serif; font-size: 10.5pt; color: #000; background: #fff;
       max-width: 190mm; margin: 0 auto; padding: 4mm; line-height: 1.35; }
h1 { font-size: 17pt; margin: 0 0 2mm 0; }
h2 { font-size: 13pt; margin: 7mm 0 2mm 0; border-bottom: 1px solid #444; }
h3 { font-size: 11pt; margin: 4mm 0 1mm 0; }
table { border-collapse: collapse; margin: 2mm 0; font-size: 9.5pt; }
th, td { border: 1px solid #777; padding: 1mm 2mm; text-align: left; vertical-align: top; }
th { background: #e6e6e6; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
table.meta th { width: 32mm; }
figure { margin: 3mm 0 5mm 0; break-inside: avoid; page-break-inside: avoid; }
figure img { width: 100%; height: auto; border: 1px solid #bbb; }
figcaption { font-size: 9.5pt; margin-top: 1.5mm; }
p.missing { border: 1px dashed #777; padding: 3mm; font-style: italic; }
ul.notes { font-size: 9.5pt; }
.small { font-size: 8.5pt; color: #333; }
@media print { h2 { break-after: avoid; } a { color: #000; text-decoration: none; } }
"""

PARAMETER_WORDS = {
    "CF_DSH": "desuperheater heat-transfer factor",
    "CF_con": "condenser heat-transfer factor",
    "CF_SC": "subcooler heat-transfer factor",
    "CF_eva": "clean-evaporator heat-transfer factor",
    "R_th_f_K_per_kW": "fouling resistance [K/kW]",
    "CF_dp_f": "source pressure-drop factor",
}


def _f(v, fmt: str, none: str = "–") -> str:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return none
    return format(x, fmt) if math.isfinite(x) else none


def _t(ts) -> str:
    if ts is None or pd.isna(ts):
        return "–"
    return pd.Timestamp(ts).strftime("%Y-%m-%d %H:%M UTC")


def _table(header: list[str], rows: list[list[str]], numeric: set[int] = frozenset(),
           cls: str = "") -> str:
    h = "".join(f"<th>{escape(c)}</th>" for c in header)
    body = []
    for r in rows:
        body.append("<tr>" + "".join(
            f'<td class="num">{escape(c)}</td>' if i in numeric else f"<td>{escape(c)}</td>"
            for i, c in enumerate(r)) + "</tr>")
    c = f' class="{cls}"' if cls else ""
    return f"<table{c}><thead><tr>{h}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def plain_warnings(doc: dict) -> list[str]:
    """A calibration document's warnings and flags as sentences an operator can act on."""
    out = []
    if doc.get("success") is False:
        out.append(f"The calibration did not converge ({doc.get('message') or 'no reason given'}); "
                   "its values are not to be used.")
    bounds = doc.get("bounds") or {}
    for name in doc.get("at_bound") or []:
        b = bounds.get(name)
        rng = f" [{b[0]:g}, {b[1]:g}]" if b and len(b) == 2 else ""
        out.append(f"{name} ({PARAMETER_WORDS.get(name, name)}) ended at its bound{rng}: the best "
                   "value may lie outside the allowed range; check the data before trusting it.")
    for w in doc.get("warnings") or []:
        if "are correlated" in w and "cannot separate" in w:
            pair = w.split(" are correlated")[0]
            out.append(f"The data cannot tell {pair} apart: their combined effect is calibrated, "
                       "not each one on its own.")
        elif "determined only jointly" in w:
            out.append(w.split(" is determined")[0] + " is only determined together with other "
                       "factors: its own value is not meaningful.")
        elif "rank-deficient" in w:
            out.append("The targets cannot determine every parameter (a combination of them is "
                       "free): the model still reproduces its targets.")
        elif "standard error" in w:
            out.append(w.split(":")[0] + " is poorly determined by this data (large standard error).")
        elif "do not depend on" in w:
            out.append("The targets do not react to " + w.split("do not depend on ")[1].split(":")[0]
                       + ": it cannot be calibrated from them.")
        else:
            out.append(w)
    if doc.get("identifiable") is False and not out:
        out.append("Not every parameter is identifiable from the targets.")
    return out


def _calibration_block(title: str, doc: dict | None, missing: str) -> str:
    if doc is None:
        return f"<h3>{escape(title)}</h3><p class=\"small\">{escape(missing)}</p>"
    se = doc.get("std_errors") or {}
    rows = []
    for name, v in (doc.get("params") or {}).items():
        rows.append([name, PARAMETER_WORDS.get(name, ""), _f(v, ".5g"), _f(se.get(name), ".3g"),
                     "yes" if name in (doc.get("at_bound") or []) else ""])
    nr = doc.get("nrmse") or {}
    window = ""
    if doc.get("window_start"):
        window = f" on {doc.get('n_samples', '?')} samples, {doc['window_start']} .. {doc.get('window_end')}"
    html = [f"<h3>{escape(title)}</h3>",
            f"<p class=\"small\">{escape(doc.get('kind', ''))} calibration{escape(window)}; NRMSE "
            + escape(", ".join(f"{k} {100 * v:.2f} %" for k, v in nr.items() if v is not None) or "–")
            + "</p>",
            _table(["parameter", "meaning", "value", "standard error", "at bound"], rows, {2, 3})]
    words = plain_warnings(doc)
    if words:
        html.append("<ul>" + "".join(f"<li>{escape(w)}</li>" for w in words) + "</ul>")
        if doc.get("warnings"):
            html.append("<p class=\"small\">As reported: " + escape(" | ".join(doc["warnings"]))
                        + "</p>")
    else:
        html.append("<p class=\"small\">No warnings: every parameter is determined by the data.</p>")
    return "".join(html)


def _dp_block(doc: dict | None) -> str:
    if doc is None:
        return "<h3>Clean pressure-drop fit</h3><p class=\"small\">not in the source</p>"
    c = doc.get("coef_bar") or [math.nan] * 3
    vr = doc.get("V_range_m3h") or [math.nan, math.nan]
    txt = (f"dp_clean = {_f(c[0], '.4g')} + {_f(c[1], '.4g')}·V + {_f(c[2], '.4g')}·V² bar "
           f"(V in m³/h, {doc.get('form', 'quadratic')}), R² {_f(doc.get('r2'), '.3f')}, flows "
           f"{_f(vr[0], '.0f')}–{_f(vr[1], '.0f')} m³/h, {doc.get('n_samples', '?')} samples")
    note = f" Note: {doc['note']}" if doc.get("note") else ""
    return f"<h3>Clean pressure-drop fit</h3><p>{escape(txt + '.' + note)}</p>"


def _window_warnings(data: ReportData) -> str:
    w = data.windows
    ok = w[w["status"] == "ok"]
    failed = w[w["status"] != "ok"]
    parts = [f"<p>{len(ok)} calibration windows succeeded, {len(failed)} failed in the period.</p>"]
    if len(failed):
        reasons = failed["status"].str.replace(r"^failed:\s*", "", regex=True).value_counts()
        parts.append("<ul>" + "".join(f"<li>{escape(str(k))}: {v} window(s)</li>"
                                      for k, v in reasons.head(8).items()) + "</ul>")
    warn = ok["calibration_warnings"].fillna("").astype(str)
    counts: dict[str, int] = {}
    for text in warn:
        for item in [x.strip() for x in text.split(";") if x.strip()]:
            counts[item] = counts.get(item, 0) + 1
    if counts:
        words = []
        for item, n in sorted(counts.items(), key=lambda kv: -kv[1]):
            sentence = plain_warnings({"warnings": [item]})[0]
            words.append(f"<li>{escape(sentence)} ({n} window(s))</li>")
        parts.append("<p>Fouling calibration warnings:</p><ul>" + "".join(words) + "</ul>")
    last = ok.tail(1)
    if len(last):
        r = last.iloc[0]
        rows = [["R_th_f_K_per_kW", PARAMETER_WORDS["R_th_f_K_per_kW"],
                 _f(r["R_th_f_K_per_kW"], ".4g"), _f(r["R_th_f_se_K_per_kW"], ".2g")],
                ["CF_dp_f", PARAMETER_WORDS["CF_dp_f"], _f(r["CF_dp_f"], ".4f"), _f(r["CF_dp_f_se"], ".2g")]]
        parts.append(f"<p class=\"small\">Latest window ({_t(r['window_start'])} .. "
                     f"{_t(r['window_end'])}); share of the evaporator resistance "
                     f"{_f(r['R_th_f_share_pct'], '.1f')} %:</p>")
        parts.append(_table(["parameter", "meaning", "value", "standard error"], rows, {2, 3}))
    return "".join(parts)


def _cip_table(data: ReportData) -> str:
    c = data.cips
    if not len(c):
        return "<p>No CIP in the period.</p>"
    rows = []
    for _, r in c.iterrows():
        rows.append([_t(r["cip_start"]), _t(r["cip_end"]), _f(r["duration_h"], ".1f"),
                     str(r["detected_by"] or "–"), _f(1e3 * r["R_th_f_before_K_per_kW"], ".2f"),
                     _f(1e3 * r["R_th_f_after_K_per_kW"], ".2f"), _f(r["R_th_f_removed_pct"], ".1f"),
                     _f(r["CF_dp_f_before"], ".3f"), _f(r["CF_dp_f_after"], ".3f")])
    return _table(["start", "end", "hours", "detected by", "R_th,f before [1e-3 K/kW]",
                   "R_th,f after [1e-3 K/kW]", "removed [%]", "CF_dp,f before", "CF_dp,f after"],
                  rows, {2, 4, 5, 6, 7, 8}) + (
        "<p class=\"small\">Before/after: the calibration windows next to each CIP; a dash where "
        "the period holds none.</p>")


def _coverage(data: ReportData) -> str:
    cov = data.coverage
    if not cov:
        return "unknown (the source carries no per-sample data)"
    n, u = cov["n_rows"], cov["n_usable"]
    share = 100.0 * u / n if n else math.nan
    txt = f"{u} of {n} one-minute samples usable ({_f(share, '.1f')} %)"
    if cov.get("unusable"):
        txt += "; unusable: " + ", ".join(f"{k} {v}" for k, v in
                                          sorted(cov["unusable"].items(), key=lambda kv: -kv[1]))
    return txt + f" [{cov.get('scope', '')}]"


def _figure_html(i: int, f: ReportFigure) -> str:
    pts = ";".join(f"{k}={v}" for k, v in f.points().items())
    head = f"<h2 id=\"fig-{f.key}\">Figure {i}. {escape(f.title)}</h2>"
    if f.png is None:
        return (f"{head}<figure data-figure=\"{f.key}\" data-points=\"\"><p class=\"missing\">Not "
                f"available: {escape(f.missing)}.</p><figcaption>{escape(f.caption)}</figcaption>"
                "</figure>")
    b64 = base64.b64encode(f.png).decode("ascii")
    return (f"{head}<figure data-figure=\"{f.key}\" data-points=\"{escape(pts)}\">"
            f"<img alt=\"{escape(f.title)}\" src=\"data:image/png;base64,{b64}\">"
            f"<figcaption>{escape(f.caption)}</figcaption></figure>")


def render(data: ReportData, figures: list[ReportFigure], version: str, generated: str,
           notes: list[str]) -> str:
    """The whole page."""
    p0, p1 = data.period
    meta_rows = [["Plant", data.plant], ["Source", data.source],
                 ["Period", f"{_t(p0)} – {_t(p1)}"], ["Data coverage", _coverage(data)],
                 ["hp-edge", f"version {version}, report generated {generated}"
                  + (f"; replay made by version {data.meta['hp_edge_version']}"
                     if data.meta.get("hp_edge_version") else "")],
                 ["Adaptive model", f"per sample: {data.adaptive_rule}"]]
    meta = "<table class=\"meta\"><tbody>" + "".join(
        f"<tr><th>{escape(k)}</th><td>{escape(str(v))}</td></tr>" for k, v in meta_rows) + "</tbody></table>"
    note_html = ("<ul class=\"notes\">" + "".join(f"<li>{escape(n)}</li>" for n in notes) + "</ul>"
                 if notes else "")
    figs = "".join(_figure_html(i, f) for i, f in enumerate(figures, start=1))
    tables = ("<h2 id=\"cips\">CIPs</h2>" + _cip_table(data)
              + "<h2 id=\"calibration\">Calibration</h2>"
              + _calibration_block("Initial calibration (the fixed model)", data.state.get("initial"),
                                   "No initial calibration in the source: the fixed model is the "
                                   "data sheet (plant.yaml).")
              + _dp_block(data.state.get("dp_clean"))
              + "<h3>Fouling calibration (the adaptive model)</h3>" + _window_warnings(data)
              + (_calibration_block("Gateway's last fouling calibration (state directory)",
                                    data.state.get("fouling"), "")
                 if data.state.get("fouling") is not None else ""))
    title = f"hp-edge report: {data.plant}, {_t(p0)} – {_t(p1)}"
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{escape(title)}</title><style>{CSS}</style></head><body>"
            f"<h1>hp-edge report</h1>{meta}{note_html}{figs}{tables}</body></html>\n")

