"""A texture ("style") loss without pretrained networks.

Weiss et al. 2023 (§4.2.1) fit wrinkle parameters with the style loss of Huang & Belongie 2017
[HB17]: after normalising prediction and target to the same global mean and variance, the squared
differences of the per-channel means and standard deviations of VGG-19 feature maps. No
pretrained weights can be downloaded here, and none are needed for what the loss does: VGG's
early layers are, to a good approximation, oriented band-pass filters at octave scales followed by
half-wave rectification (ReLU), and matching the first two moments of such rectified responses is
the classic texture representation of Heeger & Bergen 1995 and Portilla & Simoncelli 2000. So the
features here are the bands of jface's steerable pyramid (the same multiscale core that the
detail statistics use), each split into its positive and negative half-wave-rectified parts —
the ReLU stand-in, which also keeps the sign asymmetry (grooves versus ridges, the skew of the
wrinkle profile) that plain band energies would lose — plus the rectified pixel values. Like the
VGG loss, it is blind to where features are (means and deviations over the whole image), so a
wrinkle pattern drawn from another pore set compares equal to the target when its texture does.

Coarse pyramid bands carry larger coefficients (pyrtools scaling); every band is divided by its
RMS response to unit white noise first, so every octave and orientation weighs alike.
"""

from __future__ import annotations

import functools
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jface import _checks, pyramid

#: Added to the image variance: small, so gain invariance holds for images of tiny variance.
_VAR_EPS = 1e-12


class TextureStats(eqx.Module):
    """Means and standard deviations of the rectified multiscale features of one image.

    Attributes:
        means, stds: ``(F,)`` with ``F = 2 · (2 + n_scales · n_orientations + 1)`` (positive and
            negative parts of the pixels, the high-pass, every oriented band and the low-pass).
    """

    means: Float[Array, " F"]
    stds: Float[Array, " F"]


def texture_stats(
    image: Any,
    n_scales: int = 4,
    n_orientations: int = 4,
    *,
    boundary: Literal["circular", "reflect"] = "reflect",
) -> TextureStats:
    """Statistics of one image for :func:`texture_distance` (compute a fixed target's once).

    Args:
        image: ``(H, W)`` float image; it is normalised to zero mean and unit variance first.
        n_scales, n_orientations: steerable pyramid layout (``min(H, W) >= 2**(n_scales + 2)``).
        boundary: pyramid boundary; "reflect" suits measured (non-periodic) patches, "circular"
            periodic ones.

    Raises:
        TypeError: non-floating image.
        ValueError: not 2-D, non-finite, constant (checked for concrete values), or too small.
    """
    image = _checks.float_array(image, "image", ndim=2)
    if not _checks.is_traced(image) and float(jnp.std(image)) == 0.0:
        raise ValueError("image must not be constant: a texture loss needs some variation")
    return _stats_jit(image, n_scales, n_orientations, boundary)


def _stats(image: Array, n_scales: int, n_orientations: int, boundary: str) -> TextureStats:
    image = (image - jnp.mean(image)) / jnp.sqrt(jnp.var(image) + _VAR_EPS)
    pyr = pyramid.build(image, n_scales, n_orientations, boundary=boundary)
    gains = _white_noise_gains(image.shape, n_scales, n_orientations, boundary)
    coefficients = [pyr.valid(pyr.highpass, -1)[None]]
    coefficients += [pyr.valid(band, s) for s, band in enumerate(pyr.bands)]
    coefficients.append(pyr.valid(pyr.lowpass, n_scales)[None])
    groups = [image[None]] + [
        c / jnp.asarray(g, c.dtype)[:, None, None] for c, g in zip(coefficients, gains, strict=True)
    ]
    means, stds = [], []
    for group in groups:
        for part in (jax.nn.relu(group), jax.nn.relu(-group)):
            means.append(jnp.mean(part, axis=(-2, -1)))
            stds.append(jnp.sqrt(jnp.var(part, axis=(-2, -1)) + 1e-12))
    return TextureStats(jnp.concatenate(means), jnp.concatenate(stds))


# one program for a concrete image (op by op it takes seconds); the fit's loss calls _stats, as
# a nested jit would keep it from fusing with the loss's program (20 % slower)
_stats_jit = jax.jit(_stats, static_argnums=(1, 2, 3))


@functools.lru_cache(maxsize=32)
def _white_noise_gains(
    shape: tuple[int, int], n_scales: int, n_orientations: int, boundary: str
) -> tuple[np.ndarray, ...]:
    """RMS coefficient of each band (high-pass, oriented bands by scale, low-pass) for unit white
    noise. A band is linear and shift-invariant before its subsampling by ``2**s``, so by Parseval
    ``E[c²] = 4**s · ||c(δ)||²`` for the response ``c(δ)`` to one centred unit impulse."""
    impulse = np.zeros(shape, np.float32)
    impulse[shape[0] // 2, shape[1] // 2] = 1.0
    with jax.ensure_compile_time_eval():
        pyr = pyramid.build(impulse, n_scales, n_orientations, boundary=boundary)
        bands = [pyr.highpass[None], *pyr.bands, pyr.lowpass[None]]
        scales = [0, *range(n_scales), n_scales]
        return tuple(
            np.sqrt(4.0**s * np.sum(np.asarray(b, np.float64) ** 2, axis=(-2, -1))).astype(
                np.float32
            )
            for b, s in zip(bands, scales, strict=True)
        )


def texture_distance(prediction: TextureStats, target: TextureStats) -> Float[Array, ""]:
    """Style distance of [HB17] on pyramid features: the mean over features of the squared
    differences of their means and of their standard deviations."""
    return jnp.mean((prediction.means - target.means) ** 2 + (prediction.stds - target.stds) ** 2)


def texture_loss(
    prediction: Any,
    target: Any,
    n_scales: int = 4,
    n_orientations: int = 4,
    *,
    boundary: Literal["circular", "reflect"] = "reflect",
) -> Float[Array, ""]:
    """Texture loss between two ``(H, W)`` images (the VGG-free stand-in for the style loss of
    Weiss et al. 2023 §4.2.1): :func:`texture_distance` of their :func:`texture_stats`.

    Zero for identical images, unchanged by a global gain (> 0) or offset of either image,
    insensitive to where features are, growing with orientation and scale mismatch.
    Differentiable in ``prediction``; a constant prediction gives a finite (large) loss.

    Raises:
        TypeError, ValueError: as :func:`texture_stats` (a constant target is an error).
    """
    prediction = _checks.float_array(prediction, "prediction", ndim=2)
    target_stats = texture_stats(target, n_scales, n_orientations, boundary=boundary)
    stats = _stats_jit(prediction, n_scales, n_orientations, boundary)  # as the target's: same bits
    return texture_distance(stats, target_stats)
