"""Bad input on every command: an input named as output, corrupt, truncated and empty
files of every kind jface reads, wrong shapes, non-finite and huge values, folders and unwritable
paths as outputs, reruns after an edit, and a kill during a write.

For each refusal: exit status 2, one line on stderr naming the file (or argument) and what is
wrong, every input byte-identical afterwards, and no new file at all (no partial output, no
temporary).
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

from jface import _compilation, detail, faces, io, mesh
from jface.cli import _fit as cli_fit
from jface.cli import main
from jface.cli._mesh import write_face
from jface.mesh import LANDMARK_NAMES

RNG = np.random.default_rng(0)


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones included) and its bytes."""
    files = sorted(p for p in root.rglob("*") if p.is_file())
    return {str(p.relative_to(root)): p.read_bytes() for p in files}


def refused(root: Path, argv, capsys, *names: str) -> str:
    """Run ``jface ARGV``: it must exit with status 2 and one line naming each of ``names``,
    and leave every file under ``root`` as it was and nothing new. Returns the line."""
    capsys.readouterr()
    before = snapshot(root)
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("jface ")]
    assert code == 2, err
    assert len(lines) == 1 and lines[0] == err.strip().splitlines()[-1], err
    for name in names:
        assert str(name) in lines[0], lines[0]
    assert snapshot(root) == before, "an input changed, or something was written"
    return lines[0]


def noise(size: int = 64) -> np.ndarray:
    return RNG.standard_normal((size, size)).astype(np.float32)


