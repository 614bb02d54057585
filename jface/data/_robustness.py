"""Real data perturbed as real data comes: scans with holes, noise, fewer triangles, other units
and any pose; maps whose detail changes abruptly."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

#: The perturbations of :func:`scan_variants`, in the order "combined" applies them.
SCAN_KINDS = ("original", "decimated", "holes", "noise", "millimetres", "posed", "combined")


class ScanVariant(NamedTuple):
    """A perturbed scan and where it came from.

    Attributes:
        vertices: ``(V, 3)`` float64 positions.
        faces: ``(F, 3)`` int64 triangles.
        landmarks: ``(21, 3)`` the landmarks as points, moved with the scan.
        scale, rotation, translation: the similarity applied to the original,
            ``x' = scale · rotation @ x + translation``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def to_original(self, points: Any) -> np.ndarray:
        """Map ``(n, 3)`` points of this variant's frame back to the original scan's frame."""
        points = np.asarray(points, dtype=np.float64)
        return (points - self.translation) @ self.rotation / self.scale


def scan_variants(
    vertices: Any,
    faces: Any,
    landmarks: Any,
    *,
    seed: int = 0,
    kinds: tuple[str, ...] = SCAN_KINDS,
) -> dict[str, ScanVariant]:
    """A scan perturbed as real scans are, each variant with its landmarks moved along.

    - "original": unchanged.
    - "decimated": quadric decimation to 40% of the triangles (needs the ``fast_simplification``
      package, in jface's ``test`` and ``bench`` extras).
    - "holes": six holes of radius 1.2% of the bounding-box diagonal punched into the face,
      away from the landmarks.
    - "noise": Gaussian noise of 0.03% of the diagonal along the vertex normals (0.2 mm on a
      head).
    - "millimetres": scaled by 1000 (a scan in metres saved in millimetres).
    - "posed": a random rotation and a translation by three diagonals.
    - "combined": all of the above at once.

    Args:
        vertices, faces: the scan.
        landmarks: the 21 template landmarks (names → vertex ids or points, or ``(21, 3)``).
        seed: seeds every random choice.
        kinds: which variants to make.

    Returns:
        name → :class:`ScanVariant`.
    """
    from jface.mesh import landmark_points

    verts = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(faces, dtype=np.int64)
    points = np.asarray(landmark_points(landmarks, verts), dtype=np.float64)
    unknown = sorted(set(kinds) - set(SCAN_KINDS))
    if unknown:
        raise ValueError(f"kinds must be among {SCAN_KINDS}, got {unknown}")
    out = {}
    for kind in kinds:
        rng = np.random.default_rng([seed, SCAN_KINDS.index(kind)])
        steps = SCAN_KINDS[1:-1] if kind == "combined" else (kind,)
        v, f, scale = verts, tris, 1.0
        rotation, translation = np.eye(3), np.zeros(3)
        for step in steps:
            diagonal = float(np.linalg.norm(np.ptp(v, axis=0)))
            if step == "decimated":
                v, f = _decimate(v, f, 0.4)
            elif step == "holes":
                v, f = _punch_holes(v, f, points * scale, 6, 0.012 * diagonal, rng)
            elif step == "noise":
                v = v + _normals(v, f) * rng.normal(0.0, 3e-4 * diagonal, (len(v), 1))
            elif step == "millimetres":
                v, scale = v * 1000.0, scale * 1000.0
            elif step == "posed":
                rotation = _random_rotation(rng)
                translation = 3.0 * diagonal * _unit(rng.normal(size=3))
                v = v @ rotation.T + translation
        moved = scale * points @ rotation.T + translation
        out[kind] = ScanVariant(v, f, moved, scale, rotation, translation)
    return out


def _decimate(v: np.ndarray, f: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    try:
        import fast_simplification
    except ImportError as err:
        raise ImportError(
            "the 'decimated' scan variant needs the fast_simplification package "
            "(pip install 'jface[test]' or pip install fast_simplification)"
        ) from err
    points, triangles = fast_simplification.simplify(v, f, target_reduction=1.0 - fraction)
    return np.asarray(points, np.float64), np.asarray(triangles, np.int64)


def _punch_holes(v, f, landmarks, count, radius, rng) -> tuple[np.ndarray, np.ndarray]:
    """Remove the triangles within ``radius`` of ``count`` centres on the face, each at least
    2.5 radii from every landmark (so the landmarks stay on the surface)."""
    centre = landmarks.mean(axis=0)
    reach = np.linalg.norm(landmarks - centre, axis=1).max()
    gap = np.linalg.norm(v[:, None] - landmarks[None], axis=-1).min(axis=1)
    allowed = np.flatnonzero((np.linalg.norm(v - centre, axis=1) < reach) & (gap > 2.5 * radius))
    centres = v[rng.choice(allowed, size=count, replace=False)]
    near = np.linalg.norm(v[:, None] - centres[None], axis=-1).min(axis=1) < radius
    kept = f[~near[f].any(axis=1)]
    used = np.unique(kept)
    index = np.full(len(v), -1)
    index[used] = np.arange(len(used))
    return v[used], index[kept]


def _normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    tri = v[f]
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, f[:, k], face)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x)


def heterogeneous_maps(size: int = 512, *, seed: int = 0) -> dict[str, np.ndarray]:
    """Real maps whose detail changes abruptly, and a stationary one, all ``(size, size)``
    float32 with zero mean and unit standard deviation.

    - "steps": the gravel texture with occluders: six flat discs and a flat band at other
      heights, so flat regions sit beside strong relief across step edges.
    - "scan": the Lee Perry-Smith scan remeshed (:func:`jface.mesh.remesh`), its displacement
      image with the detail above a Gaussian of ``size / 32`` pixels removed.
    - "depth": a depth map of the Lee Perry-Smith head seen from the front, turned 20°, framed
      on the face: smooth relief, steps at the silhouette and the ear, flat background.
    - "gravel": the gravel texture (stationary, for comparison).

    Args:
        size: side in pixels (a multiple of 128 suits the paper's 16 × 16 tiles, 4 scales).
        seed: places the occluders of "steps".
    """
    from scipy.ndimage import gaussian_filter

    from jface import data, mesh, raster, tiles

    rng = np.random.default_rng(seed)
    gravel = tiles.mirror_tile(data.gravel(), size).astype(np.float64)
    steps = gravel.copy()
    rows, cols = np.mgrid[:size, :size]
    for _ in range(6):
        y, x, r = rng.uniform(0, size), rng.uniform(0, size), rng.uniform(0.1, 0.3) * size
        steps[(rows - y) ** 2 + (cols - x) ** 2 < r * r] = rng.uniform(0.2, 0.8)
    steps[:, : size // 5] = 0.5
    scan, marks = data.lee_perry_smith()
    image = np.asarray(mesh.remesh(scan.vertices, scan.faces, marks, image_size=size).image)
    detail = image - gaussian_filter(image.astype(np.float64), size / 32, mode="nearest")
    points = np.asarray(mesh.landmark_points(marks, scan.vertices), dtype=np.float64)
    centre = points.mean(axis=0)
    extent = 3.0 * float(np.linalg.norm(points - centre, axis=1).max())
    _, screen = raster.project(scan.vertices, (size, size), yaw=20.0, center=centre, extent=extent)
    depth = raster.rasterize(screen, scan.faces, (size, size)).depth
    depth = np.where(np.isfinite(depth), depth, depth[np.isfinite(depth)].max())
    maps = {"steps": steps, "scan": detail, "depth": depth, "gravel": gravel}
    return {k: ((m - m.mean()) / m.std()).astype(np.float32) for k, m in maps.items()}
