"""``jface landmarks``, ``jface remesh``, ``jface displace`` and the remeshing step of the
demo."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from jface import io, mesh, plots, raster, render
from jface.cli import deprecated_alias


def register(sub: argparse._SubParsersAction) -> None:
    lm = sub.add_parser(
        "landmarks",
        help="scan → its 21 template landmarks, found by fitting the built-in ICT-FaceKit model",
    )
    lm.add_argument("scan", help="scan mesh (OBJ, PLY, ...), any orientation, position and unit")
    lm.add_argument("--out", required=True, help="output JSON: name → x,y,z")
    lm.add_argument("--picture", help="PNG: the shaded scan with the markers and their names")
    lm.add_argument("--seed", type=int, default=0, help="seeds the surface samples")
    lm.set_defaults(
        run=_landmarks,
        prose="found the 21 landmarks of {scan} in {seconds:.1f} s: fit score {score:.3f} "
        "(0 perfect, 1 nothing fits), {inliers:.0%} of the face model on the scan, "
        "RMS {rms:.3g} scan units; written to {out}",
    )

    rem = sub.add_parser(
        "remesh", help="scan + 21 landmarks → base mesh + displacement image (Golovinskiy §2.2)"
    )
    rem.add_argument("scan", help="scan mesh (OBJ, PLY, ...)")
    rem.add_argument(
        "--landmarks",
        help="JSON/CSV: the 21 template names → x,y,z or vertex id (ids count the vertices as "
        "read with coincident ones merged, as jface.io.read_mesh does); without it they are "
        "found by fitting the built-in face model (as jface landmarks does)",
    )
    rem.add_argument("--out", required=True, help="output folder")
    rem.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seeds the surface samples of the landmark search (without --landmarks)",
    )
    deprecated_alias(rem, "--out-dir", "--out")
    rem.add_argument("--image-size", type=int, default=1024, help="displacement image side, pixels")
    rem.add_argument("--linear", type=int, default=2, help="projected linear subdivisions")
    rem.add_argument("--loop", type=int, default=2, help="projected Loop subdivisions")
    rem.add_argument("--smooth", type=int, default=3, help="Loop subdivisions to the base mesh")
    rem.add_argument(
        "--fit", type=int, default=0, help="least-squares fit iterations of the control mesh"
    )
    rem.add_argument(
        "--method",
        choices=("auto", "embree", "kdtree"),
        default="auto",
        help="ray caster: Embree when installed (auto), or a k-d tree of the scan",
    )
    rem.add_argument("--format", choices=("obj", "ply"), default="obj", help="base mesh format")
    rem.set_defaults(
        run=_remesh,
        prose="remeshed {scan} in {seconds:.1f} s: base mesh {triangles} triangles, displacement "
        "{image_size}×{image_size}; hit rates per level {hit_rates}; {missed} base rays missed "
        "the scan, {filled:.2%} of the image filled (red in filled.png); written to {out}/",
    )

    dis = sub.add_parser("displace", help="base mesh + displacement image → detailed mesh")
    dis.add_argument("base", help="base mesh with uv (from jface remesh)")
    dis.add_argument("disp", help="displacement image (EXR, one channel)")
    dis.add_argument("--out", required=True, help="output mesh (.obj or .ply)")
    dis.add_argument("--extra", type=int, default=0, help="midpoint subdivisions first (0-3)")
    dis.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="factor on the displacement (scan units per map unit)",
    )
    dis.set_defaults(run=_displace, prose="wrote {out}: {triangles} triangles")


def _face_pose(face) -> np.ndarray:
    """A rotation that puts the face upright and frontal whatever the scan's axes: the mean base
    normal towards the viewer (+z), chin → forehead up (+y)."""
    base = face.base
    normals = np.asarray(mesh.vertex_normals(base.vertices, base.faces), dtype=np.float64)
    forward = normals.sum(axis=0)
    markers = np.asarray(face.markers, dtype=np.float64)
    names = mesh.LANDMARK_NAMES
    up = markers[names.index("forehead")] - markers[names.index("chin")]
    forward /= np.linalg.norm(forward)
    up -= (up @ forward) * forward
    up /= np.linalg.norm(up)
    return np.stack([np.cross(up, forward), up, forward])


def _views(vertices, faces, pose: np.ndarray, center, extent: float, size: int, title: str):
    """Figure of shaded 3-D views of a mesh, frontal and turned 35° (nose to the right)."""
    posed = np.asarray(vertices, dtype=np.float64) @ pose.T
    frames = [
        raster.render(posed, np.asarray(faces), size, yaw=yaw, center=center, extent=extent)
        for yaw in (0.0, 35.0)
    ]
    return plots.panel_grid(
        [frames], title=title, col_labels=["frontal", "turned 35°"], panel_inches=3.0
    )


def check_face_outputs(out: Path, fmt: str) -> None:
    """Refuse, before any work, a face folder output that would replace an input face."""
    for name in (f"base.{fmt}", "displacement.exr", "hierarchy.npz", "filled.png"):
        io.check_output(out / name)


def write_face(out: Path, face, meta: dict, fmt: str, protect=()) -> None:
    """Write a face folder: base mesh, displacement EXR + PNG, shaded 3-D views of the base and
    the re-displaced mesh, and the hierarchy (markers, control, offsets, schedule).

    ``face`` is a :class:`jface.mesh.Remeshed` or a :class:`jface.detail.Face`.
    """
    protect = tuple(protect)
    base = face.base
    io.write_mesh(
        out / f"base.{fmt}",
        np.asarray(base.vertices),
        np.asarray(base.faces),
        uv=np.asarray(base.uv),
        comment=f"jface {meta['jface_version']} base mesh",
        protect=protect,
    )
    image = np.asarray(face.image)
    io.write_exr(out / "displacement.exr", image, metadata=meta, protect=protect)
    io.write_png(out / "displacement.png", render.shade(image), metadata=meta, protect=protect)
    # Base and re-displaced mesh seen from the same camera, so the two views align.
    pose = _face_pose(face)
    center, extent = raster.framing(np.asarray(base.vertices, dtype=np.float64) @ pose.T)
    size = min(max(image.shape), 768)
    detailed = mesh.displace(base, face.image)
    for name, shape, what in (
        ("base", base, "Base mesh"),
        ("detailed", detailed, "Base mesh re-displaced by its displacement image"),
    ):
        figure = _views(shape.vertices, shape.faces, pose, center, extent, size, what)
        io.write_figure(out / f"{name}_shaded.png", figure, metadata=meta, protect=protect)
    arrays = {"markers": face.markers, "control": face.control}
    arrays |= {f"offsets_{k + 1}": o for k, o in enumerate(face.offsets)}
    meta = {**meta, "schedule": list(face.schedule)}
    io.save_arrays(out / "hierarchy.npz", arrays, meta, kind="MeshHierarchy", protect=protect)


def _remesh(args: argparse.Namespace) -> dict:
    check_face_outputs(Path(args.out), args.format)
    scan = io.read_mesh(args.scan)
    if args.landmarks is None:
        start = time.perf_counter()
        found = mesh.find_landmarks(scan.vertices, scan.faces, key=jax.random.key(args.seed))
        marks = found.as_dict()
        print(
            f"no --landmarks: found the 21 landmarks by fitting the face model in "
            f"{time.perf_counter() - start:.1f} s (fit score {float(found.score):.3f}); "
            "written to landmarks.json"
        )
    else:
        marks = io.read_landmarks(
            args.landmarks, n_vertices=len(scan.vertices), names=mesh.LANDMARK_NAMES
        )
    start = time.perf_counter()
    result = mesh.remesh(
        scan.vertices,
        scan.faces,
        marks,
        image_size=args.image_size,
        n_linear=args.linear,
        n_loop=args.loop,
        n_smooth=args.smooth,
        fit=args.fit,
        method=args.method,
        progress=True,
    )
    seconds = time.perf_counter() - start
    rates = [round(float(r), 5) for r in np.asarray(result.hit_rate)]
    filled = np.asarray(result.filled)
    meta = io.provenance(
        source=Path(args.scan).name,
        landmarks=Path(args.landmarks).name if args.landmarks else "found (jface landmarks)",
        schedule=[args.linear, args.loop, args.smooth],
        fit=args.fit,
        hit_rates=rates,
        filled_fraction=round(float(np.mean(filled > 0.5)), 5),
        image_convention="row 0 = v 1 (forehead); u left to right = subject's right to left",
    )
    out = Path(args.out)
    inputs = (args.scan, args.landmarks) if args.landmarks else (args.scan,)
    write_face(out, result, meta, args.format, protect=inputs)
    if args.landmarks is None:
        io.write_landmarks(out / "landmarks.json", marks, protect=inputs)
    # Where rays missed the scan the image is a membrane fill: shown in red over the relief.
    shaded = np.asarray(render.shade(result.image))[..., None]
    red = np.asarray([1.0, 0.15, 0.1])
    tinted = shaded * (1 - filled[..., None]) + red * filled[..., None]
    figure = plots.panel_grid(
        [[tinted]],
        title=f"Displacement image of {Path(args.scan).name}; red: filled where rays missed",
        col_labels=[f"{np.mean(filled > 0.5):.2%} filled"],
        panel_inches=4.0,
    )
    io.write_figure(out / "filled.png", figure, metadata=meta)
    missed = int(np.sum(np.asarray(result.missed)))
    return {
        "out": str(out),
        "scan": Path(args.scan).name,
        "seconds": seconds,
        "triangles": int(result.base.faces.shape[0]),
        "image_size": int(result.image.shape[0]),
        "hit_rates": rates,
        "missed": missed,
        "filled": float(np.mean(filled > 0.5)),
    }


def _landmarks(args: argparse.Namespace) -> dict:
    io.check_output(args.out, (".json",))
    if args.picture:
        io.check_output(args.picture, (".png",))
    scan = io.read_mesh(args.scan)
    start = time.perf_counter()
    found = mesh.find_landmarks(scan.vertices, scan.faces, key=jax.random.key(args.seed))
    seconds = time.perf_counter() - start
    io.write_landmarks(args.out, found.as_dict(), protect=(args.scan,))
    if args.picture:
        meta = io.provenance(
            seed=args.seed, source=Path(args.scan).name, score=round(float(found.score), 4)
        )
        figure = landmark_picture(scan.vertices, scan.faces, found)
        io.write_figure(args.picture, figure, metadata=meta, protect=(args.scan,))
    return {
        "out": args.out,
        "picture": args.picture,
        "scan": Path(args.scan).name,
        "seconds": seconds,
        "score": float(found.score),
        "inliers": float(found.inliers),
        "rms": float(found.rms),
    }


def landmark_picture(vertices, faces, found, size: int = 640):
    """Figure of the scan shaded from the fitted face's front, the markers with their names."""
    rotation = np.asarray(found.rotation, dtype=np.float64)
    # The model's axes (right, up, front) → the camera's (x, y, z): a frontal view.
    posed = np.asarray(vertices, dtype=np.float64) @ rotation
    points = np.asarray(found.points, dtype=np.float64) @ rotation
    center = points.mean(axis=0)
    extent = 2.6 * float(np.linalg.norm(points - center, axis=1).max())
    image = raster.render(posed, np.asarray(faces), size, center=center, extent=extent)
    _, screen = raster.project(
        np.vstack([posed, points]), (size, size), center=center, extent=extent
    )
    screen = screen[-len(points) :]
    return plots.labelled_points(
        np.asarray(image),
        screen[:, :2],
        list(found.names),
        title=f"Landmarks found by fitting the face model (score {float(found.score):.3f})",
    )


