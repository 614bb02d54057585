"""Save and load face models (``.npz`` arrays + JSON metadata via :mod:`jface.io`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jface.faces._bilinear import BilinearModel
from jface.faces._fa import FactorAnalyser
from jface.faces._mofa import MixtureOfFactorAnalysers
from jface.io import load_arrays, provenance, save_arrays

KIND = "FaceModel"
_FIELDS = {
    "FactorAnalyser": ("mean", "factors", "noise"),
    "MixtureOfFactorAnalysers": ("weights", "means", "factors", "noise"),
    "BilinearModel": ("mean", "factors", "noise"),
}


def save_model(
    path: str | os.PathLike,
    model: Any,
    metadata: dict[str, Any] | None = None,
    *,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Save a :class:`FactorAnalyser`, :class:`MixtureOfFactorAnalysers` or
    :class:`BilinearModel` with its metadata (jface version, image shape, anything in
    ``metadata``) to a ``.npz`` file, atomically; ``protect`` lists inputs it must not overwrite.
    """
    if not isinstance(model, (FactorAnalyser, MixtureOfFactorAnalysers, BilinearModel)):
        raise TypeError(f"model must be a jface.faces model, got {type(model).__name__}")
    name = type(model).__name__
    arrays_of = model.stacked if isinstance(model, BilinearModel) else model
    if arrays_of.factors.ndim != (3 if name == "MixtureOfFactorAnalysers" else 2):
        raise ValueError("save one model at a time, not a batch of models")
    arrays = {field: np.asarray(getattr(arrays_of, field)) for field in _FIELDS[name]}
    meta = provenance(**(metadata or {}))
    meta.update(model_type=name, shape=list(arrays_of.shape))
    return save_arrays(path, arrays, meta, kind=KIND, protect=protect)


class SavedModel(NamedTuple):
    """A face model read back by :func:`load_model`, with the metadata saved beside it
    (provenance: jface version, image shape, training settings)."""

    model: Any
    metadata: dict[str, Any]


def load_model(path: str | os.PathLike) -> SavedModel:
    """Load what :func:`save_model` wrote: the model with its metadata.

    Raises:
        FileNotFoundError: no such file.
        ValueError: corrupt file, not a face model, or inconsistent arrays.
    """
    arrays, meta = load_arrays(path, kind=KIND)
    name = meta.get("model_type")
    if name not in _FIELDS or set(arrays) != set(_FIELDS[name]):
        raise ValueError(f"{path} is not a valid face model file (type {name!r})")
    try:
        shape = tuple(int(s) for s in meta["shape"])
    except (KeyError, TypeError, ValueError, OverflowError) as err:
        raise ValueError(f"{path} has no valid image 'shape' in its metadata") from err
    bad = [f for f in _FIELDS[name] if arrays[f].dtype.kind != "f"]
    if bad:
        raise ValueError(f"{path}: model arrays {bad} are not floating point")
    bad = [f for f in _FIELDS[name] if not np.all(np.isfinite(arrays[f]))]
    if bad or not np.all(arrays[_FIELDS[name][-1]] > 0):
        raise ValueError(
            f"{path}: model arrays {bad or [_FIELDS[name][-1]]} hold NaN, infinite or (noise) "
            "non-positive values"
        )
    values = [jnp.asarray(arrays[f]) for f in _FIELDS[name]]
    try:
        if name == "MixtureOfFactorAnalysers":
            model: Any = MixtureOfFactorAnalysers(*values, shape=shape)
        else:
            model = FactorAnalyser(*values, shape=shape)
            if name == "BilinearModel":
                model = BilinearModel(model)
    except Exception as err:  # jaxtyping/shape errors from a tampered file
        raise ValueError(f"{path} holds inconsistent model arrays: {err}") from err
    d = int(np.prod(shape))
    if values[-1].shape[-1] != d:
        raise ValueError(f"{path}: model arrays do not match the image shape {shape}")
    return SavedModel(model, meta)
