"""The README runs as written: every Python block, in order, in a fresh working directory, and
every row of its command table on small built-in inputs (issue 25: a newcomer's first hour).

A row of the command table is found by its command name (``db build``, ``faces train``, ...);
:data:`ROWS` says how this test runs it and what it must write. A new row without an entry fails
the test with a message asking for one, and so does an entry whose row is gone.
"""

import re
from pathlib import Path

import numpy as np
from conftest import TINY_FIT

from jface import data, io
from jface.cli import main
from jface.cli._faces import face_renders

README = Path(__file__).resolve().parents[1] / "README.md"

#: The shipped head scan and its hand-placed landmarks, as a user would name them.
SCAN = str(data.path("lee_perry_smith_head.obj"))
LANDMARKS = str(data.path("lee_perry_smith_landmarks.json"))
#: Records of the six maps of the database: ages that fill the README's groups.
AGES = (22, 28, 52, 58, 65, 75)

#: Command name → (arguments, files it must write), run in this order in one working directory
#: that holds the inputs of :func:`_inputs`; later rows read what earlier ones wrote. Sizes and
#: iteration counts are the rows' own options, made small.
# fmt: off
ROWS = {
    "demo": (["demo", "--out", "demo"], ["demo/index.html", "demo/age/comparison.png"]),
    "analyze": (
        ["analyze", "m0.exr", "m1.exr", "--out", "stats"],
        ["stats/m0.stats.npz", "stats/m0.stats.png", "stats/m1.stats.npz"],
    ),
    "synthesize": (
        ["synthesize", "m1.exr", "--stats", "stats/m0.stats.npz", "--out", "out.exr"],
        ["out.exr", "out.png"],
    ),
    "render": (["render", "m0.exr", "--out", "m0.png"], ["m0.png"]),
    "landmarks": (
        ["landmarks", SCAN, "--out", "L.json", "--picture", "P.png"],
        ["L.json", "P.png"],
    ),
    "remesh": (
        ["remesh", SCAN, "--landmarks", LANDMARKS, "--out", "face", "--image-size", "256"],
        ["face/base.obj", "face/displacement.exr", "face/hierarchy.npz", "face/filled.png"],
    ),
    "displace": (
        ["displace", "face/base.obj", "face/displacement.exr", "--out", "detailed.obj"],
        ["detailed.obj"],
    ),
    "db build": (
        ["db", "build", *(f"m{i}.exr" for i in range(6)), "--out", "db.npz",
         "--metadata", "records.json", "--chunk", "4"],
        ["db.npz"],
    ),
    "db compare": (
        ["db", "compare", "db.npz", "--group", "young:age=20..30", "--group", "old:age=50..60",
         "--out", "fig.png"],
        ["fig.png", "fig.json"],
    ),
    "interpolate": (
        ["interpolate", "face", "rough", "--out", "mixed", "--weights", "0.5,0.5"],
        ["mixed/average/base.obj", "mixed/coerced/displacement.exr", "mixed/interpolation.json"],
    ),
    "add-detail": (
        ["add-detail", "face", "--db", "db.npz", "--group", "age=60..80", "--out", "added"],
        ["added/displacement.exr", "added/before_after.png", "added/add_detail.json"],
    ),
    "age": (
        ["age", "face", "rough", "--out", "aged", "--levels", "3"],
        ["aged/aged/base.obj", "aged/comparison.png", "aged/comparison.json"],
    ),
    "faces train": (
        ["faces", "train", "renders", "--out", "model.npz", "--factors", "4", "--iters", "10"],
        ["model.npz"],
    ),
    "faces sample": (
        ["faces", "sample", "model.npz", "--n", "4", "--seed", "0", "--out", "samples"],
        ["samples/sample_000.png", "samples/grid.png"],
    ),
    "wrinkles simulate": (
        ["wrinkles", "simulate", "--out", "sim", "--levels", "1", "--d", "0.05", "--steps", "5"],
        ["sim/wrinkles.npz", "sim/params.json", "sim/wrinkles.png"],
    ),
    "wrinkles render": (
        ["wrinkles", "render", "--simulation", "sim", "--out", "w.exr", "--size", "64"],
        ["w.exr", "w.png"],
    ),
    "wrinkles extract": (
        ["wrinkles", "extract", str(data.path("gravel.exr")), "--out", "p.json"],
        ["p.json", "p_pores.json"],
    ),
    "wrinkles fit": (
        ["wrinkles", "fit", "w.exr", "--out", "fit.json", *TINY_FIT, "--iters", "2"],
        ["fit.json", "fit_convergence.png", "fit_target_fit.png"],
    ),
    "faces synth": (
        ["faces", "synth", "renders", "--out", "synth", "--n", "2", "--model", "model.npz"],
        ["synth/face_000.png", "synth/faces.png", "synth/summary.json"],
    ),
    "faces align": (
        ["faces", "align", "renders/f00.png", "renders/f01.png", "--out", "aligned",
         "--template", "renders/f02.png"],
        ["aligned/transforms.json"],
    ),
    "faces inpaint": (
        ["faces", "inpaint", "renders", "--image", "renders/f00.png", "--mask", "mask.png",
         "--out", "inpainted", "--n", "2"],
        ["inpainted/inpainted_000.png", "inpainted/inpainting.png"],
    ),
    "faces edit": (
        ["faces", "edit", "renders", "--image", "renders/f00.png", "--painted", "painted.png",
         "--out", "edited"],
        ["edited/edited.png", "edited/edit.png"],
    ),
    "faces restyle": (
        ["faces", "restyle", "smiling", "--model", "bilinear.npz", "--image", "neutral/p00.png",
         "--out", "restyled"],
        ["restyled/restyled.png", "restyled/restyle.png"],
    ),
}
# fmt: on


