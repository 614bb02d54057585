"""Spatially varying Heeger–Bergen synthesis (Golovinskiy et al. 2006, §2.4)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks, pyramid, tiles
from jface.detail._stats import DetailStats, check_layout, check_stats

#: Defaults chosen on real textures (see tests/test_detail.py and benchmarks/bench_detail.py).
N_ITER = 12
NOISE = 0.1


def synthesize(
    key: PRNGKeyArray,
    start: ArrayLike,
    target: DetailStats,
    *,
    n_iter: int = N_ITER,
    noise: float = NOISE,
    method: str | None = None,
    rule: str = "exact",
    boundary: pyramid.Boundary = "circular",
) -> Float[Array, "H W"]:
    """Coerce a displacement image to target per-tile statistics (Golovinskiy et al. §2.4).

    Starting from ``start`` plus Gaussian noise, each iteration expands the image into its
    steerable pyramid, matches every detail band tile by tile (tiles grown to the centres of
    their neighbours, results blended with bilinear weights; see :mod:`jface.tiles`) and
    collapses the pyramid again. The start's low-pass residual is kept throughout: it belongs to
    the base mesh. Existing detail is sharpened or blurred where the statistics ask for it;
    new detail can only grow from the noise.

    Args:
        key: random key for the noise.
        start: ``(H, W)`` displacement image to start from, of the shape the statistics were
            taken at.
        target: statistics to reach (:func:`jface.detail.analyze`, a group mean, ...).
        n_iter: number of build–match–collapse iterations.
        noise: standard deviation of the added Gaussian noise, relative to the detail amplitude
            of the target (:meth:`DetailStats.detail_rms`); 0 adds none.
        method: "std" matches standard deviations (the paper's reduced statistics), "histogram"
            matches per-tile histograms (the full statistics; needs ``target.full``). Default:
            "histogram" when the target has histograms, else "std".
        rule: how std matching picks its per-tile gains (see :func:`jface.tiles.match_std`):
            "exact" (default) makes the tiles converge to their targets; "paper" is the literal
            grown-tile rule of §2.4, which drifts when iterated long.
        boundary: pyramid boundary handling, "circular" (the paper's) or "reflect".

    Returns:
        The synthesised ``(H, W)`` image, in the dtype of ``start``. Jit-compiled; ``jax.vmap``
        over keys, starts and targets works.

    Raises:
        TypeError, ValueError: bad start image, statistics of another layout or image shape,
            bad counts or ranges.
    """
    key = _checks.key(key)
    start = _checks.float_array(start, "start", ndim=2)
    check_stats(target, "target")
    if target.std.ndim != 3:
        raise ValueError(
            f"target must be the statistics of one image (bands, grid, grid), got a stack of "
            f"shape {tuple(target.std.shape)}; pick one or use jface.detail.mean_stats"
        )
    if tuple(start.shape) != tuple(target.image_shape):
        raise ValueError(
            f"start has shape {tuple(start.shape)} but target describes images of "
            f"{tuple(target.image_shape)}; statistics are per tile and per scale, so resample the "
            "start to the analysed resolution"
        )
    n_iter = _checks.integer(n_iter, "n_iter", low=0)
    noise = _checks.real(noise, "noise", low=0.0)
    _checks.choice(boundary, "boundary", ("circular", "reflect"))
    method = method or ("histogram" if target.full else "std")
    _checks.choice(method, "method", ("std", "histogram"))
    _checks.choice(rule, "rule", ("exact", "paper"))
    if method == "histogram":
        if not target.full:
            raise ValueError("method='histogram' needs full statistics: analyze(..., bins=128)")
        tile = [n // target.grid // 2 ** (target.n_scales - 1) for n in start.shape]
        if tile[0] % 2 or tile[1] % 2:
            raise ValueError(
                f"method='histogram' needs an even number of pixels per tile side in every "
                f"band, but the coarsest band of {tuple(start.shape)} with grid={target.grid} "
                f"has tiles of {tile[0]}×{tile[1]}"
            )
    check_layout(target.grid, start.shape, target.n_scales)
    target = jax.tree.map(lambda x: x.astype(start.dtype), target)
    return _synthesize(key, start, target, n_iter, noise, method, rule, boundary)


@functools.partial(jax.jit, static_argnums=(3, 5, 6, 7))
def _synthesize(key, start, target, n_iter, noise, method, rule, boundary):
    n_scales, n_orientations = target.n_scales, target.n_orientations
    pad = pyramid.padding(start.shape, n_scales, boundary)
    padded = pyramid.pad_image(start, pad)
    filters = pyramid.make_filters(
        padded.shape, n_scales, n_orientations, jnp.dtype(start.dtype).name
    )
    *_, lowpass = pyramid.analyse_spectrum(filters, jnp.fft.rfft2(padded))  # the start's, kept
    image = start + noise * target.detail_rms() * jax.random.normal(key, start.shape, start.dtype)
    spectrum = jnp.fft.rfft2(pyramid.pad_image(image, pad))

    def match(coefficients, b):
        if method == "std":
            return tiles.match_std(coefficients, target.std[b], rule=rule)
        return tiles.match_histogram(coefficients, target.probabilities[b], target.ranges[b])

    def match_valid(coefficients, scale, b):
        """Match the image area of a (padded) band, leave the margin as it is."""
        top, left, h, w = pyramid.valid_window(start.shape, pad, scale)
        if (h, w) == coefficients.shape:
            return match(coefficients, b)
        valid = coefficients[top : top + h, left : left + w]
        return coefficients.at[top : top + h, left : left + w].set(match(valid, b))

    def step(spectrum, _):
        highpass, bands, _ = pyramid.analyse_spectrum(filters, spectrum)
        highpass = match_valid(highpass, -1, 0)
        matched = []
        for s, band in enumerate(bands):
            first = 1 + s * n_orientations
            matched.append(
                jnp.stack([match_valid(band[o], s, first + o) for o in range(n_orientations)])
            )
        spectrum = pyramid.synthesise_spectrum(filters, highpass, tuple(matched), lowpass)
        if any(pad):  # re-impose the mirror boundary on the new image
            image = jnp.fft.irfft2(spectrum, s=padded.shape)
            image = image[pad[0] : pad[0] + start.shape[0], pad[2] : pad[2] + start.shape[1]]
            spectrum = jnp.fft.rfft2(pyramid.pad_image(image, pad))
        return spectrum, None

    spectrum, _ = jax.lax.scan(step, spectrum, length=n_iter)
    result = jnp.fft.irfft2(spectrum, s=padded.shape)
    return result[pad[0] : pad[0] + start.shape[0], pad[2] : pad[2] + start.shape[1]]
