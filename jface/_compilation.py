"""JAX's persistent compilation cache, as every jface command (and the test suite) uses it, and
jface's own arrays kept beside it (work that runs rather than compiles, e.g. a fit's layout)."""

import contextlib
import functools
import hashlib
import logging
import os
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np


def keep_compiled_programs() -> bool:
    """Keep XLA's compiled programs on disk between runs (JAX's persistent compilation cache),
    so that a second fit, build or synthesis of the same sizes starts without compiling.

    ``JFACE_CACHE_DIR`` names the folder (default ``jface/xla`` under ``XDG_CACHE_HOME``, or
    ``~/.cache``); ``JFACE_CACHE_DIR=off`` turns it off; a folder given to JAX itself
    (``JAX_COMPILATION_CACHE_DIR``) is kept. Programs that took over 0.3 s to compile are
    stored (JAX's default, 1 s, left a rerun of ``wrinkles render`` compiling its binning and
    a rerun of ``wrinkles simulate`` its pore sampling and graph trimming, a few seconds each).
    Returns whether this call set the cache up.
    """
    where = os.environ.get("JFACE_CACHE_DIR", "")
    if where == "off" or jax.config.jax_compilation_cache_dir:
        return False
    if not where:
        where = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jface" / "xla"
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.3)
    return True


#: XLA options for large programs that run briefly (``jax.jit(..., compiler_options=...)``): the
#: backend's optimisation level 1 instead of 2 compiles a wrinkle fit's refinement in 23 % less
#: time (26 s against 34 s) and a small fit's swarm loss in 20 % less (10.0 s against 12.5 s), and
#: both run as fast (measured on two cores; from one start the refinement's losses agree to the
#: last bit or two, though a fit's 10-step refinement may then take another path).
QUICK_COMPILE = {"xla_backend_optimization_level": 1}


def compile_ahead(jitted: Callable, *args) -> threading.Thread:
    """Compile ``jitted`` (``jax.jit`` or ``equinox.filter_jit``) for ``args`` in a background
    thread: XLA compiles outside the GIL, so this overlaps other work (on many cores, all of it).
    Join the thread before calling ``jitted`` with arguments of those shapes, which then finds
    the program compiled (called sooner, it would compile it a second time). Errors are left to
    that call, which raises them. JAX settings local to the caller's thread (e.g. a
    ``jax.default_device`` context) do not reach this thread: pass arguments that carry them."""

    def compile_() -> None:
        try:
            jitted.lower(*args).compile()
        except Exception:  # the call itself raises it; here it only cost time
            logging.getLogger(__name__).debug("compiling %s ahead failed", jitted, exc_info=True)

    thread = threading.Thread(target=compile_, name=f"compile {jitted}", daemon=True)
    thread.start()
    return thread


#: Memory mappings past which :func:`spare_memory_mappings` drops JAX's compiled programs: each
#: loaded program keeps some (a 256² wrinkle fit's two about 4,300), and past Linux's
#: ``vm.max_map_count`` (65,530 by default) the next compile or read from the persistent cache
#: crashes the interpreter (the test suite's wrinkle fits reached it in one process).
MAPPINGS_LIMIT = 40_000


def spare_memory_mappings(limit: int | None = None) -> bool:
    """Drop JAX's compiled programs (``jax.clear_caches``) when this process holds more than
    ``limit`` (default :data:`MAPPINGS_LIMIT`) memory mappings, so that a long run that compiles
    program after program (fits of patches of many sizes) does not crash. A dropped program is
    compiled again when next called, or read back from the persistent compilation cache. Only
    where ``/proc/self/maps`` exists (Linux); elsewhere nothing. Returns whether they were
    dropped."""
    try:
        count = Path("/proc/self/maps").read_bytes().count(b"\n")
    except OSError:
        return False
    if count <= (MAPPINGS_LIMIT if limit is None else limit):
        return False
    jax.clear_caches()
    return True


def kept_arrays(
    what: str,
    settings: tuple,
    build: Callable[[], dict[str, np.ndarray]],
    shipped: Path | None = None,
) -> dict[str, np.ndarray]:
    """``build()``, kept on disk (``jface-<what>/`` in the compiled programs' folder) when
    compiled programs are kept, so that a rerun with the same ``settings`` reads it instead;
    read from the ``shipped`` file (:func:`shipped_arrays`) when jface ships it.

    The file's name hashes ``settings`` with this jface's source, the JAX version and the
    precision, so a change of any of them builds anew. A file that cannot be read (truncated,
    corrupt) is built again and replaced; one that cannot be written is skipped (the answer is
    the same, the next run builds it too).
    """
    if shipped is not None and (found := read_shipped(shipped, what, settings)):
        return found
    path = kept_path(what, settings)
    if path is None:
        return build()
    arrays = _read_kept(path)
    if arrays is None:
        arrays = build()
        with contextlib.suppress(OSError):  # unwritable: the next run builds it too
            write_arrays(path, arrays)
    return arrays


def shipped_arrays(what: str, settings: tuple, arrays: dict[str, np.ndarray]) -> dict:
    """``arrays`` named for a file of arrays that jface ships, where :func:`kept_arrays` finds
    them as ``what`` of ``settings`` (merge several into one file, written by
    :func:`write_arrays`). Unlike a kept file's, the name holds neither the source nor the JAX
    version: a shipped file stands until its test finds that a build differs."""
    return {f"{what}.{_digest(settings)}.{name}": a for name, a in arrays.items()}


def read_shipped(shipped: Path, what: str, settings: tuple) -> dict[str, np.ndarray]:
    """The arrays of ``what`` of ``settings`` in the ``shipped`` file ({} when it holds none, or
    is missing or damaged)."""
    return _read_kept(shipped, f"{what}.{_digest(settings)}.") or {}


def _digest(settings: tuple) -> str:
    return hashlib.sha256(repr(settings).encode()).hexdigest()[:16]


def _read_kept(path: Path, prefix: str = "") -> dict[str, np.ndarray] | None:
    """The arrays of ``path`` whose names start with ``prefix`` (named without it); None when
    there is none yet or it is damaged (built again)."""
    try:
        with open(path, "rb") as file, np.load(file, allow_pickle=False) as stored:
            return {k[len(prefix) :]: stored[k] for k in stored.files if k.startswith(prefix)}
    except Exception:  # a missing, truncated or corrupt copy of derived data
        return None


def write_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``path`` (compressed) through a temporary file and a rename, so readers see all of
    it or none. Not :func:`jface.io.atomic_path`: inside a command's session that would stage
    the file as one of the command's outputs."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}~", suffix=".npz", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez_compressed(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def kept_path(what: str, settings: tuple) -> Path | None:
    """Where :func:`kept_arrays` keeps ``what`` of ``settings`` (None: nothing is kept)."""
    folder = jax.config.jax_compilation_cache_dir
    if not folder:
        return None
    name = repr((settings, jax.__version__, bool(jax.config.jax_enable_x64), source_digest()))
    return Path(folder) / f"jface-{what}" / f"{hashlib.sha256(name.encode()).hexdigest()[:32]}.npz"


@functools.cache
def source_digest() -> str:
    """Hash of jface's Python source: kept arrays and resumable results of other code (an
    upgrade, or an edit the version number does not show) are not reused."""
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.rglob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()
