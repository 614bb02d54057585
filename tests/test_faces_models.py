"""Global face models: factor analyser, mixture, bilinear style model (Mohammed et al. 2009).

Against independent references (scikit-learn's FactorAnalysis, dense Gaussian conditioning with
numpy/scipy), EM invariants, recovery of known models, real faces (LFW) and ICT-FaceKit renders.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import subspace_angles
from scipy.stats import multivariate_normal
from sklearn.decomposition import FactorAnalysis
from sklearn.metrics import adjusted_rand_score

from jface import faces, raster
from jface.faces import _em

# --- data ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lfw() -> np.ndarray:
    """The 100 aligned 25×25 LFW faces shipped with scikit-image, float64 in [0, 1]."""
    from skimage import data

    return data.lfw_subset()[:100].astype(np.float64)


@pytest.fixture(scope="module")
def fa_lfw(lfw):
    return faces.fit_factor_analyser(lfw, 8)


def random_model(seed: int, d: int = 30, q: int = 4, shape=None) -> faces.FactorAnalyser:
    rng = np.random.default_rng(seed)
    return faces.FactorAnalyser(
        jnp.asarray(rng.normal(size=d)),
        jnp.asarray(rng.normal(size=(d, q))),
        jnp.asarray(rng.uniform(0.1, 0.5, size=d)),
        shape=shape or (d,),
    )


def dense_cov(model) -> np.ndarray:
    f = np.asarray(model.factors)
    return f @ f.T + np.diag(np.asarray(model.noise))


@pytest.fixture(scope="module")
def ict(ict_model) -> dict[str, np.ndarray]:
    """Renders of 80 random ICT-FaceKit identities (leading 10 identity modes), 16×16
    (rendered at 32×32, box-filtered): frontal neutral, frontal smiling, profile (yaw 90°±5°).
    Camera noise (σ = 0.01) keeps the background from being constant."""
    data = ict_model
    v = data["vertices"].astype(np.float64)
    tris = data["faces"]
    modes = data["identity_deltas"][:10].astype(np.float64).reshape(10, -1)
    smile = data["smile_delta"].astype(np.float64)  # mouthSmile_L + mouthSmile_R
    rng = np.random.default_rng(7)
    center, extent = np.array([0.0, -1.0, 5.0]), 16.0
    out = {"neutral": [], "smile": [], "profile": []}
    for _ in range(80):
        person = v + (rng.standard_normal(10) @ modes).reshape(-1, 3)
        views = {
            "neutral": (person, 0.0),
            "smile": (person + rng.uniform(0.7, 1.0) * smile, 0.0),
            "profile": (person, 90.0 + rng.uniform(-5, 5)),
        }
        for name, (verts, yaw) in views.items():
            img = raster.render(verts, tris, 32, yaw=yaw, center=center, extent=extent)
            out[name].append(img.astype(np.float64).reshape(16, 2, 16, 2).mean(axis=(1, 3)))
    return {k: np.stack(x) + 0.01 * rng.standard_normal((80, 16, 16)) for k, x in out.items()}


# --- factor analyser -------------------------------------------------------------------------


def test_log_likelihood_matches_sklearn_score(fa_lfw, lfw):
    """Same parameters → the same log-likelihood as sklearn (which forms the d×d covariance)."""
    model = fa_lfw.model
    ref = FactorAnalysis(8)
    ref.components_ = np.asarray(model.factors).T
    ref.noise_variance_ = np.asarray(model.noise)
    ref.mean_ = np.asarray(model.mean)
    flat = lfw.reshape(100, -1)
    ours = jax.vmap(lambda x: faces.log_likelihood(model, x))(lfw)
    np.testing.assert_allclose(ours, ref.score_samples(flat), rtol=1e-10)
    np.testing.assert_allclose(float(jnp.mean(ours)), ref.score(flat), rtol=1e-12)


def test_em_is_monotone_and_beats_sklearn(fa_lfw, lfw):
    history = np.asarray(fa_lfw.log_likelihood)
    assert history.shape == (41,) and int(fa_lfw.n_iter) == 40
    assert np.all(np.diff(history) >= -1e-9), np.diff(history).min()
    sk = FactorAnalysis(8, random_state=0).fit(lfw.reshape(100, -1))
    assert history[-1] >= sk.score(lfw.reshape(100, -1))
    # The float32 default path reaches the same optimum.
    f32 = faces.fit_factor_analyser(lfw.astype(np.float32), 8)
    assert f32.model.factors.dtype == jnp.float32
    assert abs(float(f32.log_likelihood[-1]) - history[-1]) < 1e-3 * abs(history[-1])


def test_recovers_synthetic_model(key):
    truth = random_model(1, d=40, q=3)
    data = faces.sample(key, truth, 4000, noise=True)
    fit = faces.fit_factor_analyser(data, 3, n_iter=300, tol=1e-9)
    assert bool(fit.converged) and int(fit.n_iter) < 300
    angle = np.degrees(subspace_angles(np.asarray(truth.factors), np.asarray(fit.model.factors)))
    assert angle.max() < 3.0, angle
    rel = np.abs(np.asarray(fit.model.noise) / np.asarray(truth.noise) - 1)
    assert rel.mean() < 0.05 and rel.max() < 0.25, rel
    ff = np.asarray(fit.model.factors) @ np.asarray(fit.model.factors).T
    f0 = np.asarray(truth.factors) @ np.asarray(truth.factors).T
    assert np.linalg.norm(ff - f0) / np.linalg.norm(f0) < 0.05


def test_posterior_against_dense_gaussian_conditioning():
    model = random_model(2)
    rng = np.random.default_rng(3)
    x = rng.normal(size=30)
    f, mu, psi = (np.asarray(a) for a in (model.factors, model.mean, model.noise))
    c = dense_cov(model)
    post = faces.posterior(model, x)
    np.testing.assert_allclose(post.mean, f.T @ np.linalg.solve(c, x - mu), rtol=1e-10)
    np.testing.assert_allclose(post.cov, np.eye(4) - f.T @ np.linalg.solve(c, f), atol=1e-12)
    ml = faces.posterior(model, x, form="ml")
    a = f.T / psi
    np.testing.assert_allclose(ml.mean, np.linalg.solve(a @ f, a @ (x - mu)), rtol=1e-10)
    np.testing.assert_allclose(ml.cov, np.linalg.inv(a @ f), rtol=1e-10)
    # Observed pixels only: equals conditioning the Gaussian of the observed rows.
    mask = rng.random(30) < 0.5
    o = np.flatnonzero(mask)
    part = faces.posterior(model, x, mask)
    c_oo = c[np.ix_(o, o)]
    np.testing.assert_allclose(part.mean, f[o].T @ np.linalg.solve(c_oo, x[o] - mu[o]), rtol=1e-10)
    np.testing.assert_allclose(
        part.cov, np.eye(4) - f[o].T @ np.linalg.solve(c_oo, f[o]), atol=1e-12
    )
    # Missing pixels may hold anything.
    junk = np.where(mask, x, 1e6)
    np.testing.assert_allclose(faces.posterior(model, junk, mask).mean, part.mean, rtol=1e-12)
    ll = faces.log_likelihood(model, x, mask)
    np.testing.assert_allclose(ll, multivariate_normal(mu[o], c_oo).logpdf(x[o]), rtol=1e-12)
    np.testing.assert_allclose(
        faces.log_likelihood(model, x), multivariate_normal(mu, c).logpdf(x), rtol=1e-12
    )
    # An all-ones mask is the full posterior.
    full = faces.posterior(model, x, np.ones(30, bool))
    np.testing.assert_allclose(full.mean, post.mean, rtol=1e-13)
    np.testing.assert_allclose(full.cov, post.cov, rtol=1e-13)


def test_vmap_equals_loop_and_jit_equals_eager(fa_lfw, lfw):
    model, images = fa_lfw.model, jnp.asarray(lfw[:6])
    mask = jnp.asarray(lfw[0] > 0.4)
    batched = jax.vmap(lambda x: faces.posterior(model, x, mask))(images)
    lls = jax.jit(jax.vmap(lambda x: faces.log_likelihood(model, x, mask)))(images)
    for i in range(6):
        one = faces.posterior(model, images[i], mask)
        np.testing.assert_allclose(batched.mean[i], one.mean, rtol=1e-11)
        np.testing.assert_allclose(batched.cov[i], one.cov, rtol=1e-11)
        np.testing.assert_allclose(lls[i], faces.log_likelihood(model, images[i], mask), rtol=1e-12)
    # A batch of masks too (one per image).
    masks = jnp.asarray(lfw[:6] > 0.4)
    per = jax.vmap(lambda x, m: faces.log_likelihood(model, x, m))(images, masks)
    np.testing.assert_allclose(per[0], lls[0], rtol=1e-12)


def test_sampling(key):
    model = random_model(4, d=12, q=2, shape=(3, 4))
    clean = faces.sample(key, model, 500)
    assert clean.shape == (500, 3, 4)
    np.testing.assert_array_equal(clean, faces.sample(key, model, 500))  # deterministic
    # Without noise (as in the paper) every sample lies in μ + span(F).
    f = np.asarray(model.factors)
    centred = np.asarray(clean).reshape(500, 12) - np.asarray(model.mean)
    resid = centred - (centred @ np.linalg.pinv(f).T) @ f.T
    assert np.abs(resid).max() < 1e-10
    noisy = np.asarray(faces.sample(key, model, 40000, noise=True)).reshape(40000, 12)
    np.testing.assert_allclose(
        np.cov(noisy.T), dense_cov(model), atol=0.08 * np.abs(dense_cov(model)).max()
    )
    # Posterior hypotheses scatter around the posterior-mean reconstruction.
    x = np.asarray(clean[0])
    mask = np.zeros((3, 4), bool)
    mask[0] = True
    draws = faces.sample_posterior(key, model, x, 4000, mask)
    post = faces.posterior(model, x, mask)
    centre = faces.reconstruct(model, post.mean)
    np.testing.assert_allclose(np.mean(draws, axis=0), centre, atol=0.05)
    spread = np.std(np.asarray(draws).reshape(4000, 12) @ np.linalg.pinv(f).T, axis=0)
    np.testing.assert_allclose(spread, np.sqrt(np.diag(post.cov)), rtol=0.05)


def test_missing_pixel_em(lfw):
    """EM with missing pixels: monotone; with nothing missing, identical to the complete EM."""
    rng = np.random.default_rng(5)
    mask = rng.random(lfw.shape) > 0.3
    holes = np.where(mask, lfw, np.nan)
    fit = faces.fit_factor_analyser(holes, 8, mask=mask, n_iter=15)
    assert np.all(np.diff(np.asarray(fit.log_likelihood)) >= -1e-9)
    # Its likelihood is the marginal likelihood of the observed pixels.
    ll = jax.vmap(lambda x, m: faces.log_likelihood(fit.model, x, m))(lfw, mask)
    np.testing.assert_allclose(jnp.mean(ll), fit.log_likelihood[-1], rtol=1e-10)
    # The missing-pixel step with an all-ones mask follows the complete-data EM exactly.
    x = jnp.asarray(lfw.reshape(100, -1))
    x = x - jnp.mean(x, axis=0)
    floor = jnp.asarray(1e-6)
    _, _, f0, n0 = _em.init_single(x, 8, floor)
    params = (jnp.zeros(625), f0[0], n0[0])
    inf = jnp.asarray(-jnp.inf)
    masked = _em.fit_masked_em(x, jnp.ones_like(x), params, 5, inf, floor)
    full = _em.fit_mixture_em(x, _em.init_single(x, 8, floor), 5, inf, floor)
    np.testing.assert_allclose(masked[1], full[1], rtol=1e-12)
    np.testing.assert_allclose(masked[0][1], full[0][2][0], atol=1e-10)


# --- mixture of factor analysers -------------------------------------------------------------


@pytest.fixture(scope="module")
def clusters():
    """600 samples from three well-separated 2-factor analysers in 20 dimensions."""
    rng = np.random.default_rng(6)
    labels = rng.integers(0, 3, 600)
    means = rng.normal(scale=4.0, size=(3, 20))
    f = rng.normal(size=(3, 20, 2))
    h = rng.normal(size=(600, 2))
    x = means[labels] + np.einsum("ndq,nq->nd", f[labels], h) + 0.3 * rng.normal(size=(600, 20))
    return x, labels


def test_mixture_em_monotone_and_dense_reference(clusters):
    x, labels = clusters
    fit = faces.fit_mixture(jax.random.key(1), x, 3, 2)
    history = np.asarray(fit.log_likelihood)
    assert np.all(np.diff(history) >= -1e-9), np.diff(history).min()
    model = fit.model
    np.testing.assert_allclose(np.sum(model.weights), 1.0, rtol=1e-12)
    resp = jax.vmap(lambda v: faces.responsibilities(model, v))(x)
    assert adjusted_rand_score(labels, np.argmax(resp, axis=1)) > 0.99
    # Log-likelihood: log-sum-exp of dense component densities.
    comps = [faces.get_component(model, k) for k in range(3)]
    dense = np.stack(
        [multivariate_normal(np.asarray(c.mean), dense_cov(c)).logpdf(x[:5]) for c in comps]
    )
    ref = np.log(np.sum(np.asarray(model.weights)[:, None] * np.exp(dense), axis=0))
    ours = jax.vmap(lambda v: faces.log_likelihood(model, v))(x[:5])
    np.testing.assert_allclose(ours, ref, rtol=1e-10)
    np.testing.assert_allclose(
        history[-1], jnp.mean(jax.vmap(lambda v: faces.log_likelihood(model, v))(x)), rtol=1e-10
    )
    # Per-component posteriors are the component factor analysers' posteriors; masked = full
    # when all pixels are observed; a partial mask still finds the right component.
    post = faces.posterior(model, x[0])
    for k in range(3):
        np.testing.assert_allclose(post.mean[k], faces.posterior(comps[k], x[0]).mean, rtol=1e-12)
    full_mask = faces.posterior(model, x[0], np.ones(20, bool))
    np.testing.assert_allclose(full_mask.mean, post.mean, rtol=1e-12)
    half = np.arange(20) < 10
    assert int(jnp.argmax(faces.responsibilities(model, x[0], half))) == int(jnp.argmax(resp[0]))
    images, comp = faces.sample(jax.random.key(2), model, 300, return_components=True)
    assert images.shape == (300, 20) and set(np.unique(comp)) <= {0, 1, 2}
    drawn = jax.vmap(lambda v: jnp.argmax(faces.responsibilities(model, v)))(images)
    assert np.mean(np.asarray(drawn) == np.asarray(comp)) > 0.97
    hyp = faces.sample_posterior(jax.random.key(3), model, x[0], 5, half)
    assert hyp.shape == (5, 20)


def test_mixture_separates_frontal_and_profile(ict):
    """Fig. 6 of the paper: two factor analysers of 8 factors on frontal + profile renders."""
    data = np.concatenate([ict["neutral"], ict["profile"]])
    truth = np.repeat([0, 1], 80)
    fit = faces.fit_mixture(jax.random.key(0), data, 2, 8)
    assert np.all(np.diff(np.asarray(fit.log_likelihood)) >= -1e-9)
    resp = jax.vmap(lambda v: faces.responsibilities(fit.model, v))(data)
    assert adjusted_rand_score(truth, np.argmax(resp, axis=1)) >= 0.9


# --- bilinear style model --------------------------------------------------------------------


def test_bilinear_predicts_held_out_smiles(ict):
    pairs = np.stack([ict["neutral"], ict["smile"]], axis=1)  # (80, 2, 16, 16)
    train, test = pairs[:60], pairs[60:]
    observed = np.ones((60, 2), bool)
    observed[:10, 1] = False  # ten people seen only neutral: stacked vectors with a missing block
    train = np.where(observed[:, :, None, None], train, np.nan)
    fit = faces.fit_bilinear(train, 12, observed=observed)
    assert np.all(np.diff(np.asarray(fit.log_likelihood)) >= -1e-9)
    assert fit.model.n_styles == 2 and fit.model.shape == (16, 16)

    def rms(a, b):
        return float(np.sqrt(np.mean((np.asarray(a) - b) ** 2)))

    predicted = jax.vmap(lambda x: faces.transfer(fit.model, x))(test[:, 0])
    detailed = jax.vmap(lambda x: faces.transfer(fit.model, x, keep_detail=True))(test[:, 0])
    baseline = rms(test[:, 0], test[:, 1])  # "no change": the neutral image itself
    err, err_detail = rms(predicted, test[:, 1]), rms(detailed, test[:, 1])
    assert err < 0.9 * baseline, (err, baseline)
    assert err_detail < 0.75 * baseline, (err_detail, baseline)
    # Style 1 → 1 is the model's reconstruction of the neutral face; the style blocks are
    # factor analysers whose posterior the transfer uses.
    s0 = faces.style(fit.model, 0)
    h = faces.posterior(s0, test[0, 0]).mean
    np.testing.assert_allclose(
        faces.transfer(fit.model, test[0, 0], 0, 0), faces.reconstruct(s0, h)
    )


# --- files and bad input ---------------------------------------------------------------------


def test_save_load_roundtrip(tmp_path, fa_lfw):
    rng = np.random.default_rng(0)
    mix = faces.MixtureOfFactorAnalysers(
        jnp.asarray([0.25, 0.75]),
        jnp.asarray(rng.normal(size=(2, 6))),
        jnp.asarray(rng.normal(size=(2, 6, 2))),
        jnp.asarray(rng.uniform(0.1, 1, size=(2, 6))),
        shape=(2, 3),
    )
    bil = faces.BilinearModel(random_model(0, d=8, q=2, shape=(2, 2, 2)))
    for i, model in enumerate([fa_lfw.model, mix, bil]):
        path = faces.save_model(tmp_path / f"m{i}.npz", model, {"note": "test"})
        saved = faces.load_model(path)
        loaded, meta = saved.model, saved.metadata
        assert type(loaded) is type(model) and meta["note"] == "test" and "jface_version" in meta
        for a, b in zip(
            jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(model), strict=True
        ):
            np.testing.assert_array_equal(a, b)
        assert loaded.shape == model.shape
    from jface.io import save_arrays

    save_arrays(tmp_path / "other.npz", {"a": np.zeros(3)}, {}, kind="DetailStats")
    with pytest.raises(ValueError, match="expected 'FaceModel'"):
        faces.load_model(tmp_path / "other.npz")


def test_constant_pixels_are_floored_with_a_warning(lfw):
    data = lfw.copy()
    data[:, 0, 0] = 0.5
    with pytest.warns(UserWarning, match="1 of 625 pixels are constant"):
        fit = faces.fit_factor_analyser(data, 8)  # same shapes as fa_lfw: no recompilation
    assert float(fit.model.noise[0]) > 0 and np.all(np.isfinite(fit.log_likelihood))


def test_bad_input(unchecked, fa_lfw, lfw):
    model = fa_lfw.model
    with pytest.raises(ValueError, match="more training images than factors"):
        faces.fit_factor_analyser(lfw[:8], 8)
    with pytest.raises(ValueError, match="must be finite"):
        faces.fit_factor_analyser(np.where(lfw > 0.9, np.nan, lfw), 4)
    with pytest.raises(TypeError, match="floating-point"):
        faces.fit_factor_analyser((lfw * 255).astype(np.uint8), 4)
    with pytest.raises(ValueError, match="constant"):
        faces.fit_factor_analyser(np.ones((20, 5, 5)), 2)
    with pytest.raises(ValueError, match="no observed pixel"):
        faces.posterior(model, lfw[0], np.zeros((25, 25), bool))
    with pytest.raises(ValueError, match=r"image shape \(25, 25\)"):
        faces.log_likelihood(model, lfw[0, :20])
    with pytest.raises(ValueError, match=r"mask must have the model's image shape"):
        faces.posterior(model, lfw[0], np.ones((5, 5), bool))
    with pytest.raises(TypeError, match="boolean"):
        faces.posterior(model, lfw[0], np.ones((25, 25)))
    with pytest.raises(ValueError, match="must be finite"):
        faces.log_likelihood(model, np.full((25, 25), np.nan))
    with pytest.raises(ValueError, match="form must be one of"):
        faces.posterior(model, lfw[0], form="map")
    with pytest.raises(ValueError, match="form='ml' needs at least"):
        mask = np.zeros((25, 25), bool)
        mask[0, :3] = True
        faces.posterior(model, lfw[0], mask, form="ml")
    with pytest.raises(ValueError, match="observed in no training image"):
        holes = np.ones(lfw.shape, bool)
        holes[:, 3, 3] = False
        faces.fit_factor_analyser(lfw, 4, mask=holes)
    with pytest.raises(ValueError, match="n_components × \\(n_factors \\+ 1\\)"):
        faces.fit_mixture(jax.random.key(0), lfw[:20], 3, 8)
    with pytest.raises(TypeError, match="must be a FactorAnalyser or MixtureOfFactorAnalysers"):
        faces.log_likelihood("model", lfw[0])
    with pytest.raises(ValueError, match="at least 2 styles"):
        faces.fit_bilinear(lfw[:, None], 4)
    with pytest.raises(ValueError, match="h must have shape"):
        faces.reconstruct(model, np.zeros(3))


# --- command line ----------------------------------------------------------------------------


def test_cli_train_and_sample(tmp_path, monkeypatch, lfw, capsys, written_figures):
    import jface.cli
    from jface.io import read_image, write_png

    monkeypatch.setattr(jface.cli, "COMMAND_MODULES", ("jface.cli._faces",))
    paths = [str(write_png(tmp_path / f"face{i}.png", lfw[i])) for i in range(12)]
    model = tmp_path / "model.npz"
    args = ["faces", "train", *paths, "--out", str(model), "--factors", "3", "--iters", "5"]
    assert jface.cli.main(args) == 0
    saved = faces.load_model(model)
    loaded, meta = saved.model, saved.metadata
    assert (
        isinstance(saved, faces.SavedModel)
        and loaded.shape == (25, 25)
        and meta["n_images"] == 12
        and meta["n_factors"] == 3
    )
    out = tmp_path / "samples"
    assert jface.cli.main(["faces", "sample", str(model), "--n", "5", "--out", str(out)]) == 0
    assert len(list(out.glob("sample_*.png"))) == 5
    grid = [ax for ax in written_figures["grid.png"].axes if ax.images]  # 3 columns, 2 rows
    assert [ax.get_title() for ax in grid] == [f"sample {i}" for i in range(5)]
    for i, ax in enumerate(grid):
        shown = ax.images[0].get_array()
        np.testing.assert_allclose(shown, read_image(out / f"sample_{i:03d}.png"), atol=1 / 255)
    write_png(tmp_path / "small.png", lfw[0, :20, :20])
    bad = [
        "faces",
        "train",
        paths[0],
        str(tmp_path / "small.png"),
        "--out",
        str(tmp_path / "x.npz"),
    ]
    assert jface.cli.main(bad) == 2
    assert "small.png is (20, 20)" in capsys.readouterr().err


def test_sampling_refuses_what_is_not_one_key(unchecked, key):
    """A seed instead of a key, or a stack of keys: the library's one message, not JAX's."""
    model = random_model(4, d=12, q=2, shape=(3, 4))
    x, mask = np.zeros((3, 4)), np.ones((3, 4), bool)
    for call in (
        lambda k: faces.sample(k, model, 2),
        lambda k: faces.sample_posterior(k, model, x, 2, mask),
    ):
        with pytest.raises(TypeError, match="key must be a JAX random key"):
            call(3)
        with pytest.raises(ValueError, match="key must be a single key"):
            call(jax.random.split(key, 2))
