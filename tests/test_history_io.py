"""History CSVs (issue 9 item 4) and the commissioning plausibility limits (item 5).

The CSVs are written by pandas from a small simulated commissioning export, in the formats SCADA
exports use (comma/point, semicolon/comma, tab); the reader must give the same frame for each.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from edge.cli import main
from edge.io.history import HistoryError, read_history, read_history_csv


@pytest.fixture(scope="module")
def clean_csv(tmp_path_factory):
    """60 minutes of clean-evaporator operation from the simulator (its own export)."""
    from simulator.config import load_simulator_config
    from simulator.export import export_history

    cfg = load_simulator_config()
    clean = cfg.replace(fouling=dataclasses.replace(
        cfg.fouling, R_th_f_initial_K_per_kW=0.0, R_th_f_inf_K_per_kW=0.0, CF_dp_f_initial=1.0,
        CF_dp_f_inf=1.0), faults=())
    path = tmp_path_factory.mktemp("history") / "clean.csv"
    export_history(60 / 1440, path, cfg=clean)
    return path


@pytest.mark.parametrize("sep, decimal", [(";", ","), ("\t", "."), ("\t", ","), (";", ".")])
def test_separator_and_decimal_mark_are_detected(clean_csv, tmp_path, sep, decimal):
    ref = read_history(clean_csv)
    assert (ref.sep, ref.decimal) == (",", ".")
    other = tmp_path / "other.csv"
    pd.read_csv(clean_csv).to_csv(other, index=False, sep=sep, decimal=decimal)
    got = read_history(other)
    assert (got.sep, got.decimal) == (sep, decimal)
    pd.testing.assert_frame_equal(got.frame, ref.frame)
    assert got.skipped == {} and got.non_numeric == {}
    # and when given explicitly, the same
    again = read_history(other, sep=sep, decimal=decimal)
    pd.testing.assert_frame_equal(again.frame, ref.frame)


def test_decimal_comma_with_commas_as_separator_needs_saying_so(tmp_path):
    path = tmp_path / "mixed.csv"
    path.write_text("timestamp;a;b\n2024-03-01T00:00Z;1,5;2.5\n")
    with pytest.raises(HistoryError, match="decimal comma and with a decimal point in the same "
                                           "file; say which with --decimal"):
        read_history(path, required=())
    h = read_history(path, decimal=",", required=())
    assert h.frame["a"].iloc[0] == 1.5 and np.isnan(h.frame["b"].iloc[0])
    assert h.first_non_numeric == {"b": "line 2: '2.5'"}


def test_the_first_bad_timestamp_is_named_with_line_value_and_format(clean_csv, tmp_path):
    lines = clean_csv.read_text().splitlines()
    lines[4] = "2024-13-01 00:03" + lines[4][lines[4].index(","):]     # file line 5
    lines[9] = "yesterday" + lines[9][lines[9].index(","):]
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    h = read_history(path)
    assert len(h.frame) == 58 and h.skipped == {"bad timestamp": 2}
    assert h.report_lines(path)[1] == (
        "  rows skipped: bad timestamp: 2 (first at line 5: '2024-13-01 00:03'; expected ISO "
        "8601, e.g. 2024-03-01T06:00:00Z or 2024-03-01 06:00 (UTC when naive))")
    everything_bad = tmp_path / "dates.csv"
    everything_bad.write_text("\n".join(
        [lines[0]] + ["01.03.2024 00:0%d" % i + ln[ln.index(","):]
                      for i, ln in enumerate(lines[1:4])]) + "\n")
    with pytest.raises(HistoryError) as info:
        read_history(everything_bad)
    assert str(info.value) == (
        f"{everything_bad}: no row has a readable timestamp; the first, at line 2: "
        "'01.03.2024 00:00', is not ISO 8601, e.g. 2024-03-01T06:00:00Z or 2024-03-01 06:00 "
        "(UTC when naive)")


@pytest.mark.parametrize("text, fragment", [
    ("a;b;c\n1;2;3\n", "line 1: no 'timestamp' column in the header (the first column of a "
                       "history CSV; separated by comma, semicolon or tab); the header starts "
                       "'a', 'b', 'c'"),
    ("", "the file is empty"),
    ("timestamp,a\n2024-03-01,1\x00\n", "line 2: a NUL byte; this is not a text file"),
    ("timestamp,a,a\n2024-03-01,1,2\n", "column(s) a appear more than once"),
])
def test_unreadable_files_are_named(tmp_path, text, fragment):
    path = tmp_path / "x.csv"
    path.write_text(text)
    with pytest.raises(HistoryError) as info:
        read_history(path, required=())
    assert str(info.value) == f"{path}: {fragment}"


def test_read_history_csv_keeps_its_contract(clean_csv):
    frame, skipped, non_numeric = read_history_csv(clean_csv)
    assert str(frame["timestamp"].dt.tz) == "UTC" and frame["timestamp"].is_monotonic_increasing
    assert skipped == {} and non_numeric == {} and len(frame) == 60


def test_cli_reads_a_semicolon_export(clean_csv, tmp_path, capsys):
    semi = tmp_path / "scada.csv"
    pd.read_csv(clean_csv).to_csv(semi, index=False, sep=";", decimal=",")
    rc = main(["optimize", str(semi), "--window", "2024-03-01T00:30/2024-03-01T00:40",
               "--state-dir", str(tmp_path / "state"), "--sep", ";", "--decimal", ","])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert out.splitlines()[0] == f"{semi}: 60 rows read (semicolon-separated, decimal comma)"


# ------------------------------------------------------- item 5: degenerate commissioning


def test_calibrate_initial_refuses_a_degenerate_state_unless_forced(clean_csv, tmp_path, capsys):
    """The campaign's case: V_source and W_LS swapped gave NRMSE 13 %, three factors at their
    bound and dp_clean R^2 -49, saved with exit 0. (With the compressor curves learned from the
    same data first, fewer factors run to a bound; the objective and the dp fit still fail.)"""
    df = pd.read_csv(clean_csv)
    df[["V_source", "W_LS"]] = df[["W_LS", "V_source"]].to_numpy()
    swapped = tmp_path / "swapped.csv"
    df.to_csv(swapped, index=False)
    state = tmp_path / "state"
    rc = main(["calibrate", "initial", str(swapped), "--state-dir", str(state)])
    err = capsys.readouterr().err.splitlines()
    assert rc == 2
    assert err[0] == ("hp-edge calibrate initial: not saved: the result fails the plausibility "
                      "limits of plant.yaml calibration.initial.limits (wrong input? e.g. "
                      "swapped columns; --force saves it anyway):")
    assert any("calibration objective" in ln and "exceeds max_objective_pct 5 %" in ln
               for ln in err), err
    assert any("clean pressure-drop fit R^2" in ln and "is below min_dp_clean_r2 0" in ln
               for ln in err), err
    assert not state.exists() or list(state.iterdir()) == []       # nothing saved
    rc = main(["calibrate", "initial", str(swapped), "--state-dir", str(state), "--force",
               "--json"])
    captured = capsys.readouterr()
    assert rc == 0
    assert "WARNING (saved with --force): calibration objective" in captured.err
    saved = json.loads((state / "initial_calibration.json").read_text())
    assert saved["objective"] > 0.05


def test_commissioning_limits_are_configurable_and_checked():
    from edge.commissioning import CommissioningLimits

    assert CommissioningLimits.from_config({}) == CommissioningLimits(5.0, 1, 0.0)
    lim = CommissioningLimits.from_config({"calibration": {"initial": {"limits": {
        "max_objective_pct": 2, "max_parameters_at_bound": 0, "min_dp_clean_r2": 0.5}}}})
    assert lim == CommissioningLimits(2, 0, 0.5)
    with pytest.raises(ValueError, match=r"key 'calibration.initial.limits.max_objective': "
                                         r"unknown \(known: max_objective_pct"):
        CommissioningLimits.from_config({"calibration": {"initial": {"limits": {
            "max_objective": 2}}}})

    @dataclasses.dataclass
    class Res:
        objective: float
        nrmse: dict
        at_bound: list
        params: dict
        bounds: dict

    @dataclasses.dataclass
    class Dp:
        r2: float

    ok = Res(0.004, {"Q_sink": 0.004}, ["CF_DSH"], {"CF_DSH": 0.5}, {"CF_DSH": (0.5, 2.0)})
    assert CommissioningLimits().failures(ok, Dp(0.16)) == []
    assert lim.failures(ok, Dp(0.16)) == [
        "1 parameters at a bound (CF_DSH 0.5 (bounds 0.5..2)), more than "
        "max_parameters_at_bound 0",
        "clean pressure-drop fit R^2 0.16 is below min_dp_clean_r2 0.5 (flow and pressure "
        "columns do not explain each other)"]


def test_rows_with_the_wrong_number_of_fields_are_skipped_and_named(tmp_path):
    path = tmp_path / "ragged.csv"
    path.write_text("timestamp,a,b\n2024-03-01T00:00Z,1,2\n2024-03-01T00:01Z,1,2,3\n"
                    "2024-03-01T00:02Z,4\n\n2024-03-01T00:03Z,5,6\n")
    h = read_history(path, required=())
    assert h.frame["a"].tolist() == [1.0, 5.0] and h.frame["b"].tolist() == [2.0, 6.0]
    assert h.skipped == {"wrong number of fields": 2}
    assert h.report_lines(path)[1] == "  rows skipped: wrong number of fields: 2 (first at line 3)"


def _tricky(path, sep=",", decimal="."):
    """Rows out of time order, a duplicate and an unreadable timestamp, cells that are not numbers,
    missing-value texts, a ragged row, a quality column, integers and decimals in one column."""
    def num(x):
        return str(x).replace(".", ",") if decimal == "," else str(x)
    rows = [["timestamp", "a", "b", "quality"]]
    for i in range(40):
        t = f"2024-03-01T{(37 * i) % 40 // 60:02d}:{(37 * i) % 40:02d}:00Z"
        a = "x" if i in (5, 23) else ("n/a" if i == 7 else num(round(0.25 * i, 2)))
        b = str(i) if i % 3 else num(i + 0.5)
        rows.append([t, a, b, "stale" if i % 11 == 0 else ""])
    rows[9][0] = "2024-13-01 00:00"        # unreadable
    rows[12][0] = rows[13][0]              # a duplicate of the next row's time
    rows[17][2] = "1.2.3"
    rows.insert(20, ["2024-03-01T00:59:00Z", "1"])      # ragged
    path.write_text("\n".join(sep.join(r) for r in rows) + "\n")
    return path


@pytest.mark.parametrize("sep, decimal", [(",", "."), (";", ",")])
def test_the_rows_are_read_in_chunks_with_the_same_result(tmp_path, monkeypatch, sep, decimal):
    """The rows are turned into numbers in chunks (a plant-year as Python strings at once took
    1.7 GB); chunks of 1, 3 and 7 rows give the whole file's result: frame, dtypes, rows skipped
    and non-numeric cells with their first occurrences (in time order), line numbers."""
    import edge.io.history as hist
    path = _tricky(tmp_path / "tricky.csv", sep, decimal)
    whole = read_history(path, required=())
    assert whole.skipped == {"wrong number of fields": 1, "bad timestamp": 1, "duplicate timestamp": 1}
    assert whole.non_numeric == {"a": 2, "b": 1}
    # 'x' in data rows 5 (minute 25, line 7) and 23 (minute 11, line 26 behind the ragged row):
    # the earlier in time is named (as the reader always did: checked against stop 25's reader)
    assert whole.first_non_numeric == {"a": "line 26: 'x'", "b": "line 18: '1.2.3'"}
    assert whole.first_bad_timestamp == "line 10: '2024-13-01 00:00'"
    assert whole.frame["timestamp"].is_monotonic_increasing
    assert pd.api.types.is_string_dtype(whole.frame["quality"])
    for n in (1, 3, 7):
        monkeypatch.setattr(hist, "CHUNK_ROWS", n)
        h = read_history(path, required=())
        pd.testing.assert_frame_equal(h.frame, whole.frame, check_exact=True)
        for f in ("skipped", "non_numeric", "first_non_numeric", "first_bad_timestamp", "first_ragged",
                  "sep", "decimal"):
            assert getattr(h, f) == getattr(whole, f), (n, f)


def test_a_header_only_file_and_header_errors_after_the_rows(tmp_path):
    """A file with a header and no rows gives an empty frame; a header error is reported after
    the rows are read, so a CSV error in them is named first."""
    p = tmp_path / "empty.csv"
    p.write_text("timestamp,a\n")
    h = read_history(p, required=())
    assert len(h.frame) == 0 and list(h.frame.columns) == ["timestamp", "a"]
    p.write_text("timestamp,a,a\n2024-03-01T00:00Z,1,2\n")
    with pytest.raises(HistoryError, match=r"column\(s\) a appear more than once"):
        read_history(p, required=())
    p.write_text('timestamp,a,a\n2024-03-01T00:00Z,' + 'x' * 200_000 + ',1\n')    # beyond csv's field limit
    with pytest.raises(HistoryError, match="cannot read as CSV"):
        read_history(p, required=())


def _cell_oracle(cells, decimal="."):
    """What a column of cells reads as, cell by cell from the module docstring's rules: the text
    without surrounding whitespace as Python's float reads it; no number (NaN) with digits other
    than ASCII, '_', or (decimal comma) a point; integers (int64) when every cell is one."""
    vals, wrong = [], []
    for c in cells:
        t = c.strip()
        v = float("nan")
        if t.isascii() and "_" not in t and not (decimal == "," and "." in t):
            try:
                v = float(t.replace(",", ".") if decimal == "," else t)
            except ValueError:
                pass
        vals.append(v)
        wrong.append(v != v and t.lower() not in ("", "nan", "na", "n/a", "null", "none"))
    import re
    if all(re.fullmatch(r"\s*[+-]?[0-9]+\s*", c) and c.isascii() for c in cells):   # none: too
        ints = [int(c.strip()) for c in cells]
        for dtype, lo, hi in ((np.int64, -2**63, 2**63), (np.uint64, 0, 2**64)):   # as pandas
            if all(lo <= i < hi for i in ints):
                return np.array(ints, dtype=dtype), np.array(wrong, dtype=bool)
    return np.array(vals, dtype=float), np.array(wrong, dtype=bool)


def test_cells_are_read_as_python_reads_a_number(tmp_path):
    """A cell is read correctly rounded (pandas' own parser is not: 59.378800835e-65 read as
    5.9378800835000006e-64), '1_0' and non-ASCII digits are not numbers, surrounding whitespace
    (also the separators below ASCII space) is not part of a cell, 'NULL' is a missing value and
    not counted, a column of integers stays integer."""
    p = tmp_path / "cells.csv"
    a = ["59.378800835e-65", "749410988.31818085921323796459658616836269987", " 3.25 ", "1.5\x1f",
         "1_0", "\u0661\u0662", "NULL", "+nan", "-0", "inf"]
    p.write_text("timestamp,a,n\n" + "".join(
        f"2024-03-01T00:{i:02d}:00Z,{c},{i - 3}\n" for i, c in enumerate(a)))
    h = read_history(p, required=())
    got = h.frame["a"].to_numpy()
    assert got[0] == 5.9378800835e-64 and got[1] == 749410988.3181809
    assert got[2] == 3.25 and got[3] == 1.5 and np.isnan(got[4:8]).all()
    assert got[8] == 0.0 and np.signbit(got[8]) and got[9] == np.inf
    assert h.non_numeric == {"a": 3}            # '1_0', the Arabic-Indic 12 and '+nan'; not NULL
    assert h.first_non_numeric == {"a": "line 6: '1_0'"}
    assert h.frame["n"].dtype == np.int64 and h.frame["n"].tolist() == list(range(-3, 7))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(
    st.sampled_from(["1.5", "-2", "1e5", " 3.25 ", "", " ", "nan", "NaN", "n/a", "x", "1_0", "\u0661",
                     "1,5", "1.2.3", "inf", "+nan", "1.5\x1f", "-0", ".5", "5.", "007", " +12 ",
                     "9223372036854775808", "99999999999999999999", "1e400", "0.1e-310"]),
    st.floats(allow_nan=False).map(repr), st.integers(-10**12, 10**12).map(str),
    st.text(alphabet="0123456789.,eE+- \t", max_size=8)), max_size=12),
    st.sampled_from([".", ","]))
@example(["1_0", "2.5"], ".").via("an underscore in a column that otherwise reads at once")
@example(["\u0661", "2"], ".").via("a non-ASCII digit")
@example(["7", " +5 ", "-0"], ".").via("integers")
@example(["7", "5\x1f"], ".").via("integers, one with a separator below ASCII space")
@example(["1,5", "2"], ",").via("decimal comma")
@example(["1.5", "2"], ",").via("a point where the decimal mark is a comma")
def test_a_column_reads_as_its_cells_one_by_one(cells, decimal):
    """Whether read in one conversion (every cell a number as it stands) or cell by cell (one that
    is not forces it: a blank cell added), a column's numbers and wrong cells are the oracle's,
    to the bit; its dtype too."""
    from edge.io.history import _numbers
    cells = tuple(cells)
    for src in (cells, cells + (" ",)):
        want, wrong = _cell_oracle(src, decimal)
        num, nn = _numbers(src, decimal)
        assert nn.tolist() == wrong.tolist()
        if want.dtype != np.float64:
            assert num.dtype == want.dtype and num.tolist() == want.tolist()
        else:
            assert num.dtype == np.float64
            assert np.array_equal(num.view(np.int64), want.view(np.int64)), (src, num, want)


# ---- the clean-file fast path (one C parse) against the row-by-row reading ------------------------
_NUMBER = st.one_of(st.floats(allow_nan=False, allow_infinity=False).map(repr),
                    st.integers(-10**15, 10**15).map(str),
                    st.decimals(allow_nan=False, allow_infinity=False, places=7).map(str),
                    st.sampled_from(["0", "-0", "007", ".5", "5.", "1e5", "1.5E-3", " 2.5", "3 ",
                                     "9223372036854775807", "-9223372036854775808"]))
_MESSY = st.sampled_from(["", " ", "nan", "NaN", "n/a", "x", "1_0", "\u0661", "1.2.3", "inf", "-inf",
                          "Infinity", "+nan", "1.5\x1f", "9223372036854775808", "1e400", '"4"', "TRUE",
                          "0x10", "1d5"])


@st.composite
def _history_text(draw):
    """A history file's text: mostly clean (the fast path's case), or with any of the things the
    row-by-row reading handles (messy cells, bad/duplicate/unsorted/offset timestamps, ragged rows,
    blank lines, CRLF, quotes, a quality column, a header after blank lines)."""
    clean = draw(st.booleans())
    sep = draw(st.sampled_from([",", ";", "\t"]))
    names = ["timestamp", "a", "b"] + (["quality"] if draw(st.booleans()) else [])
    n = draw(st.integers(0 if not clean else 1, 12))
    mins = draw(st.lists(st.integers(0, 59), min_size=n, max_size=n))
    lines = []
    for i, m in enumerate(mins):
        ts = f"2024-03-01T00:{m:02d}:00Z"
        if not clean:
            ts = draw(st.sampled_from([ts, f"2024-03-01 00:{m:02d}", f"2024-03-01T01:{m:02d}:00+01:00",
                                       f"2024-03-01T00:{m:02d}:00.5Z", "2024-13-01T00:00Z", " " + ts]))
        cells = [ts, draw(_NUMBER if clean else st.one_of(_NUMBER, _MESSY)),
                 draw(_NUMBER if clean else st.one_of(_NUMBER, _MESSY))]
        if "quality" in names:
            cells.append(draw(st.sampled_from(["", "good", "stale", " bad "])))
        if not clean and draw(st.integers(0, 9)) == 0:
            cells = cells[:-1] if draw(st.booleans()) else cells + ["9"]       # ragged
        lines.append(sep.join(cells))
        if draw(st.integers(0, 9)) == 0:
            lines.append(draw(st.sampled_from(["", "   "])))                   # blank lines
    head = sep.join(names)
    if not clean and draw(st.integers(0, 9)) == 0:
        head = "\n" + head
    eol = draw(st.sampled_from(["\n", "\r\n"]))
    return head + eol + eol.join(lines) + (eol if draw(st.booleans()) else "")


def _same_reading(a, b):
    pd.testing.assert_frame_equal(a.frame, b.frame, check_exact=True)
    for f in ("skipped", "non_numeric", "first_non_numeric", "first_bad_timestamp", "first_ragged",
              "sep", "decimal"):
        assert getattr(a, f) == getattr(b, f), f


@settings(max_examples=400, deadline=None)
@given(_history_text())
def test_a_clean_file_in_one_parse_reads_as_row_by_row(tmp_path_factory, text):
    """The fast path (pandas' C reader on a clean file) gives what the row-by-row reading gives —
    frame and dtypes to the bit, rows skipped, cells that are not numbers and where — or is not
    taken; an error is the same error."""
    import edge.io.history as hist
    path = tmp_path_factory.mktemp("h") / "h.csv"
    path.write_bytes(text.encode("utf-8"))
    try:
        slow_err, slow = None, None
        hist.FAST_PATH = False
        try:
            slow = read_history(path, required=())
        except HistoryError as exc:
            slow_err = str(exc)
    finally:
        hist.FAST_PATH = True
    try:
        fast = read_history(path, required=())
    except HistoryError as exc:
        assert str(exc) == slow_err
        return
    assert slow_err is None
    _same_reading(fast, slow)


def test_a_clean_export_takes_the_fast_path_and_reads_the_same(clean_csv, tmp_path, monkeypatch):
    """The simulator's export (and its CRLF form) is clean: read without the row-by-row reader
    at all, the same History as with it."""
    import edge.io.history as hist
    crlf = tmp_path / "crlf.csv"
    crlf.write_bytes(clean_csv.read_bytes().replace(b"\n", b"\r\n"))
    for path in (clean_csv, crlf):
        monkeypatch.setattr(hist, "FAST_PATH", False)
        slow = read_history(path)
        monkeypatch.setattr(hist, "FAST_PATH", True)

        def no_rows(*a, **k):
            raise AssertionError("the row-by-row reader was used")
        monkeypatch.setattr(hist, "_rows", no_rows)
        fast = read_history(path)
        monkeypatch.undo()
        _same_reading(fast, slow)
        assert len(fast.frame) == 60


@pytest.mark.parametrize("text", [
    "timestamp,a,b\n2024-03-01T00:00Z,1,2\n2024-03-01T00:01Z,1,2,3\n",        # a long row
    "timestamp,a,b\n2024-03-01T00:00Z,1,2,3\n2024-03-01T00:01Z,1,2,3\n",      # every row long
    "timestamp,a,b\n2024-03-01T00:00Z,1\n2024-03-01T00:01Z,1,2\n",            # a short row
    "timestamp,a,b\n2024-03-01T00:00Z,1,2\n2024-13-01T00:01Z,1,2\n",          # a bad timestamp
    "timestamp,a,b\n2024-03-01T00:00Z,1,NULL\n2024-03-01T00:01Z,1,2\n",       # a missing-value text
    "timestamp,a,b\n2024-03-01T00:00Z,1,2\r2024-03-01T00:01Z,1,2\r",          # lone carriage returns
    'timestamp,a,b\n2024-03-01T00:00Z,"1",2\n',                                # quotes
    "timestamp,a,b\n2024-03-01T00:00Z,1,inf\n",                                # not finite
    "timestamp,a,quality\n2024-03-01T00:00Z,1\n2024-03-01T00:01Z,2,good\n",   # a row without its quality
    "timestamp,a,b\n2024-03-01T00:00Z,1,2\n,,\n2024-03-01T00:01Z,1,2\n",      # a row of empty cells
])
def test_files_that_are_not_clean_take_the_row_by_row_reading(tmp_path, monkeypatch, text):
    """Each of these leaves the fast path (``_clean_file`` is None) and is read row by row."""
    import edge.io.history as hist
    from edge.io.history import _clean_file, detect_format
    sep, decimal, at = detect_format(text)
    assert _clean_file(text, sep, decimal, at, ()) is None


def test_the_fast_path_reads_numbers_correctly_rounded(tmp_path, monkeypatch):
    """Numbers pandas' default converter rounds wrongly (``test_cells_are_read_as_python_reads_a_
    number``) in a clean file: the fast path takes it and reads them as Python's float does."""
    import edge.io.history as hist
    a = ["59.378800835e-65", "749410988.31818085921323796459658616836269987", "2.2250738585072011e-308",
         "0.1000000000000000055511151231257827021181583404541015625", "1.5"]
    p = tmp_path / "round.csv"
    p.write_text("timestamp,a\n" + "".join(f"2024-03-01T00:{i:02d}:00Z,{c}\n" for i, c in enumerate(a)))
    monkeypatch.setattr(hist, "_rows", lambda *a, **k: (_ for _ in ()).throw(AssertionError("row by row")))
    got = read_history(p, required=()).frame["a"].to_numpy()
    assert np.array_equal(got.view(np.int64), np.array([float(c) for c in a]).view(np.int64))


def test_the_fast_path_keeps_the_quality_texts_under_a_header_with_spaces(tmp_path, monkeypatch):
    """Column names with spaces around them (stripped by the reading) and a quality column of
    digits: the fast path reads the quality as texts, as the row-by-row reading does."""
    import edge.io.history as hist
    p = tmp_path / "spaces.csv"
    p.write_text("timestamp , a , quality \n2024-03-01T00:00Z,1.5,0\n2024-03-01T00:01Z,2.5,1\n")
    monkeypatch.setattr(hist, "FAST_PATH", False)
    slow = read_history(p, required=())
    monkeypatch.setattr(hist, "FAST_PATH", True)
    monkeypatch.setattr(hist, "_rows", lambda *a, **k: (_ for _ in ()).throw(AssertionError("row by row")))
    fast = read_history(p, required=())
    _same_reading(fast, slow)
    assert fast.frame["quality"].tolist() == ["0", "1"]
