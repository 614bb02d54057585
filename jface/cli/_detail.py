"""``jface analyze``, ``jface synthesize``, ``jface render`` and the detail step of the demo."""

from __future__ import annotations

import argparse
import importlib.resources
import json
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jface import detail, io, plots, render
from jface.cli import deprecated_alias, refuse_shared_names
from jface.cli._processes import Elsewhere, add_process_options, spread
from jface.detail._population import check_records


def register(sub: argparse._SubParsersAction) -> None:
    analyze = sub.add_parser(
        "analyze", help="per-tile steerable-pyramid statistics of displacement maps"
    )
    analyze.add_argument(
        "files",
        nargs="+",
        help="maps: EXR (one channel), PNG/JPEG or .npy, or face folders of jface remesh "
        "(their displacement.exr, named by the folder)",
    )
    analyze.add_argument("--out", required=True, help="output folder (one .npz + .png per map)")
    analyze.add_argument(
        "--grid",
        type=int,
        default=16,
        help="tiles per side of the statistics grid (default %(default)s)",
    )
    analyze.add_argument(
        "--scales", type=int, default=4, help="pyramid scales (default %(default)s)"
    )
    analyze.add_argument(
        "--orientations", type=int, default=4, help="orientations per scale (default %(default)s)"
    )
    analyze.add_argument("--bins", type=int, default=None, help="also store histograms (full)")
    analyze.add_argument(
        "--boundary",
        choices=("circular", "reflect"),
        default="circular",
        help="pyramid boundary: periodic (the paper's) or mirrored (default %(default)s)",
    )
    analyze.add_argument(
        "--overwrite", action="store_true", help="redo maps whose statistics already exist"
    )
    analyze.set_defaults(
        run=_analyze,
        prose="analyzed {analyzed} map(s), kept {kept} already done (same content and settings), "
        "in {out}/",
    )

    synth = sub.add_parser("synthesize", help="coerce a map to target statistics")
    synth.add_argument("start", help="map to start from")
    synth.add_argument("--stats", required=True, help="target statistics (.npz from analyze)")
    synth.add_argument("--out", required=True, help="output EXR (a shaded PNG is written beside)")
    synth.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the synthesis noise (default %(default)s)",
    )
    synth.add_argument(
        "--iters",
        type=int,
        default=detail._synthesis.N_ITER,
        help="synthesis iterations (Anderson-accelerated, then a polish) (default %(default)s)",
    )
    deprecated_alias(synth, "--n-iter", "--iters")
    synth.add_argument(
        "--noise",
        type=float,
        default=detail._synthesis.NOISE,
        help="start noise, relative to the target detail amplitude (default %(default)s)",
    )
    synth.add_argument(
        "--rule",
        choices=("exact", "paper"),
        default="exact",
        help="per-tile gain: the tile's own, or the paper's grown tiles (default %(default)s)",
    )
    synth.add_argument(
        "--method",
        choices=("std", "histogram"),
        default=None,
        help="match deviations or histograms (default: histogram when the statistics have them)",
    )
    synth.add_argument(
        "--boundary",
        choices=("circular", "reflect"),
        default=None,
        help="pyramid boundary (default: the one the statistics were analysed with)",
    )
    synth.set_defaults(
        run=_synthesize, prose="wrote {out}: median per-tile std error {median_tile_std_error:.1%}"
    )

    db = sub.add_parser("db", help="statistics databases of many faces")
    db_sub = db.add_subparsers(dest="db_command", required=True, metavar="ACTION")
    build = db_sub.add_parser("build", help="analyse many maps into one population file")
    build.add_argument(
        "files",
        nargs="+",
        help="displacement maps, all of one size, or face folders of jface remesh (records "
        "named by the folder)",
    )
    build.add_argument("--out", required=True, help="population file (.npz)")
    build.add_argument(
        "--metadata", help="JSON list (or JSON-lines file) of records, one per map, with 'id'"
    )
    build.add_argument(
        "--grid",
        type=int,
        default=16,
        help="tiles per side of the statistics grid (default %(default)s)",
    )
    build.add_argument("--scales", type=int, default=4, help="pyramid scales (default %(default)s)")
    build.add_argument(
        "--bins", type=int, default=None, help="also store per-tile histograms with this many bins"
    )
    build.add_argument(
        "--chunk",
        type=int,
        default=8,
        help="maps analysed at once (bounds memory) (default %(default)s)",
    )
    add_process_options(build, "analysing a share of the maps")
    build.set_defaults(run=_db_build, prose="{faces} faces in {out}")
    compare = db_sub.add_parser(
        "compare", help="compare groups tile by tile (Golovinskiy et al. Fig. 6)"
    )
    compare.add_argument("db", help="population file")
    compare.add_argument(
        "--group",
        action="append",
        required=True,
        metavar=GROUP_FORM,
        help="a group by record fields, e.g. 'young:age=20..30,sex=m', or 'age=20..30' named by "
        "its criteria (repeat, 2-4 groups)",
    )
    compare.add_argument(
        "--show-scale", type=int, default=1, help="pyramid scale to draw, 0 = finest (default 1)"
    )
    deprecated_alias(compare, "--scale", "--show-scale")
    compare.add_argument("--out", required=True, help="output PNG (a .json table is written too)")
    compare.set_defaults(run=_db_compare, prose="wrote {out}; reference group {reference}")

    draw = sub.add_parser("render", help="shaded relief PNG of a displacement map")
    draw.add_argument("map", help="map file")
    draw.add_argument("--out", required=True, help="output PNG")
    draw.set_defaults(run=_render, prose="wrote {out}")


