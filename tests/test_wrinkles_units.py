"""Wrinkle parameter files state the frame of their lengths; a patch's are converted to the map."""

import json
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

from jface.cli import main
from jface.io import read_json, read_map
from jface.wrinkles import (
    LENGTH_POWERS,
    ParamUnits,
    WrinkleParams,
    find_pores,
    load_params,
    params_from_json,
    params_to_json,
    parse_patch_size,
    save_params,
)

#: every field away from its default, so that a conversion touching the wrong one shows
LEVEL = WrinkleParams(
    d=0.04, theta=0.6, s=0.3, dist=1.0, cont=0.2, sim=0.5, cross=0.5, deposit=0.4, decay=0.6,
    sigma=0.4, sigma_cont=0.5, dt=0.05, wrinkle_width=0.4, pore_width=0.35, dmin=0.5, blend=0.6,
    skew=0.2, cushion=0.1, fperturb=400.0, sperturb=0.5, fnoise=1000.0, snoise=0.05, scale=0.4,
)  # fmt: skip


def _document(units, levels=({"d": 0.04},)):
    doc = {"kind": "WrinkleParams", "levels": list(levels)}
    return json.dumps(doc if units is None else doc | {"units": units})


@pytest.mark.parametrize(
    "units",
    [
        ParamUnits("uv"),
        ParamUnits("patch", 0.0625, (256, 256)),
        ParamUnits("patch", None, (96, 128)),
    ],
)
def test_units_round_trip_through_the_file(tmp_path, units):
    save_params(tmp_path / "p.json", [LEVEL, LEVEL.replace(d=0.02)], units)
    assert ParamUnits.from_dict(read_json(tmp_path / "p.json")["units"]) == units
    assert json.loads(params_to_json(LEVEL, units))["units"] == units.to_dict()


def test_frames_parse_from_text():
    assert ParamUnits.parse("uv") == ParamUnits("uv")
    assert ParamUnits.parse("patch:256/4096") == ParamUnits("patch", 0.0625)
    assert ParamUnits.parse("patch:0.5") == ParamUnits("patch", 0.5)
    assert parse_patch_size("1") == 1.0
    for bad in ("0", "-0.5", "2", "1/0", "nan", "inf", "abc", "", "3/2"):
        with pytest.raises(ValueError, match=r"in \(0, 1\], e.g. 0.0625 or 256/4096"):
            parse_patch_size(bad)
    for bad in ("patch", "patch:", "uv:0.5", "mm", "face"):
        with pytest.raises(ValueError, match="'uv' or 'patch:SIZE'"):
            ParamUnits.parse(bad)


def test_every_length_field_converts_by_the_known_factor(tmp_path):
    face = LEVEL.rescaled(0.25)
    assert float(face.d) == pytest.approx(0.01)
    assert float(face.fperturb) == pytest.approx(1600.0)
    assert float(face.fnoise) == pytest.approx(4000.0)
    for name in set(LEVEL.to_dict()) - set(LENGTH_POWERS):  # pure numbers, widths (× α_d)
        assert float(getattr(face, name)) == float(getattr(LEVEL, name)), name
    # the file of a patch a quarter of the face's side loads in the face's (the map's) units
    save_params(tmp_path / "p.json", [LEVEL, LEVEL.replace(d=0.02)], "patch:1/4")
    loaded = load_params(tmp_path / "p.json")
    assert float(loaded[1].d) == pytest.approx(0.005)
    for name in LEVEL.to_dict():
        np.testing.assert_allclose(getattr(loaded[0], name), getattr(face, name), rtol=1e-6)
    # the map's own frame and a patch as big as the map change nothing
    save_params(tmp_path / "uv.json", LEVEL, "uv")
    save_params(tmp_path / "whole.json", LEVEL, "patch:1")
    for name in ("uv.json", "whole.json"):
        assert load_params(tmp_path / name)[0].to_dict() == LEVEL.to_dict()
    # textures scale value by value
    texture = WrinkleParams(d=jnp.full((2, 2), 0.04)).rescaled(0.5)
    np.testing.assert_allclose(texture.d, 0.02)


