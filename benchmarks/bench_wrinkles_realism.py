"""Realism figures of drawn wrinkle maps (one JSON line each, with the time it took).

- weak edges: share of the drawn depth coming from wrinkles with W < 0.1 (goal < 5 %), a
  directional level at its defaults;
- pores: share of the sampled pores that ``find_pores`` (§4.1, what ``jface wrinkles extract``
  runs) finds within half a pore distance on the rendered map (goal ≥ 80 %);
- border: gradient energy in a strip of two coarse pore distances along the borders of a
  non-periodic 3-level map over the interior's (goal within 10 %).

Run: ``python benchmarks/bench_wrinkles_realism.py [--size 1024]``
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from _timing import report
from scipy.spatial import cKDTree

from jface.wrinkles import WrinkleParams, find_pores, synthesize
from jface.wrinkles._drawing import DrawOptions, bin_primitives, primitives, render


def _render(key, graph, weights, params, shape, keep):
    k_perturb, k_noise = jax.random.split(key)
    prims = primitives(k_perturb, graph, weights, params, shape)
    prims = prims._replace(valid=prims.valid & keep)
    span = shape[0] // 16
    opts = DrawOptions(tile=16, span=span, capacity=16)
    bins = bin_primitives(prims, shape, tile=16, span=span, bulge=True, periodic=True)
    return np.asarray(render(k_noise, prims, bins, params, shape, opts, True))


def single_level(size: int) -> None:
    d = 20.0 / size  # 20 px between pores
    params = WrinkleParams(d=d, theta=0.5, s=0.05, cross=0.5)
    start = time.perf_counter()
    syn = synthesize(jax.random.key(3), params, (size, size), periodic=True)
    level = syn.levels[0]
    w = np.asarray(level.weights)
    n = level.graph.node_mask.shape[0]
    quiet = params.replace(snoise=0.001)
    shape = (size, size)
    full = _render(jax.random.key(4), level.graph, level.weights, quiet, shape,
                   np.ones(w.shape[0] + n, bool))  # fmt: skip
    strong = _render(jax.random.key(4), level.graph, level.weights, quiet, shape,
                     np.concatenate([w >= 0.1, np.ones(n, bool)]))  # fmt: skip
    share = float(np.sum(np.abs(full - strong)) / np.sum(np.abs(full)))
    weak = float(np.mean(w[: int(level.graph.edge_count)] < 0.1))
    report(f"weak-edge depth share, {size}² map", time.perf_counter() - start,
           share=round(share, 4), edges_below_0_1=round(weak, 3), goal="< 0.05")  # fmt: skip

    start = time.perf_counter()
    pores = level.pores
    sampled = np.asarray(pores.positions)[: int(pores.count)]
    found = find_pores(syn.displacement)
    centres = np.asarray(found.positions)[: int(found.count)]
    dist, _ = cKDTree(centres, boxsize=1.0).query(sampled)
    report(f"pores found by find_pores, {size}² map", time.perf_counter() - start,
           sampled=len(sampled), found=len(centres),
           recall=round(float(np.mean(dist < 0.5 * d)), 4), goal=">= 0.8")  # fmt: skip


def border(size: int) -> None:
    d = 40.0 / size
    levels = [WrinkleParams(d=d / 2**i, s=(0.05, 0.15, 0.3)[i], cross=0.5,
                            scale=(0.6, 0.35, 0.2)[i]) for i in range(3)]  # fmt: skip
    start = time.perf_counter()
    m = np.asarray(synthesize(jax.random.key(5), levels, (size, size), periodic=False).displacement)
    energy = np.diff(m, axis=0)[:, :-1] ** 2 + np.diff(m, axis=1)[:-1] ** 2
    strip = 80 * size // 1024 if size >= 1024 else 40
    inner = np.zeros(energy.shape, bool)
    inner[strip:-strip, strip:-strip] = True
    sides = {
        "top": energy[:strip].mean(), "bottom": energy[-strip:].mean(),
        "left": energy[:, :strip].mean(), "right": energy[:, -strip:].mean(),
    }  # fmt: skip
    ratio = {k: round(float(v / energy[inner].mean()), 3) for k, v in sides.items()}
    report(f"border / interior gradient energy, 3 levels, {size}² non-periodic",
           time.perf_counter() - start, all_borders=round(float(energy[~inner].mean()
                                                                 / energy[inner].mean()), 3),
           **ratio, goal="within 0.9-1.1")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024)
    args = parser.parse_args()
    print(f"# devices: {jax.devices()}", flush=True)
    single_level(args.size)
    border(args.size)


if __name__ == "__main__":
    main()
