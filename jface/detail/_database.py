"""Building a statistics database from many displacement maps: chunked, vmapped, sharded over all
devices, with progress, and resumable (a crash keeps every finished chunk)."""

from __future__ import annotations

import functools
import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from jface import _checks, io, pyramid
from jface.detail._population import Population
from jface.detail._stats import (
    DetailStats,
    _analyze,
    stats_from_arrays,
    stats_to_arrays,
    validate_layout,
)


def analyze_batch(
    images: Any,
    *,
    grid: int = 16,
    n_scales: int = 4,
    n_orientations: int = 4,
    bins: int | None = None,
    boundary: pyramid.Boundary = "circular",
    devices: Sequence[jax.Device] | None = None,
) -> DetailStats:
    """:func:`jface.detail.analyze` of a stack ``(n, H, W)``, sharded over devices.

    The batch axis is split over ``devices`` (default: all of JAX's devices) with
    ``jax.sharding``; each device runs the vmapped analysis on its share. The result equals
    ``jax.vmap(analyze)(images)``.
    """
    images = _checks.float_array(images, "images", ndim=3)
    devices = list(devices or jax.devices())
    n = images.shape[0]
    grid, n_scales, n_orientations, bins = validate_layout(
        images.shape[1:], grid, n_scales, n_orientations, bins, boundary
    )
    padded_n = -(-n // len(devices)) * len(devices)
    if padded_n != n:  # equal shares: pad with copies of the first map, drop their results
        images = jnp.concatenate(
            [images, jnp.broadcast_to(images[:1], (padded_n - n, *images.shape[1:]))]
        )
    mesh = Mesh(np.array(devices), ("batch",))
    images = jax.device_put(images, NamedSharding(mesh, PartitionSpec("batch")))
    stats = _analyze_stack(images, grid, n_scales, n_orientations, bins, boundary)
    return jax.tree.map(lambda x: x[:n], stats)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
def _analyze_stack(images, grid, n_scales, n_orientations, bins, boundary) -> DetailStats:
    # Module level, so every chunk of a batch run reuses one compilation; the input's sharding
    # splits the vmapped work over the devices.
    return jax.vmap(lambda x: _analyze(x, grid, n_scales, n_orientations, bins, boundary))(images)


def build_database(
    sources: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    *,
    records: Sequence[dict[str, Any]] | None = None,
    grid: int = 16,
    n_scales: int = 4,
    n_orientations: int = 4,
    bins: int | None = None,
    boundary: pyramid.Boundary = "circular",
    chunk: int = 8,
    progress: bool = True,
    devices: Sequence[jax.Device] | None = None,
) -> Population:
    """Analyse many displacement maps into one population file, resumably.

    Maps are read and analysed ``chunk`` at a time (memory stays bounded), each chunk sharded
    over all devices (:func:`analyze_batch`). Every finished chunk is written at once to a
    folder beside ``out`` (``out`` + ".parts"); a rerun after a crash loads the finished chunks
    and analyses only the rest. When all chunks are done, the population is written to ``out``
    and the parts are removed.

    Args:
        sources: map files (EXR, PNG, .npy), all of one size.
        out: the population file (``.npz``) to write.
        records: one metadata dict per map (id, age, sex, ethnicity, tags, ...); default: the
            file stem as id.
        grid, n_scales, n_orientations, bins, boundary: as for :func:`jface.detail.analyze`.
        chunk: maps per chunk.
        progress: show a progress bar.
        devices: devices to shard over (default: all).

    Returns:
        The :class:`Population`.
    """
    sources = [Path(s) for s in sources]
    if not sources:
        raise ValueError("sources must name at least one map, got none")
    missing = [str(s) for s in sources if not s.is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} source map(s) not found, e.g. {missing[0]}")
    if records is None:
        records = [{"id": s.stem} for s in sources]
    records = [dict(r) for r in records]
    if len(records) != len(sources):
        raise ValueError(f"need one record per map: {len(sources)} maps, {len(records)} records")
    chunk = _checks.integer(chunk, "chunk", low=1)
    out = Path(out)
    parts = out.with_name(out.name + ".parts")
    layout = {
        "grid": grid,
        "n_scales": n_scales,
        "n_orientations": n_orientations,
        "bins": bins,
        "boundary": boundary,
    }
    done: list[DetailStats] = []
    starts = range(0, len(sources), chunk)
    for start in tqdm(starts, desc="analyze", unit="chunk", disable=not progress):
        names = [str(s) for s in sources[start : start + chunk]]
        tag = hashlib.sha1(json.dumps([names, layout]).encode()).hexdigest()[:12]
        part = parts / f"{start:08d}-{tag}.npz"
        if part.exists():
            arrays, meta = io.load_arrays(part, kind="DetailStatsChunk")
            done.append(stats_from_arrays(arrays, meta, part))
            continue
        images = np.stack([io.read_map(name) for name in names])
        stats = analyze_batch(images, devices=devices, **layout)
        arrays, meta = stats_to_arrays(stats)
        io.save_arrays(part, arrays, {**meta, "sources": names}, kind="DetailStatsChunk")
        done.append(stats)
    merged = jax.tree.map(lambda *xs: jnp.concatenate(xs), *done)
    population = Population(merged, tuple(records))
    population.save(out, boundary=boundary, sources=[s.name for s in sources])
    for part in parts.glob("*.npz"):
        part.unlink()
    parts.rmdir()
    return population
