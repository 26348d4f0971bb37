"""hp-edge report and export-history (issue 11): the report builds from a short replay and from a
gateway history, every figure carries the data it should, the page has no external reference, and
the gateway's history exported as CSV replays like the original."""
from __future__ import annotations

import base64
import json
import math
import re
import shutil
import sqlite3
import subprocess
import sys
from dataclasses import replace
from html import escape
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from edge.cli import main as cli_main

ROOT = Path(__file__).resolve().parent.parent
PLANT = str(ROOT / "config" / "plant.yaml")
AMBIENT_BAR = 1.01325
FIGURES = ("timeseries", "residuals", "fouling", "pressure_drop", "setpoint", "cop_vs_setpoint",
           "compressors")
EXACT = 1e-9                 # relative: values that are copied, not computed
MODEL_RTOL = 1e-6            # a model value recomputed by hand (same solver, warm start may differ)
R_TOL_K_PER_KW = 0.02e-3     # replay of the exported CSV vs the original: R_th,f per window
COP_TOL = 0.005              # ... and the window COPs
CIP_SHARE_TOL = 5.0          # percentage points, removed share against the synthetic truth (15 %)
ADVISE_EVERY = 60            # gateway calibration cadence in the test [samples]


# ----------------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("report")


@pytest.fixture(scope="module")
def synthetic(plant, work):
    """12 recorded hours: 2 h commissioning (clean), 3 days later 10 h with a flagged 1.5-h CIP."""
    from simulator.synthetic import Noise, Operation, Truth, generate
    op = Operation(hours=12, commissioning_minutes=120, gap_after_commissioning_days=3,
                   cip_starts_h=(6.0,), cip_duration_h=1.5)
    h = generate(plant, op, Truth(), Noise(), seed=3)
    path = work / "history.csv"
    h.history.to_csv(path, index=False)
    return h, path


@pytest.fixture(scope="module")
def replay_dir(synthetic, work):
    out = work / "replay"
    assert cli_main(["replay", str(synthetic[1]), "--out", str(out), "--config", PLANT]) == 0
    return out


@pytest.fixture(scope="module")
def gateway_db(synthetic, replay_dir, work):
    """The synthetic history through the gateway's own ingest path (ModelAdvisor.ingest), with a
    calibration every ADVISE_EVERY samples, on the replay's commissioning state."""
    from edge.aggregate import Sample
    from edge.config import load_config
    from edge.service import ModelAdvisor, StateDir
    from edge.store import HistoryStore

    d = work / "gateway"
    (d / "state").mkdir(parents=True)
    for name in ("initial_calibration.json", "dp_clean.json"):
        shutil.copy(replay_dir / name, d / "state" / name)
    cfg = replace(load_config(ROOT / "config" / "gateway.yaml"), state_dir=d / "state",
                  history_db=d / "history.sqlite")
    hist = synthetic[0].history
    samples = []
    for rec in hist.to_dict("records"):
        ts = pd.Timestamp(rec.pop("timestamp")).timestamp()
        vals = {k: float(v) for k, v in rec.items()}
        samples.append(Sample(ts, vals, {k: "nan" for k, v in vals.items() if not math.isfinite(v)},
                              12, 12, 0, 0, ""))
    with HistoryStore(cfg.history_db, cfg.history_retention_days) as store:
        adv = ModelAdvisor(cfg, store, StateDir(cfg.state_dir))
        for k in range(0, len(samples), ADVISE_EVERY):
            chunk = samples[k:k + ADVISE_EVERY]
            adv.ingest(chunk)
            adv.advise(chunk[-1].timestamp)
    return cfg.history_db


def _report(args):
    rc = cli_main(["report", *args, "--config", PLANT])
    assert rc == 0
    return rc


def _load_replay(replay_dir, csv, start=None, end=None):
    from edge.plantfile import load_plant
    from edge.report import load_replay
    return load_replay(replay_dir, load_plant(PLANT), PLANT, start, end, history_csv=csv)


@pytest.fixture(scope="module")
def replay_report(synthetic, replay_dir, work):
    from edge.report import build_report
    data = _load_replay(replay_dir, synthetic[1])
    return data, build_report(data, work / "replay.html")


