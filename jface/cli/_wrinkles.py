"""``jface wrinkles``: pore sampling, pore graph and trail simulation (Weiss et al. 2023, §3.1)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jface.io import provenance, read_map, save_arrays, write_json, write_png
from jface.wrinkles import WrinkleParams, build_graph, load_params, sample_pores, simulate

_OVERRIDES = ("d", "theta", "s", "dist", "cont", "sim", "cross", "deposit", "decay")


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
    for name in _OVERRIDES:
        sim.add_argument(
            f"--{name}", type=float, help=f"override α_{name} on every level (Table 1 range)"
        )
    sim.add_argument("--levels", type=int, default=1, help="levels when no --params (α_d halves)")
    sim.add_argument("--radius-map", help="EXR radius scaling map R (single channel, > 0)")
    sim.add_argument("--periodic", action="store_true", help="wrap the unit square (tileable)")
    sim.add_argument("--steps", type=int, default=50, help="simulation steps per level")
    sim.add_argument("--samples", type=int, help="pores sampled per step (default min(50000, E))")
    sim.add_argument("--k", type=int, default=6, help="nearest neighbours per pore")
    sim.add_argument("--size", type=int, default=1024, help="PNG size in pixels")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    sim.set_defaults(run=_simulate)


def _levels(args) -> list[WrinkleParams]:
    if args.params:
        levels = load_params(args.params)
    else:
        if not 1 <= args.levels <= 4:
            raise ValueError(f"--levels must be in [1, 4], got {args.levels}")
        base = 0.02 if args.d is None else args.d
        levels = [WrinkleParams(d=max(base / 2**i, 0.001)) for i in range(args.levels)]
    changes = {n: getattr(args, n) for n in _OVERRIDES if getattr(args, n) is not None}
    if args.params is None:
        changes.pop("d", None)
    return [p.replace(**changes) for p in levels]


def run_levels(key, levels, *, radius_map=None, periodic=False, steps=50, samples=None, k=6):
    """Simulate the levels coarse to fine; returns per level (pores, graph, weights)."""
    results = []
    pores = None
    for i, params in enumerate(tqdm(levels, desc="levels", unit="level", leave=False)):
        k_pores, k_sim = jax.random.split(jax.random.fold_in(key, i))
        pores = sample_pores(k_pores, params.d, radius_map, initial=pores, periodic=periodic)
        graph = build_graph(pores, k=k)
        weights = simulate(k_sim, graph, params, n_steps=steps, n_samples=samples)
        results.append((pores, graph, weights))
    return results


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
        pix = np.mod(pix, size) if periodic else np.clip(pix, 0, size - 1)
        np.maximum.at(ink, (pix[..., 1].ravel(), pix[..., 0].ravel()), np.repeat(w, steps))
    return 1.0 - np.clip(ink, 0.0, 1.0)


def _simulate(args: argparse.Namespace) -> None:
    out = Path(args.out)
    if args.steps < 0 or args.size < 16:
        raise ValueError("--steps must be ≥ 0 and --size ≥ 16")
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
    meta = provenance(
        seed=args.seed,
        levels=[p.to_dict() for p in levels],
        periodic=args.periodic,
        steps=args.steps,
        samples=args.samples,
        k=args.k,
    )
    protect = (args.params,) if args.params else ()
    save_arrays(out / "wrinkles.npz", arrays, meta, kind="WrinkleGraph", protect=protect)
    write_json(out / "params.json", {"kind": "WrinkleParams", "levels": meta["levels"]})
    picture = draw_graph(results, args.size, args.periodic)
    write_png(out / "wrinkles.png", picture, metadata=meta)
    counts = ", ".join(f"{int(r[0].count)} pores/{int(r[1].edge_count)} edges" for r in results)
    print(f"wrinkles: {counts} in {time.perf_counter() - start:.1f} s → {out}/")


def demo(out_dir: Path, seed: int) -> None:
    """Pores and wrinkles on a tileable patch (a few seconds, mostly compilation)."""
    from jface.cli import main

    main(
        ["wrinkles", "simulate", "--out", str(Path(out_dir) / "wrinkles"), "--levels", "1",
         "--d", "0.015", "--theta", "0.6", "--s", "0.2", "--cross", "0.5", "--deposit", "0.4",
         "--periodic", "--size", "768", "--seed", str(seed)]
    )  # fmt: skip
