"""Mesh-level applications (Golovinskiy et al. 2006 §3.2–§3.4) on remeshed ICT-FaceKit faces."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_DATA

from jface import detail, mesh

ICT = SHARED_DATA / "ict_facekit" / "ict_face_area.npz"


@pytest.fixture(scope="module")
def faces():
    """Three real face shapes (ICT-FaceKit identities), remeshed alike at 64² with a
    three-level hierarchy (marker mesh, 3 offset levels, displacement image)."""
    if not ICT.is_file():
        pytest.skip("ICT-FaceKit data not found beside the repository")
    data = np.load(ICT)
    neutral, triangles = data["vertices"].astype(np.float64), data["faces"]
    deltas = data["identity_deltas"].astype(np.float64)
    rng = np.random.default_rng(0)
    out = []
    for _ in range(3):
        person = neutral + np.tensordot(rng.normal(size=len(deltas)), deltas, axes=1)
        remeshed = mesh.remesh(
            person, triangles, mesh.ict_landmarks(person), image_size=64,
            n_linear=2, n_loop=1, n_smooth=1,
        )  # fmt: skip
        out.append(detail.Face.from_remeshed(remeshed))
    return out


def _stats(faces):
    return detail.analyze_batch(jnp.stack([f.image for f in faces]), grid=4)


def test_interpolated_faces_share_layout_and_mix_vertices(faces, key):
    weights = np.array([0.5, 0.3, 0.2])
    result = detail.interpolate_faces(key, faces, _stats(faces), jnp.asarray(weights))
    expected = np.einsum("n,nvc->vc", weights, np.stack([f.base.vertices for f in faces]))
    for face in (result.average, result.coerced):
        np.testing.assert_allclose(face.base.vertices, expected, atol=1e-5)
        np.testing.assert_array_equal(face.base.faces, faces[0].base.faces)
        np.testing.assert_array_equal(face.base.uv, faces[0].base.uv)
        assert face.detailed().vertices.shape == faces[0].base.vertices.shape
    average = np.einsum("n,nhw->hw", weights, np.stack([f.image for f in faces]))
    np.testing.assert_allclose(result.average.image, average, atol=1e-6)
    # The coerced face is closer to the interpolated statistics than the plain average.
    errors = [
        float(jnp.median(detail.stats_error(detail.analyze(f.image, grid=4), result.target)))
        for f in (result.average, result.coerced)
    ]
    assert errors[1] < 0.5 * errors[0]


def test_one_hot_interpolation_reproduces_the_face(faces, key):
    result = detail.interpolate_faces(key, faces, _stats(faces), jnp.asarray([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(result.average.base.vertices, faces[1].base.vertices, atol=1e-6)
    np.testing.assert_allclose(result.average.image, faces[1].image, atol=1e-6)
    np.testing.assert_allclose(result.average.markers, faces[1].markers, atol=1e-6)


def test_swapping_nothing_or_everything_reproduces_each_face(faces):
    a, b = faces[:2]
    assert a.n_levels == 5
    np.testing.assert_array_equal(detail.swap_levels(a, b, 0).base.vertices, b.base.vertices)
    whole = detail.swap_levels(a, b, a.n_levels)
    np.testing.assert_allclose(whole.base.vertices, a.base.vertices, atol=1e-5)
    np.testing.assert_array_equal(whole.image, a.image)
    mixed = detail.swap_levels(a, b, 2)  # a's marker mesh and first level, b's finer levels
    np.testing.assert_array_equal(mixed.markers, a.markers)
    np.testing.assert_array_equal(mixed.offsets[0], a.offsets[0])
    np.testing.assert_array_equal(mixed.offsets[1], b.offsets[1])
    np.testing.assert_array_equal(mixed.image, b.image)
    gap = [np.abs(np.asarray(mixed.base.vertices) - f.base.vertices).max() for f in (a, b)]
    assert min(gap) > 0.05  # a new face, not a copy of either (cm)


def test_age_and_add_detail(faces, key):
    young, old = faces[:2]
    target = detail.analyze(old.image, grid=4)
    aged = detail.age(key, young, old, target, n_coarse=2)
    np.testing.assert_array_equal(aged.markers, young.markers)
    np.testing.assert_array_equal(aged.offsets[0], young.offsets[0])
    np.testing.assert_array_equal(aged.offsets[2], old.offsets[2])
    np.testing.assert_array_equal(aged.image, detail.synthesize(key, young.image, target))
    added = detail.add_detail(key, young, target)
    np.testing.assert_array_equal(added.base.vertices, young.base.vertices)
    np.testing.assert_array_equal(added.image, aged.image)
    detailed = added.detailed(extra_subdivisions=1)
    assert detailed.faces.shape[0] == 4 * young.base.faces.shape[0]


def test_bad_faces(unchecked, faces, key):
    stats = _stats(faces)
    with pytest.raises(ValueError, match="at least one face"):
        detail.interpolate_faces(key, [], stats, jnp.ones(0))
    with pytest.raises(TypeError, match="faces\\[1\\] must be"):
        detail.interpolate_faces(key, [faces[0], "x"], stats, jnp.ones(2) / 2)
    small = eqx.tree_at(lambda f: f.image, faces[1], faces[1].image[:32, :32])
    with pytest.raises(ValueError, match="remesh every face with the same settings"):
        detail.swap_levels(faces[0], small, 1)
    with pytest.raises(ValueError, match="sum to 1"):
        detail.interpolate_faces(key, faces, stats, jnp.ones(3))
    with pytest.raises(ValueError, match="n_coarse must be in \\[1, 4\\]"):
        detail.age(key, faces[0], faces[1], jax.tree.map(lambda x: x[0], stats), n_coarse=5)
    wrong = detail.analyze_batch(jnp.stack([f.image[:32, :32] for f in faces]), grid=2, n_scales=3)
    with pytest.raises(ValueError, match="stats describe images of \\(32, 32\\)"):
        detail.interpolate_faces(key, faces, wrong, jnp.ones(3) / 3)
