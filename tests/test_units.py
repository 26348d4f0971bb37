"""Units at the edges (issue 9 item 1): one conversion table (model/units.py), every supported
unit converted to the canonical one of SPEC §4, anything else refused naming file, tag and key;
a tag's range is in the tag's own unit."""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from edge.config import ConfigError, load_config
from edge.plc import _check_tag
from model.units import (CANONICAL_UNITS, UNITS, UnitError, canonical_linear, from_canonical,
                         to_canonical)

REPO = Path(__file__).resolve().parents[1]
EXACT = 1e-12   # relative: the conversions are exact linear maps


# (value, unit, pressure, ambient [bar], canonical value) - independent hand values
HAND = [
    (25.0, "degC", None, None, 25.0),
    (298.15, "K", None, None, 25.0),
    (77.0, "degF", None, None, 25.0),
    (-40.0, "degF", None, None, -40.0),
    (0.0, "K", None, None, -273.15),
    (16.0, "bar", "gauge", None, 16.0),
    (17.01325, "bar", "absolute", 1.01325, 16.0),
    (1600.0, "kPa", "gauge", None, 16.0),
    (1701.325, "kPa", "absolute", 1.01325, 16.0),
    (1.6, "MPa", "gauge", None, 16.0),
    (16000.0, "mbar", "gauge", None, 16.0),
    (1.6e6, "Pa", "gauge", None, 16.0),
    (14.503773773, "psi", "gauge", None, 1.0),        # 1 bar = 14.503773773 psi
    (14.695948775513, "psi", "absolute", 1.01325, 0.0),  # one standard atmosphere
    (101325.0, "Pa", "absolute", 0.95, 1.01325 - 0.95),
    (192.0, "m3/h", None, None, 192.0),
    (192.0 / 3600.0, "m3/s", None, None, 192.0),
    (53.3333333333, "l/s", None, None, 192.0),
    (3200.0, "l/min", None, None, 192.0),
    (450_000.0, "W", None, None, 450.0),
    (450.0, "kW", None, None, 450.0),
    (0.45, "MW", None, None, 450.0),
    (1500.0, "rpm", None, None, 1500.0),
    (1.0, "1", None, None, 1.0),
    (60.0, "s", None, None, 60.0),
]


@pytest.mark.parametrize("value, unit, pressure, ambient, expected", HAND)
def test_every_supported_unit_against_hand_values(value, unit, pressure, ambient, expected):
    got = to_canonical(value, unit, pressure, ambient)
    assert got == pytest.approx(expected, rel=1e-9, abs=1e-9)


def test_the_table_covers_exactly_the_units_of_the_issue():
    assert set(UNITS) == {"degC", "K", "degF", "bar", "mbar", "Pa", "kPa", "MPa", "psi", "m3/h",
                          "m3/s", "l/s", "l/min", "W", "kW", "MW", "rpm", "1", "s"}
    for unit, (quantity, factor, _) in UNITS.items():
        assert quantity in CANONICAL_UNITS and factor > 0, unit
        assert UNITS[CANONICAL_UNITS[quantity]][1:] == (1.0, 0.0)   # canonical is identity


@settings(max_examples=200, deadline=None)
@given(value=st.floats(-1e6, 1e6), unit=st.sampled_from(sorted(UNITS)),
       kind=st.sampled_from(["gauge", "absolute"]), ambient=st.floats(0.5, 1.2))
def test_round_trip_through_the_canonical_unit(value, unit, kind, ambient):
    pressure = kind if UNITS[unit][0] == "pressure" else None
    back = from_canonical(to_canonical(value, unit, pressure, ambient), unit, pressure, ambient)
    assert back == pytest.approx(value, rel=1e-9, abs=1e-6)


def test_refusals_are_explicit():
    with pytest.raises(UnitError, match=r"unsupported unit 'degR'; supported: degC, K, degF"):
        to_canonical(1.0, "degR")
    with pytest.raises(UnitError, match="needs 'pressure: gauge' or 'pressure: absolute'"):
        canonical_linear("kPa")
    with pytest.raises(UnitError, match="needs the ambient pressure"):
        canonical_linear("bar", "absolute")
    with pytest.raises(UnitError, match="applies to pressure units only"):
        canonical_linear("K", "gauge")


# ------------------------------------------------------------------------- the tag map


