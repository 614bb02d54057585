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

#: Power of length of every field that carries one: α_d is a length (in the units of the file's
#: frame, see :class:`ParamUnits`), the perturbation and noise frequencies are per unit length.
#: The widths are multiples of α_d and follow it; every other field is a pure number.
LENGTH_POWERS: dict[str, int] = {"d": 1, "fperturb": -1, "fnoise": -1}

#: The ranges a WrinkleParams accepts: Table 1's (the fit's search ranges), except that the
#: frequencies may be up to 50× Table 1's upper bound. Converting a patch's lengths to a whole face
#: shrinks α_d by the patch's size and multiplies the frequencies by its inverse; α_d's own range
#: spans a factor 50, so no α_d left valid by a conversion leaves its frequencies out of range.
_ACCEPTED = PARAMETER_RANGES | {
    name: (PARAMETER_RANGES[name][0], PARAMETER_RANGES[name][1] * 50.0)
    for name, power in LENGTH_POWERS.items()
    if power < 0
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
            lo, hi = _ACCEPTED[name]
            values = np.asarray(value)  # numpy's reductions of a jax array would trace under jit
            vmin, vmax = float(values.min()), float(values.max())
            # compare in float32, the values' precision (0.05 is stored as 0.0500000007)
            low, high = float(np.float32(lo)), float(np.float32(hi))
            if not (np.isfinite(vmin) and np.isfinite(vmax)) or vmin < low or vmax > high:
                got = f"{vmin}" if value.ndim == 0 else f"values in [{vmin}, {vmax}]"
                where = "Table 1" if (lo, hi) == PARAMETER_RANGES[name] else "Table 1, high ×50"
                raise ValueError(
                    f"WrinkleParams.{name} must be in [{lo}, {hi}] ({where}), got {got}"
                )

    def replace(self, **changes: Any) -> WrinkleParams:
        """A copy with some fields changed (validated again)."""
        unknown = set(changes) - set(_NAMES)
        if unknown:
            raise ValueError(f"unknown WrinkleParams field(s) {sorted(unknown)}; known: {_NAMES}")
        return dataclasses.replace(self, **changes)

    def rescaled(self, factor: float) -> WrinkleParams:
        """The same parameters with lengths ``factor`` times as long: α_d × ``factor``, the
        perturbation and noise frequencies ÷ ``factor`` (:data:`LENGTH_POWERS`). E.g. a patch
        covering 1/16 of a face's side, converted to the face's UV units: ``rescaled(1 / 16)``.

        Raises:
            ValueError: ``factor`` not a positive finite number, or a converted value outside its
                range.
        """
        factor = _checks.real(factor, "factor", low=0.0, open_low=True)
        return self.replace(
            **{name: getattr(self, name) * factor**power for name, power in LENGTH_POWERS.items()}
        )

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
                lo, hi = _ACCEPTED[name]
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


@dataclasses.dataclass(frozen=True)
class ParamUnits:
    """The frame a parameter file's lengths (:data:`LENGTH_POWERS`) are expressed in.

    ``frame="uv"``: the unit square of the map the parameters are drawn on (a whole face map).
    ``frame="patch"``: the unit square of a square patch, e.g. one cut from a face map and
    fitted; ``patch_size`` is the patch's side in the face map's UV units (a 256-pixel patch cut
    from a 4096² map: 256/4096 = 0.0625), ``None`` where nobody stated it (the file cannot be
    converted then); ``patch_pixels`` (rows, columns) is what was fitted. Files store it as
    ``"units": {"frame": ..., ...}``.
    """

    frame: str = "uv"
    patch_size: float | None = None
    patch_pixels: tuple[int, int] | None = None

    def __post_init__(self):
        _checks.choice(self.frame, "the units' frame", FRAMES)
        if self.frame == "uv" and (self.patch_size, self.patch_pixels) != (None, None):
            raise ValueError("units of frame 'uv' take no patch_size or patch_pixels")
        object.__setattr__(self, "patch_size", _patch_size(self.patch_size))
        object.__setattr__(self, "patch_pixels", _patch_pixels(self.patch_pixels))

    @classmethod
    def parse(cls, text: str) -> ParamUnits:
        """``"uv"`` or ``"patch:SIZE"``, SIZE a number or a fraction (``"patch:256/4096"``)."""
        frame, _, size = str(text).partition(":")
        if frame == "patch" and size:
            return cls("patch", parse_patch_size(size))
        if frame == "uv" and not size:
            return cls("uv")
        raise ValueError(
            f"a frame must be 'uv' or 'patch:SIZE' (e.g. patch:256/4096), got {text!r}"
        )

    def to_dict(self) -> dict[str, Any]:
        if self.frame == "uv":
            return {"frame": "uv"}
        pixels = None if self.patch_pixels is None else list(self.patch_pixels)
        return {"frame": "patch", "patch_size": self.patch_size, "patch_pixels": pixels}

    @classmethod
    def from_dict(cls, data: Any) -> ParamUnits:
        if not isinstance(data, dict) or not isinstance(data.get("frame"), str):
            raise ValueError(f"'units' must be an object with a 'frame', got {data!r}")
        unknown = set(data) - {"frame", "patch_size", "patch_pixels"}
        if unknown:
            raise ValueError(f"unknown 'units' field(s) {sorted(unknown)}")
        size, pixels = _patch_size(data.get("patch_size")), _patch_pixels(data.get("patch_pixels"))
        return cls(data["frame"], size, pixels)

    def length_factor(self) -> float:
        """Lengths in the map's UV units per length in this frame."""
        if self.frame == "uv":
            return 1.0
        if self.patch_size is None:
            raise ValueError("the patch's size on the face is not recorded (patch_size null)")
        rows, columns = self.patch_pixels or (1, 1)
        if rows != columns:
            raise ValueError(
                f"the parameters were fitted on a {rows}×{columns} patch, whose unit square is "
                "stretched: its lengths have no single size on the face (fit a square patch)"
            )
        return self.patch_size


#: The frames a parameter file may state (see :class:`ParamUnits`).
FRAMES = ("uv", "patch")


def _patch_size(size: Any) -> float | None:
    if size is None:
        return None
    if isinstance(size, bool) or not isinstance(size, int | float) or not 0 < size <= 1:
        raise ValueError(
            "patch_size (the patch's side in the face map's UV units) must be a number in "
            f"(0, 1], got {size!r}"
        )
    return float(size)


def _patch_pixels(pixels: Any) -> tuple[int, int] | None:
    if pixels is None:
        return None
    if (
        not isinstance(pixels, list | tuple)
        or len(pixels) != 2
        or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in pixels)
    ):
        raise ValueError(
            f"patch_pixels must be [rows, columns], two positive integers, got {pixels!r}"
        )
    return tuple(pixels)


