"""A whole multi-level micro-wrinkle map from parameters (§3 and §4.3 of Weiss et al. 2023)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jface import _checks
from jface.wrinkles._drawing import default_band, draw, draw_bands
from jface.wrinkles._graph import PoreGraph, build_graph
from jface.wrinkles._params import WrinkleParams
from jface.wrinkles._sampling import Pores, sample_pores
from jface.wrinkles._simulation import simulate
from jface.wrinkles._textures import lookup


class Level(eqx.Module):
    """One simulated and drawn level: its pores, graph, edge weights and displacement."""

    pores: Pores
    graph: PoreGraph
    weights: Float[Array, " E"]
    displacement: Float[Array, "H W"]


class Synthesis(eqx.Module):
    """A multi-level displacement map (the sum of the levels) and the per-level results."""

    displacement: Float[Array, "H W"]
    levels: tuple[Level, ...]


class Simulated(NamedTuple):
    """One simulated level before drawing: its pores, graph and edge weights."""

    pores: Pores
    graph: PoreGraph
    weights: Float[Array, " E"]


def _check_levels(key, levels, initial):
    key = _checks.key(key)
    if isinstance(levels, WrinkleParams):
        levels = [levels]
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("levels must be a WrinkleParams or a non-empty list of them")
    if initial is not None and not isinstance(initial, Pores):
        raise TypeError(f"initial must be Pores, got {_checks.describe(initial)}")
    return key, list(levels)


#: Margin of the simulated area around a non-periodic map, in pore distances of the coarsest
#: level: pores at the map's border then have their full neighbourhood, so the border is
#: carved like the interior (without it, border pores share their deposits among fewer edges
#: and a band of stronger wrinkles runs along the border).
MARGIN_PORES = 3.0


def _margin(levels, radius_map, periodic) -> float:
    if periodic:
        return 0.0
    reach = float(np.max(np.asarray(levels[0].d)))
    if radius_map is not None:
        reach *= float(np.max(np.asarray(radius_map)))
    return min(MARGIN_PORES * reach, 0.25)


def _texture_in_frame(texture, margin):
    """A texture over the unit square resampled over ``[−m, 1 + m]²`` (clamped beyond it)."""
    texture = jnp.asarray(texture, jnp.float32)
    if texture.ndim == 0 or margin == 0:
        return texture
    h, w = texture.shape
    ys = ((jnp.arange(h, dtype=jnp.float32) + 0.5) / h) * (1 + 2 * margin) - margin
    xs = ((jnp.arange(w, dtype=jnp.float32) + 0.5) / w) * (1 + 2 * margin) - margin
    return lookup(texture, jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), -1), periodic=False)


def _to_uv(pores: Pores, graph: PoreGraph, margin):
    """Pores and graph from the sampling frame (the unit square standing for ``[−m, 1 + m]²``)
    to map coordinates."""
    scale = 1.0 + 2.0 * margin
    pores = eqx.tree_at(
        lambda p: (p.positions, p.radius), pores,
        (jnp.where(pores.mask[:, None], pores.positions * scale - margin, 0.0),
         pores.radius * scale),
    )  # fmt: skip
    graph = eqx.tree_at(
        lambda g: (g.positions, g.half_length, g.edge_delta, g.edge_length), graph,
        (jnp.where(graph.node_mask[:, None], graph.positions * scale - margin, 0.0),
         graph.half_length * scale, graph.edge_delta * scale, graph.edge_length * scale),
    )  # fmt: skip
    return pores, graph


def _to_frame(pores: Pores, margin) -> Pores:
    scale = 1.0 + 2.0 * margin
    return eqx.tree_at(
        lambda p: (p.positions, p.radius), pores,
        (jnp.where(pores.mask[:, None], (pores.positions + margin) / scale, 0.0),
         pores.radius / scale),
    )  # fmt: skip


def simulate_levels(
    key: jax.Array,
    levels: WrinkleParams | Sequence[WrinkleParams],
    *,
    initial: Pores | None = None,
    radius_map: ArrayLike | None = None,
    periodic: bool = True,
    n_steps: int | None = None,
    n_samples: int | None = None,
    k: int = 6,
    progress: bool = False,
) -> list[Simulated]:
    """Sample, connect and simulate every level (coarse to fine), each starting from the coarser
    level's pores; the first of :func:`synthesize`'s steps.

    A non-periodic map is simulated on a larger area (a margin of :data:`MARGIN_PORES` pore
    distances of the coarsest level around the unit square) so that its border is carved like
    its interior; pores and graphs come back in map coordinates, those of the margin outside
    ``[0, 1]²``.

    Args:
        key, levels, initial, radius_map, periodic, n_steps, n_samples, progress: as
            :func:`synthesize`.
        k: nearest neighbours per pore of the graph.
    """
    key, levels = _check_levels(key, levels, initial)
    return [sim for sim, _, _ in _simulate_levels(
        key, levels, initial, radius_map, periodic, n_steps, n_samples, progress, k
    )]  # fmt: skip


def _simulate_levels(key, levels, initial, radius_map, periodic, n_steps, n_samples, progress,
                     k=6):  # fmt: skip
    """Per level (coarse to fine): the simulation, the drawing key and the bulge flag."""
    margin = _margin(levels, radius_map, periodic)
    if radius_map is not None:
        radius_map = _texture_in_frame(radius_map, margin)
    pores = None if initial is None else _to_frame(initial, margin)
    out = []
    for i, params in enumerate(levels):
        k_pores, k_sim, k_draw = jax.random.split(jax.random.fold_in(key, i), 3)
        d = _texture_in_frame(params.d, margin) / (1.0 + 2.0 * margin)
        pores = sample_pores(k_pores, d, radius_map, initial=pores, periodic=periodic)
        uv_pores, graph = _to_uv(pores, build_graph(pores, k=k), margin)
        weights = simulate(
            k_sim, graph, params, n_steps=n_steps, n_samples=n_samples, progress=progress
        )
        bulge = i < len(levels) - 1 or len(levels) == 1
        out.append((Simulated(uv_pores, graph, weights), k_draw, bulge))
    return out


def synthesize(
    key: jax.Array,
    levels: WrinkleParams | Sequence[WrinkleParams],
    shape: tuple[int, int],
    *,
    initial: Pores | None = None,
    radius_map: ArrayLike | None = None,
    periodic: bool = True,
    n_steps: int | None = None,
    n_samples: int | None = None,
    progress: bool = False,
) -> Synthesis:
    """Sample, connect, simulate and draw every level (coarse to fine) and sum the maps.

    Each level samples its pores starting from the coarser level's (``initial=``), so wrinkles of
    different levels meet at shared pores; the first level may start from pores extracted from a
    coarse scan (:func:`extract_pores`). The finest of several levels is drawn with Eq. 9's
    "no bulge" profile, the others with "bulge" (§3.2.1). Each level's additive noise and
    α_scale are part of its map.

    Args:
        key: a ``jax.random.key``; the same key gives the same map.
        levels: one :class:`WrinkleParams` per level, coarse to fine.
        shape: ``(H, W)`` of the map.
        initial: pores the first level starts from (e.g. extracted from a scan).
        radius_map: optional radius scaling map **R** (e.g. :func:`radius_map_from_mesh`).
        periodic: the map tiles (torus); False for UV atlases.
        n_steps, n_samples, progress: of :func:`simulate` (default: every level converged).

    Returns:
        :class:`Synthesis`.
    """
    key, levels = _check_levels(key, levels, initial)
    sims = _simulate_levels(
        key, levels, initial, radius_map, periodic, n_steps, n_samples, progress
    )
    return draw_simulated(key, levels, [sim for sim, _, _ in sims], shape)


def draw_simulated(
    key: jax.Array,
    levels: WrinkleParams | Sequence[WrinkleParams],
    simulated: Sequence[Simulated],
    shape: tuple[int, int],
) -> Synthesis:
    """Draw levels simulated before (:func:`simulate_levels`, or read back from a file) and sum
    them: the second of :func:`synthesize`'s steps, with the drawing keys it uses, so the same
    ``key`` gives :func:`synthesize`'s map without simulating again.

    Args:
        key: the ``jax.random.key`` the levels were simulated with.
        levels: one :class:`WrinkleParams` per level, coarse to fine.
        simulated: one :class:`Simulated` per level.
        shape: ``(H, W)`` of the map.

    Returns:
        :class:`Synthesis`.
    """
    key, levels = _check_levels(key, levels, None)
    if len(simulated) != len(levels):
        raise ValueError(f"need one simulated level per level: {len(levels)} levels, "
                         f"{len(simulated)} simulated")  # fmt: skip
    done = []
    total = None
    for i, (params, sim) in enumerate(zip(levels, simulated, strict=True)):
        k_draw = jax.random.split(jax.random.fold_in(key, i), 3)[2]  # as _simulate_levels
        bulge = i < len(levels) - 1 or len(levels) == 1
        disp = draw(k_draw, sim.graph, sim.weights, params, shape, bulge=bulge)
        done.append(Level(sim.pores, sim.graph, sim.weights, disp))
        total = disp if total is None else total + disp
    return Synthesis(jnp.asarray(total), tuple(done))


class Bands(NamedTuple):
    """A multi-level map drawn band by band (:func:`synthesize_bands`).

    Attributes:
        levels: the simulated levels.
        rows: iterator of ``(first_row, band)``, bands ``(b, W)`` top to bottom, each the sum of
            the levels' rows (iterate once).
    """

    levels: tuple[Simulated, ...]
    rows: Iterator[tuple[int, Float[Array, "b W"]]]


def synthesize_bands(
    key: jax.Array,
    levels: WrinkleParams | Sequence[WrinkleParams],
    shape: tuple[int, int],
    *,
    band: int | None = None,
    initial: Pores | None = None,
    radius_map: ArrayLike | None = None,
    periodic: bool = True,
    n_steps: int | None = None,
    n_samples: int | None = None,
    progress: bool = False,
) -> Bands:
    """:func:`synthesize` for maps larger than memory: the levels are simulated at once, then
    drawn in horizontal bands (:func:`draw_bands`), so a 16384² map never exists whole; write the
    bands as they come (:func:`jface.io.exr_rows`). The bands joined equal
    :func:`synthesize`'s displacement for the same arguments.

    Args:
        band: rows per band (default: about 32 MiB of float32 per band).
        key, levels, shape, initial, radius_map, periodic, n_steps, n_samples, progress: as
            :func:`synthesize`.

    Returns:
        :class:`Bands`.
    """
    key, levels = _check_levels(key, levels, initial)
    sims = _simulate_levels(
        key, levels, initial, radius_map, periodic, n_steps, n_samples, progress
    )
    # every level uses the same default tile (it depends on shape and periodicity only), so the
    # levels' bands cover the same rows
    band = default_band(shape) if band is None else _checks.integer(band, "band", low=1)
    streams = [
        draw_bands(k, sim.graph, sim.weights, p, shape, band=band, bulge=bulge)
        for p, (sim, k, bulge) in zip(levels, sims, strict=True)
    ]
    return Bands(tuple(sim for sim, _, _ in sims), _sum_bands(streams))


def _sum_bands(streams):
    for parts in zip(*streams, strict=True):
        yield parts[0][0], sum((rows for _, rows in parts), start=jnp.float32(0))
