"""The report's figures (matplotlib, Agg, no pyplot state): one builder per figure, each returning
a ``ReportFigure`` with the PNG and the arrays it plotted (``series``), so tests and the HTML can
check what a figure shows.

Readable in greyscale print and at 80 % zoom: every series differs by line style or marker, not
only by colour; CIPs are hatched; fonts are 8-9 pt on a 7-inch-wide figure (the width of an A4 page
inside its margins).
"""
from __future__ import annotations

import io
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .data import ReportData
from .model import CopCurve, ModelValues

WIDTH_IN = 7.0
PANEL_IN = 1.9
DPI = 150
MEASURED = dict(color="0.45", marker=".", markersize=2.5, linestyle="none")
FIXED = dict(color="black", linestyle="--", linewidth=1.0)
ADAPTIVE = dict(color="#1f5fa8", linestyle="-", linewidth=1.2)
CIP_SPAN = dict(facecolor="0.88", edgecolor="0.55", hatch="///", linewidth=0.0, zorder=0)
LEVEL_STYLES = (("-", "o", "#1f5fa8"), ("--", "s", "black"), (":", "^", "#b2182b"))
SPEED_STYLES = (("--", "0.2"), ("-", "black"), (":", "0.2"))


@dataclass
class ReportFigure:
    key: str
    title: str
    caption: str
    png: bytes | None = None
    series: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    missing: str = ""        # why the figure could not be drawn ("" when drawn)

    def points(self) -> dict[str, int]:
        """Finite points per plotted series."""
        return {k: int(np.isfinite(np.asarray(y, dtype=float)).sum()) for k, (_, y) in self.series.items()}


def style():
    """The report's matplotlib settings, as a context manager around the figure builders."""
    import matplotlib
    return matplotlib.rc_context(_RC)


_RC = {"font.size": 8.5, "axes.titlesize": 9, "axes.labelsize": 8.5, "legend.fontsize": 7.5,
       "xtick.labelsize": 7.5, "ytick.labelsize": 7.5, "axes.grid": True, "grid.color": "0.85",
       "grid.linewidth": 0.6, "lines.markeredgewidth": 0.8}


def _figure(n_rows: int, n_cols: int = 1, height: float | None = None, sharex: bool = True):
    from matplotlib.figure import Figure   # no pyplot: no global figure state, no GUI backend

    fig = Figure(figsize=(WIDTH_IN, height or PANEL_IN * n_rows + 0.5), dpi=DPI, layout="constrained")
    axes = fig.subplots(n_rows, n_cols, sharex=sharex, squeeze=False)
    return fig, axes


def _png(fig) -> bytes:
    """PNG bytes without the 'Software' text chunk (matplotlib puts its web address there)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None})
    return buf.getvalue()


def _naive(t) -> np.ndarray:
    """UTC times -> naive datetime64 (matplotlib's date axis; the axis label says UTC)."""
    idx = pd.DatetimeIndex(pd.Series(t))
    if idx.tz is not None:
        idx = idx.tz_convert("UTC").tz_localize(None)
    return idx.to_numpy(dtype="datetime64[ns]")


def _gapped(x: np.ndarray, y: np.ndarray, max_gap: np.timedelta64):
    """Insert NaN where consecutive finite points are further apart than max_gap (no line across
    a CIP or a stop)."""
    ok = np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2:
        return x, y
    cut = np.flatnonzero(np.diff(x) > max_gap) + 1
    return np.insert(x, cut, x[cut] - np.timedelta64(1, "s")), np.insert(y, cut, np.nan)


def _date_axis(ax) -> None:
    import matplotlib.dates as mdates
    loc = mdates.AutoDateLocator(minticks=3, maxticks=8)
    ax.xaxis.set_major_locator(loc)
    ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))


def _shade_cips(ax, data: ReportData, label: bool) -> None:
    """Hatch each CIP, at least 1/250 of the period wide so a short one stays visible."""
    p0, p1 = _naive([data.period[0]])[0], _naive([data.period[1]])[0]
    least = (p1 - p0) / 250 if not (np.isnat(p0) or np.isnat(p1)) else np.timedelta64(0, "s")
    for i, (a, b) in enumerate(zip(_naive(data.cips["cip_start"]), _naive(data.cips["cip_end"]))):
        if np.isnat(a) or np.isnat(b):
            continue
        if b - a < least:
            a, b = a + (b - a) / 2 - least / 2, a + (b - a) / 2 + least / 2
        ax.axvspan(a, b, label="CIP" if (label and i == 0) else None, **CIP_SPAN)


