"""hp-edge command line.

Each sub-command lives in a module of ``edge.commands`` that exposes ``register(subparsers)``.
Those modules import nothing heavy at import time (CoolProp takes ~2 s to import), so
``hp-edge --help`` stays fast; the heavy imports happen inside the command functions.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS/OpenMP thread in every hp-edge process unless the environment sets another number (set
# before numpy loads: no command module imports it at import time). The model's matrices are small,
# so more threads spend more CPU spinning than they save; and a replay here gives the numbers a
# Dask worker gives (its nanny sets the same), which the fleet's "identical results" rest on: with
# several threads a large least-squares fit (the surrogate tracker's, thousands of rows late in a
# plant-year) may round differently.
BLAS_THREADS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _name in BLAS_THREADS_ENV:
    os.environ.setdefault(_name, "1")

COMMAND_MODULES = (
    "edge.commands.model_cmds",      # point, bench, fit-compressor
    "edge.commands.sim_cmds",        # simulate
    "edge.commands.analysis_cmds",   # calibrate, optimize, fit-surrogate, replay
    "edge.commands.gateway_cmds",    # run, demo, read, check-config
    "edge.commands.report_cmds",     # report, export-history
    "edge.commands.fleet_cmds",      # fleet replay (dask, imported only when it runs)
)


def version() -> str:
    """The installed distribution's version (pyproject.toml)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version
    try:
        return dist_version("hp-edge")
    except PackageNotFoundError:   # running from a source tree that is not installed
        return "unknown (not installed)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hp-edge",
        description="Modbus TCP edge gateway with a digital twin of a two-stage ammonia heat pump.",
    )
    parser.add_argument("--version", action="version", version=f"hp-edge {version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc = args.func(args)
    except BrokenPipeError:
        # the reader went away (e.g. `hp-edge point | head`): stop quietly, as Unix tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except KeyboardInterrupt:
        # Ctrl-C (SIGINT) in a command without its own handling (the gateway's run and demo have
        # theirs): one line and the shell's code for it, no traceback
        print(f"hp-edge {args.command}: interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
