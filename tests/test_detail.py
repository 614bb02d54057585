"""Tile statistics and spatially varying synthesis (Golovinskiy et al. 2006, §2.3–2.4)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface import detail, pyramid, tiles


@pytest.fixture(scope="module")
def texture(gravel):
    return jnp.asarray(tiles.mirror_tile(gravel, 256), jnp.float32)


@pytest.fixture(scope="module")
def stats(texture):
    return detail.analyze(texture)


def test_stats_equal_a_numpy_reference(texture, stats):
    """Per-tile std of every detail band, computed independently with numpy on pyrtools bands."""
    import pyrtools as pt

    ref = pt.pyramids.SteerablePyramidFreq(np.asarray(texture, np.float64), height=4, order=3)
    bands = [ref.pyr_coeffs["residual_highpass"]]
    bands += [ref.pyr_coeffs[(s, o)] for s in range(4) for o in range(4)]
    expected = []
    for band in bands:
        t = band.shape[0] // 16
        expected.append(band.reshape(16, t, 16, t).std(axis=(1, 3)))
    assert stats.std.shape == (17, 16, 16)
    np.testing.assert_allclose(stats.std, np.stack(expected), rtol=2e-4)
    assert stats.band_names[0] == "highpass" and stats.band_names[-1] == "s3o3"


def test_histograms_describe_the_tiles(texture):
    full = detail.analyze(texture, bins=32, grid=8)
    assert full.probabilities.shape == (17, 8, 8, 32) and full.ranges.shape == (17, 8, 8, 2)
    np.testing.assert_allclose(full.probabilities.sum(-1), 1.0, rtol=1e-5)
    band = np.asarray(pyramid.build(texture).bands[1][2], np.float64)
    tile = band[:16, 16:32].ravel()
    counts, _ = np.histogram(tile, bins=32, range=(tile.min(), tile.max()))
    np.testing.assert_allclose(full.probabilities[7, 0, 1], counts / tile.size, atol=1.5 / 256)


def test_blend_weights_partition_unity_and_coverage():
    weights = np.asarray(tiles.blend_weights(64, 8, jnp.float64))
    np.testing.assert_allclose(weights.sum(1), 1.0)
    covering = (weights > 0).sum(1)
    # Interior pixels between two centres take two tiles per axis (four in 2-D); the border
    # strips before the first and after the last centre take one.
    assert covering[:4].tolist() == [1] * 4 and covering[-4:].tolist() == [1] * 4
    assert set(covering[4:-4].tolist()) == {2}
    # Tile centres lie half-way between pixels 3 and 4 (tile size 8): weights there are equal.
    np.testing.assert_allclose(weights[8 + 3, 1] + weights[8 + 4, 1], 2 * 0.9375)


@pytest.mark.parametrize(
    ("rule", "n_refine", "tolerance"), [("exact", 4, 0.02), ("exact", 0, 0.15), ("paper", 0, 0.15)]
)
def test_match_std_on_constant_targets(key, rule, n_refine, tolerance):
    """White noise scaled to a constant target: exact per tile with refined gains; within the
    sampling spread of neighbouring tiles in one pass."""
    band = jax.random.normal(key, (128, 128), jnp.float64) * 3.0
    matched = tiles.match_std(band, jnp.full((8, 8), 0.5), rule=rule, n_refine=n_refine)
    np.testing.assert_allclose(tiles.tile_std(matched, 8), 0.5, rtol=tolerance)


def test_exact_rule_reaches_varying_targets_where_the_paper_rule_drifts(texture, stats):
    band = pyramid.build(texture).bands[0][1]
    rng = np.random.default_rng(0)
    target = stats.std[2] * jnp.asarray(rng.uniform(0.5, 2.0, (16, 16)), jnp.float32)

    def error(rule, repeats, n_refine=0):
        out = band
        for _ in range(repeats):
            out = tiles.match_std(out, target, rule=rule, n_refine=n_refine)
        return float(jnp.median(jnp.abs(tiles.tile_std(out, 16) / target - 1)))

    assert error("exact", 1, n_refine=4) < 0.02
    assert error("exact", 4) < 0.5 * error("exact", 2) < 0.5 * error("exact", 1)
    assert error("paper", 4) > error("paper", 1)  # the ill-posed fixed point of §2.4


def test_fig5_resynthesis_converges_on_real_data(gravel):
    """Smooth a real map, re-synthesise from its own statistics (Golovinskiy et al. Fig. 5).

    512² with the paper's 16 × 16 grid leaves 4 × 4 pixels per tile in the coarsest band.
    """
    texture = jnp.asarray(gravel, jnp.float32)
    stats = detail.analyze(texture)
    smooth = detail.remove_detail(texture, n_bands=3)
    before = np.asarray(detail.stats_error(detail.analyze(smooth), stats))
    result = detail.synthesize(jax.random.key(0), smooth, stats)
    after = np.asarray(detail.stats_error(detail.analyze(result), stats))
    assert np.median(before) > 0.3
    assert np.median(after) <= 0.02 and np.percentile(after, 95) <= 0.08
    # The low-pass residual (the base mesh's share) is kept; re-analysis sees only the overlap
    # of the coarsest band's transition with it.
    kept, original = pyramid.build(result).lowpass, pyramid.build(jnp.asarray(smooth)).lowpass
    assert float(jnp.linalg.norm(kept - original) / jnp.linalg.norm(original)) < 1e-3


def test_synthesis_is_deterministic_and_vmaps(texture, stats, key):
    """Accelerated iterations and polish steps under vmap equal a loop. (Few polish steps: over
    tens of L-BFGS steps, the rounding differences of batched reductions can tip a line search.)
    """
    starts = jnp.stack([texture, texture[::-1]])
    keys = jax.random.split(key, 2)
    settings = {"n_iter": 3, "n_polish": 5}
    mapped = jax.vmap(lambda k, s: detail.synthesize(k, s, stats, **settings))(keys, starts)
    looped = [detail.synthesize(k, s, stats, **settings) for k, s in zip(keys, starts, strict=True)]
    np.testing.assert_allclose(mapped, jnp.stack(looped), atol=1e-5)
    again = detail.synthesize(keys[0], starts[0], stats, **settings)
    np.testing.assert_array_equal(again, looped[0])
    other = detail.synthesize(keys[1], starts[0], stats, **settings)
    assert not np.allclose(other, looped[0])


def test_analyze_vmap_equals_loop(texture):
    images = jnp.stack([texture, texture.T])
    mapped = jax.vmap(detail.analyze)(images)
    for i in range(2):
        np.testing.assert_allclose(mapped.std[i], detail.analyze(images[i]).std, rtol=1e-6)


def test_histogram_synthesis_moves_tiles_towards_targets(texture):
    texture = texture[:64, :64]
    full = detail.analyze(texture, bins=16, grid=4, n_scales=2)
    smooth = detail.remove_detail(texture, n_bands=2, n_scales=2)
    result = detail.synthesize(jax.random.key(1), smooth, full, n_iter=2)
    before = detail.stats_error(detail.analyze_like(smooth, full), full)
    after = detail.stats_error(detail.analyze_like(result, full), full)
    assert float(jnp.median(after)) < 0.25 * float(jnp.median(before))


def test_reflect_boundary_synthesis(texture, stats):
    smooth = detail.remove_detail(texture, n_bands=3)
    result = detail.synthesize(jax.random.key(2), smooth, stats, boundary="reflect", n_iter=4)
    error = detail.stats_error(detail.analyze(result, boundary="reflect"), stats)
    assert result.shape == texture.shape and float(jnp.median(error)) < 0.1


def test_save_load_and_population(tmp_path, texture, stats):
    detail.save_stats(tmp_path / "s.npz", stats, source="gravel", seed=3)
    saved = detail.load_stats(tmp_path / "s.npz")
    assert isinstance(saved, detail.SavedStats)
    loaded, meta = saved.stats, saved.metadata
    np.testing.assert_array_equal(loaded.std, stats.std)
    assert meta["source"] == "gravel" and meta["grid"] == 16 and "jface_version" in meta
    other = detail.analyze(texture * 2.0)
    population = detail.Population.from_faces(
        [stats, other], [{"id": "a", "age": 30, "sex": "f"}, {"id": "b", "age": 70, "sex": "m"}]
    )
    old = population.select(age=(60, 90))
    assert len(old) == 1 and old.records[0]["id"] == "b"
    np.testing.assert_allclose(old.mean().std, other.std, rtol=1e-6)
    np.testing.assert_allclose(population.mean().std, stats.std * float(np.sqrt(2.5)), rtol=1e-5)
    population.save(tmp_path / "p.npz", note="test")
    back = detail.Population.load(tmp_path / "p.npz")
    assert back.records == population.records
    np.testing.assert_array_equal(back.stats.std, population.stats.std)


def test_bad_input(unchecked, texture, stats, tmp_path):
    with pytest.raises(ValueError, match="grid=16 must split"):
        detail.analyze(jnp.zeros((200, 200)))
    with pytest.raises(ValueError, match="image must have 2 axes"):
        detail.analyze(jnp.zeros((2, 256, 256)))
    with pytest.raises(TypeError, match="floating-point"):
        detail.analyze(np.zeros((256, 256), np.int32))
    with pytest.raises(ValueError, match="start has shape"):
        detail.synthesize(jax.random.key(0), texture[:128, :128], stats)
    with pytest.raises(ValueError, match="needs full statistics"):
        detail.synthesize(jax.random.key(0), texture, stats, method="histogram")
    with pytest.raises(ValueError, match="noise must be in"):
        detail.synthesize(jax.random.key(0), texture, stats, noise=-1.0)
    with pytest.raises(ValueError, match="layout"):
        detail.stack_stats([stats, detail.analyze(texture, grid=8)])
    with pytest.raises(ValueError, match="selection is empty"):
        detail.Population.from_faces([stats], [{"id": "a", "age": 3}]).select(age=(50, 60))
    with pytest.raises(ValueError, match="field 'sex' is missing"):
        detail.Population.from_faces([stats], [{"id": "a"}]).select(sex="f")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable jface"):
        detail.load_stats(tmp_path / "bad.npz")


def test_fixed_point_and_noise_scale(texture, stats, key):
    """The source is a fixed point of its own statistics; the noise has the stated amplitude."""
    same = detail.synthesize(key, texture, stats, noise=0.0)
    assert float(jnp.max(jnp.abs(same - texture))) < 1e-4
    noisy = detail.synthesize(key, texture, stats, n_iter=0, n_polish=0, noise=0.5)
    np.testing.assert_allclose(jnp.std(noisy - texture), 0.5 * stats.detail_rms(), rtol=0.02)


def test_jit_equals_eager_and_vmap_over_targets(texture, stats, key):
    eager = detail.analyze(texture)
    jitted = jax.jit(detail.analyze)(texture)
    np.testing.assert_allclose(jitted.std, eager.std, rtol=1e-6)
    run = jax.jit(lambda k, s, t: detail.synthesize(k, s, t, n_iter=2, n_polish=5))
    np.testing.assert_allclose(
        run(key, texture, stats),
        detail.synthesize(key, texture, stats, n_iter=2, n_polish=5),
        atol=1e-5,
    )
    targets = detail.stack_stats([stats, detail.analyze(texture * 2.0)])
    mapped = jax.vmap(lambda t: detail.synthesize(key, texture, t, n_iter=2, n_polish=5))(targets)
    second = jax.tree.map(lambda x: x[1], targets)
    expected = detail.synthesize(key, texture, second, n_iter=2, n_polish=5)
    np.testing.assert_allclose(mapped[1], expected, atol=1e-5)


def with_std(stats, std):
    return eqx.tree_at(lambda s: s.std, stats, std)


def test_histogram_matching_reaches_spatially_varying_targets(texture):
    """A band matched to Laplacian tiles, three times wider on the right half: away from the
    seam, each half takes the quantiles of its own target."""
    band = pyramid.build(texture[:128, :128]).bands[0][0]
    rng = np.random.default_rng(0)
    width = jnp.where(jnp.arange(128) < 64, 1.0, 3.0) * float(jnp.std(band))
    target = jnp.asarray(rng.laplace(size=band.shape), band.dtype) * width.astype(band.dtype)
    probabilities, ranges = tiles.tile_histograms(target, 8, 32)
    matched = tiles.match_histogram(band, probabilities, ranges)
    levels = jnp.linspace(0.05, 0.95, 10)
    for columns in (slice(0, 48), slice(80, 128)):
        want = jnp.quantile(target[:, columns], levels)
        got = jnp.quantile(matched[:, columns], levels)
        before = jnp.quantile(band[:, columns], levels)
        assert float(jnp.max(jnp.abs(got - want))) < 0.1 * float(jnp.max(jnp.abs(want)))
        assert float(jnp.max(jnp.abs(before - want))) > 0.2 * float(jnp.max(jnp.abs(want)))


def test_bad_targets(unchecked, texture, stats, key):
    with pytest.raises(ValueError, match=r"target\.std must be non-negative"):
        detail.synthesize(key, texture, with_std(stats, -stats.std))
    with pytest.raises(ValueError, match=r"target\.std must be finite"):
        detail.synthesize(key, texture, with_std(stats, stats.std.at[0, 0, 0].set(jnp.nan)))
    with pytest.raises(ValueError, match=r"target.std must be \(..., 17, grid, grid\)"):
        detail.synthesize(key, texture, with_std(stats, stats.std[:5]))
    with pytest.raises(TypeError, match="key must be a JAX random key"):
        detail.synthesize(0, texture, stats)
    with pytest.raises(ValueError, match="at least 2×2 pixels"):
        detail.analyze(jnp.zeros((128, 128)))
    with pytest.raises(ValueError, match="n_scales must be in"):
        pyramid.build(jnp.zeros((64, 64)), n_scales=0)
    wide = jax.random.normal(key, (256, 320))
    odd = detail.analyze(wide, bins=8, grid=16, n_scales=3)
    with pytest.raises(ValueError, match="even number of pixels per tile side"):
        detail.synthesize(key, wide, odd)
    with pytest.raises(ValueError, match="image is constant"):
        detail.analyze(jnp.full((256, 256), 0.5))
    with pytest.raises(ValueError, match="image must be finite"):
        detail.analyze(texture.at[3, 4].set(jnp.nan))
    with pytest.raises(ValueError, match="target describes no detail"):
        detail.synthesize(key, texture, with_std(stats, stats.std * 0.0))
