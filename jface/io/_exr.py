"""OpenEXR 3.x maps: float32/half, one or several channels, compression, provenance headers."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import Imath
import numpy as np
import OpenEXR

from jface.io._files import atomic_path, check_output, input_file
from jface.io._images import image_size, read_image

_COMPRESSION = {
    "none": OpenEXR.NO_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    # ZSTD arrived in OpenEXR 3.4; older bindings fall back to ZIP.
    "zstd": getattr(OpenEXR, "ZSTD_COMPRESSION", OpenEXR.ZIP_COMPRESSION),
}
_PREFIX = "jface:"


class ExrImage(NamedTuple):
    """An EXR file's channels (name → (H, W) array) and its jface metadata."""

    channels: dict[str, np.ndarray]
    metadata: dict[str, Any]


def _as_channels(data: Any) -> dict[str, np.ndarray]:
    if isinstance(data, dict):
        items = dict(data)
    else:
        arr = np.asarray(data)
        if arr.ndim == 2:
            items = {"Y": arr}
        elif arr.ndim == 3 and arr.shape[-1] in (3, 4):
            items = dict(zip("RGBA", np.moveaxis(arr, -1, 0), strict=False))
        else:
            raise ValueError(
                "data must be an (H, W) map, an (H, W, 3|4) colour image or a dict of (H, W) "
                f"channels, got an array of shape {arr.shape}"
            )
    shapes = set()
    out = {}
    for name, channel in items.items():
        channel = np.asarray(channel)
        if channel.ndim != 2 or channel.size == 0:
            raise ValueError(f"channel {name!r} must be a non-empty 2-D array, got {channel.shape}")
        if channel.dtype.kind != "f":
            raise TypeError(f"channel {name!r} must be floating point, got {channel.dtype}")
        shapes.add(channel.shape)
        dtype = np.float16 if channel.dtype == np.float16 else np.float32
        # OpenEXR silently writes non-contiguous arrays wrong: always hand it a fresh C array.
        out[name] = np.ascontiguousarray(channel, dtype=dtype)
    if len(shapes) != 1:
        raise ValueError(f"all channels must have one shape, got {sorted(shapes)}")
    return out


