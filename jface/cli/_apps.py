"""``jface interpolate``, ``jface add-detail`` and ``jface age``: the applications of
Golovinskiy et al. 2006 §3.2–§3.4 (and the §4 comparison) on face folders.

A face folder is what ``jface remesh`` writes: ``base.obj`` (or ``.ply``) with uv,
``displacement.exr`` and ``hierarchy.npz`` (marker mesh + level offsets). Every command writes its
results as face folders too, so they chain (interpolate, then age the result, ...).
"""

from __future__ import annotations

import argparse
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from jface import detail, io, mesh, plots, render, wrinkles
from jface.cli import deprecated_alias
from jface.cli._detail import GROUP_FORM, parse_group
from jface.cli._mesh import check_face_outputs, write_face
from jface.detail._meshes import check_faces


def register(sub: argparse._SubParsersAction) -> None:
    interp = sub.add_parser(
        "interpolate", help="interpolate faces, detail coerced to the mixed statistics (§3.2)"
    )
    interp.add_argument("faces", nargs="+", help="face folders (from jface remesh)")
    interp.add_argument(
        "--weights", help="comma-separated weights summing to 1 (default: equal weights)"
    )
    interp.add_argument("--out", required=True, help="output folder")
    _synthesis_options(interp)
    interp.set_defaults(
        run=_interpolate,
        prose="wrote {out}/: median per-tile std error {average[median_tile_std_error]:.1%} "
        "(average), {coerced[median_tile_std_error]:.1%} (coerced)",
    )

    add = sub.add_parser(
        "add-detail", help="coerce a low-resolution face's detail to target statistics (§3.3)"
    )
    add.add_argument("face", help="face folder (from jface remesh of the low-resolution mesh)")
    _target_options(add, required=True)
    add.add_argument("--out", required=True, help="output folder")
    _synthesis_options(add)
    add.set_defaults(
        run=_add_detail,
        prose="wrote {out}/: median per-tile std error {median_tile_std_error[before]:.1%} "
        "before, {median_tile_std_error[after]:.1%} after",
    )

    age = sub.add_parser(
        "age",
        help="age a face with an old one's detail and finer levels (§3.4; swap them to de-age), "
        "and compare with Perlin noise, sharpening and detail transfer (§4)",
    )
    age.add_argument("young", help="face folder to change")
    age.add_argument("old", help="face folder giving the statistics and the finer levels")
    age.add_argument(
        "--levels",
        type=int,
        default=3,
        help="coarsest levels kept from the young face (1 = marker mesh only; default 3)",
    )
    _target_options(age, required=False)
    age.add_argument("--out", required=True, help="output folder")
    _synthesis_options(age)
    age.set_defaults(run=_age, prose="wrote {out}/; methods compared: {methods}")


def _synthesis_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grid", type=int, default=16, help="tiles per side for the statistics")
    parser.add_argument("--scales", type=int, default=4, help="pyramid scales")
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the synthesis noise (default %(default)s)",
    )
    parser.add_argument(
        "--iters",
        type=int,
        default=detail._synthesis.N_ITER,
        help="synthesis iterations (Anderson-accelerated, then a polish) (default %(default)s)",
    )
    deprecated_alias(parser, "--n-iter", "--iters")
    parser.add_argument(
        "--noise",
        type=float,
        default=detail._synthesis.NOISE,
        help="start noise, relative to the target detail amplitude (default %(default)s)",
    )
    parser.add_argument("--format", choices=("obj", "ply"), default="obj", help="mesh format")


def _target_options(parser: argparse.ArgumentParser, required: bool) -> None:
    group = parser.add_mutually_exclusive_group(required=required)
    group.add_argument("--stats", help="target statistics of one face (.npz from jface analyze)")
    group.add_argument("--target", help="target face folder (its statistics are taken)")
    group.add_argument("--db", help="population file (jface db build): target = a group mean")
    parser.add_argument(
        "--group",
        metavar=GROUP_FORM,
        help="with --db: the group whose mean statistics are the target, e.g. 'age=60..80' "
        "(a NAME: before it is allowed and unused)",
    )


