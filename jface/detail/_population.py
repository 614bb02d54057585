"""Many faces' statistics with per-face metadata (id, age, sex, ...)."""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jface import io
from jface.detail._stats import (
    DetailStats,
    mean_stats,
    stack_stats,
    stats_from_arrays,
    stats_to_arrays,
)


def check_records(records: Sequence[dict[str, Any]]) -> None:
    """Raise ValueError unless every record is a dict with an ``"id"`` and the ids are unique."""
    bad = [i for i, r in enumerate(records) if not isinstance(r, dict) or r.get("id") is None]
    if bad:
        raise ValueError(f"every record needs an 'id' field; record(s) {bad[:10]} have none")
    ids = [json.dumps(r["id"], sort_keys=True) for r in records]
    repeated = sorted({i for i in ids if ids.count(i) > 1})
    if repeated:
        raise ValueError(f"record ids must be unique; repeated: {', '.join(repeated[:10])}")


@dataclasses.dataclass(frozen=True)
class Population:
    """A stack of :class:`DetailStats` (leading axis = face) and one metadata record per face.

    Records are JSON-serialisable dicts; each has at least an ``"id"``. Select groups with
    :meth:`select` (field equality or ranges) or :meth:`where` (any predicate), average them with
    :meth:`mean`.
    """

    stats: DetailStats
    records: tuple[dict[str, Any], ...]

    def __post_init__(self):
        n = self.stats.std.shape[0] if self.stats.std.ndim == 4 else None
        if n is None:
            raise ValueError(
                f"stats must be a stack (n, bands, grid, grid), got {self.stats.std.shape}"
            )
        if len(self.records) != n:
            raise ValueError(f"need one record per face: {n} faces, {len(self.records)} records")
        check_records(self.records)

    @classmethod
    def from_faces(
        cls, stats: Sequence[DetailStats], records: Sequence[dict[str, Any]]
    ) -> Population:
        """Stack single-face statistics with their records."""
        return cls(stack_stats(list(stats)), tuple(dict(r) for r in records))

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> tuple[DetailStats, dict[str, Any]]:
        return jax.tree.map(lambda x: x[index], self.stats), self.records[index]

    def where(self, predicate: Callable[[dict[str, Any]], bool]) -> Population:
        """The faces whose record satisfies ``predicate``."""
        keep = [i for i, record in enumerate(self.records) if predicate(record)]
        if not keep:
            raise ValueError("the selection is empty: no face matches")
        index = jnp.asarray(keep)
        return Population(
            jax.tree.map(lambda x: x[index], self.stats), tuple(self.records[i] for i in keep)
        )

    def select(self, **criteria: Any) -> Population:
        """Faces whose fields equal the given values, or lie in ``(low, high)`` tuples
        (inclusive), e.g. ``select(sex="f", age=(20, 30))``.

        Raises:
            ValueError: a field missing from some record, or an empty selection.
        """
        for field in criteria:
            missing = [r["id"] for r in self.records if field not in r]
            if missing:
                raise ValueError(f"field {field!r} is missing from records {missing[:5]}")

        def matches(record):
            for field, wanted in criteria.items():
                value = record[field]
                if isinstance(wanted, tuple):
                    if not wanted[0] <= value <= wanted[1]:
                        return False
                elif value != wanted:
                    return False
            return True

        return self.where(matches)

    def mean(self, weights=None) -> DetailStats:
        """Mean statistics of the group (see :func:`jface.detail.mean_stats`)."""
        return mean_stats(self.stats, weights)

    def save(self, path: str | os.PathLike, **metadata: Any) -> None:
        """Save the whole population (statistics and records) to one ``.npz`` file."""
        arrays, layout = stats_to_arrays(self.stats)
        meta = io.provenance(**layout, records=list(self.records), **metadata)
        io.save_arrays(path, arrays, meta, kind="Population")

    @classmethod
    def load(cls, path: str | os.PathLike) -> Population:
        """Load a population saved by :meth:`save`."""
        arrays, meta = io.load_arrays(path, kind="Population")
        if not isinstance(meta.get("records"), list):
            raise ValueError(f"{path} holds a malformed Population: no records")
        stats = stats_from_arrays(arrays, meta, path)
        try:
            return cls(stats, tuple(meta["records"]))
        except ValueError as err:
            raise ValueError(f"{path} holds a malformed Population: {err}") from err

    def table(self) -> str:
        """One JSON line per face: its record and its mean std per band (for quick looks)."""
        per_band = np.asarray(self.stats.std).mean(axis=(-2, -1))
        return "\n".join(
            json.dumps({**r, "mean_std": [round(float(v), 6) for v in row]})
            for r, row in zip(self.records, per_band, strict=True)
        )
