"""Real data that ships with jface, and a robustness set made from it.

Nobody on the jface project made these files; each keeps its licence beside it (see the README's
credits):

- :func:`gravel`: the CC0 gravel height map of scikit-image (``skimage.data.gravel``).
- :func:`mediapipe_face`: the MediaPipe canonical face mesh (Apache-2.0), 468 vertices, with UVs.
- :func:`lee_perry_smith`: "Infinite, 3D Head Scan" by Lee Perry-Smith (CC BY 3.0), a real
  head scan of 8,844 vertices, with the 21 template landmarks placed by hand on it.
- :func:`ict_face_model`: the face area of the ICT-FaceKit morphable model (MIT): neutral
  face, 10 identity modes and the smile expression.

:func:`scan_variants` perturbs a scan as real scans are (holes, noise, decimation, other units,
any pose) and :func:`heterogeneous_maps` gives maps whose detail changes abruptly; tests and
benchmarks measure jface on both.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from jface.data._robustness import ScanVariant, heterogeneous_maps, scan_variants

__all__ = [
    "ScanVariant",
    "gravel",
    "heterogeneous_maps",
    "ict_face_model",
    "lee_perry_smith",
    "mediapipe_face",
    "path",
    "scan_variants",
]


def path(name: str) -> Path:
    """The path of a file of jface's data folder (``gravel.exr``, ``lee_perry_smith_head.obj``,
    ...), for commands that take file names."""
    found = Path(str(resources.files("jface") / "data" / name))
    if not found.is_file():
        raise FileNotFoundError(f"jface ships no data file named {name!r}")
    return found


def gravel() -> np.ndarray:
    """The gravel height map, ``(512, 512)`` float32 in [0, 1] (as ``skimage.data.gravel()``
    divided by 255)."""
    from jface import io

    return io.read_map(path("gravel.exr")).astype(np.float32)


def mediapipe_face():
    """The MediaPipe canonical face: a :class:`jface.io.MeshData` in cm, one UV per vertex."""
    from jface import io

    return io.read_mesh(path("mediapipe_canonical_face.obj"))


def lee_perry_smith():
    """The Lee Perry-Smith head scan (metres) and its 21 hand-placed landmarks.

    Returns:
        ``(scan, landmarks)``: a :class:`jface.io.MeshData` (vertices merged across UV seams, as
        :func:`jface.io.read_mesh` reads it) and a dict template name → vertex id of it.
    """
    from jface import io

    scan = io.read_mesh(path("lee_perry_smith_head.obj"))
    return scan, io.read_landmarks(path("lee_perry_smith_landmarks.json"))


def ict_face_model() -> dict[str, np.ndarray]:
    """The ICT-FaceKit face area: ``vertices`` (cm), ``faces``, ``identity_deltas`` (10 modes),
    ``expression_deltas`` and the other arrays of ``ict_face_small.npz``."""
    from jface.io import load_arrays

    return load_arrays(path("ict_face_small.npz"), kind="FaceMeshModel")[0]
