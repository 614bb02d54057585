"""Projection along normals onto a scan: the nearest intersection of the line ``o + t·d`` with
the scan's triangles, within ``|t| <= max_distance`` (host-side, numpy).

Only the first surface met in each direction counts, and only if it faces the way ``d`` does
(``facing=True``, the default for remeshing): from a point inside the scan the right surface is
where the ray leaves it, from a point outside where the ray enters it, and in both cases the
scan's outward normal agrees with ``d``. A sheet facing the other way (the inside of a lip, the
neck seen from under the chin, the back of the head from inside it) is rejected, and so is
anything behind it. The nearer of the two directions' accepted hits wins.

Two casters give the same answer:

- "embree": trimesh's Embree intersector (``embreex``), the first hit forward and backward per
  vertex; the few rays it misses (grazing the scan's border) are settled by the exact caster
  below. Fast; used when installed.
- "kdtree": bounded segments over a k-d tree of triangle centroids. A segment of half-length
  ``r`` around ``o`` can only meet triangles whose centroid lies within ``r + R`` of ``o``
  (``R`` = the largest centroid-to-corner distance), so candidates come from a radius query and
  are tested exactly (Möller–Trumbore) in vectorised chunks. ``r`` starts at one scan edge
  length and grows ×4 only for the rays still unsettled, up to ``max_distance``. Exact, and
  seconds rather than hours on half-million-triangle scans.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import numpy as np

Method = Literal["auto", "embree", "kdtree"]


def has_embree() -> bool:
    """True when trimesh can use Embree (the ``embreex`` package)."""
    try:
        from trimesh.ray import has_embree as available
    except ImportError:  # pragma: no cover - old trimesh
        return False
    return bool(available)


class ScanIndex:
    """A scan prepared for ray casting (an acceleration structure, built once)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, method: Method = "auto") -> None:
        if method not in ("auto", "embree", "kdtree"):
            raise ValueError(f"method must be 'auto', 'embree' or 'kdtree', got {method!r}")
        if method == "embree" and not has_embree():
            raise ValueError("method='embree' needs the embreex package (pip install embreex)")
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.method = "embree" if method == "auto" and has_embree() else method
        if self.method == "auto":
            self.method = "kdtree"
        tri = self.vertices[self.faces]
        self.triangles = tri
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1)
        self.edge_length = float(edges.mean())

        self.centroids = tri.mean(axis=1)
        self.v0 = np.ascontiguousarray(tri[:, 0])
        self.e1 = np.ascontiguousarray(tri[:, 1] - tri[:, 0])
        self.e2 = np.ascontiguousarray(tri[:, 2] - tri[:, 0])
        self._radii = np.linalg.norm(tri - self.centroids[:, None], axis=-1).max(axis=1)
        self.radius = float(self._radii.max())
        self._embree = None
        if self.method == "embree":
            import trimesh
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
            self._embree = RayMeshIntersector(mesh)

    @functools.cached_property
    def tree(self):
        """A k-d tree of the triangle centroids (built when first needed: Embree rarely does)."""
        from scipy.spatial import cKDTree

        return cKDTree(self.centroids)

    @functools.cached_property
    def groups(self) -> list[tuple[np.ndarray, object, float]]:
        """Triangles grouped by size (factors of 2), one k-d tree each: a query around a ray
        only pays for the largest triangle of each group, not of the whole scan."""
        from scipy.spatial import cKDTree

        radii = self._radii
        size_class = np.floor(np.log2(np.maximum(radii, 1e-300) / max(radii.min(), 1e-300)))
        size_class = np.minimum(size_class.astype(np.int64), 7)
        groups = []
        pending: list[np.ndarray] = []
        classes = np.unique(size_class)
        for i, c in enumerate(classes):  # merge small groups into the next larger size
            pending.append(np.flatnonzero(size_class == c))
            if sum(map(len, pending)) >= 0.05 * len(radii) or i == len(classes) - 1:
                ids = np.concatenate(pending)
                groups.append((ids, cKDTree(self.centroids[ids]), float(radii[ids].max())))
                pending = []
        return groups

    def subset(self, keep: np.ndarray) -> ScanIndex:
        """The same scan restricted to the triangles of the mask ``keep``, normals oriented as
        here."""
        part = ScanIndex(self.vertices, self.faces[keep], self.method)
        part.normals = self.normals[keep]
        return part


