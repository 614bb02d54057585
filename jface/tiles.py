"""Tile grids over pyramid bands: per-tile statistics, grown tiles and bilinear tile blending.

Golovinskiy et al. 2006 (§2.3–2.4) split each band of a displacement image's steerable pyramid
into a ``grid × grid`` array of tiles. Analysis takes the standard deviation (or the histogram)
of each tile. Synthesis grows every tile to the centres of its neighbours, so each interior pixel
is covered by four grown tiles (two along the edges, one at the corners), adjusts each grown
tile to its own target statistics, and blends the results with bilinear weights centred on the
tiles. Because the weights are separable, blending a per-tile quantity is two small matrix
products, and the moments of all grown tiles are two more.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

# --- grids -----------------------------------------------------------------------------------


def check_tiles(grid: int, shape: tuple[int, ...], what: str = "band") -> None:
    """Raise ValueError unless ``grid`` splits ``shape`` into tiles of at least 2×2 pixels.

    Args:
        grid: tiles per side.
        shape: ``(..., h, w)`` of the band.
        what: how to name the band in the message.
    """
    if isinstance(grid, bool) or not isinstance(grid, int) or grid < 1:
        raise ValueError(f"grid must be a positive integer, got {grid!r}")
    h, w = shape[-2:]
    if h % grid or w % grid or h // grid < 2 or w // grid < 2:
        raise ValueError(
            f"grid={grid} must split the {what} ({h}×{w}) into whole tiles of at least 2×2 "
            "pixels; use sides that are multiples of 2·grid·2**(n_scales-1), or another grid"
        )


def mirror_tile(image: np.ndarray, size: int) -> np.ndarray:
    """Mirror-tile a texture to ``(size, size)``, continuous across the seams (a way to bring a
    small real texture to the paper's 1024² without a visible seam)."""
    image = np.asarray(image)
    reps = -(-size // min(image.shape)) + 1
    row = np.concatenate([image, image[::-1]] * reps, axis=0)
    tile = np.concatenate([row, row[:, ::-1]] * reps, axis=1)
    return np.ascontiguousarray(tile[:size, :size])


@functools.lru_cache(maxsize=64)
def _weights_np(n: int, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear blending weights ``(n, grid)`` of tile centres for each pixel (clamped at the
    border, rows sum to one), and the 0/1 membership ``(n, grid)`` of pixels in grown tiles."""
    tile = n / grid
    position = (np.arange(n) + 0.5) / tile - 0.5  # pixel centre in tile-centre units
    left = np.floor(position).astype(int)
    frac = position - left
    weights = np.zeros((n, grid))
    rows = np.arange(n)
    np.add.at(weights, (rows, np.clip(left, 0, grid - 1)), 1.0 - frac)
    np.add.at(weights, (rows, np.clip(left + 1, 0, grid - 1)), frac)
    # A grown tile reaches from the centre of its left neighbour to that of its right one.
    centre = np.arange(grid)
    member = (position[:, None] > centre[None, :] - 1) & (position[:, None] < centre[None, :] + 1)
    member |= (position[:, None] < 0) & (centre[None, :] == 0)
    member |= (position[:, None] > grid - 1) & (centre[None, :] == grid - 1)
    return weights, member.astype(np.float64)


def blend_weights(n: int, grid: int, dtype) -> Float[Array, "n grid"]:
    """Bilinear weights ``(n, grid)`` that spread per-tile values over ``n`` pixels."""
    return jnp.asarray(_weights_np(n, grid)[0], dtype)


def grown_membership(n: int, grid: int, dtype) -> Float[Array, "n grid"]:
    """``(n, grid)`` indicator of the pixels inside each grown tile (along one axis)."""
    return jnp.asarray(_weights_np(n, grid)[1], dtype)


# --- statistics ------------------------------------------------------------------------------


def tile_view(band: Float[Array, "*batch h w"], grid: int) -> Float[Array, "*batch g g th tw"]:
    """Reshape a band into non-overlapping tiles ``(..., grid, grid, h/grid, w/grid)``."""
    h, w = band.shape[-2:]
    tiles = band.reshape(*band.shape[:-2], grid, h // grid, grid, w // grid)
    return jnp.swapaxes(tiles, -3, -2)


def tile_variance(
    band: Float[Array, "*batch h w"], grid: int
) -> tuple[Float[Array, "*batch g g"], Float[Array, "*batch g g"]]:
    """Mean and variance (ddof=0) of each non-overlapping tile, in one pass.

    Args:
        band: ``(..., h, w)``; ``grid`` must divide h and w (see :func:`check_tiles`).
        grid: tiles per side.

    Returns:
        ``(mean, variance)``, each ``(..., grid, grid)``; the variance is clamped at 0 against
        rounding, and differentiable (no square root).
    """
    check_tiles(grid, band.shape)
    h, w = band.shape[-2:]
    # Reduce over a plain reshape (axes -3 and -1): no transpose copy of the band.
    blocks = band.reshape(*band.shape[:-2], grid, h // grid, grid, w // grid)
    mean = blocks.mean(axis=(-3, -1))
    second = (blocks * blocks).mean(axis=(-3, -1))
    return mean, jnp.maximum(second - mean * mean, 0.0)


def tile_moments(
    band: Float[Array, "*batch h w"], grid: int
) -> tuple[Float[Array, "*batch g g"], Float[Array, "*batch g g"]]:
    """Mean and standard deviation (ddof=0) of each non-overlapping tile, in one pass
    (``(..., grid, grid)`` each; see :func:`tile_variance`)."""
    mean, variance = tile_variance(band, grid)
    return mean, jnp.sqrt(variance)


def tile_std(band: Float[Array, "*batch h w"], grid: int) -> Float[Array, "*batch g g"]:
    """Standard deviation (mean subtracted, ddof=0) of each non-overlapping tile
    (Golovinskiy et al. §2.3: the "reduced" statistics)."""
    return tile_moments(band, grid)[1]


def tile_histograms(
    band: Float[Array, "h w"], grid: int, bins: int
) -> tuple[Float[Array, "g g bins"], Float[Array, "g g 2"]]:
    """Histogram of each tile on ``bins`` uniform bins between the tile's min and max.

    Returns:
        ``(probabilities, ranges)``: bin probabilities (each tile sums to one) and the
        ``[min, max]`` range of each tile; the bin edges are ``linspace(min, max, bins + 1)``.
    """
    tiles = tile_view(band, grid).reshape(grid, grid, -1)
    low, high = tiles.min(axis=-1), tiles.max(axis=-1)
    span = jnp.where(high > low, high - low, 1.0)
    index = jnp.clip(
        ((tiles - low[..., None]) / span[..., None] * bins).astype(jnp.int32), 0, bins - 1
    )
    one_hot_sum = jax.vmap(jax.vmap(lambda i: jnp.bincount(i, length=bins)))(index)
    probabilities = one_hot_sum.astype(band.dtype) / tiles.shape[-1]
    return probabilities, jnp.stack([low, high], axis=-1)


def grown_moments(
    band: Float[Array, "h w"], grid: int
) -> tuple[Float[Array, "g g"], Float[Array, "g g"]]:
    """Mean and standard deviation of every grown tile (uniform weights over its pixels)."""
    h, w = band.shape
    rows = grown_membership(h, grid, band.dtype)
    cols = grown_membership(w, grid, band.dtype)
    count = jnp.outer(rows.sum(0), cols.sum(0))
    mean = rows.T @ band @ cols / count
    second = rows.T @ (band * band) @ cols / count
    return mean, jnp.sqrt(jnp.maximum(second - mean * mean, 0.0))


def blend(values: Float[Array, "*k g g"], shape: tuple[int, int]) -> Float[Array, "*k h w"]:
    """Spread per-tile values over a band of ``shape`` with bilinear weights between tile
    centres (the blending of §2.4); leading axes blend several quantities at once."""
    rows = blend_weights(shape[0], values.shape[-2], values.dtype)
    cols = blend_weights(shape[1], values.shape[-1], values.dtype)
    return rows @ values @ cols.T


# --- matching --------------------------------------------------------------------------------


def match_std(
    band: Float[Array, "h w"],
    target: Float[Array, "g g"],
    *,
    rule: str = "exact",
    n_refine: int = 0,
    eps: float = 1e-12,
) -> Float[Array, "h w"]:
    """Coerce a band towards per-tile target standard deviations (Golovinskiy et al. §2.4).

    Every tile gets a gain, and the gains are blended over the band with bilinear weights between
    tile centres, so each interior pixel takes the scaling of its four nearest tiles; the band is
    scaled about the local tile means: ``band * blend(gain) + blend(mean * (1 - gain))``.

    Args:
        band: ``(h, w)`` coefficients of one band.
        target: ``(g, g)`` target standard deviations.
        rule: how the gains are chosen. "paper": ``target / std`` of each tile grown to the
            centres of its neighbours, the literal §2.4 rule. Its fixed point is ill-posed (the
            grown tiles average neighbours with weights ¼ ½ ¼ along each axis, which cancels an
            alternating pattern of tile deviations), so repeating it drifts away from the
            targets. "exact" (default): ``target / std`` of each tile itself. Its fixed point is
            the target, and repeating it contracts the log-error of every pattern of tiles by at
            least ¾ per pass (the blended gain gives a tile at least 9/16 of its own gain), so
            the synthesis loop converges to the targets.
        n_refine: extra passes of the "exact" rule within this call, each correcting the gains
            by the remaining error of the blended result (the synthesis loop does not need
            them: its own iterations do the same work).
        eps: floor on a standard deviation before dividing by it.
    """
    if rule not in ("exact", "paper"):
        raise ValueError(f"rule must be 'exact' or 'paper', got {rule!r}")
    grid = target.shape[0]
    if rule == "paper":
        mean, std = grown_moments(band, grid)
    else:
        mean, std = tile_moments(band, grid)

    def scaled(gain):
        gain_field, offset_field = blend(jnp.stack([gain, mean * (1.0 - gain)]), band.shape)
        return band * gain_field + offset_field

    def refine(gain, _):
        return gain * target / jnp.maximum(tile_std(scaled(gain), grid), eps), None

    gain = target / jnp.maximum(std, eps)
    if rule == "exact" and n_refine:
        gain, _ = jax.lax.scan(refine, gain, length=n_refine)
    return scaled(gain)


def quantiles_from_histogram(
    probabilities: Float[Array, " bins"],
    value_range: Float[Array, " 2"],
    levels: Float[Array, " q"],
) -> Float[Array, " q"]:
    """Inverse of the piecewise-linear CDF of a histogram, at probability ``levels``."""
    bins = probabilities.shape[-1]
    edges = jnp.linspace(value_range[0], value_range[1], bins + 1)
    cdf = jnp.concatenate([jnp.zeros(1, probabilities.dtype), jnp.cumsum(probabilities)])
    return jnp.interp(levels, cdf / cdf[-1], edges)


def match_histogram(
    band: Float[Array, "h w"],
    probabilities: Float[Array, "g g bins"],
    value_range: Float[Array, "g g 2"],
) -> Float[Array, "h w"]:
    """Coerce a band towards per-tile target histograms (Heeger–Bergen matching per grown tile).

    Each grown tile's values are mapped through its own empirical CDF and the target tile's
    inverse CDF; the per-tile results are blended bilinearly as in :func:`match_std`.
    Tiles must have an even number of pixels per side (true for the paper's sizes).
    """
    grid = probabilities.shape[0]
    h, w = band.shape
    th, tw = h // grid, w // grid
    # Grown tiles as (grid, grid, 2th, 2tw) patches of a NaN-padded band (NaN = outside).
    padded = jnp.pad(band, ((th // 2, th // 2), (tw // 2, tw // 2)), constant_values=jnp.nan)
    blocks = tile_view(padded, grid + 1)
    patches = jnp.concatenate(
        [
            jnp.concatenate([blocks[:-1, :-1], blocks[:-1, 1:]], axis=-1),
            jnp.concatenate([blocks[1:, :-1], blocks[1:, 1:]], axis=-1),
        ],
        axis=-2,
    )
    levels = jnp.linspace(0.0, 1.0, 4 * probabilities.shape[-1] + 1, dtype=band.dtype)

    def one_tile(values, tile_probabilities, tile_range):
        flat = values.reshape(-1)
        valid = ~jnp.isnan(flat)
        ordered = jnp.sort(jnp.where(valid, flat, jnp.inf))
        count = valid.sum()
        rank = jnp.searchsorted(ordered, flat, side="left").astype(band.dtype)
        ties = jnp.searchsorted(ordered, flat, side="right").astype(band.dtype)
        probability = ((rank + ties) / 2) / jnp.maximum(count, 1).astype(band.dtype)
        target_quantiles = quantiles_from_histogram(tile_probabilities, tile_range, levels)
        mapped = jnp.interp(probability, levels, target_quantiles)
        return jnp.where(valid, mapped, 0.0).reshape(values.shape)

    matched = jax.vmap(jax.vmap(one_tile))(patches, probabilities, value_range)
    # Blend: weight each grown-tile pixel by the bilinear weight of its tile, fold back.
    rows = blend_weights(h, grid, band.dtype)
    cols = blend_weights(w, grid, band.dtype)
    row_w = _grown_layout(rows, grid, th)
    col_w = _grown_layout(cols, grid, tw)
    weighted = matched * row_w[:, None, :, None] * col_w[None, :, None, :]
    return _fold(weighted, grid, th, tw)[th // 2 : th // 2 + h, tw // 2 : tw // 2 + w]


def _grown_layout(weights: Float[Array, "n g"], grid: int, tile: int) -> Float[Array, "g m"]:
    """Per grown tile, the weights of its ``2 * tile`` pixels (zero outside the image)."""
    padded = jnp.pad(weights, ((tile // 2, tile // 2), (0, 0)))
    starts = jnp.arange(grid) * tile
    return jax.vmap(lambda j, s: jax.lax.dynamic_slice(padded[:, j], (s,), (2 * tile,)))(
        jnp.arange(grid), starts
    )


def _fold(patches: Float[Array, "g g a b"], grid: int, th: int, tw: int) -> Float[Array, "H W"]:
    """Sum overlapping ``(2th, 2tw)`` patches laid out with stride ``(th, tw)``."""
    quarters = patches.reshape(grid, grid, 2, th, 2, tw)
    out = jnp.zeros(((grid + 1) * th, (grid + 1) * tw), patches.dtype)
    for dy in range(2):
        for dx in range(2):
            part = jnp.swapaxes(quarters[:, :, dy, :, dx, :], 1, 2).reshape(grid * th, grid * tw)
            out = out.at[dy * th : dy * th + grid * th, dx * tw : dx * tw + grid * tw].add(part)
    return out
