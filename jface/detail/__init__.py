"""Statistics and synthesis of facial detail (Golovinskiy et al. 2006).

``analyze`` turns a displacement image into per-tile steerable-pyramid statistics;
``synthesize`` coerces an image to target statistics.
"""

from jface.detail._analysis import (
    PCA,
    CrossValidation,
    GroupComparison,
    compare_groups,
    cross_validate,
    group_by,
    log_features,
    stats_pca,
)
from jface.detail._applications import (
    Interpolation,
    band_correlation,
    compare_methods,
    interpolate,
    remove_detail,
    sharpen,
    transfer_detail,
)
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
    "PCA",
    "CrossValidation",
    "DetailStats",
    "GroupComparison",
    "Interpolation",
    "Population",
    "analyze",
    "analyze_batch",
    "analyze_like",
    "band_correlation",
    "build_database",
    "compare_groups",
    "compare_methods",
    "cross_validate",
    "group_by",
    "interpolate",
    "load_stats",
    "log_features",
    "mean_stats",
    "remove_detail",
    "save_stats",
    "sharpen",
    "stack_stats",
    "stats_error",
    "stats_pca",
    "synthesize",
    "transfer_detail",
]
