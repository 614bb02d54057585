"""Files (EXR, PNG, npz), rendering and the command line."""

import json

import jax
import numpy as np
import pytest
from conftest import write_aged_maps
from PIL import Image

from jface import io, render
from jface.cli import main


def test_exr_round_trip_with_metadata(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.standard_normal((33, 47)).astype(np.float32)
    path = io.write_exr(tmp_path / "m.exr", data, metadata=io.provenance(seed=7, noise=0.1))
    back = io.read_exr(path)
    np.testing.assert_array_equal(back.channels["Y"], data)
    assert back.metadata["seed"] == 7 and back.metadata["noise"] == 0.1
    # what a rerun needs to repeat the bits: the versions and the kind of device
    assert back.metadata["jax_version"] == jax.__version__
    assert back.metadata["device"] == jax.devices()[0].device_kind
    np.testing.assert_array_equal(io.read_map(path), data)
    half = io.write_exr(tmp_path / "h.exr", data, half=True, compression="zip")
    np.testing.assert_allclose(io.read_map(half), data, rtol=1e-3, atol=1e-3)
    # A transposed view is not contiguous: it must still be written as what it shows.
    view = io.write_exr(tmp_path / "t.exr", data.T)
    np.testing.assert_array_equal(io.read_map(view), data.T)


def test_multichannel_exr_needs_a_channel_name(tmp_path):
    rgb = np.random.default_rng(1).random((8, 9, 3)).astype(np.float32)
    path = io.write_exr(tmp_path / "rgb.exr", rgb)
    with pytest.raises(ValueError, match="has 3 channels"):
        io.read_map(path)
    np.testing.assert_array_equal(io.read_map(path, channel="G"), rgb[..., 1])


def test_corrupt_and_truncated_files(tmp_path):
    data = np.ones((16, 16), np.float32)
    good = io.write_exr(tmp_path / "good.exr", data)
    truncated = tmp_path / "truncated.exr"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match="corrupt or truncated"):
        io.read_exr(truncated)
    (tmp_path / "junk.png").write_bytes(b"\x89PNG not really")
    with pytest.raises(ValueError, match="corrupt or truncated"):
        io.read_image(tmp_path / "junk.png")
    with pytest.raises(FileNotFoundError):
        io.read_exr(tmp_path / "missing.exr")
    io.save_arrays(tmp_path / "a.npz", {"x": data}, {"n": 1}, kind="Thing")
    with pytest.raises(ValueError, match="holds 'Thing', expected 'Other'"):
        io.load_arrays(tmp_path / "a.npz", kind="Other")


def test_writes_are_atomic_and_inputs_protected(tmp_path):
    target = io.write_exr(tmp_path / "keep.exr", np.zeros((4, 4), np.float32))
    before = target.read_bytes()
    with pytest.raises(TypeError, match="must be floating point"):
        io.write_exr(target, np.zeros((4, 4), np.int32))
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr"]  # no temporary left
    with pytest.raises(ValueError, match="refusing to overwrite the input"):
        io.write_exr(target, np.zeros((4, 4), np.float32), protect=(target,))
    with pytest.raises(ValueError, match=r"this output is PNG, so its name must end in \.png"):
        io.write_png(tmp_path / "keep.exr.tmp", np.zeros((4, 4)))


def test_a_session_records_its_planned_and_written_outputs(tmp_path):
    assert io.session_outputs() == ([], [])  # no session: nothing recorded
    with io.session():
        io.check_output(tmp_path / "later.json")
        io.write_json(tmp_path / "now.json", {})
        assert io.session_outputs() == ([tmp_path / "later.json", tmp_path / "now.json"], [])
        io.commit()
        assert io.session_outputs()[1] == [tmp_path / "now.json"]
        io.write_json(tmp_path / "dropped.json", {})
        io.discard()  # a discarded output was planned, never written
        planned, written = io.session_outputs()
        assert planned[-1] == tmp_path / "dropped.json" and written == [tmp_path / "now.json"]


def test_png_round_trip_and_metadata(tmp_path):
    grey = np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)
    path = io.write_png(tmp_path / "g.png", grey, metadata={"seed": 1})
    np.testing.assert_allclose(io.read_image(path), grey, atol=1 / 255)
    with Image.open(path) as img:
        assert json.loads(img.text["jface"]) == {"seed": 1}


