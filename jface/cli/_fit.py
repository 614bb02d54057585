"""``jface wrinkles fit``: fit wrinkle parameters to measured patches (Weiss et al. 2023, §4.2).

One patch with ``--out P.json`` writes ``P.json`` and its figures beside it. Several patches (or
``--out`` a folder) write ``DIR/STEM.json`` and figures per patch, spread over the processes of
the run (patch ``i`` on process ``i mod N``), resumably: a patch whose fit exists with the same
key (the patch's bytes, every setting, the jface version and source) is kept, any other is
fitted. Every patch is fitted with the same key, ``jax.random.key(--seed)``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jface import io, plots
from jface._distributed import _Run
from jface.cli import deprecated_alias, refuse_shared_names
from jface.cli._processes import Elsewhere, add_process_options, spread
from jface.io import check_output, commit, provenance, read_map, write_figure, write_json
from jface.render import shade
from jface.wrinkles import (
    REFINE_STEPS,
    ParamUnits,
    fit_budget,
    fit_wrinkles,
    heldout_key_count,
    params_to_json,
    parse_patch_size,
)
from jface.wrinkles._fit import (
    D_LEVELS,
    checked_target,
    layout_shipped,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fit",
        help="fit two-level wrinkle parameters to a displacement patch (particle swarm + "
        "gradient refinement); write the parameters (JSON), a convergence plot and a "
        "side-by-side shaded PNG",
    )
    parser.add_argument(
        "patches",
        nargs="+",
        metavar="PATCH",
        help="displacement patches: EXR (one channel), .npy or grey PNG",
    )
    parser.add_argument(
        "--out",
        required=True,
        help="output parameter file (.json) of one patch, or a folder: STEM.json and figures "
        "per patch (resumable: a patch fitted before with the same content and settings is "
        "kept)",
    )
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
        help="the paper's procedure: every trial runs all --iters epochs, no early stop, the "
        "paper's inertia decay (default: off: trials by successive halving, each rung's bests "
        "refined by gradient in full fits and shared with their swarms, stop when the best "
        "loss improves by less than 1 %% over 10 epochs or after 48, a faster inertia decay)",
    )  # fmt: skip
    parser.add_argument("--steps", type=int, default=50, help="simulation steps (default: 50)")
    parser.add_argument(
        "--refine-steps", type=int,
        help="BFGS steps on the drawing parameters, at most (0: none; default: 30)",
    )  # fmt: skip
    parser.add_argument(
        "--d-levels", type=int,
        help="α_d values whose pores and graphs are precomputed (default: 16, 32 with --paper)",
    )  # fmt: skip
    parser.add_argument(
        "--d-range", type=float, nargs=2, default=(0.02, 0.05), metavar=("LOW", "HIGH"),
        help="search range of the pore distance α_d (default: 0.02 0.05)",
    )  # fmt: skip
    add_process_options(parser, "fitting a share of the patches")
    parser.set_defaults(
        run=_fit,
        prose=ONE_PROSE,
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
    try:  # the patch is square (checked_target): its lengths have one size on the face
        return ParamUnits("patch", parse_patch_size(patch_size), shape)
    except ValueError as err:
        raise ValueError(f"--patch-size: {err}") from None


#: Prose summary of one patch's fit (a null loss is said "undrawable", :func:`_undrawn`).
ONE_PROSE = (
    "loss {swarm_loss:.4g} (swarm) → {loss:.4g} (refined), {heldout_loss:.4g} with other "
    "simulation keys; {nonfinite} non-finite evaluations; wrote {out}, {convergence}, "
    "{comparison}"
)
#: Prose summary of a fit of several patches (or into a folder).
MANY_PROSE = (
    "fitted {fitted} patch(es), kept {kept} already done (same content and settings), in {out}/; "
    "losses {min_loss:.4g} to {max_loss:.4g}"
)
_FIGURES = ("_convergence.png", "_target_fit.png")


def _fit(args: argparse.Namespace) -> dict:
    for name, option in (("agents", "agents"), ("epochs", "iters"), ("trials", "trials"),
                         ("steps", "steps"), ("d_levels", "d-levels")):  # fmt: skip
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise ValueError(f"--{option} must be at least 1, got {getattr(args, name)}")
    mode = "paper" if args.paper else "fast"
    if args.refine_steps is None:
        args.refine_steps = REFINE_STEPS[mode]
    for patch in args.patches:
        if Path(patch).resolve() == Path(args.out).resolve():
            raise ValueError(f"--out {args.out} is the input patch {patch}; name another output")
    many = _into_folder(args.patches, args.out)
    if many:
        stems = [Path(patch).stem for patch in args.patches]
        refuse_shared_names(args.patches, [f"{stem}.json" for stem in stems])
        outs = [Path(args.out) / f"{stem}.json" for stem in stems]
    else:
        outs = [check_output(args.out, (".json",))]
    for out in outs:  # every output name checked (and an input never replaced) before any work
        check_output(out, (".json",))
        for suffix in _FIGURES:
            check_output(f"{out.with_suffix('')}{suffix}", (".png",))
    if spread(args, _command(args)):
        return Elsewhere()  # process 0 of the launched processes reports
    # every patch checked before any is fitted (in each process: after jax.distributed starts),
    # so a bad one stops the batch before it starts
    for patch in args.patches:
        target = read_map(patch, args.channel)  # read errors name the file themselves
        try:
            checked_target(target)
        except ValueError as err:
            raise ValueError(f"{patch}: {err}") from None
    run = _Run() if jax.process_count() > 1 else None
    try:
        summaries = _fit_share(run, args, mode, outs, resume=many)
    except BaseException as err:
        if run is not None:
            run.fail(err)  # the others stop at once instead of waiting for this share
        raise
    if summaries is None:
        return Elsewhere()
    if not many:  # the summary of one patch's fit, as before there were several
        summary = {k: v for k, v in summaries[0].items() if k not in ("patch", "kept")}
        args.prose = _undrawn(ONE_PROSE, summary)
        return summary
    losses = [s["loss"] for s in summaries if s["loss"] is not None]
    summary = {
        "out": args.out,
        "fitted": sum(not s["kept"] for s in summaries),
        "kept": sum(s["kept"] for s in summaries),
        "min_loss": min(losses, default=None),
        "max_loss": max(losses, default=None),
        "patches": summaries,
    }
    args.prose = _undrawn(MANY_PROSE, summary)
    return summary


def _undrawn(prose: str, summary: dict) -> str:
    """``prose`` with each loss that is null (no drawable answer) said as "undrawable"."""
    for name, value in summary.items():
        if value is None:
            prose = prose.replace(f"{{{name}:.4g}}", "undrawable")
    return prose


def _into_folder(patches: list[str], out: str) -> bool:
    """Whether ``--out`` is a folder of per-patch fits (several patches, an existing folder or a
    name without a suffix) rather than one patch's parameter file."""
    path = Path(out)
    if path.is_dir() or (len(patches) == 1 and not path.suffix):
        return True
    if len(patches) == 1:
        return False
    if path.exists() or path.suffix.lower() == ".json":
        raise ValueError(
            f"--out must be a folder when fitting {len(patches)} patches (STEM.json per patch), "
            f"got the {'existing file' if path.exists() else 'file name'} {out}"
        )
    return True


