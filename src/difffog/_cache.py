"""XLA's persistent compilation cache: compiled programs kept on disk between processes.

A difffog render or fit spends most of a short run compiling (a default render: ~11 of its
20 s on a 2-core CPU); the programs depend only on the shapes and settings, so a second
process with the same ones can load them instead.  ``import difffog`` turns the cache on
(:func:`enable_default_cache`) unless ``DIFFFOG_CACHE_DIR=off`` or the program has already
chosen a cache folder of its own (JAX's setting is global to the process: a folder set before
or after the import wins).
"""

from __future__ import annotations

import os
from pathlib import Path

#: the environment variable that moves the cache (a folder) or turns it off ("off")
CACHE_ENV = "DIFFFOG_CACHE_DIR"


def default_cache_dir() -> Path | None:
    """``$DIFFFOG_CACHE_DIR``, else ``$XDG_CACHE_HOME/difffog/xla`` (``~/.cache/difffog/xla``);
    None when ``DIFFFOG_CACHE_DIR`` is ``off``, ``0`` or empty."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "no", "false") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "difffog" / "xla"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path | None:
    """Keep XLA's compiled programs in ``path`` (default :func:`default_cache_dir`) so that a
    later process with the same scene shapes and settings loads them instead of compiling.
    Returns the folder, or None where the cache is turned off or the folder cannot be made
    (then nothing changes: programs compile as before)."""
    folder = Path(path) if path is not None else default_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    # every program that took a while to compile (the light solve, the cameras, a fit's step;
    # the many tiny ones of the host set-up are cheaper to compile than to look up)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    # (no size limit: JAX's needs the filelock package; a default render's programs are ~1 MB)
    return folder


def enable_default_cache() -> Path | None:
    """What ``import difffog`` does: :func:`enable_compilation_cache` at the default folder,
    unless JAX already has a cache folder (the program's own choice is kept)."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return None
    return enable_compilation_cache()
