"""The replay directory (``hp-edge replay --out DIR`` and each plant of ``hp-edge fleet replay``):
windows.csv, cip.csv, forecast.csv, samples.csv, summary.txt, meta.json, compressors.json,
surrogate_tracker.json and the initial calibration's state files. One writer for both commands."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

REPLAY_FILES = ("windows.csv", "cip.csv", "forecast.csv", "samples.csv", "summary.txt", "compressors.json",
                "meta.json")


def write_replay_dir(res, out: str | os.PathLike, meta: dict | None = None,
                     header: str = "") -> str:
    """Write a ``model.analysis.replay.ReplayResult`` to ``out`` (created); every file is written
    to a temporary name and renamed, so a reader never sees half a file. ``meta`` is merged into
    meta.json; ``header`` (e.g. what reading the CSV skipped) goes first in summary.txt. Returns
    the summary text."""
    from edge.statefiles import COMPRESSORS, DP_CLEAN, INITIAL_CALIBRATION, SURROGATE_TRACKER, write_state
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name, frame in (("windows.csv", res.windows), ("cip.csv", res.cips), ("forecast.csv", res.forecast),
                        ("samples.csv", res.samples)):
        if frame is None:
            continue
        tmp = out / f".{name}.tmp"
        frame_to_csv(frame, tmp)
        os.replace(tmp, out / name)
    write_state("meta.json", {**res.meta, **(meta or {})}, out)
    if res.compressors is not None:
        write_state(COMPRESSORS, res.compressors, out)
    if res.surrogate_tracker is not None:
        write_state(SURROGATE_TRACKER, res.surrogate_tracker, out)
    text = (header + "\n" if header else "") + res.summary()
    tmp = out / ".summary.txt.tmp"
    tmp.write_text(text + "\n", encoding="utf-8")
    os.replace(tmp, out / "summary.txt")
    write_state(INITIAL_CALIBRATION, res.initial.to_dict(), out)
    write_state(DP_CLEAN, res.dp_clean.to_dict(), out)
    return text


CSV_CHUNK_ROWS = 16384      # rows formatted and written at a time


def frame_to_csv(frame, path, float_format: str = "%.10g") -> None:
    """``frame.to_csv(path, index=False, float_format=float_format)`` to the byte, with the float
    columns formatted here: pandas formats each value through three Python calls, ~1.5 us, and a
    plant-year's samples.csv holds ~10 million of them (a missing value is an empty field, as
    pandas writes it). CSV_CHUNK_ROWS rows at a time: the formatted strings of a plant-year's
    samples at once took ~600 MB, more than the replay itself. A column pandas formats by what all
    its values hold (times: the date alone when every one is a midnight) is formatted as a whole
    first, as pandas would. A chunk whose every field is plain text (``_fields``) is joined into
    lines here (pandas' csv writer took ~2 s of a plant-year's ~5); any other chunk pandas writes.
    A chunk's fields are Python strings, ~1.3 kB a samples row: 16,384 rows ~20 MB (65,536 rows
    raised a plant-year's peak by ~85 MB)."""
    cols = []
    for i in range(frame.shape[1]):
        col = frame.iloc[:, i]
        k = col.dtype.kind
        if k in "Mm" and len(frame) > CSV_CHUNK_ROWS:        # (pandas' to_csv's own text of it)
            text = col.to_frame().to_csv(index=False, header=False, lineterminator="\n")
            vals = np.array(text.split("\n")[:-1], dtype=object)
            vals[vals == '""'] = ""         # a missing time: a lone empty field is quoted
            cols.append(vals)
        else:
            cols.append(None)
    with open(path, "w", encoding="utf-8", newline="") as f:
        for a in range(0, max(len(frame), 1), CSV_CHUNK_ROWS):
            part = frame.iloc[a:a + CSV_CHUNK_ROWS]
            fields = _fields(part, cols, a, float_format)
            if fields is not None:
                if a == 0:
                    part.iloc[:0].to_csv(f, index=False)           # the header line
                if len(part):
                    f.write("\n".join(map(",".join, zip(*fields))) + "\n")
                continue
            out = part.copy(deep=False)
            for i in range(frame.shape[1]):
                col = part.iloc[:, i]
                if cols[i] is not None:
                    out.isetitem(i, cols[i][a:a + CSV_CHUNK_ROWS])
                elif col.dtype.kind == "f":
                    out.isetitem(i, _floats(col, float_format))
            out.to_csv(f, index=False, header=a == 0)


_QUOTED = (",", '"', "\n", "\r")     # a field with one of these: pandas' writer quotes it (or may)


def _floats(col, float_format: str) -> list:
    """A float column's fields: ``float_format`` of each value, a missing one empty."""
    return [float_format % v if v == v else "" for v in col.tolist()]


def _fields(part, cols: list, a: int, float_format: str) -> list | None:
    """Per column of ``part`` (rows a.. of the frame) the text of each field as pandas' ``to_csv``
    writes it, when each is plain: floats, booleans, integers, the whole-column times of ``cols``
    and text (missing: empty) that holds none of _QUOTED, in a frame of two columns or more (a
    lone empty field is quoted). None for any other chunk (found before any float is formatted)."""
    import pandas as pd
    if part.shape[1] < 2:
        return None
    out: list = []
    for i in range(part.shape[1]):
        col = part.iloc[:, i]
        k = col.dtype.kind
        if cols[i] is not None:
            vals = cols[i][a:a + len(part)].tolist()
        elif k == "f":
            out.append(col)                 # formatted once every column is known to be plain
            continue
        elif k == "b" and col.dtype == np.dtype(bool):
            out.append(np.where(col.to_numpy(), "True", "False").tolist())
            continue
        elif k in "iu" and isinstance(col.dtype, np.dtype):
            out.append(list(map(str, col.tolist())))
            continue
        elif k == "O" or str(col.dtype) in ("str", "string"):
            vals = col.to_numpy(dtype=object).tolist()
        else:
            return None
        if set(map(type, vals)) - {str}:         # missing text is an empty field; anything else
            for j in [j for j, v in enumerate(vals) if type(v) is not str]:    # goes to pandas
                v = vals[j]
                if not (v is None or v is pd.NA or (type(v) is float and v != v)):
                    return None
                vals[j] = ""
        text = "".join(vals)
        if any(c in text for c in _QUOTED):
            return None
        out.append(vals)
    return [_floats(v, float_format) if isinstance(v, pd.Series) else v for v in out]
