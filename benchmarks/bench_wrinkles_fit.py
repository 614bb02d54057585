"""Wrinkle fit on 256² patches, fast mode against the paper's procedure (goal: fast mode within
10 min on the CPU with a final loss ≤ 1.05× the paper mode's; the paper: ~35 min per run on an
RTX A6000). No reference tool exists.

Targets: ``known-<seed>``, two-level maps drawn from known parameters (other pores, another
simulation key than the fit's); ``brick`` and ``gravel``, crops of the skimage textures;
``synthesized``, a map from ``detail.synthesize`` with the gravel crop's statistics. Each line
gives a mode's wall time, its swarm and refined loss, its held-out loss (the answer with other
simulation keys, ``WrinkleFit.heldout_loss``), the epochs each trial ran and, for the synthetic
targets, the recovered α_deposit and α_θ of level 1 against the truth and the truth's own
held-out loss (the same keys, the mode's pores: what a fit that found the truth would score)
with the fit's ratio to it; the paper mode's line adds the fast/paper ratios of time, loss and
held-out loss when both ran on the target.

``--save DIR`` keeps each target (``<target>.npy``) and each fit (``<target>-<mode>-<seed>.npz``,
:func:`jface.io.save_arrays` of kind ``"WrinkleFitRun"``: the fitted map, the swarm's history,
and the report's numbers, fitted levels and provenance (versions, device) as metadata) for
``examples/wrinkles_fit_modes.py``, which draws them side by side. A rerun with the same
``--save`` keeps every fit whose file was made by the same jface source with the same settings
(reported with ``"kept": true``), so the full benchmark (3 seeds × 5 targets × 2 modes, about
15 hours on two CPU cores) can run in parts and survive an interruption. Last, a summary line
per target gives the medians over the seeds of each mode's time, loss and held-out loss (from
this run's fits and the kept ones) and the fast/paper ratios of the medians against the goals
(≤ 600 s, ≤ 1.05×).

``--stages`` first prints the cost of one swarm evaluation split into simulation, drawing and
texture loss, per size class of the α_d grid, and the layout time (its pores and graphs).

Run: ``python benchmarks/bench_wrinkles_fit.py [--targets known-1 brick] [--modes fast paper]
[--agents 50] [--epochs 100] [--trials 3] [--save DIR]``.
"""

from __future__ import annotations

import os

from jface._distributed import cpu_device_flags, deterministic_cpu_flags

# as the command line fits: XLA's CPU threads deterministic and a device per core (JAX reads the
# flags when its backend starts, at the first computation)
os.environ["XLA_FLAGS"] = cpu_device_flags(deterministic_cpu_flags(os.environ.get("XLA_FLAGS", "")))

import argparse
import dataclasses
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import best_of, report
from skimage import data

from jface import detail
from jface._compilation import keep_compiled_programs
from jface.io import content_key, load_arrays, provenance, save_arrays
from jface.optim import texture_stats
from jface.wrinkles import (
    REFINE_STEPS,
    WrinkleParams,
    fit_wrinkles,
    heldout_key_count,
    params_to_json,
)
from jface.wrinkles._fit import (
    D_LEVELS,
    D_RANGE,
    PAPER_NAMES,
    _bounds,
    _draw,
    _draw_checked,
    _kept_layout,
    _layout,
    _levels_from,
    _loss,
    _noise_table,
    _polishes,
    _rung,
    _simulate,
    _SwarmLoss,
    heldout_keys,
    layout_key,
)

TARGETS = ["known-1", "known-2", "known-3", "brick", "gravel", "synthesized"]


def stages(target, layout, agents: int) -> None:
    """ms per agent of each stage of a swarm evaluation, per size class of the α_d grid (agents
    with α_d in that class, on its graph slots, one after the other as in the fit; compiled
    first)."""
    d_values = np.asarray(layout.d_values)
    for c, grid in enumerate((d_values[: layout.split], d_values[layout.split :])):
        class_stages(target, layout.narrowed(c), grid, agents)


