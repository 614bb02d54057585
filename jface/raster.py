"""A small z-buffer rasteriser: triangle mesh → shaded greyscale image.

General (any vertices/faces), vectorised numpy (no per-triangle Python loop: triangles are
grouped by the size of their pixel bounding box and each group is rasterised as one array
operation), deterministic. Used to make aligned face images from 3D face models and shaded
pictures of meshes.

Conventions: world axes x right, y up, z towards the viewer (the camera looks down −z). The head
turns about the framing centre: ``yaw`` about the vertical axis (positive turns the nose towards
the image's right, the subject's left), ``pitch`` about the horizontal axis (positive
tilts the face up), ``roll`` about the view axis. The framing — ``center`` and ``extent``, the
world size spanned by the image's shorter side — is fixed independently of the pose, so renders
of different meshes with the same framing are aligned, as the face models of
:mod:`jface.faces` need.

Typical use::

    image = render(vertices, faces, (64, 64), yaw=90.0)        # profile view, float32 in [0, 1]
    frags = rasterize(screen, faces, (64, 64))                 # face index, barycentrics, depth
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from jface import _checks

__all__ = ["Fragments", "framing", "project", "rasterize", "render", "rotation", "vertex_normals"]

#: Largest number of candidate fragments processed in one array operation.
_CHUNK = 1 << 22


class Fragments(NamedTuple):
    """What is visible at each pixel.

    Attributes:
        face: ``(H, W)`` int32 index of the visible triangle, −1 where nothing is.
        bary: ``(H, W, 3)`` barycentric coordinates of the pixel centre in that triangle
            (perspective-correct when the screen depths came from a perspective camera).
        depth: ``(H, W)`` distance along the view axis, ``inf`` where nothing is.
    """

    face: np.ndarray
    bary: np.ndarray
    depth: np.ndarray


def _floats(x: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``x`` as a finite float64 numpy array of ``shape`` (None = any length), or a clear error."""
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name} must be a numeric array, got {_checks.describe(x)}")
    arr = np.asarray(x)
    if arr.dtype.kind not in "fiu" or arr.dtype == np.bool_:
        raise TypeError(f"{name} must be a numeric array, got {_checks.describe(arr)}")
    if arr.ndim != len(shape) or any(
        n is not None and n != m for n, m in zip(shape, arr.shape, strict=True)
    ):
        want = "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
        raise ValueError(f"{name} must have shape {want}, got {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} must not be empty")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {int(np.sum(~np.isfinite(arr)))} NaN/inf")
    return arr


def _size(size: Any) -> tuple[int, int]:
    if isinstance(size, (int, np.integer)) and not isinstance(size, bool):
        size = (size, size)
    if not isinstance(size, (tuple, list)) or len(size) != 2:
        raise ValueError(f"size must be an int or (height, width), got {size!r}")
    h, w = (_checks.integer(s, "size", low=1, high=1 << 14) for s in size)
    return h, w


def _mesh(vertices: Any, faces: Any) -> tuple[np.ndarray, np.ndarray]:
    v = _floats(vertices, "vertices", (None, 3))
    f = np.asarray(faces)
    if f.dtype.kind not in "iu":
        raise TypeError(f"faces must be an integer array of vertex indices, got {f.dtype}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F >= 1, got {f.shape}")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(
            f"faces index vertices 0..{v.shape[0] - 1}, got indices in [{f.min()}, {f.max()}]"
        )
    return v, f.astype(np.int64)


def rotation(
    yaw: float | int = 0.0, pitch: float | int = 0.0, roll: float | int = 0.0
) -> np.ndarray:
    """The 3×3 rotation of a head pose in degrees: ``R = R_roll · R_pitch · R_yaw``.

    ``yaw`` turns about +y, ``pitch`` about −x (positive lifts the chin), ``roll`` about +z.
    """
    a, b, c = (
        math.radians(_checks.real(t, n))
        for t, n in ((yaw, "yaw"), (pitch, "pitch"), (roll, "roll"))
    )
    ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    rx = rx.T  # positive pitch lifts the chin: rotate about −x
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ rx @ ry


def framing(vertices: Any) -> tuple[np.ndarray, float]:
    """A pose-independent framing of a mesh: its bounding-box centre, and an extent (the
    diameter of the sphere about that centre holding every vertex, plus 5 %) that keeps the
    whole mesh in view under any rotation."""
    v = _floats(vertices, "vertices", (None, 3))
    center = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.max(np.linalg.norm(v - center, axis=1)))
    return center, 2.1 * max(radius, 1e-12)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (counter-clockwise triangles face outwards)."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    idx = faces.reshape(-1)
    size = vertices.shape[0]
    acc = np.stack(
        [np.bincount(idx, np.repeat(n[:, k], 3), minlength=size) for k in range(3)], axis=1
    )
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)


