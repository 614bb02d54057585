"""The 21 template landmarks of a scan with no clicks: the ICT-FaceKit face model shipped with
jface, fitted to the scan by robust least squares, its landmark vertices projected onto the scan.

1. **Samples.** ``n_points`` points drawn uniformly over the scan's area (seeded), with normals
   smoothed over a few rings (scanner noise), centred and scaled to unit RMS radius: every later
   step is free of the scan's unit and position, and scans resampled to the same size batch
   with ``vmap``.
2. **Pose hypotheses from the geometry.** The principal axis across which the scan is most
   mirror-symmetric is the left-right axis; the model's up and front go along the other two,
   with any sign (8 rotations). For each, the model's nose tip goes to one of the scan points
   that protrude most above their surroundings along that front and face it (the nose, but
   maybe the chin or a shoulder: several, kept apart), at two scales (a face-only scan, a bust).
3. **Fit.** Iterated closest points, each round a Gauss–Newton solve (optimistix) of the
   point-to-plane distances (plus a tenth of the point-to-point ones, against sliding) of the
   model's face vertices to their nearest scan samples, over the similarity transform and, in
   the refinement, the identity and expression coefficients under their Gaussian prior. Pairs
   farther than a trimming distance, or whose normals disagree, are dropped, and the others
   weighted by a Cauchy loss, so hair, ears, neck, shoulders and holes do not pull the fit; the
   trimming distance shrinks from round to round. Every hypothesis is fitted as a similarity;
   the best few by score are refined with the shape coefficients, and the best of those wins.
4. **Markers.** The fitted model's landmark vertices (``ICT_IDS``) go back to the scan's frame
   and onto its surface (exact closest points).

The score is the mean over the model's face vertices of ``min(d² / τ², 1)``, with ``d`` the
point-to-plane distance to the nearest scan sample (a pair beyond the last trimming distance
counts 1) and ``τ`` a twentieth of the fitted face's RMS radius: 0 for a perfect face, 1 where
nothing fits. Above ``max_score`` no face was found.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from jface import _checks
from jface.mesh._raycast import ScanIndex, closest_points
from jface.mesh._remesh import _scan_arrays
from jface.mesh._template import ICT_IDS, LANDMARK_NAMES

#: Trimming distances of the rigid rounds and of the refinement, in units of the face's RMS
#: radius (the model's face vertices about their centroid).
_RIGID_TRIM = (0.8, 0.6, 0.45, 0.35, 0.28, 0.22, 0.18, 0.15, 0.12, 0.12)
_SHAPE_TRIM = (0.15, 0.12, 0.1, 0.08, 0.07, 0.06, 0.05, 0.05, 0.05, 0.05)
#: Scales of the face hypotheses relative to the scan's RMS radius (a face-only scan, a head, a
#: bust with shoulders).
_SCALES = (0.8, 0.45)
#: Scan points per rotation and scale where the nose tip may be.
_NOSE_CANDIDATES = 3
#: The score's distance scale (face radii) and the rings over which normals are smoothed.
_SCORE_TRIM = 0.05
_NORMAL_SMOOTHING = 3
#: Samples and model vertices of the rigid fits, samples near the face of the refinement.
_COARSE_SCAN, _COARSE_MODEL, _FINE_SCAN = 4096, 300, 4096


class FaceModel(eqx.Module):
    """A linear face model: ``mean + Σ identity_i · w_i + Σ expression_j · e_j``.

    Attributes:
        mean: ``(V, 3)`` neutral face.
        identity: ``(k, V, 3)`` identity modes (coefficients ~ N(0, 1)).
        expression: ``(e, V, 3)`` expression modes (coefficients in [0, 1]).
        faces: ``(F, 3)`` triangles.
        landmark_ids: ``(21,)`` vertex ids of the template landmarks.
        fit_ids: ``(m,)`` the vertices fitted to a scan (the face, without the neck).
    """

    mean: Float[Array, "v 3"]
    identity: Float[Array, "k v 3"]
    expression: Float[Array, "e v 3"]
    faces: Int[Array, "f 3"]
    landmark_ids: Int[Array, " 21"]
    fit_ids: Int[Array, " m"]

    def shape(self, identity: Array, expression: Array) -> Float[Array, "v 3"]:
        """The model's vertices for the given coefficients."""
        return (
            self.mean
            + jnp.tensordot(identity, self.identity, axes=1)
            + jnp.tensordot(expression, self.expression, axes=1)
        )


