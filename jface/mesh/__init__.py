"""Remeshing face scans into a base mesh plus a displacement image, and back
(Golovinskiy et al. 2006, §2.2).

Typical use::

    from jface import io, mesh

    scan = io.read_mesh("scan.obj")
    marks = io.read_landmarks("scan_landmarks.json")     # 21 names → vertex ids or points
    result = mesh.remesh(scan.vertices, scan.faces, marks, image_size=1024)
    result.image                                          # (1024, 1024) displacement image
    detailed = mesh.displace(result.base, result.image, extra_subdivisions=1)
"""

from jface.mesh._geometry import (
    ImageSampler,
    image_sampler,
    mean_edge_length,
    sample_image,
    vertex_normals,
)
from jface.mesh._landmarks import (
    FaceModel,
    Fit,
    Landmarks,
    NoFaceError,
    Pose,
    Samples,
    face_model,
    find_landmarks,
    fit_samples,
    sample_surface,
)
from jface.mesh._raycast import Hits, ScanIndex, cast, exterior, has_embree
from jface.mesh._remesh import Mesh, Remeshed, displace, reconstruct, remesh
from jface.mesh._subdivision import (
    Hierarchy,
    Level,
    SubdivisionOperator,
    subdivide,
    subdivide_topology,
    template_hierarchy,
)
from jface.mesh._synthetic import (
    DetailField,
    SyntheticScan,
    canonical_face,
    detail_field,
    known_displacement,
    smooth_offset,
    synthetic_scan,
)
from jface.mesh._template import (
    ICT_IDS,
    LANDMARK_NAMES,
    MEDIAPIPE_IDS,
    MarkerTemplate,
    ict_landmarks,
    landmark_points,
    marker_template,
    mediapipe_landmarks,
)

__all__ = [
    "ICT_IDS",
    "LANDMARK_NAMES",
    "MEDIAPIPE_IDS",
    "DetailField",
    "FaceModel",
    "Fit",
    "Hierarchy",
    "Hits",
    "ImageSampler",
    "Landmarks",
    "Level",
    "MarkerTemplate",
    "Mesh",
    "NoFaceError",
    "Pose",
    "Remeshed",
    "Samples",
    "ScanIndex",
    "SubdivisionOperator",
    "SyntheticScan",
    "canonical_face",
    "cast",
    "detail_field",
    "displace",
    "exterior",
    "face_model",
    "find_landmarks",
    "fit_samples",
    "has_embree",
    "ict_landmarks",
    "image_sampler",
    "known_displacement",
    "landmark_points",
    "marker_template",
    "mean_edge_length",
    "mediapipe_landmarks",
    "reconstruct",
    "remesh",
    "sample_image",
    "sample_surface",
    "smooth_offset",
    "subdivide",
    "subdivide_topology",
    "synthetic_scan",
    "template_hierarchy",
    "vertex_normals",
]
