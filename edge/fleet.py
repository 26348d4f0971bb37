"""Fleet replay (issue 12): many plants' histories through the same Executor seam as one replay,
on a Dask distributed cluster.

PLANTS.yaml (read by edge.yamlfile's strict loader; problems name the file, line, plant and key)::

    plants:
      - name: cph-1                      # output directory DIR/cph-1 (letters, digits, . _ -)
        plant: cph-1/plant.yaml          # paths relative to PLANTS.yaml
        history: cph-1/history.csv
        state: cph-1/state               # optional: commissioning from the plant's state directory
        initial_window: 2024-03-01T00:00/2024-03-01T01:30   # optional (else the first 90 minutes)
        window_hours: 2                  # optional

PLANTS.yaml itself is checked up front (unknown or missing keys, duplicate names: exit 2 and
nothing runs); each plant's files are read by its task, so a plant whose history or plant.yaml is
missing or broken fails alone (fleet.csv status ``failed`` with the reason) and the others go on.

Each plant runs as one task (``replay_plant``) in a worker: it reads its own plant.yaml and
history, replays sequentially (one core per plant: plants are the parallelism), writes DIR/<name>/
(the same files as ``hp-edge replay``) and returns its line of the fleet table; the client writes
the table across plants, DIR/fleet.csv and DIR/fleet.txt. Paths (the plants' files and DIR) must
be reachable by the workers: always with the embedded LocalCluster, on a shared file system with a
remote scheduler. (Until stop 32 the task returned the whole ReplayResult and the client wrote
every plant's directory: a plant-year's result is ~100 MB and its samples.csv ~6 s of writing, one
plant after the other on the client — ~10 minutes for 100 plant-years, whatever the workers.) A
plant that fails is reported with its reason (fleet.csv status/reason) and the others go on.

``executor``: anything with concurrent.futures' ``submit`` whose futures have ``result()``: a
``distributed.Client`` (the cluster engine), or a stdlib executor. ``dask``/``distributed`` are
imported only by ``cluster()``, i.e. only by ``hp-edge fleet``.
"""
from __future__ import annotations

import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
PLANT_KEYS = ("name", "plant", "history", "state", "initial_window", "window_hours")
TREND_DAYS = 7.0              # R_th,f rate: linear fit over the last this many days since the last CIP
FLEET_COLUMNS = (
    "name", "status", "reason", "period_start", "period_end", "days", "windows", "windows_ok",
    "R_th_f_now_K_per_kW", "R_th_f_rate_K_per_kW_per_day", "R_th_f_rate_basis", "R_th_f_share_pct",
    "CF_dp_f_now", "cips", "cip_removed_pct_mean", "cip_removed_pct", "dCOP_setpoint_pct",
    "dCOP_setpoint_confident_pct", "advice_confident_share", "p_m_sp_actual_barg", "p_m_sp_model_opt_barg",
    "fouling_cost_eur_per_day", "replay_s", "out_dir")


class FleetError(ValueError):
    """PLANTS.yaml is invalid (``problems``: one line each) or the cluster cannot be reached."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


@dataclass(frozen=True)
class PlantEntry:
    name: str
    plant: str                     # absolute paths
    history: str
    state: str | None = None
    initial_window: str | None = None
    window_hours: float | None = None


@dataclass
class PlantOutcome:
    """What one plant's task returns (picklable)."""
    name: str
    ok: bool
    reason: str = ""
    result: object = None          # model.analysis.replay.ReplayResult (None once written)
    reading: list = field(default_factory=list)    # what reading the history skipped
    seconds: float = math.nan      # the replay's (reading the files included, writing not)
    row: dict | None = None        # its fleet-table line, once the task wrote its directory


