"""``jface wrinkles``: pore sampling, pore graph and trail simulation (§3.1 of Weiss et al.
2023), drawing displacement maps (§3.2, §5) and extraction from coarse scans (§4.1)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from jface import plots
from jface._progress import Estimate
from jface.cli import _fit, deprecated_alias
from jface.io import (
    check_output,
    exr_rows,
    load_arrays,
    provenance,
    read_json,
    read_map,
    read_mesh,
    save_arrays,
    write_exr,
    write_figure,
    write_json,
    write_mesh,
    write_png,
)
from jface.render import shade
from jface.wrinkles import (
    ParamUnits,
    PoreGraph,
    Pores,
    Simulated,
    WrinkleParams,
    blend_with_scan,
    draw_simulated,
    extract_orientation,
    find_pores,
    load_params,
    make_pores,
    radius_map_from_mesh,
    save_params,
    simulate_levels,
    synthesize_bands,
)

#: α_s and α_scale of the levels made without --params, coarse to fine
LEVEL_S, LEVEL_SCALE = (0.05, 0.15, 0.3, 0.5), (0.6, 0.35, 0.2, 0.12)
_OVERRIDES = ("d", "theta", "s", "dist", "cont", "sim", "cross", "deposit", "decay")
_UNITS = {"d": ", unit-square units", "theta": ", radians"}
_FIELDS = {
    name: [f.name for f in dataclasses.fields(kind) if f.name != "periodic"]
    for name, kind in (("pores", Pores), ("graph", PoreGraph))
}
BANDED_ABOVE = 4096  #: maps with more rows are drawn and written band by band (bounded memory)
_PREVIEW = 2048  # side of the PNG / mesh preview of a banded map
_RADIUS_SIDE = 1024  # radius maps from a mesh's UV stretch are smooth: this resolution suffices


def register(subparsers) -> None:
    parser = subparsers.add_parser("wrinkles", help="micro-wrinkle simulation (Weiss et al. 2023)")
    sub = parser.add_subparsers(dest="wrinkles_command", required=True, metavar="COMMAND")
    sim = sub.add_parser(
        "simulate",
        help="sample pores, build the pore graph and run the trail simulation; "
        "write pores, graph and weights (npz) and a picture (PNG)",
    )
    sim.add_argument("--out", required=True, help="output folder")
    sim.add_argument("--params", help="JSON file of WrinkleParams levels (coarse to fine)")
    _params_frame_option(sim)
    for name in _OVERRIDES:
        sim.add_argument(
            f"--{name}",
            type=float,
            help=f"override α_{name} on every level (Table 1 range{_UNITS.get(name, '')}) "
            "(default: the levels' own)",
        )
    sim.add_argument("--levels", type=int, default=1, help="levels when no --params (α_d halves)")
    sim.add_argument("--radius-map", help="EXR radius scaling map R (single channel, > 0)")
    sim.add_argument("--periodic", action="store_true", help="wrap the unit square (tileable)")
    sim.add_argument("--steps", type=int,
                     help="simulation steps per level (default: until converged)")  # fmt: skip
    sim.add_argument("--samples", type=int, help="pores sampled per step (default min(50000, |E|))")
    sim.add_argument("--k", type=int, default=6, help="nearest neighbours per pore")
    sim.add_argument("--size", type=int, default=1024, help="PNG side, pixels")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    sim.set_defaults(run=_simulate, prose="wrinkles: {counts} in {seconds:.1f} s → {out}/")

    ren = sub.add_parser(
        "render",
        help="simulate and draw a multi-level micro-wrinkle displacement map (EXR + shaded PNG), "
        "optionally blended with a scan's displacement and applied to a mesh",
    )
    ren.add_argument(
        "--params",
        help="JSON file of WrinkleParams levels (required without --simulation); lengths are "
        "converted from the file's frame (its 'units') to the map's unit square",
    )
    _params_frame_option(ren)
    ren.add_argument(
        "--simulation",
        metavar="DIR",
        help="folder written by 'jface wrinkles simulate': draw its levels, pores and weights "
        "(with its seed) instead of simulating again",
    )
    ren.add_argument("--out", required=True, help="output EXR (PNG and mesh beside it)")
    ren.add_argument("--size", type=int, default=1024, help="map side in pixels (16 to 16384; "
                     f"above {BANDED_ABOVE} drawn and written band by band)")  # fmt: skip
    ren.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    ren.add_argument("--base", help="scan displacement EXR (one channel) to blend with (§5)")
    ren.add_argument("--pores", help="pores JSON from 'jface wrinkles extract' seeding level 0")
    ren.add_argument(
        "--mesh",
        help="UV-mapped mesh (OBJ/PLY): pores evenly spaced on its surface "
        "(radius map from the UV stretch) and the mesh displaced with the result",
    )
    ren.add_argument("--depth", type=float, default=0.001,
                     help="mesh displacement per map unit, as a fraction of the mesh's "
                     "bounding-box diagonal (default 0.001)")  # fmt: skip
    ren.add_argument("--periodic", action="store_true", help="tileable map (torus)")
    ren.add_argument("--steps", type=int,
                     help="simulation steps per level (default: until converged)")  # fmt: skip
    ren.add_argument("--samples", type=int, help="pores sampled per step (default min(50000, |E|))")
    ren.set_defaults(
        run=_render,
        prose="wrinkles render: {pores} pores per level; {size}² in {seconds:.1f} s → {out}",
    )

    ext = sub.add_parser(
        "extract",
        help="primary orientation per crop (α_θ texture) and pores from a coarse displacement map",
    )
    ext.add_argument("coarse", help="coarse displacement map (single-channel EXR, .npy, PNG)")
    ext.add_argument("--out", required=True, help="output WrinkleParams JSON (θ texture)")
    deprecated_alias(ext, "--pores-out", "--out (the pores JSON is written beside it)",
                     dest="pores_out", default=None)  # fmt: skip
    ext.add_argument("--crop", type=int, default=128, help="crop side in pixels (default 128)")
    ext.add_argument(
        "--frequency", type=float, default=0.2, help="Gabor frequency, cycles per pixel"
    )
    ext.add_argument(
        "--threshold", type=float, default=1.0, help="pore depth threshold (high-pass std units)"
    )
    ext.add_argument(
        "--d", type=float, default=0.01, help="α_d of the written level, unit-square units"
    )
    ext.set_defaults(
        run=_extract,
        prose="wrinkles extract: {rows}×{columns} orientations, {pores} pores in {seconds:.1f} s "
        "→ {out}, {pores_out}",
    )
    _fit.register(sub)


def _params_frame_option(parser) -> None:
    parser.add_argument(
        "--params-frame",
        metavar="FRAME",
        help="frame of a --params file that states none (older jface; a fit without "
        "--patch-size): 'uv' = the whole map's unit square, 'patch:SIZE' = a patch whose side "
        "is SIZE of the map's, e.g. patch:256/4096 (default: the file's own 'units')",
    )


def _load_levels(args) -> list[WrinkleParams]:
    """The --params levels in the map's unit square."""
    frame = None
    if args.params_frame is not None:
        try:
            frame = ParamUnits.parse(args.params_frame)
        except ValueError as err:
            raise ValueError(f"--params-frame: {err}") from None
    return load_params(args.params, frame=frame)


