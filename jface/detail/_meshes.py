"""Mesh-level applications of detail statistics (Golovinskiy et al. 2006, §3.2–§3.4):
interpolating faces, adding detail to a low-resolution mesh, and aging / de-aging with the
coarse change taken from the remeshing hierarchy.

Every face is remeshed onto the same marker template, so all faces share one topology, one
rectangle layout and one hierarchy of levels: vertices, offsets and pixels correspond one to one,
and faces combine by plain arithmetic on those arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array, Float, PRNGKeyArray

from jface import _checks, mesh
from jface.detail._applications import interpolate
from jface.detail._stats import DetailStats, check_weights
from jface.detail._synthesis import synthesize


class Face(eqx.Module):
    """A remeshed face as the applications combine it: its hierarchical decomposition (marker
    mesh + per-level normal offsets), its smooth base mesh and its displacement image.

    Build one from :func:`jface.mesh.remesh` with :meth:`from_remeshed` (the applications accept
    a :class:`jface.mesh.Remeshed` directly too).

    Attributes:
        markers: ``(21, 3)`` marker-mesh vertices (level 0).
        offsets: one ``(V_k,)`` offset array per projected level (levels 1..P).
        base: the smooth base mesh with its rectangle (uv) coordinates.
        image: ``(H, W)`` displacement image over the rectangle (the finest level).
        schedule: ``(n_linear, n_loop, n_smooth)`` of the template hierarchy (static).
    """

    markers: Float[Array, "n 3"]
    offsets: tuple[Float[Array, " _"], ...]
    base: mesh.Mesh
    image: Float[Array, "h w"]
    schedule: tuple[int, int, int] = eqx.field(static=True)

    @classmethod
    def from_remeshed(cls, remeshed: mesh.Remeshed) -> Face:
        """The parts of a :func:`jface.mesh.remesh` result that the applications use."""
        return cls(
            remeshed.markers, remeshed.offsets, remeshed.base, remeshed.image, remeshed.schedule
        )

    def hierarchy(self) -> mesh.Hierarchy:
        """The template levels this face lives on."""
        return mesh.template_hierarchy(None, *self.schedule)

    @property
    def n_levels(self) -> int:
        """Levels of the decomposition: marker mesh, P offset levels, displacement image."""
        return len(self.offsets) + 2

    @property
    def control(self) -> Float[Array, "c 3"]:
        """The last projected level, rebuilt from the marker mesh and the offsets."""
        return mesh.reconstruct(self.markers, self.offsets, self.hierarchy())

    def detailed(self, *, extra_subdivisions: int = 0, scale: float = 1.0) -> mesh.Mesh:
        """The detailed face: the displacement image applied to the base mesh
        (:func:`jface.mesh.displace`)."""
        return mesh.displace(
            self.base, self.image, extra_subdivisions=extra_subdivisions, scale=scale
        )


def as_face(face: Any, name: str = "face") -> Face:
    """``face`` as a :class:`Face` (from a :class:`jface.mesh.Remeshed`), or TypeError."""
    if isinstance(face, Face):
        return face
    if isinstance(face, mesh.Remeshed):
        return Face.from_remeshed(face)
    raise TypeError(f"{name} must be a jface.detail.Face or jface.mesh.Remeshed, got {type(face)}")


def check_faces(faces: Any, name: str = "faces") -> list[Face]:
    """Validate a non-empty list of faces on one template, one schedule and one image size."""
    if isinstance(faces, (Face, mesh.Remeshed)) or not isinstance(faces, Sequence):
        raise TypeError(f"{name} must be a sequence of faces, got {type(faces).__name__}")
    if not faces:
        raise ValueError(f"{name} must hold at least one face, got an empty group")
    faces = [as_face(f, f"{name}[{i}]") for i, f in enumerate(faces)]
    first = faces[0]
    for i, face in enumerate(faces[1:], start=1):
        layout = (face.schedule, tuple(face.image.shape), face.base.vertices.shape[0])
        expected = (first.schedule, tuple(first.image.shape), first.base.vertices.shape[0])
        if layout != expected:
            raise ValueError(
                f"{name}[{i}] has (schedule, image shape, base vertices) = {layout}, but "
                f"{name}[0] has {expected}: remesh every face with the same settings"
            )
    return faces


def _base_of(markers: Array, offsets: tuple[Array, ...], hierarchy: mesh.Hierarchy) -> mesh.Mesh:
    """The smooth base mesh of a hierarchical decomposition (what remeshing builds)."""
    position = mesh.reconstruct(markers, offsets, hierarchy)
    for level in hierarchy.levels[hierarchy.n_projected + 1 :]:
        position = level.operator(position)
    base = hierarchy.base
    return mesh.Mesh(position, jnp.asarray(base.faces), base.uv)


class FaceInterpolation(NamedTuple):
    """Interpolated faces (§3.2): both share the interpolated base mesh and hierarchy; the
    ``average`` carries the plain average of the displacement images, ``coerced`` that average
    coerced to the ``target`` (interpolated) statistics."""

    average: Face
    coerced: Face
    target: DetailStats


def interpolate_faces(
    key: PRNGKeyArray, faces: Sequence[Any], stats: DetailStats, weights: ArrayLike, **options
) -> FaceInterpolation:
    """Interpolate N faces without blurring their detail (Golovinskiy et al. 2006, §3.2).

    The base meshes, marker meshes and level offsets are averaged vertex by vertex with the
    weights (all faces share one topology and layout); the displacement images are averaged and
    the average coerced to the weighted mean of the faces' statistics.

    Args:
        key: random key (synthesis noise).
        faces: N faces (:class:`Face` or :class:`jface.mesh.Remeshed`), remeshed alike.
        stats: their statistics stacked ``(N, bands, grid, grid)``
            (e.g. ``analyze_batch(jnp.stack([f.image for f in faces]))``).
        weights: ``(N,)`` non-negative weights summing to one.
        **options: passed to :func:`jface.detail.synthesize`.

    Raises:
        TypeError, ValueError: no faces, faces remeshed differently, statistics of another
            number of faces or image size, bad weights.
    """
    faces = check_faces(faces)
    weights = check_weights(weights, len(faces), jnp.float32)
    images = jnp.stack([f.image.astype(jnp.float32) for f in faces])
    if tuple(stats.image_shape) != tuple(images.shape[1:]):
        raise ValueError(
            f"stats describe images of {tuple(stats.image_shape)}, but the faces' displacement "
            f"images are {tuple(images.shape[1:])}"
        )
    images_result = interpolate(key, images, stats, weights, **options)

    def mix(arrays):
        return jnp.einsum("n,n...->...", weights, jnp.stack([jnp.asarray(a) for a in arrays]))

    first = faces[0]
    base = mesh.Mesh(mix([f.base.vertices for f in faces]), first.base.faces, first.base.uv)
    markers = mix([f.markers for f in faces])
    offsets = tuple(mix(level) for level in zip(*(f.offsets for f in faces), strict=True))
    average = Face(markers, offsets, base, images_result.average, first.schedule)
    coerced = Face(markers, offsets, base, images_result.coerced, first.schedule)
    return FaceInterpolation(average, coerced, images_result.target)


def add_detail(key: PRNGKeyArray, face: Any, target: DetailStats, **options) -> Face:
    """Add plausible detail to a low-resolution face (Golovinskiy et al. 2006, §3.3).

    The face's displacement image (remeshed from the low-resolution scan) is coerced to the
    target statistics — one high-resolution face's, or a group mean (:func:`mean_stats`) — and
    kept on the face's own base mesh; :meth:`Face.detailed` adds it back to the mesh.

    Args:
        key: random key (synthesis noise: it is where detail the scan lacks grows from).
        face: the low-resolution face (:class:`Face` or :class:`jface.mesh.Remeshed`).
        target: statistics of one image of the face's image size.
        **options: passed to :func:`jface.detail.synthesize`.

    Returns:
        The face with the coerced displacement image.
    """
    face = as_face(face)
    image = synthesize(key, face.image, target, **options)
    return Face(face.markers, face.offsets, face.base, image, face.schedule)


def swap_levels(coarse: Any, fine: Any, n_coarse: int) -> Face:
    """Mix two faces level by level: the coarsest ``n_coarse`` levels of the decomposition from
    ``coarse``, the rest from ``fine`` (§3.4).

    The levels are, in order: the marker mesh (0), the P projected offset levels (1..P) and the
    displacement image (P+1). ``n_coarse = 0`` gives ``fine``, ``n_coarse = P + 2`` gives
    ``coarse``; aging keeps the individual's marker mesh and low levels (``coarse`` = the young
    face) and takes the higher levels from the old face. The base mesh is rebuilt from the mixed
    hierarchy.

    Raises:
        TypeError, ValueError: not faces, faces remeshed differently, ``n_coarse`` out of range.
    """
    coarse, fine = check_faces([coarse, fine], "(coarse, fine)")
    n_coarse = _checks.integer(n_coarse, "n_coarse", low=0, high=coarse.n_levels)
    if n_coarse == 0:
        return fine
    n_offsets = min(n_coarse - 1, len(coarse.offsets))
    offsets = (*coarse.offsets[:n_offsets], *fine.offsets[n_offsets:])
    image = coarse.image if n_coarse == coarse.n_levels else fine.image
    base = _base_of(coarse.markers, offsets, coarse.hierarchy())
    return Face(coarse.markers, offsets, base, image, coarse.schedule)


def age(
    key: PRNGKeyArray, young: Any, old: Any, target: DetailStats, *, n_coarse: int = 3, **options
) -> Face:
    """Age a face (Golovinskiy et al. 2006, §3.4); with the roles swapped, de-age it.

    The young face's displacement image is coerced to the ``target`` statistics (the old face's,
    or an old group's mean): its own wrinkles and pores are sharpened and elongated where the old
    statistics ask for it. The coarse change comes from the hierarchy: the marker mesh and the
    lowest ``n_coarse - 1`` offset levels from the young face (individual, unchanged by age),
    the higher levels from the old face (:func:`swap_levels`).

    Args:
        key: random key (synthesis noise).
        young: the face to change (:class:`Face` or :class:`jface.mesh.Remeshed`).
        old: the face whose finer geometry levels it takes.
        target: statistics to coerce the young detail to (one image of the young image's size).
        n_coarse: levels kept from ``young``, 1..P+1 (marker mesh = 1; the paper's schedule has
            P = 4; the default keeps the marker mesh and two offset levels).
        **options: passed to :func:`jface.detail.synthesize`.

    Returns:
        The aged face: mixed hierarchy and base mesh, coerced displacement image.
    """
    young, old = check_faces([young, old], "(young, old)")
    n_coarse = _checks.integer(n_coarse, "n_coarse", low=1, high=young.n_levels - 1)
    image = synthesize(key, young.image, target, **options)
    mixed = swap_levels(young, old, n_coarse)
    return Face(mixed.markers, mixed.offsets, mixed.base, image, mixed.schedule)
