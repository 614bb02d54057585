"""OpenEXR 3.x maps: float32/half, one or several channels, compression, provenance headers."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import OpenEXR

from jface.io._files import atomic_path
from jface.io._images import read_image

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
        path: output file.
        data: an (H, W) map (channel "Y"), an (H, W, 3|4) image (RGB[A]) or a dict of channels.
        half: store 16-bit half floats instead of float32.
        compression: "zstd" (default), "zip", "piz" or "none".
        metadata: provenance (jface version, seed, parameters, ...); values must be
            JSON-serialisable. Stored as header attributes prefixed with "jface:".
        protect: input files this output must not overwrite.

    Returns:
        The path written.
    """
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
    path = Path(path)
    with atomic_path(path, protect=protect) as tmp:
        OpenEXR.File(header, channels).write(str(tmp))
    return path


def read_exr(path: str | os.PathLike) -> ExrImage:
    """Read every channel and the jface metadata of an OpenEXR file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not a readable OpenEXR image (corrupt or truncated).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such EXR file: {path}")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
        header = exr.header()
        channels = {
            name: np.array(channel.pixels, dtype=np.float32)
            for name, channel in exr.channels().items()
        }
    except Exception as err:  # the bindings raise bare RuntimeError/IOError for bad files
        raise ValueError(
            f"{path} is not a readable OpenEXR file (corrupt or truncated?): {err}"
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


def read_map(path: str | os.PathLike, channel: str | None = None) -> np.ndarray:
    """Read one single-channel map ``(H, W)`` float32: an EXR channel, a ``.npy`` array, or a
    greyscale PNG/JPEG/TIFF in [0, 1].

    Args:
        path: the file.
        channel: which EXR channel; required when the EXR file has several.

    Raises:
        FileNotFoundError: no such file.
        ValueError: several channels and none named, an unknown channel, not 2-D, or a bad file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        if not path.is_file():
            raise FileNotFoundError(f"no such file: {path}")
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as err:
            raise ValueError(f"{path} is not a readable .npy array: {err}") from err
        if data.ndim != 2:
            raise ValueError(f"{path} must hold a 2-D map, got shape {data.shape}")
        if data.dtype.kind != "f":
            raise TypeError(f"{path} must hold a floating-point map, got {data.dtype}")
        return data.astype(np.float32)
    if suffix != ".exr":
        return read_image(path, grey=True)
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
    return image.channels[channel]
