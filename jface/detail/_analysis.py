"""Analysis of facial-detail statistics across groups (Golovinskiy et al. 2006, §3.1) and beyond
the paper: principal components of statistics and cross-validated prediction of attributes."""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks
from jface.detail._population import Population
from jface.detail._stats import DetailStats, mean_stats, stack_stats


class GroupComparison(NamedTuple):
    """Mean statistics of several groups, normalised to the group with the least content.

    Attributes:
        names: the groups, in the order given.
        means: ``(n_groups, bands, grid, grid)`` mean per-tile std of each group.
        ratios: ``means / means[reference]``, tile by tile (the quantity Fig. 6 draws).
        reference: index of the group with the least content (smallest detail amplitude).
    """

    names: tuple[str, ...]
    means: Float[Array, "groups bands grid grid"]
    ratios: Float[Array, "groups bands grid grid"]
    reference: int


def compare_groups(groups: Mapping[str, DetailStats | Population]) -> GroupComparison:
    """Compare groups tile by tile, normalised to the group with the smallest amount of content
    (§3.1 of Golovinskiy et al.; e.g. age bands, or women vs men).

    Args:
        groups: name → a :class:`Population` or a stack of :class:`DetailStats` (one group each).
    """
    if len(groups) < 2:
        raise ValueError(f"need at least two groups to compare, got {len(groups)}")
    means = []
    for name, group in groups.items():
        stats = group.stats if isinstance(group, Population) else group
        if not isinstance(stats, DetailStats):
            raise TypeError(f"group {name!r} must be a Population or DetailStats")
        means.append(mean_stats(stats) if stats.std.ndim == 4 else stats)
    stacked = stack_stats([m.reduced() for m in means])
    reference = int(jnp.argmin(stacked.detail_rms()))
    base = stacked.std[reference]
    ratios = stacked.std / jnp.where(base > 0, base, 1.0)
    return GroupComparison(tuple(groups), stacked.std, ratios, reference)


def log_features(stats: DetailStats) -> Float[Array, "n features"]:
    """Feature vectors of a stack of statistics: log per-tile std, flattened (4352 for the paper's
    layout). Logs make multiplicative changes of detail additive."""
    if stats.std.ndim != 4:
        raise ValueError(f"stats must be a stack (n, bands, grid, grid), got {stats.std.shape}")
    std = stats.std.reshape(stats.std.shape[0], -1)
    return jnp.log(jnp.maximum(std, jnp.finfo(std.dtype).tiny))


class PCA(NamedTuple):
    """Principal components of statistics: ``features ≈ mean + scores @ components``."""

    mean: Float[Array, " features"]
    components: Float[Array, "k features"]
    variance: Float[Array, " k"]
    scores: Float[Array, "n k"]
    total_variance: Float[Array, ""]

    @property
    def explained(self) -> Float[Array, " k"]:
        """Fraction of the total variance each component explains."""
        return self.variance / self.total_variance


def stats_pca(stats: DetailStats, n_components: int = 8) -> PCA:
    """PCA of a population's statistics (on :func:`log_features`)."""
    features = log_features(stats)
    n = features.shape[0]
    n_components = _checks.integer(n_components, "n_components", low=1, high=max(1, n - 1))
    mean = features.mean(axis=0)
    centred = features - mean
    _, singular, vt = jnp.linalg.svd(centred, full_matrices=False)
    variance = singular**2 / max(n - 1, 1)
    return PCA(
        mean,
        vt[:n_components],
        variance[:n_components],
        centred @ vt[:n_components].T,
        jnp.sum(variance),
    )


class CrossValidation(NamedTuple):
    """Out-of-fold predictions of a ridge model and their score.

    ``score`` is the accuracy for classification (labels ±1 or two classes) and the mean
    absolute error for regression; ``chance`` is the same score of always predicting the
    training majority class / mean.
    """

    predictions: Float[Array, " n"]
    score: float
    chance: float


def cross_validate(
    key: PRNGKeyArray,
    features: ArrayLike,
    targets: ArrayLike,
    *,
    task: str = "regression",
    folds: int = 5,
    ridge: float = 1.0,
) -> CrossValidation:
    """k-fold cross-validated ridge prediction of an attribute (age, sex, ...) from statistics.

    Beyond the paper (its future work): does facial detail predict age and sex? Features are
    standardised on each training fold; the ridge model is solved in its dual form (n × n), so
    4352-dimensional statistics of a few hundred faces cost nothing.

    Args:
        key: shuffles the samples into folds.
        features: ``(n, d)``, e.g. :func:`log_features` of a population.
        targets: ``(n,)`` numbers (regression) or two distinct labels (classification).
        task: "regression" (score = mean absolute error) or "classification" (accuracy).
        folds: number of folds (2 ≤ folds ≤ n).
        ridge: regularisation strength, relative to the mean feature variance × n.
    """
    key = _checks.key(key)
    features = _checks.float_array(features, "features", ndim=2)
    targets = jnp.asarray(targets)
    n = features.shape[0]
    if targets.shape != (n,):
        raise ValueError(f"targets must have shape ({n},) like features, got {targets.shape}")
    _checks.choice(task, "task", ("regression", "classification"))
    folds = _checks.integer(folds, "folds", low=2, high=n)
    ridge = _checks.real(ridge, "ridge", low=0.0, open_low=True)
    if task == "classification":
        classes = jnp.unique(targets)
        if classes.shape[0] != 2:
            raise ValueError(f"classification needs exactly two classes, got {classes.shape[0]}")
        y = jnp.where(targets == classes[1], 1.0, -1.0).astype(features.dtype)
    else:
        y = targets.astype(features.dtype)
    order = jax.random.permutation(key, n)
    fold_of = jnp.zeros(n, jnp.int32).at[order].set(jnp.arange(n, dtype=jnp.int32) % folds)
    predictions = jnp.zeros(n, features.dtype)
    baseline = jnp.zeros(n, features.dtype)
    for fold in range(folds):
        train, test = fold_of != fold, fold_of == fold
        x_train, y_train = features[train], y[train]
        mu, sd = x_train.mean(0), x_train.std(0) + 1e-8
        a = (x_train - mu) / sd
        y_mean = y_train.mean()
        gram = a @ a.T
        alpha = jnp.linalg.solve(
            gram + ridge * a.shape[1] * jnp.eye(a.shape[0], dtype=a.dtype), y_train - y_mean
        )
        predicted = ((features[test] - mu) / sd) @ (a.T @ alpha) + y_mean
        predictions = predictions.at[test].set(predicted)
        fallback = jnp.sign(y_mean) if task == "classification" else y_mean
        baseline = baseline.at[test].set(fallback)
    if task == "classification":
        score = float(jnp.mean(jnp.sign(predictions) == y))
        chance = float(jnp.mean(baseline == y))
    else:
        score = float(jnp.mean(jnp.abs(predictions - y)))
        chance = float(jnp.mean(jnp.abs(baseline - y)))
    return CrossValidation(predictions, score, chance)


def group_by(
    population: Population, field: str, edges: Sequence[int | float]
) -> dict[str, Population]:
    """Split a population into groups by a numeric field (e.g. age bands ``[20, 30, 45, 60]``)."""
    groups = {}
    for low, high in itertools.pairwise(edges):
        groups[f"{field} {low}-{high}"] = population.select(**{field: (low, high)})
    return groups