@pytest.fixture(scope="module")
def gateway_report(gateway_db, work):
    from edge.plantfile import load_plant
    from edge.report import build_report, load_gateway
    data = load_gateway(gateway_db, gateway_db.parent / "state", load_plant(PLANT), PLANT)
    return data, build_report(data, work / "gateway.html")


def _close(a, b, rtol=EXACT, atol=0.0):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape
    assert (np.isnan(a) == np.isnan(b)).all()
    ok = ~np.isnan(a)
    np.testing.assert_allclose(a[ok], b[ok], rtol=rtol, atol=atol)


# ----------------------------------------------------------------------------- the HTML page

EXTERNAL = re.compile(r"(?i)(https?:|ftp:|file:|//[a-z0-9]|<script|<link|<iframe|<object|@import|"
                      r"url\(|@font-face)")


def assert_self_contained(html: str) -> None:
    text = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "data:", html)
    assert not EXTERNAL.search(text), EXTERNAL.search(text).group(0)
    for src in re.findall(r'\bsrc="([^"]*)"', html):
        assert src.startswith("data:image/png;base64,")
        png = base64.b64decode(src.split(",", 1)[1])
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert b"http" not in png.lower()           # no address in a PNG text chunk either
    assert html.count("<img") == html.count('src="data:image/png;base64,')


def figure_points(html: str) -> dict[str, dict[str, int]]:
    out = {}
    for key, pts in re.findall(r'<figure data-figure="(\w+)" data-points="([^"]*)"', html):
        out[key] = {k: int(v) for k, v in (p.split("=", 1) for p in pts.split(";") if p)}
    return out


def test_report_from_replay_has_every_figure_with_its_data(replay_report, replay_dir, work):
    data, res = replay_report
    html = (work / "replay.html").read_text(encoding="utf-8")
    assert_self_contained(html)
    assert [f.key for f in res.figures] == list(FIGURES)
    for f in res.figures:
        assert f.png is not None, f"{f.key}: {f.missing}"
        assert f.caption.startswith("Read:")
        assert f"id=\"fig-{f.key}\"" in html and escape(f.caption.split(".")[0]) in html
    pts = figure_points(html)
    assert set(pts) == set(FIGURES)
    for f in res.figures:
        assert pts[f.key] == f.points()
    # the header: plant, period, coverage with reasons, version
    assert PLANT in html and "2024-03-01 00:00 UTC" in html and "hp-edge</th><td>version" in html
    assert re.search(r"\d+ of 720 one-minute samples usable \([\d.]+ %\); unusable: ", html)
    assert "cip " in html and "ramping " in html
    # windows and CIPs: the plotted values are the replay's, unit-converted where the contract says
    w = pd.read_csv(replay_dir / "windows.csv")
    w = w[w["status"] == "ok"]
    fou = res.figure("fouling").series
    _close(fou["R_th_f"][1], w["R_th_f_K_per_kW"])
    _close(fou["R_th_f_se"][1], w["R_th_f_se_K_per_kW"])
    _close(fou["R_th_f_share_pct"][1], w["R_th_f_share_pct"])
    cip = pd.read_csv(replay_dir / "cip.csv")
    _close(fou["cip_removed_pct"][1], cip["R_th_f_removed_pct"])
    _close(res.figure("pressure_drop").series["CF_dp_f"][1], w["CF_dp_f"])
    _close(res.figure("pressure_drop").series["dp_fouling_bar"][1], w["dp_fouling_bar"])
    sp = res.figure("setpoint").series
    _close(sp["p_m_sp_opt_barg"][1], w["p_m_sp_opt_barg"])
    _close(sp["p_m_gm_barg"][1], w["p_m_gm_barg"], atol=1e-12)
    _close(sp["dCOP_opt_pct"][1], w["dCOP_opt_pct"])


