"""Patch libraries per grid position (Mohammed, Prince & Kautz 2009, §2.2).

Aligned training faces are divided into the same ``G × G`` grid of overlapping patches as the
image to synthesise (9 × 9 with one quarter of the patch overlapping, in the paper). Each grid
position has its own library: the patch at that position of every training image, under a few
small translations and rotations (the paper's 24000 patches per position from 2000 faces). The
source image of every patch is kept, for the symmetry constraint, the component restriction of
a mixture model and the source maps of Fig. 8.

Geometry: along each axis the grid of ``G`` patches of size ``p`` overlapping by ``o`` covers
``G p - (G - 1) o`` pixels (the *canvas*). When that is larger than the image, images are
mirror-padded at the bottom/right to the canvas and results are cropped back, so any image size
and grid work.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int

from jface import _checks

#: Default grid (the paper's 9 × 9), translations (pixels, each way) and rotations (degrees).
GRID = 9
TRANSLATIONS = 1
ANGLES = (0.0, -3.0, 3.0)


class Geometry(eqx.Module):
    """Static layout of a patch grid over an image (all fields static)."""

    image_shape: tuple[int, int] = eqx.field(static=True)
    grid: tuple[int, int] = eqx.field(static=True)
    patch: tuple[int, int] = eqx.field(static=True)
    overlap: tuple[int, int] = eqx.field(static=True)

    @property
    def step(self) -> tuple[int, int]:
        return self.patch[0] - self.overlap[0], self.patch[1] - self.overlap[1]

    @property
    def canvas(self) -> tuple[int, int]:
        """Size covered by the grid (at least the image's)."""
        return tuple(g * s + o for g, s, o in zip(self.grid, self.step, self.overlap, strict=True))

    def origin(self, row: Any, col: Any) -> tuple[Any, Any]:
        """Top-left pixel of the patch at grid position ``(row, col)``."""
        return row * self.step[0], col * self.step[1]


class PatchLibrary(eqx.Module):
    """Per-position patch libraries of aligned training images.

    Attributes:
        patches: ``(G_rows, G_cols, P, ph, pw, C)``: library ``P`` of each grid position; entry
            ``e`` comes from training image ``sources[e]`` under augmentation ``e % n_augment``
            (entry ``i * n_augment`` is image ``i``'s own patch, unmoved).
        sources: ``(P,)`` source training image of each entry (the same at every position).
        norms: ``(G_rows, G_cols, P)`` squared norm ``Σ P²`` of every patch, and
        seam_norms: ``(G_rows, G_cols, P)`` the same over the pixels that the patches before it in
            raster order cover (its overlaps with the left and upper neighbours): the quadratic
            terms of the quilting cost, computed once with the library (§4.1).
        shifts: ``(n_augment, 3)`` the augmentations ``(dy, dx, angle in degrees)``.
        geometry: the grid layout (static).
        n_images: number of training images (static).
        grey: True when the training images were greyscale ``(H, W)`` (static); results then
            drop the channel axis.
    """

    patches: Float[Array, "R Q P ph pw C"]
    sources: Int[Array, " P"]
    norms: Float[Array, "R Q P"]
    seam_norms: Float[Array, "R Q P"]
    shifts: Float[Array, "A 3"]
    geometry: Geometry = eqx.field(static=True)
    n_images: int = eqx.field(static=True)
    grey: bool = eqx.field(static=True)

    @property
    def size(self) -> int:
        """Number of patches per position."""
        return self.patches.shape[2]

    @property
    def channels(self) -> int:
        return self.patches.shape[-1]


def _axis_layout(n: int, g: int, patch: int | None, overlap: int | None, axis: str):
    if patch is None:
        patch = 2
        while True:
            o = max(1, patch // 4) if overlap is None else overlap
            if patch > o and g * patch - (g - 1) * o >= n:
                break
            patch += 1
    o = max(1, patch // 4) if overlap is None else overlap
    if not 0 <= o < patch:
        raise ValueError(f"overlap must be in [0, patch) along {axis}, got {o} for patch {patch}")
    covered = g * patch - (g - 1) * o
    if covered < n:
        raise ValueError(
            f"a grid of {g} patches of {patch} px overlapping by {o} covers {covered} px, less "
            f"than the image's {n} px along {axis}; use larger patches or a finer grid"
        )
    if covered - (patch - o) >= n:
        raise ValueError(
            f"a grid of {g} patches of {patch} px overlapping by {o} covers {covered} px: the "
            f"last row/column of patches would lie outside the image's {n} px along {axis}; "
            "use smaller patches or a coarser grid"
        )
    return patch, o


def _pair(x: Any, name: str, low: int) -> tuple[int, int] | None:
    if x is None:
        return None
    if isinstance(x, (tuple, list)):
        if len(x) != 2:
            raise ValueError(f"{name} must be an integer or a pair of integers, got {x!r}")
        return tuple(_checks.integer(v, name, low=low) for v in x)
    v = _checks.integer(x, name, low=low)
    return v, v


def make_geometry(
    image_shape: tuple[int, int],
    grid: int | tuple[int, int] = GRID,
    patch: int | tuple[int, int] | None = None,
    overlap: int | tuple[int, int] | None = None,
) -> Geometry:
    """Grid layout over an image.

    Args:
        image_shape: ``(H, W)``.
        grid: patches per side, or ``(rows, cols)`` (default 9 × 9).
        patch: patch size in pixels (or ``(ph, pw)``); by default the smallest that covers the
            image with an overlap of a quarter of the patch.
        overlap: overlap in pixels (or a pair); default ``max(1, patch // 4)``.

    Raises:
        ValueError: a grid that does not fit the image (covers less than it, or leaves a whole
            row/column of patches outside it), or an overlap not smaller than the patch.
    """
    grid = _pair(grid, "grid", 1)
    patch = _pair(patch, "patch", 2) or (None, None)
    overlap = _pair(overlap, "overlap", 0) or (None, None)
    if grid[0] > image_shape[0] or grid[1] > image_shape[1]:
        raise ValueError(f"grid {grid} has more patches than the image {image_shape} has pixels")
    rows = _axis_layout(image_shape[0], grid[0], patch[0], overlap[0], "y")
    cols = _axis_layout(image_shape[1], grid[1], patch[1], overlap[1], "x")
    return Geometry(
        image_shape=tuple(image_shape),
        grid=grid,
        patch=(rows[0], cols[0]),
        overlap=(rows[1], cols[1]),
    )


def seams(geometry: Geometry) -> np.ndarray:
    """``(R, Q, ph, pw)`` boolean: the pixels of each grid window that the patches before it in
    raster order cover (its overlaps with the left and upper neighbours)."""
    rows, cols = geometry.grid
    ph, pw = geometry.patch
    covered = np.zeros(geometry.canvas, bool)
    out = np.zeros((rows, cols, ph, pw), bool)
    for r in range(rows):
        for c in range(cols):
            y0, x0 = geometry.origin(r, c)
            out[r, c] = covered[y0 : y0 + ph, x0 : x0 + pw]
            covered[y0 : y0 + ph, x0 : x0 + pw] = True
    return out


def to_canvas(image: Array, geometry: Geometry) -> Array:
    """Mirror-pad ``(H, W, C)`` at the bottom/right to the grid's canvas."""
    ph = geometry.canvas[0] - image.shape[0]
    pw = geometry.canvas[1] - image.shape[1]
    if ph == 0 and pw == 0:
        return image
    return jnp.pad(image, ((0, ph), (0, pw), (0, 0)), mode="symmetric")


def from_canvas(canvas: Array, geometry: Geometry) -> Array:
    """Crop a canvas ``(Hc, Wc, ...)`` back to the image."""
    return canvas[: geometry.image_shape[0], : geometry.image_shape[1]]


def training_images(images: Any, name: str = "images") -> tuple[Array, bool]:
    """Validate ``(n, H, W)`` grey or ``(n, H, W, C)`` colour images → ``(n, H, W, C)``, grey."""
    arr = _checks.float_array(images, name)
    if arr.ndim not in (3, 4):
        raise ValueError(
            f"{name} must be (n, H, W) greyscale or (n, H, W, C) colour images, "
            f"got {_checks.describe(arr)}"
        )
    grey = arr.ndim == 3
    return (arr[..., None] if grey else arr), grey


def face_image(image: Any, library: PatchLibrary, name: str, dtype: Any) -> Array:
    """Validate one image of the library's shape and channels → ``(H, W, C)``."""
    arr = _checks.float_array(image, name, dtype=dtype)
    h, w = library.geometry.image_shape
    want = (h, w) if library.grey else (h, w, library.channels)
    if arr.shape != want:
        raise ValueError(
            f"{name} must have the library's image shape {want}, got {arr.shape} (misaligned "
            "image size, or grey/colour mismatch)"
        )
    return arr[..., None] if library.grey else arr


def _augmentations(translations: int, angles: Sequence[float]) -> np.ndarray:
    offsets = range(-translations, translations + 1)
    rows = [(dy, dx, a) for a in angles for dy in offsets for dx in offsets]
    rows.sort(key=lambda r: r[0] != 0 or r[1] != 0 or r[2] != 0)  # identity first
    return np.asarray(rows, np.float64)


@functools.partial(jax.jit, static_argnames=("geometry",))
def _extract(images: Array, shifts: Array, geometry: Geometry) -> Array:
    """``(R, Q, n * A, ph, pw, C)`` patches of canvas-padded images under each augmentation."""
    ph, pw = geometry.patch
    rows, cols = geometry.grid
    dtype = images.dtype
    yy, xx = jnp.meshgrid(
        jnp.arange(ph, dtype=dtype) - (ph - 1) / 2,
        jnp.arange(pw, dtype=dtype) - (pw - 1) / 2,
        indexing="ij",
    )

    def coords(r, c, shift):
        y0, x0 = geometry.origin(r, c)
        cy = y0.astype(dtype) + shift[0] + (ph - 1) / 2
        cx = x0.astype(dtype) + shift[1] + (pw - 1) / 2
        a = jnp.deg2rad(shift[2])
        cos, sin = jnp.cos(a), jnp.sin(a)
        return cy + cos * yy - sin * xx, cx + sin * yy + cos * xx

    def one(channel, y, x):
        return jax.scipy.ndimage.map_coordinates(channel, [y, x], order=1, mode="nearest")

    def position(r, c):
        ys, xs = jax.vmap(lambda s: coords(r, c, s))(shifts)  # (A, ph, pw)

        def image_patches(img):  # (Hc, Wc, C) → (A, ph, pw, C)
            per_channel = jax.vmap(lambda ch: jax.vmap(lambda y, x: one(ch, y, x))(ys, xs))
            return jnp.moveaxis(per_channel(jnp.moveaxis(img, -1, 0)), 0, -1)

        out = jax.lax.map(image_patches, images)  # (n, A, ph, pw, C)
        return out.reshape(-1, ph, pw, images.shape[-1])

    r_idx, c_idx = jnp.meshgrid(
        jnp.arange(rows, dtype=jnp.int32), jnp.arange(cols, dtype=jnp.int32), indexing="ij"
    )
    flat = jax.lax.map(lambda rc: position(rc[0], rc[1]), (r_idx.ravel(), c_idx.ravel()))
    return flat.reshape(rows, cols, *flat.shape[1:]).astype(dtype)


@jax.jit
def _norms(patches: Array, seam: Array) -> tuple[Array, Array]:
    squares = jnp.sum(patches * patches, axis=-1)  # over channels: (R, Q, P, ph, pw)
    return jnp.sum(squares, axis=(-2, -1)), jnp.einsum("rqpyx,rqyx->rqp", squares, seam)


def build_library(
    images: ArrayLike,
    grid: int | tuple[int, int] = GRID,
    *,
    patch: int | tuple[int, int] | None = None,
    overlap: int | tuple[int, int] | None = None,
    translations: int = TRANSLATIONS,
    angles: Sequence[float] = ANGLES,
) -> PatchLibrary:
    """Per-position patch libraries from aligned training images (§2.2).

    Args:
        images: ``(n, H, W)`` greyscale or ``(n, H, W, C)`` colour aligned faces, float.
        grid: patches per side or ``(rows, cols)`` (default 9).
        patch: patch size (default: smallest covering the image with quarter overlap).
        overlap: overlap in pixels (default ``max(1, patch // 4)``).
        translations: largest shift in pixels; every integer shift ``(dy, dx)`` in
            ``[-t, t]²`` is used (``(2t + 1)²`` shifts).
        angles: rotations in degrees about each patch's centre; ``0`` is always included.

    Returns:
        A :class:`PatchLibrary` with ``n · (2t + 1)² · len(angles)`` patches per position,
        sampled bilinearly (float dtype of ``images``).

    Raises:
        TypeError / ValueError: non-floating or malformed images, a grid that does not fit,
        negative translations, non-finite or out-of-range (|angle| > 45°) angles.
    """
    arr, grey = training_images(images)
    translations = _checks.integer(translations, "translations", low=0)
    angles = [_checks.real(a, "angles", low=-45.0, high=45.0) for a in angles]
    if 0.0 not in angles:
        angles = [0.0, *angles]
    geometry = make_geometry(arr.shape[1:3], grid, patch, overlap)
    shifts = _augmentations(translations, sorted(set(angles), key=abs))
    padded = jax.vmap(lambda im: to_canvas(im, geometry))(arr)
    patches = _extract(padded, jnp.asarray(shifts, arr.dtype), geometry)
    sources = jnp.repeat(jnp.arange(arr.shape[0], dtype=jnp.int32), shifts.shape[0])
    norms, seam_norms = _norms(patches, jnp.asarray(seams(geometry), arr.dtype))
    return PatchLibrary(
        patches=patches,
        sources=sources,
        norms=norms,
        seam_norms=seam_norms,
        shifts=jnp.asarray(shifts, arr.dtype),
        geometry=geometry,
        n_images=int(arr.shape[0]),
        grey=grey,
    )


def default_n_best(library: PatchLibrary) -> int:
    """The default number of best matches to choose from, the paper's ratio (100 of 24000
    patches per position): ``min(100, max(1, P // 240))``."""
    return min(100, max(1, library.size // 240))


def n_augment(library: PatchLibrary) -> int:
    return int(library.shifts.shape[0])


def describe_library(library: PatchLibrary) -> str:
    g = library.geometry
    return (
        f"{g.grid[0]}×{g.grid[1]} grid of {g.patch[0]}×{g.patch[1]} patches overlapping by "
        f"{g.overlap[0]}×{g.overlap[1]} over {g.image_shape[0]}×{g.image_shape[1]} images, "
        f"{library.size} patches per position from {library.n_images} images "
        f"({math.prod(library.patches.shape) * library.patches.dtype.itemsize / 2**20:.1f} MiB)"
    )
