"""Remeshing speed: jface.mesh.remesh against the same pipeline written with stock trimesh.

The scans are the MediaPipe canonical face Loop-subdivided 4 and 5 times plus known detail
(230k and 920k triangles, bracketing the ~500k-triangle scans of the paper). Each case prints one
JSON line: jface's time (Embree, and the exact k-d tree caster) after a warm-up run (compilation,
template levels and the image sampler are built once per template and timed apart), and the time
of the reference measured in the same run:

- "trimesh_embree": the paper's schedule written with stock trimesh — ``trimesh.remesh.subdivide``
  and ``subdivide_loop`` per level, ``mesh.ray.intersects_location`` forward and backward after
  each projected level and for the base mesh, per-vertex displacement (no image);
- "trimesh_triangle": trimesh's pure-numpy ray caster (``ray_triangle``), timed on a sample of
  the base rays and extrapolated to all of them (all of them take hours and run out of memory).

Run: ``python benchmarks/bench_remesh.py`` (``--quick`` for the small scan only).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
import trimesh

from jface import mesh


def _project_trimesh(scan: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, intersector):
    """Nearest hit along ±normal with a trimesh intersector (first hit each way)."""
    best = np.full(len(points), np.inf)
    for sign in (1.0, -1.0):
        loc, ray, _ = intersector.intersects_location(points, sign * normals, multiple_hits=False)
        t = np.einsum("ij,ij->i", loc - points[ray], normals[ray])
        closer = np.abs(t) < np.abs(best[ray])
        best[ray[closer]] = t[closer]
    return np.where(np.isfinite(best), best, 0.0)


def reference_pipeline(scan: trimesh.Trimesh, markers: np.ndarray, faces: np.ndarray) -> float:
    """The paper's schedule with stock trimesh calls; returns seconds."""
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    start = time.perf_counter()
    intersector = RayMeshIntersector(scan)
    vertices, tri = markers, faces
    for step in ("linear", "linear", "loop", "loop"):
        if step == "linear":
            vertices, tri = trimesh.remesh.subdivide(vertices, tri)
        else:
            vertices, tri = trimesh.remesh.subdivide_loop(vertices, tri)
        normals = trimesh.Trimesh(vertices, tri, process=False).vertex_normals
        vertices = (
            vertices + _project_trimesh(scan, vertices, normals, intersector)[:, None] * normals
        )
    vertices, tri = trimesh.remesh.subdivide_loop(vertices, tri, iterations=3)
    normals = trimesh.Trimesh(vertices, tri, process=False).vertex_normals
    _project_trimesh(scan, vertices, normals, intersector)
    return time.perf_counter() - start


def triangle_caster_estimate(scan: trimesh.Trimesh, base: mesh.Mesh, n_rays: int = 500) -> float:
    """Seconds trimesh's pure-numpy caster would take for all base rays (from a sample)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    intersector = RayMeshIntersector(scan)
    vertices = np.asarray(base.vertices, dtype=np.float64)
    normals = np.asarray(mesh.vertex_normals(base.vertices, base.faces), dtype=np.float64)
    pick = np.linspace(0, len(vertices) - 1, n_rays).astype(int)
    start = time.perf_counter()
    _project_trimesh(scan, vertices[pick], normals[pick], intersector)
    return (time.perf_counter() - start) * len(vertices) / n_rays


def run_case(n_subdivisions: int) -> None:
    synthetic = mesh.synthetic_scan(jax.random.key(0), n_subdivisions=n_subdivisions)
    vertices = np.asarray(synthetic.scan.vertices, dtype=np.float64)
    faces = np.asarray(synthetic.scan.faces)
    times = {}
    for method in ("embree", "kdtree"):
        start = time.perf_counter()
        mesh.remesh(vertices, faces, synthetic.landmarks, method=method)
        warm = time.perf_counter() - start
        start = time.perf_counter()
        result = mesh.remesh(vertices, faces, synthetic.landmarks, method=method)
        times[method] = (time.perf_counter() - start, warm)
    scan = trimesh.Trimesh(vertices, faces, process=False)
    markers = np.asarray(result.markers, dtype=np.float64)
    reference = reference_pipeline(scan, markers, mesh.marker_template().faces)
    estimate = triangle_caster_estimate(scan, result.base)
    for method, (seconds, warm) in times.items():
        for name, ref in (("trimesh_embree", reference), ("trimesh_triangle_est", estimate)):
            print(
                json.dumps(
                    {
                        "case": f"remesh_{method}_vs_{name}",
                        "scan_triangles": len(faces),
                        "base_triangles": int(result.base.faces.shape[0]),
                        "image": list(result.image.shape),
                        "jface_s": round(seconds, 3),
                        "jface_first_call_s": round(warm, 3),
                        "reference_s": round(ref, 3),
                        "ratio": round(ref / seconds, 2),
                    }
                ),
                flush=True,
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the 230k-triangle scan")
    args = parser.parse_args()
    for n in (4,) if args.quick else (4, 5):
        run_case(n)


if __name__ == "__main__":
    main()