def test_replay_report_per_sample_series_are_the_measurement_and_the_models(
        replay_report, synthetic, plant):
    from model.batch import simulate_batch
    from edge.report.model import model_for_report, with_fouling

    data, res = replay_report
    hist = synthetic[0].history
    ts = res.figure("timeseries").series
    # measured COP by hand from the CSV: c_p rho V (T_out - T_in) / (W_LS + W_HS), usable rows only
    q = plant.cp_w * plant.rho_w / 3600e3 * hist["V_sink"] * (hist["T_sink_out"] - hist["T_sink_in"])
    cop = (q / (hist["W_LS"] + hist["W_HS"])).to_numpy()
    usable = data.samples["usable"].to_numpy() > 0.5
    _close(ts["COP_measured"][1], np.where(usable, cop, np.nan))     # through samples.csv
    assert 0.6 * len(hist) < usable.sum() < len(hist)
    # the adaptive value of a sample inside a window: the fixed model + that window's R_th,f, CF_dp,f
    w = data.windows[data.windows["status"] == "ok"].reset_index(drop=True)
    fixed = model_for_report(plant, data.state)
    t = data.samples["timestamp"]
    i = int(np.flatnonzero(usable & (t > w["window_start"][1]).to_numpy()
                           & (t < w["window_end"][1]).to_numpy())[5])
    # replay wrote the chain's per-sample model values (samples.csv): the report plots them as written
    assert np.isfinite(data.samples["COP_adaptive"]).sum() > 100
    _close(ts["COP_adaptive"][1], np.where(usable, data.samples["COP_adaptive"], np.nan))
    _close(ts["COP_fixed"][1], np.where(usable, data.samples["COP_fixed"], np.nan))
    assert i >= 0
    # the papers' result, in the report's own series: the adaptive model follows COP better
    meas = ts["COP_measured"][1]
    both = np.isfinite(ts["COP_adaptive"][1]) & np.isfinite(meas)
    err_f = np.sqrt(np.nanmean((ts["COP_fixed"][1][both] - meas[both]) ** 2))
    err_a = np.sqrt(np.nanmean((ts["COP_adaptive"][1][both] - meas[both]) ** 2))
    assert err_a < 0.7 * err_f
    res_f = res.figure("residuals").series["COP_residual_fixed"][1]
    _close(res_f, ts["COP_fixed"][1] - meas)
    # compressors: measured eta_is per usable sample, the curve in use is plant.yaml's polynomial
    comp = res.figure("compressors").series
    _close(comp["eta_is_LS_meas"][1], np.where(usable, data.samples["eta_is_LS_meas"], np.nan))
    curve_keys = [k for k in comp if k.startswith("eta_is_HS_curve_")]
    assert len(curve_keys) == 3
    for k in curve_keys:
        N = float(k.rsplit("_", 1)[1].removesuffix("rpm"))
        x, y = comp[k]
        _close(y, [fixed.comp_HS.eta_is_at(p, N / fixed.comp_HS.N_nom) for p in x], rtol=1e-12)
    assert 0.65 < np.nanmedian(comp["eta_is_LS_meas"][1]) < 0.85


def test_cop_against_set_point_at_three_fouling_levels(replay_report):
    data, res = replay_report
    s = res.figure("cop_vs_setpoint").series
    labels = [k.removeprefix("COP_") for k in s if k.startswith("COP_")]
    assert labels == ["clean", "median of the period", "highest of the period"]
    cops = {}
    for lab in labels:
        x, y = s[f"COP_{lab}"]
        assert len(x) > 50 and np.isfinite(y).sum() > 50
        (x_opt,), (cop_opt,) = s[f"optimum_{lab}"]
        assert x.min() <= x_opt <= x.max()
        assert cop_opt >= np.nanmax(y) - 1e-3 * cop_opt      # the marked optimum is the curve's top
        cops[lab] = (x, y)
    # more fouling, lower COP at every set point both curves reach (p_e moves the range's start)
    for a, b in (("clean", "median of the period"), ("median of the period", "highest of the period")):
        xa, ya = cops[a]
        xb, yb = cops[b]
        common = np.linspace(max(xa.min(), xb.min()), min(xa.max(), xb.max()), 100)
        ya_c = np.interp(common, xa, ya)
        yb_c = np.interp(common, xb, yb)
        ok = np.isfinite(ya_c) & np.isfinite(yb_c)
        assert ok.sum() > 50 and (ya_c[ok] > yb_c[ok]).all()


