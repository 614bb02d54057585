"""Global face models against scikit-learn, measured in the same run.

Cases (the sizes of Mohammed et al. 2009, §3: 1500 faces of 70×70, 8 factors, 40 iterations):
fitting a factor analyser, the log-likelihood of 1500 images at d = 4900, and a mixture of five
factor analysers. One JSON line per case; compile time is reported apart from the warm run.

    python benchmarks/bench_faces.py [--n 1500] [--size 70]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
from _timing import report
from scipy.ndimage import shift, zoom
from skimage import data
from sklearn.decomposition import FactorAnalysis
from sklearn.mixture import GaussianMixture

from jface import faces


def face_data(n: int, size: int, seed: int = 0) -> np.ndarray:
    """``n`` distinct ``size``×``size`` faces: the 100 LFW faces upsampled, randomly shifted,
    mirrored, re-lit and with sensor noise."""
    rng = np.random.default_rng(seed)
    base = data.lfw_subset()[:100].astype(np.float64)
    base = np.stack([zoom(b, size / 25, order=1) for b in base])
    out = np.empty((n, size, size))
    for i in range(n):
        img = base[rng.integers(100)]
        img = img[:, ::-1] if rng.random() < 0.5 else img
        img = shift(img, rng.uniform(-2, 2, 2), order=1, mode="nearest")
        out[i] = rng.uniform(0.8, 1.2) * img + rng.uniform(-0.1, 0.1)
    return (out + rng.normal(0, 0.02, out.shape)).astype(np.float32)


def timed(fn, repeat: int = 1):
    start = time.perf_counter()
    result = fn()
    jax.block_until_ready(jax.tree_util.tree_leaves(result))
    first = time.perf_counter() - start
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        jax.block_until_ready(jax.tree_util.tree_leaves(result))
        best = min(best, time.perf_counter() - start)
    return result, best, first - best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=1500)
    parser.add_argument("--size", type=int, default=70)
    args = parser.parse_args()
    x = face_data(args.n, args.size)
    flat = x.reshape(args.n, -1)
    flat64 = flat.astype(np.float64)
    d = flat.shape[1]

    fit, t_fit, c_fit = timed(lambda: faces.fit_factor_analyser(x, 8, n_iter=40))
    sk = FactorAnalysis(8, random_state=0)
    start = time.perf_counter()
    sk.fit(flat64)
    t_sk = time.perf_counter() - start
    sk_ll = sk.score(flat64)
    model = fit.model
    model64 = faces.FactorAnalyser(
        *(jnp.asarray(np.asarray(a, np.float64)) for a in (model.mean, model.factors, model.noise)),
        shape=model.shape,
    )
    ref = FactorAnalysis(8)
    ref.components_ = np.asarray(model64.factors).T
    ref.noise_variance_ = np.asarray(model64.noise)
    ref.mean_ = np.asarray(model64.mean)
    report(
        f"fit factor analyser {args.n}x{d}, 8 factors, 40 iterations",
        t_fit,
        "sklearn FactorAnalysis (default tol: stops after n_iter_ iterations)",
        t_sk,
        jface_compile_s=round(c_fit, 2),
        reference_n_iter=int(sk.n_iter_),
        jface_loglik=round(float(ref.score(flat64)), 3),
        reference_loglik=round(float(sk_ll), 3),
    )

    score = jax.jit(jax.vmap(lambda v: faces.log_likelihood(model, v)))
    lls, t_ll, c_ll = timed(lambda: score(x), repeat=5)
    start = time.perf_counter()
    ref_ll = ref.score_samples(flat64)
    t_ref = time.perf_counter() - start
    report(
        f"log-likelihood of {args.n} images, d={d}",
        t_ll,
        "sklearn FactorAnalysis.score_samples (forms the d×d covariance)",
        t_ref,
        jface_compile_s=round(c_ll, 2),
        max_abs_diff_nats=float(np.max(np.abs(np.asarray(lls, np.float64) - ref_ll))),
    )

    mix, t_mix, c_mix = timed(lambda: faces.fit_mixture(jax.random.key(0), x, 5, 8, n_iter=40))
    gm = GaussianMixture(5, covariance_type="diag", max_iter=40, random_state=0)
    start = time.perf_counter()
    gm.fit(flat)
    t_gm = time.perf_counter() - start
    report(
        f"fit mixture of 5 factor analysers {args.n}x{d}, 8 factors, 40 iterations",
        t_mix,
        "sklearn GaussianMixture(5, diag), 40 iterations (no factors: a simpler model)",
        t_gm,
        jface_compile_s=round(c_mix, 2),
        jface_loglik=round(float(mix.log_likelihood[-1]), 3),
        reference_loglik=round(float(gm.score(flat)), 3),
        jface_em_monotone=bool(np.all(np.diff(np.asarray(mix.log_likelihood)) >= -1e-2)),
    )


if __name__ == "__main__":
    main()
