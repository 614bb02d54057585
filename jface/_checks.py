"""Validation at public entry points.

Every public function checks its arguments here before anything reaches a jitted kernel, and
raises ``ValueError``/``TypeError`` with a message that names the argument, what was expected
and what came. Checks that need concrete values (finiteness) are skipped for traced arrays, so
the same entry points stay usable under ``jax.jit`` and ``jax.vmap``; values closed over by a
jitted function are concrete and are checked.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_traced(x: Any) -> bool:
    """True when ``x`` is an abstract value inside a JAX transformation."""
    return isinstance(x, jax.core.Tracer)


def describe(x: Any) -> str:
    """A short description of a value for error messages."""
    if hasattr(x, "shape") and hasattr(x, "dtype"):
        return f"an array of shape {tuple(x.shape)} and dtype {x.dtype}"
    return f"{type(x).__name__} {x!r}"[:120]


def float_array(
    x: Any,
    name: str,
    *,
    min_ndim: int = 0,
    ndim: int | None = None,
    finite: bool = True,
    dtype: Any = None,
) -> jax.Array:
    """Return ``x`` as a floating JAX array, or raise a clear error.

    Args:
        x: array-like input.
        name: the argument's name, used in messages.
        min_ndim: smallest number of axes allowed.
        ndim: exact number of axes required (overrides ``min_ndim``).
        finite: reject NaN and infinity (checked only for concrete values).
        dtype: cast to this floating dtype; by default keep float32/float64 and reject others.

    Raises:
        TypeError: not array-like, or not of a floating dtype.
        ValueError: wrong number of axes, an empty axis, or non-finite values.
    """
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name} must be a floating-point array, got {describe(x)}")
    try:
        kind = np.result_type(x).kind if not hasattr(x, "dtype") else np.dtype(x.dtype).kind
    except TypeError as err:
        raise TypeError(f"{name} must be a floating-point array, got {describe(x)}") from err
    if kind != "f":
        raise TypeError(
            f"{name} must have a floating-point dtype (float32 or float64), got {describe(x)}; "
            "convert it explicitly, e.g. image.astype(np.float32) / 255"
        )
    # Converted eagerly even inside jit: a concrete input (a closed-over array, a Python number)
    # stays concrete, so it is checked and its values may size what follows.
    with jax.ensure_compile_time_eval():
        arr = x if isinstance(x, jax.Array) else jnp.asarray(x)
        if dtype is not None:
            arr = arr.astype(dtype)
        elif arr.dtype not in (jnp.float32, jnp.float64):
            arr = arr.astype(jnp.float32)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} axes, got {describe(arr)}")
    if arr.ndim < min_ndim:
        raise ValueError(f"{name} must have at least {min_ndim} axes, got {describe(arr)}")
    if arr.size == 0:
        raise ValueError(f"{name} must not be empty, got {describe(arr)}")
    if finite and not is_traced(arr) and not np.all(np.isfinite(np.asarray(arr))):
        bad = int(np.sum(~np.isfinite(np.asarray(arr))))
        raise ValueError(f"{name} must be finite, got {bad} NaN or infinite value(s)")
    return arr


def integer(x: Any, name: str, *, low: int | None = None, high: int | None = None) -> int:
    """Return ``x`` as a Python int within ``[low, high]``, or raise a clear error."""
    if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {describe(x)}")
    x = int(x)
    if (low is not None and x < low) or (high is not None and x > high):
        raise ValueError(f"{name} must be in [{low}, {high}], got {x}")
    return x


def real(
    x: Any, name: str, *, low: float | None = None, high: float | None = None, open_low=False
) -> float:
    """Return ``x`` as a finite Python float within the given bounds, or raise a clear error."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {describe(x)}")
    x = float(x)
    if not np.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    too_low = low is not None and (x <= low if open_low else x < low)
    if too_low or (high is not None and x > high):
        left = "(" if open_low else "["
        raise ValueError(f"{name} must be in {left}{low}, {high}], got {x}")
    return x


def choice(x: Any, name: str, options: Iterable[str]) -> str:
    """Return ``x`` if it is one of ``options``, or raise a clear error."""
    options = tuple(options)
    if x not in options:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, options))}; got {x!r}")
    return x


def key(x: Any, name: str = "key") -> jax.Array:
    """Return ``x`` if it is a JAX random key (typed, or legacy uint32[2]), else raise TypeError.

    A plain integer seed is refused with a hint, so a caller never gets JAX's bare message.
    """
    if isinstance(x, jax.Array) and (
        jnp.issubdtype(x.dtype, jax.dtypes.prng_key) or (x.dtype == jnp.uint32 and x.shape == (2,))
    ):
        return x
    raise TypeError(
        f"{name} must be a JAX random key such as jax.random.key(seed), got {describe(x)}"
    )


def single_key(x: Any, name: str = "key") -> jax.Array:
    """:func:`key`, and one key only: a stack of typed keys is refused (vmap for many)."""
    x = key(x, name)
    if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) and x.shape != ():
        raise ValueError(f"{name} must be a single key (vmap for many), got shape {x.shape}")
    return x
