"""The marker template: 21 named facial feature points, their connectivity and their fixed layout
in the unit square (Golovinskiy et al. 2006, §2.2: "we have defined 21 feature points ... with
predefined connectivity, these form a marker mesh ... mapped in a pre-defined manner to a
rectangle").

The layout comes from the MediaPipe canonical face: the UVs of its landmark vertices, normalised
to the unit square, with the eight points of the face outline snapped onto the square's border
(temples and jaw angles to the corners; forehead, chin and the two sides of the face to the
middles of the edges) and Delaunay-triangulated into 32 triangles. The border of the marker mesh
is therefore the square itself, and subdivision with corner and crease rules keeps it so: every
level of every face fills the whole displacement image. ``u`` runs from the subject's right to
left (image columns), ``v`` from chin (0) to forehead (1); image row 0 is ``v = 1``.
See ``docs/marker_template.png``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float

from jface import _checks

#: Landmark names in template order (the subject's left/right).
LANDMARK_NAMES: tuple[str, ...] = (
    "forehead",
    "chin",
    "nose_tip",
    "right_eye_outer",
    "left_eye_outer",
    "right_eye_inner",
    "left_eye_inner",
    "mouth_right",
    "mouth_left",
    "upper_lip",
    "lower_lip",
    "right_cheek",
    "left_cheek",
    "right_jaw",
    "left_jaw",
    "right_brow",
    "left_brow",
    "right_ala",
    "left_ala",
    "right_temple",
    "left_temple",
)

_MEDIAPIPE = (
    10, 152, 1, 33, 263, 133, 362, 61, 291, 0, 17, 234, 454, 172, 397, 70, 300, 129, 358, 67, 297
)  # fmt: skip
_ICT = (
    976, 965, 4553, 1622, 3831, 891, 3132, 6643, 6679, 4541, 5945, 1238, 3456, 757, 2998, 993,
    3213, 4565, 5030, 1859, 4059,
)  # fmt: skip

#: Vertex ids of the landmarks on the MediaPipe canonical face (and any MediaPipe face mesh).
MEDIAPIPE_IDS: dict[str, int] = dict(zip(LANDMARK_NAMES, _MEDIAPIPE, strict=True))

#: Vertex ids of the landmarks on the ICT-FaceKit face area (9409 vertices; every identity and
#: expression shares them). Found by a scaled rigid ICP of the MediaPipe face onto the ICT neutral
#: face (RMS 0.8 mm) and taking the nearest ICT vertex of each MediaPipe landmark.
ICT_IDS: dict[str, int] = dict(zip(LANDMARK_NAMES, _ICT, strict=True))

_LAYOUT = np.array(
    [
        [0.5, 1.0],
        [0.5, 0.0],
        [0.5, 0.48],
        [0.277, 0.683],
        [0.723, 0.683],
        [0.418, 0.669],
        [0.582, 0.669],
        [0.38, 0.307],
        [0.62, 0.307],
        [0.5, 0.356],
        [0.5, 0.257],
        [0.0, 0.559],
        [1.0, 0.559],
        [0.0, 0.0],
        [1.0, 0.0],
        [0.225, 0.773],
        [0.775, 0.773],
        [0.395, 0.479],
        [0.605, 0.479],
        [0.0, 1.0],
        [1.0, 1.0],
    ]
)

_FACES = np.array(
    [
        [14, 8, 1], [8, 14, 12], [7, 13, 1], [13, 7, 11], [7, 17, 11], [18, 8, 12], [18, 6, 2],
        [15, 19, 11], [15, 0, 19], [8, 10, 1], [10, 7, 1], [4, 18, 12], [4, 6, 18], [17, 3, 11],
        [3, 15, 11], [10, 9, 7], [17, 9, 2], [7, 9, 17], [9, 10, 8], [9, 18, 2], [18, 9, 8],
        [20, 16, 12], [16, 4, 12], [0, 16, 20], [6, 16, 0], [4, 16, 6], [15, 5, 0], [3, 5, 15],
        [5, 6, 0], [5, 3, 17], [5, 17, 2], [6, 5, 2],
    ],
    dtype=np.int32,
)  # fmt: skip

#: The four landmarks at the square's corners (kept fixed by subdivision).
_CORNERS = ("right_jaw", "left_jaw", "right_temple", "left_temple")


class MarkerTemplate(eqx.Module):
    """Named marker points, their triangles and their planar layout in the unit square.

    Attributes:
        uv: ``(n, 2)`` layout of the points in the unit square (the predefined rectangle map).
        faces: ``(f, 3)`` triangles, counter-clockwise in ``uv`` (outward normals on a face).
        names: the point names, in order (static).
        corners: indices of the points at the square's corners (static); subdivision fixes them.
    """

    uv: np.ndarray
    faces: np.ndarray
    names: tuple[str, ...] = eqx.field(static=True)
    corners: tuple[int, ...] = eqx.field(static=True)

    @property
    def n_points(self) -> int:
        return len(self.names)

    def key(self) -> tuple:
        """A hashable identity of the template (for caching its subdivision levels)."""
        return (self.names, self.corners, self.uv.tobytes(), self.faces.tobytes())


def marker_template() -> MarkerTemplate:
    """The 21-point marker template of jface (see the module docstring and the docs figure)."""
    return MarkerTemplate(
        uv=_LAYOUT.copy(),
        faces=_FACES.copy(),
        names=LANDMARK_NAMES,
        corners=tuple(LANDMARK_NAMES.index(n) for n in _CORNERS),
    )


def landmark_points(
    landmarks: Any,
    vertices: ArrayLike | None = None,
    template: MarkerTemplate | None = None,
) -> Float[Array, "n 3"]:
    """The 3-D landmark points in template order, from names → vertex ids or points.

    Args:
        landmarks: a mapping name → vertex id (int) or 3-D point, e.g. from
            :func:`jface.io.read_landmarks`; or an ``(n, 3)`` array already in template order.
        vertices: ``(V, 3)`` scan vertices, needed when landmarks are vertex ids.
        template: the marker template (default: :func:`marker_template`).

    Returns:
        ``(n, 3)`` float32 points.

    Raises:
        ValueError: missing, unknown or badly formed names/values, vertex ids out of range, or
            ids without ``vertices``.
        TypeError: landmarks of another type.
    """
    template = template or marker_template()
    names = template.names
    if not isinstance(landmarks, Mapping):
        points = _checks.float_array(landmarks, "landmarks", ndim=2)
        if points.shape != (len(names), 3):
            raise ValueError(
                f"landmarks as an array must have shape ({len(names)}, 3) in template order, "
                f"got {tuple(points.shape)}; or pass a mapping name → id/point"
            )
        return points.astype(jnp.float32)
    given = [str(k) for k in landmarks]
    unknown = sorted(set(given) - set(names))
    missing = [n for n in names if n not in landmarks]
    if len(set(given)) != len(given):
        raise ValueError("landmarks: duplicate names")
    if unknown or missing:
        parts = []
        if missing:
            parts.append(f"missing {missing}")
        if unknown:
            parts.append(f"unknown {unknown}")
        raise ValueError(
            f"landmarks must name exactly the {len(names)} template points; "
            + "; ".join(parts)
            + f". Expected names: {list(names)}"
        )
    verts = None
    if vertices is not None:
        verts = np.asarray(_checks.float_array(vertices, "vertices", ndim=2), dtype=np.float64)
    out = np.zeros((len(names), 3))
    for i, name in enumerate(names):
        value = landmarks[name]
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            if verts is None:
                raise ValueError(
                    f"landmark {name!r} is a vertex id ({value}); pass the scan's vertices"
                )
            if not 0 <= int(value) < len(verts):
                raise ValueError(
                    f"landmark {name!r}: vertex id {value} is outside [0, {len(verts)})"
                )
            out[i] = verts[int(value)]
            continue
        arr = np.asarray(value, dtype=np.float64) if _is_point(value) else None
        if arr is None or arr.shape != (3,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"landmark {name!r} must be a vertex id or a finite 3-D point, got {value!r}"
            )
        out[i] = arr
    return jnp.asarray(out, dtype=jnp.float32)


def _is_point(value: Any) -> bool:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        return False
    return arr.dtype.kind in "fiu" and arr.shape == (3,)


def mediapipe_landmarks(vertices: ArrayLike) -> Float[Array, "21 3"]:
    """The 21 landmark points of a MediaPipe face mesh (468 or 478 vertices), template order."""
    vertices = _checks.float_array(vertices, "vertices", ndim=2)
    if vertices.shape[0] not in (468, 478) or vertices.shape[1] != 3:
        raise ValueError(
            f"vertices must be a MediaPipe face mesh, (468, 3) or (478, 3), got "
            f"{tuple(vertices.shape)}"
        )
    return vertices[np.array([MEDIAPIPE_IDS[n] for n in LANDMARK_NAMES])].astype(jnp.float32)


def ict_landmarks(vertices: ArrayLike) -> Float[Array, "21 3"]:
    """The 21 landmark points of an ICT-FaceKit face-area mesh (9409 vertices), template order."""
    vertices = _checks.float_array(vertices, "vertices", ndim=2)
    if vertices.shape != (9409, 3):
        raise ValueError(
            f"vertices must be an ICT-FaceKit face area, (9409, 3), got {tuple(vertices.shape)}"
        )
    return vertices[np.array([ICT_IDS[n] for n in LANDMARK_NAMES])].astype(jnp.float32)
