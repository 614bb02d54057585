"""CLI commands run once on small built-in inputs, checking what they wrote: the restyled face
against the two styles, the synthesised map's tile statistics against the target's, the
simulated wrinkles' orientation against the one asked for."""

import json

import numpy as np
import pytest

from jface import detail, faces, io
from jface.cli import main


@pytest.fixture(scope="module")
def lfw() -> np.ndarray:
    """40 aligned 25×25 greyscale faces of scikit-image's LFW subset, float32."""
    from skimage import data

    return np.asarray(data.lfw_subset()[:40], np.float32)


def test_faces_restyle_writes_the_face_in_the_target_style(lfw, tmp_path, capsys):
    # two "styles" of every individual: as photographed, and darker with more contrast
    styled = np.clip(1.3 * lfw - 0.25, 0, 1).astype(np.float32)
    model = tmp_path / "bilinear.npz"
    faces.save_model(model, faces.fit_bilinear(np.stack([lfw, styled], 1), 6, n_iter=15).model)
    folder = tmp_path / "styled"
    for i, face in enumerate(styled):
        io.write_png(folder / f"{i:03d}.png", face)
    face = tmp_path / "face.png"
    io.write_png(face, lfw[7])
    original, target = io.read_image(face), io.read_image(folder / "007.png")
    mouth = np.zeros((25, 25), bool)
    mouth[15:21, 6:19] = True
    mask = tmp_path / "mouth.png"
    io.write_png(mask, mouth.astype(np.float32))
    common = ["faces", "restyle", str(folder), "--grey", "--grid", "5", "--translations", "0",
              "--angles", "--n-best", "2", "--model", str(model), "--image", str(face)]  # fmt: skip
    assert main([*common, "--out", str(tmp_path / "all"), "--seed", "3", "--json"]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[-1])["out"] == str(tmp_path / "all")
    out = io.read_image(tmp_path / "all" / "restyled.png")
    assert out.shape == (25, 25)
    # in the target style: nearer the styled face than the original, and as dark as it
    assert np.abs(out - target).mean() < 0.8 * np.abs(out - original).mean()
    assert abs(out.mean() - target.mean()) < 0.5 * abs(original.mean() - target.mean())
    panel = io.read_image(tmp_path / "all" / "restyle.png")
    assert panel.shape[1] >= 3 * 25  # source, prediction and result side by side
    # with a mask only the masked region changes
    assert main([*common, "--mask", str(mask), "--out", str(tmp_path / "mouth")]) == 0
    part = io.read_image(tmp_path / "mouth" / "restyled.png")
    np.testing.assert_allclose(part[~mouth], original[~mouth], atol=1 / 255)
    assert np.abs(part[mouth] - original[mouth]).mean() > 0.02


def test_synthesize_writes_a_map_with_the_target_statistics(gravel, brick, tmp_path, capsys):
    start, model = tmp_path / "start.exr", tmp_path / "model.exr"
    io.write_exr(start, brick[:64, :64].astype(np.float32))
    io.write_exr(model, (0.5 * gravel[:64, :64] + 0.1 * gravel[64:128, :64]).astype(np.float32))
    assert main(["analyze", str(model), "--out", str(tmp_path / "stats"), "--grid", "4",
                 "--scales", "3"]) == 0  # fmt: skip
    capsys.readouterr()
    stats_file = tmp_path / "stats" / "model.stats.npz"
    out = tmp_path / "synth.exr"
    assert main(["synthesize", str(start), "--stats", str(stats_file), "--out", str(out),
                 "--seed", "1", "--n-iter", "10"]) == 0  # fmt: skip
    written = io.read_exr(out)
    assert written.metadata["seed"] == 1
    target, _ = detail.load_stats(stats_file)
    (data,) = written.channels.values()
    got = detail.analyze_like(np.asarray(data, np.float64), target)
    before = detail.analyze_like(brick[:64, :64], target)

    def error(stats):
        return float(np.median(np.abs(np.log(np.asarray(stats.std) / np.asarray(target.std)))))

    assert error(got) < 0.1 < error(before)


def test_wrinkles_simulate_writes_weights_along_the_asked_orientation(tmp_path, written_figures):
    out = tmp_path / "sim"
    args = ["wrinkles", "simulate", "--out", str(out), "--d", "0.05", "--s", "0", "--theta",
            "1.0", "--levels", "1", "--steps", "60", "--seed", "1", "--size", "64"]  # fmt: skip
    assert main(args) == 0
    with np.load(out / "wrinkles.npz") as z:
        weights, delta = z["level0_weights"], z["level0_edge_delta"]
        positions = z["level0_positions"]
    assert weights.min() >= 0 and weights.max() <= 1 and weights.max() > 0.3
    assert len(positions) > 100
    # the weight-averaged axial direction of the edges is α_θ = 1 rad
    z = np.sum(weights * np.exp(2j * np.arctan2(delta[:, 1], delta[:, 0]))) / weights.sum()
    assert abs(np.angle(z) / 2 - 1.0) < 0.1 and abs(z) > 0.5
    assert json.loads((out / "params.json").read_text())["levels"][0]["theta"] == pytest.approx(1.0)
    # the figure draws the graph at the map's size, under a title
    (panel,) = [ax for ax in written_figures["wrinkles.png"].axes if ax.images]
    assert panel.images[0].get_array().shape[:2] == (64, 64)
    assert written_figures["wrinkles.png"].get_suptitle()
