"""The ``jface`` command.

Each pillar contributes its sub-commands from a module of this package with a
``register(subparsers)`` function, and may contribute a step to ``jface demo`` with a
``demo(out_dir, seed)`` function. Errors in user input end the command with a one-line message
and exit status 2, never a traceback.

A command runs inside one :func:`jface.io.session`: every path on its command line that exists
(except the values of the output options ``--out``, ``--out-dir`` and ``--pores-out``) and every
file it reads is an input, which no output may replace; its outputs appear together when it
succeeds, and nothing appears under their names when it fails or is interrupted (SIGINT or
SIGTERM).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path

from jface import __version__, io

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


#: Options whose values are outputs; any other existing path on a command line is an input.
OUTPUT_OPTIONS = ("out", "out_dir", "pores_out")


def _demo(args: argparse.Namespace) -> None:
    out = Path(args.out)
    for module in _modules():
        if hasattr(module, "demo"):
            module.demo(out, seed=args.seed)
            io.commit()  # a later step's failure keeps the steps done
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


def command_inputs(args: argparse.Namespace) -> list[str]:
    """The existing paths among a parsed command line's values, output options excepted."""
    found = []
    for name, value in vars(args).items():
        if name in OUTPUT_OPTIONS or name == "run":
            continue
        for item in value if isinstance(value, list | tuple) else [value]:
            if isinstance(item, str) and item and Path(item).exists():
                found.append(item)
    return found


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``jface`` command line; returns the exit status (0, 2 for an error, 130 when
    interrupted)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with _terminate_as_interrupt(), io.session(command_inputs(args)):
            args.run(args)
    except KeyboardInterrupt:
        print(f"jface {args.command}: interrupted; unfinished outputs removed", file=sys.stderr)
        return 130
    except (ValueError, TypeError, OSError, OverflowError, MemoryError) as err:
        print(f"jface {args.command}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    return 0


def _one_line(err: BaseException) -> str:
    if isinstance(err, MemoryError):
        return f"out of memory ({err or 'the input is larger than this machine can hold'})"
    if isinstance(err, OSError) and err.strerror:
        text = f"{err.filename}: {err.strerror}" if err.filename else err.strerror
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into KeyboardInterrupt while a command runs, so that a terminated command
    removes its temporary files like an interrupted one."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