def _levels(args) -> list[WrinkleParams]:
    if args.params:
        levels = _load_levels(args)
    else:
        if args.params_frame is not None:
            raise ValueError("--params-frame states the frame of a --params file; give --params")
        if not 1 <= args.levels <= 4:
            raise ValueError(f"--levels must be in [1, 4], got {args.levels}")
        base = 0.02 if args.d is None else args.d
        # the coarse level directional and deep, finer ones more even and shallower (α_s,
        # α_scale), with a crossing penalty: strong lines with weak edges between, not a mesh
        levels = [
            WrinkleParams(d=max(base / 2**i, 0.001), s=LEVEL_S[i], cross=0.5, scale=LEVEL_SCALE[i])
            for i in range(args.levels)
        ]
    changes = {n: getattr(args, n) for n in _OVERRIDES if getattr(args, n) is not None}
    if args.params is None:
        changes.pop("d", None)
    return [p.replace(**changes) for p in levels]


def run_levels(key, levels, *, radius_map=None, periodic=False, steps=None, samples=None, k=6):
    """Simulate the levels coarse to fine; returns per level (pores, graph, weights)."""
    sims = simulate_levels(key, levels, radius_map=radius_map, periodic=periodic, n_steps=steps,
                           n_samples=samples, k=k, progress=True)  # fmt: skip
    return [(sim.pores, sim.graph, sim.weights) for sim in sims]


