"""Building a statistics database from many displacement maps: chunked, vmapped, sharded over all
devices, with progress, and resumable (a crash keeps every finished chunk)."""

from __future__ import annotations

import collections
import contextlib
import functools
import os
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from jface import _checks, io, pyramid
from jface.detail._population import Population, check_records
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

    Every map's size is read from its header first, so maps of mixed sizes or a layout that
    does not fit them fail before any analysis. Maps are then read and analysed ``chunk`` at a
    time (memory stays bounded), each chunk sharded over all devices (:func:`analyze_batch`).
    Every finished chunk is written at once to a folder beside ``out`` (``out`` + ".parts"),
    named by a key of its maps' content and the settings (:func:`jface.io.content_key`); a
    rerun after a crash reuses the chunks whose key still matches and analyses the rest, so a
    map edited in between is analysed again. When all chunks are done, the population is written
    to ``out`` and the parts are removed. ``out`` is never one of the sources.

    Args:
        sources: map files (EXR, PNG, .npy), all of one size.
        out: the population file (``.npz``) to write.
        records: one metadata dict per map (id, age, sex, ethnicity, tags, ...), ids unique;
            default: the file stem as id (with as many parent folders as make the ids unique,
            e.g. ``young/face`` and ``old/face``).
        grid, n_scales, n_orientations, bins, boundary: as for :func:`jface.detail.analyze`.
        chunk: maps per chunk.
        progress: show a progress bar.
        devices: devices to shard over (default: all).

    Returns:
        The :class:`Population`.

    Raises:
        FileNotFoundError: a source that does not exist.
        ValueError: no sources, a source given twice, maps of different sizes, a bad layout,
            records that do not match the maps (count, missing or repeated ids), an unreadable
            map (the message names it), or ``out`` that is not a new ``.npz`` name.
    """
    sources = [Path(s) for s in sources]
    if not sources:
        raise ValueError("sources must name at least one map, got none")
    missing = [str(s) for s in sources if not s.is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} source map(s) not found, e.g. {missing[0]}")
    labels = _labels(sources)
    records = [{"id": label} for label in labels] if records is None else [dict(r) for r in records]
    if len(records) != len(sources):
        raise ValueError(f"need one record per map: {len(sources)} maps, {len(records)} records")
    check_records(records)
    chunk = _checks.integer(chunk, "chunk", low=1)
    with io.session(sources):
        out = io.check_output(out, (".npz",))
        shape = _common_shape(sources)
        grid, n_scales, n_orientations, bins = validate_layout(
            shape, grid, n_scales, n_orientations, bins, boundary
        )
        layout = {
            "grid": grid,
            "n_scales": n_scales,
            "n_orientations": n_orientations,
            "bins": bins,
            "boundary": boundary,
        }
        parts = out.with_name(out.name + ".parts")
        done: list[DetailStats] = []
        starts = range(0, len(sources), chunk)
        for start in tqdm(starts, desc="analyze", unit="chunk", disable=not progress):
            names = sources[start : start + chunk]
            key = io.content_key(names, {"kind": "DetailStatsChunk", **layout})
            part = parts / f"{start:08d}-{key[:16]}.npz"
            if part.exists():
                with io.own_outputs():
                    arrays, meta = io.load_arrays(part, kind="DetailStatsChunk")
                if meta.get("key") == key:
                    done.append(stats_from_arrays(arrays, meta, part))
                    continue
            images = np.stack([io.read_map(name) for name in names])
            stats = analyze_batch(images, devices=devices, **layout)
            arrays, meta = stats_to_arrays(stats)
            sources_meta = {"sources": [str(n) for n in names], "key": key}
            io.save_arrays(part, arrays, {**meta, **sources_meta}, kind="DetailStatsChunk")
            io.commit()  # a finished chunk survives a crash of a later one
            done.append(stats)
        merged = jax.tree.map(lambda *xs: jnp.concatenate(xs), *done)
        population = Population(merged, tuple(records))
        population.save(out, boundary=boundary, sources=labels)
        io.commit()
        for part in parts.glob("*.npz"):
            part.unlink()
        with contextlib.suppress(OSError):  # a folder the user put other files in stays
            parts.rmdir()
    return population


def _labels(sources: Sequence[Path]) -> list[str]:
    """A short unique name per map: its stem, with as many parent folders as tell it apart
    (compared without case), else its whole path."""
    resolved = [os.path.realpath(s) for s in sources]
    counts = collections.Counter(resolved)
    twice = sorted({str(s) for s, r in zip(sources, resolved, strict=True) if counts[r] > 1})
    if twice:
        raise ValueError(f"each map must be given once; given more than once: {twice[:5]}")
    stems = [PurePosixPath(*Path(r).with_suffix("").parts) for r in resolved]
    labels: list[str | None] = [None] * len(stems)
    pending = list(range(len(stems)))
    for depth in range(1, max(len(s.parts) for s in stems) + 1):
        names = {i: str(PurePosixPath(*stems[i].parts[-depth:])) for i in pending}
        taken = collections.Counter(n.casefold() for n in [*names.values(), *filter(None, labels)])
        for i, name in names.items():
            if taken[name.casefold()] == 1:
                labels[i] = name
        pending = [i for i in pending if labels[i] is None]
    return [label or resolved[i] for i, label in enumerate(labels)]


def _common_shape(sources: Sequence[Path]) -> tuple[int, int]:
    first = io.map_shape(sources[0])
    for source in sources[1:]:
        shape = io.map_shape(source)
        if shape != first:
            raise ValueError(
                f"{source} is {shape[0]}×{shape[1]}, but {sources[0]} is {first[0]}×{first[1]}: "
                "the maps of a database must have one size"
            )
    return first
