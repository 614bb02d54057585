"""Built-in face and synthetic scans with known fine detail (for the demo and round-trip tests).

The MediaPipe canonical face (Apache-2.0, shipped in ``jface/data``) is Loop-subdivided into a
smooth surface ``S`` and displaced along its normals by a known random field ``d``: the scan is
``S + d(S)·n(S)``, and remeshing it should recover ``d`` as the displacement image.
"""

from __future__ import annotations

from importlib import resources

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jface import _checks
from jface.mesh._geometry import vertex_normals
from jface.mesh._remesh import Mesh
from jface.mesh._subdivision import subdivide
from jface.mesh._template import LANDMARK_NAMES, MEDIAPIPE_IDS


def canonical_face() -> Mesh:
    """The MediaPipe canonical face: 468 vertices, 898 triangles, per-vertex UVs, units cm."""
    from jface.io import read_mesh

    path = resources.files("jface") / "data" / "mediapipe_canonical_face.obj"
    with resources.as_file(path) as file:
        data = read_mesh(file, merge=False)
    return Mesh(
        jnp.asarray(data.vertices, dtype=jnp.float32),
        jnp.asarray(data.faces, dtype=jnp.int32),
        None if data.uv is None else jnp.asarray(data.uv, dtype=jnp.float32),
    )


class DetailField(eqx.Module):
    """A known fine displacement field on 3-D space: a sum of random plane waves,
    ``d(p) = a · sqrt(2 / K) · Σ_k cos(ω_k · p + φ_k)`` (RMS ``a``).

    Attributes:
        frequencies: ``(K, 3)`` angular wave vectors, ``|ω_k| = 2π / wavelength``.
        phases: ``(K,)``.
        amplitude: RMS amplitude ``a``.
    """

    frequencies: Float[Array, "k 3"]
    phases: Float[Array, " k"]
    amplitude: Float[Array, ""]

    def __call__(self, points: Float[Array, "n 3"]) -> Float[Array, " n"]:
        """The displacement at ``(n, 3)`` points."""
        freq = self.frequencies.astype(points.dtype)
        waves = jnp.cos(points @ freq.T + self.phases.astype(points.dtype))
        scale = self.amplitude.astype(points.dtype) * jnp.sqrt(2.0 / freq.shape[0]).astype(
            points.dtype
        )
        return scale * jnp.sum(waves, axis=-1)


def detail_field(
    key: Array, *, wavelength: float = 0.3, amplitude: float = 0.02, n_waves: int = 96
) -> DetailField:
    """A random :class:`DetailField` with wave lengths in ``[wavelength, 2·wavelength]``.

    Args:
        key: a ``jax.random.key``.
        wavelength: shortest wave length (scan units; cm for the canonical face).
        amplitude: RMS displacement.
        n_waves: number of plane waves.
    """
    wavelength = _checks.real(wavelength, "wavelength", low=0.0, open_low=True)
    amplitude = _checks.real(amplitude, "amplitude", low=0.0)
    n_waves = _checks.integer(n_waves, "n_waves", low=1, high=4096)
    k_dir, k_len, k_phase = jax.random.split(key, 3)
    direction = jax.random.normal(k_dir, (n_waves, 3), dtype=jnp.float32)
    direction = direction / jnp.linalg.norm(direction, axis=1, keepdims=True)
    lengths = wavelength * (1.0 + jax.random.uniform(k_len, (n_waves,), dtype=jnp.float32))
    phases = jax.random.uniform(k_phase, (n_waves,), dtype=jnp.float32, maxval=2 * np.pi)
    return DetailField(
        direction * (2 * np.pi / lengths)[:, None],
        phases,
        jnp.asarray(amplitude, dtype=jnp.float32),
    )


class SyntheticScan(eqx.Module):
    """A scan with known detail: ``vertices = smooth + detail(smooth) · normals``.

    Attributes:
        scan: the displaced mesh (what a scanner would give).
        smooth: the Loop-subdivided face before displacement (same faces).
        detail: the displacement field.
        landmarks: name → vertex id of the scan (MediaPipe ids survive subdivision).
    """

    scan: Mesh
    smooth: Float[Array, "v 3"]
    detail: DetailField
    landmarks: dict[str, int] = eqx.field(static=True)


