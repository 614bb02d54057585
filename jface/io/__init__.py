"""Files in and out: OpenEXR maps, PNG images, meshes and landmarks, arrays + metadata. The only
place that touches disk (besides the command line).

Every writer goes through one atomic writer (:func:`atomic_path`); inside a :func:`session` (one
per ``jface`` command) it also refuses to overwrite the command's inputs and stages the outputs
until the command succeeds (see :mod:`jface.io._files`).
"""

from jface.io._arrays import load_arrays, save_arrays
from jface.io._exr import ExrImage, exr_rows, map_shape, read_exr, read_map, write_exr
from jface.io._figures import write_figure
from jface.io._files import (
    atomic_path,
    check_output,
    commit,
    content_key,
    discard,
    own_outputs,
    session,
    session_outputs,
    write_json,
)
from jface.io._images import read_image, write_png
from jface.io._json import read_json
from jface.io._meshes import MeshData, read_landmarks, read_mesh, write_landmarks, write_mesh
from jface.io._provenance import provenance

__all__ = [
    "ExrImage",
    "MeshData",
    "atomic_path",
    "check_output",
    "commit",
    "content_key",
    "discard",
    "exr_rows",
    "load_arrays",
    "map_shape",
    "own_outputs",
    "provenance",
    "read_exr",
    "read_image",
    "read_json",
    "read_landmarks",
    "read_map",
    "read_mesh",
    "save_arrays",
    "session",
    "session_outputs",
    "write_exr",
    "write_figure",
    "write_json",
    "write_landmarks",
    "write_mesh",
    "write_png",
]
