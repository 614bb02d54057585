"""JAX's persistent compilation cache, as every jface command (and the test suite) uses it."""

import os
from pathlib import Path

import jax


def keep_compiled_programs() -> bool:
    """Keep XLA's compiled programs on disk between runs (JAX's persistent compilation cache),
    so that a second fit, build or synthesis of the same sizes starts without compiling.

    ``JFACE_CACHE_DIR`` names the folder (default ``jface/xla`` under ``XDG_CACHE_HOME``, or
    ``~/.cache``); ``JFACE_CACHE_DIR=off`` turns it off; a folder given to JAX itself
    (``JAX_COMPILATION_CACHE_DIR``) is kept. Only programs that took over a second to compile
    are stored. Returns whether this call set the cache up.
    """
    where = os.environ.get("JFACE_CACHE_DIR", "")
    if where == "off" or jax.config.jax_compilation_cache_dir:
        return False
    if not where:
        where = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "jface" / "xla"
    jax.config.update("jax_compilation_cache_dir", str(where))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return True