def test_files_without_units_are_refused_with_the_fix(tmp_path):
    old = tmp_path / "old.json"
    old.write_text(_document(None))
    with pytest.raises(ValueError, match=r"old.json: no frame stated .*--params-frame uv"):
        load_params(old)
    # stating the frame makes an old file usable
    assert float(load_params(old, frame="uv")[0].d) == pytest.approx(0.04)
    assert float(load_params(old, frame="patch:0.5")[0].d) == pytest.approx(0.02)
    # a fit of a patch of unknown size: the size is asked for
    unsized = tmp_path / "unsized.json"
    unsized.write_text(_document({"frame": "patch", "patch_size": None, "patch_pixels": [64, 64]}))
    with pytest.raises(
        ValueError, match=r"unsized.json: .*not recorded.*--params-frame patch:SIZE"
    ):
        load_params(unsized)
    assert float(load_params(unsized, frame="patch:1/2")[0].d) == pytest.approx(0.02)


@pytest.mark.parametrize(
    ("units", "message"),
    [
        ({"frame": "mm"}, "frame must be one of 'uv', 'patch'; got 'mm'"),
        ({"frame": 3}, "'units' must be an object with a 'frame'"),
        ("uv", "'units' must be an object with a 'frame'"),
        ({"frame": "uv", "scale_mm": 2}, r"unknown 'units' field\(s\) \['scale_mm'\]"),
        ({"frame": "uv", "patch_size": 0.5}, "frame 'uv' take no patch_size"),
        ({"frame": "patch", "patch_size": 0}, r"patch_size .* must be a number in \(0, 1\], got 0"),
        ({"frame": "patch", "patch_size": -0.5}, r"must be a number in \(0, 1\], got -0.5"),
        ({"frame": "patch", "patch_size": 1.5}, r"must be a number in \(0, 1\], got 1.5"),
        ({"frame": "patch", "patch_size": float("nan")}, r"in \(0, 1\], got nan"),
        ({"frame": "patch", "patch_size": float("inf")}, r"in \(0, 1\], got inf"),
        ({"frame": "patch", "patch_size": "1/4"}, r"in \(0, 1\], got '1/4'"),
        ({"frame": "patch", "patch_size": True}, r"in \(0, 1\], got True"),
        ({"frame": "patch", "patch_size": 0.5, "patch_pixels": [0, 1]}, "two positive integers"),
        ({"frame": "patch", "patch_size": 0.5, "patch_pixels": 256}, "two positive integers"),
        # a non-square fit stretches its unit square: no single length on the face
        ({"frame": "patch", "patch_size": 0.5, "patch_pixels": [64, 128]}, "64×128 patch"),
    ],
)
def test_bad_units_are_refused_naming_the_file(tmp_path, units, message):
    path = tmp_path / "p.json"
    path.write_text(_document(units))
    with pytest.raises(ValueError, match=message) as err:
        load_params(path)
    assert str(err.value).startswith(str(path))


def test_frames_that_cannot_be_converted_are_refused(tmp_path):
    uv = _document({"frame": "uv"})
    with pytest.raises(ValueError, match=r"src: the file states units \{'frame': 'uv'\}, but"):
        params_from_json(uv, frame="patch:0.5", source="src")
    patch = _document({"frame": "patch", "patch_size": 0.5})
    with pytest.raises(ValueError, match="the frame given is"):
        params_from_json(patch, frame="patch:0.25")
    assert float(params_from_json(patch, frame="patch:1/2")[0].d) == pytest.approx(0.02)
    # a patch's texture covers the patch, not the face
    texture = _document({"frame": "patch", "patch_size": 0.5}, [{"theta": [[0.0, 1.0]] * 2}])
    with pytest.raises(ValueError, match=r"level 0: \['theta'\] vary over the patch"):
        params_from_json(texture)
    # lengths beyond Table 1 once on the face: α_d 0.02 of a patch 1/32 of the face is 0.000625
    tiny = _document({"frame": "patch", "patch_size": 1 / 32}, [{"d": 0.02}])
    with pytest.raises(ValueError, match=r"0.03125-wide patch on the map: WrinkleParams.d must"):
        params_from_json(tiny)
    with pytest.raises(ValueError, match="must be in"):
        LEVEL.rescaled(1e-4)  # frequencies beyond 50× Table 1's
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="factor must"):
            LEVEL.rescaled(bad)


