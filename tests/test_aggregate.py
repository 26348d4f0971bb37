"""Scan samples -> one-minute samples: means, bad values excluded, max age, frozen life counter."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import pytest

from edge.aggregate import FROZEN, Aggregator, sample_row


@dataclass(frozen=True)
class Tag:
    name: str
    max_age_s: float = 30.0


@dataclass(frozen=True)
class V:
    value: float | None
    bad: str | None = None


TAGS = (Tag("T"), Tag("W"), Tag("running"), Tag("cip"), Tag("life_counter", 12.0), Tag("clock"))


class Feed:
    """Drives an Aggregator with a 5-s scan on both clocks, the life counter ticking."""

    def __init__(self, agg: Aggregator, t0: float = 6000.0):
        self.agg, self.t, self.lc = agg, t0, 0
        self.samples = []

    def scan(self, n: int = 1, lc_moves: bool = True, comm: str | None = None, **values):
        for _ in range(n):
            if lc_moves:
                self.lc += 1
            vals = {} if comm else {"T": V(20.0), "W": V(100.0), "running": V(1.0),
                                    "cip": V(0.0), "life_counter": V(float(self.lc)),
                                    "clock": V(self.t)}
            if not comm:
                for k, v in values.items():
                    vals[k] = v if isinstance(v, V) else V(v)
            self.samples += self.agg.add(self.t, self.t, vals, comm)
            self.t += 5.0
        return self.samples


def make(**kw) -> Aggregator:
    return Aggregator(TAGS, 60.0, life_counter="life_counter", exclude=("clock",),
                      t_start=6000.0, **kw)


def test_mean_of_a_full_minute_and_period_start_timestamp():
    f = Feed(make())
    f.scan(12, T=21.0)
    f.scan(13)   # next minute, confirmed by the life counter -> closes the first
    s = f.samples[0]
    assert s.timestamp == 6000.0
    assert s.values["T"] == pytest.approx(21.0)
    assert s.scans == 12 and s.good_scans == 12 and s.quality == ""
    assert "life_counter" not in s.values and "clock" not in s.values


def test_bad_values_are_excluded_not_clamped():
    f = Feed(make())
    f.scan(9, T=20.0)
    f.scan(3, T=V(None, "out of range [0, 50]"))
    f.scan(13)
    s = f.samples[0]
    assert s.values["T"] == pytest.approx(20.0)        # mean of the 9 good scans only
    assert "T" not in s.bad


def test_a_tag_bad_for_most_of_the_minute_is_nan_with_its_reason():
    f = Feed(make())
    f.scan(4, T=20.0)
    f.scan(8, T=V(None, "nan"))
    f.scan(13)
    s = f.samples[0]
    assert math.isnan(s.values["T"])
    assert s.bad["T"] == "nan"
    assert sample_row(s)["quality"] == "bad: T nan"
    assert s.values["W"] == pytest.approx(100.0)


def test_flags_running_min_and_cip_max():
    f = Feed(make())
    f.scan(11)
    f.scan(1, running=0.0, cip=1.0)
    f.scan(13)
    s = f.samples[0]
    assert s.values["running"] == 0.0 and s.values["cip"] == 1.0


def test_max_age_makes_a_tag_stale():
    agg = make()
    f = Feed(agg)
    f.scan(2)
    assert agg.freshness(f.t).stale == ()
    f.scan(7, T=V(None, "timeout"))       # 35 s without a good T
    fresh = agg.freshness(f.t)
    assert fresh.stale == ("T",) and fresh.data_stale and not fresh.frozen


def test_frozen_life_counter_discards_every_scan_since_its_last_change():
    agg = make()
    f = Feed(agg)
    f.scan(6)                                # 30 s alive (first sight waits for a change)
    f.scan(6, lc_moves=False, T=99.0)        # frozen values (T would say 99)
    assert agg.freshness(f.t).frozen and agg.frozen_events == 1
    f.scan(20, lc_moves=False, T=99.0)       # still frozen, into the next minutes
    f.scan(14)                               # alive again
    assert not agg.freshness(f.t).frozen
    first = f.samples[0]
    assert first.values["T"] == pytest.approx(20.0)      # the frozen 99s never got in
    assert first.frozen_scans == 6 and first.good_scans == 6
    frozen_minute = f.samples[1]
    assert frozen_minute.quality == FROZEN and math.isnan(frozen_minute.values["T"])
    assert frozen_minute.bad["T"] == FROZEN
    assert all(s.quality in ("", FROZEN) for s in f.samples)


def test_first_scan_waits_for_the_life_counter_to_move():
    agg = make()
    assert agg.add(6000.0, 6000.0, {"life_counter": V(7.0), "T": V(1.0)}) == []
    assert agg.pending == 1
    agg.add(6005.0, 6005.0, {"life_counter": V(8.0), "T": V(1.0)})
    assert agg.pending == 0


def test_comm_outage_is_not_frozen_and_is_marked():
    agg = make()
    f = Feed(agg)
    f.scan(12)
    f.scan(12, lc_moves=False, comm="connection lost")
    assert not agg.freshness(f.t).frozen
    assert agg.freshness(f.t).data_stale
    f.scan(13)
    outage = f.samples[1]
    assert outage.quality == "comm fault" and math.isnan(outage.values["T"])
    assert outage.bad["T"] == "connection lost"


def test_scans_without_a_time_count_for_freshness_only():
    agg = make()
    out = agg.add(None, 6020.0, {"life_counter": V(1.0), "T": V(1.0)})
    assert out == [] and agg.pending == 0
    assert agg.freshness(6040.0).stale == ("W", "running", "cip", "clock")  # T was read good


def test_without_life_counter_scans_are_taken_at_once():
    agg = Aggregator(TAGS[:2], 60.0, t_start=0.0)
    for k in range(13):
        out = agg.add(60.0 + 5 * k, 5.0 * k, {"T": V(1.0 * k), "W": V(2.0)})
    assert len(out) == 1 and out[0].values["T"] == pytest.approx(5.5)


def test_clock_going_back_closes_the_open_period():
    agg = Aggregator(TAGS[:1], 60.0, t_start=0.0)
    agg.add(600.0, 0.0, {"T": V(1.0)})
    out = agg.add(300.0, 5.0, {"T": V(2.0)})
    assert [s.timestamp for s in out] == [600.0]


def test_argument_checks():
    with pytest.raises(ValueError):
        Aggregator(TAGS, 0.0)
    with pytest.raises(ValueError):
        Aggregator(TAGS, 60.0, life_counter="nope")


# ------------------------------------------------------------- stuck sensors (issue 9 item 17)

@dataclass(frozen=True)
class FTag:
    name: str
    max_age_s: float = 30.0
    flatline_s: float | None = None
    scale: float = 1.0
    type: str = "float32"


FLAT_TAGS = (FTag("T", flatline_s=120.0, scale=0.1, type="int16"), FTag("W", flatline_s=120.0),
             FTag("running"), FTag("cip"), FTag("life_counter", 12.0), FTag("clock"))


def flat_feed() -> Feed:
    return Feed(Aggregator(FLAT_TAGS, 60.0, life_counter="life_counter", exclude=("clock",),
                           t_start=6000.0))


def test_a_stuck_value_while_running_is_bad_flatline_after_flatline_s():
    f = flat_feed()
    w = iter(range(10_000))
    for _ in range(24):                       # W moves, T stays at 20.0 for 2 minutes
        f.scan(T=20.0, W=100.0 + next(w))
    assert not f.agg.freshness(f.t).flat
    f.scan(12, T=20.0, W=100.0 + next(w))     # now longer than its 120 s
    assert f.agg.freshness(f.t).flat == ("T",)
    f.scan(13, T=20.3, W=100.0 + next(w))      # it moves again
    assert f.agg.freshness(f.t).flat == ()
    s2, s3 = f.samples[2], f.samples[3]
    assert math.isnan(s2.values["T"]) and s2.bad == {"T": "flatline"}
    assert math.isfinite(s2.values["W"])                             # W is fine
    assert s3.values["T"] == pytest.approx(20.3) and "T" not in s3.bad
    assert f.agg.flatline_events == 1
    assert sample_row(s2)["quality"] == "bad: T flatline"


def test_a_change_below_the_resolution_is_no_movement():
    """T is int16 x0.1: half a raw step (0.05) is noise of the register, not movement."""
    f = flat_feed()
    for k in range(40):
        f.scan(T=20.0 + 0.04 * (k % 2), W=100.0 + k)
    assert f.agg.freshness(f.t).flat == ("T",)
    f2 = flat_feed()
    for k in range(40):
        f2.scan(T=20.0 + 0.1 * (k % 2), W=100.0 + k)
    assert f2.agg.freshness(f2.t).flat == ()


def test_flat_while_the_plant_is_off_is_no_fault_and_stuck_stays_stuck():
    f = flat_feed()
    f.scan(60, T=20.0, W=5.0, running=0.0)              # 5 min off, everything flat
    assert f.agg.freshness(f.t).flat == ()
    f.scan(20, T=20.0, W=5.0, running=1.0)              # running: counts from the start
    assert f.agg.freshness(f.t).flat == ()
    f.scan(10, T=20.0, W=5.0, running=1.0)
    assert set(f.agg.freshness(f.t).flat) == {"T", "W"}
    f.scan(5, T=20.0, W=5.0, running=0.0)               # a stop does not heal a stuck sensor
    assert set(f.agg.freshness(f.t).flat) == {"T", "W"}


def test_without_a_running_flag_the_power_decides():
    from edge.aggregate import plant_running
    assert plant_running({"running": 1.0, "cip": 1.0}) is False      # CIP: not running
    assert plant_running({"running": None, "W_LS": 10.0, "W_HS": 15.0}) is True
    assert plant_running({"running": None, "W_LS": 10.0, "W_HS": 5.0}) is False
    assert plant_running({"W_LS": 10.0}) is None


def test_flatline_defaults_and_the_tag_map_key(tmp_path):
    import shutil

    import yaml

    from edge.aggregate import FLATLINE_DEFAULT_S, flatline_limit
    from edge.config import ConfigError, load_config

    assert flatline_limit(FTag("T_source_out")) == FLATLINE_DEFAULT_S == 1800.0
    assert flatline_limit(FTag("N_LS")) is None and flatline_limit(FTag("p_m_sp")) is None
    assert flatline_limit(FTag("T_source_out", flatline_s=0.0)) is None
    assert flatline_limit(FTag("N_LS", flatline_s=600.0)) == 600.0

    root = Path(__file__).resolve().parent.parent / "config"
    for name in ("gateway.yaml", "tags.yaml"):
        shutil.copy(root / name, tmp_path / name)
    doc = yaml.safe_load((tmp_path / "tags.yaml").read_text())
    doc["tags"]["T_e"]["flatline_s"] = 600
    doc["tags"]["T_c"]["flatline_s"] = -1
    (tmp_path / "tags.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "gateway.yaml", load_plant=False)
    assert [p.split("tags.yaml: ")[1] for p in info.value.problems] == [
        "line 26: tag 'T_c': key 'flatline_s': must be >= 0 (0: no flat-line check), got -1"]
    doc["tags"]["T_c"]["flatline_s"] = 0
    (tmp_path / "tags.yaml").write_text(yaml.safe_dump(doc))
    cfg = load_config(tmp_path / "gateway.yaml", load_plant=False)
    agg = Aggregator(cfg.tags, 60.0, life_counter="life_counter", exclude=("plc_clock",))
    limits = agg.flatline_limits
    assert limits["T_e"] == 600.0 and "T_c" not in limits and limits["T_source_out"] == 1800.0
    assert not {"N_LS", "running", "cip", "p_m_sp", "plc_clock", "life_counter"} & set(limits)