def test_shade_shows_relief():
    x = np.linspace(-1, 1, 128)
    bump = np.exp(-(x[None] ** 2 + x[:, None] ** 2) * 20).astype(np.float32)
    image = render.shade(bump)
    assert image.shape == (128, 128) and image.min() >= 0 and image.max() <= 1
    # Lit from the top left: the top-left flank of the bump is brighter than the bottom-right.
    assert image[50, 50] > 0.55 > 0.45 > image[78, 78]
    # Scale-free, and no float32 overflow for huge (finite) heights.
    np.testing.assert_allclose(render.shade(bump * np.float32(3e37)), image, atol=1e-4)


def test_cli_analyze_synthesize_render(tmp_path, gravel, capsys):
    maps = []
    for i in range(3):
        path = tmp_path / f"face{i}.exr"
        io.write_exr(path, gravel[i * 64 : i * 64 + 256, :256].astype(np.float32))
        maps.append(str(path))
    stats_dir = tmp_path / "stats"
    assert main(["analyze", *maps[:2], "--out", str(stats_dir)]) == 0
    # Re-running keeps what an earlier (possibly interrupted) run finished.
    assert main(["analyze", *maps, "--out", str(stats_dir)]) == 0
    assert "analyzed 1 map(s), kept 2 already done" in capsys.readouterr().out
    assert (stats_dir / "face2.stats.png").exists()
    out = tmp_path / "synth.exr"
    code = main(
        [
            "synthesize",
            maps[0],
            "--stats",
            str(stats_dir / "face1.stats.npz"),
            "--out",
            str(out),
            "--seed",
            "3",
            "--iters",
            "4",
            "--json",
        ]
    )
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["median_tile_std_error"] < 0.15  # 2×2-pixel tiles at 256²: noisy estimates
    assert io.read_exr(out).metadata["seed"] == 3 and out.with_suffix(".png").exists()
    assert main(["render", str(out), "--out", str(tmp_path / "r.png")]) == 0
    # Bad input: one line on stderr, exit status 2, the input untouched.
    before = (tmp_path / "face0.exr").read_bytes()
    assert (
        main(
            ["synthesize", maps[0], "--stats", str(stats_dir / "face1.stats.npz"), "--out", maps[0]]
        )
        == 2
    )
    assert "refusing to overwrite the input" in capsys.readouterr().err
    assert (tmp_path / "face0.exr").read_bytes() == before
    assert main(["analyze", str(tmp_path / "nope.exr"), "--out", str(stats_dir)]) == 2
    # Two inputs that would share an output name are refused before anything is written.
    other = tmp_path / "sub"
    other.mkdir()
    twin = io.write_exr(other / "face0.exr", gravel[:256, :256].astype(np.float32))
    assert main(["analyze", maps[0], str(twin), "--out", str(tmp_path / "s2")]) == 2
    err = capsys.readouterr().err
    assert f"{maps[0]} and {twin} would both write the output 'face0.stats.npz'" in err
    # The shaded PNG beside the output must not replace an input either.
    png_input = tmp_path / "start.png"
    io.write_png(png_input, gravel[:256, :256])
    before = png_input.read_bytes()
    stats_file = str(stats_dir / "face1.stats.npz")
    code = main(
        [
            "synthesize",
            str(png_input),
            "--stats",
            stats_file,
            "--out",
            str(tmp_path / "start.exr"),
            "--iters",
            "1",
        ]
    )
    assert code == 2 and png_input.read_bytes() == before


def test_cli_db_build_and_compare(tmp_path, gravel, capsys):
    maps = write_aged_maps(tmp_path, gravel, (20, 35, 50, 65), 128)
    db = tmp_path / "db.npz"
    args = ["db", "build", *maps, "--out", str(db), "--metadata", str(tmp_path / "meta.json")]
    assert main([*args, "--grid", "8", "--scales", "3", "--chunk", "3"]) == 0
    png = tmp_path / "fig6.png"
    groups = ["--group", "young:age=20..40", "--group", "old:age=41..80"]
    assert main(["db", "compare", str(db), *groups, "--out", str(png)]) == 0
    table = json.loads(png.with_suffix(".json").read_text())
    assert table["reference"] == "young" and table["old"]["mean_ratio"] > 2
    assert png.exists()
    capsys.readouterr()
    assert (
        main(
            [
                "db",
                "compare",
                str(db),
                "--group",
                "x:age=1..2",
                "--group",
                "y:age=20..90",
                "--out",
                str(png),
            ]
        )
        == 2
    )
    assert "selection is empty" in capsys.readouterr().err
