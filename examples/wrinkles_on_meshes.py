"""Micro wrinkles on real meshes (Weiss et al. 2023, Fig. 4 and §5): the MediaPipe canonical face
and the Lee Perry-Smith head scan, both shipped in ``jface/data``.

For each mesh: the radius map **R** from the UV stretch (pores evenly spaced on the surface), a
two-level micro-wrinkle map synthesised in the mesh's UV atlas (not periodic), the mesh
subdivided and displaced along its normals (``jface.mesh.displace``), and shaded renders
(``jface.raster``) of the plain and the wrinkled mesh, plus the map and R as pictures.

Lee Perry-Smith's UVs are one unwrapped head (face in the middle, ears at the sides) that fills
the unit square; MediaPipe's UVs are the frontal face. Both have v up, the wrinkle maps y down the
rows, hence the ``[::-1]`` before displacing.

Run: ``python examples/wrinkles_on_meshes.py --out wrinkles_meshes [--size 2048]``
Credits: "Infinite, 3D Head Scan" by Lee Perry-Smith (CC BY 3.0); MediaPipe (Apache-2.0).
"""

import argparse
from pathlib import Path

import jax
import numpy as np

from jface import data, io, mesh, plots, raster, render
from jface.wrinkles import WrinkleParams, radius_map_from_mesh, synthesize

MESHES = {
    # name: (file, subdivisions before displacing, pore distance α_d, depth per map unit as a
    # fraction of the bounding-box diagonal, view yaw in degrees)
    "mediapipe_face": (data.path("mediapipe_canonical_face.obj"), 3, 0.012, 0.006, 20.0),
    "lee_perry_smith_head": (data.path("lee_perry_smith_head.obj"), 1, 0.01, 0.0015, 30.0),
}


def wrinkle(name, path, subdivisions, d, depth, yaw, size, seed, out):
    surface = io.read_mesh(path, uv_seams=True)  # one UV per vertex: split at the seams
    # R clipped to [0.4, 2.5]: the scan's neck cap is squashed 6× in UV, which would multiply
    # the pore count (and the sampler's grid) there for a region nobody looks at
    radius = radius_map_from_mesh(surface, 512, limits=(0.4, 2.5))
    levels = [
        WrinkleParams(d=d, theta=0.3, s=0.3, wrinkle_width=0.35, pore_width=0.4, dmin=0.6),
        WrinkleParams(d=d / 2, theta=1.2, s=0.2, wrinkle_width=0.25, pore_width=0.2, scale=0.3),
    ]
    syn = synthesize(jax.random.key(seed), levels, (size, size), radius_map=radius,
                     periodic=False, n_steps=50)  # fmt: skip
    disp = np.asarray(syn.displacement)
    diag = float(np.linalg.norm(np.ptp(surface.vertices, axis=0)))
    moved = mesh.displace(surface, disp[::-1], scale=depth * diag,
                          extra_subdivisions=subdivisions)  # fmt: skip
    plain = mesh.displace(surface, disp[::-1], scale=0.0, extra_subdivisions=subdivisions)
    meta = io.provenance(seed=seed, mesh=path.name, levels=[p.to_dict() for p in levels],
                         size=size, depth=depth, subdivisions=subdivisions)  # fmt: skip
    center, extent = raster.framing(np.asarray(plain.vertices))
    for tag, m in (("plain", plain), ("wrinkled", moved)):
        image = raster.render(np.asarray(m.vertices), np.asarray(m.faces), (900, 900), yaw=yaw,
                              center=center, extent=extent, light=(0.6, 0.5, 1.0))  # fmt: skip
        io.write_png(out / f"{name}_{tag}.png", image, metadata=meta)
    io.write_png(out / f"{name}_map.png", render.shade(disp), metadata=meta)
    figure = plots.image(
        np.asarray(radius)[::-1], title=f"{name}:\npore-radius scale R from the UV stretch",
        quantity="statistics", units="R: local pore spacing / α_d",
    )  # fmt: skip
    io.write_figure(out / f"{name}_radius.png", figure, metadata=meta)
    io.write_exr(out / f"{name}_map.exr", disp, metadata=meta)
    counts = ", ".join(str(int(lv.pores.count)) for lv in syn.levels)
    print(f"{name}: R in [{float(radius.min()):.2f}, {float(radius.max()):.2f}], pores {counts}, "
          f"{len(moved.faces)} triangles → {out}/{name}_*.png")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="wrinkles_meshes", help="output folder")
    parser.add_argument("--size", type=int, default=2048, help="map side in pixels")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    out = Path(args.out)
    for name, (path, subdivisions, d, depth, yaw) in MESHES.items():
        wrinkle(name, path, subdivisions, d, depth, yaw, args.size, args.seed, out)


if __name__ == "__main__":
    main()
