"""Non-stationary image quilting conditioned on a global target (Mohammed et al. 2009, §2.2, §4).

Patches are placed in raster order over the grid; at position ``(r, c)`` every patch ``P`` of
that position's own library is scored by

    cost(P) = Σ_{known pixels of the window} (P - canvas)² + λ · Σ_{window} (P - target)²

where the known pixels are those already placed (the overlaps with the patches to the left and
above) — and, when inpainting, the observed pixels around the hole, so the new patches match
the region's boundary. One of the ``N`` cheapest patches is chosen uniformly at random; the
first patch (nothing known yet) is drawn uniformly from the library when ``λ = 0``. With
``symmetric=True`` a patch whose horizontally opposite position was already filled must come
from the same training image (§4); ``allowed`` restricts the sources (the training images of a
mixture component, §4). The x/y gradients of the chosen patches are averaged where they overlap
and the image is recovered by a Poisson solve whose Dirichlet boundary is the target (§4).

§4.1 of the paper precomputes, over weeks, candidate lists for every pair of neighbouring
patches to reach 1–2 s per face. Here the cost expands as ``Σ (w + λ) P² - 2 P·(w q + λ t)`` +
const, with ``w`` the known pixels, ``q`` the canvas and ``t`` the target: the quadratic terms
(``Σ P²`` and its sum over the seams with earlier patches) are computed once with the library,
so each position costs one matrix–vector product over its library, and ``vmap`` over keys turns
those into matrix–matrix products that read the library once for the whole batch. Right of the
centre column the symmetry allows one training image, so only its entries are scored. The
synthesis is one jitted ``lax.scan`` over the grid.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from jface import _checks
from jface.faces import _poisson
from jface.faces._patches import (
    Geometry,
    PatchLibrary,
    default_n_best,
    face_image,
    from_canvas,
    to_canvas,
)

#: Default weight of the global target against the overlaps.
LAM = 1.0


class QuiltResult(eqx.Module):
    """A synthesised face and how it was made.

    Attributes:
        image: ``(H, W)`` or ``(H, W, C)``: the patches blended in the gradient domain
            (Poisson), or the pasted patches when blending was off.
        quilted: the pasted patches before blending (each pixel from the last patch placed
            over it).
        ids: ``(G_rows, G_cols)`` library entry chosen at each grid position (``-1`` where
            nothing was synthesised, e.g. outside an inpainted region).
        sources: ``(G_rows, G_cols)`` training image each chosen patch came from (``-1`` as
            above): the paper's Fig. 8 source map.
        errors: ``(G_rows, G_cols)`` SSD of the chosen patch over its known pixels (overlaps and
            region boundary), which flags patch errors like Fig. 7F.
    """

    image: Float[Array, "..."]
    quilted: Float[Array, "..."]
    ids: Int[Array, "R Q"]
    sources: Int[Array, "R Q"]
    errors: Float[Array, "R Q"]


def _windows(geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices ``(R, Q, ph, pw)`` (rows, cols) of every grid window in the canvas."""
    rows, cols = geometry.grid
    ph, pw = geometry.patch
    sy, sx = geometry.step
    ys = (np.arange(rows) * sy)[:, None, None, None] + np.arange(ph)[None, None, :, None]
    xs = (np.arange(cols) * sx)[None, :, None, None] + np.arange(pw)[None, None, None, :]
    shape = (rows, cols, ph, pw)
    return np.broadcast_to(ys, shape), np.broadcast_to(xs, shape)


