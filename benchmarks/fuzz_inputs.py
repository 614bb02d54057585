"""The fuzz set of ``tests/test_fuzz_inputs.py`` at full size: every reader and a command fed
mutated files, ``--examples`` each (the suite runs 12, deterministically; this run explores
with fresh random examples). Prints one JSON line per test: examples, passed or the failure,
seconds.

Run: ``python benchmarks/fuzz_inputs.py [--examples 500]`` (a few minutes on 2 CPU cores).
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=500, help="examples per test")
    args = parser.parse_args()
    env = {**os.environ, "JFACE_FUZZ_EXAMPLES": str(args.examples)}
    listed = subprocess.run(
        [sys.executable, "-m", "pytest", "tests/test_fuzz_inputs.py", "--collect-only"],
        cwd=ROOT, env=env, capture_output=True, text=True, check=True,
    )  # fmt: skip
    tests = [line for line in listed.stdout.splitlines() if "::" in line]
    for test in tests:
        start = time.perf_counter()
        run = subprocess.run(
            [sys.executable, "-m", "pytest", test, "-x", "-p", "no:cacheprovider"],
            cwd=ROOT, env=env, capture_output=True, text=True, check=False,
        )  # fmt: skip
        failure = [ln for ln in run.stdout.splitlines() if ln.startswith("E ")][:3]
        print(json.dumps({
            "test": test.split("::", 1)[1],
            "examples": args.examples,
            "passed": run.returncode == 0,
            "failure": " | ".join(failure) or None,
            "seconds": round(time.perf_counter() - start, 1),
        }), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
