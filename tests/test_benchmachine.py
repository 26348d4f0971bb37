"""The machine block of ``hp-edge bench``: which CPU and versions a bench ran on, and reference timings."""
from __future__ import annotations

import json
import math
import platform
import subprocess
import sys

import numpy as np
import pandas as pd

from edge import benchmachine
from edge.benchmachine import _cpuinfo, machine

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 1
model name\t: AMD EPYC
stepping\t: 1
bogomips\t: 4890.80

processor\t: 1
model name\t: Something Else
bogomips\t: 1.00
"""


def test_cpuinfo_reads_the_first_cpu(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text(CPUINFO)
    assert _cpuinfo(str(f)) == {"model_name": "AMD EPYC", "cpu_family": "25", "model": "1",
                                "stepping": "1", "bogomips": "4890.80"}


def test_cpuinfo_missing_file_gives_nones(tmp_path):
    assert _cpuinfo(str(tmp_path / "none")) == {"model_name": None, "cpu_family": None, "model": None,
                                                 "stepping": None, "bogomips": None}


def test_machine_block(monkeypatch):
    monkeypatch.setattr(benchmachine, "REPEATS", 1)
    m = machine()
    assert set(m) == {"cpu", "platform", "versions", "reference"}
    assert m["cpu"]["cpus"] >= 1
    assert m["versions"]["python"] == platform.python_version()
    assert m["versions"]["numpy"] == np.__version__
    assert m["versions"]["pandas"] == pd.__version__
    ref = m["reference"]
    assert set(ref) == {"python_loop_s", "numpy_small_call_us", "coolprop_flash_us"}
    for k, v in ref.items():
        assert v is not None and math.isfinite(v) and v > 0, k
    json.dumps(m)       # it goes into the bench's JSON as it is


def test_machine_block_imports_no_numba():
    # the versions come from the distributions' metadata: the gateway's process stays lean
    code = ("import sys; from edge.benchmachine import machine, REPEATS; import edge.benchmachine as b; "
            "b.REPEATS = 1; machine(); print('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "False"