def map_inputs(names: list[str]) -> tuple[list[str], list[str]]:
    """The map files among command-line inputs and a name for each: a face folder written by
    ``jface remesh`` stands for its ``displacement.exr`` and is named by the folder, a file by its
    stem."""
    files, labels = [], []
    for name in names:
        path = Path(name)
        if path.is_dir():
            if not (path / "displacement.exr").is_file():
                raise FileNotFoundError(
                    f"{path} is a folder without displacement.exr (not a face of jface remesh)"
                )
            files.append(str(path / "displacement.exr"))
            labels.append(path.resolve().name)
        else:
            files.append(name)
            labels.append(path.stem)
    return files, labels


def _analyze(args: argparse.Namespace) -> dict:
    out = Path(args.out)
    files, labels = map_inputs(args.files)
    refuse_shared_names(args.files, [f"{label}.stats.npz" for label in labels])
    settings = {
        "grid": args.grid,
        "n_scales": args.scales,
        "n_orientations": args.orientations,
        "bins": args.bins,
        "boundary": args.boundary,
    }
    for label in labels:
        io.check_output(out / (label + ".stats.npz"), (".npz",))
        io.check_output(out / (label + ".stats.png"), (".png",))
    done = skipped = 0
    pairs = list(zip(files, labels, strict=True))
    for name, label in tqdm(pairs, desc="analyze", unit="map", disable=len(files) < 2):
        target = out / (label + ".stats.npz")
        source = Path(name).name if label == Path(name).stem else f"{label}/{Path(name).name}"
        picture = target.with_suffix(".png")
        key = io.content_key([name], {"kind": "DetailStats", **settings})
        if target.exists() and not args.overwrite:
            with io.own_outputs():
                meta = detail.load_stats(target).metadata
            if meta.get("source") != source:
                raise ValueError(
                    f"{target} holds statistics of {meta.get('source')!r}, not of {name}; "
                    "use another --out or --overwrite"
                )
            if meta.get("key") == key and picture.exists():
                skipped += 1  # same map, same settings: a batch that died keeps what it did
                continue
        stats = detail.analyze(io.read_map(name), **settings)
        detail.save_stats(target, stats, source=source, boundary=args.boundary, key=key)
        figure = plots.band_statistics(
            stats.std, stats.n_orientations, title=f"Per-tile std of each band: {source}"
        )
        meta = io.provenance(source=source, grid=args.grid, scales=args.scales)
        io.write_figure(picture, figure, metadata=meta)
        io.commit()  # each finished map survives a crash of a later one
        done += 1
    return {"out": str(out), "analyzed": done, "kept": skipped}


