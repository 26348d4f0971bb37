"""Report commands: ``report`` (one self-contained HTML file with the papers' figures) and
``export-history`` (the gateway's SQLite history as a canonical history CSV).

Heavy imports (pandas, CoolProp, matplotlib) stay inside the command functions; matplotlib only
in ``report``, through edge.report.
"""
from __future__ import annotations

import sys
from pathlib import Path

from edge.config import DEFAULT_CONFIG, find_config
from edge.plantfile import DEFAULT_PLANT


class CommandError(Exception):
    """A user-facing error: printed as 'hp-edge <cmd>: message', exit code 2."""


def register(sub) -> None:
    p = sub.add_parser(
        "report", help="one self-contained HTML report with the papers' figures",
        description="Write one self-contained HTML file (figures embedded, no network needed) from "
                    "a replay directory (hp-edge replay --out DIR) or from the gateway's history "
                    "database and state directory: measured vs fixed vs adaptive model, fouling "
                    "with the CIPs, pressure-drop factor, set points, COP against the set point at "
                    "three fouling levels, compressor efficiencies, CIP and calibration tables.")
    p.add_argument("source", nargs="?", help="replay output directory (or use --history)")
    p.add_argument("--out", required=True, help="HTML file to write")
    p.add_argument("--history", help="the gateway's history database (instead of SOURCE)")
    p.add_argument("--state", help="the gateway's state directory (default: 'state' beside the "
                                   "history database)")
    p.add_argument("--data", help="with a replay directory: the history CSV it was made from, for "
                                  "the per-sample figures when the directory has no samples.csv")
    p.add_argument("--config", default=None,
                   help=f"plant file (default: {DEFAULT_PLANT}, else /etc/hp-edge/plant.yaml, else the one "
                        "beside the installed package)")
    p.add_argument("--from", dest="start", help="period start (ISO 8601, UTC when naive)")
    p.add_argument("--to", dest="end", help="period end (ISO 8601, UTC when naive)")
    p.add_argument("--max-model-samples", type=int, default=None,
                   help="simulate at most this many samples per model for the per-sample figures "
                        "(evenly subsampled; default 3000)")
    p.add_argument("--window-hours", type=float, default=2.0,
                   help="gateway: calibration window length, where an advice does not record its "
                        "window (default: %(default)s)")
    p.add_argument("--cip-off-minutes", type=float, default=360.0,
                   help="gateway: a plant stop longer than this counts as a CIP (default: %(default)s)")
    p.set_defaults(func=cmd_report)

    e = sub.add_parser(
        "export-history", help="the gateway's history as a canonical history CSV",
        description="Write the gateway's SQLite history as a canonical history CSV (timestamp "
                    "ISO 8601 UTC first, the SPEC §4 columns in their canonical units, then the "
                    "gateway's quality mark) that replay, calibrate and report accept.")
    e.add_argument("--out", required=True, help="CSV file to write")
    e.add_argument("--config", default=None,
                   help=f"gateway.yaml naming the history database (default: {DEFAULT_CONFIG}, else "
                        "/etc/hp-edge/gateway.yaml, else the one beside the installed package)")
    e.add_argument("--history", help="the history database (instead of --config)")
    e.add_argument("--from", dest="start", help="first sample (ISO 8601, UTC when naive)")
    e.add_argument("--to", dest="end", help="last sample (ISO 8601, UTC when naive)")
    e.set_defaults(func=cmd_export_history)


def _fail(cmd: str, exc: Exception) -> int:
    for line in str(exc).splitlines() or [type(exc).__name__]:
        print(f"hp-edge {cmd}: {line}", file=sys.stderr)
    return 2


def parse_time(text: str | None, flag: str):
    """ISO 8601 -> UTC Timestamp (UTC when naive); None stays None."""
    if text is None:
        return None
    import pandas as pd
    try:
        t = pd.Timestamp(text.strip())
    except ValueError as exc:
        raise CommandError(f"{flag} {text!r}: not an ISO 8601 time ({exc})") from None
    if pd.isna(t):
        raise CommandError(f"{flag} {text!r}: not an ISO 8601 time")
    return t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")


def _period(args):
    start, end = parse_time(args.start, "--from"), parse_time(args.end, "--to")
    if start is not None and end is not None and not start < end:
        raise CommandError("--from must be before --to")
    return start, end


def cmd_report(args) -> int:
    from edge.plantfile import PlantFileError, load_plant
    from edge.report import (MatplotlibMissing, ReportSourceError, build_report, load_gateway,
                             load_replay)
    from edge.report.model import DEFAULT_MAX_MODEL_SAMPLES
    try:
        start, end = _period(args)
        if (args.source is None) == (args.history is None):
            raise CommandError("give either a replay directory (SOURCE) or --history DB, not both")
        if args.max_model_samples is not None and args.max_model_samples < 1:
            raise CommandError("--max-model-samples must be at least 1")
        if args.window_hours <= 0 or args.cip_off_minutes <= 0:
            raise CommandError("--window-hours and --cip-off-minutes must be > 0")
        plant_file = find_config("plant.yaml", args.config)
        params = load_plant(plant_file)
        if args.source is not None:
            if args.state:
                raise CommandError("--state goes with --history (a replay directory holds its state)")
            data = load_replay(args.source, params, str(plant_file), start, end,
                               history_csv=args.data)
        else:
            if args.data:
                raise CommandError("--data goes with a replay directory; the gateway's samples are "
                                   "in its history")
            state = Path(args.state) if args.state else Path(args.history).parent / "state"
            data = load_gateway(args.history, state, params, str(plant_file), start, end,
                                window_hours=args.window_hours,
                                cip_off_minutes=args.cip_off_minutes)
        res = build_report(data, args.out, args.max_model_samples or DEFAULT_MAX_MODEL_SAMPLES)
    except (CommandError, PlantFileError, ReportSourceError, MatplotlibMissing, OSError) as exc:
        return _fail("report", exc)
    drawn = [f for f in res.figures if f.png is not None]
    print(f"wrote {res.path} ({len(drawn)} of {len(res.figures)} figures, "
          f"{res.size_bytes / 1024:.0f} kB) in {res.run_time_s:.1f} s")
    for f in res.figures:
        if f.png is None:
            print(f"  not available: {f.title}: {f.missing}")
    for n in res.notes:
        print(f"  note: {n}")
    return 0


def cmd_export_history(args) -> int:
    try:
        start, end = _period(args)
        if args.history:
            db = Path(args.history)
        else:
            from edge.commands.gateway_cmds import load_config_or_report
            cfg = load_config_or_report(find_config("gateway.yaml", args.config), load_plant=False)
            if cfg is None:
                return 2
            db = cfg.history_db
        from edge.io.export import describe, export_history
        from edge.io.historydb import HistoryDbError
        try:
            res = export_history(db, args.out, start, end)
        except (HistoryDbError, OSError) as exc:
            raise CommandError(str(exc)) from None
    except CommandError as exc:
        return _fail("export-history", exc)
    print(describe(res))
    return 0