def project(
    vertices: Any,
    size: Any,
    *,
    yaw: float | int = 0.0,
    pitch: float | int = 0.0,
    roll: float | int = 0.0,
    camera: str = "orthographic",
    fov: float | int = 20.0,
    center: Any = None,
    extent: float | int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Posed camera-space vertices and their screen positions.

    Returns:
        ``(posed, screen)``: posed vertices ``(V, 3)`` (rotated about ``center``, world units,
        centre at the origin) and screen coordinates ``(V, 3)`` = (column, row, depth) in pixels
        (pixel ``(i, j)`` has its centre at ``(j + 0.5, i + 0.5)``), depth along the view axis
        (orthographic: relative to the centre; perspective: distance from the camera).
    """
    h, w = _size(size)
    v = _floats(vertices, "vertices", (None, 3))
    _checks.choice(camera, "camera", ("orthographic", "perspective"))
    c0, e0 = framing(v) if center is None or extent is None else (None, None)
    c = c0 if center is None else _floats(center, "center", (3,))
    e = e0 if extent is None else _checks.real(extent, "extent", low=0.0, open_low=True)
    posed = (v - c) @ rotation(yaw, pitch, roll).T
    scale = min(h, w) / e  # pixels per world unit at the centre
    if camera == "orthographic":
        x, y, depth = posed[:, 0] * scale, posed[:, 1] * scale, -posed[:, 2]
    else:
        fov = _checks.real(fov, "fov", low=0.0, high=179.0, open_low=True)
        distance = 0.5 * e / math.tan(math.radians(fov) / 2)
        depth = distance - posed[:, 2]
        safe = np.where(depth > 1e-9 * distance, depth, np.nan)
        x = posed[:, 0] * scale * distance / safe
        y = posed[:, 1] * scale * distance / safe
    screen = np.stack([w / 2 + x, h / 2 - y, depth], axis=1)
    return posed, screen


def rasterize(screen: Any, faces: Any, size: Any, *, perspective: bool = False) -> Fragments:
    """Z-buffer rasterisation of triangles given in screen coordinates.

    Args:
        screen: ``(V, 3)`` (column, row, depth) per vertex; pixel centres at half-integers.
            Vertices with non-finite coordinates (behind a perspective camera) drop their
            triangles.
        faces: ``(F, 3)`` integer vertex indices.
        size: ``(H, W)`` or an int.
        perspective: depths are camera distances; interpolate barycentrics perspective-correctly.

    Returns:
        :class:`Fragments`: nearest triangle per pixel centre (smallest depth).
    """
    h, w = _size(size)
    s = np.asarray(screen, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ValueError(f"screen must have shape (V, 3), got {s.shape}")
    _, f = _mesh(np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0), faces)
    tri = s[f]  # (F, 3, 3)
    ok = np.all(np.isfinite(tri), axis=(1, 2))
    area = (tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1]) - (
        tri[:, 2, 0] - tri[:, 0, 0]
    ) * (tri[:, 1, 1] - tri[:, 0, 1])
    ok &= np.abs(area) > 1e-12
    xy = np.where(ok[:, None, None], tri[:, :, :2], 0.0)
    lo = np.ceil(xy.min(axis=1) - 0.5)
    hi = np.floor(xy.max(axis=1) - 0.5)
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [w - 1, h - 1])
    ok &= np.all(hi >= lo, axis=1)
    ids = np.flatnonzero(ok)
    span = (hi[ids] - lo[ids]).max(axis=1).astype(np.int64) + 1
    best = np.full(h * w, np.inf)
    face_buf = np.full(h * w, -1, np.int64)
    bary_buf = np.zeros((h * w, 3))
    bucket = np.ceil(np.log2(np.maximum(span, 1))).astype(np.int64)
    for b in np.unique(bucket):
        side = 1 << int(b)
        members = ids[bucket == b]
        per = max(1, _CHUNK // (side * side))
        for start in range(0, members.size, per):
            chunk = members[start : start + per]
            _fragments(
                tri[chunk],
                area[chunk],
                lo[chunk],
                chunk,
                side,
                (h, w),
                perspective,
                best,
                face_buf,
                bary_buf,
            )
    return Fragments(
        face_buf.reshape(h, w).astype(np.int32),
        bary_buf.reshape(h, w, 3),
        best.reshape(h, w),
    )


def _fragments(tri, area, lo, ids, side, shape, perspective, best, face_buf, bary_buf) -> None:
    """Rasterise triangles whose bounding boxes fit ``side × side`` pixels into the buffers."""
    h, w = shape
    off = np.arange(side)
    px = lo[:, 0, None, None] + off[None, None, :]  # (n, 1, side)
    py = lo[:, 1, None, None] + off[None, :, None]  # (n, side, 1)
    px, py = np.broadcast_arrays(px, py)
    cx, cy = px + 0.5, py + 0.5
    x0, y0 = tri[:, 0, 0, None, None], tri[:, 0, 1, None, None]
    x1, y1 = tri[:, 1, 0, None, None], tri[:, 1, 1, None, None]
    x2, y2 = tri[:, 2, 0, None, None], tri[:, 2, 1, None, None]
    a = area[:, None, None]
    b0 = ((x1 - cx) * (y2 - cy) - (x2 - cx) * (y1 - cy)) / a
    b1 = ((x2 - cx) * (y0 - cy) - (x0 - cx) * (y2 - cy)) / a
    b2 = 1.0 - b0 - b1
    eps = -1e-9
    inside = (b0 >= eps) & (b1 >= eps) & (b2 >= eps) & (px < w) & (py < h)
    bary = np.stack([b0, b1, b2], axis=-1)[inside]  # (m, 3)
    pix = (py * w + px)[inside].astype(np.int64)
    owner = np.broadcast_to(ids[:, None, None], inside.shape)[inside]
    z = np.broadcast_to(tri[:, None, None, :, 2], (*inside.shape, 3))[inside]
    if perspective:  # screen-space barycentrics → perspective-correct, depth from 1/z
        inv = bary / z
        depth = 1.0 / inv.sum(axis=1)
        bary = inv * depth[:, None]
    else:
        depth = np.sum(bary * z, axis=1)
    if pix.size == 0:
        return
    order = np.lexsort((depth, pix))
    pix, depth, owner, bary = pix[order], depth[order], owner[order], bary[order]
    first = np.ones(pix.size, bool)
    first[1:] = pix[1:] != pix[:-1]
    pix, depth, owner, bary = pix[first], depth[first], owner[first], bary[first]
    nearer = depth < best[pix]
    pix = pix[nearer]
    best[pix] = depth[nearer]
    face_buf[pix] = owner[nearer]
    bary_buf[pix] = bary[nearer]


def render(
    vertices: Any,
    faces: Any,
    size: Any = (64, 64),
    *,
    yaw: float | int = 0.0,
    pitch: float | int = 0.0,
    roll: float | int = 0.0,
    camera: str = "orthographic",
    fov: float | int = 20.0,
    center: Any = None,
    extent: float | int | None = None,
    light: Any = (0.3, 0.5, 1.0),
    ambient: float | int = 0.15,
    albedo: Any = None,
    background: float | int = 0.0,
    two_sided: bool = True,
) -> np.ndarray:
    """Render a triangle mesh as a Lambertian-shaded greyscale image.

    Smooth (per-vertex, area-weighted) normals are interpolated across each triangle;
    intensity = ``albedo · (ambient + (1 − ambient) · max(0, n·l))``, with the light direction
    ``light`` fixed relative to the camera (x right, y up, z towards the viewer).

    Args:
        vertices: ``(V, 3)`` float positions. faces: ``(F, 3)`` integer indices.
        size: ``(H, W)`` or an int.
        yaw, pitch, roll: head pose in degrees (see :func:`rotation`), about ``center``.
        camera: "orthographic" or "perspective" (pinhole with field of view ``fov`` degrees,
            placed so that ``extent`` fills the image at the centre's depth).
        center, extent: framing (world centre, and world size spanned by the image's shorter
            side); default :func:`framing` of this mesh. Pass the same values for a set of
            meshes to get aligned images.
        light: direction towards the light, camera coordinates. ambient: in [0, 1].
        albedo: optional per-vertex reflectance ``(V,)`` in [0, 1] (default 1).
        background: value where no triangle is visible.
        two_sided: light back faces as if they faced the camera (open meshes).

    Returns:
        ``(H, W)`` float32 image.

    Raises:
        TypeError, ValueError: malformed mesh (shapes, indices out of range, NaN), bad size,
            camera, angles or shading parameters.
    """
    h, w = _size(size)
    v, f = _mesh(vertices, faces)
    ambient = _checks.real(ambient, "ambient", low=0.0, high=1.0)
    background = _checks.real(background, "background")
    l_dir = _floats(light, "light", (3,))
    if not np.any(l_dir):
        raise ValueError(f"light must be a non-zero 3-vector, got {l_dir.tolist()}")
    l_dir = l_dir / np.linalg.norm(l_dir)
    rho = np.ones(v.shape[0])
    if albedo is not None:
        rho = _floats(albedo, "albedo", (v.shape[0],))
    posed, screen = project(
        v,
        (h, w),
        yaw=yaw,
        pitch=pitch,
        roll=roll,
        camera=camera,
        fov=fov,
        center=center,
        extent=extent,
    )
    frags = rasterize(screen, f, (h, w), perspective=camera == "perspective")
    hit = frags.face >= 0
    corners = f[frags.face[hit]]  # (m, 3)
    bary = frags.bary[hit][..., None]
    normals = vertex_normals(posed, f)
    n = np.sum(normals[corners] * bary, axis=1)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    if two_sided:
        if camera == "perspective":
            to_eye = -np.sum(posed[corners] * bary, axis=1)
            to_eye[:, 2] += 0.5 * (extent or framing(v)[1]) / math.tan(math.radians(fov) / 2)
        else:
            to_eye = np.array([0.0, 0.0, 1.0])
        facing = np.sum(n * to_eye, axis=-1)
        n = np.where(facing[:, None] < 0, -n, n)
    diffuse = np.maximum(n @ l_dir, 0.0)
    shade = np.sum(rho[corners] * bary[..., 0], axis=1) * (ambient + (1.0 - ambient) * diffuse)
    image = np.full((h, w), background)
    image[hit] = shade
    return image.astype(np.float32)
