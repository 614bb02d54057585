"""Wrinkle fits side by side: each target, its fast-mode fit and its paper-mode fit.

Reads the folder that ``benchmarks/bench_wrinkles_fit.py --save DIR`` fills (``<target>.npy``
and ``<target>-<mode>-<seed>.npz``) and draws one row per target: the target and the map each
mode fitted with the given seed, all normalised to zero mean and unit variance (what the texture
loss compares), on one colour scale per row. The row label gives each fit's texture loss and
wall time; a fit that is missing leaves its cell blank.

Run: ``python benchmarks/bench_wrinkles_fit.py --targets known-1 brick --save fits``, then
``python examples/wrinkles_fit_modes.py --fits fits --out docs/wrinkles``.
"""

import argparse
from pathlib import Path

import numpy as np

from jface import io, plots

MODES = ("fast", "paper")


def normalised(image: np.ndarray) -> np.ndarray:
    return (image - image.mean()) / image.std()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fits", type=Path, required=True, help="bench_wrinkles_fit.py --save")
    parser.add_argument("--out", type=Path, default=Path("docs/wrinkles"))
    parser.add_argument("--targets", nargs="+", help="default: every target in --fits")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    names = args.targets or sorted(p.stem for p in args.fits.glob("*.npy"))
    if not names:
        parser.error(f"--fits {args.fits} holds no targets (<target>.npy)")
    rows, labels, record = [], [], {}
    for name in names:
        row, notes = [normalised(np.load(args.fits / f"{name}.npy"))], []
        for mode in MODES:
            path = args.fits / f"{name}-{mode}-{args.seed}.npz"
            if not path.exists():
                row.append(None)
                continue
            arrays, fit = io.load_arrays(path, kind="WrinkleFitRun")
            row.append(normalised(arrays["fitted"]))
            loss, seconds = fit["loss"], fit["seconds"]
            notes.append(f"{mode}: {loss:.3g}, {seconds:.0f} s")
            record[f"{name}-{mode}"] = {"loss": loss, "seconds": seconds}
        rows.append(row)
        labels.append(f"{name}\n" + "\n".join(notes))
    figure = plots.panel_grid(
        rows,
        title=f"Wrinkle fits (Weiss et al. 2023 §4.2), seed {args.seed}: texture loss, wall time",
        col_labels=["target", "fast mode (default)", "paper mode (--paper)"],
        row_labels=labels,
        quantities="displacement",
        units="displacement (std of the map)",
        limits=[(-3.0, 3.0)] * len(rows),
    )
    out = args.out / "fit_modes.png"
    io.write_figure(out, figure, metadata=io.provenance(seed=args.seed, fits=record))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
