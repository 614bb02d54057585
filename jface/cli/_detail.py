"""``jface analyze``, ``jface synthesize``, ``jface render`` and the detail step of the demo."""

from __future__ import annotations

import argparse
import importlib.resources
import json
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jface import detail, io, pyramid, render


def register(sub: argparse._SubParsersAction) -> None:
    analyze = sub.add_parser(
        "analyze", help="per-tile steerable-pyramid statistics of displacement maps"
    )
    analyze.add_argument("files", nargs="+", help="maps: EXR (one channel), PNG/JPEG or .npy")
    analyze.add_argument("--out", required=True, help="output folder (one .npz + .png per map)")
    analyze.add_argument("--grid", type=int, default=16)
    analyze.add_argument("--scales", type=int, default=4)
    analyze.add_argument("--orientations", type=int, default=4)
    analyze.add_argument("--bins", type=int, default=None, help="also store histograms (full)")
    analyze.add_argument("--boundary", choices=("circular", "reflect"), default="circular")
    analyze.add_argument(
        "--overwrite", action="store_true", help="redo maps whose statistics already exist"
    )
    analyze.set_defaults(run=_analyze)

    synth = sub.add_parser("synthesize", help="coerce a map to target statistics")
    synth.add_argument("start", help="map to start from")
    synth.add_argument("--stats", required=True, help="target statistics (.npz from analyze)")
    synth.add_argument("--out", required=True, help="output EXR (a shaded PNG is written beside)")
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument("--n-iter", type=int, default=detail._synthesis.N_ITER)
    synth.add_argument("--noise", type=float, default=detail._synthesis.NOISE)
    synth.add_argument("--rule", choices=("exact", "paper"), default="exact")
    synth.add_argument("--method", choices=("std", "histogram"), default=None)
    synth.set_defaults(run=_synthesize)

    draw = sub.add_parser("render", help="shaded relief PNG of a displacement map")
    draw.add_argument("map", help="map file")
    draw.add_argument("--out", required=True, help="output PNG")
    draw.set_defaults(run=_render)


def _analyze(args: argparse.Namespace) -> None:
    out = Path(args.out)
    done = skipped = 0
    for name in tqdm(args.files, desc="analyze", unit="map", disable=len(args.files) < 2):
        target = out / (Path(name).stem + ".stats.npz")
        if target.exists() and not args.overwrite:
            skipped += 1  # finished by an earlier run: a batch that died keeps what it did
            continue
        stats = detail.analyze(
            io.read_map(name),
            grid=args.grid,
            n_scales=args.scales,
            n_orientations=args.orientations,
            bins=args.bins,
            boundary=args.boundary,
        )
        detail.save_stats(target, stats, source=Path(name).name, boundary=args.boundary)
        mosaic = render.stats_mosaic(stats.std, stats.n_orientations)
        io.write_png(target.with_suffix(".png"), mosaic, metadata={"source": Path(name).name})
        done += 1
    print(f"analyzed {done} map(s), kept {skipped} already done, in {out}/")


def _synthesize(args: argparse.Namespace) -> None:
    start = io.read_map(args.start)
    target, _ = detail.load_stats(args.stats)
    result = detail.synthesize(
        jax.random.key(args.seed),
        start,
        target,
        n_iter=args.n_iter,
        noise=args.noise,
        rule=args.rule,
        method=args.method,
    )
    error = np.asarray(detail.stats_error(detail.analyze_like(result, target), target))
    meta = io.provenance(
        seed=args.seed,
        start=Path(args.start).name,
        stats=Path(args.stats).name,
        n_iter=args.n_iter,
        noise=args.noise,
        rule=args.rule,
        method=args.method,
    )
    out = io.write_exr(args.out, np.asarray(result), metadata=meta, protect=(args.start,))
    io.write_png(out.with_suffix(".png"), render.shade(result), metadata=meta)
    print(json.dumps({"out": str(out), "median_tile_std_error": float(np.median(error))}))


def _render(args: argparse.Namespace) -> None:
    io.write_png(args.out, render.shade(io.read_map(args.map)), protect=(args.map,))


def _smooth(image: np.ndarray, n_bands: int, n_scales: int = 4) -> np.ndarray:
    """Remove the high-pass and the ``n_bands - 1`` finest scales (a smooth start, as Fig. 5)."""
    pyr = pyramid.build(image, n_scales)
    bands = tuple(b * 0 if s < n_bands - 1 else b for s, b in enumerate(pyr.bands))
    return np.asarray(
        pyramid.collapse(
            pyramid.Pyramid(pyr.highpass * 0, bands, pyr.lowpass, pyr.image_shape, pyr.pad)
        )
    )


def demo(out: Path, seed: int) -> None:
    """Golovinskiy et al. Fig. 5 on a real texture: analyse, smooth, re-synthesise."""
    out = Path(out)
    source = importlib.resources.files("jface") / "data" / "gravel.exr"
    with importlib.resources.as_file(source) as path:
        original = io.read_map(path)
    stats = detail.analyze(original, grid=16)
    smooth = _smooth(original, n_bands=3)
    result = detail.synthesize(jax.random.key(seed), smooth, stats)
    errors = {
        name: float(np.median(np.asarray(detail.stats_error(detail.analyze_like(m, stats), stats))))
        for name, m in (("smoothed", smooth), ("synthesized", np.asarray(result)))
    }
    meta = io.provenance(seed=seed, source="gravel.exr", experiment="Golovinskiy 2006 Fig. 5")
    detail.save_stats(out / "detail" / "gravel.stats.npz", stats, source="gravel.exr")
    shaded = []
    for name, image in (("original", original), ("smoothed", smooth), ("synthesized", result)):
        io.write_exr(out / "detail" / f"{name}.exr", np.asarray(image), metadata=meta)
        shaded.append(render.shade(image))
    strip = np.concatenate([np.pad(s, ((0, 0), (0, 4)), constant_values=1.0) for s in shaded], 1)
    io.write_png(out / "detail" / "fig5_original_smoothed_synthesized.png", strip, metadata=meta)
    io.write_png(
        out / "detail" / "statistics.png", render.stats_mosaic(stats.std, 4), metadata=meta
    )
    print(
        "detail: median per-tile std error to the original's statistics — "
        f"smoothed {errors['smoothed']:.1%}, re-synthesised {errors['synthesized']:.1%}"
    )
