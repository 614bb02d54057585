"""Subdivision as precomputed sparse operators.

Every level of the remeshing hierarchy has the same connectivity for every face, so each
subdivision step is a fixed sparse matrix ``S`` (new vertices × old vertices), computed once per
template from the connectivity alone and applied to anything that lives on the vertices:
positions, rectangle (uv) coordinates, displacements. New vertices are numbered after the old
ones: ``[old vertices..., one per edge in sorted (min, max) order]``; each triangle ``(a, b, c)``
becomes ``(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)``, which keeps orientation.

Rules (Loop 1987; boundary and corner rules of Hoppe et al. 1994):

- linear: old vertices stay, edge vertices are midpoints.
- Loop, interior: an old vertex of valence ``n`` becomes ``(1 - nβ) v + β Σ neighbours`` with
  Loop's ``β = (5/8 - (3/8 + cos(2π/n)/4)²) / n``; an edge vertex is ``3/8 (a + b) + 1/8 (c + d)``
  with ``c, d`` opposite the edge.
- Loop, boundary (crease): an edge vertex on the boundary is the midpoint; an old boundary vertex
  becomes ``3/4 v + 1/8 (b₀ + b₁)`` with its two boundary neighbours, so the boundary curve is
  a cubic B-spline of the boundary alone and a straight edge of the rectangle stays straight.
- Loop, corner: corner vertices (and non-manifold boundary vertices) do not move.
"""

from __future__ import annotations

import functools
import math
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

Scheme = Literal["linear", "loop"]


class SubdivisionOperator(eqx.Module):
    """A sparse ``(n_out, n_in)`` matrix in coordinate form (rows sorted), applied with a
    segment sum so it jits and vmaps.

    Attributes:
        rows, cols: ``(nnz,)`` int32 indices.
        weights: ``(nnz,)`` float32 (cast to the input's dtype when applied).
        n_in, n_out: static sizes.
    """

    rows: Int[Array, " nnz"]
    cols: Int[Array, " nnz"]
    weights: Float[Array, " nnz"]
    n_in: int = eqx.field(static=True)
    n_out: int = eqx.field(static=True)

    def __call__(self, x: Float[Array, "n_in ..."]) -> Float[Array, "n_out ..."]:
        """Apply the operator to per-vertex values ``(n_in, ...)``."""
        if x.shape[0] != self.n_in:
            raise ValueError(
                f"values must have {self.n_in} rows (one per vertex), got shape {x.shape}"
            )
        return _apply(self, x)

    def dense(self) -> np.ndarray:
        """The operator as a dense float64 numpy matrix (small levels; for tests)."""
        out = np.zeros((self.n_out, self.n_in))
        np.add.at(out, (np.asarray(self.rows), np.asarray(self.cols)), np.asarray(self.weights))
        return out


@jax.jit
def _apply(op: SubdivisionOperator, x: Array) -> Array:
    w = op.weights.astype(x.dtype).reshape((-1,) + (1,) * (x.ndim - 1))
    return jax.ops.segment_sum(
        w * x[op.cols], op.rows, num_segments=op.n_out, indices_are_sorted=True
    )


