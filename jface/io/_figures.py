"""matplotlib figures to PNG, PDF or SVG, with provenance and the same bytes for the same data."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np

from jface.io._files import atomic_path, check_output
from jface.io._images import write_png

FIGURE_SUFFIXES = (".png", ".pdf", ".svg")


def write_figure(
    path: str | os.PathLike,
    figure: Any,
    *,
    metadata: dict[str, Any] | None = None,
    protect: tuple[str | os.PathLike, ...] = (),
) -> Path:
    """Write a :class:`matplotlib.figure.Figure` (see :mod:`jface.plots`) atomically; the
    format comes from the suffix: ``.png`` (default for figures), ``.pdf`` or ``.svg``.

    A PNG is the figure drawn by Agg and written by :func:`write_png` (``metadata`` in its
    "jface" text chunk); a PDF stores ``metadata`` as JSON in its Subject, an SVG in its
    description. No format stores a date, so the same figure gives the same bytes.

    Raises:
        TypeError: ``figure`` is not a matplotlib figure.
        ValueError: another suffix, or a path :func:`check_output` refuses.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not isinstance(figure, Figure):
        raise TypeError(f"figure must be a matplotlib Figure, got {type(figure).__name__}")
    path = check_output(path, FIGURE_SUFFIXES, protect=protect)
    if path.suffix.lower() == ".png":
        canvas = FigureCanvasAgg(figure)
        canvas.draw()
        pixels = np.asarray(canvas.buffer_rgba())[..., :3]
        return write_png(path, pixels, metadata=metadata, protect=protect)
    blob = json.dumps(metadata or {})
    fields = (
        {"CreationDate": None, "Subject": blob}
        if path.suffix.lower() == ".pdf"
        else {"Date": None, "Description": blob}
    )
    with (
        atomic_path(path, protect=protect) as tmp,
        matplotlib.rc_context({"svg.hashsalt": "jface", "pdf.compression": 6}),
    ):
        figure.savefig(tmp, format=path.suffix[1:].lower(), metadata=fields)
    return path
