"""Mutation check: plant plausible one-line bugs one at a time and see which tests catch them.

Each mutant replaces one line of the library (the old text must occur exactly once) in a
temporary copy of the repository and runs the test files that cover it there (``-q``, not
``-x``, so every catching test is listed). Prints a table: mutant, caught?, catching tests.
The goal: every mutant caught, each core-equation mutant by at least two tests.

Run on demand or in a slow CI tier, not on every commit (about half a minute to a few minutes
per mutant on two cores)::

    python tests/mutation.py                 # all mutants
    python tests/mutation.py sim-decay pso   # mutants whose names start with these prefixes
    python tests/mutation.py --list

Not mutmut or cosmic-ray: both generate operator-level mutants over every line and rerun the
chosen tests for each, thousands of runs of a JAX suite whose files take 20 s – 3 min each
(mostly compilation); a curated list of bugs that a person would plausibly write, each tied to
the few test files that cover it, runs in under an hour.
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]


class Mutant(NamedTuple):
    name: str
    path: str  # library file, relative to the repository root
    old: str
    new: str
    tests: tuple[str, ...]  # pytest arguments: test files, then "-k", an expression selecting
    core: bool = True  # a numbered equation or core statistic: wants ≥ 2 catching tests


KA, KAF = "tests/test_known_answers.py", "tests/test_known_answers_faces.py"
SIM = (
    KA,
    "tests/test_wrinkles_simulation.py",
    "-k",
    "not (bad or json or perlin or default_run)",
)
DRAW = (
    KA,
    "tests/test_wrinkles_draw.py",
    "-k",
    "eq9 or eq10 or eq12 or shape or mellowmax or pore_strength or brute_force or orientation",
)
PSO = (
    KA,
    "tests/test_optim_pso.py",
    "-k",
    "swarm or sphere or rosenbrock or lbest or boundary or history or delta or bounds or "
    "free_flight or absorb",
)
FA = (
    KAF,
    "tests/test_faces_models.py",
    "-k",
    "not (cli or bad or save or profile or bilinear or constant or refuses or tile or poisson "
    "or patch)",
)
TILES = (
    KAF,
    "tests/test_detail.py",
    "-k",
    "tile or blend or stats_equal or histograms_describe or match_std or exact_rule",
)
POISSON = (KAF, "tests/test_faces_quilting.py", "-k", "poisson or dst1")
PYRAMID = ("tests/test_pyramid.py", "-k", "not bad")
QUILT = (
    KAF,
    "tests/test_faces_quilting.py",
    "-k",
    "cheapest_patch or choices or own_position or one_image or novel or same_key",
)
GRAPH = ("tests/test_wrinkles_graph.py", "tests/test_wrinkles_sampling.py", "-k", "not bad")
SYNTH = (
    "tests/test_detail.py",
    "tests/test_real_inputs.py",
    "-k",
    "fig5 or exact_rule or synthesis_puts or fixed_point or histogram_matching or match_std",
)

S, D, P = "jface/wrinkles/_simulation.py", "jface/wrinkles/_drawing.py", "jface/optim/_pso.py"
EM, FAF, T = "jface/faces/_em.py", "jface/faces/_fa.py", "jface/tiles.py"

MUTANTS = (
    # --- trail simulation, Eq. 1–8
    Mutant("sim-decay-capacity", S,
           "n_valid = jnp.maximum(graph.edge_count, 1).astype(jnp.float32)",
           "n_valid = jnp.float32(graph.edge_mask.shape[0])", SIM),
    Mutant("sim-deposit-no-dt", S, "keep = 1.0 - dt * deposit", "keep = 1.0 - deposit", SIM),
    Mutant("sim-cont-sim-swapped", S,
           "kern = cont * _gauss(math.pi - same, sigma_c) - sim * _gauss(same, sigma_c)",
           "kern = cont * _gauss(same, sigma_c) - sim * _gauss(math.pi - same, sigma_c)", SIM),
    Mutant("sim-orientation-directed", S, "d = angle_distance(angle, theta, math.pi)",
           "d = angle_distance(angle, theta, 2.0 * math.pi)", SIM),
    Mutant("sim-sigma-not-squared", S, "return s + jnp.exp(-(d * d) / (sigma * sigma))",
           "return s + jnp.exp(-(d * d) / sigma)", SIM),
    Mutant("sim-crossing-rewarded", S,
           "score = terms.pref + terms.dist * (p_cont - terms.cross * p_cross)",
           "score = terms.pref + terms.dist * (p_cont + terms.cross * p_cross)", SIM),
    Mutant("sim-distance-exponent-sign", S,
           "dist_factor = jnp.exp(-dist * jnp.log(", "dist_factor = jnp.exp(dist * jnp.log(", SIM),
    Mutant("sim-pref-without-1-minus-cont", S, "pref=dist_factor * (1.0 - cont) * p_pref,",
           "pref=dist_factor * p_pref,", SIM),
    # --- drawing, Eq. 9–13
    Mutant("draw-shape-scale", D, "(x - 3.0) ** 2 * (x - 1.0) / 9.0",
           "(x - 3.0) ** 2 * (x - 1.0) / 3.0", DRAW),
    Mutant("draw-mellowmax-no-nhat-padding", D, "pad = (n_hat_f - n) * jnp.exp(-beta * m)",
           "pad = n_hat_f * jnp.exp(-beta * m)", DRAW),
    Mutant("draw-pore-strength-blend", D,
           "return jnp.maximum(w_max + dmin, w_max + blend * (w_sum - w_max))",
           "return jnp.maximum(w_max + dmin, blend * w_sum)", DRAW),
    # --- particle swarm, Eq. 14–15
    Mutant("pso-randoms-per-agent", P,
           "r1, r2, r3 = jax.lax.optimization_barrier(counter_uniform(seed, t, (3, m, n)))",
           "r1, r2, r3 = jax.lax.optimization_barrier(jnp.broadcast_to("
           "counter_uniform(seed, t, (3, m, 1)), (3, m, n)))", PSO),
    Mutant("pso-inertia-off-by-one", P,
           "w = a + b * jnp.power(jnp.float32(c), jnp.asarray(t).astype(jnp.float32))",
           "w = a + b * jnp.power(jnp.float32(c), jnp.asarray(t).astype(jnp.float32) + 1)", PSO),
    Mutant("pso-absorb-keeps-velocity", P, "inside = r\n        v = jnp.where(out, 0.0, v)",
           "inside = r", PSO),
    Mutant("pso-ring-shifted", P, "shift = jnp.argmin(ring, axis=0) - 1",
           "shift = jnp.argmin(ring, axis=0)", PSO),
    # --- factor analysis / mixtures: EM and posteriors
    Mutant("em-masked-noise-over-all-images", EM,
           "jnp.sum(ft * sx, axis=1)) / counts, floor)", "jnp.sum(ft * sx, axis=1)) / n, floor)",
           FA),
    Mutant("em-masked-no-posterior-cov", EM, "ehh = cov + eh[:, :, None] * eh[:, None, :]",
           "ehh = eh[:, :, None] * eh[:, None, :]", FA),
    Mutant("em-mofa-noise-over-all-images", EM,
           "jnp.sum(ft * sx, axis=1)) / counts[:, None], floor)",
           "jnp.sum(ft * sx, axis=1)) / n, floor)", FA),
    Mutant("em-mofa-responsibilities-no-weights", EM, "joint = log_w[:, None] + ll",
           "joint = ll", FA),
    Mutant("fa-posterior-no-prior", FAF, "gram = gram + jnp.eye(q, dtype=gram.dtype)",
           "gram = gram + 0.5 * jnp.eye(q, dtype=gram.dtype)", FA),
    Mutant("fa-log-det-halved", FAF,
           "return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)",
           "return jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)", FA),
    # --- tiles (Golovinskiy §2.3–2.4) and synthesis
    Mutant("tiles-blend-half-pixel", T, "position = (np.arange(n) + 0.5) / tile - 0.5",
           "position = np.arange(n) / tile - 0.5", TILES),
    Mutant("tiles-variance-uncentred", T, "return mean, jnp.maximum(second - mean * mean, 0.0)",
           "return mean, jnp.maximum(second, 0.0)", TILES),
    Mutant("tiles-histogram-bins", T, "* bins).astype(jnp.int32), 0, bins - 1",
           "* (bins - 1)).astype(jnp.int32), 0, bins - 1", TILES),
    Mutant("synthesis-gain-square-root", T, "gain = target / jnp.maximum(std, eps)",
           "gain = jnp.sqrt(target / jnp.maximum(std, eps))", SYNTH),
    # --- steerable pyramid
    Mutant("pyramid-angular-order", "jface/pyramid.py",
           "np.cos(angle[None] - offsets[:, None, None]) ** order",
           "np.cos(angle[None] - offsets[:, None, None]) ** (order + 1)", PYRAMID),
    Mutant("pyramid-radial-transition", "jface/pyramid.py",
           "x = np.clip(log_radius - position, -1.0, 0.0) * (np.pi / 2)",
           "x = np.clip(log_radius - position, -1.0, 0.0) * (np.pi / 4)", PYRAMID),
    # --- Poisson editing
    Mutant("poisson-divergence-sign", "jface/faces/_poisson.py",
           "return gx[:, 1:] - gx[:, :-1] + gy[1:, :] - gy[:-1, :]",
           "return gx[:, 1:] - gx[:, :-1] - gy[1:, :] + gy[:-1, :]", POISSON),
    Mutant("poisson-edge-neighbours", "jface/faces/_poisson.py",
           "return _neighbour_sum(jnp.ones(shape, dtype))",
           "return jnp.full(shape, 4.0, dtype)", POISSON),
    # --- quilting
    Mutant("quilt-target-weight", "jface/faces/_quilting.py",
           "lam * rows_of(norms) + seam - 2 * (lib @ (wk * q + lam * tq)) + const",
           "lam * rows_of(norms) + seam - 2 * (lib @ (wk * q + tq)) + const", QUILT, core=False),
    # --- pore sampling and graph
    Mutant("sampling-min-distance-halved", "jface/wrinkles/_sampling.py",
           "(ddx * ddx + ddy * ddy < rr * rr)", "(ddx * ddx + ddy * ddy < 0.25 * rr * rr)",
           GRAPH, core=False),
    Mutant("graph-crossing-of-lines", "jface/wrinkles/_graph.py",
           "return opposite(cross(p2, q1), cross(p2, q2)) & opposite(cross(e, -q1), "
           "cross(e, p2 - q1))", "return opposite(cross(p2, q1), cross(p2, q2))", GRAPH,
           core=False),
)  # fmt: skip


def copy_repository(dest: Path) -> None:
    """The tracked and untracked-but-not-ignored files of the repository."""
    files = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=ROOT, check=True, capture_output=True, text=True,
    ).stdout.split("\0")  # fmt: skip
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)


def run_tests(copy: Path, tests: tuple[str, ...]) -> tuple[bool, list[str], str]:
    """Run pytest in the copy; return (all passed, failing test ids, last output line)."""
    env = {
        **os.environ,
        "PYTHONPATH": str(copy),  # the copy's jface, not the installed one
        # compilations of the code a mutant leaves alone are reused from the first run
        "JAX_COMPILATION_CACHE_DIR": str(copy / ".jax-cache"),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.2",
    }
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider", *tests],
        cwd=copy, env=env, capture_output=True, text=True,
    )  # fmt: skip
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", out.stdout, re.MULTILINE)
    last = (out.stdout.strip().splitlines() or [""])[-1]
    return out.returncode == 0, sorted(set(failed)), last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("prefixes", nargs="*", help="run only mutants whose names start so")
    parser.add_argument("--list", action="store_true", help="list the mutants and exit")
    args = parser.parse_args()
    chosen = [m for m in MUTANTS if not args.prefixes or m.name.startswith(tuple(args.prefixes))]
    if args.list:
        for m in chosen:
            print(f"{m.name:40s} {m.path}  ->  {' '.join(m.tests)}")
        return
    for m in chosen:  # every mutant must apply to the current source
        count = (ROOT / m.path).read_text().count(m.old)
        if count != 1:
            sys.exit(f"mutant {m.name}: its line occurs {count} times in {m.path}, not once")
    rows = []
    with tempfile.TemporaryDirectory(prefix="jface-mutation-") as tmp:
        copy = Path(tmp)
        copy_repository(copy)
        for tests in dict.fromkeys(m.tests for m in chosen):  # each selection passes unmutated
            start = time.perf_counter()
            ok, failed, last = run_tests(copy, tests)
            print(f"unmutated {' '.join(tests)}: {last} ({time.perf_counter() - start:.0f} s)",
                  flush=True)  # fmt: skip
            if not ok:
                sys.exit(f"the unmutated tests fail ({last}): {failed}")
        for m in chosen:
            target = copy / m.path
            original = target.read_text()
            target.write_text(original.replace(m.old, m.new))
            start = time.perf_counter()
            try:
                passed, failed, last = run_tests(copy, m.tests)
            finally:
                target.write_text(original)
            caught = not passed
            rows.append((m, caught, failed, time.perf_counter() - start))
            print(f"{m.name}: {'caught' if caught else 'MISSED'} by {len(failed)} "
                  f"({time.perf_counter() - start:.0f} s; {last}): {' '.join(failed)}",
                  flush=True)  # fmt: skip
    print("\n| mutant | caught | # | tests that catch it |\n|---|---|---|---|")
    for m, caught, failed, _ in rows:
        names = ", ".join(f.split("::", 1)[-1] if "::" in f else f for f in failed) or "—"
        flag = "yes" if caught else "**no**"
        if caught and m.core and len(failed) < 2:
            flag = "yes (1 test)"
        print(f"| {m.name} | {flag} | {len(failed)} | {names} |")
    missed = [m.name for m, caught, *_ in rows if not caught]
    thin = [m.name for m, caught, failed, _ in rows if caught and m.core and len(failed) < 2]
    print(f"\n{len(rows) - len(missed)}/{len(rows)} caught; missed: {missed or 'none'}; "
          f"core mutants caught by one test only: {thin or 'none'}")  # fmt: skip


if __name__ == "__main__":
    main()
