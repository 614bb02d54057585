"""The radius scaling map **R** of a UV-mapped mesh (§3.1 and Fig. 4 of Weiss et al. 2023).

Pores are sampled in UV space with the local distance ``α_d · R``; to make them uniformly spaced
on the 3-D surface, ``R`` must be large where a unit of UV covers little surface (the UV map is
stretched) and small where the surface is squashed into little UV. Per triangle the stretch
``σ = Σ|e_3D| / Σ|e_UV|`` (3-D edge length per UV edge length) is rasterised into UV space;
``R = σ̄ / σ`` with ``σ̄`` the geometric mean over the covered texels (so ``R = 1`` on average),
smoothed in the log domain (the paper approximates geodesic distances, [BWWM10]; an isotropic
scale correction like theirs).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jface import _checks
from jface.raster import rasterize
from jface.wrinkles._extraction import gaussian_blur


def radius_map_from_mesh(
    mesh: Any,
    size: int | tuple[int, int],
    *,
    smooth: float | None = None,
    limits: tuple[float, float] = (0.125, 8.0),
) -> Float[Array, "H W"]:
    """Radius scaling map **R** from the UV stretch of a mesh: pass it to :func:`sample_pores` /
    :func:`synthesize` (``radius_map=``) so pores are evenly spaced on the surface (Fig. 4).

    The map follows the pillar's convention: row ``i`` covers ``v = (i + 0.5) / H`` (``y = v``),
    column ``j`` covers ``u = (j + 0.5) / W``. Texels on no triangle get ``R = 1`` after the
    smoothing has filled what it reaches (normalised convolution).

    Args:
        mesh: anything with ``vertices (V, 3)``, ``faces (F, 3)`` and ``uv (V, 2)`` in the unit
            square (:class:`jface.io.MeshData`, :class:`jface.mesh.Mesh`).
        size: ``H = W`` or ``(H, W)`` of the map (8 to 8192; R is smooth, 512–1024 suffices).
        smooth: Gaussian σ of the smoothing in texels (default ``max(H, W) / 128``; 0 for none).
        limits: ``R`` is clipped to ``[low, high]`` (degenerate triangles; bounds the pore count).

    Returns:
        ``(H, W)`` float32 map, positive.

    Raises:
        TypeError: ``mesh`` is not a mesh.
        ValueError: a mesh without UVs, bad shapes, no triangle with a non-degenerate UV image,
            bad size, smooth or limits.
    """
    if not all(hasattr(mesh, name) for name in ("vertices", "faces", "uv")):
        raise TypeError(f"mesh must have vertices, faces and uv, got {_checks.describe(mesh)}")
    if mesh.uv is None:
        raise ValueError("mesh has no UV coordinates; a radius map needs a UV-mapped mesh")
    vertices = np.asarray(mesh.vertices, np.float64)
    uv = np.asarray(mesh.uv, np.float64)
    faces = np.asarray(mesh.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or uv.shape != (len(vertices), 2):
        raise ValueError(
            f"mesh.vertices must be (V, 3) and mesh.uv (V, 2), got {vertices.shape} and {uv.shape}"
        )
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.size == 0 or faces.dtype.kind not in "iu":
        raise ValueError(f"mesh.faces must be integers of shape (F, 3), got {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"mesh.faces index vertices outside [0, {len(vertices)})")
    if not (np.all(np.isfinite(vertices)) and np.all(np.isfinite(uv))):
        raise ValueError("mesh.vertices and mesh.uv must be finite")
    h, w = (size, size) if isinstance(size, int | np.integer) else tuple(size)
    h = _checks.integer(h, "size", low=8, high=8192)
    w = _checks.integer(w, "size", low=8, high=8192)
    smooth = max(h, w) / 128 if smooth is None else _checks.real(smooth, "smooth", low=0.0)
    low = _checks.real(limits[0], "limits[0]", low=0.0, open_low=True)
    high = _checks.real(limits[1], "limits[1]", low=low)

    def perimeter(points):
        p = points[faces]
        return np.linalg.norm(p - np.roll(p, 1, axis=1), axis=-1).sum(-1)

    length_uv = perimeter(uv)
    ok = length_uv > 1e-12
    if not np.any(ok):
        raise ValueError("mesh.uv maps every triangle to a point; no UV stretch to measure")
    log_stretch = np.log(np.maximum(perimeter(vertices)[ok], 1e-30) / length_uv[ok])
    screen = np.stack([uv[:, 0] * w, uv[:, 1] * h, np.zeros(len(uv))], axis=1)
    face = rasterize(screen, faces[ok], (h, w)).face
    covered = face >= 0
    if not np.any(covered):
        raise ValueError("mesh.uv covers no texel of the map (UVs outside the unit square?)")
    log_r = np.where(covered, log_stretch[np.maximum(face, 0)], 0.0)
    log_r = np.where(covered, np.mean(log_r[covered]) - log_r, 0.0)
    return _smooth(jnp.asarray(log_r, jnp.float32), jnp.asarray(covered, jnp.float32), smooth,
                   low, high)  # fmt: skip


def _smooth(log_r, weight, sigma, low, high):
    """Normalised convolution of ``log R`` (weights: covered texels), then ``exp`` and clip."""
    if sigma > 0:
        radius = min(int(4.0 * sigma + 0.5), min(log_r.shape) - 1)
        num = gaussian_blur(log_r * weight, sigma, radius)
        den = gaussian_blur(weight, sigma, radius)
        log_r = jnp.where(den > 1e-3, num / jnp.maximum(den, 1e-3), 0.0)
    return jnp.clip(jnp.exp(log_r), low, high)