def test_report_from_gateway_history(gateway_report, gateway_db, work):
    data, res = gateway_report
    html = (work / "gateway.html").read_text(encoding="utf-8")
    assert_self_contained(html)
    for f in res.figures:
        assert f.png is not None, f"{f.key}: {f.missing}"
    with sqlite3.connect(gateway_db) as db:
        adv = pd.read_sql("SELECT ts, ok, R_th_f, R_th_f_share, CF_dp_f, p_m_sp_rec, p_m_gm "
                          "FROM advice ORDER BY ts", db)
    adv = adv[adv["ok"] == 1]
    assert len(adv) >= 8
    fou = res.figure("fouling").series
    _close(fou["R_th_f"][1], adv["R_th_f"])
    _close(fou["R_th_f_share_pct"][1], adv["R_th_f_share"])
    _close(res.figure("setpoint").series["p_m_sp_opt_barg"][1], adv["p_m_sp_rec"])
    _close(res.figure("setpoint").series["p_m_gm_barg"][1], adv["p_m_gm"])
    # the CIP is found in the stored samples and its effect read from the advice around it
    assert len(data.cips) == 1
    assert data.cips["detected_by"][0] == "cip_flag"
    assert abs(data.cips["R_th_f_removed_pct"][0] - 15.0) <= CIP_SHARE_TOL
    assert "cip_flag" in html
    # causal adaptive model: a sample uses the latest advice at or before it
    ts = res.figure("timeseries").series
    t = data.samples["timestamp"]
    ends = adv["ts"].to_numpy(dtype=float)          # epoch s
    i = int(np.flatnonzero(np.isfinite(ts["COP_adaptive"][1]))[-1])
    latest = int(np.searchsorted(ends, t.iloc[i].timestamp(), side="right")) - 1
    assert ends[latest] <= t.iloc[i].timestamp() < (ends[latest + 1] if latest + 1 < len(ends)
                                                     else math.inf)
    from model.batch import simulate_batch
    from edge.report.model import model_for_report, with_fouling
    fixed = model_for_report(data.params, data.state)
    row = data.samples.iloc[[i]].rename(columns={"p_m_sp_barg": "p_m_sp"})
    by_hand = simulate_batch(row, with_fouling(fixed, adv["R_th_f"].iloc[latest],
                                               adv["CF_dp_f"].iloc[latest]), columns=("COP",))
    assert ts["COP_adaptive"][1][i] == pytest.approx(by_hand["COP"].iloc[0], rel=MODEL_RTOL)
    # twelve hours since commissioning: the gateway's windows carry no forecast yet, and it says so
    assert data.forecast is not None and not data.forecast["R_th_f_forecast_K_per_kW"].notna().any()
    assert "no fouling forecast in the period yet (it needs a day of windows since the last CIP or " \
        "commissioning)" in html


def test_gateway_report_draws_the_forecast_its_advice_rows_carry(gateway_db, work):
    """The forecast the gateway made at each window's end (the window row in the advice table's
    detail) is drawn with its band, as a replay's forecast.csv is."""
    db = work / "forecast.sqlite"
    shutil.copy(gateway_db, db)
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT ts, detail FROM advice ORDER BY ts").fetchall()
        n = 0
        for ts, detail in rows:
            d = json.loads(detail)
            w = d.get("window")
            if not w:
                continue
            end = pd.Timestamp(float(ts), unit="s", tz="UTC")
            w.update({"window_end": end.isoformat(), "forecast_at": (end + pd.Timedelta(days=7)).isoformat(),
                      "R_th_f_forecast_K_per_kW": 4.0e-3 + n * 1e-5, "R_th_f_forecast_lo_K_per_kW": 3.5e-3,
                      "R_th_f_forecast_hi_K_per_kW": 4.5e-3 + n * 1e-5})
            con.execute("UPDATE advice SET detail = ? WHERE ts = ?", (json.dumps(d), ts))
            n += 1
    assert n >= 8
    out = work / "gateway_forecast.html"
    _report(["--history", str(db), "--state", str(gateway_db.parent / "state"), "--out", str(out)])
    html = out.read_text(encoding="utf-8")
    pts = figure_points(html)
    assert pts["fouling"]["forecast"] == n and pts["fouling"]["forecast_hi"] == n
    assert "Dash-dot: the fouling forecast" in html