def _missing(key: str, title: str, caption: str, why: str) -> ReportFigure:
    return ReportFigure(key, title, caption, missing=why)


def _mid(w: pd.DataFrame) -> np.ndarray:
    a, b = _naive(w["window_start"]), _naive(w["window_end"])
    return a + (b - a) / 2


# --------------------------------------------------------------------------- 1 + 2: time series

QUANTITIES = (("COP", "COP", "COP [-]"), ("Q_sink_kW", "heat output", "Q_sink [kW]"),
              ("p_e_bar", "evaporating pressure", "p_e [bar a]"))


def _nrmse(sim: np.ndarray, meas: np.ndarray) -> float:
    ok = np.isfinite(sim) & np.isfinite(meas)
    if not ok.any() or not np.mean(meas[ok]) > 0:
        return math.nan
    return float(np.sqrt(np.mean((sim[ok] - meas[ok]) ** 2)) / np.mean(meas[ok]))


def fig_timeseries(data: ReportData, mv: ModelValues) -> ReportFigure:
    key, title = "timeseries", "Measured, fixed-model and adaptive-model COP, heat output and p_e"
    cap = ("Read: the adaptive model (solid) should follow the measurement (dots) through the "
           "fouling while the fixed model (dashed) drifts from it as the evaporator fouls and "
           "comes back after each CIP (hatched).")
    s = data.samples
    if s is None or not len(s):
        return _missing(key, title, cap, "no per-sample data in the source")
    usable = s["usable"].to_numpy(dtype=float) > 0.5
    t = _naive(s["timestamp"])
    fig, axes = _figure(3)
    series = {}
    gap = np.timedelta64(max(5, 3 * mv.step) * 60, "s")
    texts = []
    for ax, (q, name, label) in zip(axes[:, 0], QUANTITIES):
        meas = np.where(usable, s[f"{q}_measured"].to_numpy(dtype=float), np.nan)
        fx = s[f"{q}_fixed"].to_numpy(dtype=float)
        ad = s[f"{q}_adaptive"].to_numpy(dtype=float)
        _shade_cips(ax, data, label=ax is axes[0, 0])
        ax.plot(*_gapped(t, fx, gap), label="fixed model", **FIXED)
        ax.plot(*_gapped(t, ad, gap), label="adaptive model", **ADAPTIVE)
        ax.plot(t, meas, label="measured", zorder=3, **MEASURED)   # on top: the reference
        ax.set_ylabel(label)
        series[f"{q}_measured"], series[f"{q}_fixed"], series[f"{q}_adaptive"] = (t, meas), (t, fx), (t, ad)
        nf, na = _nrmse(fx, meas), _nrmse(ad, meas)
        if math.isfinite(nf) or math.isfinite(na):
            texts.append(f"{name} NRMSE fixed {100 * nf:.2f} %, adaptive {100 * na:.2f} %")
    axes[0, 0].legend(loc="best", ncols=4, frameon=True)
    axes[-1, 0].set_xlabel("time (UTC)")
    _date_axis(axes[-1, 0])
    if mv.caption:
        cap += f" {mv.caption[0].upper() + mv.caption[1:]}."
    if texts:
        cap += " " + "; ".join(texts) + "."
    return ReportFigure(key, title, cap, _png(fig), series)


