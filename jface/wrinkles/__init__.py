"""Micro-wrinkle simulation (Weiss et al. 2023, *Graph-Based Synthesis for Skin Micro Wrinkles*).

Pipeline of §3.1, one level::

    params = WrinkleParams(d=0.01, theta=0.5, s=0.2)
    pores = sample_pores(key1, params.d)                  # maximal Poisson-disk pores
    graph = build_graph(pores)                            # symmetric kNN, half-edges, crossings
    w = simulate(key2, graph, params)                   # trail formation → edge weights W
    disp = draw(key3, graph, w, params, (1024, 1024))     # §3.2: wrinkles + pores → displacement

A finer level starts from the coarser pores: ``sample_pores(key, d2, initial=pores)``.
All positions are ``(x, y)`` in the unit square; textures ``(H, W)`` cover it with ``x`` along
columns and ``y`` along rows. Parameter files state the frame of their lengths (:class:`ParamUnits`:
a whole map's unit square, or a patch of a known size on the face) and :func:`load_params`
converts them to the map they are drawn on.
"""

from jface.wrinkles._drawing import (
    BETA,
    N_HAT,
    draw,
    draw_bands,
    mellowmax,
    pore_strength,
    shape_function,
)
from jface.wrinkles._extraction import (
    Orientations,
    PoreCandidates,
    binary_opening,
    blend_with_scan,
    extract_orientation,
    extract_pores,
    find_pores,
    gabor_energy,
    gabor_kernels,
    gaussian_blur,
    label_components,
)
from jface.wrinkles._fit import (
    HELDOUT_KEYS,
    PAPER_NAMES,
    POLISH_FROM,
    REFINE_STARTS,
    REFINE_STEPS,
    WrinkleFit,
    fit_budget,
    fit_wrinkles,
    heldout_key_count,
)
from jface.wrinkles._graph import GraphSpec, PoreGraph, build_graph, graph_spec
from jface.wrinkles._mesh_radius import radius_map_from_mesh
from jface.wrinkles._params import (
    FRAMES,
    LENGTH_POWERS,
    PARAMETER_RANGES,
    ParamUnits,
    WrinkleParams,
    load_params,
    params_from_json,
    params_to_json,
    parse_patch_size,
    save_params,
    stack_params,
    to_map_frame,
)
from jface.wrinkles._sampling import Pores, default_capacity, make_pores, sample_pores
from jface.wrinkles._simulation import (
    N_SAMPLES,
    angle_distance,
    continuation_kernel,
    converged_steps,
    half_edge_scores,
    orientation_density,
    orientation_weight,
    samples_per_step,
    simulate,
)
from jface.wrinkles._synthesis import (
    Bands,
    Level,
    Simulated,
    Synthesis,
    draw_simulated,
    simulate_levels,
    synthesize,
    synthesize_bands,
)
from jface.wrinkles._variation import perlin_variation

__all__ = [
    "BETA",
    "FRAMES",
    "HELDOUT_KEYS",
    "LENGTH_POWERS",
    "N_HAT",
    "N_SAMPLES",
    "PAPER_NAMES",
    "PARAMETER_RANGES",
    "POLISH_FROM",
    "REFINE_STARTS",
    "REFINE_STEPS",
    "Bands",
    "GraphSpec",
    "Level",
    "Orientations",
    "ParamUnits",
    "PoreCandidates",
    "PoreGraph",
    "Pores",
    "Simulated",
    "Synthesis",
    "WrinkleFit",
    "WrinkleParams",
    "angle_distance",
    "binary_opening",
    "blend_with_scan",
    "build_graph",
    "continuation_kernel",
    "converged_steps",
    "default_capacity",
    "draw",
    "draw_bands",
    "draw_simulated",
    "extract_orientation",
    "extract_pores",
    "find_pores",
    "fit_budget",
    "fit_wrinkles",
    "gabor_energy",
    "gabor_kernels",
    "gaussian_blur",
    "graph_spec",
    "half_edge_scores",
    "heldout_key_count",
    "label_components",
    "load_params",
    "make_pores",
    "mellowmax",
    "orientation_density",
    "orientation_weight",
    "params_from_json",
    "params_to_json",
    "parse_patch_size",
    "perlin_variation",
    "pore_strength",
    "radius_map_from_mesh",
    "sample_pores",
    "samples_per_step",
    "save_params",
    "shape_function",
    "simulate",
    "simulate_levels",
    "stack_params",
    "synthesize",
    "synthesize_bands",
    "to_map_frame",
]
