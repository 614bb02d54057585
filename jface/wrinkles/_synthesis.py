"""A whole multi-level micro-wrinkle map from parameters (§3 and §4.3 of Weiss et al. 2023)."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jface import _checks
from jface.wrinkles._drawing import draw
from jface.wrinkles._graph import PoreGraph, build_graph
from jface.wrinkles._params import WrinkleParams
from jface.wrinkles._sampling import Pores, sample_pores
from jface.wrinkles._simulation import simulate


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


def synthesize(
    key: jax.Array,
    levels: WrinkleParams | Sequence[WrinkleParams],
    shape: tuple[int, int],
    *,
    initial: Pores | None = None,
    radius_map: ArrayLike | None = None,
    periodic: bool = True,
    n_steps: int = 50,
    n_samples: int | None = None,
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
        n_steps, n_samples: of :func:`simulate`.

    Returns:
        :class:`Synthesis`.
    """
    key = _checks.key(key)
    if isinstance(levels, WrinkleParams):
        levels = [levels]
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("levels must be a WrinkleParams or a non-empty list of them")
    if initial is not None and not isinstance(initial, Pores):
        raise TypeError(f"initial must be Pores, got {_checks.describe(initial)}")
    pores = initial
    done = []
    total = None
    for i, params in enumerate(levels):
        k_pores, k_sim, k_draw = jax.random.split(jax.random.fold_in(key, i), 3)
        pores = sample_pores(k_pores, params.d, radius_map, initial=pores, periodic=periodic)
        graph = build_graph(pores)
        weights = simulate(k_sim, graph, params, n_steps=n_steps, n_samples=n_samples)
        bulge = i < len(levels) - 1 or len(levels) == 1
        disp = draw(k_draw, graph, weights, params, shape, bulge=bulge)
        done.append(Level(pores, graph, weights, disp))
        total = disp if total is None else total + disp
    return Synthesis(jnp.asarray(total), tuple(done))
