"""Full wrinkle fit on a 256² patch with the paper's settings (goal ≤ 10 min on the CPU; the
paper: ~35 min per run on an RTX A6000). No reference tool exists; the line reports the wall time
of the whole fit, the swarm's best loss and the refined loss.

The target is a two-level map drawn from known parameters (another seed); pass ``--patch`` to
fit a measured EXR patch instead. ``--agents/--epochs/--trials`` shrink the run to measure the
cost per evaluation on a slow machine.

Run: ``python benchmarks/bench_wrinkles_fit.py [--size 256] [--agents 50] [--epochs 100]``.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np
from _timing import report

from jface.io import read_map
from jface.wrinkles import WrinkleParams, fit_wrinkles
from jface.wrinkles._fit import D_RANGE, _draw, _layout, _simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--patch", help="measured patch (EXR/npy/PNG) instead of a synthetic one")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--agents", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    if args.patch:
        target = read_map(args.patch)
    else:
        truth = (
            WrinkleParams(d=0.03, theta=0.8, s=0.3, deposit=0.5),
            WrinkleParams(d=0.015, theta=0.8, s=0.3, deposit=0.5, snoise=0.001),
        )
        shape = (args.size, args.size)
        key = jax.random.key(99)
        layout = _layout(key, shape, D_RANGE, args.steps)
        target = np.asarray(_draw(key, _simulate(key, truth, layout), truth, shape))
    start = time.perf_counter()
    fit = fit_wrinkles(
        jax.random.key(0), target, n_agents=args.agents, n_epochs=args.epochs,
        n_trials=args.trials, n_steps=args.steps,
    )  # fmt: skip
    jax.block_until_ready(fit.loss)
    elapsed = time.perf_counter() - start
    evaluations = args.agents * (args.epochs + 1) * args.trials
    report(
        f"wrinkle fit {target.shape[0]}x{target.shape[1]}, {args.agents} agents x {args.epochs} "
        f"epochs x {args.trials} trials, {args.steps} steps",
        elapsed,
        goal_s=600,
        evaluations=evaluations,
        ms_per_evaluation=round(1e3 * elapsed / evaluations, 1),
        swarm_loss=float(fit.swarm_loss),
        refined_loss=float(fit.loss),
    )


if __name__ == "__main__":
    main()
