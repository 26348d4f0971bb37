"""Load config/plant.yaml into model parameters; errors name the file and the key."""
from __future__ import annotations

from pathlib import Path

import yaml

DEFAULT_PLANT = "config/plant.yaml"


class PlantFileError(ValueError):
    """plant.yaml is missing, not YAML, or invalid; the message starts with the file name."""


def load_plant_dict(path: str | Path = DEFAULT_PLANT) -> dict:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise PlantFileError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise PlantFileError(f"{p}: not valid YAML: {exc}") from exc
    if not isinstance(d, dict):
        raise PlantFileError(f"{p}: expected a mapping at the top level")
    return d


def load_plant(path: str | Path = DEFAULT_PLANT, backend: str | None = None):
    """PlantParams from plant.yaml (``backend`` overrides property_backend)."""
    from model.params import ParamError, PlantParams
    d = load_plant_dict(path)
    if backend:
        d = {**d, "property_backend": backend}
    try:
        return PlantParams.from_dict(d)
    except ParamError as exc:
        raise PlantFileError("\n".join(f"{path}: {line}" for line in str(exc).splitlines())) from exc
