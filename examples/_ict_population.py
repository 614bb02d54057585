"""A population of remeshed faces for the Golovinskiy et al. 2006 application examples.

Shapes: ICT-FaceKit identities (real light-stage face shapes; MIT licence, "ICT-FaceKit, USC
Institute for Creative Technologies"), from the subset shipped with jface
(:func:`jface.data.ict_face_model`, 10 identity modes) or the full face area given with ``--ict``
(``ict_face_area.npz``, 100 modes), each a random mix of the identity modes, remeshed onto the
21-point marker template with :func:`jface.mesh.remesh` (marker mesh + offset levels + base mesh
+ displacement image).

Fine detail: the ICT meshes are too coarse (3 mm edges) to carry pores or wrinkles, and the
paper's scans are not public, so each face's displacement image gets fine detail measured from
real textures (scikit-image, CC0): the high frequencies of a randomly shifted crop of
``gravel`` (pores) and, for older faces, of ``brick`` (long, oriented creases) — young faces
(20–35) have faint pores only, old faces (60–80) stronger pores plus creases whose amplitude grows
with age. Amplitudes are in cm, like the ICT meshes (0.05–0.3 mm detail).
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
from scipy import ndimage
from skimage import data

from jface import data as jface_data
from jface import detail, io, mesh, raster, tiles


def _texture_detail(rng: np.random.Generator, texture: np.ndarray, size: int) -> np.ndarray:
    """High frequencies (wavelengths below ~size/16) of a randomly shifted real texture, unit
    standard deviation."""
    shift = rng.integers(0, texture.shape[0], size=2)
    image = tiles.mirror_tile(np.roll(texture, shift, axis=(0, 1)), size).astype(np.float64)
    image = image - ndimage.gaussian_filter(image, size / 64, mode="wrap")
    return (image / image.std()).astype(np.float32)


def population(
    n_young: int,
    n_old: int,
    *,
    image_size: int = 512,
    schedule=(2, 2, 3),
    seed: int = 0,
    ict: str | None = None,
) -> tuple[list[detail.Face], list[dict]]:
    """Remeshed ICT identities with texture detail; returns the faces and their records."""
    ict = jface_data.ict_face_model() if ict is None else dict(np.load(ict))
    neutral, triangles = ict["vertices"].astype(np.float64), ict["faces"]
    modes = ict["identity_deltas"].astype(np.float64)
    gravel = data.gravel().astype(np.float64) / 255.0
    brick = data.brick().astype(np.float64) / 255.0
    rng = np.random.default_rng(seed)
    faces, records = [], []
    for i in range(n_young + n_old):
        old = i >= n_young
        person = neutral + np.tensordot(rng.normal(size=len(modes)), modes, axes=1)
        remeshed = mesh.remesh(
            person,
            triangles,
            mesh.ict_landmarks(person),
            image_size=image_size,
            n_linear=schedule[0],
            n_loop=schedule[1],
            n_smooth=schedule[2],
        )
        age = int(rng.integers(60, 81) if old else rng.integers(20, 36))
        pores = (0.012 if old else 0.006) * rng.uniform(0.8, 1.2)
        fine = pores * _texture_detail(rng, gravel, image_size)
        if old:
            fine += 0.00025 * age * _texture_detail(rng, brick, image_size)
        face = detail.Face.from_remeshed(remeshed)
        faces.append(
            detail.Face(
                face.markers, face.offsets, face.base, face.image + jnp.asarray(fine), face.schedule
            )
        )
        records.append({"id": f"ict{i:02d}", "age": age, "group": "old" if old else "young"})
    return faces, records


def front_view(face: detail.Face, size: int = 384, frame=None) -> np.ndarray:
    """The detailed face (displacement applied to the base mesh), rendered from the front."""
    shown = face.detailed(extra_subdivisions=0)
    vertices, triangles = np.asarray(shown.vertices), np.asarray(shown.faces)
    center, extent = frame or raster.framing(vertices)
    return raster.render(
        vertices, triangles, size, center=center, extent=extent, light=(-0.4, 0.5, 0.8)
    )


def write_detailed(out: Path, name: str, face: detail.Face, meta: dict, what: str) -> None:
    """The detailed face as ``name.obj`` (with uv) and its displacement image as EXR."""
    detailed = face.detailed()
    io.write_mesh(
        out / f"{name}.obj",
        np.asarray(detailed.vertices),
        np.asarray(detailed.faces),
        uv=np.asarray(detailed.uv),
        comment=f"jface {meta['jface_version']} {what}",
    )
    io.write_exr(out / f"{name}_displacement.exr", np.asarray(face.image), metadata=meta)
