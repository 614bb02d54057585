"""A time estimate for long command-line runs, measured on the run itself."""

from __future__ import annotations

import sys
import time

from tqdm import tqdm

#: Estimates shorter than this (seconds) are not worth a line.
SHOW_ABOVE = 30.0


class Estimate:
    """Says once, on stderr, how long the rest of a run of ``total`` units will take.

    The first update only starts the clock (the first unit pays for compilation); the second
    measures the cost per unit and, when the units left would take more than
    :data:`SHOW_ABOVE` seconds at that cost, prints e.g. ``about 4 min for the remaining 24
    maps``.
    """

    def __init__(self, total: int, unit: str, *, enabled: bool = True):
        self.left, self.unit, self.enabled = total, unit, enabled
        self.start: float | None = None

    def skip(self, n: int) -> None:
        """``n`` units need no work (done by an earlier run)."""
        self.left -= n

    def update(self, n: int) -> None:
        """``n`` units are done."""
        self.left -= n
        if not self.enabled:
            return
        if self.start is None:
            self.start = time.perf_counter()
            return
        self.enabled = False  # one estimate per run
        seconds = (time.perf_counter() - self.start) / n * self.left
        if seconds > SHOW_ABOVE:
            minutes = f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"
            tqdm.write(f"about {minutes} for the remaining {self.left} {self.unit}s", sys.stderr)
