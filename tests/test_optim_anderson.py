"""jface.optim.anderson: Anderson acceleration of fixed-point iterations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import optim


@pytest.fixture(scope="module")
def contraction():
    """``x ← A x + b`` with eigenvalues of A spread over [0, 0.98]: plain iteration needs
    hundreds of steps for the slow directions."""
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(40, 40)))
    a = q @ np.diag(np.linspace(0.0, 0.98, 40)) @ q.T
    b = rng.normal(size=40)
    return jnp.asarray(a), jnp.asarray(b), np.linalg.solve(np.eye(40) - a, b)


def test_memory_zero_is_the_plain_iteration(contraction):
    a, b, _ = contraction
    x = jnp.zeros(40)
    for _ in range(7):
        x = a @ x + b
    np.testing.assert_array_equal(optim.anderson(lambda v: a @ v + b, jnp.zeros(40), 7, 0), x)


def test_acceleration_reaches_the_fixed_point(contraction):
    """On a linear map Anderson(m) is GMRES-like: 40 evaluations with memory 10 reduce the
    error 10⁴-fold where 40 plain steps leave a third of it."""
    a, b, solution = contraction
    step = lambda v: a @ v + b  # noqa: E731
    plain = optim.anderson(step, jnp.zeros(40), 40, 0)
    fast = optim.anderson(step, jnp.zeros(40), 40, 10)
    plain_error = np.linalg.norm(plain - solution) / np.linalg.norm(solution)
    fast_error = np.linalg.norm(fast - solution) / np.linalg.norm(solution)
    assert plain_error > 0.2 and fast_error < 1e-4


def test_complex_states_jit_and_vmap(contraction):
    """The Euclidean inner product of complex states is Re⟨a, b⟩; vmap equals a loop."""
    a, b, solution = contraction
    shift = jnp.asarray([1.0, 1j])  # the same problem, solved for b and for i·b

    ac, bc = a.astype(jnp.complex128), b.astype(jnp.complex128)

    def solve(s):
        return optim.anderson(lambda v: ac @ v + s * bc, jnp.zeros(40, jnp.complex128), 40, 10)

    batched = jax.jit(jax.vmap(solve))(shift)
    looped = jnp.stack([solve(s) for s in shift])
    np.testing.assert_allclose(batched, looped, atol=1e-10)
    np.testing.assert_allclose(batched[1], 1j * solution, atol=1e-3)


@pytest.mark.usefixtures("unchecked")
def test_bad_counts():
    with pytest.raises(ValueError, match="n_iter"):
        optim.anderson(lambda v: v, jnp.zeros(3), -1)
    with pytest.raises(ValueError, match="memory"):
        optim.anderson(lambda v: v, jnp.zeros(3), 3, memory=-2)
