"""Group comparison, PCA and attribute prediction on a population with known structure."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail


@pytest.fixture(scope="module")
def population(gravel):
    """60 faces: real per-tile statistics of gravel crops, with detail that grows with age in the
    upper half of the face (finest scale) and is stronger in men around the chin (bottom rows)."""
    rng = np.random.default_rng(0)
    crops = np.stack([gravel[i * 4 : i * 4 + 128, i * 3 : i * 3 + 128] for i in range(60)])
    base = detail.analyze_batch(crops.astype(np.float32), grid=8, n_scales=3)
    ages = rng.uniform(20, 70, 60)
    sexes = np.array(["f", "m"] * 30)
    std = np.asarray(base.std).copy()
    std[:, :5, :4, :] *= np.exp(0.02 * (ages - 20))[:, None, None, None]
    std[:, :, 6:, 2:6] *= np.where(sexes == "m", 1.6, 1.0)[:, None, None, None]
    stats = detail.DetailStats(jnp.asarray(std), None, None, 3, 4, (128, 128))
    records = [
        {"id": f"p{i}", "age": float(a), "sex": s}
        for i, (a, s) in enumerate(zip(ages, sexes, strict=True))
    ]
    return detail.Population(stats, tuple(records))


def test_compare_groups_normalises_to_least_content(population):
    groups = detail.group_by(population, "age", [20, 35, 50, 70])
    comparison = detail.compare_groups(groups)
    assert comparison.reference == 0  # the youngest group has the least detail
    ratios = np.asarray(comparison.ratios)
    assert np.allclose(ratios[0], 1.0)
    upper, lower = ratios[2, :5, :4].mean(), ratios[2, :5, 4:].mean()
    assert upper > 1.5 and abs(lower - 1.0) < 0.2
    by_sex = detail.compare_groups(
        {"f": population.select(sex="f"), "m": population.select(sex="m")}
    )
    assert by_sex.names[by_sex.reference] == "f"
    assert np.asarray(by_sex.ratios)[1, :, 6:, 2:6].mean() == pytest.approx(1.6, rel=0.1)


def test_pca_finds_the_age_direction(population):
    pca = detail.stats_pca(population.stats, n_components=3)
    ages = np.array([r["age"] for r in population.records])
    correlation = max(abs(np.corrcoef(pca.scores[:, k], ages)[0, 1]) for k in range(3))
    assert correlation > 0.9
    assert np.all(np.diff(np.asarray(pca.explained)) <= 0)


def test_cross_validated_prediction(population, key):
    features = detail.log_features(population.stats)
    ages = jnp.asarray([r["age"] for r in population.records])
    sexes = np.array([r["sex"] for r in population.records])
    age = detail.cross_validate(key, features, ages, task="regression", ridge=0.1)
    assert age.score < 0.3 * age.chance  # mean absolute error in years
    sex = detail.cross_validate(
        key, features, (sexes == "m").astype(np.float64), task="classification", ridge=0.1
    )
    assert sex.score >= 0.95 and sex.chance <= 0.6
    shuffled = detail.cross_validate(key, features, jax.random.permutation(key, ages), ridge=0.1)
    assert shuffled.score > 0.8 * shuffled.chance  # no structure, no skill


def test_bad_input(unchecked, population, key):
    with pytest.raises(ValueError, match="at least two groups"):
        detail.compare_groups({"all": population})
    with pytest.raises(ValueError, match="targets must have shape"):
        detail.cross_validate(key, jnp.zeros((4, 3)), jnp.zeros(5))
    with pytest.raises(ValueError, match="exactly two classes"):
        detail.cross_validate(key, jnp.zeros((6, 3)), jnp.arange(6.0), task="classification")
