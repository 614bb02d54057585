"""Steerable pyramid: reconstruction, agreement with pyrtools, batching, boundaries, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jface import pyramid, tiles


def rel_err(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.linalg.norm(a - b) / np.linalg.norm(b)


@pytest.fixture(scope="module")
def texture(gravel):
    return tiles.mirror_tile(gravel, 256)


@pytest.mark.parametrize(
    ("dtype", "tol"), [(jnp.float32, 1e-6), (jnp.float64, 1e-12)], ids=["f32", "f64"]
)
def test_perfect_reconstruction(texture, dtype, tol):
    image = jnp.asarray(texture, dtype)
    pyr = pyramid.build(image)
    assert pyr.highpass.dtype == dtype
    assert rel_err(pyramid.collapse(pyr), texture) <= tol


def test_layout(texture):
    pyr = pyramid.build(jnp.asarray(texture), n_scales=3, n_orientations=6)
    assert pyr.highpass.shape == (256, 256)
    assert [b.shape for b in pyr.bands] == [(6, 256, 256), (6, 128, 128), (6, 64, 64)]
    assert pyr.lowpass.shape == (32, 32)
    names = pyramid.band_names(3, 6)
    assert len(names) == len(pyramid.detail_bands(pyr)) == 1 + 3 * 6


def test_matches_pyrtools_on_real_texture(gravel):
    """Per-band std agrees with pyrtools (matlabPyrTools convention) within 1e-4 relative."""
    import pyrtools as pt

    image = tiles.mirror_tile(gravel, 1024)
    ref = pt.pyramids.SteerablePyramidFreq(image, height=4, order=3, twidth=1)
    pyr = pyramid.build(jnp.asarray(image, jnp.float32))
    ours = [np.std(np.asarray(pyr.highpass, np.float64))]
    theirs = [np.std(ref.pyr_coeffs["residual_highpass"])]
    for s in range(4):
        for b in range(4):
            ours.append(np.std(np.asarray(pyr.bands[s][b], np.float64)))
            theirs.append(np.std(ref.pyr_coeffs[(s, b)]))
    np.testing.assert_allclose(ours, theirs, rtol=1e-4)
    # Coefficient by coefficient too: same signs, orientation order and layout.
    assert rel_err(pyr.highpass, ref.pyr_coeffs["residual_highpass"]) < 1e-4
    for s in range(4):
        for b in range(4):
            assert rel_err(pyr.bands[s][b], ref.pyr_coeffs[(s, b)]) < 1e-4
    # Coarse bands carry pyrtools' scaling (4x per octave), not a renormalised one.
    assert 10 < ours[-1] / ours[1] < 1000


def test_batch_axes_vmap_and_jit(texture, brick):
    images = jnp.stack([jnp.asarray(texture), jnp.asarray(tiles.mirror_tile(brick, 256))])
    batched = pyramid.build(images)
    looped = [pyramid.build(im) for im in images]
    mapped = jax.vmap(pyramid.build)(images)
    jitted = jax.jit(pyramid.build)(images)
    for other in (mapped, jitted):
        for a, b in zip(jax.tree.leaves(batched), jax.tree.leaves(other), strict=True):
            np.testing.assert_allclose(a, b, atol=1e-12)
    for i, single in enumerate(looped):
        np.testing.assert_allclose(batched.bands[2][i], single.bands[2], atol=1e-12)
    np.testing.assert_allclose(pyramid.collapse(batched), images, atol=1e-12)


def test_gradient_flows(texture):
    image = jnp.asarray(texture)

    def energy(x):
        return jnp.sum(pyramid.build(x).bands[1] ** 2)

    grad = jax.grad(energy)(image)
    eps = 1e-6
    direction = jax.random.normal(jax.random.key(1), image.shape, jnp.float64)
    numeric = (energy(image + eps * direction) - energy(image - eps * direction)) / (2 * eps)
    np.testing.assert_allclose(jnp.vdot(grad, direction), numeric, rtol=1e-5)


@pytest.mark.parametrize("shape", [(97, 130), (128, 256)])
@pytest.mark.parametrize("boundary", ["circular", "reflect"])
def test_odd_and_rectangular_sizes(key, shape, boundary):
    image = jax.random.normal(key, shape, jnp.float64)
    pyr = pyramid.build(image, n_scales=3, boundary=boundary)
    assert pyr.image_shape == shape
    assert rel_err(pyramid.collapse(pyr), image) < 1e-12
    for s, band in enumerate(pyr.bands):
        assert pyr.valid(band, s).shape[-2:] == (-(-shape[0] // 2**s), -(-shape[1] // 2**s))


def test_reflect_boundary_keeps_edges_apart():
    """A step at the left edge leaks into the right edge's coefficients only with wraparound."""
    image = np.zeros((128, 128))
    image[:, :8] = 1.0
    circ = pyramid.build(jnp.asarray(image), n_scales=3, boundary="circular")
    refl = pyramid.build(jnp.asarray(image), n_scales=3, boundary="reflect")
    for s in range(3):
        right_circ = np.abs(np.asarray(circ.valid(circ.bands[s], s))[..., -2:]).max()
        right_refl = np.abs(np.asarray(refl.valid(refl.bands[s], s))[..., -2:]).max()
        # The coarsest band's filters reach past the margin a little.
        assert right_refl < (0.01 if s < 2 else 0.1) * right_circ


def test_bad_input(unchecked):
    with pytest.raises(ValueError, match="n_scales=4 is too many"):
        pyramid.build(jnp.zeros((32, 32)))
    with pytest.raises(TypeError, match="image must have a floating-point dtype"):
        pyramid.build(np.zeros((64, 64), np.uint8))
    with pytest.raises(ValueError, match="image must have at least 2 axes"):
        pyramid.build(jnp.zeros(64))
    with pytest.raises(ValueError, match="image must not be empty"):
        pyramid.build(jnp.zeros((0, 64)))
    with pytest.raises(ValueError, match="image must be finite"):
        pyramid.build(jnp.full((64, 64), jnp.nan))
    with pytest.raises(ValueError, match="boundary must be one of"):
        pyramid.build(jnp.zeros((64, 64)), boundary="zero")
    with pytest.raises(TypeError, match="n_scales must be an integer"):
        pyramid.build(jnp.zeros((64, 64)), n_scales=2.5)
    with pytest.raises(TypeError, match="pyramid must be a Pyramid"):
        pyramid.collapse(jnp.zeros((64, 64)))


@settings(max_examples=3, deadline=None)
@given(
    height=st.integers(64, 160),
    width=st.integers(64, 160),
    n_scales=st.integers(1, 4),
    boundary=st.sampled_from(["circular", "reflect"]),
)
def test_reconstruction_property(height, width, n_scales, boundary):
    """Any size the scale count allows reconstructs exactly, whatever the boundary."""
    image = np.random.default_rng(height * 1000 + width).standard_normal((height, width))
    pyr = pyramid.build(jnp.asarray(image), n_scales=n_scales, boundary=boundary)
    assert rel_err(pyramid.collapse(pyr), image) < 1e-12
