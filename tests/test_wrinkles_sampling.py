"""Pore sampling: minimum distance, maximal coverage, density vs scipy, radius maps, levels."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.stats import qmc

from jface.wrinkles import make_pores, sample_pores


def _valid(pores):
    return np.asarray(pores.positions, np.float64)[: int(pores.count)]


def _query_points(n=40000):
    return np.random.default_rng(0).random((n, 2))


@pytest.mark.parametrize("periodic", [False, True])
def test_min_distance_and_coverage_uniform(key, periodic):
    r = 0.02
    pores = sample_pores(key, r, periodic=periodic)
    x = _valid(pores)
    assert pores.mask[: len(x)].all() and not pores.mask[len(x) :].any()
    tree = cKDTree(x, boxsize=1.0 if periodic else None)
    d, _ = tree.query(x, 2)
    assert d[:, 1].min() >= r * (1 - 1e-5)  # every pair at least r apart
    empty, _ = tree.query(_query_points())
    assert empty.max() <= 1.25 * r * (1 + 1e-5)  # guarantee (issue asks ≤ 2 r)
    np.testing.assert_allclose(pores.radius[: len(x)], r, rtol=1e-6)


def test_count_matches_scipy_poisson_disk(key):
    r = 0.01
    ours = int(sample_pores(key, r).count)
    ref = len(qmc.PoissonDisk(2, radius=r, seed=0).fill_space())
    assert abs(ours - ref) / ref < 0.10, (ours, ref)


def _ramp_map():
    x = (np.arange(64) + 0.5) / 64
    return np.broadcast_to(np.where(x < 0.5, 1.0, 2.0), (64, 64)).astype(np.float32)


def test_radius_map_changes_density_and_keeps_guarantees(key):
    d = 0.01
    rmap = _ramp_map()
    pores = sample_pores(key, d, rmap)
    x = _valid(pores)
    left = np.sum(x[:, 0] < 0.45)
    right = np.sum(x[:, 0] > 0.55)
    assert 3.0 < left / right < 5.0  # density ∝ 1 / r²
    r = np.asarray(pores.radius[: len(x)], np.float64)
    tree = cKDTree(x)
    pairs = np.array(sorted(tree.query_pairs(2 * d * 2.0)))
    dist = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    assert np.all(dist >= np.maximum(r[pairs[:, 0]], r[pairs[:, 1]]) * (1 - 1e-5))
    q = _query_points()
    empty, idx = tree.query(q)
    local = d * np.where(q[:, 0] < 0.5, 1.0, 2.0)
    assert np.all(empty <= 2.0 * np.maximum(local, r[idx]))


def test_finer_level_keeps_coarse_pores(key):
    coarse = sample_pores(key, 0.04, periodic=True, radius_range=(0.02, 0.04))
    fine = sample_pores(jax.random.key(1), 0.02, initial=coarse, periodic=True)
    n0 = int(coarse.count)
    np.testing.assert_array_equal(fine.positions[:n0], coarse.positions[:n0])
    assert (np.asarray(fine.level[:n0]) == 0).all()
    assert (np.asarray(fine.level[n0 : int(fine.count)]) == 1).all()
    x = _valid(fine)
    d, _ = cKDTree(x, boxsize=1.0).query(x, 2)
    assert d[:, 1].min() >= 0.02 * (1 - 1e-5)
    assert int(fine.count) > 3 * n0


def test_same_key_same_pores_and_vmap_over_alpha_d_equals_loop(key):
    one = sample_pores(key, 0.02)
    np.testing.assert_array_equal(one.positions, sample_pores(key, 0.02).positions)
    ds = jnp.array([0.02, 0.04], jnp.float32)
    keys = jax.random.split(key, 2)

    def run(k, d):
        return sample_pores(k, d, capacity=3000, radius_range=(0.02, 0.04), periodic=True)

    batch = jax.vmap(run)(keys, ds)
    for i in range(2):
        single = run(keys[i], ds[i])
        np.testing.assert_array_equal(batch.positions[i], single.positions)
        assert int(batch.count[i]) == int(single.count)
    assert int(batch.count[0]) > int(batch.count[1])


def test_bad_input(key, unchecked):
    with pytest.raises(ValueError, match=r"d \(α_d\) must be in"):
        sample_pores(key, 0.2)
    with pytest.raises(ValueError, match="radius_map must be positive"):
        sample_pores(key, 0.02, np.zeros((4, 4), np.float32))
    with pytest.raises(ValueError, match="more than capacity"):
        sample_pores(key, 0.02, capacity=100)
    with pytest.raises(ValueError, match="radius_range"):
        jax.jit(lambda d: sample_pores(key, d, capacity=10).positions)(jnp.float32(0.02))
    close = make_pores(np.array([[0.5, 0.5], [0.5001, 0.5]], np.float32))
    with pytest.raises(ValueError, match="two initial pores"):
        sample_pores(key, 0.02, initial=close)
    with pytest.raises(TypeError, match="floating"):
        sample_pores(key, "0.02")
