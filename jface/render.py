"""Pictures of results: shaded relief of displacement maps, colour maps, polar statistics glyphs.

Fine geometric detail is invisible in a plain height image, so maps are shown the way the papers
show them: lit relief with the detail of every scale exaggerated (in the spirit of Rusinkiewicz
et al. 2006, *Exaggerated Shading*): the map is split into octave bands, each band is lit on its
own with a gain that makes its typical slope visible, and the shadings are summed.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from jface import _checks

# A compact perceptually ordered colour map (viridis at 11 stops), interpolated linearly.
_VIRIDIS = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.283, 0.141, 0.458],
        [0.254, 0.265, 0.530],
        [0.207, 0.372, 0.553],
        [0.164, 0.471, 0.558],
        [0.128, 0.567, 0.551],
        [0.135, 0.659, 0.518],
        [0.267, 0.749, 0.441],
        [0.478, 0.821, 0.318],
        [0.741, 0.873, 0.150],
        [0.993, 0.906, 0.144],
    ]
)


def _gaussian_blur(height: jnp.ndarray, sigma: float) -> jnp.ndarray:
    """Periodic Gaussian blur by FFT (the map's own boundary handling is not the point here)."""
    h, w = height.shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    kernel = np.exp(-2.0 * (np.pi * sigma) ** 2 * (fx**2 + fy**2))
    spectrum = jnp.fft.rfft2(height) * jnp.asarray(kernel, height.dtype).astype(jnp.complex64)
    return jnp.fft.irfft2(spectrum, s=(h, w))


def shade(
    height: ArrayLike,
    *,
    azimuth: float = 315.0,
    n_octaves: int | None = None,
    contrast: float = 0.35,
) -> jax.Array:
    """Exaggerated-shading relief of a height/displacement map, as grey values in [0, 1].

    Args:
        height: ``(H, W)`` map, any units.
        azimuth: light direction in the image plane, degrees (315 = from the top left); each
            band's slopes are normalised, so only the direction of the light matters.
        n_octaves: number of octave bands lit separately (default: up to 1/8 of the map).
        contrast: gain of each band's shading; each band's slopes are normalised by their own
            robust scale, so fine pores and broad wrinkles both show.

    Returns:
        ``(H, W)`` float32 image in [0, 1] (0.5 = flat); ``jax.jit`` and ``jax.vmap`` apply.
    """
    height = _checks.float_array(height, "height", ndim=2).astype(jnp.float32)
    # the shading is scale-free (every band's slopes are normalised): scaling the map into ±1 by a
    # power of two (exact) keeps huge finite values from overflowing float32
    height = jnp.ldexp(height, -jnp.frexp(jnp.max(jnp.abs(height)))[1])
    if n_octaves is None:
        n_octaves = max(1, int(math.log2(max(min(height.shape) // 8, 2))))
    n_octaves = _checks.integer(n_octaves, "n_octaves", low=1)
    light = (math.cos(math.radians(azimuth)), -math.sin(math.radians(azimuth)))
    shading = jnp.zeros_like(height)
    finer = height
    for octave in range(n_octaves):
        coarser = _gaussian_blur(height, 2.0 ** (octave + 1) / 2)
        band = finer - coarser
        gy, gx = jnp.gradient(band)
        slope = gx * light[0] + gy * light[1]
        scale = jnp.quantile(jnp.abs(slope), 0.9) + 1e-12
        shading = shading + jnp.tanh(slope / scale) / n_octaves
        finer = coarser
    gy, gx = jnp.gradient(finer)  # the broad form, lit gently
    slope = gx * light[0] + gy * light[1]
    shading = shading + 0.5 * jnp.tanh(slope / (jnp.quantile(jnp.abs(slope), 0.9) + 1e-12))
    return jnp.clip(0.5 + contrast * shading, 0.0, 1.0)


def colormap(values: ArrayLike, low: float | None = None, high: float | None = None) -> np.ndarray:
    """Map values to RGB in [0, 1] with a viridis-like colour map; returns ``(..., 3)``."""
    values = np.asarray(values, dtype=np.float64)
    low = np.nanmin(values) if low is None else low
    high = np.nanmax(values) if high is None else high
    t = np.clip((values - low) / (high - low if high > low else 1.0), 0.0, 1.0)
    position = t * (len(_VIRIDIS) - 1)
    index = np.minimum(position.astype(int), len(_VIRIDIS) - 2)
    frac = (position - index)[..., None]
    return (_VIRIDIS[index] * (1 - frac) + _VIRIDIS[index + 1] * frac).astype(np.float32)


#: Colours of overlaid groups in :func:`polar_glyphs` (black, red, blue, as the paper's Fig. 6).
GROUP_COLOURS = ((0.0, 0.0, 0.0), (0.85, 0.1, 0.1), (0.1, 0.25, 0.9), (0.1, 0.6, 0.2))


def polar_glyphs(
    std: ArrayLike, *, cell: int = 32, scale: float | None = None, colours=GROUP_COLOURS
) -> np.ndarray:
    """Golovinskiy et al. Fig. 4 / Fig. 6: per tile, a closed polar curve whose radius in each
    filter direction is that tile's standard deviation for the orientation band.

    Args:
        std: ``(K, grid, grid)`` one scale's per-tile std for its ``K`` orientations, or
            ``(groups, K, grid, grid)`` to overlay several groups in colours (Fig. 6).
        cell: pixels per tile.
        scale: data value drawn with radius half a cell (default: the largest value).
        colours: one RGB colour per group.

    Returns:
        ``(grid * cell, grid * cell, 3)`` float32 RGB image on white.
    """
    std = np.asarray(std, dtype=np.float64)
    if std.ndim == 3:
        std = std[None]
    if std.ndim != 4 or std.shape[-1] != std.shape[-2]:
        raise ValueError(f"std must be (K, g, g) or (groups, K, g, g), got {std.shape}")
    groups, k, grid, _ = std.shape
    if groups > len(colours):
        raise ValueError(f"at most {len(colours)} groups can be overlaid, got {groups}")
    scale = float(std.max()) if scale is None else float(scale)
    size = grid * cell
    out = np.ones((size, size, 3), np.float32)
    out[::cell, :] = out[:, ::cell] = 0.85  # tile borders
    # Radius as a smooth periodic function of angle: the band directions πb/K and their
    # opposites, interpolated with the steerable filters' own cos^(K-1) basis (undirected).
    angles = np.linspace(0, 2 * np.pi, 8 * cell, endpoint=False)
    basis = np.abs(np.cos(angles[:, None] - np.pi * np.arange(k)[None] / k)) ** (k - 1)
    basis /= basis.sum(axis=1, keepdims=True)
    centres = (np.arange(grid) + 0.5) * cell
    for g in range(groups):
        radius = np.einsum("ab,bij->aij", basis, std[g]) / (scale or 1.0) * (0.5 * cell - 1)
        ys = centres[None, :, None] - radius * np.sin(angles)[:, None, None]
        xs = centres[None, None, :] + radius * np.cos(angles)[:, None, None]
        ys = np.clip(np.round(ys).astype(int), 0, size - 1)
        xs = np.clip(np.round(xs).astype(int), 0, size - 1)
        out[ys.ravel(), xs.ravel()] = colours[g]
    return out
