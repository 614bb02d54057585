"""Applications of detail statistics on displacement images (Golovinskiy et al. 2006, §3.2–§4):
interpolation with detail restored, and the simple alternatives the paper compares against
(Perlin noise, sharpening, detail transfer)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks, noise, pyramid
from jface.detail._stats import (
    DetailStats,
    analyze_like,
    check_weights,
    mean_stats,
    stats_error,
)
from jface.detail._synthesis import synthesize


class Interpolation(NamedTuple):
    """The plain weighted average of the images and the average coerced to the interpolated
    statistics (§3.2: the average alone is implausibly smooth)."""

    average: Float[Array, "H W"]
    coerced: Float[Array, "H W"]
    target: DetailStats


def interpolate(
    key: PRNGKeyArray, images: ArrayLike, stats: DetailStats, weights: ArrayLike, **options
) -> Interpolation:
    """Interpolate displacement images without blurring their detail (§3.2).

    Args:
        key: random key (synthesis noise).
        images: ``(n, H, W)`` displacement images of the faces (same layout; see remeshing).
        stats: their statistics, stacked ``(n, bands, grid, grid)``.
        weights: ``(n,)`` non-negative weights summing to one.
        **options: passed to :func:`jface.detail.synthesize` (``n_iter``, ``noise``, ...).
    """
    key = _checks.key(key)
    images = _checks.float_array(images, "images", ndim=3)
    if stats.std.ndim != 4 or stats.std.shape[0] != images.shape[0]:
        raise ValueError(
            f"stats must stack one face per image ({images.shape[0]}), got {stats.std.shape}"
        )
    weights = check_weights(weights, images.shape[0], images.dtype)
    target = mean_stats(stats.reduced(), weights)
    average = jnp.einsum("n,nhw->hw", weights, images)
    return Interpolation(average, synthesize(key, average, target, **options), target)


def sharpen(image: ArrayLike, target: DetailStats) -> Float[Array, "H W"]:
    """Baseline "sharpen" (§4): one global gain on all detail bands, chosen so the detail
    amplitude matches the target's; orientation and location are ignored."""
    image = _checks.float_array(image, "image", ndim=2)
    pyr = pyramid.build(image, target.n_scales, target.n_orientations)
    own = analyze_like(image, target).detail_rms()
    gain = target.detail_rms().astype(image.dtype) / jnp.maximum(own, 1e-12)
    return pyramid.collapse(
        pyr.replace(highpass=pyr.highpass * gain, bands=tuple(b * gain for b in pyr.bands))
    )


def transfer_detail(image: ArrayLike, donor: ArrayLike, n_scales: int = 4) -> Float[Array, "H W"]:
    """Baseline "detail transfer" (§4): keep the image's low-pass, take every detail band from
    the donor; the image's own detail is overwritten."""
    image = _checks.float_array(image, "image", ndim=2)
    donor = _checks.float_array(donor, "donor", ndim=2).astype(image.dtype)
    if donor.shape != image.shape:
        raise ValueError(f"donor must have the image's shape {image.shape}, got {donor.shape}")
    own = pyramid.build(image, n_scales)
    theirs = pyramid.build(donor, n_scales)
    return pyramid.collapse(own.replace(highpass=theirs.highpass, bands=theirs.bands))


def remove_detail(image: ArrayLike, n_bands: int, n_scales: int = 4) -> Float[Array, "H W"]:
    """Smooth a map by dropping its high-pass and its ``n_bands - 1`` finest scales (the
    smoothed start of the paper's Fig. 5 experiment; also a model of a low-resolution scan).

    Args:
        image: ``(H, W)`` map.
        n_bands: detail bands to drop: 1 = the high-pass only, 2 = also scale 0, ...
        n_scales: pyramid scales.
    """
    image = _checks.float_array(image, "image", ndim=2)
    n_bands = _checks.integer(n_bands, "n_bands", low=0, high=n_scales + 1)
    pyr = pyramid.build(image, n_scales)
    keep = 0.0 if n_bands >= 1 else 1.0
    bands = tuple(b * 0.0 if s < n_bands - 1 else b for s, b in enumerate(pyr.bands))
    return pyramid.collapse(pyr.replace(highpass=pyr.highpass * keep, bands=bands))


