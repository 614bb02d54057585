"""Editing real faces with the quilting model (Mohammed et al. 2009, §6) and analysis helpers (§5).

* :func:`inpaint` — §6.1: fill a masked region. The patches are placed only over the grid
  positions that touch the region, matched to everything known around them (the observed pixels
  at the region's boundary and the patches already placed) and to a global target for the
  region; the region is then solved in the gradient domain with the observed pixels as Dirichlet
  boundary, so they are kept exactly. Several hypotheses come from several targets (posterior
  samples of a global model) or keys.
* :func:`guided_edit` — §6.2: a user-painted edit (the mustache of Fig. 11) used as the target
  of the painted region, so the painted strokes are replaced by realistic texture.
* Analysis (§5, Fig. 8): :func:`nearest_training` (the closest training face in the least
  squares sense and its distance), :func:`novelty` (that distance relative to the training
  images' own nearest-neighbour distances), :func:`distinct_sources`, :func:`source_map`,
  :func:`target_distance`.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jface import _checks
from jface.faces import _poisson
from jface.faces._patches import PatchLibrary, face_image, to_canvas, training_images
from jface.faces._quilting import (
    LAM,
    QuiltResult,
    _quilt,
    _windows,
    check_library,
    finish,
    settings,
)

#: Default target weight of a painted edit: the painting leads, the overlaps keep it seamless.
GUIDE_LAM = 4.0


def _region(mask: Any, library: PatchLibrary) -> Array:
    return _poisson.region_mask(mask, library.geometry.image_shape, "mask")


def inpaint(
    key: PRNGKeyArray,
    library: PatchLibrary,
    image: ArrayLike,
    mask: ArrayLike,
    target: ArrayLike,
    *,
    lam: float = LAM,
    n_best: int | None = None,
    symmetric: bool = True,
    allowed: ArrayLike | None = None,
    blend: bool = True,
) -> QuiltResult:
    """Fill the masked region of a face with new texture (§6.1).

    Args:
        key: ``jax.random.key``; vmap over keys (and targets) for several hypotheses.
        library: per-position patch libraries.
        image: ``(H, W)`` or ``(H, W, C)`` face, the library's shape; pixels under ``mask``
            are ignored.
        mask: ``(H, W)`` boolean, True where the face is to be replaced (not empty, not all).
        target: global target image of the library's shape for the region (e.g. the factor
            model's posterior mean given the observed pixels, or a posterior sample); only its
            values inside the windows being synthesised matter.
        lam, n_best, symmetric, allowed, blend: as in :func:`quilt`.

    Returns:
        A :class:`QuiltResult`; ``image`` equals the input exactly outside ``mask``. ``ids`` and
        ``sources`` are ``-1`` at grid positions that do not touch the region.

    Raises:
        TypeError / ValueError: bad key/library, image or target of the wrong shape, a mask of
        the wrong shape or dtype, empty or covering everything, and the errors of :func:`quilt`.
    """
    key = _checks.single_key(key)
    library = check_library(library)
    dtype = library.patches.dtype
    image = face_image(image, library, "image", dtype)
    target = face_image(target, library, "target", dtype)
    region = _region(mask, library)
    lam, n_best, entries = settings(library, lam, n_best, allowed, dtype)
    g = library.geometry
    hole = to_canvas(region[..., None], g)[..., 0]
    ys, xs = _windows(g)
    active = jnp.any(hole[ys, xs], axis=(-2, -1))
    canvas = jnp.where(region[..., None], target, image)
    out = _quilt(
        key,
        library,
        to_canvas(target, g),
        to_canvas(canvas, g),
        ~hole,
        active,
        entries,
        lam,
        n_best=n_best,
        symmetric=bool(symmetric),
        blend=bool(blend),
        fill=True,
    )
    result = finish(library, out)
    if blend:
        return result
    keep = region if library.grey else region[..., None]
    original = image[..., 0] if library.grey else image
    return QuiltResult(
        jnp.where(keep, result.image, original),
        jnp.where(keep, result.quilted, original),
        result.ids,
        result.sources,
        result.errors,
    )


def guided_edit(
    key: PRNGKeyArray,
    library: PatchLibrary,
    image: ArrayLike,
    painted: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    lam: float = GUIDE_LAM,
    n_best: int | None = None,
    grow: int = 1,
    symmetric: bool = False,
    allowed: ArrayLike | None = None,
) -> QuiltResult:
    """Turn a painted edit into realistic texture (§6.2, the mustache of Fig. 11C–E).

    The painted image is the target inside the edited region; the rest of the face is kept.

    Args:
        key: ``jax.random.key``.
        library: per-position patch libraries.
        image: the face before the edit, library's shape.
        painted: the same face with the user's strokes.
        mask: optional ``(H, W)`` region to resynthesise; by default the pixels where
            ``painted`` differs from ``image``, grown by ``grow`` pixels.
        lam: weight of the painted target (default 4: the painting leads).
        n_best, symmetric, allowed: as in :func:`quilt` (symmetry off by default: edits are
            often one-sided).
        grow: pixels by which the default region is dilated (3×3 steps).

    Raises:
        ValueError: images of the wrong shape, an edit that changes nothing, and the errors of
        :func:`inpaint`.
    """
    library = check_library(library)
    dtype = library.patches.dtype
    before = face_image(image, library, "image", dtype)
    after = face_image(painted, library, "painted", dtype)
    if mask is None:
        grow = _checks.integer(grow, "grow", low=0)
        changed = jnp.any(jnp.abs(after - before) > 1e-6, axis=-1)
        if not _checks.is_traced(changed) and not bool(changed.any()):
            raise ValueError("painted does not differ from image: nothing to edit")
        for _ in range(grow):
            p = jnp.pad(changed, 1)
            changed = changed | p[:-2, 1:-1] | p[2:, 1:-1] | p[1:-1, :-2] | p[1:-1, 2:]
        mask = changed
    squeeze = (lambda x: x[..., 0]) if library.grey else (lambda x: x)
    return inpaint(
        key,
        library,
        squeeze(before),
        mask,
        squeeze(after),
        lam=lam,
        n_best=n_best,
        symmetric=symmetric,
        allowed=allowed,
    )


# --- analysis ---------------------------------------------------------------------------------


def _flat_training(training: Any) -> Array:
    arr, _ = training_images(training, "training")
    return arr.reshape(arr.shape[0], -1)


def _squared_distances(x: Array, training: Array) -> Array:
    x2 = jnp.sum(x * x, axis=-1, keepdims=True)
    t2 = jnp.sum(training * training, axis=-1)
    return jnp.maximum(x2 + t2 - 2 * x @ training.T, 0)


def nearest_training(
    image: ArrayLike, training: ArrayLike
) -> tuple[Int[Array, ""], Float[Array, ""]]:
    """Closest training image in the least-squares sense (§5, Fig. 8G–I).

    Args:
        image: ``(H, W)`` or ``(H, W, C)``.
        training: ``(n, H, W)`` or ``(n, H, W, C)`` of the same image shape.

    Returns:
        ``(index, rms)``: the nearest training image and the root-mean-square pixel difference.
    """
    flat = _flat_training(training)
    x = _checks.float_array(image, "image", dtype=flat.dtype)
    if x.size != flat.shape[1]:
        raise ValueError(
            f"image must have the training images' shape ({flat.shape[1]} values), got {x.shape}"
        )
    d = _squared_distances(x.reshape(1, -1), flat)[0]
    i = jnp.argmin(d).astype(jnp.int32)
    return i, jnp.sqrt(d[i] / flat.shape[1])


def training_nn_distances(training: ArrayLike) -> Float[Array, " n"]:
    """RMS distance of every training image to its nearest other training image."""
    flat = _flat_training(training)
    if flat.shape[0] < 2:
        raise ValueError("training needs at least two images")
    d = _squared_distances(flat, flat)
    d = d.at[jnp.diag_indices(flat.shape[0])].set(jnp.inf)
    return jnp.sqrt(jnp.min(d, axis=1) / flat.shape[1])


def novelty(image: ArrayLike, training: ArrayLike) -> Float[Array, ""]:
    """Distance of ``image`` to its nearest training image over the median nearest-neighbour
    distance among the training images: above 1, the face is farther from every training face
    than training faces typically are from each other (§5: novel faces)."""
    _, d = nearest_training(image, training)
    return d / jnp.median(training_nn_distances(training))


def target_distance(image: ArrayLike, target: ArrayLike) -> Float[Array, ""]:
    """RMS pixel difference between a synthesised face and its global target."""
    a = _checks.float_array(image, "image")
    b = _checks.float_array(target, "target", dtype=a.dtype)
    if a.shape != b.shape:
        raise ValueError(f"target must have the image's shape {a.shape}, got {b.shape}")
    return jnp.sqrt(jnp.mean((a - b) ** 2))


def distinct_sources(result: QuiltResult) -> int:
    """Number of different training images a synthesised face was made from (Fig. 8D–F)."""
    src = np.asarray(result.sources)
    return int(np.unique(src[src >= 0]).size)


def source_map(result: QuiltResult, library: PatchLibrary) -> Int[Array, "*batch H W"]:
    """Per-pixel source training image: that of the last patch placed over the pixel in raster
    order (``-1`` where no patch was placed); the paper's Fig. 8 colour map, ready for a colour
    table. ``result`` may carry leading batch axes (from ``vmap``); so does the map."""
    library = check_library(library)
    g = library.geometry
    rows = np.minimum(np.arange(g.canvas[0]) // g.step[0], g.grid[0] - 1)
    cols = np.minimum(np.arange(g.canvas[1]) // g.step[1], g.grid[1] - 1)
    sources = jnp.asarray(result.sources)
    out = sources[..., rows[:, None], cols[None, :]]
    return out[..., : g.image_shape[0], : g.image_shape[1]]
