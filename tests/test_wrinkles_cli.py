"""``jface wrinkles simulate``: files written, loadable, consistent; errors end with status 2."""

import numpy as np

from jface.cli import main
from jface.io import load_arrays, read_image
from jface.wrinkles import WrinkleParams, save_params


def test_simulate_writes_graph_weights_and_picture(tmp_path, capsys):
    params = tmp_path / "levels.json"
    save_params(params, [WrinkleParams(d=0.04, theta=0.5, s=0.1), WrinkleParams(d=0.02)])
    out = tmp_path / "run"
    args = ["wrinkles", "simulate", "--out", str(out), "--params", str(params), "--cross", "0.5"]
    assert main([*args, "--periodic", "--steps", "20", "--size", "256", "--seed", "3"]) == 0
    arrays, meta = load_arrays(out / "wrinkles.npz", kind="WrinkleGraph")
    assert meta["seed"] == 3 and len(meta["levels"]) == 2
    assert meta["levels"][0]["cross"] == 0.5 and meta["levels"][1]["d"] == 0.02
    n0 = len(arrays["level0_positions"])
    np.testing.assert_array_equal(arrays["level1_positions"][:n0], arrays["level0_positions"])
    for i in range(2):
        w = arrays[f"level{i}_weights"]
        assert w.shape == (len(arrays[f"level{i}_edge_nodes"]),) and w.min() >= 0 and w.max() <= 1
    picture = read_image(out / "wrinkles.png")
    assert picture.shape[:2] == (256, 256) and picture.min() < 0.5
    assert "pores" in capsys.readouterr().out


def test_bad_parameters_exit_with_a_message(tmp_path, capsys):
    code = main(["wrinkles", "simulate", "--out", str(tmp_path), "--cross", "3"])
    assert code == 2
    assert "WrinkleParams.cross must be in" in capsys.readouterr().err
