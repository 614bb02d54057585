"""Fitting simulation and drawing parameters to a measured patch (§4.2 of Weiss et al. 2023).

Two levels; α_d of level 1 is free and level 2 uses half of it; per level the paper's twelve
parameters (α_θ cyclic) and one additive Perlin noise level (α_fnoise, α_snoise, drawn with level
1). A particle swarm (:func:`jface.optim.pso`, lbest, Random+Absorb) minimises the VGG-free texture
loss (:func:`jface.optim.texture_distance`) between the synthesised map and the patch. Agents whose
α_d differ share one compiled program. Pores and graph depend on α_d alone (common random
numbers: one pore key for every fit, :func:`layout_key`), so they are built on a grid of
``d_levels`` values of α_d, trimmed to the slots the data use, and each agent simulates on the
nearest (α_d is effectively quantised to that grid; the reported α_d is the grid value). Each
trial evaluates every agent with the same simulation key, so the loss is a deterministic function
of the parameters. The map is drawn at the patch size rounded up to whole 8-pixel tiles (a
periodic map needs whole tiles) and cropped. The pores and graphs do not depend on the patch
size: they are kept once per α_d grid, the draw sizes per patch size, for the next fit in the
process and, with the compiled programs, on disk.

Beyond the paper, the continuous drawing parameters of the best answers (up to
:data:`REFINE_STARTS` starts, see ``refine_starts``) are then refined by gradient (optimistix
BFGS) through the differentiable drawing with the simulation result held fixed, and the best
refined answer is the fit's. In fast mode, where it costs at most a tenth of the fit's budget, a
greedy coordinate search over the simulation parameters then goes on from it, at finer steps once
its steps no longer gain (:data:`COORDINATE_PASSES`, :data:`COORDINATE_SCALES`), and what it finds
is refined again.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array, Float

from jface import _checks
from jface._compilation import (
    QUICK_COMPILE,
    compile_ahead,
    kept_arrays,
    read_shipped,
    shipped_arrays,
    spare_memory_mappings,
    write_arrays,
)
from jface.optim import PSOResult, TextureStats, texture_distance, texture_stats
from jface.optim._pso import (
    Swarm,
    _keep_better,
    swarm_epoch,
    swarm_evaluate,
    swarm_settings,
    swarm_start,
)
from jface.optim._texture import _stats
from jface.wrinkles._drawing import (
    BETA,
    N_HAT,
    DrawOptions,
    bin_primitives,
    entries_of,
    needed_entries,
    needed_span,
    perturbation_noise,
    primitives,
    render,
)
from jface.wrinkles._graph import (
    GRAPH_TABLES,
    PoreGraph,
    _round_up,
    built,
    covering_spec,
    cut_slots,
    graph_errors,
    graph_from_tables,
    graph_tables,
    trim_batch,
)
from jface.wrinkles._params import PARAMETER_RANGES, WrinkleParams
from jface.wrinkles._sampling import SAMPLING_ERRORS, default_capacity, sampled
from jface.wrinkles._simulation import N_SAMPLES, simulate

#: Per-level parameters the paper fits (§4.2.2), besides α_d and one noise level.
LEVEL_NAMES = (
    "theta", "s", "cont", "deposit", "dist", "cross",
    "wrinkle_width", "pore_width", "blend", "skew", "cushion", "sperturb",
)  # fmt: skip
#: The paper's full set: α_d (level 1), ``"<level>.<name>"`` per level, one noise level.
PAPER_NAMES = ("d", *(f"{lv}.{n}" for lv in (1, 2) for n in LEVEL_NAMES), "fnoise", "snoise")
#: Drawing parameters refined by gradient after the swarm (continuous in the drawing).
DRAWING_NAMES = ("wrinkle_width", "pore_width", "blend", "skew", "cushion", "sperturb")
#: Default α_d search range: Table 1 allows [0.001, 0.05]; a patch holds a few hundred pores.
D_RANGE = (0.02, 0.05)
#: Number of α_d values whose pores and graphs are precomputed, per mode: building them is most
#: of a fit's fixed cost; fast mode's 16 step α_d by 4–10 %, the paper mode's 32 by 2–5 %.
D_LEVELS = {"fast": 16, "paper": 32}
#: BFGS steps of the refinement, per mode, at most (it stops earlier where its steps no longer
#: gain, :data:`REFINE_BACKTRACKS` and :data:`REFINE_FLAT_STEPS`): each costs
#: about seven swarm evaluations (a gradient through the drawing). Fast mode took 10 until
#: measured: with 30, its default fits of 256² crops (seed 0) reached 0.71x (`gravel`), 0.59x
#: (`brick`) and 0.83x (a map drawn from known parameters) the paper mode's held-out loss,
#: against 1.11x, 0.54x and 1.06x with 10, for 12-23 % more time; with seed 1 `brick` gained
#: too and `gravel` lost (1.17x against 1.00x): the held-out loss fell in 3 of 5 such pairs.
REFINE_STEPS = {"fast": 30, "paper": 30}
#: Starts of the final refinement: the best answer of every trial that ran to its end (paper mode:
#: all; fast mode: the race's winner), then the best such trial's next personal bests, up to this
#: many in all (and one more for each start's cost in the epochs a stalled race left,
#: :func:`_refine_starts`). The swarm's loss ranks answers poorly for what the refinement makes of
#: them (on gravel, the paper mode's worst trial, 0.045, refined to 0.014 and its best, 0.032, to
#: 0.021). A fit takes the extra starts while they cost at most a tenth of its swarm's evaluations
#: (a 256² exploratory fit of 40 evaluations spent 23 s on 4 starts, half its time warm).
REFINE_STARTS = 4
#: Simulation keys that score a fit's answer besides its own (:attr:`WrinkleFit.heldout_losses`):
#: each costs one agent's evaluation, once per fit (a refinement of 30 BFGS steps up to 210
#: evaluations). The losses of one answer with other keys spread by 29-45 % of their mean on
#: real textures and 5-23 % on maps drawn from known parameters (standard deviation over 32
#: keys, the benchmark's fits), so 32 give their mean within about 8 % and 4 % (8: 15 % and 8 %).
#: A fit takes as many as cost at most a tenth of its budget's evaluations, and at least
#: ``HELDOUT_MIN_KEYS`` (:func:`heldout_key_count`): a 256² exploratory fit of 40 evaluations
#: spent 15-25 s of its 46-88 s on 32 keys and 5-15 s on 8 (measured on two cores).
HELDOUT_KEYS, HELDOUT_MIN_KEYS = 32, 8
#: Fast mode: stop when the best loss fell by less than this share over ``PATIENCE`` epochs.
#: Judged after each rung's polish in full fits: there, 0.1 % ran a 256² `brick` crop's last
#: trial 24 epochs and 2 polishes past 1 %'s stop for 1.0 % of its own loss (0.4 % on other
#: simulation keys), while `gravel`'s rungs gained 2.6 % or more until the last (seed 0).
STALL_TOLERANCE, PATIENCE = 1e-2, 10
#: The swarm's inertia ``w_t = a + b · c^t`` (Eq. 14, ``optim.pso``'s ``inertia``) by mode. The
#: paper's decay (0.98) is made for 100 epochs: w is still 0.77 after 24 and reaches 0.48 at the
#: 100th. The fast mode's trials run 12-100 epochs (the last stops when it stalls), so its
#: inertia decays faster (0.58 after 24 epochs, 0.43 after 60): default fits of 256² `gravel`
#: and `synthesized` maps (seeds 0-2) then ended 0.66-1.00x as high on their own keys as with
#: 0.98 and 0.89-1.19x on the same 8 held-out keys; over 12 fits of six targets the median
#: ratios were 0.93 and 0.96 (`brick` seed 0: 1.74x, docs/wrinkles-fitting-log.md).
INERTIA = {"fast": (0.4, 0.6, 0.95), "paper": (0.4, 0.6, 0.98)}
#: Fast mode's last trial runs at most this many epochs (fewer where ``n_epochs`` is smaller);
#: the epochs of the race's budget past them buy refinement starts, as a stall's do. By then its
#: inertia (:data:`INERTIA`) has come within 13 % of its floor and the swarm has contracted. In
#: 18 default fits (256², six targets, seeds 0-2) the eight winners that ran past 48 epochs
#: lowered their swarm's best by 0-4.2 % (median 0.8 %) in the rung to 60, and the three that
#: ran on to 72 by 0-0.4 % in that rung; a rung costs about 60-70 s of a fit's 10 min. With
#: it `gravel`'s fits (seeds 0-2) took 638, 582 and 589 s on a slow day, at 1.00, 0.99 and
#: 1.00x their own-key loss without it (docs/wrinkles-fitting-log.md).
FAST_EPOCHS = 48
#: Fast mode polishes every trial's best with the refinement after each rung of successive
#: halving when a rung holds at least this many evaluations: one polish (up to 30 BFGS steps)
#: costs up to about 210 evaluations, and one of the swarm's when it gains (it is shared).
POLISH_FROM = 300
#: Swarms of fewer evaluations draw every agent with one program: the second size class saves
#: about 0.06 s an evaluation but costs about 12 s of compile (256², two cores), so it repays
#: itself from about 200 evaluations on (a fit of 50 agents, 100 epochs, 3 trials has 15,150).
SPLIT_FROM = 200
#: Swarms of fewer evaluations run on one device by default, not sharded over all: the sharded
#: loss traces for about 1.5 s longer and the refinement beside it runs about 15 % slower, while
#: an epoch of 8 agents is no faster (256², two CPU devices on two cores; 50 agents: 64 against
#: 80 ms per agent).
SHARD_FROM = SPLIT_FROM
#: Fast mode ends with up to this many passes of a coordinate search over the fitted simulation
#: parameters (:func:`_coordinate_search`), from the refined answer on its own key. Measured from
#: five fast fits' answers (256², `known-1` seeds 0-2, `gravel` seed 1, `synthesized` seed 0),
#: one pass lowered every own-key loss by 7-12 % and the mean loss on 8 held-out keys in four of
#: five (0.88-1.04x); a second gained more on `gravel` (0.83x own key, 0.88x held out) and
#: nothing on `known-1` seed 1. A pass costs up to 48 evaluations of the default names. In the
#: default fits (9 of `known-1`, `gravel`, `synthesized`) it lowered the own-key loss to
#: 0.79-0.92x for about 20-30 s (docs/wrinkles-fitting-log.md). It runs where it and the
#: refinement of its answer cost at most a tenth of the budget's evaluations (:func:`_searches`):
#: in a default fit, not in a small exploratory one, whose time it more than doubled (8 agents ×
#: 5 epochs at 256²: 108 s against 41 s).
COORDINATE_PASSES = {"fast": 2, "paper": 0}
#: The coordinate search's steps from a parameter's current value, as shares of its search range.
COORDINATE_STEPS = (-0.1, -0.05, 0.05, 0.1)
#: Sizes of those steps in turn: the search goes on at half, then a quarter, of its steps once
#: a pass gains nothing (up to ``COORDINATE_PASSES`` passes at each). In default fits (256²,
#: `known-3` seeds 0-2, `gravel` and `synthesized` seed 1) they lowered the own-key loss to
#: 0.85-0.97x and the held-out loss to 0.89-1.01x, for about 30 s on two CPU cores; the quarter
#: steps lowered the half steps' answer by a further 0.3 % (docs/wrinkles-fitting-log.md).
COORDINATE_SCALES = (1.0, 0.5, 0.25)


class WrinkleFit(eqx.Module):
    """Result of :func:`fit_wrinkles`.

    Attributes:
        levels: the fitted ``(level 1, level 2)`` parameters (after refinement and, in fast
            mode, the coordinate search).
        loss: texture loss of ``levels``.
        swarm_loss: texture loss of the swarm's best, before the final gradient refinement (in
            fast mode's full fits the swarm's bests were already polished by it on the way).
        swarm: the :class:`jface.optim.PSOResult` (history for a convergence plot).
        names: the fitted parameter names, in the order of ``swarm.params`` (static).
        sim_key: the simulation key of ``answer_trial`` (reproduces ``fitted``).
        fitted: the synthesised map of ``levels``, ``(H, W)``.
        interrupted: the fit was stopped (Ctrl-C) and reports the best found so far: the
            swarm's, unrefined, or when stopped while refining, the best start refined by then.
        epochs_run: epochs each trial ran (static).
        refined_losses: loss of each start of the final refinement (``refine_starts`` of
            :func:`fit_wrinkles` at most, the swarm's best first; one without drawing fields to
            refine); ``loss`` is the least, or lower where fast mode's coordinate search
            gained from it (empty when interrupted before any).
        answer_trial: the trial whose answer ``levels`` is (static; in paper mode not always
            ``swarm.best_trial``: another trial's answer can refine better).
        heldout_losses: losses of ``levels`` simulated and drawn with other simulation keys,
            :func:`heldout_key_count` of them (the same pores; a map the swarm's static draw
            sizes cannot hold is drawn on bins of twice the pairs, or sized to it). ``loss`` is
            the least of many answers on one key and so flatters the parameters;
            :attr:`heldout_loss`, the mean of these, flatters them less (it keeps the fit's
            pores, which a render with another seed also resamples).
    """

    levels: tuple[WrinkleParams, WrinkleParams]
    loss: Float[Array, ""]
    swarm_loss: Float[Array, ""]
    swarm: PSOResult
    names: tuple[str, ...] = eqx.field(static=True)
    sim_key: Array
    fitted: Float[Array, "H W"]
    interrupted: bool = eqx.field(static=True, default=False)
    epochs_run: tuple[int, ...] = eqx.field(static=True, default=())
    refined_losses: Float[Array, " S"] = eqx.field(default_factory=lambda: jnp.zeros(0))
    answer_trial: int = eqx.field(static=True, default=0)
    heldout_losses: Float[Array, " K"] = eqx.field(default_factory=lambda: jnp.zeros(0))

    @property
    def heldout_loss(self) -> float:
        """Mean of the finite :attr:`heldout_losses` (NaN when none is): about what a map drawn
        with these parameters and another simulation key scores, unlike ``loss``, which the
        search selected for its own key."""
        losses = np.asarray(self.heldout_losses)
        finite = losses[np.isfinite(losses)]
        return float(np.mean(finite)) if finite.size else float("nan")


class _Layout(eqx.Module):
    """Precomputed pores and graphs of the α_d grid, and the static sizes that let agents with
    different α_d share one compiled pipeline.

    With common random numbers the pores and the graph are a function of α_d alone, so they are
    built once per fit for ``d_levels`` values of α_d spanning ``d_range``, each level sized to
    the data (:func:`stack_graphs`); an agent simulates on the graphs of the nearest value.

    The densest value has about 6x the pores of the sparsest, and the simulation and the drawing
    cost in proportion to the slots, valid or not. So the grid splits in two size classes at
    ``split`` (the index that minimises the mean slots over the grid), and ``slots`` holds each
    class's node and edge slots per level: :meth:`narrowed` cuts the graphs to a class, and the
    swarm evaluates each agent with its class's program (a quarter less time per evaluation).
    :meth:`merged` makes it one class again (one program to compile: the refinement, small
    swarms).
    """

    d_values: Float[Array, " K"]
    graphs: tuple[PoreGraph, PoreGraph]
    size: tuple[int, int] = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)
    n_samples: tuple[int, int] = eqx.field(static=True)
    n_steps: int = eqx.field(static=True)
    span: tuple[int, int] = eqx.field(static=True)
    entries: tuple[int, int] = eqx.field(static=True)
    split: int = eqx.field(static=True)
    slots: tuple[tuple[tuple[int, int], tuple[int, int]], ...] = eqx.field(static=True)

    def index(self, d) -> Array:
        """Index of the grid value nearest to α_d."""
        lo, hi = self.d_values[0], self.d_values[-1]
        k = self.d_values.shape[0]
        return jnp.clip(jnp.round((d - lo) / (hi - lo) * (k - 1)), 0, k - 1).astype(jnp.int32)

    def select(self, d) -> tuple[Array, tuple[PoreGraph, PoreGraph]]:
        """The grid value nearest to α_d and its two graphs."""
        i = self.index(d)
        return self.d_values[i], jax.tree.map(lambda a: a[i], self.graphs)

    def size_class(self, d) -> Array:
        """0 for the dense values of the grid (index below ``split``), 1 for the sparse ones."""
        return (self.index(d) >= self.split).astype(jnp.int32)

    def narrowed(self, size_class: int) -> _Layout:
        """This layout with its graphs cut to the slots of a size class: the same maps for the
        α_d of that class, at a smaller static size (not valid for the other class)."""
        slots = self.slots[size_class]
        graphs = tuple(cut_slots(g, *s) for g, s in zip(self.graphs, slots, strict=True))
        return dataclasses.replace(self, graphs=graphs)

    def merged(self) -> _Layout:
        """This layout as one size class, every α_d on the whole grid's slots: one compiled
        program draws any agent (the refinement; swarms too small to repay a second class's
        compile)."""
        whole = tuple(tuple(map(max, *level)) for level in zip(*self.slots, strict=True))
        return dataclasses.replace(self, split=len(self.d_values), slots=(whole,))

    def roomier(self) -> _Layout:
        """This layout with bins of twice the (primitive, tile) pairs."""
        return dataclasses.replace(self, entries=tuple(2 * n for n in self.entries))


# screen tile (pixels) and primitives per pass of the swarm's draws: 8-pixel tiles draw a 256²
# two-level map 2-4x faster than 32-pixel ones (fewer primitives tested per pixel)
_TILE, _CAPACITY = 8, 16
#: drawing fields at their widest for sizing the draws (agents beyond get a NaN loss)
_WIDE = {"wrinkle_width": 0.6, "pore_width": 0.3, "blend": 0.5, "skew": 0.5, "sperturb": 1.0}


#: Stream of the held-out simulation keys (:data:`HELDOUT_KEYS`), folded into the fit's
#: simulation key (whose split gives the trials' keys)
_HELDOUT_STREAM = 0x4E1D

#: Seed of the fit's pores and graphs (any fixed value; not a user's seed, whose simulation and
#: swarm streams must not repeat the pores').
_LAYOUT_SEED = 0x5EED_A11D


def heldout_keys(key: Array, count: int = HELDOUT_KEYS) -> Array:
    """The ``count`` simulation keys that score the answer of a fit with ``key`` besides its
    own (folded into its simulation key, whose split gives the trials' keys); fewer are the
    first of more."""
    k_sim = jax.random.split(key)[0]
    return jax.random.split(jax.random.fold_in(k_sim, _HELDOUT_STREAM), count)


def layout_key() -> Array:
    """The key of every fit's pores and graphs. They are a fixed design of the fit, like a
    quadrature: the loss compares texture statistics, not pore positions, and the seed varies the
    simulation and the swarm. Fixed, they make every static size of a fit (slots, bins, size
    classes) a function of the patch size and the settings alone, so a fit of another patch or
    seed reuses the layout and the compiled programs of the first (measured: a 256² exploratory
    fit, 8 agents × 5 epochs, took 163 s with a new seed before, when they all compiled anew)."""
    return jax.random.key(_LAYOUT_SEED)


class _Design(NamedTuple):
    """The part of a layout that does not depend on the patch size: the α_d grid, its pores and
    graphs (sampled on the unit square), the simulation's samples and the size classes."""

    d_values: Float[Array, " K"]
    graphs: tuple[PoreGraph, PoreGraph]
    n_samples: tuple[int, int]
    split: int
    slots: tuple[tuple[tuple[int, int], tuple[int, int]], ...]


#: designs and layouts of the latest fits in this process, by what they are built from (a design
#: holds a few MB; a layout adds only its draw sizes)
_DESIGNS: dict[tuple, _Design] = {}
_LAYOUTS: dict[tuple, _Layout] = {}
_KEPT = 4


def _kept_layout(key, size, d_range, n_steps, d_levels) -> _Layout:
    """:func:`_layout`, built once: kept in this process and, where compiled programs are kept
    (:func:`jface._compilation.keep_compiled_programs`, as the command line does), on disk, so
    that a rerun reads it (the layout runs for seconds after its programs are compiled). Its
    design is kept once for every patch size, so a fit of another size builds only its draw
    sizes. jface ships the default fast fit's design and its draw sizes at
    :data:`SHIPPED_SIZES` (:data:`SHIPPED_LAYOUTS`), which a first fit would otherwise spend
    half a minute building."""
    name = _layout_name(key, size, d_range, n_steps, d_levels)

    def build() -> _Layout:
        design = _kept_design(key, d_range, d_levels)

        build_sizes = functools.partial(_draw_sizes, key, design, size, n_steps)
        entries = kept_arrays("layouts", name, build_sizes, SHIPPED_LAYOUTS)["entries"]
        return _sized(design, size, n_steps, tuple(map(int, entries)))

    return _remembered(_LAYOUTS, name, build)


def _kept_design(key, d_range, d_levels) -> _Design:
    """:func:`_design`, kept as :func:`_kept_layout` keeps a layout."""
    name = _design_name(key, d_range, d_levels)

    def build():
        return _design_arrays(_design(key, d_range, d_levels))

    return _remembered(
        _DESIGNS, name, lambda: _design_from(kept_arrays("designs", name, build, SHIPPED_LAYOUTS))
    )


#: The file of layouts that jface ships: the default fast fit's design and its draw sizes at
#: :data:`SHIPPED_SIZES`, written by ``python -m jface.wrinkles._ship`` (which a change to the
#: pores, graphs, simulation or drawing calls for; its test finds that a build differs).
SHIPPED_LAYOUTS = Path(__file__).with_name("fit_layouts.npz")

#: Square patch sizes whose draw sizes jface ships (with the default 50 simulation steps).
SHIPPED_SIZES = (64, 128, 256, 512)


def ship_layouts(path: Path = SHIPPED_LAYOUTS) -> None:
    """Build the layouts :data:`SHIPPED_LAYOUTS` holds and write them to ``path``."""
    key, d_levels, n_steps = layout_key(), D_LEVELS["fast"], 50
    design = _design(key, D_RANGE, d_levels)
    arrays = shipped_arrays("designs", _design_name(key, D_RANGE, d_levels), _design_arrays(design))
    for n in SHIPPED_SIZES:
        name = _layout_name(key, (n, n), D_RANGE, n_steps, d_levels)
        arrays |= shipped_arrays("layouts", name, _draw_sizes(key, design, (n, n), n_steps))
    write_arrays(path, arrays)


def layout_shipped(size, d_range, n_steps, d_levels) -> bool:
    """Whether jface ships the layout of a fit of these settings (its first fit only compiles;
    otherwise it builds the draw sizes, and the design unless another size's fit kept it)."""
    name = _layout_name(layout_key(), size, d_range, n_steps, d_levels)
    return bool(read_shipped(SHIPPED_LAYOUTS, "layouts", name))


def _draw_sizes(key, design: _Design, size, n_steps) -> dict[str, np.ndarray]:
    """:func:`_draw_entries` as the arrays a layout is kept as."""
    return {"entries": np.asarray(_draw_entries(key, design, size, n_steps))}


def _remembered(memo: dict, name: tuple, build):
    """``memo[name]``, built first if missing (the oldest entry makes room beyond ``_KEPT``)."""
    if name not in memo:
        while len(memo) >= _KEPT:
            del memo[next(iter(memo))]
        memo[name] = build()
    return memo[name]


def _key_bits(key) -> bytes:
    """A (concrete) key as plain bytes."""
    return np.asarray(jax.random.key_data(key)).tobytes()


def _design_name(key, d_range, d_levels) -> tuple:
    """What a design is built from, as plain values (with the setting that changes the key's
    random stream)."""
    bits = _key_bits(key)
    stream = (str(jax.random.key_impl(key)), bool(jax.config.jax_threefry_partitionable))
    return (*stream, bits, tuple(map(float, d_range)), int(d_levels))


def _layout_name(key, size, d_range, n_steps, d_levels) -> tuple:
    """What a layout is built from, as plain values."""
    return (*_design_name(key, d_range, d_levels), tuple(map(int, size)), int(n_steps))


_INT16 = np.iinfo(np.int16)


def _design_arrays(design: _Design) -> dict[str, np.ndarray]:
    """The design as named arrays (graphs as their tables, indices in 16 bits where they fit),
    for :func:`_design_from`."""
    arrays = {"d_values": np.asarray(design.d_values)}
    for field in ("n_samples", "split", "slots"):
        arrays[field] = np.asarray(getattr(design, field))
    for level, graph in enumerate(design.graphs):
        arrays[f"{level}.periodic"] = np.asarray(graph.periodic)
        for field, a in graph_tables(graph).items():
            if a.dtype == np.int32 and a.size and _INT16.min <= a.min() and a.max() <= _INT16.max:
                a = a.astype(np.int16)
            arrays[f"{level}.{field}"] = a
    return arrays


def _design_from(arrays: dict[str, np.ndarray]) -> _Design:
    graphs = tuple(
        graph_from_tables(
            {f: arrays[f"{level}.{f}"] for f in GRAPH_TABLES},
            periodic=bool(arrays[f"{level}.periodic"]),
        )
        for level in range(2)
    )
    slots = tuple(tuple(tuple(map(int, level)) for level in c) for c in arrays["slots"])
    n_samples = tuple(int(n) for n in arrays["n_samples"])
    return _Design(jnp.asarray(arrays["d_values"]), graphs, n_samples, int(arrays["split"]), slots)


def _tiled(size) -> tuple[int, int]:
    """The drawn map's shape: ``size`` rounded up to whole tiles."""
    return tuple(-(-n // _TILE) * _TILE for n in size)


def _layout(key, size, d_range, n_steps, d_levels) -> _Layout:
    """The layout of a fit of a ``size`` patch, built anew."""
    design = _design(key, d_range, d_levels)
    return _sized(design, size, n_steps, _draw_entries(key, design, size, n_steps))


def _sized(design: _Design, size, n_steps, entries) -> _Layout:
    """``design`` drawn at ``size`` with ``entries`` bins' pairs per level."""
    shape = _tiled(size)
    # the bins enumerate pairs, so a primitive may touch every tile at no extra cost
    span = (max(shape) // _TILE,) * 2
    return _Layout(
        design.d_values, design.graphs, tuple(map(int, size)), shape, design.n_samples,
        int(n_steps), span, tuple(entries), design.split, design.slots,
    )  # fmt: skip


def _design(key, d_range, d_levels) -> _Design:
    lo, hi = d_range
    ranges = ((lo, hi), (lo / 2, hi / 2))
    keys = tuple(jax.random.split(key))
    caps = _capacities(lo)
    d_values = np.linspace(lo, hi, d_levels, dtype=np.float32)
    pores, pore_flags = _grid_pores(keys, jnp.asarray(d_values), ranges, caps)
    _checked(None, pore_flags, SAMPLING_ERRORS)
    # the densest and the sparsest, on the host (measured there, not drawn)
    ends = [jax.tree.map(lambda a, j=j: np.asarray(a)[j], pores) for j in (0, -1)]
    specs = tuple(covering_spec([e[i] for e in ends], ranges[i]) for i in range(2))
    graphs, graph_flags = _grid_graphs(pores, specs)
    for flags, spec in zip(graph_flags, specs, strict=True):
        _checked(None, flags, graph_errors(spec))
    graphs = tuple(trim_batch(g) for g in graphs)
    # the simulation's N: a fixed setting of the fit, about twice the densest graph's edges, so
    # that the fit's 50 steps carve the patch (N = |E| would need ~5x the steps; the paper's
    # 50,000 on a patch of a few thousand edges decays by a quarter per step)
    n_samples = tuple(min(N_SAMPLES, specs[level].k * caps[level]) for level in range(2))
    split, slots = _size_classes(graphs)
    return _Design(jnp.asarray(d_values), graphs, n_samples, split, slots)


def _size_classes(graphs: tuple[PoreGraph, PoreGraph]):
    """The split of the grid into a dense and a sparse size class that minimises the mean slots
    (nodes and edges of both levels) over the grid, and each class's slots per level. Two
    classes save most of what more would (256², measured per agent: two classes 24-27 % less
    time, four 28-35 %, but with three times the swarm's compile time)."""
    counts = np.stack([np.stack([g.node_count, g.edge_count], -1) for g in graphs], 1)  # (K,2,2)
    caps = [(g.node_mask.shape[-1], g.edge_mask.shape[-1]) for g in graphs]
    k = counts.shape[0]

    def slots(first, stop):  # (level, (nodes, edges)) of grid values first..stop-1
        return tuple(
            tuple(min(_round_up(max(int(n), 1)), c) for n, c in zip(level, cap, strict=True))
            for level, cap in zip(np.max(counts[first:stop], axis=0), caps, strict=True)
        )

    def mean_slots(split):
        return split * np.sum(slots(0, split)) + (k - split) * np.sum(slots(split, k))

    split = min(range(1, k), key=mean_slots)
    return split, (slots(0, split), slots(split, k))


def _capacities(d) -> tuple[int, int]:
    """The two levels' pore capacities at α_d (packing bounds, as sample_pores sizes them)."""
    first = default_capacity(d)
    return first, default_capacity(d / 2, initial=first)


def _pores(keys, d, ranges, caps):
    """The two levels' pores of α_d (level 2 at half the distance, starting from level 1's), and
    the sampling's error flags of either level."""
    d = jnp.asarray(d, jnp.float32)
    p1, f1, _ = sampled(keys[0], d, None, None, caps[0], ranges[0], True)
    p2, f2, _ = sampled(keys[1], d / 2, None, p1, caps[1], ranges[1], True)
    return (p1, p2), {name: f1[name] | f2[name] for name in f1}


def _checked(value, flags: dict, messages: dict):
    """``value``, unless one of the (concrete) error ``flags`` of a batch is set."""
    for name, flag in flags.items():
        if bool(np.any(np.asarray(flag))):
            raise ValueError(f"the fit's pores and graphs: {messages[name]}")
    return value


@functools.partial(jax.jit, static_argnums=(2, 3))
def _grid_pores(keys, d_values, ranges, caps):
    """Both levels' pores for every α_d, sampled as one batch (the sampling is a long loop of
    small steps), and their error flags per α_d (returned: a program that raises holds host
    callbacks, which the persistent compilation cache does not keep)."""
    return jax.vmap(lambda d: _pores(keys, d, ranges, caps))(d_values)


@functools.partial(jax.jit, static_argnums=1)
def _grid_graphs(pores, specs):
    """Both levels' graphs for every α_d (one compile for the whole grid) and their error flags,
    built one after the other (a batch would hold every grid value's crossing search in memory
    at once)."""

    def one(levels):
        out = [built(p, spec)[:2] for p, spec in zip(levels, specs, strict=True)]
        return tuple(zip(*out, strict=True))  # (graphs, flags), a pair per level

    return jax.lax.map(one, pores)


def _draw_entries(key, design: _Design, size, n_steps) -> tuple[int, int]:
    """Binned (primitive, tile) pairs per level that draw the densest and the sparsest α_d of
    ``design`` at ``size`` with the simulation's default weights and the drawing fields at
    ``_WIDE``, with headroom (2x)."""
    key, shape, d_values = jax.random.split(key)[0], _tiled(size), design.d_values
    entries = []
    ends = jnp.asarray([0, len(d_values) - 1])
    for level in range(2):
        params = WrinkleParams(d=float(d_values[0]) / (1 + level), **_WIDE)
        ds = d_values[ends] / (1 + level)
        pairs = _extremes(
            key, design.graphs[level], params, ends, ds, shape, design.n_samples[level], n_steps,
            level == 0,
        )  # fmt: skip
        entries.append(_round_up(2 * max(int(np.max(pairs)), 1)))
    return tuple(entries)


@functools.partial(jax.jit, static_argnums=(5, 6, 7, 8))
def _extremes(key, graphs, params, ends, ds, shape, n_samples, n_steps, bulge):
    """Binned pairs of the grid's graphs ``ends``, each simulated with ``params`` at its α_d
    ``ds`` and drawn with the ``bulge`` profile or not (one compile per level)."""

    def one(end_d):
        g = jax.tree.map(lambda a: a[end_d[0]], graphs)
        p = _with(params, {"d": end_d[1]})
        w = simulate(key, g, p, n_steps=n_steps, n_samples=n_samples)
        prims = primitives(key, g, w, p, shape)
        return entries_of(prims, shape, tile=_TILE, bulge=bulge, periodic=True)

    return jax.lax.map(one, (ends, ds))


def _simulate(key, levels: tuple[WrinkleParams, WrinkleParams], layout: _Layout):
    """Graphs and trail weights of both levels (α_d snapped to the layout's grid)."""
    k = jax.random.split(key, 2)
    graphs = layout.select(levels[0].d)[1]
    levels = _snapped(levels, layout)
    sims = tuple(
        (g, simulate(kk, g, p, n_steps=layout.n_steps, n_samples=n))
        for kk, g, p, n in zip(k, graphs, levels, layout.n_samples, strict=True)
    )
    return sims, levels


def _draw(key, sims, levels, layout: _Layout) -> Float[Array, "H W"]:
    """Both levels drawn and summed (the finest with the no-bulge profile, as in the paper)."""
    return _draw_checked(key, sims, levels, layout)[0]


def _draw_checked(
    key, sims, levels, layout: _Layout, room: Array | None = None, table=None
) -> tuple[Float[Array, "H W"], Array]:
    """Like :func:`_draw`, plus whether some level was too large for the static draw sizes (or
    made more (primitive, tile) pairs than ``room``, per level, allows; ``table``: the
    perturbation's noise where it is at hand: see :class:`_SwarmLoss`).

    Extreme agents (e.g. α_blend = 1 summing a dozen wrinkles into huge pores) can make more
    (primitive, tile) pairs than the bins hold, which would leave the map incomplete. Such a
    level is drawn without primitives and flagged, so its loss becomes NaN, which the swarm
    contains and counts (and the refinement's line search backs off from). Every tile is drawn
    with as many passes as it needs, differentiably (the drawing's own gradient).
    """
    out, bad = jnp.zeros(layout.shape, jnp.float32), jnp.zeros((), bool)
    for i, (k_noise, prims, bins) in enumerate(_binned(key, sims, levels, layout, room, table)):
        bins = bins._replace(count=jnp.where(bins.overflow, 0, bins.count))  # no primitive then
        out = out + render(k_noise, prims, bins, levels[i], layout.shape, _options(i, layout), True)
        bad = bad | bins.overflow
    return out[: layout.size[0], : layout.size[1]], bad


def _options(level: int, layout: _Layout) -> DrawOptions:
    """Rasteriser settings of a level (the finest without bulge, as in the paper)."""
    return DrawOptions(
        bulge=level == 0, tile=_TILE, capacity=_CAPACITY, span=layout.span[level],
        passes=None, beta=BETA, n_hat=N_HAT, entries=layout.entries[level],
    )  # fmt: skip


def _level_keys(key) -> list[tuple[Array, Array]]:
    """Per level, the keys of a draw's perturbation and of its additive noise."""
    return [tuple(jax.random.split(k)) for k in jax.random.split(jax.random.fold_in(key, 7))]


def _binned(key, sims, levels, layout: _Layout, room: Array | None = None, table=None):
    """Per level: the noise key, the primitives and their bins (``room``: the pairs each
    level's bins may hold, default its entries; ``table``: a :class:`_NoiseTable`, or None)."""
    index = layout.index(levels[0].d)
    for i, ((k_perturb, k_noise), (graph, w), params) in enumerate(
        zip(_level_keys(key), sims, levels, strict=True)
    ):
        opts = _options(i, layout)
        noise = None if table is None else table.noise(key, i, index, graph, params)
        prims = primitives(k_perturb, graph, w, params, layout.shape, noise)
        bins = bin_primitives(
            prims, layout.shape, tile=_TILE, span=opts.span, bulge=opts.bulge, periodic=True,
            entries=opts.entries, room=None if room is None else room[i],
        )  # fmt: skip
        yield k_noise, prims, bins


def _levels_from(x: Array, names: Sequence[str], base: tuple[WrinkleParams, WrinkleParams]):
    """Both levels with the named entries of ``x`` set (level 2's α_d is half of level 1's)."""
    changes: tuple[dict, dict] = ({}, {})
    for i, name in enumerate(names):
        if name == "d":
            changes[0]["d"], changes[1]["d"] = x[i], x[i] / 2
        elif name in ("fnoise", "snoise"):
            changes[0][name] = x[i]
        else:
            level, field = name.split(".")
            changes[int(level) - 1][field] = x[i]
    return tuple(_with(p, c) for p, c in zip(base, changes, strict=True))


def _with(params: WrinkleParams, changes: dict[str, Array]) -> WrinkleParams:
    """``params`` with some fields replaced by (traced) values; ``tree_at`` skips the range
    check, which needs concrete values (the swarm keeps values inside their bounds)."""
    if not changes:
        return params
    names = list(changes)
    values = [jnp.asarray(changes[n], jnp.float32) for n in names]
    return eqx.tree_at(lambda p: [getattr(p, n) for n in names], params, values)


class _NoiseTable(eqx.Module):
    """The perturbation's noise (:func:`perturbation_noise`) of one simulation key's draws on
    every graph of a layout's grid, per level, stacked over the grid's values. It depends on
    the key, the graph and α_fperturb alone (not fitted), yet costs a seventh to a fifth of an
    agent's evaluation: a large fit computes it once per trial (:func:`_noise_table`) and
    draws each agent with its graph's rows, the same bits as computed in its draw."""

    key: Array  # the key's data
    levels: tuple[tuple[Array, Array], ...]

    def noise(self, key, level: int, index, graph: PoreGraph, params: WrinkleParams):
        """Level ``level``'s noise for ``graph``, grid value ``index`` (its rows cut to the
        graph's slots), where ``key`` is the table's, else computed (a held-out key's draws)."""
        pores, verts = (a[index] for a in self.levels[level])
        rows = (pores[: graph.positions.shape[0]], verts[: graph.edge_mask.shape[0]])
        mine = jnp.all(jax.random.key_data(key) == self.key)
        k_perturb = _level_keys(key)[level][0]
        computed = functools.partial(perturbation_noise, k_perturb, graph, params)
        return jax.lax.cond(mine, lambda: rows, computed)


@eqx.filter_jit
def _noise_table(key, layout: _Layout, base: tuple[WrinkleParams, WrinkleParams]) -> _NoiseTable:
    """The :class:`_NoiseTable` of ``key`` on ``layout``'s graphs (α_fperturb from ``base``)."""
    keys = [k_perturb for k_perturb, _ in _level_keys(key)]
    levels = tuple(
        jax.vmap(functools.partial(perturbation_noise, k), (0, None))(graphs, params)
        for k, graphs, params in zip(keys, layout.graphs, base, strict=True)
    )
    return _NoiseTable(jax.random.key_data(key), levels)


class _SwarmLoss(eqx.Module):
    """Losses of the swarm ``(M, P) → (M,)``: simulate, draw, compare statistics (arrays are
    traced leaves). The agents are evaluated one after the other (``lax.map``; batching them
    with ``vmap`` was no faster per agent), each with the program of its α_d's size class
    (``lax.switch``: the graphs cut to that class's slots, :meth:`_Layout.narrowed`) and with
    the passes its own tiles need rather than the densest agent's.

    With a ``mesh`` (axis ``"agents"``) the agent axis is sharded over its devices
    (``shard_map``): the agents are padded to a multiple of the device count with copies of
    agent 0, each device evaluates its share, and the padding's losses are dropped. An agent's
    loss has the same bits in any share (tested: 6 agents on 1 device and on 4; measured: 8
    agents on 1, 3 and 4), so the fit does not depend on the device count.

    ``room`` (traced, per level; None: the layout's entries) caps the (primitive, tile) pairs
    a level may draw below the layout's static entries: a small fit's swarm bins hold twice
    what it may draw, so that held-out keys whose maps need more are scored by the same program
    with more room rather than by a second one to compile (:func:`_heldout`).

    ``table`` (a :class:`_NoiseTable` of ``key``, or None) holds the perturbation's noise on
    every graph of the grid: the agents take their rows instead of computing them (a key other
    than the table's, e.g. a held-out one, computes its own)."""

    key: Array
    target: Any
    base: tuple[WrinkleParams, WrinkleParams]
    layout: _Layout
    names: tuple[str, ...] = eqx.field(static=True)
    mesh: Mesh | None = eqx.field(static=True, default=None)
    room: Array | None = None
    table: _NoiseTable | None = None

    def __call__(self, xs):
        if self.mesh is None:
            return self._share(xs)
        n, d = xs.shape[0], self.mesh.size
        padded = -(-n // d) * d
        if padded != n:  # equal shares: pad with copies of agent 0, drop their losses below
            xs = jnp.concatenate([xs, jnp.broadcast_to(xs[:1], (padded - n, *xs.shape[1:]))])
        arrays, rest = eqx.partition(self, eqx.is_array)
        agents = PartitionSpec("agents")

        def share(arrays, xs):
            return eqx.combine(arrays, rest)._share(xs)

        sharded = jax.shard_map(
            share,
            mesh=self.mesh,
            in_specs=(PartitionSpec(), agents),
            out_specs=agents,
            check_vma=False,  # the simulation's conds mix per-agent and shared values
        )
        return sharded(arrays, xs)[:n]

    def _share(self, xs):
        """Losses of the agents ``xs`` on one device."""

        classes = [
            functools.partial(self._map, self.layout.narrowed(c))
            for c in range(len(self.layout.slots))
        ]

        def undrawable(levels):
            return jnp.float32(jnp.nan)

        def one(x):
            levels = _levels_from(x, self.names, self.base)
            # an agent with a non-finite entry is undrawable at no cost (a held-out score's
            # unused rows); the branch also keeps one class a conditional, which draws an
            # agent the same way whatever the number of agents in a share
            drawable = jnp.all(jnp.isfinite(x))
            which = jnp.where(drawable, self.layout.size_class(levels[0].d), len(classes))
            return jax.lax.switch(which, [*classes, undrawable], levels)

        return jax.lax.map(one, xs)

    def _map(self, layout: _Layout, levels):
        """The loss of one agent (NaN where undrawable)."""
        sims, levels = _simulate(self.key, levels, layout)
        image, bad = _draw_checked(self.key, sims, levels, layout, self.room, self.table)
        return jnp.where(bad, jnp.nan, _loss(image, self.target))


def _loss(image, target: TextureStats) -> Float[Array, ""]:
    return texture_distance(_stats(image, 4, 4, "reflect"), target)


def _bounds(names, d_range, overrides) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    unknown = sorted(set(overrides) - set(names))
    if unknown:
        raise ValueError(f"bounds name parameters that are not fitted: {unknown}")
    low, high, cyclic = [], [], []
    for name in names:
        field = name.split(".")[-1]
        lo, hi = allowed = d_range if name == "d" else PARAMETER_RANGES[field]
        if name in overrides:
            lo, hi = _search_range(name, overrides[name], allowed)
        low.append(lo)
        high.append(hi)
        cyclic.append(field == "theta")
    return np.array(low), np.array(high), np.array(cyclic)


def _search_range(name: str, given: Any, allowed: tuple[float, float]) -> tuple[float, float]:
    """A (low, high) override of a search range, within the range the parameter allows."""
    where = "d_range" if name == "d" else "Table 1"
    try:
        lo, hi = (float(v) for v in given)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"bounds[{name!r}] must be (low, high), got {given!r}") from None
    if not (allowed[0] <= lo < hi <= allowed[1]):
        raise ValueError(
            f"bounds[{name!r}] must satisfy {allowed[0]} <= low < high <= {allowed[1]} "
            f"({where}), got ({lo}, {hi})"
        )
    return lo, hi


def checked_target(target_patch: Any) -> Float[Array, "H W"]:
    """``target_patch`` as the float32 map :func:`fit_wrinkles` fits, or the error it would
    raise: a patch that is not a finite 2-D float map, not square (the fit draws a periodic
    map), under 64² (the loss compares 4 pyramid levels) or constant. For checking many patches
    before fitting any."""
    target = _checks.float_array(target_patch, "target_patch", ndim=2, dtype=jnp.float32)
    if target.shape[0] != target.shape[1]:
        raise ValueError(
            f"target_patch must be square (the fit draws a periodic map), got {target.shape}"
        )
    if target.shape[0] < 64:
        raise ValueError(
            f"target_patch must be at least 64×64 (the loss compares 4 pyramid levels), got "
            f"{target.shape}"
        )
    if float(jnp.std(target)) == 0.0:
        raise ValueError("target_patch is constant: there is no texture to fit")
    return target


def fit_wrinkles(
    key: Any,
    target_patch: Any,
    *,
    names: Sequence[str] = PAPER_NAMES,
    base: tuple[WrinkleParams, WrinkleParams] | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    d_range: tuple[float, float] = D_RANGE,
    n_agents: int = 50,
    n_epochs: int = 100,
    n_trials: int = 3,
    n_steps: int = 50,
    refine_steps: int | None = None,
    refine_starts: int | None = None,
    d_levels: int | None = None,
    mode: str = "fast",
    coordinate_search: bool | None = None,
    progress=None,
    devices: Sequence[jax.Device] | None = None,
) -> WrinkleFit:
    """Fit two-level wrinkle parameters to a displacement patch (§4.2 of Weiss et al. 2023).

    Args:
        key: JAX random key (swarm, pores, simulation, drawing).
        target_patch: ``(H, W)`` displacement map, ``min(H, W) >= 64``; it is compared through
            :func:`jface.optim.texture_stats` (normalised to zero mean, unit variance).
        names: parameters to fit: ``"d"`` (α_d of level 1; level 2 uses half), ``"1.<field>"`` /
            ``"2.<field>"`` for a field of :class:`WrinkleParams` on one level, ``"fnoise"`` and
            ``"snoise"`` (the noise level, drawn with level 1). Default: the paper's 27.
        base: values of everything not fitted, ``(level 1, level 2)``; default
            ``WrinkleParams(d=0.035)`` and level 2 at half the distance with ``snoise`` at its
            minimum (one noise level). Level 2's α_d is always half of level 1's.
        bounds: narrower search ranges (``{name: (low, high)}`` for fitted names; the swarm's and
            the refinement's), within the parameter's Table 1 range (within ``d_range`` for
            ``"d"``).
        d_range: search range of α_d (fixes the pore capacities).
        n_agents, n_epochs, n_trials: swarm size, epochs, trials (paper: 50, 100, 3).
        n_steps: simulation steps per level (paper: 50).
        refine_steps: BFGS steps on the drawing parameters afterwards, at most, from each start
            (0: none; default: :data:`REFINE_STEPS` of the mode).
        refine_starts: starts of that refinement, at most (default: one, more up to
            :data:`REFINE_STARTS` while they cost at most a tenth of the swarm's evaluations,
            and one more for each start's cost in the epochs of the race's budget that its
            last trial left unspent, stalling or stopping at :data:`FAST_EPOCHS`; the third
            number of :func:`fit_budget` is the most).
        d_levels: α_d values (evenly spaced over ``d_range``) whose pores and graphs are built
            once (default: :data:`D_LEVELS` of the mode); an agent simulates with the nearest,
            and that value is what the result reports.
        mode: ``"fast"`` (default): the trials race by successive halving (each runs
            ``n_epochs // 8`` epochs, the better half goes on; the last runs up to ``n_epochs``,
            at most :data:`FAST_EPOCHS`)
            and the swarm stops when its best loss fell by less than 1 % over 10 epochs;
            when a rung holds :data:`POLISH_FROM` evaluations or more, every trial's best is
            refined (as at the end) after each of its rungs and, when that gains and stays in
            the search box, rejoins its swarm as its best agent's personal best (its refined
            entries also tried on every other personal best, kept where they gain), so the race
            compares refined answers (``progress`` saw the epoch's best before), and the last
            trial's stall is judged after each rung's polish; the epochs it leaves when it
            stalls buy more refinement starts, and the swarm's inertia decays faster than the
            paper's (:data:`INERTIA`); the refined answer is the start of a coordinate search
            over the fitted simulation parameters (each tried 5 % and 10 % of its search range
            either way, up to :data:`COORDINATE_PASSES` passes, then at half and a quarter of
            those steps, :data:`COORDINATE_SCALES`; :func:`coordinate_evaluations` evaluations
            at most), whose answer, where it gains, is refined once more (see
            ``coordinate_search``);
            ``"paper"``: every trial runs all ``n_epochs`` (the paper's procedure).
        coordinate_search: whether a fast fit ends with the coordinate search (default: where
            it and the refinement of its answer cost at most a tenth of the evaluations of the
            budget, as in a default fit; the fourth number of :func:`fit_budget`); never in
            paper mode.
        progress: ``progress(trial, epoch, best_loss)`` after every epoch. Raising
            ``KeyboardInterrupt`` there (or Ctrl-C) stops the fit, which then returns the best
            found so far (unrefined; while refining: the best start refined by then; while
            searching coordinates: the refined answer), with ``interrupted`` set.
        devices: devices the swarm's agents are sharded over (``jax.sharding``; default: this
            process's devices, :func:`jax.local_devices`, at most one per agent, for swarms of
            :data:`SHARD_FROM` evaluations or more, else the first); the agents are padded to a
            multiple of the device count with copies of agent 0. On the CPU, JAX has one device
            unless asked for more before its backend starts (``XLA_FLAGS``
            ``--xla_force_host_platform_device_count``, as the command line sets one per core,
            :func:`jface.detail.cpu_device_flags`, or ``JAX_NUM_CPU_DEVICES``). The result has
            the same bits on any number of devices (on CPU with XLA's Eigen single-threaded,
            :func:`jface.detail.deterministic_cpu_flags`).

    Returns:
        A :class:`WrinkleFit`.

    Raises:
        TypeError/ValueError: a non-float, non-2-D, non-square, too small, non-finite or
            constant patch, unknown names, bad ranges or counts, ``devices`` that are not
            distinct devices of this process.
    """
    key = _checks.key(key)
    target = checked_target(target_patch)
    names = tuple(names)
    known = {"d", "fnoise", "snoise"} | {f"{lv}.{n}" for lv in (1, 2) for n in PARAMETER_RANGES}
    unknown = [n for n in names if n not in known or n in ("1.d", "2.d")]
    if unknown or not names or len(set(names)) != len(names):
        raise ValueError(
            f"names must be distinct entries of 'd', 'fnoise', 'snoise', '<1|2>.<field>' "
            f"(α_d only as 'd'), got {names!r}"
        )
    lo_d, hi_d = d_range
    lo_t, hi_t = PARAMETER_RANGES["d"]
    if not (lo_t <= lo_d < hi_d <= hi_t and lo_d >= 0.01):
        raise ValueError(f"d_range must lie in [0.01, {hi_t}] with low < high, got {d_range}")
    bounds = dict(bounds or {})
    if base is None:
        base = (
            WrinkleParams(d=(lo_d + hi_d) / 2),
            WrinkleParams(d=(lo_d + hi_d) / 4, snoise=0.001),
        )
    base = (base[0], base[1].replace(d=base[0].d / 2))
    if "d" not in names and not lo_d <= float(base[0].d) <= hi_d:
        raise ValueError(f"base α_d {float(base[0].d)} lies outside d_range {d_range}")
    low, high, cyclic = _bounds(names, d_range, bounds)
    fields = _drawing_fields(names, low, high)

    n_steps = _checks.integer(n_steps, "n_steps", low=1)
    mode = _checks.choice(mode, "mode", ("fast", "paper"))
    d_levels = _checks.integer(D_LEVELS[mode] if d_levels is None else d_levels, "d_levels", low=2)
    if refine_steps is None:
        refine_steps = REFINE_STEPS[mode]
    refine_steps = _checks.integer(refine_steps, "refine_steps", low=0)
    n_trials = _checks.integer(n_trials, "n_trials", low=1)
    n_epochs = _checks.integer(n_epochs, "n_epochs", low=1)
    n_agents = _checks.integer(n_agents, "n_agents", low=3)
    if coordinate_search is None:
        steps = refine_steps if fields else 0  # nothing to refine without drawing fields
        coordinate_search = _searches(mode, n_agents, n_trials, n_epochs, steps, names)
    elif not isinstance(coordinate_search, bool) or (coordinate_search and mode == "paper"):
        raise ValueError(
            f"coordinate_search must be True or False (True only in fast mode), got "
            f"{coordinate_search!r} in {mode} mode"
        )
    settings = swarm_settings(n_agents, batched=True, inertia=INERTIA[mode])
    evaluations = n_agents * (n_epochs + 1) * n_trials
    mesh = _agent_mesh(devices, n_agents, evaluations)
    if refine_starts is not None:  # else counted after the swarm, from the epochs it left
        refine_starts = _checks.integer(refine_starts, "refine_starts", low=1)
    k_sim, k_swarm = jax.random.split(key)
    # each new patch size compiles programs of its own: a process fitting many must not crash
    spare_memory_mappings()
    layout = _kept_layout(layout_key(), target.shape, d_range, n_steps, d_levels)
    whole, room = layout.merged(), None
    if evaluations < SPLIT_FROM:
        # bins of twice the pairs, drawn up to the fit's own (the same losses): the held-out
        # keys that need more, about half of them near an answer with wide pores, are then
        # scored by the swarm's program, not by a second one compiled for them
        room = jnp.asarray(whole.entries, jnp.int32)
        layout = whole.roomier()
    target_stats = texture_stats(target)
    sim_keys = jax.random.split(k_sim, n_trials)
    # the perturbation's noise on every graph, once per trial, where the evaluations repay it
    tabled = evaluations >= SPLIT_FROM and not any(n.endswith("fperturb") for n in names)
    tables = [_noise_table(sk, layout, base) if tabled else None for sk in sim_keys]
    # one swarm per trial, each with its own simulation key; all share one compiled loss
    runs = [
        _Trial(k, _SwarmLoss(sk, target_stats, base, layout, names, mesh, room, table))
        for k, sk, table in zip(jax.random.split(k_swarm, n_trials), sim_keys, tables, strict=True)
    ]
    low, high = low.astype(np.float32), high.astype(np.float32)
    search = (low, high, cyclic, settings)
    # one refinement program for every answer (the whole grid's slots), compiled while the
    # swarm runs
    refining = whole.narrowed(0)
    refine_steps = refine_steps if fields else 0
    ahead = None
    if refine_steps:
        like = _levels_from(jnp.asarray((low + high) / 2), names, base)  # the answer's types
        refine_args = (refining, target_stats, fields, refine_steps)
        ahead = compile_ahead(_refined, sim_keys[0], like, *refine_args)
    # the fit's refinements by their starts, each solved once: a polish that gained nothing
    # comes back after the next rung when the swarm found nothing better, and as a start of the
    # final refinement
    solved = {}
    index = {name: i for i, name in enumerate(names)}

    def refined_params(params, refined: _Refined) -> np.ndarray:
        """``params`` with the drawing fields of a refinement's answer."""
        params = np.array(params)
        for lv, f, *_ in fields:
            params[index[f"{lv + 1}.{f}"]] = float(getattr(refined.levels[lv], f))
        return params

    def refine(sim_key, params, start):
        """:func:`_refine` of ``params`` with a trial's simulation key from its swarm loss
        ``start``."""
        bits = _key_bits(sim_key)
        name = (bits, np.asarray(params).tobytes(), float(start))
        if name not in solved:
            if ahead is not None:
                ahead.join()
            # from the host, as compiled ahead (a sharded swarm leaves its bests on its mesh)
            levels = _levels_from(jnp.asarray(np.asarray(params)), names, base)
            solved[name] = _refine(
                sim_key, levels, start, refining, target_stats, fields, refine_steps
            )
        return solved[name]

    polish = None
    if _polishes(mode, refine_steps, settings.n_agents, n_epochs):

        def polish(sim_key, best, start):  # the refinement of a trial's best, as parameters
            refined = refine(sim_key, best, start)
            return refined_params(best, refined), float(refined.loss)

    interrupted = False
    finished = list(range(n_trials))
    try:
        if mode == "paper":
            for t, run in enumerate(runs):
                run.advance(n_epochs, search, t, progress)
        else:
            finished = _halve(runs, n_epochs, search, progress, polish)
    except KeyboardInterrupt:  # keep what the swarms found so far
        interrupted = True
    swarm = _result(runs, low, high)
    epochs = tuple(len(r.history) - 1 for r in runs if r.swarm is not None)
    if refine_starts is None:  # the swarm's unspent epochs go to more starts
        planned = _budget_epochs(mode, n_trials, n_epochs)
        unspent = planned - sum(epochs)
        refine_starts = _refine_starts(settings.n_agents, planned, refine_steps, unspent)
    answers = []  # (trial, parameters, refined) of each start
    if not interrupted:
        try:
            starts = _starts(runs, finished, low, high, refine_starts if refine_steps else 1)
            for t, params, start in starts:
                answers.append((t, params, refine(sim_keys[t], params, start)))
        except KeyboardInterrupt:  # Ctrl-C while refining: the starts refined so far
            interrupted = True
    refined_losses = jnp.stack([a.loss for *_, a in answers]) if answers else jnp.zeros(0)
    if answers:
        t, params, answer = min(answers, key=lambda a: float(a[2].loss))  # the first of equals
        params = refined_params(params, answer)
    else:  # the swarm's answer as it is, unrefined (a compile may still be running)
        t, params = int(swarm.best_trial), swarm.params
        levels = _snapped(_levels_from(params, names, base), refining)
        answer = _Refined(levels, swarm.loss, None)
    if coordinate_search and not interrupted:

        def losses_of(rows):  # the swarm's program scores the search's every candidate
            return _agent_losses(runs[t].loss, rows, search)

        try:
            start = losses_of(params)[0]
            moved, loss = _coordinate_search(
                losses_of, params, start, names, search, COORDINATE_PASSES[mode]
            )
            if loss < start:  # its drawing parameters refined again, from its loss
                moved = np.asarray(moved, np.float32)
                answer = refine(sim_keys[t], moved, loss)
                params = refined_params(moved, answer)
        except KeyboardInterrupt:  # Ctrl-C while searching: the refined answer
            interrupted = True
    image = answer.image
    if image is None:  # a start the refinement did not beat (or none refined): drawn here
        image = _fitted_map(sim_keys[t], answer.levels, refining)
    count = heldout_key_count(n_agents, n_epochs, n_trials, mode=mode)
    heldout = _heldout(runs[t].loss, params, heldout_keys(key, count), search)
    return WrinkleFit(
        answer.levels, answer.loss, swarm.loss, swarm, names, sim_keys[t], image,
        interrupted, epochs, refined_losses, t, heldout,
    )  # fmt: skip


@functools.partial(eqx.filter_jit, compiler_options=QUICK_COMPILE)
def _fitted_map(sim_key, levels, layout: _Layout) -> Float[Array, "H W"]:
    """The map of ``levels`` simulated and drawn with ``sim_key``."""
    sims, levels = _simulate(sim_key, levels, layout)
    return _draw(sim_key, sims, levels, layout)


def _heldout(loss: _SwarmLoss, params, keys, search) -> Array:
    """Losses of ``params`` (one agent, in the fit's units) simulated and drawn with each of
    ``keys``: the trial's compiled swarm loss with another key and all the room of its bins
    (:class:`_SwarmLoss`), the agent in its first row and the other rows undrawable
    (non-finite), which cost nothing. A key whose map the swarm's static draw sizes cannot hold
    (non-finite there; twice the fit's own pairs in a small fit) is drawn again on bins of
    twice the pairs, a program compiled beside the other keys' losses from the first such key
    on (near an optimum that widens its pores, about half the keys of an answer overflow the
    fit's own pairs); a key that overflows those too is drawn on bins sized to its primitives,
    so every key has its loss; NaN only where even those bins overflow."""
    low, high = search[:2]
    lo, hi = jnp.asarray(low, jnp.float32), jnp.asarray(high, jnp.float32)
    x = jnp.asarray((np.asarray(params) - low) / (high - low), jnp.float32)
    units = lo + x * (hi - lo)  # the agent exactly as the swarm read it
    levels = _levels_from(units, loss.names, loss.base)
    layout = loss.layout.narrowed(int(loss.layout.size_class(levels[0].d)))
    roomier = layout.roomier()
    # the swarm's program with all the room its bins have; the redraws with all of their own
    room = None if loss.room is None else jnp.asarray(layout.entries, jnp.int32)
    keyed = [dataclasses.replace(loss, key=k, room=None) for k in keys]
    losses, ahead = np.empty(len(keys), np.float32), None
    for i, keyed_loss in enumerate(keyed):
        losses[i] = _agent_losses(dataclasses.replace(keyed_loss, room=room), params, search)[0]
        if ahead is None and not np.isfinite(losses[i]):
            ahead = compile_ahead(_redrawn_loss, keyed_loss, roomier, units)
    undrawn = np.flatnonzero(~np.isfinite(losses))
    if undrawn.size:
        ahead.join()
        for i in undrawn:
            losses[i] = _redrawn_loss(keyed[i], roomier, units)
        undrawn = undrawn[~np.isfinite(losses[undrawn])]
    if undrawn.size:
        roomy = _roomy(roomier, [_primitives_of(keyed[i].key, levels, layout) for i in undrawn])
        for i in undrawn:
            losses[i] = _redrawn_loss(keyed[i], roomy, units)
    return jnp.asarray(losses)


def _agent_losses(loss: Callable, rows, search) -> np.ndarray:
    """Losses of the agents ``rows`` (``(k, P)`` or one ``(P,)``, in the fit's units; +inf
    where undrawable) by a trial's compiled swarm loss: the agents dealt in turn to the shares of
    its devices (a sharded loss evaluates them side by side), the other rows undrawable
    (non-finite), which cost nothing."""
    low, high, _, settings = search
    mesh = getattr(loss, "mesh", None)  # a sharded loss's devices
    n, devices = settings.n_agents, 1 if mesh is None else mesh.size
    size = -(-n // devices)  # rows per device (the last share padded)
    slots = [d * size + i for i in range(size) for d in range(devices) if d * size + i < n]
    rows = np.atleast_2d(np.asarray(rows, np.float64))
    losses = []
    for first in range(0, len(rows), n):
        batch = rows[first : first + n]
        taken = slots[: len(batch)]
        x = np.full((n, low.shape[0]), np.nan, np.float32)
        x[taken] = (batch - low) / (high - low)
        s, _ = swarm_evaluate(loss, low, high, jnp.asarray(x), settings)
        losses.append(np.asarray(s)[taken])
    return np.concatenate(losses)


def _coordinate_search(
    losses_of, params, loss, names, search, passes: int, scales=COORDINATE_SCALES
):
    """A greedy coordinate search from ``params`` (the fit's units), whose loss is ``loss``:
    for each fitted simulation parameter of either level in turn (``names`` order), the values
    :data:`COORDINATE_STEPS` of its search range away, times a scale (α_θ wraps around, the
    others stay in their range), are scored by ``losses_of(rows) → losses`` and the best is kept
    where it lowers the loss; at each of ``scales`` in turn up to ``passes`` passes, the last
    one that gained nothing. Returns the parameters and their loss. The drawing parameters are
    the refinement's, α_d sits on its grid and the noise level is global: none of them is
    searched."""
    low, high, cyclic, _ = search
    params = np.asarray(params, np.float64)
    for scale in scales:
        steps = np.asarray(COORDINATE_STEPS) * scale
        for _ in range(passes):
            gained = False
            for i in _coordinates(names):
                span = float(high[i]) - float(low[i])
                values = params[i] + span * steps
                if cyclic[i]:
                    values = low[i] + np.mod(values - low[i], span)
                else:
                    values = values[(values >= low[i]) & (values <= high[i])]
                if not values.size:
                    continue
                rows = np.repeat(params[None], len(values), axis=0)
                rows[:, i] = values
                losses = losses_of(rows)
                best = int(np.argmin(losses))
                if losses[best] < loss:
                    params, loss, gained = rows[best], float(losses[best]), True
            if not gained:
                break
    return params, loss


def _coordinates(names) -> list[int]:
    """Indices of the fitted simulation parameters in ``names``: what the coordinate search
    moves."""
    return [i for i, n in enumerate(names) if "." in n and n.split(".")[1] not in DRAWING_NAMES]


def coordinate_evaluations(mode: str, names: Sequence[str] = PAPER_NAMES) -> int:
    """The most evaluations of :func:`fit_wrinkles`'s coordinate search (its start's and each
    pass's steps at each scale; a refinement of its answer follows where it gains): 289 for a
    default fast fit, 0 in paper mode."""
    passes = COORDINATE_PASSES[_checks.choice(mode, "mode", ("fast", "paper"))]
    steps = len(COORDINATE_SCALES) * len(COORDINATE_STEPS)
    return passes and 1 + passes * steps * len(_coordinates(names))


def _roomy(layout: _Layout, maps: Sequence[list]) -> _Layout:
    """``layout`` with draw sizes that hold each of ``maps`` (per map its levels' primitives),
    with a margin for a primitive that lands on a tile border in another compile: one program
    draws them all."""
    spans, entries = list(layout.span), list(layout.entries)
    for prims_of_levels in maps:
        for i, prims in enumerate(prims_of_levels):
            sized = {"tile": _TILE, "bulge": _options(i, layout).bulge, "periodic": True}
            spans[i] = max(spans[i], needed_span(prims, layout.shape, **sized) + 1)
            n = needed_entries(prims, layout.shape, **sized)
            entries[i] = max(entries[i], _round_up(n + n // 8 + 1))
    return dataclasses.replace(layout, span=tuple(spans), entries=tuple(entries))


@functools.partial(eqx.filter_jit, compiler_options=QUICK_COMPILE)
def _primitives_of(key, levels, layout: _Layout) -> list:
    """Each level's primitives of ``levels`` simulated and drawn with ``key``."""
    sims, levels = _simulate(key, levels, layout)
    return [prims for _, prims, _ in _binned(key, sims, levels, layout)]


@functools.partial(eqx.filter_jit, compiler_options=QUICK_COMPILE)
def _redrawn_loss(loss: _SwarmLoss, layout: _Layout, units) -> Array:
    """The loss of one agent (the fit's units) drawn on ``layout``, NaN if that overflows."""
    return loss._map(layout, _levels_from(units, loss.names, loss.base))


def _agent_mesh(devices, n_agents: int, evaluations: int) -> Mesh | None:
    """The mesh (axis ``"agents"``) of ``devices``, None for one device (no sharding). By default
    a swarm of ``evaluations`` from :data:`SHARD_FROM` on is sharded over the devices of this
    process, at most one per agent, a smaller one runs on the first."""
    local = jax.local_devices()
    if devices is None:
        devices = local[:n_agents] if evaluations >= SHARD_FROM else local[:1]
    expected = "a non-empty sequence of distinct devices of this process (jax.local_devices())"
    if isinstance(devices, jax.Device | str | bytes) or not isinstance(devices, Sequence):
        raise TypeError(f"devices must be {expected}, got {_checks.describe(devices)}")
    devices = list(devices)
    foreign = [d for d in devices if not isinstance(d, jax.Device) or d not in local]
    if not devices or foreign or len(set(devices)) != len(devices):
        what = f"{foreign[0]!r} among them" if foreign else f"{devices!r}"
        raise ValueError(f"devices must be {expected}, e.g. {local}; got {what}")
    return Mesh(np.array(devices), ("agents",)) if len(devices) > 1 else None


class _Trial:
    """One trial's swarm, advanced an epoch at a time, with its best loss after each epoch.
    ``loss``: the swarm's batched loss (a :class:`_SwarmLoss`), with the trial's simulation
    ``key``."""

    def __init__(self, key, loss: Callable):
        self.key, self.loss, self.swarm, self.history = key, loss, None, []

    def advance(self, epochs: int, search, index: int, progress, stall: bool = False) -> None:
        """Up to ``epochs`` more epochs (the first call starts the swarm); with ``stall``, stop
        once the best loss fell by less than ``STALL_TOLERANCE`` over ``PATIENCE`` epochs."""
        low, high, cyclic, settings = search
        if self.swarm is None:
            self.swarm = swarm_start(self.key, self.loss, low, high, settings)
            self.history.append(float(self.swarm.best))
        for _ in range(epochs):
            if stall and self.stalled():
                return
            self.swarm = swarm_epoch(self.swarm, self.loss, low, high, cyclic, settings)
            self.history.append(float(self.swarm.best))
            if progress is not None:
                progress(index, len(self.history) - 1, self.history[-1])

    def polish(self, polish, search) -> None:
        """Make ``polish(sim_key, best, best_loss) → (params, loss)`` of the swarm's best its
        best agent's personal best, when it is better and inside the search box (None: no-op),
        and try the entries the polish changed on every other agent's personal best (one
        evaluation of the swarm), which keeps them where they gain; the history's last entry
        becomes the new best. The polish refines the drawing parameters for the best agent's
        trails; shared, they let the swarm compare the other agents' simulation parameters
        with drawing parameters that suit trails, rather than with its own guesses."""
        if polish is None or self.swarm is None:
            return
        low, high, _, settings = search
        w = self.swarm
        i = int(jnp.argmin(w.ps))
        best = np.asarray(w.best_params(low, high))
        params, loss = polish(self.loss.key, best, w.best)
        # the entries the polish left keep their normalised values exactly
        u = np.where(params == best, w.p[i], (np.asarray(params) - low) / (high - low))
        if not (loss < float(w.best) and np.all((u >= 0) & (u <= 1))):
            return
        w = eqx.tree_at(lambda s: (s.p, s.ps), w, (w.p.at[i].set(u), w.ps.at[i].set(loss)))
        x = np.where(params != best, u, np.asarray(w.p)).astype(np.float32)
        losses, bad = swarm_evaluate(self.loss, low, high, x, settings)
        p, ps = _keep_better(x, losses, w.p, w.ps)
        self.swarm = eqx.tree_at(
            lambda s: (s.p, s.ps, s.n_nonfinite), w, (p, ps, w.n_nonfinite + bad)
        )
        self.history[-1] = float(self.swarm.best)

    def stalled(self) -> bool:
        h = self.history
        return len(h) > PATIENCE and h[-PATIENCE - 1] - h[-1] <= STALL_TOLERANCE * abs(h[-1])


def _halve(runs: list[_Trial], n_epochs: int, search, progress, polish=None) -> list[int]:
    """Successive halving: every trial runs a rung of ``n_epochs // 8`` epochs, the better half
    goes on to the next rung, and the last one runs up to ``n_epochs`` epochs in all (at most
    :data:`FAST_EPOCHS`), stopping early when it stalls. With ``polish``, every trial's best is
    polished after each of its rungs, before the trials are compared, and the last trial runs
    whole rungs (the last one cut at that limit), stopping when it is still stalled after a
    rung's polish: a trial runs ``ceil(epochs / rung)`` polishes. Returns the last trial (as a
    list: the trials that ran to their end). The epochs it leaves of ``n_epochs`` (when it
    stalls, and past the limit) go to refinement starts
    (:func:`_refine_starts`): running the trials it beat on with them made 17 default fits
    take 1.45x as long (median) for the same median loss (docs/wrinkles-fitting-log.md)."""
    rung, last = _rung(n_epochs), min(n_epochs, FAST_EPOCHS)
    alive = list(range(len(runs)))
    while len(alive) > 1:
        for t in alive:
            runs[t].advance(rung, search, t, progress)
            runs[t].polish(polish, search)
        alive = sorted(alive, key=lambda t: runs[t].history[-1])[: -(-len(alive) // 2)]
    (t,) = alive
    # a polishing fit runs whole rungs and judges its stall after the rung's polish (one that
    # gains sends the swarm on from the polished best)
    while (done := len(runs[t].history) - 1) < last and not runs[t].stalled():
        runs[t].advance(min(rung, last - done), search, t, progress, stall=polish is None)
        runs[t].polish(polish, search)
    return [t]


def _race_epochs(n_trials: int, n_epochs: int) -> tuple[int, int, int]:
    """Epochs of every trial of the fast mode's race together by its budget (the halved field's
    rungs, then the last trial's rest up to ``n_epochs``: what the race leaves of these buys
    refinement starts), that rest, and the most the race runs (the rest up to
    :data:`FAST_EPOCHS`)."""
    rung, epochs, done = _rung(n_epochs), 0, 0
    while n_trials > 1:
        epochs, done = epochs + n_trials * rung, done + rung
        n_trials = -(-n_trials // 2)
    rest = max(0, n_epochs - done)
    return epochs + rest, rest, epochs + max(0, min(n_epochs, FAST_EPOCHS) - done)


def _budget_epochs(mode: str, n_trials: int, n_epochs: int) -> int:
    """The epochs of a fit's budget, every trial's together: what its unspent epochs are
    counted from (:func:`_refine_starts`)."""
    return n_trials * n_epochs if mode == "paper" else _race_epochs(n_trials, n_epochs)[0]


def _refine_starts(n_agents: int, epochs: int, refine_steps: int, unspent: int = 0) -> int:
    """Starts of the final refinement after ``epochs`` of ``n_agents``: one, more (up to
    :data:`REFINE_STARTS`) while the extra ones cost at most a tenth of the epochs'
    evaluations, and one more for each start's cost (about ``7 * refine_steps`` evaluations) in
    the ``unspent`` epochs of a race whose last trial stalled before its end."""
    if not refine_steps:
        return 1
    cost = 7 * refine_steps
    return min(REFINE_STARTS, 1 + epochs * n_agents // (10 * cost)) + unspent * n_agents // cost


def _rung(n_epochs: int) -> int:
    """Epochs of a rung of the fast mode's race."""
    return max(1, n_epochs // 8)


def _polishes(mode: str, refine_steps: int, n_agents: int, n_epochs: int) -> bool:
    """Whether a fit polishes its trials' bests after every rung (fast mode, a refinement, and
    rungs of :data:`POLISH_FROM` evaluations or more)."""
    return mode == "fast" and refine_steps > 0 and n_agents * (n_epochs // 8) >= POLISH_FROM


def _searches(
    mode: str, n_agents: int, n_trials: int, n_epochs: int, refine_steps: int, names=PAPER_NAMES
) -> bool:
    """Whether a fit ends with the coordinate search by default: in fast mode, where its most
    evaluations and the refinement of its answer (about ``7 * refine_steps``) cost at most a
    tenth of the budget's evaluations (as the extra refinement starts, :func:`_refine_starts`)."""
    cost = coordinate_evaluations(mode, names) + 7 * refine_steps
    budget = _budget_epochs(mode, n_trials, n_epochs) * n_agents
    return mode == "fast" and 10 * cost <= budget


def fit_budget(
    n_agents: int = 50,
    n_epochs: int = 100,
    n_trials: int = 3,
    *,
    refine_steps: int | None = None,
    mode: str = "fast",
) -> tuple[int, int, int, int]:
    """The most swarm epochs (each ``n_agents`` evaluations), polishes (refinements of a
    trial's best, each at most about as dear as ``7 * refine_steps`` evaluations, and one
    evaluation of the swarm that shares what it refined) and starts of the
    final refinement that :func:`fit_wrinkles` with these settings runs (fitting drawing
    parameters, as the default names do; without them nothing is refined): all the epochs in
    paper mode; in fast mode a field of trials halved after every rung, then the last trial on
    to ``n_epochs``, at most :data:`FAST_EPOCHS` (fewer when it stalls). The starts: one, more
    (up to :data:`REFINE_STARTS`) while the extra ones cost at most a tenth of the budget's
    evaluations (the race up to ``n_epochs``), and in fast mode one more for each start's cost
    in the budget's epochs that the last trial left unspent (the most: all after the race,
    when it stalls there). Last, the most evaluations of the coordinate search that ends a fast
    fit (:func:`coordinate_evaluations`; 0 where it does not run, when it and the refinement of
    its answer would cost more than a tenth of the budget's evaluations)."""
    mode, n_agents, n_epochs, n_trials = _checked_budget(mode, n_agents, n_epochs, n_trials)
    refine_steps = REFINE_STEPS[mode] if refine_steps is None else refine_steps
    refine_steps = _checks.integer(refine_steps, "refine_steps", low=0)
    polishes, rest = 0, 0
    if mode == "paper":
        budget = epochs = n_trials * n_epochs
    else:
        budget, rest, epochs = _race_epochs(n_trials, n_epochs)
        if _polishes(mode, refine_steps, n_agents, n_epochs):
            # one after every rung (the last trial's last cut at its limit)
            polishes = -(-epochs // _rung(n_epochs))
    searched = _searches(mode, n_agents, n_trials, n_epochs, refine_steps)
    # the most unspent epochs: the last trial stalled at the end of the race
    starts = _refine_starts(n_agents, budget, refine_steps, rest)
    return epochs, polishes, starts, coordinate_evaluations(mode) if searched else 0


def _checked_budget(mode, n_agents, n_epochs, n_trials) -> tuple[str, int, int, int]:
    """A fit's mode and swarm sizes, checked as :func:`fit_wrinkles` checks them."""
    return (
        _checks.choice(mode, "mode", ("fast", "paper")),
        _checks.integer(n_agents, "n_agents", low=3),
        _checks.integer(n_epochs, "n_epochs", low=1),
        _checks.integer(n_trials, "n_trials", low=1),
    )


def heldout_key_count(
    n_agents: int = 50, n_epochs: int = 100, n_trials: int = 3, *, mode: str = "fast"
) -> int:
    """How many other simulation keys score the answer of :func:`fit_wrinkles` with these
    settings (:attr:`WrinkleFit.heldout_losses`, one evaluation each): as many as cost at most a
    tenth of the budget's evaluations (the race up to ``n_epochs`` in fast mode, every epoch in
    paper mode), between :data:`HELDOUT_MIN_KEYS` and :data:`HELDOUT_KEYS`."""
    mode, n_agents, n_epochs, n_trials = _checked_budget(mode, n_agents, n_epochs, n_trials)
    budget = _budget_epochs(mode, n_trials, n_epochs) * n_agents
    return min(HELDOUT_KEYS, max(HELDOUT_MIN_KEYS, budget // 10))


def _starts(runs: list[_Trial], finished: list[int], low, high, n: int):
    """``(trial, parameters, swarm loss)`` to refine, best first: the best of every ``finished``
    trial, then the best finished trial's next distinct personal bests, ``n`` in all at most."""
    bests = sorted(finished, key=lambda t: float(runs[t].swarm.best))
    w = runs[bests[0]].swarm
    ps, p = np.asarray(w.ps), np.asarray(w.p)
    order = [int(i) for i in np.argsort(ps, kind="stable")]
    others = [i for k, i in enumerate(order[1:], 1) if np.isfinite(ps[i])
              and not any(np.array_equal(p[i], p[j]) for j in order[:k])]  # fmt: skip
    starts = [(t, runs[t].swarm.best_params(low, high), runs[t].swarm.best) for t in bests]
    starts += [(bests[0], low + p[i] * (high - low), w.ps[i]) for i in others]
    return starts[: max(n, 1)]


def _result(runs: list[_Trial], low, high) -> PSOResult:
    """The trials as one :class:`PSOResult`; histories of trials that stopped early are padded
    with their final best (trials never started, after an interrupt, are left out)."""
    runs = [r for r in runs if r.swarm is not None]
    if not runs:
        raise KeyboardInterrupt  # nothing found yet
    longest = max(len(r.history) for r in runs)
    history = [r.history + [r.history[-1]] * (longest - len(r.history)) for r in runs]
    swarms: list[Swarm] = [r.swarm for r in runs]
    losses = jnp.stack([w.best for w in swarms])
    best = int(jnp.argmin(losses))
    params = jnp.stack([w.best_params(low, high) for w in swarms])
    return PSOResult(
        params=params[best],
        loss=losses[best],
        history=jnp.asarray(history, jnp.float32),
        trial_params=params,
        trial_losses=losses,
        n_nonfinite=jnp.stack([w.n_nonfinite for w in swarms]),
        best_trial=jnp.asarray(best),
    )


def _drawing_fields(names, low, high) -> tuple[tuple[int, str, float, float], ...]:
    """(level index, field, low, high) of the fitted drawing parameters, in their search ranges
    (``low``, ``high``: of every name): what the refinement optimises, within those ranges."""
    return tuple(
        (int(n[0]) - 1, n[2:], float(lo), float(hi))
        for n, lo, hi in zip(names, low, high, strict=True)
        if "." in n and n.split(".")[1] in DRAWING_NAMES
    )


class _Refined(NamedTuple):
    """A refinement's answer: its levels (α_d snapped to the grid), its loss, and its map (None
    when the answer is the start, whose map is drawn only where a fit reports it)."""

    levels: tuple[WrinkleParams, WrinkleParams]
    loss: Array
    image: Array | None


def _refine(sim_key, levels, start, layout, target_stats, fields, steps) -> _Refined:
    """BFGS on the drawing ``fields`` with the simulation result held fixed. ``start`` is the
    swarm's loss of ``levels``: the answer is kept unless the refinement beats it (a redraw of
    the same parameters can differ from the batched swarm's loss in the last bit)."""
    start = jnp.asarray(start, jnp.float32)
    if steps == 0 or not fields:
        return _Refined(_snapped(levels, layout), start, None)
    answer, loss, image = _refined(sim_key, levels, layout, target_stats, fields, steps)
    if not bool(loss < start):  # keep the swarm's answer unless beaten
        return _Refined(_snapped(levels, layout), start, None)
    return _Refined(answer, loss, image)


def _snapped(levels, layout: _Layout):
    """``levels`` with α_d at its grid value (level 2 at half of it), as simulated."""
    d = layout.d_values[layout.index(levels[0].d)]
    return _with(levels[0], {"d": d}), _with(levels[1], {"d": d / 2})


@functools.partial(eqx.filter_jit, compiler_options=QUICK_COMPILE)
def _refined(sim_key, levels, layout: _Layout, target_stats, fields, steps):
    """One program for a refinement: the simulation of ``levels`` (α_d snapped) and BFGS over
    the logits of ``fields`` (static, each in its search range). Returns the answer, its loss
    (inf where undrawable) and its map, both from the solve's last accepted step (no other
    drawing to compile: held-out keys are scored by the swarm's program)."""
    sims, levels = _simulate(sim_key, levels, layout)

    def unpack(z):
        changes: tuple[dict, dict] = ({}, {})
        for i, (lv, f, lo, hi) in enumerate(fields):
            changes[lv][f] = lo + (hi - lo) * jax.nn.sigmoid(z[i])
        return tuple(_with(p, c) for p, c in zip(levels, changes, strict=True))

    def loss(z, _):
        image, bad = _draw_checked(sim_key, sims, unpack(z), layout)
        # inf where undrawable: the line search backs off
        return jnp.where(bad, jnp.inf, _loss(image, target_stats)), image

    def logit(lv, f, lo, hi):
        u = jnp.clip((getattr(levels[lv], f) - lo) / (hi - lo), 1e-3, 1 - 1e-3)
        return jnp.log(u) - jnp.log1p(-u)

    z0 = jnp.stack([logit(*field) for field in fields]).astype(jnp.float32)
    z, value, image = _bfgs(loss, z0, steps)
    return unpack(z), value, image


#: The refinement stops once its line search has halved a step this many times in a row: the
#: gradient then no longer predicts the loss (where a primitive's coverage or a bin changes), and
#: smaller steps almost never gain.
REFINE_BACKTRACKS = 6
#: The refinement stops as well after this many accepted steps in a row (backtracks between them
#: aside) that each lowered its loss by less than ``REFINE_GAIN`` of it: a polish from a best
#: that an earlier one refined gains about 1e-5 a step for all its steps. Replayed for 30 steps,
#: the 10 refinements of a `known-1` fit and 6 from small fits' answers (`brick`, `gravel`) took
#: 285 steps instead of 480, every loss within 0.3 % of the 30 steps'
#: (docs/wrinkles-fitting-log.md).
REFINE_FLAT_STEPS, REFINE_GAIN = 2, 1e-4


def _bfgs(loss, z0, steps):
    """``optimistix.minimise`` with BFGS of ``loss(z, None) → (value, aux)`` from ``z0`` for up to
    ``steps`` steps (each one evaluation; the same steps), which stops as well after
    :data:`REFINE_BACKTRACKS` backtracks in a row or :data:`REFINE_FLAT_STEPS` accepted steps
    in a row that gained less than :data:`REFINE_GAIN` of the loss. Returns the last accepted
    ``z``, its value and its aux."""
    solver, tags = optx.BFGS(rtol=1e-4, atol=1e-6), frozenset()
    f_struct, aux_struct = jax.eval_shape(loss, z0, None)
    state = solver.init(loss, z0, None, {}, f_struct, aux_struct, tags)

    def going(carry):
        i, z, state, flat = carry
        done, _ = solver.terminate(loss, z, None, {}, state, tags)
        stuck = state.search_state.step_size <= 0.5**REFINE_BACKTRACKS
        return (i < steps) & ~done & ~stuck & (flat < REFINE_FLAT_STEPS)

    def step(carry):
        i, z, state, flat = carry
        z, new, _ = solver.step(loss, z, None, {}, state, tags)
        # a step after the first (which only evaluates the start) that the line search accepted
        moved = ~state.first_step & (new.num_accepted_steps > state.num_accepted_steps)
        slight = state.f_info.f - new.f_info.f < REFINE_GAIN * jnp.abs(new.f_info.f)
        flat = jnp.where(moved, jnp.where(slight, flat + 1, 0), flat)
        return i + 1, z, new, flat

    _, z, state, _ = jax.lax.while_loop(going, step, (0, z0, state, jnp.int32(0)))
    # the state holds the last accepted step's value and aux (the step's own aux lags a step)
    return z, state.f_info.f, state.aux
