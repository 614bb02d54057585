"""Known answers for the face models, the tile statistics and Poisson editing, each against an
independent dense reference on a tiny case: the masked EM's E- and M-step (factor analysis with
missing pixels) and recovery of known parameters with 30 % of the pixels missing, the mixture's
responsibilities, the tile-blend weights and tile statistics against numpy, and Poisson blending
against scipy's sparse solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import sparse, stats
from scipy.sparse import linalg as sparse_linalg

from jface import faces, tiles
from jface.faces import (
    MixtureOfFactorAnalysers,
    fit_factor_analyser,
    poisson_blend,
    responsibilities,
)
from jface.faces._em import masked_step, mixture_step
from jface.faces._em import responsibilities as complete_responsibilities

D, Q, N = 6, 2, 14


@pytest.fixture(scope="module")
def masked_case():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(N, D))
    m = (rng.random((N, D)) > 0.3).astype(np.float64)
    m[:, 0] = 1.0  # every image observes something
    params = (rng.normal(size=D), rng.normal(size=(D, Q)), rng.uniform(0.3, 1.0, D))
    return x, m, params


def _dense_masked_step(x, m, mean, factors, noise):
    """One EM step of factor analysis with missing pixels, image by image and pixel by pixel."""
    n, d = x.shape
    q = factors.shape[1]
    ll, eh, ehh = 0.0, np.zeros((n, q)), np.zeros((n, q, q))
    for i in range(n):
        o = m[i] > 0
        f, r = factors[o], x[i, o] - mean[o]
        cov = f @ f.T + np.diag(noise[o])
        ll += stats.multivariate_normal(mean[o], cov).logpdf(x[i, o]) / n
        post = np.linalg.inv(np.eye(q) + f.T @ np.diag(1 / noise[o]) @ f)
        eh[i] = post @ f.T @ (r / noise[o])
        ehh[i] = post + np.outer(eh[i], eh[i])
    new_mean, new_factors, new_noise = np.zeros(d), np.zeros((d, q)), np.zeros(d)
    for j in range(d):
        seen = m[:, j] > 0
        z = np.concatenate([eh[seen], np.ones((seen.sum(), 1))], axis=1)
        big = np.zeros((q + 1, q + 1))
        for i in np.flatnonzero(seen):
            big[:q, :q] += ehh[i]
            big[:q, q] += eh[i]
            big[q, :q] += eh[i]
            big[q, q] += 1.0
        row = np.linalg.solve(big, z.T @ x[seen, j])
        new_factors[j], new_mean[j] = row[:q], row[q]
        new_noise[j] = np.mean(x[seen, j] ** 2 - x[seen, j] * (z @ row))
    return ll, new_mean, new_factors, new_noise


def test_masked_em_step_matches_a_dense_reference(masked_case):
    x, m, params = masked_case
    ll, (mean, factors, noise) = masked_step(
        jnp.asarray(x), jnp.asarray(m), jnp.asarray(1e-9), tuple(map(jnp.asarray, params))
    )
    want = _dense_masked_step(x, m, *params)
    assert float(ll) == pytest.approx(want[0], rel=1e-9)
    for got, ref in zip((mean, factors, noise), want[1:], strict=True):
        np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-8, atol=1e-10)


def test_masked_em_recovers_a_known_model_with_30_percent_missing():
    rng = np.random.default_rng(1)
    d, q, n = 10, 2, 3000
    factors = rng.normal(size=(d, q))
    mean = rng.normal(size=d)
    noise = rng.uniform(0.05, 0.2, d)
    x = mean + rng.normal(size=(n, q)) @ factors.T + rng.normal(size=(n, d)) * np.sqrt(noise)
    mask = rng.random((n, d)) > 0.3
    mask[:, 0] = True
    fit = fit_factor_analyser(np.where(mask, x, np.nan), q, mask=mask, n_iter=200).model
    # factors are identified up to a rotation: compare the covariance and the noise
    cov = np.asarray(fit.factors) @ np.asarray(fit.factors).T
    np.testing.assert_allclose(cov, factors @ factors.T, atol=0.15)
    np.testing.assert_allclose(np.asarray(fit.mean), mean, atol=0.1)
    np.testing.assert_allclose(np.asarray(fit.noise), noise, rtol=0.25)


def _mixture(rng, k, d, q):
    return MixtureOfFactorAnalysers(
        weights=jnp.asarray([0.5, 0.3, 0.2][:k]),
        means=jnp.asarray(rng.normal(size=(k, d)) * 1.5),
        factors=jnp.asarray(rng.normal(size=(k, d, q))),
        noise=jnp.asarray(rng.uniform(0.2, 1.0, (k, d))),
        shape=(d,),
    )


def _scipy_responsibilities(model, x, observed):
    joint = [
        np.log(float(w))
        + stats.multivariate_normal(
            np.asarray(mu)[observed],
            (np.asarray(f) @ np.asarray(f).T + np.diag(np.asarray(s)))[np.ix_(observed, observed)],
        ).logpdf(x[observed])
        for w, mu, f, s in zip(model.weights, model.means, model.factors, model.noise, strict=True)
    ]
    joint = np.array(joint)
    return np.exp(joint - np.logaddexp.reduce(joint))


def test_mixture_responsibilities_match_scipy():
    rng = np.random.default_rng(2)
    model = _mixture(rng, 3, D, Q)
    x = rng.normal(size=(5, D)) * 1.5
    observed = np.array([True, False, True, True, False, True])
    for xi in x:
        want = _scipy_responsibilities(model, xi, np.ones(D, bool))
        np.testing.assert_allclose(np.asarray(responsibilities(model, xi)), want, rtol=1e-8)
        masked = np.asarray(responsibilities(model, xi, observed))
        np.testing.assert_allclose(masked, _scipy_responsibilities(model, xi, observed), rtol=1e-8)
    # the EM's batched form (complete images) agrees too
    params = (jnp.log(model.weights), model.means, model.factors, model.noise)
    batch = np.asarray(complete_responsibilities(jnp.asarray(x), params)).T
    want = [_scipy_responsibilities(model, xi, np.ones(D, bool)) for xi in x]
    np.testing.assert_allclose(batch, want, rtol=1e-8)


@pytest.mark.parametrize(("n", "grid"), [(8, 2), (12, 3), (10, 4)])
def test_blend_weights_interpolate_between_tile_centres(n, grid):
    # tile centres at (k + ½)·n/grid − ½ in pixel coordinates; np.interp clamps past the ends
    centres = (np.arange(grid) + 0.5) * n / grid - 0.5
    eye = np.eye(grid)
    want = np.stack([np.interp(np.arange(n), centres, eye[k]) for k in range(grid)], axis=1)
    np.testing.assert_allclose(np.asarray(tiles.blend_weights(n, grid, jnp.float64)), want)
    values = np.random.default_rng(3).normal(size=(grid, grid))
    rows = np.stack([np.interp(np.arange(n), centres, values[:, c]) for c in range(grid)], 1)
    full = np.stack([np.interp(np.arange(n), centres, r) for r in rows])
    np.testing.assert_allclose(np.asarray(tiles.blend(jnp.asarray(values), (n, n))), full)


def test_tile_statistics_match_numpy(gravel):
    # jittered off the 8-bit levels, so no value sits exactly on a bin edge
    band = gravel[:24, :24] + 1e-4 * np.random.default_rng(4).normal(size=(24, 24))
    grid, t = 3, 8
    blocks = band.reshape(grid, t, grid, t).swapaxes(1, 2)
    mean, std = tiles.tile_moments(jnp.asarray(band), grid)
    np.testing.assert_allclose(np.asarray(mean), blocks.mean(axis=(2, 3)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(std), blocks.std(axis=(2, 3)), rtol=1e-10)
    probs, ranges = tiles.tile_histograms(jnp.asarray(band), grid, 5)
    for r in range(grid):
        for c in range(grid):
            b = blocks[r, c]
            counts, _ = np.histogram(b, bins=np.linspace(b.min(), b.max(), 6))
            np.testing.assert_allclose(np.asarray(probs[r, c]), counts / b.size)
            np.testing.assert_allclose(np.asarray(ranges[r, c]), [b.min(), b.max()])
    # a grown tile spans the pixels whose centres lie strictly between its neighbours' centres
    gmean, gstd = tiles.grown_moments(jnp.asarray(band), grid)
    centres = (np.arange(grid) + 0.5) * t - 0.5
    px = np.arange(24)
    for r in range(grid):
        for c in range(grid):
            rows = (px > centres[r] - t) & (px < centres[r] + t)
            cols = (px > centres[c] - t) & (px < centres[c] + t)
            rows |= (px < centres[0]) & (r == 0) | (px > centres[-1]) & (r == grid - 1)
            cols |= (px < centres[0]) & (c == 0) | (px > centres[-1]) & (c == grid - 1)
            window = band[np.ix_(rows, cols)]
            assert float(gmean[r, c]) == pytest.approx(window.mean(), rel=1e-12)
            assert float(gstd[r, c]) == pytest.approx(window.std(), rel=1e-9)


def _scipy_poisson(source, boundary, region):
    """Σ_{q ∈ N_p} (u_p − u_q) = Σ_{q ∈ N_p} (s_p − s_q) on the region, neighbours inside the
    image only, values of ``boundary`` elsewhere: one sparse solve."""
    h, w = source.shape
    index = -np.ones((h, w), int)
    index[region] = np.arange(region.sum())
    a = sparse.lil_matrix((region.sum(), region.sum()))
    b = np.zeros(region.sum())
    for y, x in zip(*np.nonzero(region), strict=True):
        i = index[y, x]
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            v, u = y + dy, x + dx
            if not (0 <= v < h and 0 <= u < w):
                continue
            a[i, i] += 1
            b[i] += source[y, x] - source[v, u]
            if region[v, u]:
                a[i, index[v, u]] -= 1
            else:
                b[i] += boundary[v, u]
    out = boundary.copy()
    out[region] = sparse_linalg.spsolve(a.tocsr(), b)
    return out


def test_poisson_blend_matches_a_sparse_solve(brick, gravel):
    source, boundary = brick[:20, :24], gravel[:20, :24]
    interior = np.zeros(source.shape, bool)
    interior[1:-1, 1:-1] = True
    got = np.asarray(poisson_blend(source, boundary))
    np.testing.assert_allclose(got, _scipy_poisson(source, boundary, interior), atol=1e-10)
    # a region touching the image edge: natural boundary there, solved by conjugate gradients
    yy, xx = np.mgrid[:20, :24]
    region = (yy - 8) ** 2 + (xx - 2) ** 2 < 40
    got = np.asarray(poisson_blend(source, boundary, region))
    np.testing.assert_allclose(got, _scipy_poisson(source, boundary, region), atol=1e-6)


def test_masked_em_step_is_the_same_under_jit(masked_case):
    x, m, params = masked_case
    args = (jnp.asarray(x), jnp.asarray(m), jnp.asarray(1e-9), tuple(map(jnp.asarray, params)))
    eager = jax.tree.leaves(masked_step(*args))
    jitted = jax.tree.leaves(jax.jit(masked_step)(*args))
    for a, b in zip(eager, jitted, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)


def test_quilting_picks_the_cheapest_patch_for_a_target_weight_other_than_one():
    # the cost of §2.2, SSD to the known pixels + λ SSD to the target, with λ ≠ 1 so that a
    # misplaced λ shows: with n_best = 1 each choice is the argmin of a float64 replay
    from skimage import data
    from test_faces_quilting import GRID, replay_costs

    lfw = np.asarray(data.lfw_subset()[:30], np.float32)
    library = faces.build_library(lfw[1:], GRID, translations=0, angles=())
    for lam in (0.2, 5.0):
        result = faces.quilt(jax.random.key(0), library, lfw[0], lam=lam, n_best=1)
        steps = replay_costs(library, result, lfw[0], lam=lam)
        assert len(steps) > 4
        for cost, chosen in steps:
            assert cost[chosen] <= cost.min() + 1e-4 * max(1.0, abs(cost.min()))


def test_mixture_em_step_matches_a_dense_reference():
    # one EM step of a mixture of factor analysers (Ghahramani & Hinton 1997), component by
    # component with dense posteriors
    rng = np.random.default_rng(5)
    model = _mixture(rng, 2, D, Q)
    x = rng.normal(size=(20, D)) * 1.5
    params = (jnp.log(model.weights), model.means, model.factors, model.noise)
    _, (log_w, means, factors, noise) = mixture_step(
        jnp.asarray(x), jnp.asarray(x * x), jnp.asarray(1e-9), params
    )
    resp = np.array([_scipy_responsibilities(model, xi, np.ones(D, bool)) for xi in x]).T
    for k in range(2):
        f, mu, s = (np.asarray(a[k]) for a in (model.factors, model.means, model.noise))
        cov = np.linalg.inv(np.eye(Q) + f.T @ (f / s[:, None]))
        eh = (x - mu) / s @ f @ cov
        z = np.concatenate([eh, np.ones((len(x), 1))], axis=1)
        big = (resp[k][:, None] * z).T @ z
        big[:Q, :Q] += resp[k].sum() * cov
        rows = np.linalg.solve(big, (resp[k][:, None] * z).T @ x).T  # (D, Q+1)
        np.testing.assert_allclose(np.asarray(factors[k]), rows[:, :Q], rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(np.asarray(means[k]), rows[:, Q], rtol=1e-8, atol=1e-10)
        explained = np.sum(rows * ((resp[k][:, None] * z).T @ x).T, axis=1)
        want = (resp[k] @ (x * x) - explained) / resp[k].sum()
        np.testing.assert_allclose(np.asarray(noise[k]), want, rtol=1e-8)
        assert float(log_w[k]) == pytest.approx(np.log(resp[k].mean()), rel=1e-9)
