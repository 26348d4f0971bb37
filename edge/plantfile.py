"""Load and check config/plant.yaml; errors name the file, the key and (for unknown and duplicate
keys) the line.

plant.yaml is read by the same strict loader as gateway.yaml (``edge.yamlfile``) and checked
against ``PLANT_SCHEMA``: every key the product reads, at every level. A key that is not in the
schema is refused (a typo such as ``R_th_f_K_per_kw`` would otherwise be ignored and the default
used silently). To add a section or a key to plant.yaml, add it to ``PLANT_SCHEMA`` below: that
is the one place. Values are checked by the code that reads them (``PlantParams.from_dict``,
the calibration, replay and surrogate settings, the commissioning limits), all called from
``check_plant``, so every command sees every problem at start.
"""
from __future__ import annotations

from pathlib import Path

from edge.yamlfile import MapOf, Problems, Section, check_schema, display_path, load_yaml

DEFAULT_PLANT = "config/plant.yaml"


class PlantFileError(ValueError):
    """plant.yaml is missing, not YAML, or invalid; one line per problem, each starting with the
    file name."""


_COMPRESSOR = dict.fromkeys(("swept_volume_m3_per_h", "nominal_speed_rpm", "speed_min_rpm",
                             "speed_max_rpm", "eta_is", "eta_vol"))
_CALIBRATION_KIND = {
    **dict.fromkeys(("window_minutes", "window_hours", "min_samples", "tolerance",
                     "correlation_limit", "change_penalty", "use_flagged_rows")),
    "parameters": MapOf({"start": None, "bounds": None}),
    "goals": MapOf({"weight": None, "statistic": None}),
}

# Every key of plant.yaml. None: a value (checked by its reader); a dict: a section; MapOf: a
# mapping whose keys the user names (calibration parameters, goals).
PLANT_SCHEMA: dict = {
    "fluid": None,
    "property_backend": None,
    "ambient_pressure_bar": None,
    "water": dict.fromkeys(("cp_kJ_per_kgK", "rho_kg_per_m3")),
    "evaporator": dict.fromkeys(("U_W_per_m2K", "A_m2", "superheat_K")),
    "desuperheater": dict.fromkeys(("U_W_per_m2K", "A_m2")),
    "condenser": dict.fromkeys(("U_W_per_m2K", "A_m2", "design_pinch_K", "design_pressure_bar_a")),
    "subcooler": dict.fromkeys(("U_W_per_m2K", "A_m2")),
    "compressors": {"LS": _COMPRESSOR, "HS": _COMPRESSOR},
    "source_pressure_drop": {"dp_clean_coef": None},
    "calibrated": dict.fromkeys(("CF_DSH", "CF_con", "CF_SC", "CF_eva", "R_th_f_K_per_kW",
                                 "CF_dp_f")),
    "calibration": {
        "initial": {**_CALIBRATION_KIND,
                    "limits": dict.fromkeys(("max_objective_pct", "max_parameters_at_bound",
                                             "min_dp_clean_r2"))},
        "fouling": _CALIBRATION_KIND,
        "replay": dict.fromkeys(("window_hours", "min_samples", "initial_minutes",
                                 "cip_off_minutes", "cip_windows", "max_gap_minutes", "optimize",
                                 "dp_form", "hindsight", "surrogate", "lockstep_windows")),
        "heat_balance_limit_pct": None,
    },
    # the set-point advice (model.analysis.advice.AdviceSettings) and the compressor learning
    # (model.analysis.compressors.LearningSettings): every key optional
    "advice": dict.fromkeys(("representative_points", "check_rows", "uncertainty_draws",
                             "confidence_k", "min_coverage_share", "max_curve_residual",
                             "dead_band_pct", "extrapolation_share", "extrapolation_max_bar",
                             "path_step_bar", "gap_max_bar", "min_covered_bar", "shape_k", "search_k",
                             "seed")),
    "compressor_learning": dict.fromkeys((
        "enabled", "half_life_days", "prior_weight", "min_samples", "bin_pi", "bin_n",
        "min_bin_weight", "margin_pi", "margin_n", "T_c_location", "subcooling_threshold_K",
        "eta_range", "local", "local_bandwidth_bins", "local_prior_weight", "prior_sd",
        "extrapolation_sd")),
    # the surrogate fitted from the analysis windows' optima (model.analysis.surrogate_tracker)
    "surrogate_tracker": dict.fromkeys(("enabled", "reference_p_m_sp_barg", "extra_fouling_K_per_kW",
                                        "refit_every", "qualified_every", "max_rows", "min_rows",
                                        "test_share", "min_r2", "pm_tol_bar", "min_share")),
    "surrogate": dict.fromkeys(("reference_p_m_sp_barg", "fouling_levels_K_per_kW",
                                "points_per_level", "T_source_in_C", "source_cooling_K",
                                "T_sink_in_C", "V_source_m3h", "V_sink_m3h", "seed")),
    # issue 10: fouling forecast, cost of fouling, CIP timing (model.analysis.cip.CIP_KEYS,
    # CipSettings.from_config); every key optional. electricity_price_csv is read by
    # edge.io.prices (relative to plant.yaml's folder) and checked here too
    "cip": dict.fromkeys(("enabled", "electricity_price_eur_per_MWh", "electricity_price_csv",
                          "pump_efficiency", "direct_cost_eur", "downtime_h",
                          "replacement_heat_eur_per_MWh", "removal_share_default",
                          "dp_removal_share_default", "horizon_days", "band_level",
                          "R_th_f_limit_K_per_kW", "current_interval_days", "trigger",
                          "cost_levels_K_per_kW", "cost_levels_per_window", "cost_average_hours",
                          "cost_points", "tally_max_gap_h", "max_estimates")),
}


