"""Affine registration of faces to a template and un-warping (Mohammed et al. 2009, §2.2, §4).

Real faces: scikit-image's LFW crops (already aligned to one frame), upsampled to 64 × 64 and
warped by random affine maps whose inverses the alignment has to find.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jface import faces

SIZE = 64
# eye centres, nose tip, mouth corners of the mean LFW crop at 64 × 64, (x, y) pixels
TEMPLATE_LANDMARKS = np.array(
    [[18.0, 21.0], [45.0, 21.0], [31.5, 36.0], [21.0, 46.0], [42.0, 46.0]], np.float32
)
CORNERS = np.array([[0, 0], [SIZE - 1, 0], [0, SIZE - 1], [SIZE - 1, SIZE - 1]], np.float64)


def random_affine(rng: np.random.Generator) -> np.ndarray:
    """A rotation ≤ 8°, scale change ≤ 8 %, shear ≤ 0.05 and shift ≤ 4 px about the centre."""
    angle = np.deg2rad(rng.uniform(-8, 8))
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    linear = (
        (1 + rng.uniform(-0.08, 0.08))
        * rotation
        @ np.array([[1, rng.uniform(-0.05, 0.05)], [0, 1]])
    )
    centre = np.full(2, (SIZE - 1) / 2)
    shift = centre - linear @ centre + rng.uniform(-4, 4, 2)
    return np.concatenate([linear, shift[:, None]], axis=1).astype(np.float32)


def apply(transform, points) -> np.ndarray:
    a = np.asarray(transform, np.float64)
    return np.asarray(points, np.float64) @ a[:, :2].T + a[:, 2]


def corner_error(found, expected) -> float:
    """Largest distance between where two transforms send the frame's corners, in pixels."""
    return float(np.linalg.norm(apply(found, CORNERS) - apply(expected, CORNERS), axis=1).max())


@pytest.fixture(scope="module")
def lfw64() -> np.ndarray:
    from skimage import data

    crops = jnp.asarray(data.lfw_subset()[:100], jnp.float32)
    return np.clip(np.asarray(jax.image.resize(crops, (100, SIZE, SIZE), "cubic")), 0, 1)


@pytest.fixture(scope="module")
def warped(lfw64):
    """Six faces, each warped by a random affine map ``B`` (warped(q) = face(B q)); the
    alignment to the original face must find ``B⁻¹`` (template pixels → warped pixels)."""
    rng = np.random.default_rng(0)
    maps = [random_affine(rng) for _ in range(6)]
    images = np.stack([np.asarray(faces.warp(lfw64[i], b)) for i, b in enumerate(maps)])
    truth = np.stack([np.asarray(faces.invert_affine(b)) for b in maps])
    return images, truth


# --- closed form and resampling ----------------------------------------------------------------


def test_fit_affine_matches_numpy_least_squares():
    rng = np.random.default_rng(1)
    template = rng.uniform(0, 64, (12, 2))
    truth = np.array([[1.1, 0.2, 3.0], [-0.15, 0.9, -2.0]])
    points = apply(truth, template)
    assert np.allclose(faces.fit_affine(points, template), truth, atol=1e-9)
    noisy = points + rng.normal(0, 0.5, points.shape)
    design = np.concatenate([template, np.ones((12, 1))], axis=1)
    reference = np.linalg.lstsq(design, noisy, rcond=None)[0].T
    assert np.allclose(faces.fit_affine(noisy, template), reference, atol=1e-9)


def test_warp_matches_scipy_affine_transform(lfw64):
    a = np.array([[0.95, 0.1, 2.5], [-0.08, 1.05, -3.0]])
    ours = np.asarray(faces.warp(lfw64[0].astype(np.float64), a))
    # scipy indexes (row, column): swap the axes of the (x, y) matrix
    matrix = np.array([[a[1, 1], a[1, 0]], [a[0, 1], a[0, 0]]])
    offset = np.array([a[1, 2], a[0, 2]])
    reference = ndimage.affine_transform(
        lfw64[0].astype(np.float64), matrix, offset, order=1, mode="nearest"
    )
    assert np.max(np.abs(ours - reference)) < 1e-9


