"""Strict numerics for every test: float64 available, strict dtype promotion, seeded keys."""

import functools
import os
import socket
import subprocess
import sys
from pathlib import Path

# The suite compiles far more than it runs (small inputs, every program a few times): XLA's
# backend optimisation level 0 compiles in about a quarter less time, and the suite's runs are
# short (measured on two cores, fresh compilation cache: tests/test_detail.py and
# test_transforms.py 375 → 287 s, test_wrinkles_fit.py 436 → 387 s). Programs that choose their
# own level (the wrinkle fit's, jface._compilation.QUICK_COMPILE) keep it. Set before JAX starts;
# processes that tests start inherit it (tests that set XLA_FLAGS for a process append to it).
# A level given in XLA_FLAGS is kept.
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_optimization_level=0".strip()

import jax
import numpy as np
import pytest

from jface._compilation import keep_compiled_programs, spare_memory_mappings

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
# compiled programs are kept between runs of the suite in the repository's .jax-cache/ (not in
# the user's cache), so a rerun of the fast tier skips most compilation; JFACE_CACHE_DIR names
# another folder or, "off", turns it off (a folder given to JAX itself is kept)
os.environ.setdefault("JFACE_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".jax-cache"))
if keep_compiled_programs():
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)  # the tests' are small


#: Options of the suite's command-line wrinkle fits (on 64² patches; add ``--iters``): one set of
#: static sizes (the fit's layout does not depend on the seed), so that the fit compiles once per
#: process and its XLA flags, and later fits read it from the persistent cache.
TINY_FIT = ["--agents", "6", "--trials", "1", "--steps", "5", "--d-levels", "2",
            "--d-range", "0.04", "0.05", "--refine-steps", "0"]  # fmt: skip


