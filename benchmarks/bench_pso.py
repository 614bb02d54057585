"""Particle swarm: jface.optim.pso against pyswarms on Rastrigin-10D, in the same run.

Cases: (1) overhead of one 50-agent × 100-epoch run after compilation (goal ≤ 2 ms; pyswarms
8–14 ms), (2) best cost at equal evaluations (50 agents × 100 evaluations each), median over
seeds, jface's lbest/gbest against pyswarms' LocalBestPSO/GlobalBestPSO, with equal constants
on both sides: (a) pyswarms' documented options (c1 = 0.5, c2 = 0.3, w = 0.9; jface with
Δt = 1 and constant inertia), (b) the paper's c1 = c2 = 2 with Δt = 0.2 and a constant w = 0.7
(pyswarms has no Δt: x ← x + Δt v with v ← w v + c r Δ is pyswarms' update with c' = Δt c, so it
runs with c1 = c2 = 0.4, w = 0.7), and (c) jface with the paper's full schedule
(w_t = 0.4 + 0.6 · 0.98^t) against pyswarms' defaults. Both keep their own boundary handling
(jface Random+Absorb, pyswarms "periodic") and velocity initialisation. Goal: jface's median no
worse than pyswarms'.

Run: ``python benchmarks/bench_pso.py [--seeds 40]`` (needs the ``bench`` extra: pyswarms).
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
    parser.add_argument("--seeds", type=int, default=40)
    args = parser.parse_args()
    import pyswarms as ps
    from pyswarms.utils.functions import single_obj

    logging.getLogger("pyswarms").setLevel(logging.ERROR)

    def pyswarms_run(seed: int, local: bool, iters: int = EPOCHS, options=None) -> float:
        options = options or {"c1": 0.5, "c2": 0.3, "w": 0.9}
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
    pyswarms_default = {"c1": 0.5, "c2": 0.3, "w": 0.9}
    cases = (
        ("pyswarms' options", {"dt": 1.0, "c1": 0.5, "c2": 0.3, "inertia": (0.9, 0.0, 1.0)},
         pyswarms_default),
        ("paper c=2, dt=0.2, w=0.7", {"inertia": (0.7, 0.0, 1.0)},
         {"c1": 0.4, "c2": 0.4, "w": 0.7}),
        ("jface paper schedule vs pyswarms' options", {}, pyswarms_default),
    )  # fmt: skip
    for label, ours_options, theirs_options in cases:
        for topology, local in (("lbest", True), ("gbest", False)):
            settings = {"n_agents": AGENTS, "n_epochs": EPOCHS - 1, "topology": topology}
            ours = [
                float(pso(jax.random.key(s), rastrigin, BOUNDS, **settings, **ours_options).loss)
                for s in range(args.seeds)
            ]
            theirs = [pyswarms_run(s, local, options=theirs_options) for s in range(args.seeds)]
            row = {
                "case": f"best cost at {AGENTS * EPOCHS} evaluations, {topology}, {label}, "
                f"median [quartiles] of {args.seeds} seeds",
                "jface": _median_and_quartiles(ours),
                "pyswarms": _median_and_quartiles(theirs),
                "jface_no_worse": bool(np.median(ours) <= np.median(theirs)),
            }
            print(json.dumps(row), flush=True)


def _median_and_quartiles(values: list[float]) -> str:
    q1, median, q3 = np.percentile(values, [25, 50, 75])
    return f"{median:.2f} [{q1:.2f}, {q3:.2f}]"


if __name__ == "__main__":
    main()