def tetrahedron(path: Path, first: str = "v 0 0 0") -> Path:
    path.write_text(f"{first}\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    return path


@pytest.fixture(scope="module")
def face_folder(tmp_path_factory) -> Path:
    """A face folder as ``jface remesh`` writes it (a small remesh of the MediaPipe face)."""
    root = tmp_path_factory.mktemp("face")
    scan = mesh.synthetic_scan(jax.random.key(0), n_subdivisions=1)
    remeshed = mesh.remesh(
        scan.scan.vertices,
        np.asarray(scan.scan.faces),
        scan.landmarks,
        image_size=32,
        n_linear=1,
        n_loop=1,
        n_smooth=1,
    )
    write_face(root / "face", remeshed, io.provenance(), "obj")
    return root / "face"


@pytest.fixture
def files(tmp_path):
    """One good input of every kind jface reads, in ``tmp_path``."""
    np.save(tmp_path / "m.npy", noise())
    detail.save_stats(tmp_path / "st.npz", detail.analyze(noise(), grid=4, n_scales=2))
    stats = [detail.analyze(noise() * (1 + i), grid=4, n_scales=2) for i in range(4)]
    records = [{"id": f"f{i}", "age": 20 * i} for i in range(4)]
    detail.Population.from_faces(stats, records).save(tmp_path / "pop.npz")
    train = RNG.random((6, 12, 12)).astype(np.float32)
    faces.save_model(tmp_path / "model.npz", faces.fit_factor_analyser(train, 2, n_iter=2).model)
    (tmp_path / "p.json").write_text(
        '{"kind": "WrinkleParams", "units": {"frame": "uv"}, "levels": [{"d": 0.05}]}'
    )
    return {
        "m": io.write_exr(tmp_path / "m.exr", noise()),
        "png": io.write_png(tmp_path / "m.png", RNG.random((64, 64))),
        "npy": tmp_path / "m.npy",
        "stats": tmp_path / "st.npz",
        "pop": tmp_path / "pop.npz",
        "model": tmp_path / "model.npz",
        "params": tmp_path / "p.json",
        "obj": tetrahedron(tmp_path / "scan.obj"),
    }


GROUPS = ["--group", "a:age=0..25", "--group", "b:age=30..90"]


# --- inputs named as outputs -----------------------------------------------------------------


def test_every_command_refuses_its_input_as_output(files, face_folder, tmp_path, capsys):
    f, d = files, tmp_path
    for name in ("face", "average", "aged"):  # input faces where outputs would go
        shutil.copytree(face_folder, d / name)
    sub = d / "D"
    sub.mkdir()
    shutil.copy(f["params"], sub / "params.json")
    io.write_png(sub / "x.png", RNG.random((64, 64)))
    for i in range(3):
        io.write_png(sub / f"face_{i:03d}.png", RNG.random((12, 12)))
    os.link(f["pop"], d / "pop_link.png")  # hard links: another name, the same file
    os.link(f["m"], d / "m_link.json")
    os.symlink(f["png"], d / "alias.png")
    shutil.copy(f["png"], d / "m_convergence.png")  # named like an output of `fit --out m.json`
    shutil.copy(f["model"], d / "grid.png")  # a model named like an output of `faces sample`
    face = d / "face"
    cases = [
        (["analyze", f["m"], "--out", f["m"]], "is a file, not a folder"),
        (["synthesize", f["m"], "--stats", f["stats"], "--out", f["m"]], "refusing to overwrite"),
        (["render", f["png"], "--out", f["png"]], "refusing to overwrite"),
        (["render", d / "alias.png", "--out", f["png"]], "same file"),
        (["displace", f["obj"], f["m"], "--out", f["obj"]], "refusing to overwrite"),
        (["remesh", face / "base.obj", "--landmarks", f["params"], "--out", face], "base.obj"),
        (["db", "build", f["m"], "--out", f["m"]], "must end in .npz"),
        (["db", "compare", f["pop"], *GROUPS, "--out", d / "pop_link.png"], "same file"),
        (["interpolate", d / "average", face, "--out", d], "average/base.obj"),
        (["add-detail", face, "--stats", f["stats"], "--out", face], "face/base.obj"),
        (["age", d / "aged", face, "--out", d], "aged/base.obj"),
        (["faces", "train", f["png"], f["png"], "--out", f["png"]], "must end in .npz"),
        (["faces", "sample", d / "grid.png", "--out", d], "grid.png"),
        (["faces", "synth", sub, "--out", sub, "--n", "2"], "face_000.png"),
        (["wrinkles", "simulate", "--params", sub / "params.json", "--out", sub], "params.json"),
        # the PNG written beside the map would be the base
        (
            [
                "wrinkles",
                "render",
                "--params",
                f["params"],
                "--base",
                sub / "x.png",
                "--out",
                sub / "x.exr",
                "--size",
                "64",
            ],
            "x.png",
        ),
        (["wrinkles", "extract", f["m"], "--out", d / "m_link.json"], "same file"),
        (
            ["wrinkles", "extract", f["m"], "--out", d / "e.json", "--pores-out", d / "e.json"],
            "one file",
        ),
        (["wrinkles", "fit", f["m"], "--out", f["m"]], "is the input patch"),
        (["wrinkles", "fit", d / "m_convergence.png", "--out", d / "m.json"], "m_convergence.png"),
    ]
    for argv, fragment in cases:
        refused(d, argv, capsys, fragment)


# --- corrupt, truncated, empty files of every kind -------------------------------------------


def _corruptions(good: Path) -> dict[str, bytes]:
    data = good.read_bytes()
    flipped = bytearray(data)
    for i in range(len(data) // 3, len(data), max(1, len(data) // 7)):
        flipped[i] ^= 0xA5
    return {
        "truncated": data[: len(data) // 2],
        "empty": b"",
        "garbage": bytes(RNG.integers(0, 256, 300, dtype=np.uint8)),
        "bit flips": bytes(flipped),
    }


def _reader_commands(f, tmp_path, face_folder):
    """(kind, file to corrupt, command line reading it)."""
    face = tmp_path / "face"
    shutil.copytree(face_folder, face)
    meta = tmp_path / "meta.json"
    meta.write_text(json.dumps([{"id": "m", "age": 3}]))
    pores = tmp_path / "pores.json"
    pores.write_text(json.dumps({"kind": "Pores", "positions": [[0.5, 0.5]]}))
    landmarks = tmp_path / "l.csv"
    landmarks.write_text("".join(f"{n},{i % 4}\n" for i, n in enumerate(LANDMARK_NAMES)))
    ply = tmp_path / "scan.ply"
    mesh_data = io.read_mesh(f["obj"])
    io.write_mesh(ply, mesh_data.vertices, mesh_data.faces)
    out = tmp_path / "out"
    wr = ["wrinkles", "render", "--size", "64", "--out", out / "w.exr"]
    return [
        ("EXR map", f["m"], ["analyze", f["m"], "--out", out]),
        ("PNG map", f["png"], ["analyze", f["png"], "--out", out]),
        ("NPY map", f["npy"], ["analyze", f["npy"], "--out", out]),
        (
            "statistics",
            f["stats"],
            ["synthesize", f["m"], "--stats", f["stats"], "--out", out / "s.exr"],
        ),
        ("population", f["pop"], ["db", "compare", f["pop"], *GROUPS, "--out", out / "c.png"]),
        ("face model", f["model"], ["faces", "sample", f["model"], "--out", out]),
        (
            "face hierarchy",
            face / "hierarchy.npz",
            ["add-detail", face, "--stats", f["stats"], "--out", out],
        ),
        ("wrinkle parameters", f["params"], [*wr, "--params", f["params"]]),
        ("pores", pores, [*wr, "--params", f["params"], "--pores", pores]),
        ("records", meta, ["db", "build", f["m"], "--metadata", meta, "--out", out / "db.npz"]),
        ("landmarks", landmarks, ["remesh", f["obj"], "--landmarks", landmarks, "--out", out]),
        ("OBJ mesh", f["obj"], ["displace", f["obj"], f["m"], "--out", out / "d.obj"]),
        ("PLY mesh", ply, ["displace", ply, f["m"], "--out", out / "d.obj"]),
    ]


#: Formats with checksums: a flipped bit anywhere must be caught. (In the others a flipped bit
#: in the payload is another valid file: it can only be caught where it breaks the structure.)
CHECKSUMMED = ("PNG map", "statistics", "population", "face model", "face hierarchy")


def test_corrupt_truncated_and_empty_inputs_of_every_kind(files, face_folder, tmp_path, capsys):
    for kind, target, argv in _reader_commands(files, tmp_path, face_folder):
        good = target.read_bytes()
        for how, data in _corruptions(target).items():
            if how == "bit flips" and kind not in CHECKSUMMED:
                continue
            target.write_bytes(data)
            line = refused(tmp_path, argv, capsys)
            assert target.name in line, f"{kind}, {how}: {line}"
        target.write_bytes(good)


# --- wrong shapes, non-finite and huge values ------------------------------------------------


def _bomb_png(path: Path, side: int) -> Path:
    Image.new("L", (8, 8)).save(path)
    data = bytearray(path.read_bytes())
    data[16:24] = side.to_bytes(4, "big") * 2  # IHDR width and height
    data[29:33] = zlib.crc32(bytes(data[12:29])).to_bytes(4, "big")
    path.write_bytes(bytes(data))
    return path


def test_wrong_shapes_non_finite_and_huge_values(files, tmp_path, capsys):
    f, d = files, tmp_path
    np.save(d / "cube.npy", np.zeros((4, 4, 4), np.float32))
    np.save(d / "ints.npy", np.zeros((8, 8), np.int32))
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000, 1000000), }"
    header = header.ljust(118) + "\n"
    (d / "huge.npy").write_bytes(
        b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header.encode()
    )
    io.write_exr(d / "rgb.exr", RNG.random((8, 8, 3)).astype(np.float32))
    nan_map = noise()
    nan_map[3, 4] = np.inf
    io.write_exr(d / "nan.exr", nan_map)
    io.write_exr(d / "huge.exr", noise() * 1e30)
    window = bytearray(io.write_exr(d / "window.exr", noise(8), compression="none").read_bytes())
    at = window.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    window[at : at + 16] = np.array([0, 0, 2**31 - 2, 2**31 - 2], "<i4").tobytes()
    (d / "window.exr").write_bytes(bytes(window))  # declares 2³¹ × 2³¹ pixels
    _bomb_png(d / "bomb.png", 30000)
    tetrahedron(d / "nan.obj", "v nan nan nan\nv 0 0 0")
    (d / "huge.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n" + bytes(64)
    )
    arrays, meta = detail._stats.stats_to_arrays(detail.analyze(noise(), grid=4, n_scales=2))
    for name, dtype in (("int", np.int64), ("complex", np.complex64)):
        io.save_arrays(
            d / f"{name}.npz",
            {"std": np.asarray(arrays["std"]).astype(dtype)},
            io.provenance(**meta),
            kind="DetailStats",
        )
    marks = {name: i for i, name in enumerate(LANDMARK_NAMES)}
    landmark_files = {
        "list.json": "[1, 2, 3]",
        "nested.json": '{"landmarks": [[1, 2]]}',
        "short.json": json.dumps({**marks, "chin": [1.0, 2.0]}),
        "text.json": json.dumps({**marks, "chin": "left"}),
        "huge_id.json": json.dumps({**marks, "chin": 10**30}),
        "far_id.json": json.dumps({**marks, "chin": 9}),  # the scan has 4 vertices
        "huge_point.json": json.dumps({**marks, "chin": [1e39, 0, 0]}),
        "inf.csv": "nose_tip,1e400\n",
        "nan.csv": "nose_tip,nan\n",
        "fields.csv": "nose_tip,1,2\n",
        "deep.json": "[" * 100000 + "]" * 100000,
        "digits.json": '{"chin": 1' + "0" * 5000 + "}",
    }
    for name, text in landmark_files.items():
        (d / name).write_text(text)
    params = {
        "inf.json": '{"kind": "WrinkleParams", "levels": [{"theta": 1e400}]}',
        "bigint.json": '{"kind": "WrinkleParams", "levels": [{"d": 1%s}]}' % ("0" * 400),
        "float32.json": '{"kind": "WrinkleParams", "levels": [{"d": 1e39}]}',
        "ragged.json": '{"kind": "WrinkleParams", "levels": [{"d": [[0.05, 0.05], [1]]}]}',
        "cube.json": '{"kind": "WrinkleParams", "levels": [{"d": [[[0.05]]]}]}',
        "unknown.json": '{"kind": "WrinkleParams", "levels": [{"depth": 1}]}',
        "nolevels.json": '{"kind": "WrinkleParams"}',
        "nokind.json": '{"levels": [{"d": 0.05}]}',
    }
    pores = {
        "nokey.json": {"kind": "Pores"},
        "shape.json": {"kind": "Pores", "positions": [[0.1, 0.2, 0.3]]},
        "outside.json": {"kind": "Pores", "positions": [[0.1, 1.5]]},
        "text_pores.json": {"kind": "Pores", "positions": [["a", "b"]]},
    }
    for name, text in params.items():
        (d / name).write_text(text)
    for name, data in pores.items():
        (d / name).write_text(json.dumps(data))
    (d / "pnan.json").write_text('{"kind": "Pores", "positions": [[NaN, 0.5]]}')
    records = {
        "obj.json": '{"id": 1}',
        "count.json": '[{"id": 1}]',
        "noid.json": '[{"age": 1}, {"id": 2}]',
        "dup.json": '[{"id": 1}, {"id": 1}]',
    }
    for name, text in records.items():
        (d / name).write_text(text)
    out = d / "out"
    wr = ["wrinkles", "render", "--size", "64", "--out", out / "w.exr"]
    cases = [
        (["analyze", d / "cube.npy", "--out", out], "cube.npy"),
        (["analyze", d / "ints.npy", "--out", out], "ints.npy"),
        (["analyze", d / "huge.npy", "--out", out], "huge.npy"),
        (["analyze", d / "rgb.exr", "--out", out], "rgb.exr"),
        (["analyze", d / "nan.exr", "--out", out], "nan.exr"),
        (["analyze", d / "huge.exr", "--out", out], "huge.exr"),
        (["analyze", d / "window.exr", "--out", out], "window.exr"),
        (["db", "build", d / "window.exr", "--out", out / "db.npz"], "window.exr"),
        (["analyze", d / "bomb.png", "--out", out], "bomb.png"),
        (["displace", d / "nan.obj", f["m"], "--out", out / "o.obj"], "nan.obj"),
        (["displace", d / "huge.ply", f["m"], "--out", out / "o.obj"], "huge.ply"),
        (["synthesize", f["m"], "--stats", d / "int.npz", "--out", out / "s.exr"], "int.npz"),
        (
            ["synthesize", f["m"], "--stats", d / "complex.npz", "--out", out / "s.exr"],
            "complex.npz",
        ),
        *[(["remesh", f["obj"], "--landmarks", d / n, "--out", out], n) for n in landmark_files],
        *[([*wr, "--params", d / n], n) for n in params],
        *[([*wr, "--params", f["params"], "--pores", d / n], n) for n in [*pores, "pnan.json"]],
        *[
            (["db", "build", f["m"], f["png"], "--metadata", d / n, "--out", out / "db.npz"], n)
            for n in records
        ],
        (
            [
                "db",
                "compare",
                f["pop"],
                "--group",
                "a:age=x..y",
                "--group",
                "b:age=1..2",
                "--out",
                out / "c.png",
            ],
            "a:age=x..y",
        ),
    ]
    for argv, name in cases:
        refused(d, argv, capsys, name)


def test_constant_training_images_are_refused(tmp_path, capsys):
    images = [io.write_png(tmp_path / f"c{i}.png", np.full((12, 12), 0.1 * i)) for i in range(4)]
    images += [io.write_png(tmp_path / f"r{i}.png", RNG.random((12, 12))) for i in range(4)]
    argv = ["faces", "train", *images, "--out", tmp_path / "model.npz", "--factors", "2"]
    assert "constant image" in refused(tmp_path, argv, capsys, "c0.png")


def test_db_build_checks_every_size_before_any_work(tmp_path, capsys, monkeypatch):
    maps = [io.write_exr(tmp_path / f"m{i}.exr", noise()) for i in range(3)]
    maps.insert(2, io.write_exr(tmp_path / "small.exr", noise(32)))
    calls = []
    monkeypatch.setattr(detail._database, "analyze_batch", lambda *a, **k: calls.append(a))
    argv = ["db", "build", *maps, "--out", tmp_path / "db.npz", "--chunk", "1"]
    assert "must have one size" in refused(tmp_path, argv, capsys, "small.exr", "m0.exr")
    assert calls == []


def test_wrinkles_fit_checks_every_patch_before_any_work(tmp_path, capsys, monkeypatch):
    """A batch whose third patch is not square stops before the first is fitted, naming that
    patch; so does a constant one."""
    patches = [tmp_path / f"p{i}.npy" for i in range(3)]
    for path in patches:
        np.save(path, noise())
    np.save(tmp_path / "wide.npy", RNG.standard_normal((64, 80)).astype(np.float32))
    np.save(tmp_path / "flat.npy", np.ones((64, 64), np.float32))
    calls = []
    monkeypatch.setattr(cli_fit, "fit_wrinkles", lambda *a, **k: calls.append(a))
    for bad, what in (("wide.npy", "must be square"), ("flat.npy", "is constant")):
        argv = ["wrinkles", "fit", *patches[:2], tmp_path / bad, patches[2], "--out", tmp_path]
        assert what in refused(tmp_path, argv, capsys, bad)
    assert calls == []


# --- outputs that cannot be written ----------------------------------------------------------


def test_folders_and_unwritable_paths_as_outputs(files, tmp_path, capsys):
    f = files
    (tmp_path / "folder.png").mkdir()
    (tmp_path / "file.txt").write_text("x")
    if os.geteuid() == 0:  # permissions do not stop root; a read-only file system does
        locked = Path("/sys/jface-reliability")
    else:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
    cases = [
        (tmp_path / "folder.png", "it is a folder"),
        (tmp_path / "file.txt" / "sub" / "o.png", "file.txt is a file, not a folder"),
        (locked / "o.png", "cannot write"),
    ]
    for out, fragment in cases:
        line = refused(tmp_path, ["render", f["m"], "--out", out], capsys, out, fragment)
        assert "Traceback" not in line
    refused(tmp_path, ["analyze", f["m"], "--out", tmp_path / "file.txt"], capsys, "file.txt")


def test_a_failure_after_the_first_output_leaves_nothing(files, tmp_path, capsys, monkeypatch):
    """Outputs are staged: when the second of a command's outputs fails, the first one (already
    complete) is not put in place either."""
    from jface.cli import _detail

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_detail.io, "write_png", broken)
    argv = [
        "synthesize",
        files["m"],
        "--stats",
        files["stats"],
        "--out",
        tmp_path / "s.exr",
        "--iters",
        "1",
    ]
    assert "No space left on device" in refused(tmp_path, argv, capsys)


