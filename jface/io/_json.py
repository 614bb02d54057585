"""Small JSON documents (parameter sets), written atomically."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from jface.io._files import atomic_path


def write_json(
    path: str | os.PathLike, document: Any, *, protect: tuple[str | os.PathLike, ...] = ()
) -> Path:
    """Write a JSON-serialisable document (indented), atomically."""
    path = Path(path)
    text = json.dumps(document, indent=1)
    with atomic_path(path, protect=protect) as tmp:
        tmp.write_text(text + "\n")
    return path


def read_json(path: str | os.PathLike) -> Any:
    """Read a JSON document.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not valid JSON.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path} is not valid JSON: {err}") from err
