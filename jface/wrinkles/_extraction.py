"""Orientation and pores from a coarse displacement map (§4.1 of Weiss et al. 2023), and the
blending of simulated micro detail with a scan (§5).

* Orientation: the map's high frequencies (minus a Gaussian low-pass, σ = 1 px) are filtered with
  ``n_angles`` complex Gabor filters; the response energy per angle over each crop is a histogram
  that is smoothed (circularly) and whose argmax (refined by a parabola through the peak) is the
  crop's primary wrinkle orientation α_θ (the direction *along* the wrinkles, perpendicular to the
  Gabor wave vector).
* Pores: high-pass (σ = 2 px), threshold (depressions deeper than ``threshold`` standard
  deviations), one binary opening (3×3), 8-connected components of at least ``min_size`` pixels
  → centroids.

Conventions of the pillar: positions ``(x, y)`` in the unit square, ``x`` along columns; angles
measured from ``+x`` towards ``+y`` (down the rows).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Complex, Float, Int

from jface import _checks
from jface.wrinkles._sampling import Pores, make_pores


def _gaussian_1d(sigma: float, radius: int) -> np.ndarray:
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


def gaussian_blur(
    image: Float[Array, "H W"], sigma: float, radius: int | None = None
) -> Float[Array, "H W"]:
    """Separable Gaussian low-pass with mirrored borders (``scipy.ndimage.gaussian_filter`` with
    ``mode="reflect"``; the kernel is cut at ``radius``, default ``round(4σ)``)."""
    radius = int(4.0 * sigma + 0.5) if radius is None else radius
    k = _gaussian_1d(sigma, radius).tolist()
    h, w = image.shape
    x = jnp.pad(image, radius, mode="symmetric")
    # weighted sums of shifted views: XLA fuses them into one pass, ~10× faster on CPU than its
    # convolution of a single-channel image
    x = sum(k[i] * x[i : i + h] for i in range(2 * radius + 1))
    return sum(k[i] * x[:, i : i + w] for i in range(2 * radius + 1))


def gabor_kernels(
    frequency: float, n_angles: int, bandwidth: float = 1.0
) -> Complex[np.ndarray, "a k k"]:
    """Complex Gabor kernels at ``n_angles`` wave-vector angles ``π i / n_angles``.

    The kernel of ``skimage.filters.gabor_kernel(frequency, theta, bandwidth)`` (σ from the
    bandwidth in octaves, cut at 3σ), without its normalisation constant's dependence on θ.
    """
    sigma = (
        1.0 / math.pi * math.sqrt(math.log(2) / 2) * (2.0**bandwidth + 1) / (2.0**bandwidth - 1)
    ) / frequency
    r = math.ceil(3.0 * sigma)
    y, x = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64)
    out = []
    for i in range(n_angles):
        t = math.pi * i / n_angles
        rotx = x * math.cos(t) + y * math.sin(t)
        roty = -x * math.sin(t) + y * math.cos(t)
        g = np.exp(-0.5 * (rotx**2 + roty**2) / sigma**2) / (2 * math.pi * sigma**2)
        out.append(g * np.exp(1j * 2 * math.pi * frequency * rotx))
    return np.stack(out).astype(np.complex64)


class Orientations(NamedTuple):
    """Primary orientation per crop.

    Attributes:
        theta: ``(gy, gx)`` α_θ texture in ``[0, π)`` (the wrinkles' direction).
        histogram: ``(gy, gx, n_angles)`` smoothed Gabor energy per wave-vector angle.
    """

    theta: Float[Array, "gy gx"]
    histogram: Float[Array, "gy gx a"]


def gabor_energy(image: Float[Array, "H W"], kernels: ArrayLike) -> Float[Array, "a H W"]:
    """``|image ∗ kernel|²`` for each complex kernel, by FFT with mirrored borders."""
    k = jnp.asarray(kernels)
    r = k.shape[-1] // 2
    h, w = image.shape
    padded = jnp.pad(image, r, mode="symmetric")
    ph, pw = padded.shape
    spec = jnp.fft.fft2(padded.astype(jnp.complex64))
    kspec = jnp.fft.fft2(k, s=(ph, pw))
    resp = jnp.fft.ifft2(spec[None] * kspec)  # circular; the valid part is the unwrapped one
    resp = resp[:, 2 * r : 2 * r + h, 2 * r : 2 * r + w]
    return (resp.real**2 + resp.imag**2).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames=("crop", "n_angles", "frequency"))
def _orientations(image, *, crop, n_angles, frequency):
    high = image - gaussian_blur(image, 1.0)
    energy = gabor_energy(high, gabor_kernels(frequency, n_angles))
    h, w = image.shape
    gy, gx = h // crop, w // crop
    e = energy[:, : gy * crop, : gx * crop].reshape(n_angles, gy, crop, gx, crop)
    hist = jnp.moveaxis(jnp.sum(e, axis=(2, 4)), 0, -1)
    hist = 0.25 * jnp.roll(hist, 1, -1) + 0.5 * hist + 0.25 * jnp.roll(hist, -1, -1)
    i = jnp.argmax(hist, -1)
    take = functools.partial(jnp.take_along_axis, hist, axis=-1)
    left = take(((i - 1) % n_angles)[..., None])[..., 0]
    mid = take(i[..., None])[..., 0]
    right = take(((i + 1) % n_angles)[..., None])[..., 0]
    denom = left - 2 * mid + right
    shift = jnp.where(denom < 0, 0.5 * (left - right) / jnp.where(denom < 0, denom, -1.0), 0.0)
    wave = (i.astype(jnp.float32) + shift) * (math.pi / n_angles)
    return Orientations(jnp.mod(wave + 0.5 * math.pi, math.pi), hist)


def extract_orientation(
    image: ArrayLike, *, crop: int = 128, n_angles: int = 16, frequency: float = 0.2
) -> Orientations:
    """Primary wrinkle orientation per ``crop × crop`` crop of a coarse displacement map (§4.1).

    Args:
        image: ``(H, W)`` displacement map, ``H, W ≥ crop``.
        crop: crop side in pixels (the paper: 128 on a 4k map).
        n_angles: Gabor orientations (histogram bins over ``[0, π)``).
        frequency: Gabor frequency in cycles per pixel, in ``(0, 0.5]``.

    Returns:
        :class:`Orientations` (``theta`` is an α_θ texture for :class:`WrinkleParams`).
    """
    img = _checks.float_array(image, "image", ndim=2, dtype=jnp.float32)
    crop = _checks.integer(crop, "crop", low=8)
    n_angles = _checks.integer(n_angles, "n_angles", low=4, high=180)
    frequency = _checks.real(frequency, "frequency", low=0.0, high=0.5, open_low=True)
    if min(img.shape) < crop:
        raise ValueError(f"image must be at least crop={crop} pixels on each side, got {img.shape}")
    return _orientations(img, crop=crop, n_angles=n_angles, frequency=frequency)


def binary_opening(mask: Bool[Array, "H W"]) -> Bool[Array, "H W"]:
    """One binary opening with a 3×3 square (``scipy.ndimage.binary_opening``, border 0)."""

    def window(x, op, identity):  # outside the image counts as background (0)
        x = jnp.pad(x, 1)
        return lax.reduce_window(x, identity, op, (3, 3), (1, 1), "VALID")

    m = mask.astype(jnp.int32)
    eroded = window(m, lax.min, jnp.int32(1))
    return window(eroded, lax.max, jnp.int32(0)) > 0


def label_components(mask: Bool[Array, "H W"]) -> Int[Array, "H W"]:
    """8-connected components: each pixel of ``mask`` gets its component's largest flat index + 1
    (0 for background); min/max propagation with pointer jumping until stable."""
    h, w = mask.shape
    ids = jnp.arange(1, h * w + 1, dtype=jnp.int32).reshape(h, w)
    labels = jnp.where(mask, ids, 0)

    def spread(lab):
        best = lax.reduce_window(lab, jnp.int32(0), lax.max, (3, 3), (1, 1), ((1, 1), (1, 1)))
        best = jnp.where(mask, best, 0)
        # pointer jumping: follow the label to the label of the pixel it names
        flat = best.reshape(-1)
        jump = jnp.where(flat > 0, flat[jnp.maximum(flat - 1, 0)], 0)
        return jnp.maximum(best, jump.reshape(h, w))

    def cond(state):
        return state[1]

    def body(state):
        lab, _ = state
        new = spread(lab)
        return new, jnp.any(new != lab)

    out, _ = lax.while_loop(cond, body, (labels, jnp.array(True)))
    return out


class PoreCandidates(NamedTuple):
    """Pore centroids found in a map (capacity-padded).

    Attributes:
        positions: ``(capacity, 2)`` centroids ``(x, y)`` in the unit square.
        size: ``(capacity,)`` component sizes in pixels.
        count: number of pores found (the first ``count`` slots).
    """

    positions: Float[Array, "c 2"]
    size: Int[Array, " c"]
    count: Int[Array, ""]


@functools.partial(jax.jit, static_argnames=("min_size", "capacity"))
def _pore_candidates(image, threshold, *, min_size, capacity):
    high = image - gaussian_blur(image, 2.0)
    mask = binary_opening(high < -threshold * jnp.std(high))
    labels = label_components(mask)
    h, w = image.shape
    n = h * w + 1
    rows, cols = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                              indexing="ij")  # fmt: skip
    # pixel count and coordinate sums per component in one scatter
    per_pixel = jnp.stack([jnp.ones_like(rows), cols + 0.5, rows + 0.5], -1).reshape(-1, 3)
    size, sx, sy = jax.ops.segment_sum(per_pixel, labels.reshape(-1), n).T
    keep = (size >= min_size).at[0].set(False)
    (idx,) = jnp.nonzero(keep, size=capacity, fill_value=0)
    count = jnp.sum(keep).astype(jnp.int32)
    valid = jnp.arange(capacity, dtype=jnp.int32) < count
    s = jnp.where(valid, size[idx], 1.0)
    pos = jnp.stack([sx[idx] / s / w, sy[idx] / s / h], -1)
    return PoreCandidates(
        jnp.where(valid[:, None], pos, 0.0), jnp.where(valid, s, 0).astype(jnp.int32), count
    )


def find_pores(
    image: ArrayLike, *, threshold: float = 1.0, min_size: int = 15, capacity: int = 65536
) -> PoreCandidates:
    """Pore centroids of a coarse displacement map (§4.1).

    High-pass (σ = 2 px), keep depressions deeper than ``threshold`` standard deviations of the
    high-pass, one 3×3 binary opening, 8-connected components of at least ``min_size`` pixels →
    their centroids.

    Raises:
        ValueError: malformed image, or more pores than ``capacity``.
    """
    img = _checks.float_array(image, "image", ndim=2, dtype=jnp.float32)
    threshold = _checks.real(threshold, "threshold", low=0.0)
    min_size = _checks.integer(min_size, "min_size", low=1)
    capacity = _checks.integer(capacity, "capacity", low=1)
    found = _pore_candidates(img, jnp.float32(threshold), min_size=min_size, capacity=capacity)
    if int(found.count) > capacity:
        raise ValueError(f"found {int(found.count)} pores, more than capacity={capacity}")
    return found


def extract_pores(
    image: ArrayLike,
    *,
    threshold: float = 1.0,
    min_size: int = 15,
    capacity: int = 65536,
    periodic: bool = False,
) -> Pores:
    """:func:`find_pores` as the first level's :class:`Pores` (pass as ``initial=`` to
    :func:`sample_pores` / :func:`synthesize`).

    Raises:
        ValueError: as :func:`find_pores`, or no pore found.
    """
    found = find_pores(image, threshold=threshold, min_size=min_size, capacity=capacity)
    count = int(found.count)
    if count == 0:
        raise ValueError(
            f"no pore found (components of ≥ {min_size} px deeper than {threshold} std); "
            "lower threshold or min_size"
        )
    return make_pores(found.positions[:count], periodic=periodic)


def blend_with_scan(
    scan: ArrayLike, detail: ArrayLike, *, half_size: int = 5, first_row: int = 0
) -> Float[Array, "h W"]:
    """§5: the scan's displacement low-passed (Gaussian cut at ``half_size`` px, σ = half_size/2)
    plus the simulated micro detail.

    ``detail`` is the whole map (the scan's shape) or a band of it, rows ``first_row`` onwards
    (for maps drawn band by band, :func:`synthesize_bands`); a band gets exactly the whole map's
    rows (the low-pass reads ``half_size`` rows of the scan either side).
    """
    base = _checks.float_array(scan, "scan", ndim=2, dtype=jnp.float32)
    det = _checks.float_array(detail, "detail", ndim=2, dtype=jnp.float32)
    half_size = _checks.integer(half_size, "half_size", low=1, high=256)
    h, n = base.shape[0], det.shape[0]
    first_row = _checks.integer(first_row, "first_row", low=0, high=max(h - n, 0))
    if det.shape[1] != base.shape[1] or n > h:
        raise ValueError(f"scan {base.shape} and detail {det.shape} must have one shape")
    lo, hi = max(first_row - half_size, 0), min(first_row + n + half_size, h)
    low = gaussian_blur(base[lo:hi], half_size / 2.0, half_size)
    return low[first_row - lo : first_row - lo + n] + det
