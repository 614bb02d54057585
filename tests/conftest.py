"""Strict numerics for every test: float64 available, strict dtype promotion, seeded keys."""

from importlib import resources
from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

#: Real data that ships beside the repository (meshes, ICT-FaceKit); see its README.
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def ict_model() -> dict[str, np.ndarray]:
    """The ICT-FaceKit face model that ships with jface (jface/data/ict_face_small.npz: the
    face-area mesh, its 10 leading identity modes and the smile), so tests need no shared data."""
    from jface.io import load_arrays

    with resources.as_file(resources.files("jface") / "data" / "ict_face_small.npz") as path:
        return load_arrays(path, kind="FaceMeshModel")[0]


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