def class_stages(target, narrow, grid, agents: int) -> None:
    base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
    low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
    u = np.random.default_rng(0).uniform(size=(agents, len(PAPER_NAMES)))
    x = low + u * (high - low)
    x[:, PAPER_NAMES.index("d")] = np.random.default_rng(1).choice(grid, agents)
    x = jnp.asarray(x, jnp.float32)
    key, stats = jax.random.key(5), texture_stats(target)

    def one_sim(a):
        return _simulate(key, _levels_from(a, PAPER_NAMES, base), narrow)

    sim = jax.jit(lambda x: jax.lax.map(one_sim, x))
    draw = jax.jit(lambda s, lv: jax.lax.map(lambda a: _draw_checked(key, *a, narrow), (s, lv)))
    loss = jax.jit(jax.vmap(lambda image: _loss(image, stats)))
    sims, levels = jax.block_until_ready(sim(x))
    images, bad = jax.block_until_ready(draw(sims, levels))
    jax.block_until_ready(loss(images))
    for name, fn in (
        ("simulation (2 levels)", lambda: sim(x)),
        ("drawing (2 levels)", lambda: draw(sims, levels)),
        ("texture loss", lambda: loss(images)),
    ):
        report(
            f"one swarm evaluation, {agents} agents of α_d {grid[0]:.3f}-{grid[-1]:.3f}, "
            f"{target.shape[0]}², stage: {name}",
            best_of(fn, repeats=2) / agents,
            note="ms per agent",
        )
    print(f'{{"undrawable_agents": {int(np.sum(np.asarray(bad)))}, "of": {agents}}}', flush=True)


def evaluation_cost(target, layout, agents: int) -> None:
    """ms per agent of one whole swarm evaluation as a large fit runs it, with its table of
    the perturbation's noise (compiled first); and as a small fit runs it, without."""
    base = (WrinkleParams(d=0.035), WrinkleParams(d=0.0175, snoise=0.001))
    low, high, _ = _bounds(PAPER_NAMES, D_RANGE, {})
    u = np.random.default_rng(1).uniform(size=(agents, len(PAPER_NAMES)))
    x = jnp.asarray(low + u * (high - low), jnp.float32)
    key = jax.random.key(5)
    plain = _SwarmLoss(key, texture_stats(target), base, layout, PAPER_NAMES)
    tabled = dataclasses.replace(plain, table=_noise_table(key, layout, base))
    for name, loss in (("a large fit (noise table)", tabled), ("a small fit", plain)):
        loss = eqx.filter_jit(loss)
        jax.block_until_ready(loss(x))
        seconds = best_of(lambda loss=loss: loss(x), repeats=2) / agents
        report(f"one swarm evaluation as {name} runs it, {agents} agents", seconds,
               note="ms per agent")  # fmt: skip


TRUTH = (
    WrinkleParams(d=0.03, theta=0.8, s=0.3, deposit=0.5),
    WrinkleParams(d=0.015, theta=0.8, s=0.3, deposit=0.5, snoise=0.001),
)


