"""A 3-level micro-wrinkle map of 2048², drawn exactly as a user draws one from the command line.

Runs ``jface wrinkles simulate --levels 3`` and ``jface wrinkles render --simulation`` (the
command-line defaults of the levels: the coarse level directional and deep, the finer ones more
even and shallower), then shows the whole map as shaded relief, a crop at full resolution and
the crop's displacement with its colour bar (``wrinkles_map_2048.png``).

Run: ``python examples/wrinkles_map.py --out docs/wrinkles [--size 2048 --seed 1]``
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.patches import Rectangle

from jface import io, plots
from jface.cli import main as jface
from jface.render import shade

CROP = 384  # side of the full-resolution crop (pixels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/wrinkles", help="folder of the figure")
    parser.add_argument("--size", type=int, default=2048, help="side of the map (pixels)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    seed = str(args.seed)
    with tempfile.TemporaryDirectory(prefix="jface-wrinkles-map-") as tmp:
        sim, exr = Path(tmp) / "simulation", Path(tmp) / "wrinkles.exr"
        for argv in (
            ["wrinkles", "simulate", "--out", str(sim), "--levels", "3", "--seed", seed],
            ["wrinkles", "render", "--simulation", str(sim), "--out", str(exr),
             "--size", str(args.size), "--seed", seed],
        ):  # fmt: skip
            if jface(argv) != 0:
                raise SystemExit(f"jface {' '.join(argv[:2])} failed")
        depth = np.asarray(io.read_map(exr), np.float32)
    relief = np.asarray(shade(depth))
    y0 = x0 = (args.size - CROP) // 2
    crop = (slice(y0, y0 + CROP), slice(x0, x0 + CROP))
    fig, axes = plots.axes_grid(
        1, 3, size=(15.5, 5.4),
        title=f"Micro wrinkles, 3 levels at {args.size}² (Weiss et al. 2023; jface wrinkles "
        f"simulate --levels 3, render --size {args.size}, seed {args.seed})",
    )  # fmt: skip
    whole, detail, height = axes[0]
    whole.imshow(relief, cmap=plots.COLOUR_MAPS["relief"], vmin=0, vmax=1)
    whole.add_patch(Rectangle((x0, y0), CROP, CROP, fill=False, edgecolor="tab:red", lw=1.2))
    whole.set_title(f"whole map, {args.size}² (shaded relief)", fontsize=10)
    detail.imshow(relief[crop], cmap=plots.COLOUR_MAPS["relief"], vmin=0, vmax=1)
    detail.set_title(f"red square at full resolution ({CROP}²)", fontsize=10)
    limit = float(np.percentile(np.abs(depth[crop]), 99.5))
    shown = height.imshow(
        depth[crop], cmap=plots.COLOUR_MAPS["displacement"], vmin=-limit, vmax=limit
    )
    height.set_title("its displacement", fontsize=10)
    fig.colorbar(shown, ax=height, fraction=0.046, label="displacement (map units)")
    for ax in (whole, detail, height):
        ax.set_xticks([])
        ax.set_yticks([])
    meta = io.provenance(seed=args.seed, size=args.size, levels=3)
    io.write_figure(Path(args.out) / f"wrinkles_map_{args.size}.png", fig, metadata=meta)


if __name__ == "__main__":
    main()