@pytest.fixture
def cfgdir(tmp_path, monkeypatch):
    d = tmp_path / "config"
    d.mkdir()
    for name in ("gateway.yaml", "tags.yaml", "plant.yaml"):
        shutil.copy(REPO / "config" / name, d)
    monkeypatch.chdir(tmp_path)
    return d


def edit_tags(d: Path, **changes) -> None:
    path = d / "tags.yaml"
    data = yaml.safe_load(path.read_text())
    for name, change in changes.items():
        data["tags"][name].update(change)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


def test_tags_in_other_units_are_converted_and_ranges_stay_in_the_tag_unit(cfgdir):
    edit_tags(cfgdir,
              T_sink_in={"unit": "K", "scale": 0.01, "offset": 0.0, "range": [273.15, 363.15],
                         "sentinel": None, "type": "uint16"},
              p_dis_HS={"unit": "kPa", "pressure": "absolute", "range": [0, 6000]},
              V_source={"unit": "l/s", "range": [0, 110]},
              W_LS={"unit": "W", "range": [0, 1.5e6]})
    cfg = load_config("config/gateway.yaml")
    amb = cfg.plant["ambient_pressure_bar"]
    T, p, V, W = (cfg.tag(n) for n in ("T_sink_in", "p_dis_HS", "V_source", "W_LS"))
    assert T.range == (273.15, 363.15) and T.canonical_range == pytest.approx((0.0, 90.0))
    assert p.range == (0.0, 6000.0)
    assert p.canonical_range == pytest.approx((-amb, 60.0 - amb), rel=EXACT)
    # decoded from register words, validated in the tag's unit, converted once
    t = _check_tag(T, [31315])                       # 313.15 K
    assert t.ok and t.value == pytest.approx(40.0, rel=EXACT)
    t = _check_tag(T, [26000])                       # 260 K: below its range in K
    assert t.bad == "out of range [273.15, 363.15]" and t.value is None
    from edge.codec import encode
    t = _check_tag(p, encode(3201.325, "float32", "CDAB"))    # kPa absolute
    assert t.ok and t.value == pytest.approx(32.01325 - amb, rel=1e-6)
    t = _check_tag(V, encode(53.3333333, "float32", "ABCD")) if V.type == "float32" else \
        _check_tag(V, [5333])                        # 53.33 l/s
    assert t.ok and t.value == pytest.approx(192.0, rel=1e-3)
    t = _check_tag(W, encode(260_000.0, "float32", "ABCD"))
    assert t.ok and t.value == pytest.approx(260.0, rel=1e-7)


def problems() -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config("config/gateway.yaml")
    return info.value.problems


def test_unknown_units_and_wrong_quantities_are_refused(cfgdir):
    edit_tags(cfgdir, T_c={"unit": "degR"}, W_HS={"unit": "bar", "pressure": "gauge"},
              V_sink={"unit": "m³/h"})
    got = problems()
    assert any(ln.startswith("config/tags.yaml: line ") and "tag 'T_c': key 'unit': 'degR' is "
               "not a supported unit; supported: degC, K, degF, bar, mbar, Pa, kPa, MPa, psi" in ln
               for ln in got), got
    assert any("tag 'W_HS': key 'unit': 'bar' measures pressure, but W_HS is high-stage "
               "compressor electric power: a power (W, kW, MW)" in ln for ln in got), got
    assert any("tag 'V_sink': key 'unit': 'm³/h' is not a supported unit" in ln for ln in got)


def test_absolute_pressure_needs_the_plant_files_ambient(cfgdir):
    edit_tags(cfgdir, p_suc_LS={"pressure": "absolute", "range": [0.1, 26]})
    cfg = load_config("config/gateway.yaml")
    assert cfg.tag("p_suc_LS").canonical == pytest.approx((1.0, -1.01325))
    bare = load_config("config/gateway.yaml", load_plant=False)   # no plant: no ambient
    assert bare.tag("p_suc_LS").canonical is None
    from edge.codec import encode
    t = _check_tag(bare.tag("p_suc_LS"), encode(6.0, "float32", "CDAB"))
    assert t.value is None and "no ambient pressure" in t.bad      # marked bad, never guessed


def test_shipped_tag_map_is_canonical_already():
    cfg = load_config(REPO / "config" / "gateway.yaml")
    for t in cfg.tags:
        assert t.canonical == (1.0, 0.0), t.name
        assert t.canonical_range == t.range, t.name
    assert not math.isnan(cfg.tag("p_m_sp").to_canonical(16.0))
