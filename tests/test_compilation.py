"""Arrays kept beside the compiled programs (jface._compilation.kept_arrays): read back as they
were written, built anew where nothing may be kept, where the file is damaged or where it cannot
be written."""

import numpy as np
import pytest

from jface import _compilation


def counting(arrays):
    calls = []

    def build():
        calls.append(1)
        return arrays

    return build, calls


def test_kept_arrays_round_trip_and_damage(tmp_path, monkeypatch):
    path = tmp_path / "jface-things" / "a.npz"
    monkeypatch.setattr(_compilation, "kept_path", lambda what, settings: path)
    arrays = {"x": np.arange(5, dtype=np.int16), "y": np.float32(2.5), "z": np.ones((2, 3), bool)}
    build, calls = counting(arrays)
    for expected_builds in (1, 1):  # built and written, then read back
        got = _compilation.kept_arrays("things", (1,), build)
        assert len(calls) == expected_builds
        assert got.keys() == arrays.keys()
        for k, v in arrays.items():
            assert got[k].dtype == np.asarray(v).dtype and np.array_equal(got[k], v)
    path.write_bytes(b"PK\x03\x04 not a whole zip")
    _compilation.kept_arrays("things", (1,), build)
    assert len(calls) == 2  # damaged: built again
    _compilation.kept_arrays("things", (1,), build)
    assert len(calls) == 2  # and replaced
    assert [p.name for p in path.parent.iterdir()] == ["a.npz"]  # no temporary left behind


def test_kept_arrays_without_a_folder_or_unwritable(tmp_path, monkeypatch):
    build, calls = counting({"x": np.zeros(3)})
    monkeypatch.setattr(_compilation, "kept_path", lambda what, settings: None)
    for _ in range(2):
        assert np.array_equal(_compilation.kept_arrays("things", (1,), build)["x"], np.zeros(3))
    assert len(calls) == 2  # nothing kept
    blocker = tmp_path / "file"
    blocker.write_text("a file where the folder should be")
    monkeypatch.setattr(_compilation, "kept_path", lambda what, settings: blocker / "sub" / "a.npz")
    assert np.array_equal(_compilation.kept_arrays("things", (1,), build)["x"], np.zeros(3))
    assert len(calls) == 3 and blocker.read_text().startswith("a file")


def test_kept_path_names_settings_and_source():
    if _compilation.kept_path("things", (1,)) is None:
        pytest.skip("compiled programs are not kept in this run (JFACE_CACHE_DIR=off)")
    a, b = _compilation.kept_path("things", (1,)), _compilation.kept_path("things", (2,))
    assert a != b and a.parent == b.parent and a.parent.name == "jface-things"
    assert a == _compilation.kept_path("things", (1,))


def test_shipped_arrays_are_read_before_anything_is_built(tmp_path, monkeypatch):
    monkeypatch.setattr(_compilation, "kept_path", lambda what, settings: None)
    shipped = tmp_path / "shipped.npz"
    arrays = {"x": np.arange(3, dtype=np.int16), "0.y": np.ones(2, bool)}
    _compilation.write_arrays(shipped, _compilation.shipped_arrays("things", (1, "a"), arrays))
    build, calls = counting({"x": np.zeros(3)})
    got = _compilation.kept_arrays("things", (1, "a"), build, shipped)
    assert not calls and got.keys() == arrays.keys()
    assert all(got[k].dtype == a.dtype and np.array_equal(got[k], a) for k, a in arrays.items())
    for what, settings in (("things", (2, "a")), ("other", (1, "a"))):  # not shipped: built
        assert np.array_equal(
            _compilation.kept_arrays(what, settings, build, shipped)["x"], np.zeros(3)
        )
    assert len(calls) == 2
    shipped.write_bytes(b"PK\x03\x04 not a whole zip")  # a damaged install builds
    assert np.array_equal(
        _compilation.kept_arrays("things", (1, "a"), build, shipped)["x"], np.zeros(3)
    )
    assert len(calls) == 3