def face_model() -> FaceModel:
    """The ICT-FaceKit face area shipped with jface (:func:`jface.data.ict_face_model`, cm): 10
    identity modes, the smile expression; fitted on the vertices above the chin."""
    from jface import data

    arrays = data.ict_face_model()
    mean = np.asarray(arrays["vertices"], np.float32)
    ids = np.array([ICT_IDS[n] for n in LANDMARK_NAMES])
    chin = mean[ICT_IDS["chin"], 1]
    # The neck is left out: its pose relative to the face varies from scan to scan.
    keep = np.flatnonzero(mean[:, 1] > chin - 1.0)
    return FaceModel(
        mean=jnp.asarray(mean),
        identity=jnp.asarray(arrays["identity_deltas"], jnp.float32),
        expression=jnp.asarray(arrays["smile_delta"], jnp.float32)[None],
        faces=jnp.asarray(arrays["faces"], jnp.int32),
        landmark_ids=jnp.asarray(ids, jnp.int32),
        fit_ids=jnp.asarray(keep, jnp.int32),
    )


class Samples(eqx.Module):
    """Points sampled over a scan's surface, normalised (zero mean, unit RMS radius).

    Attributes:
        points: ``(n, 3)`` normalised positions.
        normals: ``(n, 3)`` unit normals (vertex normals smoothed over a few rings, interpolated).
        center: ``(3,)`` and scale: ``()`` the normalisation, ``x = points · scale + center``.
    """

    points: Float[Array, "n 3"]
    normals: Float[Array, "n 3"]
    center: Float[Array, " 3"]
    scale: Float[Array, ""]


def sample_surface(key: Array, vertices: Array, faces: Array, n_points: int) -> Samples:
    """``n_points`` points uniform over the area of a triangle mesh, normalised (pure, jittable).

    Args:
        key: a JAX PRNG key.
        vertices: ``(V, 3)`` positions; faces: ``(F, 3)`` triangles.
        n_points: how many samples (static).
    """
    vertices = jnp.asarray(vertices, jnp.float32)
    faces = jnp.asarray(faces)
    tri = vertices[faces]
    cross = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = jnp.linalg.norm(cross, axis=1)
    pick, bary = jax.random.split(key)
    which = jax.random.choice(pick, len(area), (n_points,), p=area / jnp.sum(area))
    a, b = jax.random.uniform(bary, (2, n_points, 1), vertices.dtype)
    fold = a + b > 1.0  # reflect into the triangle: uniform barycentric coordinates
    a, b = jnp.where(fold, 1.0 - a, a), jnp.where(fold, 1.0 - b, b)
    t = tri[which]
    points = t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])
    # Normals smoothed over a few rings, so scanner noise does not scramble point-to-plane
    # distances; interpolated like the points.
    normals = _vertex_normals(vertices, faces)
    for _ in range(_NORMAL_SMOOTHING):
        normals = _vertex_normals(vertices, faces, normals[faces].sum(axis=1) * area[:, None])
    n = normals[faces[which]]
    normals = n[:, 0] + a * (n[:, 1] - n[:, 0]) + b * (n[:, 2] - n[:, 0])
    normals = normals / jnp.maximum(jnp.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    center = jnp.mean(points, axis=0)
    scale = jnp.sqrt(jnp.mean(jnp.sum((points - center) ** 2, axis=1)))
    return Samples((points - center) / scale, normals, center, scale)


class Pose(eqx.Module):
    """A similarity in the normalised frame: ``x ↦ scale · rotation @ x + translation`` (or a
    batch of them)."""

    rotation: Float[Array, "*batch 3 3"]
    scale: Float[Array, "*batch"]
    translation: Float[Array, "*batch 3"]


class Fit(eqx.Module):
    """The model fitted to normalised samples.

    Attributes:
        pose: model frame (face vertices centred, unit RMS radius) → normalised scan frame.
        identity: ``(k,)`` and expression: ``(e,)`` the shape coefficients.
        score: the truncated residual (module docstring): 0 perfect, 1 nothing fits.
        inliers: fraction of the face vertices within the trimming distance of the scan.
        rms: RMS distance of those inliers, in units of the face's RMS radius.
    """

    pose: Pose
    identity: Float[Array, " k"]
    expression: Float[Array, " e"]
    score: Float[Array, ""]
    inliers: Float[Array, ""]
    rms: Float[Array, ""]


def _rotation(w: Array) -> Array:
    """Rodrigues' formula, with its Taylor series near 0 (the solver linearises at w = 0)."""
    theta2 = jnp.sum(w * w)
    small = theta2 < 1e-8
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / (theta * theta))
    zero = jnp.zeros((), w.dtype)
    k = jnp.array([[zero, -w[2], w[1]], [w[2], zero, -w[0]], [-w[1], w[0], zero]])
    return jnp.eye(3, dtype=w.dtype) + a * k + b * (k @ k)