def _command(args: argparse.Namespace) -> list[str]:
    """The command line of this fit without its process options, for processes it starts."""
    command = ["wrinkles", "fit", *args.patches, "--out", args.out, "--seed", str(args.seed)]
    command += ["--agents", str(args.agents), "--iters", str(args.epochs)]
    command += ["--trials", str(args.trials), "--steps", str(args.steps)]
    command += ["--refine-steps", str(args.refine_steps), "--d-range", *map(str, args.d_range)]
    command += ["--paper"] if args.paper else []
    command += ["--d-levels", str(args.d_levels)] if args.d_levels is not None else []
    command += ["--channel", args.channel] if args.channel else []
    command += ["--patch-size", args.patch_size] if args.patch_size else []
    return command


def _settings(args: argparse.Namespace, mode: str) -> dict:
    """Every setting that changes a fit, for its key."""
    return {
        "kind": "WrinkleFit", "seed": args.seed, "agents": args.agents, "epochs": args.epochs,
        "trials": args.trials, "mode": mode, "steps": args.steps,
        "refine_steps": args.refine_steps, "d_range": list(args.d_range),
        "d_levels": args.d_levels, "channel": args.channel, "patch_size": args.patch_size,
    }  # fmt: skip


def _fit_share(run, args, mode: str, outs: list[Path], *, resume: bool) -> list[dict] | None:
    """Fit this process's share of the patches (patch ``i`` on process ``i mod N``); on process
    0, the summaries of all patches once every process is done (None on the others)."""
    settings = _settings(args, mode)
    keys = [io.content_key([patch], settings) for patch in args.patches]
    process, n_processes = jax.process_index(), jax.process_count()
    if run is not None:
        fingerprint = json.dumps([[str(o) for o in outs], keys], sort_keys=True)
        run.same_on_all(
            "the command's arguments, its patches' contents or jface's code", fingerprint
        )
    mine = range(process, len(outs), n_processes)
    if len(outs) > 1:
        print(f"wrinkles fit: {len(outs)} patches, {len(mine)} on this process", file=sys.stderr)
    results = {}  # patch index → (its fit document, kept from an earlier run)
    for i in mine:
        document = _done(outs[i], args.patches[i], keys[i]) if resume else None
        results[i] = (document, True)  # fitted before from the same bytes and settings
        if document is None:
            document = _fit_one(args, mode, args.patches[i], outs[i], keys[i], process == 0)
            commit()  # a finished patch survives a crash of a later one
            results[i] = (document, False)
    if run is not None:
        fitted = [i for i, (_, kept) in results.items() if not kept]
        posted = run.gather("finished", json.dumps(fitted))  # process 0 waits for every share
        if process != 0:
            return None
        fitted_anywhere = {i for share in posted for i in json.loads(share)}
        for i in set(range(len(outs))) - set(results):
            document = _done(outs[i], args.patches[i], keys[i])
            if document is None:
                raise ValueError(
                    f"the fit of {args.patches[i]} ({outs[i]}) was removed or replaced while "
                    "the run went on; run it again"
                )
            results[i] = (document, i not in fitted_anywhere)
    return [_summary(outs[i], *results[i]) for i in range(len(outs))]


