"""The ``jface`` command.

Each pillar contributes its sub-commands from a module of this package with a
``register(subparsers)`` function, and may contribute a step to ``jface demo`` with a
``demo(out_dir, seed)`` function. Errors in user input end the command with a one-line message
and exit status 2, never a traceback.

A command runs inside one :func:`jface.io.session`: every path on its command line that exists
(except the values of the output options ``--out`` and ``--pores-out``) and every
file it reads is an input, which no output may replace; its outputs appear together when it
succeeds, and nothing appears under their names when it fails or is interrupted (SIGINT or
SIGTERM).

Every command speaks one vocabulary (docs/cli.md): ``--out`` names its output, ``--iters`` its
optimiser's iterations, ``--seed`` its randomness and ``--json`` turns its summary into one JSON
object on stdout. A command's run function returns that summary as a dict; without ``--json`` it
is printed as the command's prose line (its ``prose`` template). A command whose ``--out`` is a
folder also writes ``index.html`` there, the page of the run (:mod:`jface.cli._report`). Old
spellings stay accepted as hidden options (:func:`deprecated_alias`) that print a one-line
notice.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from jface import __version__, io
from jface._compilation import keep_compiled_programs

#: Modules contributing sub-commands, in the order their demo steps run.
COMMAND_MODULES = (
    "jface.cli._detail",
    "jface.cli._apps",
    "jface.cli._mesh",
    "jface.cli._faces",
    "jface.cli._wrinkles",
)


def _modules():
    return [importlib.import_module(name) for name in COMMAND_MODULES]


#: Options whose values are outputs; any other existing path on a command line is an input.
OUTPUT_OPTIONS = ("out", "pores_out")


class _Deprecated(argparse.Action):
    """A hidden old spelling of an option: stores like the new one and says it is deprecated."""

    def __init__(self, option_strings, dest, new, nargs=None, **kwargs):
        self.new = new
        kwargs.setdefault("default", argparse.SUPPRESS)  # the new option sets the default
        super().__init__(option_strings, dest, nargs=nargs, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"jface: {option_string} is deprecated; use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose required options may also be given by a deprecated spelling."""

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        for action in getattr(self, "required_either_spelling", ()):
            if getattr(namespace, action.dest, None) is None:
                self.error(f"the following arguments are required: {action.option_strings[0]}")
        return namespace, extras


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str, **kwargs) -> None:
    """Accept ``old`` as a hidden spelling of the option ``new`` already on ``parser`` (or, given
    ``dest``, as a hidden option of its own that ``new`` replaces)."""
    if "dest" not in kwargs:
        target = next(a for a in parser._actions if new in a.option_strings)
        kwargs.update(dest=target.dest, type=target.type)
        if target.required:  # either spelling satisfies it: checked after parsing
            target.required = False
            parser.required_either_spelling = [*getattr(parser, "required_either_spelling", []),
                                               target]  # fmt: skip
    parser.add_argument(old, action=_Deprecated, new=new, help=argparse.SUPPRESS, **kwargs)


def refuse_shared_names(inputs: Sequence, names: Sequence[str]) -> None:
    """Refuse, before any work, two inputs whose outputs would take one name (names compared
    without case, as some file systems do), naming both."""
    first: dict[str, int] = {}
    for i, name in enumerate(names):
        j = first.setdefault(name.casefold(), i)
        if j != i:
            raise ValueError(
                f"{inputs[j]} and {inputs[i]} would both write the output {name!r}; "
                "rename one or run them apart"
            )


