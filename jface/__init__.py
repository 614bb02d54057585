"""jface: statistics and synthesis of fine facial detail, in JAX.

Subpackages, imported on first use (``import jface; jface.detail.analyze(...)``):

- ``jface.pyramid``, ``jface.tiles``: the multiscale core (steerable pyramid, tile statistics);
- ``jface.detail``: detail statistics and synthesis, applications (Golovinskiy et al. 2006);
- ``jface.mesh``: remeshing a scan into a base mesh and a displacement image;
- ``jface.faces``: factor analysers, quilting, Poisson blending (Mohammed et al. 2009);
- ``jface.wrinkles``: pores, pore graph, wrinkle simulation and drawing (Weiss et al. 2023);
- ``jface.optim``: particle swarm, Anderson acceleration;
- ``jface.noise``: counter-based noise; ``jface.raster``, ``jface.render``: images of meshes
  and maps; ``jface.plots``: paper-style figures (matplotlib);
- ``jface.io``: every file jface reads or writes; ``jface.data``: the real data it ships.
"""

import importlib

__version__ = "0.1.0"

_SUBMODULES = (
    "data",
    "detail",
    "faces",
    "io",
    "mesh",
    "noise",
    "optim",
    "plots",
    "pyramid",
    "raster",
    "render",
    "tiles",
    "wrinkles",
)


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"jface.{name}")
    raise AttributeError(f"module 'jface' has no attribute {name!r}")


def __dir__():
    return sorted((*globals(), *_SUBMODULES))