def test_warp_by_inverse_undoes_warp_inside(lfw64):
    a = np.array([[1.05, -0.1, -2.0], [0.12, 0.97, 1.5]], np.float32)
    back = faces.warp(faces.warp(lfw64[1], a), faces.invert_affine(a))
    inner = np.s_[8:-8, 8:-8]
    err = np.sqrt(np.mean((np.asarray(back)[inner] - lfw64[1][inner]) ** 2))
    assert err < 0.02  # two bilinear resamplings blur a little, nothing more


# --- alignment ----------------------------------------------------------------------------------


@pytest.mark.parametrize("noise", [0.0, 0.25])
def test_landmark_alignment_recovers_warps(lfw64, warped, noise):
    """Landmarks of each warped face (the template's carried through its warp, plus hand-marking
    noise) align it back: every true landmark lands within 1 px of the template's."""
    images, truth = warped
    rng = np.random.default_rng(2)
    mean = lfw64.mean(axis=0)
    for image, b_inv in zip(images, truth, strict=True):
        marked = apply(b_inv, TEMPLATE_LANDMARKS) + rng.normal(0, noise, TEMPLATE_LANDMARKS.shape)
        result = faces.align(image, mean, landmarks=marked, template_landmarks=TEMPLATE_LANDMARKS)
        back = apply(faces.invert_affine(result.transform), apply(b_inv, TEMPLATE_LANDMARKS))
        error = np.linalg.norm(back - TEMPLATE_LANDMARKS, axis=1).max()
        assert error <= (1e-3 if noise == 0 else 1.0)
        if noise == 0:
            assert corner_error(result.transform, b_inv) < 1e-3


def test_intensity_alignment_recovers_known_warps(lfw64, warped):
    images, truth = warped
    for i, (image, b_inv) in enumerate(zip(images, truth, strict=True)):
        result = faces.align(image, lfw64[i])
        assert bool(result.converged) and float(result.coverage) > 0.8
        assert corner_error(result.transform, b_inv) < 0.25  # measured ≤ 0.08 px
        inner = np.s_[8:-8, 8:-8]
        assert np.sqrt(np.mean((np.asarray(result.image)[inner] - lfw64[i][inner]) ** 2)) < 0.02


def test_intensity_alignment_absorbs_gain_and_offset(lfw64, warped):
    """A template lit differently (gain 0.7, offset 0.1) is aligned to as well."""
    images, truth = warped
    result = faces.align(images[2], 0.7 * lfw64[2] + 0.1)
    assert corner_error(result.transform, truth[2]) < 0.25
    plain = faces.align(images[2], lfw64[2])
    # the fitted gain carries the residual into the template's units: 0.7 × the plain one
    assert float(result.rms) == pytest.approx(0.7 * float(plain.rms), rel=0.1)


def test_colour_faces_align_and_unwarp_into_another_size(lfw64, warped):
    images, truth = warped
    tint = np.array([1.0, 0.8, 0.6], np.float32)
    result = faces.align(images[3][..., None] * tint, lfw64[3][..., None] * tint)
    assert result.image.shape == (SIZE, SIZE, 3)
    assert corner_error(result.transform, truth[3]) < 0.25
    out, i = faces.unwarp(jax.random.key(0), result.image, truth, shape=(48, 80))
    assert out.shape == (48, 80, 3)
    assert np.allclose(
        out[..., 1], faces.warp(result.image[..., 1], faces.invert_affine(truth[int(i)]), (48, 80))
    )


def test_jit_equals_eager_and_vmap_equals_loop(lfw64, warped):
    images, _ = warped
    templates = lfw64[:3]
    loop = [faces.align(im, t) for im, t in zip(images[:3], templates, strict=True)]
    batch = jax.vmap(faces.align)(jnp.asarray(images[:3]), jnp.asarray(templates))
    for i, one in enumerate(loop):
        assert np.allclose(batch.transform[i], one.transform, atol=1e-4)
        assert np.allclose(batch.image[i], one.image, atol=1e-4)
        assert bool(batch.converged[i])
    jitted = jax.jit(faces.align)(images[0], templates[0])
    assert np.allclose(jitted.transform, loop[0].transform, atol=1e-4)


