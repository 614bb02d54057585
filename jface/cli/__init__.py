"""The ``jface`` command.

Each pillar contributes its sub-commands from a module of this package with a
``register(subparsers)`` function, and may contribute a step to ``jface demo`` with a
``demo(out_dir, seed)`` function. Errors in user input end the command with a one-line message
and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from jface import __version__

#: Modules contributing sub-commands, in the order their demo steps run.
COMMAND_MODULES = (
    "jface.cli._detail",
    "jface.cli._apps",
    "jface.cli._mesh",
    "jface.cli._faces",
    "jface.cli._wrinkles",
    "jface.cli._fit",
)


def _modules():
    return [importlib.import_module(name) for name in COMMAND_MODULES]


def _demo(args: argparse.Namespace) -> None:
    out = Path(args.out)
    for module in _modules():
        if hasattr(module, "demo"):
            module.demo(out, seed=args.seed)
    print(f"demo outputs written to {out}/")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jface", description="Statistics and synthesis of fine facial detail."
    )
    parser.add_argument("--version", action="version", version=f"jface {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the main job on built-in data and write its results")
    demo.add_argument("--out", default="jface-demo", help="output folder (default: jface-demo)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    demo.set_defaults(run=_demo)
    for module in _modules():
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``jface`` command line; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.run(args)
    except (ValueError, TypeError, FileNotFoundError, FileExistsError) as err:
        print(f"jface {args.command}: error: {err}", file=sys.stderr)
        return 2
    return 0
