"""Fuzzed input files (hypothesis): good files of every kind jface reads, truncated, overwritten,
grown or replaced by random bytes. Whatever the bytes, a reader returns data or raises
``ValueError``/``TypeError`` naming the file, never another exception; a command fed the file
exits with 0 or 2 and leaves no temporary file, its input unchanged.

``JFACE_FUZZ_EXAMPLES`` sets the examples per reader (default 12, to keep the suite fast);
``benchmarks/fuzz_inputs.py`` runs the same tests with many more.
"""

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jface import detail, faces, io, wrinkles
from jface.cli import main
from jface.mesh import LANDMARK_NAMES

EXAMPLES = int(os.environ.get("JFACE_FUZZ_EXAMPLES", "12"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,  # nothing written into the repository
    derandomize=EXAMPLES <= 100,  # the suite is deterministic; long runs explore
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _good_files() -> dict[str, tuple[str, bytes]]:
    """name → (suffix, bytes) of one valid file per kind."""
    rng = np.random.default_rng(0)
    image = rng.standard_normal((32, 32)).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        io.write_exr(d / "m.exr", image)
        io.write_png(d / "m.png", rng.random((32, 32)))
        np.save(d / "m.npy", image)
        detail.save_stats(d / "s.npz", detail.analyze(image, grid=2, n_scales=2))
        stats = [detail.analyze(image * (1 + i), grid=2, n_scales=2) for i in range(2)]
        detail.Population.from_faces(stats, [{"id": 0}, {"id": 1}]).save(d / "p.npz")
        train = rng.random((5, 6, 6)).astype(np.float32)
        faces.save_model(d / "f.npz", faces.fit_factor_analyser(train, 2, n_iter=1).model)
        wrinkles.save_params(d / "w.json", wrinkles.WrinkleParams(d=0.05), "uv")
        io.write_landmarks(d / "l.json", {n: i for i, n in enumerate(LANDMARK_NAMES)})
        (d / "l.csv").write_text("".join(f"{n},{i}\n" for i, n in enumerate(LANDMARK_NAMES)))
        tetra = (np.eye(4, 3), np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]))
        io.write_mesh(d / "t.obj", *tetra, uv=np.zeros((4, 2)))
        io.write_mesh(d / "t.ply", *tetra, uv=np.zeros((4, 2)))
        return {p.stem + p.suffix: (p.suffix, p.read_bytes()) for p in d.iterdir()}


GOOD = _good_files()

#: file → the reader that must cope with any bytes under that name
READERS: dict[str, Callable[[Path], object]] = {
    "m.exr": io.read_map,
    "m.png": io.read_map,
    "m.npy": io.read_map,
    "s.npz": detail.load_stats,
    "p.npz": detail.Population.load,
    "f.npz": faces.load_model,
    "w.json": wrinkles.load_params,
    "l.json": io.read_landmarks,
    "l.csv": io.read_landmarks,
    "t.obj": io.read_mesh,
    "t.ply": io.read_mesh,
}


def mutations(good: bytes) -> st.SearchStrategy[bytes]:
    """Truncated, overwritten in place, grown, or random bytes."""
    n = len(good)
    return st.one_of(
        st.integers(0, n - 1).map(lambda k: good[:k]),
        st.tuples(st.integers(0, n - 1), st.binary(min_size=1, max_size=16)).map(
            lambda t: good[: t[0]] + t[1] + good[t[0] + len(t[1]) :]
        ),
        st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=64)).map(
            lambda t: good[: t[0]] + t[1] + good[t[0] :]
        ),
        st.binary(max_size=512),
    )


@pytest.mark.parametrize("name", sorted(READERS))
def test_readers_refuse_bad_bytes_with_a_message(name, unchecked):
    _, good = GOOD[name]

    @FUZZ
    @given(data=mutations(good))
    def check(data):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / name
            path.write_bytes(data)
            try:
                READERS[name](path)
            except (ValueError, TypeError) as err:
                assert str(path) in str(err), f"{type(err).__name__} without the file: {err}"

    check()


@pytest.mark.parametrize("name", ["m.exr", "m.png", "m.npy"])
def test_a_command_fed_bad_bytes_exits_cleanly(name, capsys):
    _, good = GOOD[name]

    @FUZZ
    @given(data=mutations(good))
    def check(data):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / name
            path.write_bytes(data)
            code = main(["render", str(path), "--out", str(Path(tmp) / "out" / "r.png")])
            err = capsys.readouterr().err
            assert code in (0, 2), err
            assert path.read_bytes() == data
            left = sorted(p.name for p in Path(tmp).rglob("*") if p.is_file())
            assert left == (sorted([name, "r.png"]) if code == 0 else [name]), left
            if code == 2:
                assert len(err.strip().splitlines()) == 1 and name in err, err

    check()


def test_good_files_are_read():
    """The seeds themselves are valid: the fuzzing starts from files the readers accept."""
    with tempfile.TemporaryDirectory() as tmp:
        for name, reader in READERS.items():
            path = Path(tmp) / name
            path.write_bytes(GOOD[name][1])
            reader(path)
        assert json.loads(GOOD["w.json"][1])["kind"] == "WrinkleParams"
