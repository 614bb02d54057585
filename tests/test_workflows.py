"""Workflows that chain: what one step writes, the next reads."""

import json

import numpy as np
import pytest

from jface import data, faces, io, mesh
from jface.cli import main
from jface.cli._faces import face_renders


def test_landmarks_of_a_mediapipe_face_round_trip_through_io(tmp_path):
    points = np.asarray(mesh.mediapipe_landmarks(data.mediapipe_face().vertices))
    path = io.write_landmarks(tmp_path / "mp.json", points)
    back = io.read_landmarks(path, names=mesh.LANDMARK_NAMES)
    assert list(back) == list(mesh.LANDMARK_NAMES)  # template order, every name
    np.testing.assert_array_equal(np.array([back[n] for n in mesh.LANDMARK_NAMES]), points)
    # named rows of any count, and the shapes that name nothing are refused
    io.write_landmarks(tmp_path / "two.json", points[:2], names=["a", "b"])
    assert list(io.read_landmarks(tmp_path / "two.json")) == ["a", "b"]
    with pytest.raises(ValueError, match="got shape \\(2, 3\\) and no names"):
        io.write_landmarks(tmp_path / "x.json", points[:2])
    with pytest.raises(ValueError, match="got shape \\(21, 2\\)"):
        io.write_landmarks(tmp_path / "x.json", points[:, :2])


def test_faces_train_bilinear_makes_the_model_restyle_needs(tmp_path, capsys):
    folders = {}
    for style, smile in (("neutral", 0.0), ("smiling", 1.0)):
        folders[style] = tmp_path / style
        for i, image in enumerate(face_renders(3, 12, 24, smile=smile)):
            io.write_png(folders[style] / f"p{i:02d}.png", np.clip(image, 0, 1))
    model_path = tmp_path / "bilinear.npz"
    argv = ["faces", "train", "--bilinear", str(folders["neutral"]), str(folders["smiling"])]
    assert main([*argv, "--factors", "3", "--iters", "5", "--out", str(model_path)]) == 0
    model = faces.load_model(model_path).model
    assert isinstance(model, faces.BilinearModel) and model.n_styles == 2
    # the same fit as the library's on the faces read back, styles paired by file name
    stacked = np.stack(
        [np.stack([io.read_image(f, grey=True) for f in sorted(folders[s].iterdir())])
         for s in ("neutral", "smiling")], axis=1,
    )  # fmt: skip
    expected = faces.fit_bilinear(stacked.astype(np.float32), 3, n_iter=5).model
    np.testing.assert_allclose(model.stacked.mean, expected.stacked.mean, atol=1e-6)
    capsys.readouterr()
    out = tmp_path / "restyled"
    restyle = ["faces", "restyle", str(folders["smiling"]), "--model", str(model_path),
               "--image", str(folders["neutral"] / "p00.png"), "--grid", "4", "--grey",
               "--out", str(out), "--json"]  # fmt: skip
    assert main(restyle) == 0
    assert json.loads(capsys.readouterr().out) == {"out": str(out)}
    assert io.read_image(out / "restyled.png", grey=True).shape == (24, 24)
    # style folders must pair the same people
    (folders["smiling"] / "p00.png").rename(folders["smiling"] / "q00.png")
    assert main([*argv, "--out", str(tmp_path / "b2.npz")]) == 2
    assert "differ in ['p00.png', 'q00.png']" in capsys.readouterr().err


def test_wrinkles_render_draws_what_simulate_wrote(tmp_path, capsys):
    sim = tmp_path / "sim"
    argv = ["wrinkles", "simulate", "--out", str(sim), "--d", "0.05", "--steps", "3"]
    assert main([*argv, "--seed", "3", "--size", "32"]) == 0
    capsys.readouterr()
    reused, again = tmp_path / "reused.exr", tmp_path / "again.exr"
    assert main(["wrinkles", "render", "--simulation", str(sim), "--out", str(reused),
                 "--size", "32", "--json"]) == 0  # fmt: skip
    pores = json.loads(capsys.readouterr().out)["pores"]
    stored, _ = io.load_arrays(sim / "wrinkles.npz", kind="WrinkleGraph")
    assert pores == [len(stored["level0_positions"])]  # the simulation's pores, not new ones
    # the same map as simulating again with the simulation's seed and settings
    assert main(["wrinkles", "render", "--params", str(sim / "params.json"), "--seed", "3",
                 "--steps", "3", "--out", str(again), "--size", "32"]) == 0  # fmt: skip
    np.testing.assert_array_equal(io.read_map(reused), io.read_map(again))
    assert io.read_exr(reused).metadata["simulation"] == str(sim)
    assert main(["wrinkles", "render", "--simulation", str(sim), "--steps", "2",
                 "--out", str(tmp_path / "x.exr")]) == 2  # fmt: skip
    assert "--steps" in capsys.readouterr().err


def test_wrinkles_extract_warns_when_it_finds_no_pores(tmp_path, capsys):
    smooth = io.write_exr(tmp_path / "smooth.exr", np.zeros((128, 128), np.float32))
    assert main(["wrinkles", "extract", str(smooth), "--out", str(tmp_path / "p.json")]) == 0
    captured = capsys.readouterr()
    assert "warning: no pores found on" in captured.err and "--threshold" in captured.err
    assert io.read_json(tmp_path / "p_pores.json")["positions"] == []


def test_small_faces_get_a_grid_that_fits_and_figures_of_a_usable_size(
    tmp_path, capsys, written_figures
):
    from skimage.data import lfw_subset

    lfw = tmp_path / "lfw"
    for i, face in enumerate(lfw_subset()[:24]):  # 25×25 px crops
        io.write_png(lfw / f"f{i:02d}.png", face)
    out = tmp_path / "synth"
    argv = ["faces", "synth", str(lfw), "--grey", "--n", "2", "--out", str(out)]
    assert main(argv) == 0  # the default 9×9 grid does not fit 25 px: the finest that does
    assert "--grid 8: the finest grid that fits 25×25 px faces" in capsys.readouterr().out
    assert io.read_image(out / "face_000.png").shape[:2] == (25, 25)
    # the figure shows each face as written under a title, at a readable size
    shown = [ax for ax in written_figures["faces.png"].axes if ax.images]
    assert len(shown) == 2 and written_figures["faces.png"].get_suptitle()
    first = io.read_image(out / "face_000.png", grey=True)
    np.testing.assert_allclose(np.clip(shown[0].images[0].get_array(), 0, 1), first, atol=1 / 255)
    assert min(io.read_image(out / "faces.png", grey=True).shape) >= 250
    model = tmp_path / "fa.npz"
    assert main(["faces", "train", str(lfw), "--factors", "2", "--iters", "3", "--out",
                 str(model)]) == 0  # fmt: skip
    inches = {}
    for upscale in (None, "3"):
        sample = tmp_path / f"sample{upscale}"
        extra = [] if upscale is None else ["--upscale", upscale]
        assert main(["faces", "sample", str(model), "--n", "4", "--out", str(sample), *extra]) == 0
        inches[upscale] = written_figures["grid.png"].get_size_inches()
    # --upscale 3 draws the faces three times larger (titles and margins stay as they are)
    assert np.all(inches["3"] > 2 * inches[None])
    assert (
        main(["faces", "sample", str(model), "--out", str(tmp_path / "s0"), "--upscale", "0"]) == 2
    )
    assert "--upscale must be at least 1, got 0" in capsys.readouterr().err
