"""The input campaign of issue 9 (item 15), repeatable: mutated configuration files and history
CSVs through the real commands, in-process.

Every case runs one command (``check-config``, ``point``, ``simulate --export``,
``calibrate fouling``) on a copy of the shipped configuration with one file mutated, or on a
mutated commissioning CSV, and records:

* a *traceback*: any exception other than SystemExit escaping ``edge.cli.main`` (the target is 0);
* the exit code, and whether a failing one is 2 with a message on stderr (1 is accepted from
  ``point`` only, for an operating point the mutated plant cannot run);
* the size of its error output (lines, bytes: bounded), the wall time and the peak of Python
  memory (tracemalloc) of the case.

``hp-edge bench --only inputs`` runs the full campaign (300 configs, 200 CSVs) and prints JSON;
tests/test_input_campaign.py runs a seeded subset in seconds. Mutations are seeded: a case is
reproducible from (seed, index).
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import json
import random
import shutil
import tempfile
import time
import tracemalloc
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "config"
CONFIG_FILES = ("gateway.yaml", "tags.yaml", "plant.yaml", "simulator.yaml")
TARGETS = {"targets_tracebacks": 0, "max_peak_mb_config_le_64kb": 100.0}
HOSTILE = [None, "", "x", -1, 0, 1.0e309, -1.0e309, float("nan"), 10**400, True, [], {},
           "NaN", [[[1]]], "y" * 10_000, "°C", "a\x00b", 65536, -32769, 1e-320, "1e3",
           {"nested": {"deeper": [1, 2, {"x": None}]}}]


# -------------------------------------------------------------------------------- mutations


def _paths(doc, prefix=()):
    """Every (path, value) of a parsed YAML document."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield prefix + (k,), v
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield prefix + (i,), v
            yield from _paths(v, prefix + (i,))


def _parent(doc, path):
    node = doc
    for p in path[:-1]:
        node = node[p]
    return node


def _typo(key: str, rng: random.Random) -> str:
    if len(key) < 2:
        return key + "_"
    i = rng.randrange(len(key) - 1)
    ops = [key[:i] + key[i + 1] + key[i] + key[i + 2:],       # swap two letters
           key.upper() if key.lower() == key else key.lower(),
           key[:i] + key[i + 1:],                              # drop a letter
           key + "s"]
    return rng.choice(ops)


def mutate_structure(doc, rng: random.Random):
    """One structural mutation of a parsed document (a deep copy is returned)."""
    doc = copy.deepcopy(doc)
    paths = [p for p, _ in _paths(doc)]
    if not paths:
        return rng.choice(HOSTILE)
    path = rng.choice(paths)
    parent = _parent(doc, path)
    key = path[-1]
    op = rng.choice(("delete", "hostile", "hostile", "rename", "retype", "wrap"))
    if op == "delete":
        del parent[key]
    elif op == "hostile":
        parent[key] = copy.deepcopy(rng.choice(HOSTILE))
    elif op == "rename" and isinstance(parent, dict) and isinstance(key, str):
        parent[_typo(key, rng)] = parent.pop(key)
    elif op == "retype":
        v = parent[key]
        parent[key] = (str(v) if not isinstance(v, str) else
                       (int(v) if v.isdigit() else [v]))
    else:
        parent[key] = [parent[key]] if rng.random() < 0.5 else {"value": parent[key]}
    return doc


def _dump(doc) -> str:
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True, width=10_000)