# --------------------------------------------------------------------------------------------------
# PLANTS.yaml
# --------------------------------------------------------------------------------------------------
def load_plants(path: str | Path) -> list[PlantEntry]:
    """The plants of PLANTS.yaml; FleetError with every problem (file, line, plant, key)."""
    from edge.yamlfile import Problems, Section, display_path, key_line, load_yaml
    path = Path(path)
    file = display_path(path)
    p = Problems()
    data = load_yaml(p, path, file)
    if p.lines:
        raise FleetError(p.lines)
    top = Section(p, file, None, data)
    if not top.mapping():
        raise FleetError(p.lines)
    top.keys(("plants",), required=("plants",))
    plants = data.get("plants") if isinstance(data, dict) else None
    base = path.resolve().parent
    out: list[PlantEntry] = []
    if "plants" in data and not (isinstance(plants, list) and plants):
        p.add(file, None, "plants", "expected a non-empty list of plants", line=key_line(data, "plants"))
    seen: dict[str, int] = {}
    for i, item in enumerate(plants if isinstance(plants, list) else []):
        name_hint = item.get("name") if isinstance(item, dict) and isinstance(item.get("name"), str) else None
        where = f"plant {i + 1}" + (f" '{name_hint}'" if name_hint else "")
        sec = Section(p, file, where, item)
        if not isinstance(item, dict):
            p.add(file, where, None, f"expected a mapping with keys {', '.join(PLANT_KEYS)}")
            continue
        n0 = len(p.lines)
        sec.keys(PLANT_KEYS, required=("name", "plant", "history"))
        name = sec.string("name") if "name" in item else None
        if name is not None and not NAME.match(name):
            sec.problem("name", f"{name!r} is not a usable directory name (letters, digits, '.', '_', "
                                "'-'; at most 64)")
            name = None
        if name is not None:
            if name in seen:
                sec.problem("name", f"{name!r} is used twice (first by plant {seen[name]})")
            seen.setdefault(name, i + 1)
        # the files are read by the plant's task (in a worker, which may see another file system
        # than this client): a missing one fails that plant with its reason, not the whole fleet
        plant = sec.path("plant", base) if "plant" in item else None
        hist = sec.path("history", base) if "history" in item else None
        state = None
        if "state" in item and item["state"] is not None:
            state = sec.path("state", base)
            if state is not None and not state.is_dir():
                sec.problem("state", f"not a directory: {display_path(state)}")
                state = None
        iw = None
        if "initial_window" in item:
            iw = sec.string("initial_window")
            if iw is not None and (len(iw.split("/")) != 2 or not all(x.strip() for x in iw.split("/"))):
                sec.problem("initial_window", f"expected START/END (ISO 8601), got {iw!r}")
                iw = None
        wh = sec.number("window_hours", positive=True, default=None) if "window_hours" in item else None
        if len(p.lines) == n0 and name and plant and hist:
            out.append(PlantEntry(name, str(plant), str(hist), str(state) if state else None, iw, wh))
    if p.lines:
        raise FleetError(p.lines)
    return out


# --------------------------------------------------------------------------------------------------
# one plant (runs in a worker)
# --------------------------------------------------------------------------------------------------
def replay_plant(entry: PlantEntry, out_dir: str | None = None) -> PlantOutcome:
    """Read one plant's plant.yaml and history, replay it (sequentially, in this worker) and return
    the result, or the reason it failed. With ``out_dir`` the task writes the plant's directory
    there itself (``write_plant_dir``) and returns its fleet-table line instead of the result.
    Never raises: one plant cannot stop the fleet."""
    from model.analysis.replay import replay_memory
    t0 = time.perf_counter()
    try:
        with replay_memory():             # reading the history too, not only the replay
            o = _replay_plant(entry, t0)
        return o if out_dir is None else write_plant_dir(entry, o, Path(out_dir))
    except Exception as exc:       # noqa: BLE001 - the fleet's boundary: report it, go on
        return PlantOutcome(entry.name, False, f"{type(exc).__name__}: {exc}",
                            seconds=time.perf_counter() - t0)