def _displace(args: argparse.Namespace) -> dict:
    io.check_output(args.out, (".obj", ".ply"))
    base = io.read_mesh(args.base, merge=False)
    if base.uv is None:
        raise ValueError(f"{args.base} has no per-vertex uv; use a base mesh from jface remesh")
    image = io.read_map(args.disp)
    result = mesh.displace(base, image, extra_subdivisions=args.extra, scale=args.scale)
    io.write_mesh(
        args.out,
        np.asarray(result.vertices),
        np.asarray(result.faces),
        uv=np.asarray(result.uv),
        comment=f"jface displace {Path(args.base).name} {Path(args.disp).name}",
        protect=(args.base, args.disp),
    )
    return {"out": args.out, "triangles": int(result.faces.shape[0])}


def demo(out: Path, seed: int) -> None:
    """Remesh a synthetic scan of the built-in MediaPipe face whose fine detail is known."""
    out = Path(out) / "mesh"
    synthetic = mesh.synthetic_scan(jax.random.key(seed), wavelength=0.12, amplitude=0.05)
    scan = synthetic.scan
    start = time.perf_counter()
    result = mesh.remesh(scan.vertices, np.asarray(scan.faces), synthetic.landmarks, image_size=512)
    seconds = time.perf_counter() - start
    meta = io.provenance(
        seed=seed,
        source="mediapipe_canonical_face.obj, 4 Loop subdivisions + known detail",
        schedule=[2, 2, 3],
        fit=0,
        hit_rates=[round(float(r), 5) for r in np.asarray(result.hit_rate)],
    )
    write_face(out, result, meta, "ply")
    sampler = mesh.image_sampler(result.base.uv, result.base.faces, result.image.shape)
    known = np.asarray(sampler(mesh.known_displacement(synthetic, result.base)))
    offset = np.asarray(sampler(mesh.smooth_offset(synthetic, result.base)))
    io.write_exr(out / "known_displacement.exr", known, metadata=meta)
    inside = (slice(51, -51), slice(51, -51))
    image = np.asarray(result.image)[inside].ravel()
    corr = [np.corrcoef(t[inside].ravel(), image)[0, 1] for t in (known, known + offset)]
    recovered = np.asarray(result.image)
    figure = plots.panel_grid(
        [[render.shade(known), render.shade(recovered)], [known, recovered]],
        title=f"Remeshing a synthetic scan: known and recovered detail (correlation {corr[0]:.3f})",
        col_labels=["known", "recovered"],
        row_labels=["shaded relief", "displacement"],
        quantities=["relief", "displacement"],
        units=[None, "displacement (scan units)"],
        panel_inches=2.6,
    )
    io.write_figure(out / "known_vs_recovered.png", figure, metadata=meta)
    print(
        f"mesh: remeshed a {scan.faces.shape[0]}-triangle synthetic scan in {seconds:.1f} s "
        f"({result.base.faces.shape[0]}-triangle base mesh); recovered vs known detail "
        f"correlation {corr[0]:.3f}, {corr[1]:.3f} counting the base mesh's smooth offset "
        "from the face (docs/mesh.md)"
    )
