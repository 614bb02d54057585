"""Face image synthesis and editing of Mohammed, Prince & Kautz 2009 (*Visio-lization*).

* Patch libraries per grid position (§2.2): :func:`build_library`, :class:`PatchLibrary`.
* Non-stationary quilting conditioned on a global target image (§2.2, §4), one jitted scan per
  face, ``vmap`` over keys: :func:`quilt`, :class:`QuiltResult`.
* Poisson image editing (Pérez et al. 2003) with an exact DST-I solver: :func:`poisson_solve`,
  :func:`poisson_blend`, :func:`gradients`, :func:`divergence`.
* Editing (§6): :func:`inpaint`, :func:`guided_edit`.
* With the global factor models (§4, §6.1, §6.3): :func:`synthesize` (target sampled from a
  factor analyser or mixture, patches from the sampled component's images),
  :func:`assign_components`, :func:`inpaint_hypotheses` (targets from the posterior of the
  observed pixels), :func:`restyle` (expression change with the bilinear model).
* Analysis (§5): :func:`nearest_training`, :func:`novelty`, :func:`training_nn_distances`,
  :func:`target_distance`, :func:`distinct_sources`, :func:`source_map`.
"""

from jface.faces._editing import (
    distinct_sources,
    guided_edit,
    inpaint,
    nearest_training,
    novelty,
    source_map,
    target_distance,
    training_nn_distances,
)
from jface.faces._global import assign_components, inpaint_hypotheses, restyle, synthesize
from jface.faces._patches import Geometry, PatchLibrary, build_library, make_geometry
from jface.faces._poisson import divergence, gradients, poisson_blend, poisson_solve
from jface.faces._quilting import QuiltResult, quilt

__all__ = [
    "Geometry",
    "PatchLibrary",
    "QuiltResult",
    "assign_components",
    "build_library",
    "distinct_sources",
    "divergence",
    "gradients",
    "guided_edit",
    "inpaint",
    "inpaint_hypotheses",
    "make_geometry",
    "nearest_training",
    "novelty",
    "poisson_blend",
    "poisson_solve",
    "quilt",
    "restyle",
    "source_map",
    "synthesize",
    "target_distance",
    "training_nn_distances",
]
