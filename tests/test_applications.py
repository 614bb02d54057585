"""Interpolation with restored detail and the paper's §4 comparison, on real textures."""

import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail


@pytest.fixture(scope="module")
def faces(gravel):
    """Eight real 256² maps (gravel crops) and their statistics."""
    crops = np.stack([gravel[i * 32 : i * 32 + 256, i * 24 : i * 24 + 256] for i in range(8)])
    images = jnp.asarray(crops, jnp.float32)
    return images, detail.analyze_batch(images, grid=8)


def test_interpolation_restores_detail(faces, key):
    images, stats = faces
    result = detail.interpolate(key, images, stats, jnp.full(8, 1 / 8))
    target = result.target.std[0]  # high-pass band
    average = detail.analyze(result.average, grid=8).std[0]
    coerced = detail.analyze(result.coerced, grid=8).std[0]
    # The plain average loses most of the finest detail; coercion restores it.
    assert float(jnp.median(average / target)) < 0.5
    assert float(jnp.median(jnp.abs(coerced / target - 1))) < 0.05


def test_statistical_method_trades_off_better_than_the_baselines(faces, key, brick):
    images, _ = faces
    old = jnp.asarray(brick[:256, :256], jnp.float32)  # "old face": other, oriented detail
    old_stats = detail.analyze(old, grid=8)
    table = detail.compare_methods(key, images[0], old, old_stats)
    ours, sharp, transfer = table["statistical"], table["sharpen"], table["transfer"]
    assert ours["stats_error"] < 0.5 * min(sharp["stats_error"], 0.5)
    assert transfer["keeps_coarse"] < 0.2 < ours["keeps_coarse"]


def test_bad_weights(unchecked, faces, key):
    images, stats = faces
    with pytest.raises(ValueError, match="sum to 1"):
        detail.interpolate(key, images, stats, jnp.full(8, 0.2))
    with pytest.raises(ValueError, match="non-negative"):
        detail.interpolate(key, images, stats, jnp.asarray([2.0, -1.0] + [0.0] * 6))
    with pytest.raises(ValueError, match="8 entries"):
        detail.interpolate(key, images, stats, jnp.ones(3) / 3)
    with pytest.raises(ValueError, match="donor must have"):
        detail.transfer_detail(images[0], images[0, :128, :128])
