"""``index.html``: one page that shows a run: its figures, the numbers it printed, its files and
its provenance, and what is missing when the run stopped early or an output is broken.

``jface demo`` writes its page step by step; every other command that writes into an output
folder gets one from :func:`run_with_page`, the one place that decides when a command has a page.
"""

from __future__ import annotations

import argparse
import contextlib
import contextvars
import html
import io as io_text
import json
import re
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from jface import io

FIGURE_SUFFIXES = (".png", ".svg")
_NUMBERED = re.compile(r"_\d+$")
_STYLE = """
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; border-bottom: 1px solid #ccc; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0.5em 0 1em; }
td, th { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: left; vertical-align: top;
  white-space: pre-wrap; }
th { background: #f3f3f3; } .missing { color: #b00; font-weight: bold; }
code { font-size: 0.95em; }
img.thumb { width: 96px; margin: 2px; border: 1px solid #ddd; image-rendering: pixelated; }
"""


def _broken(path: Path) -> str | None:
    """Why an existing output cannot be shown, or ``None`` when it can."""
    if path.stat().st_size == 0:
        return "empty file"
    if path.suffix.lower() == ".png":
        try:
            with io.own_outputs():
                io.read_image(path)
        except ValueError:
            return "not a readable PNG (truncated?)"
    return None


class Tee(io_text.TextIOBase):
    """Text to the console that is also kept, for the run's page."""

    def __init__(self, console):
        self.console, self.lines = console, []

    def write(self, text: str) -> int:
        self.lines += [line for line in text.splitlines() if line.strip()]
        return self.console.write(text)

    def flush(self) -> None:
        self.console.flush()


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _fields(record: dict[str, Any]) -> str:
    """A record as a two-column table, values that are not text as JSON."""
    rows = [(k, v if isinstance(v, str) else json.dumps(v, default=str)) for k, v in record.items()]
    return _table(("field", "value"), rows)


def write_index(
    run_dir: str | Path,
    *,
    title: str,
    provenance: dict[str, Any],
    steps: Sequence[dict[str, Any]] = (),
    expected: Sequence[str] = (),
    files: Sequence[str] | None = None,
    summary: dict[str, Any] | None = None,
) -> Path:
    """Write ``run_dir/index.html`` for the outputs found in ``run_dir`` (on disk: commit the
    run's outputs first).

    Args:
        run_dir: the run's output folder.
        title: the page's heading.
        provenance: version, seed, parameters (shown as a table).
        steps: one record per step of the run: ``name``, ``console`` (the lines it printed),
            ``seconds`` (its time) and ``status`` (``"done"``, or why it did not finish).
        expected: outputs (relative to ``run_dir``) the run should have written; each absent
            or unreadable one is listed as missing instead of failing.
        files: the outputs to show (relative to ``run_dir``; those absent are left out);
            default: every file under ``run_dir``.
        summary: the run's summary (the numbers it printed), shown as a table.

    Returns:
        The page's path.
    """
    run_dir = Path(run_dir)
    candidates = run_dir.rglob("*") if files is None else (run_dir / name for name in files)
    found = sorted(
        p for p in set(candidates) if p.is_file() and p.name != "index.html" and not
        p.name.startswith(".")
    )  # fmt: skip
    problems = [(name, "not written") for name in expected if not (run_dir / name).is_file()]
    shown, series = [], []
    for path in found:
        reason = _broken(path)
        if reason:
            problems.append((str(path.relative_to(run_dir)), reason))
        elif path.suffix.lower() in FIGURE_SUFFIXES:
            # Numbered images (sample_000.png, ...) are a series: thumbnails, not figures.
            (series if _NUMBERED.search(path.stem) else shown).append(path)
    problems += [(s["name"], f"step did not finish: {s['status']}") for s in steps
                 if s.get("status", "done") != "done"]  # fmt: skip
    parts = [f"<h1>{html.escape(title)}</h1>"]
    if problems:
        parts.append('<h2 class="missing">Missing or broken outputs</h2>')
        parts.append('<p class="missing">This run is incomplete; these outputs are missing:</p>')
        parts.append(_table(("output", "why"), problems))
    if steps:
        parts.append("<h2>Results</h2>")
        rows = [
            (s["name"], s.get("status", "done"), f"{s.get('seconds', float('nan')):.1f}",
             "\n".join(s.get("console", ())))
            for s in steps
        ]  # fmt: skip
        parts.append(_table(("step", "status", "time (s)", "printed on the console"), rows))
    if summary:
        parts.append("<h2>Summary</h2>")
        parts.append(_fields(summary))
    parts.append("<h2>Figures</h2>")
    if not shown:
        parts.append('<p class="missing">No figures were written.</p>')
    for path in shown:
        rel = path.relative_to(run_dir).as_posix()
        parts.append(
            f'<figure><img src="{html.escape(rel)}" alt="{html.escape(rel)}">'
            f"<figcaption><code>{html.escape(rel)}</code></figcaption></figure>"
        )
    if series:
        parts.append("<h2>Image series</h2><p>")
        for path in series:
            rel = html.escape(path.relative_to(run_dir).as_posix())
            parts.append(f'<img class="thumb" src="{rel}" alt="{rel}" title="{rel}">')
        parts.append("</p>")
    parts.append("<h2>Files</h2>")
    files = [(p.relative_to(run_dir).as_posix(), p.stat().st_size) for p in found]
    links = "".join(
        f'<li><a href="{html.escape(rel)}">{html.escape(rel)}</a> ({size:,} bytes)</li>'
        for rel, size in files
    )
    parts.append(f"<ul>{links}</ul>")
    parts.append("<h2>Provenance</h2>")
    parts.append(_fields(provenance))
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head>\n<body>\n"
        + "\n".join(parts)
        + "\n</body></html>\n"
    )
    path = run_dir / "index.html"
    with io.atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return path


