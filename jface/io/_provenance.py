"""What made an output: stored in EXR headers, PNG text chunks and statistics files."""

from __future__ import annotations

from typing import Any


def provenance(*, seed: int | None = None, **params: Any) -> dict[str, Any]:
    """Provenance record: jface and JAX versions, the device kind, the seed and the parameters
    that produced an output. A seed repeats an output bit for bit only with the same versions on
    the same kind of device (XLA compiles for the device it runs on), so both are recorded."""
    import jax

    from jface import __version__

    record: dict[str, Any] = {
        "jface_version": __version__,
        "jax_version": jax.__version__,
        "device": jax.devices()[0].device_kind,
    }
    if seed is not None:
        record["seed"] = int(seed)
    record.update(params)
    return record
