"""Strict numerics for every test: float64 available, strict dtype promotion, seeded keys."""

from pathlib import Path

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture(scope="session")
def ict_model() -> dict[str, np.ndarray]:
    """The ICT-FaceKit face model that ships with jface (jface/data/ict_face_small.npz: the
    face-area mesh, its 10 leading identity modes and the smile), so tests need no shared data."""
    from jface import data

    return data.ict_face_model()


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance from points to a triangle mesh (closest point over the 16 nearest triangles)."""
    import trimesh
    from scipy.spatial import cKDTree

    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    _, cand = cKDTree(tri.mean(axis=1)).query(points, k=16)
    q = trimesh.triangles.closest_point(tri[cand.ravel()], np.repeat(points, 16, axis=0))
    return np.linalg.norm(q - np.repeat(points, 16, axis=0), axis=1).reshape(-1, 16).min(axis=1)


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    """Drop JAX's compiled executables after a module once the process holds many memory
    mappings: each executable keeps some, and past Linux's vm.max_map_count (65,530 by default)
    the next compilation crashes the interpreter. Below that, modules keep sharing compilations."""
    yield
    maps = Path("/proc/self/maps")
    if maps.exists() and maps.read_text().count("\n") > 30_000:
        jax.clear_caches()


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