def fig_residuals(data: ReportData, mv: ModelValues) -> ReportFigure:
    key, title = "residuals", "Residuals: model minus measurement"
    cap = ("Read: the adaptive model's residuals (solid) should scatter around zero; the fixed "
           "model's (dashed) grow with fouling and shrink after each CIP.")
    s = data.samples
    if s is None or not len(s):
        return _missing(key, title, cap, "no per-sample data in the source")
    usable = s["usable"].to_numpy(dtype=float) > 0.5
    t = _naive(s["timestamp"])
    fig, axes = _figure(3)
    series = {}
    fx_style = dict(FIXED, marker="x", markersize=2.5, linestyle="none")
    ad_style = dict(ADAPTIVE, marker="o", markersize=2.0, linestyle="none", fillstyle="none")
    for ax, (q, _, label) in zip(axes[:, 0], QUANTITIES):
        meas = np.where(usable, s[f"{q}_measured"].to_numpy(dtype=float), np.nan)
        rf = s[f"{q}_fixed"].to_numpy(dtype=float) - meas
        ra = s[f"{q}_adaptive"].to_numpy(dtype=float) - meas
        _shade_cips(ax, data, label=ax is axes[0, 0])
        ax.axhline(0.0, color="black", linewidth=0.6, linestyle=":")
        ax.plot(t, rf, label="fixed model", **fx_style)
        ax.plot(t, ra, label="adaptive model", **ad_style)
        ax.set_ylabel("Δ" + label)
        series[f"{q}_residual_fixed"], series[f"{q}_residual_adaptive"] = (t, rf), (t, ra)
    axes[0, 0].legend(loc="best", ncols=3)
    axes[-1, 0].set_xlabel("time (UTC)")
    _date_axis(axes[-1, 0])
    if mv.caption:
        cap += f" {mv.caption[0].upper() + mv.caption[1:]}."
    return ReportFigure(key, title, cap, _png(fig), series)


# --------------------------------------------------------------------------- 3 + 4: fouling


def _ok_windows(data: ReportData) -> pd.DataFrame:
    w = data.windows
    return w[(w["status"] == "ok")].dropna(subset=["R_th_f_K_per_kW"]).reset_index(drop=True)


def fig_fouling(data: ReportData) -> ReportFigure:
    key, title = "fouling", "Fouling resistance R_th,f and its share of the evaporator resistance"
    cap = ("Read: R_th,f per calibration window (bars: ± one standard error) and its share of the "
           "evaporator's thermal resistance; a rising trend is fouling, the drop at a CIP (hatched, "
           "labelled with the share of R_th,f it removed) its cleaning effect.")
    w = _ok_windows(data)
    if not len(w):
        return _missing(key, title, cap, "no successful calibration window in the period")
    fig, axes = _figure(2, height=4.6)
    ax, ax2 = axes[0, 0], axes[1, 0]
    x = _mid(w)
    R = 1e3 * w["R_th_f_K_per_kW"].to_numpy(dtype=float)
    se = 1e3 * w["R_th_f_se_K_per_kW"].to_numpy(dtype=float)
    share = w["R_th_f_share_pct"].to_numpy(dtype=float)
    series = {"R_th_f": (x, R / 1e3), "R_th_f_se": (x, se / 1e3), "R_th_f_share_pct": (x, share)}
    for a in (ax, ax2):
        _shade_cips(a, data, label=a is ax)
    ax.errorbar(x, R, yerr=np.where(np.isfinite(se), se, 0.0), fmt="o", color="black",
                markersize=3.5, capsize=2, elinewidth=0.8, label="R_th,f per window ± SE")
    f = data.forecast
    if f is not None and len(f) and f["R_th_f_forecast_K_per_kW"].notna().any():
        fa = _naive(f["forecast_at"])
        fv = 1e3 * f["R_th_f_forecast_K_per_kW"].to_numpy(dtype=float)
        lo = 1e3 * f["R_th_f_forecast_lo_K_per_kW"].to_numpy(dtype=float)
        hi = 1e3 * f["R_th_f_forecast_hi_K_per_kW"].to_numpy(dtype=float)
        order = np.argsort(fa)
        ax.fill_between(fa[order], lo[order], hi[order], facecolor="none", edgecolor="0.5",
                        hatch="....", linewidth=0.0, label="forecast 90 % band")
        ax.plot(fa[order], fv[order], color="#b2182b", linestyle="-.", linewidth=1.1,
                label="forecast (at window end + horizon)")
        series.update({"forecast": (fa, fv / 1e3), "forecast_lo": (fa, lo / 1e3),
                       "forecast_hi": (fa, hi / 1e3)})
        cap += (" Dash-dot: the fouling forecast made at each window for its horizon, with its "
                "90 % band (dotted hatch).")
    elif data.forecast is None:
        cap += " (No fouling forecast in the source.)"
    removed = []
    t_lo, t_hi = _naive([data.period[0]])[0], _naive([data.period[1]])[0]
    near = (t_hi - t_lo) / 20 if not (np.isnat(t_lo) or np.isnat(t_hi)) else None
    level, last_x = 0, None
    for _, c in data.cips.iterrows():
        if pd.isna(c["cip_start"]) or not math.isfinite(c["R_th_f_removed_pct"]):
            continue
        xc = _naive([c["cip_start"]])[0] + (_naive([c["cip_end"]])[0] - _naive([c["cip_start"]])[0]) / 2
        # labels closer than 1/20 of the period are staggered in three rows, so none hides another
        level = (level + 1) % 3 if (near is not None and last_x is not None
                                    and xc - last_x < near) else 0
        last_x = xc
        ax.annotate(f"−{c['R_th_f_removed_pct']:.0f} %", (xc, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(0, -2 - 11 * level), textcoords="offset points", ha="center", va="top",
                    fontsize=7.5,
                    bbox=dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="0.5",
                              linewidth=0.5))
        removed.append((xc, float(c["R_th_f_removed_pct"])))
    if removed:
        series["cip_removed_pct"] = (np.array([r[0] for r in removed]), np.array([r[1] for r in removed]))
    ax.set_ylabel("R_th,f [1e-3 K/kW]")
    ax.legend(loc="best")
    ax2.plot(x, share, marker="s", markersize=3.5, linestyle="none", color="0.2",
             fillstyle="none", label="share of the evaporator resistance")
    ax2.set_ylabel("share of R_eva [%]")
    ax2.set_xlabel("time (UTC), middle of each window")
    _date_axis(ax2)
    return ReportFigure(key, title, cap, _png(fig), series)


