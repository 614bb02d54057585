"""Named arrays plus JSON metadata in one ``.npz`` file: statistics, models, graphs."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from jface.io._files import atomic_path

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
        path: output file (".npz" is the convention).
        arrays: name → array (numpy or JAX).
        metadata: JSON-serialisable description (version, seed, parameters, ...).
        kind: what the file holds (e.g. "DetailStats"); checked again on load.
        protect: input files this output must not overwrite.
    """
    if _META in arrays:
        raise ValueError(f"array name {_META!r} is reserved")
    blob = json.dumps({"kind": kind, **metadata})
    payload = {name: np.asarray(value) for name, value in arrays.items()}
    payload[_META] = np.frombuffer(blob.encode(), dtype=np.uint8)
    path = Path(path)
    with atomic_path(path, protect=protect) as tmp, open(tmp, "wb") as handle:
        np.savez_compressed(handle, **payload)
    return path


def load_arrays(path: str | os.PathLike, *, kind: str) -> tuple[dict[str, np.ndarray], dict]:
    """Load what :func:`save_arrays` wrote; check it holds ``kind``.

    Raises:
        FileNotFoundError: no such file.
        ValueError: corrupt, truncated, not a jface file, or a file of another kind.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        msg = f"{path} is not a readable jface .npz file (corrupt, truncated or another format)"
        raise ValueError(msg) from err
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
