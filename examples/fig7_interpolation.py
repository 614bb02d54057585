"""Golovinskiy et al. 2006, Fig. 7: interpolating faces blurs their detail; coercing the
interpolated displacement image to the interpolated statistics restores it.

Eight faces from :mod:`_ict_population` (real ICT-FaceKit shapes, pores measured from a real
texture; see there) are interpolated with equal weights: base meshes, hierarchy levels and
displacement images are averaged, and the averaged image is coerced to the mean statistics.
Writes front views of four of the inputs, the plain average and the coerced average, the
displacement images, the detailed meshes, and prints the per-tile high-pass std of both
relative to the target.

Run: ``python examples/fig7_interpolation.py --out fig7`` (needs scikit-image: the test extra,
and the ICT-FaceKit data beside the repository).
"""

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _ict_population import front_view, population, write_detailed

from jface import detail, io, plots, raster, render


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="fig7")
    parser.add_argument("--faces", type=int, default=8)
    parser.add_argument("--size", type=int, default=512, help="displacement image size")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--ict", help="the full ICT-FaceKit face area (ict_face_area.npz); default: jface's subset"
    )
    args = parser.parse_args()
    out = Path(args.out)
    faces, records = population(args.faces, 0, image_size=args.size, seed=args.seed, ict=args.ict)
    stats = detail.analyze_batch(jnp.stack([f.image for f in faces]))
    weights = jnp.full(args.faces, 1.0 / args.faces)
    result = detail.interpolate_faces(jax.random.key(args.seed), faces, stats, weights)
    meta = io.provenance(
        seed=args.seed, experiment="Golovinskiy 2006 Fig. 7", faces=records, size=args.size
    )

    frame = raster.framing(np.asarray(result.average.base.vertices))
    frame = (frame[0], 0.55 * frame[1])
    inputs = [front_view(f, frame=frame) for f in faces[:4]]
    figure = plots.panel_grid(
        [inputs], title="Input faces", col_labels=[f"face {i + 1}" for i in range(len(inputs))]
    )
    io.write_figure(out / "inputs.png", figure, metadata=meta)
    images = [result.average.image, result.coerced.image]
    figure = plots.panel_grid(
        [
            [front_view(result.average, frame=frame), front_view(result.coerced, frame=frame)],
            [render.shade(image) for image in images],
        ],
        title=f"Interpolating {args.faces} faces (Golovinskiy 2006 Fig. 7)",
        col_labels=["average of the displacements", "coerced to the mean statistics"],
        row_labels=["rendered face", "displacement (shaded)"],
        panel_inches=2.8,
    )
    io.write_figure(out / "fig7_average_vs_coerced.png", figure, metadata=meta)
    for name, face in (("average", result.average), ("coerced", result.coerced)):
        write_detailed(out, name, face, meta, f"interpolated face ({name})")
        ratio = detail.analyze(face.image).std[0] / result.target.std[0]
        error = detail.stats_error(detail.analyze(face.image), result.target)
        print(
            f"{name:8s} per-tile high-pass std / target: median {float(jnp.median(ratio)):.2f}; "
            f"median per-tile error over all bands {float(jnp.median(error)):.1%}"
        )
    print(f"outputs in {out}/")


if __name__ == "__main__":
    main()
