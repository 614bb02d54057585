"""Parameters that are scalars or 2-D textures over the unit square, looked up at points.

Convention shared by the whole pillar: positions are ``(x, y)`` in ``[0, 1]²``; a texture of shape
``(H, W)`` covers the unit square with ``x`` along columns and ``y`` along rows, pixel ``(i, j)``
centred at ``((j + 0.5) / W, (i + 0.5) / H)``. Lookups are bilinear, clamped at the border or
wrapped when the domain is periodic.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def lookup(
    texture: Float[Array, "H W"], xy: Float[Array, "*n 2"], *, periodic: bool
) -> Float[Array, "*n"]:
    """Bilinear lookup of an ``(H, W)`` texture at points ``xy`` (..., 2), in the texture dtype."""
    h, w = texture.shape
    fx = xy[..., 0] * w - 0.5
    fy = xy[..., 1] * h - 0.5
    x0 = jnp.floor(fx)
    y0 = jnp.floor(fy)
    tx = (fx - x0).astype(texture.dtype)
    ty = (fy - y0).astype(texture.dtype)
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)

    def fix(i, n):
        return jnp.mod(i, n) if periodic else jnp.clip(i, 0, n - 1)

    xa, xb = fix(x0, w), fix(x0 + 1, w)
    ya, yb = fix(y0, h), fix(y0 + 1, h)
    top = texture[ya, xa] * (1 - tx) + texture[ya, xb] * tx
    bottom = texture[yb, xa] * (1 - tx) + texture[yb, xb] * tx
    return top * (1 - ty) + bottom * ty


def at(
    value: Float[Array, "*shape"], xy: Float[Array, "*n 2"], *, periodic: bool
) -> Float[Array, "*n"]:
    """A parameter that is a scalar ``()`` or a texture ``(H, W)``, evaluated at points ``xy``."""
    if value.ndim == 0:
        return jnp.broadcast_to(value, xy.shape[:-1])
    return lookup(value, xy, periodic=periodic)