def _python_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", README.read_text(), re.S | re.M)


def _table_commands() -> list[str]:
    """The command name of every row of the README's command table(s): the lowercase words after
    ``jface`` (``db build``, ``add-detail``), up to the first argument or option."""
    names = []
    for row in re.findall(r"^\| `jface ([^`]*)`", README.read_text(), re.M):
        words = []
        for word in row.split():
            if not re.fullmatch(r"[a-z][a-z-]*", word):
                break
            words.append(word)
        names.append(" ".join(words))
    return names


def test_python_blocks_run_as_written(tmp_path, monkeypatch):
    blocks = _python_blocks()
    assert len(blocks) >= 5
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__readme__"}
    for i, block in enumerate(blocks):  # later blocks use what earlier ones defined
        exec(compile(block, f"README.md python block {i + 1}", "exec"), namespace)


def test_every_table_row_has_an_entry_here():
    names = _table_commands()
    missing = [name for name in names if name not in ROWS]
    assert not missing, (
        f"README command table rows without a test here: {missing}; add each to ROWS in "
        "tests/test_readme.py (arguments on small built-in inputs, and the files it writes)"
    )
    assert sorted(set(ROWS) - set(names)) == [], "ROWS entries whose README row is gone"
    assert len(names) == len(set(names)), "two README rows of one command"


def _inputs(folder: Path) -> None:
    """Small built-in inputs, named as the rows use them."""
    gravel = data.gravel()
    for i in range(len(AGES)):  # 256² (16 × 16 tiles of 4 scales), in metres like the scan
        crop = gravel[32 * i : 32 * i + 256, :256] * 1e-4 * (1 + i / 2)  # rougher with age
        io.write_exr(folder / f"m{i}.exr", crop.astype(np.float32))
    io.write_json(folder / "records.json", [{"id": f"m{i}", "age": a} for i, a in enumerate(AGES)])
    variant = data.scan_variants(*data.lee_perry_smith()[0][:2], data.lee_perry_smith()[1],
                                 kinds=("noise",))["noise"]  # fmt: skip
    io.write_mesh(folder / "rough.obj", variant.vertices, variant.faces)
    io.write_landmarks(folder / "rough.json", variant.landmarks)
    assert main(["remesh", "rough.obj", "--landmarks", "rough.json", "--out", "rough",
                 "--image-size", "256"]) == 0  # fmt: skip
    for i, image in enumerate(face_renders(0, 24, 24)):
        io.write_png(folder / "renders" / f"f{i:02d}.png", np.clip(image, 0, 1))
    mask = np.zeros((24, 24), np.float32)
    mask[14:20, 6:18] = 1.0  # the mouth
    io.write_png(folder / "mask.png", mask)
    painted = np.clip(face_renders(0, 1, 24)[0], 0, 1)
    painted[15:17, 6:18] = 0.1  # a dark stroke: a mustache
    io.write_png(folder / "painted.png", painted)
    for style, smile in (("neutral", 0.0), ("smiling", 1.0)):
        for i, image in enumerate(face_renders(3, 12, 24, smile=smile)):
            io.write_png(folder / style / f"p{i:02d}.png", np.clip(image, 0, 1))
    assert main(["faces", "train", "--bilinear", "neutral", "smiling", "--factors", "3",
                 "--iters", "5", "--out", "bilinear.npz"]) == 0  # fmt: skip


def test_command_table_rows_run_on_small_inputs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _inputs(tmp_path)
    for name, (argv, outputs) in ROWS.items():
        assert main(argv) == 0, f"jface {' '.join(argv)}: {capsys.readouterr().err[-2000:]}"
        for output in outputs:
            assert (tmp_path / output).is_file(), f"jface {name} did not write {output}"