def write_plant_dir(e: PlantEntry, o: PlantOutcome, d: Path) -> PlantOutcome:
    """Write a replayed plant's directory ``d`` (``hp-edge replay``'s files) and return the outcome
    with its fleet-table line and without the result; a directory that cannot be written fails
    the plant with the reason."""
    from edge.replaydir import write_replay_dir
    if o.ok:
        try:
            write_replay_dir(o.result, d, {"plant": e.plant, "history": e.history, "fleet": True},
                             "\n".join(o.reading))
        except OSError as exc:
            o = PlantOutcome(e.name, False, f"writing {d}: {exc.strerror or exc}", seconds=o.seconds)
    return PlantOutcome(o.name, o.ok, o.reason, reading=o.reading, seconds=o.seconds, row=plant_row(e, o, d))


def _replay_plant(entry: PlantEntry, t0: float) -> PlantOutcome:
    import pandas as pd
    from edge.io.history import HistoryError, read_history
    from edge.plantfile import PlantFileError, load_plant
    from edge.statefiles import COMPRESSORS, DP_CLEAN, INITIAL_CALIBRATION, StateError, read_state
    from model.calibration import CalibrationError
    from model.dpfit import DpFitError
    from model.analysis.replay import ReplayError, ReplaySettings, replay
    try:
        params = load_plant(entry.plant)
        h = read_history(entry.history)
        settings = ReplaySettings.from_config(params.extra, window_hours=entry.window_hours)
        iw = None
        if entry.initial_window:
            a, b = (pd.Timestamp(x.strip()) for x in entry.initial_window.split("/"))
            iw = (a, b)
        commissioning = None
        if entry.state:
            docs = {k: read_state(n, entry.state) for k, n in
                    (("initial", INITIAL_CALIBRATION), ("dp_clean", DP_CLEAN), ("compressors", COMPRESSORS))}
            if docs["initial"] is not None and docs["dp_clean"] is not None:
                commissioning = docs
        res = replay(h.frame, params, settings, initial_window=iw, commissioning=commissioning)
    except (PlantFileError, HistoryError, ReplayError, CalibrationError, DpFitError, StateError,
            ValueError, OSError) as exc:
        return PlantOutcome(entry.name, False, _one_line(exc), seconds=time.perf_counter() - t0)
    return PlantOutcome(entry.name, True, result=res, reading=h.report_lines(entry.history),
                        seconds=time.perf_counter() - t0)


def _one_line(exc: Exception) -> str:
    lines = [ln for ln in str(exc).splitlines() if ln.strip()] or [type(exc).__name__]
    return lines[0] + (f" (+{len(lines) - 1} more)" if len(lines) > 1 else "")


# --------------------------------------------------------------------------------------------------
# the fleet
# --------------------------------------------------------------------------------------------------
def run_fleet(entries: list[PlantEntry], out: str | Path, executor=None, progress=None,
              stalled=None) -> "pd.DataFrame":
    """Replay every plant through ``executor`` (None: one after the other, here), write each
    plant's directory and the fleet table (DIR/fleet.csv, DIR/fleet.txt); return the table.
    ``stalled``: see ``await_all``; the plants still waiting when it gives a reason are cancelled
    and reported as not replayed, with that reason."""
    import pandas as pd
    out = Path(out).absolute()         # the workers write there (their own working directory differs)
    out.mkdir(parents=True, exist_ok=True)
    if executor is None:
        outcomes = (replay_plant(e, str(out / e.name)) for e in entries)
    else:
        futures = {i: executor.submit(replay_plant, entries[i], str(out / entries[i].name))
                   for i in submission_order(entries)}
        interrupted = False
        try:
            why = await_all(futures.values(), progress, stalled=stalled)
        except KeyboardInterrupt:       # Ctrl-C (or the command's SIGTERM): the table of what finished
            why, interrupted = INTERRUPTED, True
        if why is not None:
            for f in futures.values():
                if not f.done():
                    f.cancel()
        outcomes = (_outcome(futures[i], e, why) for i, e in enumerate(entries))
    rows = []
    for k, (e, o) in enumerate(zip(entries, outcomes), start=1):
        # the task's line (it wrote the directory); a task that died has none
        rows.append(o.row if o.row is not None else plant_row(e, o, out / e.name))
        if progress is not None and executor is None:
            progress(k, len(entries))
    table = pd.DataFrame(rows, columns=list(FLEET_COLUMNS))
    tmp = out / ".fleet.csv.tmp"
    table.to_csv(tmp, index=False, float_format="%.6g")
    tmp.replace(out / "fleet.csv")
    (out / "fleet.txt").write_text(fleet_text(table) + "\n", encoding="utf-8")
    if executor is not None and interrupted:
        raise FleetInterrupted(table)
    return table


