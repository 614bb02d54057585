"""Affine registration of face images to a template, and un-warping (Mohammed et al. 2009).

§2.2 of *Visio-lization* affine-warps every library face to a standard template shape before its
patches are cut; §4 ends a synthesis by un-warping the face "using the inverse of a randomly chosen
transformation from the training data". This module supplies both steps:

* :func:`fit_affine` — the least-squares affine map between two point sets (closed form).
* :func:`warp` — resample an image under an affine map (bilinear, edges extended).
* :func:`align` — register one image to a template, from landmarks (closed form) or by intensity
  (Levenberg–Marquardt on the affine parameters, coarse to fine); :class:`Alignment`.
* :func:`unwarp` — move a face synthesised in the template frame back into the frame of a
  training face chosen at random (by ``key``).
* :func:`invert_affine`.

Conventions: points are ``(x, y)`` = (column, row) in pixels, pixel centres at integers. A
*transform* is a ``(2, 3)`` matrix ``A`` mapping a point ``t`` of the template frame to the point
``A[:, :2] @ t + A[:, 2]`` of the image frame: the aligned image at ``t`` is the input image at
``A t``. Every function works on one image; batch with ``jax.vmap``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jface import _checks

# Below this share of template pixels inside the image, an intensity alignment is not trusted.
MIN_COVERAGE = 0.5
# The coarsest level of the intensity pyramid keeps at least this many pixels per side.
MIN_LEVEL_SIZE = 8


class Alignment(NamedTuple):
    """One image registered to a template.

    Attributes:
        image: the image resampled into the template frame, the template's ``(H, W)`` (and the
            input's channels).
        transform: ``(2, 3)`` affine map from template pixels to input-image pixels.
        rms: root-mean-square intensity difference to the template over the covered pixels,
            weighted by ``weights`` (after the fitted gain and offset, by intensity).
        coverage: share of template pixels whose source lies inside the input image.
        converged: whether the solver met its tolerance within ``max_steps`` at the finest level
            and the coverage is at least ``MIN_COVERAGE`` (always True from landmarks).
    """

    image: Float[Array, "H W *C"]
    transform: Float[Array, "2 3"]
    rms: Float[Array, ""]
    coverage: Float[Array, ""]
    converged: Bool[Array, ""]


# --- affine algebra ---------------------------------------------------------------------------


def _homogeneous(transform: Array) -> Array:
    bottom = jnp.zeros((1, 3), transform.dtype).at[0, 2].set(1.0)
    return jnp.concatenate([transform, bottom])


def _apply(transform: Array, points: Array) -> Array:
    return points @ transform[:, :2].T + transform[:, 2]


def _invert(transform: Array) -> Array:
    return jnp.linalg.inv(_homogeneous(transform))[:2]


def _check_transform(transform: Any, name: str, *, batch: bool = False) -> Array:
    """A finite, invertible ``(2, 3)`` transform (``(n, 2, 3)`` with ``batch``)."""
    arr = _checks.float_array(transform, name, ndim=3 if batch else 2)
    if arr.shape[-2:] != (2, 3) or (batch and arr.shape[0] == 0):
        want = "(n, 2, 3)" if batch else "(2, 3)"
        raise ValueError(f"{name} must be {want} affine matrices, got {_checks.describe(arr)}")
    if not _checks.is_traced(arr):
        det = np.linalg.det(np.asarray(arr[..., :2], np.float64)).reshape(-1)
        scale = np.abs(np.asarray(arr[..., :2], np.float64)).reshape(len(det), -1).max(axis=1)
        singular = np.flatnonzero(np.abs(det) <= 1e-6 * np.maximum(scale, 1e-30) ** 2)
        if singular.size:
            where = f" (matrix {singular[:5].tolist()})" if batch else ""
            raise ValueError(
                f"{name} must be invertible, got a singular linear part{where} "
                f"(determinant {det[singular[0]]:.3g})"
            )
    return arr


def invert_affine(transform: ArrayLike) -> Float[Array, "2 3"]:
    """The inverse of a ``(2, 3)`` affine transform.

    Raises:
        ValueError: not ``(2, 3)``, not finite, or singular.
    """
    return _invert(_check_transform(transform, "transform"))


def _check_points(points: Any, name: str, dtype=None) -> Array:
    arr = _checks.float_array(points, name, ndim=2, dtype=dtype)
    if arr.shape[1] != 2:
        raise ValueError(f"{name} must be (n, 2) points (x, y), got {_checks.describe(arr)}")
    return arr


def fit_affine(points: ArrayLike, template_points: ArrayLike) -> Float[Array, "2 3"]:
    """The affine transform ``A`` minimising ``Σ_i |A t_i − p_i|²`` (closed-form least squares).

    Args:
        points: ``(n, 2)`` landmarks ``p_i`` in the image, ``(x, y)`` pixels.
        template_points: ``(n, 2)`` the same landmarks ``t_i`` in the template frame.

    Returns:
        ``(2, 3)`` transform from the template frame to the image frame.

    Raises:
        ValueError: shapes differ, fewer than 3 points, NaN/inf, or template points on one line
            (the affine map is then not determined).
    """
    return _fit_affine(*_check_pairs(points, template_points, "points", "template_points"))


def _check_pairs(points: Any, template_points: Any, name: str, template_name: str):
    tp = _check_points(template_points, template_name)
    p = _check_points(points, name, dtype=tp.dtype)
    if p.shape != tp.shape:
        raise ValueError(
            f"{name} and {template_name} must have one shape, got {p.shape} and {tp.shape}"
        )
    if tp.shape[0] < 3:
        raise ValueError(f"need at least 3 {name} for an affine map, got {tp.shape[0]}")
    if not _checks.is_traced(tp):
        centred = np.asarray(tp, np.float64) - np.asarray(tp, np.float64).mean(axis=0)
        s = np.linalg.svd(centred, compute_uv=False)
        if s[1] <= 1e-9 * max(s[0], 1e-30):
            raise ValueError(
                f"{template_name} must not all lie on one line: the affine map is not determined"
            )
    return p, tp


@jax.jit
def _fit_affine(p: Array, tp: Array) -> Array:
    # centred coordinates keep the normal equations well conditioned
    cp, ct = jnp.mean(p, axis=0), jnp.mean(tp, axis=0)
    linear = jnp.linalg.lstsq(tp - ct, p - cp)[0].T
    return jnp.concatenate([linear, (cp - linear @ ct)[:, None]], axis=1)


# --- resampling -------------------------------------------------------------------------------


def _sample(image: Array, x: Array, y: Array) -> tuple[Array, Array]:
    """Bilinear samples of ``image`` at pixel positions ``(x, y)``, edges extended, and whether
    each position lies inside the image (within half a pixel of a pixel centre)."""
    h, w = image.shape[:2]
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0, y - y0
    if image.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]

    def at(yy, xx):
        return image[
            jnp.clip(yy, 0, h - 1).astype(jnp.int32), jnp.clip(xx, 0, w - 1).astype(jnp.int32)
        ]

    top = (1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)
    bottom = (1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1)
    inside = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    return (1 - fy) * top + fy * bottom, inside


def _grid(shape: tuple[int, int], dtype) -> Array:
    ys, xs = jnp.meshgrid(
        jnp.arange(shape[0], dtype=dtype), jnp.arange(shape[1], dtype=dtype), indexing="ij"
    )
    return jnp.stack([xs, ys], axis=-1)


def _warp(image: Array, transform: Array, shape: tuple[int, int]) -> tuple[Array, Array]:
    points = _apply(transform, _grid(shape, transform.dtype))
    return _sample(image, points[..., 0], points[..., 1])


def _check_image(image: Any, name: str, dtype=None) -> Array:
    arr = _checks.float_array(image, name, dtype=dtype)
    if arr.ndim not in (2, 3) or min(arr.shape[:2]) < 2:
        raise ValueError(
            f"{name} must be one image (H, W) or (H, W, C) of at least 2×2 pixels, got "
            f"{_checks.describe(arr)}"
        )
    return arr


def _check_shape(shape: Any, name: str = "shape") -> tuple[int, int]:
    if not isinstance(shape, (tuple, list)) or len(shape) != 2:
        raise TypeError(f"{name} must be (height, width), got {_checks.describe(shape)}")
    return (
        _checks.integer(shape[0], f"{name}[0]", low=1),
        _checks.integer(shape[1], f"{name}[1]", low=1),
    )


def warp(
    image: ArrayLike, transform: ArrayLike, shape: tuple[int, int] | None = None
) -> Float[Array, "H W *C"]:
    """Resample ``image`` under ``transform``: ``out[y, x] = image(A (x, y))`` (bilinear).

    Args:
        image: ``(h, w)`` or ``(h, w, C)``.
        transform: ``(2, 3)`` map from output pixels to ``image`` pixels.
        shape: ``(H, W)`` of the output (default: the image's).

    Returns:
        ``(H, W[, C])``; outside the image its edge pixels are extended.

    Raises:
        ValueError, TypeError: not an image, a transform that is not ``(2, 3)``, finite and
            invertible, a bad shape.
    """
    img = _check_image(image, "image")
    a = _check_transform(transform, "transform").astype(img.dtype)
    shape = img.shape[:2] if shape is None else _check_shape(shape)
    return _warp(img, a, tuple(shape))[0]


# --- registration -----------------------------------------------------------------------------


def _normaliser(shape: tuple[int, int], dtype) -> Array:
    """``(3, 3)`` map from pixel coordinates of a frame to ``[-1, 1]²`` (pixel edges at ±1): the
    same point of a picture has the same coordinates at every resolution of the pyramid."""
    h, w = shape
    return jnp.array([[2 / w, 0, 1 / w - 1], [0, 2 / h, 1 / h - 1], [0, 0, 1]], dtype)


def _to_pixels(m: Array, image_shape, template_shape) -> Array:
    ni, nt = _normaliser(image_shape, m.dtype), _normaliser(template_shape, m.dtype)
    return (jnp.linalg.inv(ni) @ _homogeneous(m) @ nt)[:2]


def _to_normalised(a: Array, image_shape, template_shape) -> Array:
    ni, nt = _normaliser(image_shape, a.dtype), _normaliser(template_shape, a.dtype)
    return (ni @ _homogeneous(a) @ jnp.linalg.inv(nt))[:2]


def _resize(image: Array, factor: int) -> Array:
    if factor == 1:
        return image
    h, w = image.shape[:2]
    shape = (max(1, round(h / factor)), max(1, round(w / factor)), *image.shape[2:])
    return jax.image.resize(image, shape, "linear", antialias=True)


def _photometric_residual(params: Array, image: Array, template: Array, root_w: Array) -> Array:
    """``√w · (g · image(A t) + b − template(t))`` over the template pixels ``t``; ``params`` =
    the normalised affine map (6) then ``g − 1`` and ``b``; the image's edges are extended."""
    shape = template.shape[:2]
    a = _to_pixels(params[:6].reshape(2, 3), image.shape[:2], shape)
    warped = _warp(image, a, shape)[0]
    return root_w * ((1 + params[6]) * warped + params[7] - template)


def _inside(params: Array, image: Array, template: Array) -> Array:
    a = _to_pixels(params[:6].reshape(2, 3), image.shape[:2], template.shape[:2])
    inside = _warp(image, a, template.shape[:2])[1].astype(params.dtype)
    return inside[..., None] if template.ndim == 3 else inside


def _levels(shape: tuple[int, int], levels: int) -> list[int]:
    """Down-sampling factors, coarsest first, none below MIN_LEVEL_SIZE pixels per side."""
    factors = [1]
    while len(factors) < levels and min(shape) / (2 * factors[-1]) >= MIN_LEVEL_SIZE:
        factors.append(2 * factors[-1])
    return factors[::-1]


def _residual(params, args):
    return _photometric_residual(params, *args)


@eqx.filter_jit
def _align_intensity(image, template, weights, start, levels, max_steps, tol):
    # optimistix's damping is in the default float type: solve in it (float64 under jax_enable_x64)
    dtype = template.dtype
    work = jax.dtypes.canonicalize_dtype(jnp.float64)
    shape = template.shape[:2]
    if start is None:  # the template frame stretched over the whole image
        start = _to_pixels(jnp.eye(2, 3, dtype=work), image.shape[:2], shape)
    weights = weights * jnp.ones_like(template)
    image, template, weights, start = (x.astype(work) for x in (image, template, weights, start))
    normalised = _to_normalised(start, image.shape[:2], shape).reshape(-1)
    params = jnp.concatenate([normalised, jnp.zeros(2, start.dtype)])
    solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    root_w = jnp.sqrt(weights)
    for factor in _levels(shape, levels):
        img, tpl = _resize(image, factor), _resize(template, factor)
        # pixels whose source is outside the image at the level's start are left out for the
        # whole level: a mask that followed the solution would reward pushing the face out
        args = (img, tpl, _resize(root_w, factor) * _inside(params, img, tpl))
        sol = optx.least_squares(_residual, solver, params, args, max_steps=max_steps, throw=False)
        params = sol.value
    transform = _to_pixels(params[:6].reshape(2, 3), image.shape[:2], shape)
    root_w = root_w * _inside(params, image, template)
    res = _photometric_residual(params, image, template, root_w)
    rms = jnp.sqrt(jnp.sum(res * res) / jnp.maximum(jnp.sum(root_w * root_w), 1e-12))
    coverage = jnp.mean(_warp(image, transform, shape)[1].astype(transform.dtype))
    converged = (sol.result == optx.RESULTS.successful) & (coverage >= MIN_COVERAGE)
    transform = transform.astype(dtype)
    aligned = _warp(image.astype(dtype), transform, shape)[0]
    return Alignment(aligned, transform, rms.astype(dtype), coverage.astype(dtype), converged)


def align(
    image: ArrayLike,
    template: ArrayLike,
    *,
    landmarks: ArrayLike | None = None,
    template_landmarks: ArrayLike | None = None,
    init: ArrayLike | None = None,
    levels: int = 3,
    max_steps: int = 100,
    tol: float = 1e-4,
    weights: ArrayLike | None = None,
    throw: bool = True,
) -> Alignment:
    """Register one face image to a template by an affine map (§2.2 of Mohammed et al. 2009).

    *From landmarks* (``landmarks`` and ``template_landmarks`` given): the least-squares affine
    map of the landmarks onto the template's (:func:`fit_affine`), in closed form.

    *By intensity* (otherwise): the affine map ``A`` and a gain ``g`` and offset ``b`` that
    minimise ``Σ_t w(t) (g · image(A t) + b − template(t))²`` over the template pixels ``t``
    (bilinear sampling, the image's edges extended), by Levenberg–Marquardt (optimistix), coarse to
    fine over ``levels`` resolutions (halving down to 8 pixels per side), from ``init`` (default:
    the map stretching the template frame over the whole image). The gain and offset absorb
    differences of lighting between the face and the template. Like every local method it needs
    a start within roughly the face's features of the answer (a few pixels and degrees at 64²).

    Args:
        image: ``(h, w)`` or ``(h, w, C)`` float image.
        template: ``(H, W)`` or ``(H, W, C)``: the frame to align to (its intensities are used
            by the intensity alignment and for ``rms``), e.g. the mean of aligned faces.
        landmarks: ``(n, 2)`` ``(x, y)`` pixel positions of ``n ≥ 3`` landmarks in ``image``.
        template_landmarks: ``(n, 2)`` the same landmarks in the template frame.
        init: ``(2, 3)`` starting transform of the intensity alignment.
        levels: number of pyramid levels of the intensity alignment.
        max_steps: solver steps per level.
        tol: relative and absolute tolerance of the solver on the normalised parameters, where
            the frame spans 2 (the default, 1e-4, is 0.003 px at 64²; 1e-6 takes about 1.5× the
            steps and left the largest corner error on 12 warped LFW faces at 0.076 px).
        weights: optional ``(H, W)`` non-negative weight of each template pixel in the
            intensity alignment and ``rms`` (e.g. 1 on the face, 0 on the background).
        throw: raise when an intensity alignment does not converge (checked on concrete values
            only; under ``jax.jit``/``jax.vmap`` read :attr:`Alignment.converged`).

    Returns:
        :class:`Alignment`: the aligned image, the transform (template → image pixels), the rms
        difference to the template, the coverage and the convergence flag.

    Raises:
        TypeError, ValueError: images that are not float images with matching channels,
            landmarks given without their template positions (or of other shapes), an ``init``
            that is not a finite invertible ``(2, 3)`` matrix, and, with ``throw``, an
            intensity alignment that did not converge.
    """
    tpl = _check_image(template, "template")
    img = _check_image(image, "image", dtype=tpl.dtype)
    if img.shape[2:] != tpl.shape[2:]:
        raise ValueError(
            f"image and template must have the same channels, got {_checks.describe(img)} and "
            f"{_checks.describe(tpl)}"
        )
    shape = tpl.shape[:2]
    w = _check_weights(weights, shape, tpl.dtype)
    w = w[..., None] if tpl.ndim == 3 else w
    if (landmarks is None) != (template_landmarks is None):
        raise ValueError("landmarks and template_landmarks must be given together")
    if landmarks is not None:
        if init is not None:
            raise ValueError("init applies to the intensity alignment, not with landmarks")
        pairs = _check_pairs(landmarks, template_landmarks, "landmarks", "template_landmarks")
        transform = _fit_affine(*pairs).astype(tpl.dtype)
        warped, inside = _warp(img, transform, shape)
        inside = inside.astype(tpl.dtype)
        covered = w * (inside[..., None] if tpl.ndim == 3 else inside)
        rms = jnp.sqrt(
            jnp.sum(covered * (warped - tpl) ** 2)
            / jnp.maximum(jnp.sum(covered * jnp.ones_like(tpl)), 1e-12)
        )
        coverage = jnp.mean(inside)
        return Alignment(warped, transform, rms, coverage, jnp.ones((), bool))
    levels = _checks.integer(levels, "levels", low=1)
    max_steps = _checks.integer(max_steps, "max_steps", low=1)
    tol = _checks.real(tol, "tol", low=0.0, open_low=True)
    start = None if init is None else _check_transform(init, "init").astype(tpl.dtype)
    result = _align_intensity(img, tpl, w, start, levels, max_steps, tol)
    rms, coverage = result.rms, result.coverage
    if throw and not _checks.is_traced(result.converged) and not bool(result.converged):
        raise ValueError(
            f"image did not align to the template: after up to {max_steps} solver steps per "
            f"level, rms {float(rms):.3g} and {float(coverage):.0%} of the template inside the "
            f"image (converged needs the solver's tolerance met and ≥ {MIN_COVERAGE:.0%}); start "
            "closer (init, or landmarks), raise max_steps, or check that the image shows a face "
            "framed like the template"
        )
    return result


def _check_weights(weights: Any, shape: tuple[int, int], dtype) -> Array:
    if weights is None:
        return jnp.ones(shape, dtype)
    w = _checks.float_array(weights, "weights", ndim=2, dtype=dtype)
    if w.shape != shape:
        raise ValueError(
            f"weights must have the template's shape {shape}, got {_checks.describe(w)}"
        )
    if not _checks.is_traced(w):
        arr = np.asarray(w)
        if arr.min() < 0 or arr.max() <= 0:
            raise ValueError(
                f"weights must be ≥ 0 and not all 0, got values in [{arr.min():.3g}, "
                f"{arr.max():.3g}]"
            )
    return w


# --- un-warping -------------------------------------------------------------------------------


def unwarp(
    key: PRNGKeyArray,
    image: ArrayLike,
    transforms: ArrayLike,
    shape: tuple[int, int] | None = None,
) -> tuple[Float[Array, "h w *C"], Int[Array, ""]]:
    """Un-warp a face made in the template frame by the inverse of a randomly chosen training
    transformation (the last step of §4 of Mohammed et al. 2009).

    The registration of training face ``i`` maps it to the template by ``A_i⁻¹`` (``A_i`` its
    :attr:`Alignment.transform`); its inverse ``A_i`` carries the template frame back to that
    face's frame, so the result at image pixel ``q`` is ``image(A_i⁻¹ q)``.

    Args:
        key: ``jax.random.key``; chooses ``i`` uniformly (vmap over keys for many faces).
        image: ``(H, W)`` or ``(H, W, C)`` face in the template frame.
        transforms: ``(n, 2, 3)`` training transforms (template → training-image pixels).
        shape: ``(h, w)`` of the training images (default: the image's).

    Returns:
        ``(unwarped, i)``: the face in the frame of training face ``i``, and ``i``.

    Raises:
        TypeError, ValueError: not a key, not an image, transforms that are not finite,
            invertible ``(n, 2, 3)`` matrices, a bad shape.
    """
    key = _checks.key(key)
    img = _check_image(image, "image")
    stack = _check_transform(transforms, "transforms", batch=True).astype(img.dtype)
    shape = img.shape[:2] if shape is None else _check_shape(shape)
    index = jax.random.randint(key, (), 0, stack.shape[0])
    return _warp(img, _invert(stack[index]), tuple(shape))[0], index
