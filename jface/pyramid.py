"""Real steerable pyramid in the frequency domain.

The filters are those of ``buildSFpyr`` in matlabPyrTools and of pyrtools'
``SteerablePyramidFreq(height, order=n_orientations - 1, twidth=1)``, the decomposition behind the
statistics of Golovinskiy et al. 2006 (§2.3): a radial raised-cosine split into a high-pass residual
and a low-pass band, then per scale an octave band-pass split into ``n_orientations`` angular
filters ``sqrt(c) cos(θ - πb/K)^(K-1)`` and a half-resolution low-pass. The coefficient scaling is
pyrtools' too (each scale is the inverse FFT of a cropped spectrum, so coarse bands are larger by
4 per octave), so per-band statistics are directly comparable with the field's reference.

Unlike pyrtools, the masks are evaluated analytically rather than from 256-entry lookup tables,
and the transform works on real FFTs, so reconstruction is exact to rounding: the squared masks
sum to one at every frequency.

Typical use::

    pyr = build(image)              # image (..., H, W)
    pyr.bands[0].shape              # (..., 4, H, W)
    image2 = collapse(pyr)          # equals image to ~1e-7 (float32)
"""

from __future__ import annotations

import functools
import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float

from jface import _checks

Boundary = Literal["circular", "reflect"]


class Pyramid(eqx.Module):
    """Coefficients of a steerable pyramid; a pytree, so it jits, vmaps and differentiates.

    Attributes:
        highpass: high-pass residual, ``(..., H, W)`` (padded size).
        bands: one array per scale, ``(..., n_orientations, H / 2**s, W / 2**s)``, fine to coarse.
        lowpass: low-pass residual, ``(..., H / 2**n_scales, W / 2**n_scales)``.
        image_shape: ``(H, W)`` of the image the pyramid was built from (static).
        pad: rows/columns added before the transform, ``(top, bottom, left, right)`` (static).
    """

    highpass: Float[Array, "*batch H W"]
    bands: tuple[Float[Array, "*batch K _ _"], ...]
    lowpass: Float[Array, "*batch _ _"]
    image_shape: tuple[int, int] = eqx.field(static=True)
    pad: tuple[int, int, int, int] = eqx.field(static=True, default=(0, 0, 0, 0))

    def replace(self, **coefficients: Any) -> Pyramid:
        """A copy with some of ``highpass``, ``bands``, ``lowpass`` replaced (same layout)."""
        fields = {"highpass": self.highpass, "bands": self.bands, "lowpass": self.lowpass}
        unknown = set(coefficients) - set(fields)
        if unknown:
            raise TypeError(f"only highpass, bands and lowpass can be replaced, got {unknown}")
        fields |= coefficients
        return Pyramid(**fields, image_shape=self.image_shape, pad=self.pad)

    @property
    def n_scales(self) -> int:
        return len(self.bands)

    @property
    def n_orientations(self) -> int:
        return self.bands[0].shape[-3] if self.bands else 0

    def valid(self, coefficients: Array, scale: int) -> Array:
        """Crop a band of the given scale (``-1`` for the high-pass) to the image's own area.

        Removes what boundary padding added, so statistics see only the image: the result has
        ``ceil(H / 2**scale)`` rows and ``ceil(W / 2**scale)`` columns.
        """
        top, left, height, width = valid_window(self.image_shape, self.pad, scale)
        return coefficients[..., top : top + height, left : left + width]