def parse_patch_size(text: str) -> float:
    """A patch's side in a face map's UV units from ``"0.0625"`` or ``"256/4096"``, in (0, 1]."""
    top, _, bottom = str(text).partition("/")
    try:
        size = float(top) / float(bottom) if bottom else float(top)
    except (ValueError, ZeroDivisionError):
        size = math.nan
    if not 0.0 < size <= 1.0:  # NaN too
        raise ValueError(
            "a patch size must be its side as a fraction of the face map's side, in (0, 1], "
            f"e.g. 0.0625 or 256/4096, got {text!r}"
        )
    return size


def to_map_frame(
    levels: list[WrinkleParams], units: ParamUnits, source: str = "parameters"
) -> list[WrinkleParams]:
    """Levels stated in ``units`` expressed in the unit square of the map they are drawn on.

    Raises:
        ValueError (naming ``source``): the frame cannot be converted (a patch of unknown size, a
            non-square patch, a patch with textures, which cover the patch and not the face) or a
            converted value leaves its range.
    """
    try:
        factor = units.length_factor()
    except ValueError as err:
        raise ValueError(f"{source}: {err}; {_STATE_FRAME}") from None
    if factor == 1.0:
        return list(levels)
    for i, level in enumerate(levels):
        textures = [n for n in _NAMES if getattr(level, n).ndim == 2]
        if textures:
            raise ValueError(
                f"{source}: level {i}: {textures} vary over the patch; a patch's textures cannot "
                "be placed on the face (give scalars)"
            )
    try:
        return [level.rescaled(factor) for level in levels]
    except ValueError as err:
        raise ValueError(
            f"{source}: lengths of the {units.patch_size:g}-wide patch on the map: {err}"
        ) from None


_STATE_FRAME = (
    "state the frame: 'jface wrinkles render/simulate --params-frame uv' (the whole map) or "
    "'--params-frame patch:SIZE' (a patch whose side is SIZE of the map's, e.g. patch:256/4096), "
    'or add "units": {"frame": "patch", "patch_size": SIZE} to the file '
    "('jface wrinkles fit --patch-size' records it)"
)


