"""What made an output: stored in EXR headers, PNG text chunks and statistics files."""

from __future__ import annotations

from typing import Any


def provenance(*, seed: int | None = None, **params: Any) -> dict[str, Any]:
    """Provenance record: jface version, seed and the parameters that produced an output."""
    from jface import __version__

    record: dict[str, Any] = {"jface_version": __version__}
    if seed is not None:
        record["seed"] = int(seed)
    record.update(params)
    return record