def fig_pressure_drop(data: ReportData) -> ReportFigure:
    key, title = "pressure_drop", "Fouling pressure-drop factor CF_dp,f and fouling pressure drop"
    cap = ("Read: CF_dp,f (1 = clean) per window with ± one standard error, and the extra source-side "
           "pressure drop it causes at the window's flow; both rise with fouling and fall at a CIP.")
    w = _ok_windows(data)
    if not len(w) or not w["CF_dp_f"].notna().any():
        return _missing(key, title, cap, "no successful calibration window in the period")
    fig, axes = _figure(2, height=4.2)
    ax, ax2 = axes[0, 0], axes[1, 0]
    x = _mid(w)
    CF = w["CF_dp_f"].to_numpy(dtype=float)
    se = w["CF_dp_f_se"].to_numpy(dtype=float)
    dp = w["dp_fouling_bar"].to_numpy(dtype=float)
    for a in (ax, ax2):
        _shade_cips(a, data, label=a is ax)
    ax.errorbar(x, CF, yerr=np.where(np.isfinite(se), se, 0.0), fmt="D", color="black",
                markersize=3, capsize=2, elinewidth=0.8, label="CF_dp,f ± SE")
    ax.axhline(1.0, color="0.3", linestyle=":", linewidth=0.8, label="clean (1)")
    ax.set_ylabel("CF_dp,f [-]")
    ax.legend(loc="best")
    ax2.plot(x, 1e3 * dp, marker="v", markersize=3.5, linestyle="none", color="0.2",
             fillstyle="none")
    ax2.set_ylabel("fouling Δp [mbar]")
    ax2.set_xlabel("time (UTC), middle of each window")
    _date_axis(ax2)
    return ReportFigure(key, title, cap, _png(fig),
                        {"CF_dp_f": (x, CF), "CF_dp_f_se": (x, se), "dp_fouling_bar": (x, dp)})


# --------------------------------------------------------------------------- 5: set point