def _synthesize(args: argparse.Namespace) -> dict:
    out = io.check_output(args.out, (".exr",))
    io.check_output(out.with_suffix(".png"), (".png",))
    start = io.read_map(args.start)
    saved = detail.load_stats(args.stats)
    target, stats_meta = saved.stats, saved.metadata
    boundary = args.boundary or stats_meta.get("boundary", "circular")
    method = args.method or ("histogram" if target.full else "std")
    result = detail.synthesize(
        jax.random.key(args.seed),
        start,
        target,
        n_iter=args.iters,
        noise=args.noise,
        rule=args.rule,
        method=method,
        boundary=boundary,
    )
    analysed = detail.analyze_like(result, target, boundary=boundary)
    error = np.asarray(detail.stats_error(analysed, target))
    meta = io.provenance(
        seed=args.seed,
        start=Path(args.start).name,
        stats=Path(args.stats).name,
        iters=args.iters,
        noise=args.noise,
        rule=args.rule,
        method=method,
        boundary=boundary,
    )
    io.write_exr(out, np.asarray(result), metadata=meta)
    io.write_png(out.with_suffix(".png"), render.shade(result), metadata=meta)
    return {"out": str(out), "median_tile_std_error": float(np.median(error))}


def _read_records(path: str, n_maps: int) -> list[dict]:
    try:
        data = io.read_json(path)
    except ValueError as whole:
        try:  # not one JSON document: JSON lines, one record per line
            data = io.read_json(path, lines=True)
        except ValueError as lines:  # "extra data" after a first document: meant as lines
            raise (lines if "Extra data" in str(whole) else whole) from None
    if not isinstance(data, list) or not all(isinstance(r, dict) for r in data):
        raise ValueError(f"{path} must hold a JSON list of records (objects), one per map")
    if len(data) != n_maps:
        raise ValueError(f"{path} holds {len(data)} record(s) for {n_maps} map(s); one per map")
    try:
        check_records(data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from err
    return data


def _db_build(args: argparse.Namespace) -> dict:
    files, labels = map_inputs(args.files)
    if args.metadata:
        records = _read_records(args.metadata, len(files))
    elif any(Path(name).is_dir() for name in args.files):
        refuse_shared_names(args.files, labels)
        records = [{"id": label} for label in labels]
    else:
        records = None  # ids from the file names, as many parent folders as tell them apart
    command = ["db", "build", *args.files, "--out", args.out, "--grid", str(args.grid)]
    command += ["--scales", str(args.scales), "--chunk", str(args.chunk)]
    command += ["--metadata", args.metadata] if args.metadata else []
    command += ["--bins", str(args.bins)] if args.bins is not None else []
    if spread(args, command):
        return Elsewhere()  # process 0 of the launched processes reports
    population = detail.build_database(
        files,
        args.out,
        records=records,
        grid=args.grid,
        n_scales=args.scales,
        bins=args.bins,
        chunk=args.chunk,
        progress=jax.process_index() == 0,
    )
    if population is None:  # process 0 writes the database and reports
        return Elsewhere()
    return {"out": args.out, "faces": len(population)}


#: The one spelling of ``--group`` (``db compare``, ``add-detail``, ``age``); NAME is optional.
GROUP_FORM = "[NAME:]FIELD=VALUE[,FIELD=LOW..HIGH]"


def parse_group(spec: str) -> tuple[str, dict]:
    """``(name, criteria)`` of a ``--group`` value ``[NAME:]FIELD=VALUE[,FIELD=LOW..HIGH]``.

    A group without a name is named by its criteria (``age=20..30``); a colon after the first
    ``=`` belongs to a value, not to a name."""
    head, colon, rest = spec.partition(":")
    name, rules = (head, rest) if colon and "=" not in head else (spec, spec)
    expected = f"--group must look like {GROUP_FORM}, e.g. 'old:age=50..60' or 'age=50..60'"
    if not name or not rules:
        raise ValueError(f"{expected}; got {spec!r}")
    criteria = {}
    for rule in rules.split(","):
        field, _, value = rule.partition("=")
        if not field or not value:
            raise ValueError(f"{expected}; got {spec!r} ({rule!r} is not FIELD=VALUE)")
        if ".." in value:
            try:
                low, high = (float(v) for v in value.split(".."))
            except ValueError:
                raise ValueError(
                    f"{expected}; got {spec!r} ({value!r} is not a range LOW..HIGH of two numbers)"
                ) from None
            criteria[field] = (low, high)
        else:
            try:  # numbers compare as numbers ("age=30"), anything else as text ("sex=f")
                criteria[field] = json.loads(value)
            except ValueError:
                criteria[field] = value
    return name, criteria


def _db_compare(args: argparse.Namespace) -> dict:
    out = io.check_output(args.out, (".png",))
    io.check_output(out.with_suffix(".json"), (".json",))
    population = detail.Population.load(args.db)
    groups = {}
    for spec in args.group:
        name, criteria = parse_group(spec)
        if name in groups:
            raise ValueError(f"two --group options name the group {name!r}; name them apart")
        groups[name] = population.select(**criteria)
    if len(groups) > len(render.GROUP_COLOURS):
        raise ValueError(f"at most {len(render.GROUP_COLOURS)} groups, got {len(groups)}")
    comparison = detail.compare_groups(groups)
    k = population.stats.n_orientations
    if not 0 <= args.show_scale < population.stats.n_scales:
        raise ValueError(f"--show-scale must be in [0, {population.stats.n_scales - 1}]")
    first = 1 + args.show_scale * k
    ratios = np.asarray(comparison.ratios[:, first : first + k])
    # One heat map per group and orientation, then the paper's Fig. 6 glyphs of all groups.
    colours = ("black", "red", "blue", "green")[: len(groups)]
    glyphs = ", ".join(f"{c}: {n}" for c, n in zip(colours, comparison.names, strict=True))
    figure = plots.panel_grid(
        [list(row) for row in ratios] + [[render.polar_glyphs(ratios)]],
        title=f"Per-tile std of each group over the reference group's, scale {args.show_scale}",
        col_labels=[f"{180 * b / k:.0f}°" for b in range(k)],
        row_labels=[*comparison.names, f"polar glyphs\n({glyphs})"],
        quantities=["statistics"] * len(groups) + ["relief"],
        units="std ratio to reference",
        limits=[(float(ratios.min()), float(ratios.max()))] * len(groups) + [(None, None)],
    )
    meta = io.provenance(db=Path(args.db).name, groups=args.group, scale=args.show_scale)
    io.write_figure(out, figure, metadata=meta)
    table = {
        name: {"faces": len(groups[name]), "mean_ratio": float(ratios[i].mean())}
        for i, name in enumerate(comparison.names)
    }
    table["reference"] = comparison.names[comparison.reference]
    io.write_json(out.with_suffix(".json"), table)
    return {"out": str(out), **table}


def _render(args: argparse.Namespace) -> dict:
    io.check_output(args.out, (".png",))
    meta = io.provenance(source=Path(args.map).name)
    io.write_png(args.out, render.shade(io.read_map(args.map)), metadata=meta)
    return {"out": args.out}


def demo(out: Path, seed: int) -> None:
    """Golovinskiy et al. Fig. 5 on a real texture: analyse, smooth, re-synthesise."""
    out = Path(out)
    source = importlib.resources.files("jface") / "data" / "gravel.exr"
    with importlib.resources.as_file(source) as path:
        original = io.read_map(path)
    stats = detail.analyze(original, grid=16)
    smooth = np.asarray(detail.remove_detail(original, n_bands=3))
    result = detail.synthesize(jax.random.key(seed), smooth, stats)
    errors = {
        name: float(np.median(np.asarray(detail.stats_error(detail.analyze_like(m, stats), stats))))
        for name, m in (("smoothed", smooth), ("synthesized", np.asarray(result)))
    }
    meta = io.provenance(seed=seed, source="gravel.exr", experiment="Golovinskiy 2006 Fig. 5")
    detail.save_stats(out / "detail" / "gravel.stats.npz", stats, source="gravel.exr")
    shaded = []
    for name, image in (("original", original), ("smoothed", smooth), ("synthesized", result)):
        io.write_exr(out / "detail" / f"{name}.exr", np.asarray(image), metadata=meta)
        shaded.append(render.shade(image))
    figure = plots.panel_grid(
        [shaded],
        title="Re-synthesis of gravel detail (Golovinskiy 2006 Fig. 5)",
        col_labels=[
            "original",
            f"smoothed ({errors['smoothed']:.0%} std error)",
            f"synthesized ({errors['synthesized']:.0%} std error)",
        ],
    )
    io.write_figure(
        out / "detail" / "fig5_original_smoothed_synthesized.png", figure, metadata=meta
    )
    figure = plots.band_statistics(stats.std, 4, title="Per-tile std of each band: gravel")
    io.write_figure(out / "detail" / "statistics.png", figure, metadata=meta)
    print(
        "detail: median per-tile std error to the original's statistics — "
        f"smoothed {errors['smoothed']:.1%}, re-synthesised {errors['synthesized']:.1%}"
    )