INTERRUPTED = "the fleet command was stopped (Ctrl-C or SIGTERM) before the plant's task ended"


class FleetInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM, see ``hp-edge fleet replay``) during ``run_fleet``: the table (every plant
    not finished: INTERRUPTED) is written."""

    def __init__(self, table) -> None:
        super().__init__("interrupted")
        self.table = table


def submission_order(entries: list[PlantEntry]) -> list[int]:
    """The order in which the plants are handed to the executor: the longest histories first (by
    file size; equal sizes in PLANTS.yaml's order). A plant's replay takes about the time of its
    windows, and a worker that takes the longest plant last keeps the others waiting: longest first
    ends within 4/3 of the best possible schedule (Graham), any order within 2. Histories of nearly
    the same size are ordered by a few bytes: as good as any order. A history that cannot be read
    counts as empty (its task fails at once)."""
    import os
    sizes = []
    for e in entries:
        try:
            sizes.append(os.stat(e.history).st_size)
        except OSError:
            sizes.append(0)
    return sorted(range(len(entries)), key=lambda i: (-sizes[i], i))


AWAIT_POLL_S = 0.2          # how often await_all looks at the futures not done yet
STALL_CHECK_S = 2.0         # how often it asks ``stalled`` (a Dask client: one scheduler query)


def await_all(futures, progress=None, poll_s: float | None = None, stalled=None) -> str | None:
    """Wait until every future is done (a result or an exception), calling ``progress(done,
    total)`` as each finishes, in whatever order they finish: the plants go to the cluster longest
    first, so counting them in PLANTS.yaml's order would show a long run standing still (its first
    plant may be the last to finish). Looks at ``done()`` every ``poll_s`` — any executor's futures
    have it (concurrent.futures', Dask's). ``stalled``: a callable asked every STALL_CHECK_S while
    futures are pending; when it returns a reason (e.g. ``Cluster.stalled``: the scheduler has had
    no worker for a while, so the tasks would wait for ever) the wait ends and that reason is
    returned; None when every future is done."""
    poll_s = AWAIT_POLL_S if poll_s is None else poll_s
    pending = list(futures)
    total, finished = len(pending), 0
    if progress is not None:
        progress(0, total)
    next_check = time.monotonic() + STALL_CHECK_S
    while pending:
        still = [f for f in pending if not f.done()]
        if len(still) < len(pending):
            finished += len(pending) - len(still)
            pending = still
            if progress is not None:
                progress(finished, total)
        elif pending:
            if stalled is not None and time.monotonic() >= next_check:
                why = stalled()
                if why is not None:
                    return why
                next_check = time.monotonic() + STALL_CHECK_S
            time.sleep(poll_s)
    return None


LOST = "scheduler-connection-lost"      # distributed's reason for the futures of a lost scheduler


def _outcome(future, entry: PlantEntry, stalled: str | None = None) -> PlantOutcome:
    """A future's outcome; a task that died (worker lost, cancelled) is a failed plant too:
    ``stalled`` (``await_all``'s reason) for a task still waiting when the wait ended, the
    scheduler's lost connection for the tasks distributed cancelled then."""
    if stalled is not None and (future.cancelled() or not future.done()):
        return PlantOutcome(entry.name, False, f"not replayed: {stalled}")
    try:
        return future.result()
    except Exception as exc:       # noqa: BLE001 - e.g. distributed's KilledWorker: report, go on
        if getattr(exc, "reason", None) == LOST:
            return PlantOutcome(entry.name, False, "not replayed: the connection to the scheduler was lost "
                                                   "before the plant's task ended")
        return PlantOutcome(entry.name, False, f"task failed: {type(exc).__name__}: {_one_line(exc)}")


def plant_row(e: PlantEntry, o: PlantOutcome, out_dir: Path) -> dict:
    """One plant's line of the fleet table (see FLEET_COLUMNS)."""
    import numpy as np
    import pandas as pd
    row = dict.fromkeys(FLEET_COLUMNS, math.nan)
    row.update(name=e.name, status="ok" if o.ok else "failed", reason=o.reason, R_th_f_rate_basis="",
               cip_removed_pct="", replay_s=round(o.seconds, 2) if math.isfinite(o.seconds) else math.nan,
               out_dir=str(out_dir) if o.ok else "")
    if not o.ok:
        return row
    r = o.result
    w = r.windows
    row.update(period_start=r.meta.get("period_start", ""), period_end=r.meta.get("period_end", ""),
               windows=int(len(w)))
    t0, t1 = pd.Timestamp(row["period_start"]), pd.Timestamp(row["period_end"])
    row["days"] = round((t1 - t0).total_seconds() / 86400.0, 3)
    ok = w[w["status"] == "ok"]
    row["windows_ok"] = int(len(ok))
    if not len(ok):
        row["reason"] = "no window calibrated"
        return row
    t_end = pd.to_datetime(ok["window_end"], utc=True)
    R = ok["R_th_f_K_per_kW"].to_numpy(dtype=float)
    last_day = (t_end >= t_end.iloc[-1] - pd.Timedelta(days=1)).to_numpy()
    row["R_th_f_now_K_per_kW"] = float(np.nanmedian(R[last_day]))
    row["R_th_f_share_pct"] = float(np.nanmedian(ok["R_th_f_share_pct"].to_numpy(dtype=float)[last_day]))
    row["CF_dp_f_now"] = float(np.nanmedian(ok["CF_dp_f"].to_numpy(dtype=float)[last_day]))
    # the rate: a straight line through the windows of the last TREND_DAYS since the last CIP
    since = t_end.iloc[0] - pd.Timedelta(seconds=1)
    if len(r.cips):
        since = max(since, pd.Timestamp(r.cips["cip_end"].iloc[-1]))
    start = max(since, t_end.iloc[-1] - pd.Timedelta(days=TREND_DAYS))
    sel = (t_end > start).to_numpy() & np.isfinite(R)
    x = (t_end[sel] - t_end[sel].iloc[0]).dt.total_seconds().to_numpy() / 86400.0 if sel.sum() else np.array([])
    if sel.sum() >= 6 and np.ptp(x) >= 0.5:
        slope = float(np.polyfit(x, R[sel], 1)[0])
        row["R_th_f_rate_K_per_kW_per_day"] = slope
        row["R_th_f_rate_basis"] = (f"linear fit of {int(sel.sum())} windows over the last {np.ptp(x):.1f} d"
                                    f"{' since the last CIP' if len(r.cips) else ''} (the forecast's "
                                    "rate: the plant's forecast.csv)")
    else:
        row["R_th_f_rate_basis"] = "too few windows since the last CIP for a rate"
    if len(r.cips):
        rem = r.cips["R_th_f_removed_pct"].to_numpy(dtype=float)
        row["cips"] = int(len(r.cips))
        row["cip_removed_pct_mean"] = float(np.nanmean(rem)) if np.isfinite(rem).any() else math.nan
        row["cip_removed_pct"] = " ".join(f"{v:.1f}" for v in rem)
    else:
        row["cips"] = 0
    recent = ok[last_day]
    row["dCOP_setpoint_pct"] = float(np.nanmean(recent["dCOP_model_opt_pct"].to_numpy(dtype=float)))
    conf = recent["advice_confident"].astype(bool).to_numpy()
    row["advice_confident_share"] = float(conf.mean())
    row["dCOP_setpoint_confident_pct"] = float(np.nanmean(recent["dCOP_opt_pct"].to_numpy(dtype=float)[conf])) \
        if conf.any() else math.nan
    row["p_m_sp_actual_barg"] = float(np.nanmedian(recent["p_m_sp_actual_barg"].to_numpy(dtype=float)))
    row["p_m_sp_model_opt_barg"] = float(np.nanmedian(recent["p_m_sp_model_opt_barg"].to_numpy(dtype=float)))
    for col in ("fouling_cost_eur_per_day", "cost_eur_per_day"):   # once replay prices fouling
        if col in ok.columns:
            row["fouling_cost_eur_per_day"] = float(np.nanmedian(ok[col].to_numpy(dtype=float)[last_day]))
            break
    return row


def fleet_text(table) -> str:
    """The fleet table for a terminal (one line per plant) with the notes that explain it."""
    L = [f"{'plant':<16} {'status':<7} {'period':<23} {'R_th,f now':>10} {'rate/day':>9} {'CIPs':>4} "
         f"{'removed':>8} {'dCOP sp':>8} {'conf':>5} {'cost/day':>8}",
         f"{'':<16} {'':<7} {'':<23} {'e-3 K/kW':>10} {'e-3K/kW':>9} {'':>4} {'%':>8} {'%':>8} {'%':>5} {'EUR':>8}"]

    def f(v, fmt):
        return format(v, fmt) if isinstance(v, (int, float)) and math.isfinite(v) else "-"
    for _, r in table.iterrows():
        if r["status"] != "ok":
            L.append(f"{r['name']:<16} {'FAILED':<7} {r['reason']}")
            continue
        period = f"{str(r['period_start'])[:10]}..{str(r['period_end'])[:10]}"
        L.append(f"{r['name']:<16} {'ok':<7} {period:<23} {f(1e3 * r['R_th_f_now_K_per_kW'], '10.3f')} "
                 f"{f(1e3 * r['R_th_f_rate_K_per_kW_per_day'], '9.4f')} {f(r['cips'], '4.0f')} "
                 f"{f(r['cip_removed_pct_mean'], '8.1f')} {f(r['dCOP_setpoint_pct'], '8.2f')} "
                 f"{f(100 * r['advice_confident_share'], '5.0f')} {f(r['fouling_cost_eur_per_day'], '8.1f')}")
    n_fail = int((table["status"] != "ok").sum())
    L.append("")
    L.append(f"{len(table)} plants, {len(table) - n_fail} replayed, {n_fail} failed")
    L.append("R_th,f now: median of the last day's windows; rate: a linear fit of the last "
             f"{TREND_DAYS:g} days' windows since the last CIP (the forecast's rate is in each plant's "
             "forecast.csv); "
             "removed: mean share of R_th,f each CIP removed; dCOP sp: the COP gain the model optimum "
             "offers over the actual set point (last day's mean; conf: share of those windows whose "
             "advice is confident); cost/day: the cost of fouling against a clean evaporator (median of the "
             "last day's windows)")
    return "\n".join(L)


# --------------------------------------------------------------------------------------------------
# the cluster
# --------------------------------------------------------------------------------------------------
# the embedded cluster's workers. distributed's nanny starts every worker with
# MALLOC_TRIM_THRESHOLD_=65536 (distributed.nanny.pre-spawn-environ: give freed memory back to the
# OS at once, for workers that hold data). A replay allocates and frees numpy arrays of a few
# hundred kB all the time: with that setting glibc returns them to the OS and takes them back again
# page by page (a 10-day replay: 4.6x the page faults, 0.3 -> 0.8 s of system time), and two such
# workers on two cores slow each other (the kernel zeroes every page afresh). Unset here, glibc's
# own threshold applies, as in ``hp-edge replay``. The statistical profiler (a thread sampling the
# task's stack every 10 ms) serves the dashboard, which the embedded cluster does not start; the
# event loops' health tick (20 ms) and the memory monitor (100 ms) every second instead: idle, the
# cluster's three processes then take 1.4 % of a core instead of 3.5 % (measured on 2 cores, where
# every such wake-up is taken from a worker).
LOCAL_WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                       "distributed.worker.profile.enabled": False,
                       "distributed.admin.tick.interval": "1s",
                       "distributed.worker.memory.monitor-interval": "1s"}