def exterior(
    index: ScanIndex, candidates: np.ndarray, length: float, n_directions: int = 16
) -> np.ndarray:
    """Which triangles are seen from outside the scan: those from which at least one of
    ``n_directions`` rays, spread over a cone of 85° around the triangle's outward normal, runs
    ``length`` without meeting the scan.

    The walls of closed pockets (an eye socket behind the lids, the inside of the nostrils or of
    the mouth) fail the test: no ray from them gets out. Remeshing projects onto the exterior
    triangles only, so a vertex that falls into such a pocket is carried to the skin in front of
    it, not to the back of the pocket.

    Args:
        index: the scan, normals oriented outward (:class:`ScanIndex`).
        candidates: ``(F,)`` mask of the triangles to test; the others count as exterior.
        length: how far a ray must get; shorter hits occlude it.
        n_directions: rays per triangle.

    Returns:
        ``(F,)`` boolean mask.
    """
    out = np.ones(len(index.faces), bool)
    ids = np.flatnonzero(candidates)
    if not len(ids):
        return out
    # A Fibonacci spiral over the cap, the normal itself first.
    k = np.arange(n_directions)
    cos_theta = 1.0 - k / max(n_directions - 1, 1) * (1.0 - np.cos(np.radians(85.0)))
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    sin_theta = np.sqrt(1.0 - cos_theta**2)
    cap = np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta], axis=1)
    normal = index.normals[ids]
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(normal, helper)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    v = np.cross(normal, u)
    # Start off the surface (farther than the casters' own start offset of 1e-3 edges), so the
    # triangle does not occlude itself.
    origins = index.centroids[ids] + 1e-2 * index.edge_length * normal
    # One direction at a time, for the triangles not yet seen to escape: on skin most escape
    # along their normal, so the cost is about one ray per triangle, not n_directions.
    escaped = np.zeros(len(ids), bool)
    for j in range(n_directions):
        todo = np.flatnonzero(~escaped)
        if not len(todo):
            break
        o = origins[todo]
        d = cap[j, 0] * u[todo] + cap[j, 1] * v[todo] + cap[j, 2] * normal[todo]
        if index.method == "embree":
            forward, _ = _first_embree(index, o, d)
        else:
            reach = np.full(len(todo), float(length))
            forward = _cast_kdtree(index, o, d, reach, facing=False).forward
        escaped[todo] = ~(np.abs(forward) <= length)
    out[ids] = escaped
    return out


class Hits(NamedTuple):
    """Signed distances along the directions (0 where missed), the hit mask, and the scan
    triangle hit (-1 where missed)."""

    distance: np.ndarray
    hit: np.ndarray
    triangle: np.ndarray


class _FirstHits(NamedTuple):
    """The first triangle met in each direction (``t`` of +inf / -inf and -1 where none)."""

    forward: np.ndarray
    forward_triangle: np.ndarray
    backward: np.ndarray
    backward_triangle: np.ndarray


