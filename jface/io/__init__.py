"""Files in and out: OpenEXR maps, PNG images, meshes and landmarks, arrays + metadata. The only
place that touches disk (besides the command line)."""

from jface.io._arrays import load_arrays, save_arrays
from jface.io._exr import ExrImage, exr_rows, read_exr, read_map, write_exr
from jface.io._files import atomic_path, write_json
from jface.io._images import read_image, write_png
from jface.io._json import read_json
from jface.io._meshes import MeshData, read_landmarks, read_mesh, write_landmarks, write_mesh
from jface.io._provenance import provenance

__all__ = [
    "ExrImage",
    "MeshData",
    "atomic_path",
    "exr_rows",
    "load_arrays",
    "provenance",
    "read_exr",
    "read_image",
    "read_json",
    "read_landmarks",
    "read_map",
    "read_mesh",
    "save_arrays",
    "write_exr",
    "write_json",
    "write_landmarks",
    "write_mesh",
    "write_png",
]
