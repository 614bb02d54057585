"""Simulation parameters of one level (Table 1 of Weiss et al. 2023), as a pytree.

Each continuous parameter is a scalar or a 2-D texture over the unit square (§4.3: "all
continuous-valued parameters can be made spatial-varying parameters by specifying them not as a
scalar value, but rather as a 2D texture"). Values are validated against the ranges of Table 1
when a :class:`WrinkleParams` is constructed with concrete values. A batch of parameter sets (for
``vmap``, e.g. the agents of a particle swarm) is the same type with a leading axis on every
leaf: build it with :func:`stack_params`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jface import _checks

#: Ranges of every user parameter of Table 1 (simulation rows, then drawing rows), keyed by the
#: paper's suffix. ``cont`` spans [0, 1], not Table 1's [0, 0.01]: Eq. 3 blends ``(1 − α_cont)``
#: of the orientation term against the continuation term, which needs α_cont on [0, 1], and at
#: 0.01 the continuation moves the weights by 0.002 on average although Fig. 6 shows a clear
#: effect (docs/wrinkles/convergence.png). ``deposit`` uses the range stated in §3.1.2
#: ([0.01, 1.0]; Table 1's [0.3, 0.9] excludes the paper's own default 0.25). ``decay`` (fixed
#: to 0.5 in the paper, not in Table 1), ``sigma`` (σ of Eq. 1), ``sigma_cont`` (σ_cspread of
#: Eq. 4) and ``dt`` (Δt of Eq. 7–8) are the method's constants, exposed with the ranges given
#: here.
PARAMETER_RANGES: dict[str, tuple[float, float]] = {
    "d": (0.001, 0.05),
    "theta": (0.0, 2.0 * math.pi),
    "s": (0.0, 1.0),
    "dist": (0.0, 5.0),
    "cont": (0.0, 1.0),
    "sim": (0.0, 2.0),
    "cross": (0.0, 1.0),
    "deposit": (0.01, 1.0),
    "decay": (0.0, 1.0),
    "sigma": (0.01, math.pi),
    "sigma_cont": (0.01, math.pi),
    "dt": (1e-4, 1.0),
    # drawing (§3.2). Table 1 lists [0.001, 0.2] for the additive-noise frequency and [100, 3000]
    # for its strength: evidently swapped (α_fperturb, a frequency, spans [100, 2000] and
    # α_sperturb, a strength, [0.001, 3]), so the ranges are exchanged here.
    "wrinkle_width": (0.1, 0.6),
    "pore_width": (0.01, 0.5),
    "dmin": (0.001, 1.0),
    "blend": (0.0, 1.0),
    "skew": (0.0, 1.0),
    "cushion": (0.0, 1.0),
    "fperturb": (100.0, 2000.0),
    "sperturb": (0.001, 3.0),
    "fnoise": (100.0, 3000.0),
    "snoise": (0.001, 0.2),
    "scale": (0.1, 0.9),
}


def _as_param(x: Any) -> Array:
    if isinstance(x, bool) or not isinstance(
        x, int | float | np.integer | np.floating | list | tuple | jax.Array | np.ndarray
    ):
        raise TypeError(f"a WrinkleParams value must be a real number or a 2-D texture, got {x!r}")
    # eagerly even inside jit: a concrete value stays concrete and is checked against Table 1
    with jax.ensure_compile_time_eval():
        if isinstance(x, jax.Array):
            return jnp.asarray(x, dtype=jnp.float32)
        try:
            with np.errstate(over="ignore"):  # beyond float32: ±inf, refused by the range check
                return jnp.asarray(np.asarray(x, dtype=np.float32))
        except OverflowError:  # a Python integer beyond any float
            raise ValueError("a WrinkleParams value must be within float32's range") from None


def _field(default: float):
    return eqx.field(default=default, converter=_as_param)


class WrinkleParams(eqx.Module):
    """Simulation and drawing parameters of one level (Eq. 1–13 and Table 1 of Weiss et al. 2023).

    Every field is a scalar or an ``(H, W)`` texture over the unit square (looked up bilinearly at
    the pore for node terms, at the edge midpoint for ``deposit`` and ``decay``). Defaults are the
    paper's: the four reward/penalty terms 0, ``deposit`` 0.25, ``decay`` 0.5, σ = σ_cspread = 0.3,
    Δt = 0.03. Table 1 gives no defaults for the drawing rows; ours draw moderately wide wrinkles
    with pores as visible pits (found by :func:`find_pores` on a map with ≥ 20 px between pores),
    mild perturbation and little additive noise.

    Attributes:
        d: α_d, average pore distance (minimum distance of the Poisson-disk sampling) in UV units.
        theta: α_θ, primary orientation (radians) of the orientation sampler, Eq. 1.
        s: α_s, orientation uniformity (base strength) of Eq. 1; 0 = only α_θ, 1 ≈ uniform.
        dist: α_dist, distance exponent of Eq. 3 (larger prefers short edges).
        cont: α_cont, continuation reward of Eq. 4.
        sim: α_sim, similarity (T-crossing) penalty of Eq. 4.
        cross: α_cross, crossing penalty of Eq. 3.
        deposit: α_deposit, deposit strength of Eq. 7.
        decay: α_decay, decay of Eq. 8.
        sigma: σ of Eq. 1.
        sigma_cont: σ_cspread of Eq. 4.
        dt: Δt of Eq. 7–8.
        wrinkle_width: α_wrinkle-width; a wrinkle's valley half-width is ``W · wrinkle_width · d``
            (UV units, so widths follow the pore distance).
        pore_width: α_pore-width; a pore's radius is ``w_v · pore_width · d`` (w_v of Eq. 13).
        dmin: α_dmin of Eq. 13, the least extra depth of a pore over its strongest wrinkle.
        blend: α_blend of Eq. 13, from the strongest incident wrinkle (0) to their sum (1).
        skew: α_skew, stretch of the pores along the primary orientation α_θ (1 = 3× longer).
        cushion: α_cushion, fraction of the pore strength added to the wrinkles near their pores.
        fperturb: α_fperturb, frequency (cells per UV unit) of the wrinkle-geometry perturbation.
        sperturb: α_sperturb, its strength (offset of the centre line in wrinkle widths).
        fnoise: α_fnoise, frequency (cells per UV unit) of the additive Perlin noise.
        snoise: α_snoise, strength of the additive Perlin noise (displacement units).
        scale: α_scale, global displacement scaling of the level.
    """

    d: Float[Array, "*shape"] = _field(0.01)
    theta: Float[Array, "*shape"] = _field(0.0)
    s: Float[Array, "*shape"] = _field(0.5)
    dist: Float[Array, "*shape"] = _field(0.0)
    cont: Float[Array, "*shape"] = _field(0.0)
    sim: Float[Array, "*shape"] = _field(0.0)
    cross: Float[Array, "*shape"] = _field(0.0)
    deposit: Float[Array, "*shape"] = _field(0.25)
    decay: Float[Array, "*shape"] = _field(0.5)
    sigma: Float[Array, "*shape"] = _field(0.3)
    sigma_cont: Float[Array, "*shape"] = _field(0.3)
    dt: Float[Array, "*shape"] = _field(0.03)
    wrinkle_width: Float[Array, "*shape"] = _field(0.3)
    pore_width: Float[Array, "*shape"] = _field(0.3)
    dmin: Float[Array, "*shape"] = _field(0.4)
    blend: Float[Array, "*shape"] = _field(0.5)
    skew: Float[Array, "*shape"] = _field(0.0)
    cushion: Float[Array, "*shape"] = _field(0.0)
    fperturb: Float[Array, "*shape"] = _field(400.0)
    sperturb: Float[Array, "*shape"] = _field(0.3)
    fnoise: Float[Array, "*shape"] = _field(1000.0)
    snoise: Float[Array, "*shape"] = _field(0.01)
    scale: Float[Array, "*shape"] = _field(0.5)

    def __check_init__(self):
        for name in _NAMES:
            value = getattr(self, name)
            if value.ndim not in (0, 2):
                raise ValueError(
                    f"WrinkleParams.{name} must be a scalar or a 2-D texture (H, W), "
                    f"got {_checks.describe(value)}"
                )
            if _checks.is_traced(value):
                continue
            lo, hi = PARAMETER_RANGES[name]
            values = np.asarray(value)  # numpy's reductions of a jax array would trace under jit
            vmin, vmax = float(values.min()), float(values.max())
            # compare in float32, the values' precision (0.05 is stored as 0.0500000007)
            low, high = float(np.float32(lo)), float(np.float32(hi))
            if not (np.isfinite(vmin) and np.isfinite(vmax)) or vmin < low or vmax > high:
                got = f"{vmin}" if value.ndim == 0 else f"values in [{vmin}, {vmax}]"
                raise ValueError(
                    f"WrinkleParams.{name} must be in [{lo}, {hi}] (Table 1), got {got}"
                )

    def replace(self, **changes: Any) -> WrinkleParams:
        """A copy with some fields changed (validated again)."""
        unknown = set(changes) - set(_NAMES)
        if unknown:
            raise ValueError(f"unknown WrinkleParams field(s) {sorted(unknown)}; known: {_NAMES}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: scalars as floats, textures as nested lists."""
        out = {}
        for name in _NAMES:
            value = np.asarray(getattr(self, name))
            # shortest decimal that round-trips the float32 value (0.02, not 0.0199999996)
            out[name] = float(str(value)) if value.ndim == 0 else value.tolist()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WrinkleParams:
        """Inverse of :meth:`to_dict`; missing fields take the defaults."""
        if not isinstance(data, dict):
            raise TypeError(f"WrinkleParams data must be a dict, got {_checks.describe(data)}")
        unknown = set(data) - set(_NAMES)
        if unknown:
            raise ValueError(f"unknown WrinkleParams field(s) {sorted(unknown)}; known: {_NAMES}")
        values = {}
        for name, value in data.items():
            try:
                values[name] = np.asarray(value, dtype=np.float64)
            except OverflowError:  # an integer beyond any float: out of every range
                lo, hi = PARAMETER_RANGES[name]
                raise ValueError(
                    f"WrinkleParams.{name} must be in [{lo}, {hi}] (Table 1), got a number "
                    "too large for a float"
                ) from None
            except (TypeError, ValueError):
                raise ValueError(
                    f"WrinkleParams.{name} must be a number or a 2-D texture (rows of numbers, "
                    f"all of one length), got {_checks.describe(value)}"
                ) from None
        return cls(**values)


