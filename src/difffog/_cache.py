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


def user_cache_root() -> Path:
    """difffog's folder in the user's cache: ``$XDG_CACHE_HOME/difffog`` (``~/.cache/difffog``);
    XLA's programs go in ``xla/``, the native sweep kernel's build in ``native/``."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "difffog"


def default_cache_dir() -> Path | None:
    """``$DIFFFOG_CACHE_DIR``, else ``$XDG_CACHE_HOME/difffog/xla`` (``~/.cache/difffog/xla``);
    None when ``DIFFFOG_CACHE_DIR`` is ``off``, ``0`` or empty."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "no", "false") else Path(env)
    return user_cache_root() / "xla"


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


#: the share of the kernel's per-process memory-mapping limit above which a new model drops
#: JAX's compiled programs (:func:`release_if_crowded`)
CROWDED = 0.6


def memory_maps() -> tuple[int, int] | None:
    """(this process's memory mappings, the kernel's limit per process: vm.max_map_count), or
    None where the system does not say (not Linux)."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            limit = int(f.read())
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f), limit
    except (OSError, ValueError):
        return None


def release_if_crowded(share: float = CROWDED, warn: bool = True) -> bool:
    """Drop JAX's compiled programs (``jax.clear_caches()``) when this process holds more than
    ``share`` of the memory mappings Linux allows it, with a :class:`difffog.MemoryWarning`
    (unless ``warn`` is False: the test suite's own guard); True if it did.  Each XLA CPU program maps its own code and data (~1,100 mappings for a
    small render), so a long session that compiles many models (a notebook rendering many
    lattice sizes: ~60 of them at the default limit of 65,530) would otherwise die inside
    XLA's compiler when the next one cannot be mapped.  Programs needed again compile anew, or
    load from the persistent cache.  Called before every model is built (``forward._registry.guard``)."""
    maps = memory_maps()
    if maps is None or maps[0] <= share * maps[1]:
        return False
    import gc
    import warnings

    import jax

    from ._errors import MemoryWarning

    jax.clear_caches()
    gc.collect()
    if not warn:
        return True
    after = memory_maps()
    warnings.warn(
        f"this process held {maps[0]:,} of the {maps[1]:,} memory mappings Linux allows it "
        f"(compiled programs: ~1,100 each), so difffog dropped JAX's compiled programs "
        f"({after[0] if after else '?':,} left); they compile again (or load from the "
        f"persistent cache) when needed. For long sessions raise the limit: sudo sysctl "
        f"vm.max_map_count=262144", MemoryWarning, stacklevel=4)
    return True
