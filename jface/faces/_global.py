"""Quilting guided by the global factor models (Mohammed et al. 2009, §4, §6.1, §6.3).

These functions join the patch model (:func:`quilt`, :func:`inpaint`) to the global models of
:mod:`jface.faces` (factor analyser, mixture of factor analysers, bilinear style model):

* :func:`synthesize` — a global target sampled from the model (for a mixture: a component from
  ``π``, then loadings), and quilting restricted to the training images of that component (§4).
* :func:`assign_components` — the component each training image is primarily associated with.
* :func:`inpaint_hypotheses` — global targets from the posterior of the observed pixels (its
  mean, or samples: the multiple hypotheses of Fig. 10I), each filled in by quilting (§6.1).
* :func:`restyle` — the face's loadings under style ``source`` predict its global image in style
  ``target`` (Eq. 8); quilting with a library of style-``target`` images turns that prediction
  into a realistic face (Fig. 12).

The factor models are imported when these functions run, so the patch model works on its own.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jface import _checks
from jface.faces import _poisson
from jface.faces._editing import inpaint
from jface.faces._patches import PatchLibrary, training_images
from jface.faces._quilting import LAM, QuiltResult, check_library, quilt


def _models():
    try:
        from jface.faces import _api, _bilinear, _fa, _mofa
    except ImportError as err:  # pragma: no cover - only without the factor models
        raise ImportError(
            "the global factor models of jface.faces (factor analyser, mixture, bilinear) are "
            "needed here and are not installed in this copy of jface"
        ) from err
    return _api, _fa.FactorAnalyser, _mofa.MixtureOfFactorAnalysers, _bilinear.BilinearModel


def _image_shape(library: PatchLibrary) -> tuple[int, ...]:
    h, w = library.geometry.image_shape
    return (h, w) if library.grey else (h, w, library.channels)


def _check_model_shape(model: Any, library: PatchLibrary, name: str = "model") -> None:
    if tuple(model.shape) != _image_shape(library):
        raise ValueError(
            f"{name} describes images of shape {tuple(model.shape)}, the library "
            f"{_image_shape(library)}"
        )


def assign_components(model: Any, images: ArrayLike) -> Int[Array, " n"]:
    """Component of a mixture each training image is primarily associated with (§4).

    Args:
        model: a ``MixtureOfFactorAnalysers``.
        images: the library's training images, ``(n, H, W)`` or ``(n, H, W, C)``.

    Returns:
        ``(n,)`` int32: ``argmax_k p(k | x_i)``.
    """
    api, _, mixture, _ = _models()
    if not isinstance(model, mixture):
        raise TypeError(f"model must be a MixtureOfFactorAnalysers, got {type(model).__name__}")
    arr, grey = training_images(images)
    arr = arr[..., 0] if grey else arr
    resp = jax.vmap(lambda x: api.responsibilities(model, x))(arr)
    return jnp.argmax(resp, axis=-1).astype(jnp.int32)


def synthesize(
    key: PRNGKeyArray,
    library: PatchLibrary,
    model: Any,
    *,
    assignment: ArrayLike | None = None,
    lam: float = LAM,
    n_best: int | None = None,
    symmetric: bool = True,
    blend: bool = True,
) -> tuple[QuiltResult, Float[Array, "..."], Int[Array, ""]]:
    """A new face: global target from the model, texture by quilting (§4, Fig. 5).

    Args:
        key: ``jax.random.key`` (vmap over keys for many faces).
        library: patch libraries of the model's training images (same image shape).
        model: ``FactorAnalyser`` or ``MixtureOfFactorAnalysers``.
        assignment: for a mixture, ``(n_images,)`` component of every training image
            (:func:`assign_components`); patches then come only from the sampled component's
            images. Required for a mixture.
        lam, n_best, symmetric, blend: as in :func:`quilt`.

    Returns:
        ``(result, target, component)``: the face, its global target, and the sampled component
        (``0`` for a factor analyser).
    """
    api, analyser, mixture, _ = _models()
    key = _checks.single_key(key)
    library = check_library(library)
    if not isinstance(model, (analyser, mixture)):
        raise TypeError(
            "model must be a FactorAnalyser or MixtureOfFactorAnalysers, got "
            f"{type(model).__name__}"
        )
    _check_model_shape(model, library)
    k_model, k_quilt = jax.random.split(key)
    dtype = library.patches.dtype
    if isinstance(model, analyser):
        target = api.sample(k_model, model, 1)[0].astype(dtype)
        return (
            quilt(
                k_quilt, library, target, lam=lam, n_best=n_best, symmetric=symmetric, blend=blend
            ),
            target,
            jnp.zeros((), jnp.int32),
        )
    if assignment is None:
        raise ValueError(
            "assignment (the component of each training image, from assign_components) is "
            "required with a mixture"
        )
    assignment = jnp.asarray(assignment)
    if assignment.shape != (library.n_images,) or not jnp.issubdtype(assignment.dtype, jnp.integer):
        raise ValueError(
            f"assignment must be ({library.n_images},) integers, got {_checks.describe(assignment)}"
        )
    images, comp = api.sample(k_model, model, 1, return_components=True)
    target, comp = images[0].astype(dtype), comp[0].astype(jnp.int32)
    allowed = assignment == comp
    # a component that owns no training image falls back to every image
    allowed = jnp.where(jnp.any(allowed), allowed, jnp.ones_like(allowed))
    result = quilt(
        k_quilt,
        library,
        target,
        lam=lam,
        n_best=n_best,
        symmetric=symmetric,
        allowed=allowed,
        blend=blend,
    )
    return result, target, comp


def inpaint_hypotheses(
    key: PRNGKeyArray,
    library: PatchLibrary,
    model: Any,
    image: ArrayLike,
    mask: ArrayLike,
    n: int = 1,
    *,
    lam: float = LAM,
    n_best: int | None = None,
    symmetric: bool = True,
    form: str = "exact",
) -> tuple[QuiltResult, Float[Array, "n ..."]]:
    """Inpaint a region from the global model's posterior given the observed pixels (§6.1).

    Args:
        key: ``jax.random.key``.
        library: patch libraries.
        model: ``FactorAnalyser`` or ``MixtureOfFactorAnalysers`` of the same image shape.
        image: the face, library's shape.
        mask: ``(H, W)`` boolean, True where to replace.
        n: number of hypotheses. ``n = 1`` uses the posterior mean (the most likely loadings,
            Eq. 5); ``n > 1`` draws the loadings from the posterior (Fig. 10I).
        lam, n_best, symmetric: as in :func:`quilt`.
        form: "exact" (Bayesian posterior) or "ml" (Eq. 5–6 as printed), see
            ``jface.faces.posterior``.

    Returns:
        ``(results, targets)``: a :class:`QuiltResult` with a leading axis of ``n`` and the
        ``n`` global targets.
    """
    api, analyser, _, _ = _models()
    key = _checks.single_key(key)
    library = check_library(library)
    _check_model_shape(model, library)
    n = _checks.integer(n, "n", low=1)
    dtype = library.patches.dtype
    img = _checks.float_array(image, "image", dtype=dtype)
    hole = _poisson.region_mask(mask, library.geometry.image_shape, "mask")
    seen = hole if library.grey else jnp.broadcast_to(hole[..., None], img.shape)
    k_model, k_fill = jax.random.split(key)
    if n == 1:
        post = api.posterior(model, img, ~seen, form=form)
        if isinstance(model, analyser):
            targets = api.reconstruct(model, post.mean)[None]
        else:
            best = int(jnp.argmax(post.responsibilities))
            targets = api.reconstruct(model, post.mean[best], best)[None]
    else:
        targets = api.sample_posterior(k_model, model, img, n, ~seen, form=form)
    targets = targets.astype(dtype)
    keys = jax.random.split(k_fill, n)
    results = [
        inpaint(k, library, img, hole, t, lam=lam, n_best=n_best, symmetric=symmetric)
        for k, t in zip(keys, targets, strict=True)
    ]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *results), targets


def restyle(
    key: PRNGKeyArray,
    library: PatchLibrary,
    model: Any,
    image: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    source: int = 0,
    target: int = 1,
    keep_detail: bool = False,
    lam: float = LAM,
    n_best: int | None = None,
    symmetric: bool = True,
) -> tuple[QuiltResult, Float[Array, "..."]]:
    """Change a face's style (e.g. expression) with the bilinear model (§6.3, Fig. 12).

    Args:
        key: ``jax.random.key``.
        library: patch libraries built from training images **in the target style** only, so
            only patches of that style are pasted.
        model: a ``BilinearModel`` of the library's image shape.
        image: the face in style ``source``.
        mask: optional ``(H, W)`` boolean region to restyle (e.g. the mouth); by default the
            whole face is resynthesised with the prediction as boundary.
        source, target: style indices (e.g. 0 neutral, 1 smiling).
        keep_detail: add the face's own residual outside the model to the prediction (see
            ``jface.faces.transfer``).
        lam, n_best, symmetric: as in :func:`quilt`.

    Returns:
        ``(result, prediction)``: the restyled face and the bilinear model's global image in the
        target style (Eq. 8, Fig. 12C).
    """
    api, _, _, bilinear = _models()
    key = _checks.single_key(key)
    library = check_library(library)
    if not isinstance(model, bilinear):
        raise TypeError(f"model must be a BilinearModel, got {type(model).__name__}")
    _check_model_shape(model, library)
    dtype = library.patches.dtype
    img = _checks.float_array(image, "image", dtype=dtype)
    prediction = api.transfer(model, img, source, target, keep_detail=keep_detail).astype(dtype)
    if mask is None:
        out = quilt(key, library, prediction, lam=lam, n_best=n_best, symmetric=symmetric)
    else:
        out = inpaint(
            key, library, img, mask, prediction, lam=lam, n_best=n_best, symmetric=symmetric
        )
    return out, prediction