#: Set while a command runs under :func:`run_with_page`: a command it runs in turn (a step of
#: the demo) is part of the caller's run and page.
_RUNNING: contextvars.ContextVar[bool] = contextvars.ContextVar("jface_page", default=False)

#: Namespace entries that are the parser's machinery, not parameters of the run.
_MACHINERY = ("run", "prose", "json", "deprecated", "page_title", "own_page")


def run_with_page(args: argparse.Namespace, command_line: Sequence[str]) -> dict:
    """Run a parsed command (inside its :func:`jface.io.session`) and, when its ``--out`` is a
    folder, write ``index.html`` there: the figures and files the command wrote, its summary,
    what it printed, the command line, parameters, seed, version and time.

    A failed command leaves no page, unless it had already put outputs in place in its folder
    (a resumable batch): then the page says why it stopped and which outputs are missing. A
    command that writes its own page (``own_page``) or is run by another gets none here.
    """
    if _RUNNING.get():
        return args.run(args)
    token = _RUNNING.set(True)
    tee, start = Tee(sys.stdout), time.perf_counter()
    try:
        with contextlib.redirect_stdout(tee):
            summary = args.run(args)
    except BaseException as err:
        io.discard()  # the session removes these anyway; the page must not show them
        _command_page(args, command_line, time.perf_counter() - start, tee.lines, error=err)
        raise
    finally:
        _RUNNING.reset(token)
    _command_page(args, command_line, time.perf_counter() - start, tee.lines, summary=summary)
    return summary


def _command_page(args, command_line, seconds, console, *, summary=None, error=None) -> None:
    from jface.cli import summary_text

    out = getattr(args, "out", None)
    if getattr(args, "own_page", False) or not isinstance(out, str) or summary == {}:
        return  # no folder of this command's (or another process reports and writes)
    run_dir = Path(out)
    if error is None:
        io.commit()  # the page reads the outputs on disk
    planned, written = io.session_outputs()
    if not run_dir.is_dir() or (error is not None and not _inside(written, run_dir)):
        return
    names = _inside(planned, run_dir)
    line = summary_text(summary, getattr(args, "prose", None)) if summary else None
    if error is None:
        status = "done"
    elif isinstance(error, KeyboardInterrupt):
        status = "interrupted"
    else:
        status = f"failed: {type(error).__name__}: {error}"
    step = {"name": args.page_title, "status": status, "seconds": seconds,
            "console": [*console, *([line] if line else [])]}  # fmt: skip
    meta = io.provenance(
        seed=getattr(args, "seed", None),
        command=shlex.join(["jface", *command_line]),
        timings_s={"run": round(seconds, 2)},
    )
    meta |= {k: v for k, v in vars(args).items()
             if k not in meta and k not in _MACHINERY and not k.endswith("_command")}  # fmt: skip
    try:
        write_index(
            run_dir, title=args.page_title, provenance=meta, steps=[step], files=names,
            expected=names if error is not None else (), summary=summary,
        )  # fmt: skip
        io.commit()
    except (ValueError, OSError) as err:  # the outputs stand without their page
        io.discard()
        print(f"{args.page_title}: warning: no index.html written: {err}", file=sys.stderr)


def _inside(paths: Sequence[Path], run_dir: Path) -> list[str]:
    """The paths below ``run_dir``, relative to it, in order."""
    root = run_dir.resolve()
    return [p.resolve().relative_to(root).as_posix() for p in paths
            if p.resolve().is_relative_to(root) and p.resolve() != root]  # fmt: skip
