"""Electricity price series for the cost of fouling (issue 10): plant.yaml ``cip.electricity_price_csv``.

A CSV with a header line naming the columns ``timestamp`` (ISO 8601, UTC when naive) and
``eur_per_MWh`` (other columns are ignored), one price per row, e.g. a day-ahead spot market export::

    timestamp,eur_per_MWh
    2024-03-01T00:00:00Z,84.10
    2024-03-01T01:00:00Z,79.55

Each price holds from its timestamp to the next one; the last one for one median step
(``model.analysis.cost.PriceSeries``). Separator (``,`` ``;`` or tab) and decimal mark are detected as
for history CSVs (``edge.io.history.detect_format``). Unlike a history, a price file is refused as a
whole at the first bad row: a missing price would silently change every cost. Every message starts
with the file and names the line.
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from edge.io.history import HistoryError, _read_text, detect_format

COLUMNS = ("timestamp", "eur_per_MWh")
MAX_BYTES = 50_000_000
MAX_ROWS = 1_000_000
PRICE_RANGE = (-10_000.0, 100_000.0)      # EUR/MWh; spot prices go negative, and spike, but not this far


class PriceFileError(ValueError):
    """The price CSV cannot be used; the message starts with the path and names the line."""


def read_price_csv(path):
    """The ``PriceSeries`` of a price CSV (see the module docstring). Raises PriceFileError."""
    import pandas as pd

    from model.analysis.cost import CostError, PriceSeries

    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError:
        size = 0
    if size > MAX_BYTES:
        raise PriceFileError(f"{path}: {size} bytes is more than a price file may have ({MAX_BYTES})")
    try:
        text = _read_text(path)
        sep, decimal, _ = detect_format(text)
    except HistoryError as exc:
        msg = str(exc)
        if "no 'timestamp' column" in msg:
            msg = (f"{msg.split(':')[0]}: no column 'timestamp' in the header (expected "
                   f"{', '.join(COLUMNS)})")
        raise PriceFileError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    reader = csv.reader(io.StringIO(text), delimiter=sep)
    names = None
    times: list[float] = []
    prices: list[float] = []
    lines: list[int] = []
    try:
        for row in reader:
            if not any(c.strip() for c in row):
                continue
            if names is None:
                names = [c.strip().strip('"') for c in row]
                missing = [c for c in COLUMNS if c not in names]
                if missing:
                    raise PriceFileError(f"{path}: line {reader.line_num}: no column "
                                         f"{' and no column '.join(repr(c) for c in missing)} in the "
                                         f"header (expected {', '.join(COLUMNS)})")
                i_t, i_p = names.index("timestamp"), names.index("eur_per_MWh")
                continue
            line = reader.line_num
            if len(row) != len(names):
                raise PriceFileError(f"{path}: line {line}: {len(row)} fields, the header has {len(names)}")
            t_text, p_text = row[i_t].strip(), row[i_p].strip()
            try:
                t = pd.Timestamp(t_text)
                if pd.isna(t):
                    raise ValueError
            except (ValueError, TypeError):
                raise PriceFileError(f"{path}: line {line}: timestamp {t_text[:40]!r} is not ISO 8601 "
                                     "(e.g. 2024-03-01T06:00:00Z; UTC when naive)") from None
            t = t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")
            num = p_text.replace(",", ".") if decimal == "," and "." not in p_text else p_text
            try:
                p = float(num)
            except ValueError:
                raise PriceFileError(f"{path}: line {line}: price {p_text[:40]!r} is not a number "
                                     "[EUR/MWh]") from None
            if not (math.isfinite(p) and PRICE_RANGE[0] <= p <= PRICE_RANGE[1]):
                raise PriceFileError(f"{path}: line {line}: price {p_text[:40]!r} is outside "
                                     f"{PRICE_RANGE[0]:g}..{PRICE_RANGE[1]:g} EUR/MWh")
            ts = t.timestamp()
            if times and ts <= times[-1]:
                raise PriceFileError(f"{path}: line {line}: timestamp {t_text[:40]!r} is not after the "
                                     f"one at line {lines[-1]} (prices must be in time order, once each)")
            times.append(ts)
            prices.append(p)
            lines.append(line)
            if len(times) > MAX_ROWS:
                raise PriceFileError(f"{path}: more than {MAX_ROWS} prices")
    except csv.Error as exc:
        raise PriceFileError(f"{path}: line {reader.line_num}: cannot read as CSV: {str(exc)[:200]}") from None
    if names is None:
        raise PriceFileError(f"{path}: the file is empty")
    if not times:
        raise PriceFileError(f"{path}: no prices after the header")
    try:
        return PriceSeries(times, prices)
    except CostError as exc:           # not reachable after the checks above; kept as a guard
        raise PriceFileError(f"{path}: {exc}") from None


def price_file(extra: dict | None, plant_file) -> Path | None:
    """plant.yaml's ``cip.electricity_price_csv`` as a path (relative to plant.yaml's folder), or
    None when the plant file gives a constant price."""
    sec = (extra or {}).get("cip") or {}
    name = sec.get("electricity_price_csv") if isinstance(sec, dict) else None
    if not isinstance(name, str) or not name.strip():
        return None
    p = Path(name).expanduser()
    return p if p.is_absolute() else Path(plant_file).resolve().parent / p


def price_for_plant(extra: dict | None, plant_file):
    """The PriceSeries plant.yaml names (None for a constant price). Raises PriceFileError."""
    p = price_file(extra, plant_file)
    return None if p is None else read_price_csv(p)
