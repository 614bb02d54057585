"""Draw the marker template: its layout in the unit square (left) and the same triangles on the
MediaPipe canonical face (right, frontal view). Writes ``docs/marker_template.png``.

Run: ``python examples/marker_template_figure.py [--out docs/marker_template.png]``
"""

from __future__ import annotations

import argparse

import numpy as np
from matplotlib.collections import PolyCollection

from jface import io, mesh, plots


def _panel(ax, points: np.ndarray, faces: np.ndarray, names, corners, title: str) -> None:
    """The marker triangles over ``points`` (x right, y up), each marker numbered and named;
    the fixed corners in red."""
    ax.add_collection(
        PolyCollection(points[np.asarray(faces)], facecolors="#ebf0fa", edgecolors="#5a5a5a")
    )
    colours = ["tab:red" if i in corners else "navy" for i in range(len(points))]
    ax.scatter(points[:, 0], points[:, 1], s=18, c=colours, zorder=3)
    for i, (x, y) in enumerate(points):
        ax.annotate(f"{i} {names[i]}", (x, y), (4, 4), textcoords="offset points", fontsize=7)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_title(title, fontsize=9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/marker_template.png")
    args = parser.parse_args()
    template = mesh.marker_template()
    face = mesh.canonical_face()
    points3d = np.asarray(mesh.mediapipe_landmarks(face.vertices))
    figure, ((left, right),) = plots.axes_grid(
        1, 2, size=(13, 6.6), title="The marker template of remeshing (red: fixed corners)"
    )
    _panel(left, np.asarray(template.uv), template.faces, template.names, template.corners,
           "layout in the unit square")  # fmt: skip
    left.set(xlabel="u", ylabel="v")
    _panel(right, points3d[:, :2], template.faces, template.names, template.corners,
           "the marker mesh on the MediaPipe canonical face (front view)")  # fmt: skip
    right.set(xlabel="x", ylabel="y")
    io.write_figure(args.out, figure, metadata=io.provenance(figure="marker template"))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
