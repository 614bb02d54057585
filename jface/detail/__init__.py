"""Statistics and synthesis of facial detail (Golovinskiy et al. 2006).

``analyze`` turns a displacement image into per-tile steerable-pyramid statistics;
``synthesize`` coerces an image to target statistics; ``interpolate_faces``, ``add_detail`` and
``age`` apply it to remeshed faces (§3), ``method_results`` / ``method_scores`` compare it with
the paper's baselines (§4).
"""

from jface._distributed import (
    cpu_device_flags,
    deterministic_cpu_flags,
    join_processes,
    run_local_processes,
)
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
    METHODS,
    Interpolation,
    band_correlation,
    compare_methods,
    interpolate,
    method_results,
    method_scores,
    perlin_detail,
    remove_detail,
    sharpen,
    transfer_detail,
)
from jface.detail._database import analyze_batch, build_database
from jface.detail._meshes import (
    Face,
    FaceInterpolation,
    add_detail,
    age,
    as_face,
    interpolate_faces,
    swap_levels,
)
from jface.detail._population import Population
from jface.detail._stats import (
    DetailStats,
    SavedStats,
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
    "METHODS",
    "PCA",
    "CrossValidation",
    "DetailStats",
    "Face",
    "FaceInterpolation",
    "GroupComparison",
    "Interpolation",
    "Population",
    "SavedStats",
    "add_detail",
    "age",
    "analyze",
    "analyze_batch",
    "analyze_like",
    "as_face",
    "band_correlation",
    "build_database",
    "compare_groups",
    "compare_methods",
    "cpu_device_flags",
    "cross_validate",
    "deterministic_cpu_flags",
    "group_by",
    "interpolate",
    "interpolate_faces",
    "join_processes",
    "load_stats",
    "log_features",
    "mean_stats",
    "method_results",
    "method_scores",
    "perlin_detail",
    "remove_detail",
    "run_local_processes",
    "save_stats",
    "sharpen",
    "stack_stats",
    "stats_error",
    "stats_pca",
    "swap_levels",
    "synthesize",
    "transfer_detail",
]