NO_WORKERS_S = 300.0        # a scheduler without workers this long: the plants waiting are given up


class Cluster:
    """A Dask distributed Client on an embedded LocalCluster (``scheduler='local'``: processes on
    127.0.0.1, no dashboard, ``LOCAL_WORKER_CONFIG``) or on a running scheduler's address; closes
    what it started."""

    def __init__(self, scheduler: str = "local", workers: int = 2, timeout_s: float = 60.0,
                 no_workers_s: float = NO_WORKERS_S) -> None:
        self.scheduler, self.no_workers_s = scheduler, float(no_workers_s)
        self._workers_seen = time.monotonic()
        try:
            from distributed import Client, LocalCluster
        except ImportError as exc:
            raise FleetError([f"the fleet command needs dask[distributed]: pip install 'hp-edge[fleet]' "
                              f"({exc})"]) from None
        self.local = None
        try:
            if scheduler == "local":
                import dask

                from edge.procsignals import ignored
                # SIGINT ignored while the cluster starts: its worker processes inherit that and
                # never see a terminal's Ctrl-C (they died with a traceback each, their nannies
                # restarted them, and the shutdown could hang); only this process takes it, and
                # run_fleet writes the table of what finished (a Ctrl-C in these seconds is lost)
                with dask.config.set(LOCAL_WORKER_CONFIG), ignored():
                    self.local = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                              host="127.0.0.1", scheduler_port=0, dashboard_address=None,
                                              silence_logs=40)
                self.client = Client(self.local, timeout=timeout_s)
                self._pin()
            else:
                self.client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError) as exc:
            if self.local is not None:
                self.local.close()
            raise FleetError([f"scheduler {scheduler}: cannot connect ({exc})"]) from None
        except KeyboardInterrupt:       # Ctrl-C as the client connects: close what was started
            if self.local is not None:
                self.local.close()
            raise
        except (TypeError, ValueError) as exc:
            # e.g. tls:// without the client's TLS files in Dask's configuration: distributed raises
            # TypeError("TLS expects a `ssl_context` argument ...") from deep in its connector
            if self.local is not None:
                self.local.close()
            if scheduler.startswith("tls://") and "TLS" in str(exc):
                why = ("no TLS settings for the client: Dask's configuration needs "
                       "distributed.comm.tls.ca-file, .client.cert and .client.key")
            else:
                why = _one_line(exc)
            raise FleetError([f"scheduler {scheduler}: cannot connect ({why})"]) from None

    def stalled(self) -> str | None:
        """``await_all``'s ``stalled``: a reason once the scheduler has had no worker for
        ``no_workers_s`` (its tasks would wait for ever: a cluster whose workers all died or never
        came); None while it has workers, or has had none for less. A scheduler that does not
        answer counts as having none (its lost connection cancels the tasks anyway)."""
        try:
            n = int(self.client.scheduler_info(n_workers=0).get("n_workers", 0))
        except Exception:       # noqa: BLE001 - a scheduler that does not answer has no worker for us
            n = 0
        now = time.monotonic()
        if n > 0:
            self._workers_seen = now
            return None
        if now - self._workers_seen >= self.no_workers_s:
            return f"the scheduler {self.scheduler} has had no worker for {self.no_workers_s:g} s"
        return None

    def _pin(self) -> None:
        """Each local worker on its own CPU (``edge.fleet_pin``), where the OS allows it."""
        if not hasattr(os, "sched_getaffinity"):
            return
        from edge.fleet_pin import PinWorkerToCPU
        try:
            self.client.register_plugin(PinWorkerToCPU(sorted(os.sched_getaffinity(0))))
        except Exception as exc:    # noqa: BLE001 - pinning is for speed: the cluster works unpinned
            import warnings
            warnings.warn(f"the local cluster's workers are not pinned to CPUs ({type(exc).__name__}: {exc}); "
                          "they run unpinned, slower where every core is busy", RuntimeWarning, stacklevel=2)

    def __enter__(self):
        return self.client

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.client.close()
        if self.local is not None:
            self.local.close()
