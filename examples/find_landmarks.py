"""Landmarks without clicks on the real Lee Perry-Smith scan: the built-in face model fitted to
the scan, its markers against the hand-placed ones, and the error of each marker.

Writes ``docs/mesh/landmarks_found.png`` (or ``--out``): left, the scan seen from the fitted
face's front with the hand-placed markers (green) and the found ones (red); right, each marker's
distance to its hand-placed position in % of the inter-ocular distance, on the scan and on the
scan posed at random and in millimetres.

Run: ``python examples/find_landmarks.py``.
"""

from __future__ import annotations

import argparse

import numpy as np

from jface import data, io, mesh, plots, raster

NAMES = mesh.LANDMARK_NAMES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/mesh/landmarks_found.png")
    args = parser.parse_args()
    scan, marks = data.lee_perry_smith()
    truth = np.asarray(mesh.landmark_points(marks, scan.vertices), np.float64)
    iod = np.linalg.norm(
        truth[NAMES.index("right_eye_outer")] - truth[NAMES.index("left_eye_outer")]
    )
    found = mesh.find_landmarks(scan.vertices, scan.faces)
    errors = {"scan": np.linalg.norm(np.asarray(found.points) - truth, axis=1) / iod * 100}
    moved = data.scan_variants(scan.vertices, scan.faces, marks, kinds=("combined",))["combined"]
    again = mesh.find_landmarks(moved.vertices, moved.faces)
    back = moved.to_original(np.asarray(again.points, np.float64))
    errors["posed, mm, holes, noise, decimated"] = np.linalg.norm(back - truth, axis=1) / iod * 100

    rotation = np.asarray(found.rotation, np.float64)  # model axes → scan: a frontal camera
    posed = np.asarray(scan.vertices, np.float64) @ rotation
    center = truth.mean(axis=0) @ rotation
    extent = 2.6 * float(np.linalg.norm(truth - truth.mean(axis=0), axis=1).max())
    size = 600
    image = raster.render(posed, np.asarray(scan.faces), size, center=center, extent=extent)
    fig, ((left, right),) = plots.axes_grid(
        1, 2, size=(13, 6.4), width_ratios=(1, 1.25),
        title="Landmarks without clicks: the face model fitted to the Lee Perry-Smith scan",
    )  # fmt: skip
    left.imshow(np.asarray(image), cmap="gray", vmin=0, vmax=1)
    for points, colour, label in (
        (truth, "lime", "hand-placed"),
        (np.asarray(found.points, np.float64), "red", "found"),
    ):
        both = np.vstack([posed, points @ rotation])
        _, screen = raster.project(both, (size, size), center=center, extent=extent)
        screen = screen[-len(points) :]
        left.scatter(screen[:, 0], screen[:, 1], s=16, c=colour, label=label, edgecolors="k")
    left.legend(loc="lower right")
    left.set_title("Lee Perry-Smith scan: hand-placed and found markers")
    left.set_axis_off()
    x = np.arange(len(NAMES))
    for k, (label, err) in enumerate(errors.items()):
        right.bar(x + (k - 0.5) * 0.4, err, 0.4, label=f"{label} (mean {err.mean():.1f}%)")
    right.set_xticks(x, NAMES, rotation=70, ha="right", fontsize=8)
    right.set_ylabel("distance to the hand-placed marker (% of inter-ocular distance)")
    right.set_title("error per marker")
    right.legend(loc="upper left")
    right.grid(axis="y", alpha=0.3)
    right.set_xlabel("marker")
    meta = io.provenance(seed=0, source="lee_perry_smith_head.obj", score=float(found.score))
    io.write_figure(args.out, fig, metadata=meta)
    print(
        f"wrote {args.out}: mean error {errors['scan'].mean():.1f}% IOD on the scan, "
        f"{errors['posed, mm, holes, noise, decimated'].mean():.1f}% on the combined variant"
    )


if __name__ == "__main__":
    main()