def draw_graph(results, size: int, periodic: bool) -> np.ndarray:
    """A diagnostic picture: every edge a dark line of darkness W (coarse levels darker)."""
    ink = np.zeros((size, size), np.float32)
    for level, (_, graph, weights) in enumerate(results):
        e = int(graph.edge_count)
        start = np.asarray(graph.positions)[np.asarray(graph.edge_nodes)[:e, 0]]
        delta = np.asarray(graph.edge_delta)[:e]
        w = np.asarray(weights)[:e] / (1.0 + 0.5 * level)
        steps = max(2, int(np.ceil(2 * size * float(np.max(np.abs(delta), initial=0)))) + 1)
        t = np.linspace(0.0, 1.0, steps, dtype=np.float32)
        pts = start[:, None, :] + t[None, :, None] * delta[:, None, :]
        pix = np.floor(pts * size).astype(np.int64)
        ink_w = np.broadcast_to(w[:, None], pix.shape[:2])
        if periodic:
            pix = np.mod(pix, size)
        else:  # the simulation's margin lies outside the map
            inside = np.all((pix >= 0) & (pix < size), axis=-1)
            pix, ink_w = pix[inside], ink_w[inside]
        np.maximum.at(ink, (pix[..., 1].ravel(), pix[..., 0].ravel()), ink_w.ravel())
    return 1.0 - np.clip(ink, 0.0, 1.0)


def _simulate(args: argparse.Namespace) -> dict:
    out = Path(args.out)
    if (args.steps is not None and args.steps < 0) or args.size < 16:
        raise ValueError("--steps must be ≥ 0 and --size ≥ 16")
    for name in ("wrinkles.npz", "params.json", "wrinkles.png"):
        check_output(out / name)
    levels = _levels(args)
    radius_map = read_map(args.radius_map) if args.radius_map else None
    start = time.perf_counter()
    results = run_levels(
        jax.random.key(args.seed), levels, radius_map=radius_map, periodic=args.periodic,
        steps=args.steps, samples=args.samples, k=args.k,
    )  # fmt: skip
    arrays = {}
    for i, (pores, graph, weights) in enumerate(results):
        n, e = int(pores.count), int(graph.edge_count)
        arrays[f"level{i}_positions"] = np.asarray(pores.positions)[:n]
        arrays[f"level{i}_pore_level"] = np.asarray(pores.level)[:n]
        arrays[f"level{i}_radius"] = np.asarray(pores.radius)[:n]
        arrays[f"level{i}_edge_nodes"] = np.asarray(graph.edge_nodes)[:e]
        arrays[f"level{i}_edge_delta"] = np.asarray(graph.edge_delta)[:e]
        arrays[f"level{i}_weights"] = np.asarray(weights)[:e]
        # the whole graph, padding included, so that 'render --simulation' can draw it
        arrays[f"level{i}_weights_all"] = np.asarray(weights)
        for prefix, item in (("pores", pores), ("graph", graph)):
            for field in _FIELDS[prefix]:
                arrays[f"level{i}_{prefix}_{field}"] = np.asarray(getattr(item, field))
    meta = provenance(
        seed=args.seed,
        levels=[p.to_dict() for p in levels],
        periodic=args.periodic,
        steps=args.steps,
        samples=args.samples,
        k=args.k,
    )
    save_arrays(out / "wrinkles.npz", arrays, meta, kind="WrinkleGraph")
    save_params(out / "params.json", levels, "uv")
    counts = ", ".join(f"{int(r[0].count)} pores/{int(r[1].edge_count)} edges" for r in results)
    figure = plots.panel_grid(
        [[draw_graph(results, args.size, args.periodic)]],
        title="Pore graph after trail formation (Weiss et al. 2023 §3.1): darker = heavier edge",
        col_labels=[counts],
        quantities="image",
        panel_inches=6.0,
    )
    write_figure(out / "wrinkles.png", figure, metadata=meta)
    return {"out": str(out), "counts": counts, "seconds": time.perf_counter() - start}


