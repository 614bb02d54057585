"""jface: statistics and synthesis of fine facial detail, in JAX.

Subpackages: ``jface.pyramid`` and ``jface.tiles`` (the multiscale core), ``jface.detail``
(Golovinskiy et al. 2006), ``jface.io`` (files), ``jface.render`` (figures).
"""

__version__ = "0.1.0"