def free_port() -> int:
    """A TCP port on localhost that is free now (for a test's coordinator)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


#: ``python -c JFACE_ENTRY ARGV`` runs ``jface ARGV`` in a process of its own
JFACE_ENTRY = "import sys; from jface.cli import main; sys.exit(main())"


def run_jface(*argv: str, env: dict | None = None, timeout: float = 60):
    """``jface ARGV`` in a process of its own, with ``env`` added to this one's environment."""
    return subprocess.run(
        [sys.executable, "-c", JFACE_ENTRY, *argv],
        env=dict(os.environ, **(env or {})),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def run_with_process_counts(argv: list[str], counts: tuple[str, str]) -> list[tuple[int, str]]:
    """Run ``jface ARGV`` as processes 0 and 1 of a distributed run that were told the process
    counts ``counts``; their exit statuses and stderr."""
    command = [sys.executable, "-c", JFACE_ENTRY, *argv]
    workers = [
        subprocess.Popen(
            [*command, "--process-id", str(i), "--num-processes", n],
            stderr=subprocess.PIPE,
            text=True,
        )
        for i, n in enumerate(counts)
    ]
    errors = [w.communicate(timeout=60)[1] for w in workers]
    return [(w.returncode, err) for w, err in zip(workers, errors, strict=True)]


@pytest.fixture(scope="session")
def ict_model() -> dict[str, np.ndarray]:
    """The ICT-FaceKit face model that ships with jface (jface/data/ict_face_small.npz: the
    face-area mesh, its 10 leading identity modes and the smile), so tests need no shared data."""
    from jface import data

    return data.ict_face_model()


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance from points to a triangle mesh (closest point over the 16 nearest triangles)."""
    import trimesh
    from scipy.spatial import cKDTree

    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    _, cand = cKDTree(tri.mean(axis=1)).query(points, k=16)
    q = trimesh.triangles.closest_point(tri[cand.ravel()], np.repeat(points, 16, axis=0))
    return np.linalg.norm(q - np.repeat(points, 16, axis=0), axis=1).reshape(-1, 16).min(axis=1)


#: The slow tier, in one place: whole modules (None) or tests by name. ``pytest -m "not slow"``
#: is the fast tier for development; CI runs everything (the README's test command).
SLOW = {
    "test_reliability.py": None,  # long runs, large inputs, interrupted jobs
    "test_real_inputs.py": None,  # full pipelines on the shipped scan and real textures
    "test_landmarks.py": None,  # model fits on scans
    "test_mesh_remesh.py": None,
    "test_detail_meshes.py": None,
    "test_applications.py": None,
    "test_database.py": None,
    "test_wrinkles_realism.py": None,
    "test_wrinkles_fit.py": None,
    "test_wrinkles_extract.py": None,
    "test_fuzz_inputs.py": None,  # hypothesis searches
    "test_cli_content.py": None,
    "test_wrinkles_cli.py": None,
    "test_readme.py": None,  # every Python block and command-table row of the README
    # the rest: the longest tests of the fast tier as measured (3–33 s each on two cores)
    "test_detail.py": {
        "test_fig5_resynthesis_converges_on_real_data",
        "test_reflect_boundary_synthesis",
        "test_jit_equals_eager_and_vmap_over_targets",
        "test_synthesis_is_deterministic_and_vmaps",
        "test_fixed_point_and_noise_scale",
        "test_histogram_synthesis_moves_tiles_towards_targets",
        "test_histogram_matching_reaches_spatially_varying_targets",
    },
    "test_wrinkles_simulation.py": {
        "test_scoring_every_pore_equals_scoring_the_samples",
        "test_fixed_steps_with_progress_move_the_bar_and_give_the_same_weights",
        "test_vmap_over_parameter_sets_equals_loop",
        "test_default_run_is_converged",
        "test_default_run_in_chunks_equals_one_scan",
        "test_weights_do_not_depend_on_capacity",
    },
    "test_wrinkles_draw.py": {
        "test_textured_params_and_skew_orientation",
        "test_straight_wrinkle_has_the_eq9_profile",
        "test_scale_multiplies_the_fragments_before_the_blend",
        "test_periodic_map_tiles_without_a_seam",
        "test_radius_map_from_known_uv_stretch",
        "test_bands_join_to_the_whole_map",
        "test_bad_input",
        "test_jit_eager_vmap_determinism_and_grad",
        "test_tiled_rasteriser_matches_brute_force",
        "test_packed_bins_and_passes_as_needed_draw_the_same_map",
    },
    "test_transforms.py": None,  # jit/vmap of every public function
    "test_noise.py": {"test_periodic_noise_tiles_and_is_zero_on_lattice"},
    "test_analysis.py": {"test_cross_validated_prediction"},
    "test_plots.py": {"test_commands_that_write_a_folder_write_its_page"},
    "test_wrinkles_units.py": {"test_fit_records_the_patch_frame"},
    "test_wrinkles_graph.py": {"test_covering_spec_and_stack_graphs_keep_every_graph"},
    "test_align.py": {
        "test_jit_equals_eager_and_vmap_equals_loop",
        "test_colour_faces_align_and_unwarp_into_another_size",
        "test_alignment_that_does_not_converge_is_an_error",
        "test_unwarp_returns_an_aligned_face_to_its_training_frame",
    },
    "test_workflows.py": {
        "test_wrinkles_render_draws_what_simulate_wrote",
        "test_small_faces_get_a_grid_that_fits_and_figures_of_a_usable_size",
        "test_faces_train_bilinear_makes_the_model_restyle_needs",
    },
    "test_wrinkles_sampling.py": {
        "test_same_key_same_pores_and_vmap_over_alpha_d_equals_loop",
        "test_radius_map_changes_density_and_keeps_guarantees",
        "test_finer_level_keeps_coarse_pores",
        "test_count_matches_scipy_poisson_disk",
    },
    "test_optim_texture.py": {
        "test_jit_vmap_and_gradient",
        "test_zero_for_identical_and_invariant_to_gain_and_offset",
    },
    "test_optim_pso.py": {
        "test_rastrigin_10d_reaches_the_low_basin",
        "test_lbest_converges_slower_than_gbest",
    },
    "test_faces_models.py": {
        "test_mixture_separates_frontal_and_profile",
        "test_bilinear_predicts_held_out_smiles",
        "test_mixture_em_monotone_and_dense_reference",
    },
    "test_faces_quilting.py": {
        "test_choices_match_a_numpy_reference_of_the_cost",
        "test_synthesis_from_factor_models",
        "test_restyle_with_bilinear_model",
    },
    "test_known_answers.py": {"test_one_step_hits_follow_eq3_in_distribution"},
    # runs of several processes: each starts Python and JAX, some compile a fit (measured on two
    # shared cores: 50 s for test_distributed.py, 7.8 min for test_distributed_fit.py, most of it
    # compiling the fit in four processes; on CPU JAX's compilation cache keys include the
    # device assignment, which apparently keeps the 2-process run from reusing the cache)
    "test_distributed.py": {
        "test_builds_are_byte_identical",
        "test_two_processes_equal_one",
        "test_killed_process_resumes",
        "test_mismatched_process_counts_are_refused",
        "test_a_failing_process_stops_the_others",
        "test_cluster_outside_a_cluster_job_is_refused",
    },
    "test_distributed_fit.py": {
        "test_sharded_swarm_equals_the_unsharded_one",
        "test_two_processes_fit_three_patches_like_three_single_fits",
        "test_rerun_keeps_finished_patches_and_refits_a_changed_one",
        "test_mismatched_process_counts_are_refused",
    },
}


def pytest_collection_modifyitems(config, items):
    """Mark the slow tier: the modules and tests of :data:`SLOW`, and every command-line run
    (tests named ``test_cli_*``)."""
    for item in items:
        names = SLOW.get(item.path.name, ())
        if names is None or item.originalname in names or item.originalname.startswith("test_cli"):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(autouse=True)
def _release_compiled_code():
    """Drop JAX's compiled executables after a test once the process holds many memory
    mappings (:func:`jface._compilation.spare_memory_mappings`): tests compile far more
    programs in one process than any run of jface. Below that, tests keep sharing compilations
    (a cleared program is read back from the persistent cache)."""
    yield
    spare_memory_mappings()


@pytest.fixture(autouse=True)
def _xla_flags_kept():
    """``XLA_FLAGS`` as it was before the test: a command run in this process sets its own
    (deterministic threads, a device per core), which this process, started long before, does
    not read, but the processes later tests start would inherit."""
    flags = os.environ["XLA_FLAGS"]
    yield
    os.environ["XLA_FLAGS"] = flags


@pytest.fixture
def key():
    """A fixed-seed key: tests are deterministic."""
    return jax.random.key(0)


@pytest.fixture(scope="session")
def gravel() -> np.ndarray:
    """scikit-image's real gravel texture (CC0), 512×512, float64 in [0, 1]."""
    from skimage import data

    return data.gravel().astype(np.float64) / 255.0


def write_aged_maps(folder: Path, gravel: np.ndarray, ages, size: int) -> list[str]:
    """Gravel crops of growing amplitude, one per age, as ``f<i>.exr`` in ``folder``, with their
    records in ``folder/meta.json``: a small population for the database commands."""
    from jface import io

    maps = []
    for i in range(len(ages)):
        image = gravel[i * 32 : i * 32 + size, :size].astype(np.float32) * (1 + i)
        maps.append(str(io.write_exr(folder / f"f{i}.exr", image)))
    io.write_json(folder / "meta.json", [{"id": f"f{i}", "age": a} for i, a in enumerate(ages)])
    return maps


@pytest.fixture(scope="session")
def brick() -> np.ndarray:
    """scikit-image's real brick texture (CC0), 512×512, float64 in [0, 1]."""
    from skimage import data

    return data.brick().astype(np.float64) / 255.0


@pytest.fixture
def unchecked():
    """Switch off the test-time jaxtyping/beartype checks, so bad-input tests see the library's
    own validation messages (what a user without the checker gets)."""
    import jaxtyping

    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", False)


def titled(figure) -> bool:
    """The figure has a title (its suptitle)."""
    return figure._suptitle is not None and figure._suptitle.get_text().strip() != ""


def value_images_have_colour_bars(figure) -> bool:
    """Every 2-D array drawn with a colour map (not grey relief or photographs) shares its
    scale with a colour bar of the figure."""
    with_bar = {id(im.norm) for ax in figure.axes for im in ax.images if im.colorbar is not None}
    for ax in figure.axes:
        for im in ax.images:
            encodes_value = im.get_array().ndim == 2 and im.get_cmap().name != "gray"
            if encodes_value and id(im.norm) not in with_bar:
                return False
    return True


@pytest.fixture(autouse=True)
def written_figures(monkeypatch) -> dict:
    """File name → the matplotlib figure written there by :func:`jface.io.write_figure`, from
    any jface module that writes figures (each holds its own reference to the writer).

    In every test: each figure written (by a command, a workflow, a library call) must have a
    title and, where a colour map encodes a value, a colour bar; checked when the test ends."""
    import importlib
    import sys

    from jface import io
    from jface.cli import COMMAND_MODULES

    for name in COMMAND_MODULES:  # each command module imported, so its reference is replaced
        importlib.import_module(name)
    real, found = io.write_figure, {}

    @functools.wraps(real)  # the stand-in keeps the writer's name and docstring (test_api)
    def capture(path, figure, **kwargs):
        written = real(path, figure, **kwargs)
        found[Path(path).name] = figure
        return written

    for name, module in list(sys.modules.items()):
        if name.startswith("jface") and getattr(module, "write_figure", None) is real:
            monkeypatch.setattr(module, "write_figure", capture)
    yield found
    untitled = [name for name, figure in found.items() if not titled(figure)]
    unbarred = [n for n, figure in found.items() if not value_images_have_colour_bars(figure)]
    assert not untitled, f"figures written without a title: {untitled}"
    assert not unbarred, f"figures with a colour-mapped value but no colour bar: {unbarred}"
