"""Named JSON state documents in a state directory, written atomically (SPEC §7.5).

A write goes to a temporary file in the same directory, is flushed and fsync'ed, then renamed over
the target with ``os.replace`` (atomic on POSIX), and the directory is fsync'ed so the rename itself
survives a power cut. A crash at any moment leaves either the old or the new document, never a torn
one. Readers get ``None`` for a document that was never written and ``StateError`` (naming the file)
for one that is unreadable.
"""
from __future__ import annotations

import json
import math
import os
import re
import tempfile
from datetime import datetime, timezone
from pathlib import Path

DEFAULT_STATE_DIR = Path("var/state")
INITIAL_CALIBRATION = "initial_calibration.json"
FOULING_CALIBRATION = "fouling_calibration.json"
DP_CLEAN = "dp_clean.json"
SURROGATE = "surrogate.json"
COMPRESSORS = "compressors.json"          # learned compressor curves (model.analysis.compressors)
CHAIN = "chain_state.json"                # what one analysis window hands to the next
SURROGATE_TRACKER = "surrogate_tracker.json"  # window optima and the surrogate fitted on them
KNOWN = (INITIAL_CALIBRATION, FOULING_CALIBRATION, DP_CLEAN, SURROGATE, COMPRESSORS, CHAIN,
         SURROGATE_TRACKER)
_NAME = re.compile(r"^[a-z0-9_]+\.json$")


class StateError(RuntimeError):
    """A state document cannot be read or written; the message names the file."""


def _check(name: str) -> None:
    if not _NAME.match(name):
        raise StateError(f"invalid state document name {name!r} (expected lower_case_name.json)")


def _jsonable(v):
    """NaN/inf -> None (JSON has no NaN); numpy scalars -> Python numbers."""
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def write_state(name: str, doc: dict, state_dir: str | os.PathLike = DEFAULT_STATE_DIR) -> Path:
    """Atomically write ``doc`` as ``state_dir/name``; adds ``saved_at`` (UTC ISO 8601).

    Raises StateError (naming the file and the OS error) for every failure of the file system:
    a directory that cannot be created or written (read-only, permissions), a full disk, an I/O
    error. The previous document, if any, is then left as it was; no temporary file remains.
    """
    _check(name)
    d = Path(state_dir)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StateError(f"cannot create state directory {d}: {exc}") from exc
    target = d / name
    body = json.dumps({**_jsonable(doc), "saved_at": datetime.now(timezone.utc).isoformat()},
                      indent=1, allow_nan=False)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=d)
    except OSError as exc:
        raise StateError(f"cannot write state file {target}: {exc}") from exc
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(body)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except OSError as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise StateError(f"cannot write state file {target}: {exc}") from exc
    try:
        dfd = os.open(d, os.O_RDONLY)
    except OSError:
        return target               # platforms without directory fds: the rename is still atomic
    try:
        os.fsync(dfd)
    except OSError as exc:
        raise StateError(f"state file {target} written, but the directory {d} could not be "
                         f"synced (the rename may not survive a power cut): {exc}") from exc
    finally:
        os.close(dfd)
    return target


def read_state(name: str, state_dir: str | os.PathLike = DEFAULT_STATE_DIR) -> dict | None:
    """The document ``state_dir/name``, or None when it does not exist."""
    _check(name)
    path = Path(state_dir) / name
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise StateError(f"cannot read state file {path}: {exc}") from exc
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise StateError(f"state file {path} is not valid JSON: {exc}") from exc
    if not isinstance(doc, dict):
        raise StateError(f"state file {path}: expected a JSON object")
    return doc


def state_path(name: str, state_dir: str | os.PathLike = DEFAULT_STATE_DIR) -> Path:
    _check(name)
    return Path(state_dir) / name