def _render(args: argparse.Namespace) -> dict:
    if not 16 <= args.size <= 16384:
        raise ValueError(f"--size must be in [16, 16384], got {args.size}")
    if (args.steps is not None and args.steps < 0) or not args.depth > 0:
        raise ValueError("--steps must be ≥ 0 and --depth > 0")
    out = check_output(args.out, (".exr",))
    check_output(out.with_suffix(".png"), (".png",))
    if args.mesh:
        check_output(out.with_suffix(".obj"), (".obj",))
    if (args.params is None) == (args.simulation is None):
        raise ValueError("give --params (simulate here) or --simulation (reuse a simulation)")
    if args.simulation:
        names = ("pores", "mesh", "steps", "samples", "params_frame")
        clash = [f"--{n.replace('_', '-')}" for n in names if getattr(args, n)]
        if clash or args.size > BANDED_ABOVE:
            raise ValueError(
                f"--simulation draws a finished simulation: {clash or '--size above 4096'} "
                "does not go with it"
            )
        levels, simulated, sim_meta = _read_simulation(args.simulation)
        args.seed, args.periodic = int(sim_meta["seed"]), bool(sim_meta["periodic"])
    else:
        levels = _load_levels(args)
    base = read_map(args.base) if args.base else None
    if base is not None and base.shape != (args.size, args.size):
        raise ValueError(f"--base is {base.shape}, expected ({args.size}, {args.size}) (--size)")
    mesh = read_mesh(args.mesh, uv_seams=True) if args.mesh else None
    radius_map = None
    if mesh is not None:
        if mesh.uv is None:
            raise ValueError(f"{args.mesh} has no UV coordinates; --mesh needs a UV-mapped mesh")
        if args.periodic:
            raise ValueError("--periodic does not go with --mesh (a UV atlas does not tile)")
        radius_map = radius_map_from_mesh(mesh, min(args.size, _RADIUS_SIDE))
    initial = _read_pores(args.pores, args.periodic) if args.pores else None
    start = time.perf_counter()
    meta = provenance(
        seed=args.seed, levels=[p.to_dict() for p in levels], size=args.size, base=args.base,
        mesh=args.mesh, periodic=args.periodic, steps=args.steps, samples=args.samples,
    )  # fmt: skip
    run = dict(initial=initial, radius_map=radius_map, periodic=args.periodic,
               n_steps=args.steps, n_samples=args.samples, progress=True)  # fmt: skip
    key = jax.random.key(args.seed)
    shape = (args.size, args.size)
    if args.simulation:
        meta["simulation"] = str(args.simulation)
    if args.size > BANDED_ABOVE:
        counts, preview = _render_bands(key, levels, shape, base, out, meta, run)
    else:
        if not args.simulation:  # the simulation shows its own progress
            simulated = simulate_levels(key, levels, **run)
        print(f"drawing {len(levels)} level(s) at {args.size}²…", file=sys.stderr)
        syn = draw_simulated(key, levels, simulated, shape)
        disp = syn.displacement if base is None else blend_with_scan(base, syn.displacement)
        preview = np.asarray(disp)
        write_exr(out, preview, metadata=meta)
        counts = [int(lv.pores.count) for lv in syn.levels]
    write_png(out.with_suffix(".png"), shade(preview), metadata=meta)
    if mesh is not None:
        from jface.mesh import displace

        diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
        # maps are drawn with v down the rows; mesh UVs have v up
        moved = displace(mesh, preview[::-1], scale=args.depth * diag)
        comment = f"jface {meta['jface_version']} wrinkles render, seed {args.seed}"
        write_mesh(out.with_suffix(".obj"), np.asarray(moved.vertices), np.asarray(moved.faces),
                   uv=np.asarray(moved.uv), comment=comment)  # fmt: skip
    return {
        "out": str(out),
        "pores": counts,
        "size": args.size,
        "seconds": time.perf_counter() - start,
    }


def _read_simulation(folder: str):
    """Levels, simulated graphs and weights, and the provenance of a ``wrinkles simulate``
    folder."""
    arrays, meta = load_arrays(Path(folder) / "wrinkles.npz", kind="WrinkleGraph")
    # 'simulate' simulates the unit square: its params.json is in that frame, stated or not
    levels = load_params(Path(folder) / "params.json", frame="uv")
    simulated = []
    periodic = bool(meta["periodic"])
    for i in range(len(levels)):
        parts = {}
        for prefix, kind in (("pores", Pores), ("graph", PoreGraph)):
            fields = {f: arrays.get(f"level{i}_{prefix}_{f}") for f in _FIELDS[prefix]}
            if any(v is None for v in fields.values()):
                raise ValueError(
                    f"{folder}/wrinkles.npz holds no drawable level {i} (written by an older "
                    "jface?): simulate again"
                )
            parts[prefix] = kind(**{f: jnp.asarray(v) for f, v in fields.items()},
                                 periodic=periodic)  # fmt: skip
        weights = jnp.asarray(arrays[f"level{i}_weights_all"])
        simulated.append(Simulated(parts["pores"], parts["graph"], weights))
    return levels, simulated, meta


