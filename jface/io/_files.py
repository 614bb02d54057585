"""Safe file writing: a temporary file in the target folder, then an atomic rename."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike, *, protect: Iterable[str | os.PathLike] = ()
) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` when the block succeeds.

    A crash inside the block leaves any existing ``path`` untouched and removes the temporary
    file. ``protect`` lists input files of the same operation: writing onto one of them raises
    ``ValueError`` (inputs are never overwritten).
    """
    path = Path(path)
    for other in protect:
        if Path(other).exists() and path.exists() and path.resolve() == Path(other).resolve():
            raise ValueError(f"refusing to overwrite the input file {other} with an output")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual mode
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: str | os.PathLike, data: object, *, protect=()) -> Path:
    """Write JSON (indented) atomically."""
    path = Path(path)
    with atomic_path(path, protect=protect) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
    return path
