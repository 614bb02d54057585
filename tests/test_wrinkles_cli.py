"""``jface wrinkles simulate``: files written, loadable, consistent; errors end with status 2."""

from pathlib import Path

import numpy as np

import jface
from jface.cli import main
from jface.io import load_arrays, read_image, read_json, read_mesh
from jface.wrinkles import WrinkleParams, save_params


def test_simulate_writes_graph_weights_and_picture(tmp_path, capsys, written_figures):
    params = tmp_path / "levels.json"
    save_params(params, [WrinkleParams(d=0.04, theta=0.5, s=0.1), WrinkleParams(d=0.02)], "uv")
    out = tmp_path / "run"
    args = ["wrinkles", "simulate", "--out", str(out), "--params", str(params), "--cross", "0.5"]
    assert main([*args, "--periodic", "--size", "256", "--seed", "3"]) == 0  # converged
    arrays, meta = load_arrays(out / "wrinkles.npz", kind="WrinkleGraph")
    assert meta["seed"] == 3 and len(meta["levels"]) == 2
    assert meta["levels"][0]["cross"] == 0.5 and meta["levels"][1]["d"] == 0.02
    assert read_json(out / "params.json")["units"] == {"frame": "uv"}
    n0 = len(arrays["level0_positions"])
    np.testing.assert_array_equal(arrays["level1_positions"][:n0], arrays["level0_positions"])
    for i in range(2):
        w = arrays[f"level{i}_weights"]
        assert w.shape == (len(arrays[f"level{i}_edge_nodes"]),) and w.min() >= 0 and w.max() <= 1
    picture = written_figures["wrinkles.png"].axes[0].images[0].get_array()
    assert picture.shape[:2] == (256, 256) and picture.min() < 0.5
    assert read_image(out / "wrinkles.png").ndim == 3  # the figure, in colour
    assert "pores" in capsys.readouterr().out


def test_bad_parameters_exit_with_a_message(tmp_path, capsys):
    code = main(["wrinkles", "simulate", "--out", str(tmp_path), "--cross", "3"])
    assert code == 2
    assert "WrinkleParams.cross must be in" in capsys.readouterr().err


def test_render_and_extract(tmp_path, capsys):
    from jface.io import read_exr, write_exr

    params = tmp_path / "p.json"
    save_params(params, [WrinkleParams(d=0.05, theta=0.5, s=0.2, pore_width=0.5, dmin=1.0)], "uv")
    out = tmp_path / "w.exr"
    args = ["wrinkles", "render", "--params", str(params), "--size", "64", "--steps", "10"]
    assert main([*args, "--out", str(out), "--seed", "1", "--periodic"]) == 0
    image = read_exr(out)
    disp = image.channels["Y"]
    assert disp.shape == (64, 64) and disp.min() < 0 and image.metadata["seed"] == 1
    assert read_image(out.with_suffix(".png")).shape[:2] == (64, 64)
    # blended with a "scan" of the same size: the micro detail on top of its low-pass
    assert main([*args, "--out", str(tmp_path / "b.exr"), "--seed", "1", "--periodic",
                 "--base", str(out)]) == 0  # fmt: skip
    assert not np.allclose(read_exr(tmp_path / "b.exr").channels["Y"], disp)
    assert main(["wrinkles", "extract", str(out), "--out", str(tmp_path / "e.json"),
                 "--crop", "32", "--threshold", "0.5"]) == 0  # fmt: skip
    levels = read_json(tmp_path / "e.json")["levels"]
    assert read_json(tmp_path / "e.json")["units"] == {"frame": "uv"}
    assert np.asarray(levels[0]["theta"]).shape == (2, 2)
    assert read_json(tmp_path / "e_pores.json")["kind"] == "Pores"
    # on the built-in UV-mapped MediaPipe face: pores spaced by its UV stretch, mesh displaced
    face = Path(jface.__file__).parent / "data" / "mediapipe_canonical_face.obj"
    assert main([*args, "--out", str(tmp_path / "m.exr"), "--mesh", str(face)]) == 0
    moved, plain = read_mesh(tmp_path / "m.obj"), read_mesh(face)
    shift = np.linalg.norm(moved.vertices - plain.vertices, axis=1)
    assert (
        moved.faces.shape == plain.faces.shape
        and 0 < np.median(shift) < 1e-2 * np.ptp(plain.vertices, axis=0).max()
    )
    assert main([*args, "--out", str(tmp_path / "n.exr"), "--mesh", str(face), "--periodic"]) == 2
    assert "does not go with --mesh" in capsys.readouterr().err
    # a multi-channel EXR where one channel is expected, a bad size: one line, status 2
    write_exr(tmp_path / "rgb.exr", np.zeros((64, 64, 3), np.float32))
    capsys.readouterr()
    assert main(["wrinkles", "extract", str(tmp_path / "rgb.exr"), "--out", "x.json"]) == 2
    assert "expected one" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "z.exr"), "--size", "0"]) == 2
    assert "--size must be in" in capsys.readouterr().err
