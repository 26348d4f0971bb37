"""The cycle tables' cache file (``model.cycletables.cache_file``): a later process reads the same
arrays to the bit; storage that cannot keep it (a damaged file, a directory that cannot be
created, the cache switched off) costs the build and nothing else."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

import model.cycletables as ct


@pytest.fixture(scope="module")
def built():
    return ct.CycleTables("Ammonia")


def _same(a, b) -> None:
    assert set(vars(a)) == set(vars(b))
    for k, v in vars(a).items():
        w = getattr(b, k)
        assert type(v) is type(w), k
        if isinstance(v, np.ndarray):
            assert v.dtype == w.dtype and v.shape == w.shape and v.tobytes() == w.tobytes(), k
        else:
            assert v == w, k


def test_a_cached_table_is_the_built_one_to_the_bit(built, tmp_path, monkeypatch):
    monkeypatch.setenv(ct.CACHE_ENV, str(tmp_path / "cache"))
    path = ct.cache_file("Ammonia")
    assert path.parent == tmp_path / "cache" and path.name.startswith("cycletables-Ammonia-")
    first = ct._load_or_build("Ammonia")            # builds and keeps
    assert path.is_file() and list(path.parent.iterdir()) == [path]   # no temporary file left
    _same(built, first)
    calls = []
    monkeypatch.setattr(ct.CycleTables, "__init__", lambda self, name="Ammonia": calls.append(name))
    second = ct._load_or_build("Ammonia")           # read, not built
    assert calls == []
    _same(built, second)
    # the lookups answer the same
    T = np.linspace(250.0, 380.0, 57)
    assert np.array_equal(built.sat_raw(T), second.sat_raw(T), equal_nan=True)


def test_a_damaged_cache_file_is_built_again_and_replaced(built, tmp_path, monkeypatch):
    monkeypatch.setenv(ct.CACHE_ENV, str(tmp_path))
    path = ct.cache_file("Ammonia")
    path.write_bytes(b"PK\x03\x04 not a table")
    got = ct._load_or_build("Ammonia")
    _same(built, got)
    _same(built, ct._load(path))                    # replaced by a good one


def test_storage_that_cannot_keep_the_tables_costs_the_build_only(built, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would be")
    monkeypatch.setenv(ct.CACHE_ENV, str(blocker / "cache"))
    _same(built, ct._load_or_build("Ammonia"))
    assert blocker.read_text().startswith("a file")
    monkeypatch.setenv(ct.CACHE_ENV, "off")
    assert ct.cache_file("Ammonia") is None
    _same(built, ct._load_or_build("Ammonia"))


def test_the_file_name_follows_the_code_and_the_property_data(built, tmp_path, monkeypatch):
    monkeypatch.setenv(ct.CACHE_ENV, str(tmp_path))
    a = ct.cache_file("Ammonia")
    stale = tmp_path / "cycletables-Ammonia-0123456789abcdef.npz"     # an earlier version's
    stale.write_bytes(b"old")
    other = tmp_path / "cycletables-Water-0123456789abcdef.npz"       # another fluid's
    other.write_bytes(b"other")
    killed = tmp_path / (a.name + ".k1ll3d")                          # a write killed half-way
    killed.write_bytes(b"half")
    os.utime(killed, (time.time() - ct.STALE_TMP_S - 60,) * 2)
    running = tmp_path / (a.name + ".runn1n")                         # another process's, under way
    running.write_bytes(b"part")
    ct._load_or_build("Ammonia")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([a.name, other.name, running.name])
    import CoolProp
    monkeypatch.setattr(CoolProp, "__version__", CoolProp.__version__ + ".other")
    assert ct.cache_file("Ammonia") != a