_NAMES = tuple(f.name for f in dataclasses.fields(WrinkleParams))


def save_params(path, levels) -> None:
    """Write one level or a list of levels (coarse to fine) to a JSON file, atomically."""
    from jface.io import write_json

    write_json(path, json.loads(params_to_json(levels)))


def load_params(path) -> list[WrinkleParams]:
    """Levels (coarse to fine) from a file written by :func:`save_params`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a WrinkleParams document, or values out of range.
    """
    from jface.io import read_json

    data = read_json(path)
    try:
        return params_from_json(json.dumps(data))
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: {err}") from err


def params_to_json(levels: WrinkleParams | list[WrinkleParams] | tuple[WrinkleParams, ...]) -> str:
    """JSON text of one level or a list of levels (coarse to fine)."""
    if isinstance(levels, WrinkleParams):
        levels = [levels]
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("levels must be a WrinkleParams or a non-empty list of them")
    return json.dumps({"kind": "WrinkleParams", "levels": [p.to_dict() for p in levels]})


def params_from_json(text: str) -> list[WrinkleParams]:
    """Levels (coarse to fine) from :func:`params_to_json` text.

    Raises:
        ValueError: not JSON, not a WrinkleParams document, or values out of range.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"wrinkle parameters are not valid JSON: {err}") from err
    if not isinstance(data, dict) or data.get("kind") != "WrinkleParams":
        raise ValueError("not a WrinkleParams document (missing kind 'WrinkleParams')")
    levels = data.get("levels")
    if not isinstance(levels, list) or not levels:
        raise ValueError("a WrinkleParams document needs a non-empty 'levels' list")
    return [WrinkleParams.from_dict(level) for level in levels]


def stack_params(levels: list[WrinkleParams] | tuple[WrinkleParams, ...]) -> WrinkleParams:
    """Stack parameter sets of identical leaf shapes into a batch (leading axis) for ``vmap``."""
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("stack_params needs a non-empty list of WrinkleParams")
    shapes = {tuple(jnp.shape(getattr(p, n)) for n in _NAMES) for p in levels}
    if len(shapes) != 1:
        raise ValueError("stack_params needs parameter sets whose fields have identical shapes")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *levels)
