"""Shared fixtures: the default plant parameters and a nominal operating point."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PLANT_YAML = ROOT / "config" / "plant.yaml"


@pytest.fixture(scope="session")
def plant():
    from edge.plantfile import load_plant
    return load_plant(PLANT_YAML)


@pytest.fixture(scope="session")
def nominal_row():
    """SPEC §2 nominal operating point in canonical units."""
    return {"T_source_in": 25.0, "T_source_out": 18.0, "T_sink_in": 40.0,
            "V_source": 192.0, "V_sink": 62.0, "p_m_sp": 16.0}


@pytest.fixture(scope="session", autouse=True)
def _tables_cache(tmp_path_factory):
    """The cycle tables' cache file (model.cycletables.cache_file) in this session's temporary
    directory, not the user's: the first process of the session builds the tables, the later ones
    (the CLI's subprocesses) read them."""
    import os
    from model.cycletables import CACHE_ENV
    old = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(tmp_path_factory.mktemp("hp-edge-cache"))
    yield
    if old is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = old
