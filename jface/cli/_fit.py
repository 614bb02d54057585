"""``jface wrinkles fit``: fit wrinkle parameters to a measured patch (Weiss et al. 2023, §4.2)."""

from __future__ import annotations

import argparse
import json
import sys

import jax
import numpy as np
from tqdm import tqdm

from jface import plots
from jface.cli import deprecated_alias
from jface.io import check_output, commit, provenance, read_map, write_figure, write_json
from jface.render import shade
from jface.wrinkles import (
    REFINE_STEPS,
    ParamUnits,
    fit_wrinkles,
    params_to_json,
    parse_patch_size,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fit",
        help="fit two-level wrinkle parameters to a displacement patch (particle swarm + "
        "gradient refinement); write the parameters (JSON), a convergence plot and a "
        "side-by-side shaded PNG",
    )
    parser.add_argument("patch", help="displacement patch: EXR (one channel), .npy or grey PNG")
    parser.add_argument("--out", required=True, help="output parameter file (.json)")
    parser.add_argument("--channel", help="EXR channel when the file has several")
    parser.add_argument(
        "--patch-size",
        metavar="SIZE",
        help="side of the (square) patch as a fraction of the face map's side, e.g. 256/4096 "
        "for 256 px cut from a 4096² map: recorded so that 'wrinkles render' converts the "
        "fitted lengths to the face (default: not recorded; render then needs --params-frame)",
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--agents", type=int, default=50, help="swarm agents (default: 50)")
    parser.add_argument(
        "--iters",
        dest="epochs",
        metavar="N",
        type=int,
        default=100,
        help="swarm epochs (default: 100)",
    )
    deprecated_alias(parser, "--epochs", "--iters")
    parser.add_argument(
        "--trials", type=int, default=3,
        help="independent trials; without --paper they race, the better half going on "
        "(default: 3)",
    )  # fmt: skip
    parser.add_argument(
        "--paper", action="store_true",
        help="the paper's procedure: every trial runs all --iters epochs, no early stop "
        "(default: off: trials by successive halving, stop when the best loss improves by less "
        "than 0.1 %% over 10 epochs)",
    )  # fmt: skip
    parser.add_argument("--steps", type=int, default=50, help="simulation steps (default: 50)")
    parser.add_argument(
        "--refine-steps", type=int,
        help="BFGS steps on the drawing parameters (0: none; default: 10, 30 with --paper)",
    )  # fmt: skip
    parser.add_argument(
        "--d-levels", type=int,
        help="α_d values whose pores and graphs are precomputed (default: 16, 32 with --paper)",
    )  # fmt: skip
    parser.add_argument(
        "--d-range", type=float, nargs=2, default=(0.02, 0.05), metavar=("LOW", "HIGH"),
        help="search range of the pore distance α_d (default: 0.02 0.05)",
    )  # fmt: skip
    parser.set_defaults(
        run=_fit,
        prose="loss {swarm_loss:.4g} (swarm) → {loss:.4g} (refined); {nonfinite} non-finite "
        "evaluations; wrote {out}, {convergence}, {comparison}",
    )


def _units(patch_size: str | None, shape: tuple[int, int]) -> ParamUnits:
    """The frame of the fitted lengths: the patch's unit square, of the given size on the face."""
    if patch_size is None:
        print(
            "wrinkles fit: the patch's size on the face is not recorded (--patch-size); "
            "'wrinkles render' will ask for it (--params-frame patch:SIZE)",
            file=sys.stderr,
        )
        return ParamUnits("patch", None, shape)
    if shape[0] != shape[1]:
        raise ValueError(
            f"--patch-size needs a square patch: the fit stretches its unit square over the "
            f"{shape[0]}×{shape[1]} patch, so its lengths have no single size on the face"
        )
    try:
        return ParamUnits("patch", parse_patch_size(patch_size), shape)
    except ValueError as err:
        raise ValueError(f"--patch-size: {err}") from None


def _fit(args: argparse.Namespace) -> dict:
    out = check_output(args.out, (".json",))
    stem = out.with_suffix("")
    for suffix in ("_convergence.png", "_target_fit.png"):
        check_output(f"{stem}{suffix}", (".png",))
    for name, option in (("agents", "agents"), ("epochs", "iters"), ("trials", "trials"),
                         ("steps", "steps"), ("d_levels", "d-levels")):  # fmt: skip
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise ValueError(f"--{option} must be at least 1, got {getattr(args, name)}")
    patch = read_map(args.patch, args.channel)
    units = _units(args.patch_size, patch.shape)
    mode = "paper" if args.paper else "fast"
    if args.refine_steps is None:
        args.refine_steps = REFINE_STEPS[mode]
    total = args.trials * args.epochs if args.paper else _halving_epochs(args.trials, args.epochs)
    # measured on 2 CPU cores: 0.15 s per agent and epoch at 256², plus about 2 min of fixed
    # cost (1 min when the compiled programs of an earlier run with this seed are cached)
    minutes = (total * args.agents * 0.15 * patch.size / 256**2 + 120) / 60
    print(
        f"wrinkles fit ({mode}): {args.agents} agents × {args.epochs} epochs × {args.trials} "
        f"trials on a {patch.shape[1]}×{patch.shape[0]} patch: at most about {minutes:.0f} min "
        "on 2 CPU cores (fewer --agents, --iters or --trials for a quick look; Ctrl-C keeps the "
        "best parameters so far)",
        file=sys.stderr,
    )
    with tqdm(total=total, desc="particle swarm", unit="epoch") as bar:

        def progress(trial, epoch, best):
            bar.update(1)
            bar.set_postfix(trial=trial + 1, epoch=epoch, best=f"{best:.4g}", refresh=False)

        fit = fit_wrinkles(
            jax.random.key(args.seed),
            patch,
            d_range=tuple(args.d_range),
            n_agents=args.agents,
            n_epochs=args.epochs,
            n_trials=args.trials,
            n_steps=args.steps,
            refine_steps=args.refine_steps,
            d_levels=None if args.d_levels is None else max(2, args.d_levels),
            mode=mode,
            progress=progress,
        )
    meta = provenance(
        seed=args.seed, patch=str(args.patch), agents=args.agents, epochs=args.epochs,
        trials=args.trials, mode=mode, steps=args.steps, refine_steps=args.refine_steps,
        d_range=list(args.d_range), d_levels=args.d_levels,
    )  # fmt: skip
    document = json.loads(params_to_json(list(fit.levels), units))
    document |= {
        "fit": {
            "loss": float(fit.loss),
            "swarm_loss": float(fit.swarm_loss),
            "trial_losses": np.asarray(fit.swarm.trial_losses).tolist(),
            "nonfinite_losses": np.asarray(fit.swarm.n_nonfinite).tolist(),
            "names": list(fit.names),
            "mode": mode,
            "epochs_run": list(fit.epochs_run),
            "interrupted": fit.interrupted,
        },
        "provenance": meta,
    }
    write_json(out, document)
    history = np.asarray(fit.swarm.history)
    figure = plots.convergence(
        history,
        title="Wrinkle fit: particle swarm, best loss per trial",
        xlabel="epoch (0: the initial swarm)",
    )
    write_figure(f"{stem}_convergence.png", figure, metadata=meta)
    pair = plots.panel_grid(
        [[shade(patch), shade(fit.fitted)], [np.asarray(patch), np.asarray(fit.fitted)]],
        title=f"Wrinkle fit: measured patch and fitted simulation (loss {float(fit.loss):.3g})",
        col_labels=["measured", "fitted"],
        row_labels=["shaded relief", "displacement"],
        quantities=["relief", "displacement"],
        units=[None, "displacement (map units)"],
    )
    write_figure(f"{stem}_target_fit.png", pair, metadata=meta)
    bad = int(np.sum(fit.swarm.n_nonfinite))
    if fit.interrupted:
        commit()  # keep the best parameters found so far, then exit as interrupted (130)
        print(f"wrinkles fit: interrupted; wrote the best parameters so far to {out}",
              file=sys.stderr)  # fmt: skip
        raise KeyboardInterrupt
    return {
        "out": str(out),
        "convergence": f"{stem}_convergence.png",
        "comparison": f"{stem}_target_fit.png",
        "swarm_loss": float(fit.swarm_loss),
        "loss": float(fit.loss),
        "nonfinite": bad,
    }


def _halving_epochs(trials: int, epochs: int) -> int:
    """Epochs of a fast fit at most: rungs of ``epochs // 8`` for a halving field of trials,
    then the last trial on to ``epochs`` in all."""
    rung, total, done = max(1, epochs // 8), 0, 0
    while trials > 1:
        total, done, trials = total + trials * rung, done + rung, -(-trials // 2)
    return total + max(0, epochs - done)