# --- un-warping ---------------------------------------------------------------------------------


def test_unwarp_returns_an_aligned_face_to_its_training_frame(lfw64, warped):
    images, truth = warped
    aligned = jnp.stack([faces.warp(im, t) for im, t in zip(images, truth, strict=True)])
    keys = jax.random.split(jax.random.key(3), 40)
    unwarped, chosen = jax.vmap(lambda k, im: faces.unwarp(k, im, truth))(
        keys, jnp.broadcast_to(aligned[0], (40, SIZE, SIZE))
    )
    assert set(np.asarray(chosen).tolist()) == set(range(len(truth)))  # every transform drawn
    for k in range(3):
        again, i = faces.unwarp(keys[k], aligned[0], truth)
        assert np.array_equal(again, faces.unwarp(keys[k], aligned[0], truth)[0])  # seeded
        # vmap may fuse the bilinear weights differently from an eager call: equal to rounding
        assert int(i) == int(chosen[k]) and np.allclose(again, unwarped[k], rtol=0, atol=1e-5)
        reference = faces.warp(aligned[0], faces.invert_affine(truth[int(i)]))
        assert np.allclose(unwarped[k], reference, atol=1e-6)
    # a face aligned by transform i and un-warped by it is the training face again
    for i in range(len(truth)):
        back = np.asarray(faces.warp(aligned[i], faces.invert_affine(truth[i])))
        inner = np.s_[10:-10, 10:-10]
        assert np.sqrt(np.mean((back[inner] - images[i][inner]) ** 2)) < 0.03


# --- bad input ----------------------------------------------------------------------------------


def _bad_cases(face):
    good_t = np.eye(2, 3, dtype=np.float32)
    nan_t = good_t.copy()
    nan_t[0, 2] = np.nan
    lm = TEMPLATE_LANDMARKS
    key = jax.random.key(0)
    return [
        (lambda: faces.warp(face, nan_t), "transform must be finite"),
        (lambda: faces.warp(face, np.zeros((2, 3), np.float32)), "transform must be invertible"),
        (lambda: faces.warp(face, np.eye(3, dtype=np.float32)), r"transform must be \(2, 3\)"),
        (lambda: faces.unwarp(key, face, nan_t[None]), "transforms must be finite"),
        (lambda: faces.unwarp(key, face, good_t), "transforms must have 3 axes"),
        (lambda: faces.unwarp(0, face, good_t[None]), "key"),
        (lambda: faces.align(face[0], face), "image must be one image"),
        (lambda: faces.align(face, np.stack([face] * 3, -1)), "same channels"),
        (lambda: faces.align(face, face, landmarks=lm), "must be given together"),
        (
            lambda: faces.align(face, face, landmarks=lm[:, :1], template_landmarks=lm),
            "landmarks must be",
        ),
        (
            lambda: faces.align(face, face, landmarks=lm[:2], template_landmarks=lm[:2]),
            "at least 3 landmarks",
        ),
        (
            lambda: faces.fit_affine(lm[:3], np.array([[0, 0], [1, 1], [2, 2]], np.float32)),
            "on one line",
        ),
        (lambda: faces.align(face, face, init=nan_t), "init must be finite"),
        (lambda: faces.align(face, face, weights=-np.ones_like(face)), "weights must be ≥ 0"),
        (lambda: faces.align(face, face, weights=np.ones((3, 3))), "weights must have"),
    ]


def test_bad_input_names_the_argument(lfw64):
    for call, message in _bad_cases(lfw64[0]):
        with pytest.raises((ValueError, TypeError), match=message):
            call()


def test_alignment_that_does_not_converge_is_an_error(lfw64, warped):
    images, _ = warped
    with pytest.raises(ValueError, match="image did not align to the template"):
        faces.align(images[0], lfw64[0], max_steps=1)
    # a start that puts the template outside the image finds no gradient to come back
    far = np.array([[1, 0, 200], [0, 1, 0]], np.float32)
    with pytest.raises(ValueError, match="0% of the template inside the image"):
        faces.align(images[0], lfw64[0], init=far)
    quiet = faces.align(images[0], lfw64[0], init=far, throw=False)
    assert not bool(quiet.converged)