class Topology:
    """Edges of a triangle mesh, as numpy arrays (host-side precomputation).

    Attributes:
        edges: ``(E, 2)`` unique edges, sorted pairs, in lexicographic order.
        face_edges: ``(F, 3)`` edge index of each face's edges ``(a,b), (b,c), (c,a)``.
        edge_faces: ``(E,)`` number of faces on each edge.
        opposite: ``(3F,)`` the vertex opposite each face-edge occurrence.
        occurrence_edge: ``(3F,)`` the edge of each occurrence (order: edge k of all faces).
    """

    def __init__(self, faces: np.ndarray, n_vertices: int) -> None:
        faces = np.asarray(faces, dtype=np.int64)
        n_faces = len(faces)
        pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        lo, hi = pairs.min(axis=1), pairs.max(axis=1)
        if np.any(lo == hi):
            raise ValueError("faces must not repeat a vertex (degenerate triangles)")
        keys = lo * n_vertices + hi
        uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        self.n_vertices = n_vertices
        self.edges = np.stack([uniq // n_vertices, uniq % n_vertices], axis=1)
        self.face_edges = inverse.reshape(3, n_faces).T
        self.edge_faces = counts
        self.occurrence_edge = inverse
        self.opposite = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
        self.faces = faces

    @property
    def n_nonmanifold(self) -> int:
        return int(np.sum(self.edge_faces > 2))

    def boundary_edges(self) -> np.ndarray:
        return self.edges[self.edge_faces == 1]


def check_manifold(faces: np.ndarray, n_vertices: int, name: str = "mesh") -> Topology:
    """Edge topology of ``faces``; raise ValueError if an edge has more than two faces."""
    topo = Topology(faces, n_vertices)
    if topo.n_nonmanifold:
        raise ValueError(
            f"{name} is non-manifold: {topo.n_nonmanifold} edge(s) are shared by more than two "
            "triangles; repair it (e.g. split those edges) before remeshing"
        )
    return topo


def subdivide_topology(
    faces: np.ndarray,
    n_vertices: int,
    scheme: Scheme,
    corners: tuple[int, ...] = (),
) -> tuple[np.ndarray, SubdivisionOperator]:
    """One subdivision step of a manifold triangle mesh (with or without boundary).

    Args:
        faces: ``(F, 3)`` triangles.
        n_vertices: number of vertices.
        scheme: "linear" (midpoint) or "loop".
        corners: vertex indices kept fixed by Loop (they keep their index at every level).

    Returns:
        ``(4F, 3)`` int32 faces of the finer mesh and the operator that maps per-vertex values
        of this mesh to the finer one.

    Raises:
        ValueError: unknown scheme, degenerate or non-manifold faces.
    """
    if scheme not in ("linear", "loop"):
        raise ValueError(f"scheme must be 'linear' or 'loop', got {scheme!r}")
    topo = check_manifold(faces, n_vertices)
    n_old, n_edges = n_vertices, len(topo.edges)
    a, b = topo.edges[:, 0], topo.edges[:, 1]
    odd = n_old + np.arange(n_edges)
    if scheme == "linear":
        rows = [np.arange(n_old), odd, odd]
        cols = [np.arange(n_old), a, b]
        vals = [np.ones(n_old), np.full(n_edges, 0.5), np.full(n_edges, 0.5)]
    else:
        rows, cols, vals = _loop_weights(topo, corners)
    rows, cols, vals = map(np.concatenate, (rows, cols, vals))
    op = _operator(rows, cols, vals, n_old, n_old + n_edges)
    fe = topo.face_edges + n_old
    f = topo.faces
    new_faces = np.concatenate(
        [
            np.stack([f[:, 0], fe[:, 0], fe[:, 2]], 1),
            np.stack([fe[:, 0], f[:, 1], fe[:, 1]], 1),
            np.stack([fe[:, 2], fe[:, 1], f[:, 2]], 1),
            np.stack([fe[:, 0], fe[:, 1], fe[:, 2]], 1),
        ]
    )
    return new_faces.astype(np.int32), op


def _loop_weights(topo: Topology, corners: tuple[int, ...]):
    n_old, n_edges = topo.n_vertices, len(topo.edges)
    a, b = topo.edges[:, 0], topo.edges[:, 1]
    odd = n_old + np.arange(n_edges)
    on_boundary = topo.edge_faces == 1
    # Odd (edge) vertices.
    end_w = np.where(on_boundary, 0.5, 3.0 / 8.0)
    occ_interior = ~on_boundary[topo.occurrence_edge]
    rows = [odd, odd, n_old + topo.occurrence_edge[occ_interior]]
    cols = [a, b, topo.opposite[occ_interior]]
    vals = [end_w, end_w, np.full(int(occ_interior.sum()), 1.0 / 8.0)]
    # Even (old) vertices.
    valence = np.bincount(topo.edges.ravel(), minlength=n_old)
    n_boundary = np.bincount(topo.boundary_edges().ravel(), minlength=n_old)
    fixed = np.zeros(n_old, bool)
    fixed[list(corners)] = True
    fixed |= n_boundary > 2  # non-manifold vertex where two boundary loops touch
    fixed |= valence == 0
    crease = (n_boundary > 0) & ~fixed
    interior = (n_boundary == 0) & ~fixed
    n = np.maximum(valence, 1).astype(np.float64)
    beta = (5.0 / 8.0 - (3.0 / 8.0 + np.cos(2.0 * math.pi / n) / 4.0) ** 2) / n
    self_w = np.where(interior, 1.0 - n * beta, np.where(crease, 0.75, 1.0))
    rows.append(np.arange(n_old))
    cols.append(np.arange(n_old))
    vals.append(self_w)
    for src, dst in ((a, b), (b, a)):
        use_interior = interior[src]
        rows += [src[use_interior]]
        cols += [dst[use_interior]]
        vals += [beta[src[use_interior]]]
        use_crease = crease[src] & on_boundary
        rows += [src[use_crease]]
        cols += [dst[use_crease]]
        vals += [np.full(int(use_crease.sum()), 1.0 / 8.0)]
    return rows, cols, vals


def _operator(rows, cols, vals, n_in: int, n_out: int) -> SubdivisionOperator:
    keys = rows.astype(np.int64) * n_in + cols
    uniq, inverse = np.unique(keys, return_inverse=True)
    summed = np.zeros(len(uniq))
    np.add.at(summed, inverse, vals)
    keep = summed != 0.0
    uniq, summed = uniq[keep], summed[keep]
    return SubdivisionOperator(
        rows=jnp.asarray(uniq // n_in, dtype=jnp.int32),
        cols=jnp.asarray(uniq % n_in, dtype=jnp.int32),
        weights=jnp.asarray(summed, dtype=jnp.float32),
        n_in=n_in,
        n_out=n_out,
    )


def subdivide(
    vertices: Float[Array, "v c"] | np.ndarray,
    faces: np.ndarray,
    scheme: Scheme = "loop",
    *,
    levels: int = 1,
    corners: tuple[int, ...] = (),
) -> tuple[Float[Array, "w c"], Int[np.ndarray, "g 3"]]:
    """Subdivide a mesh ``levels`` times (per-vertex values of any width: positions, uv, ...).

    Convenience for one-off meshes; the remeshing hierarchy caches its operators instead.
    """
    faces = np.asarray(faces)
    values = jnp.asarray(vertices)
    for _ in range(levels):
        faces, op = subdivide_topology(faces, values.shape[0], scheme, corners)
        values = op(values)
    return values, faces


class Level(eqx.Module):
    """One level of the template hierarchy: its triangles, rectangle coordinates, and the
    operator from the previous level (None at level 0, the marker mesh)."""

    faces: np.ndarray
    uv: Float[Array, "v 2"]
    operator: SubdivisionOperator | None
    scheme: str = eqx.field(static=True)

    @property
    def n_vertices(self) -> int:
        return self.uv.shape[0]


class Hierarchy(eqx.Module):
    """The subdivision levels of a marker template (same for every face).

    Level 0 is the marker mesh; levels ``1..n_projected`` are re-projected onto the scan during
    remeshing; the last level is the base mesh.
    """

    levels: tuple[Level, ...]
    corners: tuple[int, ...] = eqx.field(static=True)
    n_projected: int = eqx.field(static=True)

    @property
    def base(self) -> Level:
        return self.levels[-1]

    @property
    def control(self) -> Level:
        return self.levels[self.n_projected]


@functools.lru_cache(maxsize=8)
def _hierarchy(key: tuple, schedule: tuple[str, ...], n_projected: int) -> Hierarchy:
    _, corners, uv_bytes, faces_bytes = key
    uv = jnp.asarray(np.frombuffer(uv_bytes, dtype=np.float64).reshape(-1, 2), dtype=jnp.float32)
    faces = np.frombuffer(faces_bytes, dtype=np.int32).reshape(-1, 3).copy()
    levels = [Level(faces=faces, uv=uv, operator=None, scheme="marker")]
    for scheme in schedule:
        faces, op = subdivide_topology(faces, uv.shape[0], scheme, corners)  # type: ignore[arg-type]
        uv = op(uv)
        levels.append(Level(faces=faces, uv=uv, operator=op, scheme=scheme))
    return Hierarchy(levels=tuple(levels), corners=corners, n_projected=n_projected)


def template_hierarchy(
    template=None, n_linear: int = 2, n_loop: int = 2, n_smooth: int = 3
) -> Hierarchy:
    """The subdivision levels of the remeshing of Golovinskiy et al. 2006, §2.2.

    ``n_linear`` linear then ``n_loop`` Loop subdivisions (each re-projected onto the scan during
    remeshing), then ``n_smooth`` Loop subdivisions without re-projection → the base mesh.
    Computed once per (template, schedule) and cached.

    Args:
        template: a :class:`~jface.mesh.MarkerTemplate` (default: the built-in one).
        n_linear, n_loop, n_smooth: the schedule (paper: 2, 2, 3 → 524,288 base triangles).
    """
    from jface import _checks
    from jface.mesh._template import marker_template

    template = template or marker_template()
    n_linear = _checks.integer(n_linear, "n_linear", low=0, high=8)
    n_loop = _checks.integer(n_loop, "n_loop", low=0, high=8)
    n_smooth = _checks.integer(n_smooth, "n_smooth", low=0, high=8)
    if n_linear + n_loop + n_smooth > 9:
        raise ValueError(
            "n_linear + n_loop + n_smooth must be at most 9 (the base mesh has "
            f"32·4^levels triangles), got {n_linear + n_loop + n_smooth}"
        )
    schedule = ("linear",) * n_linear + ("loop",) * (n_loop + n_smooth)
    return _hierarchy(template.key(), schedule, n_linear + n_loop)
