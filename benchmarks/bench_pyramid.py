"""Steerable pyramid build + collapse at 1024², float32: jface vs pyrtools (same run).

Run: ``python benchmarks/bench_pyramid.py`` (needs the ``bench`` extra).
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pyrtools as pt
from _timing import best_of, report

from jface import pyramid


def main(size: int = 1024) -> None:
    image = np.random.default_rng(0).standard_normal((size, size)).astype(np.float32)
    x = jnp.asarray(image)
    round_trip = jax.jit(lambda im: pyramid.collapse(pyramid.build(im)))
    start = time.perf_counter()
    jax.block_until_ready(round_trip(x))
    compile_s = time.perf_counter() - start
    ours = best_of(lambda: round_trip(x), repeats=10)

    def reference():
        pyr = pt.pyramids.SteerablePyramidFreq(image, height=4, order=3)
        return pyr.recon_pyr()

    theirs = best_of(reference, repeats=3)
    report(
        f"build+collapse {size}² f32, 4 scales × 4 orientations",
        ours,
        "pyrtools SteerablePyramidFreq",
        theirs,
        compile_s=round(compile_s, 2),
    )
    spectra = jax.jit(lambda im: jnp.fft.irfft2(jnp.fft.rfft2(im), s=im.shape))
    spectra(x).block_until_ready()
    report(f"FFT floor: one rfft2 + irfft2 {size}²", best_of(lambda: spectra(x), repeats=10))


if __name__ == "__main__":
    main()
