"""Detail statistics and synthesis at 1024²: jface vs a pyrtools + numpy implementation.

Cases:
- one synthesis iteration (build, match 17 bands per tile with bilinear blending, collapse),
  Anderson-accelerated (the default) and plain, and one polish step (L-BFGS on the tiles'
  log-errors); the reference is pyrtools' pyramid with the same per-tile matching in numpy;
- convergence on the real maps of ``jface.data.heterogeneous_maps`` (step edges, the Lee
  Perry-Smith scan's displacement image, a face depth map, gravel) and on the step-edge map at
  384²: smoothed, re-synthesised from their own statistics; per-tile deviation errors over all
  17 bands with the defaults and with the paper's plain 12 iterations;
- analyze a batch of 32 maps, in chunks of ``--chunk`` (memory bounded by the chunk), faces/s.

Run: ``python benchmarks/bench_detail.py`` (needs the ``bench`` extra).
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import pyrtools as pt
from _timing import best_of, report

from jface import data, detail, tiles


def numpy_match_std(band, target):
    """The paper's matching in plain numpy: per grown tile, scale about its mean; blend."""
    grid = target.shape[0]
    h, w = band.shape
    rows = np.asarray(tiles.blend_weights(h, grid, jnp.float32))
    cols = np.asarray(tiles.blend_weights(w, grid, jnp.float32))
    out = np.zeros_like(band)
    th, tw = h // grid, w // grid
    for i in range(grid):
        for j in range(grid):
            y0, y1 = max(0, i * th - th // 2), min(h, (i + 1) * th + th // 2)
            x0, x1 = max(0, j * tw - tw // 2), min(w, (j + 1) * tw + tw // 2)
            region = band[y0:y1, x0:x1]
            mean, std = region.mean(), region.std()
            scaled = mean + (region - mean) * (target[i, j] / max(std, 1e-12))
            out[y0:y1, x0:x1] += scaled * rows[y0:y1, i, None] * cols[None, x0:x1, j]
    return out


def reference_iteration(image, target):
    pyr = pt.pyramids.SteerablePyramidFreq(image, height=4, order=3)
    keys = ["residual_highpass"] + [(s, o) for s in range(4) for o in range(4)]
    for b, key in enumerate(keys):
        pyr.pyr_coeffs[key] = numpy_match_std(pyr.pyr_coeffs[key], target[b])
    return pyr.recon_pyr()


def convergence(name: str, image: np.ndarray) -> None:
    """Per-tile errors after re-synthesising a smoothed map from its own statistics; the
    reference time is that of as many pyrtools + numpy iterations on the same map."""
    image = jnp.asarray(image)
    stats = detail.analyze(image)
    smooth = detail.remove_detail(image, n_bands=3)
    smooth_np, std = np.asarray(smooth), np.asarray(stats.std)
    iteration_s = best_of(lambda: reference_iteration(smooth_np, std), repeats=1)
    for label, settings in (
        ("defaults", {}),
        ("paper's plain iteration", {"n_iter": 12, "memory": 0, "n_polish": 0}),
    ):

        def run(settings=settings):
            return detail.synthesize(jax.random.key(0), smooth, stats, **settings)

        error = np.asarray(detail.stats_error(detail.analyze(run()), stats))
        report(
            f"synthesis of {name} {image.shape[0]}², {label}",
            best_of(run, 1),
            "pyrtools + numpy, the same number of paper iterations",
            iteration_s * settings.get("n_iter", detail._synthesis.N_ITER),
            median=round(float(np.median(error)), 4),
            p95=round(float(np.percentile(error, 95)), 4),
            max=round(float(error.max()), 2),
        )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--chunk", type=int, default=4)
    parser.add_argument("--skip-convergence", action="store_true")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    image = rng.standard_normal((args.size, args.size)).astype(np.float32)
    target = detail.analyze(image * 1.5)
    key = jax.random.key(0)

    def per_step(counts, **settings):
        """Time of one iteration (or polish step), without the fixed cost around the loop."""

        def run(n):
            return detail.synthesize(key, image, target, **settings, **{counts: n})

        run(1).block_until_ready(), run(9).block_until_ready()  # compile both
        return (best_of(lambda: run(9), 3) - best_of(lambda: run(1), 3)) / 8

    std = np.asarray(target.std)
    theirs = best_of(lambda: reference_iteration(image, std), repeats=2)
    reference = "pyrtools + numpy per-tile loop (paper rule)"
    report(
        f"one synthesis iteration {args.size}², Anderson-accelerated (default)",
        per_step("n_iter", n_polish=0),
        reference,
        theirs,
    )
    report(
        f"one synthesis iteration {args.size}², plain",
        per_step("n_iter", n_polish=0, memory=0),
        reference,
        theirs,
    )
    report(
        f"one synthesis iteration {args.size}², plain, rule=paper",
        per_step("n_iter", n_polish=0, memory=0, rule="paper"),
        reference,
        theirs,
    )
    report(
        f"one polish step {args.size}² (L-BFGS, preconditioned)",
        per_step("n_polish", n_iter=0),
        reference,
        theirs,
    )

    if not args.skip_convergence:
        for name, real in data.heterogeneous_maps(args.size).items():
            convergence(name, real)
        convergence("steps", data.heterogeneous_maps(384)["steps"])

    analyze_chunk = jax.jit(jax.vmap(detail.analyze))
    maps = rng.standard_normal((args.batch, args.size, args.size)).astype(np.float32)
    analyze_chunk(jnp.asarray(maps[: args.chunk])).std.block_until_ready()
    start = time.perf_counter()
    for i in range(0, args.batch, args.chunk):
        analyze_chunk(jnp.asarray(maps[i : i + args.chunk])).std.block_until_ready()
    elapsed = time.perf_counter() - start
    reference_one = best_of(
        lambda: pt.pyramids.SteerablePyramidFreq(maps[0], height=4, order=3), repeats=2
    )
    report(
        f"analyze {args.batch} maps of {args.size}² in chunks of {args.chunk}",
        elapsed / args.batch,
        "pyrtools pyramid alone, per map",
        reference_one,
        faces_per_s=round(args.batch / elapsed, 2),
    )


if __name__ == "__main__":
    main()
