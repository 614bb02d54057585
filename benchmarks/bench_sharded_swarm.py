"""Agent evaluations per second of the wrinkle fit's swarm loss, with its agent axis sharded over
1, 2 and 4 virtual CPU devices (``fit_wrinkles(..., devices=...)``).

Each device count runs in a process of its own (``XLA_FLAGS=--xla_force_host_platform_device_count``
must be set before JAX starts, with XLA's Eigen single-threaded as the command line runs it): the
swarm's loss of ``--agents`` agents at random positions on a real gravel patch, compiled once,
then timed best of ``--repeats``. The reference is the 1-device run of the same benchmark;
``speedup`` is its time over the case's, ``efficiency`` the speedup per device. Every case must
give the 1-device losses' bits.

Run: ``python benchmarks/bench_sharded_swarm.py [--agents 48 --size 128]``.
"""

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
from _timing import report

CHILD = """
import json, sys, time
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh
from _timing import best_of
from jface import data
from jface.optim import texture_stats
from jface.wrinkles import WrinkleParams
from jface.wrinkles._fit import D_RANGE, PAPER_NAMES, _bounds, _layout, _SwarmLoss

agents, size, repeats = (int(a) for a in sys.argv[1:4])
devices = jax.local_devices()
patch = jnp.asarray(data.gravel()[:size, :size], jnp.float32)
key = jax.random.key(0)
layout = _layout(key, patch.shape, D_RANGE, 50, 16)
base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
mesh = Mesh(np.array(devices), ("agents",)) if len(devices) > 1 else None
loss = _SwarmLoss(key, texture_stats(patch), base, layout, PAPER_NAMES, mesh)
low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
u = np.random.default_rng(0).uniform(size=(agents, len(PAPER_NAMES)))
x = jnp.asarray(low + u * (high - low), jnp.float32)
run = eqx.filter_jit(lambda loss, x: loss(x))
start = time.perf_counter()
losses = jax.block_until_ready(run(loss, x))
first = time.perf_counter() - start
seconds = best_of(lambda: run(loss, x), repeats)
print(json.dumps({"devices": len(devices), "first_s": first, "seconds": seconds,
                  "losses": np.asarray(losses).tobytes().hex()}))
"""


def measure(devices: int, agents: int, size: int, repeats: int) -> dict:
    flags = f"--xla_force_host_platform_device_count={devices} --xla_cpu_multi_thread_eigen=false"
    env = dict(os.environ, XLA_FLAGS=flags)
    here = os.path.dirname(os.path.abspath(__file__))
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(agents), str(size), str(repeats)],
        env=env, cwd=here, check=True, capture_output=True, text=True,
    )  # fmt: skip
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--agents", type=int, default=48)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    start = time.perf_counter()
    one = measure(1, args.agents, args.size, args.repeats)
    for devices in (1, 2, 4):
        case = one if devices == 1 else measure(devices, args.agents, args.size, args.repeats)
        report(
            f"swarm loss of {args.agents} agents on a {args.size}² patch, {devices} device(s)",
            case["seconds"],
            "1 device",
            one["seconds"],
            agent_evaluations_per_s=round(args.agents / case["seconds"], 1),
            efficiency=round(one["seconds"] / case["seconds"] / devices, 2),
            compile_and_first_s=round(case["first_s"], 1),
            same_bits=case["losses"] == one["losses"],
            cpu_cores=os.cpu_count(),
        )
    print(f"# total {time.perf_counter() - start:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
