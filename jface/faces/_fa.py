"""Factor analyser: the global parametric face model of Mohammed et al. 2009, §3.

An image ``x`` (flattened to ``d`` pixels) is modelled as ``x = μ + F h + ε`` with loadings
``h ~ N(0, I)`` and per-pixel noise ``ε ~ N(0, diag Σ)`` (Eq. 1–3). Everything here works on one
image; batch with ``jax.vmap``. No ``d × d`` matrix is ever formed: the marginal covariance
``C = F Fᵀ + Σ`` enters only through the Woodbury identity and the matrix determinant lemma,

    C⁻¹ = Σ⁻¹ − Σ⁻¹F M⁻¹FᵀΣ⁻¹,   log|C| = log|Σ| + log|M|,   M = I + FᵀΣ⁻¹F  (q × q),

so a log-likelihood or a posterior costs ``O(d q²)`` (``O(d q)`` per image once ``M`` is shared).

A mask of observed pixels restricts every quantity to those pixels (the inpainting posterior of
§6.1): ``Σ⁻¹`` is replaced by ``diag(m / Σ)``, which equals dropping the missing rows of ``F``,
``μ``, ``Σ`` and ``x``.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks

Form = Literal["exact", "ml"]


class FactorDims:
    """Sizes read off ``factors`` (``(..., d, q)``), shared by the factor models."""

    factors: Array

    @property
    def n_features(self) -> int:
        return self.factors.shape[-2]

    @property
    def n_factors(self) -> int:
        return self.factors.shape[-1]


class FactorAnalyser(FactorDims, eqx.Module):
    """A factor analyser ``x = μ + F h + ε`` over images of a fixed shape (Eq. 1–3).

    Attributes:
        mean: ``μ``, ``(d,)`` with ``d = prod(shape)``.
        factors: ``F``, ``(d, q)``; column ``j`` is the ``j``-th basis face.
        noise: diagonal of ``Σ``, ``(d,)``, per-pixel noise variances (positive).
        shape: image shape the model describes (static), e.g. ``(70, 70)``.
    """

    mean: Float[Array, "*batch d"]
    factors: Float[Array, "*batch d q"]
    noise: Float[Array, "*batch d"]
    shape: tuple[int, ...] = eqx.field(static=True)


class Posterior(eqx.Module):
    """Gaussian posterior over factor loadings ``p(h | x) = N(mean, cov)``."""

    mean: Float[Array, "*batch q"]
    cov: Float[Array, "*batch q q"]


# --- validation ------------------------------------------------------------------------------


def check_model(model: Any, name: str = "model", kinds: tuple[type, ...] | None = None) -> None:
    """Raise TypeError unless ``model`` is one of ``kinds`` (default: a FactorAnalyser)."""
    kinds = kinds or (FactorAnalyser,)
    if not isinstance(model, kinds):
        names = " or ".join(k.__name__ for k in kinds)
        raise TypeError(f"{name} must be a {names}, got {type(model).__name__}")


def image_vector(x: ArrayLike, shape: tuple[int, ...], name: str, dtype: Any) -> Array:
    """Validate one image of ``shape`` (or its flattened ``(d,)`` vector); return it flat."""
    arr = _checks.float_array(x, name, dtype=dtype)
    d = math.prod(shape)
    if arr.shape != tuple(shape) and arr.shape != (d,):
        raise ValueError(
            f"{name} must have the model's image shape {tuple(shape)} (or ({d},)), got "
            f"{_checks.describe(arr)}"
        )
    return arr.reshape(d)


def mask_vector(mask: ArrayLike | None, shape: tuple[int, ...], dtype: Any) -> Array:
    """Validate a mask of observed pixels (True = observed); return it flat as 0/1 floats.

    ``None`` means every pixel is observed.
    """
    d = math.prod(shape)
    if mask is None:
        return jnp.ones((d,), dtype)
    if isinstance(mask, (str, bytes)) or mask is None:
        raise TypeError(f"mask must be a boolean array, got {_checks.describe(mask)}")
    try:
        arr = mask if isinstance(mask, jax.Array) else jnp.asarray(mask)
    except TypeError as err:
        raise TypeError(f"mask must be a boolean array, got {_checks.describe(mask)}") from err
    if arr.dtype != jnp.bool_:
        raise TypeError(
            f"mask must be a boolean array (True = observed pixel), got {_checks.describe(arr)}"
        )
    if arr.shape != tuple(shape) and arr.shape != (d,):
        raise ValueError(
            f"mask must have the model's image shape {tuple(shape)} (or ({d},)), got "
            f"{_checks.describe(arr)}"
        )
    if not _checks.is_traced(arr) and not np.any(np.asarray(arr)):
        raise ValueError("mask has no observed pixel (all False): nothing to condition on")
    return arr.reshape(d).astype(dtype)


def form_choice(form: Any) -> bool:
    """True for the exact posterior (with the prior), False for the paper's ML form."""
    return _checks.choice(form, "form", ("exact", "ml")) == "exact"


