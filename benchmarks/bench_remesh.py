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

Then the real Lee Perry-Smith scan and its perturbed variants (holes, noise, decimation,
millimetres, pose, all at once): time and the detailed mesh's distance to the clean scan, for
jface and for the stock trimesh pipeline.

Run: ``python benchmarks/bench_remesh.py`` (``--quick`` for the small synthetic scan only).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
import trimesh

from jface import data, mesh


def _project_trimesh(scan: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray, intersector):
    """Nearest hit along ±normal with a trimesh intersector (first hit each way)."""
    best = np.full(len(points), np.inf)
    for sign in (1.0, -1.0):
        loc, ray, _ = intersector.intersects_location(points, sign * normals, multiple_hits=False)
        t = np.einsum("ij,ij->i", loc - points[ray], normals[ray])
        closer = np.abs(t) < np.abs(best[ray])
        best[ray[closer]] = t[closer]
    return np.where(np.isfinite(best), best, 0.0)


def reference_pipeline(
    scan: trimesh.Trimesh, markers: np.ndarray, faces: np.ndarray
) -> tuple[float, np.ndarray]:
    """The paper's schedule with stock trimesh calls (nearest hit along ±normal, misses left
    where they are); returns seconds and the displaced base vertices."""
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
    displaced = vertices + _project_trimesh(scan, vertices, normals, intersector)[:, None] * normals
    return time.perf_counter() - start, displaced


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
    reference, _ = reference_pipeline(scan, markers, mesh.marker_template().faces)
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


def _distance_to_scan(points: np.ndarray, scan: trimesh.Trimesh) -> np.ndarray:
    """Distance from points to the scan (closest point over the 16 nearest triangles)."""
    from scipy.spatial import cKDTree

    tri = scan.triangles
    _, cand = cKDTree(tri.mean(axis=1)).query(points, k=16)
    q = trimesh.triangles.closest_point(tri[cand.ravel()], np.repeat(points, 16, axis=0))
    return np.linalg.norm(q - np.repeat(points, 16, axis=0), axis=1).reshape(-1, 16).min(axis=1)


def real_scans(image_size: int) -> None:
    """The Lee Perry-Smith head and its perturbed variants (jface.data.scan_variants): time, and
    the distance of 20,000 detailed-mesh vertices (mapped back) to the clean scan in % of its
    diagonal, for jface and for the stock trimesh pipeline (nearest hit, misses not filled)."""
    scan, marks = data.lee_perry_smith()
    clean = trimesh.Trimesh(scan.vertices, scan.faces, process=False)
    diagonal = float(np.linalg.norm(np.ptp(scan.vertices, axis=0)))

    def sample(points: np.ndarray) -> np.ndarray:
        return points[np.random.default_rng(0).choice(len(points), 20000, replace=False)]

    for kind, v in data.scan_variants(scan.vertices, scan.faces, marks).items():
        mesh.remesh(v.vertices, v.faces, v.landmarks, image_size=image_size)  # warm
        start = time.perf_counter()
        result = mesh.remesh(v.vertices, v.faces, v.landmarks, image_size=image_size)
        seconds = time.perf_counter() - start
        detailed = np.asarray(mesh.displace(result.base, result.image).vertices, np.float64)
        ours = _distance_to_scan(v.to_original(sample(detailed)), clean) / diagonal * 100
        variant = trimesh.Trimesh(v.vertices, v.faces, process=False)
        markers = np.asarray(result.markers, dtype=np.float64)
        reference, stock = reference_pipeline(variant, markers, mesh.marker_template().faces)
        theirs = _distance_to_scan(v.to_original(sample(stock)), clean) / diagonal * 100
        row = {
            "case": f"remesh Lee Perry-Smith, {kind}",
            "scan_triangles": len(v.faces),
            "jface_s": round(seconds, 3),
            "reference": "stock trimesh pipeline (Embree, nearest hit)",
            "reference_s": round(reference, 3),
            "ratio": round(reference / seconds, 2),
            "p99_pct": round(float(np.percentile(ours, 99)), 4),
            "max_pct": round(float(ours.max()), 3),
            "reference_p99_pct": round(float(np.percentile(theirs, 99)), 4),
            "reference_max_pct": round(float(theirs.max()), 3),
            "hit_rates": [round(float(r), 4) for r in np.asarray(result.hit_rate)],
            "filled": round(float(np.mean(np.asarray(result.filled) > 0.5)), 4),
        }
        print(json.dumps(row), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the 230k-triangle scan")
    parser.add_argument("--image-size", type=int, default=1024, help="for the real scans")
    args = parser.parse_args()
    for n in (4,) if args.quick else (4, 5):
        run_case(n)
    real_scans(args.image_size)


if __name__ == "__main__":
    main()