def _demo(args: argparse.Namespace) -> dict:
    from jface.cli._report import Tee, write_index

    out = Path(args.out)
    steps = [m for m in _modules() if hasattr(m, "demo")]
    records = [{"name": m.__name__.rsplit("._", 1)[-1], "status": "not run"} for m in steps]
    meta = io.provenance(seed=args.seed, command="jface demo", out=str(out))

    def page() -> None:
        meta["timings_s"] = {r["name"]: round(r["seconds"], 2) for r in records if "seconds" in r}
        write_index(out, title="jface demo", provenance=meta, steps=records)
        io.commit()

    for module, record in zip(steps, records, strict=True):
        tee, start = Tee(sys.stdout), time.perf_counter()
        try:
            with contextlib.redirect_stdout(tee):
                module.demo(out, seed=args.seed)
        except BaseException as err:
            # The failed step's outputs go; the page tells what the steps done left.
            record |= {"status": f"failed: {type(err).__name__}: {err}", "console": tee.lines}
            io.discard()
            page()
            raise
        record |= {"status": "done", "console": tee.lines}
        record["seconds"] = time.perf_counter() - start
        io.commit()  # a later step's failure keeps the steps done
    page()
    return {"out": str(out)}


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jface", description="Statistics and synthesis of fine facial detail.")
    parser.add_argument("--version", action="version", version=f"jface {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    demo = sub.add_parser("demo", help="run the main job on built-in data and write its results")
    demo.add_argument("--out", default="jface-demo", help="output folder (default: jface-demo)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    demo.set_defaults(
        run=_demo,
        prose="demo outputs written to {out}/; the page {out}/index.html shows them",
        own_page=True,
    )
    for module in _modules():
        module.register(sub)
    _hidden_fit(sub)
    for leaf in _leaves(parser):
        leaf.add_argument(
            "--json",
            action="store_true",
            help="print a machine-readable summary (one JSON object on stdout) instead of prose",
        )
        _show_defaults(leaf)
        leaf.set_defaults(page_title=leaf.prog)
    return parser


def _hidden_fit(sub: argparse._SubParsersAction) -> None:
    """``jface fit``: the deprecated spelling of ``jface wrinkles fit``, left out of the help."""
    from jface.cli import _fit

    _fit.register(sub)
    sub._choices_actions = [a for a in sub._choices_actions if a.dest != "fit"]
    sub.choices["fit"].set_defaults(deprecated=("fit", "wrinkles fit"))


def _leaves(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    """The parsers that run a command (those without sub-commands), each once."""
    commands = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not commands:
        yield parser
    seen = set()
    for action in commands:
        for child in action.choices.values():
            if id(child) not in seen:
                seen.add(id(child))
                yield from _leaves(child)


def _show_defaults(parser: argparse.ArgumentParser) -> None:
    """Append the default to an option's help where the help does not state it already, or
    say that the option is required."""
    required = [*getattr(parser, "required_either_spelling", [])]
    for action in parser._actions:
        if not action.option_strings or action.help in (None, argparse.SUPPRESS):
            continue
        if action.required or action in required:
            action.help += " (required)"
            continue
        if "default" in action.help or action.default is argparse.SUPPRESS:
            continue
        if action.default is None:  # an optional input or setting left out unless given
            action.help += " (default: none)"
        elif isinstance(action, argparse._StoreTrueAction):
            action.help += " (default: off)"
        elif not isinstance(action, argparse._HelpAction | argparse._VersionAction):
            action.help += " (default: %(default)s)"


def command_inputs(args: argparse.Namespace) -> list[str]:
    """The existing paths among a parsed command line's values, output options excepted."""
    found = []
    for name, value in vars(args).items():
        if name in OUTPUT_OPTIONS or name in ("run", "prose", "deprecated"):
            continue
        for item in value if isinstance(value, list | tuple) else [value]:
            if isinstance(item, str) and item and Path(item).exists():
                found.append(item)
    return found


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``jface`` command line; returns the exit status (0, 2 for an error, 130 when
    interrupted)."""
    from jface.cli._processes import Elsewhere
    from jface.cli._report import run_with_page

    parser = build_parser()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    name = args.page_title  # the sub-command, e.g. "jface wrinkles fit", names its messages
    keep_compiled_programs()
    if getattr(args, "deprecated", None):
        old, new = args.deprecated
        print(f"jface: {old} is deprecated; use {new}", file=sys.stderr)
    try:
        # with --json only the summary goes to stdout; any prose a step prints goes to stderr
        prose_to = sys.stderr if args.json else sys.stdout
        with (
            _terminate_as_interrupt(),
            io.session(command_inputs(args)),
            contextlib.redirect_stdout(prose_to),
        ):
            summary = run_with_page(args, argv)
    except KeyboardInterrupt:
        print(f"{name}: interrupted; unfinished outputs removed", file=sys.stderr)
        return 130
    except (ValueError, TypeError, OSError, OverflowError, MemoryError) as err:
        print(f"{name}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    if not isinstance(summary, Elsewhere):  # else process 0 of a distributed run reports
        _print_summary(summary or {}, getattr(args, "prose", None), as_json=args.json)
    return 0


def _print_summary(summary: dict, prose: str | None, *, as_json: bool) -> None:
    if as_json:
        print(json.dumps(summary, default=str))
    elif summary:  # an empty summary: another process reports
        print(summary_text(summary, prose))


def summary_text(summary: dict, prose: str | None) -> str:
    """A command's summary as its prose line (its ``prose`` template, or name: value pairs)."""
    if prose is not None:
        return prose.format(**summary)
    return ", ".join(f"{name}: {value}" for name, value in summary.items())


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
