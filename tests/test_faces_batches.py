"""faces.log_likelihood and faces.posterior on batches of images (leading axes)."""

import jax
import numpy as np
import pytest
from scipy.stats import multivariate_normal
from skimage.data import lfw_subset

from jface import faces


@pytest.fixture(scope="module")
def lfw():
    return lfw_subset()[:60].astype(np.float32)  # (60, 25, 25) real faces in [0, 1]


@pytest.fixture(scope="module")
def models(lfw):
    fa = faces.fit_factor_analyser(lfw[:50], 4, n_iter=10).model
    mix = faces.fit_mixture(jax.random.key(0), lfw[:50], 2, 3, n_iter=5).model
    return {"fa": fa, "mixture": mix}


@pytest.mark.parametrize("kind", ["fa", "mixture"])
def test_a_batch_equals_a_loop_over_its_images(models, lfw, kind):
    model, batch = models[kind], lfw[50:56].reshape(2, 3, 25, 25)
    mask = np.ones((25, 25), bool)
    mask[8:16, 5:20] = False  # one hole shared by the batch
    for m in (None, mask):
        ll = faces.log_likelihood(model, batch, m)
        loop = np.array([[faces.log_likelihood(model, x, m) for x in row] for row in batch])
        assert ll.shape == (2, 3)
        np.testing.assert_allclose(ll, loop, rtol=1e-5)
        post = faces.posterior(model, batch, m)
        for i, j in np.ndindex(2, 3):
            one = faces.posterior(model, batch[i, j], m)
            np.testing.assert_allclose(post.mean[i, j], one.mean, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(post.cov[i, j], one.cov, rtol=1e-4, atol=1e-6)
    flat = faces.log_likelihood(model, batch.reshape(6, 625))  # flattened images too
    np.testing.assert_allclose(flat, faces.log_likelihood(model, batch).reshape(6), rtol=1e-6)
    jitted = jax.jit(lambda x: faces.log_likelihood(model, x))(batch)
    np.testing.assert_allclose(jitted, faces.log_likelihood(model, batch), rtol=1e-5)


def test_batch_log_likelihood_matches_the_gaussian_density(models, lfw):
    fa = models["fa"]
    cov = np.asarray(fa.factors, np.float64) @ np.asarray(fa.factors, np.float64).T
    cov += np.diag(np.asarray(fa.noise, np.float64))
    reference = multivariate_normal(np.asarray(fa.mean, np.float64), cov).logpdf(
        lfw[50:60].reshape(10, -1).astype(np.float64)
    )
    np.testing.assert_allclose(faces.log_likelihood(fa, lfw[50:60]), reference, rtol=1e-4)


def test_a_batch_with_nan_is_refused_naming_x(models, lfw):
    batch = lfw[50:54].copy()
    batch[2, 3, 4] = np.nan
    with pytest.raises(ValueError, match="x"):
        faces.log_likelihood(models["fa"], batch)
    with pytest.raises(ValueError, match="image shape"):
        faces.posterior(models["fa"], lfw[50:54, :20, :20])
