"""Texture loss: agreement with a pyrtools formulation, invariances, sensitivity, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jface.optim import texture_distance, texture_loss, texture_stats


def oriented_noise(key, angle, frequency, size=64):
    """Stationary periodic noise whose spectrum is concentrated at ``angle`` and ``frequency``
    (cycles per image); a ground truth for orientation and scale mismatch."""
    fy = np.fft.fftfreq(size)[:, None] * size
    fx = np.fft.fftfreq(size)[None, :] * size
    radius = np.hypot(fx, fy)
    direction = np.abs(np.cos(np.arctan2(fy, fx) - angle))
    spectrum = np.exp(-0.5 * (np.log2(np.maximum(radius, 1e-9) / frequency) / 0.3) ** 2)
    spectrum *= direction**8
    phase = np.asarray(jax.random.normal(key, (size, size)), np.float64)
    return np.real(np.fft.ifft2(np.fft.fft2(phase) * spectrum)).astype(np.float32)


@pytest.fixture(scope="module")
def patches(gravel, brick):
    return (
        np.asarray(gravel[:64, :64], np.float32),
        np.asarray(gravel[300:364, 200:264], np.float32),
        np.asarray(brick[:64, :64], np.float32),
    )


def test_matches_a_pyrtools_formulation_in_float64(gravel):
    import pyrtools as pt

    image, other = gravel[:64, :64], gravel[100:164, 100:164]

    def bands(x):
        ref = pt.pyramids.SteerablePyramidFreq(x, height=3, order=3, twidth=1).pyr_coeffs
        out = [ref["residual_highpass"][None]]
        out += [np.stack([ref[(s, b)] for b in range(4)]) for s in range(3)]
        return [*out, ref["residual_lowpass"][None]]

    # white-noise RMS of every band, by Parseval from pyrtools' response to one impulse
    impulse = np.zeros((64, 64))
    impulse[32, 32] = 1.0
    scales = [0, 0, 1, 2, 3]
    gains = [
        np.sqrt(4.0**s * np.sum(b**2, axis=(1, 2)))
        for b, s in zip(bands(impulse), scales, strict=True)
    ]

    def features(x):
        x = (x - x.mean()) / np.sqrt(x.var() + 1e-12)
        groups = [x[None]] + [b / g[:, None, None] for b, g in zip(bands(x), gains, strict=True)]
        means, stds = [], []
        for g in groups:
            for part in (np.maximum(g, 0), np.maximum(-g, 0)):
                means += list(part.mean(axis=(1, 2)))
                stds += list(part.std(axis=(1, 2)))
        return np.array(means), np.array(stds)

    (mp, sp), (mt, st) = features(other), features(image)
    expected = np.mean((mp - mt) ** 2 + (sp - st) ** 2)
    ours = texture_loss(other, image, n_scales=3, boundary="circular")
    assert ours.dtype == jnp.float64
    np.testing.assert_allclose(float(ours), expected, rtol=1e-5)


def test_zero_for_identical_and_invariant_to_gain_and_offset(patches):
    a, b, _ = patches
    assert float(texture_loss(a, a)) == 0.0
    base = float(texture_loss(b, a))
    assert float(texture_loss(3.0 * a + 0.7, a)) < 1e-8
    np.testing.assert_allclose(float(texture_loss(0.2 * b - 5.0, 4.0 * a + 1.0)), base, rtol=1e-3)


def test_translation_insensitive_for_stationary_textures(key, patches):
    a, b, brick = patches
    noise = oriented_noise(key, 0.3, 8.0)
    different = float(texture_loss(oriented_noise(key, 1.2, 8.0), noise, boundary="circular"))
    # a circular shift of a periodic texture by whole coarsest-scale pixels: the same statistics;
    # by any other amount: nearly so (the subsampled coarse bands see other sample positions)
    assert float(texture_loss(np.roll(noise, (16, 32), (0, 1)), noise, boundary="circular")) < 1e-9
    shifted = float(texture_loss(np.roll(noise, (17, 29), (0, 1)), noise, boundary="circular"))
    assert shifted < 1e-2 * different
    # two crops of one real texture are much closer than two different textures
    assert float(texture_loss(b, a)) < 0.25 * float(texture_loss(brick, a))


def test_grows_with_orientation_mismatch(key):
    target = oriented_noise(key, 0.0, 8.0)
    other = jax.random.split(key)[1]
    losses = [
        float(texture_loss(oriented_noise(other, angle, 8.0), target))
        for angle in (0.0, np.pi / 16, np.pi / 8, np.pi / 4, np.pi / 2)
    ]
    # rises with the mismatch up to the spacing of the four orientation bands, then stays high
    assert np.all(np.diff(losses[:4]) > 0) and losses[4] > 5 * losses[0], losses


def test_grows_with_scale_mismatch(key):
    target = oriented_noise(key, 0.0, 4.0)
    other = jax.random.split(key)[1]
    losses = [
        float(texture_loss(oriented_noise(other, 0.0, f), target)) for f in (4.0, 6.0, 8.0, 16.0)
    ]
    assert losses[0] < 0.1 * losses[-1] and np.all(np.diff(losses) > 0), losses


def test_jit_vmap_and_gradient(patches):
    a, b, brick = patches
    target = texture_stats(a)
    loss = jax.jit(lambda x: texture_distance(texture_stats(x), target))
    batch = jnp.stack([b, brick])
    np.testing.assert_allclose(
        jax.vmap(loss)(batch), [texture_loss(b, a), texture_loss(brick, a)], rtol=1e-5
    )
    grad = jax.grad(loss)(jnp.asarray(brick))
    assert grad.shape == brick.shape and np.all(np.isfinite(grad)) and np.any(grad != 0)
    # a step against the gradient lowers the loss
    step = 0.01 / float(jnp.max(jnp.abs(grad)))
    assert float(loss(brick - step * grad)) < float(loss(brick))


def test_a_constant_prediction_gives_a_finite_loss(patches):
    a = patches[0]
    value = float(texture_loss(np.zeros_like(a), a))
    assert np.isfinite(value) and value > float(texture_loss(patches[2], a))


@pytest.mark.parametrize(
    ("prediction", "target", "error", "match"),
    [
        (np.zeros((64, 64), np.float32), np.ones((64, 64), np.float32), ValueError, "constant"),
        (
            np.zeros((64, 64), np.float32),
            np.full((64, 64), np.nan, np.float32),
            ValueError,
            "finite",
        ),
        (np.zeros((64, 64), np.int32), np.eye(64, dtype=np.float32), TypeError, "prediction"),
        (np.zeros((2, 64, 64), np.float32), np.eye(64, dtype=np.float32), ValueError, "2 axes"),
        (np.eye(8, dtype=np.float32), np.eye(8, dtype=np.float32), ValueError, "n_scales"),
    ],
)
def test_bad_input(prediction, target, error, match, unchecked):
    with pytest.raises(error, match=match):
        texture_loss(prediction, target)