def _with_units(units: ParamUnits | str) -> ParamUnits:
    return units if isinstance(units, ParamUnits) else ParamUnits.parse(units)


def save_params(path, levels, units: ParamUnits | str) -> None:
    """Write one level or a list of levels (coarse to fine) and the frame of their lengths
    (:class:`ParamUnits` or ``"uv"`` / ``"patch:SIZE"``) to a JSON file, atomically."""
    from jface.io import write_json

    write_json(path, json.loads(params_to_json(levels, units)))


def load_params(path, *, frame: ParamUnits | str | None = None) -> list[WrinkleParams]:
    """Levels (coarse to fine) of a file written by :func:`save_params`, their lengths converted
    to the unit square of the map they are drawn on (:func:`to_map_frame`).

    ``frame`` states the frame of a file that does not (older jface, or a fit of a patch of
    unknown size); it must agree with what the file does state.

    Raises:
        FileNotFoundError: no such file.
        ValueError (naming the file): not a WrinkleParams document, values out of range, no frame
            stated, or one that cannot be converted.
    """
    from jface.io import read_json

    return params_from_json(json.dumps(read_json(path)), frame=frame, source=str(path))


def params_to_json(
    levels: WrinkleParams | list[WrinkleParams] | tuple[WrinkleParams, ...],
    units: ParamUnits | str,
) -> str:
    """JSON text of one level or a list of levels (coarse to fine) and their frame."""
    if isinstance(levels, WrinkleParams):
        levels = [levels]
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("levels must be a WrinkleParams or a non-empty list of them")
    return json.dumps(
        {
            "kind": "WrinkleParams",
            "units": _with_units(units).to_dict(),
            "levels": [p.to_dict() for p in levels],
        }
    )


def params_from_json(
    text: str, *, frame: ParamUnits | str | None = None, source: str = "wrinkle parameters"
) -> list[WrinkleParams]:
    """Levels (coarse to fine) of :func:`params_to_json` text, in the map's frame (see
    :func:`load_params`); errors name ``source``.

    Raises:
        ValueError: not JSON, not a WrinkleParams document, values out of range, no frame stated,
            or one that cannot be converted.
    """
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{source}: not valid JSON: {err}") from err
    if not isinstance(data, dict) or data.get("kind") != "WrinkleParams":
        raise ValueError(f"{source}: not a WrinkleParams document (missing kind 'WrinkleParams')")
    levels = data.get("levels")
    if not isinstance(levels, list) or not levels:
        raise ValueError(f"{source}: a WrinkleParams document needs a non-empty 'levels' list")
    try:
        levels = [WrinkleParams.from_dict(level) for level in levels]
        stated = None if "units" not in data else ParamUnits.from_dict(data["units"])
        given = None if frame is None else _with_units(frame)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source}: {err}") from err
    return to_map_frame(levels, _agreed(stated, given, source), source)


def _agreed(stated: ParamUnits | None, given: ParamUnits | None, source: str) -> ParamUnits:
    """The file's frame completed by the one given (--params-frame); a contradiction is refused."""
    if stated is None and given is None:
        raise ValueError(f"{source}: no frame stated for the lengths (no 'units'); {_STATE_FRAME}")
    if given is None:
        return stated
    if stated is None:
        return given
    size_known = stated.patch_size is not None
    if given.frame != stated.frame or (size_known and given.patch_size != stated.patch_size):
        raise ValueError(
            f"{source}: the file states units {stated.to_dict()}, but the frame given is "
            f"{given.to_dict()}: drop the given frame or correct the file"
        )
    return dataclasses.replace(stated, patch_size=given.patch_size)


def stack_params(levels: list[WrinkleParams] | tuple[WrinkleParams, ...]) -> WrinkleParams:
    """Stack parameter sets of identical leaf shapes into a batch (leading axis) for ``vmap``."""
    if not levels or not all(isinstance(p, WrinkleParams) for p in levels):
        raise TypeError("stack_params needs a non-empty list of WrinkleParams")
    shapes = {tuple(jnp.shape(getattr(p, n)) for n in _NAMES) for p in levels}
    if len(shapes) != 1:
        raise ValueError("stack_params needs parameter sets whose fields have identical shapes")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *levels)