def valid_window(
    image_shape: tuple[int, int], pad: tuple[int, int, int, int], scale: int
) -> tuple[int, int, int, int]:
    """``(top, left, height, width)`` of the image area inside a padded band of ``scale``
    (``-1`` for the high-pass)."""
    step = 2 ** max(scale, 0)
    height, width = (-(-n // step) for n in image_shape)
    return pad[0] // step, pad[2] // step, height, width


def max_scales(shape: tuple[int, int]) -> int:
    """Largest ``n_scales`` an image of ``shape`` supports (pyrtools' rule)."""
    return math.floor(math.log2(min(shape))) - 2


def build(
    image: ArrayLike,
    n_scales: int = 4,
    n_orientations: int = 4,
    *,
    boundary: Boundary = "circular",
) -> Pyramid:
    """Decompose images into a real steerable pyramid.

    Args:
        image: ``(..., H, W)`` float32 or float64, any leading batch axes.
        n_scales: number of band-pass scales (the paper uses 4).
        n_orientations: orientations per scale (the paper uses 4); the filter order is
            ``n_orientations - 1``.
        boundary: "circular" treats the image as periodic (the FFT's own boundary, and
            pyrtools'); "reflect" mirror-pads each side by ``2**(n_scales + 2)`` pixels first,
            which keeps the opposite edges from bleeding into each other. Sizes that are not
            multiples of ``2**n_scales`` are mirror-padded at the bottom/right in both modes.

    Returns:
        The :class:`Pyramid`; :func:`collapse` inverts it.

    Raises:
        TypeError: non-floating image.
        ValueError: fewer than two axes, empty or non-finite image, bad counts, or an image too
            small for ``n_scales`` (it needs ``min(H, W) >= 2**(n_scales + 2)``).
    """
    image = _checks.float_array(image, "image", min_ndim=2)
    n_scales = _checks.integer(n_scales, "n_scales", low=1)
    n_orientations = _checks.integer(n_orientations, "n_orientations", low=1, high=16)
    _checks.choice(boundary, "boundary", ("circular", "reflect"))
    shape = image.shape[-2:]
    if n_scales > max_scales(shape):
        raise ValueError(
            f"n_scales={n_scales} is too many for an image of {shape[0]}×{shape[1]}: it allows "
            f"at most {max(max_scales(shape), 0)} (min(H, W) must be >= 2**(n_scales + 2) = "
            f"{2 ** (n_scales + 2)})"
        )
    return _build(image, n_scales, n_orientations, boundary)


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _build(image: Array, n_scales: int, n_orientations: int, boundary: str) -> Pyramid:
    shape = image.shape[-2:]
    pad = padding(shape, n_scales, boundary)
    padded = pad_image(image, pad)
    filters = make_filters(padded.shape[-2:], n_scales, n_orientations, np.dtype(image.dtype).name)
    highpass, bands, lowpass = _analyze(filters, padded)
    return Pyramid(highpass, bands, lowpass, image_shape=tuple(shape), pad=pad)


def collapse(pyramid: Any) -> Float[Array, "*batch H W"]:
    """Reconstruct the image from a :class:`Pyramid` (exact inverse of :func:`build`)."""
    if not isinstance(pyramid, Pyramid):
        raise TypeError(f"pyramid must be a Pyramid, got {type(pyramid).__name__}")
    return _collapse(pyramid)


@jax.jit
def _collapse(pyramid: Pyramid) -> Array:
    dtype = np.dtype(pyramid.highpass.dtype).name
    shape = pyramid.highpass.shape[-2:]
    filters = make_filters(shape, pyramid.n_scales, pyramid.n_orientations, dtype)
    padded = _synthesise(filters, pyramid.highpass, pyramid.bands, pyramid.lowpass)
    top, _, left, _ = pyramid.pad
    h, w = pyramid.image_shape
    return padded[..., top : top + h, left : left + w]


# --- filters ---------------------------------------------------------------------------------


class Filters(eqx.Module):
    """Frequency masks of one (shape, n_scales, n_orientations), on the rfft2 half-plane.

    ``band[s]`` holds the orientation masks times the scale's high-pass, ``(K, h, w//2+1)``;
    ``low[s]`` is the low-pass applied after cropping to scale ``s + 1``.
    """

    hi0: Array
    lo0: Array
    band: tuple[Array, ...]
    low: tuple[Array, ...]
    sizes: tuple[tuple[int, int], ...] = eqx.field(static=True)


def _grid(h: int, w: int, level: int, dc_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """log2 radius and angle of rfft2 frequencies of a (h, w) grid at ``level``, in the units of
    the full-resolution grid (Nyquist = 1), with the DC radius replaced as pyrtools does."""
    fy = 2.0 * np.fft.fftfreq(h)[:, None] / 2**level
    fx = 2.0 * np.fft.rfftfreq(w)[None, :] / 2**level
    radius = np.sqrt(fx**2 + fy**2)
    radius[0, 0] = dc_radius
    return np.log2(radius), np.arctan2(np.broadcast_to(fy, radius.shape), fx)


def _raised_cosine(log_radius: np.ndarray, position: float) -> tuple[np.ndarray, np.ndarray]:
    """High and low halves of the radial split whose transition spans [position - 1, position]."""
    x = np.clip(log_radius - position, -1.0, 0.0) * (np.pi / 2)
    return np.abs(np.cos(x)), np.abs(np.sin(x))


@functools.lru_cache(maxsize=32)
def make_filters(shape: tuple[int, int], n_scales: int, n_orientations: int, dtype: str) -> Filters:
    """The frequency masks for images of ``shape`` (computed once per arguments, cached).

    For algorithms that iterate in the frequency domain (see :func:`analyze_spectrum` and
    :func:`synthesize_spectrum`); :func:`build` and :func:`collapse` call it themselves.
    """
    h, w = shape
    order = n_orientations - 1
    const = (2 ** (2 * order)) * math.factorial(order) ** 2
    const /= n_orientations * math.factorial(2 * order)
    dc_radius = 2.0 / w
    log_r, _ = _grid(h, w, 0, dc_radius)
    hi0, lo0 = _raised_cosine(log_r, 0.0)
    bands, lows, sizes = [], [], [(h, w)]
    for s in range(n_scales):
        hs, ws = sizes[-1]
        log_r, angle = _grid(hs, ws, s, dc_radius)
        himask, _ = _raised_cosine(log_r, -float(s + 1))
        offsets = np.pi * np.arange(n_orientations) / n_orientations
        angular = np.sqrt(const) * np.cos(angle[None] - offsets[:, None, None]) ** order
        bands.append(angular * himask[None])
        sizes.append((hs // 2, ws // 2))
        log_r, _ = _grid(*sizes[-1], s + 1, dc_radius)
        _, lomask = _raised_cosine(log_r, -float(s + 1))
        lows.append(lomask)
    as_array = functools.partial(jnp.asarray, dtype=dtype)
    # Concrete arrays even when first asked for inside a trace: the cache must never hold tracers.
    with jax.ensure_compile_time_eval():
        return Filters(
            hi0=as_array(hi0),
            lo0=as_array(lo0),
            band=tuple(map(as_array, bands)),
            low=tuple(map(as_array, lows)),
            sizes=tuple(sizes),
        )


# --- transform -------------------------------------------------------------------------------


def _crop(spectrum: Array, size: tuple[int, int]) -> Array:
    """Keep the rfft2 coefficients of the frequencies a grid of ``size`` represents."""
    h, w = size
    top = (h + 1) // 2
    rows = jnp.concatenate([spectrum[..., :top, :], spectrum[..., -(h - top) :, :]], axis=-2)
    return rows[..., : w // 2 + 1]


def _uncrop(spectrum: Array, size: tuple[int, int]) -> Array:
    """Place a smaller grid's rfft2 coefficients into a zero spectrum of ``size`` (adjoint of
    :func:`_crop`)."""
    h, w = size
    hs = spectrum.shape[-2]
    top = (hs + 1) // 2
    out = jnp.zeros((*spectrum.shape[:-2], h, w // 2 + 1), spectrum.dtype)
    out = out.at[..., :top, : spectrum.shape[-1]].set(spectrum[..., :top, :])
    return out.at[..., h - (hs - top) :, : spectrum.shape[-1]].set(spectrum[..., top:, :])


def _times(spectrum: Array, mask: Array) -> Array:
    """Spectrum times a real mask (cast explicitly: strict promotion forbids real × complex)."""
    return spectrum * mask.astype(spectrum.dtype)


def _analyze(filters: Filters, image: Array) -> tuple[Array, tuple[Array, ...], Array]:
    spectrum = jnp.fft.rfft2(image)
    return analyze_spectrum(filters, spectrum)


def analyze_spectrum(filters: Filters, spectrum: Array) -> tuple[Array, tuple[Array, ...], Array]:
    """Pyramid coefficients ``(highpass, bands, lowpass)`` from the rfft2 of a (padded) image,
    so an iterative algorithm can stay in the frequency domain between iterations."""
    sizes = filters.sizes
    highpass = jnp.fft.irfft2(_times(spectrum, filters.hi0), s=sizes[0])
    low = _times(spectrum, filters.lo0)
    bands = []
    for s, (band_masks, low_mask) in enumerate(zip(filters.band, filters.low, strict=True)):
        # (-1j)**order rotates odd-order bands to real values, as in buildSFpyr.
        phase = (-1j) ** (band_masks.shape[0] - 1)
        band_spectra = _times(low[..., None, :, :], band_masks) * phase
        bands.append(jnp.fft.irfft2(band_spectra, s=sizes[s]))
        low = _times(_crop(low, sizes[s + 1]), low_mask)
    lowpass = jnp.fft.irfft2(low, s=sizes[-1])
    return highpass, tuple(bands), lowpass


def synthesize_spectrum(
    filters: Filters, highpass: Array, bands: tuple[Array, ...], lowpass: Array
) -> Array:
    """rfft2 of the (padded) image that the coefficients reconstruct."""
    sizes = filters.sizes
    low = jnp.fft.rfft2(lowpass)
    for s in reversed(range(len(bands))):
        phase = (1j) ** (filters.band[s].shape[0] - 1)
        low = _uncrop(_times(low, filters.low[s]), sizes[s])
        low = low + jnp.sum(_times(jnp.fft.rfft2(bands[s]), filters.band[s]), axis=-3) * phase
    return _times(low, filters.lo0) + _times(jnp.fft.rfft2(highpass), filters.hi0)


def _synthesise(filters: Filters, highpass: Array, bands: tuple[Array, ...], lowpass: Array):
    spectrum = synthesize_spectrum(filters, highpass, bands, lowpass)
    return jnp.fft.irfft2(spectrum, s=filters.sizes[0])


# --- boundary handling -----------------------------------------------------------------------


def padding(shape: tuple[int, int], n_scales: int, boundary: str) -> tuple[int, int, int, int]:
    """Rows/columns ``(top, bottom, left, right)`` that :func:`build` adds for ``boundary``."""
    step = 2**n_scales
    margin = 2 ** (n_scales + 2) if boundary == "reflect" else 0
    h, w = shape
    extra_h = -(h + 2 * margin) % step
    extra_w = -(w + 2 * margin) % step
    return (margin, margin + extra_h, margin, margin + extra_w)


def pad_image(image: Array, pad: tuple[int, int, int, int]) -> Array:
    """Mirror-pad the last two axes by ``pad`` (see :func:`padding`)."""
    if not any(pad):
        return image
    top, bottom, left, right = pad
    widths = [(0, 0)] * (image.ndim - 2) + [(top, bottom), (left, right)]
    return jnp.pad(image, widths, mode="symmetric")


def band_names(n_scales: int = 4, n_orientations: int = 4) -> tuple[str, ...]:
    """Names of the detail bands in statistics order: high-pass, then scale-major orientations."""
    names = ["highpass"]
    for s in range(n_scales):
        names += [f"s{s}o{o}" for o in range(n_orientations)]
    return tuple(names)


def detail_bands(pyramid: Pyramid) -> tuple[Array, ...]:
    """The high-pass and every oriented band, each cropped to the image area, in statistics order
    (see :func:`band_names`); the low-pass is left out (it belongs to the base mesh)."""
    out = [pyramid.valid(pyramid.highpass, -1)]
    for s, band in enumerate(pyramid.bands):
        cropped = pyramid.valid(band, s)
        out += [cropped[..., o, :, :] for o in range(band.shape[-3])]
    return tuple(out)
