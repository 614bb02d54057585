"""Files in and out: OpenEXR maps, PNG images, arrays + metadata. The only place that touches disk
(besides the command line)."""

from jface.io._arrays import load_arrays, save_arrays
from jface.io._exr import ExrImage, read_exr, read_map, write_exr
from jface.io._files import atomic_path
from jface.io._images import read_image, write_png
from jface.io._json import read_json, write_json
from jface.io._provenance import provenance

__all__ = [
    "ExrImage",
    "atomic_path",
    "load_arrays",
    "provenance",
    "read_exr",
    "read_image",
    "read_json",
    "read_map",
    "save_arrays",
    "write_exr",
    "write_json",
    "write_png",
]