def cast(index: ScanIndex, origins, directions, max_distance, *, facing: bool = True) -> Hits:
    """Nearest intersection along ``±directions`` from ``origins`` within ``max_distance``.

    Args:
        index: the scan (:class:`ScanIndex`).
        origins: ``(n, 3)`` ray origins.
        directions: ``(n, 3)`` unit directions (the sign of the result is along them).
        max_distance: hits farther than this are misses; a number or one per ray ``(n,)``.
        facing: keep only the first surface met in each direction, and only where the scan
            faces the way of ``directions`` (see the module docstring); False takes the nearest
            intersection of the line, whichever sheet it lies on.
    """
    origins = np.asarray(origins, dtype=np.float64)
    directions = np.asarray(directions, dtype=np.float64)
    reach = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), (len(origins),))
    if index.method == "embree":
        first = _cast_embree(index, origins, directions)
        missed = np.flatnonzero(np.isinf(first.forward) & np.isinf(first.backward))
        if len(missed):  # grazing rays (origins on the scan's border): settle them exactly
            again = _cast_kdtree(index, origins[missed], directions[missed], reach[missed], facing)
            for field, value in zip(first, again, strict=True):
                field[missed] = value
    else:
        first = _cast_kdtree(index, origins, directions, reach, facing)
    return _choose(index, first, directions, reach, facing)


def _choose(
    index: ScanIndex, first: _FirstHits, d: np.ndarray, reach: np.ndarray, facing: bool
) -> Hits:
    """The nearer of the two directions' first hits that lie within reach (and face along d)."""
    forward = _accepted(index, first.forward, first.forward_triangle, d, reach, facing)
    backward = _accepted(index, first.backward, first.backward_triangle, d, reach, facing)
    nearer = forward <= backward
    hit = np.isfinite(np.minimum(forward, backward))
    distance = np.where(nearer, first.forward, first.backward)
    triangle = np.where(nearer, first.forward_triangle, first.backward_triangle)
    return Hits(np.where(hit, distance, 0.0), hit, np.where(hit, triangle, -1))


def _accepted(index: ScanIndex, t, triangle, d, reach, facing: bool) -> np.ndarray:
    """``|t|`` of the hits that count (within reach, facing along ``d``), +inf for the others."""
    ok = np.abs(t) <= reach
    if facing:
        ok &= np.einsum("ij,ij->i", index.normals[np.maximum(triangle, 0)], d) > 0.0
    return np.where(ok, np.abs(t), np.inf)


def _cast_embree(index: ScanIndex, o: np.ndarray, d: np.ndarray) -> _FirstHits:
    # Start each ray a little behind its origin, so a surface through the origin itself is hit.
    eps = 1e-3 * index.edge_length
    out = []
    for sign in (1.0, -1.0):
        t, which = _first_embree(index, o - eps * sign * d, sign * d)
        out += [sign * (t - eps), which]
    return _FirstHits(*out)


