"""Trail-formation simulation of the edge weights (§3.1.2, Eq. 1–8 of Weiss et al. 2023).

Per step, ``N`` pores are drawn uniformly at random; each samples one of its half-edges ``h``
with probability proportional to

    max(0, d_h^(−α_dist) · (p_cont + (1 − α_cont) p_pref − α_cross p_cross))        (Eq. 3)

(Eq. 4–6: continuation reward/similarity penalty against the pore's other edges, the orientation
sampler of Eq. 1–2, and the summed weight of the crossing edges) and deposits
``W ← W + Δt α_deposit (1 − W)`` on the chosen edge (Eq. 7). All ``N`` choices of a step see the
same weights (they run in parallel, as in the paper's CUDA kernel); when ``m`` of them hit one edge
the deposit compounds exactly: ``W ← 1 − (1 − W)(1 − Δt α_deposit)^m``. Then the global decay
``W ← W (1 − Δt α_decay N / |E|)`` (Eq. 8) is applied. The whole run is one ``lax.scan``.

``P[θ]`` of Eq. 1 enters Eq. 3 as ``p_pref`` as printed, ``α_s + exp(−|θ − α_θ|²_π / σ²)``
(:func:`orientation_weight`; its normalised form, :func:`orientation_density`, is that divided by
``2π α_s + 2σ√π erf(π / 2σ)``, a factor of 1.06 at α_s = 0 to 7.35 at α_s = 1 against the
other terms). Where the paper is silent: ``d_h^(−α_dist)`` is evaluated as
``(d_h / min_h' d_h')^(−α_dist)``,
which leaves the distribution unchanged (a positive factor per pore) and avoids overflow for tiny
UV lengths.
Parameter textures are looked up at the pore for the node terms and at the edge midpoint for
``deposit``, ``decay`` and ``dt``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float
from tqdm import tqdm

from jface import _checks
from jface.noise import counter_bits, counter_uniform
from jface.wrinkles._graph import PoreGraph, _trim
from jface.wrinkles._params import WrinkleParams
from jface.wrinkles._textures import at

#: Default number of pores sampled per step (the paper's N).
N_SAMPLES = 50_000


def angle_distance(a: ArrayLike, b: ArrayLike, period: float) -> Array:
    """``|a − b|`` with wrap-around at ``period`` (Eq. 2: ``period = π``; Eq. 4: ``2π``)."""
    half = 0.5 * period
    a, b = jnp.asarray(a), jnp.asarray(b, dtype=jnp.result_type(a))
    return jnp.abs(jnp.mod(a - b + half, period) - half)


def orientation_weight(angle: ArrayLike, theta: ArrayLike, s: ArrayLike, sigma: ArrayLike) -> Array:
    """The orientation sampler of Eq. 1 as printed, ``α_s + exp(−|θ − α_θ|²_π / σ²)``: the
    ``p_pref`` of Eq. 3 (5). Undirected (``P[θ] = P[θ + π]``)."""
    d = angle_distance(angle, theta, math.pi)
    return s + jnp.exp(-(d * d) / (sigma * sigma))


def orientation_density(
    angle: ArrayLike, theta: ArrayLike, s: ArrayLike, sigma: ArrayLike
) -> Array:
    """:func:`orientation_weight` normalised to a probability density over ``[0, 2π)`` (divided
    by ``2π α_s + 2σ√π erf(π / 2σ)``); undirected."""
    z = 2.0 * math.pi * s + 2.0 * sigma * math.sqrt(math.pi) * jax.scipy.special.erf(
        math.pi / (2.0 * sigma)
    )
    return orientation_weight(angle, theta, s, sigma) / z


def _gauss(x, sigma):
    return jnp.exp(-(x * x) / (2.0 * sigma * sigma)) / (sigma * math.sqrt(2.0 * math.pi))


def continuation_kernel(
    graph: PoreGraph, params: WrinkleParams, nodes: ArrayLike
) -> Float[Array, "N D D"]:
    """The weights of Eq. 4 for the half-edge pairs of ``nodes``:
    ``K[h, h'] = α_cont N(|θ_h − (θ_h' + π)|_2π) − α_sim N(|θ_h − θ_h'|_2π)``, zero on the
    diagonal and on empty slots, so that ``p_cont = K @ W_h'``."""
    pos = graph.positions[nodes]
    per = graph.periodic
    cont = at(params.cont, pos, periodic=per)[:, None, None]
    sim = at(params.sim, pos, periodic=per)[:, None, None]
    sigma_c = at(params.sigma_cont, pos, periodic=per)[:, None, None]
    hm = graph.half_mask[nodes]
    th = graph.half_angle[nodes]
    same = angle_distance(th[:, :, None], th[:, None, :], 2.0 * math.pi)  # in [0, π]
    kern = cont * _gauss(math.pi - same, sigma_c) - sim * _gauss(same, sigma_c)
    d = hm.shape[-1]
    return jnp.where(~jnp.eye(d, dtype=bool) & hm[:, None, :] & hm[:, :, None], kern, 0.0)


def half_edge_scores(
    graph: PoreGraph,
    params: WrinkleParams,
    weights: ArrayLike,
    nodes: ArrayLike,
    kernel: ArrayLike | None = None,
) -> Float[Array, "N D"]:
    """Unnormalised probabilities of Eq. 3 for the half-edges of ``nodes`` (N,) given edge
    ``weights`` (E,); zero on empty slots. ``kernel``: optionally :func:`continuation_kernel` of
    all pores, reshaped to ``(n, D·D)``."""
    terms = _static_terms(graph, params, nodes)
    if kernel is not None:  # rows of a per-pore table (n, D·D): 2-D gathers are much faster on CPU
        kernel = kernel[nodes].reshape(*terms.mask.shape, terms.mask.shape[-1])
    return _scores(graph, params, terms, weights, nodes, kernel)


class _Terms(NamedTuple):
    """The weight-independent parts of Eq. 3 for a set of pores (fixed over a simulation)."""

    mask: Array  # (N, D) valid half-edges
    edge: Array  # (N, D) edge index of each half-edge
    cont: Array  # (N, 1) α_cont
    sim: Array  # (N, 1) α_sim
    cross: Array  # (N, 1) α_cross
    pref: Array  # (N, D) d_h^(−α_dist) (1 − α_cont) p_pref (Eq. 3, 5)
    dist: Array  # (N, D) d_h^(−α_dist)


def _static_terms(graph: PoreGraph, params: WrinkleParams, nodes) -> _Terms:
    pos = graph.positions[nodes]
    per = graph.periodic

    def node(v):
        return at(v, pos, periodic=per)[:, None]

    theta, s, sigma = node(params.theta), node(params.s), node(params.sigma)
    dist, cont = node(params.dist), node(params.cont)
    hm = graph.half_mask[nodes]
    hl = graph.half_length[nodes]
    # Eq. 5: the orientation sampler as printed (not normalised: its balance against the
    # continuation and crossing terms is the paper's)
    p_pref = orientation_weight(graph.half_angle[nodes], theta, s, sigma)
    ref = jnp.min(jnp.where(hm, hl, jnp.inf), axis=-1, keepdims=True)
    ratio = jnp.where(hm, hl / jnp.where(jnp.isfinite(ref), ref, 1.0), 1.0)
    dist_factor = jnp.exp(-dist * jnp.log(jnp.maximum(ratio, 1e-12)))
    return _Terms(
        mask=hm,
        edge=graph.half_edge[nodes],
        cont=cont,
        sim=node(params.sim),
        cross=node(params.cross),
        pref=dist_factor * (1.0 - cont) * p_pref,
        dist=dist_factor,
    )


def _scores(graph: PoreGraph, params, terms: _Terms, weights, nodes, kernel, per_edge=False):
    """Eq. 3 from the fixed terms and the current weights. ``kernel``: ``(N, D, D)`` rows of Eq.
    4's kernel (None: computed here); ``per_edge``: sum the crossing weights once per edge rather
    than per half-edge (cheaper when every pore is scored)."""
    hm, he = terms.mask, terms.edge
    w = jnp.where(hm, weights[he], 0.0)

    def continuation():  # Eq. 4: reward the opposite direction, penalise similar directions
        kern = continuation_kernel(graph, params, nodes) if kernel is None else kernel
        # a sum over the D columns, not an einsum: (N, D) products vectorise better on CPU
        return sum(kern[:, :, k] * w[:, None, k] for k in range(kern.shape[-1]))

    def crossing():  # Eq. 6: summed weight of the crossing edges
        if per_edge:
            cw = jnp.where(graph.crossing_mask, weights[graph.crossings], 0.0)
            return jnp.sum(cw, axis=-1)[he]
        flat = he.reshape(-1)  # 2-D row gathers are much faster than 3-D ones on CPU
        cw = jnp.where(graph.crossing_mask[flat], weights[graph.crossings[flat]], 0.0)
        return jnp.sum(cw, axis=-1).reshape(he.shape)

    def zeros():
        return jnp.zeros(hm.shape, w.dtype)

    # the terms cost most; skip them when their parameters are zero everywhere
    p_cont = jax.lax.cond(jnp.any(terms.cont != 0) | jnp.any(terms.sim != 0), continuation, zeros)
    p_cross = jax.lax.cond(jnp.any(terms.cross != 0), crossing, zeros)
    # Eq. 3
    score = terms.pref + terms.dist * (p_cont - terms.cross * p_cross)
    return jnp.where(hm, jnp.maximum(score, 0.0), 0.0)


#: Decay time constants a default run lasts: the weights relax at least at the decay's rate
#: ``Δt α_decay N/|E|`` per step (Eq. 8), so after 4 time constants they are within e⁻⁴ ≈ 2 % of
#: equilibrium (measured on a 130k-edge graph: mean W within 0.5 % of a run 8× longer).
TIME_CONSTANTS = 4.0
#: Slowest decay rate ``Δt α_decay`` the default step count assumes: with less decay the weights
#: saturate through their deposits instead, and the step count stays bounded.
_MIN_RATE = 0.005
#: Steps per compiled chunk of a long run (one progress tick each).
CHUNK = 256


def samples_per_step(graph: PoreGraph) -> int | Array:
    """The paper's ``N``: 50,000 pores per step, or ``|E|`` on smaller graphs (never the array
    capacity, so a result does not depend on how large a buffer was allocated). An ``int`` for a
    concrete graph, else a traced count."""
    if _checks.is_traced(graph.edge_count):
        return jnp.minimum(N_SAMPLES, jnp.maximum(graph.edge_count, 1))
    return min(N_SAMPLES, max(int(graph.edge_count), 1))


def converged_steps(graph: PoreGraph, params: WrinkleParams, n_samples: int | None = None) -> int:
    """Steps after which the weights are converged: :data:`TIME_CONSTANTS` decay time constants
    ``|E| / (N Δt α_decay)`` (Eq. 8), at the slowest decay of the parameter textures, rounded up
    to whole :data:`CHUNK` s. Needs a concrete graph and parameters."""
    leaves = (graph.edge_count, params.dt, params.decay)
    if any(_checks.is_traced(x) for x in leaves):
        raise TypeError("converged_steps needs a concrete graph and parameters (pass n_steps)")
    count = max(int(graph.edge_count), 1)
    n = samples_per_step(graph) if n_samples is None else n_samples
    rate = max(float(np.min(np.asarray(params.dt) * np.asarray(params.decay))), _MIN_RATE)
    steps = math.ceil(TIME_CONSTANTS * count / (n * rate))
    return -(-steps // CHUNK) * CHUNK


def simulate(
    key: jax.Array,
    graph: PoreGraph,
    params: WrinkleParams,
    *,
    n_steps: int | None = None,
    n_samples: int | None = None,
    weights: ArrayLike | None = None,
    progress: bool = False,
) -> Float[Array, " E"]:
    """Run the trail-formation simulation and return the edge weights ``W``.

    Implements Eq. 1–8 of Weiss et al. 2023 (see the module docstring). By default the run lasts
    until the weights are converged (:func:`converged_steps`), at any graph size; a fixed budget
    (``n_steps``, e.g. the paper's 50 steps of the fit) is still available. Jit- and
    vmap-friendly with ``n_steps`` given: ``jax.vmap(simulate, in_axes=(0, None, 0))(keys,
    graph, batched_params)`` runs a batch of parameter sets (e.g. particle-swarm agents) on one
    graph, and a vmapped graph works too.

    Args:
        key: a ``jax.random.key``; the same key gives identical weights.
        graph: the pore graph (:func:`build_graph`).
        params: one level's :class:`WrinkleParams` (scalars or textures).
        n_steps: simulation steps (static); default: converged (needs concrete inputs).
        n_samples: pores sampled per step, ``N`` (static); default the paper's 50,000, or the
            number of valid edges ``|E|`` when smaller (:func:`samples_per_step`; the same
            weights whatever the graph's capacity). ``Δt α_decay N`` must not exceed ``|E|``.
        weights: optional ``(E,)`` starting weights in [0, 1] (default zeros), e.g. to continue a
            run.
        progress: show a progress bar (default runs only, which go in chunks of :data:`CHUNK`).

    Returns:
        ``(E,)`` weights in ``[0, 1]``, zero on invalid edge slots.

    Raises:
        TypeError/ValueError: wrong types, non-positive sizes, weights of the wrong shape or out
            of [0, 1], a decay factor ``1 − Δt α_decay N/|E|`` below zero, or no ``n_steps``
            for traced inputs.
    """
    key = _checks.key(key)
    if not isinstance(graph, PoreGraph):
        raise TypeError(f"graph must be a PoreGraph, got {_checks.describe(graph)}")
    if not isinstance(params, WrinkleParams):
        raise TypeError(f"params must be WrinkleParams, got {_checks.describe(params)}")
    n_edges = graph.edge_mask.shape[-1]
    if n_steps is not None:
        n_steps = _checks.integer(n_steps, "n_steps", low=0)
    if n_samples is not None:
        n_samples = _checks.integer(n_samples, "n_samples", low=1)
    if weights is None:
        w0 = jnp.zeros(n_edges, jnp.float32)
    else:
        w0 = _checks.float_array(weights, "weights", ndim=1, dtype=jnp.float32)
        if w0.shape[0] != n_edges:
            raise ValueError(f"weights must have shape ({n_edges},), got {_checks.describe(w0)}")
        if not _checks.is_traced(w0) and bool(np.any((np.asarray(w0) < 0) | (np.asarray(w0) > 1))):
            raise ValueError("weights must lie in [0, 1]")
    leaves = (params.dt, params.decay, graph.edge_count)
    concrete = not any(_checks.is_traced(x) for x in leaves)
    if concrete:
        count = int(graph.edge_count)
        rate = float(np.max(np.asarray(params.dt))) * float(np.max(np.asarray(params.decay)))
        worst = rate * (samples_per_step(graph) if n_samples is None else n_samples)
        if count > 0 and worst > count:
            raise ValueError(
                f"n_samples={n_samples} is too large for a graph of {count} edges: the decay "
                f"factor 1 - dt·decay·N/|E| = {1 - worst / count:.3g} would be negative "
                f"(use n_samples ≤ {int(count / rate)})"
            )
    if n_steps is None:
        if not concrete or any(_checks.is_traced(x) for x in jax.tree.leaves(graph)):
            raise TypeError(
                "simulate needs n_steps under jit/vmap (the default run is sized "
                "from the concrete graph)"
            )
        n_steps = converged_steps(graph, params, n_samples)
        chunk = CHUNK
    else:  # one call, unless a progress bar is to move (chunks continue the same run)
        chunk = CHUNK if progress else max(n_steps, 1)
    # the sample array's static size: N itself when known, else the most it can be
    if n_samples is not None:
        size, active = n_samples, jnp.int32(n_samples)
    elif concrete:
        size = samples_per_step(graph)
        active = jnp.int32(size)
    else:
        size = min(N_SAMPLES, max(n_edges, 1))
        active = jnp.asarray(samples_per_step(graph), jnp.int32)
    w = jnp.where(graph.edge_mask, w0, 0.0)
    full = graph.edge_mask.shape[0]
    if not any(_checks.is_traced(x) for x in jax.tree.leaves(graph)):
        # run on the slots the data use: every step's updates cost O(edge slots)
        graph = _trim(
            graph,
            max(int(graph.node_count), 1),
            max(int(graph.edge_count), 1),
            max(int(np.max(np.sum(np.asarray(graph.half_mask), -1))), 1),
            int(np.max(np.sum(np.asarray(graph.crossing_mask), -1), initial=0)),
        )
        w = w[: graph.edge_mask.shape[0]]
    for first in tqdm(range(0, n_steps, chunk), desc="simulate", unit="chunk",
                      disable=not progress):  # fmt: skip
        steps = min(chunk, n_steps - first)
        w = _simulate(key, graph, params, w, jnp.uint32(first), active, steps, size)
    return jnp.pad(jnp.clip(w, 0.0, 1.0), (0, full - w.shape[0]))


@functools.partial(jax.jit, static_argnums=(6, 7))
def _simulate(key, graph, params, w0, first, n_active, n_steps, n_samples):
    """``n_steps`` steps from step ``first`` (so chunks continue one run); ``n_samples`` static
    sample slots of which the first ``n_active`` count (the paper's N)."""
    per = graph.periodic
    mid = graph.edge_midpoints()
    deposit = at(params.deposit, mid, periodic=per)
    decay = at(params.decay, mid, periodic=per)
    dt = at(params.dt, mid, periodic=per)
    keep = 1.0 - dt * deposit  # per hit: 1 - W is multiplied by (1 - Δt α_deposit)
    n_edges = graph.edge_mask.shape[0]
    n_valid = jnp.maximum(graph.edge_count, 1).astype(jnp.float32)
    fade = jnp.maximum(0.0, 1.0 - dt * decay * (n_active.astype(jnp.float32) / n_valid))
    active = jnp.arange(n_samples, dtype=jnp.int32) < n_active
    n_nodes, d = graph.half_mask.shape
    # Eq. 4's kernel depends only on the graph and the parameters: precompute it per pore when it
    # fits in memory (2^25 entries), else evaluate it for the sampled pores each step
    table = None
    if n_nodes * d * d <= 2**25:
        all_nodes = jnp.arange(n_nodes, dtype=jnp.int32)
        table = jax.lax.cond(
            jnp.any(params.cont != 0) | jnp.any(params.sim != 0),
            lambda: continuation_kernel(graph, params, all_nodes).reshape(n_nodes, d * d),
            lambda: jnp.zeros((n_nodes, d * d), jnp.float32),
        )

    # Eq. 3's weight-independent terms are fixed for the run: computed once per pore. When the
    # pores are fewer than the samples per step, scoring every pore once per step and gathering
    # the sampled rows is cheaper than scoring each sample (the same numbers either way)
    all_nodes = jnp.arange(n_nodes, dtype=jnp.int32)
    terms = _static_terms(graph, params, all_nodes)
    score_all = n_nodes <= n_samples
    if score_all:
        kernel = None if table is None else table.reshape(n_nodes, d, d)

    # counter-based random numbers: threefry's would be 40% of the run on the CPU
    seed = jax.random.bits(key, (), jnp.uint32)
    n_nodes_valid = jnp.maximum(graph.node_count, 1).astype(jnp.uint32)

    def step(w, t):
        # modulo bias ≤ n / 2³² (5e-4 for two million pores)
        nodes = (counter_bits(seed, 2 * t, (n_samples,)) % n_nodes_valid).astype(jnp.int32)
        # the inverse CDF of each sample's pore, one column at a time: (N,) gathers and compares
        # vectorise far better on the CPU than (N, D) rows
        if score_all:
            cum = jnp.cumsum(_scores(graph, params, terms, w, all_nodes, kernel, True), -1).T
            columns = [cum[j][nodes] for j in range(d)]
        else:
            rows = jax.tree.map(lambda a: a[nodes], terms)  # 2-D row gathers: fast on CPU
            kern = None if table is None else table[nodes].reshape(n_samples, d, d)
            cum = jnp.cumsum(_scores(graph, params, rows, w, nodes, kern), axis=-1)
            columns = [cum[:, j] for j in range(d)]
        total = columns[-1]
        u = counter_uniform(seed, 2 * t + 1, (n_samples,)) * total  # u < total when total > 0
        pick = sum((c <= u).astype(jnp.int32) for c in columns[:-1])
        edge = graph.half_edge.reshape(-1)[nodes * d + pick]  # one element, not a row, each
        edge = jnp.where((total > 0) & active, edge, n_edges)
        # Eq. 7, compounded exactly over an edge's hits: 1 - W is multiplied once per hit
        rest = (1.0 - w).at[edge].multiply(keep[edge % n_edges], mode="drop")
        w = (1.0 - rest) * fade  # Eq. 8
        return jnp.where(graph.edge_mask, w, 0.0), None

    w, _ = jax.lax.scan(step, w0, first + jnp.arange(n_steps, dtype=jnp.uint32))
    return w