def test_gateway_report_subsamples_a_long_period_and_says_so(gateway_db, work, capsys):
    _report(["--history", str(gateway_db), "--out", str(work / "sub.html"),
             "--max-model-samples", "50"])
    html = (work / "sub.html").read_text(encoding="utf-8")
    assert re.search(r"Model values on one usable sample in \d+ \(\d+ of \d+, to bound the "
                     r"report&#x27;s run time\)", html)
    pts = figure_points(html)["timeseries"]
    assert pts["COP_fixed"] <= 50 < pts["COP_measured"]
    assert "wrote" in capsys.readouterr().out


def test_period_selection(synthetic, replay_dir, work):
    start = "2024-03-04T08:00"                 # after the CIP (naive: UTC)
    _report([str(replay_dir), "--data", str(synthetic[1]), "--from", start,
             "--out", str(work / "late.html")])
    html = (work / "late.html").read_text(encoding="utf-8")
    assert "No CIP in the period." in html and "2024-03-04 08:00 UTC" in html
    data = _load_replay(replay_dir, synthetic[1], start)
    assert (data.samples["timestamp"] >= pd.Timestamp(start, tz="UTC")).all()
    assert (data.windows["window_end"] >= pd.Timestamp(start, tz="UTC")).all()
    assert len(data.windows) == 2 and len(data.cips) == 0


