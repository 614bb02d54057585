"""Spatially varying Heeger–Bergen synthesis (Golovinskiy et al. 2006, §2.4)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks, pyramid, tiles
from jface.detail._stats import DetailStats, check_layout, check_stats
from jface.optim import anderson

#: Defaults chosen on real heterogeneous maps (docs/detail.md, "Convergence on real maps").
N_ITER = 40
MEMORY = 5
N_POLISH = 150
NOISE = 0.1
#: Tile deviations below this fraction of their band's RMS count as zero in the polish loss.
_FLOOR = 1e-4
#: Scale of the polish's robust (Cauchy) loss on the tiles' log-errors: tiles off by much more
#: than 20% weigh less and less, so a few tiles that cannot be reached (far-field filter
#: leakage into flat tiles) do not take the steps that bring the bulk within a few percent.
_ROBUST = 0.2
#: L-BFGS steps per polish round, and the log-error within which 95% of the tiles must lie for
#: the polish to stop early.
_ROUND = 50
_SETTLED = 0.005


def synthesize(
    key: PRNGKeyArray,
    start: ArrayLike,
    target: DetailStats,
    *,
    n_iter: int = N_ITER,
    memory: int = MEMORY,
    n_polish: int = N_POLISH,
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

    Two additions make the per-tile statistics converge on maps whose detail changes abruptly
    (flat regions beside strong relief, a remeshed scan), where the plain iteration stalls:

    - The iterations are Anderson-accelerated (:func:`jface.optim.anderson`): the plain
      iteration contracts slowly wherever a tile's gain is blended with neighbours whose
      targets differ by orders of magnitude; combining the last ``memory + 1`` iterates
      extrapolates along those slow directions.
    - ``n_polish`` L-BFGS steps then minimise a robust loss of the log-ratios of every tile's
      deviation to its target directly over the image (:func:`_polish`). Per-tile gains cannot
      bring a tile below the detail that its neighbours' filter responses leak into it (a flat
      tile beside a rough one); moving the image itself can, by cancelling that leakage.
      ("std" method only.)

    ``memory=0, n_polish=0, rule="paper"`` is the paper's algorithm as written.

    Args:
        key: random key for the noise.
        start: ``(H, W)`` displacement image to start from, of the shape the statistics were
            taken at.
        target: statistics to reach (:func:`jface.detail.analyze`, a group mean, ...).
        n_iter: number of build–match–collapse iterations.
        memory: earlier iterates that Anderson acceleration combines (0: plain iteration).
        n_polish: at most this many L-BFGS steps on the statistics after the iterations, in
            rounds that stop once the tiles are settled (0: none; "std" only).
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
        over keys, starts and targets works (over long polishes, batched and single runs agree
        to rounding only while no line search decision tips). See ``benchmarks/bench_detail.py``
        for the cost of an iteration and of a polish step.

    Raises:
        TypeError, ValueError: bad start image, statistics of another layout or image shape or
            without any detail, bad counts or ranges.
    """
    key = _checks.key(key)
    start = _checks.float_array(start, "start", ndim=2)
    check_stats(target, "target")
    if not _checks.is_traced(target.std) and not np.any(np.asarray(target.std) > 0):
        raise ValueError("target describes no detail (every deviation is zero): nothing to reach")
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
    memory = _checks.integer(memory, "memory", low=0, high=64)
    n_polish = _checks.integer(n_polish, "n_polish", low=0)
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
    settings = (n_iter, memory, n_polish if method == "std" else 0, method, rule, boundary)
    return _synthesize(key, start, target, noise, settings)


@functools.partial(jax.jit, static_argnums=4)
def _synthesize(key, start, target, noise, settings):
    n_iter, memory, n_polish, method, rule, boundary = settings
    n_scales, n_orientations = target.n_scales, target.n_orientations
    pad = pyramid.padding(start.shape, n_scales, boundary)
    padded = pyramid.pad_image(start, pad)
    filters = pyramid.make_filters(
        padded.shape, n_scales, n_orientations, jnp.dtype(start.dtype).name
    )
    *_, lowpass = pyramid.analyze_spectrum(filters, jnp.fft.rfft2(padded))  # the start's, kept
    # Noise as strong as the detail each tile should have: a flat tile beside a rough one starts
    # near its target instead of having to shed noise it cannot (leakage from its neighbours).
    local = jnp.sqrt(tiles.blend(target.tile_energy(), start.shape))
    image = start + noise * local * jax.random.normal(key, start.shape, start.dtype)

    def crop(spectrum):
        image = jnp.fft.irfft2(spectrum, s=padded.shape)
        return image[pad[0] : pad[0] + start.shape[0], pad[2] : pad[2] + start.shape[1]]

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

    def step(spectrum):
        highpass, bands, _ = pyramid.analyze_spectrum(filters, spectrum)
        highpass = match_valid(highpass, -1, 0)
        matched = []
        for s, band in enumerate(bands):
            first = 1 + s * n_orientations
            matched.append(
                jnp.stack([match_valid(band[o], s, first + o) for o in range(n_orientations)])
            )
        spectrum = pyramid.synthesize_spectrum(filters, highpass, tuple(matched), lowpass)
        if any(pad):  # re-impose the mirror boundary on the new image
            spectrum = jnp.fft.rfft2(pyramid.pad_image(crop(spectrum), pad))
        return spectrum

    spectrum = jnp.fft.rfft2(pyramid.pad_image(image, pad))
    image = crop(anderson(step, spectrum, n_iter, memory))
    if n_polish:
        image = _polish(image, target, pad, n_polish)
    return image