def check_plant(p: Problems, path: Path, file: str | None = None) -> dict | None:
    """plant.yaml as a dict when it is valid; every problem is recorded on ``p`` (and None is
    returned when the file cannot be read at all)."""
    file = file or display_path(path)
    data = load_yaml(p, Path(path), file)
    if data is None:
        return None
    top = Section(p, file, "top level", data)
    if not isinstance(data, dict):
        top.mapping()
        return None
    n0 = len(p.lines)
    check_schema(top, PLANT_SCHEMA)
    if len(p.lines) != n0:
        return data     # values are not checked on a file of the wrong shape
    problems = _value_problems(data)
    for msg in problems:
        p.add(file, None, None, msg)
    if not problems:                       # the price series plant.yaml names (issue 10)
        from edge.io.prices import PriceFileError, price_for_plant
        try:
            price_for_plant(data, path)
        except PriceFileError as exc:
            p.add(file, None, None, f"key 'cip.electricity_price_csv': {exc}")
    return data


def _value_problems(d: dict) -> list[str]:
    """What the readers of plant.yaml say about its values (one line each)."""
    from model.params import ParamError, PlantParams

    out: list[str] = []
    try:
        params = PlantParams.from_dict(d)
    except ParamError as exc:
        return str(exc).splitlines()
    from edge.commissioning import CommissioningLimits
    from model.calibration import CalibrationError, spec_from_config
    from model.analysis.advice import AdviceError
    from model.analysis.chain import ChainSettings
    from model.analysis.compressors import LearningError
    from model.analysis.surrogate_tracker import TrackerError
    from model.analysis.replay import ReplayError, ReplaySettings
    from model.surrogate import SurrogateError, design_from_config

    checks = [lambda: spec_from_config(params.extra, "initial"),
              lambda: spec_from_config(params.extra, "fouling"),
              lambda: ReplaySettings.from_config(params.extra),
              lambda: design_from_config(params.extra),
              lambda: CommissioningLimits.from_config(params.extra),
              lambda: ChainSettings.from_config(params.extra)]
    for check in checks:
        try:
            check()
        except (CalibrationError, ReplayError, SurrogateError, AdviceError, LearningError,
                TrackerError, ValueError, TypeError, OverflowError) as exc:
            out.append(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    return out


def load_plant_dict(path: str | Path = DEFAULT_PLANT) -> dict:
    """plant.yaml as a dict, checked; raises PlantFileError with every problem."""
    p = Problems()
    data = check_plant(p, Path(path))
    if p.lines:
        raise PlantFileError("\n".join(p.lines))
    return data


def load_plant(path: str | Path = DEFAULT_PLANT, backend: str | None = None):
    """PlantParams from plant.yaml (``backend`` overrides property_backend)."""
    from model.params import ParamError, PlantParams
    d = load_plant_dict(path)
    if backend:
        d = {**d, "property_backend": backend}
    try:
        return PlantParams.from_dict(d)
    except ParamError as exc:
        raise PlantFileError("\n".join(f"{display_path(path)}: {line}"
                                       for line in str(exc).splitlines())) from exc
