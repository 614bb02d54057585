"""Asymmetric bilinear style model (Mohammed et al. 2009, §6.3, Eq. 7–8).

``x_ij = μ_j + F_j h_i + ε_ij``: individual ``i`` has one loading vector ``h_i`` shared by all its
styles ``j`` (e.g. neutral, smiling); each style has its own mean, factors and noise. Stacking the
``S`` styles of one individual into one vector of ``S·d`` pixels makes this exactly a factor
analyser with ``μ = [μ_1; …; μ_S]``, ``F = [F_1; …; F_S]``, ``Σ = diag(Σ_1, …, Σ_S)``; an
individual not seen in some style is a stacked vector with missing blocks. So the model *is* a
:class:`~jface.faces.FactorAnalyser` over ``(S, *shape)`` images, fitted by the missing-pixel EM,
and style transfer is its posterior from one block and its prediction of another.
"""

from __future__ import annotations

import equinox as eqx

from jface.faces._fa import FactorAnalyser


class BilinearModel(eqx.Module):
    """Asymmetric bilinear model: a factor analyser over the stacked styles.

    Attributes:
        stacked: the factor analyser of shape ``(S, *shape)``: its first axis is the style.
    """

    stacked: FactorAnalyser

    @property
    def n_styles(self) -> int:
        return self.stacked.shape[0]

    @property
    def shape(self) -> tuple[int, ...]:
        return self.stacked.shape[1:]

    @property
    def n_factors(self) -> int:
        return self.stacked.n_factors


def style_block(model: BilinearModel, j: int) -> FactorAnalyser:
    """The factor analyser ``(μ_j, F_j, Σ_j)`` of style ``j``."""
    fa = model.stacked
    d = fa.n_features // model.n_styles
    rows = slice(j * d, (j + 1) * d)
    return FactorAnalyser(
        fa.mean[..., rows], fa.factors[..., rows, :], fa.noise[..., rows], shape=model.shape
    )
