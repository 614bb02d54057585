"""Optimisation: a vectorised particle swarm (general, not wrinkle-specific), a texture loss and
Anderson acceleration of fixed-point iterations.

``pso(key, loss_fn, (low, high))`` minimises any JAX loss over a box (§4.2.1 of Weiss et al.
2023); ``texture_loss(prediction, target)`` compares two images by multiscale feature statistics,
the stand-in for the VGG style loss of Huang & Belongie 2017 used by the paper.
"""

from jface.optim._anderson import anderson
from jface.optim._pso import PSOResult, pso
from jface.optim._texture import TextureStats, texture_distance, texture_loss, texture_stats

__all__ = [
    "PSOResult",
    "TextureStats",
    "anderson",
    "pso",
    "texture_distance",
    "texture_loss",
    "texture_stats",
]