class _Frame(eqx.Module):
    """The model's fitted vertices in its own normalised frame."""

    base: Float[Array, "m 3"]
    identity: Float[Array, "k m 3"]
    expression: Float[Array, "e m 3"]
    normals: Float[Array, "m 3"]
    nose: Float[Array, " 3"]


def _frame(model: FaceModel, n_model: int) -> tuple[_Frame, Array, Array]:
    """The model's face vertices (every ``stride``-th, ``n_model`` at most), centred and scaled
    to unit RMS radius; and that centre and radius (cm)."""
    ids = model.fit_ids
    stride = max(1, -(-len(ids) // n_model))
    ids = ids[::stride]
    mean = model.mean[ids]
    center = jnp.mean(mean, axis=0)
    radius = jnp.sqrt(jnp.mean(jnp.sum((mean - center) ** 2, axis=1)))
    normals = _vertex_normals(model.mean, model.faces)[ids]
    nose = (model.mean[ICT_IDS["nose_tip"]] - center) / radius
    frame = _Frame(
        (mean - center) / radius,
        model.identity[:, ids] / radius,
        model.expression[:, ids] / radius,
        normals,
        nose,
    )
    return frame, center, radius


def _vertex_normals(vertices: Array, faces: Array, face_vectors: Array | None = None) -> Array:
    """Unit vertex normals: the sum of the adjacent faces' vectors (default: area normals)."""
    if face_vectors is None:
        tri = vertices[faces]
        face_vectors = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    cross = face_vectors
    out = jnp.zeros_like(vertices)
    for k in range(3):
        out = out.at[faces[:, k]].add(cross)
    return out / jnp.maximum(jnp.linalg.norm(out, axis=1, keepdims=True), 1e-30)


def _nearest(query: Array, points: Array) -> Array:
    """Index of the nearest of ``points`` to each query (brute force: fixed shapes, vmappable)."""
    d2 = (
        jnp.sum(query**2, axis=1)[:, None]
        - 2.0 * query @ points.T
        + jnp.sum(points**2, axis=1)[None, :]
    )
    return jnp.argmin(d2, axis=1)


def _icp(
    frame: _Frame,
    samples: Samples,
    pose: Pose,
    identity: Array,
    expression: Array,
    trims: tuple[float, ...],
    shape: bool,
) -> Fit:
    """Trimmed, Cauchy-weighted ICP: per round, correspondences then a Gauss–Newton solve."""
    solver = optx.GaussNewton(rtol=1e-5, atol=1e-6)

    def place(params, rotation):
        w, log_s, t, ident, expr = params
        verts = (
            frame.base
            + jnp.tensordot(ident, frame.identity, axes=1)
            + jnp.tensordot(expr, frame.expression, axes=1)
        )
        rot = rotation @ _rotation(w)
        return jnp.exp(log_s) * verts @ rot.T + t, rot

    def round_(carry, trim):
        rotation, log_s, t, ident, expr = carry
        params = (jnp.zeros(3, t.dtype), log_s, t, ident, expr)
        placed, _ = place(params, rotation)
        near = _nearest(placed, samples.points)
        target, normal = samples.points[near], samples.normals[near]
        size = jnp.exp(log_s)
        dist = jnp.linalg.norm(placed - target, axis=1) / size
        facing = jnp.abs(jnp.sum((frame.normals @ rotation.T) * normal, axis=1)) > 0.5
        cauchy = 1.0 / (1.0 + (3.0 * dist / trim) ** 2)
        weight = jnp.sqrt(jnp.where((dist < trim) & facing, cauchy, 0.0))

        def residuals(p, _):
            moved, _ = place(p, rotation)
            delta = (moved - target) / jnp.exp(p[1])
            plane = jnp.sum(delta * normal, axis=1)
            # 1/σ with σ = 1 % of the face: the data outweighs the N(0, 1) prior on identity.
            data = 300.0 * weight[:, None] * jnp.concatenate([plane[:, None], 0.1 * delta], 1)
            used = jnp.maximum(jnp.sum(weight > 0), 1).astype(weight.dtype)
            count = jnp.sqrt(used / len(weight))
            return (data.ravel() / jnp.sqrt(len(weight)) / count, p[3], p[4])

        free = params if shape else params[:3]

        def fn(free, args):  # the rigid rounds hold the shape coefficients fixed
            return residuals(free if shape else (*free, ident, expr), args)

        sol = optx.least_squares(fn, solver, free, max_steps=6, throw=False)
        out = sol.value if shape else (*sol.value, ident, expr)
        w, log_s, t, ident, expr = out
        return (rotation @ _rotation(w), log_s, t, ident, expr), None

    start = (pose.rotation, jnp.log(pose.scale), pose.translation, identity, expression)
    end, _ = jax.lax.scan(round_, start, jnp.asarray(trims, pose.scale.dtype))
    rotation, log_s, t, ident, expr = end
    placed, _ = place((jnp.zeros(3, t.dtype), log_s, t, ident, expr), rotation)
    near = _nearest(placed, samples.points)
    delta = (placed - samples.points[near]) / jnp.exp(log_s)
    # Point-to-plane, so the score does not depend on how densely the scan is sampled; pairs
    # beyond the last trimming distance count as misses.
    plane = jnp.abs(jnp.sum(delta * samples.normals[near], axis=1))
    reach = jnp.linalg.norm(delta, axis=1) < trims[-1]
    inlier = reach & (plane < _SCORE_TRIM)
    n_in = inlier.astype(t.dtype)
    return Fit(
        pose=Pose(rotation, jnp.exp(log_s), t),
        identity=ident,
        expression=expr,
        score=jnp.mean(jnp.where(reach, jnp.minimum((plane / _SCORE_TRIM) ** 2, 1.0), 1.0)),
        inliers=jnp.mean(n_in),
        rms=jnp.sqrt(jnp.sum(jnp.where(inlier, plane**2, 0.0)) / jnp.maximum(jnp.sum(n_in), 1.0)),
    )


def _symmetry_axis(points: Array, axes: Array) -> Array:
    """The principal axis across which the points are most mirror-symmetric (a face's or a
    head's left-right axis): the mean distance of the reflected points to the originals."""

    def asymmetry(axis):
        mirrored = points - 2.0 * (points @ axis)[:, None] * axis[None, :]
        near = _nearest(mirrored, points)
        return jnp.mean(jnp.linalg.norm(mirrored - points[near], axis=1))

    return jnp.argmin(jax.vmap(asymmetry, in_axes=1)(axes))


def _hypotheses(frame: _Frame, points: Array, normals: Array) -> Pose:
    """Initial poses from the geometry: the model's right-left axis along the scan's symmetry
    axis (both signs), up and front along the other two principal axes (any sign), the nose tip
    on one of the scan points protruding most along that front, at a few scales."""
    _, axes = jnp.linalg.eigh(points.T @ points)
    side = _symmetry_axis(points, axes)
    others = jnp.stack([axes[:, (side + 1) % 3], axes[:, (side + 2) % 3]])
    rotations = []
    for up in range(2):
        for su in (1.0, -1.0):
            for sf in (1.0, -1.0):
                y, z = su * others[up], sf * others[1 - up]
                rotations.append(jnp.stack([jnp.cross(y, z), y, z], axis=1))
    rotations = jnp.stack(rotations)  # (8, 3, 3): model axes (right, up, front) → scan

    # The nose tip protrudes most above its surroundings: height along the front minus the
    # mean height within a third of the face's radius, per scale hypothesis; and it faces the
    # front (unlike the rims of shoulders and ears).
    d2 = jnp.sum((points[:, None] - points[None]) ** 2, axis=-1)
    scales = jnp.asarray(_SCALES, points.dtype)

    def noses(rotation, scale):
        height = points @ rotation[:, 2]
        around = (d2 < (scale / 3.0) ** 2).astype(points.dtype)
        bump = height - (around @ height) / jnp.sum(around, axis=1)
        bump = jnp.where(jnp.abs(normals @ rotation[:, 2]) > 0.7, bump, -jnp.inf)
        picked = []
        for _ in range(_NOSE_CANDIDATES):
            apart = jnp.ones(len(points), bool)
            for p in picked:
                apart &= jnp.sum((points - p) ** 2, axis=1) > (0.5 * scale) ** 2
            picked.append(points[jnp.argmax(jnp.where(apart, bump, -jnp.inf))])
        return jnp.stack(picked)

    n_rot, n_nose, n_scale = len(rotations), _NOSE_CANDIDATES, len(_SCALES)
    per_scale = jax.vmap(noses, in_axes=(None, 0), out_axes=1)
    nose_points = jax.vmap(per_scale, in_axes=(0, None))(rotations, scales)  # (r, c, s, 3)
    rot = jnp.broadcast_to(rotations[:, None, None], (n_rot, n_nose, n_scale, 3, 3))
    s = jnp.broadcast_to(scales[None, None, :], rot.shape[:3])
    nose_model = jnp.einsum("hij,j->hi", rotations, frame.nose)
    t = nose_points - s[..., None] * nose_model[:, None, None, :]
    return Pose(rot.reshape(-1, 3, 3), s.reshape(-1), t.reshape(-1, 3))


def _near_face(key: Array, samples: Samples, pose: Pose, n: int) -> Samples:
    """``n`` of the samples, at random, among those within two face radii of the placed face."""
    dist = jnp.linalg.norm(samples.points - pose.translation, axis=1) / pose.scale
    rank = jnp.where(dist < 2.0, jax.random.uniform(key, dist.shape), -1.0)
    _, pick = jax.lax.top_k(rank, n)
    return Samples(samples.points[pick], samples.normals[pick], samples.center, samples.scale)


def fit_samples(
    key: Array,
    samples: Samples,
    model: FaceModel,
    *,
    n_model: int = 1000,
    n_refine: int = 4,
    expression: bool = True,
) -> Fit:
    """Fit the face model to normalised scan samples (pure and jittable; ``vmap`` it over scans
    resampled to the same size).

    Every pose hypothesis is fitted rigidly (similarity) on ``_COARSE_SCAN`` of the samples and
    ``_COARSE_MODEL`` face vertices; the ``n_refine`` best by score are refined with identity
    (and expression) coefficients on ``n_model`` face vertices and ``_FINE_SCAN`` samples near
    the face; the best refinement is returned.

    Args:
        key: a JAX PRNG key (which samples near the face the refinement uses).
        samples: from :func:`sample_surface`.
        model: the face model (:func:`face_model`).
        n_model: face vertices used in the refinement (static).
        n_refine: hypotheses refined (static).
        expression: fit the expression coefficients too (static).
    """
    frame, _, _ = _frame(model, n_model)
    coarse_frame, _, _ = _frame(model, _COARSE_MODEL)
    k, e = frame.identity.shape[0], frame.expression.shape[0]
    dtype = samples.points.dtype
    zeros_k, zeros_e = jnp.zeros(k, dtype), jnp.zeros(e, dtype)
    coarse = Samples(
        samples.points[:_COARSE_SCAN], samples.normals[:_COARSE_SCAN], samples.center, samples.scale
    )
    poses = _hypotheses(frame, coarse.points, coarse.normals)

    def rigid(pose):
        return _icp(coarse_frame, coarse, pose, zeros_k, zeros_e, _RIGID_TRIM, shape=False)

    rigid_fits = jax.vmap(rigid)(poses)
    best = jnp.argsort(rigid_fits.score)[:n_refine]
    chosen = jax.tree.map(lambda x: x[best], rigid_fits.pose)
    if not expression:
        frame = eqx.tree_at(lambda f: f.expression, frame, frame.expression * 0.0)

    def refine(key, pose):
        near = _near_face(key, samples, pose, _FINE_SCAN)
        return _icp(frame, near, pose, zeros_k, zeros_e, _SHAPE_TRIM, shape=True)

    refined = jax.vmap(refine)(jax.random.split(key, n_refine), chosen)
    win = jnp.argmin(refined.score)
    return jax.tree.map(lambda x: x[win], refined)


class Landmarks(eqx.Module):
    """Landmarks found by fitting the face model to a scan.

    Attributes:
        points: ``(21, 3)`` the markers on the scan, template order (scan units and frame).
        model_points: ``(21, 3)`` the fitted model's landmark vertices, before projection.
        vertices: ``(V, 3)`` the fitted model in the scan's frame; faces: its ``(F, 3)``
            triangles.
        rotation: ``(3, 3)``, scale: ``()``, translation: ``(3,)``: the model (cm) → scan
            similarity, ``x ↦ scale · rotation @ x + translation``.
        identity: ``(k,)`` and expression: ``(e,)`` the fitted coefficients.
        score: the truncated residual (0 perfect, 1 nothing fits); inliers: fraction of the face
            vertices within a twentieth of the face's RMS radius of the scan; rms: their RMS
            distance in scan units.
        names: the landmark names (static).
    """

    points: Float[Array, "21 3"]
    model_points: Float[Array, "21 3"]
    vertices: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    rotation: Float[Array, "3 3"]
    scale: Float[Array, ""]
    translation: Float[Array, " 3"]
    identity: Float[Array, " k"]
    expression: Float[Array, " e"]
    score: Float[Array, ""]
    inliers: Float[Array, ""]
    rms: Float[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True, default=LANDMARK_NAMES)

    def as_dict(self) -> dict[str, list[float]]:
        """name → 3-D point, as :func:`jface.io.write_landmarks` and :func:`remesh` take them."""
        pts = np.asarray(self.points, dtype=np.float64)
        return {n: [float(c) for c in p] for n, p in zip(self.names, pts, strict=True)}


class NoFaceError(ValueError):
    """The face model fits nowhere on the mesh."""


_sample = jax.jit(sample_surface, static_argnums=3)
_fit = eqx.filter_jit(fit_samples)


def find_landmarks(
    vertices: Any,
    faces: Any,
    *,
    key: Any = None,
    n_points: int = 32768,
    n_model: int = 1000,
    expression: bool = True,
    max_score: float = 0.6,
    model: FaceModel | None = None,
) -> Landmarks:
    """The 21 template landmarks of a face scan, with no hand-placed points.

    The scan may be in any orientation, position and unit, a full head (neck, ears, hair,
    shoulders) or a face with open borders and holes. See the module docstring for the method.

    Args:
        vertices: ``(V, 3)`` scan vertices; faces: ``(F, 3)`` integer triangles.
        key: a JAX PRNG key for the surface samples (default ``jax.random.key(0)``).
        n_points: surface samples.
        n_model: face-model vertices fitted.
        expression: fit the expression (smile) coefficient too.
        max_score: the largest fit score (0 perfect, 1 nothing fits) still taken for a face.
        model: the face model (default: :func:`face_model`, the ICT-FaceKit face area).

    Returns:
        :class:`Landmarks`: the markers on the scan, the fitted model, pose, coefficients and
        residuals.

    Raises:
        ValueError: malformed, empty, tiny or non-finite meshes.
        NoFaceError: (a ValueError) the best fit's score is above ``max_score``.
    """
    verts, tri = _scan_arrays(vertices, faces, manifold=False)
    if len(tri) < 100:
        raise ValueError(f"the mesh has {len(tri)} triangles: too few for a face (100 at least)")
    cross = np.cross(verts[tri[:, 1]] - verts[tri[:, 0]], verts[tri[:, 2]] - verts[tri[:, 0]])
    if not np.linalg.norm(cross, axis=1).sum() > 0:
        raise ValueError("the mesh has zero area: every triangle is degenerate")
    n_points = _checks.integer(n_points, "n_points", low=1024, high=1 << 20)
    n_model = _checks.integer(n_model, "n_model", low=256, high=9409)
    max_score = _checks.real(max_score, "max_score", low=0.0, high=1.0)
    key = jax.random.key(0) if key is None else _checks.key(key)
    model = face_model() if model is None else model

    center = verts.mean(axis=0)
    draw, fit_key = jax.random.split(key)
    samples = _sample(draw, verts - center, tri.astype(np.int32), n_points)
    fit = _fit(fit_key, samples, model, n_model=n_model, expression=bool(expression))
    score = float(fit.score)
    if not score <= max_score:
        raise NoFaceError(
            f"no face found: the best fit of the face model has score {score:.3f} (0 perfect, "
            f"1 nothing fits; a face scores below {max_score}), {float(fit.inliers):.0%} of the "
            "model within reach of the mesh"
        )
    _, m_center, m_radius = _frame(model, n_model)
    # model (cm) → model frame → normalised scan frame → scan frame
    s_scan = float(samples.scale)
    rotation = np.asarray(fit.pose.rotation, np.float64)
    scale = float(fit.pose.scale) * s_scan / float(m_radius)
    translation = (
        s_scan
        * (
            np.asarray(fit.pose.translation)
            - float(fit.pose.scale) / float(m_radius) * rotation @ np.asarray(m_center)
        )
        + np.asarray(samples.center)
        + center
    )
    shape = np.asarray(model.shape(fit.identity, fit.expression), np.float64)
    placed = scale * shape @ rotation.T + translation
    model_points = placed[np.asarray(model.landmark_ids)]
    on_scan, _, _ = closest_points(ScanIndex(verts, tri, method="kdtree"), model_points)
    return Landmarks(
        points=jnp.asarray(on_scan),
        model_points=jnp.asarray(model_points),
        vertices=jnp.asarray(placed),
        faces=model.faces,
        rotation=jnp.asarray(rotation),
        scale=jnp.asarray(scale),
        translation=jnp.asarray(translation),
        identity=fit.identity,
        expression=fit.expression,
        score=fit.score,
        inliers=fit.inliers,
        rms=fit.rms * float(fit.pose.scale) * s_scan,
    )