def assemble_gradients(
    patches: Float[Array, "R Q ph pw C"],
    use: Bool[Array, "R Q"],
    fallback: Float[Array, "H W C"],
    geometry: Geometry,
) -> tuple[Float[Array, "H _ C"], Float[Array, "_ W C"]]:
    """x/y gradients of the chosen patches placed on the canvas, averaged where they overlap;
    where no used patch covers a pixel pair, the gradient of ``fallback``."""
    ys, xs = _windows(geometry)
    dtype = patches.dtype
    weight = use.astype(dtype)[:, :, None, None, None]
    fx, fy = fallback[:, 1:] - fallback[:, :-1], fallback[1:] - fallback[:-1]

    def average(grad, rows, cols, like):
        total = jnp.zeros_like(like).at[rows, cols].add(grad * weight)
        count = jnp.zeros(like.shape[:2], dtype).at[rows, cols].add(weight[..., 0])
        return jnp.where(count[..., None] > 0, total / jnp.maximum(count, 1)[..., None], like)

    gx = average(patches[:, :, :, 1:] - patches[:, :, :, :-1], ys[..., :, 1:], xs[..., :, :-1], fx)
    gy = average(patches[:, :, 1:] - patches[:, :, :-1], ys[..., :-1, :], xs[..., :-1, :], fy)
    return gx, gy


def _poisson_channels(gx: Array, gy: Array, boundary: Array, region: Array | None) -> Array:
    def one(a, b, c):
        if region is None:
            return _poisson._solve_rectangle(a, b, c)
        tol = jnp.asarray(_poisson.CG_TOL, c.dtype)
        return _poisson._solve_masked(a, b, c, region, tol, _poisson.CG_MAXITER)

    out = jax.vmap(one, in_axes=(-1, -1, -1), out_axes=-1)(gx, gy, boundary)
    return out


