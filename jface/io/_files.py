"""The one way jface writes a file, and the record of what a command read and wrote.

Every writer of :mod:`jface.io` goes through :func:`atomic_path`: the bytes go to a temporary file
beside the target (``.NAME~jface-HOST-PID-XXXXXXXX.EXT``), which is renamed onto the target only
when the writing succeeded, and removed on every other exit. A killed process cannot clean up, so
a write removes the temporaries that dead jface processes of its host left in the target's
folder (once per folder in a session).

Within a :func:`session` (the ``jface`` command opens one per run) writes are also checked
against the command's inputs: a path that is an input, resolves to one or is a hard link of one
is refused, and so is a second output under a name already written. Inputs are the paths given
to the session plus every file a reader of :mod:`jface.io` opened. Outputs are staged: their
temporary files are renamed into place together when the session ends without an error (or at
a :func:`commit`, the checkpoint of a resumable batch), and removed when it fails, so a failed
command leaves nothing under its output names. :func:`session_outputs` tells what the session
meant to write (every output it checked) and what it has put in place, for the run's page.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import errno
import hashlib
import json
import os
import re
import socket
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

_HOST = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]
_TEMPORARY = re.compile(r"^\..*~jface-(?P<host>[0-9a-f]{6})-(?P<pid>\d+)-[a-z0-9_]{8}(\.[^.]*)?$")


@dataclasses.dataclass
class _Session:
    inputs: dict[tuple[int, int], str] = dataclasses.field(default_factory=dict)
    claimed: set[str] = dataclasses.field(default_factory=set)
    swept: set[str] = dataclasses.field(default_factory=set)  # folders cleared of dead temporaries
    staged: list[tuple[Path, Path]] = dataclasses.field(default_factory=list)
    planned: dict[Path, None] = dataclasses.field(default_factory=dict)  # checked, in order
    written: list[Path] = dataclasses.field(default_factory=list)  # committed
    tracking: bool = True

    def add_input(self, path: str | os.PathLike) -> None:
        self.inputs.update(_identities(path))

    def commit(self) -> None:
        staged, self.staged = self.staged, []
        for i, (tmp, path) in enumerate(staged):
            try:
                _replace(tmp, path)
            except BaseException:  # an interrupt too: no temporary may stay behind
                _remove(tmp for tmp, _ in staged[i:])
                raise
            self.written.append(path)

    def discard(self) -> None:
        staged, self.staged = self.staged, []
        _remove(tmp for tmp, _ in staged)


_active: contextvars.ContextVar[_Session | None] = contextvars.ContextVar(
    "jface_io_session", default=None
)


@contextlib.contextmanager
def session(inputs: Iterable[str | os.PathLike] = ()) -> Iterator[None]:
    """Treat the writes of the block as the outputs of one command.

    ``inputs`` (files, or folders: their files) and every file read through :mod:`jface.io`
    inside the block are protected: writing onto one raises ``ValueError``, as does writing two
    outputs under one name. Outputs appear when the block ends without an error (or at
    :func:`commit`); an error removes the ones not yet committed. A session opened inside
    another joins it, and its end commits (or, on an error, removes) everything staged so far.
    """
    outer = _active.get()
    current = outer or _Session()
    for path in inputs:
        current.add_input(path)
    token = _active.set(current)
    try:
        yield
    except BaseException:
        current.discard()
        raise
    finally:
        _active.reset(token)
    current.commit()


def commit() -> None:
    """Put the outputs written so far in the current :func:`session` in place (a checkpoint a
    rerun can resume from); without a session every write is in place at once anyway."""
    current = _active.get()
    if current is not None:
        current.commit()


def discard() -> None:
    """Remove the outputs staged since the last :func:`commit` of the current :func:`session`
    (a failed step's), so that what follows can still be committed."""
    current = _active.get()
    if current is not None:
        current.discard()


def session_outputs() -> tuple[list[Path], list[Path]]:
    """The outputs of the current :func:`session`: those it checked or wrote (its planned
    outputs, in order), and those it has put in place so far; both empty without a session."""
    current = _active.get()
    if current is None:
        return [], []
    return list(current.planned), list(current.written)


@contextlib.contextmanager
def own_outputs() -> Iterator[None]:
    """Reads inside the block are of outputs of this command or an earlier run of it (a cache,
    a resumable part), not inputs: they may be replaced."""
    current = _active.get()
    if current is None:
        yield
        return
    before, current.tracking = current.tracking, False
    try:
        yield
    finally:
        current.tracking = before


def input_file(path: str | os.PathLike, what: str = "file") -> Path:
    """``path`` as a file to read, recorded as an input of the current :func:`session`.

    Raises:
        FileNotFoundError: no such file.
        IsADirectoryError: a folder where a file is needed.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"{path} is a folder, not a {what}")
    if not path.is_file():
        raise FileNotFoundError(f"no such {what}: {path}")
    current = _active.get()
    if current is not None and current.tracking:
        current.add_input(path)
    return path


def content_key(paths: Iterable[str | os.PathLike], settings: dict) -> str:
    """The key of a result computed from files with settings, for caches and resumable runs:
    SHA-256 (hex) of the files' bytes, the settings (as JSON), the jface version and its source,
    so an edit of any file, another setting or other jface code (an upgrade, also one that keeps
    the version number) gives another key. The files count as inputs of the current
    :func:`session`."""
    from jface import __version__
    from jface._compilation import source_digest

    versions = [__version__, source_digest()]
    digest = hashlib.sha256(json.dumps([*versions, settings], sort_keys=True).encode())
    for path in paths:
        with open(input_file(path), "rb") as handle:
            digest.update(hashlib.file_digest(handle, "sha256").digest())
    return digest.hexdigest()


def _identities(path: str | os.PathLike) -> dict[tuple[int, int], str]:
    """(device, inode) → path of a file, or of the files directly inside a folder."""
    path = Path(path)
    try:
        files = [p for p in path.iterdir() if p.is_file()] if path.is_dir() else [path]
    except OSError:
        return {}
    out = {}
    for file in files:
        with contextlib.suppress(OSError):
            info = file.stat()
            out[(info.st_dev, info.st_ino)] = str(file)
    return out


def check_output(
    path: str | os.PathLike,
    suffixes: tuple[str, ...] = (),
    *,
    protect: Iterable[str | os.PathLike] = (),
) -> Path:
    """Raise unless ``path`` can be an output: a name ending in one of ``suffixes`` (when
    given; the format follows the name), not a folder, not below a file, and not an input of the
    current :func:`session` or one of ``protect`` (the same file under any name: a link, a hard
    link). Commands call it before they compute, so a bad output name costs nothing."""
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise ValueError(
            f"{path}: this output is {suffixes[0][1:].upper()}, so its name must end in "
            f"{' or '.join(suffixes)}"
        )
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"cannot write {path}: it is a folder; name a file")
    blocker = next((p for p in path.parents if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise NotADirectoryError(
            errno.ENOTDIR, f"cannot write {path}: {blocker} is a file, not a folder"
        )
    current = _active.get()
    inputs = dict(current.inputs) if current is not None else {}
    if current is not None:
        current.planned[path] = None
    for other in protect:
        inputs.update(_identities(other))
    try:
        info = path.stat()
    except OSError:
        return path  # nothing there (or nothing reachable): no input to lose
    source = inputs.get((info.st_dev, info.st_ino))
    if source is not None:
        same = "" if Path(source) == path else f" ({path} is the same file)"
        raise ValueError(
            f"refusing to overwrite the input file {source} with an output{same}; "
            "choose another output name"
        )
    return path


def _claim(path: Path, current: _Session | None) -> None:
    if current is None:
        return
    key = os.path.realpath(path)
    if key in current.claimed:
        raise ValueError(
            f"two outputs of this command would be written to {path}; choose other names"
        )
    current.claimed.add(key)


def _cannot_write(path: Path, err: OSError) -> OSError:
    """The OS error of writing ``path``, naming ``path`` (not a temporary) and the problem."""
    return type(err)(err.errno, f"cannot write {path}: {err.strerror or err}")


def _sweep(folder: Path, current: _Session | None) -> None:
    """Remove the temporaries that dead jface processes of this host left in ``folder`` (once
    per session and folder)."""
    if current is not None:
        key = os.path.realpath(folder)
        if key in current.swept:
            return
        current.swept.add(key)
    with contextlib.suppress(OSError), os.scandir(folder) as entries:
        for entry in entries:
            match = _TEMPORARY.match(entry.name)
            if match and match["host"] == _HOST and not _alive(int(match["pid"])):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True  # another user's process (or an id this system cannot have)
    return True


def _replace(tmp: Path, path: Path) -> None:
    try:
        os.replace(tmp, path)
    except OSError as err:
        _remove([tmp])
        raise _cannot_write(path, err) from err


def _remove(paths: Iterable[Path]) -> None:
    for path in paths:
        with contextlib.suppress(OSError):
            os.unlink(path)


@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike, *, protect: Iterable[str | os.PathLike] = ()
) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; put it in place as ``path`` when the block
    succeeds (at once, or when the current :func:`session` commits).

    A failure inside the block, an interrupt included, leaves any existing ``path`` untouched and
    removes the temporary file. ``protect`` lists input files (or folders) of the same operation
    besides the session's: writing onto one of them, a link to one or a hard link of one raises
    ``ValueError`` (inputs are never overwritten), as does a folder as ``path``
    (``IsADirectoryError``). Folders are made as needed; an OS error (no permission, a file
    where a folder should be) is raised with a message naming ``path``.
    """
    path = check_output(path, protect=protect)
    current = _active.get()
    _claim(path, current)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _sweep(path.parent, current)
        prefix = f".{path.name[:100]}~jface-{_HOST}-{os.getpid()}-"
        fd, name = tempfile.mkstemp(prefix=prefix, suffix=path.suffix[:20], dir=path.parent)
    except OSError as err:
        raise _cannot_write(path, err) from err
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual mode
    except BaseException:
        _remove([tmp])
        raise
    if current is None:
        _replace(tmp, path)
    else:
        current.staged.append((tmp, path))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path: str | os.PathLike, data: object, *, protect=()) -> Path:
    """Write JSON (indented) atomically; the path must end in ``.json``."""
    path = check_output(path, (".json",), protect=protect)
    text = json.dumps(data, indent=2)
    with atomic_path(path, protect=protect) as tmp:
        tmp.write_text(text + "\n")
    return path
