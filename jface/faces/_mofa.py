"""Mixture of factor analysers (Mohammed et al. 2009, §4; Ghahramani & Hinton 1997).

``p(x) = Σ_k π_k N(x; μ_k, F_k F_kᵀ + Σ_k)`` with a diagonal, per-pixel ``Σ_k`` for every
component. One component is a :class:`~jface.faces.FactorAnalyser`; every per-image computation
here is the factor analyser's, vmapped over components and combined in log space.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from jface.faces._fa import (
    FactorAnalyser,
    FactorDims,
    Posterior,
    fa_posterior_flat,
    gaussian_log_likelihood,
    terms,
)


class MixtureOfFactorAnalysers(FactorDims, eqx.Module):
    """``K`` factor analysers with mixing weights (§4 of the paper).

    Attributes:
        weights: ``π``, ``(K,)``, positive, summing to one.
        means: ``μ_k``, ``(K, d)``.
        factors: ``F_k``, ``(K, d, q)``.
        noise: diagonals of ``Σ_k``, ``(K, d)``.
        shape: image shape (static).
    """

    weights: Float[Array, "*batch K"]
    means: Float[Array, "*batch K d"]
    factors: Float[Array, "*batch K d q"]
    noise: Float[Array, "*batch K d"]
    shape: tuple[int, ...] = eqx.field(static=True)

    @property
    def n_components(self) -> int:
        return self.weights.shape[-1]


class MixturePosterior(eqx.Module):
    """Posterior of a mixture: ``p(k | x)`` and, per component, ``p(h | x, k) = N(mean, cov)``."""

    responsibilities: Float[Array, "*batch K"]
    mean: Float[Array, "*batch K q"]
    cov: Float[Array, "*batch K q q"]


def component(model: MixtureOfFactorAnalysers, k: int) -> FactorAnalyser:
    """Component ``k`` as a :class:`FactorAnalyser`."""
    return FactorAnalyser(model.means[k], model.factors[k], model.noise[k], shape=model.shape)


def _joint(model: MixtureOfFactorAnalysers, x: Array, m: Array) -> Array:
    def one(mean, factors, noise):
        return gaussian_log_likelihood(terms(mean, factors, noise, x, m))

    return jnp.log(model.weights) + jax.vmap(one)(model.means, model.factors, model.noise)


@eqx.filter_jit
def mofa_log_likelihood(model: MixtureOfFactorAnalysers, x: Array, m: Array) -> Array:
    return jax.scipy.special.logsumexp(_joint(model, x, m))


@eqx.filter_jit
def mofa_responsibilities(model: MixtureOfFactorAnalysers, x: Array, m: Array) -> Array:
    return jax.nn.softmax(_joint(model, x, m))


@eqx.filter_jit
def mofa_posterior(
    model: MixtureOfFactorAnalysers, x: Array, m: Array, prior: bool
) -> MixturePosterior:
    def one(mean, factors, noise):
        fa = FactorAnalyser(mean, factors, noise, shape=model.shape)
        return fa_posterior_flat(fa, x, m, prior)

    post: Posterior = jax.vmap(one)(model.means, model.factors, model.noise)
    return MixturePosterior(mofa_responsibilities(model, x, m), post.mean, post.cov)


@eqx.filter_jit
def mofa_sample(
    key: PRNGKeyArray, model: MixtureOfFactorAnalysers, n: int, noise: bool
) -> tuple[Array, Array]:
    """Images and the component each was drawn from (the generation steps of §4)."""
    kc, kh, ke = jax.random.split(key, 3)
    dtype = model.factors.dtype
    comp = jax.random.categorical(kc, jnp.log(model.weights), shape=(n,))
    h = jax.random.normal(kh, (n, model.n_factors), dtype=dtype)
    x = model.means[comp] + jnp.einsum("ndq,nq->nd", model.factors[comp], h)
    if noise:
        x = x + jnp.sqrt(model.noise[comp]) * jax.random.normal(ke, x.shape, dtype=dtype)
    return x.reshape((n, *model.shape)), comp
