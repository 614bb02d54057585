"""Poisson blending over a whole image (Dirichlet ring): jface's DST-I solve vs scipy's DST
solve and scipy's sparse direct solve of the same 5-point system (same run).

Run: ``python benchmarks/bench_poisson.py [size]`` (needs the ``bench`` extra); 1024² by default.
The sparse direct solve dominates the run (about a minute at 1024² on a loaded CPU).
"""

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.fft
import scipy.sparse
import scipy.sparse.linalg
from _timing import best_of, report

from jface import faces


def system(guide: np.ndarray, boundary: np.ndarray) -> np.ndarray:
    """Right-hand side of Eq. 7 of Pérez et al. for the interior (ring known)."""
    lap = 4 * guide[1:-1, 1:-1] - guide[:-2, 1:-1] - guide[2:, 1:-1]
    lap = lap - guide[1:-1, :-2] - guide[1:-1, 2:]
    ring = boundary.copy()
    ring[1:-1, 1:-1] = 0
    known = ring[:-2, 1:-1] + ring[2:, 1:-1] + ring[1:-1, :-2] + ring[1:-1, 2:]
    return lap + known


def scipy_dst_solve(rhs: np.ndarray) -> np.ndarray:
    n, m = rhs.shape
    ky = 2 - 2 * np.cos(np.pi * np.arange(1, n + 1) / (n + 1))
    kx = 2 - 2 * np.cos(np.pi * np.arange(1, m + 1) / (m + 1))
    coef = scipy.fft.dstn(rhs, type=1) / (ky[:, None] + kx[None, :])
    return scipy.fft.idstn(coef, type=1)


def laplacian(n: int, m: int) -> scipy.sparse.csc_matrix:
    def d(k):
        return scipy.sparse.diags([-np.ones(k - 1), 2 * np.ones(k), -np.ones(k - 1)], [-1, 0, 1])

    return (
        scipy.sparse.kron(d(n), scipy.sparse.eye(m)) + scipy.sparse.kron(scipy.sparse.eye(n), d(m))
    ).tocsc()


def main(size: int = 1024) -> None:
    rng = np.random.default_rng(0)
    guide = rng.standard_normal((size, size)).astype(np.float32)
    boundary = rng.standard_normal((size, size)).astype(np.float32)
    gx, gy = (np.asarray(g) for g in faces.gradients(jnp.asarray(guide)))
    args = (jnp.asarray(gx), jnp.asarray(gy), jnp.asarray(boundary))
    start = time.perf_counter()
    ours = jax.block_until_ready(faces.poisson_solve(*args))
    compile_s = time.perf_counter() - start
    ours_s = best_of(lambda: faces.poisson_solve(*args), repeats=10)

    rhs = system(guide.astype(np.float64), boundary.astype(np.float64))
    dst_s = best_of(lambda: scipy_dst_solve(rhs), repeats=5)
    report(
        f"Poisson solve {size}² f32 (jface DST-I on rfft, jitted)",
        ours_s,
        "scipy.fft.dstn/idstn solve (float64)",
        dst_s,
        compile_s=round(compile_s, 2),
    )
    rhs32 = rhs.astype(np.float32)
    report(
        f"Poisson solve {size}² f32 (jface DST-I on rfft, jitted)",
        ours_s,
        "scipy.fft.dstn/idstn solve (float32)",
        best_of(lambda: scipy_dst_solve(rhs32), repeats=5),
    )
    a = laplacian(size - 2, size - 2)
    start = time.perf_counter()
    direct = scipy.sparse.linalg.spsolve(a, rhs.ravel()).reshape(rhs.shape)
    sparse_s = time.perf_counter() - start
    err = float(np.abs(np.asarray(ours)[1:-1, 1:-1] - direct).max())
    report(
        f"Poisson solve {size}² f32 (jface DST-I on rfft, jitted)",
        ours_s,
        "scipy.sparse.linalg.spsolve (SuperLU, float64, one run)",
        sparse_s,
        max_abs_difference=err,
    )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1024)
