"""hp-edge fleet replay: many plants' replays on a Dask cluster (issue 12; edge/fleet.py)."""
from __future__ import annotations

import os
import sys


def register(sub) -> None:
    fl = sub.add_parser("fleet", help="replay many plants on a Dask cluster (needs the [fleet] extra)",
                        description="Fleet commands (issue 12). They import dask only here.")
    fsub = fl.add_subparsers(dest="fleet_command", metavar="SUBCOMMAND")
    fsub.required = True
    rp = fsub.add_parser(
        "replay", help="replay every plant of PLANTS.yaml; one table across plants",
        description="Replay every plant listed in PLANTS.yaml (each with its plant.yaml, history CSV "
                    "and optional state directory) as one task per plant on a Dask distributed "
                    "cluster; writes DIR/<name>/ (as hp-edge replay) and DIR/fleet.csv, "
                    "DIR/fleet.txt. A plant that fails is reported with its reason; the others go on.")
    rp.add_argument("plants", help="PLANTS.yaml (see edge/fleet.py or the README)")
    rp.add_argument("--out", required=True, help="output directory")
    rp.add_argument("--scheduler", default="local",
                    help="'local' (default): an embedded LocalCluster on 127.0.0.1; or a running "
                         "scheduler's address, e.g. tcp://host:8786 (the workers must read the "
                         "plants' files: a shared file system)")
    rp.add_argument("--workers", type=int, default=None, metavar="N",
                    help="LocalCluster worker processes (default: the CPUs, at most the plants); "
                         "with a scheduler address the cluster's own workers are used")
    rp.add_argument("--no-workers-timeout", type=float, default=None, metavar="SECONDS",
                    help="give up the plants still waiting once the scheduler has had no worker for "
                         "this long (default 300): they are reported as not replayed, with the reason")
    rp.set_defaults(func=cmd_fleet_replay)


class _OneLine:
    """A logging handler for distributed's client-side loggers: WARNING and above as one line on
    stderr, without tracebacks (a lost scheduler logs its reconnect's traceback at ERROR; the fleet
    reports what it means in the plants' reasons)."""

    def __init__(self):
        import logging

        class H(logging.Handler):
            def emit(self, record):
                try:
                    msg = record.getMessage().strip().splitlines()
                except Exception:       # noqa: BLE001 - a log line must never stop the fleet
                    return
                if msg:
                    print(f"hp-edge fleet replay: dask {record.levelname.lower()}: {msg[0]}", file=sys.stderr)
        self.handler = H(logging.WARNING)
        self.logging = logging

    def __enter__(self):
        try:        # distributed configures its loggers (own handlers) when it is imported
            import distributed  # noqa: F401
        except ImportError:
            pass    # Cluster says what is missing
        names = ["distributed"] + [n for n in self.logging.root.manager.loggerDict if n.startswith("distributed.")]
        self.saved = []
        for name in names:
            lg = self.logging.getLogger(name)
            self.saved.append((lg, lg.handlers[:], lg.propagate))
            lg.handlers[:] = [self.handler] if name == "distributed" else []
            lg.propagate = name != "distributed"
        return self

    def __exit__(self, *exc):
        for lg, handlers, propagate in self.saved:
            lg.handlers[:], lg.propagate = handlers, propagate


def cmd_fleet_replay(args) -> int:
    from edge.fleet import Cluster, FleetError, FleetInterrupted, load_plants, run_fleet
    from edge.commands.analysis_cmds import Progress, _fail
    from edge.procsignals import term_as_interrupt
    got: list = []
    try:
        entries = load_plants(args.plants)
        if args.workers is not None and not 1 <= args.workers <= 256:
            raise FleetError([f"--workers: expected 1..256, got {args.workers}"])
        sched = args.scheduler
        if sched != "local" and not (sched.startswith("tcp://") or sched.startswith("tls://")):
            raise FleetError([f"--scheduler: expected 'local' or an address such as tcp://host:8786, "
                              f"got {sched!r}"])
        wait = args.no_workers_timeout
        if wait is not None and not (wait > 0 and wait < float("inf")):
            raise FleetError([f"--no-workers-timeout: expected seconds > 0, got {wait:g}"])
        n = args.workers or max(1, min(os.cpu_count() or 1, len(entries)))
        with _OneLine(), term_as_interrupt() as got:
            cluster = Cluster(sched, n, **({} if wait is None else {"no_workers_s": wait}))
            with cluster as client:
                table = run_fleet(entries, args.out, executor=client, progress=Progress("plants"),
                                  stalled=cluster.stalled)
    except FleetError as exc:
        return _fail("fleet replay", exc)
    except FleetInterrupted as exc:
        done = int((exc.table["status"] == "ok").sum())
        how = "stopped by SIGTERM" if got else "interrupted"
        print(f"hp-edge fleet replay: {how}; wrote {os.path.join(args.out, 'fleet.csv')} and "
              f"{os.path.join(args.out, 'fleet.txt')}: {done} of {len(exc.table)} plants replayed, the others "
              f"marked not replayed", file=sys.stderr)
        return 143 if got else 130
    except OSError as exc:
        return _fail("fleet replay", exc)
    from edge.fleet import fleet_text
    print(fleet_text(table))
    failed = int((table["status"] != "ok").sum())
    print(f"wrote {os.path.join(args.out, 'fleet.csv')}, {os.path.join(args.out, 'fleet.txt')} and a "
          f"replay directory for each of the {len(table) - failed} plants replayed")
    return 1 if failed == len(table) else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(1)
