"""Remeshing a face scan into a base mesh plus a scalar displacement image, and back
(Golovinskiy et al. 2006, §2.2, after Guskov et al. 2000 and Lee et al. 2000).

1. The 21 landmarks form the marker mesh (level 0), snapped onto the scan.
2. ``n_linear`` linear then ``n_loop`` Loop subdivisions, each followed by moving every vertex
   along its normal to the nearest intersection with the scan: levels 1..4 of the hierarchy. The
   signed normal offsets of each level are kept: the marker mesh plus these offsets is the
   hierarchical decomposition of the face (:func:`reconstruct`), and mixing levels of two faces is
   how the paper ages a face.
3. ``n_smooth`` Loop subdivisions without projection: the smooth base mesh.
4. Each base vertex is projected along the base normal onto the scan; the signed distance is the
   displacement, rasterised through the rectangle coordinates into the displacement image.

Real scans have several sheets along a normal (lips, eyelids, nostrils, ears, the neck under the
chin). A projection takes the first surface met in each direction, only if it faces the way the
mesh does, and only within a reach of ``search`` local edge lengths of the mesh being projected
(:func:`jface.mesh.cast`), so every threshold scales with the scan: mm, cm and m scans remesh
alike. Rays that miss (holes, borders, rejected sheets) are counted per level and filled with a
membrane (harmonic) interpolation of the offsets that hit, over the mesh: smooth, with no steps
at the rim of a hole. :attr:`Remeshed.filled` shows where the image was filled.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int
from tqdm.auto import tqdm

from jface import _checks
from jface.mesh._geometry import (
    image_sampler,
    sample_image,
    vertex_edge_length,
    vertex_normals,
)
from jface.mesh._raycast import Method, ScanIndex, cast, closest_points, exterior
from jface.mesh._subdivision import Hierarchy, check_manifold, subdivide, template_hierarchy
from jface.mesh._template import LANDMARK_NAMES, landmark_points


class Mesh(eqx.Module):
    """A triangle mesh with optional per-vertex rectangle (uv) coordinates.

    Attributes:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` int32 triangles, counter-clockwise seen from outside.
        uv: ``(V, 2)`` coordinates in the unit square, or None.
    """

    vertices: Float[Array, "v 3"]
    faces: Int[Array, "f 3"]
    uv: Float[Array, "v 2"] | None = None


class Remeshed(eqx.Module):
    """A scan remeshed onto the marker template.

    Attributes:
        markers: ``(21, 3)`` marker-mesh vertices (the landmarks snapped onto the scan).
        offsets: per projected level, the ``(V_k,)`` signed offsets along the normals of the
            subdivided previous level (the hierarchical decomposition; :func:`reconstruct`).
        control: ``(V_c, 3)`` the last projected level (the control mesh of the base mesh).
        base: the smooth base mesh, with its rectangle coordinates.
        displacement: ``(V_b,)`` signed displacement of each base vertex along its normal.
        image: ``(H, W)`` the displacement image.
        hit_rate: per projected level and the base projection, the fraction of rays that hit.
        missed: ``(V_b,)`` base vertices whose ray missed (their displacement is filled).
        filled: ``(H, W)`` how much of each pixel comes from filled base vertices (0: measured,
            1: filled).
        schedule: ``(n_linear, n_loop, n_smooth)`` (static).
    """

    markers: Float[Array, "n 3"]
    offsets: tuple[Float[Array, " _"], ...]
    control: Float[Array, "c 3"]
    base: Mesh
    displacement: Float[Array, " b"]
    image: Float[Array, "h w"]
    hit_rate: Float[Array, " k"]
    missed: Bool[Array, " b"]
    filled: Float[Array, "h w"]
    schedule: tuple[int, int, int] = eqx.field(static=True)

    def hierarchy(self) -> Hierarchy:
        """The template levels this face was remeshed on."""
        return template_hierarchy(None, *self.schedule)


def _scan_arrays(
    vertices: Any, faces: Any, *, manifold: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """A scan's vertices (float64) and faces (int64), checked; ``manifold`` also refuses edges
    shared by more than two triangles."""
    verts = np.asarray(_checks.float_array(vertices, "scan vertices", ndim=2), dtype=np.float64)
    if verts.shape[1] != 3:
        raise ValueError(f"scan vertices must have shape (V, 3), got {verts.shape}")
    if faces is None or np.size(faces) == 0:
        raise ValueError("the scan has no faces: a triangle mesh is needed, not a point cloud")
    tri = np.asarray(faces)
    if tri.dtype.kind not in "iu":
        raise TypeError(f"scan faces must be integers, got dtype {tri.dtype}")
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"scan faces must have shape (F, 3), got {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(verts):
        raise ValueError(f"scan faces index vertices outside [0, {len(verts)})")
    if manifold:
        check_manifold(tri, len(verts), "the scan")
    return verts, tri.astype(np.int64)


def _fill(values: np.ndarray, hit: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Membrane fill: missed vertices take the harmonic interpolation (graph Laplacian of the
    mesh's edges) of the values that hit, so a filled hole joins its rim without a step."""
    if hit.all():
        return values
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = len(values)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ones = np.ones(2 * len(edges))
    adjacency = sp.coo_matrix(
        (ones, (np.concatenate(edges.T[::-1]), np.concatenate(edges.T))), shape=(n, n)
    ).tocsr()
    adjacency.data[:] = 1.0  # an edge shared by two triangles was summed twice
    laplacian = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency
    miss = np.flatnonzero(~hit)
    system = laplacian[miss][:, miss].tocsc()
    rhs = adjacency[miss][:, np.flatnonzero(hit)] @ values[hit]
    out = values.copy()
    out[miss] = np.atleast_1d(spsolve(system, rhs))
    return out


def _image_shape(image_size: Any) -> tuple[int, int]:
    if isinstance(image_size, (tuple, list)):
        if len(image_size) != 2:
            raise ValueError(f"image_size must be an int or (H, W), got {image_size!r}")
        return tuple(_checks.integer(s, "image_size", low=8, high=16384) for s in image_size)
    size = _checks.integer(image_size, "image_size", low=8, high=16384)
    return size, size


def remesh(
    scan_vertices: ArrayLike,
    scan_faces: ArrayLike,
    landmarks: Any,
    *,
    image_size: int | tuple[int, int] = 1024,
    n_linear: int = 2,
    n_loop: int = 2,
    n_smooth: int = 3,
    method: Method = "auto",
    search: float = 2.0,
    landmark_tolerance: float = 0.02,
    fit: int = 0,
    progress: bool = False,
) -> Remeshed:
    """Remesh a face scan onto the marker template (Golovinskiy et al. 2006, §2.2).

    Host-side (ray casting is not traceable); subdivision, normals and rasterisation run in JAX.

    Args:
        scan_vertices: ``(V, 3)`` scan positions (any unit).
        scan_faces: ``(F, 3)`` scan triangles.
        landmarks: the 21 template landmarks: a mapping name → scan vertex id or 3-D point
            (e.g. from :func:`jface.io.read_landmarks`), or a ``(21, 3)`` array in template order.
        image_size: displacement image size, ``N`` (N×N) or ``(H, W)`` (paper: 1024).
        n_linear, n_loop: projected linear and Loop subdivisions (paper: 2 and 2).
        n_smooth: Loop subdivisions of the control mesh giving the base mesh (paper: 3).
        method: ray caster, "auto" (Embree when installed), "embree" or "kdtree".
        search: projection reach, in local edge lengths of the mesh being projected (the control
            mesh for the base projection); farther intersections count as misses.
        landmark_tolerance: largest allowed landmark distance from the scan, as a fraction of
            the scan's bounding-box diagonal.
        fit: Gauss–Newton iterations of a least-squares fit of the control mesh to the scan
            (Lee et al. 2000) before smoothing; 0 (default) is the paper's method, where the
            control mesh interpolates the scan at its vertices, so the base mesh picks up
            detail aliased at those vertices and the shrinkage of Loop smoothing as a smooth
            offset from the scan's smooth shape; 2–3 iterations reduce it (docs/mesh.md).
        progress: show a progress bar over the levels.

    Returns:
        :class:`Remeshed`.

    Raises:
        ValueError: bad or non-manifold scan, missing/unknown landmark names, landmarks far from
            the surface, or no ray meeting the scan.
    """
    verts, faces = _scan_arrays(scan_vertices, scan_faces)
    shape = _image_shape(image_size)
    search = _checks.real(search, "search", low=0.0, open_low=True)
    tolerance = _checks.real(landmark_tolerance, "landmark_tolerance", low=0.0, open_low=True)
    fit = _checks.integer(fit, "fit", low=0, high=10)
    hier = template_hierarchy(None, n_linear, n_loop, n_smooth)
    points = np.asarray(landmark_points(landmarks, verts), dtype=np.float64)
    # Work in a frame centred on the scan: float32 positions keep their precision for scans
    # placed far from their origin (millimetre scans in a scanner's frame).
    centre = verts.mean(axis=0)
    index = ScanIndex(verts - centre, faces, method)
    markers, dist, triangles = closest_points(index, points - centre)
    diagonal = float(np.linalg.norm(verts.max(0) - verts.min(0)))
    far = np.flatnonzero(dist > tolerance * diagonal)
    if len(far):
        listing = ", ".join(f"{LANDMARK_NAMES[i]} ({dist[i]:.3g})" for i in far)
        raise ValueError(
            f"landmarks far from the scan surface (more than {tolerance:g} × the bounding-box "
            f"diagonal = {tolerance * diagonal:.3g}): {listing}"
        )
    _check_face(markers, hier.levels[0])
    _orient(index, markers, triangles, hier.levels[0].faces)
    index = _skin(index, markers)
    steps = tqdm(total=hier.n_projected + 1 + fit, desc="remesh", disable=not progress)
    position = jnp.asarray(markers, dtype=jnp.float32)
    offsets, rates = [], []
    directions = position
    for k, level in enumerate(hier.levels[1 : hier.n_projected + 1], start=1):
        position, offset, hit, directions = _project(
            index, level.operator(position), level, search, f"level {k}"
        )
        offsets.append(offset)
        rates.append(hit.mean())
        steps.update()
    control = position
    base_faces = jnp.asarray(hier.base.faces)
    # The reach of the base projection: the control mesh's local scale, carried to the base.
    scale = vertex_edge_length(np.asarray(control), hier.control.faces)
    reach = search * np.asarray(_smooth(hier, jnp.asarray(scale[:, None], jnp.float32)))[:, 0]
    if fit and hier.n_projected and len(hier.levels) > hier.n_projected + 1:
        delta = _fit_control(index, hier, control, directions, reach, fit)
        control = control + delta[:, None] * directions
        offsets[-1] = offsets[-1] + delta
        steps.update()
    base = _smooth(hier, control)
    normals = vertex_normals(base, base_faces)
    hits = cast(index, np.asarray(base), np.asarray(normals), reach)
    _check_coverage(hits.hit, "the base mesh")
    displacement = _fill(hits.distance, hits.hit, np.asarray(hier.base.faces))
    rates.append(hits.hit.mean())
    steps.update()
    steps.close()
    displacement = jnp.asarray(displacement, dtype=jnp.float32)
    sampler = image_sampler(np.asarray(hier.base.uv), hier.base.faces, shape)
    shift = jnp.asarray(centre, dtype=jnp.float32)
    return Remeshed(
        markers=jnp.asarray(markers + centre, dtype=jnp.float32),
        offsets=tuple(offsets),
        control=control + shift,
        base=Mesh(base + shift, base_faces, hier.base.uv),
        displacement=displacement,
        image=sampler(displacement),
        hit_rate=jnp.asarray(rates, dtype=jnp.float32),
        missed=jnp.asarray(~hits.hit),
        filled=sampler(jnp.asarray(~hits.hit, dtype=jnp.float32)),
        schedule=(n_linear, n_loop, n_smooth),
    )


def _check_face(markers: np.ndarray, template) -> None:
    """Raise ValueError unless the snapped landmarks are laid out like a face: the marker
    triangles keep the orientation of the template's planar layout (seen along the mean marker
    normal: 94–97% do on real faces, about half on a shuffled or random set), and the nose tip
    stands out of the face along that normal (mirrored landmarks turn it inwards)."""
    faces, uv = np.asarray(template.faces), np.asarray(template.uv, dtype=np.float64)
    normal = np.asarray(vertex_normals(jnp.asarray(markers), jnp.asarray(faces))).sum(axis=0)
    normal = normal / max(np.linalg.norm(normal), 1e-300)
    flat = markers - markers.mean(axis=0)
    flat = flat - np.outer(flat @ normal, normal)
    first = np.linalg.svd(flat)[2][0]
    plane = np.stack([flat @ first, flat @ np.cross(normal, first)], axis=1)

    def signed_areas(p):
        a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
        return (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]

    agree = float(np.mean(np.sign(signed_areas(plane)) == np.sign(signed_areas(uv))))
    if agree < 0.8:
        raise ValueError(
            f"the landmarks do not lie on the scan like a face: {1 - agree:.0%} of the marker "
            "triangles are folded over (a face folds none or one or two); check that each name "
            "marks the right feature"
        )
    names = LANDMARK_NAMES
    around = [
        names.index(k) for k in ("left_eye_inner", "right_eye_inner", "mouth_left", "mouth_right")
    ]
    nose = (markers[names.index("nose_tip")] - markers[around].mean(axis=0)) @ normal
    size = float(np.linalg.norm(np.ptp(markers, axis=0)))
    if nose < 0.03 * size:
        raise ValueError(
            "the nose tip does not stand out of the face the landmarks describe: are left and "
            "right named from the subject's point of view, and is the scan a face?"
        )


def _orient(index: ScanIndex, markers: np.ndarray, triangles: np.ndarray, faces) -> None:
    """Make the scan's triangle normals point out of the face, as the template's do: a scan
    stored inside out (clockwise triangles) is recognised at the landmarks and flipped, so the
    facing test of the projections holds for it too."""
    template = np.asarray(vertex_normals(jnp.asarray(markers), jnp.asarray(faces)))
    agree = np.einsum("ij,ij->i", template, index.normals[triangles])
    if np.median(agree) < 0:
        index.normals = -index.normals


def _check_coverage(hit: np.ndarray, what: str) -> None:
    """Raise ValueError when most normal rays of a level missed the scan (filling would invent
    most of the face)."""
    if hit.mean() < 0.5:
        raise ValueError(
            f"only {hit.mean():.0%} of the normal rays of {what} met the scan: it does not cover "
            "the face the landmarks span (a partial scan, or landmarks off the face?)"
        )


def _skin(index: ScanIndex, markers: np.ndarray) -> ScanIndex:
    """The scan without the walls of closed pockets around the face (see
    :func:`jface.mesh.exterior`): rays tested over the face's radius, from the landmarks'
    centre, within one and a half radii of it."""
    centre = markers.mean(axis=0)
    radius = float(np.linalg.norm(markers - centre, axis=1).max())
    near = np.linalg.norm(index.centroids - centre, axis=1) < 1.5 * radius
    outside = exterior(index, near, radius)
    return index if outside.all() else index.subset(outside)


def _project(index: ScanIndex, position: Array, level, search: float, what: str):
    """Move the vertices of a subdivided level along their normals onto the scan."""
    normals = vertex_normals(position, jnp.asarray(level.faces))
    reach = search * vertex_edge_length(np.asarray(position), level.faces)
    hits = cast(index, np.asarray(position), np.asarray(normals), reach)
    _check_coverage(hits.hit, what)
    offset = jnp.asarray(_fill(hits.distance, hits.hit, np.asarray(level.faces)), jnp.float32)
    return position + offset[:, None] * normals, offset, hits.hit, normals


def _smooth(hier: Hierarchy, control: Array) -> Array:
    base = control
    for level in hier.levels[hier.n_projected + 1 :]:
        base = level.operator(base)
    return base


def _fit_control(
    index: ScanIndex, hier: Hierarchy, control: Array, directions: Array, reach, n: int
) -> Array:
    """Least-squares fit of the control mesh along its projection directions, so the base
    surface approximates the scan instead of interpolating it at the control vertices (the
    fitting step of Lee et al. 2000, §4): Gauss–Newton on ``Σ_b disp_b²`` over base vertices."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import lsqr

    smooth = None
    for level in hier.levels[hier.n_projected + 1 :]:
        op = level.operator
        m = sp.csr_matrix(
            (np.asarray(op.weights, np.float64), (np.asarray(op.rows), np.asarray(op.cols))),
            shape=(op.n_out, op.n_in),
        )
        smooth = m if smooth is None else m @ smooth
    smooth = smooth.tocoo()
    dirs = np.asarray(directions, dtype=np.float64)
    delta = np.zeros(control.shape[0])
    base_faces = jnp.asarray(hier.base.faces)
    for _ in range(n):
        moved = control + jnp.asarray(delta[:, None], dtype=jnp.float32) * directions
        base = _smooth(hier, moved)
        normals = np.asarray(vertex_normals(base, base_faces), dtype=np.float64)
        hits = cast(index, np.asarray(base), normals, reach)
        rows = np.flatnonzero(hits.hit)
        keep = hits.hit[smooth.row]
        r, c = smooth.row[keep], smooth.col[keep]
        data = smooth.data[keep] * np.einsum("ij,ij->i", normals[r], dirs[c])
        a = sp.csr_matrix((data, (r, c)), shape=smooth.shape)[rows]
        step = lsqr(a, hits.distance[rows], damp=1e-3, atol=1e-8, btol=1e-8, iter_lim=500)[0]
        delta = delta + step
    return jnp.asarray(delta, dtype=jnp.float32)


def reconstruct(
    markers: ArrayLike, offsets: tuple[ArrayLike, ...], hierarchy: Hierarchy
) -> Float[Array, "c 3"]:
    """Rebuild the control mesh from the marker mesh and per-level offsets.

    ``P_k = S_k P_{k-1} + o_k · n(S_k P_{k-1})``: the inverse of the projection steps of
    :func:`remesh`, exact for its own output. Offsets of different faces can be mixed level by
    level (same topology for every face): coarse levels from one face, fine ones from another.

    Args:
        markers: ``(21, 3)`` marker-mesh vertices.
        offsets: one ``(V_k,)`` array per projected level of ``hierarchy``.
        hierarchy: from :meth:`Remeshed.hierarchy` or :func:`template_hierarchy`.
    """
    position = _checks.float_array(markers, "markers", ndim=2).astype(jnp.float32)
    if len(offsets) != hierarchy.n_projected:
        raise ValueError(f"offsets must hold {hierarchy.n_projected} levels, got {len(offsets)}")
    for k, (level, offset) in enumerate(
        zip(hierarchy.levels[1 : hierarchy.n_projected + 1], offsets, strict=True)
    ):
        offset = _checks.float_array(offset, f"offsets[{k}]", ndim=1).astype(jnp.float32)
        position = level.operator(position)
        if offset.shape[0] != position.shape[0]:
            raise ValueError(
                f"offsets[{k}] must have {position.shape[0]} values, got {offset.shape[0]}"
            )
        normals = vertex_normals(position, jnp.asarray(level.faces))
        position = position + offset[:, None] * normals
    return position


def displace(
    base: Any,
    image: ArrayLike,
    *,
    extra_subdivisions: int = 0,
    scale: float = 1.0,
) -> Mesh:
    """Apply a displacement image to a base mesh: the detailed face.

    Each vertex moves along the base normal by ``scale ×`` the image sampled (bilinearly) at its
    rectangle coordinates. With ``extra_subdivisions`` the base is first split at its edge
    midpoints, positions, rectangle coordinates and normals alike, so detail finer than the
    base mesh shows: the new vertices lie on the base triangles, where :func:`remesh` measured
    the displacement, and move along interpolated normals.

    Args:
        base: a mesh with ``vertices (V, 3)``, ``faces (F, 3)`` and ``uv (V, 2)``
            (:class:`Mesh`, :class:`jface.io.MeshData`, or :attr:`Remeshed.base`).
        image: ``(H, W)`` displacement image (same units as the mesh).
        extra_subdivisions: midpoint subdivisions before displacing (0–3).
        scale: factor on the displacement (0 gives the base mesh, 2 exaggerates).

    Returns:
        The displaced :class:`Mesh` (with uv).

    Raises:
        ValueError: a base without uv, bad shapes, non-manifold base, bad image.
        TypeError: ``base`` is not a mesh.
    """
    if not all(hasattr(base, name) for name in ("vertices", "faces", "uv")):
        raise TypeError(f"base must be a mesh with vertices, faces and uv, got {type(base)}")
    if base.uv is None:
        raise ValueError("base has no uv (rectangle coordinates); displace needs them")
    vertices = _checks.float_array(base.vertices, "base.vertices", ndim=2).astype(jnp.float32)
    uv = _checks.float_array(base.uv, "base.uv", ndim=2).astype(jnp.float32)
    faces = np.asarray(base.faces)
    if vertices.shape[1] != 3 or uv.shape != (vertices.shape[0], 2):
        raise ValueError(
            f"base.vertices must be (V, 3) and base.uv (V, 2), got {tuple(vertices.shape)} "
            f"and {tuple(uv.shape)}"
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0 or faces.dtype.kind not in "iu":
        raise ValueError(f"base.faces must be integers of shape (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise ValueError(f"base.faces index vertices outside [0, {vertices.shape[0]})")
    image = _checks.float_array(image, "image", ndim=2).astype(jnp.float32)
    extra = _checks.integer(extra_subdivisions, "extra_subdivisions", low=0, high=3)
    scale = _checks.real(scale, "scale")
    check_manifold(faces, vertices.shape[0], "the base mesh")
    normals = vertex_normals(vertices, jnp.asarray(faces, dtype=jnp.int32))
    if extra:
        # Midpoint subdivision of positions, uv and normals: the new vertices lie on the base
        # triangles (where the displacement was measured) with interpolated normals.
        stacked, faces = subdivide(
            jnp.concatenate([vertices, uv, normals], axis=1), faces, "linear", levels=extra
        )
        vertices, uv, normals = stacked[:, :3], stacked[:, 3:5], stacked[:, 5:]
        normals = normals / jnp.linalg.norm(normals, axis=1, keepdims=True)
    faces_j = jnp.asarray(faces, dtype=jnp.int32)
    amount = jnp.asarray(scale, dtype=jnp.float32) * sample_image(image, uv)
    return Mesh(vertices + amount[:, None] * normals, faces_j, uv)