def _log_errors(image, target, filters, pad):
    """``log(σ / τ)`` of every tile and band (deviations below the floor count as the floor)."""
    padded = pyramid.pad_image(image, pad)
    highpass, bands, _ = pyramid.analyze_spectrum(filters, jnp.fft.rfft2(padded))
    coefficients = [(highpass, -1)] + [
        (b[o], s) for s, b in enumerate(bands) for o in range(len(b))
    ]
    floor = (_FLOOR**2) * jnp.mean(target.std**2, axis=(-2, -1)) + jnp.finfo(image.dtype).tiny
    errors = []
    for b, (band, scale) in enumerate(coefficients):
        top, left, h, w = pyramid.valid_window(image.shape, pad, scale)
        _, variance = tiles.tile_variance(band[top : top + h, left : left + w], target.grid)
        errors.append(0.5 * jnp.log((variance + floor[b]) / (target.std[b] ** 2 + floor[b])))
    return jnp.stack(errors)


def _polish(image, target, pad, n_steps):
    """Minimise a robust loss of the tile deviations' log-errors (L-BFGS), preconditioned, in
    rounds of at most :data:`_ROUND` steps until ``n_steps`` are spent or the tiles are settled
    (95% of them within :data:`_SETTLED` of their targets): maps that the iterations already
    brought there (stationary textures, most scans) skip the polish.

    Each round's unknowns ``y`` move the image by ``B^T D B y``: its pyramid coefficients
    ``B y`` scaled by ``D``, the deviation of their band and tile in the image being polished
    (blended between tile centres), and collapsed (``B^T``) without a low-pass, so the start's
    low-pass stays as it is. Without ``D`` a tile's curvature grows as ``1 / σ²``: flat tiles
    beside rough ones would take almost all of the steps. With it every tile sees about the same
    curvature. A round that does not lower the loss is not taken.
    """
    # In JAX's default float dtype: optimistix's L-BFGS keeps part of its state in it.
    work = jax.dtypes.canonicalize_dtype(jnp.float64)
    shape = image.shape
    padded = tuple(n + a + b for n, a, b in zip(shape, pad[::2], pad[1::2], strict=True))
    filters = pyramid.make_filters(padded, target.n_scales, target.n_orientations, work.name)
    target = jax.tree.map(lambda x: x.astype(work), target)

    def amplitude(band, scale):
        top, left, h, w = pyramid.valid_window(shape, pad, scale)
        _, variance = tiles.tile_variance(band[top : top + h, left : left + w], target.grid)
        field = tiles.blend(jnp.sqrt(variance), (h, w)) / target.detail_rms()
        bottom, right = band.shape[0] - top - h, band.shape[1] - left - w
        return jnp.pad(field, ((top, bottom), (left, right)), mode="edge")

    def polish_round(start, n):
        highpass, bands, lowpass = pyramid.analyze_spectrum(
            filters, jnp.fft.rfft2(pyramid.pad_image(start, pad))
        )
        scales = [amplitude(highpass, -1)] + [
            jnp.stack([amplitude(b, s) for b in band]) for s, band in enumerate(bands)
        ]

        def move(y):
            spectrum = jnp.fft.rfft2(pyramid.pad_image(y, pad))
            high, parts, _ = pyramid.analyze_spectrum(filters, spectrum)
            parts = tuple(p * d for p, d in zip(parts, scales[1:], strict=True))
            spectrum = pyramid.synthesize_spectrum(
                filters, high * scales[0], parts, jnp.zeros_like(lowpass)
            )
            moved = jnp.fft.irfft2(spectrum, s=padded)
            return moved[pad[0] : pad[0] + shape[0], pad[2] : pad[2] + shape[1]]

        def loss(y, _):
            errors = _log_errors(start + move(y), target, filters, pad) / _ROBUST
            return jnp.mean(jnp.log1p(errors * errors))

        zero = jnp.zeros(shape, work)
        solver = optx.LBFGS(rtol=1e-12, atol=1e-12)
        solution = optx.minimise(loss, solver, zero, max_steps=n, throw=False)
        polished = start + move(solution.value)
        better = loss(solution.value, None) <= loss(zero, None)
        return jnp.where(better & jnp.all(jnp.isfinite(polished)), polished, start)

    n_rounds = -(-n_steps // _ROUND)
    per_round = -(-n_steps // n_rounds)

    def unsettled(state):
        current, done = state
        errors = jnp.abs(_log_errors(current, target, filters, pad))
        return (done < n_rounds) & (jnp.quantile(errors, 0.95) > _SETTLED)

    def step(state):
        current, done = state
        return polish_round(current, per_round), done + 1

    start = jax.lax.stop_gradient(image).astype(work)
    polished, _ = jax.lax.while_loop(unsettled, step, (start, jnp.asarray(0)))
    return polished.astype(image.dtype)
