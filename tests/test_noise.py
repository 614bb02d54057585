"""Perlin noise: range, determinism, seamless tiling, traced frequency, bad input; the
counter-based uniform numbers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface.noise import counter_bits, counter_uniform, perlin, perlin_at


def test_grid_range_mean_and_determinism(key):
    a = perlin(key, (128, 96), frequency=8, octaves=3)
    b = perlin(key, (128, 96), frequency=8, octaves=3)
    c = perlin(jax.random.key(1), (128, 96), frequency=8, octaves=3)
    assert a.shape == (128, 96) and a.dtype == jnp.float32
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    assert float(jnp.max(jnp.abs(a))) <= 1.0
    assert abs(float(jnp.mean(a))) < 0.1 and 0.1 < float(jnp.std(a)) < 0.5


def test_periodic_noise_tiles_and_is_zero_on_lattice(key):
    y = jnp.linspace(0.0, 1.0, 17, dtype=jnp.float32)
    left = perlin_at(key, jnp.stack([jnp.zeros_like(y), y], -1), frequency=5, periodic=True)
    right = perlin_at(key, jnp.stack([jnp.ones_like(y), y], -1), frequency=5, periodic=True)
    np.testing.assert_allclose(left, right, atol=1e-6)
    lattice = jnp.stack(jnp.meshgrid(jnp.arange(5.0) / 5, jnp.arange(5.0) / 5), -1)
    np.testing.assert_allclose(
        perlin_at(key, lattice.astype(jnp.float32), frequency=5), 0, atol=1e-6
    )


def test_smooth_and_frequency_may_be_traced(key):
    pts = jax.random.uniform(jax.random.key(3), (200, 2), dtype=jnp.float32)
    eager = perlin_at(key, pts, frequency=3.5, octaves=2)
    traced = jax.jit(lambda f: perlin_at(key, pts, frequency=f, octaves=2))(jnp.float32(3.5))
    np.testing.assert_allclose(eager, traced, atol=1e-6)
    near = perlin_at(key, pts + 1e-4, frequency=3.5, octaves=2)
    assert float(jnp.max(jnp.abs(near - eager))) < 0.01  # continuous


def _reference_perlin(key, xy, frequency, octaves, periodic):
    """The noise written out corner by corner in NumPy (float64, wrapping uint32 hash), with
    the octave seeds drawn as jface draws them."""

    def mix(x):  # lowbias32
        x = x ^ (x >> np.uint32(16))
        x = x * np.uint32(0x7FEB352D)
        x = x ^ (x >> np.uint32(15))
        x = x * np.uint32(0x846CA68B)
        return x ^ (x >> np.uint32(16))

    seeds = np.asarray(jax.random.bits(key, (octaves,), dtype=jnp.uint32))
    xy = np.asarray(xy, np.float64)
    total = np.zeros(xy.shape[:-1])
    for o in range(octaves):
        freq = frequency * 2.0**o
        period = round(freq) if periodic else 0
        p = xy * (period or freq)
        cell = np.floor(p)
        f = p - cell
        values = {}
        for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
            ix, iy = cell[..., 0].astype(np.int64) + dx, cell[..., 1].astype(np.int64) + dy
            if period:
                ix, iy = ix % period, iy % period
            h = mix(ix.astype(np.uint32) ^ mix(iy.astype(np.uint32) ^ seeds[o]))
            angle = (h >> np.uint32(24)).astype(np.float64) * (2 * np.pi / 256)
            values[dx, dy] = np.cos(angle) * (f[..., 0] - dx) + np.sin(angle) * (f[..., 1] - dy)
        u, v = (t * t * t * (t * (t * 6 - 15) + 10) for t in (f[..., 0], f[..., 1]))
        n0 = values[0, 0] + u * (values[1, 0] - values[0, 0])
        n1 = values[0, 1] + u * (values[1, 1] - values[0, 1])
        total += 0.5**o * (n0 + v * (n1 - n0)) * np.sqrt(2.0)
    return total / sum(0.5**o for o in range(octaves))


@pytest.mark.parametrize("periodic", [False, True])
def test_agrees_with_a_corner_by_corner_reference(key, periodic):
    """Known answer: points anywhere (also outside the unit square) and a pixel grid against an
    independent NumPy evaluation of the same hash-based noise."""
    pts = jax.random.uniform(jax.random.key(5), (500, 2), jnp.float32, -1.5, 2.5)
    np.testing.assert_allclose(
        perlin_at(key, pts, frequency=3, octaves=3, periodic=periodic),
        _reference_perlin(key, pts, 3.0, 3, periodic),
        atol=2e-5,
    )
    grid = perlin(key, (40, 56), frequency=4, octaves=2, periodic=periodic)
    y, x = ((np.arange(n) + 0.5) / n for n in (40, 56))
    xy = np.stack(np.meshgrid(x, y, indexing="xy"), -1)
    np.testing.assert_allclose(grid, _reference_perlin(key, xy, 4.0, 2, periodic), atol=2e-5)


def test_counter_numbers_are_uniform_deterministic_and_unrelated_across_streams():
    u = np.asarray(counter_uniform(jnp.uint32(7), jnp.uint32(0), (200_000,)))
    np.testing.assert_array_equal(u, counter_uniform(jnp.uint32(7), jnp.uint32(0), (200_000,)))
    assert u.min() >= 0.0 and u.max() < 1.0
    counts = np.histogram(u, bins=100, range=(0, 1))[0]
    chi2 = np.sum((counts - 2000.0) ** 2 / 2000.0)
    assert chi2 < 160  # 99 degrees of freedom: p ≈ 1e-4
    # neighbouring and far streams and seeds: no correlation, no shared values in any order
    for seed, stream in ((7, 1), (7, 2), (7, 1 << 16), (8, 0)):
        v = np.asarray(counter_uniform(jnp.uint32(seed), jnp.uint32(stream), (200_000,)))
        assert abs(np.corrcoef(u, v)[0, 1]) < 0.01
        assert np.mean(np.sort(u) == np.sort(v)) < 0.01
    # words modulo n (the simulation's pore draws) stay uniform
    draws = np.asarray(counter_bits(jnp.uint32(3), jnp.uint32(5), (100_000,)) % jnp.uint32(37))
    counts = np.bincount(draws, minlength=37)
    assert np.sum((counts - 100_000 / 37) ** 2 / (100_000 / 37)) < 75  # 36 dof: p ≈ 2e-4


def test_bad_input(key, unchecked):
    with pytest.raises(ValueError, match="frequency"):
        perlin(key, (8, 8), frequency=0.0)
    with pytest.raises(ValueError, match="whole number"):
        perlin(key, (8, 8), frequency=2.5, periodic=True)
    with pytest.raises(ValueError, match="octaves"):
        perlin(key, (8, 8), frequency=2, octaves=0)
    with pytest.raises(ValueError, match="points"):
        perlin_at(key, jnp.zeros((4, 3), jnp.float32), frequency=2)


def test_every_counter_depends_on_the_seed():
    # counter 0 included: a first word shared by all seeds makes every run's first sample equal
    words = np.stack(
        [np.asarray(counter_bits(jnp.uint32(s), jnp.uint32(0), (4,))) for s in range(64)]
    )
    for column in words.T:
        assert len(np.unique(column)) == 64
