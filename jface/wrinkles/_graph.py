"""The pore graph (§3.1.1 of Weiss et al. 2023): symmetric k-nearest-neighbour edges between
pores, stored as half-edges per node, with the list of crossing edges per edge.

Layout (all static capacities with masks, so graphs of different pore counts share shapes):

* nodes ``n`` = the pores' capacity; half-edge slots ``D`` per node (``max_degree``);
* edges ``E = n · k`` (the largest possible number of symmetric kNN edges);
* crossing slots ``C`` per edge (``max_crossings``).

Each half-edge ``h`` of node ``v`` stores its target ``t_h``, angle ``θ_h`` (radians in
``[0, 2π)``, from ``v`` to ``t_h``), length ``d_h`` (UV units) and edge index ``w_h``; each edge
stores its two nodes ``(a, b)`` with ``a < b``, the vector ``b − a`` (minimum image on a periodic
domain, so a rasteriser draws the band from ``positions[a]`` to ``positions[a] + delta`` and
wraps), its length and angle, and the edges that cross it (exact proper segment intersection;
edges sharing a pore do not cross).

Built with uniform grids (cell lists) in JAX: kNN queries look at the cells within a reach that is
verified afterwards (an error, not a silently wrong neighbour list, when it is too small); crossing
candidates are the edges whose midpoints lie within the longest edge length.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from jface import _checks
from jface.wrinkles._sampling import Pores

_CHUNK = 4096  # queries per batch in the kNN and crossing kernels (bounds memory; only batches
# below the valid count run, so a small batch saves the padding of sparse graphs)


class GraphSpec(NamedTuple):
    """Static sizes of a pore graph (fix its array shapes; see :func:`graph_spec`).

    Attributes:
        k: neighbours per pore before symmetrisation.
        max_degree: half-edge slots per node ``D``.
        max_crossings: crossing-edge slots per edge ``C``.
        knn_grid: cells per side of the kNN grid.
        knn_cell_capacity: pores per kNN cell.
        knn_reach: cells searched on each side of a pore's cell.
        edge_grid: cells per side of the edge-midpoint grid (cell ≥ half the longest edge).
        edge_cell_capacity: edge midpoints per cell.
    """

    k: int = 6
    max_degree: int = 16
    max_crossings: int = 24
    knn_grid: int = 1
    knn_cell_capacity: int = 1
    knn_reach: int = 1
    edge_grid: int = 1
    edge_cell_capacity: int = 1


class PoreGraph(eqx.Module):
    """Symmetric kNN graph of pores as half-edges per node, with crossing lists per edge.

    Attributes:
        positions: ``(n, 2)`` pore positions (copied from the :class:`Pores`).
        node_mask: ``(n,)`` valid pores (the first ``node_count``).
        node_count: number of valid pores.
        half_target: ``(n, D)`` target node of each half-edge.
        half_edge: ``(n, D)`` edge index ``w_h`` of each half-edge.
        half_angle: ``(n, D)`` angle ``θ_h`` in ``[0, 2π)``.
        half_length: ``(n, D)`` length ``d_h``.
        half_mask: ``(n, D)`` valid half-edge slots.
        edge_nodes: ``(E, 2)`` nodes ``(a, b)``, ``a < b``.
        edge_delta: ``(E, 2)`` vector from ``a`` to ``b`` (minimum image when periodic).
        edge_length: ``(E,)`` length.
        edge_angle: ``(E,)`` angle of ``a → b`` in ``[0, 2π)``.
        edge_mask: ``(E,)`` valid edges (the first ``edge_count``).
        edge_count: number of valid edges ``|E|``.
        crossings: ``(E, C)`` indices of the edges crossing each edge.
        crossing_mask: ``(E, C)`` valid crossing slots.
        periodic: domain wraps around (static).
    """

    positions: Float[Array, "*b n 2"]
    node_mask: Bool[Array, "*b n"]
    node_count: Int[Array, "*b"]
    half_target: Int[Array, "*b n D"]
    half_edge: Int[Array, "*b n D"]
    half_angle: Float[Array, "*b n D"]
    half_length: Float[Array, "*b n D"]
    half_mask: Bool[Array, "*b n D"]
    edge_nodes: Int[Array, "*b E 2"]
    edge_delta: Float[Array, "*b E 2"]
    edge_length: Float[Array, "*b E"]
    edge_angle: Float[Array, "*b E"]
    edge_mask: Bool[Array, "*b E"]
    edge_count: Int[Array, "*b"]
    crossings: Int[Array, "*b E C"]
    crossing_mask: Bool[Array, "*b E C"]
    periodic: bool = eqx.field(static=True, default=False)

    @property
    def degree(self) -> Int[Array, "*b n"]:
        return jnp.sum(self.half_mask, axis=-1).astype(jnp.int32)

    def edge_midpoints(self) -> Float[Array, "*b E 2"]:
        """Midpoints of the edges (wrapped into the unit square when periodic)."""
        a = jnp.take_along_axis(self.positions, self.edge_nodes[..., :1], axis=-2)
        mid = a + 0.5 * self.edge_delta
        return jnp.mod(mid, 1.0) if self.periodic else mid


def _wrap(delta, periodic):
    return delta - jnp.round(delta) if periodic else delta


def _bucket(cell_ids, n_cells, cap):
    """Cell table ``(n_cells + 1, cap)`` of item indices (sentinel = number of items; row
    ``n_cells`` is empty) and an overflow flag. ``cell_ids`` holds ``n_cells`` for invalid items.
    Slots are filled by ``cap`` rounds of scatter-min (no sort: XLA's CPU sort is slow)."""
    table, pending = _scatter_rounds(cell_ids, cell_ids < n_cells, n_cells, cap)
    return table.at[n_cells].set(cell_ids.shape[0]), jnp.any(pending)


def _scatter_rounds(targets, pending, n_rows, cap):
    """Table ``(n_rows + 1, cap)``: row ``r`` lists (ascending) up to ``cap`` items whose target
    is ``r`` (sentinel: the number of items); also returns the items left over."""
    n = targets.shape[0]
    ids = jnp.arange(n, dtype=jnp.int32)

    def one(q, carry):
        table, pending = carry
        row = jnp.where(pending, targets, n_rows)
        winner = jnp.full(n_rows + 1, n, jnp.int32).at[row].min(ids)
        table = lax.dynamic_update_slice_in_dim(table, winner[:, None], q, axis=1)
        return table, pending & (winner[jnp.minimum(targets, n_rows)] != ids)

    table = jnp.full((n_rows + 1, cap), n, jnp.int32)
    return lax.fori_loop(0, cap, one, (table, pending))


def _window(cell_xy, grid, reach, periodic, sentinel=None):
    """Flat ids ``(W,)`` of the cells within ``reach`` of a cell (``sentinel``, default
    ``grid²``, outside the grid)."""
    r = jnp.arange(-reach, reach + 1, dtype=jnp.int32)
    oy, ox = (a.reshape(-1) for a in jnp.meshgrid(r, r, indexing="ij"))
    cx = cell_xy[0] + ox
    cy = cell_xy[1] + oy
    if periodic:
        return jnp.mod(cy, grid) * grid + jnp.mod(cx, grid)
    inside = (cx >= 0) & (cx < grid) & (cy >= 0) & (cy < grid)
    return jnp.where(inside, cy * grid + cx, grid * grid if sentinel is None else sentinel)


def _cells(xy, grid):
    cell = jnp.floor(xy * jnp.asarray(grid, xy.dtype)).astype(jnp.int32)
    return jnp.clip(cell, 0, grid - 1)


def _angle(delta):
    return jnp.mod(jnp.arctan2(delta[..., 1], delta[..., 0]), 2.0 * math.pi).astype(delta.dtype)


def _map_first(f, count, total, chunk):
    """``vmap(f)`` over indices ``0 .. total-1`` in chunks, computing only the chunks below
    ``count`` (a traced number of valid items); the rest of the outputs are zeros."""
    chunk = max(1, min(chunk, total))
    n_chunks = -(-total // chunk)
    shapes = jax.eval_shape(jax.vmap(f), jnp.zeros(chunk, jnp.int32))
    outs = jax.tree.map(lambda sd: jnp.zeros((n_chunks * chunk, *sd.shape[1:]), sd.dtype), shapes)

    def body(c, outs):
        idx = jnp.minimum(c * chunk + jnp.arange(chunk, dtype=jnp.int32), total - 1)
        res = jax.vmap(f)(idx)
        return jax.tree.map(
            lambda o, r: lax.dynamic_update_slice_in_dim(o, r, c * chunk, axis=0), outs, res
        )

    outs = lax.fori_loop(0, (count + chunk - 1) // chunk, body, outs)
    return jax.tree.map(lambda o: o[:total], outs)


@functools.partial(jax.jit, static_argnames=("k", "deg", "grid", "cell_cap", "reach", "periodic"))
def _topology(positions, mask, count, *, k, deg, grid, cell_cap, reach, periodic):
    n = positions.shape[0]
    cell = _cells(positions, grid)
    cid = jnp.where(mask, cell[:, 1] * grid + cell[:, 0], grid * grid)
    table, cell_overflow = _bucket(cid, grid * grid, cell_cap)
    pos_table = jnp.concatenate([positions, jnp.zeros((1, 2), positions.dtype)])[table]

    def query(i):  # one pore
        window = _window(cell[i], grid, reach, periodic)
        cand = table[window].reshape(-1)
        delta = _wrap(pos_table[window].reshape(-1, 2) - positions[i], periodic)
        d2 = jnp.sum(delta * delta, axis=-1)
        d2 = jnp.where((cand == n) | (cand == i), jnp.inf, d2)
        neg, idx = lax.top_k(-d2, k)
        found = jnp.sum(jnp.isfinite(d2)).astype(jnp.int32)
        return jnp.where(jnp.isfinite(neg), cand[idx], n), -neg, found

    nbr, nd2, found = _map_first(query, count, n, _CHUNK)
    limit = (reach / grid) ** 2
    inexact = mask & (nd2[:, -1] > limit) & (found < count - 1)

    # symmetric edge set: entry (i -> j) creates edge {i, j} if i < j or i is not a neighbour of j
    i = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], (n, k))
    valid = mask[:, None] & (nbr < n)
    nbr_safe = jnp.where(valid, nbr, 0)
    back = nbr[nbr_safe] == i[:, :, None]  # (n, k, k): row j's slot holding i
    mirrored = valid & jnp.any(back, axis=-1)
    creates = valid & ((i < nbr) | ~mirrored)
    n_edges = n * k
    eid_flat = jnp.where(creates.reshape(-1), jnp.cumsum(creates.reshape(-1)) - 1, n_edges)
    eid = eid_flat.reshape(n, k).astype(jnp.int32)
    back_slot = jnp.argmax(back, axis=-1)
    eid = jnp.where(creates, eid, eid[nbr_safe, back_slot])
    edge_count = jnp.sum(creates).astype(jnp.int32)
    edge_a = (
        jnp.zeros(n_edges, jnp.int32).at[eid_flat].set(jnp.minimum(i, nbr).reshape(-1), mode="drop")
    )
    edge_b = (
        jnp.zeros(n_edges, jnp.int32).at[eid_flat].set(jnp.maximum(i, nbr).reshape(-1), mode="drop")
    )
    edge_mask = jnp.arange(n_edges, dtype=jnp.int32) < edge_count

    # half-edges: the pore's own k entries, then the entries of pores that list it unmirrored
    extra = (valid & ~mirrored).reshape(-1)
    target = nbr_safe.reshape(-1)
    extra_tab, pending = _scatter_rounds(target, extra, n, max(deg - k, 0))
    degree_overflow = jnp.any(pending)
    src_flat = i.reshape(-1)
    eid_all = eid.reshape(-1)
    extra_tab = extra_tab[:n]  # (n, deg - k) entry ids
    extra_ok = extra_tab < n * k
    extra_safe = jnp.where(extra_ok, extra_tab, 0)
    half_target = jnp.concatenate([nbr_safe, src_flat[extra_safe]], axis=1)
    half_edge = jnp.concatenate([eid, eid_all[extra_safe]], axis=1)
    half_mask = jnp.concatenate([valid, extra_ok], axis=1)
    half_target = jnp.where(half_mask, half_target, 0)
    half_edge = jnp.where(half_mask, half_edge, 0)
    edge_nodes = jnp.stack([edge_a, edge_b], axis=-1)
    topo = dict(
        half_target=half_target,
        half_edge=half_edge,
        half_mask=half_mask,
        edge_nodes=edge_nodes,
        edge_mask=edge_mask,
        edge_count=edge_count,
        **_geometry(positions, half_target, half_mask, edge_nodes, edge_mask, periodic),
    )
    flags = dict(cell=cell_overflow, inexact=jnp.any(inexact), degree=degree_overflow)
    return topo, flags


def _geometry(positions, half_target, half_mask, edge_nodes, edge_mask, periodic) -> dict:
    """The vectors, lengths and angles of the edges and half-edges (zero in unused slots): what
    follows from the positions and the tables."""
    edge_delta = _wrap(positions[edge_nodes[:, 1]] - positions[edge_nodes[:, 0]], periodic)
    edge_delta = jnp.where(edge_mask[:, None], edge_delta, 0.0)
    half_delta = _wrap(positions[half_target] - positions[:, None], periodic)
    half_delta = jnp.where(half_mask[..., None], half_delta, 0.0)
    return dict(
        half_angle=jnp.where(half_mask, _angle(half_delta), 0.0),
        half_length=jnp.sqrt(jnp.sum(half_delta * half_delta, axis=-1)),
        edge_delta=edge_delta,
        edge_length=jnp.sqrt(jnp.sum(edge_delta * edge_delta, axis=-1)),
        edge_angle=jnp.where(edge_mask, _angle(edge_delta), 0.0),
    )


#: The arrays a graph is stored as (:func:`graph_tables`); the rest follows from them.
GRAPH_TABLES = {
    "positions": jnp.float32, "node_count": jnp.int32, "half_edge": jnp.int32,
    "half_mask": jnp.bool_, "edge_nodes": jnp.int32, "edge_count": jnp.int32,
    "crossings": jnp.int32, "crossing_mask": jnp.bool_,
}  # fmt: skip


def graph_tables(g: PoreGraph) -> dict[str, np.ndarray]:
    """The arrays of :data:`GRAPH_TABLES` of ``g`` (a graph or a batch), about half its bytes:
    :func:`graph_from_tables` rebuilds the same graph, bit for bit (as built: float32
    positions)."""
    return {f: np.asarray(getattr(g, f)) for f in GRAPH_TABLES}


@functools.partial(jax.jit, static_argnames="periodic")
def graph_from_tables(tables: dict, periodic: bool) -> PoreGraph:
    """The graph (or batch, leading axis) whose :func:`graph_tables` are ``tables`` (integers of
    any width)."""
    tables = {f: jnp.asarray(tables[f], dtype) for f, dtype in GRAPH_TABLES.items()}
    if tables["positions"].ndim == 3:
        return jax.vmap(lambda t: graph_from_tables(t, periodic))(tables)
    n, edges = tables["positions"].shape[0], tables["edge_nodes"]
    node_mask = jnp.arange(n, dtype=jnp.int32) < tables["node_count"]
    edge_mask = jnp.arange(edges.shape[0], dtype=jnp.int32) < tables["edge_count"]
    half_mask = tables["half_mask"]
    ends = edges[tables["half_edge"]]  # (n, D, 2): the half-edge's target is the other end
    own = jnp.arange(n, dtype=jnp.int32)[:, None]
    other = jnp.where(ends[..., 0] == own, ends[..., 1], ends[..., 0])
    half_target = jnp.where(half_mask, other, 0)
    return PoreGraph(
        **tables,
        node_mask=node_mask,
        half_target=half_target,
        edge_mask=edge_mask,
        **_geometry(tables["positions"], half_target, half_mask, edges, edge_mask, periodic),
        periodic=periodic,
    )


def _crosses(p2, q1, q2):
    """Proper intersection of segments ``0–p2`` and ``q1–q2`` (touching does not count)."""

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    def opposite(x, y):
        return ((x > 0) & (y < 0)) | ((x < 0) & (y > 0))

    e = q2 - q1
    return opposite(cross(p2, q1), cross(p2, q2)) & opposite(cross(e, -q1), cross(e, p2 - q1))


def _midpoint_grid(edge_length, edge_mask, max_grid):
    """Cells per side of the edge-midpoint grid: cells at least half the longest edge, so the
    crossing search reads the 5x5 cells around an edge; at most ``max_grid``."""
    longest = jnp.maximum(jnp.max(jnp.where(edge_mask, edge_length, 0.0)), 1e-6)
    return jnp.clip(jnp.floor(2.0 / longest), 1, max_grid).astype(jnp.int32)


@functools.partial(jax.jit, static_argnames=("cap", "max_grid", "cell_cap", "periodic"))
def _crossing_lists(
    positions, edge_nodes, edge_delta, edge_mask, edge_count, edge_length, *, cap, max_grid,
    cell_cap, periodic,
):  # fmt: skip
    # the grid follows the edges (a traced size in a table of max_grid² cells), so graphs of
    # any density share one compile and read about the same number of candidates per edge
    grid = _midpoint_grid(edge_length, edge_mask, max_grid)
    n_edges = edge_nodes.shape[0]
    pa = positions[edge_nodes[:, 0]]
    mid = pa + 0.5 * edge_delta
    if periodic:
        mid = jnp.mod(mid, 1.0)
    cell = _cells(mid, grid)
    cid = jnp.where(edge_mask, cell[:, 1] * grid + cell[:, 0], max_grid * max_grid)
    table, cell_overflow = _bucket(cid, max_grid * max_grid, cell_cap)
    # per-cell data inline, so a query reads contiguous blocks
    nodes_t = jnp.concatenate([edge_nodes, jnp.full((1, 2), -1, edge_nodes.dtype)])[table]
    geom = jnp.concatenate([pa, edge_delta], axis=1)
    geom_t = jnp.concatenate([geom, jnp.zeros((1, 4), geom.dtype)])[table]

    def query(e):  # one edge
        window = _window(cell[e], grid, 2, periodic, max_grid * max_grid)
        cand = table[window].reshape(-1)
        nodes_f = nodes_t[window].reshape(-1, 2)
        g = geom_t[window].reshape(-1, 4)
        shared = jnp.any(nodes_f[:, :, None] == edge_nodes[e][None, None, :], axis=(-1, -2))
        q1 = _wrap(g[:, :2] - pa[e], periodic)
        q2 = q1 + g[:, 2:]
        hit = _crosses(edge_delta[e], q1, q2) & (cand != n_edges) & ~shared
        slot = jnp.where(hit, jnp.cumsum(hit) - 1, cap)
        lists = jnp.zeros(cap, jnp.int32).at[slot].set(cand, mode="drop")
        return lists, jnp.sum(hit).astype(jnp.int32)

    lists, counts = _map_first(query, edge_count, n_edges, _CHUNK)
    counts = jnp.where(edge_mask, counts, 0)
    cmask = jnp.arange(cap, dtype=jnp.int32) < counts[:, None]
    sparse = periodic & (grid < 5)  # the 5x5 window would wrap onto itself
    return jnp.where(cmask, lists, 0), cmask, cell_overflow, jnp.max(counts), sparse


def graph_spec(
    pores: Pores,
    *,
    k: int = 6,
    max_degree: int | None = None,
    max_crossings: int | None = None,
    radius_range: tuple[float, float] | None = None,
    edge_cell_capacity: int | None = None,
) -> GraphSpec:
    """Static sizes for :func:`build_graph` from concrete pores.

    The kNN grid has cells of ``r_lo/√2`` (one pore per cell for Poisson-disk pores) and reaches
    ``(1 + 0.75 √k) · r_hi``; ``radius_range`` (default: the pores' own radii) lets one spec serve
    several pore sets (e.g. a vmapped batch whose α_d differ: pass the bounds of all of them and
    explicit ``max_degree``, ``max_crossings`` and ``edge_cell_capacity``).

    Raises:
        ValueError: ``k`` out of [1, 32], pores without radii, or no valid pore.
    """
    if not isinstance(pores, Pores):
        raise TypeError(f"pores must be Pores, got {_checks.describe(pores)}")
    k = _checks.integer(k, "k", low=1, high=32)
    if radius_range is None:
        count = int(pores.count)
        if count < 1:
            raise ValueError("pores has no valid pore")
        rad = np.asarray(pores.radius)[:count]
        if not np.all(rad > 0):
            raise ValueError("pores need positive radii (as sample_pores gives) for graph_spec")
        radius_range = (float(rad.min()), float(rad.max()))
    r_lo = _checks.real(radius_range[0], "radius_range[0]", low=0.0, open_low=True)
    r_hi = _checks.real(radius_range[1], "radius_range[1]", low=r_lo)
    grid = max(1, math.ceil(math.sqrt(2.0) / r_lo))
    reach = math.ceil((1.0 + 0.75 * math.sqrt(k)) * r_hi * grid)
    if pores.periodic:
        grid = max(grid, 2 * reach + 1)
    cell_capacity = 1
    if not _checks.is_traced(pores.positions):
        cells = np.clip(np.floor(np.asarray(pores.positions) * grid).astype(np.int64), 0, grid - 1)
        ids = (cells[:, 1] * grid + cells[:, 0])[np.asarray(pores.mask)]
        cell_capacity = int(np.bincount(ids).max()) if ids.size else 1
    longest = reach / grid
    edge_grid = max(1, math.floor(2.0 / longest))
    if pores.periodic and edge_grid < 5:
        raise ValueError("the pores are too sparse for a periodic graph (edges longer than 0.4)")
    if edge_cell_capacity is None:
        # at most k edges per pore and 2/(√3 r_lo²) pores per unit area, with 50% headroom;
        # build_graph raises (never drops) if a cell holds more
        side = 1.0 / edge_grid
        edge_cell_capacity = max(8, math.ceil(1.5 * k * 2.0 / math.sqrt(3.0) * (side / r_lo) ** 2))
    return GraphSpec(
        k=k,
        max_degree=2 * k + 4
        if max_degree is None
        else _checks.integer(max_degree, "max_degree", low=1),
        max_crossings=4 * k
        if max_crossings is None
        else _checks.integer(max_crossings, "max_crossings", low=1),
        knn_grid=grid,
        knn_cell_capacity=cell_capacity,
        knn_reach=reach,
        edge_grid=edge_grid,
        edge_cell_capacity=_checks.integer(edge_cell_capacity, "edge_cell_capacity", low=1),
    )


def _edge_grid(pores: Pores, topo: dict) -> dict[str, int]:
    """Table size and cell capacity of the edge-midpoint grid for concrete edges, both rounded up
    to a multiple of 16 so that similar graphs share a compile of the crossing kernel."""
    grid = int(_midpoint_grid(topo["edge_length"], topo["edge_mask"], 1 << 30))
    if pores.periodic and grid < 5:
        raise ValueError("the pores are too sparse for a periodic graph (edges longer than 0.4)")
    capacity = _occupancy(pores, topo, grid)
    return {"edge_grid": -(-grid // 16) * 16, "edge_cell_capacity": -(-capacity // 16) * 16}


def _occupancy(pores: Pores, topo: dict, grid: int) -> int:
    """Most edge midpoints in one cell of a ``grid`` x ``grid`` grid (concrete edges)."""
    mid = np.asarray(pores.positions)[np.asarray(topo["edge_nodes"][:, 0])]
    mid = mid + 0.5 * np.asarray(topo["edge_delta"])
    mid = np.mod(mid, 1.0) if pores.periodic else mid
    cells = np.clip(np.floor(mid * grid).astype(np.int64), 0, grid - 1)
    ids = (cells[:, 1] * grid + cells[:, 0])[np.asarray(topo["edge_mask"])]
    return int(np.bincount(ids).max()) if ids.size else 1


def build_graph(pores: Pores, spec: GraphSpec | None = None, *, k: int = 6) -> PoreGraph:
    """The pore graph of §3.1.1: symmetric kNN edges, half-edges per node, crossing lists.

    For each pore its ``k`` nearest pores are found and the undirected edges ``{v_i, v_j}``
    collected (so every pore has at least ``k`` neighbours, typically a few more); each edge lists
    the edges that properly cross it. Works under ``jit``/``vmap`` given a ``spec``.

    Args:
        pores: the nodes (e.g. from :func:`sample_pores`), valid ones first.
        spec: static sizes; default :func:`graph_spec` ``(pores, k=k)`` (needs concrete pores).
            With concrete pores the edge-midpoint grid is sized from the edges present; the
            spec's ``edge_grid`` and ``edge_cell_capacity`` serve traced ones.
        k: neighbours per pore when ``spec`` is not given.

    Returns:
        :class:`PoreGraph` with ``n = pores.capacity`` nodes and ``n · k`` edge slots.

    Raises:
        ValueError: a capacity of ``spec`` is exceeded (a node with more than ``max_degree``
            half-edges, an edge with more than ``max_crossings`` crossings, a crowded grid cell)
            or the kNN reach was too small for an exact answer. Under ``jit`` these raise through
            ``equinox.error_if``.
    """
    if not isinstance(pores, Pores):
        raise TypeError(f"pores must be Pores, got {_checks.describe(pores)}")
    auto = spec is None
    if auto and (_checks.is_traced(pores.positions) or _checks.is_traced(pores.count)):
        raise ValueError(
            "build_graph needs an explicit spec=graph_spec(...) under jit/vmap "
            "(the static sizes cannot be read from traced pores)"
        )
    if auto:
        spec = graph_spec(pores, k=k)
    if not isinstance(spec, GraphSpec):
        raise TypeError(f"spec must be a GraphSpec, got {_checks.describe(spec)}")
    graph, flags, max_cross = built(pores, spec, auto)
    messages = graph_errors(spec)
    if not any(_checks.is_traced(f) for f in flags.values()):
        for name, flag in flags.items():
            if bool(flag):
                detail = f" (found {int(max_cross)})" if name == "crossings" else ""
                raise ValueError(messages[name] + detail)
    else:
        positions = graph.positions
        for name, flag in flags.items():
            positions = eqx.error_if(positions, flag, messages[name])
        graph = eqx.tree_at(lambda g: g.positions, graph, positions)
    if auto and not _checks.is_traced(graph.half_mask):
        # default sizes: trim the slots to what this graph uses
        used_deg = max(1, int(jnp.max(jnp.sum(graph.half_mask, axis=-1))))
        used_cross = max(1, int(max_cross))
        order = jnp.argsort(~graph.half_mask, axis=-1, stable=True)[:, :used_deg]
        halves = ("half_target", "half_edge", "half_angle", "half_length", "half_mask")
        graph = eqx.tree_at(
            lambda g: [getattr(g, n) for n in halves] + [g.crossings, g.crossing_mask],
            graph,
            [jnp.take_along_axis(getattr(graph, n), order, axis=-1) for n in halves]
            + [graph.crossings[:, :used_cross], graph.crossing_mask[:, :used_cross]],
        )
    return graph


def graph_errors(spec: GraphSpec) -> dict[str, str]:
    """What each flag of :func:`built` means."""
    return {
        "cell": "a kNN grid cell holds more pores than knn_cell_capacity",
        "inexact": "the kNN reach is too small for an exact k-nearest-neighbour answer "
        "(raise GraphSpec.knn_reach)",
        "degree": f"a pore has more than max_degree={spec.max_degree} half-edges "
        "(raise GraphSpec.max_degree)",
        "edge_cell": "an edge-midpoint grid cell holds more edges than edge_cell_capacity",
        "sparse": "the pores are too sparse for a periodic graph (edges longer than 0.4)",
        "crossings": f"an edge is crossed by more than max_crossings={spec.max_crossings} edges "
        "(raise GraphSpec.max_crossings)",
    }


def built(pores: Pores, spec: GraphSpec, auto: bool = False):
    """:func:`build_graph` of checked arguments, untrimmed, with its error flags
    (:func:`graph_errors`) returned rather than raised (a program that raises through
    ``equinox.error_if`` holds host callbacks, which JAX's persistent compilation cache does
    not keep) and the most crossings of an edge. ``auto``: widen the kNN reach until the answer
    is exact (concrete pores)."""
    while True:
        topo, flags = _topology(
            pores.positions, pores.mask, pores.count, k=spec.k, deg=spec.max_degree,
            grid=spec.knn_grid, cell_cap=spec.knn_cell_capacity, reach=spec.knn_reach,
            periodic=pores.periodic,
        )  # fmt: skip
        if not auto or _checks.is_traced(flags["inexact"]) or not bool(flags["inexact"]):
            break
        if spec.knn_reach >= spec.knn_grid:
            break
        spec = spec._replace(knn_reach=min(2 * spec.knn_reach, spec.knn_grid))  # sparse pores
    if not _checks.is_traced(topo["edge_length"]):
        # size the midpoint grid's table from the edges present (a spec covering a range of α_d
        # holds the densest pores' table and the occupancy at each graph's own grid)
        spec = spec._replace(**_edge_grid(pores, topo))
    crossings, cmask, edge_overflow, max_cross, flags["sparse"] = _crossing_lists(
        pores.positions, topo["edge_nodes"], topo["edge_delta"], topo["edge_mask"],
        topo["edge_count"], topo["edge_length"], cap=spec.max_crossings,
        max_grid=spec.edge_grid, cell_cap=spec.edge_cell_capacity, periodic=pores.periodic,
    )  # fmt: skip
    flags["edge_cell"] = edge_overflow
    flags["crossings"] = max_cross > spec.max_crossings
    graph = PoreGraph(
        positions=pores.positions,
        node_mask=pores.mask,
        node_count=pores.count,
        crossings=crossings,
        crossing_mask=cmask,
        periodic=pores.periodic,
        **topo,
    )
    return graph, flags, max_cross


def covering_spec(
    pores: list[Pores] | tuple[Pores, ...],
    radius_range: tuple[float, float],
    *,
    k: int = 6,
    headroom: float = 1.5,
) -> GraphSpec:
    """One :class:`GraphSpec` for graphs of pores whose radii span ``radius_range``, measured on
    concrete examples (e.g. the densest and the sparsest pore sets of a parameter range).

    :func:`graph_spec` sizes the crossing search from the kNN reach, a bound several times the
    longest edge; here the edge-midpoint grid (each graph's own, from its longest edge) and its
    cell occupancy and the degree are measured on ``pores`` (with ``headroom``), so the crossing
    search reads far fewer candidates. ``max_crossings`` keeps its default bound. Grid and
    occupancy are rounded up to multiples of 16, so pore sets of other seeds mostly get the same
    spec (and share compiled code). A graph that exceeds the spec raises, as always.
    """
    base = graph_spec(pores[0], k=k, radius_range=radius_range)
    grid, degree, occupancy = 1, 1, 1
    for p in pores:
        topo, _ = _topology(
            p.positions, p.mask, p.count, k=base.k, deg=base.max_degree, grid=base.knn_grid,
            cell_cap=base.knn_cell_capacity, reach=base.knn_reach, periodic=p.periodic,
        )  # fmt: skip
        degree = max(degree, int(np.max(np.sum(topo["half_mask"], -1))))
        own = int(_midpoint_grid(topo["edge_length"], topo["edge_mask"], 1 << 30))
        grid, occupancy = max(grid, own), max(occupancy, _occupancy(p, topo, own))
    return base._replace(
        max_degree=min(base.max_degree, -(-(degree + 4) // 4) * 4),
        edge_grid=-(-math.ceil(headroom * grid) // 16) * 16,
        edge_cell_capacity=-(-math.ceil(headroom * occupancy) // 16) * 16,
    )


_HALF_EDGES = ("half_target", "half_edge", "half_angle", "half_length", "half_mask")
_NODE_SLOTS = ("positions", "node_mask", *_HALF_EDGES)
_EDGE_SLOTS = ("edge_nodes", "edge_delta", "edge_length", "edge_angle", "edge_mask", "crossings",
               "crossing_mask")  # fmt: skip


def cut_slots(g: PoreGraph, nodes: int, edges: int) -> PoreGraph:
    """``g`` (one graph or a batch, leading axes) cut to its first ``nodes`` node slots and
    ``edges`` edge slots. The valid ones come first, so a graph holding at most that many loses
    nothing: the same graph at a smaller static size."""
    axis = g.node_mask.ndim - 1
    cut = {f: lax.slice_in_dim(getattr(g, f), 0, nodes, axis=axis) for f in _NODE_SLOTS}
    cut |= {f: lax.slice_in_dim(getattr(g, f), 0, edges, axis=axis) for f in _EDGE_SLOTS}
    return dataclasses.replace(g, **cut)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4))
def _trim(g: PoreGraph, n: int, e: int, d: int, c: int) -> PoreGraph:
    """``g`` cut to ``n`` nodes, ``e`` edges, ``d`` half-edges per node (valid ones first) and
    ``c`` crossings per edge."""
    g = cut_slots(g, n, e)  # first, so that only the nodes kept sort their half-edges
    order = jnp.argsort(~g.half_mask, axis=-1, stable=True)[:, :d]
    half = {f: jnp.take_along_axis(getattr(g, f), order, axis=-1) for f in _HALF_EDGES}
    c = max(c, 1)
    return dataclasses.replace(
        g, crossings=g.crossings[:, :c], crossing_mask=g.crossing_mask[:, :c], **half
    )


def stack_graphs(graphs: list[PoreGraph] | tuple[PoreGraph, ...]) -> PoreGraph:
    """Concrete graphs of equal capacities stacked into a batch (leading axis), every slot axis
    (nodes, edges, half-edges per node, crossings per edge) trimmed to what some graph uses.

    This sizes a batch of precomputed graphs (e.g. one per α_d of a parameter fit) to the data
    rather than to the bounds, which is what a vmapped simulation and drawing pay for.

    Raises:
        TypeError/ValueError: not a non-empty list of single :class:`PoreGraph` of equal shapes.
    """
    if not graphs or not all(isinstance(g, PoreGraph) for g in graphs):
        raise TypeError("stack_graphs needs a non-empty list of PoreGraph")
    shapes = {tuple(x.shape for x in jax.tree.leaves(g)) for g in graphs}
    if len(shapes) != 1 or graphs[0].positions.ndim != 2:
        raise ValueError("stack_graphs needs single graphs of identical shapes (one GraphSpec)")
    return trim_batch(jax.tree.map(lambda *xs: jnp.stack(xs), *graphs))


def trim_batch(batch: PoreGraph) -> PoreGraph:
    """A batch of concrete graphs (leading axis, e.g. built under ``lax.map`` with one spec) with
    every slot axis trimmed to what some graph of the batch uses, rounded up by at most an
    eighth (so batches of other seeds mostly get the same shapes and share compiled code)."""
    used = (
        np.max(batch.node_count), np.max(batch.edge_count), np.max(batch.degree),
        np.max(np.sum(batch.crossing_mask, -1)),
    )  # fmt: skip
    slots = (batch.node_mask.shape[-1], batch.edge_mask.shape[-1], batch.half_mask.shape[-1],
             batch.crossing_mask.shape[-1])  # fmt: skip
    n, e, d, c = (min(_round_up(max(int(u), 1)), s) for u, s in zip(used, slots, strict=True))
    return jax.vmap(lambda g: _trim(g, n, e, d, c))(batch)


def _round_up(x: int) -> int:
    """``x`` rounded up to a multiple of a power of two at most an eighth of it."""
    step = 1 << max(0, x.bit_length() - 4)
    return -(-x // step) * step