@functools.partial(jax.jit, static_argnames=("n_best", "symmetric", "blend", "fill"))
def _quilt(
    key: PRNGKeyArray,
    library: PatchLibrary,
    target: Array,
    canvas: Array,
    observed: Array,
    active: Array,
    allowed: Array,
    lam: Array,
    n_best: int,
    symmetric: bool,
    blend: bool,
    fill: bool,
) -> tuple[Array, Array, Array, Array, Array]:
    """The raster-order scan on the canvas; see :func:`quilt`. ``fill`` is False for whole-image
    synthesis (Poisson on the rectangle, target as boundary) and True for filling the unobserved
    pixels of ``canvas`` (masked Poisson, observed pixels as boundary)."""
    geometry = library.geometry
    patches, sources = library.patches, library.sources
    rows, cols = geometry.grid
    ph, pw = geometry.patch
    n_ch = patches.shape[-1]
    dtype = patches.dtype
    n_entries = patches.shape[2]
    flat = patches.reshape(rows * cols, n_entries, -1)  # (R Q, P, D): one matrix per position
    norms = library.norms.reshape(rows * cols, n_entries)
    seam_norms = library.seam_norms.reshape(rows * cols, n_entries)
    n_aug = library.shifts.shape[0]  # entries of image i: [i A, (i + 1) A)
    zero = jnp.zeros((), jnp.int32)

    def entries_cost(t, start, count, wk, q, tq):
        # Σ wk (P - q)² + λ Σ (P - t)² = Σ wk P² + λ Σ P² - 2 P·(wk q + λ t) + const over the
        # library entries [start, start + count): one mat-vec (a mat-mat for a vmapped batch of
        # faces); the quadratic terms come with the library, except over the arbitrary known
        # pixels of a fill (in a synthesis the known pixels are exactly the seams)
        def rows_of(x):
            return jax.lax.dynamic_slice_in_dim(x[t], start, count)

        lib = rows_of(flat)
        seam = (lib * lib) @ wk if fill else rows_of(seam_norms)
        const = jnp.sum(wk * q * q) + lam * jnp.sum(tq * tq)
        return lam * rows_of(norms) + seam - 2 * (lib @ (wk * q + lam * tq)) + const

    def mirrored_cost(t, mirror, wk, q, tq):
        # the symmetry allows only the mirrored patch's training image: score its entries only
        own = entries_cost(t, mirror * n_aug, n_aug, wk, q, tq)
        return jax.lax.dynamic_update_slice(
            jnp.full(n_entries, jnp.inf, dtype), own, (mirror * n_aug,)
        )

    def step(state, t):
        canvas, known, chosen_src, ids, errors = state
        r, c = t // cols, t % cols
        y0, x0 = geometry.origin(r, c)
        window = jax.lax.dynamic_slice(canvas, (y0, x0, zero), (ph, pw, n_ch))
        kwin = jax.lax.dynamic_slice(known, (y0, x0), (ph, pw))
        owin = jax.lax.dynamic_slice(observed, (y0, x0), (ph, pw))
        twin = jax.lax.dynamic_slice(target, (y0, x0, zero), (ph, pw, n_ch))
        wk = jnp.broadcast_to(kwin[..., None], window.shape).astype(dtype).ravel()
        q, tq = window.ravel(), twin.ravel()
        go = active[r, c]
        if fill:  # most positions lie outside an inpainted region: skip their library pass
            cost = jax.lax.cond(
                go,
                lambda: entries_cost(t, 0, n_entries, wk, q, tq),
                lambda: jnp.zeros(n_entries, dtype),
            )
        elif symmetric:  # right of the centre the mirrored position is always filled
            cost = jax.lax.cond(
                2 * c > cols - 1,
                lambda: mirrored_cost(t, chosen_src[r, cols - 1 - c], wk, q, tq),
                lambda: entries_cost(t, 0, n_entries, wk, q, tq),
            )
        else:
            cost = entries_cost(t, 0, n_entries, wk, q, tq)

        ok = allowed
        if symmetric:
            mirror = chosen_src[r, cols - 1 - c]
            same = ok & ((mirror < 0) | (sources == mirror))
            ok = jnp.where(jnp.any(same), same, ok)
        cost = jnp.where(ok, cost, jnp.inf)
        k_pick, k_free = jax.random.split(jax.random.fold_in(key, t))
        neg, best = jax.lax.top_k(-cost, n_best)
        n_ok = jnp.sum(jnp.isfinite(neg)).astype(jnp.int32)
        pick = best[jax.random.randint(k_pick, (), 0, jnp.maximum(n_ok, 1), dtype=jnp.int32)]
        free = ~jnp.any(kwin) & (lam == 0)
        choice = jax.lax.cond(  # nothing to match yet and no target: any allowed patch
            free,
            lambda: jax.random.categorical(
                k_free, jnp.where(ok, 0.0, -jnp.inf).astype(dtype)
            ).astype(jnp.int32),
            lambda: pick.astype(jnp.int32),
        )

        patch = patches[r, c, choice]
        placed = jnp.where(owin[..., None], window, patch)
        canvas = jax.lax.dynamic_update_slice(canvas, jnp.where(go, placed, window), (y0, x0, zero))
        known = jax.lax.dynamic_update_slice(known, kwin | go, (y0, x0))
        err = jnp.sum(wk * (patch.ravel() - q) ** 2)
        chosen_src = chosen_src.at[r, c].set(jnp.where(go, sources[choice], -1))
        ids = ids.at[r, c].set(jnp.where(go, choice, -1))
        errors = errors.at[r, c].set(jnp.where(go, err, 0).astype(dtype))
        return (canvas, known, chosen_src, ids, errors), None

    minus = -jnp.ones((rows, cols), jnp.int32)
    state = (canvas, observed, minus, minus, jnp.zeros((rows, cols), dtype))
    (quilted, _, chosen_src, ids, errors), _ = jax.lax.scan(
        step, state, jnp.arange(rows * cols, dtype=jnp.int32)
    )
    if not blend:
        return quilted, quilted, ids, chosen_src, errors
    chosen = jnp.take_along_axis(
        patches, jnp.maximum(ids, 0)[:, :, None, None, None, None], axis=2
    )[:, :, 0]
    gx, gy = assemble_gradients(chosen, ids >= 0, quilted, geometry)
    if fill:
        image = _poisson_channels(gx, gy, canvas, ~observed)
    else:
        image = _poisson_channels(gx, gy, target, None)
    return image, quilted, ids, chosen_src, errors


def check_library(library: Any) -> PatchLibrary:
    if not isinstance(library, PatchLibrary):
        raise TypeError(
            f"library must be a PatchLibrary (from build_library), got {type(library).__name__}"
        )
    return library


