"""Building a statistics database from many displacement maps: chunked, sharded over all
devices, spread over the processes of a ``jax.distributed`` run, with progress, and resumable (a
crash keeps every finished chunk). The result does not depend on the chunk size, the device count
or the process count: the same maps give the same bytes."""

from __future__ import annotations

import collections
import contextlib
import functools
import json
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
from jface._distributed import _Run
from jface._progress import Estimate
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

    The batch axis is split over ``devices`` (default: this process's devices, at most one per
    map) with
    ``jax.sharding``; each device analyses its share one map at a time. The result equals
    ``jax.vmap(analyze)(images)``, and a map's result has the same bits in any batch.
    """
    images = _checks.float_array(images, "images", ndim=3)
    n = images.shape[0]
    # by default at most one device per map: the padding never outgrows the batch
    devices = list(devices or jax.local_devices()[: max(n, 1)])
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
    stats = _analyze_stack(images, mesh, grid, n_scales, n_orientations, bins, boundary)
    return jax.tree.map(lambda x: x[:n], stats)


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5, 6))
def _analyze_stack(images, mesh, grid, n_scales, n_orientations, bins, boundary) -> DetailStats:
    # Module level, so every chunk of a batch run reuses one compilation. Each device analyses
    # its share one map at a time (lax.map, not vmap): a batched FFT groups rows of neighbouring
    # maps into its vector lanes, which changes the last bit of a map's result with the batch
    # size; one map's program gives the same bits in any chunk, on any number of devices or
    # processes.
    one = functools.partial(
        _analyze,
        grid=grid,
        n_scales=n_scales,
        n_orientations=n_orientations,
        bins=bins,
        boundary=boundary,
    )
    share = PartitionSpec("batch")
    return jax.shard_map(lambda x: jax.lax.map(one, x), mesh=mesh, in_specs=share, out_specs=share)(
        images
    )


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
) -> Population | None:
    """Analyse many displacement maps into one population file, resumably, on one process or
    on all processes of a ``jax.distributed`` run.

    Every map's size is read from its header first, so maps of mixed sizes or a layout that
    does not fit them fail before any analysis. Maps are then read and analysed ``chunk`` at a
    time (memory stays bounded), each chunk sharded over all devices (:func:`analyze_batch`).
    Every finished chunk is written at once to a folder beside ``out`` (``out`` + ".parts"),
    named by a key of its maps' content and the settings (:func:`jface.io.content_key`); a
    rerun after a crash reuses the chunks whose key still matches and analyses the rest, so a
    map edited in between is analysed again. When all chunks are done, the population is written
    to ``out`` and the parts are removed. ``out`` is never one of the sources.

    Under ``jax.distributed`` (:func:`join_processes`), every process runs this call with the
    same arguments: chunk ``i`` is analysed by process ``i % jax.process_count()`` on its own
    devices, and process 0 merges the parts (``out`` must be on a file system all processes
    see). The database has the same bytes as a one-process build (each map is analysed by the
    same single-map program, whatever the chunk, device or process count; on CPU this needs
    XLA's single-threaded Eigen, :func:`deterministic_cpu_flags`, which ``jface db build``
    sets). A process that fails stops the others at once with its message, one that dies
    unannounced within the heartbeat timeout; a rerun reuses every finished chunk, whichever
    process wrote it.

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
        The :class:`Population` (None on processes other than 0 of a distributed run).

    Raises:
        FileNotFoundError: a source that does not exist.
        ValueError: no sources, a source given twice, maps of different sizes, a bad layout,
            records that do not match the maps (count, missing or repeated ids), an unreadable
            map (the message names it), ``out`` that is not a ``.npz`` name, ``out`` that holds
            a database of another jface version or layout, processes given different arguments
            or seeing different files, or a map or finished chunk that changed while the build
            ran.
        ChildProcessError: another process of the distributed run failed (its message).
    """
    run = _Run() if jax.process_count() > 1 else None
    try:
        return _build_database(
            run, sources, out, records, grid, n_scales, n_orientations, bins, boundary, chunk,
            progress, devices,
        )  # fmt: skip
    except BaseException as err:
        if run is not None:
            run.fail(err)  # the others stop at once instead of waiting for this share
        raise


def _build_database(
    run, sources, out, records, grid, n_scales, n_orientations, bins, boundary, chunk, progress,
    devices,
) -> Population | None:  # fmt: skip
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
        _check_previous(out, layout, shape)
        parts = out.with_name(out.name + ".parts")
        chunks = [sources[start : start + chunk] for start in range(0, len(sources), chunk)]
        settings = {"kind": "DetailStatsChunk", **layout}
        keys = [io.content_key(names, settings) for names in chunks]
        paths = [parts / f"{i * chunk:08d}-{key[:16]}.npz" for i, key in enumerate(keys)]
        process, n_processes = jax.process_index(), jax.process_count()
        if run is not None:
            fingerprint = json.dumps([str(out), keys, records, chunk], sort_keys=True)
            run.same_on_all(
                "the command's arguments, its maps' contents or jface's code", fingerprint
            )
        mine = range(process, len(chunks), n_processes)
        devices = list(devices) if devices else None  # default: analyze_batch's
        estimate = Estimate(sum(len(chunks[i]) for i in mine), "map", enabled=progress)
        for i in tqdm(mine, desc="analyze", unit="chunk", disable=not progress):
            if _part(paths[i], keys[i]) is not None:
                estimate.skip(len(chunks[i]))  # kept from an earlier run
                continue
            images = np.stack([io.read_map(name) for name in chunks[i]])
            if io.content_key(chunks[i], settings) != keys[i]:
                raise ValueError(
                    f"a map of {', '.join(map(str, chunks[i]))} changed while the build ran "
                    "(its content differs from when the build started); run it again"
                )
            stats = analyze_batch(images, devices=devices, **layout)
            arrays, meta = stats_to_arrays(stats)
            sources_meta = {"sources": [str(n) for n in chunks[i]], "key": keys[i]}
            io.save_arrays(paths[i], arrays, {**meta, **sources_meta}, kind="DetailStatsChunk")
            io.commit()  # a finished chunk survives a crash of a later one
            estimate.update(len(chunks[i]))
        if run is not None:
            run.gather("finished", "")  # process 0 waits for every share
            if process != 0:
                return None
        done = []
        for path, key, names in zip(paths, keys, chunks, strict=True):
            part = _part(path, key)
            if part is None:
                raise ValueError(
                    f"the finished chunk of {names[0]} ... {names[-1]} ({path}) was removed or "
                    "replaced while the build ran; run it again"
                )
            done.append(part)
        merged = jax.tree.map(lambda *xs: jnp.concatenate(xs), *done)
        population = Population(merged, tuple(records))
        population.save(out, boundary=boundary, sources=labels)
        io.commit()
        for part in parts.glob("*.npz"):
            part.unlink()
        with contextlib.suppress(OSError):  # a folder the user put other files in stays
            parts.rmdir()
    return population


def _part(path: Path, key: str) -> DetailStats | None:
    """The statistics of a finished chunk, or None when it is not there or was analysed from
    other contents or settings (its key differs)."""
    if not path.exists():
        return None
    with io.own_outputs():
        arrays, meta = io.load_arrays(path, kind="DetailStatsChunk")
    return stats_from_arrays(arrays, meta, path) if meta.get("key") == key else None


def _check_previous(out: Path, layout: dict[str, Any], shape: tuple[int, int]) -> None:
    """Refuse to replace a database of another jface version or layout: a study's files must
    not mix, and a rebuild with other settings is a new database under a new name."""
    from jface import __version__

    if not out.exists():
        return
    try:
        with io.own_outputs():
            _, meta = io.load_arrays(out, kind="Population")
    except ValueError as err:
        raise ValueError(
            f"{out} exists and is not a jface database ({err}); choose another name"
        ) from err
    wanted = {"jface_version": __version__, **layout, "image_shape": list(shape)}
    wanted.pop("bins")  # a database stores its histograms, not the bin count as a setting
    differ = {k: (meta.get(k), v) for k, v in wanted.items() if meta.get(k) != v}
    if differ:
        what = ", ".join(f"{k} {old!r} (now {new!r})" for k, (old, new) in differ.items())
        raise ValueError(
            f"{out} holds a database of another version or layout: {what}; "
            "remove it or choose another --out"
        )


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
