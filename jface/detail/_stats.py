"""Per-tile steerable-pyramid statistics of displacement images (Golovinskiy et al. 2006, §2.3)."""

from __future__ import annotations

import functools
import os
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float

from jface import _checks, io, pyramid, tiles


class DetailStats(eqx.Module):
    """Statistics of one displacement image (or, with leading axes, of many).

    ``std[b, i, j]`` is the standard deviation of band ``b`` in tile ``(i, j)``; bands are ordered
    [high-pass, scale 0 orientations 0..K-1, scale 1 ..., ...] (:func:`jface.pyramid.band_names`).
    The low-pass residual is excluded: it belongs to the base mesh. These are the paper's
    "reduced" statistics, 17 × 16 × 16 numbers per face. The "full" statistics add a histogram per
    tile and band: ``probabilities[b, i, j, :]`` on uniform bins spanning ``ranges[b, i, j]``.

    Attributes:
        std: ``(..., n_bands, grid, grid)``.
        probabilities: ``(..., n_bands, grid, grid, bins)`` or None.
        ranges: ``(..., n_bands, grid, grid, 2)`` (min, max) or None.
        n_scales, n_orientations: the pyramid the statistics come from (static).
        image_shape: ``(H, W)`` of the analysed image (static).
    """

    std: Float[Array, "*batch bands grid grid"]
    probabilities: Float[Array, "*batch bands grid grid bins"] | None
    ranges: Float[Array, "*batch bands grid grid 2"] | None
    n_scales: int = eqx.field(static=True)
    n_orientations: int = eqx.field(static=True)
    image_shape: tuple[int, int] = eqx.field(static=True)

    @property
    def grid(self) -> int:
        return self.std.shape[-1]

    @property
    def bins(self) -> int | None:
        return None if self.probabilities is None else self.probabilities.shape[-1]

    @property
    def band_names(self) -> tuple[str, ...]:
        return pyramid.band_names(self.n_scales, self.n_orientations)

    @property
    def full(self) -> bool:
        """True when per-tile histograms are present (the paper's "full" statistics)."""
        return self.probabilities is not None

    def reduced(self) -> DetailStats:
        """The same statistics without histograms."""
        return DetailStats(
            self.std, None, None, self.n_scales, self.n_orientations, self.image_shape
        )

    def detail_rms(self) -> Float[Array, "*batch"]:
        """Root-mean-square amplitude of the detail these statistics describe.

        The pyramid is a tight frame, and with pyrtools' scaling a band of scale ``s`` carries
        ``16**-s`` of its variance back into the image, so this is the standard deviation that an
        image with these statistics has once its low-pass is removed.
        """
        return jnp.sqrt(jnp.mean(self.tile_energy(), axis=(-2, -1)))

    def tile_energy(self) -> Float[Array, "*batch grid grid"]:
        """Per tile, the variance of the detail (the squared local :meth:`detail_rms`)."""
        weights = jnp.asarray(
            [1.0] + [16.0**-s for s in range(self.n_scales) for _ in range(self.n_orientations)],
            self.std.dtype,
        )
        return jnp.tensordot(weights, self.std**2, axes=((0,), (-3,)))


