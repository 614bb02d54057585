"""EM for factor analysers and their mixtures, each fit one jitted ``lax.scan``.

Two E/M steps serve every model of this package:

* :func:`mixture_step` — complete images, ``K ≥ 1`` components (Ghahramani & Hinton 1997 with a
  diagonal ``Σ_k`` per component). A single factor analyser is the case ``K = 1``: its joint
  update of ``[F, μ]`` keeps ``μ`` at the sample mean, so it is the classic FA EM (Bishop 2006,
  §12.2.4).
* :func:`masked_step` — one factor analyser with missing pixels (per image observed-pixel masks).
  Each image gets its own ``M_i = I + FᵀW_iF``; each pixel its own ``(q+1) × (q+1)`` system for
  its row of ``[F, μ]``. The bilinear style model is this step on stacked styles.

The log-likelihood of the parameters entering each iteration comes out of the E-step for free
(Woodbury / determinant lemma, never a ``d × d`` matrix); EM never decreases it.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jface import _checks
from jface.faces._fa import chol_solve, log_det_chol


class EMResult(eqx.Module):
    """What a fit returns.

    Attributes:
        model: the fitted model.
        log_likelihood: mean log-likelihood per image (nats) of the parameters entering each
            iteration, then of the returned model: ``(n_iter + 1,)``. After convergence the
            entries repeat the converged value. Never decreases.
        n_iter: number of EM updates applied.
        converged: whether an iteration improved the log-likelihood by less than ``tol``.
    """

    model: Any
    log_likelihood: Float[Array, " n"]
    n_iter: Int[Array, ""]
    converged: Bool[Array, ""]


def _log_2pi(dtype: Any) -> Array:
    return jnp.asarray(math.log(2.0 * math.pi), dtype)


def run_em(step: Callable, loglik: Callable, params: Any, n_iter: int, tol: Array) -> tuple:
    """Iterate ``step(params) -> (loglik(params), new_params)`` ``n_iter`` times in a scan.

    Stops updating (the scan idles) once an iteration gains less than ``tol`` nats per image.
    Returns ``(params, history (n_iter + 1,), n_updates, converged)``.
    """
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    neg_inf = jnp.asarray(-jnp.inf, dtype)

    def body(carry, _):
        params, prev, done, count = carry

        def frozen(p):
            return prev, p

        ll, new = jax.lax.cond(done, frozen, step, params)
        stop = done | (ll - prev < tol)
        params = jax.tree_util.tree_map(lambda a, b: jnp.where(stop, a, b), params, new)
        return (params, ll, stop, count + jnp.where(stop, 0, 1)), ll

    init = (params, neg_inf, jnp.asarray(False), jnp.asarray(0, jnp.int32))
    (params, _, converged, count), history = jax.lax.scan(body, init, None, length=n_iter)
    final = loglik(params)
    return params, jnp.concatenate([history, final[None]]), count, converged


# --- initialisation --------------------------------------------------------------------------


def pca_init(
    r: Float[Array, "n d"], n_eff: Array, n_factors: int, floor: Array
) -> tuple[Float[Array, "d q"], Float[Array, " d"]]:
    """Factor loadings and noise from the top principal subspace of centred rows ``r``.

    The subspace comes from a deterministic block power iteration (no ``d × d`` matrix, no
    random key); ``F = V (λ − σ²)^½`` is the probabilistic-PCA solution (Tipping & Bishop 1999)
    and ``Σ`` the per-pixel residual variance, floored.
    """
    n, d = r.shape
    k = min(n_factors + 10, n, d)
    dtype = r.dtype
    rows = jnp.arange(n, dtype=dtype)[:, None] + 0.5
    cols = jnp.arange(1, k + 1, dtype=dtype)[None, :]
    omega = jnp.cos(jnp.pi * rows * cols / n)
    basis = _orthonormal((omega.T @ r).T)  # (k, n) @ (n, d): the fast layout on CPU

    def power(_, q):
        return _orthonormal(((r @ q).T @ r).T)

    basis = jax.lax.fori_loop(0, 6, power, basis)
    y = r @ basis
    evals, evecs = jnp.linalg.eigh(y.T @ y)  # ascending
    v = basis @ evecs[:, ::-1]
    # an eigenvector's sign is arbitrary and differs between jit and eager: make each direction's
    # largest entry positive, so that the same data give the same factors however they are run
    largest = v[jnp.argmax(jnp.abs(v), axis=0), jnp.arange(v.shape[1])]
    v = v * jnp.where(largest < 0, -1.0, 1.0).astype(dtype)
    s = jnp.sqrt(jnp.maximum(evals[::-1], 0.0))
    lam = s**2 / n_eff
    s2 = jnp.sum(r * r, axis=0) / n_eff
    top = lam[:n_factors]
    if top.shape[0] < n_factors:  # fewer directions than factors: pad with tiny ones
        top = jnp.concatenate([top, jnp.zeros((n_factors - top.shape[0],), dtype)])
        v = jnp.concatenate([v, jnp.zeros((d, n_factors - v.shape[1]), dtype)], axis=1)
    rest = jnp.maximum(d - n_factors, 1)
    sigma2 = jnp.maximum((jnp.sum(s2) - jnp.sum(top)) / rest, floor)
    factors = v[:, :n_factors] * jnp.sqrt(jnp.maximum(top - sigma2, 0.01 * sigma2))
    noise = jnp.maximum(s2 - jnp.sum(factors**2, axis=1), floor)
    return factors, noise


def _orthonormal(y: Array) -> Array:
    """Orthonormal basis of the columns of a tall ``y`` through the eigendecomposition of its
    small Gram matrix (much faster than a Householder QR on the CPU). Directions of numerically
    zero weight — rank-deficient blocks, e.g. a cluster with fewer members than columns — become
    zero columns instead of noise."""
    for _ in range(2):  # a second pass restores orthogonality lost to rounding
        evals, evecs = jnp.linalg.eigh(y.T @ y)
        keep = evals > 1e3 * jnp.finfo(y.dtype).eps * jnp.maximum(evals[-1], 0.0)
        scale = jnp.where(keep, 1.0 / jnp.sqrt(jnp.where(keep, evals, 1.0)), 0.0)
        y = y @ (evecs * scale[None, :])
    return y


def kmeans(key: Array, x: Float[Array, "n d"], k: int, n_iter: int) -> Float[Array, "n k"]:
    """k-means++ seeding then Lloyd iterations; returns hard assignments as one-hot rows."""
    n = x.shape[0]
    dtype = x.dtype
    sq = jnp.sum(x * x, axis=1)

    def dist(c):
        return jnp.maximum(sq - 2.0 * (x @ c) + c @ c, 0.0)

    k0, key = jax.random.split(key)
    first = x[jax.random.randint(k0, (), 0, n)]
    centres = jnp.zeros((k, x.shape[1]), dtype).at[0].set(first)

    def seed(i, state):
        centres, d2 = state
        pick = jax.random.categorical(jax.random.fold_in(key, i), jnp.log(d2 + 1e-30))
        centres = centres.at[i].set(x[pick])
        return centres, jnp.minimum(d2, dist(x[pick]))

    centres, _ = jax.lax.fori_loop(1, k, seed, (centres, dist(first)))

    def assign(c):
        d2 = sq[:, None] - 2.0 * (x @ c.T) + jnp.sum(c * c, axis=1)[None, :]
        return jax.nn.one_hot(jnp.argmin(d2, axis=1), k, dtype=dtype)

    def lloyd(_, c):
        onehot = assign(c)
        counts = jnp.sum(onehot, axis=0)
        means = (onehot.T @ x) / jnp.maximum(counts, 1.0)[:, None]
        return jnp.where(counts[:, None] > 0, means, c)

    return assign(jax.lax.fori_loop(0, n_iter, lloyd, centres))


# --- complete data: mixtures (K = 1 is a factor analyser) ------------------------------------

Mixture = tuple[Array, Array, Array, Array]  # log weights (K,), means (K,d), F (K,d,q), Σ (K,d)


def _responsibilities(x, x2, params: Mixture):
    """Log-likelihood, responsibilities ``(K, n)``, posterior means ``(K, n, q)`` and the
    per-component posterior covariances ``(K, q, q)`` of complete images.

    Works from ``x`` and the precomputed ``x²`` (both ``(n, d)``) through one matrix product
    for all components (``x @ [A_1, μ_1/Σ_1, …, A_K, μ_K/Σ_K]``, ``A_k = Σ_k⁻¹F_k``), so no
    ``(n, d)`` temporary is made per component and iteration.
    """
    log_w, means, factors, noise = params
    k, d, q = factors.shape
    eye = jnp.eye(q, dtype=x.dtype)
    inv = 1.0 / noise
    a = factors * inv[..., None]
    chol = jnp.linalg.cholesky(eye + jnp.einsum("kdq,kdp->kqp", factors, a))
    stacked = jnp.concatenate([a, (means * inv)[..., None]], axis=-1)  # (K, d, q+1)
    proj = (x @ stacked.transpose(1, 0, 2).reshape(d, k * (q + 1))).reshape(-1, k, q + 1)
    z = proj[..., :q].transpose(1, 0, 2) - jnp.einsum("kd,kdq->kq", means, a)[:, None]
    eh = jax.vmap(lambda c, zk: chol_solve(c, zk.T).T)(chol, z)  # (K, n, q)
    quad = (
        (x2 @ inv.T).T
        - 2.0 * proj[..., q].T
        + jnp.sum(means * means * inv, axis=1)[:, None]
        - jnp.sum(z * eh, axis=2)
    )
    const = d * _log_2pi(x.dtype) + jnp.sum(jnp.log(noise), axis=1) + log_det_chol(chol)
    ll = -0.5 * (const[:, None] + quad)
    cov = jax.vmap(lambda c: chol_solve(c, eye))(chol)
    joint = log_w[:, None] + ll
    lse = jax.scipy.special.logsumexp(joint, axis=0)
    return jnp.mean(lse), jnp.exp(joint - lse), eh, cov


def mixture_step(x: Array, x2: Array, floor: Array, params: Mixture) -> tuple[Array, Mixture]:
    """One EM iteration of a mixture of factor analysers on complete images ``x`` (n, d), with
    ``x2 = x²`` precomputed: the joint update of each component's ``[F_k, μ_k]`` and ``Σ_k``
    (Ghahramani & Hinton 1997)."""
    _, means, factors, noise = params
    n, d = x.shape
    k, _, q = factors.shape
    ll, resp, eh, cov = _responsibilities(x, x2, params)
    counts = jnp.sum(resp, axis=1)
    eht = jnp.concatenate([eh, jnp.ones((k, n, 1), x.dtype)], axis=2)  # (K, n, q+1)
    weighted = resp[..., None] * eht
    sx = (weighted.transpose(0, 2, 1).reshape(k * (q + 1), n) @ x).reshape(k, q + 1, d)
    p = jnp.einsum("kni,knj->kij", eht, weighted)
    p = p.at[:, :q, :q].add(counts[:, None, None] * cov)
    ft = jnp.linalg.solve(p, sx)  # (K, q+1, d): rows of [F_kᵀ; μ_kᵀ]
    sq = resp @ x2  # (K, d): Σ_i r_ik x_i²
    new_noise = jnp.maximum((sq - jnp.sum(ft * sx, axis=1)) / counts[:, None], floor)
    ok = (counts > q + 1.0)[:, None]  # a starved component keeps its parameters (a GEM step)
    new_means = jnp.where(ok, ft[:, q], means)
    new_factors = jnp.where(ok[..., None], ft[:, :q].transpose(0, 2, 1), factors)
    new_noise = jnp.where(ok, new_noise, noise)
    tiny = jnp.asarray(jnp.finfo(x.dtype).tiny, x.dtype)
    log_w = jnp.log(jnp.maximum(counts, tiny) / n)
    return ll, (log_w, new_means, new_factors, new_noise)


@functools.partial(jax.jit, static_argnames=("n_factors",))
def init_single(x: Array, n_factors: int, floor: Array) -> Mixture:
    """PCA initialisation of one factor analyser on centred complete data."""
    n = jnp.asarray(x.shape[0], x.dtype)
    factors, noise = pca_init(x, n, n_factors, floor)
    d = x.shape[1]
    return (jnp.zeros((1,), x.dtype), jnp.zeros((1, d), x.dtype), factors[None], noise[None])


@functools.partial(jax.jit, static_argnames=("n_components", "n_factors", "kmeans_iter"))
def init_mixture(
    key: Array, x: Array, n_components: int, n_factors: int, floor: Array, kmeans_iter: int
) -> Mixture:
    """k-means++ / Lloyd clustering, then a PCA factor analyser per cluster."""
    onehot = kmeans(key, x, n_components, kmeans_iter)
    counts = jnp.sum(onehot, axis=0)
    centres = (onehot.T @ x) / jnp.maximum(counts, 1.0)[:, None]

    def per_cluster(args):
        w, c, n_k = args
        r = jnp.sqrt(w)[:, None] * (x - c)
        return pca_init(r, jnp.maximum(n_k, 1.0), n_factors, floor)

    factors, noise = jax.lax.map(per_cluster, (onehot.T, centres, counts))
    n = x.shape[0]
    log_w = jnp.log((counts + 1.0) / (n + n_components))
    return log_w, centres, factors, noise


@functools.partial(jax.jit, static_argnames=("n_iter",))
def fit_mixture_em(x: Array, params: Mixture, n_iter: int, tol: Array, floor: Array):
    x2 = x * x

    def step(p):
        return mixture_step(x, x2, floor, p)

    def loglik(p):
        return _responsibilities(x, x2, p)[0]

    return run_em(step, loglik, params, n_iter, tol)


def responsibilities(x: Array, params: Mixture) -> Array:
    """Posterior component probabilities ``(K, n)`` of complete images."""
    return _responsibilities(x, x * x, params)[1]


# --- missing pixels: one factor analyser ---------------------------------------------------


def _masked_e_step(x, m, mean, factors, noise):
    n, d = x.shape
    q = factors.shape[1]
    w = m / noise
    r = (x - mean) * m
    b = (w * r) @ factors
    outer = (factors[:, :, None] * factors[:, None, :]).reshape(d, q * q)
    gram = (w @ outer).reshape(n, q, q) + jnp.eye(q, dtype=x.dtype)
    chol = jnp.linalg.cholesky(gram)
    eh = jax.vmap(chol_solve)(chol, b)
    quad = jnp.sum(w * r * r, axis=1) - jnp.sum(b * eh, axis=1)
    const = jnp.sum(m, axis=1) * _log_2pi(x.dtype) + m @ jnp.log(noise) + log_det_chol(chol)
    cov = jax.vmap(chol_solve, in_axes=(0, None))(chol, jnp.eye(q, dtype=x.dtype))
    return jnp.mean(-0.5 * (const + quad)), eh, cov


def masked_step(x: Array, m: Array, floor: Array, params: tuple) -> tuple[Array, tuple]:
    """One EM iteration of a factor analyser on images ``x`` (n, d) observed where ``m`` = 1.

    Joint update of each pixel's row ``[F_j, μ_j]`` from the images that observe it.
    """
    mean, factors, noise = params
    n, d = x.shape
    q = factors.shape[1]
    ll, eh, cov = _masked_e_step(x, m, mean, factors, noise)
    eht = jnp.concatenate([eh, jnp.ones((n, 1), x.dtype)], axis=1)
    ehh = cov + eh[:, :, None] * eh[:, None, :]
    aug = jnp.zeros((n, q + 1, q + 1), x.dtype)
    aug = aug.at[:, :q, :q].set(ehh).at[:, :q, q].set(eh).at[:, q, :q].set(eh).at[:, q, q].set(1)
    p = (aug.reshape(n, -1).T @ m).T.reshape(d, q + 1, q + 1)
    mx = m * x
    sx = (eht.T @ mx).T
    ft = jnp.linalg.solve(p, sx[..., None])[..., 0]
    counts = jnp.sum(m, axis=0)
    new_noise = jnp.maximum((jnp.sum(mx * x, axis=0) - jnp.sum(ft * sx, axis=1)) / counts, floor)
    return ll, (ft[:, q], ft[:, :q], new_noise)


@functools.partial(jax.jit, static_argnames=("n_iter",))
def fit_masked_em(x: Array, m: Array, params: tuple, n_iter: int, tol: Array, floor: Array):
    def step(p):
        return masked_step(x, m, floor, p)

    def loglik(p):
        return _masked_e_step(x, m, *p)[0]

    return run_em(step, loglik, params, n_iter, tol)


# --- shared validation -----------------------------------------------------------------------


def noise_floor_value(variance: Array, noise_floor: float, name: str = "data") -> Array:
    """The absolute noise floor (``noise_floor`` × mean pixel variance); warn about constant
    pixels, whose noise variance it sets.

    Constant data (no variance at all) is refused: with ``ValueError`` for concrete data, and
    under ``jax.jit``/``jax.vmap`` tracing with an error when the compiled fit runs
    (``equinox.error_if``); the warning needs concrete data.
    """
    if _checks.is_traced(variance):
        mean_var = jnp.mean(variance)
        floor = eqx.error_if(
            noise_floor * mean_var,
            mean_var <= 0.0,
            f"{name} is constant: every pixel has zero variance, nothing to model",
        )
        return floor.astype(variance.dtype)
    values = np.asarray(variance)
    mean_var = float(np.mean(values))
    if mean_var <= 0.0:
        raise ValueError(f"{name} is constant: every pixel has zero variance, nothing to model")
    floor = noise_floor * mean_var
    constant = int(np.sum(values <= 1e-12 * mean_var))
    if constant:
        warnings.warn(
            f"{constant} of {values.shape[0]} pixels are constant across the training images "
            f"(zero variance); their noise variance is floored at {floor:.3g} "
            f"(noise_floor={noise_floor:g} × mean pixel variance)",
            UserWarning,
            stacklevel=3,
        )
    return jnp.asarray(floor, variance.dtype)
