"""Landmarks without clicks: accuracy and speed of ``jface.mesh.find_landmarks`` on real scans.

1. The Lee Perry-Smith scan and each of its variants (``jface.data.scan_variants``: decimated,
   holes, noise, millimetres, posed, all at once): per-marker distance to the hand-placed
   landmarks in mm (of the original scan's frame) and in % of the inter-ocular distance (IOD)
   and of the head's bounding-box diagonal; median, mean and max; the spread of each variant's
   markers (mapped back) around the original's; time per scan after a warm-up (compilation).
2. A 283k-triangle scan (the Lee Perry-Smith scan Loop-subdivided twice): time per scan.
3. A vmapped batch of 16 scans resampled to the same size (``sample_surface`` then
   ``fit_samples``): time per scan.
4. Remeshing with the found landmarks against remeshing with the hand-placed ones: correlation
   of the two displacement images and each detailed mesh's distance to the scan; and where each
   marker's error comes from (fit, projection, template convention).
5. How much landmark accuracy the remeshing needs: the hand-placed landmarks moved by random
   offsets of known size (along the scan, a given RMS in % IOD, on all markers or only on the
   eight outline ones), remeshed, and the displacement image correlated with the hand one.

There is no reference implementation to time against: the alternative is placing the 21
markers by hand. Each case prints one JSON line.

Run: ``python benchmarks/bench_landmarks.py`` (``--quick``: the scan and two variants, the
diagnosis and the found-vs-hand remesh only).
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import numpy as np
import trimesh

from jface import data, mesh
from jface.mesh._raycast import ScanIndex, closest_points

NAMES = mesh.LANDMARK_NAMES


def _print(row: dict) -> None:
    print(json.dumps(row, ensure_ascii=False), flush=True)


def _timed(fn):
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - start


def accuracy(quick: bool) -> np.ndarray:
    scan, marks = data.lee_perry_smith()
    truth = np.asarray(mesh.landmark_points(marks, scan.vertices), np.float64)
    iod = float(
        np.linalg.norm(truth[NAMES.index("right_eye_outer")] - truth[NAMES.index("left_eye_outer")])
    )
    diagonal = float(np.linalg.norm(np.ptp(scan.vertices, axis=0)))
    kinds = ("original", "posed", "noise") if quick else None
    variants = data.scan_variants(
        scan.vertices, scan.faces, marks, **({"kinds": kinds} if kinds else {})
    )
    mesh.find_landmarks(scan.vertices, scan.faces)  # warm-up: compilation
    reference = None
    per_marker = {}
    for name, variant in variants.items():
        found, seconds = _timed(lambda v=variant: mesh.find_landmarks(v.vertices, v.faces))
        back = variant.to_original(np.asarray(found.points, np.float64))
        err = np.linalg.norm(back - truth, axis=1)
        if reference is None:
            reference = back
        spread = np.linalg.norm(back - reference, axis=1)
        per_marker[name] = err
        _print(
            {
                "case": f"lee_perry_smith/{name}",
                "jface_ms": round(seconds * 1e3, 1),
                "triangles": len(variant.faces),
                "score": round(float(found.score), 3),
                "median_mm": round(1e3 * float(np.median(err)), 2),
                "mean_mm": round(1e3 * float(err.mean()), 2),
                "max_mm": round(1e3 * float(err.max()), 2),
                "mean_iod_pct": round(100 * float(err.mean()) / iod, 2),
                "max_iod_pct": round(100 * float(err.max()) / iod, 2),
                "median_diag_pct": round(100 * float(np.median(err)) / diagonal, 3),
                "max_diag_pct": round(100 * float(err.max()) / diagonal, 3),
                "spread_vs_original_max_iod_pct": round(100 * float(spread.max()) / iod, 2),
            }
        )
    table = {
        n: [round(1e3 * float(per_marker[k][i]), 1) for k in per_marker]
        for i, n in enumerate(NAMES)
    }
    _print({"case": "per_marker_mm", "variants": list(per_marker), "markers": table})
    diagnosis(scan, truth, iod)
    return reference


def _similarity_onto(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` moved by the least-squares similarity onto ``b`` (Umeyama)."""
    ca, cb = a - a.mean(axis=0), b - b.mean(axis=0)
    u, s, vt = np.linalg.svd(cb.T @ ca)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    scale = float(np.sum(s * np.diag(d))) / float(np.sum(ca**2))
    return scale * ca @ (u @ d @ vt).T + b.mean(axis=0)


