"""Particle swarm: standard test functions, invariants, boundary handling, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface.optim import PSOResult, pso
from jface.optim._pso import _bound, _delta, _neighbourhood_best


def sphere(x):
    return jnp.sum((x - 1.0) ** 2)


def rosenbrock(x):
    return jnp.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)


def rastrigin(x):
    return 10.0 * x.shape[0] + jnp.sum(x**2 - 10.0 * jnp.cos(2.0 * jnp.pi * x))


def box(n, r):
    return (-r * np.ones(n), r * np.ones(n))


@pytest.fixture(scope="module")
def rastrigin_runs():
    """Best-so-far histories of 8 single-trial Rastrigin-10D runs per topology, ``(8, 101)``."""
    return {
        topology: np.concatenate(
            [
                pso(jax.random.key(i), rastrigin, box(10, 5.12), topology=topology).history
                for i in range(8)
            ]
        )
        for topology in ("lbest", "gbest")
    }


def test_sphere_reaches_the_minimum(key):
    result = pso(key, sphere, box(5, 5.0))
    assert isinstance(result, PSOResult)
    np.testing.assert_allclose(result.params, np.ones(5), atol=2e-2)
    assert float(result.loss) < 1e-3
    assert float(result.loss) == pytest.approx(float(sphere(result.params)), rel=1e-5, abs=1e-7)


def test_rosenbrock_reaches_the_valley_minimum(key):
    result = pso(key, rosenbrock, box(2, 2.0), n_epochs=200, topology="gbest")
    np.testing.assert_allclose(result.params, [1.0, 1.0], atol=1e-2)


def test_rastrigin_10d_reaches_the_low_basin(rastrigin_runs):
    # random points score ~180 on average; a working swarm ends near the origin's basins
    assert np.median(rastrigin_runs["gbest"][:, -1]) < 30.0
    assert np.median(rastrigin_runs["lbest"][:, -1]) < 40.0


def test_lbest_converges_slower_than_gbest(rastrigin_runs):
    # [KM02]: gbest exploits (fast, low final loss on this budget); lbest keeps exploring
    lbest, gbest = rastrigin_runs["lbest"], rastrigin_runs["gbest"]
    assert np.all(np.median(lbest[:, 50:], axis=0) > np.median(gbest[:, 50:], axis=0))


def test_history_is_monotone_and_ends_at_the_trial_best(key):
    result = pso(key, rastrigin, box(4, 5.12), n_agents=10, n_epochs=30, n_trials=2)
    assert result.history.shape == (2, 31)
    assert np.all(np.diff(np.asarray(result.history), axis=1) <= 0)
    np.testing.assert_array_equal(result.history[:, -1], result.trial_losses)
    assert int(result.best_trial) == int(np.argmin(result.trial_losses))
    assert float(result.loss) == float(np.min(result.trial_losses))
    np.testing.assert_array_equal(result.params, result.trial_params[int(result.best_trial)])


def test_same_seed_same_result_and_trials_differ(key):
    # the same settings as the test above: one compile serves both
    a = pso(key, rastrigin, box(4, 5.12), n_agents=10, n_epochs=30, n_trials=2)
    b = pso(key, rastrigin, box(4, 5.12), n_agents=10, n_epochs=30, n_trials=2)
    c = pso(jax.random.key(1), rastrigin, box(4, 5.12), n_agents=10, n_epochs=30, n_trials=2)
    np.testing.assert_array_equal(a.history, b.history)
    np.testing.assert_array_equal(a.params, b.params)
    assert not np.array_equal(a.history[0], a.history[1])
    assert not np.array_equal(a.history, c.history)


def test_cyclic_dimension_finds_the_minimum_across_the_wrap(key):
    # minimum at angle 0.05 ≡ 2π + 0.05: only reachable fast by wrapping around 2π
    def loss(x):
        return 1.0 - jnp.cos(x[0] - 0.05)

    result = pso(key, loss, ([0.0], [2 * np.pi]), cyclic=[True], n_agents=10, n_epochs=60)
    angle = float(result.params[0])
    assert 0.0 <= angle < 2 * np.pi
    assert min(abs(angle - 0.05), abs(angle - 0.05 - 2 * np.pi)) < 1e-2


def test_delta_is_the_shortest_cyclic_distance():
    target = jnp.array([[0.95, 0.95]])
    x = jnp.array([[0.05, 0.05]])
    d = _delta(target, x, jnp.array([True, False]))
    np.testing.assert_allclose(d, [[-0.1, 0.9]], atol=1e-6)


@pytest.mark.parametrize("boundary", ["random_absorb", "nearest_absorb", "reflect", "periodic"])
def test_boundary_handling_keeps_positions_in_the_box(boundary):
    x = jnp.array([[-0.3, 0.5, 1.2, 1.7]])
    v = jnp.array([[-1.0, 0.2, 1.0, 1.0]])
    r = jnp.array([[0.25, 0.9, 0.75, 0.6]])
    cyclic = jnp.array([False, False, False, True])
    nx, nv = _bound(r, x, v, cyclic, boundary)
    expected = {
        "random_absorb": ([0.25, 0.5, 0.75, 0.7], [0.0, 0.2, 0.0, 1.0]),
        "nearest_absorb": ([0.0, 0.5, 1.0, 0.7], [0.0, 0.2, 0.0, 1.0]),
        "reflect": ([0.3, 0.5, 0.8, 0.7], [1.0, 0.2, -1.0, 1.0]),
        "periodic": ([0.7, 0.5, 0.2, 0.7], [-1.0, 0.2, 1.0, 1.0]),
    }[boundary]
    np.testing.assert_allclose(nx, [expected[0]], atol=1e-6)
    np.testing.assert_allclose(nv, [expected[1]], atol=1e-6)


@pytest.mark.parametrize("boundary", ["random_absorb", "nearest_absorb", "reflect", "periodic"])
def test_every_evaluated_point_lies_in_the_bounds(key, boundary):
    # the minimum lies outside the box: agents press against the bound all run long
    seen = []

    def loss(x):
        jax.debug.callback(lambda p: seen.append(np.asarray(p)), x)
        return jnp.sum((x - 3.0) ** 2)

    # 30 epochs: the absorbing and reflecting strategies end within 0.2 of the corner for 20 of
    # 20 seeds (15: not all)
    result = pso(key, loss, box(2, 1.0), n_agents=6, n_epochs=30, boundary=boundary)
    points = np.stack(seen)
    assert points.shape[0] >= 6 * 31
    assert np.all(points >= -1.0) and np.all(points <= 1.0)
    if boundary != "periodic":  # wrapping sends an agent pressing on a bound to the far side
        np.testing.assert_allclose(result.params, [1.0, 1.0], atol=0.2)


def test_lbest_sees_only_its_ring_neighbours():
    p = jnp.arange(5.0)[:, None]
    ps = jnp.array([5.0, 4.0, 3.0, 9.0, 0.5])
    g = _neighbourhood_best(p, ps, "lbest")
    # agent i sees i-1, i, i+1 (ring): best indices 4, 2, 2, 4, 4
    np.testing.assert_array_equal(g[:, 0], [4.0, 2.0, 2.0, 4.0, 4.0])
    np.testing.assert_array_equal(_neighbourhood_best(p, ps, "gbest")[:, 0], [4.0] * 5)


def test_nan_losses_are_contained_and_counted(key):
    # the bad region x > 0.5 holds the would-be minimum, yet its NaNs never become the best
    def loss(x):
        return jnp.where(x[0] > 0.5, jnp.nan, (x[0] - 0.3) ** 2 + x[1] ** 2)

    result = pso(key, loss, box(2, 1.0), n_agents=12, n_epochs=30, n_trials=2)
    assert np.all(np.isfinite(result.history))
    assert np.all(np.asarray(result.n_nonfinite) > 0)
    assert float(result.params[0]) <= 0.5
    np.testing.assert_allclose(result.params, [0.3, 0.0], atol=0.05)


def test_progress_reports_every_epoch(key):
    calls = []
    pso(
        key,
        sphere,
        box(2, 1.0),
        n_agents=4,
        n_epochs=5,
        n_trials=2,
        progress=lambda trial, epoch, best: calls.append((trial, epoch, best)),
    )
    jax.effects_barrier()
    assert sorted((t, e) for t, e, _ in calls) == [(t, e) for t in range(2) for e in range(1, 6)]


def test_loss_closing_over_arrays_through_partial(key):
    loss = jax.tree_util.Partial(
        lambda target, x: jnp.sum((x - target) ** 2), jnp.array([0.2, -0.4], jnp.float32)
    )
    result = pso(key, loss, box(2, 1.0), n_agents=10, n_epochs=50)
    np.testing.assert_allclose(result.params, [0.2, -0.4], atol=1e-2)


def test_batched_loss_equals_the_vmapped_one(key):
    """A loss that evaluates the whole swarm itself (here one agent after the other) runs the
    same swarm as the vmapped per-agent loss."""
    mapped = pso(key, rastrigin, box(4, 5.12), n_agents=12, n_epochs=20)
    batched = pso(
        key, lambda xs: jax.lax.map(rastrigin, xs), box(4, 5.12), n_agents=12, n_epochs=20,
        batched=True,
    )  # fmt: skip
    np.testing.assert_allclose(batched.history, mapped.history, rtol=1e-6)
    np.testing.assert_allclose(batched.params, mapped.params, rtol=1e-6)
    with pytest.raises(TypeError, match="one loss per agent"):
        pso(key, rastrigin, box(4, 5.12), n_agents=12, batched=True)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"bounds": ([0.0, 1.0], [1.0, 1.0])}, ValueError, "low < high"),
        ({"bounds": ([0.0], [np.nan])}, ValueError, "finite"),
        ({"bounds": np.zeros((3, 2))}, ValueError, r"\(low, high\)"),
        ({"n_agents": 2}, ValueError, "n_agents"),
        ({"n_epochs": 0}, ValueError, "n_epochs"),
        ({"topology": "ring"}, ValueError, "topology"),
        ({"boundary": "clip"}, ValueError, "boundary"),
        ({"cyclic": [1, 0]}, ValueError, "cyclic"),
        ({"inertia": 0.5}, ValueError, "inertia"),
        ({"loss_fn": "sphere"}, TypeError, "loss_fn must be callable"),
        ({"loss_fn": lambda x: x}, TypeError, "scalar"),
        ({"key": 0}, TypeError, "key"),
    ],
)
def test_bad_input(kwargs, error, match, unchecked):
    args = {"key": jax.random.key(0), "loss_fn": sphere, "bounds": box(2, 1.0)} | kwargs
    key, loss_fn, bounds = args.pop("key"), args.pop("loss_fn"), args.pop("bounds")
    with pytest.raises(error, match=match):
        pso(key, loss_fn, bounds, **args)
