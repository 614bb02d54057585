"""Landmarks without clicks: the built-in face model fitted to real scans and to faces whose
landmarks are known, under any pose and unit; non-faces and malformed meshes refused."""

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jface import data, mesh
from jface.cli import main

NAMES = mesh.LANDMARK_NAMES


def iod(points: np.ndarray) -> float:
    """Inter-ocular distance (outer eye corners)."""
    return float(
        np.linalg.norm(
            points[NAMES.index("right_eye_outer")] - points[NAMES.index("left_eye_outer")]
        )
    )


def errors(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-marker distances in % of the inter-ocular distance."""
    return 100.0 * np.linalg.norm(np.asarray(found, np.float64) - truth, axis=1) / iod(truth)


@pytest.fixture(scope="module")
def lee_perry_smith():
    scan, marks = data.lee_perry_smith()
    truth = np.asarray(mesh.landmark_points(marks, scan.vertices), np.float64)
    return scan, marks, truth


@pytest.fixture(scope="module")
def found(lee_perry_smith):
    scan, _, _ = lee_perry_smith
    return mesh.find_landmarks(scan.vertices, scan.faces)


def test_lee_perry_smith_markers_near_the_hand_placed_ones(lee_perry_smith, found):
    scan, _, truth = lee_perry_smith
    err = errors(found.points, truth)
    # Features the geometry pins down (nose tip, inner eye corners, mouth, alae) land within a
    # few mm; the outline points (temples, jaw, cheeks) are defined differently by the model's
    # ids and by the hand placement, so only a loose bound holds for them.
    central = [NAMES.index(n) for n in ("nose_tip", "upper_lip", "left_ala", "right_ala")]
    assert err[central].max() < 7.0, err
    assert np.median(err) < 10.0, err
    assert err.max() < 30.0, err
    assert float(found.score) < 0.55
    # Markers lie on the scan.
    gap = np.asarray(
        [np.min(np.linalg.norm(scan.vertices - p, axis=1)) for p in np.asarray(found.points)]
    )
    assert gap.max() < 0.01  # metres: within a triangle's size of a vertex


def test_pose_and_unit_do_not_change_the_markers(lee_perry_smith, found):
    # One fit for both: a random rotation, metres to millimetres and a move of a few metres.
    scan, _, truth = lee_perry_smith
    rng = np.random.default_rng(3)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation = q * np.sign(np.diag(r))
    rotation[:, 0] *= np.sign(np.linalg.det(rotation))
    translation = 1e3 * rng.normal(size=3)
    moved = mesh.find_landmarks(1e3 * scan.vertices @ rotation.T + translation, scan.faces)
    back = (np.asarray(moved.points, np.float64) - translation) @ rotation / 1e3
    spread = 100.0 * np.linalg.norm(back - np.asarray(found.points), axis=1) / iod(truth)
    assert spread.max() < 1.0, spread


def test_sampling_jit_equals_eager_and_vmap_equals_a_loop():
    face = data.mediapipe_face()
    v, f = jnp.asarray(face.vertices, jnp.float32), jnp.asarray(face.faces, jnp.int32)
    keys = jax.random.split(jax.random.key(5), 3)
    batched = jax.jit(jax.vmap(mesh.sample_surface, (0, None, None, None)), static_argnums=3)
    many = batched(keys, v, f, 2048)
    for i, key in enumerate(keys):
        eager = mesh.sample_surface(key, v, f, 2048)
        for name in ("points", "normals", "center", "scale"):
            np.testing.assert_allclose(
                getattr(many, name)[i], getattr(eager, name), rtol=1e-4, atol=1e-5
            )
    # Normalised: centred, unit RMS radius; distinct keys draw distinct points.
    assert np.abs(np.asarray(many.points).mean(axis=1)).max() < 1e-4
    np.testing.assert_allclose(np.sqrt((np.asarray(many.points) ** 2).sum(-1).mean(-1)), 1.0, 1e-4)
    assert not np.allclose(many.points[0], many.points[1])


def test_recovers_known_ict_faces_under_random_similarities():
    model = data.ict_face_model()
    rng = np.random.default_rng(7)
    identity = model["identity_deltas"].astype(np.float32)
    for smile in (0.0, 1.0):
        shape = model["vertices"] + np.tensordot(rng.normal(size=10), identity, axes=1)
        shape = shape + smile * model["smile_delta"].astype(np.float32)
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        rotation = (
            q * np.sign(np.diag(r)) * (1 if np.linalg.det(q * np.sign(np.diag(r))) > 0 else -1)
        )
        scale = 10.0 ** rng.uniform(-2.0, 3.0)
        translation = scale * 100.0 * rng.normal(size=3)
        posed = scale * shape @ rotation.T + translation
        truth = scale * np.asarray(mesh.ict_landmarks(shape), np.float64) @ rotation.T
        truth = truth + translation
        fit = mesh.find_landmarks(posed, model["faces"])
        err = errors(fit.points, truth)
        assert err.mean() < 3.0 and err.max() < 8.0, (smile, err)
        # The recovered similarity maps the model's frame onto the posed one.
        assert float(fit.scale) == pytest.approx(scale, rel=0.05)


def test_mediapipe_face_markers_at_its_known_ids():
    face = data.mediapipe_face()
    truth = np.asarray(mesh.mediapipe_landmarks(face.vertices), np.float64)
    err = errors(mesh.find_landmarks(face.vertices, face.faces).points, truth)
    assert err.mean() < 5.0 and err.max() < 10.0, err


@pytest.mark.parametrize("shape", ["sphere", "box", "blob"])
def test_not_a_face_is_refused_with_the_residual(shape):
    if shape == "sphere":
        body = trimesh.creation.icosphere(4)
    elif shape == "box":
        body = trimesh.creation.box(extents=(1.0, 2.0, 3.0)).subdivide().subdivide().subdivide()
    else:
        body = trimesh.creation.icosphere(4)
        v = body.vertices
        body.vertices = v * (1.0 + 0.3 * np.sin(3.0 * v[:, :1]) * np.cos(2.0 * v[:, 1:2]))
    with pytest.raises(mesh.NoFaceError, match=r"no face found.*score"):
        mesh.find_landmarks(body.vertices, body.faces)


def test_malformed_meshes_are_refused():
    face = data.mediapipe_face()
    v, f = np.asarray(face.vertices, np.float64), np.asarray(face.faces)
    with pytest.raises(ValueError, match="no faces"):
        mesh.find_landmarks(v, np.zeros((0, 3), np.int64))
    with pytest.raises(ValueError, match="too few"):
        mesh.find_landmarks(v, f[:10])
    bad = v.copy()
    bad[5] = np.nan
    with pytest.raises(ValueError, match="vertices"):
        mesh.find_landmarks(bad, f)
    with pytest.raises(ValueError, match="outside"):
        mesh.find_landmarks(v, f + len(v))
    with pytest.raises(ValueError, match="zero area"):
        mesh.find_landmarks(np.zeros_like(v), f)
    with pytest.raises(TypeError, match="integers"):
        mesh.find_landmarks(v, f.astype(np.float64))


def test_cli_writes_landmarks_and_picture(tmp_path, lee_perry_smith, found, monkeypatch):
    out, picture = tmp_path / "marks.json", tmp_path / "marks.png"
    scan_path = str(data.path("lee_perry_smith_head.obj"))
    monkeypatch.setattr(sys, "argv", ["jface"])
    main(["landmarks", scan_path, "--out", str(out), "--picture", str(picture)])
    written = json.loads(out.read_text())
    assert list(written) == list(NAMES)
    points = np.asarray([written[n] for n in NAMES])
    # Same default key, same markers: the command is deterministic.
    np.testing.assert_allclose(points, np.asarray(found.points), atol=1e-6)
    assert picture.stat().st_size > 10_000


def test_remesh_without_landmarks_finds_them(tmp_path, found, capsys, monkeypatch):
    scan_path = str(data.path("lee_perry_smith_head.obj"))
    monkeypatch.setattr(sys, "argv", ["jface"])
    out = tmp_path / "face"
    main(["remesh", scan_path, "--out", str(out), "--image-size", "64"])
    assert "no --landmarks: found the 21 landmarks" in capsys.readouterr().out
    written = json.loads((out / "landmarks.json").read_text())
    points = np.asarray([written[n] for n in NAMES])
    np.testing.assert_allclose(points, np.asarray(found.points), atol=1e-6)
    assert (out / "displacement.exr").is_file()