def _first_embree(index: ScanIndex, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Embree's first triangle along each ray ``o + t·d``, ``t >= 0`` (-1 where none), and
    ``t`` (+inf where none) from the triangle's plane in float64: Embree itself works in
    float32."""
    which = index._embree.intersects_first(o, d)
    t = np.full(len(o), np.inf)
    hit = which >= 0
    f = which[hit]
    normal = index.normals[f]
    t[hit] = np.einsum("ij,ij->i", normal, index.v0[f] - o[hit]) / np.einsum(
        "ij,ij->i", normal, d[hit]
    )
    return t, which


def _cast_kdtree(
    index: ScanIndex, o: np.ndarray, d: np.ndarray, max_distance: np.ndarray, facing: bool
) -> _FirstHits:
    forward, backward = np.full(len(o), np.inf), np.full(len(o), -np.inf)
    forward_tri, backward_tri = np.full(len(o), -1), np.full(len(o), -1)
    pending = np.arange(len(o))
    reach = np.minimum(index.edge_length, max_distance)
    while len(pending):
        found = (forward, forward_tri, backward, backward_tri)
        _first_hits(index, o, d, pending, reach[pending], *found)
        # Settled: a hit that counts (nothing met farther out could be nearer), both directions
        # already blocked, or the reach exhausted.
        p, r = pending, reach[pending]
        counts = np.minimum(
            _accepted(index, forward[p], forward_tri[p], d[p], r, facing),
            _accepted(index, backward[p], backward_tri[p], d[p], r, facing),
        )
        open_ = np.isinf(counts) & (np.isinf(forward[p]) | np.isinf(backward[p]))
        pending = p[open_ & (r < max_distance[p])]
        reach[pending] = np.minimum(4.0 * reach[pending], max_distance[pending])
    return _FirstHits(forward, forward_tri, backward, backward_tri)


def _first_hits(
    index: ScanIndex, o, d, rays, reach, forward, forward_tri, backward, backward_tri
) -> None:
    """Update the first hits per direction of ``rays`` with intersections within ``reach``."""
    bound = np.full(len(o), np.nan)
    bound[rays] = reach
    for ids, tree, radius in index.groups:
        n_faces = len(ids)
        k = min(16, n_faces)
        todo = rays
        while len(todo):
            overfull = []
            step = max(1, (1 << 21) // k)
            for start in range(0, len(todo), step):
                chunk = todo[start : start + step]
                limit = float(bound[chunk].max()) + radius
                dist, cand = tree.query(o[chunk], k=k, distance_upper_bound=limit, workers=-1)
                dist, cand = dist.reshape(len(chunk), k), cand.reshape(len(chunk), k)
                near = dist <= (bound[chunk] + radius)[:, None]
                full = near[:, -1] if k < n_faces else np.zeros(len(chunk), bool)
                overfull.append(chunk[full])  # maybe more candidates: again with a larger k
                local, col = np.nonzero(near & ~full[:, None])
                r, f = chunk[local], ids[cand[local, col]]
                t, ok = _intersect(o[r], d[r], index.v0[f], index.e1[f], index.e2[f])
                ok &= np.abs(t) <= bound[r]
                r, t, f = r[ok], t[ok], f[ok]
                for side, which, closer in (
                    (forward, forward_tri, t >= 0),
                    (backward, backward_tri, t < 0),
                ):
                    rs, ts, fs = r[closer], t[closer], f[closer]
                    order = np.argsort(np.abs(ts))[::-1]  # nearest last, so it wins
                    rs, ts, fs = rs[order], ts[order], fs[order]
                    better = np.abs(ts) < np.abs(side[rs])
                    side[rs[better]] = ts[better]
                    which[rs[better]] = fs[better]
            todo = np.concatenate(overfull)
            k = min(4 * k, n_faces)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _intersect(o, d, v0, e1, e2) -> tuple[np.ndarray, np.ndarray]:
    """Möller–Trumbore for lines (any sign of t): parameter t and whether the line meets the
    triangle ``v0 + a·e1 + b·e2``."""
    p = _cross(d, e2)
    det = _dot(e1, p)
    ok = np.abs(det) > 1e-14 * np.maximum(_dot(e1, e1), 1e-300)
    inv = 1.0 / np.where(ok, det, 1.0)
    s = o - v0
    u = _dot(s, p) * inv
    q = _cross(s, e1)
    v = _dot(d, q) * inv
    t = _dot(e2, q) * inv
    # Triangles grown by 1e-4 of their size: a vertex snapped onto the scan's border and rounded
    # to float32 (1e-7 relative) still meets the triangle it lies on.
    eps = 1e-4
    ok &= (u >= -eps) & (v >= -eps) & (u + v <= 1.0 + eps)
    return t, ok


def closest_points(index: ScanIndex, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points on the scan to a few query points, their distances and the scan
    triangles they lie on (exact)."""
    import trimesh

    points = np.asarray(points, dtype=np.float64)
    out = np.zeros_like(points)
    dist = np.zeros(len(points))
    triangle = np.zeros(len(points), np.int64)
    _, nearest = index.tree.query(points)
    for i, p in enumerate(points):
        bound = np.linalg.norm(index.centroids[nearest[i]] - p) + 2 * index.radius
        cand = np.asarray(index.tree.query_ball_point(p, bound), dtype=np.int64)
        q = trimesh.triangles.closest_point(index.triangles[cand], np.repeat(p[None], len(cand), 0))
        j = np.argmin(np.linalg.norm(q - p, axis=1))
        out[i], dist[i], triangle[i] = q[j], float(np.linalg.norm(q[j] - p)), cand[j]
    return out, dist, triangle
