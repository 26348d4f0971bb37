"""The input campaign of issue 9 (item 15), a seeded subset: mutated configuration files and
history CSVs through the real commands give no traceback, a failing exit is 2 with a bounded
message, and a config of at most 64 KB costs little memory. The full campaign (300 configs, 200
CSVs) is `hp-edge bench --only inputs`."""
from __future__ import annotations

import random

import pytest

from edge.bench_inputs import mutate_csv, mutated_config, run_campaign


@pytest.mark.parametrize("seed", [11, 12])
def test_mutated_configs_and_csvs_never_give_a_traceback(seed):
    result = run_campaign(n_configs=30, n_csvs=20, seed=seed)
    for kind in ("configs", "csvs"):
        s = result[kind]
        assert s["tracebacks"] == 0, s["bad_cases"]
        assert s["failing"] == 0, s["bad_cases"]
        assert set(s["exit_codes"]) <= {"0", "1", "2"}
        assert s["max_error_lines"] <= 60 and s["max_error_bytes"] <= 20_000
    assert result["configs"]["max_peak_mb_le_64kb"] < 100
    assert int(result["configs"]["exit_codes"].get("2", 0)) >= 15   # most mutations are errors


def test_mutations_are_reproducible_and_varied():
    a = [mutated_config(random.Random(3)) for _ in range(3)]
    b = [mutated_config(random.Random(3)) for _ in range(3)]
    assert a == b
    rng = random.Random(5)
    files = {mutated_config(rng)[0] for _ in range(40)}
    assert files == {"gateway.yaml", "tags.yaml", "plant.yaml", "simulator.yaml"}
    text = "timestamp,a\n2024-03-01T00:00Z,1.5\n2024-03-01T00:01Z,2.5\n"
    outs = {mutate_csv(text, random.Random(i)) for i in range(30)}
    assert len(outs) > 10
