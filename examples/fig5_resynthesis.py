"""Golovinskiy et al. 2006, Fig. 5: smooth a real map, re-synthesise its detail from its statistics.

The map is scikit-image's real gravel texture, mirror-tiled to the paper's 1024² (the displacement
images of the paper are not public). Writes shaded PNGs of original / smoothed / re-synthesised,
the per-band statistics, and prints how close each is to the original's per-tile statistics.

Run: ``python examples/fig5_resynthesis.py --out fig5`` (needs scikit-image: the test extra).
"""

import argparse
from pathlib import Path

import jax
import numpy as np
from skimage import data

from jface import detail, io, plots, render, tiles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="fig5")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    out = Path(args.out)

    original = tiles.mirror_tile(data.gravel().astype(np.float32) / 255.0, args.size)
    stats = detail.analyze(original)
    smooth = np.asarray(detail.remove_detail(original, n_bands=3))
    result = np.asarray(detail.synthesize(jax.random.key(args.seed), smooth, stats))
    meta = io.provenance(seed=args.seed, experiment="Golovinskiy 2006 Fig. 5", size=args.size)
    labels = []
    for name, image in (("original", original), ("smoothed", smooth), ("synthesized", result)):
        error = np.asarray(detail.stats_error(detail.analyze(image), stats))
        labels.append(f"{name} ({np.median(error):.1%} std error)")
        print(
            f"{name:12s} per-tile std error: median {np.median(error):6.1%}, "
            f"p95 {np.percentile(error, 95):6.1%}"
        )
        io.write_exr(out / f"{name}.exr", image, metadata=meta)
        io.write_png(out / f"{name}.png", render.shade(image), metadata=meta)
    figure = plots.panel_grid(
        [[render.shade(image) for image in (original, smooth, result)]],
        title="Smoothed gravel re-synthesised to its statistics (Golovinskiy 2006 Fig. 5)",
        col_labels=labels,
        panel_inches=3.0,
    )
    io.write_figure(out / "fig5.png", figure, metadata=meta)
    figure = plots.band_statistics(stats.std, 4, title="Per-tile std of each band: gravel")
    io.write_figure(out / "statistics.png", figure, metadata=meta)
    print(f"wrote {out}/")


if __name__ == "__main__":
    main()