def settings(
    library: PatchLibrary, lam: Any, n_best: Any, allowed: Any, dtype: Any
) -> tuple[Array, int, Array]:
    """Validate ``lam``, ``n_best`` and ``allowed`` (sources) → λ, N, per-entry mask."""
    if _checks.is_traced(lam):
        lam = jnp.asarray(lam, dtype)
    else:
        lam = jnp.asarray(_checks.real(lam, "lam", low=0.0), dtype)
    n_best = default_n_best(library) if n_best is None else _checks.integer(n_best, "n_best", low=1)
    if n_best > library.size:
        raise ValueError(
            f"n_best={n_best} is more than the library's {library.size} patches per position; "
            "use a smaller n_best or more training images/augmentations"
        )
    if allowed is None:
        return lam, n_best, jnp.ones(library.size, bool)
    allowed = jnp.asarray(allowed)
    if allowed.dtype != jnp.bool_ or allowed.shape != (library.n_images,):
        raise ValueError(
            f"allowed must be a boolean array with one entry per training image "
            f"({library.n_images},), got {_checks.describe(allowed)}"
        )
    if not _checks.is_traced(allowed) and not bool(allowed.any()):
        raise ValueError("allowed must allow at least one training image")
    return lam, n_best, allowed[library.sources]


def finish(library: PatchLibrary, out: tuple[Array, ...]) -> QuiltResult:
    """Crop canvas results to the image and drop the channel axis of grey libraries."""
    image, quilted, ids, src, errors = out
    g = library.geometry

    def crop(x):
        x = from_canvas(x, g)
        return x[..., 0] if library.grey else x

    return QuiltResult(crop(image), crop(quilted), ids, src, errors)


def quilt(
    key: PRNGKeyArray,
    library: PatchLibrary,
    target: ArrayLike,
    *,
    lam: float = LAM,
    n_best: int | None = None,
    symmetric: bool = True,
    allowed: ArrayLike | None = None,
    blend: bool = True,
) -> QuiltResult:
    """Synthesise one face by non-stationary quilting conditioned on a global target (§2.2, §4).

    Args:
        key: ``jax.random.key``; the same key gives the same face. ``jax.vmap`` over keys (and
            targets) for many faces.
        library: per-position patch libraries (:func:`build_library`).
        target: ``(H, W)`` or ``(H, W, C)`` global target image (e.g. a factor-analyser sample),
            the library's shape. It also gives the Poisson boundary.
        lam: weight ``λ ≥ 0`` of the SSD to the target against the overlap SSD; ``0`` gives
            the purely local model (Fig. 3, "Frankenstein" faces).
        n_best: choose uniformly among this many cheapest patches (default
            ``min(100, P // 240)``, the paper's 100 of 24000).
        symmetric: horizontally opposite positions take patches from the same training image.
        allowed: optional ``(n_images,)`` boolean: only these training images may be used
            (the images of the sampled mixture component).
        blend: Poisson-blend the patches (§4); False returns the pasted patches.

    Returns:
        A :class:`QuiltResult` (image, pasted patches, chosen ids and sources, overlap errors).

    Raises:
        TypeError / ValueError: a bad key or library, a target of the wrong shape, ``lam < 0``,
            ``n_best`` larger than the library, a malformed or empty ``allowed``.
    """
    key = _checks.single_key(key)
    library = check_library(library)
    dtype = library.patches.dtype
    target = face_image(target, library, "target", dtype)
    lam, n_best, entries = settings(library, lam, n_best, allowed, dtype)
    g = library.geometry
    canvas_target = to_canvas(target, g)
    nothing = jnp.zeros(g.canvas, bool)
    out = _quilt(
        key,
        library,
        canvas_target,
        jnp.zeros_like(canvas_target),
        nothing,
        jnp.ones(g.grid, bool),
        entries,
        lam,
        n_best=n_best,
        symmetric=bool(symmetric),
        blend=bool(blend),
        fill=False,
    )
    return finish(library, out)