def _done(out: Path, patch: str, key: str) -> dict | None:
    """The fit in ``out`` when it is complete (figures too, not interrupted) and was made from
    this patch's content with these settings (``key``); None when there is none or it is stale.

    Raises:
        ValueError: ``out`` exists but is not a jface fit of this patch's name.
    """
    if not out.exists():
        return None
    try:
        with io.own_outputs():
            document = io.read_json(out)
        source = Path(document["provenance"]["patch"]).name
        fit = document["fit"]
    except (ValueError, KeyError, TypeError):
        raise ValueError(
            f"{out} exists and is not a jface wrinkle fit; remove it or use another --out"
        ) from None
    if source != Path(patch).name:
        raise ValueError(f"{out} holds the fit of {source!r}, not of {patch}; use another --out")
    stem = out.with_suffix("")
    complete = all(Path(f"{stem}{suffix}").is_file() for suffix in _FIGURES)
    if fit.get("key") != key or fit.get("interrupted") or not complete:
        return None
    return document


def _finite_or_none(value) -> float | None:
    """A loss for JSON, which has no infinity or NaN (null: undrawable)."""
    return float(value) if np.isfinite(value) else None


def _finite_list(values) -> list[float | None]:
    return [_finite_or_none(v) for v in np.asarray(values).ravel()]


def _shown(loss: float | None) -> str:
    return "undrawable" if loss is None else f"{loss:.3g}"


def _summary(out: Path, document: dict, kept: bool) -> dict:
    stem = out.with_suffix("")
    fit = document["fit"]
    return {
        "patch": document["provenance"]["patch"],
        "out": str(out),
        "convergence": f"{stem}_convergence.png",
        "comparison": f"{stem}_target_fit.png",
        "swarm_loss": fit["swarm_loss"],
        "loss": fit["loss"],
        "heldout_loss": fit.get("heldout_loss"),
        "nonfinite": int(np.sum(fit["nonfinite_losses"])),
        "kept": kept,
    }


