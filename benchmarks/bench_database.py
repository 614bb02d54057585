"""Analyse the paper's population: 149 displacement maps of 1024² (Golovinskiy et al. 2006 §3.1).

Maps are made and analysed ``--chunk`` at a time (:func:`jface.detail.analyze_batch`, sharded
over all devices), so memory stays bounded by the chunk, not the population; the peak resident
memory of the process is reported. The reference is pyrtools' steerable pyramid plus the per-tile
standard deviations in numpy, the same work per map; it is timed on ``--reference-maps`` maps of
this run and extrapolated to the population (it is too slow to run on all of them).

Run: ``python benchmarks/bench_database.py`` (needs the ``bench`` extra).
"""

import argparse
import resource
import time

import jax
import jax.numpy as jnp
import numpy as np
import pyrtools as pt
from _timing import report

from jface import detail


def reference_stats(image: np.ndarray, grid: int = 16) -> np.ndarray:
    """Per-tile std of the 17 detail bands with pyrtools (float64)."""
    pyr = pt.pyramids.SteerablePyramidFreq(image.astype(np.float64), height=4, order=3)
    keys = ["residual_highpass"] + [(s, o) for s in range(4) for o in range(4)]
    out = []
    for key in keys:
        band = pyr.pyr_coeffs[key]
        h, w = band.shape
        tiles = band.reshape(grid, h // grid, grid, w // grid)
        out.append(tiles.std(axis=(1, 3)))
    return np.stack(out)


def make_chunk(seed: int, n: int, size: int) -> np.ndarray:
    """``n`` maps with detail at every scale (white noise plus a blurred copy)."""
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((n, size, size)).astype(np.float32)
    spectrum = np.fft.rfft2(white)
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    blur = np.exp(-((fx**2 + fy**2) * size**2) / (2 * 40.0**2))
    return (white + 3 * np.fft.irfft2(spectrum * blur, s=(size, size))).astype(np.float32)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--faces", type=int, default=149)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--chunk", type=int, default=8)
    parser.add_argument("--reference-maps", type=int, default=3)
    args = parser.parse_args()

    first = make_chunk(0, args.chunk, args.size)
    detail.analyze_batch(first).std.block_until_ready()  # compile for the chunk shape
    tail = args.faces % args.chunk
    if tail:
        detail.analyze_batch(first[:tail]).std.block_until_ready()
    stds, making = [], 0.0
    start = time.perf_counter()
    for i, begin in enumerate(range(0, args.faces, args.chunk)):
        tick = time.perf_counter()
        maps = make_chunk(i, min(args.chunk, args.faces - begin), args.size)
        making += time.perf_counter() - tick
        stds.append(np.asarray(detail.analyze_batch(jnp.asarray(maps)).std))
    elapsed = time.perf_counter() - start - making
    stds = np.concatenate(stds)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    sample = make_chunk(0, args.chunk, args.size)[: args.reference_maps]
    tick = time.perf_counter()
    reference = [reference_stats(m) for m in sample]
    per_map = (time.perf_counter() - tick) / len(sample)
    error = max(
        float(np.max(np.abs(r - s) / np.maximum(np.abs(r), 1e-6)))
        for r, s in zip(reference, stds, strict=False)
    )
    report(
        f"analyze {args.faces} maps of {args.size}² in chunks of {args.chunk}",
        elapsed,
        f"pyrtools + numpy tile std, {args.reference_maps} maps timed, × {args.faces}",
        per_map * args.faces,
        devices=len(jax.devices()),
        faces_per_s=round(args.faces / elapsed, 2),
        peak_rss_mib=round(peak_mib),
        max_rel_diff_vs_reference=float(f"{error:.2e}"),
        goal_s=20,
    )


if __name__ == "__main__":
    main()
