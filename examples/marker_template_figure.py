"""Draw the marker template: its layout in the unit square (left) and the same triangles on the
MediaPipe canonical face (right, frontal view). Writes ``docs/marker_template.png``.

Run: ``python examples/marker_template_figure.py [--out docs/marker_template.png]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from jface import io, mesh

SIZE, PAD = 560, 40


def _panel(points: np.ndarray, faces: np.ndarray, names, corners, title: str) -> Image.Image:
    img = Image.new("RGB", (SIZE + 2 * PAD + 80, SIZE + 2 * PAD + 24), "white")
    draw = ImageDraw.Draw(img)
    lo, hi = points.min(0), points.max(0)
    scale = SIZE / max(hi - lo)
    xy = (points - lo) * scale
    xy[:, 1] = SIZE - xy[:, 1]  # v (or y) up
    xy += PAD
    for f in faces:
        draw.polygon([tuple(xy[i]) for i in f], outline=(90, 90, 90), fill=(235, 240, 250))
    for i, (x, y) in enumerate(xy):
        colour = (200, 40, 40) if i in corners else (30, 60, 160)
        draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=colour)
        draw.text((x + 5, y - 12), f"{i} {names[i]}", fill=(0, 0, 0))
    draw.text((PAD, SIZE + 2 * PAD - 4), title, fill=(0, 0, 0))
    return img


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/marker_template.png")
    args = parser.parse_args()
    template = mesh.marker_template()
    face = mesh.canonical_face()
    points3d = np.asarray(mesh.mediapipe_landmarks(face.vertices))
    left = _panel(
        template.uv,
        template.faces,
        template.names,
        template.corners,
        "layout in the unit square (u right, v up; red: fixed corners)",
    )
    right = _panel(
        points3d[:, :2],
        template.faces,
        template.names,
        template.corners,
        "the marker mesh on the MediaPipe canonical face (front view)",
    )
    both = Image.new("RGB", (left.width + right.width, left.height), "white")
    both.paste(left, (0, 0))
    both.paste(right, (left.width, 0))
    io.write_png(Path(args.out), np.asarray(both), metadata={"figure": "marker template"})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