def mutate_text(text: str, rng: random.Random) -> str | bytes:
    """One textual mutation of a YAML file."""
    lines = text.splitlines()
    op = rng.choice(("nul", "truncate", "nest", "alias_bomb", "bytes", "dup_line", "indent",
                     "dup_key", "tab", "anchor", "huge_int", "long_line"))
    at = rng.randrange(max(1, len(text)))
    if op == "nul":
        return text[:at] + "\x00" + text[at:]
    if op == "truncate":
        return text[:at]
    if op == "nest":
        depth = rng.choice((30, 200, 500))
        return text + "\ndeep: " + "[" * depth + "]" * depth + "\n"
    if op == "alias_bomb":
        bomb = ["lol0: &a0 [x, x, x, x, x, x, x, x, x]"] + [
            f"lol{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 10)]
        return text + "\n" + "\n".join(bomb) + "\n"
    if op == "bytes":
        raw = bytearray(text.encode("utf-8"))
        for _ in range(rng.randint(1, 5)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
        return bytes(raw)
    if op == "dup_line" and lines:
        i = rng.randrange(len(lines))
        return "\n".join(lines[: i + 1] + [lines[i]] + lines[i + 1:]) + "\n"
    if op == "indent" and lines:
        i = rng.randrange(len(lines))
        lines[i] = (" " * rng.choice((1, 3, 8))) + lines[i]
        return "\n".join(lines) + "\n"
    if op == "dup_key":
        return text + "\n" + (lines[0] if lines and ":" in lines[0] else "plc: {}") + "\n"
    if op == "tab" and lines:
        i = rng.randrange(len(lines))
        lines[i] = "\t" + lines[i]
        return "\n".join(lines) + "\n"
    if op == "anchor":
        return text.replace(":", ": &anchor", 1)
    if op == "huge_int":
        return text.replace(": ", ": " + "9" * rng.choice((50, 400, 5000)) + " #", 1)
    return text + "\nlong_line: " + "z" * rng.choice((1000, 60_000)) + "\n"


def mutated_config(rng: random.Random) -> tuple[str, str | bytes, str]:
    """(file name, mutated content, description)."""
    name = rng.choice(CONFIG_FILES)
    text = (CONFIG / name).read_text(encoding="utf-8")
    if rng.random() < 0.55:
        doc = yaml.safe_load(text)
        n = rng.choice((1, 1, 2, 3))
        for _ in range(n):
            doc = mutate_structure(doc, rng)
        return name, _dump(doc), f"{n} structural mutation(s)"
    return name, mutate_text(text, rng), "textual mutation"


def mutate_csv(text: str, rng: random.Random) -> str | bytes:
    """One mutation of a history CSV (comma-separated, decimal point)."""
    lines = text.splitlines()
    header, rows = lines[0], lines[1:]
    cols = header.split(",")
    op = rng.choice(("semicolon", "tab", "bad_timestamp", "drop_column", "rename_column",
                     "cell", "truncate", "no_header", "empty", "header_only", "nul", "bytes",
                     "dup_rows", "shuffle", "extra_field", "missing_field", "bom_crlf",
                     "quoted", "long_line", "all_bad_timestamps", "dup_column"))
    if op in ("semicolon", "tab"):
        sep = ";" if op == "semicolon" else "\t"
        dec = rng.choice((".", ","))
        out = [header.replace(",", sep)] + [
            sep.join(c.replace(".", dec) if i else c for i, c in enumerate(r.split(",")))
            for r in rows]
        return "\n".join(out) + "\n"
    if op in ("bad_timestamp", "all_bad_timestamps"):
        bad = rng.choice(("", "yesterday", "2024-13-01", "01.03.2024 00:00", "2024-02-30T00:00",
                          "1709251200", "NaT", "2024-03-01T25:00"))
        idx = range(len(rows)) if op == "all_bad_timestamps" else \
            rng.sample(range(len(rows)), k=min(len(rows), rng.randint(1, 5)))
        for i in idx:
            parts = rows[i].split(",")
            parts[0] = bad
            rows[i] = ",".join(parts)
        return "\n".join([header] + rows) + "\n"
    if op in ("drop_column", "rename_column", "dup_column"):
        j = rng.randrange(len(cols))
        if op == "drop_column":
            keep = [i for i in range(len(cols)) if i != j]
            return "\n".join(",".join(r.split(",")[i] for i in keep if i < len(r.split(",")))
                             for r in [header] + rows) + "\n"
        cols[j] = _typo(cols[j], rng) if op == "rename_column" else cols[(j + 1) % len(cols)]
        return "\n".join([",".join(cols)] + rows) + "\n"
    if op == "cell":
        for _ in range(rng.randint(1, 10)):
            i = rng.randrange(len(rows))
            parts = rows[i].split(",")
            parts[rng.randrange(1, len(parts))] = rng.choice(
                ("", "n/a", "nan", "inf", "-inf", "1e400", "9" * 400, "abc", "1,5", "-0",
                 "1e-400", "0x10", "true"))
            rows[i] = ",".join(parts)
        return "\n".join([header] + rows) + "\n"
    if op == "truncate":
        return text[: rng.randrange(len(text))]
    if op == "no_header":
        return "\n".join(rows) + "\n"
    if op == "empty":
        return ""
    if op == "header_only":
        return header + "\n"
    if op == "nul":
        at = rng.randrange(len(text))
        return text[:at] + "\x00" + text[at:]
    if op == "bytes":
        raw = bytearray(text.encode())
        for _ in range(rng.randint(1, 20)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
        return bytes(raw)
    if op == "dup_rows":
        return "\n".join([header] + rows + rows[: rng.randint(1, len(rows))]) + "\n"
    if op == "shuffle":
        rng.shuffle(rows)
        return "\n".join([header] + rows) + "\n"
    if op == "extra_field":
        i = rng.randrange(len(rows))
        rows[i] += ",1,2"
        return "\n".join([header] + rows) + "\n"
    if op == "missing_field":
        i = rng.randrange(len(rows))
        rows[i] = ",".join(rows[i].split(",")[:-3])
        return "\n".join([header] + rows) + "\n"
    if op == "bom_crlf":
        return "\ufeff" + "\r\n".join([header] + rows) + "\r\n"
    if op == "quoted":
        return "\n".join(",".join(f'"{c}"' for c in r.split(",")) for r in [header] + rows) + "\n"
    i = rng.randrange(len(rows))
    rows[i] += "," + "7" * 100_000
    return "\n".join([header] + rows) + "\n"


# -------------------------------------------------------------------------------- running


@dataclasses.dataclass
class Case:
    kind: str            # config | csv
    index: int
    file: str
    what: str
    command: str
    size: int = 0
    rc: int | None = None
    traceback: str | None = None
    err_lines: int = 0      # what a failure prints (stderr): bounded
    err_bytes: int = 0
    out_bytes: int = 0      # what a success prints (stdout, e.g. check-config's layout)
    seconds: float = 0.0
    peak_mb: float = 0.0
    message: str = ""

    @property
    def ok(self) -> bool:
        """No traceback; a failure exits 2 with a message (point may exit 1 for an operating
        point the mutated plant cannot run); output bounded."""
        if self.traceback is not None:
            return False
        if self.err_lines > 60 or self.err_bytes > 20_000:
            return False
        if self.rc == 0:
            return True
        if self.rc == 1 and self.command == "point":
            return bool(self.message)
        return self.rc == 2 and bool(self.message)


def _run(argv: list[str], measure_memory: bool) -> tuple[int | None, str | None, str, str, float, float]:
    from edge.cli import main

    out, err = io.StringIO(), io.StringIO()
    rc, tb = None, None
    if measure_memory:
        tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = main(argv)
    except SystemExit as exc:
        rc = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except Exception as exc:  # noqa: BLE001 - counting tracebacks is the point
        tb = f"{type(exc).__name__}: {str(exc)[:200]}"
    seconds = time.perf_counter() - t0
    peak = 0.0
    if measure_memory:
        peak = tracemalloc.get_traced_memory()[1] / 1e6
        tracemalloc.stop()
    return rc, tb, out.getvalue(), err.getvalue(), seconds, peak


def _record(case: Case, result) -> Case:
    rc, tb, out, err, seconds, peak = result
    case.rc, case.traceback, case.seconds, case.peak_mb = rc, tb, seconds, peak
    case.err_lines = len(err.splitlines())
    case.err_bytes = len(err.encode("utf-8", "replace"))
    case.out_bytes = len(out.encode("utf-8", "replace"))
    case.message = (err.strip().splitlines() or [""])[0][:200]
    return case


def config_cases(n: int, seed: int, work: Path, measure_memory: bool = True) -> list[Case]:
    rng = random.Random(seed)
    cases = []
    for i in range(n):
        name, content, what = mutated_config(rng)
        d = work / f"config-{i}"
        shutil.copytree(CONFIG, d)
        target = d / name
        if isinstance(content, bytes):
            target.write_bytes(content)
        else:
            target.write_text(content, encoding="utf-8")
        size = target.stat().st_size
        if name == "simulator.yaml":   # it names its companions (default: the shipped ones)
            argv = ["simulate", "--config", str(target), "--export", str(d / "out.csv"),
                    "--days", "0.0007"]
            command = "simulate"
        elif name == "plant.yaml" and rng.random() < 0.5:
            argv, command = ["point", "--config", str(target), "--json"], "point"
        else:
            argv, command = ["check-config", "--config", str(d / "gateway.yaml")], "check-config"
        case = Case("config", i, name, what, command, size)
        cases.append(_record(case, _run(argv, measure_memory)))
        shutil.rmtree(d, ignore_errors=True)
    return cases


def base_csv(work: Path, minutes: int = 45) -> Path:
    """A clean commissioning export (the simulator's own) to mutate."""
    from simulator.config import load_simulator_config
    from simulator.export import export_history

    cfg = load_simulator_config()
    clean = cfg.replace(fouling=dataclasses.replace(
        cfg.fouling, R_th_f_initial_K_per_kW=0.0, R_th_f_inf_K_per_kW=0.0, CF_dp_f_initial=1.0,
        CF_dp_f_inf=1.0), faults=())
    path = work / "base.csv"
    with contextlib.redirect_stdout(io.StringIO()):
        export_history(minutes / 1440, path, cfg=clean)
    return path


def csv_cases(n: int, seed: int, work: Path, measure_memory: bool = False) -> list[Case]:
    rng = random.Random(seed + 1)
    base = base_csv(work)
    text = base.read_text(encoding="utf-8")
    cases = []
    for i in range(n):
        content = mutate_csv(text, rng)
        path = work / f"history-{i}.csv"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content, encoding="utf-8")
        argv = ["calibrate", "fouling", str(path), "--window", "2024-03-01T00:00/2024-03-02T00:00",
                "--state-dir", str(work / f"state-{i}"), "--json"]
        case = Case("csv", i, path.name, "csv mutation", "calibrate fouling", path.stat().st_size)
        cases.append(_record(case, _run(argv, measure_memory)))
        path.unlink()
        shutil.rmtree(work / f"state-{i}", ignore_errors=True)
    return cases


def run_campaign(n_configs: int = 300, n_csvs: int = 200, seed: int = 1,
                 measure_memory: bool = True) -> dict:
    """Run the campaign; a JSON-ready summary with every failing case listed."""
    import logging
    import resource

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hp-edge-campaign-") as tmp:
        work = Path(tmp)
        # warm-up: the imports (CoolProp, SciPy, pandas) are not a case's memory
        for argv in (["check-config", "--config", str(CONFIG / "gateway.yaml")],
                     ["point", "--config", str(CONFIG / "plant.yaml"), "--json"],
                     ["simulate", "--export", str(work / "warm.csv"), "--days", "0.0007"]):
            _run(argv, measure_memory=False)
        configs = config_cases(n_configs, seed, work, measure_memory)
        csvs = csv_cases(n_csvs, seed, work, measure_memory=False)
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def summary(cases: list[Case]) -> dict:
        rcs: dict[str, int] = {}
        for c in cases:
            rcs[str(c.rc)] = rcs.get(str(c.rc), 0) + 1
        small = [c.peak_mb for c in cases if c.size <= 64 * 1024]
        return {"cases": len(cases), "tracebacks": sum(c.traceback is not None for c in cases),
                "exit_codes": rcs, "failing": sum(not c.ok for c in cases),
                "max_error_lines": max((c.err_lines for c in cases), default=0),
                "max_error_bytes": max((c.err_bytes for c in cases), default=0),
                "max_seconds": round(max((c.seconds for c in cases), default=0.0), 3),
                "max_peak_mb_le_64kb": round(max(small, default=0.0), 2),
                "max_peak_mb": round(max((c.peak_mb for c in cases), default=0.0), 2),
                "bad_cases": [dataclasses.asdict(c) for c in cases if not c.ok][:20]}

    return {"seed": seed, "configs": summary(configs), "csvs": summary(csvs),
            "seconds": round(time.perf_counter() - t0, 1),
            "process_max_rss_mb": {"before": round(rss0, 1), "after": round(rss1, 1)},
            "targets": TARGETS}


def bench_inputs() -> dict:
    """`hp-edge bench --only inputs`: the full campaign (300 configs, 200 CSVs)."""
    return run_campaign()


if __name__ == "__main__":   # pragma: no cover
    print(json.dumps(run_campaign(), indent=2))
