"""Maximal Poisson-disk sampling of pores in UV space (§3.1.1 of Weiss et al. 2023), in JAX.

The local minimum distance is ``r(x) = α_d(x) · R(x)``: the average pore distance α_d (a scalar
or a texture, e.g. varied with Perlin noise) times an optional radius scaling map ``R`` (UV-stretch
compensation; ``R > 1`` spreads pores out). Two pores ``p, q`` must satisfy
``|p − q| ≥ max(r(p), r(q))``.

Algorithm (parallel, grid-based, after Bowers et al. 2010 — the paper's [BWM10] — with a coverage
pass that makes the sample maximal):

* A background grid of cell size ``h ≤ r_min / √2`` holds at most one pore per cell. A candidate
  conflicts only with pores within ``k = ⌈r_max / h⌉`` cells.
* Cells are split into ``(k + 1)²`` phase groups (cell index modulo ``k + 1``); candidates of one
  group cannot conflict with each other, so a whole group is tested and accepted in parallel.
* Each cell is split into 4 × 4 sub-cells visited in a random per-cell order; in round ``t`` every
  empty cell throws one dart uniformly into its ``t``-th sub-cell (16 rounds, groups in random
  order per round). A rejected dart stays rejected (pores are never removed), so after the last
  round every point of the domain lies within ``max(r) + h·√2/4 ≤ 1.25 r`` of a pore: the
  sampling is maximal up to a quarter of the radius, a guarantee rather than a probability.

Everything has static shapes (grid size from the radius bounds, output capacity + mask), so the
sampler runs under ``jit`` and ``vmap`` (e.g. over agents whose α_d differ, given ``radius_range``
and ``capacity``). A finer level starts from the coarser level's pores (``initial``) and adds
new pores in between. The domain is the unit square, optionally periodic (a torus).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int

from jface import _checks
from jface.wrinkles._params import PARAMETER_RANGES
from jface.wrinkles._textures import at

_SUB = 4  # sub-cells per cell side in the coverage rounds (guarantee: coverage ≤ (1 + 1/4) r)
_ROUNDS = _SUB * _SUB


class Pores(eqx.Module):
    """Pores (graph nodes) in UV space, with a fixed capacity and a mask.

    Valid pores come first: pore ``i`` is valid iff ``i < count``. Pores inherited from a coarser
    level keep their indices.

    Attributes:
        positions: ``(capacity, 2)`` coordinates ``(x, y)`` in ``[0, 1)²``.
        radius: ``(capacity,)`` local minimum distance ``r`` of the level at each pore.
        level: ``(capacity,)`` index of the level that created each pore (0 = coarsest).
        mask: ``(capacity,)`` True for valid pores.
        count: number of valid pores (a 0-d array).
        periodic: whether the domain wraps around (static).
    """

    positions: Float[Array, "*b n 2"]
    radius: Float[Array, "*b n"]
    level: Int[Array, "*b n"]
    mask: Bool[Array, "*b n"]
    count: Int[Array, "*b"]
    periodic: bool = eqx.field(static=True, default=False)

    @property
    def capacity(self) -> int:
        return self.positions.shape[-2]


def make_pores(
    positions: ArrayLike,
    *,
    radius: ArrayLike | float = 0.0,
    periodic: bool = False,
    capacity: int | None = None,
) -> Pores:
    """Pores from given positions (e.g. extracted from a coarse scan, §4.1), padded to ``capacity``.

    Args:
        positions: ``(n, 2)`` coordinates in ``[0, 1]²``.
        radius: a scalar or ``(n,)`` local distances to record (informative).
        periodic: domain wraps around.
        capacity: total slots (default ``n``).

    Raises:
        ValueError/TypeError: malformed positions, points outside the unit square, capacity < n.
    """
    pos = _checks.float_array(positions, "positions", ndim=2, dtype=jnp.float32)
    if pos.shape[1] != 2:
        raise ValueError(f"positions must have shape (n, 2), got {_checks.describe(pos)}")
    if not _checks.is_traced(pos) and bool(np.any((np.asarray(pos) < 0) | (np.asarray(pos) > 1))):
        raise ValueError("positions must lie in the unit square [0, 1]²")
    n = pos.shape[0]
    capacity = n if capacity is None else _checks.integer(capacity, "capacity", low=n)
    if periodic:
        pos = jnp.mod(pos, 1.0)
    rad = jnp.broadcast_to(jnp.asarray(radius, jnp.float32), (n,))
    pad = capacity - n
    return Pores(
        positions=jnp.pad(pos, ((0, pad), (0, 0))),
        radius=jnp.pad(rad, (0, pad)),
        level=jnp.zeros(capacity, jnp.int32),
        mask=jnp.arange(capacity, dtype=jnp.int32) < n,
        count=jnp.asarray(n, jnp.int32),
        periodic=bool(periodic),
    )


def grid_layout(r_lo: float, r_hi: float) -> tuple[int, int]:
    """Background grid ``(G, k)``: ``G`` cells per side (a multiple of ``k + 1``, cell size
    ``1/G ≤ r_lo/√2``) and the reach ``k = ⌈r_hi · G⌉`` in cells of a conflict check."""
    g = math.ceil(math.sqrt(2.0) / r_lo)
    while True:
        k = max(1, math.ceil(r_hi * g))
        s = k + 1
        g2 = max(2 * s, math.ceil(g / s) * s)
        if g2 == g:
            return g, k
        g = g2


def default_capacity(d: Any, radius_map: Any = None, *, initial: int = 0) -> int:
    """An upper bound of the pore count for the local distance ``d · R`` (hexagonal packing
    bound ``2/(√3 r²)`` per unit area, integrated over the map, plus a boundary margin)."""
    grid = (np.arange(64, dtype=np.float32) + 0.5) / 64
    # concrete values (also closed over inside jit) are looked up eagerly: they size arrays
    with jax.ensure_compile_time_eval():
        xy = jnp.asarray(np.stack(np.meshgrid(grid, grid), -1))
        r = np.asarray(at(jnp.asarray(d, jnp.float32), xy, periodic=False), np.float64)
        if radius_map is not None:
            r = r * np.asarray(at(jnp.asarray(radius_map, jnp.float32), xy, periodic=False))
    dens = float(np.mean(1.0 / r**2)) * 2.0 / math.sqrt(3.0)
    return math.ceil(1.05 * dens + 4.0 / float(np.min(r)) + 16) + int(initial)


def sample_pores(
    key: jax.Array,
    d: ArrayLike,
    radius_map: ArrayLike | None = None,
    *,
    capacity: int | None = None,
    initial: Pores | None = None,
    periodic: bool = False,
    radius_range: tuple[float, float] | None = None,
) -> Pores:
    """Maximal Poisson-disk sampling with a uniform or spatially varying minimum distance.

    Implements the pore sampling of §3.1.1 of Weiss et al. 2023: minimum distance
    ``r(x) = d(x) · R(x)`` (average pore distance α_d times the radius scaling map **R**).
    Guarantees: every pair of pores ``p, q`` with at least one new pore is at least
    ``max(r(p), r(q))`` apart (up to float32 rounding of the coordinates), and every point ``x``
    of the domain lies within ``1.25 · max(r(x), r(p))`` of its nearest pore ``p`` (maximal
    coverage).

    Args:
        key: a ``jax.random.key``.
        d: α_d, a scalar or an ``(H, W)`` texture over the unit square, in [0.001, 0.05]
            (Table 1).
        radius_map: optional ``(H', W')`` positive radius scaling map **R**.
        capacity: pore slots of the result (static). Default: a packing bound of the pore count.
            Required when ``d``/``radius_map`` are traced (under ``jit``/``vmap``).
        initial: pores of a coarser level (or extracted pores) that the result starts from and
            keeps, first and in order; new pores are added in between. Two initial pores must
            not fall into one grid cell (closer than about ``r_min/√2``).
        periodic: the unit square wraps around (a torus); distances use the minimum image.
        radius_range: static bounds ``(r_lo, r_hi)`` of ``d · R`` over the domain; required when
            ``d``/``radius_map`` are traced (they fix the grid), computed from the values
            otherwise.

    Returns:
        :class:`Pores` with ``capacity`` slots; ``level`` of the new pores is one more than the
        largest initial level (0 without ``initial``).

    Raises:
        ValueError: ``d`` outside Table 1's range, a non-positive radius map, more pores than
            ``capacity`` (never silently dropped), colliding initial pores. Under ``jit`` the
            same conditions raise through ``equinox.error_if``.
    """
    key = _checks.key(key)
    d = _checks.float_array(d, "d", dtype=jnp.float32)
    if d.ndim not in (0, 2):
        raise ValueError(f"d must be a scalar or a 2-D texture (H, W), got {_checks.describe(d)}")
    lo, hi = PARAMETER_RANGES["d"]
    # numpy copies of concrete values: numpy's reductions of a jax array would trace under jit
    d_values = None if _checks.is_traced(d) else np.asarray(d)
    low, high = np.float32(lo), np.float32(hi)
    if d_values is not None and (d_values.min() < low or d_values.max() > high):
        raise ValueError(
            f"d (α_d) must be in [{lo}, {hi}] (Table 1), got values in "
            f"[{float(d_values.min())}, {float(d_values.max())}]"
        )
    if radius_map is not None:
        radius_map = _checks.float_array(radius_map, "radius_map", ndim=2, dtype=jnp.float32)
        if not _checks.is_traced(radius_map) and float(np.min(np.asarray(radius_map))) <= 0:
            raise ValueError(
                "radius_map must be positive everywhere, got minimum "
                f"{float(np.min(np.asarray(radius_map)))}"
            )
    if initial is not None:
        if not isinstance(initial, Pores):
            raise TypeError(f"initial must be Pores, got {_checks.describe(initial)}")
        if initial.periodic != bool(periodic):
            raise ValueError(
                f"initial pores have periodic={initial.periodic}, but periodic={periodic}"
            )
    traced = _checks.is_traced(d) or _checks.is_traced(radius_map)
    if radius_range is None:
        if traced:
            raise ValueError(
                "radius_range=(r_lo, r_hi) is required when d or radius_map are traced "
                "(under jit/vmap); it fixes the sampling grid"
            )
        rmap = np.ones(()) if radius_map is None else np.asarray(radius_map)
        radius_range = (
            float(d_values.min()) * float(np.min(rmap)),
            float(d_values.max()) * float(np.max(rmap)),
        )
    r_lo = _checks.real(radius_range[0], "radius_range[0]", low=0.0, open_low=True)
    r_hi = _checks.real(radius_range[1], "radius_range[1]", low=r_lo)
    if r_lo < 2e-4:
        raise ValueError(f"the smallest pore distance must be at least 2e-4, got {r_lo}")
    if r_hi > 0.25:
        raise ValueError(f"the largest pore distance d·R must be at most 0.25, got {r_hi}")
    if capacity is None:
        if traced:
            raise ValueError("capacity is required when d or radius_map are traced")
        capacity = default_capacity(
            d, radius_map, initial=0 if initial is None else initial.capacity
        )
    capacity = _checks.integer(capacity, "capacity", low=1)
    if initial is not None and initial.capacity > capacity:
        raise ValueError(
            f"capacity ({capacity}) must be at least the initial pores' capacity "
            f"({initial.capacity})"
        )
    pores, flags, total = sampled(
        key, d, radius_map, initial, capacity, (r_lo, r_hi), bool(periodic)
    )
    if not any(_checks.is_traced(f) for f in flags.values()):
        if bool(flags["range"]):
            raise ValueError(f"d · radius_map leaves radius_range {radius_range}")
        if bool(flags["collide"]):
            raise ValueError(
                "two initial pores fall into one sampling cell (closer than about "
                f"{r_lo / math.sqrt(2):.3g}); thin them out first"
            )
        if bool(flags["overflow"]):
            raise ValueError(
                f"the sampling produced {int(total)} pores, more than capacity={capacity}; "
                "raise the capacity (pores are never dropped silently)"
            )
        return pores
    positions = pores.positions
    for name, flag in flags.items():
        positions = eqx.error_if(positions, flag, SAMPLING_ERRORS[name])
    return eqx.tree_at(lambda p: p.positions, pores, positions)


#: What each flag of :func:`sampled` means.
SAMPLING_ERRORS = {
    "range": "d · radius_map leaves radius_range",
    "collide": "two initial pores fall into one sampling cell",
    "overflow": "more pores than capacity",
}


def sampled(key, d, radius_map, initial, capacity, radius_range, periodic):
    """:func:`sample_pores` of checked arguments, with its error flags (``SAMPLING_ERRORS``)
    returned rather than raised: a program that raises through ``equinox.error_if`` holds host
    callbacks, which JAX's persistent compilation cache does not keep. Also returns the number
    of pores sampled (more than ``capacity`` on overflow)."""
    if initial is None:
        init = make_pores(jnp.zeros((1, 2), jnp.float32), periodic=periodic)
        init = eqx.tree_at(lambda p: (p.mask, p.count), init, (jnp.zeros(1, bool), jnp.int32(0)))
        new_level = jnp.int32(0)
    else:
        init = initial
        new_level = jnp.max(jnp.where(init.mask, init.level, -1)).astype(jnp.int32) + 1
    r_lo, r_hi = radius_range
    g, k = grid_layout(r_lo, r_hi)
    pores, total, collide, out_of_range = _sample(
        key, d, radius_map, init, new_level, r_lo, r_hi, g=g, k=k, capacity=capacity,
        periodic=periodic,
    )  # fmt: skip
    flags = {"range": out_of_range, "collide": collide, "overflow": total > capacity}
    return pores, flags, total


def _radius_cells(d, radius_map, xy, g, periodic):
    r = at(d, xy, periodic=periodic)
    if radius_map is not None:
        r = r * at(radius_map, xy, periodic=periodic)
    return r * g


def _sample(key, d, radius_map, init, new_level, r_lo, r_hi, *, g, k, capacity, periodic):
    grid, init_xy, init_mask, init_level, collide, out_of_range = _insert(
        d, radius_map, init, r_lo, r_hi, g=g, periodic=periodic
    )
    occ, offs, rad = _fill(key, d, radius_map, grid, g=g, k=k, periodic=periodic)
    pores, total = _compact(
        d, radius_map, occ, grid[0], offs, rad, init_xy, init_mask, init_level, new_level,
        g=g, capacity=capacity, periodic=periodic,
    )  # fmt: skip
    return pores, total, collide, out_of_range


@functools.partial(jax.jit, static_argnames=("g", "periodic"))
def _insert(d, radius_map, init, r_lo, r_hi, *, g, periodic):
    f32 = jnp.float32

    def radius_cells(xy):
        return _radius_cells(d, radius_map, xy, g, periodic)

    rmin, rmax = jnp.min(d), jnp.max(d)
    if radius_map is not None:
        rmin, rmax = rmin * jnp.min(radius_map), rmax * jnp.max(radius_map)
    out_of_range = (rmin < r_lo * (1 - 1e-5)) | (rmax > r_hi * (1 + 1e-5))

    # initial pores, valid first
    order = jnp.argsort(~init.mask, stable=True)
    init_xy = init.positions[order]
    init_mask = init.mask[order]
    init_level = init.level[order]
    cell = jnp.clip(jnp.floor(init_xy * g).astype(jnp.int32), 0, g - 1)
    flat = jnp.where(init_mask, cell[:, 1] * g + cell[:, 0], g * g)
    hits = jnp.zeros(g * g, jnp.int32).at[flat].add(1, mode="drop")
    collide = jnp.max(hits) > 1
    occ = (hits > 0).reshape(g, g)
    offs = (
        jnp.zeros((g * g, 2), f32)
        .at[flat]
        .set(init_xy * g - cell.astype(f32), mode="drop")
        .reshape(g, g, 2)
    )
    rad = jnp.zeros(g * g, f32).at[flat].set(radius_cells(init_xy), mode="drop").reshape(g, g)
    return (occ, offs, rad), init_xy, init_mask, init_level, collide, out_of_range


@functools.partial(jax.jit, static_argnames=("g", "k", "periodic"))
def _fill(key, d, radius_map, grid, *, g, k, periodic):
    s = k + 1
    n = g // s
    f32 = jnp.float32
    occ, offs, rad = grid

    def radius_cells(xy):
        return _radius_cells(d, radius_map, xy, g, periodic)

    k_bits, k_order, k_darts = jax.random.split(key, 3)
    bits = jax.random.bits(k_bits, (g, g), dtype=jnp.uint32)
    perm_a = ((bits & 7) << 1) | 1  # odd multiplier: t ↦ a t + b is a bijection modulo 16
    perm_b = (bits >> 3) & 15
    perm_c = (bits >> 7) & 15

    def view(x, a, b):
        xr = x.reshape((n, s, n, s, *x.shape[2:]))
        xr = lax.dynamic_index_in_dim(xr, a, 1, keepdims=False)
        return lax.dynamic_index_in_dim(xr, b, 2, keepdims=False)

    def put(x, a, b, v):
        xr = x.reshape((n, s, n, s, *x.shape[2:]))
        zero = jnp.int32(0)
        start = (zero, a, zero, b) + (zero,) * (x.ndim - 2)
        xr = lax.dynamic_update_slice(xr, v[:, None, :, None], start)
        return xr.reshape(x.shape)

    mode = "wrap" if periodic else "constant"
    span = s * (n - 1) + 1
    width = 2 * k + 1
    rows = jnp.arange(n, dtype=jnp.int32) * s
    cols = jnp.arange(n, dtype=jnp.int32) * s

    def phase(state, a, b, t, key_tp):
        occ, offs, rad = state
        cand_occ = view(occ, a, b)
        sub = ((view(perm_a, a, b) * t.astype(jnp.uint32) + view(perm_b, a, b)) & 15) ^ view(
            perm_c, a, b
        )
        sub_xy = jnp.stack([sub & 3, sub >> 2], axis=-1).astype(f32)
        cand_off = (sub_xy + jax.random.uniform(key_tp, (n, n, 2), dtype=f32)) / _SUB
        cell_xy = jnp.stack(
            jnp.broadcast_arrays((cols + b)[None, :], (rows + a)[:, None]), axis=-1
        ).astype(f32)
        cand_rad = radius_cells((cell_xy + cand_off) / g)
        p_occ = jnp.pad(occ, k, mode=mode)
        p_off = jnp.pad(offs, ((k, k), (k, k), (0, 0)), mode=mode)
        p_rad = jnp.pad(rad, k, mode=mode)

        def check(w, conflict):
            dy, dx = w // width - k, w % width - k
            r0, c0 = a + dy + k, b + dx + k
            no = lax.dynamic_slice(p_occ, (r0, c0), (span, span))[::s, ::s]
            noff = lax.dynamic_slice(p_off, (r0, c0, jnp.int32(0)), (span, span, 2))[::s, ::s]
            nrad = lax.dynamic_slice(p_rad, (r0, c0), (span, span))[::s, ::s]
            ddx = dx.astype(f32) + noff[..., 0] - cand_off[..., 0]
            ddy = dy.astype(f32) + noff[..., 1] - cand_off[..., 1]
            rr = jnp.maximum(cand_rad, nrad)
            return conflict | (no & (ddx * ddx + ddy * ddy < rr * rr))

        conflict = lax.fori_loop(0, width * width, check, jnp.zeros((n, n), bool))
        accept = ~cand_occ & ~conflict
        occ = put(occ, a, b, cand_occ | accept)
        offs = put(offs, a, b, jnp.where(accept[..., None], cand_off, view(offs, a, b)))
        rad = put(rad, a, b, jnp.where(accept, cand_rad, view(rad, a, b)))
        return occ, offs, rad

    def round_(t, state):
        phases = jax.random.permutation(jax.random.fold_in(k_order, t), s * s)
        key_t = jax.random.fold_in(k_darts, t)

        def one(p, state):
            ph = phases[p].astype(jnp.int32)
            return phase(state, ph // s, ph % s, t, jax.random.fold_in(key_t, p))

        return lax.fori_loop(0, s * s, one, state)

    return lax.fori_loop(0, _ROUNDS, round_, (occ, offs, rad))


@functools.partial(jax.jit, static_argnames=("g", "capacity", "periodic"))
def _compact(
    d, radius_map, occ, init_occ, offs, rad, init_xy, init_mask, init_level, new_level, *,
    g, capacity, periodic,
):  # fmt: skip
    f32 = jnp.float32

    def radius_cells(xy):
        return _radius_cells(d, radius_map, xy, g, periodic)

    init_count = jnp.sum(init_mask).astype(jnp.int32)
    # compaction: initial pores first (in order), then the new ones in cell order
    new = (occ & ~init_occ).reshape(-1)
    count_new = jnp.sum(new).astype(jnp.int32)
    idx = jnp.nonzero(new, size=capacity, fill_value=0)[0]
    cell_new = jnp.stack([idx % g, idx // g], axis=-1).astype(f32)
    valid_new = jnp.arange(capacity, dtype=jnp.int32) < count_new
    xy_new = jnp.where(valid_new[:, None], (cell_new + offs.reshape(-1, 2)[idx]) / g, 0.0)
    rad_new = jnp.where(valid_new, rad.reshape(-1)[idx] / g, 0.0)
    rad_init = radius_cells(init_xy) / g
    m = init_xy.shape[0]
    slots = init_count + jnp.arange(capacity, dtype=jnp.int32)
    init_keep = jnp.where(init_mask, jnp.arange(m, dtype=jnp.int32), capacity)
    positions = jnp.zeros((capacity, 2), f32).at[init_keep].set(init_xy, mode="drop")
    positions = positions.at[slots].set(xy_new, mode="drop")
    radius = jnp.zeros(capacity, f32).at[init_keep].set(rad_init, mode="drop")
    radius = radius.at[slots].set(rad_new, mode="drop")
    level = jnp.zeros(capacity, jnp.int32).at[init_keep].set(init_level, mode="drop")
    level = level.at[slots].set(jnp.broadcast_to(new_level, (capacity,)), mode="drop")
    total = init_count + count_new
    mask = jnp.arange(capacity, dtype=jnp.int32) < total
    level = jnp.where(mask, level, 0)
    if periodic:
        positions = jnp.mod(positions, 1.0)
    pores = Pores(
        positions=positions,
        radius=radius,
        level=level,
        mask=mask,
        count=jnp.minimum(total, capacity).astype(jnp.int32),
        periodic=periodic,
    )
    return pores, total
