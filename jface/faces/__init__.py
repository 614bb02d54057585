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
"""

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
from jface.faces._em import EMResult
from jface.faces._fa import FactorAnalyser, Posterior
from jface.faces._mofa import MixtureOfFactorAnalysers, MixturePosterior
from jface.faces._store import load_model, save_model

__all__ = [
    "BilinearModel",
    "EMResult",
    "FactorAnalyser",
    "MixtureOfFactorAnalysers",
    "MixturePosterior",
    "Posterior",
    "fit_bilinear",
    "fit_factor_analyser",
    "fit_mixture",
    "get_component",
    "load_model",
    "log_likelihood",
    "posterior",
    "reconstruct",
    "responsibilities",
    "sample",
    "sample_posterior",
    "save_model",
    "style",
    "transfer",
]
