"""Micro-wrinkle pipeline: pore sampling, pore graph + crossings, trail simulation.

References measured in the same run: scipy ``qmc.PoissonDisk`` (sampling, at 100k pores — it
needs ~1000 s for 1M), scipy ``cKDTree`` kNN + shapely ``STRtree`` "crosses" queries (graph and
crossing lists), and a vectorised numpy implementation of the same simulation step (edge
samples per second). jface alone at 1M pores against the goals (sampling ≤ 15 s uniform, ≤ 30 s
variable radius; graph + crossings ≤ 30 s; simulation ≥ 1e6 edge samples/s).

Run: ``python benchmarks/bench_wrinkles_sim.py [--pores 1000000] [--skip-reference-1m]``
(needs the ``bench`` extra: scipy, shapely).
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import numpy as np
from _timing import best_of, report

from jface.wrinkles import WrinkleParams, build_graph, sample_pores, simulate
from jface.wrinkles._simulation import converged_steps

DENSITY = 0.654  # maximal Poisson-disk pores per r² (measured)


def radius_for(pores: int) -> float:
    return math.sqrt(DENSITY / pores)


def timed(fn):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def as_d_and_map(radius: np.ndarray):
    """α_d (≥ 0.001, Table 1) and a radius map R with d · R = radius."""
    d = max(0.001, float(radius.min()))
    return d, (radius / d).astype(np.float32)


def bench_sampling(pores: int, reference: bool) -> None:
    r = radius_for(pores)
    d, rmap = as_d_and_map(np.full((4, 4), r))
    rmap = None if np.all(rmap == 1) else rmap
    _, first = timed(lambda: sample_pores(jax.random.key(0), d, rmap))
    ours = best_of(lambda: sample_pores(jax.random.key(1), d, rmap), repeats=2)
    count = int(sample_pores(jax.random.key(1), d, rmap).count)
    case = f"Poisson-disk sampling, uniform r={r:.5f}"
    if reference:
        from scipy.stats import qmc

        ref, theirs = timed(lambda: qmc.PoissonDisk(2, radius=r, seed=0).fill_space())
        report(case, ours, "scipy qmc.PoissonDisk", theirs, pores=count, scipy_pores=len(ref),
               compile_s=round(first - ours, 2))  # fmt: skip
    else:
        report(case, ours, pores=count, compile_s=round(first - ours, 2), goal_s=15)


def bench_variable(pores: int) -> None:
    x = (np.arange(256) + 0.5) / 256
    shape = np.broadcast_to(1.0 + x, (256, 256))  # radius doubles across u
    radius = radius_for(pores) * math.sqrt(np.mean(1.0 / shape**2)) * shape
    d, rmap = as_d_and_map(radius)
    _, first = timed(lambda: sample_pores(jax.random.key(0), d, rmap))
    ours = best_of(lambda: sample_pores(jax.random.key(1), d, rmap), repeats=2)
    count = int(sample_pores(jax.random.key(1), d, rmap).count)
    report(f"Poisson-disk sampling, radius map (r doubles across u), d={d}", ours, pores=count,
           compile_s=round(first - ours, 2), goal_s=30)  # fmt: skip


def reference_graph(x: np.ndarray, k: int):
    """scipy cKDTree symmetric kNN + shapely STRtree 'crosses' pairs."""
    import shapely
    from scipy.spatial import cKDTree

    _, nn = cKDTree(x).query(x, k + 1)
    i = np.repeat(np.arange(len(x)), k)
    j = nn[:, 1:].ravel()
    edges = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], 1), axis=0)
    lines = shapely.linestrings(np.stack([x[edges[:, 0]], x[edges[:, 1]]], 1))
    tree = shapely.STRtree(lines)
    pairs = tree.query(lines, predicate="crosses")
    return edges, pairs


def bench_graph(pores: int, reference: bool):
    d, rmap = as_d_and_map(np.full((4, 4), radius_for(pores)))
    p = sample_pores(jax.random.key(0), d, None if np.all(rmap == 1) else rmap)
    graph, first = timed(lambda: build_graph(p))
    ours = best_of(lambda: build_graph(p), repeats=2)
    n_edges = int(graph.edge_count)
    n_cross = int(np.asarray(graph.crossing_mask).sum()) // 2
    case = f"pore graph kNN k=6 + crossing lists, {int(p.count)} pores"
    if reference:
        x = np.asarray(p.positions, np.float64)[: int(p.count)]
        (edges, pairs), theirs = timed(lambda: reference_graph(x, 6))
        report(case, ours, "scipy cKDTree + shapely STRtree crosses", theirs, edges=n_edges,
               reference_edges=len(edges), crossing_pairs=n_cross,
               reference_crossing_pairs=pairs.shape[1] // 2,
               compile_s=round(first - ours, 2))  # fmt: skip
    else:
        report(case, ours, edges=n_edges, crossing_pairs=n_cross,
               compile_s=round(first - ours, 2), goal_s=30)  # fmt: skip
    return graph


def numpy_step(rng, g, w, n, params):
    """One simulation step (Eq. 3–8) in vectorised numpy: the reference for edge samples/s."""
    nodes = rng.integers(0, g["count"], n)
    he, hm, th, hl = (
        g["half_edge"][nodes],
        g["half_mask"][nodes],
        g["angle"][nodes],
        g["length"][nodes],
    )
    wh = np.where(hm, w[he], 0.0)
    diff = th[:, :, None] - th[:, None, :]

    def dist(a, period):
        return np.abs(np.mod(a + period / 2, period) - period / 2)

    def gauss(x):
        return np.exp(-(x**2) / (2 * 0.09)) / (0.3 * math.sqrt(2 * math.pi))

    kern = params["cont"] * gauss(dist(diff - math.pi, 2 * math.pi)) - params["sim"] * gauss(
        dist(diff, 2 * math.pi)
    )
    kern *= ~np.eye(hm.shape[1], dtype=bool) & hm[:, None, :]
    p_cont = np.einsum("nhk,nk->nh", kern, wh)
    dp = dist(th - params["theta"], math.pi)
    z = 2 * math.pi * params["s"] + 2 * 0.3 * math.sqrt(math.pi) * math.erf(math.pi / 0.6)
    p_pref = (params["s"] + np.exp(-(dp**2) / 0.09)) / z
    cr = g["crossings"][he]
    p_cross = np.sum(np.where(g["crossing_mask"][he], w[cr], 0.0), -1)
    ref = np.min(np.where(hm, hl, np.inf), -1, keepdims=True)
    ratio = np.where(hm, hl / np.where(np.isfinite(ref), ref, 1.0), 1.0)
    score = ratio ** (-params["dist"]) * (p_cont + (1 - params["cont"]) * p_pref
                                               - params["cross"] * p_cross)  # fmt: skip
    score = np.where(hm, np.maximum(score, 0), 0)
    cum = np.cumsum(score, -1)
    pick = np.minimum(np.sum(cum <= rng.random(n)[:, None] * cum[:, -1:], -1), hm.shape[1] - 1)
    edge = he[np.arange(n), pick][cum[:, -1] > 0]
    hits = np.bincount(edge, minlength=len(w))
    w = 1 - (1 - w) * (1 - 0.03 * params["deposit"]) ** hits
    return w * (1 - 0.03 * params["decay"] * n / g["edges"])


def bench_simulation(graph, steps: int, n: int) -> None:
    values = dict(
        theta=0.5, s=0.2, dist=1.0, cont=0.005, sim=0.5, cross=0.5, deposit=0.4, decay=0.5
    )
    params = WrinkleParams(**values)
    _, first = timed(lambda: simulate(jax.random.key(0), graph, params, n_steps=steps, n_samples=n))
    ours = best_of(
        lambda: simulate(jax.random.key(1), graph, params, n_steps=steps, n_samples=n), 2
    )
    g = {
        "count": int(graph.node_count), "edges": int(graph.edge_count),
        "half_edge": np.asarray(graph.half_edge), "half_mask": np.asarray(graph.half_mask),
        "angle": np.asarray(graph.half_angle, np.float64),
        "length": np.asarray(graph.half_length, np.float64),
        "crossings": np.asarray(graph.crossings), "crossing_mask": np.asarray(graph.crossing_mask),
    }  # fmt: skip
    rng = np.random.default_rng(0)
    w = np.zeros(graph.edge_mask.shape[0])
    ref_steps = max(1, steps // 10)
    start = time.perf_counter()
    for _ in range(ref_steps):
        w = numpy_step(rng, g, w, n, values)
    theirs = (time.perf_counter() - start) * steps / ref_steps
    report(f"trail simulation, {int(graph.edge_count)} edges, N={n}, {steps} steps, all terms on",
           ours, "numpy, same step vectorised (extrapolated from "
           f"{ref_steps} steps)", theirs, edge_samples_per_s=round(steps * n / ours),
           numpy_edge_samples_per_s=round(steps * n / theirs), compile_s=round(first - ours, 2),
           goal_edge_samples_per_s=1e6)  # fmt: skip


EDGES_PER_PORE = 3.2  # valid edges per pore of the kNN graph (k = 6, measured)


def bench_converged(edges: int) -> None:
    """The default (converged) simulation on a graph of about ``edges`` edges: wall time, steps
    and the weights' statistics; the goal is ≤ 3 min for 1M edges on the CPU."""
    graph = build_graph(sample_pores(jax.random.key(1), radius_for(int(edges / EDGES_PER_PORE)),
                                     periodic=True))  # fmt: skip
    params = WrinkleParams(theta=0.0, s=0.2)
    steps = converged_steps(graph, params)
    w, total = timed(lambda: simulate(jax.random.key(2), graph, params))
    w = np.asarray(w)[: int(graph.edge_count)]
    report(f"converged trail simulation (default), {int(graph.edge_count)} edges", total,
           steps=steps, mean_w=round(float(w.mean()), 4),
           share_above_half=round(float((w > 0.5).mean()), 4), goal_s=180)  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pores", type=int, default=1_000_000, help="pores of the large cases")
    parser.add_argument("--reference-pores", type=int, default=100_000,
                        help="pores of the cases with a reference")  # fmt: skip
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--converged-only", action="store_true",
                        help="only the default (converged) runs at 130k and 1M edges")  # fmt: skip
    args = parser.parse_args()
    print(f"# devices: {jax.devices()}", flush=True)
    for edges in (130_000, 1_000_000):
        bench_converged(edges)
    if args.converged_only:
        return
    bench_sampling(args.reference_pores, reference=True)
    small = bench_graph(args.reference_pores, reference=True)
    bench_simulation(small, args.steps, 50_000)
    bench_sampling(args.pores, reference=False)
    bench_variable(args.pores)
    big = bench_graph(args.pores, reference=False)
    bench_simulation(big, args.steps, 50_000)


if __name__ == "__main__":
    main()
