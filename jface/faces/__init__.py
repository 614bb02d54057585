"""Global face models of Mohammed, Prince & Kautz 2009 (*Visio-lization*), §3, §4, §6.1, §6.3.

* :class:`FactorAnalyser` — ``x = μ + F h + ε`` (Eq. 1–3), fitted by EM
  (:func:`fit_factor_analyser`), also from images with missing pixels.
* :class:`MixtureOfFactorAnalysers` — ``K`` of them (§4, :func:`fit_mixture`).
* :class:`BilinearModel` — the asymmetric bilinear style model (Eq. 7–8, :func:`fit_bilinear`,
  :func:`transfer`), a factor analyser over stacked styles.

Per image (vmap for batches): :func:`log_likelihood`, :func:`posterior` (exact, or the paper's
ML form; from observed pixels only with a mask), :func:`responsibilities`,
:func:`sample_posterior`, :func:`reconstruct`. Generation: :func:`sample`. Files:
:func:`save_model`, :func:`load_model`.

Synthesis and editing (§2, §4, §5, §6):

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
* Registration (§2.2, §4): :func:`align` (affine registration of a face to a template, from
  landmarks in closed form or by intensity, coarse to fine), :class:`Alignment`,
  :func:`fit_affine`, :func:`warp`, :func:`invert_affine`, and :func:`unwarp` (a synthesised
  face carried into the frame of a randomly chosen training face).
* Analysis (§5): :func:`nearest_training`, :func:`novelty`, :func:`training_nn_distances`,
  :func:`target_distance`, :func:`distinct_sources`, :func:`source_map`.
"""

from jface.faces._align import Alignment, align, fit_affine, invert_affine, unwarp, warp
from jface.faces._api import (
    fit_bilinear,
    fit_factor_analyser,
    fit_mixture,
    get_component,
    log_likelihood,
    posterior,
    reconstruct,
    responsibilities,
    sample,
    sample_posterior,
    style,
    transfer,
)
from jface.faces._bilinear import BilinearModel
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
from jface.faces._em import EMResult
from jface.faces._fa import FactorAnalyser, Posterior
from jface.faces._global import assign_components, inpaint_hypotheses, restyle, synthesize
from jface.faces._mofa import MixtureOfFactorAnalysers, MixturePosterior
from jface.faces._patches import Geometry, PatchLibrary, build_library, make_geometry
from jface.faces._poisson import divergence, gradients, poisson_blend, poisson_solve
from jface.faces._quilting import QuiltResult, quilt
from jface.faces._store import SavedModel, load_model, save_model

__all__ = [
    "Alignment",
    "BilinearModel",
    "EMResult",
    "FactorAnalyser",
    "Geometry",
    "MixtureOfFactorAnalysers",
    "MixturePosterior",
    "PatchLibrary",
    "Posterior",
    "QuiltResult",
    "SavedModel",
    "align",
    "assign_components",
    "build_library",
    "distinct_sources",
    "divergence",
    "fit_affine",
    "fit_bilinear",
    "fit_factor_analyser",
    "fit_mixture",
    "get_component",
    "gradients",
    "guided_edit",
    "inpaint",
    "inpaint_hypotheses",
    "invert_affine",
    "load_model",
    "log_likelihood",
    "make_geometry",
    "nearest_training",
    "novelty",
    "poisson_blend",
    "poisson_solve",
    "posterior",
    "quilt",
    "reconstruct",
    "responsibilities",
    "restyle",
    "sample",
    "sample_posterior",
    "save_model",
    "source_map",
    "style",
    "synthesize",
    "target_distance",
    "training_nn_distances",
    "transfer",
    "unwarp",
    "warp",
]
