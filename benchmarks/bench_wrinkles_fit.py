"""Full wrinkle fit on a 256² patch with the paper's settings (goal ≤ 10 min on the CPU; the
paper: ~35 min per run on an RTX A6000). No reference tool exists; the lines report the cost of
one swarm evaluation split into its stages (simulation, drawing, texture loss; pores and graphs
are precomputed once per fit, reported as "layout"), the cost of one evaluation as the fit runs
it, the wall time of the whole fit, the swarm's best loss, the refined loss and the share of
agents that could not be drawn (NaN loss).

The target is a two-level map drawn from known parameters (other pores, another seed); pass
``--patch`` to fit a measured EXR patch instead. ``--agents/--epochs/--trials`` shrink the run;
the line then also extrapolates to the paper's 50 × 101 × 3 evaluations: the fit's fixed cost
(its time less its evaluations at the measured cost each) plus that many evaluations.

Run: ``python benchmarks/bench_wrinkles_fit.py [--size 256] [--agents 50] [--epochs 100]``.
"""

from __future__ import annotations

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import best_of, report

from jface.io import read_map
from jface.optim import texture_stats
from jface.wrinkles import WrinkleParams, fit_wrinkles
from jface.wrinkles._fit import (
    D_LEVELS,
    D_RANGE,
    PAPER_NAMES,
    _bounds,
    _draw,
    _draw_checked,
    _layout,
    _levels_from,
    _loss,
    _simulate,
    _SwarmLoss,
)

PAPER_EVALUATIONS = 50 * 101 * 3


def stages(target, layout, agents: int) -> None:
    """ms per agent of each stage of one vmapped swarm evaluation (compiled first)."""
    base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
    low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
    u = np.random.default_rng(0).uniform(size=(agents, len(PAPER_NAMES)))
    x = jnp.asarray(low + u * (high - low), jnp.float32)
    key, stats = jax.random.key(5), texture_stats(target)
    sim = jax.jit(jax.vmap(lambda x: _simulate(key, _levels_from(x, PAPER_NAMES, base), layout)))
    # the agents draw one after the other, each with the passes its tiles need (as in the fit)
    draw = jax.jit(lambda s, lv: jax.lax.map(lambda a: _draw_checked(key, *a, layout), (s, lv)))
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
            f"one swarm evaluation, {agents} agents, {target.shape[0]}², stage: {name}",
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patch", help="measured patch (EXR/npy/PNG) instead of a synthetic one")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--agents", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--d-levels", type=int, default=D_LEVELS)
    parser.add_argument("--refine-steps", type=int, default=30)
    parser.add_argument("--stage-agents", type=int, default=8, help="agents of the stage split")
    args = parser.parse_args()
    shape = (args.size, args.size)
    if args.patch:
        target = read_map(args.patch)
    else:
        truth = (
            WrinkleParams(d=0.03, theta=0.8, s=0.3, deposit=0.5),
            WrinkleParams(d=0.015, theta=0.8, s=0.3, deposit=0.5, snoise=0.001),
        )
        key = jax.random.key(99)
        layout = _layout(key, shape, D_RANGE, args.steps, 4)
        sims, levels = _simulate(key, truth, layout)
        target = np.asarray(_draw(key, sims, levels, layout))
    start = time.perf_counter()
    layout = _layout(jax.random.key(0), target.shape, D_RANGE, args.steps, args.d_levels)
    report(f"layout: pores and graphs of {args.d_levels} α_d values", time.perf_counter() - start)
    if args.stage_agents:
        stages(target, layout, args.stage_agents)
    per_evaluation = evaluation_cost(target, layout, args.agents)
    start = time.perf_counter()
    fit = fit_wrinkles(
        jax.random.key(0), target, n_agents=args.agents, n_epochs=args.epochs,
        n_trials=args.trials, n_steps=args.steps, d_levels=args.d_levels,
        refine_steps=args.refine_steps,
    )  # fmt: skip
    jax.block_until_ready(fit.loss)
    elapsed = time.perf_counter() - start
    evaluations = args.agents * (args.epochs + 1) * args.trials
    fixed = max(0.0, elapsed - per_evaluation * evaluations)
    report(
        f"wrinkle fit {target.shape[0]}x{target.shape[1]}, {args.agents} agents x {args.epochs} "
        f"epochs x {args.trials} trials, {args.steps} steps",
        elapsed,
        goal_s=600,
        evaluations=evaluations,
        # what does not grow with the evaluations: layout, compilation, refinement
        fixed_s=round(fixed, 1),
        paper_run_extrapolated_s=round(fixed + per_evaluation * PAPER_EVALUATIONS),
        swarm_loss=float(fit.swarm_loss),
        refined_loss=float(fit.loss),
        nonfinite_evaluations=int(np.sum(np.asarray(fit.swarm.n_nonfinite))),
    )


if __name__ == "__main__":
    main()
