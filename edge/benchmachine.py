"""What machine a bench ran on: the CPU, the library versions, and three short reference timings.

The benches' figures are CPU seconds on whatever machine runs them, and a figure from one session is
compared with another's. Stop 39 found the development machine ~1.8 times slower than stop 38's
(the same code, the same plant-year: 142 then 260 CPU-s) with nothing in the bench's JSON to say
so. ``hp-edge bench`` now records this block beside its sections, so that two JSON documents tell
whether their machines differ before their figures are compared:

- ``cpu``: /proc/cpuinfo's model name, family/model/stepping and BogoMIPS of the first CPU, the
  number of CPUs this process may use (Linux; None elsewhere);
- ``versions``: Python and the packages whose speed the replay depends on, read from the installed
  distributions' metadata (nothing is imported for it: numba stays out of the gateway's process);
- ``reference``: three fixed workloads, each the best CPU time of REPEATS runs: a pure-Python loop
  (``python_loop_s``: 2,000,000 multiply-adds), numpy's cost per call on small arrays
  (``numpy_small_call_us``: exp, multiply and add on 50 floats) and one HEOS (P,s) flash of ammonia
  (``coolprop_flash_us``). Their ratio between two machines is a guide, not a conversion factor:
  a replay mixes these in proportions of its own.
"""
from __future__ import annotations

import os
import platform
import time
from importlib import metadata

REPEATS = 3
PACKAGES = ("numpy", "scipy", "pandas", "CoolProp", "numba", "pymodbus", "dask", "distributed")


def _cpuinfo(path: str = "/proc/cpuinfo") -> dict:
    """The first CPU's fields of /proc/cpuinfo that identify it (None where missing)."""
    out = {"model_name": None, "cpu_family": None, "model": None, "stepping": None, "bogomips": None}
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    except OSError:
        return out
    first = text.split("\n\n", 1)[0]
    keys = {"model name": "model_name", "cpu family": "cpu_family", "model": "model",
            "stepping": "stepping", "bogomips": "bogomips"}
    for line in first.splitlines():
        name, sep, value = line.partition(":")
        key = keys.get(name.strip().lower())
        if sep and key:
            out[key] = value.strip()
    return out


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _best(fn) -> float:
    best = float("inf")
    for _ in range(REPEATS):
        c = time.process_time()
        fn()
        best = min(best, time.process_time() - c)
    return best


def _python_loop() -> None:
    s = 0
    for i in range(2_000_000):
        s += i * i


def reference() -> dict:
    """The three reference timings (see the module docstring)."""
    import numpy as np
    a = np.linspace(0.0, 1.0, 50)
    calls = 20_000

    def small() -> None:
        for _ in range(calls):
            np.exp(a) * 2.0 + a

    out = {"python_loop_s": _best(_python_loop), "numpy_small_call_us": _best(small) / calls * 1e6}
    try:
        import CoolProp.CoolProp as CP
        st = CP.AbstractState("HEOS", "Ammonia")
        st.update(CP.PT_INPUTS, 5e5, 300.0)
        s = st.smass()
        flashes = 300

        def flash() -> None:
            for i in range(flashes):
                st.update(CP.PSmass_INPUTS, 5e5 + i, s)
        out["coolprop_flash_us"] = _best(flash) / flashes * 1e6
    except Exception:          # noqa: BLE001 - a missing or failing CoolProp: no figure, no bench failure
        out["coolprop_flash_us"] = None
    return out


def machine() -> dict:
    """The block ``hp-edge bench`` records beside its sections."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count()
    return {"cpu": dict(_cpuinfo(), cpus=cpus), "platform": platform.platform(),
            "versions": {"python": platform.python_version(), **{p: _version(p) for p in PACKAGES}},
            "reference": reference()}