def write_exr(
    path: str | os.PathLike,
    data: Any,
    *,
    half: bool = False,
    compression: str = "zstd",
    metadata: dict[str, Any] | None = None,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write a map to an OpenEXR file, atomically.

    Args:
        path: output file, ending in ".exr".
        data: an (H, W) map (channel "Y"), an (H, W, 3|4) image (RGB[A]) or a dict of channels.
        half: store 16-bit half floats instead of float32.
        compression: "zstd" (default), "zip", "piz" or "none".
        metadata: provenance (jface version, seed, parameters, ...); values must be
            JSON-serialisable. Stored as header attributes prefixed with "jface:".
        protect: input files this output must not overwrite.

    Returns:
        The path written.
    """
    path = check_output(path, (".exr",), protect=protect)
    if compression not in _COMPRESSION:
        raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}")
    channels = _as_channels(data)
    if half:
        channels = {k: v.astype(np.float16) for k, v in channels.items()}
    header: dict[str, Any] = {
        "compression": _COMPRESSION[compression],
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (metadata or {}).items():
        header[_PREFIX + key] = json.dumps(value)
    with atomic_path(path, protect=protect) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
    return path


# The scanline writer below uses the bindings' classic OutputFile API (writePixels), the one that
# writes a file in pieces; it knows no ZSTD, so "zstd" falls back to ZIP there.
_CLASSIC_COMPRESSION = {
    "none": Imath.Compression.NO_COMPRESSION,
    "zip": Imath.Compression.ZIP_COMPRESSION,
    "piz": Imath.Compression.PIZ_COMPRESSION,
    "zstd": Imath.Compression.ZIP_COMPRESSION,
}


@contextlib.contextmanager
def exr_rows(
    path: str | os.PathLike,
    shape: tuple[int, int],
    *,
    compression: str = "zip",
    metadata: dict[str, Any] | None = None,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Iterator[Callable[[Any], None]]:
    """Write a single-channel float32 map (channel "Y") to an OpenEXR scanline file band by band,
    so that a map larger than memory is never held whole. Atomic: the file appears only when
    every row was written and the block succeeded.

    Usage::

        with exr_rows("big.exr", (16384, 16384), metadata=meta) as write:
            for band in bands:          # (rows, 16384) arrays, top to bottom
                write(band)

    Args:
        path: output file, ending in ".exr".
        shape: ``(H, W)`` of the whole map.
        compression: "zip" (default), "piz", "none" ("zstd" writes ZIP here).
        metadata: provenance, stored like :func:`write_exr`'s.
        protect: input files this output must not overwrite.

    Yields:
        ``write(rows)``: appends an ``(n, W)`` array of the next ``n`` rows.

    Raises:
        ValueError: bad shape or compression, a band of the wrong width, more rows than ``H``,
            or fewer than ``H`` rows written when the block ends.
    """
    if compression not in _CLASSIC_COMPRESSION:
        raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, got {compression!r}")
    if not (
        isinstance(shape, tuple | list)
        and len(shape) == 2
        and all(isinstance(n, int | np.integer) and n > 0 for n in shape)
    ):
        raise ValueError(f"shape must be two positive integers (H, W), got {shape!r}")
    path = check_output(path, (".exr",), protect=protect)
    h, w = int(shape[0]), int(shape[1])
    header = OpenEXR.Header(w, h)
    header["channels"] = {"Y": Imath.Channel(Imath.PixelType(Imath.PixelType.FLOAT))}
    header["compression"] = Imath.Compression(_CLASSIC_COMPRESSION[compression])
    for key, value in (metadata or {}).items():
        header[_PREFIX + key] = json.dumps(value).encode()
    done = 0

    def write(rows: Any) -> None:
        nonlocal done
        band = np.ascontiguousarray(rows, dtype=np.float32)
        if band.ndim != 2 or band.shape[1] != w:
            raise ValueError(f"rows must have shape (n, {w}), got {band.shape}")
        if done + band.shape[0] > h:
            raise ValueError(f"more than the map's {h} rows written ({done} + {band.shape[0]})")
        out.writePixels({"Y": band.tobytes()}, band.shape[0])
        done += band.shape[0]

    with atomic_path(path, protect=protect) as tmp:
        out = OpenEXR.OutputFile(str(tmp), header)
        try:
            yield write
        finally:
            out.close()
        if done != h:
            raise ValueError(f"only {done} of the map's {h} rows were written")


def read_exr(path: str | os.PathLike) -> ExrImage:
    """Read every channel and the jface metadata of an OpenEXR file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a readable OpenEXR image (corrupt or truncated, or it
            declares more pixels than memory holds).
    """
    path = input_file(path, "EXR file")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
        header = exr.header()
        channels = {
            name: np.array(channel.pixels, dtype=np.float32)
            for name, channel in exr.channels().items()
        }
    except Exception as err:  # the bindings raise bare RuntimeError/IOError for bad files
        reason = "it declares more pixels than memory holds" if isinstance(err, MemoryError) \
            else f"{type(err).__name__}: {err}"  # fmt: skip
        raise ValueError(
            f"{path} is not a readable OpenEXR file (corrupt or truncated?): {reason}"
        ) from err
    metadata = {}
    for key, value in header.items():
        if isinstance(key, str) and key.startswith(_PREFIX):
            try:
                metadata[key[len(_PREFIX) :]] = json.loads(value)
            except (TypeError, json.JSONDecodeError):
                metadata[key[len(_PREFIX) :]] = value
    for name, pixels in channels.items():
        if pixels.ndim != 2:
            raise ValueError(f"{path}: channel {name!r} has shape {pixels.shape}, expected 2-D")
    return ExrImage(channels, metadata)


#: The largest magnitude :func:`read_map` accepts: sums of squares over a 16384² map stay
#: finite in float32 (a kilometre in nanometres; no displacement map comes near).
MAP_LIMIT = 1e12


def read_map(path: str | os.PathLike, channel: str | None = None) -> np.ndarray:
    """Read one single-channel map ``(H, W)`` float32: an EXR channel, a ``.npy`` array, or a
    greyscale PNG/JPEG/TIFF in [0, 1].

    Args:
        path: the file.
        channel: which EXR channel; required when the EXR file has several.

    Raises:
        FileNotFoundError: no such file.
        TypeError: a ``.npy`` array that is not floating point.
        ValueError: several channels and none named, an unknown channel, not 2-D, NaN or
            infinite values or values beyond ±:data:`MAP_LIMIT`, or a bad file; the message
            names the file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        data = _read_npy(path)
    elif suffix != ".exr":
        data = read_image(path, grey=True)
    else:
        image = read_exr(path)
        names = list(image.channels)
        if channel is None:
            if len(names) != 1:
                raise ValueError(
                    f"{path} has {len(names)} channels {names}; expected one, or name the channel"
                )
            channel = names[0]
        if channel not in image.channels:
            raise ValueError(f"{path} has no channel {channel!r}; it has {names}")
        data = image.channels[channel]
    if data.size == 0:
        raise ValueError(f"{path} holds an empty map of shape {data.shape}")
    bad = int(np.count_nonzero(~np.isfinite(data)))
    if bad:
        raise ValueError(f"{path} holds {bad} NaN or infinite value(s); a map must be finite")
    largest = float(np.max(np.abs(data)))
    if largest > MAP_LIMIT:
        raise ValueError(
            f"{path} holds values up to {largest:.3g}; a map must lie within ±{MAP_LIMIT:g} "
            "(float32 statistics of larger values overflow)"
        )
    return data


def map_shape(path: str | os.PathLike) -> tuple[int, int]:
    """The ``(H, W)`` of the map :func:`read_map` would return, from the file's header only (so
    a batch can check its maps before reading any).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable map file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        shape = _open_npy(path).shape
    elif suffix == ".exr":
        path = input_file(path, "EXR file")
        try:
            (x0, y0), (x1, y1) = OpenEXR.File(str(path), header_only=True).header()["dataWindow"]
        except Exception as err:  # the bindings raise bare RuntimeError/IOError for bad files
            raise ValueError(
                f"{path} is not a readable OpenEXR file (corrupt or truncated?): {err}"
            ) from err
        shape = (int(y1) - int(y0) + 1, int(x1) - int(x0) + 1)
    else:
        shape = image_size(path)
    if len(shape) != 2:
        raise ValueError(f"{path} must hold a 2-D map, got shape {shape}")
    return int(shape[0]), int(shape[1])


def _open_npy(path: Path) -> np.ndarray:
    """A ``.npy`` file memory-mapped: a header declaring more data than the file holds fails
    here, before anything is allocated."""
    path = input_file(path, ".npy file")
    try:
        return np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as err:  # numpy's header parser raises many types for a bad header
        raise ValueError(
            f"{path} is not a readable .npy array (corrupt header or truncated?): "
            f"{type(err).__name__}: {err}"
        ) from err


def _read_npy(path: Path) -> np.ndarray:
    mapped = _open_npy(path)
    if mapped.ndim != 2:
        raise ValueError(f"{path} must hold a 2-D map, got shape {mapped.shape}")
    if mapped.dtype.kind != "f":
        raise TypeError(f"{path} must hold a floating-point map, got {mapped.dtype}")
    try:
        return np.array(mapped, dtype=np.float32)
    except MemoryError as err:
        raise ValueError(f"{path} holds a map of {mapped.shape}, more than memory holds") from err