# --- the Woodbury kernel ---------------------------------------------------------------------


class Terms(eqx.Module):
    """What every Gaussian computation of one image needs (see the module docstring)."""

    chol: Float[Array, "q q"]  # Cholesky factor of M (or of FᵀWF for the ML form)
    proj: Float[Array, " q"]  # b = Fᵀ W (x − μ)
    quad: Float[Array, ""]  # (x − μ)ᵀ W (x − μ)
    logdet_noise: Float[Array, ""]  # Σ_observed log Σ
    n_obs: Float[Array, ""]  # number of observed pixels


def terms(
    mean: Array, factors: Array, noise: Array, x: Array, m: Array, *, prior: bool = True
) -> Terms:
    """Woodbury quantities of one image with observed-pixel weights ``m`` (0/1), ``W = m/Σ``.

    ``M`` depends on ``x`` only through ``m``: with a shared mask it is computed once under
    ``vmap``.
    """
    w = m / noise
    r = (x - mean) * m
    q = factors.shape[-1]
    gram = factors.T @ (w[:, None] * factors)
    if prior:
        gram = gram + jnp.eye(q, dtype=gram.dtype)
    return Terms(
        chol=jnp.linalg.cholesky(gram),
        proj=factors.T @ (w * r),
        quad=jnp.sum(w * r * r),
        logdet_noise=jnp.sum(m * jnp.log(noise)),
        n_obs=jnp.sum(m),
    )


def chol_solve(chol: Array, b: Array) -> Array:
    """Solve ``(L Lᵀ) y = b`` for a lower Cholesky factor ``L``."""
    return jax.scipy.linalg.cho_solve((chol, True), b)


def log_det_chol(chol: Array) -> Array:
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def gaussian_log_likelihood(t: Terms) -> Float[Array, ""]:
    """log N(x_o; μ_o, F_o F_oᵀ + Σ_o) from the Woodbury terms (determinant lemma)."""
    mahalanobis = t.quad - t.proj @ chol_solve(t.chol, t.proj)
    log_2pi = jnp.asarray(math.log(2.0 * math.pi), t.quad.dtype)
    return -0.5 * (t.n_obs * log_2pi + t.logdet_noise + log_det_chol(t.chol) + mahalanobis)


# --- kernels on one flattened image (validated by the public functions) ------------------------


@eqx.filter_jit
def fa_log_likelihood_flat(model: FactorAnalyser, x: Array, m: Array) -> Array:
    return gaussian_log_likelihood(terms(model.mean, model.factors, model.noise, x, m))


@eqx.filter_jit
def fa_posterior_flat(model: FactorAnalyser, x: Array, m: Array, prior: bool) -> Posterior:
    t = terms(model.mean, model.factors, model.noise, x, m, prior=prior)
    q = model.n_factors
    return Posterior(chol_solve(t.chol, t.proj), chol_solve(t.chol, jnp.eye(q, dtype=x.dtype)))


@eqx.filter_jit
def draw_loadings(key: PRNGKeyArray, posterior: Posterior, n: int) -> Float[Array, "n q"]:
    """``n`` draws of ``h`` from a Gaussian posterior."""
    chol = jnp.linalg.cholesky(posterior.cov)
    z = jax.random.normal(key, (n, posterior.mean.shape[-1]), dtype=posterior.mean.dtype)
    return posterior.mean + z @ chol.T


@eqx.filter_jit
def fa_sample(key: PRNGKeyArray, model: FactorAnalyser, n: int, noise: bool) -> Array:
    kh, ke = jax.random.split(key)
    dtype = model.factors.dtype
    h = jax.random.normal(kh, (n, model.n_factors), dtype=dtype)
    x = model.mean + h @ model.factors.T
    if noise:
        x = x + jnp.sqrt(model.noise) * jax.random.normal(ke, x.shape, dtype=dtype)
    return x.reshape((n, *model.shape))