def fig_setpoint(data: ReportData) -> ReportFigure:
    key, title = "setpoint", "Recommended, actual and geometric-mean intermediate pressure"
    cap = ("Read: where the recommended set point (circles) sits against the actual one (crosses) "
           "and the geometric mean √(p_e·p_c) (triangles), and the COP gain expected from moving to "
           "it (lower panel).")
    w = data.windows[data.windows["status"] == "ok"].reset_index(drop=True)
    if not len(w) or not w["p_m_sp_opt_barg"].notna().any():
        return _missing(key, title, cap, "no set-point recommendation in the period")
    fig, axes = _figure(2, height=4.4)
    ax, ax2 = axes[0, 0], axes[1, 0]
    x = _naive(w["window_end"])
    act = w["p_m_sp_actual_barg"].to_numpy(dtype=float)
    rec = w["p_m_sp_opt_barg"].to_numpy(dtype=float)
    gm = w["p_m_gm_barg"].to_numpy(dtype=float)
    dcop = w["dCOP_opt_pct"].to_numpy(dtype=float)
    sd = w["dCOP_opt_sd_pct"].to_numpy(dtype=float)
    conf = w["advice_confident"].to_numpy(dtype=float)
    has_conf = np.isfinite(conf).any()
    unsure = has_conf & (conf < 0.5)
    for a in (ax, ax2):
        _shade_cips(a, data, label=a is ax)
    ax.plot(x, act, marker="x", markersize=4, linestyle="-", linewidth=0.7, color="black",
            label="actual")
    ax.plot(x, gm, marker="^", markersize=3.5, linestyle="--", linewidth=0.7, color="0.45",
            fillstyle="none", label="geometric mean")
    sure = ~unsure
    ax.plot(x[sure], rec[sure], marker="o", markersize=4, linestyle="none", color="#1f5fa8",
            label="recommended")
    if unsure.any():
        ax.plot(x[unsure], rec[unsure], marker="o", markersize=4, linestyle="none", color="#1f5fa8",
                fillstyle="none", label="recommended, not confident")
    ax.set_ylabel("p_m,sp [bar(g)]")
    ax.legend(loc="best", ncols=2)
    yerr = np.where(np.isfinite(sd), sd, 0.0)
    ax2.axhline(0.0, color="black", linewidth=0.6, linestyle=":")
    ax2.errorbar(x[sure], dcop[sure], yerr=yerr[sure], fmt="o", color="#1f5fa8", markersize=3.5,
                 capsize=2, elinewidth=0.8, label="expected ΔCOP" + (" ± SD" if np.isfinite(sd).any() else ""))
    if unsure.any():
        ax2.errorbar(x[unsure], dcop[unsure], yerr=yerr[unsure], fmt="o", color="#1f5fa8",
                     markersize=3.5, capsize=2, elinewidth=0.8, fillstyle="none",
                     label="not confident")
    ax2.set_ylabel("expected ΔCOP [%]")
    ax2.set_xlabel("time (UTC), end of each window")
    ax2.legend(loc="best")
    _date_axis(ax2)
    if np.isfinite(sd).any():
        cap += " Bars: the expected gain's standard deviation."
    if has_conf:
        cap += (f" Hollow markers: advice not confident ({int(unsure.sum())} of {len(w)} windows; "
                "the block then recommends keeping the current set point).")
        why = w.loc[unsure, "advice_note"].astype(str).str.strip()
        why = why[why != ""].value_counts()
        if len(why):
            cap += " Why: " + "; ".join(f"{k} ({v})" for k, v in why.head(4).items()) + "."
    return ReportFigure(key, title, cap, _png(fig),
                        {"p_m_sp_actual_barg": (x, act), "p_m_sp_opt_barg": (x, rec),
                         "p_m_gm_barg": (x, gm), "dCOP_opt_pct": (x, dcop),
                         "dCOP_opt_sd_pct": (x, sd)})


# --------------------------------------------------------------------------- 6: COP vs set point


