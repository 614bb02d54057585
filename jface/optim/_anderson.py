"""Anderson acceleration of fixed-point iterations ``x ← g(x)`` (Anderson 1965; Walker & Ni
2011).

Plain iteration uses only the newest ``g(x)``. Anderson's method keeps the last ``memory + 1``
values ``g(x_j)`` and residuals ``f_j = g(x_j) − x_j`` and steps to the combination
``Σ α_j g(x_j)`` whose residuals cancel best: ``α = argmin ‖Σ α_j f_j‖`` subject to
``Σ α_j = 1``. It is a multisecant quasi-Newton method on ``g(x) − x = 0``: where plain
iteration contracts slowly (a fixed point with weakly coupled, very different directions), the
combination extrapolates along the slow directions.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Inexact

from jface import _checks

#: Tikhonov regularisation of the residual Gram matrix, relative to its largest diagonal entry:
#: nearly parallel residuals (a converged history) must not give huge, cancelling weights.
_RIDGE = 1e-8


def anderson(
    step: Callable[[Array], Array],
    x0: Inexact[Array, "..."],
    n_iter: int,
    memory: int = 5,
) -> Inexact[Array, "..."]:
    """Iterate ``x ← step(x)`` ``n_iter`` times with Anderson acceleration.

    Each iteration evaluates ``step`` once. With ``memory=0`` this is the plain iteration
    ``x_{k+1} = step(x_k)``, bit for bit.

    Args:
        step: the fixed-point map, array → array of the same shape and dtype (real or complex;
            the residual norm is the Euclidean one, ``Re⟨a, b⟩`` for complex arrays).
        x0: starting point.
        n_iter: number of evaluations of ``step``.
        memory: earlier iterates combined with the newest one (the ``m`` of Anderson(m)).

    Returns:
        The last iterate (after ``n_iter`` steps). Jit- and vmap-compatible; ``n_iter`` and
        ``memory`` are Python integers.
    """
    n_iter = _checks.integer(n_iter, "n_iter", low=0)
    memory = _checks.integer(memory, "memory", low=0)
    if memory == 0 or n_iter == 0:
        return jax.lax.fori_loop(0, n_iter, lambda _, x: step(x), x0)
    size = memory + 1
    values = jnp.zeros((size, *x0.shape), x0.dtype)  # g(x_j), a ring buffer
    residuals = jnp.zeros((size, *x0.shape), x0.dtype)  # conj(f_j), ready for inner products
    gram = jnp.zeros((size, size), jnp.real(x0).dtype)

    def iterate(k, state):
        x, values, residuals, gram = state
        gx = step(x)
        f = gx - x
        slot = k % size
        values = values.at[slot].set(gx)
        residuals = residuals.at[slot].set(jnp.conj(f))
        row = jnp.real(residuals.reshape(size, -1) @ f.reshape(-1))
        gram = gram.at[slot].set(row).at[:, slot].set(row)
        valid = jnp.arange(size) < jnp.minimum(k + 1, size)
        both = valid[:, None] & valid[None, :]
        ridge = _RIDGE * jnp.max(jnp.where(valid, jnp.diagonal(gram), 0.0)) + 1e-30
        system = jnp.where(both, gram, 0.0) + jnp.diag(jnp.where(valid, ridge, 1.0))
        weights = jnp.linalg.solve(system, valid.astype(gram.dtype))
        alpha = weights / jnp.sum(weights)
        x = jnp.tensordot(alpha.astype(values.dtype), values, axes=1)
        return x, values, residuals, gram

    x, *_ = jax.lax.fori_loop(0, n_iter, iterate, (x0, values, residuals, gram))
    return x
