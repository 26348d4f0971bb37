"""The ``simulate`` command: run the plant simulator (Modbus TCP server) or export a history.

Heavy imports (pymodbus, CoolProp through model/) stay inside the command function.
"""
from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser(
        "simulate", help="run the plant simulator (Modbus TCP PLC) or export a simulated history",
        description="Serve the simulated heat pump PLC on Modbus TCP (every tag of tags.yaml, the "
                    "p_m set point and the advisory block writable, anything else exception 2), "
                    "stepping the hidden plant at --speed x wall time; or, with --export, write "
                    "--days of one-minute history (canonical columns) without a server.")
    p.add_argument("--config", default=None, help="simulator settings (config/simulator.yaml)")
    p.add_argument("--host", default="127.0.0.1", help="listen address (127.0.0.1)")
    p.add_argument("--port", type=int, default=5020, help="listen port (5020; 0 = any free port)")
    p.add_argument("--speed", type=float, default=60.0, help="plant seconds per wall second, 1..3600 (60)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the config's)")
    p.add_argument("--compressors", default=None, metavar="FAMILY",
                   help="the plant's hidden compressor curves: perturbed (plant.yaml's polynomials "
                        "perturbed, the default), nominal (plant.yaml's polynomials) or a family of "
                        "simulator.yaml's compressor_families (ratio_only, speed_peak, low_peak)")
    p.add_argument("--truth-log", default=None, metavar="FILE",
                   help="append the hidden truth (JSON lines) once per plant minute")
    p.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="inject a fault: KIND[:TAG][:key=value,...], e.g. stuck:T_e, slow:delay_s=3, "
                        "frozen:at_h=2,duration_h=0.5 (repeatable)")
    p.add_argument("--duration", type=float, default=0.0,
                   help="stop after this many wall seconds (0 = run until interrupted)")
    p.add_argument("--export", default=None, metavar="CSV", help="write a history CSV instead of serving")
    p.add_argument("--days", type=float, default=30.0, help="plant days to export (30)")
    p.add_argument("--truth", default=None, metavar="CSV", help="with --export: also write the hidden truth")
    p.add_argument("--start-fouled", action="store_true",
                   help="with --export: start from the configured fouling instead of a clean "
                        "evaporator (by default an export begins at commissioning, so that replay's "
                        "default initial window is clean, as commissioning data are)")
    p.set_defaults(func=cmd_simulate)


def _fail(msg: str) -> int:
    from edge.yamlfile import format_problems
    for line in format_problems(msg.splitlines() or [msg]):
        print(f"hp-edge simulate: {line}", file=sys.stderr)
    return 2


def _check_plant_file(path) -> None:
    """plant.yaml through the checker every command uses (edge.plantfile): unknown or duplicate
    keys are refused here too, before the simulated plant is built from the file."""
    from edge.plantfile import check_plant
    from edge.yamlfile import Problems
    from simulator.config import SimConfigError

    p = Problems()
    check_plant(p, path)
    if p.lines:
        raise SimConfigError("\n".join(p.lines))


def cmd_simulate(args) -> int:
    from simulator.config import SimConfigError, load_simulator_config, read_tags
    from simulator.faults import parse_cli_fault
    try:
        cfg = load_simulator_config(args.config)
        if args.seed is not None:
            cfg = cfg.replace(seed=args.seed)
        if args.compressors is not None:
            cfg = cfg.with_compressor_family(args.compressors)
        faults = [parse_cli_fault(f) for f in args.fault]
        _check_plant_file(cfg.plant_file)     # the same strict check as every other command
        served = read_tags(cfg.tags_file)
        for text, f in zip(args.fault, faults):
            if f.tag is not None and f.tag not in served:
                import difflib
                close = difflib.get_close_matches(f.tag, list(served), 1)
                raise SimConfigError(
                    f"--fault {text}: unknown tag {f.tag!r}"
                    + (f" (did you mean {close[0]!r}?)" if close else "")
                    + f"; the simulator serves {', '.join(served)}")
    except SimConfigError as exc:
        return _fail(str(exc))
    if args.export:
        if not args.days > 0:
            return _fail("--days must be > 0")
        import dataclasses
        from simulator.export import export_history
        cfg = cfg.replace(faults=cfg.faults + tuple(
            f for f in faults if f.kind in ("stuck", "out_of_range", "nan", "frozen")))
        if not args.start_fouled:
            cfg = cfg.replace(fouling=dataclasses.replace(
                cfg.fouling, R_th_f_initial_K_per_kW=0.0, CF_dp_f_initial=1.0))
        try:
            res = export_history(args.days, args.export, cfg=cfg, truth_path=args.truth)
        except SimConfigError as exc:
            return _fail(str(exc))
        except OSError as exc:
            return _fail(f"cannot write {args.export}: {exc.strerror or exc}")
        print(json.dumps({"history": args.export, "truth": args.truth, "rows": res.rows,
                          "days": args.days, "seed": cfg.seed,
                          "compressors": cfg.truth.compressor_family, "seconds": round(res.seconds, 2)}))
        return 0
    if not 1.0 <= args.speed <= 3600.0:
        return _fail("--speed must be within 1..3600")
    if not 0 <= args.port <= 65535:
        return _fail("--port must be within 0..65535")
    import asyncio
    return asyncio.run(_serve(cfg, args, faults))


async def _serve(cfg, args, faults) -> int:
    import asyncio
    import signal

    from simulator.config import SimConfigError
    from simulator.server import PlantSimulator
    try:
        sim = PlantSimulator(cfg, host=args.host, port=args.port, speed=args.speed,
                             truth_log=args.truth_log)
    except (SimConfigError, ValueError) as exc:
        return _fail(str(exc))
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    installed = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
            installed.append(sig)
        except (NotImplementedError, RuntimeError):   # not the main thread / platform without it
            pass
    try:
        try:
            await sim.start()
        except OSError as exc:
            return _fail(f"cannot listen on {args.host}:{args.port}: {exc.strerror or exc}")
        except RuntimeError as exc:
            return _fail(str(exc))
        try:
            for f in faults:
                sim.add_fault(f)
        except SimConfigError as exc:
            return _fail(str(exc))
        print(json.dumps({"listening": f"{args.host}:{sim.port}", "speed": sim.speed, "seed": cfg.seed,
                          "start_time": cfg.start_time, "device_id": cfg.device_id,
                          "compressors": cfg.truth.compressor_family,
                          "truth_log": args.truth_log,
                          "faults": [f.kind + (f":{f.tag}" if f.tag else "") for f in faults]}),
              flush=True)
        timeout = args.duration if args.duration > 0 else None
        waiter = asyncio.ensure_future(stop.wait())
        task = sim.loop_task
        done, _ = await asyncio.wait({waiter, task}, timeout=timeout,
                                     return_when=asyncio.FIRST_COMPLETED)
        waiter.cancel()
        if task in done and task.exception() is not None:
            return _fail(f"plant loop failed: {task.exception()}")
        return 0
    finally:
        await sim.stop()
        for sig in installed:
            loop.remove_signal_handler(sig)
