"""Paper-style figures with matplotlib: panel grids with row and column labels, images with
colour bars and units, line plots with labelled axes.

Every function returns a :class:`matplotlib.figure.Figure` made without :mod:`matplotlib.pyplot`
(an Agg canvas, no global figure registry, no rcParams changed), so building a figure leaves no
state behind; :func:`jface.io.write_figure` writes one to PNG, PDF or SVG with provenance.

One colour map per quantity (:data:`COLOUR_MAPS`), so a reader sees at a glance what a panel
shows: signed displacement is blue–white–red around zero, statistics are viridis, errors are
magma, weights are greens, shaded relief is grey.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import LogNorm, Normalize, TwoSlopeNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator, NullLocator

from jface import _checks

#: Colour map of each quantity a panel can show.
COLOUR_MAPS = {
    "relief": "gray",  # shaded relief from jface.render.shade, in [0, 1]
    "displacement": "RdBu_r",  # signed height, centred on zero
    "statistics": "viridis",  # per-tile standard deviations, ratios
    "error": "magma",  # distance to a target
    "weight": "Greens",  # blending / mixture weights in [0, 1]
    "image": "gray",  # grey photographs
}

PANEL_INCHES = 1.9
_DPI = 100


def _figure(width: float, height: float) -> Figure:
    figure = Figure(figsize=(width, height), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _panel(x: Any, name: str) -> np.ndarray:
    """A panel as float64: ``(H, W)`` values or ``(H, W, 3|4)`` colour in [0, 1]."""
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name} must be an image array, got {_checks.describe(x)}")
    arr = np.asarray(x)
    if arr.dtype == np.uint8:
        arr = arr / 255.0
    if arr.dtype.kind not in "fiub":
        raise TypeError(f"{name} must be a numeric image array, got {_checks.describe(arr)}")
    arr = arr.astype(np.float64)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (3, 4)) or not arr.size:
        raise ValueError(f"{name} must be (H, W) or (H, W, 3|4), got {_checks.describe(arr)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {int(np.sum(~np.isfinite(arr)))} bad values")
    return arr


def _norm(values: Sequence[np.ndarray], quantity: str, vmin, vmax, log: bool):
    data = np.concatenate([v.ravel() for v in values])
    low = float(data.min()) if vmin is None else float(vmin)
    high = float(data.max()) if vmax is None else float(vmax)
    if quantity in ("relief", "image"):
        return Normalize(0.0, 1.0)
    if log:
        positive = data[data > 0]
        low = low if vmin is not None else float(positive.min()) if positive.size else 1e-12
        return LogNorm(max(low, 1e-12), max(high, low * 10))
    if quantity == "displacement" and vmin is None and vmax is None:
        bound = max(abs(low), abs(high)) or 1.0
        return TwoSlopeNorm(0.0, -bound, bound)
    return Normalize(low, high if high > low else low + 1.0)


def panel_grid(
    rows: Sequence[Sequence[Any]],
    *,
    title: str,
    col_labels: Sequence[str] | None = None,
    row_labels: Sequence[str] | None = None,
    quantities: Sequence[str] | str = "relief",
    units: Sequence[str | None] | str | None = None,
    limits: Sequence[tuple[float | None, float | None]] | None = None,
    log: Sequence[bool] | bool = False,
    panel_inches: float = PANEL_INCHES,
) -> Figure:
    """A grid of image panels: one row per entry of ``rows``, a title, column labels above the
    first row and row labels left of each row. Each row shows one quantity: colour panels and
    shaded relief are drawn as they are; any other quantity is drawn with its colour map on one
    scale shared along the row, with a colour bar labelled with the row's unit.

    Args:
        rows: rows of panels, each an ``(H, W)`` array or ``(H, W, 3|4)`` colour image in
            [0, 1]; ``None`` leaves a blank cell.
        title: the figure's title.
        col_labels: one label per column (e.g. method names).
        row_labels: one label per row.
        quantities: a key of :data:`COLOUR_MAPS` per row (or one for all rows).
        units: the colour bar's label per row (or one for all), e.g. ``"fraction of target std"``.
        limits: ``(low, high)`` of the colour scale per row (``None``: the data's range).
        log: logarithmic colour scale per row (or one for all).
        panel_inches: size of one panel.

    Raises:
        ValueError: no panels, ragged labels, an unknown quantity, a malformed panel.
        TypeError: a panel that is not a numeric array.
    """
    if isinstance(rows, (str, bytes)) or not len(rows) or not all(len(r) for r in rows):
        raise ValueError(f"rows must be a non-empty list of non-empty rows, got {rows!r:.80}")
    n_rows, n_cols = len(rows), max(len(r) for r in rows)

    def per_row(value, name):
        values = [value] * n_rows if isinstance(value, (str, bool)) or value is None else value
        if len(values) != n_rows:
            raise ValueError(f"{name} must have one entry per row ({n_rows}), got {len(values)}")
        return list(values)

    quantities = [
        _checks.choice(q, "quantities", COLOUR_MAPS) for q in per_row(quantities, "quantities")
    ]
    units, logs = per_row(units, "units"), per_row(log, "log")
    limits = per_row(limits, "limits") if limits is not None else [(None, None)] * n_rows
    for labels, count, name in (
        (col_labels, n_cols, "col_labels"),
        (row_labels, n_rows, "row_labels"),
    ):
        if labels is not None and len(labels) != count:
            raise ValueError(f"{name} must have {count} entries, got {len(labels)}")
    panels = [
        [None if p is None else _panel(p, f"rows[{i}][{j}]") for j, p in enumerate(row)]
        for i, row in enumerate(rows)
    ]
    heights = [max(p.shape[0] / p.shape[1] for p in row if p is not None) for row in panels]
    barred = [
        q not in ("relief", "image") and any(p is not None and p.ndim == 2 for p in row)
        for q, row in zip(quantities, panels, strict=True)
    ]
    figure = _figure(
        panel_inches * n_cols + 1.6 + 0.4 * (row_labels is not None),
        sum(panel_inches * h for h in heights) + 0.7 + 0.25 * (col_labels is not None),
    )
    # the colour bars get a column of their own, so that the panels of rows with and without a
    # bar line up
    widths = [1.0] * n_cols + [0.06] * any(barred)
    grid = {"height_ratios": heights, "width_ratios": widths}
    axes = figure.subplots(n_rows, len(widths), squeeze=False, gridspec_kw=grid)
    for i, row in enumerate(panels):
        values = [p for p in row if p is not None and p.ndim == 2]
        norm = _norm(values, quantities[i], *limits[i], logs[i]) if values else None
        mappable = None
        for j in range(n_cols):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            panel = row[j] if j < len(row) else None
            if panel is None:
                ax.set_axis_off()
                continue
            if panel.ndim == 3:
                ax.imshow(np.clip(panel, 0.0, 1.0), interpolation="nearest")
            else:
                mappable = ax.imshow(
                    panel, cmap=COLOUR_MAPS[quantities[i]], norm=norm, interpolation="nearest"
                )
            first = next(
                k for k in range(n_rows) if j < len(panels[k]) and panels[k][j] is not None
            )
            if i == first and col_labels is not None:
                ax.set_title(col_labels[j], fontsize=9)
            if j == 0 and row_labels is not None:
                ax.set_ylabel(row_labels[i], fontsize=9)
        if barred[i]:
            bar = figure.colorbar(mappable, cax=axes[i, n_cols])
            bar.set_label(units[i] or quantities[i], fontsize=8)
            bar.ax.tick_params(labelsize=7)
        elif any(barred):
            axes[i, n_cols].set_axis_off()
    figure.suptitle(title, fontsize=11)
    return figure


def image(
    values: Any,
    *,
    title: str,
    quantity: str = "displacement",
    units: str | None = None,
    limits: tuple[float | None, float | None] = (None, None),
    log: bool = False,
) -> Figure:
    """One image with a title and, for a quantity with a colour map, a colour bar in ``units``."""
    return panel_grid(
        [[values]], title=title, quantities=quantity, units=units, limits=[limits], log=log,
        panel_inches=3.2,
    )  # fmt: skip


def lines(
    x: Any,
    series: dict[str, Any],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    logx: bool = False,
    logy: bool = False,
    markers: bool = False,
    points: dict[str, tuple[float, float]] | None = None,
) -> Figure:
    """A line plot: one line per entry of ``series`` (label → y values over ``x``), with a
    legend when there is more than one, labelled axes and optional log scales. ``points``:
    single labelled points (label → ``(x, y)``, e.g. a final answer) drawn as stars.

    Raises:
        ValueError: no series, a series whose length differs from ``x``'s, non-positive values
            on a log axis.
    """
    x = np.asarray(_checks.float_array(np.asarray(x, np.float64), "x", ndim=1))
    if not series:
        raise ValueError("series must hold at least one line, got none")
    figure = _figure(5.0, 3.2)
    ax = figure.subplots()
    for label, y in series.items():
        y = np.asarray(y, np.float64)
        if y.shape != x.shape:
            raise ValueError(f"series {label!r} must have {x.size} values like x, got {y.shape}")
        if logy and np.any(y[np.isfinite(y)] <= 0):
            raise ValueError(f"series {label!r} must be positive on a log y axis")
        ax.plot(x, y, label=label, marker="o" if markers else None, markersize=3, linewidth=1.4)
    points = dict(points or {})
    for label, (px, py) in points.items():
        ax.plot([px], [py], label=label, marker="*", markersize=11, linestyle="none", color="k")
    if logx:
        ax.set_xscale("log")
        _plain_within_a_decade(ax.xaxis, ax.get_xlim())
    if logy:
        ax.set_yscale("log")
        _plain_within_a_decade(ax.yaxis, ax.get_ylim())
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="major", alpha=0.3)
    if len(series) + len(points) > 1:
        ax.legend(fontsize=8, frameon=False)
    figure.suptitle(title, fontsize=11)
    return figure


def _plain_within_a_decade(axis, limits) -> None:
    """Plain, evenly spaced ticks (``0.6, 0.8, …, 1.8``) on a log axis spanning less than a
    decade, where matplotlib labels its minor ticks ``1.716×10⁰`` and leaves a range such as 1–2
    without any; wider axes keep the powers of ten."""
    low, high = limits
    if low > 0 and high / low < 10:
        axis.set_major_locator(MaxNLocator(nbins=6))
        axis.set_minor_locator(NullLocator())
        axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:.4g}"))


def heatmap(
    values: Any,
    *,
    title: str,
    row_labels: Sequence[str],
    col_labels: Sequence[str],
    quantity: str = "statistics",
    units: str | None = None,
    xlabel: str | None = None,
    ylabel: str | None = None,
    annotate: bool = True,
) -> Figure:
    """A labelled matrix of values (rows × columns) with a colour bar; each cell shows its
    value when ``annotate``."""
    values = np.asarray(_checks.float_array(np.asarray(values, np.float64), "values", ndim=2))
    if len(row_labels) != values.shape[0] or len(col_labels) != values.shape[1]:
        raise ValueError(
            f"labels must match values of shape {values.shape}, got {len(row_labels)} row and "
            f"{len(col_labels)} column labels"
        )
    _checks.choice(quantity, "quantity", COLOUR_MAPS)
    figure = _figure(1.2 + 0.55 * values.shape[1] + 1.2, 1.0 + 0.4 * values.shape[0])
    ax = figure.subplots()
    norm = _norm([values], quantity, None, None, False)
    mappable = ax.imshow(values, cmap=COLOUR_MAPS[quantity], norm=norm, aspect="auto")
    ax.set_xticks(range(values.shape[1]), col_labels, fontsize=8)
    ax.set_yticks(range(values.shape[0]), row_labels, fontsize=8)
    if xlabel:
        ax.set_xlabel(xlabel)
    if ylabel:
        ax.set_ylabel(ylabel)
    if annotate:
        middle = 0.5 * (norm.vmin + norm.vmax)
        for (r, c), v in np.ndenumerate(values):
            colour = "white" if (v < middle) != (quantity == "displacement") else "black"
            ax.text(c, r, f"{v:.2f}", ha="center", va="center", fontsize=7, color=colour)
    bar = figure.colorbar(mappable, ax=ax, shrink=0.9)
    bar.set_label(units or quantity, fontsize=8)
    figure.suptitle(title, fontsize=11)
    return figure


def image_grid(
    images: Sequence[Any],
    *,
    title: str,
    columns: int | None = None,
    labels: Sequence[str] | None = None,
    quantity: str = "image",
    units: str | None = None,
    panel_inches: float = 1.1,
) -> Figure:
    """Images (grey in [0, 1], colour, or values of ``quantity``) in a near-square grid, each
    under its label when given.

    Raises:
        ValueError: no images, or a label count that differs from the image count.
    """
    if not len(images):
        raise ValueError("images must hold at least one image, got none")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"labels must have {len(images)} entries, got {len(labels)}")
    columns = columns or int(np.ceil(np.sqrt(len(images))))
    rows = [list(images[i : i + columns]) for i in range(0, len(images), columns)]
    figure = panel_grid(
        rows, title=title, quantities=quantity, units=units, panel_inches=panel_inches
    )
    if labels is not None:
        for ax, label in zip([a for a in figure.axes if a.images], labels, strict=False):
            ax.set_title(label, fontsize=7)
    return figure


def labelled_points(image: Any, xy: Any, names: Sequence[str], *, title: str) -> Figure:
    """An image (shaded relief or a photograph) with named points drawn on it.

    Args:
        image: ``(H, W)`` grey or ``(H, W, 3)`` colour image in [0, 1].
        xy: ``(N, 2)`` point positions in pixels (x right, y down).
        names: one label per point.
        title: the figure's title.
    """
    picture = _panel(image, "image")
    xy = np.asarray(_checks.float_array(np.asarray(xy, np.float64), "xy", ndim=2))
    if xy.shape[1] != 2 or len(names) != len(xy):
        raise ValueError(
            f"xy must be (N, 2) with one name per point, got {xy.shape} for {len(names)} names"
        )
    figure = _figure(7.0, 7.0 * picture.shape[0] / picture.shape[1] + 0.4)
    ax = figure.subplots()
    ax.imshow(picture, cmap="gray", vmin=0, vmax=1)
    ax.scatter(xy[:, 0], xy[:, 1], s=18, c="red", edgecolors="white", linewidths=0.5)
    for (x, y), name in zip(xy, names, strict=True):
        ax.annotate(
            name, (x, y), (4, -4), textcoords="offset points", fontsize=7, color="yellow",
            bbox={"boxstyle": "round,pad=0.1", "fc": "black", "alpha": 0.55, "lw": 0},
        )  # fmt: skip
    ax.set_axis_off()
    figure.suptitle(title, fontsize=11)
    return figure


def axes_grid(
    n_rows: int = 1,
    n_cols: int = 1,
    *,
    title: str,
    size: tuple[int | float, int | float] = (6.4, 4.0),
    **subplots: Any,
) -> tuple[Figure, np.ndarray]:
    """A titled figure of empty axes (``(n_rows, n_cols)`` array), for drawings the functions
    above do not make (bars, histograms, meshes, markers over images): draw on the axes with
    matplotlib's object interface, then write with :func:`jface.io.write_figure`.

    Args:
        n_rows, n_cols: the grid of axes.
        title: the figure's title.
        size: width and height in inches.
        subplots: more arguments of :meth:`matplotlib.figure.Figure.subplots` (``width_ratios``,
            ``sharex``, ...).
    """
    if not title or not str(title).strip():
        raise ValueError("title must be a non-empty text: every figure has one")
    figure = _figure(float(size[0]), float(size[1]))
    axes = figure.subplots(n_rows, n_cols, squeeze=False, **subplots)
    figure.suptitle(title, fontsize=11)
    return figure, axes


# --- the figures of jface's commands ---------------------------------------------------------


def method_comparison(
    images: Sequence[Any], errors: Sequence[Any], names: Sequence[str], *, title: str
) -> Figure:
    """Golovinskiy et al. 2006 Fig. 10: each method's result as shaded relief (top row) and its
    per-tile error to the target statistics (bottom row, one colour bar for all methods).

    Args:
        images: ``(H, W)`` displacement maps, one per method.
        errors: ``(g, g)`` per-tile errors (fraction of the target's std), one per method.
        names: the method names, the column labels.
        title: the figure's title.
    """
    from jface import render

    if not len(images) == len(errors) == len(names):
        raise ValueError(
            f"need one error map and name per image: {len(images)} images, {len(errors)} error "
            f"maps, {len(names)} names"
        )
    shaded = [np.asarray(render.shade(np.asarray(i, np.float32))) for i in images]
    return panel_grid(
        [shaded, list(errors)],
        title=title,
        col_labels=names,
        row_labels=["shaded relief", "per-tile error"],
        quantities=["relief", "error"],
        units=[None, "std error (fraction of target)"],
        limits=[(None, None), (0.0, 1.0)],
    )


def band_statistics(std: Any, n_orientations: int, *, title: str, units: str = "std") -> Figure:
    """Per-tile statistics of every band of a steerable pyramid: the high-pass first, then one
    row per scale with its orientations as columns; one colour bar per row (scales differ by
    orders of magnitude)."""
    std = np.asarray(_checks.float_array(np.asarray(std, np.float64), "std", ndim=3))
    k = _checks.integer(n_orientations, "n_orientations", low=1)
    if (std.shape[0] - 1) % k:
        raise ValueError(f"std must hold 1 + scales × {k} bands, got {std.shape[0]}")
    n_scales = (std.shape[0] - 1) // k
    rows = [[std[0]]] + [list(std[1 + s * k : 1 + (s + 1) * k]) for s in range(n_scales)]
    return panel_grid(
        rows,
        title=title,
        col_labels=[f"{180 * b / k:.0f}°" for b in range(k)],
        row_labels=["high-pass"] + [f"scale {s}" for s in range(n_scales)],
        quantities="statistics",
        units=units,
        panel_inches=1.4,
    )


def convergence(
    history: Any,
    *,
    title: str,
    ylabel: str = "best loss so far",
    xlabel: str = "epoch",
    answer: tuple[str, float] | None = None,
) -> Figure:
    """Best-so-far loss per epoch of each trial of an optimiser, on a log axis when the losses
    are positive: one labelled line per trial.

    Args:
        history: ``(trials, epochs)`` best-so-far losses (non-finite entries are left out);
            column 0 is drawn at epoch 0 (the initial population).
        answer: ``(label, loss)`` of the final answer when it is not the history's last best
            (e.g. refined after the search), drawn as a star at the last epoch (left out when
            not finite).
    """
    history = np.asarray(history, np.float64)
    if history.ndim == 1:
        history = history[None]
    if history.ndim != 2 or not history.size:
        raise ValueError(f"history must be (trials, epochs), got {_checks.describe(history)}")
    finite = history[np.isfinite(history)]
    logy = bool(finite.size) and bool(np.all(finite > 0))
    epochs = np.arange(history.shape[1], dtype=np.float64)
    series = {f"trial {i + 1}": np.where(np.isfinite(h), h, np.nan) for i, h in enumerate(history)}
    points = {}
    if answer is not None and np.isfinite(answer[1]) and (answer[1] > 0 or not logy):
        points[answer[0]] = (epochs[-1], float(answer[1]))
    return lines(epochs, series, title=title, xlabel=xlabel, ylabel=ylabel, logy=logy,
                 points=points)  # fmt: skip