# --- command line -------------------------------------------------------------------------------


def test_cli_align_then_synth_and_unwarp(tmp_path, lfw64, warped, capsys):
    """`jface faces align` from landmarks recovers the warps; `synth --unwarp` puts each new
    face into the frame of one training face."""
    import json

    from jface import io
    from jface.cli import main

    images, truth = warped
    folder = tmp_path / "warped"
    names = [f"face{i}.png" for i in range(len(images))]
    for name, image in zip(names, images, strict=True):
        io.write_png(folder / name, np.clip(image, 0, 1))
    marks = {
        "template": TEMPLATE_LANDMARKS.tolist(),
        "images": {
            n: apply(t, TEMPLATE_LANDMARKS).tolist() for n, t in zip(names, truth, strict=True)
        },
    }
    (tmp_path / "marks.json").write_text(json.dumps(marks))
    aligned = tmp_path / "aligned"
    args = ["faces", "align", str(folder), "--grey", "--landmarks", str(tmp_path / "marks.json")]
    assert main([*args, "--out", str(aligned)]) == 0
    document = io.read_json(aligned / "transforms.json")
    assert document["template_shape"] == [SIZE, SIZE] and "jface_version" in document
    for record, name, b_inv in zip(document["faces"], names, truth, strict=True):
        assert record["file"] == name and corner_error(record["transform"], b_inv) < 1e-3
    synth = tmp_path / "synth"
    code = main(
        ["faces", "synth", str(aligned), "--grey", "--n", "2", "--grid", "4", "--out", str(synth),
         "--unwarp", str(aligned / "transforms.json"), "--json"]
    )  # fmt: skip
    assert code == 0
    frames = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames_of"]
    for i, name in enumerate(frames):
        face = io.read_image(synth / f"face_{i:03d}.png", grey=True)
        unwarped = io.read_image(synth / f"unwarped_{i:03d}.png", grey=True)
        b_inv = truth[names.index(name)]
        expected = np.asarray(faces.warp(face, faces.invert_affine(b_inv)))
        assert np.max(np.abs(unwarped - expected)) < 2 / 255  # PNG rounding only


def test_cli_names_the_bad_input(tmp_path, lfw64, warped, capsys):
    from jface import io
    from jface.cli import main

    images, _ = warped
    folder = tmp_path / "warped"
    for i, image in enumerate(images[:3]):
        io.write_png(folder / f"face{i}.png", np.clip(image, 0, 1))
    args = ["faces", "align", str(folder), "--grey", "--max-steps", "1"]
    assert main([*args, "--out", str(tmp_path / "a")]) == 2
    assert "face0.png: image did not align" in capsys.readouterr().err
    partial = {"template": TEMPLATE_LANDMARKS.tolist(), "images": {"face0.png": [[1, 2]] * 5}}
    io.write_json(tmp_path / "marks.json", partial)
    marked = ["--landmarks", str(tmp_path / "marks.json"), "--out", str(tmp_path / "b")]
    assert main(["faces", "align", str(folder), "--grey", *marked]) == 2
    assert "marks.json has no landmarks for face1.png" in capsys.readouterr().err
    before = (folder / "face0.png").read_bytes()
    assert main(["faces", "align", str(folder), "--grey", "--out", str(folder)]) == 2
    assert "face0.png" in capsys.readouterr().err  # an input named as an output
    assert (folder / "face0.png").read_bytes() == before
    bad = {"template_shape": [SIZE, SIZE], "faces": [
        {"file": "x.png", "shape": [SIZE, SIZE], "transform": [[1, 0, float("nan")], [0, 1, 0]]}
    ]}  # fmt: skip
    io.write_json(tmp_path / "bad.json", bad)
    code = main(
        ["faces", "synth", str(folder), "--grey", "--n", "1", "--grid", "4",
         "--out", str(tmp_path / "s"), "--unwarp", str(tmp_path / "bad.json")]
    )  # fmt: skip
    assert code == 2
    assert "bad.json: transforms must be finite" in capsys.readouterr().err
