"""Strict numerics for every test: float64 available, strict dtype promotion, seeded keys."""

from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

#: Real data that ships beside the repository (meshes, ICT-FaceKit); see its README.
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def key():
    """A fixed-seed key: tests are deterministic."""
    return jax.random.key(0)


@pytest.fixture(scope="session")
def gravel() -> np.ndarray:
    """scikit-image's real gravel texture (CC0), 512×512, float64 in [0, 1]."""
    from skimage import data

    return data.gravel().astype(np.float64) / 255.0


@pytest.fixture(scope="session")
def brick() -> np.ndarray:
    """scikit-image's real brick texture (CC0), 512×512, float64 in [0, 1]."""
    from skimage import data

    return data.brick().astype(np.float64) / 255.0


@pytest.fixture
def unchecked():
    """Switch off the test-time jaxtyping/beartype checks, so bad-input tests see the library's
    own validation messages (what a user without the checker gets)."""
    import jaxtyping

    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", False)