def fig_cop_vs_setpoint(point: dict | None, curves: list[CopCurve], why: str = "") -> ReportFigure:
    key, title = "cop_vs_setpoint", "COP against the intermediate-pressure set point at three fouling levels"
    cap = ("Read: how the model's COP depends on p_m,sp at the period's typical operating point, "
           "where its optimum lies (filled markers) against the geometric mean (crosses) and the "
           "usual set point (dotted line), and how both move as the evaporator fouls.")
    if point is None or not curves:
        return _missing(key, title, cap, why or "no representative operating point")
    fig, axes = _figure(1, height=3.4)
    ax = axes[0, 0]
    series = {}
    lines = []
    for (ls, mk, col), c in zip(LEVEL_STYLES, curves):
        if not len(c.p_m_sp_barg):
            lines.append(f"{c.label}: {c.note}")
            continue
        lab = f"{c.label}: R_th,f {1e3 * c.R_th_f_K_per_kW:.2f}e-3 K/kW"
        ax.plot(c.p_m_sp_barg, c.COP, linestyle=ls, color=col, linewidth=1.2, label=lab)
        ax.plot([c.p_m_sp_opt_barg], [c.COP_opt], marker=mk, color=col, markersize=6,
                linestyle="none")
        ax.plot([c.p_m_gm_barg], [c.COP_gm], marker="x", color=col, markersize=6, linestyle="none")
        series[f"COP_{c.label}"] = (c.p_m_sp_barg, c.COP)
        series[f"optimum_{c.label}"] = (np.array([c.p_m_sp_opt_barg]), np.array([c.COP_opt]))
        lines.append(f"{c.label} optimum {c.p_m_sp_opt_barg:.2f} bar(g), COP {c.COP_opt:.3f}"
                     + (" (lowest p_m the HS compressor can hold)" if c.hs_saturated_opt else "")
                     + f", geometric mean {c.p_m_gm_barg:.2f} bar(g)")
    ax.axvline(point["p_m_sp"], color="0.3", linestyle=":", linewidth=0.9,
               label=f"median set point {point['p_m_sp']:.1f} bar(g)")
    ax.set_xlabel("p_m,sp [bar(g)]")
    ax.set_ylabel("COP [-]")
    ax.legend(loc="best")
    cap += (f" Operating point (median of {point['n_samples']} usable samples): source "
            f"{point['T_source_in']:.1f} → {point['T_source_out']:.1f} °C at {point['V_source']:.0f} m³/h, "
            f"sink return {point['T_sink_in']:.1f} °C at {point['V_sink']:.0f} m³/h. "
            + "; ".join(lines) + ".")
    return ReportFigure(key, title, cap, _png(fig), series)


# --------------------------------------------------------------------------- 7: compressors


def fig_compressors(data: ReportData, fixed, speeds: dict) -> ReportFigure:
    key, title = "compressors", "Compressor isentropic efficiency: measured against the curve in use"
    cap = ("Read: each sample's measured η_is (dots) against the model's curve at the period's "
           "10th/50th/90th-percentile speed (lines); points systematically below the curves mean the "
           "compressor does worse than the model assumes (wear, or curves that are not this plant's).")
    s = data.samples
    if s is None or not len(s):
        return _missing(key, title, cap, "no per-sample data in the source")
    usable = s["usable"].to_numpy(dtype=float) > 0.5
    fig, axes = _figure(1, 2, height=3.0, sharex=False)
    series = {}
    notes = []
    for ax, stage in zip(axes[0], ("LS", "HS")):
        comp = fixed.comp_LS if stage == "LS" else fixed.comp_HS
        pi = np.where(usable, s[f"pi_{stage}"].to_numpy(dtype=float), np.nan)
        eta = np.where(usable, s[f"eta_is_{stage}_meas"].to_numpy(dtype=float), np.nan)
        model = np.where(usable, s[f"eta_is_{stage}_model"].to_numpy(dtype=float), np.nan)
        ok = np.isfinite(pi) & np.isfinite(eta)
        ax.plot(pi, eta, label="measured", **MEASURED)
        series[f"eta_is_{stage}_meas"] = (pi, eta)
        series[f"eta_is_{stage}_model"] = (pi, model)
        lo, hi = (np.nanpercentile(pi[ok], [0.5, 99.5]) if ok.any() else (1.5, 4.0))
        span = max(hi - lo, 0.2)
        grid = np.linspace(lo - 0.1 * span, hi + 0.1 * span, 60)
        N_list, what = speeds[stage]
        for (ls, col), N in zip(SPEED_STYLES if len(N_list) > 1 else (("-", "black"),), N_list):
            curve = np.array([comp.eta_is_at(float(p), float(N) / comp.N_nom) for p in grid])
            ax.plot(grid, curve, linestyle=ls, color=col, linewidth=1.1, label=f"curve at {N:.0f} rpm")
            series[f"eta_is_{stage}_curve_{N:.0f}rpm"] = (grid, curve)
        dev = eta - model
        if np.isfinite(dev).any():
            notes.append(f"{stage} median measured − curve {np.nanmedian(dev):+.3f}")
        ax.set_title(f"{'low' if stage == 'LS' else 'high'} stage ({stage}), speeds {what}")
        ax.set_xlabel(f"pressure ratio π_{stage} [-]")
        ax.set_ylabel("η_is [-]")
        ax.legend(loc="best")
    if notes:
        cap += " " + ", ".join(notes) + " (at each sample's own pressure ratio and speed)."
    return ReportFigure(key, title, cap, _png(fig), series)