def synthetic_scan(
    key: Array,
    face: Mesh | None = None,
    *,
    n_subdivisions: int = 4,
    wavelength: float = 0.3,
    amplitude: float = 0.02,
) -> SyntheticScan:
    """A "scan" from a real face: Loop-subdivided, plus a known fine displacement.

    Args:
        key: a ``jax.random.key`` for the detail field.
        face: a MediaPipe-topology face (default: :func:`canonical_face`).
        n_subdivisions: Loop subdivisions (4: ~115k vertices, 230k triangles).
        wavelength, amplitude: of the detail field (:func:`detail_field`), in the face's units.
    """
    face = face or canonical_face()
    n_subdivisions = _checks.integer(n_subdivisions, "n_subdivisions", low=0, high=6)
    smooth, faces = subdivide(face.vertices, np.asarray(face.faces), "loop", levels=n_subdivisions)
    field = detail_field(key, wavelength=wavelength, amplitude=amplitude)
    faces_j = jnp.asarray(faces, dtype=jnp.int32)
    normals = vertex_normals(smooth, faces_j)
    vertices = smooth + field(smooth)[:, None] * normals
    landmarks = {name: MEDIAPIPE_IDS[name] for name in LANDMARK_NAMES}
    return SyntheticScan(Mesh(vertices, faces_j, None), smooth, field, landmarks)


def _cast_base(base: Mesh, vertices: np.ndarray, faces: np.ndarray):
    """Rays from the base vertices along the base normals onto a mesh, reaching 5% of its
    bounding-box diagonal (far beyond any fine detail; a whole-diagonal reach makes the exact
    caster search the whole mesh for the rays that leave the border)."""
    from jface.mesh._raycast import ScanIndex, cast

    points = np.asarray(base.vertices, dtype=np.float64)
    normals = np.asarray(vertex_normals(base.vertices, jnp.asarray(base.faces)), dtype=np.float64)
    reach = 0.05 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    return points, normals, cast(ScanIndex(vertices, faces), points, normals, reach)


def known_displacement(synthetic: SyntheticScan, base: Mesh) -> Float[Array, " v"]:
    """The detail a synthetic scan carries where each base vertex's normal meets it: the scan's
    per-vertex displacement interpolated over the scan triangle that the ray hits (0 where it
    misses). What :func:`~jface.mesh.remesh` should recover, per base vertex, up to the base
    mesh's own departure from the smooth face (:func:`smooth_offset`).

    Args:
        synthetic: from :func:`synthetic_scan`.
        base: the base mesh of a remeshing of ``synthetic.scan``.
    """
    import trimesh

    verts = np.asarray(synthetic.scan.vertices, dtype=np.float64)
    faces = np.asarray(synthetic.scan.faces)
    points, normals, hits = _cast_base(base, verts, faces)
    tri = faces[np.maximum(hits.triangle, 0)]
    bary = trimesh.triangles.points_to_barycentric(
        verts[tri], points + hits.distance[:, None] * normals
    )
    per_vertex = np.asarray(synthetic.detail(synthetic.smooth), dtype=np.float64)
    known = np.where(hits.hit, np.sum(bary * per_vertex[tri], axis=1), 0.0)
    return jnp.asarray(known, dtype=jnp.float32)


def smooth_offset(synthetic: SyntheticScan, base: Mesh) -> Float[Array, " v"]:
    """Signed distance from each base vertex along its normal to the smooth face the synthetic
    detail was added to (0 where the ray misses): how far the base mesh departs from that
    surface. A displacement measured from the base is ``known_displacement + smooth_offset``.

    Args:
        synthetic: from :func:`synthetic_scan`.
        base: the base mesh of a remeshing of ``synthetic.scan``.
    """
    smooth = np.asarray(synthetic.smooth, dtype=np.float64)
    _, _, hits = _cast_base(base, smooth, np.asarray(synthetic.scan.faces))
    return jnp.asarray(np.where(hits.hit, hits.distance, 0.0), dtype=jnp.float32)
