"""Model commands: point, bench, fit-compressor. Heavy imports stay inside the functions."""
from __future__ import annotations

import argparse
import json
import sys

PLANT_HELP = ("plant file (default: config/plant.yaml, else /etc/hp-edge/plant.yaml, else the one "
              "shipped with the package)")


def finite(text: str) -> float:
    """argparse type: a finite number (nan/inf are refused with the flag's name)."""
    import math
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return v


def register(sub) -> None:
    p = sub.add_parser("point", help="solve one operating point of the heat pump model",
                       description="Solve one quasi-steady operating point and print it.")
    p.add_argument("--T-source-in", type=finite, default=25.0, help="source inlet [degC] (25)")
    p.add_argument("--T-source-out", type=finite, default=18.0, help="source outlet [degC] (18)")
    p.add_argument("--T-sink-in", type=finite, default=40.0, help="sink inlet (return) [degC] (40)")
    p.add_argument("--V-source", type=finite, default=192.0, help="source flow [m3/h] (192)")
    p.add_argument("--V-sink", type=finite, default=62.0, help="sink flow [m3/h] (62)")
    p.add_argument("--p-m-sp", type=finite, default=16.0, help="intermediate-pressure set point [bar(g)] (16)")
    p.add_argument("--R-th-f", type=finite, default=None, help="evaporator fouling resistance [K/kW]")
    p.add_argument("--CF-dp-f", type=finite, default=None, help="fouling pressure-drop factor [-]")
    p.add_argument("--config", default=None, help=PLANT_HELP)
    p.add_argument("--backend", choices=("HEOS", "BICUBIC&HEOS"), default=None,
                   help="property backend (default: the plant file's)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(func=cmd_point)

    b = sub.add_parser("bench", help="measure speed and accuracy targets, print JSON",
                       description="Benchmarks of every part; prints one JSON document: the machine "
                                   "(its CPU, the versions, three reference timings) and one key per section.")
    b.add_argument("--config", default=None, help=PLANT_HELP)
    b.add_argument("--only", default="model,simulator,analysis,gateway,inputs",
                   help="comma-separated sections (model,simulator,analysis,gateway,inputs; also "
                        "vcycle: the vectorised solver against the scalar one; advice, closed_loop, "
                        "and cip: the CIP policies on 120 simulated days, about "
                        "15 min; replay: one 30-day replay on one core against the plain path and a "
                        "full-window reference; fleet: 8 plant-months on a LocalCluster with 1 and 2 "
                        "workers (needs the [fleet] extra); plant_year: one plant-year replayed on one core, its "
                        "cost per window by quarter; these run longer)")
    b.add_argument("--grid-levels", type=int, default=3, help="levels per axis of the validation grid (3)")
    b.add_argument("--out", default=None, help="also write the JSON to this file")
    b.set_defaults(func=cmd_bench)

    f = sub.add_parser("fit-compressor", help="fit eta_is/eta_vol polynomials to a manufacturer table",
                       description="Fit the compressor efficiency polynomials (basis 1, pi, n, pi^2, "
                                   "pi*n, n^2; n = speed/nominal) to a table with columns speed_rpm, "
                                   "p_suc_bar, T_suc_C, p_dis_bar, m_dot_kg_s, power_kW "
                                   "(pressures absolute, shaft power).")
    f.add_argument("table", help="manufacturer table (CSV)")
    f.add_argument("--stage", choices=("LS", "HS"), default="LS",
                   help="which compressor's swept volume and nominal speed to use (LS)")
    f.add_argument("--config", default=None, help=PLANT_HELP)
    f.add_argument("--out", default=None, help="write the coefficients (YAML) to this file")
    f.set_defaults(func=cmd_fit_compressor)


def _params(args):
    from edge.config import find_config
    from edge.plantfile import PlantFileError, load_plant
    try:
        return load_plant(find_config("plant.yaml", args.config), getattr(args, "backend", None))
    except PlantFileError as exc:
        from edge.yamlfile import format_problems
        for line in format_problems(str(exc).splitlines()):
            print(f"hp-edge: {line}", file=sys.stderr)
        raise SystemExit(2) from None


def cmd_point(args) -> int:
    from model.batch import inputs_from_row
    from model.cycle import InfeasibleOperation, ModelError, solve
    params = _params(args)
    if args.R_th_f is not None:
        params = params.replace(R_th_f=args.R_th_f * 1e-3)
    if args.CF_dp_f is not None:
        params = params.replace(CF_dp_f=args.CF_dp_f)
    amb = params.ambient_pressure / 1e5
    inp = inputs_from_row({"T_source_in": args.T_source_in, "T_source_out": args.T_source_out,
                           "T_sink_in": args.T_sink_in, "V_source": args.V_source,
                           "V_sink": args.V_sink, "p_m_sp": args.p_m_sp}, amb)
    warning = None
    try:
        res = solve(inp, params)
    except InfeasibleOperation as exc:
        if exc.result is None:
            print(f"hp-edge point: infeasible ({exc.reason}): {exc}", file=sys.stderr)
            return 1
        res, warning = exc.result, f"{exc.reason}: {exc}"
    except ModelError as exc:
        print(f"hp-edge point: no solution ({exc.reason}): {exc}", file=sys.stderr)
        return 1
    d = res.to_dict(params.ambient_pressure)
    d["status"] = "ok" if warning is None else warning.split(":")[0]
    if warning:
        d["warning"] = warning
    if args.json:
        print(json.dumps(d, indent=2))
        return 0
    print(format_point(d, params.backend))
    if warning:
        print(f"\nWARNING: {warning}")
    return 0


def format_point(d: dict, backend: str) -> str:
    rows = [
        ("pressures [bar(a)]", f"p_e {d['p_e_bar']:.3f}   p_m {d['p_m_bar']:.3f} ({d['p_m_barg']:.2f} bar(g))   p_c {d['p_c_bar']:.3f}"),
        ("saturation [degC]", f"T_e {d['T_e_C']:.2f}   T_m {d['T_m_C']:.2f}   T_c {d['T_c_C']:.2f}"),
        ("compressor speeds [rpm]", f"LS {d['N_LS_rpm']:.0f}   HS {d['N_HS_rpm']:.0f}" + ("  (HS at its limit, p_m floats)" if d["hs_saturated"] else "")),
        ("efficiencies [-]", f"eta_is LS {d['eta_is_LS']:.3f} HS {d['eta_is_HS']:.3f}   eta_vol LS {d['eta_vol_LS']:.3f} HS {d['eta_vol_HS']:.3f}"),
        ("mass flows [kg/s]", f"LS {d['m_LS_kg_s']:.3f}   HS {d['m_HS_kg_s']:.3f}"),
        ("heat [kW]", f"Q_source {d['Q_source_kW']:.1f}   Q_sink {d['Q_sink_kW']:.1f}  (DSH {d['Q_DSH_kW']:.1f}, con {d['Q_con_kW']:.1f}, SC {d['Q_SC_kW']:.1f})"),
        ("power [kW]", f"W_LS {d['W_LS_kW']:.1f}   W_HS {d['W_HS_kW']:.1f}   total {d['W_total_kW']:.1f}"),
        ("COP [-]", f"{d['COP']:.3f}"),
        ("sink outlet [degC]", f"{d['T_sink_out_C']:.2f}"),
        ("superheat / subcooling / pinch [K]", f"{d['superheat_K']:.2f} / {d['subcooling_K']:.2f} / {d['pinch_K']:.2f}"),
        ("source pressure drop [bar]", f"{d['dp_source_bar']:.4f}"),
        ("energy balance residual [-]", f"{d['energy_residual']:.1e}"),
    ]
    w = max(len(r[0]) for r in rows)
    out = [f"{k:<{w}}  {v}" for k, v in rows]
    out.append("")
    out.append(f"{'state':<14}{'T [degC]':>10}{'p [bar(a)]':>12}{'h [kJ/kg]':>12}")
    for name, s in d["states"].items():
        out.append(f"{name:<14}{s['T_C']:>10.2f}{s['p_bar']:>12.3f}{s['h_J_kg'] / 1e3:>12.2f}")
    out.append(f"(CoolProp {backend}; enthalpies on CoolProp's reference state, compare differences)")
    return "\n".join(out)


def cmd_bench(args) -> int:
    import importlib
    params = _params(args)
    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    known = {"model": ("model.bench", "bench_model"), "simulator": ("simulator.bench", "bench_simulator"),
             "analysis": ("model.bench_analysis", "bench_analysis"),
             "vcycle": ("model.vcycle", "bench_vcycle"),
             "gateway": ("edge.bench_gateway", "bench_gateway"),
             "advice": ("edge.bench_advice", "bench_advice"),
             "inputs": ("edge.bench_inputs", "bench_inputs"),
             "closed_loop": ("edge.bench_closed_loop", "bench_closed_loop"),
             "cip": ("edge.bench_cip", "bench_cip"),
             "replay": ("edge.bench_fleet", "bench_replay"),
             "fleet": ("edge.bench_fleet", "bench_fleet"),
             "plant_year": ("edge.bench_fleet", "bench_plant_year")}
    unknown = [s for s in sections if s not in known]
    if unknown:
        print(f"hp-edge bench: unknown section(s) {', '.join(unknown)}; choose from {', '.join(known)}",
              file=sys.stderr)
        return 2
    from edge.benchmachine import machine
    # the CPU, the versions and three reference timings: figures from two machines are told apart
    result = {"machine": machine()}
    for s in sections:
        mod, fn = known[s]
        print(f"hp-edge bench: {s} ...", file=sys.stderr, flush=True)
        func = getattr(importlib.import_module(mod), fn)
        if s == "model":
            result[s] = func(params, grid_levels=args.grid_levels)
        elif s == "cip":
            result[s] = func(params, progress=_day_progress)
        elif s == "analysis":
            from edge.config import find_config
            result[s] = func(params, json.loads(find_config("surrogate.json").read_text(encoding="utf-8")))
        elif s in ("vcycle", "replay", "fleet", "plant_year"):
            result[s] = func(params)
        else:
            result[s] = func()
    text = json.dumps(result, indent=2, default=float)
    print(text)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            fh.write(text + "\n")
    return 0


def _day_progress(day: int, days: int) -> None:
    if day % 10 == 0:
        print(f"hp-edge bench: cip: plant day {day} of at most {days}", file=sys.stderr, flush=True)


def cmd_fit_compressor(args) -> int:
    from model.compressor_fit import TableError, fit, read_table
    params = _params(args)
    comp = params.comp_LS if args.stage == "LS" else params.comp_HS
    try:
        res = fit(read_table(args.table), comp, params.fluid)
    except TableError as exc:
        print(f"hp-edge fit-compressor: {exc}", file=sys.stderr)
        return 2
    fmt = lambda c: "[" + ", ".join(f"{v:.6g}" for v in c) + "]"  # noqa: E731
    print(f"{args.table}: {res.n_rows} rows, stage {args.stage} "
          f"(swept volume {comp.swept_volume * 3600:.1f} m3/h at {comp.N_nom:.0f} rpm)")
    print(f"eta_is : R^2 = {res.r2_is:.5f}, max |error| = {res.max_err_is:.2e}")
    print(f"eta_vol: R^2 = {res.r2_vol:.5f}, max |error| = {res.max_err_vol:.2e}")
    snippet = (f"# fitted by hp-edge fit-compressor from {args.table} ({res.n_rows} rows)\n"
               f"# basis: 1, pi, n, pi^2, pi*n, n^2 with n = speed / nominal_speed_rpm\n"
               f"compressors:\n  {args.stage}:\n"
               f"    eta_is:  {fmt(res.eta_is)}   # R^2 {res.r2_is:.5f}\n"
               f"    eta_vol: {fmt(res.eta_vol)}   # R^2 {res.r2_vol:.5f}\n")
    print()
    print(snippet, end="")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            fh.write(snippet)
        print(f"written to {args.out}")
    return 0