def read_face(folder: str | Path) -> detail.Face:
    """Read a face folder written by ``jface remesh`` (or by these commands)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"no such face folder: {folder} (make one with jface remesh)")
    bases = [folder / f"base.{ext}" for ext in ("obj", "ply") if (folder / f"base.{ext}").is_file()]
    if not bases:
        raise FileNotFoundError(f"{folder} has no base.obj or base.ply (see jface remesh)")
    base = io.read_mesh(bases[0], merge=False)
    if base.uv is None:
        raise ValueError(f"{bases[0]} has no per-vertex uv; use a base mesh from jface remesh")
    image = io.read_map(folder / "displacement.exr")
    arrays, meta = io.load_arrays(folder / "hierarchy.npz", kind="MeshHierarchy")
    if "schedule" not in meta:
        raise ValueError(f"{folder / 'hierarchy.npz'} lacks the 'schedule' metadata field")
    try:
        schedule = tuple(int(n) for n in meta["schedule"])
        hierarchy = mesh.template_hierarchy(None, *schedule)
    except (TypeError, ValueError, OverflowError) as err:
        raise ValueError(
            f"{folder / 'hierarchy.npz'} has an invalid 'schedule' (three subdivision counts): "
            f"{err}"
        ) from err
    names = ["markers"] + [f"offsets_{k + 1}" for k in range(hierarchy.n_projected)]
    missing = [name for name in names if name not in arrays]
    if missing:
        raise ValueError(f"{folder / 'hierarchy.npz'} lacks the arrays {missing}")
    if len(base.vertices) != hierarchy.base.n_vertices:
        raise ValueError(
            f"{bases[0]} has {len(base.vertices)} vertices, but schedule {list(schedule)} gives "
            f"base meshes of {hierarchy.base.n_vertices}"
        )
    return detail.Face(
        jnp.asarray(arrays["markers"], jnp.float32),
        tuple(jnp.asarray(arrays[name], jnp.float32) for name in names[1:]),
        mesh.Mesh(
            jnp.asarray(base.vertices, jnp.float32),
            jnp.asarray(base.faces, jnp.int32),
            jnp.asarray(base.uv, jnp.float32),
        ),
        jnp.asarray(image, jnp.float32),
        schedule,
    )


def _layout(args: argparse.Namespace) -> dict:
    return {"grid": args.grid, "n_scales": args.scales}


def _target(
    args: argparse.Namespace, default: detail.Face | None
) -> tuple[detail.DetailStats, str]:
    """``(statistics, description)`` of the target named by --stats / --target / --db --group,
    or of ``default`` (the old face)."""
    if args.group and not args.db:
        raise ValueError("--group needs --db")
    if args.stats:
        return detail.load_stats(args.stats).stats.reduced(), Path(args.stats).name
    if args.db:
        if not args.group:
            raise ValueError(f"--db needs --group {GROUP_FORM} naming the target group")
        population = detail.Population.load(args.db)
        _, criteria = parse_group(args.group)
        return population.select(**criteria).mean().reduced(), f"{args.db} [{args.group}]"
    face = read_face(args.target) if args.target else default
    name = args.target or "the old face"
    return detail.analyze(face.image, **_layout(args)), str(name)


def _options(args: argparse.Namespace) -> dict:
    return {"n_iter": args.iters, "noise": args.noise}


def _error(image, target: detail.DetailStats) -> float:
    """Median per-tile std error of an image to the target statistics."""
    return float(jnp.median(detail.stats_error(detail.analyze_like(image, target), target)))


def _tile_errors(image, target: detail.DetailStats) -> np.ndarray:
    """Per-tile error to the target statistics, median over bands."""
    return np.median(np.asarray(detail.stats_error(detail.analyze_like(image, target), target)), 0)


def _interpolate(args: argparse.Namespace) -> dict:
    for name in ("average", "coerced"):
        check_face_outputs(Path(args.out) / name, args.format)
    faces = [read_face(f) for f in tqdm(args.faces, desc="read faces", unit="face")]
    check_faces(faces)  # one layout, before their images are stacked
    if args.weights:
        weights = [float(w) for w in args.weights.split(",")]
    else:
        weights = [1.0 / len(faces)] * len(faces)
    images = jnp.stack([f.image for f in faces])
    stats = detail.analyze_batch(images, **_layout(args))
    result = detail.interpolate_faces(
        jax.random.key(args.seed), faces, stats, jnp.asarray(weights, jnp.float32), **_options(args)
    )
    meta = io.provenance(
        seed=args.seed,
        faces=[Path(f).name for f in args.faces],
        weights=weights,
        experiment="Golovinskiy 2006 §3.2 interpolation",
        **_layout(args),
        **_options(args),
    )
    out = Path(args.out)
    for name, face in (("average", result.average), ("coerced", result.coerced)):
        write_face(out / name, face, meta, args.format)
    table = {
        name: {"median_tile_std_error": _error(face.image, result.target)}
        for name, face in (("average", result.average), ("coerced", result.coerced))
    }
    figure = plots.panel_grid(
        [[render.shade(result.average.image), render.shade(result.coerced.image)]],
        title="Interpolated faces: averaged detail, then coerced to the interpolated statistics",
        col_labels=["average", "coerced"],
    )
    io.write_figure(out / "average_vs_coerced.png", figure, metadata=meta)
    io.write_json(out / "interpolation.json", {**meta, "results": table})
    return {"out": str(out), **table}


def _add_detail(args: argparse.Namespace) -> dict:
    check_face_outputs(Path(args.out), args.format)
    face = read_face(args.face)
    target, source = _target(args, None)
    result = detail.add_detail(jax.random.key(args.seed), face, target, **_options(args))
    meta = io.provenance(
        seed=args.seed,
        face=Path(args.face).name,
        target=source,
        experiment="Golovinskiy 2006 §3.3 adding detail",
        **_options(args),
    )
    out = Path(args.out)
    write_face(out, result, meta, args.format)
    figure = plots.panel_grid(
        [[render.shade(face.image), render.shade(result.image)]],
        title="Adding detail: the face before and after synthesis to the target statistics",
        col_labels=["before", "after"],
    )
    io.write_figure(out / "before_after.png", figure, metadata=meta)
    table = {"before": _error(face.image, target), "after": _error(result.image, target)}
    io.write_json(out / "add_detail.json", {**meta, "median_tile_std_error": table})
    return {"out": str(out), "median_tile_std_error": table}


def _age(args: argparse.Namespace) -> dict:
    for name in ("aged", "detail_only"):
        check_face_outputs(Path(args.out) / name, args.format)
    young, old = read_face(args.young), read_face(args.old)
    target, source = _target(args, old)
    meta = io.provenance(
        seed=args.seed,
        young=Path(args.young).name,
        old=Path(args.old).name,
        target=source,
        levels=args.levels,
        experiment="Golovinskiy 2006 §3.4 aging, §4 comparison",
        **_options(args),
    )
    out = Path(args.out)
    scores = age_and_compare(
        jax.random.key(args.seed), young, old, target, out, meta, args.levels, _options(args),
        fmt=args.format,
    )  # fmt: skip
    return {"out": str(out), "methods": scores}


def age_and_compare(
    key, young, old, target, out: Path, meta: dict, levels: int, options: dict, *,
    fmt: str = "obj",
) -> dict:  # fmt: skip
    """Age ``young`` towards ``target`` (§3.4), make the §4 baselines beside it and write the
    aged face, the detail-only face, each method's EXR, the Fig. 10 comparison figure and table;
    returns the table."""
    steps = tqdm(total=3, desc="age", unit="step")
    aged = detail.age(key, young, old, target, n_coarse=levels, **options)
    steps.update()
    # The statistical method's image is the aged face's; the baselines are made beside it.
    baselines = [m for m in detail.METHODS if m != "statistical"]
    results = {
        "statistical": aged.image,
        **detail.method_results(key, young.image, old.image, target, methods=baselines, **options),
    }
    steps.update()
    scores = detail.method_scores(results, young.image, target)
    steps.update()
    steps.close()
    write_face(out / "aged", aged, meta, fmt)
    detail_only = detail.Face(young.markers, young.offsets, young.base, aged.image, young.schedule)
    write_face(out / "detail_only", detail_only, meta, fmt)
    for name, image in results.items():
        io.write_exr(out / "methods" / f"{name}.exr", np.asarray(image), metadata=meta)
    # Fig. 10: young, old, then the four methods; below, each one's per-tile error to the target
    # statistics.
    images = [young.image, old.image, *results.values()]
    figure = plots.method_comparison(
        images,
        [_tile_errors(image, target) for image in images],
        ["young", "old", *results],
        title="Aging the young face to the target statistics: methods compared (GMP06 Fig. 10)",
    )
    io.write_figure(out / "comparison.png", figure, metadata=meta)
    io.write_json(out / "comparison.json", {**meta, "methods": scores})
    return scores


def _demo_faces(seed: int, size: int) -> tuple[detail.Face, detail.Face]:
    """Two identities of the built-in ICT-FaceKit model, remeshed; the young one gets faint
    pores (high frequencies of the built-in gravel map), the old one deeper pores plus micro
    wrinkles from :mod:`jface.wrinkles`. Amplitudes in cm, like the ICT meshes."""
    with resources.as_file(resources.files("jface") / "data" / "ict_face_small.npz") as path:
        model, _ = io.load_arrays(path, kind="FaceMeshModel")
    with resources.as_file(resources.files("jface") / "data" / "gravel.exr") as path:
        gravel = io.read_map(path)
    rng = np.random.default_rng(seed)
    modes = model["identity_deltas"].astype(np.float64)
    keys = jax.random.split(jax.random.key(seed))

    def fine(texture):
        return texture / texture.std()

    pores = [fine(crop - detail.remove_detail(crop, n_bands=3)) for crop in (
        jnp.asarray(gravel[:size, :size]), jnp.asarray(gravel[-size:, -size:])
    )]  # fmt: skip
    creases = wrinkles.synthesize(
        keys[1], wrinkles.WrinkleParams(d=0.04, theta=0.6, s=0.6, deposit=0.6), (size, size)
    ).displacement
    detail_maps = (0.004 * pores[0], 0.008 * pores[1] + 0.012 * fine(creases))
    result = []
    for extra in detail_maps:
        person = model["vertices"] + np.tensordot(rng.normal(size=len(modes)), modes, axes=1)
        remeshed = mesh.remesh(
            person, model["faces"], mesh.ict_landmarks(person), image_size=size, n_smooth=2
        )
        face = detail.Face.from_remeshed(remeshed)
        result.append(
            detail.Face(face.markers, face.offsets, face.base, face.image + extra, face.schedule)
        )
    return result[0], result[1]


def demo(out_dir: Path, seed: int) -> None:
    """Aging and the §4 comparison (Fig. 10) on two remeshed identities of the built-in
    ICT-FaceKit model."""
    out = Path(out_dir) / "age"
    young, old = _demo_faces(seed, 256)
    target = detail.analyze(old.image)
    meta = io.provenance(
        seed=seed,
        source="jface/data/ict_face_small.npz identities + gravel pores + jface.wrinkles",
        levels=3,
        experiment="Golovinskiy 2006 §3.4 aging, §4 comparison",
    )
    write_face(out / "young", young, meta, "ply")
    write_face(out / "old", old, meta, "ply")
    scores = age_and_compare(jax.random.key(seed), young, old, target, out, meta, 3, {}, fmt="ply")
    print(
        "age: young ICT face aged to the old one's statistics — median per-tile std error "
        + ", ".join(f"{name} {row['stats_error']:.1%}" for name, row in scores.items())
        + f"; keeps {scores['statistical']['keeps_coarse']:.2f} of the young detail's coarsest "
        "band (correlation)"
    )
