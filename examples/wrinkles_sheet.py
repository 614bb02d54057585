"""Weiss et al. 2023, Fig. 5/6/8/9/15 style: one contact sheet of drawing-parameter sweeps.

One pore graph and one simulation per orientation setting; every panel is the same level drawn
with different parameters (shaded relief), so the rows isolate one effect each:

* Fig. 5/6 — simulation: primary orientation uniformity α_s, crossing penalty.
* Fig. 8 — pores: wrinkles only (tiny pores), pores (α_dmin 0.6, α_blend 1), plus cushioning.
* Fig. 9 — perturbation: straight, strong low-frequency, weak high-frequency.
* Fig. 15 — Perlin variation of α_scale and α_wrinkle-width.

Run: ``python examples/wrinkles_sheet.py --out sheet [--size 384]``
"""

import argparse
from pathlib import Path

import jax
import numpy as np

from jface import io, plots
from jface.render import shade
from jface.wrinkles import (
    WrinkleParams,
    build_graph,
    draw,
    perlin_variation,
    sample_pores,
    simulate,
)

BASE = {"d": 0.02, "theta": 0.6, "s": 0.2, "deposit": 0.5, "wrinkle_width": 0.4}

ROWS = {
    "simulation (Fig. 5/6)": [
        ({"s": 0.05}, {}),
        ({"s": 0.6}, {}),
        ({"cross": 1.0}, {}),
    ],
    "pores (Fig. 8)": [
        ({}, {"pore_width": 0.01, "dmin": 0.001, "blend": 0.0}),
        ({}, {"pore_width": 0.3, "dmin": 0.6, "blend": 1.0}),
        ({}, {"pore_width": 0.3, "dmin": 0.6, "blend": 1.0, "cushion": 0.3}),
    ],
    "perturbation (Fig. 9)": [
        ({}, {"sperturb": 0.001}),
        ({}, {"sperturb": 2.0, "fperturb": 100.0}),
        ({}, {"sperturb": 0.5, "fperturb": 1500.0}),
    ],
}


def _label(changes: dict, prefix: str = "") -> str:
    """A panel's parameters as the paper names them (α_dmin = 0.6, ...)."""
    return ", ".join(f"{prefix}α_{k.replace('_', '-')} = {v:g}" for k, v in changes.items())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="sheet")
    parser.add_argument("--size", type=int, default=384)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    key = jax.random.key(args.seed)
    graph = build_graph(sample_pores(key, BASE["d"], periodic=True))
    shape = (args.size, args.size)

    def panel(sim_change, draw_change, variation=None):
        params = WrinkleParams(**{**BASE, **sim_change})
        weights = simulate(key, graph, params, n_steps=80, n_samples=5000)
        params = params.replace(**draw_change)
        if variation:
            params = perlin_variation(jax.random.fold_in(key, 7), params, variation)
        return shade(np.asarray(draw(key, graph, weights, params, shape)))

    variations = [{}, {"scale": 0.5}, {"wrinkle_width": 0.6}]
    rows = [[panel(s, d) for s, d in cells] for cells in ROWS.values()]
    rows.append([panel({}, {}, v) for v in variations])
    labels = [[_label({**s, **d}) for s, d in cells] for cells in ROWS.values()]
    labels.append(["no variation", *(_label(v, "Perlin-varied ") for v in variations[1:])])
    names = [*ROWS, "variation (Fig. 15)"]
    figure = plots.panel_grid(
        rows,
        title="Drawing-parameter sweeps of one pore graph (Weiss et al. 2023), shaded relief",
        row_labels=names,
        panel_inches=2.6,
    )
    panels = np.array(figure.axes).reshape(len(rows), -1)
    for ax, label in zip(panels.ravel(), [t for row in labels for t in row], strict=True):
        ax.set_title(label, fontsize=7)
    meta = io.provenance(seed=args.seed, rows=names, base=BASE)
    io.write_figure(Path(args.out) / "wrinkles_sheet.png", figure, metadata=meta)
    print("rows:", ", ".join(names))


if __name__ == "__main__":
    main()
