"""PNG/JPEG images: read as float arrays, write figures with provenance text chunks."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, PngImagePlugin

from jface.io._files import atomic_path, check_output, input_file


def write_png(
    path: str | os.PathLike,
    image: Any,
    *,
    metadata: dict[str, Any] | None = None,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write an (H, W) grey or (H, W, 3|4) colour image to PNG (a path ending in ".png"),
    atomically.

    Float images are taken to lie in [0, 1] (clipped); uint8 images are written as they are.
    ``metadata`` goes into a "jface" text chunk as JSON.
    """
    path = check_output(path, (".png",), protect=protect)
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (3, 4)) or arr.size == 0:
        raise ValueError(f"image must be (H, W) or (H, W, 3|4), got shape {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)):
            raise ValueError("image must be finite to be written as PNG")
        arr = np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    elif arr.dtype != np.uint8:
        raise TypeError(f"image must be float in [0, 1] or uint8, got {arr.dtype}")
    info = PngImagePlugin.PngInfo()
    if metadata:
        info.add_text("jface", json.dumps(metadata))
    with atomic_path(path, protect=protect) as tmp:
        Image.fromarray(np.ascontiguousarray(arr)).save(tmp, format="PNG", pnginfo=info)
    return path


def read_image(path: str | os.PathLike, *, grey: bool = False) -> np.ndarray:
    """Read a PNG/JPEG/TIFF image as float32 in [0, 1]: (H, W) grey or (H, W, 3) colour.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable image (corrupt or truncated), or one that declares more
            pixels than Pillow's decompression-bomb limit (``PIL.Image.MAX_IMAGE_PIXELS`` × 2).
    """
    path = input_file(path, "image file")
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode in ("I;16", "I;16B", "I"):  # 16-bit grey
                return np.asarray(img, dtype=np.float32) / 65535.0
            if img.mode == "F":
                return np.asarray(img, dtype=np.float32)
            mode = "L" if grey or (img.mode in ("L", "LA", "1", "P") and _is_grey(img)) else "RGB"
            return np.asarray(img.convert(mode), dtype=np.float32) / 255.0
    except Image.DecompressionBombError as err:
        raise ValueError(f"{path} declares too many pixels to read safely: {err}") from err
    except MemoryError as err:
        raise ValueError(f"{path} declares an image larger than memory holds") from err
    except Exception as err:  # Pillow's decoders raise many types for bad files
        raise ValueError(
            f"{path} is not a readable image (corrupt or truncated?): {type(err).__name__}: {err}"
        ) from err


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(H, W)`` of an image file, from its header.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a readable image.
    """
    path = input_file(path, "image file")
    try:
        with Image.open(path) as img:
            return img.height, img.width
    except Exception as err:  # Pillow raises many types for bad files
        raise ValueError(
            f"{path} is not a readable image (corrupt or truncated?): {type(err).__name__}: {err}"
        ) from err


def _is_grey(img: Image.Image) -> bool:
    if img.mode != "P":
        return True
    rgb = np.asarray(img.convert("RGB"))
    return bool(np.all(rgb[..., 0] == rgb[..., 1]) and np.all(rgb[..., 1] == rgb[..., 2]))
