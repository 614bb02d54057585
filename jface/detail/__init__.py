"""Statistics and synthesis of facial detail (Golovinskiy et al. 2006).

``analyze`` turns a displacement image into per-tile steerable-pyramid statistics;
``synthesize`` coerces an image to target statistics.
"""

from jface.detail._database import analyze_batch, build_database
from jface.detail._population import Population
from jface.detail._stats import (
    DetailStats,
    analyze,
    analyze_like,
    load_stats,
    mean_stats,
    save_stats,
    stack_stats,
    stats_error,
)
from jface.detail._synthesis import synthesize

__all__ = [
    "DetailStats",
    "Population",
    "analyze",
    "analyze_batch",
    "analyze_like",
    "build_database",
    "load_stats",
    "mean_stats",
    "save_stats",
    "stack_stats",
    "stats_error",
    "synthesize",
]