# --- reruns after an edit --------------------------------------------------------------------


def test_analyze_reruns_recompute_what_changed(tmp_path, capsys):
    m = io.write_exr(tmp_path / "m.exr", noise())
    other = io.write_exr(tmp_path / "n.exr", noise())
    out = tmp_path / "stats"

    def run(*extra):
        assert main(["analyze", str(m), str(other), "--out", str(out), *extra]) == 0
        return capsys.readouterr().out

    def stats_of(path, **layout):
        return np.asarray(detail.analyze(io.read_map(path), **layout).std)

    assert "analyzed 2 map(s), kept 0" in run("--grid", "4", "--scales", "2")
    assert "analyzed 0 map(s), kept 2" in run("--grid", "4", "--scales", "2")
    edited = io.write_exr(m, noise() * 3)
    assert "analyzed 1 map(s), kept 1" in run("--grid", "4", "--scales", "2")
    np.testing.assert_allclose(
        detail.load_stats(out / "m.stats.npz").stats.std, stats_of(edited, grid=4, n_scales=2)
    )
    assert "analyzed 2 map(s), kept 0" in run("--grid", "8", "--scales", "2")
    assert detail.load_stats(out / "n.stats.npz").stats.grid == 8
    (out / "n.stats.png").unlink()  # a lost picture is made again
    assert "analyzed 1 map(s), kept 1" in run("--grid", "8", "--scales", "2")


