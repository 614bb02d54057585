"""Drawing one level's wrinkles and pores into a displacement map (§3.2 of Weiss et al. 2023).

Every wrinkle (edge with weight ``W > 0``) and every pore is a *primitive*: a segment from ``p0``
to ``p0 + delta`` (a point for pores) with a valley half-width ``w`` and a strength ``s``. A pixel
at distance ``x · w`` from the (perturbed) centre line receives the fragment ``s_i = s · S(x)``
with the shape function of Eq. 9; fragments are blended with the modified mellowmax of
Eq. 10–11. The wrinkle geometry is perturbed like the paper's vertex shader: the centre line's
vertices (``N_VERTICES`` along the wrinkle) move along the normal by multi-octave Perlin noise and
the offset is interpolated linearly in between, which is the exact inverse of displacing the
band's vertices.

The rasteriser bins primitives to square screen tiles (each primitive to the at most
``span × span`` tiles its bounding box touches: the pairs are enumerated and sorted by tile), then
evaluates each tile's pixels against its primitives in ``passes`` chunks of ``capacity`` with the
blend accumulated additively (as in the paper's three-channel framebuffer, with a running maximum
for float32 range), so any resolution works with memory bounded by the tile batch. Each tile
batch draws the passes its fullest tile needs, up to a static bound (``passes``; ``passes=None``
in :func:`render` does without one). The map is reverse-differentiable in the primitives by a
gradient of its own, which recomputes each pass's fragments and weights each by its share of
Eq. 10's log-sum-exp: reverse-mode through the passes' running sums cost about four forward
draws, this about two.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jface import _checks
from jface.noise import _fractal, _octave
from jface.wrinkles._graph import PoreGraph
from jface.wrinkles._params import WrinkleParams
from jface.wrinkles._textures import at

BETA = 20.0  #: β of Eq. 10
N_HAT = 16  #: N̂_f of Eq. 10, fragments expected on top of each other
N_VERTICES = 8  #: perturbed centre-line vertices per wrinkle
_PERTURB_OCTAVES = 3
_MAX_SIDE = 65536  # largest map side (16k maps are drawn in bands, see draw_bands)
_TILE = 16  # default screen tile: the fastest on CPU (fewer wasted primitive tests than 32)


def shape_function(x: ArrayLike, *, bulge: bool = True) -> Float[Array, "..."]:
    """Wrinkle profile of Eq. 9 at distance ``x`` (in valley half-widths) from the centre line.

    ``S_bulge(x) = (x − 3)² (x − 1) / 9`` on ``[0, 3]`` (valley on ``[0, 1]``, bulge on
    ``[1, 3]``) or ``S_no-bulge(x) = −(1 − 2x/3)³`` on ``[0, 1.5]``; zero outside the domain.
    """
    x = jnp.abs(jnp.asarray(x, jnp.float32))
    if bulge:
        return jnp.where(x < 3.0, (x - 3.0) ** 2 * (x - 1.0) / 9.0, 0.0)
    return jnp.where(x < 1.5, -((1.0 - 2.0 * x / 3.0) ** 3), 0.0)


def _extent(bulge: bool) -> float:
    return 3.0 if bulge else 1.5


def _mm_finish(m, total, n, beta, n_hat):
    """Eq. 10 from a running maximum ``m`` ≥ 0, ``total = Σ exp(β (x_i − m))`` and count ``n``."""
    n_hat_f = jnp.maximum(jnp.asarray(n_hat, total.dtype), n)  # standard mellowmax when n > N̂
    pad = (n_hat_f - n) * jnp.exp(-beta * m)  # the N̂ − N_f implicit zero fragments
    return m + (jnp.log(total + pad) - jnp.log(n_hat_f)) / beta


def mellowmax(
    x: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    beta: float = BETA,
    n_hat: int = N_HAT,
) -> Float[Array, "..."]:
    """Modified mellowmax of Eq. 10 over the last axis (the fragments of one pixel).

    ``(1/β) log((N̂ − N_f + Σ exp(β x_i)) / N̂)`` with ``N_f`` the number of (unmasked)
    fragments; when ``N_f > N̂`` it is the standard mellowmax (``N̂ = N_f``). ``n_hat=1`` gives
    the standard mellowmax, which equals the value for one fragment; the modified one equals the
    standard mellowmax of the fragments padded with zeros to ``N̂``.

    Args:
        x: ``(..., k)`` fragment values.
        mask: optional ``(..., k)`` booleans, the fragments present (default all).
        beta: β > 0.
        n_hat: N̂_f ≥ 1.
    """
    xs = _checks.float_array(x, "x", min_ndim=1, dtype=jnp.float32)
    beta = _checks.real(beta, "beta", low=0.0, open_low=True)
    n_hat = _checks.integer(n_hat, "n_hat", low=1)
    present = jnp.ones(xs.shape, bool) if mask is None else jnp.asarray(mask, bool)
    if present.shape != xs.shape:
        raise ValueError(f"mask must have the shape of x {xs.shape}, got {present.shape}")
    m = jnp.maximum(jnp.max(jnp.where(present, xs, -jnp.inf), axis=-1), 0.0)
    total = jnp.sum(jnp.where(present, jnp.exp(beta * (xs - m[..., None])), 0.0), axis=-1)
    n = jnp.sum(present, axis=-1).astype(jnp.float32)
    return _mm_finish(m, total, n, beta, n_hat)


class Primitives(NamedTuple):
    """Wrinkles and pores of one level, as segments to rasterise (UV units).

    Attributes:
        p0: ``(m, 2)`` start point.
        delta: ``(m, 2)`` vector to the end point (zero for pores).
        width: ``(m,)`` valley half-width ``w``.
        strength: ``(m,)`` depth ``s`` (Eq. 9 is scaled by it).
        cushion: ``(m, 2)`` extra strength at the start and end (cushioning, falls off to zero at
            the middle).
        offsets: ``(m, N_VERTICES)`` centre-line offsets along the normal (perturbation).
        axis: ``(m, 2)`` unit axis of the pore skew.
        stretch: ``(m,)`` stretch factor along ``axis`` (1 = round).
        valid: ``(m,)`` primitive is drawn.
    """

    p0: Float[Array, "m 2"]
    delta: Float[Array, "m 2"]
    width: Float[Array, " m"]
    strength: Float[Array, " m"]
    cushion: Float[Array, "m 2"]
    offsets: Float[Array, "m v"]
    axis: Float[Array, "m 2"]
    stretch: Float[Array, " m"]
    valid: Bool[Array, " m"]


def pore_strength(
    graph: PoreGraph, weights: Float[Array, " E"], dmin: ArrayLike, blend: ArrayLike
) -> Float[Array, " n"]:
    """Strength ``w_v`` of every pore from its incident edge weights (Eq. 12–13)."""
    w = jnp.where(graph.half_mask, weights[graph.half_edge], 0.0)
    w_max = jnp.max(w, axis=-1)
    w_sum = jnp.sum(w, axis=-1)
    return jnp.maximum(w_max + dmin, w_max + blend * (w_sum - w_max))


#: Smallest valley half-width drawn, in pixels: a narrower wrinkle or pore is widened to it with
#: its depth lowered in proportion (the same depth × width), so that it fades out smoothly instead
#: of showing as a hairline of full depth (pixel-centre sampling of a sub-pixel line).
FOOTPRINT = 0.7


def perturbation_noise(
    key: jax.Array, graph: PoreGraph, params: WrinkleParams
) -> tuple[Float[Array, "n 2"], Float[Array, "E v 2"]]:
    """The perturbation's noise before its amplitude, at the graph's pores ``(n, 2)`` and at its
    wrinkles' inner centre-line vertices ``(E, N_VERTICES - 2, 2)``: two-channel multi-octave
    Perlin noise of frequency α_fperturb, periodic on periodic graphs.

    One field for every wrinkle and pore: the paper queries it at the centre-line point nearest
    each vertex, so wrinkles that meet at a pore move with it and stay joined. It is evaluated
    once over pores and vertices (one traced field: less to compile). A function of the key, the
    graph and α_fperturb alone, so a fit that draws many agents on one graph computes it once
    (:func:`primitives`' ``noise``)."""
    pos, verts = graph.positions, _inner_vertices(graph)
    flat = jnp.concatenate([pos, verts.reshape(-1, 2)])
    freq = at(params.fperturb, flat, periodic=graph.periodic)
    kx, ky = jax.random.split(key)
    fx = _fractal(kx, flat, freq, _PERTURB_OCTAVES, 0.5, 2.0, graph.periodic)
    fy = _fractal(ky, flat, freq, _PERTURB_OCTAVES, 0.5, 2.0, graph.periodic)
    unit = jnp.stack([fx, fy], -1)
    n = pos.shape[0]
    return unit[:n], unit[n:].reshape(verts.shape)


def _inner_t() -> Float[Array, " v"]:
    """Positions along a wrinkle (0 to 1) of its inner centre-line vertices."""
    return jnp.linspace(0.0, 1.0, N_VERTICES, dtype=jnp.float32)[1:-1]


def _inner_vertices(graph: PoreGraph) -> Float[Array, "E v 2"]:
    """The wrinkles' inner centre-line vertices before the perturbation (the end vertices move
    with their pores)."""
    a = graph.positions[graph.edge_nodes[:, 0]]
    verts = a[:, None, :] + _inner_t()[None, :, None] * graph.edge_delta[:, None, :]
    return jnp.mod(verts, 1.0) if graph.periodic else verts


def _perturbation_amplitude(params: WrinkleParams, xy, periodic: bool) -> Float[Array, "..."]:
    """``α_sperturb · α_wrinkle-width · α_d`` at points ``xy``: the valley half-width of a
    full-strength wrinkle."""
    amp = at(params.sperturb, xy, periodic=periodic) * at(params.wrinkle_width, xy,
                                                          periodic=periodic)  # fmt: skip
    return amp * at(params.d, xy, periodic=periodic)


@functools.partial(jax.jit, static_argnames="shape")
def primitives(
    key: jax.Array,
    graph: PoreGraph,
    weights,
    params: WrinkleParams,
    shape: tuple[int, int],
    noise: tuple[Array, Array] | None = None,
) -> Primitives:
    """The wrinkle and pore primitives of one level drawn at ``shape`` (traced-friendly, no
    validation). α_scale multiplies every strength before the blend (§3.1.2); widths below
    :data:`FOOTPRINT` pixels are widened at equal depth × width. ``noise``: the perturbation's
    :func:`perturbation_noise` of ``key`` and ``graph`` where it is at hand (default: computed
    here)."""
    per = graph.periodic
    pos = graph.positions
    a = pos[graph.edge_nodes[:, 0]]
    mid = a + 0.5 * graph.edge_delta
    mid = jnp.mod(mid, 1.0) if per else mid

    # pores (Eq. 12-13): width w_v · α_pore-width · α_d, skewed along α_θ
    w_v = pore_strength(graph, weights, at(params.dmin, pos, periodic=per),
                        at(params.blend, pos, periodic=per))  # fmt: skip
    d_v = at(params.d, pos, periodic=per)
    theta_v = at(params.theta, pos, periodic=per)
    pore_valid = graph.node_mask
    n = pos.shape[0]
    scale_v = at(params.scale, pos, periodic=per)
    scale_e = at(params.scale, mid, periodic=per)

    # wrinkles: half-width W · α_wrinkle-width · α_d, strength W, cushion from the end pores
    d_e = at(params.d, mid, periodic=per)
    width_e = weights * at(params.wrinkle_width, mid, periodic=per) * d_e
    cushion = at(params.cushion, mid, periodic=per)[:, None] * (scale_v * w_v)[graph.edge_nodes]
    edge_valid = graph.edge_mask & (weights > 0)

    # perturbation (Fig. 7a, 9): one offset field moves the pores, the wrinkles' end points with
    # them, and the centre-line vertices in between (the normal component, relative to the
    # moved straight line, is what the rasteriser interpolates)
    # the inner vertices only: the end vertices move with their pores (no offset)
    t = _inner_t()
    noise = perturbation_noise(key, graph, params) if noise is None else noise
    move_v, move_verts = (
        _perturbation_amplitude(params, xy, per)[..., None] * unit
        for xy, unit in zip((pos, _inner_vertices(graph)), noise, strict=True)
    )
    ends = move_v[graph.edge_nodes]  # (E, 2, 2)
    start = a + ends[:, 0]
    delta = graph.edge_delta + ends[:, 1] - ends[:, 0]
    along = ends[:, None, 0] + t[None, :, None] * (ends[:, None, 1] - ends[:, None, 0])
    rest = move_verts - along
    length = jnp.sqrt(jnp.maximum(jnp.sum(delta * delta, -1), 1e-20))
    normal = jnp.stack([-delta[:, 1], delta[:, 0]], -1) / length[:, None]  # as _fragments
    offsets = jnp.pad(jnp.sum(rest * normal[:, None, :], -1), ((0, 0), (1, 1)))

    e = weights.shape[0]
    zeros2 = jnp.zeros((n, 2), jnp.float32)
    axis_v = jnp.stack([jnp.cos(theta_v), jnp.sin(theta_v)], axis=-1)
    width = jnp.concatenate([width_e, w_v * at(params.pore_width, pos, periodic=per) * d_v])
    # the pixel footprint: sub-pixel lines fade out rather than alias to hairlines
    foot = FOOTPRINT / max(shape)
    wide = jnp.sqrt(width * width + foot * foot)
    fade = width / wide
    return Primitives(
        p0=jnp.concatenate([start, pos + move_v]),
        delta=jnp.concatenate([delta, zeros2]),
        width=wide,
        strength=fade * jnp.concatenate([scale_e * weights, scale_v * w_v]),
        cushion=fade[:, None] * jnp.concatenate([cushion, zeros2]),
        offsets=jnp.concatenate([offsets, jnp.zeros((n, N_VERTICES), jnp.float32)]),
        axis=jnp.concatenate([jnp.tile(jnp.array([[1.0, 0.0]], jnp.float32), (e, 1)), axis_v]),
        stretch=jnp.concatenate(
            [jnp.ones(e, jnp.float32), 1.0 + 2.0 * at(params.skew, pos, periodic=per)]
        ),
        valid=jnp.concatenate([edge_valid, pore_valid]),
    )


class Bins(NamedTuple):
    """Primitives sorted by screen tile: tile ``t`` owns ``order[start[t]:][:count[t]]``."""

    order: Int[Array, " k"]
    start: Int[Array, " g"]
    count: Int[Array, " g"]
    overflow: Bool[Array, ""]


def _bbox(prims: Primitives, bulge: bool):
    """Per primitive UV bounding box ``(lo, hi)`` of everything it can touch."""
    reach = prims.width * _extent(bulge) * prims.stretch + jnp.max(jnp.abs(prims.offsets), -1)
    end = prims.p0 + prims.delta
    lo = jnp.minimum(prims.p0, end) - reach[:, None]
    hi = jnp.maximum(prims.p0, end) + reach[:, None]
    return lo, hi


def _tile_range(lo, hi, shape, tile):
    """First tile index and number of tiles per axis ``(x, y)`` of every bounding box."""
    size = jnp.array([shape[1], shape[0]], jnp.float32)
    first = jnp.floor(lo * size / tile).astype(jnp.int32)
    last = jnp.floor(hi * size / tile).astype(jnp.int32)
    return first, last - first + 1


def needed_span(
    prims: Primitives, shape: tuple[int, int], *, tile: int, bulge: bool, periodic: bool
) -> int:
    """Smallest ``span`` that bins these (concrete) primitives without overflow."""
    n = np.asarray(_tiles_touched(prims, shape, tile, bulge, periodic)[1])
    return int(n.max(initial=1))


def needed_entries(
    prims: Primitives, shape: tuple[int, int], *, tile: int, bulge: bool, periodic: bool
) -> int:
    """Number of (primitive, tile) pairs these (concrete) primitives make when binned."""
    return int(entries_of(prims, shape, tile=tile, bulge=bulge, periodic=periodic))


def entries_of(
    prims: Primitives, shape: tuple[int, int], *, tile: int, bulge: bool, periodic: bool
) -> Array:
    """:func:`needed_entries` as an array (also of traced primitives, e.g. inside a program
    that sizes the bins of many draws at once)."""
    n = _tiles_touched(prims, shape, tile, bulge, periodic)[1]
    return jnp.sum(jnp.prod(n, -1))


def _tiles_touched(prims, shape, tile, bulge, periodic) -> tuple[Array, Array]:
    """First tile and tiles per axis ``(m, 2)`` each valid primitive touches (0 for invalid
    ones); a box wider than a periodic map covers every tile once, and on a non-periodic map only
    the visible tiles count."""
    first, n = _tile_range(*_bbox(prims, bulge), shape, tile)
    grid = jnp.array([-(-shape[1] // tile), -(-shape[0] // tile)], jnp.int32)
    if periodic:
        n = jnp.minimum(n, grid)
    else:
        last = jnp.minimum(first + n - 1, grid - 1)
        first = jnp.maximum(first, 0)
        n = jnp.maximum(last - first + 1, 0)
    return first, jnp.where(prims.valid[:, None], n, 0)


def bin_primitives(
    prims: Primitives, shape: tuple[int, int], *, tile: int, span: int, bulge: bool,
    periodic: bool, entries: int | None = None, room: ArrayLike | None = None,
) -> Bins:  # fmt: skip
    """Bin primitives to ``tile``-pixel screen tiles (each to ≤ ``span`` tiles per axis).

    The (primitive, tile) pairs are enumerated into ``entries`` slots (static; default
    ``m · span²``, always enough) and sorted by tile. A primitive wider than ``span`` tiles, or
    more pairs than ``room`` (at most ``entries``, may be traced; default ``entries``), set
    ``overflow``.
    """
    m = prims.valid.shape[0]
    gy, gx = -(-shape[0] // tile), -(-shape[1] // tile)
    first, n = _tiles_touched(prims, shape, tile, bulge, periodic)
    overflow = jnp.any(n > span)
    n = jnp.minimum(n, span)
    pairs = n[:, 0] * n[:, 1]
    end = jnp.cumsum(pairs)
    entries = m * span * span if entries is None else entries
    overflow = overflow | (end[-1] > (entries if room is None else jnp.minimum(room, entries)))
    # slot j holds pair j: primitive i with end[i-1] <= j < end[i], its (j - end[i-1])-th tile.
    # i counts the ends at or before j (searchsorted, side "right"): a cumulative sum of the ends
    # marked on the slots, the same numbers 5-8x faster on the CPU than the binary search
    j = jnp.arange(entries, dtype=jnp.int32)
    marks = jnp.zeros(entries, jnp.int32).at[end].add(1, mode="drop")
    i = jnp.minimum(jnp.cumsum(marks), m - 1).astype(jnp.int32)
    local = j - (end[i] - pairs[i])
    nx = jnp.maximum(n[i, 0], 1)
    tx, ty = first[i, 0] + local % nx, first[i, 1] + local // nx
    if periodic:
        tx, ty = jnp.mod(tx, gx), jnp.mod(ty, gy)
    empty = gy * gx
    tile_id = jnp.where(j < end[-1], ty * gx + tx, empty)
    if (empty + 1) * m < 2**31:  # one int32 key (tile, primitive): a plain sort, 5x an argsort
        by_tile = jnp.sort(tile_id * m + i) % m
    else:
        by_tile = i[jnp.argsort(tile_id, stable=True)]
    count = jnp.bincount(tile_id, length=empty + 1)[:-1].astype(jnp.int32)
    start = (jnp.cumsum(count) - count).astype(jnp.int32)
    return Bins(by_tile, start, count, overflow)


def _fragments(prims: Primitives, q, periodic, bulge):
    """Fragment values ``(P, K)`` of pixels ``q`` (P, 2) against primitives with (K, ...) leaves.

    Written component by component on ``(P, K)`` arrays (no trailing axes of 2 or N_VERTICES),
    which the CPU vectorises several times better.
    """
    rx = q[:, 0, None] - prims.p0[None, :, 0]
    ry = q[:, 1, None] - prims.p0[None, :, 1]
    if periodic:
        rx, ry = rx - jnp.round(rx), ry - jnp.round(ry)
    dx, dy = prims.delta[:, 0], prims.delta[:, 1]
    len2 = dx * dx + dy * dy
    safe_len2 = jnp.where(len2 > 0, len2, 1.0)
    t = jnp.clip((rx * dx + ry * dy) / safe_len2, 0.0, 1.0)
    # perturbed centre line: offset interpolated between the vertices, along the normal
    # (linear interpolation as a sum of hat functions: no gather, which is slow on CPU)
    u = t * (N_VERTICES - 1)
    offset = sum(
        jnp.maximum(1.0 - jnp.abs(u - j), 0.0) * prims.offsets[:, j] for j in range(N_VERTICES)
    )
    inv_len = jax.lax.rsqrt(safe_len2)
    px = rx - t * dx + offset * dy * inv_len
    py = ry - t * dy - offset * dx * inv_len
    # pore skew: distances along the primary orientation shrink by the stretch factor
    ax, ay = prims.axis[:, 0], prims.axis[:, 1]
    along = (px * ax + py * ay) / prims.stretch
    across = px * ay - py * ax
    width = jnp.where(prims.valid, prims.width, 1.0)
    x = jnp.sqrt(along * along + across * across + 1e-14) / width
    covered = prims.valid & (x < _extent(bulge))
    # cushioning: a fraction of the pore strength, falling off smoothly to zero at the middle
    fall = 1.0 - _smoothstep(jnp.minimum(t, 0.5) * 2.0)
    fall_end = 1.0 - _smoothstep(jnp.minimum(1.0 - t, 0.5) * 2.0)
    strength = prims.strength + prims.cushion[:, 0] * fall + prims.cushion[:, 1] * fall_end
    return strength * shape_function(x, bulge=bulge), covered


def _smoothstep(x):
    return x * x * (3.0 - 2.0 * x)


class _Acc(NamedTuple):
    """Running Eq. 10 sums of one pixel batch: per side (valley, bulge) the maximum ``m``, the sum
    ``Σ exp(β (x_i − m))`` over the fragments on that side and their count; ``n`` covered in all
    (a fragment on the other side adds ``x_i = 0``)."""

    m_valley: Array
    s_valley: Array
    n_valley: Array
    m_bulge: Array
    s_bulge: Array
    n_bulge: Array
    n: Array


def _accumulate(acc: _Acc, s, covered, beta):
    valley = covered & (s < 0)
    bulge = covered & (s > 0)
    mv = jnp.maximum(acc.m_valley, jnp.max(jnp.where(valley, -s, 0.0), -1))
    mb = jnp.maximum(acc.m_bulge, jnp.max(jnp.where(bulge, s, 0.0), -1))
    # one exponential per fragment: each lies on one side (Eq. 11)
    e = jnp.exp(beta * (jnp.abs(s) - jnp.where(s < 0, mv[:, None], mb[:, None])))
    sv = acc.s_valley * jnp.exp(beta * (acc.m_valley - mv)) + jnp.sum(jnp.where(valley, e, 0), -1)
    sb = acc.s_bulge * jnp.exp(beta * (acc.m_bulge - mb)) + jnp.sum(jnp.where(bulge, e, 0), -1)

    def count(mask):
        return jnp.sum(mask, -1).astype(jnp.float32)

    return _Acc(mv, sv, acc.n_valley + count(valley), mb, sb, acc.n_bulge + count(bulge),
                acc.n + count(covered))  # fmt: skip


def _blend(acc: _Acc, beta, n_hat):
    """Eq. 11: mellowmax of the bulges minus mellowmax of the valleys (Eq. 10 each)."""

    def side(m, total, n_side):  # the other side's fragments count as zeros
        return _mm_finish(m, total + (acc.n - n_side) * jnp.exp(-beta * m), acc.n, beta, n_hat)

    return side(acc.m_bulge, acc.s_bulge, acc.n_bulge) - side(
        acc.m_valley, acc.s_valley, acc.n_valley
    )


class _Tiling(NamedTuple):
    """Settings of :func:`_render_tiles` (see :class:`DrawOptions`); β and N̂ are None where
    they are passed as arrays."""

    shape: tuple[int, int]
    tile: int
    capacity: int
    passes: int | None
    bulge: bool
    periodic: bool
    beta: float
    n_hat: int


def _render_tiles(
    prims, bins, tile_ids, shape, *, tile, capacity, passes, bulge, periodic, beta, n_hat
):
    """Blended displacement (Eq. 11) of the given tiles, ``(len(tile_ids), tile, tile)``.

    The tiles go in batches (about 1 Mi fragments a pass), and a batch takes the passes its
    fullest tile needs (at most ``passes``, None: no bound). Reverse-differentiable in the
    primitives by a gradient of its own (:func:`_tiles_backward`), which costs the passes
    drawn.
    """
    n = tile_ids.shape[0]
    batches = -(-n // max(1, (1 << 20) // (tile * tile * capacity)))
    size = -(-n // batches)  # even batches: fewer than one tile a batch repeats the last tile
    padded = batches * size
    ids = jnp.concatenate([tile_ids, jnp.broadcast_to(tile_ids[-1:], (padded - n,))])
    ids = ids.reshape(-1, size)
    static = _Tiling(tuple(shape), tile, capacity, passes, bulge, periodic, None, None)
    # β and N̂ are arrays in ``draw`` (traced: one compile for all)
    blended = _tiles_vjp(static, (beta, n_hat), prims._replace(valid=None), prims.valid, bins, ids)
    return blended.reshape(padded, tile, tile)[:n]


def _tile_pixels(cfg: _Tiling, tid):
    """UV centres ``(tile², 2)`` of the pixels of tile ``tid``."""
    gx = -(-cfg.shape[1] // cfg.tile)
    h, w = cfg.shape
    offs = jnp.arange(cfg.tile, dtype=jnp.float32)
    ys = ((tid // gx * cfg.tile).astype(jnp.float32) + offs + 0.5) / h
    xs = ((tid % gx * cfg.tile).astype(jnp.float32) + offs + 0.5) / w
    return jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)


def _batch(cfg: _Tiling, bins, tids):
    """Pixel centres ``(tiles, tile², 2)``, primitive counts and bin starts of tiles ``tids``."""
    return jax.vmap(lambda t: _tile_pixels(cfg, t))(tids), bins.count[tids], bins.start[tids]


def _pass_chunk(cfg: _Tiling, prims, bins, count, start, c):
    """The primitives ``c·capacity…`` of one tile (slots past its count invalid) and their
    indices."""
    slot = c * cfg.capacity + jnp.arange(cfg.capacity, dtype=jnp.int32)
    idx = bins.order[jnp.minimum(start + slot, bins.order.shape[0] - 1)]
    chunk = jax.tree.map(lambda a: a[idx], prims)
    return chunk._replace(valid=chunk.valid & (slot < count)), idx


def _over_passes(cfg: _Tiling, count, body, init):
    """``body(c, carry)`` for the passes ``c`` that a batch of tiles holding ``count``
    primitives needs (at most ``cfg.passes``)."""
    need = jnp.max(count)
    if cfg.passes is not None:
        need = jnp.minimum(need, cfg.passes * cfg.capacity)
    _, out = lax.while_loop(
        lambda st: st[0] * cfg.capacity < need,
        lambda st: (st[0] + 1, body(*st)),
        (jnp.int32(0), init),
    )
    return out


def _accumulated(cfg: _Tiling, prims, bins, tids) -> _Acc:
    """Eq. 10 sums of a batch of tiles over all their fragments."""
    q, count, start = _batch(cfg, bins, tids)

    def one_pass(acc, q, count, start, c):
        chunk, _ = _pass_chunk(cfg, prims, bins, count, start, c)
        s, covered = _fragments(chunk, q, cfg.periodic, cfg.bulge)
        return _accumulate(acc, s, covered, cfg.beta)

    def drawn(c, acc):  # pass c of every tile of the batch
        return jax.vmap(one_pass, (0, 0, 0, 0, None))(acc, q, count, start, c)

    init = _Acc(*[jnp.zeros((tids.shape[0], cfg.tile**2), jnp.float32)] * 7)
    return _over_passes(cfg, count, drawn, init)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _tiles_vjp(static: _Tiling, blend, floats, valid, bins, ids):
    """Blended tiles of the batches ``ids``; ``static``: the settings but β and N̂, which are
    ``blend``; ``floats``: the primitives without ``valid``."""
    return _tiles_forward(static, blend, floats, valid, bins, ids)[0]


def _joined(static: _Tiling, blend, floats, valid):
    """The settings and primitives that :func:`_tiles_vjp` takes apart."""
    return static._replace(beta=blend[0], n_hat=blend[1]), floats._replace(valid=valid)


def _tiles_forward(static: _Tiling, blend, floats, valid, bins, ids):
    cfg, prims = _joined(static, blend, floats, valid)
    acc = lax.map(lambda t: _accumulated(cfg, prims, bins, t), ids)
    return _blend(acc, *blend), (blend, floats, valid, bins, ids, acc)


def _tiles_backward(static: _Tiling, residuals, g):
    """The gradient of the blend in the primitives, pass by pass: Eq. 10 is a log-sum-exp per
    side, so a fragment's share of its pixel's gradient is its softmax weight on its side (its
    running maximum cancels). Each pass recomputes its fragments and keeps only their
    primitives' gradients."""
    blend, floats, valid, bins, ids, accs = residuals
    cfg, prims = _joined(static, blend, floats, valid)
    beta = cfg.beta

    def batch(total, xs):
        tids, acc, g = xs
        g = g.reshape(tids.shape[0], -1)
        n_hat = jnp.maximum(jnp.asarray(cfg.n_hat, jnp.float32), acc.n)

        def weight(m, s_side, n_side):  # g over Eq. 10's sum (its zeros and padding too)
            return g / (s_side + (n_hat - n_side) * jnp.exp(-beta * m))

        w_b = weight(acc.m_bulge, acc.s_bulge, acc.n_bulge)
        w_v = weight(acc.m_valley, acc.s_valley, acc.n_valley)
        q, count, start = _batch(cfg, bins, tids)

        def one_tile(q, count, start, w_b, w_v, m_b, m_v, c):
            chunk, idx = _pass_chunk(cfg, prims, bins, count, start, c)

            def frag(fl):
                return _fragments(fl._replace(valid=chunk.valid), q, cfg.periodic, cfg.bulge)

            s, vjp, covered = jax.vjp(frag, chunk._replace(valid=None), has_aux=True)
            # the softmax weights: exponents ≤ 0 on each fragment's own side
            bulge = jnp.exp(beta * (s - m_b[:, None])) * w_b[:, None]
            valley = jnp.exp(beta * (-s - m_v[:, None])) * w_v[:, None]
            ds = jnp.where(covered & (s > 0), bulge, jnp.where(covered & (s < 0), valley, 0.0))
            return vjp(ds)[0], idx

        def one_pass(c, total):
            cts, idx = jax.vmap(one_tile, (0, 0, 0, 0, 0, 0, 0, None))(
                q, count, start, w_b, w_v, acc.m_bulge, acc.m_valley, c
            )
            flat = idx.reshape(-1)
            return jax.tree.map(
                lambda t, d: t.at[flat].add(d.reshape(-1, *d.shape[2:])), total, cts
            )

        return _over_passes(cfg, count, one_pass, total), None

    zero = jax.tree.map(jnp.zeros_like, floats)
    total, _ = lax.scan(batch, zero, (ids, accs, g))
    return None, total, None, None, None


_tiles_vjp.defvjp(_tiles_forward, _tiles_backward)


def _pixel_uv(shape, rows):
    h, w = shape
    y = (rows.astype(jnp.float32) + 0.5) / h
    x = (jnp.arange(w, dtype=jnp.float32) + 0.5) / w
    return jnp.stack(jnp.meshgrid(x, y, indexing="xy"), -1)


def _finish(key, blended, params, uv, periodic):
    """Additive Perlin noise (α_fnoise, α_snoise) of one level."""
    freq = at(params.fnoise, uv, periodic=periodic)
    if periodic:
        freq = jnp.maximum(jnp.round(freq), 1.0)
    period = jnp.round(freq).astype(jnp.int32) if periodic else jnp.int32(0)
    noise = _noise(key, uv, freq, period)
    # α_scale is already in the primitives' strengths (applied before the blend, §3.1.2)
    return blended + at(params.snoise, uv, periodic=periodic) * noise


def _noise(key, uv, freq, period):
    seeds = jax.random.bits(key, (2,), dtype=jnp.uint32)
    total = _octave(uv, freq, seeds[0], period) + 0.5 * _octave(uv, 2 * freq, seeds[1], 2 * period)
    return total / 1.5


class DrawOptions(NamedTuple):
    """Static settings of the rasteriser (see :func:`draw`)."""

    bulge: bool = True
    tile: int | None = None
    capacity: int = 16
    span: int | None = None
    passes: int | None = None
    beta: float = BETA
    n_hat: int = N_HAT
    entries: int | None = None


def _check_draw(key, graph, weights, params, shape, opts: DrawOptions):
    key = _checks.key(key)
    if not isinstance(graph, PoreGraph):
        raise TypeError(f"graph must be a PoreGraph, got {_checks.describe(graph)}")
    if not isinstance(params, WrinkleParams):
        raise TypeError(f"params must be WrinkleParams, got {_checks.describe(params)}")
    if graph.positions.ndim != 2:
        raise ValueError(
            f"draw takes one graph (vmap for a batch), got positions {graph.positions.shape}"
        )
    n_edges = graph.edge_mask.shape[-1]
    w = _checks.float_array(weights, "weights", ndim=1, dtype=jnp.float32)
    if w.shape[0] != n_edges:
        raise ValueError(f"weights must have shape ({n_edges},), got {_checks.describe(w)}")
    if not _checks.is_traced(w) and bool(np.any((np.asarray(w) < 0) | (np.asarray(w) > 1))):
        raise ValueError("weights must lie in [0, 1]")
    if not (isinstance(shape, tuple | list) and len(shape) == 2):
        raise TypeError(f"shape must be a pair (H, W), got {_checks.describe(shape)}")
    shape = (
        _checks.integer(shape[0], "shape[0]", low=1, high=_MAX_SIDE),
        _checks.integer(shape[1], "shape[1]", low=1, high=_MAX_SIDE),
    )
    if opts.tile is None:  # periodic binning wraps by whole tiles: the tile must divide the map
        # above 4096 px the tile grows with the map, so that a primitive still touches only a
        # few tiles: the bins (primitives × span²) would otherwise grow like the map itself
        top = _TILE << max(0, (max(shape) // 4096).bit_length() - 1)
        side = math.gcd(*shape) if graph.periodic else top
        tile = max(t for t in range(1, top + 1) if side % t == 0)
    else:
        tile = _checks.integer(opts.tile, "tile", low=1, high=1024)
    if graph.periodic and (shape[0] % tile or shape[1] % tile):
        raise ValueError(f"tile must divide both sides of a periodic map {shape}, got {tile}")
    capacity = _checks.integer(opts.capacity, "capacity", low=1, high=4096)
    for name in ("span", "passes"):
        if getattr(opts, name) is not None:
            _checks.integer(getattr(opts, name), name, low=1, high=4096)
    _checks.real(opts.beta, "beta", low=0.0, open_low=True)
    _checks.integer(opts.n_hat, "n_hat", low=1)
    return key, w, shape, opts._replace(tile=tile, capacity=capacity)


def draw(
    key: jax.Array,
    graph: PoreGraph,
    weights: ArrayLike,
    params: WrinkleParams,
    shape: tuple[int, int],
    *,
    bulge: bool = True,
    tile: int | None = None,
    capacity: int = 16,
    span: int | None = None,
    passes: int | None = None,
    beta: float = BETA,
    n_hat: int = N_HAT,
) -> Float[Array, "H W"]:
    """One level's displacement map: wrinkles, pores and perturbation (§3.2, Eq. 9–13).

    Wrinkles are bands between their pores with valley half-width ``W · α_wrinkle-width · α_d``
    and depth ``W`` shaped by Eq. 9; pores have strength ``w_v`` (Eq. 12–13), radius
    ``w_v · α_pore-width · α_d``, are stretched along α_θ by ``1 + 2 α_skew`` and pass
    ``α_cushion · w_v`` back onto their wrinkles (falling off to zero at the wrinkle's middle);
    the centre lines are perturbed by Perlin noise (α_fperturb, α_sperturb); fragments blend with
    the modified mellowmax (Eq. 10–11); additive Perlin noise (α_fnoise, α_snoise) and the global
    α_scale finish the level. Parameters may be textures (looked up at edge midpoints, pores or
    pixels). Valleys are negative.

    Pure and jit-able for static ``shape`` and options; ``vmap``-able over a batch of
    ``(key, graph, weights, params)`` with the graphs' static capacities equal; differentiable
    with respect to the continuous drawing fields (graph and weights fixed).

    Args:
        key: a ``jax.random.key`` (perturbation and additive noise).
        graph: the level's pore graph (:func:`build_graph`).
        weights: ``(E,)`` edge weights ``W`` in ``[0, 1]`` (:func:`simulate`).
        params: the level's :class:`WrinkleParams`.
        shape: ``(H, W)`` of the map covering the unit square (static).
        bulge: Eq. 9's "ours, bulge" profile (True) or "ours, no bulge" (the paper's finest level).
        tile: screen-tile side in pixels (static; performance only). Default 16 (32 from
            8192 px, 64 from 16384 px, ...), or for a periodic graph the largest divisor of both
            sides up to that (periodic maps need one).
        capacity: primitives evaluated per tile and pass (static; performance only).
        span: most tiles per axis a primitive's bounding box may touch (static).
        passes: passes per tile, so a tile holds up to ``passes · capacity`` primitives (static).
            ``span`` and ``passes`` default to the exact need when the inputs are concrete, else
            (under jit/vmap) to values that always suffice but evaluate every primitive in every
            tile: pass them (e.g. measured on one concrete agent) for speed. Exceeding either
            raises an error (at run time under jit) rather than drawing a wrong map.
        beta, n_hat: β and N̂_f of Eq. 10.

    Returns:
        ``(H, W)`` float32 displacement.

    Raises:
        TypeError/ValueError: wrong types, sizes ≤ 0 or above 65536, weights outside [0, 1], a
            tile that does not divide a periodic map; for concrete inputs, a ``span`` or
            ``passes`` too small (under jit: an error when the program runs).
    """
    opts = DrawOptions(bulge, tile, capacity, span, passes, beta, n_hat)
    key, w, shape, opts = _check_draw(key, graph, weights, params, shape, opts)
    k_perturb, k_noise = jax.random.split(key)
    prims = primitives(k_perturb, graph, w, params, shape)
    opts = _static_sizes(prims, shape, opts, graph.periodic)
    return _draw(k_noise, prims, params, shape, opts, graph.periodic)


def _static_sizes(prims, shape, opts: DrawOptions, periodic: bool) -> DrawOptions:
    """Fill in ``span`` and ``passes``: exact for concrete primitives, else always sufficient."""
    concrete = not any(_checks.is_traced(x) for x in jax.tree.leaves(prims))
    span, passes = opts.span, opts.passes
    if concrete:  # a span too small is found here, before anything is compiled
        need = needed_span(prims, shape, tile=opts.tile, bulge=opts.bulge, periodic=periodic)
        if span is not None and span < need:
            raise ValueError(
                f"a wrinkle or pore touches {need} tiles per axis, more than span={span}; pass "
                "a larger span (or a larger tile) to draw"
            )
        span = need if span is None else span
    elif span is None:
        span = max(-(-shape[0] // opts.tile), -(-shape[1] // opts.tile))
    entries = None
    if concrete:  # sort only the pairs that exist (a power of two: few distinct compilations)
        need = needed_entries(prims, shape, tile=opts.tile, bulge=opts.bulge, periodic=periodic)
        entries = 1 << max(need - 1, 1).bit_length()
    if passes is None:
        passes = -(-prims.valid.shape[0] // opts.capacity)
        if concrete:
            bins = _bin(prims, shape, opts._replace(span=span, entries=entries), periodic)
            passes = max(1, -(-int(jnp.max(bins.count)) // opts.capacity))
    # β and N̂ as arrays: traced, so that they do not each compile the rasteriser anew
    return opts._replace(span=span, passes=passes, entries=entries, beta=jnp.float32(opts.beta),
                         n_hat=jnp.float32(opts.n_hat))  # fmt: skip


@eqx.filter_jit
def _bin(prims, shape, opts: DrawOptions, periodic):
    return bin_primitives(
        prims, shape, tile=opts.tile, span=opts.span, bulge=opts.bulge, periodic=periodic,
        entries=opts.entries,
    )  # fmt: skip


def _tile_rows(key, prims, bins, params, shape, opts, periodic, first, n):
    """Finished rows of ``n`` tile rows from tile row ``first`` (rows past the map repeat the
    last tile row): ``(n · tile, W)``."""
    tile = opts.tile
    gy, gx = -(-shape[0] // tile), -(-shape[1] // tile)
    ty = jnp.minimum(first + jnp.arange(n, dtype=jnp.int32), gy - 1)
    tile_ids = (ty[:, None] * gx + jnp.arange(gx, dtype=jnp.int32)[None]).reshape(-1)
    tiles = _render_tiles(
        prims, bins, tile_ids, shape, tile=tile, capacity=opts.capacity, passes=opts.passes,
        bulge=opts.bulge, periodic=periodic, beta=opts.beta, n_hat=opts.n_hat,
    )  # fmt: skip
    band = tiles.reshape(n, gx, tile, tile).transpose(0, 2, 1, 3).reshape(n * tile, gx * tile)
    rows = first * tile + jnp.arange(n * tile, dtype=jnp.int32)
    return _finish(key, band[:, : shape[1]], params, _pixel_uv(shape, rows), periodic)


def _draw(key, prims, params, shape, opts, periodic):
    """The map, checked: under a transformation (jit, vmap, grad) an error at run time, else
    raised here (concrete inputs draw with a program that holds no host callback, which JAX's
    persistent compilation cache would not keep: a rerun of ``wrinkles render`` then compiles
    no drawing)."""
    out, overflow, crowded = _draw_flagged(key, prims, params, shape, opts, periodic)
    errors = (
        (overflow, f"a wrinkle or pore touches more than span={opts.span} tiles per axis; pass a "
                   "larger span (or a larger tile) to draw"),
        (crowded, f"a tile holds more than passes·capacity={opts.passes * opts.capacity} "
                  "wrinkles and pores; pass larger passes or capacity (or a smaller tile) to draw"),
    )  # fmt: skip
    for flag, message in errors:
        if _checks.is_traced(out):
            out = eqx.error_if(out, flag, message)
        elif bool(flag):
            raise ValueError(message)
    return out


@eqx.filter_jit
def _draw_flagged(key, prims, params, shape, opts, periodic):
    """The map, whether some primitive overflowed the bins and whether a tile held more than the
    passes draw."""
    bins = _bin(prims, shape, opts, periodic)
    out = render(key, prims, bins, params, shape, opts, periodic)
    return out, bins.overflow, jnp.max(bins.count) > opts.passes * opts.capacity


def render(key, prims, bins, params, shape, opts: DrawOptions, periodic) -> Float[Array, "H W"]:
    """The finished map of binned primitives (no checks; ``opts.passes=None``: each tile batch
    takes as many passes as its fullest tile needs, without a bound)."""
    gy = -(-shape[0] // opts.tile)
    return _tile_rows(key, prims, bins, params, shape, opts, periodic, 0, gy)[: shape[0]]


_band_rows = eqx.filter_jit(_tile_rows)


def default_band(shape: tuple[int, int]) -> int:
    """Rows per band of :func:`draw_bands`: about 8 Mi pixels (32 MiB of float32) per band."""
    return max(32, min(shape[0], (1 << 23) // max(shape[1], 1)) // 32 * 32)


def draw_bands(
    key: jax.Array,
    graph: PoreGraph,
    weights: ArrayLike,
    params: WrinkleParams,
    shape: tuple[int, int],
    *,
    band: int | None = None,
    bulge: bool = True,
    tile: int | None = None,
    capacity: int = 16,
    beta: float = BETA,
    n_hat: int = N_HAT,
) -> Iterator[tuple[int, Float[Array, "b W"]]]:
    """:func:`draw` in horizontal bands, top to bottom, for maps larger than memory (16k²).

    The primitives are made and binned to screen tiles once; each band then renders only its
    own tiles, so no more than one band (plus the primitives and their bins) is held at a time.
    The bands joined are :func:`draw`'s map with the same arguments (a band is the same
    computation on a subset of the tiles).

    Args:
        key, graph, weights, params, shape, bulge, tile, capacity, beta, n_hat: as :func:`draw`
            (concrete values; not for use under ``jit``/``vmap``).
        band: rows per band, rounded up to a multiple of the tile (default
            about 32 MiB of float32 per band).

    Yields:
        ``(first_row, rows)`` with ``rows`` of shape ``(b, W)``; the last band may be shorter.

    Raises:
        As :func:`draw`, and ValueError for a band < 1.
    """
    opts = DrawOptions(bulge, tile, capacity, None, None, beta, n_hat)
    key, w, shape, opts = _check_draw(key, graph, weights, params, shape, opts)
    band = default_band(shape) if band is None else _checks.integer(band, "band", low=1)
    if _checks.is_traced(w) or any(_checks.is_traced(x) for x in jax.tree.leaves(params)):
        raise TypeError("draw_bands takes concrete inputs (it is not for use under jit/vmap)")
    return _bands(key, graph, w, params, shape, opts, band)


def _bands(key, graph, weights, params, shape, opts, band):
    k_perturb, k_noise = jax.random.split(key)
    prims = primitives(k_perturb, graph, weights, params, shape)
    opts = _static_sizes(prims, shape, opts, graph.periodic)
    bins = _bin(prims, shape, opts, graph.periodic)
    n = -(-min(band, shape[0]) // opts.tile)  # tile rows per band
    for first in range(0, -(-shape[0] // opts.tile), n):
        at_row = jnp.asarray(first, jnp.int32)  # traced: one compilation for every band
        rows = _band_rows(k_noise, prims, bins, params, shape, opts, graph.periodic, at_row, n)
        start = first * opts.tile
        yield start, rows[: shape[0] - start]