def _fit_one(args, mode: str, patch_path: str, out: Path, key: str, progress: bool) -> dict:
    """Fit one patch and write its parameters and figures; the parameter file's document."""
    stem = out.with_suffix("")
    patch = read_map(patch_path, args.channel)
    units = _units(args.patch_size, patch.shape)
    total, polishes, starts, searched = fit_budget(
        args.agents, args.epochs, args.trials, refine_steps=args.refine_steps, mode=mode
    )
    # measured on 2 CPU cores: 0.24 s per agent and epoch at 256² on a slow day (0.13 on a fast
    # one: "at most" holds on either), a refinement step (polishes and the final refinement's
    # starts, and the coordinate search's answer) about 7 of those, each polish's sharing one per
    # agent and each held-out key of the answer one, plus about 50 s of fixed cost (20 s when an
    # earlier fit of this patch size left its compiled programs cached) and about 45 s more to
    # build a layout that jface does not ship
    refined = polishes + starts + bool(searched)
    refinements = refined * 7 * args.refine_steps + polishes * args.agents
    heldout = heldout_key_count(args.agents, args.epochs, args.trials, mode=mode)
    evaluations = total * args.agents + refinements + searched + heldout
    d_levels = D_LEVELS[mode] if args.d_levels is None else max(2, args.d_levels)
    shipped = layout_shipped(patch.shape, tuple(args.d_range), args.steps, d_levels)
    minutes = (evaluations * 0.24 * patch.size / 256**2 + 50 + 45 * (not shipped)) / 60
    print(
        f"wrinkles fit ({mode}): {args.agents} agents × {args.epochs} epochs × {args.trials} "
        f"trials on the {patch.shape[1]}×{patch.shape[0]} patch {patch_path}: at most about "
        f"{minutes:.0f} min on 2 CPU cores (fewer --agents, --iters or --trials for a quick "
        "look; Ctrl-C keeps the best parameters so far)",
        file=sys.stderr,
    )
    with tqdm(total=total, desc="particle swarm", unit="epoch", disable=not progress) as bar:

        def report(trial, epoch, best):
            bar.update(1)
            bar.set_postfix(trial=trial + 1, epoch=epoch, best=f"{best:.4g}", refresh=False)

        fit = fit_wrinkles(
            jax.random.key(args.seed),  # the same key for every patch
            patch,
            d_range=tuple(args.d_range),
            n_agents=args.agents,
            n_epochs=args.epochs,
            n_trials=args.trials,
            n_steps=args.steps,
            refine_steps=args.refine_steps,
            d_levels=d_levels,
            mode=mode,
            progress=report,
        )
    meta = provenance(
        seed=args.seed, patch=str(patch_path), agents=args.agents, epochs=args.epochs,
        trials=args.trials, mode=mode, steps=args.steps, refine_steps=args.refine_steps,
        d_range=list(args.d_range), d_levels=args.d_levels,
    )  # fmt: skip
    document = json.loads(params_to_json(list(fit.levels), units))
    document |= {
        "fit": {
            "loss": _finite_or_none(fit.loss),
            "swarm_loss": _finite_or_none(fit.swarm_loss),
            "refined_losses": _finite_list(fit.refined_losses),
            # the answer with other simulation keys (null: undrawable even on bins sized to it)
            "heldout_loss": _finite_or_none(fit.heldout_loss),
            "heldout_losses": _finite_list(fit.heldout_losses),
            "answer_trial": fit.answer_trial,
            "trial_losses": _finite_list(fit.swarm.trial_losses),
            "nonfinite_losses": np.asarray(fit.swarm.n_nonfinite).tolist(),
            "names": list(fit.names),
            "mode": mode,
            "epochs_run": list(fit.epochs_run),
            "interrupted": fit.interrupted,
            "key": key,
        },
        "provenance": meta,
    }
    write_json(out, document)
    history = np.asarray(fit.swarm.history)
    figure = plots.convergence(
        history,
        title="Wrinkle fit: particle swarm, best loss per trial",
        xlabel="epoch (0: the initial swarm)",
        answer=("the fit's answer", float(fit.loss)),
    )
    write_figure(f"{stem}_convergence.png", figure, metadata=meta)
    # the loss compares zero-mean, unit-variance maps: so does the figure (a measured patch in
    # [0, 1] and the zero-mean fit on one scale would saturate)
    maps = [np.asarray(m, np.float64) for m in (patch, fit.fitted)]
    standard = [(m - m.mean()) / max(float(m.std()), 1e-12) for m in maps]
    losses = document["fit"]
    pair = plots.panel_grid(
        [[shade(patch), shade(fit.fitted)], standard],
        title="Wrinkle fit: measured patch and fitted simulation\n"
        f"(loss {_shown(losses['loss'])}; {_shown(losses['heldout_loss'])} with other simulation "
        "keys)",
        col_labels=["measured", "fitted"],
        row_labels=["shaded relief", "displacement"],
        quantities=["relief", "displacement"],
        units=[None, "displacement (standard deviations)"],
    )
    write_figure(f"{stem}_target_fit.png", pair, metadata=meta)
    if fit.interrupted:
        commit()  # keep the best parameters found so far, then exit as interrupted (130)
        print(f"wrinkles fit: interrupted; wrote the best parameters so far to {out}",
              file=sys.stderr)  # fmt: skip
        raise KeyboardInterrupt
    return document
