"""Wrinkle fit on 256² patches, fast mode against the paper's procedure (goal: fast mode within
10 min on the CPU with a final loss ≤ 1.05× the paper mode's; the paper: ~35 min per run on an
RTX A6000). No reference tool exists.

Targets: ``known-<seed>``, two-level maps drawn from known parameters (other pores, another
simulation key than the fit's); ``brick`` and ``gravel``, crops of the skimage textures;
``synthesized``, a map from ``detail.synthesize`` with the gravel crop's statistics. Each line
gives a mode's wall time, its swarm and refined loss, its held-out loss (the answer with other
simulation keys, ``WrinkleFit.heldout_loss``), the epochs each trial ran and, for the synthetic
targets, the recovered α_deposit and α_θ of level 1 against the truth; the paper mode's line
adds the fast/paper ratios of time, loss and held-out loss when both ran on the target.

``--save DIR`` keeps each target (``<target>.npy``) and each fit (``<target>-<mode>-<seed>.npz``:
the fitted map, the swarm's history, the fitted levels as JSON) for
``examples/wrinkles_fit_modes.py``, which draws them side by side.

``--stages`` first prints the cost of one swarm evaluation split into simulation, drawing and
texture loss, per size class of the α_d grid, and the layout time (its pores and graphs).

Run: ``python benchmarks/bench_wrinkles_fit.py [--targets known-1 brick] [--modes fast paper]
[--agents 50] [--epochs 100] [--trials 3] [--save DIR]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import best_of, report
from skimage import data

from jface import detail
from jface._compilation import keep_compiled_programs
from jface.optim import texture_stats
from jface.wrinkles import REFINE_STEPS, WrinkleParams, fit_wrinkles, params_to_json
from jface.wrinkles._fit import (
    D_RANGE,
    PAPER_NAMES,
    _bounds,
    _draw,
    _draw_checked,
    _layout,
    _levels_from,
    _loss,
    _polishes,
    _rung,
    _simulate,
    _SwarmLoss,
)

TARGETS = ["known-1", "known-2", "known-3", "brick", "gravel", "synthesized"]


def stages(target, layout, agents: int) -> None:
    """ms per agent of each stage of a swarm evaluation, per size class of the α_d grid (agents
    with α_d in that class, on its graph slots, one after the other as in the fit; compiled
    first)."""
    d_values = np.asarray(layout.d_values)
    for c, grid in enumerate((d_values[: layout.split], d_values[layout.split :])):
        class_stages(target, layout.narrowed(c), grid, agents)


def class_stages(target, narrow, grid, agents: int) -> None:
    base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
    low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
    u = np.random.default_rng(0).uniform(size=(agents, len(PAPER_NAMES)))
    x = low + u * (high - low)
    x[:, PAPER_NAMES.index("d")] = np.random.default_rng(1).choice(grid, agents)
    x = jnp.asarray(x, jnp.float32)
    key, stats = jax.random.key(5), texture_stats(target)

    def one_sim(a):
        return _simulate(key, _levels_from(a, PAPER_NAMES, base), narrow)

    sim = jax.jit(lambda x: jax.lax.map(one_sim, x))
    draw = jax.jit(lambda s, lv: jax.lax.map(lambda a: _draw_checked(key, *a, narrow), (s, lv)))
    loss = jax.jit(jax.vmap(lambda image: _loss(image, stats)))
    sims, levels = jax.block_until_ready(sim(x))
    images, bad = jax.block_until_ready(draw(sims, levels))
    jax.block_until_ready(loss(images))
    for name, fn in (
        ("simulation (2 levels)", lambda: sim(x)),
        ("drawing (2 levels)", lambda: draw(sims, levels)),
        ("texture loss", lambda: loss(images)),
    ):
        report(
            f"one swarm evaluation, {agents} agents of α_d {grid[0]:.3f}-{grid[-1]:.3f}, "
            f"{target.shape[0]}², stage: {name}",
            best_of(fn, repeats=2) / agents,
            note="ms per agent",
        )
    print(f'{{"undrawable_agents": {int(np.sum(np.asarray(bad)))}, "of": {agents}}}', flush=True)


def evaluation_cost(target, layout, agents: int) -> float:
    """Seconds per agent of one whole swarm evaluation as the fit runs it (compiled first)."""
    base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
    low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
    u = np.random.default_rng(1).uniform(size=(agents, len(PAPER_NAMES)))
    x = jnp.asarray(low + u * (high - low), jnp.float32)
    loss = eqx.filter_jit(_SwarmLoss(jax.random.key(5), texture_stats(target), base, layout,
                                     PAPER_NAMES))  # fmt: skip
    jax.block_until_ready(loss(x))
    seconds = best_of(lambda: loss(x), repeats=2) / agents
    report(f"one swarm evaluation as the fit runs it, {agents} agents", seconds,
           note="ms per agent")  # fmt: skip
    return seconds


TRUTH = (
    WrinkleParams(d=0.03, theta=0.8, s=0.3, deposit=0.5),
    WrinkleParams(d=0.015, theta=0.8, s=0.3, deposit=0.5, snoise=0.001),
)


def polish_count(fit, mode: str, args) -> int:
    """Polishes the fit ran: one after each of a trial's rungs (the last trial's: its chunks of a
    rung's epochs), when the fit polishes."""
    steps = REFINE_STEPS[mode] if args.refine_steps is None else args.refine_steps
    if not _polishes(mode, steps, args.agents, args.epochs):
        return 0
    return sum(-(-epochs // _rung(args.epochs)) for epochs in fit.epochs_run)


def make_target(name: str, size: int, steps: int) -> np.ndarray:
    if name.startswith("known-"):
        key = jax.random.key(1000 + int(name.split("-")[1]))
        layout = _layout(key, (size, size), D_RANGE, steps, 4)
        sims, levels = _simulate(key, TRUTH, layout)
        return np.asarray(_draw(key, sims, levels, layout))
    gravel = data.gravel().astype(np.float32) / 255.0
    if name == "synthesized":
        crop = gravel[:size, :size]
        smooth = np.asarray(detail.remove_detail(crop, n_bands=3))
        stats = detail.analyze(crop, grid=4)  # whole tiles at every scale of a small crop
        return np.asarray(detail.synthesize(jax.random.key(3), smooth, stats))
    texture = {"brick": data.brick().astype(np.float32) / 255.0, "gravel": gravel}[name]
    return texture[:size, :size]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", nargs="+", default=TARGETS, choices=TARGETS)
    parser.add_argument("--modes", nargs="+", default=["fast", "paper"], choices=["fast", "paper"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="fit seeds")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--agents", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--d-levels", type=int, help="default: the mode's (16 fast, 32 paper)")
    parser.add_argument("--refine-steps", type=int, help="default: the mode's (30 in both)")
    parser.add_argument("--stages", action="store_true", help="the cost split of one evaluation")
    parser.add_argument("--save", type=Path, help="folder for the targets and the fits")
    args = parser.parse_args()
    keep_compiled_programs()  # as the command line does (JFACE_CACHE_DIR=off: compile afresh)
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    for name in args.targets:
        target = make_target(name, args.size, args.steps)
        if args.save:
            np.save(args.save / f"{name}.npy", target)
        if args.stages:
            start = time.perf_counter()
            levels = args.d_levels or 32
            layout = _layout(jax.random.key(0), target.shape, D_RANGE, args.steps, levels)
            report(f"layout: pores and graphs of {levels} α_d values",
                   time.perf_counter() - start)  # fmt: skip
            stages(target, layout, 8)
            evaluation_cost(target, layout, args.agents)
        for seed in args.seeds:
            done = {}
            for mode in args.modes:
                start = time.perf_counter()
                fit = fit_wrinkles(
                    jax.random.key(seed), target, n_agents=args.agents, n_epochs=args.epochs,
                    n_trials=args.trials, n_steps=args.steps, d_levels=args.d_levels,
                    refine_steps=args.refine_steps, mode=mode,
                )  # fmt: skip
                jax.block_until_ready(fit.loss)
                elapsed = time.perf_counter() - start
                done[mode] = (elapsed, float(fit.loss), fit.heldout_loss)
                if args.save:
                    np.savez(
                        args.save / f"{name}-{mode}-{seed}.npz", fitted=np.asarray(fit.fitted),
                        history=np.asarray(fit.swarm.history), seconds=elapsed,
                        loss=float(fit.loss), levels=params_to_json(fit.levels, "uv"),
                    )  # fmt: skip
                extra = {}
                if name.startswith("known-"):
                    extra = {"deposit": round(float(fit.levels[0].deposit), 3),
                             "theta": round(float(fit.levels[0].theta), 3),
                             "truth": {"deposit": 0.5, "theta": 0.8}}  # fmt: skip
                if mode == "paper" and "fast" in done:
                    fast_s, fast_loss, fast_heldout = done["fast"]
                    extra |= {
                        "time_fast_over_paper": round(fast_s / elapsed, 3),
                        "loss_fast_over_paper": round(fast_loss / float(fit.loss), 3),
                        "heldout_fast_over_paper": finite(fast_heldout / fit.heldout_loss),
                    }
                report(
                    f"wrinkle fit, {mode} mode, target {name} {target.shape[0]}², seed {seed}, "
                    f"{args.agents} agents, {args.epochs} epochs, {args.trials} trials",
                    elapsed,
                    goal_s=600,
                    swarm_loss=float(fit.swarm_loss),
                    loss=float(fit.loss),
                    heldout_loss=finite(fit.heldout_loss),
                    epochs_run=list(fit.epochs_run),
                    evaluations=args.agents * sum(e + 1 for e in fit.epochs_run),
                    polishes=polish_count(fit, mode, args),
                    refined_from_each_start=[float(v) for v in fit.refined_losses],
                    nonfinite_evaluations=int(np.sum(np.asarray(fit.swarm.n_nonfinite))),
                    **extra,
                )


def finite(value: float) -> float | None:
    """A number for the report's JSON (None where it is not finite: JSON has no NaN)."""
    return round(float(value), 6) if np.isfinite(value) else None


if __name__ == "__main__":
    main()