def check_layout(grid: int, shape: tuple[int, int], n_scales: int) -> None:
    """Raise ValueError unless ``grid`` tiles every detail band of an image of ``shape`` into
    whole tiles of at least 2×2 pixels."""
    for s in range(n_scales):
        band_shape = (-(-shape[0] // 2**s), -(-shape[1] // 2**s))
        tiles.check_tiles(grid, band_shape, f"scale-{s} band of a {shape[0]}×{shape[1]} image")


def validate_layout(
    shape: tuple[int, int],
    grid: Any,
    n_scales: Any,
    n_orientations: Any,
    bins: Any,
    boundary: Any,
) -> tuple[int, int, int, int | None]:
    """Check the analysis settings for images of ``shape``; returns them as ints."""
    grid = _checks.integer(grid, "grid", low=1)
    if bins is not None:
        bins = _checks.integer(bins, "bins", low=2)
    n_scales = _checks.integer(n_scales, "n_scales", low=1)
    n_orientations = _checks.integer(n_orientations, "n_orientations", low=1, high=16)
    _checks.choice(boundary, "boundary", ("circular", "reflect"))
    if n_scales > pyramid.max_scales(shape):
        raise ValueError(
            f"n_scales={n_scales} is too many for images of {shape[0]}×{shape[1]}: they allow "
            f"at most {max(pyramid.max_scales(shape), 0)}"
        )
    check_layout(grid, shape, n_scales)
    return grid, n_scales, n_orientations, bins


def check_stats(stats: Any, name: str = "target") -> DetailStats:
    """Raise TypeError/ValueError unless ``stats`` is well-formed :class:`DetailStats`:
    floating-point, finite, non-negative deviations, one band per pyramid band, consistent
    histograms. Value checks look at concrete arrays only (with numpy, so they add nothing to a
    trace); under ``jax.jit``/``jax.vmap`` tracing they step aside."""
    if not isinstance(stats, DetailStats):
        raise TypeError(f"{name} must be DetailStats, got {type(stats).__name__}")
    n_bands = 1 + stats.n_scales * stats.n_orientations
    std = stats.std
    for field in ("std", "probabilities", "ranges"):
        value = getattr(stats, field)
        if value is not None and not jnp.issubdtype(value.dtype, jnp.floating):
            raise TypeError(
                f"{name}.{field} must be floating point (float32 or float64), got "
                f"{_checks.describe(value)}"
            )
    if std.ndim < 3 or std.shape[-3] != n_bands or std.shape[-1] != std.shape[-2]:
        raise ValueError(
            f"{name}.std must be (..., {n_bands}, grid, grid) for {stats.n_scales} scales × "
            f"{stats.n_orientations} orientations, got {tuple(std.shape)}"
        )
    if not _checks.is_traced(std):
        values = np.asarray(std)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{name}.std must be finite, got NaN or infinite values")
        if np.any(values < 0):
            raise ValueError(f"{name}.std must be non-negative, got a minimum of {values.min()}")
    if (stats.probabilities is None) != (stats.ranges is None):
        raise ValueError(f"{name} must have both probabilities and ranges, or neither")
    if stats.full:
        expected = (*std.shape, stats.probabilities.shape[-1])
        if stats.probabilities.shape != expected or stats.ranges.shape != (*std.shape, 2):
            raise ValueError(
                f"{name} histograms must be {expected} with ranges {(*std.shape, 2)}, got "
                f"{tuple(stats.probabilities.shape)} and {tuple(stats.ranges.shape)}"
            )
        for field in ("probabilities", "ranges"):
            value = getattr(stats, field)
            if not _checks.is_traced(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"{name}.{field} must be finite, got NaN or infinite values")
    return stats


def check_weights(weights: ArrayLike, n: int, dtype) -> Float[Array, " n"]:
    """Validate averaging weights: ``n`` finite, non-negative, summing to one."""
    weights = _checks.float_array(weights, "weights", ndim=1).astype(dtype)
    if weights.shape[0] != n:
        raise ValueError(f"weights must have {n} entries (one per face), got {weights.shape[0]}")
    if _checks.is_traced(weights):
        return weights
    values = np.asarray(weights)
    if np.any(values < 0):
        raise ValueError(f"weights must be non-negative, got {values.tolist()}")
    if abs(float(values.sum()) - 1.0) > 1e-4:
        raise ValueError(f"weights must sum to 1, got {float(values.sum()):.6g}")
    return weights


def analyze(
    image: ArrayLike,
    *,
    grid: int = 16,
    n_scales: int = 4,
    n_orientations: int = 4,
    bins: int | None = None,
    boundary: pyramid.Boundary = "circular",
) -> DetailStats:
    """Per-tile statistics of a displacement image (Golovinskiy et al. 2006, §2.3).

    The image is decomposed by a steerable pyramid with ``n_scales`` scales and
    ``n_orientations`` orientations; every detail band (the high-pass residual and each oriented
    band, not the low-pass) is cut into ``grid × grid`` non-overlapping tiles, and each tile's
    standard deviation (mean subtracted, ddof=0) is taken. With ``bins``, each tile's histogram
    is stored too. One image per call; use ``jax.vmap(analyze)`` for batches.

    Args:
        image: ``(H, W)`` float displacement image. ``grid`` must divide every band size, i.e.
            H and W must be multiples of ``grid * 2**(n_scales - 1)`` (1024 for the paper's
            16 × 16 grid and 4 scales works, so do 128 or 256).
        grid: tiles per side (the paper: 16).
        n_scales, n_orientations: pyramid layout (the paper: 4 and 4, giving 17 bands).
        bins: number of histogram bins for the "full" statistics (the paper: 128), or None.
        boundary: "circular" (the paper's FFT pyramid) or "reflect" (see
            :func:`jface.pyramid.build`).

    Returns:
        :class:`DetailStats` with ``std`` of shape ``(1 + n_scales * n_orientations, grid, grid)``.

    Raises:
        TypeError, ValueError: bad image (see :func:`jface.pyramid.build`), a constant image,
            grid not dividing the band sizes, bad counts.
    """
    image = _checks.float_array(image, "image", ndim=2)
    grid, n_scales, n_orientations, bins = validate_layout(
        image.shape, grid, n_scales, n_orientations, bins, boundary
    )
    if not _checks.is_traced(image) and np.ptp(np.asarray(image)) == 0.0:
        raise ValueError(
            f"image is constant (every pixel {float(image[0, 0]):g}): it has no detail to analyse"
        )
    return _analyze(image, grid, n_scales, n_orientations, bins, boundary)


def analyze_like(image: ArrayLike, like: DetailStats, **options: Any) -> DetailStats:
    """:func:`analyze` with the layout (grid, scales, orientations, bins) of ``like``."""
    return analyze(
        image,
        grid=like.grid,
        n_scales=like.n_scales,
        n_orientations=like.n_orientations,
        bins=like.bins,
        **options,
    )


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
def _analyze(image, grid, n_scales, n_orientations, bins, boundary) -> DetailStats:
    pyr = pyramid.build(image, n_scales, n_orientations, boundary=boundary)
    bands = pyramid.detail_bands(pyr)
    std = jnp.stack([tiles.tile_std(b, grid) for b in bands])
    probabilities = ranges = None
    if bins is not None:
        histograms = [tiles.tile_histograms(b, grid, bins) for b in bands]
        probabilities = jnp.stack([h[0] for h in histograms])
        ranges = jnp.stack([h[1] for h in histograms])
    return DetailStats(std, probabilities, ranges, n_scales, n_orientations, tuple(image.shape))


def stats_error(stats: DetailStats, target: DetailStats) -> Float[Array, "*batch bands grid grid"]:
    """Relative per-tile std error ``|std - target| / target`` (0 where the target is 0)."""
    safe = jnp.where(target.std > 0, target.std, 1.0)
    return jnp.where(target.std > 0, jnp.abs(stats.std - target.std) / safe, 0.0)


def mean_stats(stats: DetailStats, weights: ArrayLike | None = None) -> DetailStats:
    """Weighted mean over the leading axis of a stack of statistics.

    Standard deviations are averaged as variances (the square root of the mean variance), so the
    mean describes the average amount of detail; histograms are averaged as distributions.
    """
    if stats.std.ndim != 4:
        raise ValueError(f"stats must be a stack (n, bands, grid, grid), got {stats.std.shape}")
    n = stats.std.shape[0]
    if weights is None:
        weights = jnp.full(n, 1.0 / n, stats.std.dtype)
    weights = check_weights(weights, n, stats.std.dtype)
    std = jnp.sqrt(jnp.einsum("n,n...->...", weights, stats.std**2))
    probabilities = ranges = None
    if stats.full:
        low = stats.ranges[..., 0].min(axis=0)
        high = stats.ranges[..., 1].max(axis=0)
        ranges = jnp.stack([low, high], axis=-1)
        probabilities = jax.vmap(_rebin, in_axes=(0, 0, None))(
            stats.probabilities, stats.ranges, ranges
        )
        probabilities = jnp.einsum("n,n...->...", weights, probabilities)
    return DetailStats(
        std, probabilities, ranges, stats.n_scales, stats.n_orientations, stats.image_shape
    )


def _rebin(probabilities, ranges, new_ranges):
    """Re-express histograms on other uniform bins (linear CDF interpolation)."""
    bins = probabilities.shape[-1]

    def one(p, r, nr):
        edges = jnp.linspace(r[0], r[1], bins + 1)
        cdf = jnp.concatenate([jnp.zeros(1, p.dtype), jnp.cumsum(p)])
        new_edges = jnp.linspace(nr[0], nr[1], bins + 1)
        return jnp.diff(jnp.interp(new_edges, edges, cdf, left=0.0, right=1.0))

    flat = (probabilities.reshape(-1, bins), ranges.reshape(-1, 2), new_ranges.reshape(-1, 2))
    return jax.vmap(one)(*flat).reshape(probabilities.shape)


# --- files -----------------------------------------------------------------------------------


def stats_to_arrays(stats: DetailStats) -> tuple[dict[str, Array], dict[str, Any]]:
    """Arrays and layout metadata of statistics, for :func:`jface.io.save_arrays`."""
    arrays = {"std": stats.std}
    if stats.full:
        arrays |= {"probabilities": stats.probabilities, "ranges": stats.ranges}
    layout = {
        "n_scales": stats.n_scales,
        "n_orientations": stats.n_orientations,
        "grid": stats.grid,
        "image_shape": list(stats.image_shape),
    }
    return arrays, layout


def stats_from_arrays(arrays: dict[str, Any], meta: dict[str, Any], path) -> DetailStats:
    """Inverse of :func:`stats_to_arrays`; a clear error names ``path`` if anything is off."""
    try:
        std = jnp.asarray(arrays["std"])
        n_bands = 1 + meta["n_scales"] * meta["n_orientations"]
        if std.shape[-3:] != (n_bands, meta["grid"], meta["grid"]):
            raise ValueError(f"std has shape {std.shape}, expected (..., {n_bands}, g, g)")
        return check_stats(
            DetailStats(
                std,
                jnp.asarray(arrays["probabilities"]) if "probabilities" in arrays else None,
                jnp.asarray(arrays["ranges"]) if "ranges" in arrays else None,
                int(meta["n_scales"]),
                int(meta["n_orientations"]),
                tuple(int(n) for n in meta["image_shape"]),
            ),
            "statistics",
        )
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path} holds malformed statistics: {err}") from err


def save_stats(
    path: str | os.PathLike, stats: DetailStats, *, source: str | None = None, **metadata: Any
) -> None:
    """Save statistics (one face or a stack) with provenance to one ``.npz`` file."""
    arrays, layout = stats_to_arrays(stats)
    io.save_arrays(
        path, arrays, io.provenance(**layout, source=source, **metadata), kind="DetailStats"
    )


class SavedStats(NamedTuple):
    """Statistics read back by :func:`load_stats`, with the metadata saved beside them
    (provenance: jface version, source map, settings such as the pyramid boundary)."""

    stats: DetailStats
    metadata: dict[str, Any]


def load_stats(path: str | os.PathLike) -> SavedStats:
    """Load statistics saved by :func:`save_stats`, with their metadata."""
    arrays, meta = io.load_arrays(path, kind="DetailStats")
    return SavedStats(stats_from_arrays(arrays, meta, path), meta)


def stack_stats(items: list[DetailStats]) -> DetailStats:
    """Stack statistics of several faces along a new leading axis (layouts must agree)."""
    if not items:
        raise ValueError("need at least one DetailStats to stack, got none")
    first = items[0]
    for i, item in enumerate(items):
        layout = (item.n_scales, item.n_orientations, item.grid, item.bins, item.image_shape)
        expected = (first.n_scales, first.n_orientations, first.grid, first.bins, first.image_shape)
        if layout != expected:
            raise ValueError(
                f"statistics {i} has layout (n_scales, n_orientations, grid, bins, image_shape) "
                f"= {layout}, expected {expected} like the first"
            )
    return jax.tree.map(lambda *xs: jnp.stack(xs), *items)
