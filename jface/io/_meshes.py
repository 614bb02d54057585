"""Triangle meshes (OBJ/PLY) and landmark files (JSON/CSV).

Meshes are read through trimesh, which knows many formats and their quirks; they are written by
jface itself (plain OBJ with one ``vt`` per vertex, binary little-endian PLY with ``s, t``
vertex properties) so the UVs of a remeshed face survive the round trip exactly.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from jface.io._files import atomic_path, check_output, input_file, write_json

#: A landmark is a vertex id of the scan or a 3-D point.
Landmark = int | tuple[float, float, float]


class MeshData(NamedTuple):
    """A triangle mesh as numpy arrays.

    Attributes:
        vertices: ``(V, 3)`` float64 positions.
        faces: ``(F, 3)`` int64 vertex indices, counter-clockwise seen from outside.
        uv: ``(V, 2)`` float64 texture coordinates (one per vertex), or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None


def read_mesh(path: str | os.PathLike, *, merge: bool = True, uv_seams: bool = False) -> MeshData:
    """Read a triangle mesh (OBJ, PLY, STL, OFF, GLB, ...) through trimesh.

    Args:
        path: the mesh file.
        merge: merge vertices that share a position, texture and normal seams included (a scan
            split along its UV seams has cracks that rays slip through). UVs are kept only when
            every vertex then has exactly one.
        uv_seams: with ``merge``, keep vertices apart where their UVs differ, so a UV-mapped
            mesh keeps one UV per vertex (for texturing, radius maps, displacement by UV).

    Returns:
        :class:`MeshData` (quads and polygons are triangulated by trimesh).

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable, empty, a point cloud or a mesh without faces, faces that index
            missing vertices, or a vertex or uv that is NaN or infinite (anywhere in the file:
            dropping it would shift the ids of every vertex after it, which landmarks refer to).
    """
    import trimesh

    path = input_file(path, "mesh file")
    if path.suffix.lower() == ".obj":
        _check_obj_numbers(path)
    try:
        # unprocessed first: processing would drop non-finite vertices before they are seen
        loaded = trimesh.load(str(path), process=False)
        parts = list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene) else [loaded]
    except MemoryError as err:
        raise ValueError(f"{path} declares a mesh larger than memory holds (corrupt?)") from err
    except Exception as err:  # trimesh raises many types for bad files
        raise ValueError(f"{path} is not a readable mesh (corrupt or truncated?): {err}") from err
    for part in parts:
        part_vertices = np.asarray(getattr(part, "vertices", np.zeros((0, 3))), np.float64)
        if part_vertices.ndim == 2 and len(part_vertices):
            _check_finite(path, "vertex", part_vertices)
    meshes = [g for g in parts if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    for part in meshes:  # before processing, which indexes the vertices with them
        if part.faces.min() < 0 or part.faces.max() >= len(part.vertices):
            raise ValueError(f"{path}: faces index vertices outside [0, {len(part.vertices)})")
    if merge:
        try:
            for part in meshes:
                part.process()
                if not uv_seams:
                    _merge_seams(part)
        except Exception as err:  # trimesh's processing of a malformed mesh
            raise ValueError(f"{path} is not a valid mesh: {err}") from err
    if len(meshes) > 1:
        loaded = trimesh.util.concatenate(meshes)
    else:
        loaded = meshes[0] if meshes else (parts[0] if parts else None)
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if vertices.ndim != 2 or len(vertices) == 0:
        raise ValueError(f"{path} holds no vertices: the mesh is empty")
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or len(faces) == 0:
        raise ValueError(
            f"{path} has {len(vertices)} vertices but no faces (a point cloud?); "
            "a triangle mesh is needed"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{path}: faces index vertices outside [0, {len(vertices)})")
    uv = None
    visual = getattr(loaded, "visual", None)
    raw_uv = getattr(visual, "uv", None) if visual is not None else None
    if raw_uv is not None and len(raw_uv) == len(vertices):
        uv = np.asarray(raw_uv, dtype=np.float64)
        _check_finite(path, "uv", uv)
    return MeshData(vertices, faces, uv)


def _merge_seams(mesh) -> None:
    """Merge a processed trimesh's vertices that share a position across UV and normal seams
    (a scan split along its seams has cracks that rays slip through); drop the UVs if that
    merged different ones."""
    before = len(mesh.vertices)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    if len(mesh.vertices) != before:
        mesh.visual = type(mesh.visual)()


# A "v" or "vt" line with a number that may not be finite (nan, inf, or a huge exponent).
_SUSPECT_OBJ_LINE = re.compile(rb"^[ \t]*(vt?)[ \t][^\n]*(?:nan|inf|e\+?0*\d{3})", re.I | re.M)


def _check_obj_numbers(path: Path) -> None:
    """Reject an OBJ with a non-finite ``v``/``vt`` value anywhere: trimesh's OBJ reader drops
    vertices no face uses, so :func:`_check_finite` alone would not see them."""
    with open(path, "rb") as handle:
        text = handle.read()
    for match in _SUSPECT_OBJ_LINE.finditer(text):
        line = match.group(0).split(b"#")[0].split()
        try:
            values = [float(v) for v in line[1:]]
        except ValueError:
            continue  # not numbers at all: trimesh reports the file as unreadable
        if not all(math.isfinite(v) for v in values):
            number = text.count(b"\n", 0, match.start()) + 1
            shown = match.group(0).decode(errors="replace").strip()
            raise ValueError(
                f"{path}, line {number}: {shown!r} is not finite; a mesh must not hold NaN or "
                "infinite coordinates (fix or remove the vertex)"
            )


def _check_finite(path: Path, what: str, values: np.ndarray) -> None:
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if bad.size:
        raise ValueError(
            f"{path}: {bad.size} {what} value(s) are NaN or infinite (first: {what} {bad[0]}, "
            f"{values[bad[0]].tolist()}); a mesh must be finite"
        )


def write_mesh(
    path: str | os.PathLike,
    vertices: Any,
    faces: Any,
    *,
    uv: Any = None,
    comment: str = "",
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write a triangle mesh with optional per-vertex UVs as OBJ or PLY, atomically.

    Args:
        path: output file; the suffix (".obj" or ".ply") picks the format.
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        uv: ``(V, 2)`` texture coordinates or None (OBJ: ``vt`` lines, PLY: ``s, t``).
        comment: one line of provenance written as a comment in the header.
        protect: input files this output must not overwrite.

    Raises:
        ValueError: unknown suffix, bad shapes, indices out of range or non-finite values.
    """
    path = check_output(path, (".obj", ".ply"), protect=protect)
    suffix = path.suffix.lower()
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V > 0, got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.dtype.kind not in "iu":
        raise ValueError(f"faces must be integers of shape (F, 3), got {faces.shape} {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"faces index vertices outside [0, {len(vertices)})")
    if uv is not None:
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape != (len(vertices), 2):
            raise ValueError(f"uv must have shape ({len(vertices)}, 2), got {uv.shape}")
    for name, arr in (("vertices", vertices), ("uv", uv)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite to be written")
    comment = " ".join(str(comment).split())
    with atomic_path(path, protect=protect) as tmp:
        if suffix == ".obj":
            _write_obj(tmp, vertices, faces.astype(np.int64), uv, comment)
        else:
            _write_ply(tmp, vertices, faces.astype(np.int64), uv, comment)
    return path


def _write_obj(path: Path, vertices, faces, uv, comment: str) -> None:
    out = io.StringIO()
    if comment:
        out.write(f"# {comment}\n")
    np.savetxt(out, vertices, fmt="v %.8g %.8g %.8g")
    one = faces + 1
    if uv is not None:
        np.savetxt(out, uv, fmt="vt %.8g %.8g")
        np.savetxt(out, np.repeat(one, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
    else:
        np.savetxt(out, one, fmt="f %d %d %d")
    path.write_text(out.getvalue())


def _write_ply(path: Path, vertices, faces, uv, comment: str) -> None:
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if uv is not None:
        fields += [("s", "<f4"), ("t", "<f4")]
    vert = np.empty(len(vertices), dtype=fields)
    for i, axis in enumerate("xyz"):
        vert[axis] = vertices[:, i]
    if uv is not None:
        vert["s"], vert["t"] = uv[:, 0], uv[:, 1]
    face = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    face["n"], face["idx"] = 3, faces
    header = ["ply", "format binary_little_endian 1.0"]
    if comment:
        header.append(f"comment {comment}")
    header.append(f"element vertex {len(vertices)}")
    header += [f"property float {name}" for name, _ in fields]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    with open(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode())
        handle.write(vert.tobytes())
        handle.write(face.tobytes())


# --- landmarks ---------------------------------------------------------------------------------


def read_landmarks(
    path: str | os.PathLike,
    *,
    n_vertices: int | None = None,
    names: Sequence[str] | None = None,
) -> dict[str, Landmark]:
    """Read named landmarks from JSON or CSV.

    JSON: an object ``{"nose_tip": 1, "chin": [0.0, -9.4, 4.3], ...}`` (optionally nested under a
    "landmarks" key): each value is a vertex id of the scan (as :func:`read_mesh` numbers the
    vertices) or a 3-D point. CSV: rows
    ``name,id`` or ``name,x,y,z``; a first row whose second field is not a number is a header.

    Args:
        path: the file.
        n_vertices: the scan's vertex count, when known: ids must lie below it.
        names: the landmark names expected (e.g. :data:`jface.mesh.LANDMARK_NAMES`), when
            known: the file must name exactly these.

    Returns:
        name → vertex id (int) or point (3 floats), in file order.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable file, duplicate names, or a value that is neither an id (a
            non-negative integer below ``n_vertices``, or below 2³¹) nor a 3-D point of finite
            float32 coordinates, or (with ``names``) missing or unknown names; the message
            names the file and the landmark.
    """
    path = input_file(path, "landmark file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ValueError(f"{path} is not a UTF-8 text file: {err.reason}") from err
    is_csv = path.suffix.lower() == ".csv"
    pairs = _csv_pairs(path, text) if is_csv else _json_pairs(path, text)
    limit = (_ID_LIMIT, "") if n_vertices is None else (int(n_vertices), " (the scan's vertices)")
    seen: dict[str, Landmark] = {}
    duplicates = []
    for name, value in pairs:
        if name in seen:
            duplicates.append(name)
        seen[name] = _landmark_value(path, name, value, limit)
    if duplicates:
        raise ValueError(f"{path}: duplicate landmark name(s) {sorted(set(duplicates))}")
    if not seen:
        raise ValueError(f"{path} holds no landmarks")
    if names is not None:
        missing = [n for n in names if n not in seen]
        unknown = [n for n in seen if n not in names]
        if missing or unknown:
            raise ValueError(
                f"{path} must name exactly the {len(names)} landmarks {list(names)}; "
                f"missing {missing}, unknown {unknown}"
            )
    return seen


_ID_LIMIT = 2**31  # vertex ids are int32 on the device
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _json_pairs(path: Path, text: str) -> list[tuple[str, Any]]:
    def keep_pairs(pairs):
        return pairs

    try:
        data = json.loads(text, object_pairs_hook=keep_pairs)
    except ValueError as err:  # JSONDecodeError, or an integer of more digits than Python reads
        raise ValueError(f"{path} is not valid JSON: {err}") from err
    except RecursionError as err:
        raise ValueError(f"{path} nests JSON too deeply to read") from err
    # an object arrives as a list of (name, value) tuples; JSON arrays arrive as lists
    nested = isinstance(data, list) and len(data) == 1 and isinstance(data[0], tuple)
    if nested and data[0][0] == "landmarks":
        data = data[0][1]
    if not isinstance(data, list) or not all(isinstance(p, tuple) for p in data):
        raise ValueError(f"{path} must hold a JSON object of name → vertex id or [x, y, z]")
    return [(str(name), value) for name, value in data]


def _csv_pairs(path: Path, text: str) -> list[tuple[str, Any]]:
    try:
        rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    except csv.Error as err:
        raise ValueError(f"{path} is not a readable CSV file: {err}") from err
    rows = [[c.strip() for c in r] for r in rows if not r[0].lstrip().startswith("#")]
    if rows and len(rows[0]) > 1 and not _is_number(rows[0][1]):
        rows = rows[1:]
    pairs = []
    for i, row in enumerate(rows):
        if len(row) == 2:
            pairs.append((row[0], row[1]))
        elif len(row) == 4:
            pairs.append((row[0], row[1:]))
        else:
            raise ValueError(
                f"{path}, data row {i + 1}: expected 'name,id' or 'name,x,y,z', got {row}"
            )
    return pairs


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _landmark_value(path: Path, name: str, value: Any, limit: tuple[int, str]) -> Landmark:
    shown = repr(value) if len(repr(value)) <= 80 else repr(value)[:77] + "..."
    what = f"{path}: landmark {name!r} must be a vertex id or three coordinates, got {shown}"
    if isinstance(value, bool):
        raise ValueError(what)
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            raise ValueError(what) from None
        if not math.isfinite(number) or number != round(number):
            raise ValueError(what)
        value = int(number)
    if isinstance(value, int):
        if not 0 <= value < limit[0]:
            raise ValueError(
                f"{path}: landmark {name!r} is vertex id {shown}, outside [0, {limit[0]}){limit[1]}"
            )
        return value
    if isinstance(value, (list, tuple)) and len(value) == 3:
        if not all(isinstance(c, int | float | str) and not isinstance(c, bool) for c in value):
            raise ValueError(what)
        try:
            point = tuple(float(c) for c in value)
        except (ValueError, OverflowError):
            raise ValueError(what) from None
        if not all(math.isfinite(c) and abs(c) <= _FLOAT32_MAX for c in point):
            raise ValueError(
                f"{path}: landmark {name!r} must have finite float32 coordinates, got {shown}"
            )
        return point  # type: ignore[return-value]
    raise ValueError(what)


def write_landmarks(
    path: str | os.PathLike,
    landmarks: Any,
    *,
    names: Sequence[str] | None = None,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write name → vertex id or 3-D point as JSON (readable by :func:`read_landmarks`).

    Args:
        path: the JSON file.
        landmarks: a mapping name → vertex id or 3-D point, or an ``(n, 3)`` array of points
            named by ``names`` (e.g. ``jface.mesh.mediapipe_landmarks(vertices)``).
        names: the names of an array's rows; default for 21 rows: the template's
            (:data:`jface.mesh.LANDMARK_NAMES`).
        protect: inputs the file must not replace.

    Raises:
        ValueError: an array that is not ``(n, 3)`` or whose row count differs from the names'.
    """
    if not isinstance(landmarks, Mapping):
        points = np.asarray(landmarks)
        if names is None and points.shape[:1] == (21,):
            from jface.mesh._template import LANDMARK_NAMES as names  # the template's order
        if points.ndim != 2 or points.shape[1] != 3 or names is None or len(names) != len(points):
            raise ValueError(
                f"landmarks must be a mapping name → id or point, or an (n, 3) array with n "
                f"names (21 rows: the template's), got shape {points.shape} and "
                f"{'no' if names is None else len(names)} names"
            )
        landmarks = dict(zip(names, points, strict=True))
    data = {}
    for name, value in landmarks.items():
        arr = np.asarray(value)
        data[str(name)] = int(arr) if arr.ndim == 0 else [float(c) for c in arr.reshape(-1)]
    return write_json(path, data, protect=protect)
