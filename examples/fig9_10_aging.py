"""Golovinskiy et al. 2006, Fig. 9 (aging and de-aging) and Fig. 10 with §4 (comparison with
Perlin noise, sharpening and detail transfer), on remeshed ICT-FaceKit faces.

A young and an old face come from :mod:`_ict_population` (real ICT shapes, detail measured from
real textures; see there). Aging coerces the young displacement image to the old face's
statistics and takes the finer hierarchy levels from the old face (the marker mesh and the lowest
levels stay the young face's); de-aging does the reverse. Writes front views of the faces
(young, detail-only aged, aged with the coarse change, old, and the same for de-aging), the
Fig. 10 strip (young, old, the four methods; per-tile error to the old statistics below) and the
§4 table (``comparison.md``/``.json``), and prints the numbers.

Run: ``python examples/fig9_10_aging.py --out fig9`` (needs scikit-image: the test extra, and
the ICT-FaceKit data beside the repository).
"""

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _ict_population import front_view, population, write_detailed

from jface import detail, io, plots, raster


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="fig9")
    parser.add_argument("--size", type=int, default=512, help="displacement image size")
    parser.add_argument("--levels", type=int, default=3, help="coarse levels kept (1-5)")
    parser.add_argument("--iters", type=int, default=24, help="synthesis iterations")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--ict", help="the full ICT-FaceKit face area (ict_face_area.npz); default: jface's subset"
    )
    args = parser.parse_args()
    out = Path(args.out)
    (young, old), records = population(1, 1, image_size=args.size, seed=args.seed, ict=args.ict)
    key_age, key_young = jax.random.split(jax.random.key(args.seed))
    stats = {name: detail.analyze(f.image) for name, f in (("young", young), ("old", old))}
    aged = detail.age(key_age, young, old, stats["old"], n_coarse=args.levels, n_iter=args.iters)
    young_again = detail.age(
        key_young, old, young, stats["young"], n_coarse=args.levels, n_iter=args.iters
    )
    meta = io.provenance(
        seed=args.seed,
        experiment="Golovinskiy 2006 Fig. 9-10, §4",
        faces=records,
        levels=args.levels,
        n_iter=args.iters,
        size=args.size,
    )

    def with_image(face, image):
        return detail.Face(face.markers, face.offsets, face.base, image, face.schedule)

    frame = raster.framing(np.asarray(young.base.vertices))
    frame = (frame[0], 0.55 * frame[1])  # the face fills the view
    rows = {
        "aging": [young, with_image(young, aged.image), aged, old],
        "deaging": [old, with_image(old, young_again.image), young_again, young],
    }
    columns = {
        "aging": ["young", "young + old detail", "aged", "old"],
        "deaging": ["old", "old + young detail", "de-aged", "young"],
    }
    for name, faces in rows.items():
        figure = plots.panel_grid(
            [[front_view(f, frame=frame) for f in faces]],
            title=f"{name.capitalize()} (Golovinskiy 2006 Fig. 9)",
            col_labels=columns[name],
            panel_inches=2.6,
        )
        io.write_figure(out / f"fig9_{name}.png", figure, metadata=meta)
    for name, face in (("aged", aged), ("deaged", young_again)):
        write_detailed(out, name, face, meta, f"{name} face (Golovinskiy 2006 §3.4)")

    # §4 / Fig. 10: the young image after the coarse change, given the old detail four ways.
    results = detail.method_results(
        key_age, young.image, old.image, stats["old"], n_iter=args.iters
    )
    scores = detail.method_scores(results, young.image, stats["old"])
    images = [young.image, old.image, *results.values()]
    errors = [
        np.median(np.asarray(detail.stats_error(detail.analyze(image), stats["old"])), axis=0)
        for image in images
    ]
    figure = plots.method_comparison(
        images,
        errors,
        ["young", "old", *results],
        title="Aging the young face's detail: methods compared (Golovinskiy 2006 Fig. 10)",
    )
    io.write_figure(out / "fig10_comparison.png", figure, metadata=meta)
    lines = [
        "| method | median per-tile std error to the old face | corr. with young, coarsest "
        "detail scale | corr. with young, mid scale |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {m} | {s['stats_error']:.1%} | {s['keeps_coarse']:.2f} | {s['keeps_mid']:.2f} |"
        for m, s in scores.items()
    ]
    with io.atomic_path(out / "comparison.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    io.write_json(out / "comparison.json", {**meta, "methods": scores})
    print("\n".join(lines))
    gap = float(jnp.abs(aged.base.vertices - young.base.vertices).max())
    print(
        f"aging: coarse change moves base vertices by up to {gap * 10:.1f} mm; the young "
        f"low-pass is kept exactly; median per-tile error to the old statistics "
        f"{scores['statistical']['stats_error']:.1%}; outputs in {out}/"
    )


if __name__ == "__main__":
    main()