def test_reruns_with_other_jface_code_recompute(tmp_path, capsys, monkeypatch):
    """A result made by other jface code is not reused, also when the version number is the
    same (an upgrade from source, an edit)."""
    m = io.write_exr(tmp_path / "m.exr", noise())
    argv = ["analyze", str(m), "--out", str(tmp_path / "stats"), "--grid", "4", "--scales", "2"]
    assert main(argv) == 0 and "analyzed 1 map(s), kept 0" in capsys.readouterr().out
    assert main(argv) == 0 and "analyzed 0 map(s), kept 1" in capsys.readouterr().out
    monkeypatch.setattr(_compilation, "source_digest", lambda: "other code")
    assert main(argv) == 0 and "analyzed 1 map(s), kept 0" in capsys.readouterr().out


def test_db_build_resume_reuses_only_unchanged_chunks(tmp_path, capsys, monkeypatch):
    maps = [io.write_exr(tmp_path / f"m{i}.exr", noise()) for i in range(3)]
    good = maps[2].read_bytes()
    maps[2].write_bytes(good[: len(good) * 2 // 3])  # header intact: dies at the third chunk
    out = tmp_path / "db.npz"
    argv = [*map(str, maps), "--out", str(out), "--grid", "4", "--scales", "2", "--chunk", "1"]
    assert main(["db", "build", *argv]) == 2
    assert "m2.exr" in capsys.readouterr().err and not out.exists()
    assert len(list((tmp_path / "db.npz.parts").glob("*.npz"))) == 2  # finished chunks kept
    edited = noise() * 4
    io.write_exr(maps[0], edited)
    maps[2].write_bytes(good)
    analysed = []
    real = detail._database.analyze_batch
    monkeypatch.setattr(
        detail._database, "analyze_batch", lambda x, **k: analysed.append(x) or real(x, **k)
    )
    assert main(["db", "build", *argv]) == 0
    assert len(analysed) == 2  # the edited map and the one that failed; m1 was reused
    population = detail.Population.load(out)
    expected = [edited, io.read_map(maps[1]), io.read_map(maps[2])]
    for i, image in enumerate(expected):
        np.testing.assert_allclose(
            population.stats.std[i], detail.analyze(image, grid=4, n_scales=2).std, rtol=1e-5
        )
    assert not (tmp_path / "db.npz.parts").exists()


def test_db_build_gives_maps_of_one_name_unique_ids(tmp_path):
    for folder in ("young", "old"):
        (tmp_path / folder).mkdir()
    maps = [io.write_exr(tmp_path / f / "face.exr", noise()) for f in ("young", "old")]
    out = tmp_path / "db.npz"
    assert main(["db", "build", *map(str, maps), "--out", str(out), "--grid", "4",
                 "--scales", "2"]) == 0  # fmt: skip
    assert [r["id"] for r in detail.Population.load(out).records] == ["young/face", "old/face"]


# --- killed and terminated writers -----------------------------------------------------------

_DIES_WHILE_WRITING = """
import os, signal, sys
from jface.cli import main
from jface.io import _files

def die(tmp, path):  # the output is complete in its temporary file; the rename never comes
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))

_files._replace = die
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("how", ["SIGKILL", "SIGTERM"])
def test_killed_command_leaves_no_output_and_next_run_sweeps(files, tmp_path, how):
    out = tmp_path / "shaded.png"
    argv = ["render", str(files["m"]), "--out", str(out)]
    before = snapshot(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_DIES_WHILE_WRITING), how, *argv],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    left = sorted(set(snapshot(tmp_path)) - set(before))
    assert not out.exists()
    if how == "SIGTERM":  # turned into an interrupt: the temporary file is removed at once
        assert proc.returncode == 130 and "interrupted" in proc.stderr, proc.stderr
        assert left == []
    else:  # nothing can clean up after SIGKILL ...
        assert proc.returncode == -signal.SIGKILL
        assert len(left) == 1 and left[0].startswith(".shaded.png~jface-"), left
        assert main(argv) == 0  # ... the next run writing there removes the dead one's file
        assert sorted(set(snapshot(tmp_path)) - set(before)) == ["shaded.png"]
    assert snapshot(tmp_path).items() >= before.items()  # inputs unchanged


def test_same_seed_same_bytes(files, tmp_path):
    """A command run twice with the same inputs and seed writes identical files."""
    f = files
    shutil.copy(f["png"], tmp_path / "n.png")
    (tmp_path / "levels.json").write_text(
        '{"kind": "WrinkleParams", "units": {"frame": "uv"}, "levels": [{"d": 0.05, "theta": 0.5}]}'
    )
    commands = [
        ["synthesize", f["m"], "--stats", f["stats"], "--out", "{out}/s.exr", "--seed", "3",
         "--iters", "2"],
        ["analyze", f["m"], tmp_path / "n.png", "--out", "{out}/stats", "--grid", "4",
         "--scales", "2"],
        ["db", "build", f["m"], f["png"], "--out", "{out}/db.npz", "--grid", "4", "--scales",
         "2"],
        ["wrinkles", "render", "--params", tmp_path / "levels.json", "--out", "{out}/w.exr",
         "--size", "64", "--steps", "5", "--seed", "2"],
        ["faces", "sample", f["model"], "--n", "3", "--seed", "1", "--out", "{out}"],
    ]  # fmt: skip
    runs = []
    for name in ("first", "second"):
        out = tmp_path / name
        for argv in commands:
            assert main([str(a).replace("{out}", str(out)) for a in argv]) == 0
        files = snapshot(out)  # the run pages record times and the command line: not compared
        assert {"index.html", "stats/index.html"} <= set(files)
        runs.append({name: data for name, data in files.items() if "index.html" not in name})
    assert runs[0] == runs[1]
    assert len(runs[0]) == 13  # EXR + PNG, 2 × (npz + PNG), npz, EXR + PNG, 3 + 1 PNGs
