"""Named arrays plus JSON metadata in one ``.npz`` file: statistics, models, graphs."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from jface.io._files import atomic_path, check_output, input_file

_META = "__metadata__"


def save_arrays(
    path: str | os.PathLike,
    arrays: dict[str, Any],
    metadata: dict[str, Any],
    *,
    kind: str,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Save arrays and JSON metadata in one compressed ``.npz`` file, atomically.

    Args:
        path: output file, ending in ".npz".
        arrays: name → array (numpy or JAX).
        metadata: JSON-serialisable description (version, seed, parameters, ...).
        kind: what the file holds (e.g. "DetailStats"); checked again on load.
        protect: input files this output must not overwrite.
    """
    if _META in arrays:
        raise ValueError(f"array name {_META!r} is reserved")
    path = check_output(path, (".npz",), protect=protect)
    blob = json.dumps({"kind": kind, **metadata})
    payload = {name: np.asarray(value) for name, value in arrays.items()}
    payload[_META] = np.frombuffer(blob.encode(), dtype=np.uint8)
    with atomic_path(path, protect=protect) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(handle, **payload)
    return path


def load_arrays(path: str | os.PathLike, *, kind: str) -> tuple[dict[str, np.ndarray], dict]:
    """Load what :func:`save_arrays` wrote; check it holds ``kind``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: corrupt, truncated, not a jface file, a file of another kind, or arrays
            declared larger than memory.
    """
    path = input_file(path, "file")
    try:
        # our own handle: numpy leaves the file open when it fails to read a bad archive
        with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except MemoryError as err:
        raise ValueError(f"{path} declares arrays larger than memory (corrupt?): {err}") from err
    except Exception as err:  # zipfile, zlib, numpy's header parser: many types for bad files
        raise ValueError(
            f"{path} is not a readable jface .npz file (corrupt, truncated or another format: "
            f"{type(err).__name__}: {err})"
        ) from err
    if _META not in arrays:
        raise ValueError(f"{path} is not a jface file: it has no metadata")
    try:
        metadata = json.loads(arrays.pop(_META).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} has corrupt metadata: {err}") from err
    if not isinstance(metadata, dict):
        raise ValueError(f"{path} has corrupt metadata: not a JSON object")
    found = metadata.pop("kind", None)
    if found != kind:
        raise ValueError(f"{path} holds {found!r}, expected {kind!r}")
    return arrays, metadata
