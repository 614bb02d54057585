"""Reading small JSON documents (parameter sets, records); writing is ``write_json`` in
``_files``."""

from __future__ import annotations

import json
import os
from typing import Any

from jface.io._files import input_file


def read_json(path: str | os.PathLike, *, lines: bool = False) -> Any:
    """Read a JSON document, or with ``lines`` a JSON-lines file (one document per non-empty
    line, returned as a list).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not UTF-8 text, not valid JSON (the message names the file and the place),
            or nested too deeply to read.
    """
    path = input_file(path, "JSON file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{path} is not UTF-8 text, so not JSON: {err.reason} at byte {err.start}"
        ) from err
    where = str(path)
    try:
        if not lines:
            return json.loads(text)
        documents = []
        for number, line in enumerate(text.splitlines(), 1):
            where = f"{path}, line {number},"
            if line.strip():
                documents.append(json.loads(line))
        return documents
    except ValueError as err:  # JSONDecodeError, or an integer of more digits than Python reads
        raise ValueError(f"{where} is not valid JSON: {err}") from err
    except RecursionError as err:
        raise ValueError(f"{where} nests JSON too deeply to read") from err