def polish_count(fit, mode: str, args) -> int:
    """Polishes the fit ran: one after each of a trial's rungs (the last trial's: its chunks of a
    rung's epochs), when the fit polishes."""
    steps = REFINE_STEPS[mode] if args.refine_steps is None else args.refine_steps
    if not _polishes(mode, steps, args.agents, args.epochs):
        return 0
    return sum(-(-epochs // _rung(args.epochs)) for epochs in fit.epochs_run)


def make_target(name: str, size: int, steps: int) -> np.ndarray:
    if name.startswith("known-"):
        key = jax.random.key(1000 + int(name.split("-")[1]))
        layout = _layout(key, (size, size), D_RANGE, steps, 4)
        sims, levels = _simulate(key, TRUTH, layout)
        return np.asarray(_draw(key, sims, levels, layout))
    gravel = data.gravel().astype(np.float32) / 255.0
    if name == "synthesized":
        crop = gravel[:size, :size]
        smooth = np.asarray(detail.remove_detail(crop, n_bands=3))
        stats = detail.analyze(crop, grid=4)  # whole tiles at every scale of a small crop
        return np.asarray(detail.synthesize(jax.random.key(3), smooth, stats))
    texture = {"brick": data.brick().astype(np.float32) / 255.0, "gravel": gravel}[name]
    return texture[:size, :size]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", nargs="+", default=TARGETS, choices=TARGETS)
    parser.add_argument("--modes", nargs="+", default=["fast", "paper"], choices=["fast", "paper"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="fit seeds")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--agents", type=int, default=50)
    parser.add_argument("--epochs", type=int, default=100)
    parser.add_argument("--trials", type=int, default=3)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--d-levels", type=int, help="default: the mode's (16 fast, 32 paper)")
    parser.add_argument("--refine-steps", type=int, help="default: the mode's (30 in both)")
    parser.add_argument("--stages", action="store_true", help="the cost split of one evaluation")
    parser.add_argument("--save", type=Path, help="folder for the targets and the fits")
    args = parser.parse_args()
    keep_compiled_programs()  # as the command line does (JFACE_CACHE_DIR=off: compile afresh)
    if args.save:
        args.save.mkdir(parents=True, exist_ok=True)
    for name in args.targets:
        target = make_target(name, args.size, args.steps)
        if args.save:
            np.save(args.save / f"{name}.npy", target)
        if args.stages:
            start = time.perf_counter()
            levels = args.d_levels or 32
            layout = _layout(jax.random.key(0), target.shape, D_RANGE, args.steps, levels)
            report(f"layout: pores and graphs of {levels} α_d values",
                   time.perf_counter() - start)  # fmt: skip
            stages(target, layout, 8)
            evaluation_cost(target, layout, args.agents)
        runs = {}  # (mode, seed) → the run's numbers
        for seed in args.seeds:
            for mode in args.modes:
                run = runs[mode, seed] = fit_run(name, target, mode, seed, args)
                if name.startswith("known-"):
                    truth = truth_heldout(target, mode, seed, args)
                    run |= {"truth_heldout_loss": finite(truth),
                            "heldout_over_truth": ratio(run["heldout_loss"], truth)}  # fmt: skip
                extra = {}
                if mode == "paper" and ("fast", seed) in runs:
                    fast = runs["fast", seed]
                    extra = {f"{what}_fast_over_paper": ratio(fast[field], run[field])
                             for what, field in (("time", "seconds"), ("loss", "loss"),
                                                 ("heldout", "heldout_loss"))}  # fmt: skip
                report(
                    f"wrinkle fit, {mode} mode, target {name} {target.shape[0]}², seed {seed}, "
                    f"{args.agents} agents, {args.epochs} epochs, {args.trials} trials",
                    run["seconds"], goal_s=600, **{k: v for k, v in run.items() if k != "seconds"},
                    **extra,
                )  # fmt: skip
        summary(name, target.shape[0], runs, args.modes)


def fit_run(name: str, target: np.ndarray, mode: str, seed: int, args) -> dict:
    """The numbers of one fit: kept from ``--save`` when the same source and settings made them,
    else fitted now (and kept there, atomically)."""
    settings = {
        "target": name, "size": args.size, "mode": mode, "seed": seed, "agents": args.agents,
        "epochs": args.epochs, "trials": args.trials, "steps": args.steps,
        "d_levels": args.d_levels, "refine_steps": args.refine_steps,
    }  # fmt: skip
    key = content_key([], settings)
    path = args.save / f"{name}-{mode}-{seed}.npz" if args.save else None
    if path is not None and path.exists():
        try:
            _, kept = load_arrays(path, kind="WrinkleFitRun")
        except ValueError as err:  # damaged or of an older format: fitted again
            print(f"{path}: not kept ({err})", flush=True)
        else:
            if kept.pop("key", None) == key:  # the run's numbers, without what describes it
                dropped = {"levels", "seed", *provenance()}
                return {f: v for f, v in kept.items() if f not in dropped} | {"kept": True}
    start = time.perf_counter()
    fit = fit_wrinkles(
        jax.random.key(seed), target, n_agents=args.agents, n_epochs=args.epochs,
        n_trials=args.trials, n_steps=args.steps, d_levels=args.d_levels,
        refine_steps=args.refine_steps, mode=mode,
    )  # fmt: skip
    jax.block_until_ready(fit.loss)
    run = {
        "seconds": time.perf_counter() - start,
        "swarm_loss": float(fit.swarm_loss),
        "loss": float(fit.loss),
        "heldout_loss": finite(fit.heldout_loss),
        "heldout_losses": [finite(v) for v in fit.heldout_losses],  # per key, for their spread
        "epochs_run": list(fit.epochs_run),
        "evaluations": args.agents * sum(e + 1 for e in fit.epochs_run),
        "polishes": polish_count(fit, mode, args),
        "refined_from_each_start": [float(v) for v in fit.refined_losses],
        "nonfinite_evaluations": int(np.sum(np.asarray(fit.swarm.n_nonfinite))),
    }
    if name.startswith("known-"):
        run |= {f: round(float(getattr(fit.levels[0], f)), 3) for f in ("deposit", "theta")} | {
            "truth": {f: float(getattr(TRUTH[0], f)) for f in ("deposit", "theta")}
        }
    if path is not None:
        arrays = {"fitted": np.asarray(fit.fitted), "history": np.asarray(fit.swarm.history)}
        levels = params_to_json(fit.levels, "uv")
        meta = provenance(seed=seed, **run, key=key, levels=levels)  # the versions a rerun needs
        save_arrays(path, arrays, meta, kind="WrinkleFitRun")
    return run


def truth_heldout(target: np.ndarray, mode: str, seed: int, args) -> float:
    """The truth's mean loss with the keys that score the answer of a fit with ``seed`` (its
    held-out keys, with the mode's pores and graphs): the held-out loss of a fit that found the
    truth. The target was drawn with other pores, so the objective's least can lie elsewhere
    and a fit can score below it."""
    d_levels = args.d_levels or D_LEVELS[mode]
    whole = _kept_layout(layout_key(), target.shape, D_RANGE, args.steps, d_levels).merged()
    layout = whole.narrowed(0)  # every α_d value in one class, as the fit's refinement draws
    stats = texture_stats(jnp.asarray(target))
    count = heldout_key_count(args.agents, args.epochs, args.trials, mode=mode)
    keys = heldout_keys(jax.random.key(seed), count)
    return float(np.mean([float(truth_loss(k, stats, layout)) for k in keys]))


@eqx.filter_jit
def truth_loss(key, stats, layout):
    """The truth's loss drawn with ``key`` on ``layout`` (one program per layout's sizes)."""
    return _SwarmLoss(key, stats, TRUTH, layout, PAPER_NAMES)._map(layout, TRUTH)


def summary(name: str, size: int, runs: dict, modes) -> None:
    """One line: per mode the medians over the seeds of time, loss and held-out loss (and of the
    α_deposit and α_θ errors and of the held-out loss over the truth's for the known targets;
    α_θ is axial), and the fast/paper ratios of the medians against the goals."""
    medians, seeds = {}, {}
    for mode in modes:
        rows = [r for (m, _), r in runs.items() if m == mode]
        if not rows:
            continue
        med = {f: float(np.median([r[f] for r in rows if r[f] is not None] or [np.nan]))
               for f in ("seconds", "loss", "heldout_loss")}  # fmt: skip
        if "truth" in rows[0]:
            truth = rows[0]["truth"]
            axial = [
                abs((r["theta"] - truth["theta"] + np.pi / 2) % np.pi - np.pi / 2) for r in rows
            ]
            med |= {"deposit_error": float(np.median([abs(r["deposit"] - truth["deposit"])
                                                      for r in rows])),
                    "theta_error": float(np.median(axial)),
                    "heldout_over_truth": float(np.median(
                        [r["heldout_over_truth"] for r in rows
                         if r["heldout_over_truth"] is not None] or [np.nan]))}  # fmt: skip
        medians[mode], seeds[mode] = med, len(rows)
    extra = {}
    if {"fast", "paper"} <= medians.keys():
        fast, paper = medians["fast"], medians["paper"]
        # small budgets give the modes different numbers of held-out keys (heldout_key_count):
        # compared on the keys both have, the first of each fit's
        shared = min(len(r["heldout_losses"]) for r in runs.values())
        heldout = {m: np.median([np.nanmean(np.asarray(r["heldout_losses"][:shared], float))
                                 for (mode, _), r in runs.items() if mode == m])
                   for m in ("fast", "paper")}  # fmt: skip
        extra = {"loss_fast_over_paper": ratio(fast["loss"], paper["loss"]),
                 "heldout_fast_over_paper": ratio(heldout["fast"], heldout["paper"]),
                 "goal_loss_ratio": 1.05}  # fmt: skip
    shown = medians.get("fast") or next(iter(medians.values()))  # the time of the fast mode
    per_mode = {m: {k: finite(v) for k, v in med.items()} | {"seeds": seeds[m]}
                for m, med in medians.items()}  # fmt: skip
    report(f"wrinkle fit summary, target {name} {size}², medians over seeds", shown["seconds"],
           goal_s=600, **per_mode, **extra)  # fmt: skip


def finite(value: float) -> float | None:
    """A number for the report's JSON (None where it is not finite: JSON has no NaN)."""
    return round(float(value), 6) if np.isfinite(value) else None


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b`` for the report (None where either is missing or it is not finite)."""
    return None if a is None or b is None else finite(a / b)


if __name__ == "__main__":
    main()
