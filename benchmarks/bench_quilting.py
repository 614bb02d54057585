"""Non-stationary quilting of one face on the paper's 9 × 9 grid of 70 × 70 faces, after the
library is built: jface (one jitted scan + DST Poisson solve; and 64 faces by vmap) vs the same
algorithm as a straightforward numpy loop (per position: masked SSD over the library, N best,
random choice; Poisson by scipy's DST), same run.

Faces: scikit-image's LFW subset (100 aligned faces, 25 × 25) resized to 70 × 70. Two libraries:
27 augmentations per face (2700 patches per position) and 243 (24300, the paper's ~24000).

Run: ``python benchmarks/bench_quilting.py`` (needs the ``bench`` extra).
"""

import time

import jax
import numpy as np
import scipy.fft
from _timing import best_of, report
from skimage import data, transform

from jface import faces

LAM = 1.0


def numpy_quilt(rng, patches, sources, target, geometry, n_best, lam=LAM):
    """Reference: the same quilting in plain numpy (raster loop over positions)."""
    rows, cols = geometry.grid
    ph, pw = geometry.patch
    sy, sx = geometry.step
    hc, wc = geometry.canvas
    canvas = np.zeros((hc, wc, patches.shape[-1]), np.float32)
    known = np.zeros((hc, wc), bool)
    src = -np.ones((rows, cols), int)
    ids = np.zeros((rows, cols), int)
    tgt = np.pad(
        target, ((0, hc - target.shape[0]), (0, wc - target.shape[1]), (0, 0)), "symmetric"
    )
    for r in range(rows):
        for c in range(cols):
            y, x = r * sy, c * sx
            lib = patches[r, c]
            window = canvas[y : y + ph, x : x + pw]
            mask = known[y : y + ph, x : x + pw, None]
            cost = (((lib - window) ** 2) * mask).sum(axis=(1, 2, 3))
            cost += lam * ((lib - tgt[y : y + ph, x : x + pw]) ** 2).sum(axis=(1, 2, 3))
            mirror = src[r, cols - 1 - c]
            if mirror >= 0:
                cost = np.where(sources == mirror, cost, np.inf)
            best = np.argpartition(cost, n_best - 1)[:n_best]
            best = best[np.isfinite(cost[best])]
            choice = best[rng.integers(len(best))]
            ids[r, c], src[r, c] = choice, sources[choice]
            canvas[y : y + ph, x : x + pw] = lib[choice]
            known[y : y + ph, x : x + pw] = True
    # gradients averaged in overlaps, then a DST Poisson solve with the target as boundary
    gx = np.zeros((hc, wc - 1)), np.zeros((hc, wc - 1))
    gy = np.zeros((hc - 1, wc)), np.zeros((hc - 1, wc))
    for r in range(rows):
        for c in range(cols):
            y, x = r * sy, c * sx
            p = patches[r, c, ids[r, c], ..., 0]
            gx[0][y : y + ph, x : x + pw - 1] += p[:, 1:] - p[:, :-1]
            gx[1][y : y + ph, x : x + pw - 1] += 1
            gy[0][y : y + ph - 1, x : x + pw] += p[1:] - p[:-1]
            gy[1][y : y + ph - 1, x : x + pw] += 1
    fx, fy = gx[0] / gx[1], gy[0] / gy[1]
    b = tgt[..., 0].astype(np.float64)
    div = np.zeros((hc, wc))
    div[:, :-1] += fx
    div[:, 1:] -= fx
    div[:-1] += fy
    div[1:] -= fy
    ring = b.copy()
    ring[1:-1, 1:-1] = 0
    rhs = (div + np.pad(ring, 1)[:-2, 1:-1] + np.pad(ring, 1)[2:, 1:-1])[1:-1, 1:-1]
    rhs += (np.pad(ring, 1)[1:-1, :-2] + np.pad(ring, 1)[1:-1, 2:])[1:-1, 1:-1]
    n, m = rhs.shape
    ky = 2 - 2 * np.cos(np.pi * np.arange(1, n + 1) / (n + 1))
    kx = 2 - 2 * np.cos(np.pi * np.arange(1, m + 1) / (m + 1))
    inner = scipy.fft.idstn(scipy.fft.dstn(rhs, type=1) / (ky[:, None] + kx[None, :]), type=1)
    out = b.copy()
    out[1:-1, 1:-1] = inner
    return out[: target.shape[0], : target.shape[1]], src


def run_case(images: np.ndarray, target: np.ndarray, translations: int, angles) -> None:
    start = time.perf_counter()
    library = faces.build_library(images, 9, translations=translations, angles=angles)
    jax.block_until_ready(library.patches)
    build_s = time.perf_counter() - start
    n_best = min(100, library.size // 240)

    def one(k, t, lib):
        return faces.quilt(k, lib, t, n_best=n_best).image

    quilt = jax.jit(one)
    key = jax.random.key(0)
    start = time.perf_counter()
    jax.block_until_ready(quilt(key, target, library))
    compile_s = time.perf_counter() - start
    ours = best_of(lambda: quilt(key, target, library), repeats=5)
    patches = np.asarray(library.patches)
    sources = np.asarray(library.sources)
    rng = np.random.default_rng(0)
    theirs = best_of(
        lambda: numpy_quilt(rng, patches, sources, target[..., None], library.geometry, n_best),
        repeats=2,
    )
    report(
        f"one 70×70 face, 9×9 grid, {library.size} patches/position, N={n_best}",
        ours,
        "numpy quilting loop + scipy DST Poisson",
        theirs,
        compile_s=round(compile_s, 2),
        library_build_s=round(build_s, 2),
    )
    keys = jax.random.split(jax.random.key(1), 64)
    batch = jax.jit(jax.vmap(one, in_axes=(0, None, None)))
    jax.block_until_ready(batch(keys, target, library))
    many = best_of(lambda: batch(keys, target, library), repeats=2)
    report(
        f"64 faces by vmap, {library.size} patches/position (time per face)",
        many / 64,
        "numpy quilting loop + scipy DST Poisson (per face)",
        theirs,
        batch_ms=round(many * 1e3, 1),
    )


def main() -> None:
    small = data.lfw_subset()[:100]
    images = np.stack([transform.resize(f, (70, 70), order=1) for f in small]).astype(np.float32)
    target = images.mean(0)
    run_case(images, target, 1, (-3.0, 3.0))  # 27 augmentations: 2700 patches per position
    run_case(images, target, 4, (-3.0, 3.0))  # 243: 24300, the paper's ~24000


if __name__ == "__main__":
    main()
