"""§4.1 extraction (Gabor orientation, pores) and §5 blending: the building blocks against
scikit-image / scipy in float64, orientation and pores recovered from simulated maps, bad input."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi
from scipy.spatial import cKDTree

from jface.wrinkles import (
    WrinkleParams,
    binary_opening,
    blend_with_scan,
    extract_orientation,
    extract_pores,
    gabor_energy,
    gabor_kernels,
    gaussian_blur,
    label_components,
    sample_pores,
    synthesize,
)


@pytest.fixture(scope="module")
def noise_image():
    return np.random.default_rng(0).normal(size=(48, 40)).astype(np.float32)


def test_gaussian_blur_matches_scipy(noise_image):
    for sigma in (1.0, 2.0):
        ref = ndi.gaussian_filter(noise_image.astype(np.float64), sigma, mode="reflect")
        np.testing.assert_allclose(gaussian_blur(jnp.asarray(noise_image), sigma), ref, atol=1e-5)


def test_gabor_matches_scikit_image(noise_image):
    from skimage.filters import gabor, gabor_kernel

    kernels = gabor_kernels(0.2, 8)
    r = kernels.shape[-1] // 2
    for i in (0, 3, 6):
        theta = math.pi * i / 8
        ref = gabor_kernel(0.2, theta=theta)
        ky, kx = ref.shape[0] // 2, ref.shape[1] // 2
        np.testing.assert_allclose(kernels[i][r - ky : r + ky + 1, r - kx : r + kx + 1], ref,
                                   atol=1e-6)  # fmt: skip
        # the convolution itself, with scikit-image's kernel (cut tighter along some angles)
        padded = np.zeros_like(kernels[:1])
        padded[0, r - ky : r + ky + 1, r - kx : r + kx + 1] = ref
        energy = np.asarray(gabor_energy(jnp.asarray(noise_image), padded))[0]
        real, imag = gabor(noise_image.astype(np.float64), 0.2, theta=theta, mode="reflect")
        np.testing.assert_allclose(energy, real**2 + imag**2, atol=1e-5 * np.max(energy))


def test_opening_and_components_match_scipy_and_skimage():
    from skimage.measure import label

    rng = np.random.default_rng(1)
    mask = ndi.gaussian_filter(rng.normal(size=(64, 72)), 1.5) > 0.05
    opened = np.asarray(binary_opening(jnp.asarray(mask)))
    np.testing.assert_array_equal(opened, ndi.binary_opening(mask, np.ones((3, 3))))
    ours = np.asarray(label_components(jnp.asarray(opened)))
    ref = label(opened, connectivity=2)
    assert (ours > 0).tolist() == (ref > 0).tolist()
    pairs = {(int(a), int(b)) for a, b in zip(ours[opened], ref[opened], strict=True)}
    assert len(pairs) == ref.max() == len(np.unique(ours[opened]))  # the same partition


def _simulated(params):
    """A simulated 256² map; every test here simulates with the drawing tests' α_d and settings,
    so the compiled sampling, graph, simulation and drawing are shared."""
    return synthesize(jax.random.key(0), [params], (256, 256), n_steps=60, n_samples=3000)


@pytest.mark.parametrize("theta", [0.4, 2.2])
def test_orientation_recovered_on_simulated_map(theta):
    syn = _simulated(WrinkleParams(d=0.05, theta=theta, s=0.05, wrinkle_width=0.4, snoise=0.001))
    got = extract_orientation(syn.displacement, crop=256, frequency=0.1)
    err = (float(got.theta[0, 0]) - theta + math.pi / 2) % math.pi - math.pi / 2
    assert abs(math.degrees(err)) < 5.0
    assert got.histogram.shape == (1, 1, 16)


def test_pores_recovered_on_simulated_map():
    params = WrinkleParams(d=0.05, theta=0.5, s=0.3, wrinkle_width=0.1, pore_width=0.5,
                           dmin=1.0, blend=0.0, snoise=0.001, sperturb=0.001)  # fmt: skip
    syn = _simulated(params)
    pores = syn.levels[0].pores
    known = np.asarray(pores.positions)[: int(pores.count)] * 256
    found = extract_pores(syn.displacement)
    got = np.asarray(found.positions)[: int(found.count)] * 256
    dist, _ = cKDTree(got).query(known)
    assert np.mean(dist <= 2.0) >= 0.9
    assert int(found.count) <= 1.1 * len(known)  # not by flooding the map with detections
    # they seed the next level's sampling
    again = sample_pores(jax.random.key(1), 0.03, initial=found, periodic=False)
    assert int(again.count) > int(found.count)
    first = np.asarray(again.positions)[: int(found.count)]
    np.testing.assert_allclose(first, np.asarray(found.positions)[: int(found.count)])


def test_blend_with_scan():
    rng = np.random.default_rng(2)
    scan = rng.normal(size=(40, 40)).astype(np.float32)
    detail = rng.normal(size=(40, 40)).astype(np.float32)
    out = blend_with_scan(scan, detail)
    ref = ndi.gaussian_filter(scan.astype(np.float64), 2.5, mode="reflect", truncate=2.0)
    np.testing.assert_allclose(np.asarray(out) - detail, ref, atol=1e-5)


def test_bad_input(unchecked):
    with pytest.raises(ValueError, match="at least crop=128"):
        extract_orientation(np.zeros((64, 300), np.float32))
    with pytest.raises(ValueError, match="image"):
        extract_pores(np.zeros((8, 8, 3), np.float32))
    with pytest.raises(ValueError, match="frequency"):
        extract_orientation(np.zeros((128, 128), np.float32), frequency=0.9)
    with pytest.raises(ValueError, match="one shape"):
        blend_with_scan(np.zeros((8, 8), np.float32), np.zeros((8, 9), np.float32))
