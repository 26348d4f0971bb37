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


CSV_CHUNK_ROWS = 65536      # rows formatted and written at a time


def frame_to_csv(frame, path, float_format: str = "%.10g") -> None:
    """``frame.to_csv(path, index=False, float_format=float_format)`` to the byte, with the float
    columns formatted here: pandas formats each value through three Python calls, ~1.5 us, and a
    plant-year's samples.csv holds ~10 million of them (a missing value is an empty field, as
    pandas writes it). CSV_CHUNK_ROWS rows at a time: the formatted strings of a plant-year's
    samples at once took ~600 MB, more than the replay itself. A column pandas formats by what all
    its values hold (times: the date alone when every one is a midnight) is formatted as a whole
    first, as pandas would."""
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
            out = part.copy(deep=False)
            for i in range(frame.shape[1]):
                col = part.iloc[:, i]
                if cols[i] is not None:
                    out.isetitem(i, cols[i][a:a + CSV_CHUNK_ROWS])
                elif col.dtype.kind == "f":
                    out.isetitem(i, [float_format % v if v == v else "" for v in col.tolist()])
            out.to_csv(f, index=False, header=a == 0)