def diagnosis(scan, truth: np.ndarray, iod: float) -> None:
    """Where each marker's error comes from, in % IOD: the fit (the fitted model's landmark
    vertex before projection), the projection onto the scan (found), the error's component along
    the scan's normal (what projecting or a non-rigid refinement along normals can remove), and
    the definition: the MediaPipe canonical face's landmarks (the template's convention) moved
    by their best similarity onto the hand-placed ones, a floor no similarity fit of that
    convention goes below."""
    found = mesh.find_landmarks(scan.vertices, scan.faces)
    index = ScanIndex(scan.vertices, scan.faces)
    _, _, tri = closest_points(index, truth)
    corners = np.asarray(scan.vertices, np.float64)[np.asarray(scan.faces)[np.asarray(tri)]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    model_error = np.asarray(found.model_points, np.float64) - truth
    face = data.mediapipe_face()
    convention = _similarity_onto(np.asarray(mesh.mediapipe_landmarks(face.vertices)), truth)
    rows = {
        "found": np.linalg.norm(np.asarray(found.points, np.float64) - truth, axis=1),
        "model_vertex": np.linalg.norm(model_error, axis=1),
        "model_vertex_along_normal": np.abs(np.sum(model_error * normals, axis=1)),
        "mediapipe_convention_floor": np.linalg.norm(convention - truth, axis=1),
    }
    _print(
        {
            "case": "per_marker_diagnosis_iod_pct",
            **{f"{k}_mean": round(100 * float(v.mean()) / iod, 2) for k, v in rows.items()},
            "markers": {
                n: {k: round(100 * float(v[i]) / iod, 1) for k, v in rows.items()}
                for i, n in enumerate(NAMES)
            },
        }
    )


def large_scan() -> None:
    scan, _ = data.lee_perry_smith()
    v, f = np.asarray(scan.vertices), np.asarray(scan.faces)
    for _ in range(2):
        v, f = trimesh.remesh.subdivide_loop(v, f)
    mesh.find_landmarks(v, f)  # warm-up: compilation for this mesh size
    times = [_timed(lambda: mesh.find_landmarks(v, f))[1] for _ in range(2)]
    _print({"case": "large_scan", "triangles": len(f), "jface_ms": round(min(times) * 1e3, 1)})


def batch(size: int = 16) -> None:
    scan, marks = data.lee_perry_smith()
    variants = data.scan_variants(scan.vertices, scan.faces, marks, kinds=("posed",), seed=1)
    model = mesh.face_model()
    keys = jax.random.split(jax.random.key(0), size)
    draw = jax.jit(jax.vmap(mesh.sample_surface, in_axes=(0, None, None, None)), static_argnums=3)
    posed = variants["posed"]
    v = np.asarray(posed.vertices - posed.vertices.mean(axis=0), np.float32)
    f = np.asarray(posed.faces, np.int32)
    fit = jax.jit(jax.vmap(lambda k, s: mesh.fit_samples(k, s, model)))
    run = lambda: fit(keys, draw(keys, v, f, 32768))  # noqa: E731
    _timed(run)  # warm-up: compilation
    fits, seconds = _timed(run)
    _print(
        {
            "case": f"vmapped_batch_{size}",
            "jface_ms_per_scan": round(seconds * 1e3 / size, 1),
            "jface_ms_batch": round(seconds * 1e3, 1),
            "score_range": [round(float(fits.score.min()), 3), round(float(fits.score.max()), 3)],
        }
    )


def remesh_agreement(found_points: np.ndarray, image_size: int = 256) -> None:
    scan, marks = data.lee_perry_smith()
    index = ScanIndex(scan.vertices, scan.faces)
    results = {}
    for name, landmarks in (("hand", marks), ("found", found_points)):
        result, seconds = _timed(
            lambda m=landmarks: mesh.remesh(scan.vertices, scan.faces, m, image_size=image_size)
        )
        detailed = mesh.displace(result.base, result.image)
        points = np.asarray(detailed.vertices, np.float64)
        sample = points[np.random.default_rng(0).choice(len(points), 4000, replace=False)]
        _, dist, _ = closest_points(index, sample)
        results[name] = (np.asarray(result.image, np.float64), dist, seconds)
    _print(
        {
            "case": "remesh_found_vs_hand",
            "image_size": image_size,
            "image_correlation": round(
                _image_correlation(results["hand"][0], results["found"][0]), 4
            ),
            **{
                f"{k}_detailed_to_scan_median_mm": round(1e3 * float(np.median(r[1])), 3)
                for k, r in results.items()
            },
            **{
                f"{k}_detailed_to_scan_p99_mm": round(1e3 * float(np.quantile(r[1], 0.99)), 3)
                for k, r in results.items()
            },
        }
    )


def _image_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Correlation of two displacement images over their inner 80 % (the border is the outline)."""
    n = a.shape[0]
    inside = (slice(n // 10, -n // 10),) * 2
    return float(np.corrcoef(a[inside].ravel(), b[inside].ravel())[0, 1])


def remesh_sensitivity(image_size: int = 256, seeds: int = 3) -> None:
    scan, marks = data.lee_perry_smith()
    truth = np.asarray(mesh.landmark_points(marks, scan.vertices), np.float64)
    iod = float(
        np.linalg.norm(truth[NAMES.index("right_eye_outer")] - truth[NAMES.index("left_eye_outer")])
    )
    index = ScanIndex(scan.vertices, scan.faces)
    _, _, tri = closest_points(index, truth)
    corners = np.asarray(scan.vertices, np.float64)[np.asarray(scan.faces)[np.asarray(tri)]]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)

    def image(points):
        return np.asarray(
            mesh.remesh(scan.vertices, scan.faces, points, image_size=image_size).image
        )

    reference = image(truth)
    outline = [
        NAMES.index(n)
        for n in NAMES
        if n.endswith(("cheek", "jaw", "temple")) or n in ("forehead", "chin")
    ]
    for which, ids in (("all", list(range(len(NAMES)))), ("outline", outline)):
        for pct in (0.25, 0.5, 1.0, 2.0, 5.0, 10.0):
            corr = []
            for seed in range(seeds):
                rng = np.random.default_rng(seed)
                step = rng.normal(size=truth.shape)
                step -= np.sum(step * normals, axis=1, keepdims=True) * normals  # along the scan
                step *= pct / 100.0 * iod / np.sqrt(np.mean(np.sum(step[ids] ** 2, axis=1)))
                moved = truth.copy()
                moved[ids] += step[ids]
                moved, _, _ = closest_points(index, moved)
                corr.append(_image_correlation(reference, image(np.asarray(moved))))
            _print(
                {
                    "case": "remesh_vs_landmark_error",
                    "moved": which,
                    "rms_iod_pct": pct,
                    "image_size": image_size,
                    "correlation": [round(c, 3) for c in corr],
                }
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the scan and two variants only")
    args = parser.parse_args()
    found = accuracy(args.quick)
    remesh_agreement(found)
    if not args.quick:
        remesh_sensitivity()
        large_scan()
        batch()


if __name__ == "__main__":
    main()