def test_render_and_simulate_refuse_files_without_units(tmp_path, capsys):
    old = tmp_path / "old.json"
    old.write_text(_document(None))
    render = ["wrinkles", "render", "--out", str(tmp_path / "o.exr"), "--size", "64"]
    cases = [
        ([*render, "--params", str(old)], f"{old}: no frame stated"),
        ([*render, "--params", str(old), "--params-frame", "patch:2"], "--params-frame: a patch"),
        ([*render, "--params", str(old), "--params-frame", "mm"], "--params-frame: a frame must"),
        ([*render, "--simulation", str(tmp_path), "--params-frame", "uv"], "--params-frame"),
        (["wrinkles", "simulate", "--out", str(tmp_path / "s"), "--params-frame", "uv"],
         "give --params"),
    ]  # fmt: skip
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.json"]


def _stand_in_fit(heldout: list, loss: float = 0.4):
    """A stand-in for ``fit_wrinkles`` (a real fit takes minutes) whose answer has ``loss``
    (the swarm's is 0.5, or inf with it) and the held-out losses ``heldout``."""

    def fit(key, patch, **kwargs):
        losses = np.asarray(heldout, np.float32)
        mean = float(np.mean(losses)) if np.all(np.isfinite(losses)) else float("nan")
        swarm_loss = 0.5 if np.isfinite(loss) else loss
        history = np.linspace(1.0, 0.5, 3)[None] if np.isfinite(loss) else np.full((1, 3), loss)
        swarm = SimpleNamespace(trial_losses=[swarm_loss], n_nonfinite=np.zeros(1),
                                history=history)  # fmt: skip
        return SimpleNamespace(
            levels=(LEVEL, LEVEL.replace(d=0.02)), loss=loss, swarm_loss=swarm_loss, swarm=swarm,
            names=("d",), fitted=patch, epochs_run=(3,), interrupted=False,
            refined_losses=[loss], answer_trial=0, heldout_loss=mean, heldout_losses=losses,
        )  # fmt: skip

    return fit


def test_fit_records_the_patch_frame(tmp_path, monkeypatch, capsys):
    """The fit's file states its frame (the fit itself is replaced by a stand-in: minutes), and
    its held-out losses (null and said so where no held-out key could be drawn)."""
    from jface.cli import _fit

    heldout = [0.5, 0.7]
    monkeypatch.setattr(_fit, "fit_wrinkles", _stand_in_fit(heldout))
    titles = []
    grid = _fit.plots.panel_grid
    monkeypatch.setattr(
        _fit.plots, "panel_grid", lambda *a, **k: titles.append(k["title"]) or grid(*a, **k)
    )
    square, other, wide = (tmp_path / f"{n}.npy" for n in ("square", "other", "wide"))
    np.save(square, np.random.default_rng(0).normal(size=(64, 64)).astype(np.float32))
    np.save(other, np.random.default_rng(1).normal(size=(96, 96)).astype(np.float32))
    np.save(wide, np.random.default_rng(0).normal(size=(64, 96)).astype(np.float32))
    fit = ["wrinkles", "fit", "--iters", "1", "--trials", "1"]
    assert (
        main([*fit, str(square), "--out", str(tmp_path / "f.json"), "--patch-size", "64/1024"]) == 0
    )
    document = read_json(tmp_path / "f.json")
    assert document["units"] == {"frame": "patch", "patch_size": 0.0625, "patch_pixels": [64, 64]}
    assert document["fit"]["heldout_loss"] == pytest.approx(0.6)
    assert document["fit"]["heldout_losses"] == pytest.approx([0.5, 0.7])
    assert "0.6 with other simulation keys" in capsys.readouterr().out
    assert "0.6 with other simulation keys" in titles[-1]  # the target/fit figure's title
    assert float(load_params(tmp_path / "f.json")[0].d) == pytest.approx(0.04 / 16)
    # without the size: recorded as unknown, and said so (and no held-out key drawable)
    heldout[:] = [np.inf, np.inf]
    assert main([*fit, str(other), "--out", str(tmp_path / "g.json")]) == 0
    out, err = capsys.readouterr()
    assert "not recorded (--patch-size)" in err and "undrawable with other simulation keys" in out
    assert "undrawable with other simulation keys" in titles[-1]
    document = read_json(tmp_path / "g.json")
    assert document["units"]["patch_size"] is None
    assert document["fit"]["heldout_loss"] is None
    assert document["fit"]["heldout_losses"] == [None, None]
    for argv, message in (
        ([str(wide), "--patch-size", "0.5"], "wide.npy: target_patch must be square"),
        ([str(square), "--patch-size", "1.5"], "--patch-size: a patch size must"),
        ([str(square), "--patch-size", "0"], "--patch-size: a patch size must"),
    ):
        assert main([*fit, *argv, "--out", str(tmp_path / "h.json")]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "h.json").exists()


