"""Timing helpers shared by the benchmark scripts: best-of-n wall time, one JSON line per case."""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import jax


def best_of(fn: Callable[[], object], repeats: int = 5) -> float:
    """Best wall time of ``repeats`` calls, in seconds; JAX results are waited for."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def report(case: str, jface_s: float, reference: str | None = None, reference_s=None, **extra):
    """Print one JSON line: jface's time, the reference's time from the same run, the ratio."""
    row = {"case": case, "jface_ms": round(jface_s * 1e3, 2)}
    if reference is not None:
        row |= {
            "reference": reference,
            "reference_ms": round(reference_s * 1e3, 2),
            "speedup": round(reference_s / jface_s, 2),
        }
    row |= extra
    print(json.dumps(row, ensure_ascii=False), flush=True)
