"""Real inputs: the pictures of docs/mesh.md and docs/detail.md on remeshing a real scan and on
synthesis over maps whose detail changes abruptly.

1. ``real_scan.png``: the Lee Perry-Smith head remeshed from its hand-placed landmarks: the scan,
   the detailed mesh (base + displacement image) seen from the same camera, the displacement
   image and the pixels filled where rays missed. With ``--before DIR`` (a face folder written
   by ``jface remesh`` of an earlier jface) a first row shows that result beside it.
2. ``heterogeneous_synthesis.png``: each map of :func:`jface.data.heterogeneous_maps`, smoothed
   and re-synthesised from its own statistics with the paper's plain 12 iterations and with
   jface's defaults, and the per-tile errors of both (largest over the 17 bands).

Run: ``python examples/real_inputs.py --out docs``.
"""

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.colors import LogNorm

from jface import data, detail, io, mesh, plots, raster, render


def _pose(vertices: np.ndarray, marks: np.ndarray) -> np.ndarray:
    """A rotation putting the face upright and frontal: nose out of the eye/mouth plane → +z,
    chin → forehead → +y."""
    names = mesh.LANDMARK_NAMES
    centre = marks[[names.index(n) for n in ("left_eye_inner", "right_eye_inner")]].mean(axis=0)
    forward = marks[names.index("nose_tip")] - centre
    forward /= np.linalg.norm(forward)
    up = marks[names.index("forehead")] - marks[names.index("chin")]
    up -= (up @ forward) * forward
    up /= np.linalg.norm(up)
    return np.stack([np.cross(up, forward), up, forward])


def _distances(detailed: np.ndarray, scan) -> np.ndarray:
    from scipy.spatial import cKDTree
    from trimesh.triangles import closest_point

    tri = scan.vertices[scan.faces]
    _, cand = cKDTree(tri.mean(axis=1)).query(detailed, k=16)
    q = closest_point(tri[cand.ravel()], np.repeat(detailed, 16, axis=0))
    return np.linalg.norm(q - np.repeat(detailed, 16, axis=0), axis=1).reshape(-1, 16).min(1)


def real_scan(out: Path, before: Path | None, size: int) -> None:
    scan, marks = data.lee_perry_smith()
    points = np.asarray(mesh.landmark_points(marks, scan.vertices), dtype=np.float64)
    pose = _pose(scan.vertices, points)
    centre, extent = raster.framing(points @ pose.T)
    extent *= 1.5
    diagonal = float(np.linalg.norm(np.ptp(scan.vertices, axis=0)))

    def view(vertices, faces):
        posed = np.asarray(vertices, dtype=np.float64) @ pose.T
        return raster.render(posed, np.asarray(faces), 512, center=centre, extent=extent)

    result = mesh.remesh(scan.vertices, scan.faces, marks, image_size=size)
    rows = []
    if before is not None:
        base = io.read_mesh(before / "base.obj", merge=False)
        image = io.read_map(before / "displacement.exr")
        old = mesh.displace(mesh.Mesh(base.vertices, base.faces, base.uv), image)
        rows.append(("earlier jface", old, image, None))
    detailed = mesh.displace(result.base, result.image)
    rows.append(("now", detailed, np.asarray(result.image), np.asarray(result.filled)))
    scan_view = view(scan.vertices, scan.faces)
    fig, axes = plots.axes_grid(
        len(rows), 4, size=(16, 4.4 * len(rows)),
        title="Remeshing a real head scan (Golovinskiy et al. 2006, §2.2)",
    )  # fmt: skip
    for (label, shape, image, filled), row in zip(rows, axes, strict=True):
        gap = 100 * _distances(np.asarray(shape.vertices, np.float64)[::13], scan) / diagonal
        row[0].imshow(scan_view, cmap="gray", vmin=0, vmax=1)
        row[0].set_title("scan (Lee Perry-Smith)")
        row[1].imshow(view(shape.vertices, shape.faces), cmap="gray", vmin=0, vmax=1)
        row[1].set_title(
            f"detailed mesh, {label}\nto scan: p99 {np.percentile(gap, 99):.3f}%, "
            f"max {gap.max():.2f}% of diag."
        )
        row[2].imshow(render.shade(image), cmap="gray", vmin=0, vmax=1)
        row[2].set_title(f"displacement image, {label}")
        if filled is None:
            row[3].axis("off")
        else:
            shown = row[3].imshow(filled, cmap=plots.COLOUR_MAPS["weight"], vmin=0, vmax=1)
            row[3].set_title(f"filled where rays missed ({np.mean(filled > 0.5):.2%})")
            fig.colorbar(shown, ax=row[3], fraction=0.046, label="share of the pixel filled")
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
            ax.title.set_fontsize(10)
    meta = io.provenance(source="lee_perry_smith_head.obj", image_size=size)
    io.write_figure(out / "mesh" / "real_scan.png", fig, metadata=meta)


def heterogeneous_synthesis(out: Path, size: int) -> None:
    maps = data.heterogeneous_maps(size)
    fig, axes = plots.axes_grid(
        len(maps), 6, size=(20, 3.6 * len(maps)),
        title=f"Re-synthesis from a map's own 16×16 statistics ({size}², Golovinskiy et al. "
        "Fig. 5) on real maps whose detail changes abruptly",
    )  # fmt: skip
    norm = LogNorm(1e-3, 10.0)
    key = jax.random.key(0)
    for (name, image), row in zip(maps.items(), axes, strict=True):
        image = jnp.asarray(image)
        stats = detail.analyze(image)
        smooth = detail.remove_detail(image, n_bands=3)
        panels = [("original", image), ("smoothed (no 3 finest bands)", smooth)]
        errors = []
        for label, settings in (
            ("paper, 12 plain iterations", {"n_iter": 12, "memory": 0, "n_polish": 0}),
            ("jface defaults", {}),
        ):
            result = detail.synthesize(key, smooth, stats, **settings)
            error = np.asarray(detail.stats_error(detail.analyze(result), stats))
            panels.append(
                (
                    f"{label}\nmedian {np.median(error):.1%}, p95 {np.percentile(error, 95):.1%}",
                    result,
                )
            )
            errors.append((label.split(",")[0], error.max(axis=0)))
        for ax, (label, panel) in zip(row[:4], panels, strict=True):
            ax.imshow(render.shade(panel), cmap="gray", vmin=0, vmax=1)
            ax.set_title(label, fontsize=10)
        for ax, (label, error) in zip(row[4:], errors, strict=True):
            shown = ax.imshow(np.maximum(error, 1e-3), cmap=plots.COLOUR_MAPS["error"], norm=norm)
            ax.set_title(f"{label}: per-tile error\n(largest over the bands)", fontsize=10)
        fig.colorbar(shown, ax=row[4:], fraction=0.05, label="|σ − τ| / τ")
        row[0].set_ylabel(name, fontsize=13)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    meta = io.provenance(seed=0, maps=list(maps), size=size)
    io.write_figure(out / "detail" / "heterogeneous_synthesis.png", fig, metadata=meta)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs", help="folder with mesh/ and detail/")
    parser.add_argument("--before", help="a face folder of an earlier `jface remesh` run")
    parser.add_argument("--image-size", type=int, default=1024)
    parser.add_argument("--map-size", type=int, default=512)
    args = parser.parse_args()
    out = Path(args.out)
    real_scan(out, Path(args.before) if args.before else None, args.image_size)
    heterogeneous_synthesis(out, args.map_size)


if __name__ == "__main__":
    main()