def test_an_undrawable_fit_writes_strict_json_and_says_so(tmp_path, monkeypatch, capsys):
    """A fit whose every evaluation was undrawable (all losses infinite) writes null for them,
    never JSON's missing Infinity, and its summary line and figure title say "undrawable"; so
    does a batch's summary when no patch could be drawn."""
    from jface.cli import _fit

    monkeypatch.setattr(_fit, "fit_wrinkles", _stand_in_fit([np.inf], loss=np.inf))
    titles = []
    grid = _fit.plots.panel_grid
    monkeypatch.setattr(
        _fit.plots, "panel_grid", lambda *a, **k: titles.append(k["title"]) or grid(*a, **k)
    )
    patch = tmp_path / "patch.npy"
    np.save(patch, np.random.default_rng(0).normal(size=(64, 64)).astype(np.float32))
    fit = ["wrinkles", "fit", "--iters", "1", "--trials", "1", str(patch)]

    def strict(text):  # JSON as the standard has it: no NaN or Infinity
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))

    assert main([*fit, "--out", str(tmp_path / "f.json")]) == 0
    document = strict((tmp_path / "f.json").read_text())["fit"]
    assert document["loss"] is document["swarm_loss"] is None
    assert document["refined_losses"] == document["trial_losses"] == [None]
    out = capsys.readouterr().out
    assert "loss undrawable (swarm) → undrawable (refined), undrawable with other" in out
    assert "(loss undrawable; undrawable with other simulation keys)" in titles[-1]
    assert main([*fit, "--out", str(tmp_path / "batch"), "--json"]) == 0
    summary = strict(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["min_loss"] is summary["max_loss"] is None


def _pore_density(image: np.ndarray, margin: int = 10) -> float:
    """Pores found per unit area of ``image``'s unit square, away from its border."""
    found = find_pores(image)
    positions = np.asarray(found.positions)[: int(found.count)]
    m = margin / image.shape[0]
    inside = np.all((positions > m) & (positions < 1 - m), axis=1)
    return float(inside.sum()) / (1 - 2 * m) ** 2


def test_cli_patch_parameters_rerender_the_face_at_the_patch_pore_density(tmp_path):
    """The issue's check: a patch cut from a face map (a 1024² map drawn from known parameters,
    pores 20 px apart), its parameters in the patch's units (α_d and the frequencies relative to
    the patch, as a fit writes them), re-rendered on the whole face: the same pores per area."""
    face_level = WrinkleParams(d=0.02, theta=0.6, s=0.3, cross=0.5, snoise=0.05, fnoise=600.0,
                               fperturb=800.0)  # fmt: skip
    save_params(tmp_path / "face.json", face_level, "uv")
    render = ["wrinkles", "render", "--size", "1024"]
    assert main([*render, "--params", str(tmp_path / "face.json"), "--out",
                 str(tmp_path / "face.exr"), "--seed", "1"]) == 0  # fmt: skip
    patch = read_map(tmp_path / "face.exr")[256:768, 256:768]  # half the face's side
    save_params(tmp_path / "patch.json", face_level.rescaled(2.0), "patch:512/1024")
    assert main([*render, "--params", str(tmp_path / "patch.json"), "--out",
                 str(tmp_path / "again.exr"), "--seed", "2"]) == 0  # fmt: skip
    again = read_map(tmp_path / "again.exr")
    patch_density = _pore_density(patch) / 0.5**2  # per unit area of the face
    assert patch_density > 1000  # hundreds of pores found on the patch
    assert _pore_density(again) == pytest.approx(patch_density, rel=0.1)