def _render_bands(key, levels, shape, base, out, meta, run):
    """Draw and write the map band by band; returns the pore counts and a ≤ 2048² preview (for
    the PNG and the mesh), so the whole map is never in memory."""
    step = -(-shape[0] // _PREVIEW)
    bands = synthesize_bands(key, levels, shape, **run)
    preview = []
    with (
        exr_rows(out, shape, metadata=meta) as write,
        tqdm(total=shape[0], desc="draw + write", unit="row", leave=False) as bar,
    ):
        estimate = Estimate(shape[0], "row")
        for first, rows in bands.rows:
            if base is not None:
                rows = blend_with_scan(base, rows, first_row=first)
            rows = np.asarray(rows)
            write(rows)
            preview.append(rows[(-first) % step :: step, ::step])
            bar.update(rows.shape[0])
            estimate.update(rows.shape[0])
    return [int(sim.pores.count) for sim in bands.levels], np.concatenate(preview)


def _read_pores(path, periodic):
    data = read_json(path)
    if not isinstance(data, dict) or data.get("kind") != "Pores" or "positions" not in data:
        raise ValueError(
            f"{path} is not a pores file (kind 'Pores' with 'positions') from "
            "'jface wrinkles extract'"
        )
    try:
        positions = np.asarray(data["positions"], np.float64)
    except (TypeError, ValueError, OverflowError):
        positions = np.zeros((1, 0))  # not numbers: refused below
    if positions.size == 0 and positions.ndim == 1:
        return None  # no pores: the first level samples its own
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise ValueError(f"{path}: 'positions' must be a list of [x, y] pairs of numbers")
    inside = np.isfinite(positions) & (positions >= 0) & (positions <= 1)
    if not np.all(inside):
        bad = int(np.flatnonzero(~inside.all(axis=1))[0])
        raise ValueError(
            f"{path}: pore {bad} at {positions[bad].tolist()} lies outside the unit square "
            "[0, 1]² (or is not finite)"
        )
    return make_pores(positions.astype(np.float32), periodic=periodic)


def _extract(args: argparse.Namespace) -> dict:
    out = check_output(args.out, (".json",))
    pores_out = Path(args.pores_out) if args.pores_out else out.with_name(out.stem + "_pores.json")
    check_output(pores_out, (".json",))
    if pores_out.resolve() == out.resolve():
        raise ValueError(f"--out and --pores-out name one file, {out}; give two names")
    coarse = read_map(args.coarse)
    start = time.perf_counter()
    orient = extract_orientation(coarse, crop=args.crop, frequency=args.frequency)
    pores = find_pores(coarse, threshold=args.threshold)
    save_params(out, WrinkleParams(d=args.d, theta=np.asarray(orient.theta)), "uv")
    n = int(pores.count)
    write_json(
        pores_out,
        {"kind": "Pores", "positions": np.asarray(pores.positions)[:n].tolist(),
         **provenance(source=str(args.coarse), crop=args.crop, frequency=args.frequency,
                      threshold=args.threshold)},
    )  # fmt: skip
    if n == 0:
        print(
            f"jface wrinkles extract: warning: no pores found on {args.coarse} (none deeper than "
            f"--threshold {args.threshold} high-pass std); try a lower --threshold",
            file=sys.stderr,
        )
    gy, gx = orient.theta.shape
    return {
        "out": str(out),
        "pores_out": str(pores_out),
        "rows": int(gy),
        "columns": int(gx),
        "pores": n,
        "seconds": time.perf_counter() - start,
    }


def demo(out_dir: Path, seed: int) -> None:
    """Pores and wrinkles on a tileable patch, simulated to convergence, and its map drawn."""
    from jface.cli import main

    main(
        ["wrinkles", "simulate", "--out", str(Path(out_dir) / "wrinkles"), "--levels", "3",
         "--d", "0.03", "--theta", "0.6", "--s", "0.2", "--cross", "0.5", "--deposit", "0.4",
         "--periodic", "--size", "768", "--seed", str(seed)]
    )  # fmt: skip
    # and a drawn displacement map (§3.2) of that simulation (its weights, not simulated again)
    main(
        ["wrinkles", "render", "--simulation", str(Path(out_dir) / "wrinkles"), "--out",
         str(Path(out_dir) / "wrinkles" / "displacement.exr"), "--size", "512", "--periodic",
         "--seed", str(seed)]
    )  # fmt: skip
