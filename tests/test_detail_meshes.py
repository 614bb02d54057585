"""Mesh-level applications (Golovinskiy et al. 2006 §3.2–§3.4) on remeshed ICT-FaceKit faces."""

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail, mesh


@pytest.fixture(scope="module")
def faces(ict_model):
    """Three real face shapes (ICT-FaceKit identities), remeshed alike at 64² with a
    three-level hierarchy (marker mesh, 3 offset levels, displacement image)."""
    data = ict_model
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


@pytest.fixture(scope="module")
def face_dirs(faces, tmp_path_factory):
    """The faces written as ``jface remesh`` writes them."""
    from jface import io
    from jface.cli._mesh import write_face

    root = tmp_path_factory.mktemp("faces")
    meta = io.provenance(schedule=list(faces[0].schedule))
    for i, face in enumerate(faces):
        write_face(root / f"face{i}", face, meta, "obj")
    return [str(root / f"face{i}") for i in range(len(faces))]


def test_cli_interpolate_age_add_detail(face_dirs, faces, tmp_path, capsys):
    import json

    from jface import io
    from jface.cli import main
    from jface.cli._apps import read_face

    back = read_face(face_dirs[0])
    np.testing.assert_allclose(back.base.vertices, faces[0].base.vertices, atol=1e-5)
    np.testing.assert_allclose(back.offsets[-1], faces[0].offsets[-1], atol=1e-6)
    small = ["--grid", "4", "--iters", "4", "--json"]
    out = tmp_path / "mix"
    assert (
        main(["interpolate", *face_dirs, "--weights", "0.5,0.25,0.25", "--out", str(out), *small])
        == 0
    )
    table = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert table["coerced"]["median_tile_std_error"] < table["average"]["median_tile_std_error"]
    mixed = read_face(out / "coerced")  # outputs are face folders again
    expected = 0.5 * faces[0].base.vertices + 0.25 * (
        faces[1].base.vertices + faces[2].base.vertices
    )
    np.testing.assert_allclose(mixed.base.vertices, expected, atol=1e-4)
    assert io.read_exr(out / "coerced" / "displacement.exr").metadata["weights"] == [
        0.5,
        0.25,
        0.25,
    ]

    aged = tmp_path / "aged"
    assert (
        main(["age", face_dirs[0], face_dirs[1], "--levels", "2", "--out", str(aged), *small]) == 0
    )
    scores = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["methods"]
    assert set(scores) == set(detail.METHODS)
    result = read_face(aged / "aged")
    np.testing.assert_allclose(result.markers, faces[0].markers, atol=1e-6)
    np.testing.assert_allclose(result.offsets[2], faces[1].offsets[2], atol=1e-6)
    assert (aged / "comparison.png").is_file() and (aged / "detail_only" / "base.obj").is_file()

    stats = tmp_path / "old.stats.npz"
    detail.save_stats(stats, detail.analyze(faces[1].image, grid=4))
    added = tmp_path / "added"
    assert (
        main(["add-detail", face_dirs[2], "--stats", str(stats), "--out", str(added), *small]) == 0
    )
    errors = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["median_tile_std_error"]
    assert errors["after"] < errors["before"]

    # User errors: one line, exit 2.
    assert main(["age", face_dirs[0], str(tmp_path), "--out", str(tmp_path / "x")]) == 2
    assert "no base.obj" in capsys.readouterr().err
    assert main(["add-detail", face_dirs[0], "--db", str(stats), "--out", str(tmp_path / "y")]) == 2
    assert "--db needs --group" in capsys.readouterr().err
    assert (
        main(
            ["interpolate", *face_dirs, "--weights", "1,1,1", "--out", str(tmp_path / "z"), *small]
        )
        == 2
    )
    assert "sum to 1" in capsys.readouterr().err
    from jface import io as jio

    arrays, meta = jio.load_arrays(Path(face_dirs[1]) / "hierarchy.npz", kind="MeshHierarchy")
    broken = tmp_path / "broken"
    for name in ("base.obj", "displacement.exr"):
        (broken / name).parent.mkdir(exist_ok=True)
        (broken / name).write_bytes((Path(face_dirs[1]) / name).read_bytes())
    meta.pop("schedule")
    jio.save_arrays(broken / "hierarchy.npz", arrays, meta, kind="MeshHierarchy")
    assert main(["age", face_dirs[0], str(broken), "--out", str(tmp_path / "w")]) == 2
    assert "lacks the 'schedule' metadata field" in capsys.readouterr().err
