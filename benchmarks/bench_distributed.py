"""Scaling of ``jface db build`` over processes (``--processes``) and virtual CPU devices.

Each case is a whole command on the same maps (start-up and compilation included, as a user
sees it): 1 and 2 processes, each with 1, 2 or 4 host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count``). The reference is the 1-process,
1-device build of the same run; ``speedup`` is its time over the case's, ``efficiency`` the
speedup per worker (processes × devices). Every case must give the reference's bytes.

Run: ``python benchmarks/bench_distributed.py [--maps 32 --size 512]``.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _timing import report

from jface import data, io, tiles


def build(maps: list[str], out: Path, processes: int, devices: int, chunk: int) -> float:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")
    entry = "import sys; from jface.cli import main; sys.exit(main())"
    command = [sys.executable, "-c", entry, "db", "build", *maps, "--out", str(out)]
    command += ["--chunk", str(chunk), "--processes", str(processes)]
    start = time.perf_counter()
    subprocess.run(command, env=env, check=True, capture_output=True)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--maps", type=int, default=32)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--chunk", type=int, default=4)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        gravel = tiles.mirror_tile(data.gravel(), 2 * args.size).astype(np.float32)
        rng = np.random.default_rng(0)
        maps = []
        for i in range(args.maps):  # real texture, a different crop per map
            y, x = rng.integers(0, args.size, 2)
            crop = gravel[y : y + args.size, x : x + args.size]
            maps.append(str(io.write_exr(folder / f"m{i:03d}.exr", crop)))
        reference = folder / "p1d1.npz"
        reference_s = build(maps, reference, 1, 1, args.chunk)
        for processes in (1, 2):
            for devices in (1, 2, 4):
                out = folder / f"p{processes}d{devices}.npz"
                seconds = build(maps, out, processes, devices, args.chunk)
                report(
                    f"db build {args.maps} maps of {args.size}², {processes} process(es) × "
                    f"{devices} device(s)",
                    seconds,
                    "1 process × 1 device",
                    reference_s,
                    maps_per_s=round(args.maps / seconds, 2),
                    efficiency=round(reference_s / seconds / (processes * devices), 2),
                    same_bytes=out.read_bytes() == reference.read_bytes(),
                    cpu_cores=os.cpu_count(),
                )


if __name__ == "__main__":
    main()
