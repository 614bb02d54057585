"""Particle swarm: jface.optim.pso against pyswarms on Rastrigin-10D, in the same run.

Cases: (1) overhead of one 50-agent × 100-epoch run after compilation (goal ≤ 2 ms; pyswarms
8–14 ms), (2) best cost at equal evaluations (50 agents × 100 evaluations each), median over
seeds, jface's lbest/gbest against pyswarms' LocalBestPSO/GlobalBestPSO with the options of its
documentation (c1 = 0.5, c2 = 0.3, w = 0.9; ring k = 2). Goal: jface's median no worse than
pyswarms'.

Run: ``python benchmarks/bench_pso.py [--seeds 10]`` (needs the ``bench`` extra: pyswarms).
"""

from __future__ import annotations

import argparse
import json
import logging

import jax
import jax.numpy as jnp
import numpy as np
from _timing import best_of, report

from jface.optim import pso

DIM, AGENTS, EPOCHS = 10, 50, 100
BOUNDS = (-5.12 * np.ones(DIM), 5.12 * np.ones(DIM))


def rastrigin(x):
    return 10.0 * x.shape[0] + jnp.sum(x**2 - 10.0 * jnp.cos(2.0 * jnp.pi * x))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    import pyswarms as ps
    from pyswarms.utils.functions import single_obj

    logging.getLogger("pyswarms").setLevel(logging.ERROR)
    options = {"c1": 0.5, "c2": 0.3, "w": 0.9}

    def pyswarms_run(seed: int, local: bool, iters: int = EPOCHS) -> float:
        np.random.seed(seed)  # noqa: NPY002 (pyswarms draws from numpy's global generator)
        if local:
            opt = ps.single.LocalBestPSO(AGENTS, DIM, options | {"k": 2, "p": 2}, bounds=BOUNDS)
        else:
            opt = ps.single.GlobalBestPSO(AGENTS, DIM, options, bounds=BOUNDS)
        cost, _ = opt.optimize(single_obj.rastrigin, iters=iters, verbose=False)
        return float(cost)

    # (1) overhead: one full run, compiled once beforehand
    for topology, local in (("lbest", True), ("gbest", False)):

        def run(topology=topology):
            return pso(
                jax.random.key(0), rastrigin, BOUNDS, n_agents=AGENTS, n_epochs=EPOCHS,
                topology=topology,
            ).loss  # fmt: skip

        jax.block_until_ready(run())
        ours = best_of(run, repeats=20)
        theirs = best_of(lambda local=local: pyswarms_run(0, local), repeats=5)
        name = "LocalBestPSO" if local else "GlobalBestPSO"
        case = f"pso overhead {topology}, {AGENTS} agents x {EPOCHS} epochs, Rastrigin-{DIM}D"
        report(case, ours, f"pyswarms {name}", theirs, goal_ms=2.0)

    # (2) best cost at equal evaluations: jface evaluates the start too, so EPOCHS - 1 epochs
    for topology, local in (("lbest", True), ("gbest", False)):
        equal_evaluations = {"n_agents": AGENTS, "n_epochs": EPOCHS - 1, "topology": topology}
        ours = np.median(
            [
                float(pso(jax.random.key(s), rastrigin, BOUNDS, **equal_evaluations).loss)
                for s in range(args.seeds)
            ]
        )
        theirs = np.median([pyswarms_run(s, local) for s in range(args.seeds)])
        row = {
            "case": f"best cost at {AGENTS * EPOCHS} evaluations, {topology}, "
            f"median of {args.seeds} seeds",
            "jface": round(float(ours), 3),
            "pyswarms": round(float(theirs), 3),
            "jface_no_worse": bool(ours <= theirs),
        }
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
