"""``index.html``: one page that shows a run: its figures, the numbers it printed, its files and
its provenance, and what is missing when the run stopped early or an output is broken."""

from __future__ import annotations

import html
import json
import re
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


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def write_index(
    run_dir: str | Path,
    *,
    title: str,
    provenance: dict[str, Any],
    steps: Sequence[dict[str, Any]] = (),
    expected: Sequence[str] = (),
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

    Returns:
        The page's path.
    """
    run_dir = Path(run_dir)
    found = sorted(
        p for p in run_dir.rglob("*") if p.is_file() and p.name != "index.html" and not
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
    parts.append(
        _table(("field", "value"), [(k, v if isinstance(v, str) else json.dumps(v))
                                    for k, v in provenance.items()])
    )  # fmt: skip
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
