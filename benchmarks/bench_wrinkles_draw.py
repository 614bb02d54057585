"""Micro-wrinkle drawing and extraction (§3.2, §4.1 of Weiss et al. 2023).

Cases: drawing one level's displacement map at 1024² and 4096² (graph and weights given; the
paper's goal 1024² ≤ 2 s, 4096² ≤ 20 s); Gabor orientation histograms of a 512² map × 16 angles
against scikit-image's ``filters.gabor`` (one call per angle) in the same run (goal ≤ 0.25 s);
pore extraction on a 4096² map against a scipy/scikit-image pipeline of the same steps
(``gaussian_filter``, ``binary_opening``, ``measure.label``, ``regionprops`` centroids) in the
same run (goal ≤ 2 s). The maps have visible pores (α_pore-width 0.5, α_dmin 1), so the pore
extraction has real components to find. Compilation is excluded (one warm-up call).

``--big 16384`` instead draws a 16384² map band by band straight into an EXR (what ``jface
wrinkles render --size 16384`` does) and reports the wall time, the peak resident memory of the
process (``getrusage``) and the size of the whole map in float32 for comparison.

Run: ``python benchmarks/bench_wrinkles_draw.py [--sizes 1024 4096] [--pore-size 4096]`` or
``python benchmarks/bench_wrinkles_draw.py --big 16384``
"""

from __future__ import annotations

import argparse
import math
import resource
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from _timing import best_of, report

from jface.io import exr_rows, provenance
from jface.wrinkles import (
    WrinkleParams,
    build_graph,
    draw,
    extract_orientation,
    find_pores,
    sample_pores,
    simulate,
    synthesize_bands,
)

PARAMS = WrinkleParams(d=0.01, theta=0.6, s=0.3, sperturb=0.5, pore_width=0.5, dmin=1.0)


def _peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def bench_big(size: int) -> None:
    before = _peak_rss_mib()
    start = time.perf_counter()
    bands = synthesize_bands(jax.random.key(0), [PARAMS], (size, size), n_samples=5000)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "big.exr"
        with exr_rows(out, (size, size), metadata=provenance(seed=0, size=size)) as write:
            for _, rows in bands.rows:
                write(np.asarray(rows))
        file_mib = out.stat().st_size / 2**20
    report(f"draw + write {size}² band by band", time.perf_counter() - start,
           peak_rss_mib=round(_peak_rss_mib(), 1), rss_before_mib=round(before, 1),
           whole_map_float32_mib=size * size * 4 / 2**20, exr_mib=round(file_mib, 1),
           pores=int(bands.levels[0].pores.count))  # fmt: skip


def bench_draw(size: int, repeats: int) -> np.ndarray:
    key = jax.random.key(0)
    params = PARAMS
    graph = build_graph(sample_pores(key, params.d, periodic=True))
    weights = simulate(key, graph, params, n_steps=50, n_samples=5000)
    jax.block_until_ready(draw(key, graph, weights, params, (size, size)))  # compile
    t = best_of(lambda: draw(key, graph, weights, params, (size, size)), repeats)
    report(f"draw {size}²", t, pores=int(graph.node_count), edges=int(graph.edge_count),
           goal_s=2.0 if size <= 1024 else 20.0)  # fmt: skip
    return np.asarray(draw(key, graph, weights, params, (size, size)))


def bench_gabor(image: np.ndarray, repeats: int) -> None:
    from scipy import ndimage as ndi
    from skimage.filters import gabor

    img = image[:512, :512].astype(np.float32)
    run = lambda: extract_orientation(img, crop=128, n_angles=16)  # noqa: E731
    jax.block_until_ready(run())
    t = best_of(run, repeats)
    high = img.astype(np.float64) - ndi.gaussian_filter(img.astype(np.float64), 1.0)
    start = time.perf_counter()
    for i in range(16):
        gabor(high, 0.2, theta=math.pi * i / 16)
    ref = time.perf_counter() - start
    report("Gabor orientation 512² × 16", t, "skimage.filters.gabor", ref, goal_s=0.25)


def bench_pores(image: np.ndarray, repeats: int) -> None:
    from scipy import ndimage as ndi
    from skimage.measure import label, regionprops

    img = image.astype(np.float32)
    run = lambda: find_pores(img)  # noqa: E731
    jax.block_until_ready(run())
    t = best_of(run, repeats)
    start = time.perf_counter()
    x = img.astype(np.float64)
    high = x - ndi.gaussian_filter(x, 2.0)
    mask = ndi.binary_opening(high < -high.std(), np.ones((3, 3)))
    ref_count = sum(
        r.area >= 15 and r.centroid is not None for r in regionprops(label(mask, connectivity=2))
    )
    ref = time.perf_counter() - start
    report(f"pore extraction {img.shape[0]}²", t, "scipy + skimage pipeline", ref, goal_s=2.0,
           pores=int(run().count), reference_pores=int(ref_count))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--pore-size", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--big", type=int, help="only: draw this size band by band into an EXR")
    args = parser.parse_args()
    if args.big:
        return bench_big(args.big)
    maps = {s: bench_draw(s, args.repeats) for s in args.sizes}
    first = maps[min(maps)]
    bench_gabor(np.tile(first, (2, 2)) if first.shape[0] < 512 else first, args.repeats)
    base = maps.get(args.pore_size)
    if base is None:
        reps = -(-args.pore_size // first.shape[0])
        base = np.tile(first, (reps, reps))[: args.pore_size, : args.pore_size]
    bench_pores(base, args.repeats)


if __name__ == "__main__":
    main()
