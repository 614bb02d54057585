"""jface.mesh: marker template, subdivision operators, image sampling, mesh/landmark files."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jface import io, mesh


def _direct_loop(vertices: np.ndarray, faces: np.ndarray, corners=()) -> np.ndarray:
    """Loop subdivision written vertex by vertex (the textbook rules), for comparison."""
    edges: dict[tuple[int, int], list[int]] = {}
    for f in faces:
        for k in range(3):
            a, b, c = int(f[k]), int(f[(k + 1) % 3]), int(f[(k + 2) % 3])
            edges.setdefault((min(a, b), max(a, b)), []).append(c)
    neighbours: dict[int, set] = {i: set() for i in range(len(vertices))}
    boundary: dict[int, set] = {i: set() for i in range(len(vertices))}
    for (a, b), opp in edges.items():
        neighbours[a].add(b)
        neighbours[b].add(a)
        if len(opp) == 1:
            boundary[a].add(b)
            boundary[b].add(a)
    out = []
    for i, v in enumerate(vertices):
        if i in corners:
            out.append(v)
        elif boundary[i]:
            b0, b1 = sorted(boundary[i])
            out.append(0.75 * v + 0.125 * (vertices[b0] + vertices[b1]))
        else:
            n = len(neighbours[i])
            beta = (5 / 8 - (3 / 8 + np.cos(2 * np.pi / n) / 4) ** 2) / n
            out.append((1 - n * beta) * v + beta * sum(vertices[j] for j in neighbours[i]))
    for (a, b), opp in sorted(edges.items()):
        if len(opp) == 1:
            out.append(0.5 * (vertices[a] + vertices[b]))
        else:
            out.append(3 / 8 * (vertices[a] + vertices[b]) + 1 / 8 * sum(vertices[c] for c in opp))
    return np.array(out)


@pytest.fixture(scope="module")
def template():
    return mesh.marker_template()


def test_template_is_a_triangulated_square(template):
    uv, faces = template.uv, template.faces
    assert template.n_points == 21 and faces.shape == (32, 3)
    p = uv[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
    assert np.all(area > 0), "every triangle counter-clockwise in the layout"
    assert np.isclose(area.sum(), 1.0), "the triangles tile the unit square"
    assert sorted(map(tuple, uv[list(template.corners)])) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert len(set(template.names)) == 21 and set(mesh.MEDIAPIPE_IDS) == set(template.names)


def test_loop_operator_matches_direct_implementation(template):
    points = np.concatenate([template.uv, np.sin(3 * template.uv[:, :1])], axis=1)
    _, op = mesh.subdivide_topology(template.faces, 21, "loop", template.corners)
    want = _direct_loop(points, template.faces, set(template.corners))
    np.testing.assert_allclose(op.dense() @ points, want, atol=1e-6)
    np.testing.assert_allclose(op.dense().sum(axis=1), 1.0, atol=1e-6)  # affine invariance


def test_loop_matches_trimesh_on_closed_mesh():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    ours, faces = mesh.subdivide(np.asarray(sphere.vertices, np.float32), sphere.faces, "loop")
    theirs = trimesh.remesh.subdivide_loop(sphere.vertices, sphere.faces)[0]
    assert len(faces) == 4 * len(sphere.faces)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(theirs).query(np.asarray(ours))
    assert dist.max() < 1e-5


def test_loop_on_plane_stays_planar_with_square_fixed(template):
    square = np.concatenate([template.uv, np.zeros((21, 1))], axis=1).astype(np.float32)
    points, faces = mesh.subdivide(
        square, template.faces, "loop", levels=3, corners=template.corners
    )
    points = np.asarray(points)
    assert np.all(points[:, 2] == 0), "a plane stays a plane"
    np.testing.assert_array_equal(points[list(template.corners)], square[list(template.corners)])
    topo_boundary = mesh._subdivision.Topology(faces, len(points)).boundary_edges().ravel()
    on_border = points[np.unique(topo_boundary), :2]
    assert np.all(np.min(np.abs(np.concatenate([on_border, 1 - on_border], 1)), 1) < 1e-6)
    assert points[:, :2].min() >= -1e-6 and points[:, :2].max() <= 1 + 1e-6


def test_linear_subdivision_keeps_vertices_and_adds_midpoints(template):
    faces, op = mesh.subdivide_topology(template.faces, 21, "linear")
    out = np.asarray(op(jnp.asarray(template.uv, dtype=jnp.float32)))
    np.testing.assert_allclose(out[:21], template.uv, atol=1e-7)
    topo = mesh._subdivision.Topology(template.faces, 21)
    np.testing.assert_allclose(out[21:], template.uv[topo.edges].mean(axis=1), atol=1e-7)
    assert faces.shape == (128, 3)


def test_operator_jit_and_vmap(template):
    hier = mesh.template_hierarchy(None, 1, 1, 0)
    op = hier.levels[2].operator
    x = jax.random.normal(jax.random.key(1), (3, op.n_in, 3), dtype=jnp.float32)
    looped = jnp.stack([op(xi) for xi in x])
    np.testing.assert_allclose(jax.vmap(op)(x), looped, atol=1e-6)
    np.testing.assert_allclose(jax.jit(lambda o, v: o(v))(op, x[0]), looped[0], atol=1e-6)


def test_hierarchy_uv_covers_square_and_sampler_is_exact_for_linear_functions():
    hier = mesh.template_hierarchy(None, 2, 1, 1)
    base = hier.base
    assert base.faces.shape == (32 * 4**4, 3)
    sampler = mesh.image_sampler(np.asarray(base.uv), base.faces, (64, 48))
    image = np.asarray(sampler(base.uv[:, 0]))
    cols = (np.arange(48) + 0.5) / 48
    np.testing.assert_allclose(image, np.broadcast_to(cols, (64, 48)), atol=1e-5)
    back = mesh.sample_image(jnp.asarray(image), base.uv)
    np.testing.assert_allclose(back, base.uv[:, 0], atol=1.0 / 48)


def test_mesh_files_round_trip_with_uv(tmp_path, template):
    points = np.concatenate([template.uv, np.ones((21, 1))], axis=1)
    for suffix in (".obj", ".ply"):
        path = io.write_mesh(tmp_path / f"m{suffix}", points, template.faces, uv=template.uv)
        back = io.read_mesh(path, merge=False)
        np.testing.assert_allclose(back.vertices, points, atol=1e-6)
        np.testing.assert_array_equal(back.faces, template.faces)
        np.testing.assert_allclose(back.uv, template.uv, atol=1e-6)
        with pytest.raises(ValueError, match="overwrite the input"):
            io.write_mesh(path, points, template.faces, protect=(path,))


def test_landmark_files_and_names(tmp_path):
    ids = dict(mesh.MEDIAPIPE_IDS)
    face = mesh.canonical_face()
    io.write_landmarks(tmp_path / "l.json", ids)
    got = mesh.landmark_points(io.read_landmarks(tmp_path / "l.json"), face.vertices)
    np.testing.assert_allclose(got, mesh.mediapipe_landmarks(face.vertices))
    rows = [f"{n},{x},{y},{z}" for n, (x, y, z) in zip(ids, np.asarray(got), strict=True)]
    (tmp_path / "l.csv").write_text("name,x,y,z\n" + "\n".join(rows) + "\n")
    np.testing.assert_allclose(mesh.landmark_points(io.read_landmarks(tmp_path / "l.csv")), got)


@pytest.mark.usefixtures("unchecked")
def test_bad_landmarks(tmp_path):
    ids = dict(mesh.MEDIAPIPE_IDS)
    verts = np.asarray(mesh.canonical_face().vertices)
    with pytest.raises(ValueError, match=r"missing \['chin'\]"):
        mesh.landmark_points({k: v for k, v in ids.items() if k != "chin"}, verts)
    with pytest.raises(ValueError, match=r"unknown \['nose'\]"):
        mesh.landmark_points(ids | {"nose": 3}, verts)
    with pytest.raises(ValueError, match="outside"):
        mesh.landmark_points(ids | {"chin": 10_000}, verts)
    with pytest.raises(ValueError, match="pass the scan's vertices"):
        mesh.landmark_points(ids)
    (tmp_path / "dup.csv").write_text("chin,1\nchin,2\n")
    with pytest.raises(ValueError, match="duplicate landmark name"):
        io.read_landmarks(tmp_path / "dup.csv")
    (tmp_path / "dup.json").write_text('{"chin": 1, "chin": 2}')
    with pytest.raises(ValueError, match="duplicate landmark name"):
        io.read_landmarks(tmp_path / "dup.json")
    (tmp_path / "bad.json").write_text(json.dumps({"chin": [1, 2]}))
    with pytest.raises(ValueError, match="vertex id or three coordinates"):
        io.read_landmarks(tmp_path / "bad.json")
    with pytest.raises(FileNotFoundError):
        io.read_landmarks(tmp_path / "none.json")


def test_bad_mesh_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        io.read_mesh(tmp_path / "missing.obj")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match="no faces"):
        io.read_mesh(tmp_path / "points.obj")
    (tmp_path / "empty.obj").write_text("")
    with pytest.raises(ValueError, match=r"empty|no faces|not a readable"):
        io.read_mesh(tmp_path / "empty.obj")
    (tmp_path / "junk.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(ValueError, match=r"not a readable mesh|empty|no faces"):
        io.read_mesh(tmp_path / "junk.ply")
    with pytest.raises(ValueError, match=r"\.obj or \.ply"):
        io.write_mesh(tmp_path / "m.stl", np.zeros((3, 3)), np.array([[0, 1, 2]]))


@pytest.mark.usefixtures("unchecked")
def test_non_manifold_and_degenerate_topology():
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])
    with pytest.raises(ValueError, match="non-manifold"):
        mesh.subdivide_topology(faces, 5, "loop")
    with pytest.raises(ValueError, match="degenerate"):
        mesh.subdivide_topology(np.array([[0, 0, 1]]), 2, "loop")
    with pytest.raises(ValueError, match="scheme"):
        mesh.subdivide_topology(faces[:1], 3, "butterfly")


def test_cli_remesh_and_displace(tmp_path, capsys, written_figures):
    from jface.cli import main

    face = mesh.canonical_face()
    scan = io.write_mesh(tmp_path / "face.obj", np.asarray(face.vertices), np.asarray(face.faces))
    marks = io.write_landmarks(tmp_path / "marks.json", mesh.MEDIAPIPE_IDS)
    out = tmp_path / "out"
    small = ["--linear", "1", "--loop", "1", "--smooth", "1", "--image-size", "64"]
    argv = ["remesh", str(scan), "--landmarks", str(marks), "--out", str(out), *small]
    assert main(argv) == 0
    assert "hit rates" in capsys.readouterr().out
    names = {p.name for p in out.iterdir()}
    assert {"base.obj", "displacement.exr", "displacement.png", "base_shaded.png"} <= names
    for name in ("base_shaded.png", "detailed_shaded.png"):  # 3-D views: frontal and turned
        axes = [ax for ax in written_figures[name].axes if ax.images]
        assert [ax.get_title() for ax in axes] == ["frontal", "turned 35°"]
        for view in (np.asarray(ax.images[0].get_array(), np.float64) for ax in axes):
            assert view.shape == (64, 64)
            assert view[0, 0] == 0 and view[-1, -1] == 0  # background around the face
            assert view[32, 32] > 0  # the lit face in the middle
        assert io.read_image(out / name).shape[1] > 2 * 64  # a figure, not the raw views
    exr = io.read_exr(out / "displacement.exr")
    assert exr.metadata["source"] == "face.obj" and exr.metadata["schedule"] == [1, 1, 1]
    assert np.all(np.isfinite(exr.channels["Y"]))
    result = tmp_path / "detailed.ply"
    argv = ["displace", str(out / "base.obj"), str(out / "displacement.exr"), "--out", str(result)]
    assert main([*argv, "--extra", "1"]) == 0
    detailed = io.read_mesh(result, merge=False)
    assert len(detailed.faces) == 4 * 32 * 4**3 and detailed.uv is not None
    base = out / "base.obj"
    before = base.read_bytes()
    argv = ["displace", str(base), str(out / "displacement.exr"), "--out", str(base)]
    assert main(argv) == 2  # an input is never overwritten
    assert base.read_bytes() == before
    assert "overwrite" in capsys.readouterr().err


def test_paper_schedule_sizes():
    hier = mesh.template_hierarchy()  # 2 linear + 2 Loop projected, 3 Loop smoothing
    assert [level.scheme for level in hier.levels[1:]] == ["linear"] * 2 + ["loop"] * 5
    assert hier.control.faces.shape == (8192, 3)
    assert hier.base.faces.shape == (524_288, 3)  # the paper's "~500k triangles"
    uv = np.asarray(hier.base.uv)
    assert uv.min() >= -1e-6 and uv.max() <= 1 + 1e-6
    corners = uv[list(mesh.marker_template().corners)]
    np.testing.assert_allclose(sorted(map(tuple, corners)), [(0, 0), (0, 1), (1, 0), (1, 1)])
