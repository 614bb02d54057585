"""Poisson image editing (Pérez, Gangnet & Blake 2003) in the gradient domain.

Given a guidance field ``v = (gx, gy)`` (forward differences: ``gx[i, j] ≈ u[i, j+1] - u[i, j]``,
``gy[i, j] ≈ u[i+1, j] - u[i, j]``) and Dirichlet values ``b``, find the image ``u`` that equals
``b`` where it is known and whose gradients are as close as possible to ``v`` elsewhere
(Eq. 3 of Pérez et al.: ``min ∫∫ |∇u - v|²`` with ``u = b`` on ``∂Ω``). Its Euler–Lagrange equation
discretised on the 4-neighbour grid is, for every unknown pixel ``p``,

    |N_p| u_p - Σ_{q ∈ N_p ∩ Ω} u_q = Σ_{q ∈ N_p ∩ ∂Ω} b_q + Σ_{q ∈ N_p} v_pq      (Eq. 7)

* Over the whole image with the outer ring of pixels fixed (what Mohammed et al. 2009, §4, do with
  the global model's image as boundary), this is the Dirichlet Laplacian on a rectangle, which
  the type-I discrete sine transform diagonalises: :func:`poisson_solve` solves it exactly in
  ``O(HW log HW)`` (two DST-I of the interior, written on real FFTs so it jits).
* Over an arbitrary region (inpainting, §6.1) the unknowns are the masked pixels; pixels on the
  image edge inside the region have fewer neighbours (natural boundary). :func:`poisson_solve`
  with ``mask`` runs preconditioned conjugate gradients with the rectangle's DST solve as
  preconditioner, which converges in a few dozen iterations.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float

from jface import _checks

#: Default relative residual tolerance and iteration cap of the masked (CG) solve.
CG_TOL = 1e-6
CG_MAXITER = 500


# --- the type-I discrete sine transform -------------------------------------------------------


def dst1(x: Float[Array, "..."], axis: int = -1) -> Float[Array, "..."]:
    """Unnormalised DST-I along ``axis``, ``y_k = Σ_j x_j sin(π (j+1)(k+1) / (n+1))``.

    Written as the imaginary part of a real FFT of the odd extension ``[0, x, 0, -x[::-1]]``
    (length ``2(n + 1)``); applying it twice multiplies by ``(n + 1) / 2``. Same as
    ``scipy.fft.dst(x, type=1, axis=axis) / 2``.
    """
    axis = axis % x.ndim
    n = x.shape[axis]
    zero = jnp.zeros_like(jax.lax.slice_in_dim(x, 0, 1, axis=axis))
    odd = jnp.concatenate([zero, x, zero, -jnp.flip(x, axis)], axis=axis)
    spectrum = jnp.fft.rfft(odd, axis=axis).imag
    return -jax.lax.slice_in_dim(spectrum, 1, n + 1, axis=axis).astype(x.dtype) / 2


def _dst2(x: Array) -> Array:
    return dst1(dst1(x, -1), -2)


def _eigenvalues(n: int, m: int, dtype: Any) -> Array:
    """Eigenvalues of the 5-point Dirichlet Laplacian ``4u - Σ neighbours`` on an n×m grid."""
    ky = 2 - 2 * jnp.cos(jnp.pi * jnp.arange(1, n + 1, dtype=dtype) / (n + 1))
    kx = 2 - 2 * jnp.cos(jnp.pi * jnp.arange(1, m + 1, dtype=dtype) / (m + 1))
    return ky[:, None] + kx[None, :]


def dirichlet_solve(rhs: Float[Array, "n m"]) -> Float[Array, "n m"]:
    """Solve ``4u - Σ_4-neighbours u = rhs`` on an n×m grid with zero values outside (exact)."""
    n, m = rhs.shape
    scale = jnp.asarray(4.0 / ((n + 1) * (m + 1)), rhs.dtype)
    return _dst2(_dst2(rhs) / _eigenvalues(n, m, rhs.dtype)) * scale


# --- guidance -----------------------------------------------------------------------------------


def gradients(image: Float[Array, "H W"]) -> tuple[Float[Array, "H _"], Float[Array, "_ W"]]:
    """Forward differences ``(gx (H, W-1), gy (H-1, W))`` of an image."""
    return image[:, 1:] - image[:, :-1], image[1:, :] - image[:-1, :]


def divergence(grad_x: Float[Array, "H _"], grad_y: Float[Array, "_ W"]) -> Float[Array, "H W"]:
    """Backward-difference divergence of a forward-difference field, ``Σ_q v_qp`` per pixel.

    Differences that would leave the image are zero, so ``-divergence`` is the guidance term
    ``Σ_{q ∈ N_p} v_pq`` of Eq. 7 for every pixel, including those on the image edge.
    """
    h, w = grad_y.shape[0] + 1, grad_x.shape[1] + 1
    zx = jnp.zeros((h, 1), grad_x.dtype)
    zy = jnp.zeros((1, w), grad_y.dtype)
    gx = jnp.concatenate([zx, grad_x, zx], axis=1)
    gy = jnp.concatenate([zy, grad_y, zy], axis=0)
    return gx[:, 1:] - gx[:, :-1] + gy[1:, :] - gy[:-1, :]


# --- solvers ------------------------------------------------------------------------------------


def _neighbour_sum(u: Array) -> Array:
    """Σ of the in-image 4-neighbours of every pixel (zero outside)."""
    p = jnp.pad(u, 1)
    return p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:]


def _neighbour_count(shape: tuple[int, int], dtype: Any) -> Array:
    return _neighbour_sum(jnp.ones(shape, dtype))


@jax.jit
def _solve_rectangle(grad_x: Array, grad_y: Array, boundary: Array) -> Array:
    guide = -divergence(grad_x, grad_y)
    ring = boundary.at[1:-1, 1:-1].set(0)
    rhs = (_neighbour_sum(ring) + guide)[1:-1, 1:-1]
    inner = dirichlet_solve(rhs)
    return boundary.at[1:-1, 1:-1].set(inner)


def _pcg(operator, precondition, b: Array, x0: Array, tol: Array, maxiter: int) -> Array:
    """Preconditioned conjugate gradients until ``|r| <= tol |b|`` or ``maxiter`` steps."""
    dot = jnp.vdot
    r = b - operator(x0)
    z = precondition(r)
    stop = (tol * jnp.sqrt(dot(b, b))) ** 2

    def cond(state):
        _, r, _, _, _, k = state
        return (dot(r, r) > stop) & (k < maxiter)

    def body(state):
        x, r, z, p, rz, k = state
        ap = operator(p)
        alpha = rz / dot(p, ap)
        x = x + alpha * p
        r = r - alpha * ap
        z = precondition(r)
        rz_new = dot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, z, p, rz_new, k + 1

    state = (x0, r, z, z, dot(r, z), jnp.zeros((), jnp.int32))
    return jax.lax.while_loop(cond, body, state)[0]


@functools.partial(jax.jit, static_argnames=("maxiter",))
def _solve_masked(
    grad_x: Array, grad_y: Array, boundary: Array, mask: Array, tol: Array, maxiter: int
) -> Array:
    dtype = boundary.dtype
    m = mask.astype(dtype)
    count = _neighbour_count(boundary.shape, dtype)
    known = boundary * (1 - m)
    rhs = m * (_neighbour_sum(known) - divergence(grad_x, grad_y))

    edge = jnp.ones_like(boundary).at[1:-1, 1:-1].set(0)

    def operator(x):  # the system restricted to the region (an SPD operator on it)
        x = x * m
        return m * (count * x - _neighbour_sum(x))

    def precondition(r):  # DST solve of the rectangle inside, Jacobi on the image edge
        r = r * m
        inner = jnp.zeros_like(r).at[1:-1, 1:-1].set(dirichlet_solve(r[1:-1, 1:-1]))
        return m * (inner + edge * r / count)

    x = _pcg(operator, precondition, rhs, boundary * m, tol, maxiter)
    return jnp.where(mask, x, boundary)


def poisson_solve(
    grad_x: ArrayLike,
    grad_y: ArrayLike,
    boundary: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    tol: float = CG_TOL,
    maxiter: int = CG_MAXITER,
) -> Float[Array, "H W"]:
    """Image whose gradients best match a guidance field, with Dirichlet values (Eq. 7).

    Args:
        grad_x: ``(H, W-1)`` guidance along x (``u[:, 1:] - u[:, :-1]``).
        grad_y: ``(H-1, W)`` guidance along y.
        boundary: ``(H, W)`` Dirichlet values: the result equals it exactly wherever it is not
            solved for.
        mask: optional ``(H, W)`` boolean, True where the image is unknown (the region Ω). By
            default Ω is everything but the outer ring of pixels, solved exactly by DST-I.
            With a mask, pixels of Ω on the image edge get the natural boundary condition and
            the system is solved by DST-preconditioned conjugate gradients.
        tol: relative residual tolerance of the masked solve.
        maxiter: iteration cap of the masked solve.

    Returns:
        ``(H, W)`` solution, dtype of ``boundary``.

    Raises:
        TypeError: non-floating inputs or a non-boolean mask.
        ValueError: shapes that do not fit together, an image smaller than 3×3, an empty mask
            or one that leaves no known pixel.
    """
    boundary = _checks.float_array(boundary, "boundary", ndim=2)
    h, w = boundary.shape
    if h < 3 or w < 3:
        raise ValueError(f"boundary must be at least 3×3, got {h}×{w}")
    grad_x = _checks.float_array(grad_x, "grad_x", ndim=2, dtype=boundary.dtype)
    grad_y = _checks.float_array(grad_y, "grad_y", ndim=2, dtype=boundary.dtype)
    if grad_x.shape != (h, w - 1):
        raise ValueError(f"grad_x must have shape {(h, w - 1)}, got {grad_x.shape}")
    if grad_y.shape != (h - 1, w):
        raise ValueError(f"grad_y must have shape {(h - 1, w)}, got {grad_y.shape}")
    if mask is None:
        return _solve_rectangle(grad_x, grad_y, boundary)
    mask = region_mask(mask, (h, w), "mask")
    tol = _checks.real(tol, "tol", low=0.0, open_low=True)
    maxiter = _checks.integer(maxiter, "maxiter", low=1)
    return _solve_masked(grad_x, grad_y, boundary, mask, jnp.asarray(tol, boundary.dtype), maxiter)


def region_mask(mask: Any, shape: tuple[int, int], name: str) -> Bool[Array, "H W"]:
    """Validate a boolean region mask of ``shape`` that is neither empty nor everything."""
    arr = jnp.asarray(mask)
    if arr.dtype != jnp.bool_:
        raise TypeError(f"{name} must be a boolean array, got {_checks.describe(arr)}")
    if arr.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)}, got {arr.shape}")
    if not _checks.is_traced(arr):
        if not bool(arr.any()):
            raise ValueError(f"{name} is empty: it selects no pixel")
        if bool(arr.all()):
            raise ValueError(f"{name} selects every pixel: at least one must stay known")
    return arr


def poisson_blend(
    source: ArrayLike, boundary: ArrayLike, mask: ArrayLike | None = None
) -> Float[Array, "H W"]:
    """Seamless cloning: the gradients of ``source`` inside the region, ``boundary`` outside.

    Args:
        source: ``(H, W)`` image whose gradients guide the region.
        boundary: ``(H, W)`` image giving the values outside the region.
        mask: optional ``(H, W)`` boolean region (default: all but the outer ring).

    Returns:
        ``(H, W)`` blended image (see :func:`poisson_solve`).
    """
    source = _checks.float_array(source, "source", ndim=2)
    boundary = _checks.float_array(boundary, "boundary", ndim=2, dtype=source.dtype)
    gx, gy = gradients(source)
    return poisson_solve(gx, gy, boundary, mask)