def band_correlation(a: ArrayLike, b: ArrayLike, scale: int, n_scales: int = 4) -> float:
    """Correlation of two images' coefficients in one pyramid scale (all orientations): how much
    of ``b``'s own detail at that scale survives in ``a``."""
    pa = pyramid.build(_checks.float_array(a, "a", ndim=2), n_scales)
    pb = pyramid.build(_checks.float_array(b, "b", ndim=2).astype(pa.highpass.dtype), n_scales)
    x, y = pa.bands[scale].ravel(), pb.bands[scale].ravel()
    x, y = x - x.mean(), y - y.mean()
    return float(jnp.vdot(x, y) / jnp.sqrt(jnp.vdot(x, x) * jnp.vdot(y, y)))


def perlin_detail(key: PRNGKeyArray, image: ArrayLike, target: DetailStats) -> Float[Array, "H W"]:
    """Baseline "noise" (§4, Fig. 10d): add fractal Perlin noise to the image, with the amount
    that brings its detail amplitude to the target's; location and orientation are ignored.

    The noise has one octave per pyramid scale plus one for the high-pass: its finest lattice
    cells are 2 pixels wide, its coarsest as wide as the coarsest detail band's wavelengths.
    """
    key = _checks.key(key)
    image = _checks.float_array(image, "image", ndim=2)
    h, w = image.shape
    octaves = target.n_scales + 1
    frequency = max(1, round(max(h, w) / 2**octaves))
    texture = noise.perlin(key, (h, w), frequency=frequency, octaves=octaves, dtype=image.dtype)
    own = analyze_like(image, target).detail_rms()
    theirs = analyze_like(texture, target).detail_rms()
    wanted = target.detail_rms().astype(image.dtype)
    # Independent detail adds in energy: own² + (gain · theirs)² = wanted².
    gain = jnp.sqrt(jnp.maximum(wanted**2 - own**2, 0.0)) / jnp.maximum(theirs, 1e-12)
    return image + gain * texture


#: The methods of the §4 comparison, in the order of the paper's Fig. 10 (c)–(f).
METHODS = ("statistical", "perlin", "sharpen", "transfer")


def method_results(
    key: PRNGKeyArray,
    source: ArrayLike,
    target_image: ArrayLike,
    target: DetailStats,
    *,
    methods: Sequence[str] = METHODS,
    **options,
) -> dict[str, Float[Array, "H W"]]:
    """Give ``source`` the detail of a target face by each method of §4 (Fig. 10 c–f).

    Args:
        key: random key (synthesis and Perlin noise).
        source: ``(H, W)`` displacement image to change (the young face).
        target_image: ``(H, W)`` displacement image of the target face (the donor of "transfer").
        target: its statistics (or a group's).
        methods: which of :data:`METHODS` to run (e.g. leave out "statistical" when
            :func:`jface.detail.age` already made that image).
        **options: passed to :func:`jface.detail.synthesize`.

    Returns:
        method name → ``(H, W)`` image, in the order of ``methods``.
    """
    key = _checks.key(key)
    source = _checks.float_array(source, "source", ndim=2)
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ValueError(f"methods must be a non-empty subset of {METHODS}, got {list(methods)}")
    synth_key, noise_key = jax.random.split(key)
    run = {
        "statistical": lambda: synthesize(synth_key, source, target, **options),
        "perlin": lambda: perlin_detail(noise_key, source, target),
        "sharpen": lambda: sharpen(source, target),
        "transfer": lambda: transfer_detail(source, target_image, target.n_scales),
    }
    return {name: run[name]() for name in methods}


def method_scores(
    results: dict[str, ArrayLike], source: ArrayLike, target: DetailStats
) -> dict[str, dict[str, float]]:
    """The §4 comparison as numbers, for each image of ``results``: the median per-tile std
    error to the target statistics (lower is better) and the correlation with the source's own
    detail at the coarsest and at a mid scale (higher keeps more of the individual's detail).

    Returns:
        name → {"stats_error", "keeps_coarse", "keeps_mid"}.
    """
    source = _checks.float_array(source, "source", ndim=2)
    coarse, mid = target.n_scales - 1, max(target.n_scales // 2 - 1, 0)
    table = {}
    for name, image in results.items():
        error = stats_error(analyze_like(image, target), target)
        table[name] = {
            "stats_error": float(jnp.median(error)),
            "keeps_coarse": band_correlation(image, source, coarse, target.n_scales),
            "keeps_mid": band_correlation(image, source, mid, target.n_scales),
        }
    return table


def compare_methods(
    key: PRNGKeyArray, source: ArrayLike, target_image: ArrayLike, target: DetailStats, **options
) -> dict[str, dict[str, float]]:
    """:func:`method_scores` of :func:`method_results`: the comparison of §4 in one call."""
    results = method_results(key, source, target_image, target, **options)
    return method_scores(results, source, target)
