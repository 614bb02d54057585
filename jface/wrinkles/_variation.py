"""Perlin-noise variation of selected parameters (§4.3 and Fig. 15 of Weiss et al. 2023)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jface import _checks
from jface.noise import perlin
from jface.wrinkles._params import _NAMES, PARAMETER_RANGES, WrinkleParams


def perlin_variation(
    key: jax.Array,
    params: WrinkleParams,
    amounts: dict[str, float],
    *,
    resolution: int = 64,
    frequency: float = 4.0,
    octaves: int = 2,
) -> WrinkleParams:
    """Break up the regular look of constant parameters with Perlin noise (Fig. 15).

    Each selected parameter becomes a texture ``clip(value + amount · (hi − lo) · noise, lo, hi)``
    with ``[lo, hi]`` its Table 1 range and ``noise`` seamless fractal Perlin noise in about
    ``[-1, 1]`` (an independent field per parameter). The paper's example varies ``d``
    (α_d, which then also varies the pore density when passed to :func:`sample_pores`), the
    drawing scale and ``cont``.

    Args:
        key: a ``jax.random.key``.
        params: the level's parameters.
        amounts: parameter name → amplitude as a fraction of its range (≥ 0).
        resolution: texture size for parameters that are scalars (textures keep their size).
        frequency, octaves: of the noise (lattice cells per unit length; see
            :func:`jface.noise.perlin`).

    Returns:
        A new :class:`WrinkleParams` with the selected fields as textures.

    Raises:
        ValueError: unknown parameter names or negative amounts.
    """
    key = _checks.key(key)
    if not isinstance(params, WrinkleParams):
        raise TypeError(f"params must be WrinkleParams, got {_checks.describe(params)}")
    if not isinstance(amounts, dict):
        raise TypeError(f"amounts must be a dict name → amplitude, got {_checks.describe(amounts)}")
    unknown = set(amounts) - set(_NAMES)
    if unknown:
        raise ValueError(f"unknown parameter(s) {sorted(unknown)} in amounts; known: {_NAMES}")
    resolution = _checks.integer(resolution, "resolution", low=2, high=8192)
    changes = {}
    for i, name in enumerate(_NAMES):
        if name not in amounts:
            continue
        amount = _checks.real(amounts[name], f"amounts[{name!r}]", low=0.0)
        lo, hi = PARAMETER_RANGES[name]
        value = getattr(params, name)
        shape = value.shape if value.ndim == 2 else (resolution, resolution)
        noise = perlin(
            jax.random.fold_in(key, i), shape, frequency=frequency, octaves=octaves, periodic=True
        )
        changes[name] = jnp.clip(value + amount * (hi - lo) * noise, lo, hi)
    return params.replace(**changes)