def test_contract_columns_forecast_and_confidence(replay_report, replay_dir, synthetic, work):
    """A replay directory in the new contract's names (R_th_f_share_pct, p_m_gm_barg,
    advice_confident, dCOP_opt_sd_pct, forecast.csv, samples.csv, meta.json) reads the same."""
    data, _ = replay_report
    new = work / "contract"
    shutil.copytree(replay_dir, new)
    w = pd.read_csv(replay_dir / "windows.csv")
    assert {"R_th_f_share_pct", "p_m_gm_barg", "advice_confident"} <= set(w.columns)  # as written
    w["dCOP_opt_sd_pct"] = 0.4
    w["advice_confident"] = ["true", "false"] * (len(w) // 2) + ["true"] * (len(w) % 2)
    w["advice_note"] = np.where(w["advice_confident"] == "false", "gain within its uncertainty", "")
    w.to_csv(new / "windows.csv", index=False)
    c = pd.read_csv(replay_dir / "cip.csv").rename(columns={"R_th_f_before": "R_th_f_before_K_per_kW",
                                                           "R_th_f_after": "R_th_f_after_K_per_kW"})
    c.to_csv(new / "cip.csv", index=False)
    f = pd.DataFrame({"window_end": w["window_end"],
                      "forecast_at": pd.to_datetime(w["window_end"]) + pd.Timedelta(days=2),
                      "R_th_f_forecast_K_per_kW": w["R_th_f_K_per_kW"] + 0.1e-3,
                      "R_th_f_forecast_lo_K_per_kW": w["R_th_f_K_per_kW"],
                      "R_th_f_forecast_hi_K_per_kW": w["R_th_f_K_per_kW"] + 0.2e-3,
                      "fouling_rate_K_per_kW_per_day": 0.05e-3, "fouling_cost_eur_per_day": 12.0,
                      "days_to_recommended_cip": 9.0})
    f.to_csv(new / "forecast.csv", index=False)
    s = data.samples.copy()
    s["timestamp"] = s["timestamp"].dt.strftime("%Y-%m-%dT%H:%M:%SZ")
    s["usable"] = np.where(s["usable"] > 0.5, "true", "false")
    # samples.csv as the contract lists it: without the boundary conditions, which --data supplies
    s.drop(columns=["N_LS_model", "N_HS_model", "T_source_in", "T_source_out", "T_sink_in",
                    "V_source", "V_sink"], errors="ignore").to_csv(new / "samples.csv", index=False)
    (new / "meta.json").write_text(json.dumps({"plant": "Test plant 2 MW", "n_rows": 720,
                                               "hp_edge_version": "9.9.9"}))
    out = work / "contract.html"
    _report([str(new), "--out", str(out), "--data", str(synthetic[1])])
    html = out.read_text(encoding="utf-8")
    assert_self_contained(html)
    assert "Test plant 2 MW" in html and "replay made by version 9.9.9" in html
    pts = figure_points(html)
    assert pts["fouling"]["forecast"] == len(w) and pts["fouling"]["forecast_hi"] == len(w)
    assert pts["setpoint"]["dCOP_opt_sd_pct"] == len(w)
    assert f"not confident ({len(w) // 2} of {len(w)} windows" in html
    assert f"Why: gain within its uncertainty ({len(w) // 2})." in html
    assert pts["timeseries"]["COP_adaptive"] == int(np.isfinite(data.samples["COP_adaptive"]).sum())
    assert "Dash-dot: the fouling forecast" in html
    # the model values are the file's (not recomputed), the operating point comes from --data
    assert "model values computed by the report" not in html
    assert pts["cop_vs_setpoint"]["COP_clean"] > 50


def test_old_replay_directory_without_samples_says_what_is_missing(replay_dir, work, capsys):
    old = work / "old-replay"                  # what replay wrote before samples.csv and meta.json
    shutil.copytree(replay_dir, old)
    for name in ("samples.csv", "meta.json", "compressors.json"):
        (old / name).unlink(missing_ok=True)
    out = work / "old.html"
    _report([str(old), "--out", str(out)])
    html = out.read_text(encoding="utf-8")
    assert_self_contained(html)
    pts = figure_points(html)
    assert pts["timeseries"] == {} and pts["fouling"]["R_th_f"] > 0
    assert html.count("Not available:") == 4          # time series, residuals, COP curve, compressors
    assert "data coverage unknown" in html
    assert "not available: " in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["SRC", "--history", "DB"], "give either a replay directory (SOURCE) or --history DB"),
    (["--history", "NOPE.sqlite"], "NOPE.sqlite: no such history database"),
    (["NODIR"], "NODIR: not a directory (expected the output of hp-edge replay)"),
    (["NODIR", "--from", "yesterday-ish"], "--from 'yesterday-ish': not an ISO 8601 time"),
    (["NODIR", "--from", "2024-03-02", "--to", "2024-03-01"], "--from must be before --to"),
])
def test_report_refuses_bad_arguments_with_exit_2(args, message, work, capsys, monkeypatch):
    monkeypatch.chdir(work)
    out = work / "never.html"
    assert cli_main(["report", *args, "--out", str(out), "--config", PLANT]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hp-edge report: ") and message in err
    assert not out.exists()


# ----------------------------------------------------------------------------- export-history


def test_export_history_round_trip_replays_like_the_original(gateway_db, synthetic, replay_dir,
                                                             work):
    from edge.commands.analysis_cmds import read_history_csv
    from edge.io.export import CANONICAL_COLUMNS

    out = work / "exported.csv"
    assert cli_main(["export-history", "--history", str(gateway_db), "--out", str(out)]) == 0
    header = out.read_text(encoding="utf-8").splitlines()[0].split(",")
    assert header[0] == "timestamp" and header[-1] == "quality"
    assert header[1:-1] == [c for c in CANONICAL_COLUMNS if c in synthetic[0].history.columns]
    first = out.read_text(encoding="utf-8").splitlines()[1]
    assert first.startswith("2024-03-01T00:00:00Z,")
    orig, _, _ = read_history_csv(synthetic[1])
    back, skipped, non_numeric = read_history_csv(out)
    assert not skipped and not non_numeric
    assert (back["timestamp"] == orig["timestamp"]).all()
    for c in header[1:-1]:
        _close(back[c], orig[c])                            # stored and written unchanged
    # replay of the export = replay of the original, window by window
    rep2 = work / "replay_exported"
    assert cli_main(["replay", str(out), "--out", str(rep2), "--config", PLANT]) == 0
    a = pd.read_csv(replay_dir / "windows.csv")
    b = pd.read_csv(rep2 / "windows.csv")
    assert list(a["window_start"]) == list(b["window_start"]) and len(a) >= 4
    np.testing.assert_allclose(b["R_th_f_K_per_kW"], a["R_th_f_K_per_kW"], atol=R_TOL_K_PER_KW)
    for c in ("COP_measured", "COP_fixed", "COP_adaptive"):
        np.testing.assert_allclose(b[c], a[c], atol=COP_TOL)
    ca, cb = pd.read_csv(replay_dir / "cip.csv"), pd.read_csv(rep2 / "cip.csv")
    assert list(ca["cip_start"]) == list(cb["cip_start"])
    # the other two readers docs/deploy.md names: commissioning from the gateway's own data, and a
    # report with the export as its per-sample data
    # (this fixture's first 90 minutes put two factors at a bound: refused, exit 2, unless --force;
    # then the saved commissioning is the replay's own initial calibration of the same minutes)
    state = work / "state_from_export"
    args = ["calibrate", "initial", str(out), "--state-dir", str(state), "--config", PLANT]
    assert cli_main(args) == 2 and not (state / "initial_calibration.json").exists()
    assert cli_main(args + ["--force"]) == 0
    doc = json.loads((state / "initial_calibration.json").read_text(encoding="utf-8"))
    ref = json.loads((rep2 / "initial_calibration.json").read_text(encoding="utf-8"))
    for k, v in ref["params"].items():
        assert doc["params"][k] == pytest.approx(v, abs=1e-3), k
    html = work / "from_export.html"
    assert cli_main(["report", str(rep2), "--data", str(out), "--out", str(html), "--config", PLANT]) == 0
    assert html.stat().st_size > 50_000 and "<img" in html.read_text(encoding="utf-8")


def test_export_history_period_and_quality(gateway_db, work, capsys):
    out = work / "part.csv"
    assert cli_main(["export-history", "--history", str(gateway_db), "--from",
                     "2024-03-04T06:00", "--to", "2024-03-04T06:59:59Z", "--out", str(out)]) == 0
    df = pd.read_csv(out, keep_default_na=False)
    assert len(df) == 60
    assert df["timestamp"].iloc[0] == "2024-03-04T06:00:00Z"
    assert df["timestamp"].iloc[-1] == "2024-03-04T06:59:00Z"
    assert "wrote 60 one-minute samples 2024-03-04T06:00:00Z .. 2024-03-04T06:59:00Z" in \
        capsys.readouterr().out
    # a minute the gateway marked (frozen data) stays marked, and unusable, after the round trip
    with sqlite3.connect(gateway_db) as db:
        db.execute("UPDATE samples SET quality='frozen' WHERE ts = ?",
                   (int(pd.Timestamp("2024-03-04T10:00Z").timestamp()),))
    try:
        assert cli_main(["export-history", "--history", str(gateway_db), "--out", str(out),
                         "--from", "2024-03-04T09:00", "--to", "2024-03-04T11:00"]) == 0
        from edge.commands.analysis_cmds import read_history_csv
        from edge.plantfile import load_plant
        from model.measured import process
        hist, _, _ = read_history_csv(out)
        p = process(hist, load_plant(PLANT))
        i = int(np.flatnonzero(hist["timestamp"] == pd.Timestamp("2024-03-04T10:00Z"))[0])
        assert hist["quality"][i] == "frozen" and p["reason"][i] == "frozen" and not p["usable"][i]
    finally:
        with sqlite3.connect(gateway_db) as db:
            db.execute("UPDATE samples SET quality='' WHERE quality='frozen'")


def test_export_history_errors_name_the_file(work, capsys):
    out = work / "none.csv"
    assert cli_main(["export-history", "--history", str(work / "missing.sqlite"),
                     "--out", str(out)]) == 2
    assert "missing.sqlite: no such history database" in capsys.readouterr().err
    assert not out.exists() and not (work / "missing.sqlite").exists()
    bad = work / "not-a-db.sqlite"
    bad.write_text("hello")
    assert cli_main(["export-history", "--history", str(bad), "--out", str(out)]) == 2
    assert "not-a-db.sqlite: not a readable history database" in capsys.readouterr().err
    assert cli_main(["export-history", "--config", str(work / "nope.yaml"), "--out", str(out)]) == 2
    assert "nope.yaml" in capsys.readouterr().err


# ----------------------------------------------------------------------------- the gateway stays lean


def test_the_gateway_does_not_import_matplotlib():
    code = ("import sys\n"
            "import edge.service, edge.loop, edge.store, edge.plc, edge.demo\n"
            "from edge.cli import build_parser\n"
            "p = build_parser()\n"
            "from edge.commands.gateway_cmds import cmd_run\n"
            "import edge.commands.report_cmds, edge.io.export\n"
            "try:\n"
            "    p.parse_args(['run', '--help'])\n"
            "except SystemExit:\n"
            "    pass\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib'\n"
            "             or m.startswith('edge.report'))\n"
            "print('IMPORTED:' + ','.join(bad))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "IMPORTED:"
