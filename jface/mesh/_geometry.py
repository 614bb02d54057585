"""Vertex normals, and the map between per-vertex values and displacement images.

Image convention (shared by :func:`image_sampler` and :func:`sample_image`): an ``(H, W)`` image
covers the unit square; pixel ``(row i, column j)`` has its centre at
``u = (j + 0.5) / W, v = 1 - (i + 0.5) / H``, so row 0 is the top of the face (``v = 1``).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int


@jax.jit
def vertex_normals(vertices: Float[Array, "v 3"], faces: Int[Array, "f 3"]) -> Float[Array, "v 3"]:
    """Unit vertex normals: area-weighted sums of the incident face normals.

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` triangles, counter-clockwise seen from outside.

    Returns:
        ``(V, 3)`` unit normals (zero for vertices on no face).
    """
    p = vertices[faces]
    n = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    acc = jax.ops.segment_sum(jnp.repeat(n, 3, axis=0), faces.reshape(-1), vertices.shape[0])
    length = jnp.linalg.norm(acc, axis=-1, keepdims=True)
    return acc / jnp.maximum(length, jnp.finfo(vertices.dtype).tiny)


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length of the faces' edges (each interior edge counted twice)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    e = v[f] - v[np.roll(f, 1, axis=1)]
    return float(np.mean(np.linalg.norm(e, axis=-1)))


def vertex_edge_length(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(V,)`` mean length of the edges at each vertex: the local scale of a mesh (0 for
    vertices on no face)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    start, end = f.reshape(-1), np.roll(f, 1, axis=1).reshape(-1)
    length = np.linalg.norm(v[start] - v[end], axis=-1)
    total = np.bincount(start, length, len(v)) + np.bincount(end, length, len(v))
    count = np.bincount(start, minlength=len(v)) + np.bincount(end, minlength=len(v))
    return total / np.maximum(count, 1)


class ImageSampler(eqx.Module):
    """Linear interpolation of per-vertex values at every pixel centre of an image: the
    precomputed map from a mesh laid out in the unit square to a displacement image.

    Attributes:
        corners: ``(H·W, 3)`` vertex indices of the triangle under each pixel centre.
        weights: ``(H·W, 3)`` barycentric weights of the pixel centre in that triangle.
        shape: ``(H, W)`` (static).
    """

    corners: Int[Array, "p 3"]
    weights: Float[Array, "p 3"]
    shape: tuple[int, int] = eqx.field(static=True)

    def __call__(self, values: Float[Array, " v"]) -> Float[Array, "h w"]:
        """The image of per-vertex values ``(V,)``."""
        return _rasterise(self, values)


@jax.jit
def _rasterise(sampler: ImageSampler, values: Array) -> Array:
    w = sampler.weights.astype(values.dtype)
    return jnp.sum(w * values[sampler.corners], axis=-1).reshape(sampler.shape)


def image_sampler(uv: ArrayLike, faces: ArrayLike, shape: tuple[int, int]) -> ImageSampler:
    """Locate every pixel centre of an ``shape`` image in a triangle mesh laid out in ``uv``.

    Pixel centres on no triangle (outside the layout, or in a crack of rounding width) take the
    value of the nearest vertex, so the image is always complete.

    Args:
        uv: ``(V, 2)`` layout of the vertices in the unit square.
        faces: ``(F, 3)`` triangles.
        shape: ``(H, W)``.
    """
    return _image_sampler(
        np.asarray(uv, dtype=np.float64).tobytes(),
        np.asarray(faces, dtype=np.int64).tobytes(),
        tuple(int(s) for s in shape),
    )


@functools.lru_cache(maxsize=8)
def _image_sampler(uv_bytes: bytes, faces_bytes: bytes, shape: tuple[int, int]) -> ImageSampler:
    from scipy.spatial import cKDTree

    uv = np.frombuffer(uv_bytes, dtype=np.float64).reshape(-1, 2)
    faces = np.frombuffer(faces_bytes, dtype=np.int64).reshape(-1, 3)
    h, w = shape
    x = uv[:, 0] * w - 0.5  # pixel-centre coordinates of each vertex
    y = (1.0 - uv[:, 1]) * h - 0.5
    corner_ids = np.zeros((h * w, 3), np.int64)
    weights = np.zeros((h * w, 3))
    found = np.zeros(h * w, bool)
    eps = 1e-9
    for start in range(0, len(faces), 65536):
        f = faces[start : start + 65536]
        fx, fy = x[f], y[f]
        x0 = np.clip(np.ceil(fx.min(1) - eps), 0, w).astype(np.int64)
        x1 = np.clip(np.floor(fx.max(1) + eps), -1, w - 1).astype(np.int64)
        y0 = np.clip(np.ceil(fy.min(1) - eps), 0, h).astype(np.int64)
        y1 = np.clip(np.floor(fy.max(1) + eps), -1, h - 1).astype(np.int64)
        nx, ny = np.maximum(x1 - x0 + 1, 0), np.maximum(y1 - y0 + 1, 0)
        count = nx * ny
        tri = np.repeat(np.arange(len(f)), count)
        if len(tri) == 0:
            continue
        local = np.arange(len(tri)) - np.repeat(np.cumsum(count) - count, count)
        px = x0[tri] + local % nx[tri]
        py = y0[tri] + local // nx[tri]
        ax, ay = fx[tri, 0], fy[tri, 0]
        bx, by = fx[tri, 1] - ax, fy[tri, 1] - ay
        cx, cy = fx[tri, 2] - ax, fy[tri, 2] - ay
        det = bx * cy - by * cx
        ok = np.abs(det) > 1e-18
        det = np.where(ok, det, 1.0)
        qx, qy = px - ax, py - ay
        l1 = (qx * cy - qy * cx) / det
        l2 = (bx * qy - by * qx) / det
        l0 = 1.0 - l1 - l2
        inside = ok & (l0 >= -1e-7) & (l1 >= -1e-7) & (l2 >= -1e-7)
        pix = (py * w + px)[inside]
        corner_ids[pix] = f[tri[inside]]
        weights[pix] = np.clip(np.stack([l0, l1, l2], 1)[inside], 0.0, 1.0)
        found[pix] = True
    if not found.all():
        rows, cols = np.divmod(np.flatnonzero(~found), w)
        _, nearest = cKDTree(np.stack([x, y], 1)).query(np.stack([cols, rows], 1).astype(float))
        corner_ids[~found] = nearest[:, None]
        weights[~found] = [1.0, 0.0, 0.0]
    weights /= weights.sum(1, keepdims=True)
    return ImageSampler(
        corners=jnp.asarray(corner_ids, dtype=jnp.int32),
        weights=jnp.asarray(weights, dtype=jnp.float32),
        shape=(h, w),
    )


@jax.jit
def sample_image(image: Float[Array, "h w"], uv: Float[Array, "v 2"]) -> Float[Array, " v"]:
    """Bilinear samples of an image at unit-square coordinates (edge pixels repeat outward).

    Args:
        image: ``(H, W)`` displacement image (module convention: row 0 is ``v = 1``).
        uv: ``(V, 2)`` coordinates in the unit square.
    """
    h, w = image.shape
    col = uv[:, 0].astype(image.dtype) * w - 0.5
    row = (1 - uv[:, 1].astype(image.dtype)) * h - 0.5
    return jax.scipy.ndimage.map_coordinates(image, [row, col], order=1, mode="nearest")
