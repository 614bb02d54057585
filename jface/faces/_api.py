"""Public entry points of ``jface.faces``: fitting, likelihoods, posteriors, sampling, transfer.

Per-image functions take one image (the model's shape, or its flattened vector) and an optional
boolean mask of observed pixels; batch them with ``jax.vmap``. Fitting takes the whole training
set and runs one jitted EM scan.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jface import _checks
from jface.faces import _em
from jface.faces._bilinear import BilinearModel, style_block
from jface.faces._em import EMResult
from jface.faces._fa import (
    FactorAnalyser,
    Form,
    Posterior,
    check_model,
    draw_loadings,
    fa_log_likelihood_flat,
    fa_posterior_flat,
    fa_sample,
    form_choice,
    image_vector,
    mask_vector,
)
from jface.faces._mofa import (
    MixtureOfFactorAnalysers,
    MixturePosterior,
    component,
    mofa_log_likelihood,
    mofa_posterior,
    mofa_responsibilities,
    mofa_sample,
)

_IMAGE_MODELS = (FactorAnalyser, MixtureOfFactorAnalysers)


# --- fitting ---------------------------------------------------------------------------------


def _training_data(data: ArrayLike, mask: ArrayLike | None, name: str = "data"):
    """Validate ``(n, *shape)`` training images and an optional observed-pixel mask.

    Value checks (finiteness, empty rows and columns of the mask) look at concrete arrays
    only: under ``jax.jit``/``jax.vmap`` tracing they step aside.
    """
    arr = _checks.float_array(data, name, min_ndim=2, finite=mask is None)
    shape = tuple(arr.shape[1:])
    flat = arr.reshape(arr.shape[0], -1)
    if mask is None:
        return flat, None, shape
    m = mask if isinstance(mask, jax.Array) else np.asarray(mask)
    if m.dtype != np.bool_:
        raise TypeError(
            f"mask must be a boolean array (True = observed), got {_checks.describe(m)}"
        )
    if m.shape != arr.shape:
        raise ValueError(f"mask must have the shape of {name}, {arr.shape}, got {m.shape}")
    m = m.reshape(flat.shape)
    if _checks.is_traced(m):
        return flat, m, shape
    m = np.asarray(m)
    if not _checks.is_traced(flat):
        observed_values = np.asarray(flat)[m]
        if not np.all(np.isfinite(observed_values)):
            bad = int(np.sum(~np.isfinite(observed_values)))
            raise ValueError(
                f"{name} must be finite where observed, got {bad} NaN or infinite value(s)"
            )
    empty_rows = np.flatnonzero(~m.any(axis=1))
    if empty_rows.size:
        raise ValueError(f"mask has no observed pixel in image(s) {empty_rows[:10].tolist()}")
    unseen = np.flatnonzero(~m.any(axis=0))
    if unseen.size:
        raise ValueError(
            f"{unseen.size} pixel(s) are observed in no training image (first: flat index "
            f"{int(unseen[0])}): the model cannot learn them"
        )
    return flat, jnp.asarray(m), shape


def _fit_settings(n: int, d: int, n_factors: Any, n_iter: Any, tol: Any, noise_floor: Any):
    n_factors = _checks.integer(n_factors, "n_factors", low=1)
    if n_factors >= d:
        raise ValueError(f"n_factors={n_factors} must be smaller than the pixel count {d}")
    if n <= n_factors:
        raise ValueError(
            f"need more training images than factors: got {n} image(s) for n_factors={n_factors}"
        )
    n_iter = _checks.integer(n_iter, "n_iter", low=1)
    tol = -math.inf if tol is None else _checks.real(tol, "tol", low=0.0)
    noise_floor = _checks.real(noise_floor, "noise_floor", low=0.0, open_low=True)
    return n_factors, n_iter, tol, noise_floor


def _fit_fa(flat, m, shape, n_factors, n_iter, tol, noise_floor) -> EMResult:
    dtype = flat.dtype
    tol_arr = jnp.asarray(tol, dtype)
    # a traced mask may miss pixels: the masked EM, which equals the complete one on full masks
    if m is None or (not _checks.is_traced(m) and bool(np.all(np.asarray(m)))):
        mu = jnp.mean(flat, axis=0)
        x = flat - mu
        floor = _em.noise_floor_value(jnp.mean(x * x, axis=0), noise_floor)
        params = _em.init_single(x, n_factors, floor)
        params, hist, count, conv = _em.fit_mixture_em(x, params, n_iter, tol_arr, floor)
        _, means, factors, noise = params
        mean, factors, noise = means[0] + mu, factors[0], noise[0]
    else:
        mf = m.astype(dtype)
        counts = jnp.sum(mf, axis=0)
        mu = jnp.sum(jnp.where(m, flat, 0.0), axis=0) / counts
        x = jnp.where(m, flat - mu, 0.0)
        floor = _em.noise_floor_value(jnp.sum(x * x, axis=0) / counts, noise_floor)
        _, _, f0, n0 = _em.init_single(x, n_factors, floor)
        params = (jnp.zeros_like(mu), f0[0], n0[0])
        params, hist, count, conv = _em.fit_masked_em(x, mf, params, n_iter, tol_arr, floor)
        mean, factors, noise = params[0] + mu, params[1], params[2]
    model = FactorAnalyser(mean, factors, noise, shape=shape)
    return EMResult(model, hist, count, conv)


def fit_factor_analyser(
    data: ArrayLike,
    n_factors: int = 8,
    *,
    mask: ArrayLike | None = None,
    n_iter: int = 40,
    tol: float | int | None = None,
    noise_floor: float | int = 1e-4,
) -> EMResult:
    """Fit a factor analyser ``x = μ + F h + ε`` by EM (§3 of Mohammed et al. 2009).

    PCA initialisation, then ``n_iter`` EM iterations in one jitted ``lax.scan`` (the paper uses
    40 iterations and 8 factors). With ``mask``, pixels where it is False are missing: the EM
    integrates them out exactly (per-image posteriors from the observed pixels, per-pixel
    updates from the images that observe them).

    Args:
        data: training images ``(n, *shape)`` (or vectors ``(n, d)``), float32/float64.
            Missing pixels (mask False) may hold anything, NaN included.
        n_factors: ``q``, the number of factors.
        mask: optional boolean ``(n, *shape)``, True where a pixel is observed.
        n_iter: maximum number of EM iterations.
        tol: stop once an iteration gains less than ``tol`` nats per image (default: never).
        noise_floor: lower bound of each pixel's noise variance, relative to the mean pixel
            variance of the data (keeps constant pixels from driving the likelihood to ∞).

    Returns:
        :class:`EMResult` with the :class:`FactorAnalyser` and the log-likelihood history.

    Raises:
        TypeError: non-floating data, non-boolean mask.
        ValueError: NaN/inf (where observed), no more images than factors, ``n_factors ≥ d``,
            a mask leaving an image or a pixel with no observation, constant data.

    Warns:
        UserWarning: some pixels are constant across the images (their noise is floored).
    """
    flat, m, shape = _training_data(data, mask)
    settings = _fit_settings(flat.shape[0], flat.shape[1], n_factors, n_iter, tol, noise_floor)
    return _fit_fa(flat, m, shape, *settings)


def fit_mixture(
    key: PRNGKeyArray,
    data: ArrayLike,
    n_components: int,
    n_factors: int = 8,
    *,
    n_iter: int = 40,
    tol: float | int | None = None,
    noise_floor: float | int = 1e-4,
    kmeans_iter: int = 10,
) -> EMResult:
    """Fit a mixture of factor analysers by EM (§4; Ghahramani & Hinton 1997).

    Each component has its own mean, factors and per-pixel noise. Initialisation: k-means++
    seeding and ``kmeans_iter`` Lloyd iterations, then a PCA factor analyser per cluster.
    Responsibilities are computed in log space (log-sum-exp), so images whose likelihoods
    underflow float32 are still assigned correctly.

    Args:
        key: random key for the k-means++ seeding.
        data: training images ``(n, *shape)``, float32/float64, finite.
        n_components: ``K``.
        n_factors, n_iter, tol, noise_floor: as for :func:`fit_factor_analyser`.
        kmeans_iter: Lloyd iterations after seeding.

    Returns:
        :class:`EMResult` with the :class:`MixtureOfFactorAnalysers`.

    Raises:
        TypeError, ValueError: as for :func:`fit_factor_analyser`; fewer images than components.
    """
    flat, _, shape = _training_data(data, None)
    n, d = flat.shape
    n_factors, n_iter, tol, noise_floor = _fit_settings(n, d, n_factors, n_iter, tol, noise_floor)
    n_components = _checks.integer(n_components, "n_components", low=1)
    if n < n_components * (n_factors + 1):
        raise ValueError(
            f"need at least n_components × (n_factors + 1) = {n_components * (n_factors + 1)} "
            f"training images, got {n}"
        )
    kmeans_iter = _checks.integer(kmeans_iter, "kmeans_iter", low=0)
    mu = jnp.mean(flat, axis=0)
    x = flat - mu
    floor = _em.noise_floor_value(jnp.mean(x * x, axis=0), noise_floor)
    params = _em.init_mixture(key, x, n_components, n_factors, floor, kmeans_iter)
    params, hist, count, conv = _em.fit_mixture_em(
        x, params, n_iter, jnp.asarray(tol, flat.dtype), floor
    )
    log_w, means, factors, noise = params
    weights = jax.nn.softmax(log_w)
    model = MixtureOfFactorAnalysers(weights, means + mu, factors, noise, shape=shape)
    return EMResult(model, hist, count, conv)


def fit_bilinear(
    images: ArrayLike,
    n_factors: int = 8,
    *,
    observed: ArrayLike | None = None,
    n_iter: int = 40,
    tol: float | int | None = None,
    noise_floor: float | int = 1e-4,
) -> EMResult:
    """Fit the asymmetric bilinear model ``x_ij = μ_j + F_j h_i + ε_ij`` (Eq. 7).

    Args:
        images: ``(n, S, *shape)``: individual ``i`` in style ``j`` (e.g. 0 neutral, 1 smiling).
        n_factors: ``q``, the dimension of the identity loadings ``h_i``.
        observed: optional boolean ``(n, S)``: which styles each individual was seen in (images
            of unseen styles may hold anything); by default all.
        n_iter, tol, noise_floor: as for :func:`fit_factor_analyser`.

    Returns:
        :class:`EMResult` with the :class:`BilinearModel`.

    Raises:
        TypeError, ValueError: as for :func:`fit_factor_analyser`; fewer than two styles; an
            individual seen in no style; a style seen in nobody.
    """
    arr = _checks.float_array(images, "images", min_ndim=3, finite=observed is None)
    n, s = arr.shape[:2]
    if s < 2:
        raise ValueError(
            f"images must hold at least 2 styles on axis 1, got {_checks.describe(arr)}"
        )
    mask = None
    if observed is not None:
        obs = np.asarray(observed)
        if obs.dtype != np.bool_ or obs.shape != (n, s):
            raise ValueError(
                f"observed must be a boolean array of shape ({n}, {s}), got {_checks.describe(obs)}"
            )
        mask = np.broadcast_to(obs.reshape(n, s, *([1] * (arr.ndim - 2))), arr.shape)
    flat, m, shape = _training_data(arr, mask, "images")
    settings = _fit_settings(flat.shape[0], flat.shape[1], n_factors, n_iter, tol, noise_floor)
    result = _fit_fa(flat, m, shape, *settings)
    return EMResult(
        BilinearModel(result.model), result.log_likelihood, result.n_iter, result.converged
    )


# --- per-image inference ---------------------------------------------------------------------


def _prepare(model: Any, x: ArrayLike, mask: ArrayLike | None) -> tuple[Array, Array]:
    check_model(model, kinds=_IMAGE_MODELS)
    dtype = model.factors.dtype
    return image_vector(x, model.shape, "x", dtype), mask_vector(mask, model.shape, dtype)


def _batch_shape(model: Any, x: ArrayLike) -> tuple[int, ...]:
    """The leading axes of ``x`` before one image (of the model's shape, or flattened)."""
    shape, dims = tuple(model.shape), tuple(np.shape(x))
    if len(dims) > len(shape) and dims[len(dims) - len(shape) :] == shape:
        return dims[: len(dims) - len(shape)]
    if len(dims) > 1 and dims[-1] == math.prod(shape) and len(shape) > 1:
        return dims[:-1]
    return ()  # one image (or a shape that image_vector refuses by name)


def _per_image(one, model: Any, x: ArrayLike, mask: ArrayLike | None):
    """``one(x_flat, mask_flat)`` on an image, or mapped over the leading axes of a batch with
    the mask shared, the results given the batch's leading axes."""
    check_model(model, kinds=_IMAGE_MODELS)
    batch = _batch_shape(model, x)
    if not batch:
        return one(*_prepare(model, x, mask))
    dtype = model.factors.dtype
    flat = _checks.float_array(x, "x", dtype=dtype).reshape(-1, math.prod(model.shape))
    out = jax.vmap(one, in_axes=(0, None))(flat, mask_vector(mask, model.shape, dtype))
    return jax.tree.map(lambda a: a.reshape(*batch, *a.shape[1:]), out)


def log_likelihood(model: Any, x: ArrayLike, mask: ArrayLike | None = None) -> Float[Array, "*b"]:
    """log p(x) of an image (of its observed pixels, with ``mask``), in nats; of every image of
    a batch ``(*b, *shape)`` at once (as scikit-learn's ``score_samples``).

    For a factor analyser ``log N(x; μ, F Fᵀ + Σ)`` by the determinant lemma and Woodbury
    (``O(d q²)``, no ``d × d`` matrix; under ``vmap`` with a shared mask the ``q × q`` system is
    built once); for a mixture the log-sum-exp over components.

    Args:
        model: :class:`FactorAnalyser` or :class:`MixtureOfFactorAnalysers`.
        x: one image of the model's shape (or flattened), or a batch ``(*b, *shape)`` (or
            ``(*b, d)``).
        mask: optional boolean, the image's shape, True where observed (default: all); one
            mask for every image of a batch.

    Returns:
        ``(*b,)`` log-likelihoods (a scalar for one image).

    Raises:
        TypeError, ValueError: wrong model type, shape mismatch, NaN, a mask without any
            observed pixel.
    """
    if isinstance(model, FactorAnalyser):
        return _per_image(lambda xv, m: fa_log_likelihood_flat(model, xv, m), model, x, mask)
    return _per_image(lambda xv, m: mofa_log_likelihood(model, xv, m), model, x, mask)


def posterior(
    model: Any, x: ArrayLike, mask: ArrayLike | None = None, *, form: Form = "exact"
) -> Posterior | MixturePosterior:
    """Posterior over the factor loadings of an image, from its observed pixels (§6.1); for a
    batch ``(*b, *shape)`` (or ``(*b, d)``) of images and one shared mask, every field gains the
    leading axes ``b``.

    ``form="exact"`` (default) is the Bayesian posterior under the ``N(0, I)`` prior of Eq. 3:

        E[h] = (I + FᵀΣ⁻¹F)⁻¹ FᵀΣ⁻¹ (x − μ),   Cov[h] = (I + FᵀΣ⁻¹F)⁻¹.

    ``form="ml"`` is what Eq. 5–6 of the paper print: the same without the identity, i.e. the
    generalised-least-squares / maximum-likelihood estimate of ``h`` and its sampling covariance
    ``(FᵀΣ⁻¹F)⁻¹``. It ignores the prior, so it does not shrink loadings towards 0: with few
    observed pixels (large holes) it overfits them and its "posterior" is too wide. The two agree
    when ``FᵀΣ⁻¹F ≫ I`` (many well-explained pixels). With a mask, only the observed rows of
    ``F``, ``μ``, ``Σ`` and ``x`` enter (the paper's inpainting rule).

    For a mixture: the responsibilities ``p(k | x)`` and per-component posteriors.

    Raises:
        TypeError, ValueError: as for :func:`log_likelihood`; ``form="ml"`` with fewer observed
            pixels than factors.
    """
    check_model(model, kinds=_IMAGE_MODELS)
    m = mask_vector(mask, model.shape, model.factors.dtype)
    prior = form_choice(form)
    if not prior and not _checks.is_traced(m) and float(jnp.sum(m)) < model.n_factors:
        raise ValueError(
            f"form='ml' needs at least n_factors={model.n_factors} observed pixels, got "
            f"{int(jnp.sum(m))}; use form='exact'"
        )
    if isinstance(model, FactorAnalyser):
        return _per_image(lambda xv, m: fa_posterior_flat(model, xv, m, prior), model, x, mask)
    return _per_image(lambda xv, m: mofa_posterior(model, xv, m, prior), model, x, mask)


def responsibilities(
    model: MixtureOfFactorAnalysers, x: ArrayLike, mask: ArrayLike | None = None
) -> Float[Array, " K"]:
    """``p(k | x)`` of one image under a mixture (the posterior component); sums to one."""
    check_model(model, kinds=(MixtureOfFactorAnalysers,))
    xv, m = _prepare(model, x, mask)
    return mofa_responsibilities(model, xv, m)


def _count(n: Any) -> int:
    return _checks.integer(n, "n", low=1)


def sample(
    key: PRNGKeyArray, model: Any, n: int, *, noise: bool = False, return_components: bool = False
) -> Float[Array, "n ..."] | tuple[Float[Array, "n ..."], Int[Array, " n"]]:
    """Draw ``n`` images from a factor analyser or mixture (§3, §4).

    Loadings from the prior ``N(0, I)`` (a component from ``π`` first, for a mixture), then
    ``μ + F h``; the per-pixel noise ``ε`` is left out as in the paper unless ``noise=True``.

    Returns:
        images ``(n, *shape)``; with ``return_components`` (mixtures only) also the component
        index of each image.
    """
    key = _checks.single_key(key)
    check_model(model, kinds=_IMAGE_MODELS)
    n = _count(n)
    if isinstance(model, FactorAnalyser):
        if return_components:
            raise ValueError("return_components needs a MixtureOfFactorAnalysers")
        return fa_sample(key, model, n, bool(noise))
    images, comp = mofa_sample(key, model, n, bool(noise))
    return (images, comp) if return_components else images


def sample_posterior(
    key: PRNGKeyArray,
    model: Any,
    x: ArrayLike,
    n: int,
    mask: ArrayLike | None = None,
    *,
    form: Form = "exact",
) -> Float[Array, "n ..."]:
    """``n`` hypotheses ``μ + F h`` with ``h`` drawn from the posterior of one image (§6.1).

    With a mask these are the "multiple hypotheses" global targets of inpainting (Fig. 10I). For
    a mixture each draw first picks a component from ``p(k | x)``.
    """
    key = _checks.single_key(key)
    n = _count(n)
    post = posterior(model, x, mask, form=form)
    if isinstance(model, FactorAnalyser):
        h = draw_loadings(key, post, n)
        return (model.mean + h @ model.factors.T).reshape((n, *model.shape))
    return _mixture_hypotheses(key, model, post, n)


@eqx.filter_jit
def _mixture_hypotheses(key, model, post, n):
    kc, kh = jax.random.split(key)
    comp = jax.random.categorical(kc, jnp.log(post.responsibilities), shape=(n,))
    keys = jax.random.split(kh, n)

    def one(k, c):
        h = draw_loadings(k, Posterior(post.mean[c], post.cov[c]), 1)[0]
        return model.means[c] + model.factors[c] @ h

    return jax.vmap(one)(keys, comp).reshape((n, *model.shape))


def reconstruct(model: Any, h: ArrayLike, k: int | None = None) -> Float[Array, "..."]:
    """The noise-free image ``μ + F h`` (of component ``k`` for a mixture), model's shape."""
    check_model(model, kinds=_IMAGE_MODELS)
    if isinstance(model, MixtureOfFactorAnalysers):
        if k is None:
            raise ValueError("k (the component) is required for a MixtureOfFactorAnalysers")
        model = component(model, k)
    hv = _checks.float_array(h, "h", ndim=1, dtype=model.factors.dtype)
    if hv.shape != (model.n_factors,):
        raise ValueError(f"h must have shape ({model.n_factors},), got {_checks.describe(hv)}")
    return (model.mean + model.factors @ hv).reshape(model.shape)


def get_component(model: MixtureOfFactorAnalysers, k: int) -> FactorAnalyser:
    """Component ``k`` of a mixture as a :class:`FactorAnalyser`."""
    check_model(model, kinds=(MixtureOfFactorAnalysers,))
    return component(model, _checks.integer(k, "k", low=0, high=model.n_components - 1))


def style(model: BilinearModel, j: int) -> FactorAnalyser:
    """Style ``j`` of a bilinear model as a :class:`FactorAnalyser` ``(μ_j, F_j, Σ_j)``."""
    check_model(model, kinds=(BilinearModel,))
    return style_block(model, _checks.integer(j, "j", low=0, high=model.n_styles - 1))


def transfer(
    model: BilinearModel,
    x: ArrayLike,
    source: int = 0,
    target: int = 1,
    mask: ArrayLike | None = None,
    *,
    form: Form = "exact",
    keep_detail: bool = False,
) -> Float[Array, "..."]:
    """Predict an individual's image in style ``target`` from its image in style ``source``.

    ``h* = E[h | x_source]`` (Eq. 8, from the observed pixels with ``mask``; ``form="ml"`` is the
    paper's printed form without the prior, see :func:`posterior`), then the global target
    ``μ_target + F_target h*`` of §6.3 — the posterior-predictive mean of the stacked model.

    With ``keep_detail=True`` the source's own residual ``x − (μ_source + F_source h*)`` (its
    detail outside the model's subspace, on observed pixels) is added back: the model then only
    supplies the *change* of style, which is what an edit of a real image usually wants.
    """
    src, tgt = style(model, source), style(model, target)
    post = posterior(src, x, mask, form=form)
    out = tgt.mean + tgt.factors @ post.mean
    if keep_detail:
        xv = image_vector(x, src.shape, "x", src.factors.dtype)
        m = mask_vector(mask, src.shape, src.factors.dtype)
        out = out + m * (xv - src.mean - src.factors @ post.mean)
    return out.reshape(tgt.shape)
