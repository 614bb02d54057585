"""Converged versus 50-step trail simulation on one graph, and the continuation reward α_cont.

Top: the same ~130k-edge periodic pore graph (α_d = 0.004, α_θ = 0, α_s = 0.2) simulated for
the old default of 50 steps and for the default converged run (:func:`converged_steps`); a crop
of each drawn as lines of darkness W, and the two weight histograms. Bottom: Fig. 6's
continuation panel — a small graph at α_cont = 0, at Table 1's maximum 0.01 and at 0.5 — with the
mean weight change against α_cont = 0.

Run: ``python examples/wrinkles_convergence.py --out docs/wrinkles``
"""

import argparse
from pathlib import Path

import jax
import numpy as np
from matplotlib.collections import LineCollection

from jface import io, plots
from jface.wrinkles import (
    WrinkleParams,
    build_graph,
    converged_steps,
    sample_pores,
    simulate,
)

CROP = 0.12  # side of the drawn crop (UV)


def crop_lines(ax, graph, weights, title, crop=CROP):
    e = int(graph.edge_count)
    a = np.asarray(graph.positions)[np.asarray(graph.edge_nodes)[:e, 0]]
    b = a + np.asarray(graph.edge_delta)[:e]
    w = np.asarray(weights)[:e]
    keep = np.all((a < crop) & (b < crop) & (a > 0) & (b > 0), axis=1)
    lines = LineCollection(np.stack([a[keep], b[keep]], 1), colors="k", linewidths=2.5 * w[keep],
                           alpha=1.0)  # fmt: skip
    ax.add_collection(lines)
    ax.set(xlim=(0, crop), ylim=(crop, 0), aspect="equal", xlabel="u", ylabel="v")
    ax.set_title(title, fontsize=9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/wrinkles")
    args = parser.parse_args()
    out = Path(args.out)

    graph = build_graph(sample_pores(jax.random.key(1), 0.004, periodic=True))
    params = WrinkleParams(d=0.004, theta=0.0, s=0.2)
    steps = converged_steps(graph, params)
    e = int(graph.edge_count)
    short = np.asarray(simulate(jax.random.key(2), graph, params, n_steps=50))
    full = np.asarray(simulate(jax.random.key(2), graph, params))

    fig, axes = plots.axes_grid(
        2, 3, size=(12, 8.4),
        title="Trail simulation (Weiss et al. 2023 §3.1): converged vs 50 steps (top); "
        "continuation reward α_cont (bottom, Fig. 6)",
    )  # fmt: skip
    crop_lines(axes[0, 0], graph, short, f"50 steps: mean W {short[:e].mean():.3f}")
    crop_lines(axes[0, 1], graph, full, f"converged, {steps} steps: mean W {full[:e].mean():.3f}")
    bins = np.linspace(0, 1, 41)
    axes[0, 2].hist(short[:e], bins, alpha=0.6, label="50 steps")
    axes[0, 2].hist(full[:e], bins, alpha=0.6, label=f"converged ({steps} steps)")
    axes[0, 2].set(xlabel="W", ylabel="edges")
    axes[0, 2].set_title(f"edge weights, {e} edges, N = 50,000", fontsize=9)
    axes[0, 2].legend()

    small = build_graph(sample_pores(jax.random.key(3), 0.01, periodic=True))
    base = WrinkleParams(d=0.01, theta=0.0, s=0.2, sim=0.5)
    ref = np.asarray(simulate(jax.random.key(4), small, base))
    es = int(small.edge_count)
    # α_cont = 1 leaves no orientation term to start from (every score is 0 at W = 0)
    for ax, cont in zip(axes[1], (0.0, 0.01, 0.5), strict=True):
        w = np.asarray(simulate(jax.random.key(4), small, base.replace(cont=cont)))
        change = np.abs(w[:es] - ref[:es]).mean()
        crop_lines(ax, small, w, f"α_cont = {cont}: mean |ΔW| vs 0 = {change:.4f}", 3 * CROP)
    meta = io.provenance(seed=2, d=0.004, steps=steps, edges=e)
    io.write_figure(out / "convergence.png", fig, metadata=meta)
    print(f"wrote {out / 'convergence.png'}")


if __name__ == "__main__":
    main()
